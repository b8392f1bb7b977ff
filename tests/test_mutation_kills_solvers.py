"""Tests written to kill mutants of solvers/ that survived `make mutate` (issue 15; tests/mutation/survivors.md).

Each checks a documented property against an independent truth (a count made outside the code under test, a
closed form, a finite difference), never the implementation's own intermediate values.
"""
from __future__ import annotations

import dataclasses
import time

import numpy as np
import pytest

from shadowopt.solvers.cameras import Camera
from shadowopt.solvers.lights import DirectionalLight
from shadowopt.solvers.samples import Samples, pixel_derivatives
from testkit import ground_samples


# ---------------------------------------------------------------- split_search: the evaluation count
def test_split_search_nfev_is_the_number_of_candidate_fits(monkeypatch):
    """SplitResult.nfev reports how many split candidates were scored. Each candidate costs exactly one map fit
    (the module's docstring), so a counter wrapped around fit_baseline is an independent count; and the search
    scores the three standard starts plus at most maxeval BOBYQA points.
    (kills split_search's `nfev += 1` -> `nfev += 2`)"""
    from shadowopt.solvers import split_search

    calls = []
    real = split_search.fit_baseline

    def counting(*a, **k):
        calls.append(1)
        return real(*a, **k)

    monkeypatch.setattr(split_search, "fit_baseline", counting)
    cam = Camera.look([0, 2, 0], [0, -0.1, 1], near=0.1, far=300, resolution=(1280, 720))
    sun = DirectionalLight.make([-0.3, -0.8, 0.5])
    bounds = (np.array([-150.0, 0.0, -150.0]), np.array([150.0, 10.0, 150.0]))
    pts, samples = ground_samples(cam, grid=(48, 27))
    r = split_search.optimize_splits(cam, sun, samples, pts, bounds, (256, 256), 3, maxeval=6)
    assert r.nfev == len(calls)
    assert 3 < r.nfev <= 3 + 6
    assert r.to_json()["nfev"] == len(calls)


# ---------------------------------------------------------------- metric: samples behind a warp's centre
def _q(P, X):
    c = X @ P[:, :3].T + P[:, 3]
    return c[:, :2] / c[:, 3:4]


def test_warped_moments_drop_samples_behind_the_projection_centre():
    """warped_moments' fifth sum is the weight of samples with no footprint, e.g. behind the perspective
    warp's centre (clip w <= 0); the first four sums are over the others only. Truth: G = (J_q J_q^T)^-1 with
    J_q from central differences of q = (c0/cw, c1/cw) along each sample's dX/dx, dX/dy, summed in NumPy over
    the samples in front, and the lost weight summed over those behind.
    (kills metric.warped_moments_kernel's `valid & ...` -> `valid | ...`)"""
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


# ---------------------------------------------------------------- samples: full-resolution pixels per sample
def test_coarse_samples_stand_for_the_whole_screen_in_full_resolution_pixels():
    """Each coarse sample stands for (W H) / (w h) full-resolution pixels, so when every coarse pixel is a
    sample their pixels sum to the rig's W x H, whatever the coarse size and the aspect.
    (kills select_samples' `W * H / (w h)` -> `W / H / (w h)`)"""
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


# ---------------------------------------------------------------- fitting: the map-space margin
def test_texel_margin_closed_form_and_the_floor_for_degenerate_boxes():
    """texel_margin grows a box so that it takes n - 2 m of an axis's n texels: the padded extent is
    size n / (n - 2 m), centred on the box; a dimension thinner than `floor` is first grown to `floor`
    about its centre (so a point becomes a box of floor n / (n - 2 m)).
    (kills the floor term's `/ 2` -> `/ 3`)"""
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


def test_split_search_without_samples_returns_the_practical_splits():
    """With no samples there is nothing to score: optimize_splits returns the k - 1 inner practical splits
    (λ = 0.5: the mean of Lloyd et al.'s log split z_n (z_f/z_n)^(i/k) and the uniform one) over the receivers'
    view-depth range, without evaluating anything.
    (kills the early return's `[1:-1]` -> `[1:not 1]`, which returned no splits, and its time
    `(t - t0) * 1e3` -> `(t - t0) - 1e3`, a negative time)"""
    from shadowopt.solvers.split_search import optimize_splits

    cam = Camera.look([0, 2, 0], [0, 0, 1], near=0.1, far=300, resolution=(640, 480))
    sun = DirectionalLight.make([-0.3, -0.8, 0.5])
    rec = np.array([[0.0, 0.0, 5.0], [1.0, 0.0, 80.0], [-2.0, 0.0, 30.0]])
    _, samples = ground_samples(cam, grid=(16, 9))
    none = samples.subset(np.zeros(len(samples), bool))
    bounds = (np.array([-10.0, 0.0, 0.0]), np.array([10.0, 5.0, 100.0]))
    zn, zf = 5.0, 80.0
    want = [0.5 * zn * (zf / zn) ** (i / 3) + 0.5 * (zn + (zf - zn) * i / 3) for i in (1, 2)]
    t0 = time.perf_counter()
    r = optimize_splits(cam, sun, none, rec, bounds, (256, 256), 3)
    wall_ms = (time.perf_counter() - t0) * 1e3
    assert r.split_at == pytest.approx(want, rel=1e-9)
    assert r.nfev == 0 and r.start == "practical"
    assert 0 <= r.time_ms <= wall_ms  # milliseconds, measured inside the call


def test_split_search_under_a_budget_scores_the_samples_weighted_mean():
    """Under a texel budget a candidate's value is still the samples' weighted mean h (plus the receivers'
    term), each sample on the cascade serving its view depth: scaling every weight leaves the standard starts'
    values unchanged, while giving the far samples ten times the weight of the near ones changes them.
    (kills the per-cascade sample selection's `view_depth >= split[0]` -> `==`, which left the cascades empty)"""
    from shadowopt.solvers.split_search import optimize_splits

    cam = Camera.look([0, 2, 0], [0, -0.1, 1], near=0.1, far=300, resolution=(1280, 720))
    sun = DirectionalLight.make([-0.3, -0.8, 0.5])
    bounds = (np.array([-150.0, 0.0, -150.0]), np.array([150.0, 10.0, 150.0]))
    pts, samples = ground_samples(cam, grid=(48, 27))

    def starts(weight):  # a new Samples object: the arrays of one are never modified (its subsets are cached)
        s = dataclasses.replace(samples, weight=np.asarray(weight, float), _device={}, _subsets={})
        return optimize_splits(cam, sun, s, pts, bounds, (256, 256), 3, texel_budget=3 * 256 * 256, maxeval=1).starts

    base = starts(np.ones(len(samples)))
    assert starts(np.full(len(samples), 3.0)) == pytest.approx(base, rel=1e-9)
    far = np.where(samples.view_depth > np.median(samples.view_depth), 10.0, 1.0)
    moved = starts(far)
    for kind in base:
        assert abs(moved[kind] / base[kind] - 1) > 0.05, (kind, moved[kind], base[kind])


# ---------------------------------------------------------------- light_frames: the usable-hint threshold
def test_perpendicular_up_needs_more_than_1e_6_of_perpendicular_component():
    """A hint is usable when its component perpendicular to `forward` is longer than 1e-6 (the light within
    ~1e-6 rad of the view axis falls back to the camera's up): at exactly 1e-6 the next hint is taken, just
    above it the hint itself. The perpendicular parts here are exact in binary floating point.
    (kills `norm(u) > 1e-6` -> `>= 1e-6`)"""
    from shadowopt.solvers.light_frames import perpendicular_up

    f = np.array([0.0, 0.0, 1.0])
    at = np.array([1e-6, 0.0, 1.0])  # h - (h.f) f = (1e-6, 0, 0): norm exactly 1e-6
    assert np.linalg.norm(at - np.dot(at, f) * f) == 1e-6
    assert perpendicular_up(f, at, [0.0, 1.0, 0.0]) == pytest.approx([0.0, 1.0, 0.0], abs=0)
    above = np.array([2e-6, 0.0, 1.0])
    assert perpendicular_up(f, above, [0.0, 1.0, 0.0]) == pytest.approx([1.0, 0.0, 0.0], abs=0)


# ---------------------------------------------------------------- optimize: the finite difference across a jump
def test_robust_difference_takes_the_side_without_the_jump():
    """The optimizer's finite difference of a piecewise-smooth objective (its fit switches hull edges): the
    central difference where both sides agree, else the one-sided difference with the smaller change, on
    whichever side the jump is. f = 2 x + 3 y with a jump of 10 at x = 0.5 + h/2 (or x = 0.5 - h/2): the slope
    (2, 3) is recovered from the smooth side.
    (kills the side choice's `sum(dp * dp)` -> `sum(dp % dp)`, which always took the forward side)"""
    from shadowopt.solvers.optimize import robust_difference

    h = 1e-3
    x0 = np.array([0.5, 0.2])

    def f(x, jump_at):
        return np.array([2 * x[0] + 3 * x[1] + (10.0 if (x[0] - jump_at) * np.sign(jump_at - 0.5) > 0 else 0.0)])

    for jump_at in (0.5 + h / 2, 0.5 - h / 2):
        g = [robust_difference(f(x0 - h * e, jump_at), f(x0, jump_at), f(x0 + h * e, jump_at), h)[0]
             for e in np.eye(2)]
        assert g == pytest.approx([2.0, 3.0], rel=1e-6)
    h = 1e-4  # x^2 at 1: the sides agree to 1e-4, so the central difference, exact for a quadratic
    smooth = robust_difference(np.array([(1 - h) ** 2]), np.array([1.0]), np.array([(1 + h) ** 2]), h)
    assert smooth[0] == pytest.approx(2.0, rel=1e-9)


# ---------------------------------------------------------------- baselines: each cascade fitted to its own slice
def test_a_middle_cascade_is_fitted_to_its_slice_not_to_every_deeper_receiver():
    """Only the last cascade takes every receiver past its near split (and the first every one before its far
    split); a middle cascade's focused or LiSPSM map is fitted to its own depth slice, so on the ground under a
    tilted sun no receiver two slices deeper falls inside it (map coordinates in [0, 1]^2, w > 0). 7 cascades:
    the fifth is the one `len(z) / 2` names.
    (kills _cascade_part's `i == len(z) - 2` -> `i == len(z) / 2`, which fitted cascade 4 of 7 to every
    deeper receiver; for 3 cascades the two agree, for 2 and 4 they differ only beyond the far plane)"""
    from shadowopt.solvers.baselines import baseline

    cam = Camera.look([0, 2, 0], [0, -0.1, 1], near=0.1, far=300, resolution=(1280, 720))
    sun = DirectionalLight.make([-0.3, -0.8, 0.5])
    bounds = (np.array([-150.0, 0.0, -150.0]), np.array([150.0, 10.0, 150.0]))
    pts, _ = ground_samples(cam, far=150.0)
    depth = (pts - cam.position) @ cam.forward
    for method in ("focused", "lispsm"):
        maps = baseline(method, cam, sun, pts, bounds, (512, 512), cascades=7, splits="practical")
        for k in range(len(maps) - 2):
            deep = pts[depth > maps[k + 1].split[1]]
            assert len(deep) > 10
            s, t, _, w = maps[k].map_coords(deep)
            inside = (s >= 0) & (s <= 1) & (t >= 0) & (t <= 1) & (w > 0)
            assert not inside.any(), (method, k, float(inside.mean()))


# ---------------------------------------------------------------- optimize: the affine fit named at run time
def test_objective_affine_fit_named_by_a_runtime_string():
    """The optimizer's affine fit is chosen by name, and names arrive at run time (request JSON, settings),
    not as interned literals: Problem(affine=<"objective" built at run time>) evaluates exactly as the literal,
    and its value is no worse than the axis-aligned box's (the "objective" fit minimises the weighted mean h
    over parallelograms that include the flush rectangles; Chong & Gortler's h via solvers.metric).
    (kills `self.affine == "objective"` -> `self.affine is "objective"`)"""
    from shadowopt.solvers.optimize import Problem

    cam = Camera.look_at([0, 2, 0], [0, 0, 30], near=0.1, far=200, resolution=(1280, 720))
    pts, s = ground_samples(cam, grid=(48, 27))
    sun = DirectionalLight.make([1, -1, 0])
    bounds = (np.array([-150, 0, -150.0]), np.array([150, 10, 150.0]))
    name = "".join(["objec", "tive"])
    assert name == "objective" and name is not "objective"  # noqa: F632  (the point of the test)
    lit = Problem(cam, sun, s, pts, bounds, (1024, 1024), affine="objective")
    run = Problem(cam, sun, s, pts, bounds, (1024, 1024), affine=name)
    box = Problem(cam, sun, s, pts, bounds, (1024, 1024), affine="axis")
    for x in ([0.1, 1.0], [0.3, 2.0]):
        x = np.array(x)
        assert run.value(x) == lit.value(x)
        assert run.value(x) <= box.value(x) * (1 + 1e-9)


# ---------------------------------------------------------------- optimize: Chong & Gortler 2007's line search
def test_cg07_line_search_backtracks_downhill_when_every_fixed_step_overshoots():
    """Chong & Gortler 2007 Algorithm 1: fixed steps along the negative gradient, and when none helps, the
    smallest positive one halved. On f(x) = 1000 (x_0 - 0.01)^2 + x_1^2 from x = 0 every fixed step (3 deg and
    up, x 4 in (phi, u) units) overshoots the minimum at x_0 = 0.01; halving 3 deg reaches f < f(0) / 10, and the
    search keeps iterating towards the closed-form minimum f = 0.
    (kills the backtracking start `min(a > 0)` -> `min(a != 0)`, i.e. -10 deg: steps uphill)"""
    from shadowopt.solvers.search_methods import cg07_linesearch

    class Quadratic:  # the problem's interface the line search uses
        def __init__(self):
            self.seen = []

        def value(self, x):
            v = 1000.0 * (x[0] - 0.01) ** 2 + x[1] ** 2
            self.seen.append(v)
            return v

        def gradient(self, x):
            return np.array([2000.0 * (x[0] - 0.01), 2.0 * x[1]])

        def clip(self, x):
            return np.clip(x, -10.0, 10.0)

    prob = Quadratic()
    f0 = prob.value(np.zeros(2))
    assert all(prob.value(np.array([np.radians(a) * 4, 0.0])) > f0 for a in (3, 5, 50))  # every fixed step overshoots
    it = cg07_linesearch(prob, np.zeros(2), 8)
    assert min(prob.seen) < f0 / 10
    assert it >= 2


# ---------------------------------------------------------------- optimized_maps: the receivers' score memo
def test_receiver_terms_do_not_depend_on_an_earlier_call_with_fewer_receivers():
    """receiver_terms scores at most n receivers (a seeded subset) and keeps the subset per receiver array
    for speed only: the same numbers with or without the memo. Truth: the terms of all receivers
    (n >= their count) on a fresh array, against the same call on a copy that was first scored with n = 50.
    (kills the memo's `hit[2] == n` -> `hit[2] < n`, which served the 50-receiver subset to n = 5000)"""
    from shadowopt.solvers.baselines import baseline
    from shadowopt.solvers.cascade_scores import receiver_terms

    cam = Camera.look([0, 2, 0], [0, -0.1, 1], near=0.1, far=300, resolution=(1280, 720))
    sun = DirectionalLight.make([-0.3, -0.8, 0.5])
    bounds = (np.array([-150.0, 0.0, -150.0]), np.array([150.0, 10.0, 150.0]))
    pts, _ = ground_samples(cam, grid=(48, 27))
    assert 50 < len(pts) < 5000
    smap = baseline("focused", cam, sun, pts, bounds, (512, 512))[0]
    want = receiver_terms(smap, pts.copy(), cam, sun, 5000)
    other = pts.copy()
    few = receiver_terms(smap, other, cam, sun, 50)
    assert few != want  # a subset scores differently, so the check below can fail
    assert receiver_terms(smap, other, cam, sun, 5000) == want


# ---------------------------------------------------------------- optimize: the minimum-area parallelogram fit
def test_parallelogram_fit_of_a_parallelogram_is_the_parallelogram_itself():
    """affine="parallelogram": the minimum-area enclosing parallelogram (two pairs of parallel lines flush with
    hull edges). For points that are a parallelogram (sides (2, 0) and (1, 1), area 2; its axis box is 3 x 1) the
    map's region in q space, area prod(hi - lo) / |det C|, is exactly 2 and every point lies inside it.
    (kills `if not np.isfinite(area)` -> `if not not ...`, which fell back to the axis box)"""
    from shadowopt.solvers.optimize import affine_fit

    corners = np.array([[0.0, 0.0], [2.0, 0.0], [3.0, 1.0], [1.0, 1.0]])
    rng = np.random.default_rng(5)
    inner = rng.uniform(0, 1, (40, 2)) @ np.array([[2.0, 0.0], [1.0, 1.0]])  # points inside it
    q = np.vstack([corners, inner])
    for res in ((512, 512), (1024, 512)):
        C, lo, hi = affine_fit(q, "parallelogram", res)
        A = C[:2, :2]
        assert np.prod(hi - lo) / abs(np.linalg.det(A)) == pytest.approx(2.0, rel=1e-9)
        r = q @ A.T
        assert np.all((r >= lo - 1e-12) & (r <= hi + 1e-12))
    C, lo, hi = affine_fit(q, "axis", (512, 512))
    assert np.prod(hi - lo) == pytest.approx(3.0, rel=1e-12)


# ---------------------------------------------------------------- baselines: texel extents of an orthographic map
def test_texel_extents_of_an_orthographic_map_are_its_width_per_unit():
    """texel_extents: world metres per unit s and t, by central differences in the plane perpendicular to the
    light. An overhead orthographic map of half-size hw is 2 hw metres per unit on both axes, exactly; the
    difference step scales with the points' extent, so scenes of 2 km to 40 km agree with the closed form to
    1e-8 (a step fixed near 1e-9 m leaves roundoff of ~2e-6 there).
    (kills `extent = ... if len(pts) > 1 else 0` -> `len(pts) < 1`, which dropped the extent from the step)"""
    from shadowopt.solvers.texel_size import texel_extents
    from shadowopt.solvers.shadow_map import ShadowMap

    sun = DirectionalLight.make([0, -1, 0])
    view = np.array([[1.0, 0, 0, 0], [0, 0, -1.0, 0], [0, 1.0, 0, -50.0], [0, 0, 0, 1.0]])  # looks down -y from y = 50
    rng = np.random.default_rng(1)
    for hw in (1000.0, 5000.0, 20000.0):
        proj = np.diag([1 / hw, 1 / hw, -2 / 199.0, 1.0])
        proj[2, 3] = -201 / 199.0
        sm = ShadowMap(view, proj, (1024, 1024))
        pts = np.column_stack([rng.uniform(-0.9 * hw, 0.9 * hw, 200), np.zeros(200), rng.uniform(-0.9 * hw, 0.9 * hw, 200)])
        s, t, _, w = sm.map_coords(pts)
        assert np.all((s > 0) & (s < 1) & (t > 0) & (t < 1) & (w > 0))
        per_s, per_t = texel_extents(sm, pts, sun)
        assert per_s == pytest.approx(np.full(200, 2 * hw), rel=1e-8)
        assert per_t == pytest.approx(np.full(200, 2 * hw), rel=1e-8)


# ---------------------------------------------------------------- path_optimize: the joint optimum's camera
def test_joint_grid_is_seen_from_the_middle_frame():
    """joint_grid optimizes one canonical part for several frames, on the union of their samples and
    receivers, seen from the middle frame's camera (its splits and warp frame). So with three frames the first
    frame's camera plays no part: moving it (same samples and receivers) leaves the grid unchanged, while
    moving the middle frame's camera changes it.
    (kills `frames[len(frames) // 2]` -> `frames[len(frames) >> 2]`, the first of three frames)"""
    from shadowopt.solvers.path_optimize import FrameProblem, joint_grid

    sun = DirectionalLight.make([-0.3, -0.8, 0.5])
    bounds = (np.array([-150.0, 0.0, -150.0]), np.array([150.0, 10.0, 150.0]))
    cams = [Camera.look([x, 2, 0], [0.1 * x, -0.1, 1], near=0.1, far=300, resolution=(640, 360)) for x in (-4.0, 0.0, 4.0)]
    data = [ground_samples(c, far=120.0, grid=(32, 18)) for c in cams]
    opts = {"resolution": (512, 512), "cascades": 1}

    def frames(cameras):
        return [FrameProblem(c, sun, s, p, bounds, dict(opts)) for c, (p, s) in zip(cameras, data)]

    moved = Camera.look([30.0, 8, -20], [-0.5, -0.3, 1], near=0.1, far=300, resolution=(640, 360))
    base = joint_grid(frames(cams), 0)
    assert base is not None
    first = joint_grid(frames([moved, cams[1], cams[2]]), 0)
    middle = joint_grid(frames([cams[0], moved, cams[2]]), 0)
    assert np.array_equal(first.view, base.view) and np.array_equal(first.G, base.G)
    assert not (np.allclose(middle.view, base.view) and np.allclose(middle.G, base.G))


# ---------------------------------------------------------------- optimize: the warped depth range
def test_optimized_map_depth_range_is_set_by_the_receivers_amid_a_small_caster():
    """The optimized map's depth range spans the receivers' and the casters' warped light depths z / w'
    (Lloyd et al.'s warp: depth divides by w', constant along each light ray), padded by 1%: no wider, so no
    depth precision is wasted. With one 4 x 3 x 4 m caster amid 100 m of ground receivers under a 45 degree
    sun the receivers themselves set both ends: their clip depths reach within 3% of -1 and of 1.
    (kills `zv = z / w'` -> `z * w'`, which squeezed the receivers into 0.4% of the depth range, and the
    scene corners' far end `zc_lo / w'` -> `zc_lo - w'`, which pushed the far plane out by w')"""
    from shadowopt.solvers.optimize import minimize

    cam = Camera.look_at([0, 2, 0], [0, 0, 30], near=0.1, far=200, resolution=(1280, 720))
    pts, s = ground_samples(cam, grid=(48, 27))
    caster = (np.array([-2.0, 0.0, 8.0]), np.array([2.0, 3.0, 12.0]))
    r = minimize(cam, DirectionalLight.make([1, -1, 0]), s, pts, caster, (1024, 1024))
    _, _, z, w = r.map.map_coords(pts)
    assert np.all(w > 0) and np.all(np.abs(z) <= 1)
    assert z.min() < -0.97 and z.max() > 0.97, (float(z.min()), float(z.max()))


# ---------------------------------------------------------------- stable_csm: each cascade biased by its own receivers
def test_stable_csm_cascade_bias_comes_from_its_own_depth_slice():
    """stable_csm's maps do not depend on the receivers (world-fixed spheres and grid); only each cascade's
    bias does, from the receivers in its view-depth slice (baselines' rule). Truth: cascade i's bias and depth
    block equal those of the same call given only the receivers of slice i, with the camera far from the world
    origin (position . forward = -60 m) so that depths measured from the wrong point pick other receivers.
    (kills `depth = (receivers - camera.position) . forward` -> `receivers + camera.position`)"""
    from shadowopt.solvers.stable_csm import stable_csm_maps

    cam = Camera.look([0, 2, -60], [0, -0.1, 1], near=0.1, far=300, resolution=(1280, 720))
    sun = DirectionalLight.make([-0.3, -0.8, 0.5])
    bounds = (np.array([-150.0, 0.0, -150.0]), np.array([150.0, 10.0, 150.0]))
    pts, _ = ground_samples(cam, far=150.0)
    # some relief, so that the slices' receivers ask for different slope biases
    pts = pts + np.column_stack([np.zeros(len(pts)), 0.02 * (pts[:, 2] + 60) * np.sin(pts[:, 0]), np.zeros(len(pts))])
    maps = stable_csm_maps(cam, sun, pts, bounds, (1024, 1024), cascades=3)
    depth = (pts - cam.position) @ cam.forward
    differs = checked = 0
    for i, m in enumerate(maps):
        sel = (depth >= m.split[0]) & (depth <= m.split[1])
        if not sel.any():  # a slice past the receivers: biased by all of them
            continue
        checked += 1
        alone = stable_csm_maps(cam, sun, pts[sel], bounds, (1024, 1024), cascades=3)[i]
        assert np.array_equal(alone.matrix, m.matrix)
        assert alone.depth_bias == m.depth_bias and alone.depth == m.depth
        other = stable_csm_maps(cam, sun, pts[~sel], bounds, (1024, 1024), cascades=3)[i]
        differs += other.depth != m.depth or other.depth_bias != m.depth_bias
    assert checked >= 2 and differs  # the bias does depend on which receivers, so the check above can fail


# ---------------------------------------------------------------- optimize: a point light's single-map cone
def test_point_light_receivers_within_the_single_map_cone_get_one_tight_spot():
    """single_map_spot: a point light whose receivers lie within SINGLE_MAP_CONE_DEG (70 deg) of one axis gets
    one map, a spot on the receivers' mean direction with a cone just covering them. Receivers on a circle at
    half-angle a about -y (plus the axis point): the cone covers a and exceeds it by at most 1 deg, for a = 20
    and for a = 68.5, still one map.
    (kills the cone margin `+ 1.0` -> `+ 2.0`, which wasted texels and sent a = 68.5 to the cube)"""
    from shadowopt.solvers.lights import PointLight
    from shadowopt.solvers.optimize import SINGLE_MAP_CONE_DEG, single_map_spot

    light = PointLight.make([0.0, 10.0, 0.0])
    phi = np.linspace(0, 2 * np.pi, 24, endpoint=False)
    for a in (20.0, 68.5):
        assert a < SINGLE_MAP_CONE_DEG
        r = np.tan(np.radians(a)) * 10.0
        ring = np.column_stack([r * np.cos(phi), np.zeros_like(phi), r * np.sin(phi)])
        spot = single_map_spot(light, np.vstack([ring, [[0.0, 0.0, 0.0]]]))
        assert spot is not None, a
        assert spot.direction == pytest.approx([0.0, -1.0, 0.0], abs=1e-9)
        assert a <= spot.cone_deg <= a + 1.0 + 1e-9


def test_cg07_line_search_stops_at_a_stationary_point_without_evaluating():
    """At a point where the gradient vanishes (or is not finite) there is no direction to search: the line
    search stops after the first gradient, evaluates no step (every step would be 0 / 0 = NaN) and leaves x.
    (kills `norm == 0 or not isfinite(norm)` -> `and`, which went on to evaluate 15 NaN points)"""
    from shadowopt.solvers.search_methods import cg07_linesearch

    class Bowl:
        def __init__(self, grad):
            self.seen, self.grad = [], grad

        def value(self, x):
            self.seen.append(np.array(x, float))
            return float(np.sum((np.asarray(x) - 0.25) ** 2))

        def gradient(self, x):
            return np.array(self.grad(x), float)

        def clip(self, x):
            return np.clip(x, -10.0, 10.0)

    for grad in (lambda x: 2 * (np.asarray(x) - 0.25), lambda x: [np.inf, 0.0], lambda x: [np.nan, 1.0]):
        prob = Bowl(grad)
        it = cg07_linesearch(prob, np.array([0.25, 0.25]), 8)
        assert it == 1
        assert len(prob.seen) == 1 and np.all(np.isfinite(prob.seen[0]))  # only the start was evaluated


# ---------------------------------------------------------------- analysis: d_min along a light ray (Lloyd et al.)
def test_min_depth_along_light_matches_a_brute_force_walk_of_the_ray():
    """analysis.min_depth_along_light: d_min of Lloyd et al. 2006 eqs. 45/54, the smallest view depth on the
    light's line through p inside the view frustum (n <= z <= f, |x|, |y| <= z tan theta). Truth: walk the line
    in 1e-3 m steps and take the least z of the points inside the frustum. Light directions that leave through
    the near plane (d_min = n), a side plane, and the far plane. (Written for the near plane's normal mutant
    (0, 0, -1) -> (0, 0, +1), which this does not kill: it is equivalent, see tests/mutation/equivalent.json.)"""
    from shadowopt.solvers.analysis import min_depth_along_light

    n, f, tan_t = 1.0, 20.0, np.tan(np.radians(30.0))
    rng = np.random.default_rng(11)
    z = rng.uniform(2.0, 18.0, 30)
    p = np.column_stack([rng.uniform(-0.8, 0.8, 30) * z * tan_t, rng.uniform(-0.8, 0.8, 30) * z * tan_t, z])
    mu = np.arange(-60.0, 60.0, 1e-3)
    for l in ([0.0, 0.0, 1.0], [0.3, -0.4, 0.866], [0.0, -1.0, 0.0], [0.6, 0.0, -0.8]):
        l = np.asarray(l) / np.linalg.norm(l)
        got = min_depth_along_light(p, l, n, f, tan_t)
        for i in range(len(p)):
            q = p[i] + mu[:, None] * l
            inside = (q[:, 2] >= n) & (q[:, 2] <= f) & (np.abs(q[:, 0]) <= q[:, 2] * tan_t) & (np.abs(q[:, 1]) <= q[:, 2] * tan_t)
            want = q[inside, 2].min()
            assert got[i] == pytest.approx(want, abs=2e-3), (l, i)
    on_axis = np.array([[0.0, 0.0, 5.0], [0.0, 0.0, 15.0]])  # on the view axis, the line along it reaches z = n
    assert min_depth_along_light(on_axis, np.array([0.0, 0.0, 1.0]), n, f, tan_t) == pytest.approx([n, n])


# ---------------------------------------------------------------- stable_csm: the slice's bounding sphere
def test_stable_csm_slice_sphere_encloses_the_slice_and_touches_a_corner():
    """slice_sphere (Valient 2008): the bounding sphere of the view-frustum slice [z0, z1]. Truth: the slice's
    eight corners from the camera's field of view (depth z, +-z tan(fov_x / 2) right, +-z tan(fov_y / 2) up) lie
    inside it, and the farthest one lies on it (radius = the larger corner distance from the centre).
    (kills k^2 = tan_y^2 (1 + aspect^2) -> tan_y^2 (0 + aspect^2), which forgot the vertical half-angle)"""
    from shadowopt.solvers.stable_csm import slice_sphere

    for fov, res, (z0, z1) in ((60.0, (1280, 720), (0.1, 10.0)), (45.0, (1920, 1080), (10.0, 40.0)),
                              (90.0, (1000, 1000), (2.0, 2.5))):
        cam = Camera.look([3.0, 2.0, -7.0], [0.2, -0.3, 1.0], fov_y_deg=fov, near=0.1, far=300, resolution=res)
        ty = np.tan(np.radians(fov) / 2)
        tx = ty * res[0] / res[1]
        corners = np.array([cam.position + z * (cam.forward + sx * tx * cam.right + sy * ty * cam.up)
                            for z in (z0, z1) for sx in (-1, 1) for sy in (-1, 1)])
        centre, r = slice_sphere(cam, z0, z1)
        dist = np.linalg.norm(corners - centre, axis=1)
        assert dist.max() == pytest.approx(r, rel=1e-9)


def test_cg07_line_search_stops_when_no_step_improves():
    """At the kink of f = 1000 |x_0 - 0.25| + |x_1| (a minimum with a non-zero gradient there) every fixed step
    and every halving overshoots: no step lowers f by the 1e-4 relative the search asks for, so it stops after
    the first iteration, having evaluated the start, the nine fixed steps and the six halvings, and x stays.
    (kills the stop test `best >= fx (1 - 1e-4)` -> `best is fx (1 - 1e-4)`, which ran all eight iterations)"""
    from shadowopt.solvers.search_methods import CG07_ANGLES_DEG, cg07_linesearch

    class Vee:
        def __init__(self):
            self.seen = []

        def value(self, x):
            self.seen.append(np.array(x, float))
            return float(1000.0 * abs(x[0] - 0.25) + abs(x[1]) + 1.0)

        def gradient(self, x):
            return np.array([1000.0 * np.sign(x[0] - 0.25 + 1e-300), np.sign(x[1])])

        def clip(self, x):
            return np.clip(x, -10.0, 10.0)

    prob = Vee()
    it = cg07_linesearch(prob, np.array([0.25, 0.0]), 8)
    assert it == 1
    assert len(prob.seen) == 1 + len(CG07_ANGLES_DEG) + 6
    assert min(float(prob.value(x)) for x in list(prob.seen)) == pytest.approx(1.0)


# ---------------------------------------------------------------- baselines: a perspective light's near plane
def test_perspective_light_near_plane_rule():
    """perspective_near (spot and point lights): 1e-4 of the far distance (at least 0.1 mm), pulled in to half the
    nearest receiver's depth, never below 1e-7 of far. Closed forms: far 100 m with receivers at 5 and 20 m
    keeps 1 cm; a receiver at 4 mm pulls it to 2 mm; one at 1e-9 m stops at the 1e-5 m floor; no receiver: 1 cm.
    (kills `0.5 * d.min()` -> `-0.5 * d.min()`, which put every near plane on the 1e-7 floor)"""
    from shadowopt.solvers.fitting import perspective_near

    assert perspective_near(np.array([5.0, 20.0, np.inf, -3.0]), 100.0) == pytest.approx(0.01, rel=1e-12)
    assert perspective_near(np.array([0.004, 7.0]), 100.0) == pytest.approx(0.002, rel=1e-12)
    assert perspective_near(np.array([1e-9]), 100.0) == pytest.approx(1e-5, rel=1e-12)
    assert perspective_near(np.zeros(0), 100.0) == pytest.approx(0.01, rel=1e-12)
    assert perspective_near(np.array([1.0]), 0.5) == pytest.approx(1e-4, rel=1e-12)  # the 0.1 mm minimum


# ---------------------------------------------------------------- baselines: LogPSM's eta from the camera's half-angle
def test_logpsm_eta_follows_lloyd_shaping_with_the_smaller_half_angle():
    """The LogPSM baseline's warp strength is Lloyd et al. 2007 eq. 79's eta(gamma) with theta the camera's
    smaller half field of view (30 deg for a 60 deg vertical fov at 16:9; 30 deg horizontal for a 9:16 portrait
    camera of 2 atan(tan 30 deg * 16/9) vertical). gamma = 45 deg lies between gamma_b = theta and gamma_c, where
    eta depends on theta. Truth: warp.eta_shaping at that theta, the angle between view and light in NumPy.
    (kills theta = min(atan t_y, atan(t_y * aspect)) -> atan(t_y - aspect))"""
    from shadowopt.solvers.baselines import baseline
    from shadowopt.solvers.warp import eta_shaping

    sun = DirectionalLight.make([0.0, -np.sin(np.radians(45)), np.cos(np.radians(45))])
    bounds = (np.array([-150.0, 0.0, -150.0]), np.array([150.0, 10.0, 150.0]))
    tall = float(np.degrees(2 * np.arctan(np.tan(np.radians(30)) * 16 / 9)))
    for fov_y, res in ((60.0, (1280, 720)), (tall, (720, 1280))):
        cam = Camera.look([0, 2, 0], [0, 0, 1], fov_y_deg=fov_y, near=0.1, far=300, resolution=res)
        pts, _ = ground_samples(cam, far=150.0, grid=(48, 27))
        m = baseline("logpsm", cam, sun, pts, bounds, (1024, 1024))[0]
        gamma = float(np.degrees(np.arccos(np.clip(cam.forward @ sun.direction, -1, 1))))
        assert gamma == pytest.approx(45.0, abs=1e-9)
        assert m.eta == pytest.approx(eta_shaping(gamma, 30.0), rel=1e-9), (fov_y, m.eta)


def test_texel_extents_with_the_light_along_the_x_axis():
    """texel_extents measures in the plane perpendicular to the light with axes e1 = l x y (l x x when l is
    along y): a light travelling exactly along +x is an ordinary case. An orthographic map looking along +x of
    half-size 40 m is 80 m per unit on both axes.
    (kills the along-y test `|l x y| < 1e-6` -> `< 1.000001`, which took l x x = 0 for every light and gave NaN)"""
    from shadowopt.solvers.texel_size import texel_extents
    from shadowopt.solvers.light_frames import look_matrix
    from shadowopt.solvers.shadow_map import ShadowMap

    sun = DirectionalLight.make([1.0, 0.0, 0.0])
    view = look_matrix(np.array([-100.0, 0.0, 0.0]), np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]))
    proj = np.diag([1 / 40.0, 1 / 40.0, -2 / 199.0, 1.0])
    proj[2, 3] = -201 / 199.0
    sm = ShadowMap(view, proj, (512, 512))
    rng = np.random.default_rng(2)
    pts = np.column_stack([rng.uniform(-20, 20, 50), rng.uniform(-30, 30, 50), rng.uniform(-30, 30, 50)])
    per_s, per_t = texel_extents(sm, pts, sun)
    assert per_s == pytest.approx(np.full(50, 80.0), rel=1e-8)
    assert per_t == pytest.approx(np.full(50, 80.0), rel=1e-8)


def test_split_result_json_keeps_microseconds():
    """SplitResult.to_json: time_ms to the microsecond (3 decimals), the resolution every solver's time in the
    responses has. (kills `round(time_ms, 3)` -> `round(time_ms, 2)`)"""
    from shadowopt.solvers.split_search import SplitResult

    r = SplitResult(np.array([3.0, 9.0]), 1.5, "log", {"log": 1.5}, 7, 12.3456)
    assert r.to_json()["time_ms"] == 12.346


# ---------------------------------------------------------------- fitting: the depth range's margin
def test_depth_range_grows_by_the_margin_of_the_span():
    """fitting.depth_range: [min, max] of the distances grown by `margin` of the span on each side, the span at
    least `floor` (default 1e-6 of the largest |d|). Closed forms: d in [10, 50], margin 0.01 -> [9.6, 50.4];
    a flat set at 7 -> 7 -+ 0.01 * 7e-6; an explicit floor of 2 -> 7 -+ 0.02.
    (kills `span = far - near` -> `far ** near`)"""
    from shadowopt.solvers.fitting import depth_range

    assert depth_range(np.array([10.0, 30.0, 50.0, np.nan]), 0.01) == pytest.approx((9.6, 50.4), rel=1e-12)
    assert depth_range(np.array([-20.0, -5.0]), 0.1) == pytest.approx((-21.5, -3.5), rel=1e-12)
    assert depth_range(np.array([7.0, 7.0]), 0.01) == pytest.approx((7.0 - 7e-8, 7.0 + 7e-8), rel=1e-15)
    assert depth_range(np.array([7.0]), 0.01, 2.0) == pytest.approx((6.98, 7.02), rel=1e-12)


# ---------------------------------------------------------------- path_optimize: the cut of a path into segments
def test_segment_pass_finds_the_cheapest_cut(monkeypatch):
    """segment_pass cuts a path into segments (dynamic programming over segment counts) and, with the reference
    out of reach, returns the cut of least summed objective (the fewest segments among equals). The map fits
    are replaced by a table whose segment cost is g(the segment's coarsest level) x the sum of its frames'
    weights (not additive over frames, so the cut matters). Truth: every one of the 2^3 cuts of 4 frames
    evaluated by brute force.
    (kills the programme's `prev + seg < best` -> `prev * seg < best`, which kept a cut of sum 17.6 for 3.6)"""
    import itertools
    from types import SimpleNamespace

    from shadowopt.solvers import path_optimize as PO

    lv, w, g = [1, 0, 2, 1], [5.0, 0.5, 5.0, 0.5], {0: 3.0, 1: 0.2, 2: 10.0}
    n = len(lv)

    def fake_fit(grid, kk, corners, held=None, origin=None, force=None, depth_frame=None):
        cost = 0.0 if held is None else g[held[0]] * w[kk]
        return SimpleNamespace(cost=cost, depth_frame=(0.0, 0.0, 1.0, (0.0, 1.0))), held or (0, 0)

    monkeypatch.setattr(PO, "fit_on_grid", fake_fit)
    monkeypatch.setattr(PO, "tight_levels", lambda grid, kk: (lv[kk], lv[kk]))
    cam = SimpleNamespace(position=np.zeros(3))
    frames = [SimpleNamespace(camera=cam, light=None) for _ in range(n)]
    fits = [[SimpleNamespace(fit_pts=kk, corners=None, score=lambda smap, c, l: smap.cost)] for kk in range(n)]
    fresh = [[PO.Grid(np.eye(4), np.zeros((3, 4)), (64, 64))] for _ in range(n)]
    maps, grids, report = PO.segment_pass(frames, fits, fresh, [[0.0]] * n, tolerance=1.0, joint=False)

    def seg(i, j):
        return g[min(lv[i:j + 1])] * sum(w[i:j + 1])

    best = None
    for k in range(n):
        for cuts in itertools.combinations(range(1, n), k):
            b = (0,) + cuts + (n,)
            total = sum(seg(b[t], b[t + 1] - 1) for t in range(len(b) - 1))
            if best is None or total < best[0] - 1e-12:
                best = (total, [[b[t], b[t + 1] - 1] for t in range(len(b) - 1)])
    assert report[0]["objective_sum"] == pytest.approx(best[0], rel=1e-12)
    assert report[0]["segments"] == best[1]
    assert best[0] == pytest.approx(3.6)
