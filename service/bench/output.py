"""What a benchmark prints and writes: a progress bar on stderr, the machine line, and its section of
BENCHMARKS.md (replaced in place, the others kept)."""
from __future__ import annotations

import os
import platform
import sys
import time

from tqdm import tqdm

from .definitions import ROOT

BENCH_FILE = ROOT / "BENCHMARKS.md"


def progress(total: int, desc: str):
    return tqdm(total=total, desc=desc, file=sys.stderr, leave=False, disable=not sys.stderr.isatty())


def machine() -> str:
    return f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}"


def write_section(name: str, table: str, command: str) -> None:
    """Replace (or append) the `name` section of BENCHMARKS.md, keeping the others."""
    begin, end = f"<!-- bench:{name}:begin -->", f"<!-- bench:{name}:end -->"
    stamp = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    body = f"{begin}\nMeasured {stamp} on {machine()} with `{command}`.\n\n{table}\n{end}"
    text = BENCH_FILE.read_text() if BENCH_FILE.exists() else "# Benchmarks\n\nNumbers measured on the project's own machines by the `shadowopt bench` commands.\n"
    if begin in text and end in text:
        pre, rest = text.split(begin, 1)
        post = rest.split(end, 1)[1]
        text = pre + body + post
    else:
        text = text.rstrip("\n") + f"\n\n## {name}\n\n{body}\n"
    BENCH_FILE.write_text(text)
