"""A real three.js page in Debian's Chromium headless through Playwright (SwiftShader WebGL2): three.js r187 (npm,
`make setup` puts it in out/web/node_modules) and its CSM addon, service/bench/three_harness/ drawing the scene's
triangles with the rig's camera and sun, an emitted module imported as it is; `render_modules` returns, per module,
three's shadowed pixels and view depth of the screen. Used by `shadowopt bench engines` and the browser tests
(tests/test_three_module.py, tests/test_tune_three.py)."""
from __future__ import annotations

import base64
import os
import shutil
from contextlib import contextmanager
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
THREE_MODULE = ROOT / "out" / "web" / "node_modules" / "three" / "build" / "three.module.js"
ADDONS = THREE_MODULE.parents[1] / "examples" / "jsm"  # three/addons/ (the CSM addon)
HARNESS = Path(__file__).with_name("three_harness")
CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
CHROMIUM_ARGS = ["--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--no-sandbox"]
ORIGIN = "http://shadowopt.test"


def missing() -> str | None:
    """Why the page cannot run here (None: it can)."""
    if not os.path.exists(CHROMIUM):
        return "Debian's chromium is absent (make setup installs it)"
    if not THREE_MODULE.exists():
        return "three.js is absent (make setup: npm install --prefix out/web three@0.187.0)"
    return None


@contextmanager
def chromium():
    """A launched headless Chromium (RuntimeError saying why when it cannot run)."""
    why = missing()
    if why:
        raise RuntimeError(why)
    from playwright.sync_api import sync_playwright  # lazy: a dev dependency, only for the browser bench and tests

    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        try:
            yield b
        finally:
            b.close()


def scene_geometry(entry, sun_direction) -> bytes:
    """The scene's triangles, unindexed, each with its flat normal turned to the light's side (x y z nx ny nz per
    vertex, float32): the normal a closed, consistently wound mesh has on its lit side. Triangles longer than
    MAX_EDGE are split into coplanar pieces (the same surfaces): SwiftShader interpolates the varyings of a huge
    triangle clipped by the near plane (the demo's 300 m ground) a few tenths of a percent off (view depth 69.06
    against the exact 68.90 m), which moved three's shadow lookups and added ~20 wrongly lit pixels per sun."""
    g = entry.loaded.geometry
    tri = split_long_triangles(np.asarray(g.vertices, np.float64)[np.asarray(g.faces)])  # (n, 3, 3)
    nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-300)
    nrm *= np.where(nrm @ -np.asarray(sun_direction) < 0, -1.0, 1.0)[:, None]
    out = np.concatenate([tri, np.repeat(nrm[:, None, :], 3, axis=1)], axis=2)
    return out.astype(np.float32).tobytes()


MAX_EDGE = 4.0  # metres


def split_long_triangles(tri: np.ndarray) -> np.ndarray:
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


def render(browser, module_text: str, geometry: bytes, camera: dict, sun_direction, classify: str = "shadow",
           screen: tuple[int, int] = (320, 180)) -> dict:
    """One module rendered (render_modules)."""
    return render_modules(browser, [module_text], geometry, camera, sun_direction, classify, screen)[0]


def render_modules(browser, modules: list[str], geometry: bytes, camera: dict, sun_direction, classify: str = "shadow",
                   screen: tuple[int, int] = (320, 180)) -> list[dict]:
    """Each module imported as it is into one page, rendered in turn (a fresh renderer each, disposed after):
    per module {alpha (H, W) uint8, 255 where three shadows the pixel; depth (H, W) float32 view depth, 0 where
    nothing is hit; installed, restored, defaults: what the harness read}. A page error is a RuntimeError."""
    files = {"/index.html": (HARNESS / "index.html").read_bytes(), "/harness.js": (HARNESS / "harness.js").read_bytes(),
             "/three.module.js": THREE_MODULE.read_bytes(), "/scene.bin": geometry}
    for k, text in enumerate(modules):
        files[f"/apply-{k}.js"] = text.encode()
    params = [{"screen": list(screen), "geometry": "/scene.bin", "module": f"/apply-{k}.js",
               "sun_direction": list(sun_direction), "camera": camera, "classify": classify} for k in range(len(modules))]
    return [decode_screen(out, screen) for out in run_page(browser, files, _three_fallback, params, "three.js")]


def _three_fallback(path: str):
    """three's build files (three.module.js imports ./three.core.js) and the CSM addon under /addons/csm/."""
    build = THREE_MODULE.parent / path.lstrip("/")
    addon = ADDONS / path.removeprefix("/addons/")
    if path.endswith(".js") and "/" not in path[1:] and build.is_file():
        return build.read_bytes()
    if path.startswith("/addons/csm/") and path.endswith(".js") and addon.is_file():
        return addon.read_bytes()
    return None


TYPES = {".html": "text/html", ".js": "text/javascript", ".bin": "application/octet-stream", ".wasm": "application/wasm",
         ".glb": "model/gltf-binary"}


def run_page(browser, files: dict, fallback, params: list[dict], what: str, call: str = "render") -> list:
    """A harness page (index.html setting window.harnessReady, window.harness.<call>) served from `files` (path ->
    bytes) and `fallback(path)` (bytes or None: 404; never for a path with ".."), `window.harness.<call>(p)` for each
    p of `params` in turn; the answers. A page error or console error is a RuntimeError naming `what`."""
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
    outs = []
    try:
        page.goto(ORIGIN + "/index.html")
        page.wait_for_function("() => window.harnessReady === true", timeout=30000)
        for p in params:
            outs.append(page.evaluate(f"(p) => window.harness.{call}(p)", p))
    finally:
        ctx.close()
    if errors:
        raise RuntimeError(f"{what} page: {errors}")
    return outs


def decode_screen(out: dict, screen) -> dict:
    """A harness answer's base64 screens as arrays, row 0 at the top: alpha (H, W) uint8, depth (H, W) float32."""
    W, H = screen
    out["alpha"] = np.frombuffer(base64.b64decode(out["alpha"]), np.uint8).reshape(H, W)[::-1]
    out["depth"] = np.frombuffer(base64.b64decode(out["depth"]), np.float32).reshape(H, W)[::-1]
    return out
