"""The benchmark's hand-fitted plain shadow map (service/bench/engine_baselines.py): the light box is tight around the
scene, its depth axis is the sun, and the hand settings are 3 biases x front/double-sided in the box's depth units."""
from __future__ import annotations

import numpy as np
import pytest

from shadowopt.service.bench.engine_baselines import BIAS_TEXELS, SIDES, grid, light_box, light_frame


@pytest.mark.parametrize("sun", [(-0.3, -0.6, -0.74), (0.0, -1.0, 0.0), (0.8, -0.2, 0.1)])
def test_the_box_holds_every_vertex_and_each_face_touches_one(sun):
    rng = np.random.default_rng(3)
    v = rng.normal(size=(200, 3)) * [30.0, 5.0, 12.0] + [1e3, 0.0, -40.0]
    corners, extents = light_box(v, sun)
    R = light_frame(sun)
    assert R @ R.T == pytest.approx(np.eye(3), abs=1e-12)
    assert R[2] == pytest.approx(np.asarray(sun) / np.linalg.norm(sun))  # depth along the light's travel
    p, c = v @ R.T, corners @ R.T
    assert np.all(p >= c.min(axis=0) - 1e-9) and np.all(p <= c.max(axis=0) + 1e-9)
    assert p.min(axis=0) == pytest.approx(c.min(axis=0)) and p.max(axis=0) == pytest.approx(c.max(axis=0))
    assert extents == pytest.approx(c.max(axis=0) - c.min(axis=0))


def test_the_hand_grid_is_three_biases_in_texels_of_depth_times_two_sides():
    settings = grid(np.array([200.0, 100.0, 50.0]), 1000)  # a texel: 0.2 m; the depth range: 50 m
    assert len(settings) == len(BIAS_TEXELS) * len(SIDES) == 6
    assert {s["side"] for s in settings} == {"front", "double"}
    assert sorted({s["bias"] for s in settings}) == pytest.approx([k * 0.2 / 50.0 for k in BIAS_TEXELS])
