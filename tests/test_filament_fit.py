"""solvers.engine_fits.filament: Filament's own directional shadow fit (ShadowMap.cpp, ShadowMapManager.cpp) as pure
math, checked against closed forms: the split positions, the light view, the LiSPSM warp's planes, the frustum-box
clip, the focus covering what the camera sees of the scene, the bias in the product's units, and the settings'
validation. Against the real engine (Filament.js 1.53.4's defaults): tests/test_filament_module.py."""
from __future__ import annotations

import numpy as np
import pytest

from shadowopt.solvers.cameras import Camera
from shadowopt.solvers.engine_fits import filament as fe
from shadowopt.solvers.lights import DirectionalLight

CAMERA = Camera.look(position=(0.0, 1.7, 0.0), forward=(0.0, -0.14, 0.99), fov_y_deg=58.7, near=0.1, far=300.0,
                     resolution=(320, 180))
SUN = DirectionalLight.make((0.766, -0.568, 0.302))
BOXES = [(np.array([-150.0, 0.0, -150.0]), np.array([150.0, 24.0, 150.0]))]


def test_splits_are_filaments_default_positions_over_the_receivers_depth_range():
    # tightly bound: near = max(camera near, receivers' nearest), far = min(camera far, receivers' farthest); here
    # the camera is inside the box (near 0.1) and its farthest corner ahead is nearer than the far plane (300 m)
    lo, hi = BOXES[0]
    corners = np.array([[x, y, z, 1.0] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    far = -(corners @ CAMERA.view_matrix().T)[:, 2].min()
    assert 100.0 < far < 300.0
    d = fe.splits(CAMERA, {"shadowCascades": 4}, BOXES)
    assert d == pytest.approx(0.1 + (far - 0.1) * np.array([0.0, 0.125, 0.25, 0.5, 1.0]))
    small = [(np.array([-1.0, 0.0, 9.0]), np.array([1.0, 2.0, 11.0]))]  # a box 9-11 m ahead: cut to it
    d = fe.splits(CAMERA, {"shadowCascades": 1}, small)
    assert d[0] == pytest.approx(-(CAMERA.view_matrix() @ [1.0, 2.0, 9.0, 1.0])[2], rel=0.05) and d[1] < 12.0


def test_the_light_view_looks_along_the_light_with_y_up():
    mv = fe.light_view(SUN.direction, SUN.direction * 5.0)
    p = np.array([3.0, 1.0, -2.0, 1.0])
    step = mv @ (p + np.append(SUN.direction, 0.0)) - mv @ p
    assert step[:3] == pytest.approx([0.0, 0.0, -1.0])  # one metre along the light: one metre down -Z
    assert (mv @ np.append(SUN.direction * 5.0, 1.0))[:3] == pytest.approx([0, 0, 0])  # from `position`
    assert mv[1, 1] > 0  # +Y world is up in the light's image


def test_the_lispsm_warp_maps_its_near_and_far_planes_to_minus_one_and_one():
    w = fe.warp_frustum(2.0, 10.0)
    for y, z in ((2.0, -1.0), (10.0, 1.0)):
        h = w @ [0.3, y, 0.2, 1.0]
        assert h[1] / h[3] == pytest.approx(z)


def test_clip_box_keeps_whichever_volume_lies_inside_the_other():
    cube = np.array([[x, y, z] for z in (-1, 1) for y in (-1, 1) for x in (-1, 1)], float)
    planes = np.array([[-1, 0, 0, -1], [0, -1, 0, -1], [1, 0, 0, -1], [0, 1, 0, -1], [0, 0, 1, -1], [0, 0, -1, -1]],
                      float)  # the cube's own faces, normals outward
    inner = fe.clip_box(planes, cube, np.full(3, -0.5), np.full(3, 0.5))  # a small box inside the "frustum"
    assert len(inner) == 8 and np.abs(inner).max() == pytest.approx(0.5)
    outer = fe.clip_box(planes, cube, np.full(3, -5.0), np.full(3, 5.0))  # the frustum inside the box
    assert len(outer) == 8 and np.abs(outer).max() == pytest.approx(1.0)
    half = fe.clip_box(planes, cube, np.array([0.0, -5, -5]), np.full(3, 5.0))  # half of it
    assert half[:, 0].min() == pytest.approx(0.0) and half[:, 0].max() == pytest.approx(1.0)


@pytest.mark.parametrize("settings", [{}, {"lispsm": False}, {"stable": True}, {"shadowCascades": 3}])
def test_the_fit_covers_what_the_camera_sees_of_the_scene(settings):
    maps = fe.fit(CAMERA, SUN, settings, BOXES)
    assert len(maps) == (3 if settings.get("shadowCascades") == 3 else 1)
    # ground points the camera sees between 2 and 150 m ahead: inside their cascade's map, in front of its far plane
    rng = np.random.default_rng(0)
    d = rng.uniform(2.0, 150.0, 300)
    x = rng.uniform(-0.5, 0.5, 300) * d
    pts = np.stack([x, np.zeros(300), d], axis=1)
    for m in maps:
        serve = (d >= m.split[0]) & (d < m.split[1])
        s, t, z, _ = m.map_coords(pts[serve])
        assert np.all((s >= 0) & (s <= 1) & (t >= 0) & (t <= 1) & (z <= 1.0)), m.split
    assert [m.split[1] for m in maps][-1] == np.inf and maps[0].split[0] == 0.0
    assert all(m.resolution == (1022, 1022) for m in maps)  # mapSize - 2: the 1-texel border


def test_the_bias_is_filaments_in_the_products_units():
    # a scene box around the whole camera frustum: the cascade is the whole-frustum fit the shader's bias uses
    big = [(np.full(3, -400.0), np.full(3, 400.0))]
    (m,) = fe.fit(CAMERA, SUN, {"lispsm": False, "constantBias": 0.0, "normalBias": 2.0}, big)
    hw = m.depth["hardware"]
    assert hw["constant"] == pytest.approx(0.5 / 65535) and hw["slope_scaled"] == 2.0 and hw["slope_clamp"] == 1.0
    # orthographic: texelSizeWorldSpace inverts the texture matrix (scale s (1022 / 1024) / 2 in x and y) and takes
    # 1 / 1022 of its longer column: 2 * 1024 / (s * 1022^2) with the smaller s; the normal offset is half of it per
    # unit of normalBias
    s = min(np.linalg.norm(m.projection[0, :3]), np.linalg.norm(m.projection[1, :3]))
    assert hw["normal_offset"] == pytest.approx(0.5 * 2.0 * 2.0 * 1024 / (s * 1022 ** 2), rel=1e-6)
    (m2,) = fe.fit(CAMERA, SUN, {"lispsm": False, "constantBias": 1.0, "polygonOffsetConstant": 0.0}, BOXES)
    assert m2.depth["hardware"]["constant"] == pytest.approx(1.0 / (m2.light_depth[1] - m2.light_depth[0]))


@pytest.mark.parametrize("settings, field", [({"mapSize": 1000}, "settings.mapSize"),
                                            ({"shadowCascades": 5}, "settings.shadowCascades"),
                                            ({"cascadeSplitPositions": [0.1]}, "settings.cascadeSplitPositions")])
def test_settings_filament_does_not_take_are_refused_naming_the_knob(settings, field):
    with pytest.raises(ValueError, match=f"^{field}: .*(accepted|expected)"):
        fe.fit(CAMERA, SUN, settings, BOXES)


def test_the_fit_needs_the_scene():
    with pytest.raises(ValueError, match="^boxes: .*accepted"):
        fe.fit(CAMERA, SUN, {})
