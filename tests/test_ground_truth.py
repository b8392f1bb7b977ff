"""Ground-truth evaluation against independent truths: resolution convergence, an exact light view,
the analytic metric, coverage, and the heatmap's colours. Shadow maps are built by hand here."""
from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from shadowopt.renderers.ground_truth import evaluate, evaluate_buffers
from shadowopt.renderers.heatmap import colour_key, ground_truth_heatmap, side_by_side
from shadowopt.renderers.ray_scene import build_ray_scene
from shadowopt.renderers.scene_data import SceneGeometry
from shadowopt.solvers.cameras import Camera
from shadowopt.solvers.lights import DirectionalLight, PointLight
from shadowopt.solvers.metric import per_sample_maps
from shadowopt.solvers.samples import Samples, pixel_derivatives
from shadowopt.solvers.shadow_map import LogWarp, ShadowMap
from testkit import box, frustum, merge, plane

BOX_LO, BOX_HI = np.array([-1.0, 0.5, 9.0]), np.array([1.0, 2.5, 11.0])
SCREEN = (320, 240)


# --- geometry helpers (as in test_coarse) -------------------------------------------------------







def rotate_x(v, deg, pivot):
    a = np.radians(deg)
    r = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    return (v - pivot) @ r.T + pivot


# --- hand-built shadow maps ---------------------------------------------------------------------

def view_matrix(eye, direction):
    f = np.asarray(direction, float) / np.linalg.norm(direction)
    up = np.array([0.0, 0.0, 1.0]) if abs(f[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    r = np.cross(f, up)
    r /= np.linalg.norm(r)
    u = np.cross(r, f)
    v = np.eye(4)
    v[0, :3], v[1, :3], v[2, :3] = r, u, -f
    v[:3, 3] = -v[:3, :3] @ np.asarray(eye, float)
    return v


def ortho(l, r, b, t, near, far):
    p = np.eye(4)
    p[0, 0], p[0, 3] = 2 / (r - l), -(r + l) / (r - l)
    p[1, 1], p[1, 3] = 2 / (t - b), -(t + b) / (t - b)
    p[2, 2], p[2, 3] = -2 / (far - near), -(far + near) / (far - near)
    return p




def ortho_map_around(direction, points, res, bias_texels=0.0, shrink=1.0):
    """An ortho light frustum fit to `points` (light-space bounding box), optionally shrunk."""
    centre = points.mean(axis=0)
    V = view_matrix(centre - 100.0 * np.asarray(direction) / np.linalg.norm(direction), direction)
    q = points @ V[:3, :3].T + V[:3, 3]
    lo, hi = q.min(axis=0), q.max(axis=0)
    mid, half = (lo + hi) / 2, (hi - lo) / 2 * shrink * 1.001
    near, far = -hi[2] - 1.0, -lo[2] + 1.0
    P = ortho(mid[0] - half[0], mid[0] + half[0], mid[1] - half[1], mid[1] + half[1], near, far)
    texel = 2 * max(half[0], half[1]) / res
    bias = {"constant": 0.5 * bias_texels * texel, "slope": bias_texels * texel}
    return ShadowMap(V, P, (res, res), light_depth=(near, far), depth_bias=bias)


def receiver_points(rs, cam, light):
    gt = evaluate_buffers(rs, cam, light, [])
    return gt.screen.position[gt.receivers]


@pytest.fixture(scope="module")
def box_scene():
    return build_ray_scene(merge(plane(40.0), box(BOX_LO, BOX_HI)))


# --- tests ----------------------------------------------------------------------------------------

def test_misclassification_falls_with_map_resolution(box_scene):
    cam = Camera.look_at([-3.0, 6.0, 5.0], [-1.0, 0.0, 12.0], resolution=SCREEN)
    light = DirectionalLight.make([-0.3, -0.8, 0.5])
    pts = np.vstack([receiver_points(box_scene, cam, light), box(BOX_LO, BOX_HI)[0]])
    out = {}
    for res in (256, 512, 1024, 2048, 4096):
        r = evaluate(box_scene, cam, light, [ortho_map_around(light.direction, pts, res, bias_texels=1.5)])
        assert r["outside_pixels"] == 0 and r["receiver_pixels"] > 30000 and r["boundary_pixels"] > 100
        out[res] = r["misclassified_pixels"]
    assert out[256] > 50  # a coarse map really misclassifies
    assert out[4096] < 0.25 * out[256]
    counts = [out[r] for r in sorted(out)]
    assert all(b <= 1.1 * a + 10 for a, b in zip(counts, counts[1:])), out  # monotone within noise
    # The exact shadow matches the slab test of the box (independent truth for the reference).
    gt = evaluate_buffers(box_scene, cam, light, [])
    ground = gt.receivers & (gt.screen.prim == 0)
    p = gt.screen.position[ground]
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / -light.direction
        t1, t2 = (BOX_LO - p) * inv, (BOX_HI - p) * inv
    blocked = np.nanmin(np.maximum(t1, t2), -1) >= np.maximum(np.nanmax(np.minimum(t1, t2), -1), 0)
    assert np.count_nonzero(blocked != gt.exact_shadowed[ground]) <= 2


@pytest.mark.parametrize("bias", [0.0, 1e-3])
def test_exact_light_view_of_a_plane_has_no_error(bias):
    rs = build_ray_scene(merge(plane(30.0)))
    cam = Camera.look_at([2.0, 5.0, -4.0], [0.0, 0.0, 15.0], resolution=SCREEN)
    light = DirectionalLight.make([0.0, -1.0, 0.0])
    sm = ortho_map_around(light.direction, plane(30.0)[0], 512)
    sm.depth_bias = {"constant": bias, "slope": 0.0}
    r = evaluate(rs, cam, light, [sm])
    assert r["receiver_pixels"] > 40000 and r["outside_pixels"] == 0
    assert r["misclassified_pixels"] == 0 and r["boundary_pixels"] == 0


def _predicted_vs_measured(rs, cam, light, sm):
    gt = evaluate_buffers(rs, cam, light, [sm])
    mask = gt.sample_mask
    assert gt.sample_kind == "all_facing" and mask.sum() > 20000
    pos = gt.screen.position[mask]
    nrm = gt.screen.normal[mask]
    dx, dy, depth = pixel_derivatives(cam, pos, nrm)
    samples = Samples(pos, nrm, dx, dy, depth, np.ones(len(pos)), np.zeros((len(pos), 2), int), "all_facing")
    _, m_pred, _ = per_sample_maps([sm], samples)
    return gt, m_pred, gt.m[mask]


@pytest.mark.parametrize("tilt", [0.0, -25.0])
@pytest.mark.parametrize("kind", ["ortho", "perspective", "log"])
def test_predicted_m_agrees_with_measured_m(tilt, kind):
    v, f = plane(25.0)
    v = rotate_x(v, tilt, np.array([0.0, 0.0, 10.0]))
    rs = build_ray_scene(merge((v, f)))
    cam = Camera.look_at([1.0, 6.0, -6.0], [0.0, 0.0, 12.0], fov_y_deg=50, resolution=SCREEN)
    if kind in ("ortho", "log"):
        light = DirectionalLight.make([0.3, -1.0, 0.4])
        sm = ortho_map_around(light.direction, v, 700)
        if kind == "log":  # t' = log(1 + 2 t) / log(3): texels denser towards t = 0
            sm.log_warp, sm.warp_kind = LogWarp(-1.0 / np.log(3.0), -2.0 / 3.0, 1.0), "log"
    else:
        eye = np.array([3.0, 14.0, 8.0])
        light = PointLight.make(eye)
        sm = ShadowMap(view_matrix(eye, [0.0, -1.0, 0.15]), frustum(1.6, 1.6, 1.0, 60.0), (600, 600),
                       light_depth=(1.0, 60.0), warp_kind="perspective")
    gt, m_pred, m_meas = _predicted_vs_measured(rs, cam, light, sm)
    rel = np.abs(m_meas - m_pred) / m_pred
    assert np.all(np.isfinite(m_pred)) and m_pred.min() < 1.0 < m_pred.max()  # both regimes present
    assert np.percentile(rel, 99) < 0.05
    stats = gt.result["measured_error"]
    for key, fn in (("mean_m", np.mean), ("median_m", np.median), ("max_m", np.max)):
        assert stats[key] == pytest.approx(fn(m_pred), rel=0.05)
    assert stats["samples"] == len(m_pred)


def test_outside_pixels_count_receivers_the_map_misses(box_scene):
    cam = Camera.look_at([0.0, 7.0, -3.0], [0.0, 0.0, 12.0], resolution=SCREEN)
    light = DirectionalLight.make([-0.3, -0.8, 0.5])
    pts = np.vstack([receiver_points(box_scene, cam, light), box(BOX_LO, BOX_HI)[0]])
    full = evaluate(box_scene, cam, light, [ortho_map_around(light.direction, pts, 512, 1.5)])
    assert full["outside_pixels"] == 0
    part = evaluate(box_scene, cam, light, [ortho_map_around(light.direction, pts, 512, 1.5, shrink=0.6)])
    assert part["outside_pixels"] > 0.1 * part["receiver_pixels"]
    assert part["receiver_pixels"] == full["receiver_pixels"]
    # Outside receivers are treated as lit: exactly shadowed ones among them are misclassified.
    assert part["misclassified_pixels"] >= full["misclassified_pixels"]


def test_cascades_are_selected_by_view_depth(box_scene):
    cam = Camera.look_at([0.0, 7.0, -3.0], [0.0, 0.0, 12.0], resolution=SCREEN)
    light = DirectionalLight.make([-0.3, -0.8, 0.5])
    gt0 = evaluate_buffers(box_scene, cam, light, [])
    pts, depth = gt0.screen.position[gt0.receivers], gt0.screen.depth[gt0.receivers]
    split = float(np.median(depth))
    near_map = ortho_map_around(light.direction, pts[depth <= split * 1.01], 1024, 1.5)
    far_map = ortho_map_around(light.direction, np.vstack([pts[depth >= split * 0.99], box(BOX_LO, BOX_HI)[0]]),
                               1024, 1.5)
    near_map.split, far_map.split = (0.0, split), (split, np.inf)
    gt = evaluate_buffers(box_scene, cam, light, [near_map, far_map])
    assert gt.result["outside_pixels"] == 0
    served = gt.map_index[gt.receivers]
    assert np.array_equal(served, np.where(depth <= split, 0, 1))
    # Swapped splits: each cascade is asked for points it does not contain.
    near_map.split, far_map.split = (split, np.inf), (0.0, split)
    swapped = evaluate(box_scene, cam, light, [near_map, far_map])
    assert swapped["outside_pixels"] > 0.2 * swapped["receiver_pixels"]


def test_pancaking_keeps_casters_in_front_of_the_near_plane(box_scene):
    cam = Camera.look_at([0.0, 7.0, -3.0], [0.0, 0.0, 12.0], resolution=SCREEN)
    light = DirectionalLight.make([0.0, -1.0, 0.0])
    pts = receiver_points(box_scene, cam, light)
    sm = ortho_map_around(light.direction, pts, 1024, 1.5)
    # Near plane 0.2 m above the ground: the box (0.5 m to 2.5 m) lies in front of it.
    eye_height = 100.0 + pts.mean(axis=0)[1]
    sm.projection = ortho(*_xy_bounds(sm), eye_height - 0.2, eye_height + 1.0)
    clamped = evaluate(box_scene, cam, light, [sm])
    clipped = evaluate(box_scene, cam, light, [sm], pancake=False)
    # The box's top (in front of the near plane) is outside the map; the ground is not.
    assert 0 < clamped["outside_pixels"] < 0.05 * clamped["receiver_pixels"]
    assert clipped["misclassified_pixels"] > 150  # clipping loses the box's shadow
    assert clamped["misclassified_pixels"] < 0.1 * clipped["misclassified_pixels"]


def _xy_bounds(sm):
    p = sm.projection
    l, r = (-1 - p[0, 3]) / p[0, 0], (1 - p[0, 3]) / p[0, 0]
    b, t = (-1 - p[1, 3]) / p[1, 1], (1 - p[1, 3]) / p[1, 1]
    return l, r, b, t


def test_heatmap_colours_and_size(tmp_path, box_scene):
    cam = Camera.look_at([0.0, 4.0, -6.0], [0.0, 0.0, 12.0], resolution=SCREEN)
    light = DirectionalLight.make([-0.3, -0.8, 0.5])
    pts = np.vstack([receiver_points(box_scene, cam, light), box(BOX_LO, BOX_HI)[0]])
    sm = ortho_map_around(light.direction, pts, 640, 1.5)
    path = tmp_path / "heat.png"
    r = evaluate(box_scene, cam, light, [sm], heatmap_path=str(path))
    img = np.asarray(Image.open(path).convert("RGB")).astype(int)
    assert img.shape == (SCREEN[1], SCREEN[0], 3)
    gt = evaluate_buffers(box_scene, cam, light, [sm])
    low = gt.receivers & (gt.m <= 1.0)
    high = gt.receivers & (gt.m >= 10 ** (2 / 3))
    assert low.sum() > 500 and high.sum() > 500 and r["receiver_pixels"] == gt.receivers.sum()
    g, rr = img[..., 1], img[..., 0]
    assert np.all((g[low] > 120) & (rr[low] < 60))  # green
    assert np.all((rr[high] > 90) & (g[high] < 10))  # red to dark red
    assert np.all(img[~gt.screen.hit] == 48)  # non-receivers: dark grey
    assert tuple(colour_key(np.array([0.5, 1.0, 10.0, 1e3]))[0]) == tuple(colour_key(np.array([1.0]))[0])
    # Grid overlay and the side-by-side report.
    grid = np.asarray(ground_truth_heatmap(gt, grid_every=8)).astype(int)
    changed = np.any(grid != img, axis=-1)
    assert changed.sum() > 200 and not changed[~gt.receivers].any()
    both = side_by_side([ground_truth_heatmap(gt), ground_truth_heatmap(gt, 8)], ["plain", "grid"],
                        str(tmp_path / "report.png"))
    assert both.width >= 2 * SCREEN[0] and both.height > SCREEN[1] + 40
    assert (tmp_path / "report.png").exists()


def test_point_light_cube_map_faces(box_scene):
    cam = Camera.look_at([0.0, 7.0, -3.0], [0.0, 0.0, 12.0], resolution=SCREEN)
    eye = np.array([0.5, 6.0, 10.0])
    light = PointLight.make(eye)
    faces = []
    for name, d in (("+x", [1, 0, 0]), ("-x", [-1, 0, 0]), ("+y", [0, 1, 0]), ("-y", [0, -1, 0]),
                    ("+z", [0, 0, 1]), ("-z", [0, 0, -1])):
        faces.append(ShadowMap(view_matrix(eye, d), frustum(0.1, 0.1, 0.1, 200.0), (1024, 1024),
                               light_depth=(0.1, 200.0), warp_kind="perspective",
                               depth_bias={"constant": 0.01, "slope": 0.02}, face=name))
    gt = evaluate_buffers(box_scene, cam, light, faces)
    r = gt.result
    assert r["outside_pixels"] == 0 and r["receiver_pixels"] > 30000
    assert gt.exact_shadowed.sum() > 300  # the box's shadow is in view
    assert r["misclassified_pixels"] < 0.05 * gt.exact_shadowed.sum()
    assert len(set(np.unique(gt.map_index[gt.receivers]).tolist())) >= 2  # several faces serve


def test_scene_far_from_origin_and_no_recompilation(monkeypatch):
    import drjit as dr

    off = np.array([1e5, 0.0, -1e5])
    v, f = plane(30.0)
    rs = build_ray_scene(merge((v + off, f), box(BOX_LO + off, BOX_HI + off)))
    light = DirectionalLight.make([0.0, -1.0, 0.0])
    cam = Camera.look_at(off + [2.0, 5.0, -4.0], off + [0.0, 0.0, 15.0], resolution=SCREEN)
    everything = np.vstack([v, box(BOX_LO, BOX_HI)[0]]) + off
    sm = ortho_map_around(light.direction, everything, 512)  # exact light view, zero bias
    r = evaluate(rs, cam, light, [sm])
    assert r["receiver_pixels"] > 40000 and r["outside_pixels"] == 0
    # Only the box's shadow outline may be misclassified (nearest texel), never acne on the plane.
    assert r["misclassified_pixels"] <= 3 * r["boundary_pixels"]
    cam2 = Camera.look_at(off + [-3.0, 4.0, -2.0], off + [1.0, 0.0, 12.0], resolution=SCREEN)
    sm2 = ortho_map_around(light.direction, everything, 512)  # same size: sizes may shape kernels
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    dr.kernel_history()
    evaluate(rs, cam2, DirectionalLight.make([0.01, -1.0, 0.02]), [sm2])
    hist = dr.kernel_history()
    dr.set_flag(dr.JitFlag.KernelHistory, False)
    compiled = [k for k in hist if k.get("type") == dr.KernelType.JIT and not k.get("cache_hit", True)]
    assert compiled == [], (f"{len(compiled)} kernels were compiled for a new camera, light and map: "
                            f"{[(k.get('hash'), k.get('size')) for k in compiled]}")

    # Maps rendered in several chunks, of a size never seen before (a fresh size per run, so that
    # Dr.Jit's on-disk kernel cache cannot hide a kernel that bakes sizes or offsets in).
    from shadowopt.renderers import shadow_map_rays as M

    monkeypatch.setattr(M, "RAY_CHUNK", 100_000)
    evaluate(rs, cam, light, [ortho_map_around(light.direction, everything, 500)])
    rng = np.random.default_rng()
    sm3 = ortho_map_around(light.direction, everything, 512)
    sm3.resolution = (int(rng.integers(600, 1000)), int(rng.integers(600, 1000)))
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    dr.kernel_history()
    r3 = evaluate(rs, cam2, light, [sm3])
    hist = dr.kernel_history()
    dr.set_flag(dr.JitFlag.KernelHistory, False)
    compiled = [k for k in hist if k.get("type") == dr.KernelType.JIT and not k.get("cache_hit", True)]
    assert compiled == [], f"map {sm3.resolution} in chunks compiled {[k.get('size') for k in compiled]}"
    assert r3["outside_pixels"] == 0 and r3["misclassified_pixels"] <= 3 * r3["boundary_pixels"]


def _test_maps(light_dir, pts):
    """An ortho map, the same map with a log warp on t, and a perspective map over the points."""
    sm = ortho_map_around(light_dir, pts, 333, bias_texels=1.5)
    logm = ShadowMap(sm.view, sm.projection, (257, 611), light_depth=sm.light_depth, warp_kind="log",
                     log_warp=LogWarp(-1.0 / np.log(3.0), -2.0 / 3.0, 1.0), depth_bias=sm.depth_bias)
    eye = pts.mean(axis=0) - 30.0 * np.asarray(light_dir) / np.linalg.norm(light_dir)
    persp = ShadowMap(view_matrix(eye, light_dir), frustum(0.5, 0.5, 1.0, 80.0), (400, 300),
                      light_depth=(1.0, 80.0), warp_kind="perspective",
                      depth_bias={"constant": 0.001, "slope": 0.001, "constant_texels": 1.5, "slope_texels": 1.0})
    return [sm, logm, persp]


def test_device_rays_and_lookup_match_the_numpy_reference(box_scene):
    """The Dr.Jit texel rays and shadow test are ShadowMap.texel_rays / map_coords + shadow_test."""
    from shadowopt.renderers import depth_tests as D
    from shadowopt.renderers import ground_truth as G
    from shadowopt.renderers import shadow_map_rays as M
    from shadowopt.renderers.mitsuba_setup import mitsuba

    import drjit as dr

    mi = mitsuba()
    cam = Camera.look_at([-3.0, 6.0, 5.0], [-1.0, 0.0, 12.0], resolution=SCREEN)
    light = DirectionalLight.make([-0.3, -0.8, 0.5])
    sb = G.render_screen(box_scene, cam, light)
    pts = np.vstack([sb.position[sb.receivers], box(BOX_LO, BOX_HI)[0]])
    X_np, N_np = sb.position[sb.hit], sb.normal[sb.hit]
    X, N = M.device_points(mi, X_np - box_scene.origin), M.device_points(mi, N_np)
    tol = D.NUMERIC_TOLERANCE * box_scene.extent
    for smap in _test_maps(light.direction, pts):
        w, h = smap.resolution
        near, dirn, length, _ = M.device_texel_rays(mi, dr, smap, box_scene.origin, dr.opaque(mi.UInt32, 0), w * h)
        jj, ii = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
        ref_near, ref_far = smap.texel_rays((ii.ravel() + 0.5) / w, (jj.ravel() + 0.5) / h)
        dev_near = np.stack([v.numpy() for v in near], -1) + box_scene.origin
        dev_far = dev_near + np.stack([v.numpy() for v in dirn], -1) * length.numpy()[:, None]
        scale = np.abs(ref_far).max()
        assert np.abs(dev_near - ref_near).max() < 1e-9 * scale and np.abs(dev_far - ref_far).max() < 1e-9 * scale
        d_occ_np = M.render_map(box_scene, light, smap)
        assert np.isfinite(d_occ_np).mean() > 0.3  # the map sees the scene
        sh, inside, u, v = D.device_lookup(box_scene, light, smap, M.device_map(box_scene, light, smap), X, N, tol)
        ref_sh, ref_out = D.shadow_test(smap, d_occ_np, X_np, N_np, light, tol)
        assert np.array_equal(inside, ~ref_out) and 0.2 < inside.mean()
        assert np.count_nonzero(sh != ref_sh) <= 1e-4 * len(sh) and sh.sum() > 100
        ref_uv = D.texel_coords(smap, X_np)
        assert np.nanmax(np.abs(np.stack([u, v], -1) - ref_uv)) < 1e-6


@pytest.mark.slow
def test_engine_depth_lookup_matches_the_numpy_reference(box_scene):
    """The Dr.Jit light pass (stored depth with the caster-side slope-scaled bias of the map's depth block,
    float32, cleared texels at 1) is engine_stored_map, and the Dr.Jit engine-faithful test (hardware and
    linear stored depth, a normal offset) is shadow_test(..., engine=...) on the same texels."""
    from shadowopt.renderers import depth_tests as D
    from shadowopt.renderers import ground_truth as G
    from shadowopt.renderers import shadow_map_rays as M
    from shadowopt.renderers.mitsuba_setup import mitsuba
    from shadowopt.solvers.depth_modes import depth_block

    mi = mitsuba()
    cam = Camera.look_at([-3.0, 6.0, 5.0], [-1.0, 0.0, 12.0], resolution=SCREEN)
    light = DirectionalLight.make([-0.3, -0.8, 0.5])
    sb = G.render_screen(box_scene, cam, light)
    pts = np.vstack([sb.position[sb.receivers], box(BOX_LO, BOX_HI)[0]])
    X_np, N_np = sb.position[sb.hit], sb.normal[sb.hit]
    X, N = M.device_points(mi, X_np - box_scene.origin), M.device_points(mi, N_np)
    for smap in _test_maps(light.direction, pts):
        smap.depth = depth_block(smap, sb.position[sb.receivers], light)
        d_occ_np, prim_np = M.render_map(box_scene, light, smap, prims=True)
        d_occ, prim = M.device_map(box_scene, light, smap, prims=True)
        for mode in ("hardware", "linear"):
            for offset in (0.0, 0.02):
                eng = {**D.engine_depth(smap, mode), "normal_offset": offset}
                assert eng["slope_scaled"] > 0 and eng["slope"] == 0.0  # the caster-side slope bias is on
                stored = M.device_engine_map(box_scene, smap, d_occ, prim, eng)
                ref_stored = M.engine_stored_map(box_scene, smap, d_occ_np, prim_np, eng)
                w, h = smap.resolution
                dev_stored = stored.numpy().reshape(h, w)
                # the light pass's depth buffer: float32 values, equal up to one float32 step on the
                # texels where float64 rounding of D + min(k DZ, m) falls on the other side of a step
                assert np.count_nonzero(np.abs(dev_stored - ref_stored) > 1.5 * np.spacing(np.float32(1))) \
                    <= 1e-4 * w * h
                assert (ref_stored < 1).mean() > 0.3
                sh, inside, u, v = D.device_lookup(box_scene, light, smap, stored, X, N, 0.0, eng)
                ref_sh, ref_out = D.shadow_test(smap, ref_stored, X_np, N_np, light, 0.0, engine=eng)
                assert np.count_nonzero(inside != ~ref_out) <= 1e-4 * len(sh) and 0.2 < inside.mean()
                assert np.count_nonzero(sh != ref_sh) <= 1e-4 * len(sh) and sh.sum() > 100, (mode, offset)
                assert np.nanmax(np.abs(np.stack([u, v], -1) - D.texel_coords(smap, X_np))) < 1e-6


def test_a_camera_that_sees_nothing_gives_zero_counts(box_scene):
    cam = Camera.look_at([0.0, 7.0, -3.0], [0.0, 20.0, -30.0], resolution=SCREEN)  # looking at the sky
    light = DirectionalLight.make([-0.3, -0.8, 0.5])
    sm = ortho_map_around(light.direction, box(BOX_LO, BOX_HI)[0], 256, 1.5)
    for maps in ([sm], []):
        r = evaluate(box_scene, cam, light, maps)
        assert r["receiver_pixels"] == 0 and r["misclassified_pixels"] == 0 and r["outside_pixels"] == 0
        assert r["misclassified_fraction"] == 0.0 and r["measured_error"]["samples"] == 0
