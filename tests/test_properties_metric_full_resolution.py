"""The predicted error is in the rig's full-resolution pixels, end to end: coarse buffers (ray-traced at
whatever coarse size), sample selection, pixel derivatives and the metric.

Independent truth (closed form): a camera looking straight down from height H at a flat ground sees a
ground pixel p = 2 H tan(fov_y / 2) / H_px metres wide (the ground is at one view depth, so every pixel is
the same size). An overhead sun's orthographic map of R x R texels fitted to a ground rectangle of
size X x Y with PAD_TEXELS texels free on each side (solvers.fitting.texel_margin) has texels of
X / (R - 2 PAD) by Y / (R - 2 PAD) metres, perpendicular on the ground, so the texel footprint in pixels
is F = diag(tx, ty) / p and m = |ds +- dt| = sqrt(tx^2 + ty^2) / p (Lloyd et al. 2007 eq. 85),
h = ||F||_F^2 = (tx^2 + ty^2) / p^2 (Chong & Gortler 2007 eqs. 6 and 9).
"""
from __future__ import annotations

import math

import numpy as np
import pytest
from testkit import plane

from shadowopt.renderers.ray_scene import build_ray_scene
from shadowopt.renderers.scene_data import LoadedScene, SceneGeometry
from shadowopt.service.scenes import SceneEntry
from shadowopt.service.request import SolveRequest
from shadowopt.service.solve import solve
from shadowopt.solvers.fitting import PAD_TEXELS
from shadowopt.solvers.frames import stage_to_world

HEIGHT, FOV_Y = 10.0, 50.0
HALF = 100.0  # the ground: [-HALF, HALF]^2 at y = 0


@pytest.fixture(scope="module")
def ground():
    v, f = plane(HALF)
    g = SceneGeometry(v, f.astype(np.int32), np.zeros(len(f), np.int32), ["/ground"])
    loaded = LoadedScene("mem", "hash", g, [], [], "Y", 1.0, stage_to_world("Y", 1.0), None)
    return SceneEntry(loaded, build_ray_scene(g), 0.0, 0.0)


def overhead_rig(screen, map_res, coarse):
    return {"camera": {"position": (0, HEIGHT, 0), "forward": (0, -1, 0), "up": (0, 0, 1), "resolution": screen,
                       "fov_y_deg": FOV_Y, "near": 0.1, "far": 100},
            "lights": [{"type": "directional", "direction": (0, -1, 0)}],
            "shadow": {"resolution": (map_res, map_res), "cascades": 1, "splits": "practical", "lambda": 0.5},
            "output": {"convention": "opengl", "layout": "column_major", "frame": "world"}, "frame": "world",
            "coarse_long_side": coarse}


@pytest.mark.parametrize("screen", [(1280, 720), (640, 480)])
@pytest.mark.parametrize("coarse", [96, 180])
def test_predicted_m_is_the_texel_footprint_in_full_resolution_pixels(ground, screen, coarse):
    w_px, h_px = screen
    th = math.tan(math.radians(FOV_Y / 2))
    ground_h = 2 * HEIGHT * th  # the visible ground rectangle (overhead camera), metres
    ground_w = ground_h * w_px / h_px
    pixel = ground_h / h_px  # one full-resolution pixel on the ground, metres
    res = 1024
    cases = {
        # focused: fitted to the visible receivers, i.e. the visible rectangle
        "focused": math.hypot(ground_w, ground_h) / (res - 2 * PAD_TEXELS),
        # uniform: fitted to the scene's bounds, the whole 2 HALF square
        "uniform": math.hypot(2 * HALF, 2 * HALF) / (res - 2 * PAD_TEXELS),
    }
    for method, texel_diagonal in cases.items():
        pe = solve(ground, overhead_rig(screen, res, coarse), SolveRequest(method))["lights"][0]["predicted_error"]
        m_true = texel_diagonal / pixel
        assert pe["samples"] > 0
        for key in ("mean_m", "median_m", "max_m"):
            assert pe[key] == pytest.approx(m_true, rel=1e-4), (method, screen, coarse, key, pe)
        assert pe["frac_m_gt_1"] == (1.0 if m_true > 1 else 0.0)
        assert pe["objective"] == pytest.approx(m_true ** 2, rel=2e-4), (method, screen, coarse, pe)
