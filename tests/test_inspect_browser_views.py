"""The inspector's views in a real browser (the fixtures and helpers of tests/test_inspect_browser.py:
Debian's chromium, headless, through Playwright, against a real uvicorn on 127.0.0.1 with tokens): two
methods side by side (each half of the canvas is that method's own render, each method's numbers shown),
the overlays (cascade colours, evaluate's wrong pixels, the m heatmap's legend), the fly keys (the request's
camera moves) and engine presets (still agreeing with evaluate). Screenshots go where the other file's go."""
from __future__ import annotations

import base64
import colorsys
import io

import numpy as np
import pytest
from PIL import Image
from serverkit import DEMO, TOKENS
from test_inspect_browser import SCREEN, _classes, _evaluator_mask, _solved, browser, page, server, shots  # noqa: F401

pytestmark = pytest.mark.browser


def _responses(page) -> int:
    return page.evaluate("window.inspector.state.stats.optimizeResponses")


def _choose(page, selector: str, value: str, answers: int = 1) -> None:
    """Select `value` and wait for the `answers` optimize answers that change asks for."""
    _after(page, lambda: page.select_option(selector, value), answers)


def _after(page, act, answers: int = 1) -> None:
    """Do `act` and wait until its `answers` optimize answers are drawn and nothing more is queued (one
    drawn frame for the method and its compared twin: test_inspect_browser's _solved counts one per answer)."""
    n, drawn = _responses(page), page.evaluate("window.inspector.state.stats.latencies.length")
    act()
    page.wait_for_function(f"""() => {{ const s = window.inspector.state;
        return s.stats.optimizeResponses >= {n + answers} && !s.inFlight && !s.pending
               && s.stats.latencies.length > {drawn}; }}""", timeout=60000)


def _pixels(page, canvas: str = "view-canvas") -> np.ndarray:
    """A canvas read back as RGBA, row 0 at the top."""
    url = page.evaluate(f"document.getElementById('{canvas}').toDataURL('image/png')")
    return np.asarray(Image.open(io.BytesIO(base64.b64decode(url.split(",", 1)[1]))).convert("RGBA"))


def _evaluated(page, before: int, mode: str) -> dict:
    page.wait_for_function(f"window.inspector.state.evalSeq > {before} && window.inspector.state.evaluation "
                           f"&& window.inspector.state.evaluation.image && window.inspector.state.evaluation.mode "
                           f"=== '{mode}'", timeout=120000)
    return page.evaluate("(() => { const e = Object.assign({}, window.inspector.state.evaluation); delete e.image;"
                         " delete e.heatmap_png_base64; return e; })()")


def test_page_loads_the_demo_scene(page, server, shots):
    page.goto(server.base + "/inspect")
    page.wait_for_selector("#token-form:not([hidden])")
    page.fill("#token", TOKENS["alice"])
    page.click("#token-form button")
    page.wait_for_function("document.body.dataset.ready === '1' && window.inspector.state.listings >= 1")
    page.select_option("#resolution", f"{SCREEN[0]}x{SCREEN[1]}")
    page.select_option("#budget", "1048576")
    page.uncheck("#auto-evaluate")
    page.select_option("#method", "uniform")
    page.set_input_files("#file", str(DEMO))
    _solved(page, 1)
    assert page.evaluate("window.inspector.state.solution.method") == "uniform" and page.errors == []


def test_split_view_shows_each_methods_own_render_and_numbers(page, shots):
    """Left of the split: the first method's own single render; right: the compared method's. Compared on
    the read-back classification where the two methods' shadows differ."""
    single_a = _classes(page)  # uniform alone
    _choose(page, "#method", "focused")
    single_b = _classes(page)  # focused alone
    _choose(page, "#method", "uniform")
    assert (_classes(page) == single_a).all()  # the closed forms are deterministic: a fair reference
    page.fill("#split", "50")
    _choose(page, "#compare", "focused", answers=2)  # the method and the compared one, solved together
    split = _classes(page)
    x = int(round(SCREEN[0] * 0.5))
    left, right = np.s_[:, : x - 1], np.s_[:, x + 1:]  # the 2-pixel divide at x - 1, x is drawn white
    differ = (single_a == "S") != (single_b == "S")
    print(f"uniform vs focused: {differ[left].sum()} / {differ[right].sum()} pixels differ in shadow left / right")
    assert differ[left].sum() >= 50 and differ[right].sum() >= 50  # there is something to tell them apart by
    assert np.mean(split[left] == single_a[left]) >= 0.999 and np.mean(split[right] == single_b[right]) >= 0.999
    assert np.mean(split[left][differ[left]] == single_a[left][differ[left]]) >= 0.99
    assert np.mean(split[right][differ[right]] == single_b[right][differ[right]]) >= 0.99
    report = page.text_content("#solver-report")
    table = page.text_content("#solution-table")
    sol = page.evaluate("window.inspector.state.solution")
    cmp = page.evaluate("window.inspector.state.compareSolution")
    assert sol["method"] == "uniform" and cmp["method"] == "focused" and "uniform" in table
    assert "compared (right of the split): focused" in report
    p95 = cmp["lights"][0]["predicted_error"]["p95_m"]
    assert f"predicted p95 m {float(f'{p95:.3g}'):g}" in report.replace("e+", "e")
    page.screenshot(path=str(shots / "6-split.png"))
    page.fill("#split", "20")  # the slider moves the divide: more of the right method
    moved = _classes(page)
    x2 = int(round(SCREEN[0] * 0.2))
    assert np.mean(moved[:, x2 + 1:] == single_b[:, x2 + 1:]) >= 0.999
    assert np.mean(moved[:, : x2 - 1] == single_a[:, : x2 - 1]) >= 0.999
    _choose(page, "#compare", "")


def _surface_hues(rgba: np.ndarray, surface: np.ndarray) -> np.ndarray:
    """The hue bins (30 degrees) of the saturated surface pixels; -1 for an unsaturated one."""
    px = rgba[..., :3][surface].astype(float) / 255
    hsv = np.array([colorsys.rgb_to_hsv(*p) for p in px])
    return np.where(hsv[:, 1] > 0.12, (hsv[:, 0] * 12).astype(int) % 12, -1)


def test_cascade_colours_show_one_hue_per_cascade(page, shots):
    _choose(page, "#cascades", "4")
    k = len(page.evaluate("window.inspector.state.renderSolution.lights[0].cascades"))
    surface = _classes(page) != "0"
    shaded = _surface_hues(_pixels(page), surface)
    page.select_option("#view", "cascades")
    tinted = _surface_hues(_pixels(page), surface)
    bins, counts = np.unique(tinted[tinted >= 0], return_counts=True)
    hues = bins[counts >= 0.002 * surface.sum()]
    print(f"{k} cascades: hue bins {dict(zip(bins.tolist(), counts.tolist()))} of {surface.sum()} surface pixels; "
          f"shaded view: {np.sum(shaded >= 0)} saturated")
    assert k >= 2 and len(hues) >= k
    assert np.sum(shaded >= 0) < 0.01 * surface.sum()  # the hues are the overlay's, not the shading's
    page.screenshot(path=str(shots / "7-cascade-colours.png"))
    page.select_option("#view", "shaded")
    _choose(page, "#cascades", "1")


def test_wrong_pixel_overlay_is_evaluates_misclassified_pixels(page, shots):
    """The errors overlay shows exactly evaluate's wrongly shadowed / lit pixels (the PNG's screen-sized
    part drawn 1:1 at the canvas's resolution, every other pixel transparent): its opaque pixel count equals
    misclassified_pixels. Tolerance 0: nothing is resampled; a colour-managed or scaled copy would miss it."""
    before = page.evaluate("window.inspector.state.evalSeq")
    page.select_option("#overlay", "errors")
    ev = _evaluated(page, before, "errors")
    over = _pixels(page, "overlay-canvas")
    assert over.shape[:2] == (SCREEN[1], SCREEN[0])
    opaque = over[..., 3] == 255
    print(f"errors overlay: {opaque.sum()} opaque pixels, evaluate: {ev['misclassified_pixels']} misclassified "
          f"({ev['wrongly_shadowed_pixels']} wrongly shadowed, {ev['wrongly_lit_pixels']} wrongly lit)")
    assert ev["misclassified_pixels"] > 0
    assert opaque.sum() == ev["misclassified_pixels"]
    assert np.sum(opaque & (over[..., 0] == 213)) == ev["wrongly_shadowed_pixels"]
    assert np.sum(opaque & (over[..., 2] == 178)) == ev["wrongly_lit_pixels"]
    assert np.all((over[..., 3] == 0) | opaque)
    assert page.inner_text("#evaluation-table").count(str(ev["misclassified_pixels"])) >= 1
    page.screenshot(path=str(shots / "8-wrong-pixels.png"))


def test_m_heatmap_overlay_has_its_legend_and_none_clears_it(page, shots):
    before = page.evaluate("window.inspector.state.evalSeq")
    page.select_option("#overlay", "m")
    ev = _evaluated(page, before, "m")
    assert ev["mode"] == "m"
    over = _pixels(page, "overlay-canvas")
    assert np.mean(over[..., 3] > 0) > 0.99  # the heatmap covers the picture (alpha 0.85)
    legend = page.evaluate("(() => { const c = document.querySelector('#legend canvas'); "
                           "return c ? [c.width, c.height] : null; })()")
    assert legend and legend[0] >= SCREEN[0] and legend[1] >= 8, legend
    page.screenshot(path=str(shots / "9-m-heatmap.png"))
    page.select_option("#overlay", "none")
    assert not _pixels(page, "overlay-canvas")[..., 3].any()
    assert page.evaluate("document.querySelector('#legend canvas')") is None


def test_fly_keys_move_the_requests_camera(page, shots):
    _choose(page, "#camera", "orbit")
    page.evaluate("document.activeElement.blur()")
    cam0 = page.evaluate("window.inspector.state.solution.rig.camera")
    p0, t0 = np.array(cam0["position"]), np.array(cam0["target"])
    step = 0.15 * np.linalg.norm(t0 - p0)
    forward = (t0 - p0) / np.linalg.norm(t0 - p0)
    for key, move in (("w", forward), ("e", np.array([0.0, 1.0, 0.0]))):
        posts = len(page.optimize_posts)
        _after(page, lambda: page.keyboard.press(key))
        page.wait_for_timeout(300)
        assert len(page.optimize_posts) == posts + 1  # one optimize for the key
        p1 = np.array(page.evaluate("window.inspector.state.solution.rig.camera.position"))
        print(f"key {key}: camera moved {p1 - p0}")
        np.testing.assert_allclose(p1 - p0, step * move, atol=1e-6 * max(1.0, np.abs(p0).max()))
        p0 = p1
    page.screenshot(path=str(shots / "10-flown.png"))


@pytest.mark.parametrize("preset", ["vulkan", "engine:unity"])
def test_engine_preset_agrees_with_evaluate_as_opengl_does(page, server, shots, preset):
    """The same agreement with evaluate in OpenGL's clip space and in a preset's: Vulkan's (clip depth [0, 1],
    NDC y down: glClipControl's lower-left origin) and Unity's (the page draws the world-frame twin it asks
    beside it; evaluate scores the preset's own solution)."""
    _choose(page, "#preset", "opengl")
    base = page.evaluate("window.inspector.state.solution")
    receivers, map_shadowed, _ = _evaluator_mask(server, page)
    agree_gl = float(np.mean((_classes(page) == "S")[receivers] == map_shadowed[receivers]))
    _choose(page, "#preset", preset, answers=2 if preset.startswith("engine:") else 1)
    sol = page.evaluate("window.inspector.state.solution")
    if preset == "vulkan":
        assert sol["convention"]["api"] == "vulkan"
    else:
        assert sol["convention"].get("engine") == "unity"
        rend = page.evaluate("window.inspector.state.renderSolution")
        assert rend["convention"]["api"] == "opengl" and rend["lights"][0]["cascades"][0]["texture_matrix"] != \
            sol["lights"][0]["cascades"][0]["texture_matrix"]
    assert sol["lights"][0]["cascades"][0]["resolution"] == base["lights"][0]["cascades"][0]["resolution"]
    receivers, map_shadowed, _ = _evaluator_mask(server, page)
    classes = _classes(page)
    agree = float(np.mean((classes == "S")[receivers] == map_shadowed[receivers]))
    print(f"{preset}: {agree:.4%} agree with evaluate (opengl {agree_gl:.4%}) on {receivers.sum()} receivers")
    assert map_shadowed[receivers].sum() > 0.005 * receivers.sum()
    assert agree >= 0.99 and agree >= agree_gl - 0.005
    page.screenshot(path=str(shots / f"11-preset-{preset.replace(':', '-')}.png"))
