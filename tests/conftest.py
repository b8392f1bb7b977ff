"""Shared fixtures. Tests that need the USD working group's assets read ../shared/usd-assets and
skip with a message when it is absent (the assets are never copied into this repository)."""
from __future__ import annotations

import os
from pathlib import Path

import pytest

os.environ.setdefault("DRJIT_LIBLLVM_PATH", "/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1") if os.path.exists(
    "/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1") else None

REPO = Path(__file__).resolve().parents[1]
USD_ASSETS = REPO.parent / "shared" / "usd-assets"


@pytest.fixture(scope="session")
def usd_assets() -> Path:
    if not USD_ASSETS.is_dir():
        pytest.skip(f"{USD_ASSETS} is absent: these tests read the USD working group's assets from ../shared/usd-assets")
    return USD_ASSETS


@pytest.fixture(scope="session")
def repo() -> Path:
    return REPO
