"""The optimizer's temporal hysteresis (Chong & Gortler 2007 §3): with the previous frame's parameters, the
previous map (refit to the current receivers) is kept unless the new map's median h is below
`hysteresis` (0.8) x the refit one's.

The band that tells the rule from "keep unless better" is a new median between 0.8x and 1x the previous
one: there the previous map must be kept. The test makes previous parameters that land in that band (a
blend of the fresh optimum's parameters with the unwarped ones, found by bisection on the blend) and checks
what a user sees: the solution's parameters are the previous ones; below 0.8x they are the fresh ones."""
from __future__ import annotations

import numpy as np
import pytest
from testkit import box, plane, scene_entry_of

from shadowopt.service.request import SolveRequest
from shadowopt.service.solve import solve

LIGHT = {"type": "directional", "direction": (-0.3, -0.8, 0.5)}
CAM = {"position": (0, 1.7, 0), "forward": (0, -0.15, 1.0), "near": 0.1, "far": 300}


@pytest.fixture(scope="module")
def entry():
    parts = [plane(100), box([-1, 0, 8], [1, 3, 10]), box([3, 0, 20], [5, 6, 23])]
    return scene_entry_of(parts)


def rig():
    return {"camera": {"resolution": (320, 180), "fov_y_deg": 60, **CAM}, "lights": [LIGHT],
            "shadow": {"resolution": (512, 512), "cascades": 1, "splits": "practical", "lambda": 0.5},
            "output": {"convention": "opengl", "layout": "column_major", "frame": "world"}, "frame": "world",
            "coarse_long_side": 120}


def with_previous(entry, x_prev):
    sol = solve(entry, rig(), SolveRequest("optimized", previous={"solver": {"x": [list(x_prev)]}}))
    t = sol["solver"]["cascades"][0]["temporal"]
    return sol, t["median_h_new"] / t["median_h_previous_refit"], t["kept_previous"]


def test_a_new_median_between_0_8_and_1_times_the_previous_keeps_the_previous_map(entry):
    fresh = solve(entry, rig(), SolveRequest("optimized"))
    x_fresh = np.asarray(fresh["solver"]["x"][0], dtype=np.float64)
    assert fresh["solver"]["cascades"][0]["chosen"] == "optimized" and np.any(x_fresh != 0)

    def prev(f):  # f = 1: the fresh optimum itself; f = 0: no warp at all (far off)
        return f * x_fresh

    # bisection on the blend for a ratio new / previous-refit in the band (0.8, 1)
    lo, hi = 0.0, 1.0
    for _ in range(12):
        f = 0.5 * (lo + hi)
        sol, ratio, kept = with_previous(entry, prev(f))
        if 0.84 < ratio < 0.96:
            break
        lo, hi = (f, hi) if ratio < 0.9 else (lo, f)
    assert 0.84 < ratio < 0.96, (f, ratio)
    assert kept, ratio
    assert sol["solver"]["x"][0] == pytest.approx(list(prev(f)), abs=1e-12)  # the previous parameters, kept

    # clearly better (below 0.8x): replaced by the fresh optimum
    sol, ratio, kept = with_previous(entry, prev(0.5 * f))
    assert ratio < 0.8 and not kept, ratio
    assert sol["solver"]["x"][0] == pytest.approx(list(x_fresh), rel=1e-6, abs=1e-9)

    # worse than the previous (above 1x): kept too
    sol, ratio, kept = with_previous(entry, prev(1.2))
    assert ratio > 1.0 and kept, ratio
    assert sol["solver"]["x"][0] == pytest.approx(list(prev(1.2)), abs=1e-12)
