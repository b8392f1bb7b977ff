"""What the real-engine browser tests share beyond the three.js page (service/bench/three_page.py, tests/three_page.py):
`optimize --emit` in process, a page whose files are served by page.route, the Babylon.js page's files, and the score
of an engine's shadowed pixels against the product's exact ray-traced visibility of the same screen
(renderers.ground_truth.evaluate_buffers, what `evaluate --depth solution` runs). tests/test_three_module.py and
tests/test_babylon_module.py use it; Chromium and the scene's triangles come from service.bench.three_page."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from shadowopt.service.bench import babylon_page, three_page

ROOT = Path(__file__).resolve().parents[1]
DEMO = ROOT / "configs" / "demo_scene.usda"
SCREEN = (320, 180)
from shadowopt.service.bench.screen_score import DEPTH_TOLERANCE  # noqa: F401 (the tests compare where both renderers see the same surface)
ORIGIN = three_page.ORIGIN


def launch_browser(engine_file: Path, what: str):
    """A module-scoped fixture's body: Chromium headless (three_page.chromium), skipped when it, the engine or
    Playwright is absent."""
    if not Path(three_page.CHROMIUM).exists():
        pytest.skip("Debian's chromium is absent (make setup installs it)")
    if not engine_file.exists():
        pytest.skip(f"{what} is absent (make setup installs it into out/web)")
    pytest.importorskip("playwright.sync_api", reason="playwright is not installed (requirements.lock)")
    if not three_page.THREE_MODULE.exists():  # three_page.chromium() asks for three.js too (make setup installs both)
        pytest.skip("three.js is absent (make setup installs it into out/web)")
    with three_page.chromium() as b:
        yield b


def geometry(entry, sun_direction, axes=(1.0, 1.0, 1.0)) -> bytes:
    """three_page.scene_geometry (the scene's split triangles with their lit-side flat normals, x y z nx ny nz per
    vertex, float32) in the world's frame, or in Babylon's (axes (-1, 1, 1): babylon_page.scene_geometry)."""
    if tuple(axes) == babylon_page.TO_BABYLON:
        return babylon_page.scene_geometry(entry, sun_direction)
    assert tuple(axes) == (1.0, 1.0, 1.0), axes
    return three_page.scene_geometry(entry, sun_direction)


def solve_and_emit(tmp_path, rig: dict, *extra: str) -> tuple[dict, str]:
    """`optimize DEMO --rig RIG --out --emit` in process: the solution and the module's text."""
    from shadowopt.api.cli import main

    (tmp_path / "rig.json").write_text(json.dumps(rig))
    sol, js = tmp_path / "solution.json", tmp_path / "apply.js"
    assert main(["optimize", str(DEMO), "--rig", str(tmp_path / "rig.json"), "--out", str(sol),
                 "--emit", str(js), *extra]) == 0
    return json.loads(sol.read_text()), js.read_text()


def render_page(browser, files: dict, fallback, params: dict, call: str = "render") -> dict:
    """Open ORIGIN/index.html with `files` (path -> bytes) served and `fallback(path)` (bytes or None) for the rest,
    wait for window.harnessReady, run window.harness[call](params), and decode its `alpha` (uint8: 255 where the
    engine shadows) and `depth` (float32 view depth, 0 where nothing is hit), when it has them, into (H, W) arrays,
    top row first. A page error or console error is a RuntimeError (three_page.run_page)."""
    out = three_page.run_page(browser, files, fallback, [params], "engine", call)[0]
    return three_page.decode_screen(out, params["screen"]) if "alpha" in out else out


BABYLON = babylon_page.BABYLON


def babylon_files(**extra: bytes) -> dict:
    """The Babylon.js page's own files (service/bench/babylon_harness/) and `extra` ("/apply.js": ..., ...)."""
    return babylon_page.page_files(**extra)


babylon_fallback = babylon_page.fallback  # @babylonjs/core's ES modules under /babylon/


def score(entry, rig: dict, solution: dict, rendered: dict, screen=SCREEN) -> dict:
    """evaluate's ground truth and verdicts of the screen, and the engine's verdicts, on the receivers both
    renderers see the same surface at (service.bench.screen_score; engine_vs_evaluate: the pixels where the two
    verdicts differ)."""
    from shadowopt.renderers.ground_truth import evaluate_buffers
    from shadowopt.service.bench.screen_score import score_screen
    from shadowopt.service.rigs import resolve_rig
    from shadowopt.service.solution_json import maps_from_solution

    resolved = resolve_rig(rig, entry.loaded)
    gt = evaluate_buffers(entry.rays, resolved.camera, resolved.lights[0], maps_from_solution(solution)[0],
                          screen=screen, depth="solution")
    return score_screen(gt, rendered)
