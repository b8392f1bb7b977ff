"""The texel limit (solvers.metric.texel_limit) and Chong 2003 Theorem 1 on a plane.

Truths: the limit's closed form 2N/T for uniform samples, the inequality h >= 2/det J per sample
(checked on every baseline map), and on a single plane the constant-footprint map the limit is reached
by: the optimized map's objective within 2% of 2N/T (when the plane fills the screen; else within 2%
of the aspect-corrected bound (1 + r^2)/(2r) * 2N/T, r the visible region's aspect over the map's) and
max_m / mean_m <= 1.05."""
from __future__ import annotations

import math

import numpy as np
import pytest

from shadowopt.solvers.baselines import baseline
from shadowopt.solvers.cameras import Camera
from shadowopt.solvers.lights import DirectionalLight
from shadowopt.solvers.metric import DeviceSamples, per_sample, predicted_error, texel_limit
from shadowopt.solvers.optimize import minimize
from shadowopt.solvers.samples import Samples, pixel_derivatives

GRID = (64, 64)
BOUNDS = (np.array([-200, -0.01, -200.0]), np.array([200, 0.01, 200.0]))
CAMS = {  # (camera, far end of the receivers along the view axis)
    "eye_level": (Camera.look_at([0, 1.7, 0], [0, 1.7, 30], near=0.1, far=100, resolution=(512, 512)), 100.0),
    "pitched_45": (Camera.look_at([0, 2, 0], [0, 0, 2], near=0.1, far=100, resolution=(512, 512)), 100.0),
    "5cm_30m": (Camera.look_at([0, 0.05, 0], [0, 0.0, 1], near=0.01, far=30, resolution=(512, 512)), 30.0),
}
E30 = math.radians(30)
SUNS = {"overhead": [0, -1, 0.0], "45_side": [1, -1, 0.0], "30_side": [math.cos(E30), -math.sin(E30), 0.0],
        "30_front": [0, -math.sin(E30), math.cos(E30)], "30_diagonal": [0.6124, -0.5, 0.6124]}


def plane_samples(cam: Camera, far: float):
    """Samples on y = 0 through a GRID of the camera's pixels up to view depth `far`, each standing
    for (W H) / (64 64) full-resolution pixels; and the visible region's rows and columns of the grid."""
    d = cam.ray_directions(*GRID).reshape(-1, 3)
    with np.errstate(divide="ignore"):
        t = -cam.position[1] / d[:, 1]
    ok = (t > 0) & (t * (d @ cam.forward) < far)
    pts = cam.position + t[ok, None] * d[ok]
    n = np.tile([0, 1.0, 0], (len(pts), 1))
    dx, dy, dep = pixel_derivatives(cam, pts, n)
    a = cam.resolution[0] * cam.resolution[1] / (GRID[0] * GRID[1])
    rows = int(ok.reshape(GRID[1], GRID[0]).any(axis=1).sum())
    return pts, Samples(pts, n, dx, dy, dep, np.ones(len(pts)), np.zeros((len(pts), 2), int), "all_facing",
                        np.full(len(pts), a)), rows


def test_limit_closed_form_and_weights():
    cam, far = CAMS["pitched_45"]
    _, s, _ = plane_samples(cam, far)
    n_pixels = len(s) * s.pixels[0]
    assert texel_limit(s, 512 * 512) == pytest.approx(2 * n_pixels / (512 * 512), rel=1e-12)
    # weights: 2 (Σ a √w)² / (T Σ a w), below the uniform-weight value (Cauchy-Schwarz) unless w is constant
    w = np.linspace(0.5, 2.0, len(s))
    sw = Samples(s.position, s.normal, s.dx, s.dy, s.view_depth, w, s.pixel, s.kind, s.pixels)
    a = s.pixels
    assert texel_limit(sw, 1000) == pytest.approx(2 * np.sum(a * np.sqrt(w)) ** 2 / (1000 * np.sum(a * w)))
    assert texel_limit(sw, 1000) < texel_limit(s, 1000)


def test_limit_is_the_optimum_of_its_relaxation():
    """An independent truth for the closed form: SciPy minimising the weighted mean of 2/d_i (the least
    h at texel density d_i) under the texel budget Σ a_i d_i / f_i = T reaches texel_limit, with
    uneven pixels a_i, weights w_i and grazing factors f_i (below 1 too: a normal turned towards the camera
    raises |n.v|, so the turned plane claims less light-space area than the surface covers)."""
    from scipy.optimize import minimize as sp_minimize

    rng = np.random.default_rng(3)
    n, T = 12, 5000.0
    a, w, f = rng.uniform(1, 4, n), rng.uniform(0.2, 3, n), rng.uniform(0.2, 5, n)
    z = np.zeros((n, 3))
    s = Samples(z, z, z, z, np.ones(n), w, np.zeros((n, 2), int), "boundary", a, f)
    # in units of T (d = T x): the mean of 2 / x under Σ a_i x_i / f_i = 1 is T times the limit
    obj = lambda x: float(np.sum(a * w * 2 / x) / np.sum(a * w))  # noqa: E731
    budget = {"type": "eq", "fun": lambda x: float(np.sum(a * x / f) - 1.0)}
    r = sp_minimize(obj, np.full(n, 1.0 / np.sum(a / f)), constraints=[budget], bounds=[(1e-9, None)] * n,
                    method="SLSQP", options={"ftol": 1e-13, "maxiter": 1000})
    r.fun /= T
    assert r.success and texel_limit(s, T) == pytest.approx(r.fun, rel=1e-6)


def grazing_samples(cam: Camera, light, far: float):
    """select_samples on a GRID of the camera's pixels seeing the plane y = 0 (the grazing rule applied)."""
    from shadowopt.solvers.samples import select_samples

    d = cam.ray_directions(*GRID).reshape(GRID[1], GRID[0], 3)
    with np.errstate(divide="ignore"):
        t = -cam.position[1] / d[..., 1]
    hit = (t > 0) & (t * (d @ cam.forward) < far)
    pos = np.where(hit[..., None], cam.position + np.where(hit, t, 0)[..., None] * d, 0.0)
    nrm = np.broadcast_to([0, 1.0, 0], pos.shape).copy()
    yes = np.ones(hit.shape, bool)
    return pos[hit], select_samples(cam, light, pos, nrm, hit, yes, np.zeros(hit.shape, bool), yes)


@pytest.mark.parametrize("elevation_deg", [1.0, 3.0])
def test_grazing_light_stays_above_the_limit(elevation_deg):
    """With the sun a few degrees above the plane the grazing rule turns every normal towards the light
    (the metric then sees a steeper plane): the limit counts the texels the real plane spends, so the
    optimized map, the one nearest the bound, stays above it (it was 0.57x of the uncorrected bound)."""
    cam, far = CAMS["pitched_45"]
    e = math.radians(elevation_deg)
    light = DirectionalLight.make([0, -math.sin(e), math.cos(e)])
    pts, s = grazing_samples(cam, light, far)
    assert s.light_area_factor is not None and np.all(s.light_area_factor > 1)
    r = minimize(cam, light, s, pts, BOUNDS, (512, 512))
    assert r.fun >= 0.95 * texel_limit(s, 512 * 512), (r.fun, texel_limit(s, 512 * 512))


@pytest.mark.parametrize("sun", sorted(SUNS))
def test_no_baseline_beats_the_limit(sun):
    """h >= 2 / |det J| for each sample (||F||² >= 2 |det F|), and Σ a |det J| <= T: every method's
    objective is at least the limit, on the plane where the samples' texels are distinct."""
    cam, far = CAMS["pitched_45"]
    pts, s, _ = plane_samples(cam, far)
    light = DirectionalLight.make(SUNS[sun])
    for method in ("uniform", "focused", "lispsm", "logpsm"):
        maps = baseline(method, cam, light, pts, BOUNDS, (512, 512))
        pe = predicted_error(maps, s)
        assert pe["objective"] >= pe["limit"] * (1 - 1e-9), (method, pe)
        assert pe["ratio_to_limit"] == pytest.approx(pe["objective"] / pe["limit"])


@pytest.mark.parametrize("sun", sorted(SUNS))
@pytest.mark.parametrize("cam_name", sorted(CAMS))
def test_plane_reaches_the_limit(cam_name, sun):
    """Chong 2003 Theorem 1: on a plane some light matrix makes the map an affine image of the screen.
    A square map: within 2% of 2N/T when the plane fills the screen, else within 2% of the
    aspect-corrected bound (the visible region is the screen's lower part, r:1 against the map's 1:1);
    a map of the region's own aspect: within 2% of 2N/T (the affine fit assigns s and t by the objective). Constant footprint: max_m / mean_m <= 1.05."""
    cam, far = CAMS[cam_name]
    pts, s, rows = plane_samples(cam, far)
    light = DirectionalLight.make(SUNS[sun])
    r_aspect = GRID[1] / rows  # the visible region is the screen's lowest `rows` grid rows
    for res in ((512, 512), (512, max(8, round(512 / r_aspect)))):  # square, and the region's own aspect
        r = minimize(cam, light, s, pts, BOUNDS, res)
        T = res[0] * res[1]
        lim = texel_limit(s, T)
        q = (512 / res[1]) / r_aspect  # the map's rows per screen row over its columns per screen column
        q = max(q, 1 / q)
        bound = lim * (1 + q * q) / (2 * q)  # the best a rectangle map of this aspect can do (h = sx^-2 + sy^-2)
        _, m, ok = per_sample(r.map, DeviceSamples(s, cam.position))
        assert ok.all()
        assert r.fun <= 1.02 * bound, (res, r.fun, lim, bound, r.start, r.x)
        # and not below the limit by more than the samples' discretisation (texel_limit's docstring: the
        # map need only contain the sample centres, about one sample spacing per side; measured 0.96-0.98)
        assert r.fun >= 0.95 * lim, (res, r.fun, lim)
        assert m.max() / m.mean() <= 1.05, (res, float(m.max() / m.mean()), r.x)
    if rows == GRID[1]:  # the whole screen sees the plane: the square map itself is within 2% of 2N/T
        assert r.fun <= 1.02 * 2 * len(s) * s.pixels[0] / T


@pytest.mark.parametrize("d_over_n", [10.0, 100.0, 1000.0])
def test_log_family_pads_after_its_log_step(d_over_n):
    """The optimizer's LogPSM family (output.allow_log_warp) pads t after the log warp, as the LogPSM
    baseline does: the receivers use all but the PAD_TEXELS margin of the map's rows and columns at any
    warp strength (padding before the log step left 1.1%, 4.9% and 18.2% of the rows unused at
    D/n' = 10, 100, 1000)."""
    from shadowopt.solvers.optimize import Problem

    cam, far = CAMS["eye_level"]
    pts, s, _ = plane_samples(cam, far)
    prob = Problem(cam, DirectionalLight.make(SUNS["30_front"]), s, pts, BOUNDS, (400, 400), log=True)
    m = prob.map_for(np.array([0.0, math.log1p(d_over_n)]))
    assert m.log_warp is not None
    si, ti, _, _ = m.map_coords(pts)
    i, j = np.floor(si * 400).astype(int), np.floor(ti * 400).astype(int)
    assert i.min() >= 0 and j.min() >= 0 and i.max() < 400 and j.max() < 400
    unused_cols, unused_rows = 1 - (np.ptp(i) + 1) / 400, 1 - (np.ptp(j) + 1) / 400
    assert max(unused_cols, unused_rows) <= 0.01, (unused_cols, unused_rows)
