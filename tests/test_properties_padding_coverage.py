"""More fit padding never loses coverage.

Each fitted map keeps PAD_TEXELS texels free on each side of its receivers (solvers.fitting.texel_margin; the
optimizer's solvers.optimize._padded_box). Coverage must come from the exact receivers (service.receivers.receiver_points:
coarse hits, the edge pass and their tangent-plane reach), not from the pad being tiny: with any pad, from none
to a wide one, every receiver pixel of the full-resolution screen lies inside a map. Independent truth: the
ground-truth evaluation's exact ray-traced receivers (evaluate_solution's outside_pixels: receiver pixels outside
every map). The padding is checked to have taken effect: the focused maps' texels grow with it."""
from __future__ import annotations

import numpy as np
import pytest
from testkit import box, plane, scene_entry_of

from shadowopt.service.evaluation import evaluate_solution
from shadowopt.service.request import SolveRequest
from shadowopt.service.solve import solve
from shadowopt.solvers import baselines, optimize, warp

PADS = (0.0, 64.0)  # texels on each side of a 512-texel map: none, an eighth of the map
CAM = {"position": (0, 1.7, 0), "forward": (0, -0.15, 1.0), "near": 0.1, "far": 300, "resolution": (320, 180),
       "fov_y_deg": 60}


@pytest.fixture(scope="module")
def entry():
    parts = [plane(100), box([-1, 0, 8], [1, 3, 10]), box([3, 0, 20], [5, 6, 23])]
    return scene_entry_of(parts)


def rig(cascades):
    return {"camera": CAM, "lights": [{"type": "directional", "direction": (-0.3, -0.8, 0.5)}],
            "shadow": {"resolution": (512, 512), "cascades": cascades, "splits": "practical", "lambda": 0.5},
            "output": {"convention": "opengl", "layout": "column_major", "frame": "world"}, "frame": "world",
            "coarse_long_side": 120}


# one optimized cascade: the optimizer's own map is the one kept (with four, most cascades keep a baseline)
@pytest.mark.parametrize("method, cascades", [("optimized", 1), ("optimized", 4), ("focused", 4)])
def test_more_fit_padding_never_loses_coverage(entry, method, cascades, monkeypatch):
    mean_m = []
    for pad in PADS:
        monkeypatch.setattr(baselines, "PAD_TEXELS", pad)
        monkeypatch.setattr(optimize, "PAD_TEXELS", pad)
        monkeypatch.setattr(warp, "PAD_TEXELS", pad)  # the log warp's padding (warp.padded_log)
        r = rig(cascades)
        sol = solve(entry, r, SolveRequest(method))
        res = evaluate_solution(entry, r, sol, screen=(320, 180))
        assert res["outside_pixels"] == 0, (method, cascades, pad, res["outside_pixels"])
        if (method, cascades) == ("optimized", 1):
            assert sol["solver"]["cascades"][0]["chosen"] == "optimized", pad
        mean_m.append(sol["lights"][0]["predicted_error"]["mean_m"])
    if method == "focused":  # the pad did take effect: the same receivers on fewer texels, coarser texels
        assert mean_m[0] < mean_m[1], mean_m
