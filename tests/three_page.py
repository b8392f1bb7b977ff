"""The browser tests' three.js page (service/bench/three_page.py) as pytest fixtures: a Chromium, the demo scene,
and `render` at the tests' small screen."""
from __future__ import annotations

from pathlib import Path

import pytest

from shadowopt.service.bench import three_page
from shadowopt.service.bench.three_page import scene_geometry  # noqa: F401 (re-exported for the tests)

ROOT = Path(__file__).resolve().parents[1]
DEMO = ROOT / "configs" / "demo_scene.usda"
SCREEN = (320, 180)
from shadowopt.service.bench.screen_score import DEPTH_TOLERANCE  # noqa: F401 (the tests compare where both renderers see the same surface)


@pytest.fixture(scope="module")
def browser():
    why = three_page.missing()
    if why:
        pytest.skip(why)
    pytest.importorskip("playwright.sync_api", reason="playwright is not installed (requirements.lock)")
    with three_page.chromium() as b:
        yield b


@pytest.fixture(scope="module")
def entry():
    from shadowopt.service.pipeline import scene_entry

    return scene_entry(str(DEMO))


def render(browser, module_text: str, geometry: bytes, camera: dict, sun_direction, classify: str = "shadow") -> dict:
    """One module in the page at SCREEN; a page error fails the test."""
    try:
        return three_page.render(browser, module_text, geometry, camera, sun_direction, classify, SCREEN)
    except RuntimeError as e:
        pytest.fail(str(e))
