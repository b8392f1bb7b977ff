"""Output conventions against hand-computed values."""
from __future__ import annotations

import numpy as np
import pytest

from shadowopt.solvers import fitting
from shadowopt.solvers.conventions import (CONVENTIONS, LAYOUTS, clip_from_canonical, export_matrices,
                                           from_layout, from_stage_frame, projection_for, stage_from,
                                           texture_from_clip, texture_matrix, to_layout, to_stage_frame)
from shadowopt.solvers.frames import stage_to_world
from shadowopt.solvers.shadow_map import ShadowMap


def project(m, p):
    h = m @ np.append(p, 1.0)
    return h[:3] / h[3]


# The canonical projections, written out from the OpenGL reference pages (glOrtho, glFrustum), so these
# tests do not depend on the code under test or on solvers.fitting (whose agreement is checked below).
def ortho(l, r, b, t, n, f):
    return np.array([[2 / (r - l), 0, 0, -(r + l) / (r - l)],
                     [0, 2 / (t - b), 0, -(t + b) / (t - b)],
                     [0, 0, -2 / (f - n), -(f + n) / (f - n)],
                     [0, 0, 0, 1.0]])


def frustum(l, r, b, t, n, f):
    return np.array([[2 * n / (r - l), 0, (r + l) / (r - l), 0],
                     [0, 2 * n / (t - b), (t + b) / (t - b), 0],
                     [0, 0, -(f + n) / (f - n), -2 * f * n / (f - n)],
                     [0, 0, -1.0, 0]])


def test_project_projections_are_the_canonical_opengl_ones():
    # the canonical clip space the conventions start from is what solvers.fitting builds
    assert np.allclose(fitting.ortho(-2, 3, -1, 4, 0.5, 20), ortho(-2, 3, -1, 4, 0.5, 20))
    assert np.allclose(fitting.frustum(-0.7, 0.4, -0.5, 0.6, 2, 40), frustum(-0.7, 0.4, -0.5, 0.6, 2, 40))


@pytest.mark.parametrize("P", [ortho(-3, 2, -1, 2, 0.5, 30), frustum(-0.7, 0.4, -0.5, 0.6, 0.2, 80)])
def test_random_points_each_convention_ndc(P):
    # canonical NDC (x, y, z) -> opengl (x, y, z); d3d (x, y, (z+1)/2); vulkan (x, -y, (z+1)/2)
    rng = np.random.default_rng(11)
    pts = np.column_stack([rng.uniform(-2, 2, 200), rng.uniform(-2, 2, 200), -rng.uniform(0.5, 30, 200)])
    for p in pts:
        x, y, z = project(P, p)
        assert np.allclose(project(projection_for(P, "opengl"), p), [x, y, z])
        assert np.allclose(project(projection_for(P, "d3d"), p), [x, y, (z + 1) / 2])
        assert np.allclose(project(projection_for(P, "vulkan"), p), [x, -y, (z + 1) / 2])
        # texture coordinates from the canonical NDC, by the documented formulas
        st = {"opengl": [(x + 1) / 2, (y + 1) / 2, (z + 1) / 2],
              "d3d": [(x + 1) / 2, (1 - y) / 2, (z + 1) / 2],
              "vulkan": [(x + 1) / 2, (1 - y) / 2, (z + 1) / 2]}
        for conv in CONVENTIONS:
            assert np.allclose(project(texture_matrix(np.eye(4), P, conv), p), st[conv]), conv
        # the w row never changes: the perspective divide is the same in every convention
        for conv in CONVENTIONS:
            assert np.allclose(projection_for(P, conv)[3], P[3])


def test_clip_and_bias_matrices_by_hand():
    assert np.array_equal(clip_from_canonical("d3d"), [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, .5, .5], [0, 0, 0, 1]])
    assert np.array_equal(clip_from_canonical("vulkan"), [[1, 0, 0, 0], [0, -1, 0, 0], [0, 0, .5, .5], [0, 0, 0, 1]])
    assert np.array_equal(texture_from_clip("opengl"), [[.5, 0, 0, .5], [0, .5, 0, .5], [0, 0, .5, .5], [0, 0, 0, 1]])
    assert np.array_equal(texture_from_clip("d3d"), [[.5, 0, 0, .5], [0, -.5, 0, .5], [0, 0, 1, 0], [0, 0, 0, 1]])
    assert np.array_equal(texture_from_clip("vulkan"), [[.5, 0, 0, .5], [0, .5, 0, .5], [0, 0, 1, 0], [0, 0, 0, 1]])
    for bad in ("metal", "OpenGL", ""):
        with pytest.raises(ValueError, match="convention"):
            clip_from_canonical(bad)
        with pytest.raises(ValueError, match="convention"):
            texture_from_clip(bad)


# (plane of the light's ortho frustum, which texture coordinate, its value per convention)
_PLANES = [("left", 0, {"opengl": 0, "d3d": 0, "vulkan": 0}), ("right", 0, {"opengl": 1, "d3d": 1, "vulkan": 1}),
           ("bottom", 1, {"opengl": 0, "d3d": 1, "vulkan": 1}), ("top", 1, {"opengl": 1, "d3d": 0, "vulkan": 0}),
           ("near", 2, {"opengl": 0, "d3d": 0, "vulkan": 0}), ("far", 2, {"opengl": 1, "d3d": 1, "vulkan": 1})]


@pytest.mark.parametrize("conv", CONVENTIONS)
@pytest.mark.parametrize("plane, axis, value", _PLANES)
def test_texture_matrix_on_light_frustum_planes(conv, plane, axis, value):
    # light 10 m above the origin looking down; ortho x in [-2, 2], y in [-1, 1], distance in [1, 11]:
    # light view (x, y, z) is world (x, 10 + z, -y). Random points on each plane of that box.
    P = ortho(-2, 2, -1, 1, 1, 11)
    rng = np.random.default_rng(5)
    x, y, d = rng.uniform(-2, 2, 30), rng.uniform(-1, 1, 30), rng.uniform(1, 11, 30)
    x = {"left": np.full(30, -2.0), "right": np.full(30, 2.0)}.get(plane, x)
    y = {"bottom": np.full(30, -1.0), "top": np.full(30, 1.0)}.get(plane, y)
    d = {"near": np.full(30, 1.0), "far": np.full(30, 11.0)}.get(plane, d)
    world = np.column_stack([x, 10.0 - d, -y])
    T = texture_matrix(LIGHT_DOWN, P, conv)
    got = np.array([project(T, p) for p in world])
    assert np.allclose(got[:, axis], value[conv])
    assert np.all((got > -1e-12) & (got < 1 + 1e-12))  # inside the box: everything in [0, 1]


# Light 10 m above the origin looking straight down (-Y): light view (x, y, z) = (x, -z, y - 10).
LIGHT_DOWN = np.array([[1.0, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, -10], [0, 0, 0, 1]])


def test_each_convention_clip_space_ortho():
    P = ortho(-2, 2, -1, 1, 1, 11)  # x in [-2,2], y in [-1,1], distance in [1, 11]
    near_top_right = np.array([2.0, 1.0, -1.0])
    far_bottom_left = np.array([-2.0, -1.0, -11.0])
    assert np.allclose(project(P, near_top_right), [1, 1, -1]) and np.allclose(project(P, far_bottom_left), [-1, -1, 1])
    d3d = clip_from_canonical("d3d") @ P
    assert np.allclose(project(d3d, near_top_right), [1, 1, 0]) and np.allclose(project(d3d, far_bottom_left), [-1, -1, 1])
    vk = clip_from_canonical("vulkan") @ P
    assert np.allclose(project(vk, near_top_right), [1, -1, 0]) and np.allclose(project(vk, far_bottom_left), [-1, 1, 1])
    assert np.array_equal(clip_from_canonical("opengl"), np.eye(4))


def test_each_convention_ndc_of_a_perspective_point():
    # glFrustum(-1, 1, -1, 1, 1, 3); view point (0.5, 0.25, -2), w = 2:
    # x = 0.5/2 = 0.25, y = 0.25/2 = 0.125, z = (-(3+1)/(3-1) * -2 - 2*3*1/(3-1)) / 2 = (4 - 3)/2 = 0.5
    P = frustum(-1, 1, -1, 1, 1, 3)
    p = np.array([0.5, 0.25, -2.0])
    expected = {"opengl": [0.25, 0.125, 0.5],
                "d3d": [0.25, 0.125, 0.75],      # depth (z + 1)/2
                "vulkan": [0.25, -0.125, 0.75]}  # depth (z + 1)/2 and y flipped
    for conv, ndc in expected.items():
        assert np.allclose(project(projection_for(P, conv), p), ndc), conv
    # texture (s, t, depth): opengl t = (y+1)/2, depth (z+1)/2; d3d and vulkan t = (1 - y_gl)/2, depth z_d3d
    tex = {"opengl": [0.625, 0.5625, 0.75], "d3d": [0.625, 0.4375, 0.75], "vulkan": [0.625, 0.4375, 0.75]}
    for conv, st in tex.items():
        assert np.allclose(project(texture_matrix(np.eye(4), P, conv), p), st), conv


@pytest.mark.parametrize("conv", CONVENTIONS)
def test_depth_range_near_and_far_planes(conv):
    P = frustum(-1, 1, -1, 1, 1, 3)
    lo = -1.0 if conv == "opengl" else 0.0
    assert project(projection_for(P, conv), [0.0, 0.0, -1.0])[2] == pytest.approx(lo)
    assert project(projection_for(P, conv), [0.0, 0.0, -3.0])[2] == pytest.approx(1.0)


@pytest.mark.parametrize("conv, top_right_st, bottom_left_st", [
    ("opengl", (1, 1), (0, 0)),  # t = 0 at the bottom
    ("d3d", (1, 0), (0, 1)),     # v flipped: origin top-left
    ("vulkan", (1, 0), (0, 1)),  # NDC y down: origin top-left
])
def test_texture_matrix_maps_frustum_corners(conv, top_right_st, bottom_left_st):
    P = ortho(-2, 2, -1, 1, 1, 11)
    T = texture_matrix(LIGHT_DOWN, P, conv)
    # world points of the light frustum: light-view (2, 1, -1) is world (2, 9, -1); (-2, -1, -11) is (-2, -1, 1)
    tr = project(T, np.array([2.0, 9.0, -1.0]))
    bl = project(T, np.array([-2.0, -1.0, 1.0]))
    mid = project(T, np.array([0.0, 4.0, 0.0]))
    assert np.allclose(tr[:2], top_right_st) and np.allclose(bl[:2], bottom_left_st)
    assert tr[2] == pytest.approx(0.0) and bl[2] == pytest.approx(1.0)  # depth in [0, 1] near to far
    assert np.allclose(mid, [0.5, 0.5, 0.5])
    # the chain is exactly S · C · P · V
    assert np.allclose(T, texture_from_clip(conv) @ clip_from_canonical(conv) @ P @ LIGHT_DOWN)


@pytest.mark.parametrize("conv", CONVENTIONS)
def test_texture_coordinates_agree_with_the_internal_map(conv):
    # ShadowMap.map_coords is the internal (OpenGL) s, t; top-left conventions see t mirrored
    rng = np.random.default_rng(3)
    P = frustum(-0.7, 0.4, -0.5, 0.6, 2, 40)
    view = LIGHT_DOWN
    sm = ShadowMap(view, P, (512, 512))
    pts = np.column_stack([rng.uniform(-3, 3, 50), rng.uniform(-25, 5, 50), rng.uniform(-3, 3, 50)])
    s, t, z, _ = sm.map_coords(pts)
    T = texture_matrix(view, P, conv)
    got = np.array([project(T, p) for p in pts])
    assert np.allclose(got[:, 0], s)
    assert np.allclose(got[:, 1], t if conv == "opengl" else 1.0 - t)
    assert np.allclose(got[:, 2], (z + 1) / 2)  # depth in [0, 1] in every convention


def test_layout_round_trip_and_memory_order():
    m = np.arange(16, dtype=float).reshape(4, 4)
    assert to_layout(m, "row_major")[:4] == [0, 1, 2, 3]
    assert to_layout(m, "column_major")[:4] == [0, 4, 8, 12]
    for lay in ("row_major", "column_major"):
        assert np.array_equal(from_layout(to_layout(m, lay), lay), m)
    with pytest.raises(ValueError, match="layout"):
        to_layout(m, "diagonal")
    with pytest.raises(ValueError, match="16"):
        from_layout(list(range(12)), "row_major")
    # an OpenGL ortho's translation sits at memory indices 12, 13, 14 in column-major (glUniformMatrix4fv)
    P = ortho(0, 4, 0, 2, 1, 11)
    flat = to_layout(P, "column_major")
    assert flat[12:15] == pytest.approx([-1.0, -1.0, -1.2]) and flat[3] == 0.0
    assert to_layout(P, "row_major")[3] == pytest.approx(-1.0)


def test_export_matrices_layout_and_convention():
    P = frustum(-1, 1, -1, 1, 1, 3)
    out = export_matrices(LIGHT_DOWN, P, "vulkan", "row_major", "world")
    assert set(out) == {"view_matrix", "projection_matrix", "texture_matrix"}
    assert all(len(v) == 16 for v in out.values())
    assert np.allclose(from_layout(out["view_matrix"], "row_major"), LIGHT_DOWN)
    assert np.allclose(from_layout(out["projection_matrix"], "row_major"), clip_from_canonical("vulkan") @ P)
    col = export_matrices(LIGHT_DOWN, P, "vulkan", "column_major", "world")
    for key in out:
        assert np.allclose(from_layout(col[key], "column_major"), from_layout(out[key], "row_major"))
    for bad in (dict(convention="metal"), dict(layout="diagonal"), dict(frame="camera")):
        args = dict(convention="opengl", layout="row_major", frame="world") | bad
        with pytest.raises(ValueError):
            export_matrices(LIGHT_DOWN, P, **args)


@pytest.mark.parametrize("conv", CONVENTIONS)
def test_stage_frame_matrices_act_on_stage_coordinates(conv):
    s2w = stage_to_world("Z", 0.01)  # Z up, centimetres
    view = LIGHT_DOWN.copy()
    view[:3, 3] += [1.0, -2.0, 3.0]
    P = frustum(-5, 5, -5, 5, 0.1, 50)
    world = export_matrices(view, P, conv, "row_major", "world")
    stage = export_matrices(view, P, conv, "row_major", "stage", s2w)
    p_stage = np.array([120.0, -40.0, 250.0])  # cm, Z up
    p_world = np.array([1.2, 2.5, 0.4])  # (x, z, -y) / 100, by hand
    assert np.allclose(s2w @ np.append(p_stage, 1), np.append(p_world, 1))
    for key in ("view_matrix", "texture_matrix"):
        a = from_layout(world[key], "row_major") @ np.append(p_world, 1)
        b = from_layout(stage[key], "row_major") @ np.append(p_stage, 1)
        assert np.allclose(a, b)
    # the stage matrix differs from the world one (it really takes centimetres, Z up)
    assert not np.allclose(world["view_matrix"], stage["view_matrix"])
    assert world["projection_matrix"] == stage["projection_matrix"]
    # frame "stage" without a conversion: the stage is the world frame
    assert export_matrices(view, P, conv, "row_major", "stage") == world
    assert np.allclose(to_stage_frame(view, np.eye(4)), view)


def test_stage_frame_inverses():
    s2w = stage_to_world("Z", 0.01)  # world = 0.01 (x, z, -y) of the stage point
    view = LIGHT_DOWN.copy()
    view[:3, 3] += [1.0, -2.0, 3.0]  # light view = (x + 1, -z - 2, y - 7)
    st = to_stage_frame(view, s2w)
    assert np.allclose(from_stage_frame(st, s2w), view)
    # by hand: the light sits at world (-1, 7, -2); light view (0, 0, -1) is world (-1, 6, -2), i.e. the
    # stage point 100 (x, -z, y) = (-100, 200, 600) cm
    assert np.allclose(view @ np.array([-1.0, 7.0, -2.0, 1.0]), [0, 0, 0, 1])
    assert np.allclose(stage_from(view, s2w) @ np.array([0.0, 0.0, -1.0, 1.0]), [-100, 200, 600, 1])
    assert np.allclose(stage_from(view, s2w) @ st, np.eye(4))
    # the texture chain's inverse for a point: the centre texel at depth 0.75 (NDC z 0.5 -> distance 2 for
    # glFrustum n = 1, f = 3: (2d - 3)/d = 0.5) is light view (0, 0, -2) = world (-1, 5, -2) = stage
    # (-100, 200, 500); homogeneous, so divide by w
    P = frustum(-1, 1, -1, 1, 1, 3)
    for conv in CONVENTIONS:
        h = stage_from(texture_matrix(view, P, conv), s2w) @ np.array([0.5, 0.5, 0.75, 1.0])
        assert np.allclose(h[:3] / h[3], [-100, 200, 500]), conv


@pytest.mark.parametrize("layout", LAYOUTS)
def test_layout_round_trip_random(layout):
    m = np.random.default_rng(2).normal(size=(4, 4))
    flat = to_layout(m, layout)
    assert isinstance(flat, list) and len(flat) == 16 and all(isinstance(v, float) for v in flat)
    assert np.array_equal(from_layout(flat, layout), m)
    other = "column_major" if layout == "row_major" else "row_major"
    assert np.array_equal(from_layout(flat, other), m.T)  # reading in the wrong order transposes


@pytest.mark.parametrize("P", [ortho(-3, 2, -1, 2, 0.5, 30), frustum(-0.7, 0.4, -0.5, 0.6, 0.2, 80)])
def test_reversed_z_near_is_one_far_is_zero(P):
    # reversed Z (Reed 2015, "Depth Precision Visualized"): window depth 1 at the light's near plane, 0 at
    # the far plane; x, y, w and the texture s, t are those of the unreversed convention
    near, far = (0.5, 30) if P[3, 3] == 1 else (0.2, 80)
    for conv in CONVENTIONS:
        R = projection_for(P, conv, reversed_z=True)
        F = projection_for(P, conv)
        assert np.allclose(R[[0, 1, 3]], F[[0, 1, 3]])
        for d, want in ((near, 1.0), (far, 0.0)):
            z_ndc = project(R, np.array([0.1, -0.2, -d]))[2]
            window = (z_ndc + 1) / 2 if conv == "opengl" else z_ndc  # glDepthRange(0, 1) / D3D viewport
            assert np.isclose(window, want), (conv, d)
            tex = project(texture_matrix(np.eye(4), P, conv, reversed_z=True), np.array([0.1, -0.2, -d]))
            assert np.isclose(tex[2], want)
        # in between: the texture depth is 1 - the unreversed one, for every point
        p = np.array([0.3, 0.1, -0.5 * (near + far)])
        a = project(texture_matrix(np.eye(4), P, conv, reversed_z=True), p)
        b = project(texture_matrix(np.eye(4), P, conv), p)
        assert np.allclose(a[:2], b[:2]) and np.isclose(a[2], 1 - b[2])
    assert np.array_equal(clip_from_canonical("d3d", True), [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, -.5, .5], [0, 0, 0, 1]])
    assert np.array_equal(clip_from_canonical("opengl", True), np.diag([1.0, 1.0, -1.0, 1.0]))
    out = export_matrices(np.eye(4), P, "vulkan", "row_major", reversed_z=True)
    assert np.allclose(from_layout(out["projection_matrix"], "row_major"), clip_from_canonical("vulkan", True) @ P)


def test_texture_origin_override_and_convention_info():
    from shadowopt.solvers.conventions import convention_info

    # an engine that samples a d3d-clip map bottom-left: t = 0.5 + 0.5 y; depth passes through
    assert np.array_equal(texture_from_clip("d3d", "bottom-left"), [[.5, 0, 0, .5], [0, .5, 0, .5], [0, 0, 1, 0], [0, 0, 0, 1]])
    # Vulkan's NDC y points down: bottom-left is t = 0.5 - 0.5 y_vk
    assert np.array_equal(texture_from_clip("vulkan", "bottom-left")[1], [0, -.5, 0, .5])
    assert np.array_equal(texture_from_clip("opengl", "top-left")[1], [0, -.5, 0, .5])
    with pytest.raises(ValueError, match="texture_origin"):
        texture_from_clip("opengl", "centre")
    # the plain conventions in the world frame; a Z-up centimetre stage: +Z up, right-handed, lengths in metres
    info = convention_info({"convention": "vulkan", "reversed_z": True})
    assert (info["frame"], info["handedness"], info["up_axis"], info["length_unit"], info["texture_origin"],
            info["reversed_z"], info["engine"]) == ("world", "right", "+Y", "metres", "top-left", True, None)
    info = convention_info({"frame": "stage"}, stage_to_world("Z", 0.01))
    assert (info["frame"], info["handedness"], info["up_axis"], info["length_unit"]) == ("stage", "right", "+Z", "metres")


def test_perpendicular_up_needs_more_than_1e_6_of_perpendicular_component():
    """A hint is usable when its component perpendicular to `forward` is longer than 1e-6 (the light within
    ~1e-6 rad of the view axis falls back to the camera's up): at exactly 1e-6 the next hint is taken, just
    above it the hint itself. The perpendicular parts here are exact in binary floating point."""
    from shadowopt.solvers.light_frames import perpendicular_up

    f = np.array([0.0, 0.0, 1.0])
    at = np.array([1e-6, 0.0, 1.0])  # h - (h.f) f = (1e-6, 0, 0): norm exactly 1e-6
    assert np.linalg.norm(at - np.dot(at, f) * f) == 1e-6
    assert perpendicular_up(f, at, [0.0, 1.0, 0.0]) == pytest.approx([0.0, 1.0, 0.0], abs=0)
    above = np.array([2e-6, 0.0, 1.0])
    assert perpendicular_up(f, above, [0.0, 1.0, 0.0]) == pytest.approx([1.0, 0.0, 0.0], abs=0)
