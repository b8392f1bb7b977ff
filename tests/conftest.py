"""Shared fixtures, and the layers (TESTING.md). Tests that need the USD working group's assets read
../shared/usd-assets and skip with a message when it is absent (the assets are never copied into this repository).

Every test is in exactly one layer: `server` (starts uvicorn, or runs the CLI in a subprocess), `browser`
(Chromium through Playwright), `gl` (OpenGL or the shader compilers in a subprocess) or `unit` (everything else:
in process, no server, browser or OpenGL); a test marked with none of them is `unit`. `slow` (over ~10 s on
its own) goes with any of them. `make test-fast` runs `-m "unit and not slow"`."""
from __future__ import annotations

import os
import re
from pathlib import Path

import pytest
from _pytest.mark.expression import Expression

_LLVM = "/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1"
if os.path.exists(_LLVM):
    os.environ.setdefault("DRJIT_LIBLLVM_PATH", _LLVM)

REPO = Path(__file__).resolve().parents[1]
USD_ASSETS = Path(__file__).resolve().parents[2] / "shared" / "usd-assets"


LAYERS = ("unit", "server", "browser", "gl")


@pytest.hookimpl(tryfirst=True)  # before -m selects on the marks
def pytest_collection_modifyitems(config, items):
    """An unmarked test is `unit`; a test in two layers is a mistake in its marks (the layers partition the suite)."""
    for item in items:
        layers = [name for name in LAYERS if item.get_closest_marker(name) is not None]
        if not layers:
            item.add_marker(pytest.mark.unit)
        elif len(layers) > 1:
            raise pytest.UsageError(f"{item.nodeid} is marked {' and '.join(layers)}: a test is in one layer")
    items[:] = heavy_files_first(items)


def heavy_files_first(items: list) -> list:
    """The files in the order two xdist workers finish soonest in (`make test`: --dist loadfile
    --no-loadscope-reorder hands out whole files in this order): likely the longest first, so that the last files
    handed out are short ones and neither worker waits for the other at the end. A file with a `slow` test first,
    then one with a server, browser or gl test (a subprocess, a server or Chromium to start), then unit-only files;
    within each, more tests first (xdist's own order). A file's tests keep their order."""
    files: dict = {}
    for i, item in enumerate(items):
        f = files.setdefault(item.nodeid.split("::")[0], {"first": i, "n": 0, "group": 2})
        f["n"] += 1
        if item.get_closest_marker("slow") is not None:
            f["group"] = 0
        elif f["group"] == 2 and any(item.get_closest_marker(name) is not None for name in LAYERS[1:]):
            f["group"] = 1
    key = {name: (f["group"], -f["n"], f["first"]) for name, f in files.items()}
    return sorted(items, key=lambda item: key[item.nodeid.split("::")[0]])


FILE_LAYER = re.compile(r"^pytestmark = pytest\.mark\.(unit|server|browser|gl)$", re.M)


def pytest_ignore_collect(collection_path, config):
    """A test file wholly in one layer (a module `pytestmark` naming it) is not even imported when `-m` leaves that
    layer out, slow or not: `make test-fast` then skips the browser, server and fuzzing stacks' imports
    (schemathesis alone takes ~10 s). Only the layers and `slow` are read from the expression: one naming any
    other mark keeps every file."""
    expr = config.getoption("markexpr", "")
    if not expr or collection_path.suffix != ".py" or not collection_path.name.startswith("test_"):
        return None
    m = FILE_LAYER.search(collection_path.read_text())
    if not m:
        return None
    compiled = Expression.compile(expr)
    for other in (False, True):
        for marks in ({m.group(1)}, {m.group(1), "slow"}):
            if compiled.evaluate(lambda name, **kw: name in marks or (other and name not in LAYERS + ("slow",))):
                return None
    return True


@pytest.fixture(scope="session")
def usd_assets() -> Path:
    if not USD_ASSETS.is_dir():
        pytest.skip(f"../shared/usd-assets is absent: these tests read the USD working group's assets from "
                    f"{USD_ASSETS} (next to the repository; they are never copied into it)")
    return USD_ASSETS


@pytest.fixture(scope="session")
def repo() -> Path:
    return REPO
