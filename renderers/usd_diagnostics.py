"""usd-core's diagnostics and errors as scene warnings and messages.

- usd-core's diagnostics (missing files, MaterialX it cannot read) become scene warnings (captured_stderr): one
  line per file usd-core cannot open, with the number of prims that name it (not one line per prim).
- Tf errors' texts without the C++ location (tf_text, usd_error_text); warnings without repeats (dedupe).
"""
from __future__ import annotations

import contextlib
import os
import re
import sys
import tempfile
import threading

_FD2_LOCK = threading.RLock()  # fd 2 is process-wide: one redirect at a time (loads are serialised)


@contextlib.contextmanager
def captured_stderr(sink: list[str]):
    """Collect what C++ code writes on file descriptor 2 (usd-core's diagnostics) into `sink`.

    usd-core's Python bindings offer no diagnostic delegate, so fd 2 is redirected to a temporary
    file for the duration. Anything other threads write to stderr meanwhile lands there too."""
    with _FD2_LOCK:
        with _redirect_fd2(sink):
            yield


@contextlib.contextmanager
def _redirect_fd2(sink: list[str]):
    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile(mode="w+b") as tmp:
        os.dup2(tmp.fileno(), 2)
        try:
            yield
        finally:
            sys.stderr.flush()
            os.dup2(saved, 2)
            os.close(saved)
            tmp.seek(0)
            text = tmp.read().decode("utf-8", "replace")
            sink.extend(_summarize_diagnostics(text))


# usd-core's message for a composition arc to a file it cannot open: one per prim that names the file (a
# material layer referenced by every piece of a model gives hundreds of lines that differ only in the prim)
_CANNOT_OPEN = re.compile(r"^(?P<kind>[A-Za-z ]+): In <[^>]*>: Could not open asset @(?P<asset>[^@]*)@ ")


def _summarize_diagnostics(text: str) -> list[str]:
    """One line per diagnostic, without C++ locations, addresses and repeats; the prims that cannot open the
    same file give one line (the first prim's) with how many prims name it."""
    out, per_file = [], {}
    for line in text.splitlines():
        line = line.strip()
        if not line:
            continue
        line = re.sub(r"^(Warning|Error|Coding Error|Runtime Error): in \S+ at line \d+ of \S+ -- ", r"\1: ", line)
        line = re.sub(r" \(instantiating stage on stage @[^@]*@ <0x[0-9a-f]+>\)", "", line)
        line = re.sub(r" <0x[0-9a-f]+>", "", line)
        line = re.sub(r"anon:0x[0-9a-f]+:([^@\s]*?)\.checked\.usda", r"\1", line)
        m = _CANNOT_OPEN.match(line)
        if m:
            key = (m["kind"], m["asset"].split(":SDF_FORMAT_ARGS:")[0])
            if key in per_file:
                per_file[key][1] += 1
                continue
            per_file[key] = [len(out), 1]
        if line not in out:
            out.append(line)
    for (_, asset), (i, n) in per_file.items():
        if n > 1:
            out[i] += f" [one line for the {n} prims that name @{asset}@]"
    return out


def tf_text(e) -> str:
    """str() of a Tf error: USD's parser message quotes the damaged file, whose bytes may not be UTF-8."""
    try:
        return str(e)
    except UnicodeDecodeError:
        return "the file is not valid UTF-8 text"


def usd_error_text(text: str) -> str:
    """The useful part of a Tf error: drop the C++ location and namespaces."""
    text = text.strip().strip("'")
    m = re.search(r" : '(.*)'?$", text, re.S)
    if m:
        text = m.group(1)
    text = re.sub(r"pxrInternal_v\w+::", "", text).strip().strip("'")
    return text or "unreadable"


def dedupe(items: list[str]) -> list[str]:
    seen, out = set(), []
    for w in items:
        if w not in seen:
            seen.add(w)
            out.append(w)
    return out
