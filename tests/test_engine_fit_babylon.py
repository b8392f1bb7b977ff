"""solvers.engine_fits.babylon: Babylon.js 9.35's CascadedShadowGenerator fit as pure math, against the formulas of
its source worked by hand (Lights/Shadows/cascadedShadowGenerator.pure.js) and the geometry they must produce:
the split formula, numCascades clamped to [2, 4], a shadowMaxZ beyond the camera's ignored, the bias 1.5x in the
default PCF + depthClamp path, every slice inside its cascade's map, the world origin on a texel corner."""
from __future__ import annotations

import numpy as np
import pytest

from shadowopt.solvers.cameras import Camera
from shadowopt.solvers.engine_fits import babylon
from shadowopt.solvers.lights import DirectionalLight

CAM = Camera.look([3.0, 4.0, 20.0], [0.2, -0.3, -1.0], near=0.5, far=300.0, fov_y_deg=50.0, resolution=(640, 360))
SUN = DirectionalLight.make([0.4, -1.0, 0.3])


def _fit(**settings):
    return babylon.fit(CAM, SUN, babylon.validate(settings))


def test_splits_follow_babylons_practical_formula():
    maps = _fit(numCascades=3, **{"lambda": 0.7})
    n, f = 0.5, 300.0
    want = [0.7 * n * (f / n) ** p + 0.3 * (n + (f - n) * p) for p in (1 / 3, 2 / 3, 1.0)]
    assert [m.split[1] for m in maps] == pytest.approx(want)
    assert maps[0].split[0] == n and [m.split[0] for m in maps[1:]] == pytest.approx(want[:2])


@pytest.mark.parametrize("asked, got", [(1, 2), (3, 3), (8, 4)])
def test_num_cascades_is_clamped_to_two_to_four(asked, got):
    assert len(_fit(numCascades=asked)) == got


def test_a_shadow_max_z_beyond_the_camera_far_plane_is_ignored():
    assert _fit(shadowMaxZ=1e5)[-1].split[1] == pytest.approx(300.0)
    assert _fit(shadowMaxZ=120.0)[-1].split[1] == pytest.approx(120.0)


@pytest.mark.parametrize("filt, clamp, factor", [("PCF", True, 1.5), ("PCF", False, 0.5), ("NONE", True, 1.0)])
def test_the_bias_reaches_the_stored_depth_as_the_shaders_add_it(filt, clamp, factor):
    block = _fit(bias=0.001, filter=filt, depthClamp=clamp)[0].depth
    assert block["hardware"]["constant"] == pytest.approx(0.001 * factor)
    assert block["hardware"]["constant_side"] == "caster"
    assert block["format"] == ("float16" if filt == "NONE" else "unorm24")


@pytest.mark.parametrize("stable", [False, True])
def test_every_slice_lies_in_its_cascade_and_the_origin_on_a_texel_corner(stable):
    maps = _fit(numCascades=4, stabilizeCascades=stable, mapSize=512)
    to_world = np.linalg.inv(CAM.view_matrix())
    th = CAM.tan_half_fov_y
    for m in maps:
        for d in m.split:  # the slice's corners at both ends of the view depths it serves
            for sx in (-1, 1):
                for sy in (-1, 1):
                    p = to_world @ np.array([sx * th * CAM.aspect * d, sy * th * d, -d, 1.0])
                    c = m.projection @ m.view @ p
                    assert np.all(np.abs(c[:3] / c[3]) <= 1.0 + 4.0 / 512), (m.split, c)
        o = (m.projection @ m.view)[:2, 3] * 512 / 2
        assert o == pytest.approx(np.round(o), abs=1e-6)
        assert np.allclose(m.view[:3, :3] @ m.view[:3, :3].T, np.eye(3))  # a rigid light view (world -> -Z forward)
        assert m.view[2, :3] @ SUN.direction == pytest.approx(-1.0)  # it looks along the sun
        if stable:
            r = 1.0 / m.projection[0, 0]
            assert r * 16 == pytest.approx(round(r * 16))


def test_a_knob_outside_babylons_range_names_its_field():
    with pytest.raises(ValueError, match=r"^settings\.normalBias: expected a number in \[0, 0\]"):
        babylon.validate({"normalBias": 0.1})
    with pytest.raises(ValueError, match=r"^settings\.filter: expected one of 'PCF', 'NONE'"):
        babylon.validate({"filter": "PCSS"})


CASTERS = (np.array([-20.0, -1.0, -30.0]), np.array([25.0, 10.0, 15.0]))  # a world box: the render list's bounds
MIRROR = np.diag([-1.0, 1.0, 1.0])  # the babylon preset's frame


RUNS = [{"numCascades": 8, "shadowMaxZ": 1e5, "mapSize": 1024},  # clamped to 4; a shadowMaxZ the setter ignores
        {"numCascades": 3, "lambda": 0.8, "shadowMaxZ": 120.0, "stabilizeCascades": True, "depthClamp": False,
         "filter": "NONE", "mapSize": 512}]


@pytest.mark.browser
def test_the_fit_matches_babylon_js_own_cascade_matrices():
    """Babylon.js 9.35 in Chromium (service/bench/babylon_harness/ fitCascades): its CascadedShadowGenerator with the same
    camera, sun, settings (RUNS) and caster box; each cascade's transform (projection . view, world -> clip) equals
    the emulation's in Babylon's frame, to float32 precision."""
    from web_engine_kit import BABYLON, SCREEN, babylon_fallback, babylon_files, launch_browser, render_page

    runs = [babylon.validate(r) for r in RUNS]
    cam = {"position": list(MIRROR @ CAM.position), "forward": list(MIRROR @ CAM.forward), "up": list(MIRROR @ CAM.up),
           "fov_y_deg": CAM.fov_y_deg, "near": CAM.near, "far": CAM.far}
    lo, hi = MIRROR @ CASTERS[0], MIRROR @ CASTERS[1]
    params = {"screen": list(SCREEN), "camera": cam, "sun_direction": list(MIRROR @ SUN.direction),
              "casters_box": [list(np.minimum(lo, hi)), list(np.maximum(lo, hi))], "runs": runs}
    browser = launch_browser(BABYLON / "index.js", "Babylon.js (make setup)")
    try:
        out = render_page(next(browser), babylon_files(), babylon_fallback, params, call="fitCascades")
    finally:
        browser.close()
    to_world = np.eye(4)
    to_world[:3, :3] = MIRROR
    for s, got in zip(runs, out["runs"]):
        maps = babylon.fit(CAM, SUN, s, casters_box=CASTERS)
        effective = babylon.effective(s, CAM)
        assert got["numCascades"] == effective["numCascades"] == len(maps), (s, got)
        assert got["shadowMaxZ"] == pytest.approx(effective["shadowMaxZ"]), (s, got)
        for m, t in zip(maps, got["transforms"]):
            mine = m.projection @ m.view @ to_world  # Babylon-frame points -> clip
            theirs = np.asarray(t).reshape(4, 4).T  # Matrix.m: column-major for column vectors
            assert theirs == pytest.approx(mine, rel=1e-4, abs=1e-5 * np.abs(mine).max()), (s, m.split, theirs, mine)
