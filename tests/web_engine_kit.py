"""What the real-engine browser tests share (tests/test_three_module.py, tests/test_babylon_module.py): Debian's
Chromium through Playwright, the demo scene's triangles for a page, `optimize --emit`, a page whose files are served
by page.route, and the score of an engine's shadowed pixels against the product's exact ray-traced visibility of
the same screen (renderers.ground_truth.evaluate_buffers, what `evaluate --depth solution` runs)."""
from __future__ import annotations

import base64
import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
DEMO = ROOT / "configs" / "demo_scene.usda"
CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
CHROMIUM_ARGS = ["--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--no-sandbox"]
SCREEN = (320, 180)
DEPTH_TOLERANCE = 0.01  # relative view-depth difference under which both renderers hit the same surface
ORIGIN = "http://shadowopt.test"
TYPES = {".html": "text/html", ".js": "text/javascript", ".bin": "application/octet-stream"}
MAX_EDGE = 4.0  # metres


def launch_browser(engine_file: Path, what: str):
    """A module-scoped fixture's body: Chromium headless, skipped when it, the engine or Playwright is absent."""
    if not os.path.exists(CHROMIUM):
        pytest.skip("Debian's chromium is absent (make setup installs it)")
    if not engine_file.exists():
        pytest.skip(f"{what} is absent (make setup installs it into out/web)")
    playwright = pytest.importorskip("playwright.sync_api", reason="playwright is not installed (requirements.lock)")
    with playwright.sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        yield b
        b.close()


def geometry(entry, sun_direction, axes=(1.0, 1.0, 1.0)) -> bytes:
    """The scene's triangles, unindexed, each with its flat normal turned to the light's side (x y z nx ny nz per
    vertex, float32), in an engine frame whose coordinates are the world's times `axes` (Babylon: (-1, 1, 1)): the
    normal a closed, consistently wound mesh has on its lit side. Triangles longer than MAX_EDGE are split into
    coplanar pieces (the same surfaces): SwiftShader interpolates the varyings of a huge triangle clipped by the near
    plane (the demo's 300 m ground) a few tenths of a percent off (view depth 69.06 against the exact 68.90 m),
    which moved three's shadow lookups and added ~20 wrongly lit pixels per sun."""
    g = entry.loaded.geometry
    tri = _split(np.asarray(g.vertices, np.float64)[np.asarray(g.faces)])  # (n, 3, 3)
    nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-300)
    nrm *= np.where(nrm @ -np.asarray(sun_direction) < 0, -1.0, 1.0)[:, None]
    out = np.concatenate([tri, np.repeat(nrm[:, None, :], 3, axis=1)], axis=2) * np.tile(np.asarray(axes, float), 2)
    return out.astype(np.float32).tobytes()


def _split(tri: np.ndarray) -> np.ndarray:
    """Each triangle in four at its edge midpoints until no edge is longer than MAX_EDGE."""
    done = []
    while len(tri):
        edge = np.max(np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2), axis=1)
        done.append(tri[edge <= MAX_EDGE])
        t = tri[edge > MAX_EDGE]
        a, b, c = t[:, 0], t[:, 1], t[:, 2]
        ab, bc, ca = (a + b) / 2, (b + c) / 2, (c + a) / 2
        tri = np.concatenate([np.stack(q, axis=1) for q in ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))])
    return np.concatenate(done)


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
    top row first. No page error or console error may occur."""
    ctx = browser.new_context()
    page = ctx.new_page()
    errors = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)

    def serve(route):
        path = route.request.url.removeprefix(ORIGIN).split("?")[0]
        body = files.get(path)
        if body is None and ".." not in path:
            body = fallback(path)
        if body is None:
            route.fulfill(status=404, body="")
        else:
            route.fulfill(status=200, body=body, content_type=TYPES.get(Path(path).suffix, "text/plain"))

    page.route(ORIGIN + "/**", serve)
    try:
        page.goto(ORIGIN + "/index.html")
        page.wait_for_function("() => window.harnessReady === true", timeout=30000)
        out = page.evaluate("([c, p]) => window.harness[c](p)", [call, params])
    finally:
        ctx.close()
    assert not errors, errors
    if "alpha" not in out:
        return out
    W, H = params["screen"]
    out["alpha"] = np.frombuffer(base64.b64decode(out["alpha"]), np.uint8).reshape(H, W)[::-1]
    out["depth"] = np.frombuffer(base64.b64decode(out["depth"]), np.float32).reshape(H, W)[::-1]
    return out


BABYLON = ROOT / "out" / "web" / "node_modules" / "@babylonjs" / "core"
BABYLON_HARNESS = Path(__file__).with_name("babylon_harness")


def babylon_files(**extra: bytes) -> dict:
    """The Babylon.js page's own files (tests/babylon_harness/) and `extra` ("/apply.js": ..., "/scene.bin": ...)."""
    return {"/index.html": (BABYLON_HARNESS / "index.html").read_bytes(),
            "/harness.js": (BABYLON_HARNESS / "harness.js").read_bytes(), **extra}


def babylon_fallback(path: str):
    """@babylonjs/core's ES modules under /babylon/ (the page's import map), and the shaders they import on demand."""
    f = BABYLON / path.removeprefix("/babylon/")
    return f.read_bytes() if path.startswith("/babylon/") and path.endswith(".js") and f.is_file() else None


def score(entry, rig: dict, solution: dict, rendered: dict, screen=SCREEN) -> dict:
    """evaluate's ground truth and verdicts of the screen, and the engine's verdicts, on the receivers both
    renderers see the same surface at (engine_vs_evaluate: the pixels where the two verdicts differ)."""
    from shadowopt.renderers.ground_truth import evaluate_buffers
    from shadowopt.service.rigs import resolve_rig
    from shadowopt.service.solution_json import maps_from_solution

    resolved = resolve_rig(rig, entry.loaded)
    gt = evaluate_buffers(entry.rays, resolved.camera, resolved.lights[0], maps_from_solution(solution)[0],
                          screen=screen, depth="solution")
    ze, zr = rendered["depth"].astype(np.float64), gt.screen.depth
    with np.errstate(invalid="ignore"):
        same = (ze > 0) & gt.screen.hit & (np.abs(ze - zr) <= DEPTH_TOLERANCE * zr)
    keep = gt.receivers & same
    shadowed = rendered["alpha"] > 127
    exact = gt.exact_shadowed
    wrong = keep & (shadowed != exact)
    wrong_eval = keep & gt.misclassified
    return {"receivers": int(gt.receivers.sum()), "compared": int(keep.sum()),
            "exact_shadowed": int((keep & exact).sum()), "engine_shadowed": int((keep & shadowed).sum()),
            "engine_wrong": int(wrong.sum()), "engine_wrongly_lit": int((wrong & exact).sum()),
            "engine_wrongly_shadowed": int((wrong & ~exact).sum()),
            "evaluate_wrong_compared": int(wrong_eval.sum()), "evaluate_wrong": gt.result["misclassified_pixels"],
            "engine_vs_evaluate": int((keep & (shadowed != (exact ^ gt.misclassified))).sum())}
