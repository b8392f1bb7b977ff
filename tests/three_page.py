"""The real three.js page of the browser tests (tests/test_three_module.py, tests/test_tune_three.py): three.js r187
(npm, `make setup` puts it in out/web/node_modules) in Debian's Chromium headless through Playwright (SwiftShader
WebGL2), tests/three_harness/ serving the scene's triangles, the rig's camera and sun, and an emitted module imported
as it is; `render` returns three's shadowed pixels and view depth of the screen."""
from __future__ import annotations

import base64
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
from web_scene import scene_triangles

ROOT = Path(__file__).resolve().parents[1]
THREE_MODULE = ROOT / "out" / "web" / "node_modules" / "three" / "build" / "three.module.js"
ADDONS = THREE_MODULE.parents[1] / "examples" / "jsm"  # three/addons/ (the CSM addon)
HARNESS = Path(__file__).with_name("three_harness")
DEMO = ROOT / "configs" / "demo_scene.usda"
CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
CHROMIUM_ARGS = ["--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--no-sandbox"]
SCREEN = (320, 180)
DEPTH_TOLERANCE = 0.01  # relative view-depth difference under which both renderers hit the same surface
ORIGIN = "http://shadowopt.test"



@pytest.fixture(scope="module")
def browser():
    if not os.path.exists(CHROMIUM):
        pytest.skip("Debian's chromium is absent (make setup installs it)")
    if not THREE_MODULE.exists():
        pytest.skip("three.js is absent (make setup: npm install --prefix out/web three@0.187.0)")
    playwright = pytest.importorskip("playwright.sync_api", reason="playwright is not installed (requirements.lock)")
    with playwright.sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        yield b
        b.close()


@pytest.fixture(scope="module")
def entry():
    from shadowopt.service.pipeline import scene_entry

    return scene_entry(str(DEMO))


def scene_geometry(entry, sun_direction) -> bytes:
    """The scene's triangles (web_scene.scene_triangles: split, flat normals on the light's side), unindexed, as
    x y z nx ny nz per vertex, float32."""
    tri, nrm = scene_triangles(entry, sun_direction)
    out = np.concatenate([tri, np.repeat(nrm[:, None, :], 3, axis=1)], axis=2)
    return out.astype(np.float32).tobytes()


def render(browser, module_text: str, geometry: bytes, camera: dict, sun_direction, classify: str = "shadow") -> dict:
    files = {"/index.html": (HARNESS / "index.html").read_bytes(), "/harness.js": (HARNESS / "harness.js").read_bytes(),
             "/three.module.js": THREE_MODULE.read_bytes(), "/apply.js": module_text.encode(),
             "/scene.bin": geometry}
    types = {".html": "text/html", ".js": "text/javascript", ".bin": "application/octet-stream"}
    ctx = browser.new_context()
    page = ctx.new_page()
    errors = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)

    def serve(route):
        path = route.request.url.removeprefix(ORIGIN).split("?")[0]
        build = THREE_MODULE.parent / path.lstrip("/")  # three.module.js imports ./three.core.js
        addon = ADDONS / path.removeprefix("/addons/")
        if path in files:
            route.fulfill(status=200, body=files[path], content_type=types[Path(path).suffix])
        elif path.endswith(".js") and "/" not in path[1:] and build.is_file():
            route.fulfill(status=200, body=build.read_bytes(), content_type="text/javascript")
        elif path.startswith("/addons/csm/") and path.endswith(".js") and ".." not in path and addon.is_file():
            route.fulfill(status=200, body=addon.read_bytes(), content_type="text/javascript")
        else:
            route.fulfill(status=404, body="")

    page.route(ORIGIN + "/**", serve)
    try:
        page.goto(ORIGIN + "/index.html")
        page.wait_for_function("() => window.harnessReady === true", timeout=30000)
        out = page.evaluate("(p) => window.harness.render(p)", {
            "screen": list(SCREEN), "geometry": "/scene.bin", "module": "/apply.js",
            "sun_direction": list(sun_direction), "camera": camera, "classify": classify})
    finally:
        ctx.close()
    assert not errors, errors
    W, H = SCREEN
    out["alpha"] = np.frombuffer(base64.b64decode(out["alpha"]), np.uint8).reshape(H, W)[::-1]
    out["depth"] = np.frombuffer(base64.b64decode(out["depth"]), np.float32).reshape(H, W)[::-1]
    return out
