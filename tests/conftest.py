"""Shared fixtures. Tests that need the USD working group's assets read ../shared/usd-assets and
skip with a message when it is absent (the assets are never copied into this repository)."""
from __future__ import annotations

import os
from pathlib import Path

import pytest

_LLVM = "/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1"
if os.path.exists(_LLVM):
    os.environ.setdefault("DRJIT_LIBLLVM_PATH", _LLVM)

REPO = Path(__file__).resolve().parents[1]
USD_ASSETS = Path(__file__).resolve().parents[2] / "shared" / "usd-assets"


@pytest.fixture(scope="session")
def usd_assets() -> Path:
    if not USD_ASSETS.is_dir():
        pytest.skip(f"../shared/usd-assets is absent: these tests read the USD working group's assets from "
                    f"{USD_ASSETS} (next to the repository; they are never copied into it)")
    return USD_ASSETS


@pytest.fixture(scope="session")
def repo() -> Path:
    return REPO
