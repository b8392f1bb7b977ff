"""The metric against closed forms and an independent finite-difference path."""
from __future__ import annotations

import numpy as np
import pytest

from shadowopt.solvers.cameras import Camera
from shadowopt.solvers.lights import DirectionalLight, SpotLight
from shadowopt.solvers.metric import DeviceSamples, matrix_to_device, objective, per_sample_maps, predicted_error, recentre
from shadowopt.solvers.samples import GRAZING_LIGHT_DEG, Samples, pixel_derivatives, select_samples
from shadowopt.solvers.shadow_map import LogWarp, ShadowMap
from testkit import frustum


def look_down_view(center, dir_=(0.0, -1.0, 0.0), up=(0.0, 0.0, 1.0)):
    f = np.asarray(dir_, float) / np.linalg.norm(dir_)
    r = np.cross(f, up)
    r /= np.linalg.norm(r)
    u = np.cross(r, f)
    v = np.eye(4)
    v[0, :3], v[1, :3], v[2, :3] = r, u, -f
    v[:3, 3] = -v[:3, :3] @ np.asarray(center, float)
    return v


def ortho(half_w, half_h, near, far):
    p = np.diag([1 / half_w, 1 / half_h, -2 / (far - near), 1.0])
    p[2, 3] = -(far + near) / (far - near)
    return p




def samples_on_plane(cam, pts, normal):
    n = np.broadcast_to(np.asarray(normal, float), pts.shape).copy()
    dx, dy, d = pixel_derivatives(cam, pts, n)
    return Samples(pts, n, dx, dy, d, np.ones(len(pts)), np.zeros((len(pts), 2), int), "boundary")


@pytest.mark.parametrize("texels", [500, 1000, 4000])
def test_overhead_camera_and_light_closed_form(texels):
    # Camera 10 m above the ground looking straight down, 90 deg fov, 1000 px: a pixel is 0.02 m.
    # An ortho light straight down over 20 m with `texels` texels: a texel is 20/texels m.
    cam = Camera.look([0, 10, 0], [0, -1, 0], up=[0, 0, 1], fov_y_deg=90, resolution=(1000, 1000))
    sm = ShadowMap(look_down_view([0, 20, 0]), ortho(10, 10, 1, 50), (texels, texels))
    err = predicted_error([sm], samples_on_plane(cam, np.array([[0.0, 0, 0]]), [0, 1, 0]))
    a = (20 / texels) / 0.02  # texel size in pixels
    assert err["objective"] == pytest.approx(2 * a * a, rel=1e-9)  # |F|_F^2 of a*I
    assert err["max_m"] == pytest.approx(np.sqrt(2) * a, rel=1e-9)  # longer diagonal of an a x a square
    assert err["frac_m_gt_1"] == (1.0 if np.sqrt(2) * a > 1 else 0.0)


def _fd_jacobian(cam, sm, pixel, plane_point, plane_normal, eps=1e-3):
    """Texels per pixel by central differences of map coordinates of ray-plane hits (NumPy only)."""
    w, h = cam.resolution
    th = cam.tan_half_fov_y
    tw = th * cam.aspect

    def hit(px, py):
        a = ((px + 0.5) / w * 2 - 1) * tw
        b = (1 - (py + 0.5) / h * 2) * th
        d = cam.forward + a * cam.right + b * cam.up
        t = np.dot(plane_normal, plane_point - cam.position) / np.dot(plane_normal, d)
        s, tt, _, _ = sm.map_coords((cam.position + t * d)[None])
        return np.array([s[0] * sm.resolution[0], tt[0] * sm.resolution[1]])

    px, py = pixel
    jx = (hit(px + eps, py) - hit(px - eps, py)) / (2 * eps)
    jy = (hit(px, py + eps) - hit(px, py - eps)) / (2 * eps)
    return np.stack([jx, jy], axis=1), hit(px, py)


@pytest.mark.parametrize("case", ["ortho", "perspective", "log", "tilted"])
def test_analytic_jacobian_matches_finite_differences(case):
    cam = Camera.look_at([0, 2, 0], [3, 0, 25], fov_y_deg=50, resolution=(1280, 720))
    plane_n = np.array([0.0, 1.0, 0.0])
    if case == "tilted":
        plane_n = np.array([0.3, 1.0, -0.2]) / np.linalg.norm([0.3, 1.0, -0.2])
    plane_p = np.array([0.0, 0.0, 10.0])
    if case in ("ortho", "tilted"):
        sm = ShadowMap(look_down_view([2, 30, 15], [-0.3, -1, 0.4]), ortho(25, 20, 1, 80), (2048, 1024))
    else:
        sm = ShadowMap(look_down_view([0, 30, 15], [0.1, -1, 0.2]), frustum(1.2, 1.0, 1, 80), (2048, 2048))
        if case == "log":
            sm.log_warp = LogWarp(-1 / np.log(1 / 3), -(2 / 3), 1.0)  # y0=1, y1=3, a=0 (Lloyd eq. 78)
    pixels = [(100, 500), (640, 400), (1100, 650), (300, 380)]
    pts = []
    for px, py in pixels:
        a = ((px + 0.5) / 1280 * 2 - 1) * cam.tan_half_fov_y * cam.aspect
        b = (1 - (py + 0.5) / 720 * 2) * cam.tan_half_fov_y
        d = cam.forward + a * cam.right + b * cam.up
        t = np.dot(plane_n, plane_p - cam.position) / np.dot(plane_n, d)
        pts.append(cam.position + t * d)
    s = samples_on_plane(cam, np.array(pts), plane_n)
    h, m, _ = per_sample_maps([sm], s)
    for k, px in enumerate(pixels):
        J, _ = _fd_jacobian(cam, sm, px, plane_p, plane_n)
        F = np.linalg.inv(J)
        ds, dt = F[:, 0], F[:, 1]
        assert h[k] == pytest.approx(np.sum(F * F), rel=1e-4)
        assert m[k] == pytest.approx(max(np.linalg.norm(ds + dt), np.linalg.norm(ds - dt)), rel=1e-4)


def test_gradient_by_ad_matches_finite_differences():
    import drjit as dr

    cam = Camera.look_at([0, 2, 0], [3, 0, 25], fov_y_deg=50, resolution=(1280, 720))
    rng = np.random.default_rng(1)
    pts = np.column_stack([rng.uniform(-8, 8, 200), np.zeros(200), rng.uniform(5, 40, 200)])
    s = samples_on_plane(cam, pts, [0, 1, 0])
    sm = ShadowMap(look_down_view([0, 30, 15], [0.1, -1, 0.2]), frustum(1.2, 1.0, 1, 80), (1024, 1024))
    ds = DeviceSamples(s, cam.position)
    P0 = recentre(sm.matrix, cam.position)
    P = matrix_to_device(P0)
    for v in P:
        dr.enable_grad(v)
    f = objective(P, sm.resolution, None, ds)
    dr.backward(f)
    grad = np.array([dr.grad(v)[0] for v in P])

    def value(Pn):
        return float(objective(matrix_to_device(Pn), sm.resolution, None, ds)[0])

    for idx in [0, 1, 5, 12, 13, 14]:  # affine rows and the projective (4th) row
        e = 1e-6 * max(1.0, abs(P0.flat[idx]))
        Pp, Pm = P0.copy(), P0.copy()
        Pp.flat[idx] += e
        Pm.flat[idx] -= e
        fd = (value(Pp) - value(Pm)) / (2 * e)
        assert grad[idx] == pytest.approx(fd, rel=1e-4, abs=1e-9 * abs(float(f[0])))


def test_grazing_light_samples_stay_finite():
    # Light 0.5 degrees above the ground: projection aliasing is huge but the rule keeps it finite.
    cam = Camera.look_at([0, 2, 0], [0, 0, 20], resolution=(640, 480))
    el = np.radians(0.5)
    light = DirectionalLight.make([0, -np.sin(el), np.cos(el)])
    hgt, wdt = 4, 4
    pos = np.zeros((hgt, wdt, 3))
    pos[..., 0] = np.linspace(-1, 1, wdt)[None, :]
    pos[..., 2] = np.linspace(8, 12, hgt)[:, None]
    normal = np.broadcast_to([0.0, 1.0, 0.0], pos.shape).astype(np.float32)
    ones = np.ones((hgt, wdt), bool)
    s = select_samples(cam, light, pos, normal, ones, ones, ones)
    ang = np.degrees(np.arccos(s.normal @ -light.direction))
    assert np.all(ang <= GRAZING_LIGHT_DEG + 1e-9)
    sm = ShadowMap(look_down_view([0, 5, -50], light.direction, up=[0, 1, 0]), ortho(5, 5, 1, 200), (1024, 1024))
    err = predicted_error([sm], s)
    assert np.isfinite(err["objective"]) and np.isfinite(err["max_m"]) and err["samples"] == 16


def test_samples_prefer_boundaries_and_fall_back_to_all_facing():
    cam = Camera.look_at([0, 2, 0], [0, 0, 20], resolution=(640, 480))
    light = SpotLight.make([0, 10, 10], [0, -1, 0], 45)
    pos = np.zeros((3, 3, 3))
    pos[..., 2] = 10
    nrm = np.broadcast_to([0.0, 1.0, 0.0], pos.shape).astype(np.float32)
    hit = np.ones((3, 3), bool)
    boundary = np.zeros((3, 3), bool)
    boundary[1, 1] = True
    s = select_samples(cam, light, pos, nrm, hit, hit, boundary)
    assert s.kind == "boundary" and len(s) == 1 and s.pixel.tolist() == [[1, 1]]
    s = select_samples(cam, light, pos, nrm, hit, hit, np.zeros((3, 3), bool))
    assert s.kind == "all_facing" and len(s) == 9
    s = select_samples(cam, light, pos, nrm, hit, np.zeros((3, 3), bool), boundary)
    assert s.kind == "none" and len(s) == 0
    assert predicted_error([], s)["samples"] == 0
    # no sample: every per-sample array is empty with the columns of a non-empty one (so they stack)
    full = select_samples(cam, light, pos, nrm, hit, hit, np.zeros((3, 3), bool))
    for name in ("position", "normal", "dx", "dy", "pixel"):
        assert getattr(s, name).shape == (0,) + getattr(full, name).shape[1:], name
    assert s.view_depth.shape == s.weight.shape == (0,)


def test_warped_moments_give_every_affine_parts_objective():
    """metric.warped_moments (the optimizer's affine fit): for q = the first two rows of a perspective
    P over its fourth, and any affine A on q, tr(Ḡ (AᵀA)^-1) equals the objective of the map A∘P
    computed directly (objective on the composed matrix)."""
    from shadowopt.solvers.metric import warped_moments

    cam = Camera.look_at([0, 2, 0], [0, 0, 20], fov_y_deg=60, resolution=(800, 600))
    rng = np.random.default_rng(3)
    pts = np.column_stack([rng.uniform(-10, 10, 300), np.zeros(300), rng.uniform(3, 40, 300)])
    s = samples_on_plane(cam, pts, [0, 1, 0])
    ds = DeviceSamples(s, cam.position)
    Pq = np.array([[1.0, 0, 0.2, 0], [0, 0.1, 1.0, 0], [0, 1.0, 0, 0], [0, 0, 0.05, 1.0]])  # w = 1 + z/20 > 0
    G = warped_moments(recentre(Pq, ds.origin), ds)
    Gm = np.array([[G[0], G[1]], [G[1], G[2]]]) / G[3]
    assert G[4] == 0
    for _ in range(4):
        A2 = rng.normal(size=(2, 2)) * 50
        A = np.eye(4)
        A[:2, :2] = A2
        M = A @ Pq  # u_ndc = A q (resolution 2: u = (ndc + 1) / 2 * 2 = q-space units times A)
        want = float(objective(matrix_to_device(recentre(M, ds.origin)), (2.0, 2.0), None, ds)[0])
        got = float(np.trace(Gm @ np.linalg.inv(A2.T @ A2)))
        assert got == pytest.approx(want, rel=1e-9)


def test_predicted_misclassified_pixels_by_hand():
    from shadowopt.solvers.metric import MISCLASSIFIED_K, predicted_misclassified

    # h = 4, 9 (footprints of 2 and 3 pixels), a = 2, 1 pixels, weights 1, 3:
    # Σ a w √h = 2*1*2 + 1*3*3 = 13, normalised by Σa / Σaw = 3 / 5.
    assert predicted_misclassified(np.array([4.0, 9.0]), np.array([2.0, 1.0]), np.array([1.0, 3.0])) == \
        pytest.approx(MISCLASSIFIED_K * 13 * 3 / 5, rel=1e-12)
    assert predicted_misclassified(np.array([4.0, 9.0]), np.array([2.0, 1.0])) == pytest.approx(MISCLASSIFIED_K * 7)
    assert predicted_misclassified(np.array([4.0, np.inf]), np.array([2.0, 1.0])) == float("inf")
    assert predicted_misclassified(np.array([]), np.array([])) == 0.0


def test_predicted_error_counts_misclassified_pixels_in_full_resolution_pixels():
    # The overhead closed form: every sample's footprint is a x a pixels (√h = √2 a); samples standing
    # for 3 and 5 full-resolution pixels predict K √2 a (3 + 5) pixels, whatever their weights.
    from shadowopt.solvers.metric import MISCLASSIFIED_K

    cam = Camera.look([0, 10, 0], [0, -1, 0], up=[0, 0, 1], fov_y_deg=90, resolution=(1000, 1000))
    sm = ShadowMap(look_down_view([0, 20, 0]), ortho(10, 10, 1, 50), (1000, 1000))
    s = samples_on_plane(cam, np.array([[0.0, 0, 0], [1.0, 0, 1.0]]), [0, 1, 0])
    s.pixels = np.array([3.0, 5.0])
    s.weight = np.array([1.0, 4.0])
    a = (20 / 1000) / 0.02
    err = predicted_error([sm], s)
    assert err["misclassified_pixels"] == pytest.approx(MISCLASSIFIED_K * np.sqrt(2) * a * 8, rel=1e-6)


def _q(P, X):
    c = X @ P[:, :3].T + P[:, 3]
    return c[:, :2] / c[:, 3:4]


def test_warped_moments_drop_samples_behind_the_projection_centre():
    """warped_moments' fifth sum is the weight of samples with no footprint, e.g. behind the perspective
    warp's centre (clip w <= 0); the first four sums are over the others only. Truth: G = (J_q J_q^T)^-1 with
    J_q from central differences of q = (c0/cw, c1/cw) along each sample's dX/dx, dX/dy, summed in NumPy over
    the samples in front, and the lost weight summed over those behind."""
    from shadowopt.solvers.metric import DeviceSamples, recentre, warped_moments

    cam = Camera.look_at([0, 2, 0], [0, 0, 20], fov_y_deg=60, resolution=(800, 600))
    rng = np.random.default_rng(7)
    n = 240
    pts = np.column_stack([rng.uniform(-10, 10, n), np.zeros(n), rng.uniform(3, 60, n)])
    nrm = np.tile([0.0, 1.0, 0.0], (n, 1))
    dx, dy, dep = pixel_derivatives(cam, pts, nrm)
    w = rng.uniform(0.5, 2.0, n)
    s = Samples(pts, nrm, dx, dy, dep, w, np.zeros((n, 2), int), "boundary")
    ds = DeviceSamples(s, cam.position)
    # w_clip = 1 - z/40: the centre of projection is the plane z = 40, samples beyond it are behind
    Pq = np.array([[1.0, 0, 0.2, 0], [0, 0.1, 1.0, 0], [0, 1.0, 0, 0], [0, 0, -1 / 40, 1.0]])
    front = 1 - pts[:, 2] / 40 > 1e-9
    assert 40 < front.sum() < n - 40  # both kinds present
    G = warped_moments(recentre(Pq, ds.origin), ds)

    eps = 1e-6
    want = np.zeros(3)
    for i in np.flatnonzero(front):
        X = pts[i:i + 1]
        cols = [(_q(Pq, X + eps * d[i]) - _q(Pq, X - eps * d[i]))[0] / (2 * eps) for d in (dx, dy)]
        J = np.column_stack(cols)  # dq / dpixel, 2 x 2
        Gi = np.linalg.inv(J @ J.T)
        want += w[i] * np.array([Gi[0, 0], Gi[0, 1], Gi[1, 1]])
    assert G[:3] == pytest.approx(want, rel=1e-5)
    assert G[3] == pytest.approx(w[front].sum(), rel=1e-12)
    assert G[4] == pytest.approx(w[~front].sum(), rel=1e-12)


def test_coarse_samples_stand_for_the_whole_screen_in_full_resolution_pixels():
    """Each coarse sample stands for (W H) / (w h) full-resolution pixels, so when every coarse pixel is a
    sample their pixels sum to the rig's W x H, whatever the coarse size and the aspect."""
    from shadowopt.solvers.lights import SpotLight
    from shadowopt.solvers.samples import select_samples

    light = SpotLight.make([0, 10, 10], [0, -1, 0], 60)
    for res, (hgt, wdt) in (((640, 480), (3, 4)), ((1920, 1080), (9, 16)), ((1000, 1000), (5, 5))):
        cam = Camera.look_at([0, 2, 0], [0, 0, 20], resolution=res)
        pos = np.zeros((hgt, wdt, 3))
        pos[..., 0] = np.linspace(-1, 1, wdt)[None, :]
        pos[..., 2] = np.linspace(8, 12, hgt)[:, None]
        nrm = np.broadcast_to([0.0, 1.0, 0.0], pos.shape).astype(np.float32)
        ones = np.ones((hgt, wdt), bool)
        s = select_samples(cam, light, pos, nrm, ones, ones, ones)
        assert len(s) == hgt * wdt
        assert float(np.sum(s.pixels)) == pytest.approx(res[0] * res[1], rel=1e-12)
        half = np.zeros((hgt, wdt), bool)
        half[:, : wdt // 2] = True  # the boundary samples alone: their share of the screen
        s = select_samples(cam, light, pos, nrm, ones, ones, half)
        assert float(np.sum(s.pixels)) == pytest.approx(res[0] * res[1] * half.sum() / half.size, rel=1e-12)


def test_cube_face_samples_are_scored_on_the_face_their_dominant_axis_points_into():
    """A point light's six 90-degree faces: a sample belongs to the face along the largest component of its
    offset from the light (the cube-map rule), whatever its coordinates on the other faces; in the metric
    (per_sample_maps) and in the evaluator (shadow_map.serving_maps)."""
    from shadowopt.solvers.fitting import frustum as gl_frustum
    from shadowopt.solvers.light_frames import CUBE_FACES, cube_face_views

    light = np.array([0.5, 3.0, -1.0])
    maps = [ShadowMap(view, gl_frustum(-0.1, 0.1, -0.1, 0.1, 0.1, 500.0), (256, 256), light_depth=(0.1, 500.0), face=f)
            for f, view in cube_face_views(light).items()]
    cam = Camera.look_at([0, 2, 0], [0, 0, 20], resolution=(640, 480))
    rng = np.random.default_rng(3)
    d = rng.normal(size=(400, 3))
    m = np.abs(d).max(1, keepdims=True)
    d = d[(np.sort(np.abs(d), 1)[:, -2:-1] < 0.9 * m).ravel()]  # clear of the faces' shared edges
    pts = light + d * rng.uniform(1.0, 20.0, size=(len(d), 1))
    s = samples_on_plane(cam, pts, [0.0, 1.0, 0.0])
    _, _, idx = per_sample_maps(maps, s)
    axes = np.array([fwd for fwd, _ in CUBE_FACES.values()], float)
    truth = np.argmax(d @ axes.T, axis=1)  # the face whose forward axis has the largest dot product
    assert len(d) > 200 and np.array_equal(idx, truth)
    from shadowopt.solvers.shadow_map import serving_maps  # the evaluator's choice of face (depth unused for faces)

    assert np.array_equal(serving_maps(maps, pts, s.view_depth), truth)


@pytest.mark.parametrize("dtype", [np.float64, np.float32, np.int64, np.uint32])
def test_aligned_copies_are_64_byte_aligned_equal_and_cost_at_most_64_bytes_more(dtype):
    """solvers.jit.aligned (every array handed to Dr.Jit in a hot path): the same values and shape, at a
    64-byte boundary, in a buffer at most one 64-byte line larger than the data."""
    from shadowopt.solvers.jit import aligned

    for shape in [(1,), (3, 4), (1000, 3)]:
        a = np.arange(int(np.prod(shape))).reshape(shape)
        b = aligned(a, dtype)
        assert b.dtype == dtype and b.shape == shape and np.array_equal(b, a.astype(dtype))
        assert b.ctypes.data % 64 == 0
        assert b.nbytes <= b.base.nbytes <= b.nbytes + 64


def test_limit_angle_turns_a_normal_in_its_plane_to_exactly_the_limit_and_keeps_it_unit():
    """samples.limit_angle: a normal farther than max_deg from `toward` ends a unit vector at exactly max_deg
    from it, in the plane of the two and on the normal's side; a normal within the limit is untouched."""
    from shadowopt.solvers.samples import limit_angle

    rng = np.random.default_rng(7)
    n = rng.normal(size=(500, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    to = rng.normal(size=(500, 3))
    to /= np.linalg.norm(to, axis=1, keepdims=True)
    out = limit_angle(n, to, 60.0)
    before = np.degrees(np.arccos(np.clip(np.sum(n * to, 1), -1, 1)))
    after = np.degrees(np.arccos(np.clip(np.sum(out * to, 1), -1, 1)))
    far = before > 60.0
    assert 100 < far.sum() < 500
    assert np.allclose(np.linalg.norm(out, axis=1), 1.0, atol=1e-12)
    assert np.allclose(after[far], 60.0, atol=1e-6) and np.array_equal(out[~far], n[~far])
    plane_normal = np.cross(n[far], to[far])
    assert np.allclose(np.sum(out[far] * plane_normal, 1), 0.0, atol=1e-9)  # in the plane of n and toward
    side = lambda v: v - np.sum(v * to[far], 1, keepdims=True) * to[far]  # noqa: E731 (the part across toward)
    assert np.all(np.sum(side(out[far]) * side(n[far]), 1) > 0)  # turned towards `toward`, not past it
