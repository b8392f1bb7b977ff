"""Output conventions against hand-computed values."""
from __future__ import annotations

import numpy as np
import pytest

from shadowopt.solvers.conventions import (clip_from_canonical, export_matrices, from_layout, texture_matrix,
                                           to_layout)
from shadowopt.solvers.fitting import ortho
from shadowopt.solvers.frames import stage_to_world


def project(m, p):
    h = m @ np.append(p, 1.0)
    return h[:3] / h[3]


def test_each_convention_clip_space():
    P = ortho(-2, 2, -1, 1, 1, 11)  # x in [-2,2], y in [-1,1], distance in [1, 11]
    near_top_right = np.array([2.0, 1.0, -1.0])
    far_bottom_left = np.array([-2.0, -1.0, -11.0])
    assert np.allclose(project(P, near_top_right), [1, 1, -1]) and np.allclose(project(P, far_bottom_left), [-1, -1, 1])
    d3d = clip_from_canonical("d3d") @ P
    assert np.allclose(project(d3d, near_top_right), [1, 1, 0]) and np.allclose(project(d3d, far_bottom_left), [-1, -1, 1])
    vk = clip_from_canonical("vulkan") @ P
    assert np.allclose(project(vk, near_top_right), [1, -1, 0]) and np.allclose(project(vk, far_bottom_left), [-1, 1, 1])


@pytest.mark.parametrize("conv, top_right_st, bottom_left_st", [
    ("opengl", (1, 1), (0, 0)),  # t = 0 at the bottom
    ("d3d", (1, 0), (0, 1)),     # v flipped: origin top-left
    ("vulkan", (1, 0), (0, 1)),  # NDC y down: origin top-left
])
def test_texture_matrix_maps_frustum_corners(conv, top_right_st, bottom_left_st):
    view = np.eye(4)
    P = ortho(-2, 2, -1, 1, 1, 11)
    T = texture_matrix(view, P, conv)
    tr = project(T, np.array([2.0, 1.0, -1.0]))
    bl = project(T, np.array([-2.0, -1.0, -11.0]))
    assert np.allclose(tr[:2], top_right_st) and np.allclose(bl[:2], bottom_left_st)
    assert tr[2] == pytest.approx(0.0) and bl[2] == pytest.approx(1.0)  # depth in [0, 1] near to far


def test_layout_round_trip_and_memory_order():
    m = np.arange(16, dtype=float).reshape(4, 4)
    assert to_layout(m, "row_major")[:4] == [0, 1, 2, 3]
    assert to_layout(m, "column_major")[:4] == [0, 4, 8, 12]
    for lay in ("row_major", "column_major"):
        assert np.array_equal(from_layout(to_layout(m, lay), lay), m)
    with pytest.raises(ValueError, match="layout"):
        to_layout(m, "diagonal")


def test_stage_frame_matrices_act_on_stage_coordinates():
    s2w = stage_to_world("Z", 0.01)  # Z up, centimetres
    view = np.eye(4)
    view[:3, 3] = [1.0, -2.0, 3.0]
    P = ortho(-5, 5, -5, 5, 0.1, 50)
    world = export_matrices(view, P, "opengl", "row_major", "world")
    stage = export_matrices(view, P, "opengl", "row_major", "stage", s2w)
    p_stage = np.array([120.0, -40.0, 250.0])  # cm, Z up
    p_world = np.array([1.2, 2.5, 0.4])  # (x, z, -y) / 100
    for key in ("view_matrix", "texture_matrix"):
        a = from_layout(world[key], "row_major") @ np.append(p_world, 1)
        b = from_layout(stage[key], "row_major") @ np.append(p_stage, 1)
        assert np.allclose(a, b)
    assert world["projection_matrix"] == stage["projection_matrix"]
