"""A real Babylon.js page in Debian's Chromium headless through Playwright (SwiftShader WebGL2): @babylonjs/core 9.35.0
(npm, `make setup` puts it in out/web/node_modules) as ES modules under /babylon/ (the page's import map),
service/bench/babylon_harness/ drawing the scene's triangles in Babylon's left-handed frame (the `babylon` preset:
x -> -x) with the rig's camera and sun, an emitted module imported as it is; `render_modules` returns, per module,
Babylon's shadowed pixels and view depth of the screen. Used by `shadowopt bench engines --engine babylon` and the
browser tests (tests/web_engine_kit.py: tests/test_babylon_module.py, tests/test_tune_babylon.py,
tests/test_engine_fit_babylon.py)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .three_page import ROOT, decode_screen, run_page
from .three_page import scene_geometry as world_geometry

BABYLON = ROOT / "out" / "web" / "node_modules" / "@babylonjs" / "core"
HARNESS = Path(__file__).with_name("babylon_harness")
TO_BABYLON = (-1.0, 1.0, 1.0)  # solvers.conventions.ENGINE_PRESETS["babylon"] axes ("-x", "y", "z")


def missing() -> str | None:
    """Why the page cannot run here (None: it can; Chromium itself: three_page.missing)."""
    if not (BABYLON / "index.js").exists():
        return "Babylon.js is absent (make setup: npm install --prefix out/web @babylonjs/core@9.35.0)"
    return None


def to_babylon(v) -> list:
    """A world vector (position, direction) in Babylon's frame."""
    return [float(a) * s for a, s in zip(v, TO_BABYLON)]


def scene_geometry(entry, sun_direction) -> bytes:
    """three_page.scene_geometry (the scene's split triangles with their lit-side flat normals, x y z nx ny nz per
    vertex, float32) in Babylon's frame."""
    data = np.frombuffer(world_geometry(entry, sun_direction), np.float32).reshape(-1, 6)
    return (data * np.tile(np.asarray(TO_BABYLON, np.float32), 2)).astype(np.float32).tobytes()


def camera_json(camera) -> dict:
    """The harness's camera object from a solvers.cameras.Camera, in Babylon's frame."""
    return {"position": to_babylon(camera.position), "forward": to_babylon(camera.forward),
            "up": to_babylon(camera.up), "fov_y_deg": camera.fov_y_deg, "near": camera.near, "far": camera.far}


def page_files(**extra: bytes) -> dict:
    """The page's own files and `extra` ("/apply.js": ..., "/scene.bin": ...)."""
    return {"/index.html": (HARNESS / "index.html").read_bytes(), "/harness.js": (HARNESS / "harness.js").read_bytes(),
            **extra}


def fallback(path: str):
    """@babylonjs/core's ES modules under /babylon/, and the shaders they import on demand."""
    f = BABYLON / path.removeprefix("/babylon/")
    return f.read_bytes() if path.startswith("/babylon/") and path.endswith(".js") and f.is_file() else None


def render_modules(browser, modules: list[str], geometry: bytes, camera: dict, sun_direction,
                   screen: tuple[int, int] = (320, 180)) -> list[dict]:
    """Each module imported as it is into one page, rendered in turn (a fresh engine and scene each, disposed
    after): per module {alpha (H, W) uint8, 255 where Babylon shadows the pixel; depth (H, W) float32 view depth, 0
    where nothing is hit; installed, restored: what the harness read}. `camera`, `sun_direction` and `geometry` in
    Babylon's frame. A page error is a RuntimeError."""
    files = page_files(**{"/scene.bin": geometry}, **{f"/apply-{k}.js": m.encode() for k, m in enumerate(modules)})
    params = [{"screen": list(screen), "geometry": "/scene.bin", "module": f"/apply-{k}.js",
               "sun_direction": list(sun_direction), "camera": camera} for k in range(len(modules))]
    return [decode_screen(out, screen) for out in run_page(browser, files, fallback, params, "Babylon.js")]
