"""The `shadowopt` command line for tests: `run` as a user runs it (a subprocess of the installed script), `run_here`
in this process (`main(argv)`, what the installed script calls). Both answer .returncode, .stdout and .stderr.

A process start costs ~5 s on 2 cores (Python, Mitsuba and Dr.Jit imports, the scene load, kernel compilation), so
the tests cross the process boundary where it is the point (a command's round trip as a user runs it, the README's
lines verbatim) and run in process where the answer is (refusals before any work, commands run several times to
compare their answers)."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

REPO = Path(__file__).resolve().parents[1]


def _checked(p, check):
    if check is not None:
        assert p.returncode == check, (p.returncode, p.stdout, p.stderr)
    return p


def run(*args, check=None):
    exe = Path(sys.executable).with_name("shadowopt")
    return _checked(subprocess.run([str(exe), *map(str, args)], capture_output=True, text=True, timeout=300,
                                   cwd=REPO), check)


def run_here(capsys, *args, check=None):
    """`shadowopt ARGS` in process with pytest's capsys (an exception escaping main fails the test, as its
    traceback on stderr would)."""
    from shadowopt.api.cli import main  # lazy: test files that only use `run` do not import the CLI

    capsys.readouterr()
    cwd = os.getcwd()
    os.chdir(REPO)
    try:
        code = main([str(a) for a in args])
    except SystemExit as e:  # argparse's own refusals
        code = e.code
    finally:
        os.chdir(cwd)
    out = capsys.readouterr()
    return _checked(SimpleNamespace(returncode=code, stdout=out.out, stderr=out.err), check)
