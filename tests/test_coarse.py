"""Coarse buffers against independent truths: analytic planes, spheres and a box's shadow."""
from __future__ import annotations

import numpy as np
import pytest

from shadowopt.renderers.coarse import boundary_mask, render_coarse
from shadowopt.renderers.ray_scene import build_ray_scene
from shadowopt.renderers.scene_data import SceneGeometry
from shadowopt.solvers.cameras import Camera
from shadowopt.solvers.lights import DirectionalLight, PointLight, SpotLight
from testkit import box, merge, plane

BOX_LO, BOX_HI = np.array([-1.0, 0.5, 9.0]), np.array([1.0, 2.5, 11.0])






def uv_sphere(center, r, n=128):
    th = np.linspace(0, np.pi, n + 1)
    ph = np.linspace(0, 2 * np.pi, 2 * n, endpoint=False)
    T, P = np.meshgrid(th, ph, indexing="ij")
    v = np.stack([np.sin(T) * np.cos(P), np.cos(T), np.sin(T) * np.sin(P)], -1).reshape(-1, 3) * r + center
    m = 2 * n
    f = []
    for i in range(n):
        for j in range(m):
            a, b, c, d = i * m + j, i * m + (j + 1) % m, (i + 1) * m + j, (i + 1) * m + (j + 1) % m
            f += [[a, c, b], [b, c, d]]
    return v, np.array(f)




def ray_plane_truth(cam: Camera, w, h, y=0.0):
    d = cam.ray_directions(w, h)
    t = (y - cam.position[1]) / d[..., 1]
    hit = t > 0
    return hit, cam.position + t[..., None] * d, t


def box_shadow_truth(p, to_light):
    """Slab test: is the ray p + s*to_light (s > 0) blocked by the box?"""
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / to_light
        t1 = (BOX_LO - p) * inv
        t2 = (BOX_HI - p) * inv
    tmin = np.nanmax(np.minimum(t1, t2), axis=-1)
    tmax = np.nanmin(np.maximum(t1, t2), axis=-1)
    return (tmax >= np.maximum(tmin, 0.0))


@pytest.fixture(scope="module")
def box_scene():
    return build_ray_scene(merge(plane(), box(BOX_LO, BOX_HI)))


def test_plane_positions_normals_depth_match_ray_plane_intersection():
    rs = build_ray_scene(merge(plane()))
    cam = Camera.look_at([0.3, 2.0, -1.0], [5.0, 0.0, 20.0], resolution=(640, 480))
    cb = render_coarse(rs, cam, [DirectionalLight.make([0.2, -1.0, 0.1])])
    assert (cb.width, cb.height) == (180, 135)
    hit_true, pos_true, t_true = ray_plane_truth(cam, cb.width, cb.height)
    hit_true &= np.all(np.abs(pos_true[..., [0, 2]]) < 200, axis=-1)
    assert np.array_equal(cb.hit, hit_true)
    err = np.linalg.norm(cb.position[cb.hit] - pos_true[cb.hit], axis=-1) / t_true[cb.hit]
    assert err.max() < 1e-5  # relative to the distance: float32 ray casting
    assert np.allclose(cb.normal[cb.hit], [0, 1, 0], atol=1e-6)
    d = cam.ray_directions(cb.width, cb.height)
    depth_true = t_true * (d @ cam.forward)
    assert np.allclose(cb.depth[cb.hit], depth_true[cb.hit], rtol=1e-5)
    assert np.all(np.isinf(cb.depth[~cb.hit])) and np.all(cb.prim_id[~cb.hit] == -1)
    assert cb.lights[0].visible[cb.hit].all() and cb.lights[0].facing[cb.hit].all()


def test_sphere_positions_lie_on_the_sphere_and_normals_point_out():
    c, r, n = np.array([0.0, 1.0, 6.0]), 1.5, 128
    rs = build_ray_scene(merge(uv_sphere(c, r, n)))
    cam = Camera.look_at([0.0, 1.0, 0.0], c, fov_y_deg=40, resolution=(400, 400))
    cb = render_coarse(rs, cam, [DirectionalLight.make([0, -1, 0])])
    # Analytic ray-sphere hits; tessellation makes the silhouette differ by at most a pixel ring.
    d = cam.ray_directions(cb.width, cb.height)
    oc = cam.position - c
    b = d @ oc
    disc = b * b - (oc @ oc - r * r)
    hit_true = disc > 0
    assert abs(int(cb.hit.sum()) - int(hit_true.sum())) < 0.03 * hit_true.sum()
    dist = np.linalg.norm(cb.position[cb.hit] - c, axis=-1)
    sagitta = r * (1 - np.cos(np.pi / n))  # deepest a flat facet gets under the sphere
    assert np.all(dist <= r + 1e-4) and np.all(dist >= r - sagitta - 1e-4)
    outward = (cb.position[cb.hit] - c) / dist[:, None]
    assert np.all(np.sum(outward * cb.normal[cb.hit], axis=-1) > np.cos(np.radians(3)))
    # Light from above: the upper half is lit and facing, the lower half faces away.
    lb = cb.lights[0]
    up = cb.position[..., 1] > c[1] + 0.05 * r
    down = cb.position[..., 1] < c[1] - 0.05 * r
    assert lb.lit[cb.hit & up].all() and not lb.facing[cb.hit & down].any()


@pytest.mark.parametrize("direction", [[0.0, -1.0, 0.0], [-0.3, -0.8, 0.5], [0.6, -0.4, -0.2]])
def test_box_shadow_on_ground_matches_slab_test(box_scene, direction):
    cam = Camera.look_at([0.0, 6.0, -2.0], [0.0, 0.0, 12.0], resolution=(800, 800))
    light = DirectionalLight.make(direction)
    cb = render_coarse(box_scene, cam, [light])
    ground = cb.hit & (cb.prim_id == 0)
    assert ground.sum() > 10000
    shadowed_true = box_shadow_truth(cb.position[ground], -light.direction)
    visible = cb.lights[0].visible[ground]
    assert shadowed_true.sum() > 50  # the shadow is in view
    assert np.count_nonzero(visible == shadowed_true) <= 2  # exact rays; ties only at the outline


def test_boundary_mask_follows_the_analytic_outline(box_scene):
    cam = Camera.look_at([0.0, 8.0, 0.0], [0.0, 0.0, 12.0], resolution=(900, 900))
    light = DirectionalLight.make([-0.3, -0.8, 0.5])
    cb = render_coarse(box_scene, cam, [light], boundary_radius=0)
    ground = cb.hit & (cb.prim_id == 0)
    lit_true = np.zeros_like(ground)
    lit_true[ground] = ~box_shadow_truth(cb.position[ground], -light.direction)
    # Every ground pixel whose analytic state differs from a ground 4-neighbour's is on the boundary.
    expected = np.zeros_like(ground)
    for a, b in (((slice(None, -1), slice(None)), (slice(1, None), slice(None))),
                 ((slice(None), slice(None, -1)), (slice(None), slice(1, None)))):
        diff = ground[a] & ground[b] & (lit_true[a] != lit_true[b])
        expected[a] |= diff
        expected[b] |= diff
    got = cb.lights[0].boundary & ground
    assert expected.sum() > 20
    assert np.array_equal(got, expected)
    # Dilation by r grows the mask by r pixels and only onto hits.
    cb2 = render_coarse(box_scene, cam, [light], boundary_radius=2)
    assert (cb2.lights[0].boundary | ~cb2.hit)[got].all() and cb2.lights[0].boundary.sum() > got.sum()
    assert not (cb2.lights[0].boundary & ~cb2.hit).any()


def test_boundary_mask_ignores_depth_discontinuities():
    lit = np.array([[1, 1, 0, 0]], bool)
    hit = np.ones_like(lit)
    same = np.array([[10, 10.1, 10.2, 10.3]], np.float32)
    far = np.array([[10, 10.1, 20.0, 20.1]], np.float32)
    assert boundary_mask(lit, hit, same, radius=0).tolist() == [[False, True, True, False]]
    assert not boundary_mask(lit, hit, far, radius=0).any()


def test_spot_cone_and_point_light_visibility():
    rs = build_ray_scene(merge(plane(), box(BOX_LO, BOX_HI)))
    cam = Camera.look_at([0.0, 8.0, 0.0], [0.0, 0.0, 12.0], resolution=(600, 600))
    lp = np.array([0.0, 6.0, 10.0])
    spot = SpotLight.make(lp, [0.0, -1.0, 0.0], 30.0)
    point = PointLight.make(lp)
    cb = render_coarse(rs, cam, [spot, point])
    ground = cb.hit & (cb.prim_id == 0)
    to_l = lp - cb.position[ground]
    cos_axis = to_l[:, 1] / np.linalg.norm(to_l, axis=1)  # angle between the axis (0,-1,0) and light->p
    inside = cos_axis >= np.cos(np.radians(30.0))
    margin = np.abs(cos_axis - np.cos(np.radians(30.0))) > 1e-5
    assert np.array_equal(cb.lights[0].in_light[ground][margin], inside[margin])
    assert cb.lights[1].in_light[ground].all()
    # Point light straight above the box: the box hides the ground right below it.
    ps = cb.position[ground]
    toward = (lp - ps) / np.linalg.norm(lp - ps, axis=1, keepdims=True)
    shadowed = np.array([box_shadow_truth(p[None], t[None])[0] for p, t in zip(ps, toward)])
    assert shadowed.sum() > 50
    assert np.count_nonzero(cb.lights[1].visible[ground] == shadowed) <= 2


def test_scene_far_from_origin_keeps_millimetre_precision():
    off = np.array([1e5, 0.0, -1e5])
    v, f = plane(50.0)
    rs = build_ray_scene(merge((v + off, f)))
    cam = Camera.look_at(off + [0.0, 1.7, 0.0], off + [3.0, 0.0, 20.0], resolution=(320, 240))
    cb = render_coarse(rs, cam, [DirectionalLight.make([0.3, -0.7, 0.2])])
    hit_true, pos_true, _ = ray_plane_truth(cam, cb.width, cb.height)
    both = cb.hit & hit_true
    assert both.sum() > 1000
    assert np.abs(cb.position[both] - pos_true[both]).max() < 1e-3
    assert cb.lights[0].visible[both].all()  # no self-shadowing acne on a plane


def test_new_camera_reuses_the_compiled_kernel(box_scene):
    import drjit as dr

    light = DirectionalLight.make([-0.3, -0.8, 0.5])
    render_coarse(box_scene, Camera.look_at([0, 5, 0], [0, 0, 10]), [light])
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    dr.kernel_history_clear() if hasattr(dr, "kernel_history_clear") else dr.kernel_history()
    # Same coarse size: Dr.Jit writes the packed sizes of evaluated vectors into the kernel, so each
    # coarse resolution compiles once (measured); a camera or light change must not.
    render_coarse(box_scene, Camera.look_at([1, 4, -1], [2, 0, 12]), [DirectionalLight.make([0.2, -0.9, 0.1])])
    hist = dr.kernel_history()
    dr.set_flag(dr.JitFlag.KernelHistory, False)
    compiled = [k for k in hist if k.get("type") == dr.KernelType.JIT and not k.get("cache_hit", True)]
    assert compiled == [], f"{len(compiled)} kernels were compiled for a new camera and light"
