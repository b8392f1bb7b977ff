"""The inspector's lights in a real browser (the fixtures and helpers of tests/test_inspect_browser.py: Debian's
chromium, headless, through Playwright, against a real uvicorn on 127.0.0.1 with tokens): the light picker lists
the scene's lights; a spot light's map and a point light's cube faces or face-partitioned maps (faces of
different sizes) are drawn with the document's shadow-lookup-local piece, and budgeted cascades (one size per light)
drawn from their layers; each render agrees with evaluate's shadowed/lit classification on >= 99% of the
receiver pixels (evaluate's own receivers: for the spot, those inside its cone). The scene is the demo scene
with a spot and a point light added (tests/lights_scene.py, written to a temporary folder). Screenshots go where
the other files' go."""
from __future__ import annotations

import numpy as np
import pytest
from lights_scene import write_lights_scene
from serverkit import TOKENS
from test_inspect_browser import SCREEN, _classes, _evaluator_mask, _solved, browser, page, server, shots  # noqa: F401

pytestmark = pytest.mark.browser


def _responses(page) -> int:
    return page.evaluate("window.inspector.state.stats.optimizeResponses")


def _choose(page, selector: str, value: str, answers: int = 1) -> None:
    n = _responses(page)
    page.select_option(selector, value)
    _solved(page, n + answers)


def _agreement(page, server) -> tuple[float, int, int, dict]:
    classes = _classes(page)
    receivers, map_shadowed, ev = _evaluator_mask(server, page)
    agree = float(np.mean((classes == "S")[receivers] == map_shadowed[receivers]))
    return agree, int(receivers.sum()), int(map_shadowed[receivers].sum()), ev


@pytest.fixture(scope="module")
def lights_scene(tmp_path_factory):
    return write_lights_scene(tmp_path_factory.mktemp("lights-scene"))


def test_the_light_picker_lists_the_scenes_lights(page, server, lights_scene, shots):
    page.goto(server.base + "/inspect")
    page.wait_for_selector("#token-form:not([hidden])")
    page.fill("#token", TOKENS["alice"])
    page.click("#token-form button")
    page.wait_for_function("document.body.dataset.ready === '1' && window.inspector.state.listings >= 1")
    page.select_option("#resolution", f"{SCREEN[0]}x{SCREEN[1]}")
    page.select_option("#budget", "1048576")
    page.uncheck("#auto-evaluate")
    page.set_input_files("#file", str(lights_scene))
    _solved(page, 1)
    options = page.eval_on_selector_all("#light option", "os => os.map(o => [o.value, o.textContent])")
    assert [o[0] for o in options] == ["sliders", "/World/Sun", "/World/Spot", "/World/Bulb"]
    assert "(spot)" in options[2][1] and "(point)" in options[3][1]
    assert page.errors == []


def test_spot_light_render_agrees_with_evaluate(page, server, shots):
    _choose(page, "#light", "/World/Spot")
    sol = page.evaluate("window.inspector.state.renderSolution")
    light = sol["lights"][0]
    assert light["type"] == "spot" and light["shadow"] == "map" and len(light["cascades"]) == 1
    assert "no shadow" not in page.text_content("#render-note")
    agree, receivers, shadowed, ev = _agreement(page, server)
    print(f"spot: {agree:.4%} of {receivers} receiver pixels agree with evaluate ({shadowed} map-shadowed; evaluate "
          f"{ev['misclassified_pixels']} misclassified)")
    assert shadowed > 0.005 * receivers  # there are shadows to agree on
    assert agree >= 0.99
    classes = _classes(page)  # outside the cone the page lights nothing: only in-cone pixels are receivers
    assert np.sum(np.isin(classes, ["L", "S"])) <= 1.01 * receivers
    page.screenshot(path=str(shots / "lights-1-spot.png"))


def test_point_light_faces_agree_with_evaluate(page, server, shots):
    _choose(page, "#light", "/World/Bulb")
    light = page.evaluate("window.inspector.state.renderSolution.lights[0]")
    maps = light["cascades"]
    sizes = {tuple(m["resolution"]) for m in maps}
    print(f"point light: {len(maps)} maps, faces {[m['face'] for m in maps]}, sizes {sorted(sizes)}, "
          f"{(light.get('face_partitioning') or {}).get('chosen', 'cube')}")
    assert light["type"] == "point" and len(maps) >= 2 and all(m.get("face") for m in maps)
    agree, receivers, shadowed, ev = _agreement(page, server)
    print(f"point: {agree:.4%} of {receivers} receiver pixels agree with evaluate ({shadowed} map-shadowed; "
          f"evaluate {ev['misclassified_pixels']} misclassified, {ev['outside_pixels']} outside)")
    assert shadowed > 0.005 * receivers
    assert agree >= 0.99
    page.select_option("#view", "cascades")
    page.screenshot(path=str(shots / "lights-2-point-faces.png"))
    page.select_option("#view", "shaded")


def test_point_light_cube_faces_agree_with_evaluate(page, server, shots):
    """shadow.point_light_maps "cube" from the page's picker: the cube's faces (one size, each a 90 degree
    frustum), served by the first face holding the point as evaluate takes it."""
    _choose(page, "#point-maps", "cube")
    light = page.evaluate("window.inspector.state.renderSolution.lights[0]")
    maps = light["cascades"]
    assert page.evaluate("window.inspector.state.solution.rig.shadow.point_light_maps") == "cube"
    assert light["type"] == "point" and len(maps) >= 2 and all(m.get("face") for m in maps)
    assert len({tuple(m["resolution"]) for m in maps}) == 1 and "face_partitioning" not in light
    agree, receivers, shadowed, ev = _agreement(page, server)
    print(f"point, cube: {len(maps)} faces {[m['face'] for m in maps]} of {maps[0]['resolution']}: {agree:.4%} of "
          f"{receivers} receiver pixels agree with evaluate ({shadowed} map-shadowed)")
    assert shadowed > 0.005 * receivers and agree >= 0.99
    page.screenshot(path=str(shots / "lights-2b-point-cube.png"))
    _choose(page, "#point-maps", "auto")


def test_budgeted_cascades_share_one_size_and_agree_with_evaluate(page, server, shots):
    """Cascades under a texel budget: the service gives one light's cascades one size (solvers.cascades
    ONE_SIZE_PER_LIGHT: engines keep them in one texture array), the inspector draws each from its layer, and the
    render agrees with evaluate."""
    _choose(page, "#light", "/World/Sun")
    _choose(page, "#cascades", "3")
    maps = page.evaluate("window.inspector.state.renderSolution.lights[0].cascades")
    sizes = [tuple(m["resolution"]) for m in maps]
    print(f"budgeted cascades: {sizes}")
    assert len(sizes) >= 2 and len(set(sizes)) == 1, sizes
    agree, receivers, shadowed, _ = _agreement(page, server)
    print(f"budgeted cascades: {agree:.4%} of {receivers} receiver pixels agree ({shadowed} map-shadowed)")
    assert shadowed > 0.005 * receivers and agree >= 0.99
    page.screenshot(path=str(shots / "lights-3-auto-cascades.png"))
    _choose(page, "#cascades", "1")


def test_solved_counts_answers_after_the_split_view(page):
    """A split view's optimize has two answers and one drawn frame: the helper still returns once the
    next answer is drawn (it waited on the frame count before, and never returned after a split view)."""
    _choose(page, "#compare", "focused", answers=2)
    _choose(page, "#compare", "")
    n = _responses(page)
    page.fill("#azimuth", str(int(page.input_value("#azimuth")) + 20))
    _solved(page, n + 1)
    stats = page.evaluate("window.inspector.state.stats")
    assert stats["drawnResponses"] == stats["optimizeResponses"] == n + 1
    assert len(stats["latencies"]) < stats["optimizeResponses"]  # the frame count lags: what the helper hung on
