"""Fitting a map to its receivers (solvers.fitting): the map-space margin in texels and the depth range's margin,
against their closed forms."""
from __future__ import annotations

import numpy as np
import pytest


def test_texel_margin_closed_form_and_the_floor_for_degenerate_boxes():
    """texel_margin grows a box so that it takes n - 2 m of an axis's n texels: the padded extent is
    size n / (n - 2 m), centred on the box; a dimension thinner than `floor` is first grown to `floor`
    about its centre (so a point becomes a box of floor n / (n - 2 m))."""
    from shadowopt.solvers.fitting import texel_margin

    lo = np.array([0.0, 1.0, -3.0])
    hi = np.array([4.0, 1.0, -2.9999999])  # y a point, z thinner than the floor
    n, m, floor = np.array([512.0, 256.0, 100.0]), 2.0, 0.5
    lo2, hi2 = texel_margin(lo, hi, n, m, floor)
    size = np.maximum(hi - lo, floor)
    assert hi2 - lo2 == pytest.approx(size * n / (n - 2 * m), rel=1e-9)
    assert (lo2 + hi2) / 2 == pytest.approx((lo + hi) / 2, rel=1e-12, abs=1e-12)
    # no margin: exactly the floor around the point
    lo3, hi3 = texel_margin(lo, hi, n, 0.0, floor)
    assert hi3[1] - lo3[1] == pytest.approx(floor, rel=1e-9)
    assert lo3[1] == pytest.approx(1.0 - floor / 2, rel=1e-9)


def test_depth_range_grows_by_the_margin_of_the_span():
    """fitting.depth_range: [min, max] of the distances grown by `margin` of the span on each side, the span at
    least `floor` (default 1e-6 of the largest |d|). Closed forms: d in [10, 50], margin 0.01 -> [9.6, 50.4];
    a flat set at 7 -> 7 -+ 0.01 * 7e-6; an explicit floor of 2 -> 7 -+ 0.02."""
    from shadowopt.solvers.fitting import depth_range

    assert depth_range(np.array([10.0, 30.0, 50.0, np.nan]), 0.01) == pytest.approx((9.6, 50.4), rel=1e-12)
    assert depth_range(np.array([-20.0, -5.0]), 0.1) == pytest.approx((-21.5, -3.5), rel=1e-12)
    assert depth_range(np.array([7.0, 7.0]), 0.01) == pytest.approx((7.0 - 7e-8, 7.0 + 7e-8), rel=1e-15)
    assert depth_range(np.array([7.0]), 0.01, 2.0) == pytest.approx((6.98, 7.02), rel=1e-12)
