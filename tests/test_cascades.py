"""Cascades: split formulas (Lloyd eqs. 80-82, practical λ), eq. 83 allocation, and cascaded
baselines at the solver level (tight SDSM range, coverage, error against one map)."""
from __future__ import annotations

import dataclasses
import math
import time

import numpy as np
import pytest

from shadowopt.solvers.baselines import baseline
from shadowopt.solvers.cameras import Camera
from shadowopt.solvers.cascades import allocate, critical_factors, pixel_world_size, split_depths
from shadowopt.solvers.lights import DirectionalLight
from shadowopt.solvers.metric import predicted_error
from shadowopt.solvers.samples import Samples, pixel_derivatives
from shadowopt.solvers.shadow_map import map_for_depth
from testkit import ground_samples

SUN = DirectionalLight.make([-0.3, -0.8, 0.5])
BOUNDS = (np.array([-150.0, 0.0, -150.0]), np.array([150.0, 10.0, 150.0]))




CAM = Camera.look([0, 2, 0], [0, -0.1, 1], near=0.1, far=300, resolution=(1280, 720))


# ---------------------------------------------------------------- formulas
def test_equal_ratio_splits():
    for n, f, k in ((1.0, 1000.0, 3), (0.1, 50.0, 5), (2.0, 7.0, 1)):
        z = split_depths(n, f, k, "log")
        assert z == pytest.approx([n * (f / n) ** (i / k) for i in range(k + 1)], rel=1e-12)
        assert np.allclose(z[1:] / z[:-1], (f / n) ** (1 / k))  # f_i / n_i the same for every partition


def test_practical_splits_interpolate_uniform_and_log():
    assert split_depths(1, 1000, 3, "practical", 0.0) == pytest.approx([1, 334, 667, 1000])
    assert split_depths(1, 1000, 3, "uniform") == pytest.approx([1, 334, 667, 1000])
    assert split_depths(1, 1000, 3, "practical", 1.0) == pytest.approx([1, 10, 100, 1000])
    assert split_depths(1, 1000, 3, "practical", 0.25) == pytest.approx(
        0.25 * np.array([1, 10, 100, 1000]) + 0.75 * np.array([1, 334, 667, 1000]))
    with pytest.raises(ValueError):
        split_depths(1, 10, 2, "nonsense")


def test_allocation_is_eq_83():
    R_s, R_t = np.array([400.0, 900.0, 100.0]), np.array([200.0, 900.0, 400.0])
    T = 3 * 1024 * 1024
    r = allocate(R_s, R_t, T)
    S = R_s * R_t
    for (rs, rt), a, b, sg in zip(r, R_s, R_t, S / S.sum()):
        assert rs == pytest.approx(math.sqrt(a / b * sg * T), abs=1)
        assert rt == pytest.approx(math.sqrt(b / a * sg * T), abs=1)
        assert rs / a == pytest.approx(math.sqrt(T / S.sum()), rel=0.01)  # one texel/pixel ratio for all
    assert sum(a * b for a, b in r) <= T


def test_critical_factors_ignore_receivers_outside_the_map():
    per_s = np.array([1.0, 2.0, np.nan, 4.0])
    per_t = np.array([2.0, 2.0, 1.0, np.inf])
    pix = np.array([0.01, 0.01, 0.01, 0.01])
    assert critical_factors(per_s, per_t, pix, q=100) == pytest.approx((200.0, 200.0))
    assert critical_factors(np.zeros(0), np.zeros(0), np.zeros(0)) == (1.0, 1.0)
    # pixel size: view depth x 2 tan(fov_y / 2) / height
    p = CAM.position + 10 * CAM.forward
    assert pixel_world_size(CAM, p[None])[0] == pytest.approx(10 * 2 * math.tan(math.radians(30)) / 720)


# ---------------------------------------------------------------- cascaded baselines
@pytest.mark.parametrize("method", ["uniform", "focused", "lispsm", "logpsm"])
@pytest.mark.parametrize("splits", ["uniform", "log", "practical"])
def test_cascades_split_the_tight_receiver_range_and_keep_every_receiver(method, splits):
    pts, _ = ground_samples(CAM)
    depth = (pts - CAM.position) @ CAM.forward
    maps = baseline(method, CAM, SUN, pts, BOUNDS, cascades=4, splits=splits, split_lambda=0.7)
    z = split_depths(depth.min(), depth.max(), 4, splits, 0.7)  # SDSM: receivers' min/max, not near/far
    assert np.array([m.split for m in maps]).ravel() == pytest.approx([0.0, z[1], z[1], z[2], z[2], z[3], z[3], CAM.far])
    idx = map_for_depth(maps, depth)
    for k, m in enumerate(maps):
        sel = idx == k
        assert sel.any()
        s, t, zz, w = m.map_coords(pts[sel])
        assert np.all((s >= 0) & (s <= 1) & (t >= 0) & (t <= 1) & (np.abs(zz) <= 1) & (w > 0)), (method, k)


@pytest.mark.parametrize("method", ["focused", "lispsm", "logpsm"])
def test_more_cascades_predict_less_error(method):
    pts, samples = ground_samples(CAM)
    err = [predicted_error(baseline(method, CAM, SUN, pts, BOUNDS, resolution=(1024, 1024), cascades=k,
                                    splits="log"), samples)["objective"] for k in (1, 2, 4)]
    assert err[0] > err[1] > err[2]


def test_texel_budget_buys_one_size_for_every_cascade_fit_to_the_worst_map():
    # The cascades of one light share one size (solvers.cascades.ONE_SIZE_PER_LIGHT: engines keep them in one
    # texture array or equal atlas tiles). Focused maps are orthographic: metres per unit s is the map's width
    # everywhere, so the texel-to-pixel ratio along s of cascade k is width_k / (w p5_k) with one w for all; the
    # shared aspect (max R_s / max R_t, eq. 83's factors) makes the worst cascade along s and along t meet the same
    # ratio.
    pts, samples = ground_samples(CAM)
    T = 3 * 512 * 512
    maps = baseline("focused", CAM, DirectionalLight.make([0, -1, 0]), pts, BOUNDS, cascades=3, splits="log",
                    texel_budget=T)
    assert len({m.resolution for m in maps}) == 1
    total = sum(m.resolution[0] * m.resolution[1] for m in maps)
    assert 0.95 * T <= total <= T
    depth = (pts - CAM.position) @ CAM.forward
    idx = map_for_depth(maps, depth)
    ratios = []
    for k, m in enumerate(maps):
        pix = depth[idx == k] * 2 * CAM.tan_half_fov_y / CAM.resolution[1]
        width, height = 2 / m.projection[0, 0], 2 / m.projection[1, 1]
        ratios.append([width / m.resolution[0] / np.percentile(pix, 5), height / m.resolution[1] / np.percentile(pix, 5)])
        assert m.depth_bias["texel_world_size"] == pytest.approx(max(width / m.resolution[0], height / m.resolution[1]),
                                                                 rel=1e-3)  # bias follows the allocated resolution
    worst = np.array(ratios).max(axis=0)
    assert worst[0] / worst[1] == pytest.approx(1.0, rel=0.1), ratios
    # and the shared aspect is not worse than spending the budget in equal squares
    even = baseline("focused", CAM, DirectionalLight.make([0, -1, 0]), pts, BOUNDS, cascades=3, splits="log",
                    resolution=(512, 512))
    assert predicted_error(maps, samples)["max_m"] <= predicted_error(even, samples)["max_m"]


def test_allocation_never_exceeds_the_budget_when_a_side_hits_the_floor():
    # A thin far cascade (R_s << R_t) would get a side below MIN_RES; flooring it must not overspend T,
    # and the other maps share what the floored ones leave: only the rounding down of each side is left
    # over (less than one row and one column per map).
    from shadowopt.solvers.cascades import MIN_RES

    for R_s, R_t, T in (([1e6, 1.0, 1.0], [1.0, 1.0, 1.0], 3 * 512 * 512), ([547.0, 54.0, 1.0], [1404.0, 305.0, 400.0], 3 * 512 * 512),
                        ([5e4, 1e-9], [1e4, 3.0], 2 ** 20), ([1.0, 2.0, np.nan], [1.0, 1.0, np.inf], 2 ** 18)):
        r = allocate(np.array(R_s), np.array(R_t), T)
        assert sum(a * b for a, b in r) <= T, r
        assert T - sum(a * b for a, b in r) < sum(a + b for a, b in r), r
        assert all(a >= MIN_RES and b >= MIN_RES for a, b in r)
    pts, _ = ground_samples(CAM)
    maps = baseline("focused", CAM, SUN, pts, BOUNDS, cascades=3, splits="uniform", texel_budget=3 * 512 * 512)
    assert 0.9 * 3 * 512 * 512 <= sum(m.resolution[0] * m.resolution[1] for m in maps) <= 3 * 512 * 512


# ---------------------------------------------------------------- optimized splits
def test_optimized_splits_beat_every_standard_split_and_keep_every_receiver():
    from shadowopt.solvers.split_search import optimize_splits

    pts, samples = ground_samples(CAM)
    depth = (pts - CAM.position) @ CAM.forward
    r = optimize_splits(CAM, SUN, samples, pts, BOUNDS, (512, 512), 4)
    assert len(r.split_at) == 3 and np.all(np.diff(r.split_at) > 0)
    assert depth.min() <= r.split_at[0] and r.split_at[-1] <= depth.max()
    # independent recomputation: the metric on the maps at those splits, on all receivers
    maps = baseline("lispsm", CAM, SUN, pts, BOUNDS, (512, 512), cascades=4, split_at=r.split_at)
    opt = predicted_error(maps, samples)["objective"]
    for kind in ("uniform", "log", "practical"):
        std = predicted_error(baseline("lispsm", CAM, SUN, pts, BOUNDS, (512, 512), cascades=4, splits=kind),
                              samples)["objective"]
        assert opt <= std * 1.02, (kind, opt, std)
    idx = map_for_depth(maps, depth)
    for k, m in enumerate(maps):
        s, t, _, w = m.map_coords(pts[idx == k])
        assert np.all((s >= 0) & (s <= 1) & (t >= 0) & (t <= 1) & (w > 0))


def test_explicit_split_depths_are_checked():
    pts, _ = ground_samples(CAM)
    with pytest.raises(ValueError, match="split_at: need 3"):
        baseline("focused", CAM, SUN, pts, BOUNDS, cascades=4, split_at=[5.0, 10.0])


def test_split_search_nfev_is_the_number_of_candidate_fits(monkeypatch):
    """SplitResult.nfev reports how many split candidates were scored. Each candidate costs exactly one map fit
    (the module's docstring), so a counter wrapped around fit_baseline is an independent count; and the search
    scores the three standard starts plus at most maxeval BOBYQA points."""
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


def test_split_search_without_samples_returns_the_practical_splits():
    """With no samples there is nothing to score: optimize_splits returns the k - 1 inner practical splits
    (λ = 0.5: the mean of Lloyd et al.'s log split z_n (z_f/z_n)^(i/k) and the uniform one) over the receivers'
    view-depth range, without evaluating anything."""
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
    values unchanged, while giving the far samples ten times the weight of the near ones changes them."""
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


def test_split_result_json_keeps_microseconds():
    """SplitResult.to_json: time_ms to the microsecond (3 decimals), the resolution every solver's time in the
    responses has."""
    from shadowopt.solvers.split_search import SplitResult

    r = SplitResult(np.array([3.0, 9.0]), 1.5, "log", {"log": 1.5}, 7, 12.3456)
    assert r.to_json()["time_ms"] == 12.346



def _near_ground_scene():
    """A 40 m ground patch with a box on it in front of the camera, and a box 250 m behind the camera that only
    widens the scene's bounds: stable cascades (fit to a shadow distance from the bounds) get slices beyond every
    receiver; the other methods split the receivers' own depth range."""
    from testkit import box, plane, scene_entry_of  # lazy: only the solve test builds scenes

    return scene_entry_of([plane(20.0), box((-1.0, 0.0, 8.0), (1.0, 3.0, 10.0)),
                           box((-2.0, 0.0, -250.0), (2.0, 2.0, -248.0))])


@pytest.mark.parametrize("method", ["focused", "lispsm", "optimized", "stable_csm", "path"])
def test_a_budget_gives_one_size_per_light_and_an_empty_slice_is_dropped_with_a_note(method):
    """issue 25: under a texel budget the cascades of one light got sizes of their own (16x16 maps on slices a
    few centimetres deep), which no engine's texture array or atlas tiles can hold, and a cascade with no sample
    came back without a word. Now: one size for every cascade of the light within the budget, a slice with no
    receiver dropped with a note naming it (its texels given to the kept cascades unless their grid is snapped),
    and a note for every cascade no sample reaches."""
    from shadowopt.api.cli import validate_rig  # lazy: the service stack, for an end-to-end solve
    from shadowopt.service.request import SolveRequest  # lazy: as above
    from shadowopt.service.solve import solve  # lazy: as above

    budget = 4 * 256 * 256
    rig = validate_rig({"camera": {"position": [0, 1.7, 0], "target": [0, 1.0, 40], "fov_y_deg": 60, "near": 0.1,
                                   "far": 300, "resolution": [320, 180]},
                        "lights": [{"type": "directional", "direction": [0.3, -0.6, 0.7]}],
                        "shadow": {"texel_budget": budget, "cascades": 4}, "coarse_long_side": 96})
    light = solve(_near_ground_scene(), rig, SolveRequest(method))["lights"][0]
    cascades, notes = light["cascades"], light.get("notes", [])
    sizes = {tuple(c["resolution"]) for c in cascades}
    assert len(sizes) == 1, sizes
    w, h = sizes.pop()
    used = len(cascades) * w * h
    assert used <= budget
    dropped = [n for n in notes if " dropped: none of the light's" in n]
    assert len(cascades) + len(dropped) == 4
    if method == "stable_csm":  # its slices run to the shadow distance, far beyond the 20 m of receivers
        assert dropped and any("texels are not used" in n for n in notes), notes
    elif dropped:
        assert used >= 0.9 * budget and any("texels go to the" in n for n in notes), notes
    else:
        assert used >= 0.9 * budget
    for k, c in enumerate(cascades):
        if c["predicted_error"]["samples"] == 0:
            assert any(n.startswith(f"cascade {k} (view depth {c['split'][0]:.4g}-") for n in notes), (k, notes)


def test_cascade_splits_tile_the_view_from_the_eye_to_the_far_plane():
    """fit_baseline's cascades serve [0, split_1], [split_1, split_2] ... [split_k-1, camera.far]: contiguous, the
    first from the eye and the last to the far plane, whatever the receivers' depth range (here 2-150 m of
    0.1-300), with the standard splits and with explicit ones."""
    pts, _ = ground_samples(CAM)
    for kw in ({"splits": "practical"}, {"splits": "log"}, {"split_at": [6.0, 20.0, 60.0]}):
        maps = baseline("focused", CAM, SUN, pts, BOUNDS, (256, 256), cascades=4, **kw)
        ends = [m.split for m in maps]
        assert ends[0][0] == 0.0 and ends[-1][1] == CAM.far, (kw, ends)
        assert all(a[1] == b[0] for a, b in zip(ends, ends[1:])), (kw, ends)
    assert [m.split[1] for m in maps[:-1]] == [6.0, 20.0, 60.0]


def test_a_budgets_shared_size_takes_its_aspect_from_each_cascades_own_receivers():
    """Under a texel budget (one size per light, cascades.ONE_SIZE_PER_LIGHT) fit_baseline gives every cascade
    T / k texels at the aspect max R_s / max R_t, each map's critical factors (Lloyd et al. 2007 §4) estimated
    from the receivers of its own depth slice. Truth: those factors recomputed here from texel_extents and the
    pixel sizes of each slice's receivers, then cascades.allocate."""
    from shadowopt.solvers.texel_size import texel_extents

    ground, _ = ground_samples(CAM, grid=(64, 36))
    pole = np.column_stack([np.full(60, 1.0), np.linspace(0.0, 30.0, 60), np.full(60, 8.0)])  # 30 m tall, 8 m ahead
    pts = np.vstack([ground, pole])  # a sun from behind sees its upper part on far ground's light rays (far maps)
    depth = (pts - CAM.position) @ CAM.forward
    T = 3 * 700 * 500
    for sun in (SUN, DirectionalLight.make([0.9, -0.3, 0.1]), DirectionalLight.make([0.0, -0.4, 1.0]),
                DirectionalLight.make([0.0, -0.3, -1.0]), DirectionalLight.make([0.2, -1.0, 0.05])):
        maps = baseline("focused", CAM, sun, pts, BOUNDS, cascades=3, texel_budget=T)
        R_s, R_t = [], []
        for m in maps:
            sel = (depth >= m.split[0]) & (depth <= m.split[1])
            assert 0 < sel.sum() <= 4000
            per_s, per_t = texel_extents(m, pts[sel], sun)
            rs, rt = critical_factors(per_s, per_t, pixel_world_size(CAM, pts[sel]))
            R_s.append(rs)
            R_t.append(rt)
        want = allocate(np.array(R_s), np.array(R_t), T, shared=True)
        assert [tuple(m.resolution) for m in maps] == want
