"""The inspector page in a real browser: Debian's chromium, headless, driven by Playwright (pointed at the
system browser; its software WebGL2 is SwiftShader through ANGLE) against a real uvicorn on 127.0.0.1 with
tokens. The page loads and asks for a token; a scene uploaded through the page appears; the WebGL render
of the demo rig (the document's light pass and lookup) agrees with evaluate's shadowed/lit classification
on >= 99% of the receiver pixels (also with four cascades in Direct3D's reversed-Z clip space); moving the sun slider sends one optimize and moves the shadows; another
tenant's scene is not listed. Screenshots of each step are written to the test's temporary folder (and
to $SHADOWOPT_SCREENSHOTS when set)."""
from __future__ import annotations

import base64
import io
import os
import shutil
from pathlib import Path

import httpx
import numpy as np
import pytest
from PIL import Image
from serverkit import DEMO, TOKENS, auth, running, upload

from shadowopt.renderers.heatmap import LIT_GREY, SHADOWED_GREY, WRONGLY_LIT, WRONGLY_SHADOWED

pytestmark = pytest.mark.browser

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
if not os.path.exists(CHROMIUM):
    pytest.skip("Debian's chromium is absent (make setup installs it: apt-get install chromium); the inspector's "
                "browser tests need it", allow_module_level=True)
playwright = pytest.importorskip("playwright.sync_api", reason="playwright is not installed (requirements.lock)")

SCREEN = (480, 270)
CHROMIUM_ARGS = ["--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--no-sandbox"]


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    with running(tmp_path_factory.mktemp("inspect-browser") / "data") as s:
        yield s


@pytest.fixture(scope="module")
def shots(tmp_path_factory):
    out = tmp_path_factory.mktemp("inspect-screenshots")
    yield out
    extra = os.environ.get("SHADOWOPT_SCREENSHOTS")
    if extra:
        Path(extra).mkdir(parents=True, exist_ok=True)
        for p in out.glob("*.png"):
            shutil.copy(p, Path(extra) / p.name)


@pytest.fixture(scope="module")
def browser():
    with playwright.sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        yield b
        b.close()


@pytest.fixture(scope="module")
def page(browser, server):
    ctx = browser.new_context(viewport={"width": 1400, "height": 900})
    pg = ctx.new_page()
    pg.errors = []
    pg.on("pageerror", lambda e: pg.errors.append(str(e)))
    pg.optimize_posts = []
    pg.on("request", lambda r: pg.optimize_posts.append(r.url) if r.url.endswith("/v1/optimize") else None)
    yield pg
    ctx.close()


def _solved(page, count: int) -> None:
    """Wait until `count` optimize answers have been drawn and nothing more is queued. Counted in answers
    (stats.drawnResponses), not in drawn frames: a split view's optimize has two answers and one frame, so
    after it the frame count (stats.latencies) stays behind the answer count and waiting on it never ended."""
    page.wait_for_function(f"""() => {{ const s = window.inspector.state;
        return s.stats.optimizeResponses >= {count} && !s.inFlight && !s.pending && s.stats.lastLatencyMs !== null
               && s.stats.drawnResponses >= {count}; }}""", timeout=60000)


def _classes(page) -> np.ndarray:
    c = page.evaluate("window.inspector.classification()")
    assert (c["width"], c["height"]) == SCREEN
    return np.array([list(r) for r in c["rows"]])


def test_page_asks_for_the_token_then_loads(page, server, shots):
    page.goto(server.base + "/inspect")
    page.wait_for_selector("#token-form:not([hidden])")
    assert "401" in page.text_content("#status")  # the server's message, shown as it is
    page.fill("#token", TOKENS["alice"])
    page.click("#token-form button")
    page.wait_for_function("document.body.dataset.ready === '1' && window.inspector.state.listings >= 1")
    assert page.evaluate("sessionStorage.getItem('shadowopt-token')") == TOKENS["alice"]
    assert "no scenes" in page.text_content("#status")
    assert page.errors == []
    page.screenshot(path=str(shots / "1-token.png"))


def test_scene_uploaded_through_the_page_appears(page, server, shots):
    page.select_option("#resolution", f"{SCREEN[0]}x{SCREEN[1]}")
    page.select_option("#budget", "1048576")  # 1024² maps: the evaluator ray-traces every texel
    page.uncheck("#auto-evaluate")
    page.set_input_files("#file", str(DEMO))
    _solved(page, 1)
    options = page.eval_on_selector_all("#scene option", "os => os.map(o => [o.value, o.textContent])")
    listed = httpx.get(server.base + "/v1/scenes", headers=auth("alice")).json()["scenes"]
    assert [o[0] for o in options] == [s["scene_id"] for s in listed] and len(listed) == 1
    assert options[0][1].startswith("demo_scene.usda")
    assert page.input_value("#camera") == "/World/Camera"
    assert len(page.optimize_posts) == 1 and page.errors == []
    page.screenshot(path=str(shots / "2-uploaded.png"))


def _evaluator_mask(server, page):
    """evaluate's classification at the canvas's resolution, decoded from its errors picture (exact shading in
    two greys, its wrongly shadowed / wrongly lit receivers in two colours): (receivers, map-shadowed)."""
    sol = page.evaluate("window.inspector.state.solution")
    rig = sol.pop("rig")
    r = httpx.post(server.base + "/v1/evaluate", headers=auth("alice"), timeout=120,
                   json={"scene_id": page.input_value("#scene"), "rig": rig, "solution": sol, "screen": list(SCREEN),
                         "heatmap": True, "heatmap_mode": "errors"})
    assert r.status_code == 200, r.text
    ev = r.json()
    img = np.asarray(Image.open(io.BytesIO(base64.b64decode(ev["heatmap_png_base64"][0]))).convert("RGB"))
    img = img[:SCREEN[1], :SCREEN[0]]
    lit, shadowed, ws, wl = (np.all(img == np.array(c), axis=-1) for c in (LIT_GREY, SHADOWED_GREY, WRONGLY_SHADOWED,
                                                                          WRONGLY_LIT))
    receivers = lit | shadowed | ws | wl
    assert receivers.sum() == ev["receiver_pixels"] and ws.sum() + wl.sum() == ev["misclassified_pixels"]
    return receivers, ws | (shadowed & ~wl), ev


def test_webgl_render_agrees_with_evaluate(page, server, shots):
    classes = _classes(page)
    receivers, map_shadowed, ev = _evaluator_mask(server, page)
    shadowed = classes == "S"
    agree = float(np.mean(shadowed[receivers] == map_shadowed[receivers]))
    print(f"WebGL vs evaluate: {agree:.4%} of {receivers.sum()} receiver pixels agree; shadowed "
          f"{shadowed[receivers].sum()} (page) vs {map_shadowed[receivers].sum()} (evaluate)")
    assert map_shadowed[receivers].sum() > 0.005 * receivers.sum()  # there are shadows to agree on
    assert agree >= 0.99
    # the page's surface is the evaluator's: hit pixels where its rays hit
    assert np.mean((classes != "0")[receivers]) >= 0.99
    page.screenshot(path=str(shots / "3-agrees.png"))


def test_sun_slider_sends_one_optimize_and_moves_the_shadows(page, shots):
    before = _classes(page)
    posts = len(page.optimize_posts)
    answered = page.evaluate("window.inspector.state.stats.optimizeResponses")
    azimuth = int(page.input_value("#azimuth"))
    page.fill("#azimuth", str(azimuth + 40 if azimuth < 100 else azimuth - 40))
    _solved(page, answered + 1)
    page.wait_for_timeout(300)  # nothing else follows
    assert len(page.optimize_posts) == posts + 1
    after = _classes(page)
    moved = np.mean((before == "S") != (after == "S"))
    assert moved > 0.003, f"only {moved:.2%} of the pixels changed shadow"
    latency = page.evaluate("window.inspector.state.stats.lastLatencyMs")
    print(f"slider to shadows on screen: {latency:.0f} ms")
    page.screenshot(path=str(shots / "4-sun-moved.png"))


def test_another_tenants_scene_is_not_listed(page, server, shots):
    other = DEMO.read_bytes() + b"\n# bob's copy\n"
    tmp = shots / "bob_scene.usda"
    tmp.write_bytes(other)
    r = upload(server.base, "bob", tmp)
    assert r.status_code == 201, r.text
    bob_id = r.json()["scene_id"]
    listed = page.evaluate("window.inspector.state.listings")
    page.click("#refresh")  # the page lists this tab's token's scenes again
    page.wait_for_function(f"window.inspector.state.listings > {listed}")
    ids = page.eval_on_selector_all("#scene option", "os => os.map(o => o.value)")
    assert bob_id not in ids and len(ids) == 1
    assert [s["scene_id"] for s in httpx.get(server.base + "/v1/scenes", headers=auth("bob")).json()["scenes"]] == [bob_id]
    status = page.evaluate(f"""async () => (await fetch('/v1/scenes/{bob_id}/geometry.glb',
        {{headers: {{Authorization: 'Bearer ' + sessionStorage.getItem('shadowopt-token')}}}})).status""")
    assert status == 404
    page.screenshot(path=str(shots / "5-other-tenant.png"))


def test_four_cascades_reversed_z_agree_with_evaluate(page, server, shots):
    """Four cascades in one array texture, Direct3D's clip space with reversed Z (EXT_clip_control, the
    comparison flipped): the same agreement."""
    for sel, value in (("#preset", "reversed_z"), ("#cascades", "4")):
        n = page.evaluate("window.inspector.state.stats.optimizeResponses")
        page.select_option(sel, value)
        _solved(page, n + 1)
    sol = page.evaluate("window.inspector.state.solution")
    assert sol["convention"]["api"] == "d3d" and sol["convention"]["reversed_z"] and len(sol["lights"][0]["cascades"]) == 4
    classes = _classes(page)
    receivers, map_shadowed, _ = _evaluator_mask(server, page)
    agree = float(np.mean((classes == "S")[receivers] == map_shadowed[receivers]))
    print(f"4 cascades, reversed Z: {agree:.4%} agree")
    assert agree >= 0.99
    page.select_option("#view", "cascades")
    page.screenshot(path=str(shots / "3b-cascades.png"))
    page.select_option("#view", "shaded")


def test_orbit_camera_agrees_with_evaluate(page, server):
    """The orbit camera: the page builds its view from the pose it sends, the evaluator from the rig."""
    n = page.evaluate("window.inspector.state.stats.optimizeResponses")
    page.select_option("#camera", "orbit")
    _solved(page, n + 1)
    rig = page.evaluate("window.inspector.state.solution.rig")
    assert "position" in rig["camera"] and "usd_path" not in rig["camera"]
    classes = _classes(page)
    receivers, map_shadowed, _ = _evaluator_mask(server, page)
    assert float(np.mean((classes == "S")[receivers] == map_shadowed[receivers])) >= 0.99
