"""The path optimizer (solvers.path_optimize, method "path"): on a short strafe along the demo scene, its
maps keep a world-fixed texel grid between frames (world points move by whole texels: checked with
ShadowMap.map_coords on the returned matrices), predict no more than 1.1x the per-frame optimizer's error,
keep every receiver inside its map (renderers.coverage at a small screen) and flicker less than the
per-frame optimizer (renderers.stability against ray-traced visibility); whole paths: the second pass and
keyframes whose reported interpolation error is recomputed by hand."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from shadowopt.solvers.cameras import Camera
from shadowopt.solvers.lights import DirectionalLight
from testkit import ground_samples

SCREEN = (320, 180)
MAP = 256
FRAMES = 6
# a sideways strafe at eye height, looking along the demo's row of casters, 0.13 m per frame
STRAFE = [((0.13 * i, 1.7, 0.0), (0.0, -0.14, 1.0)) for i in range(FRAMES)]


def _rig(validate_rig, pos, fwd):
    return validate_rig({"camera": {"position": list(pos), "forward": list(fwd), "resolution": list(SCREEN),
                                    "fov_y_deg": 60, "near": 0.1, "far": 300},
                         "lights": [{"usd_path": "/World/Sun"}],
                         "shadow": {"resolution": [MAP, MAP], "cascades": 1}, "coarse_long_side": 120})


@pytest.fixture(scope="module")
def strafe():
    from shadowopt.api.cli import validate_rig
    from shadowopt.service.pipeline import scene_entry
    from shadowopt.service.rigs import resolve_rig
    from shadowopt.service.request import SolveRequest
    from shadowopt.service.solution_json import maps_from_solution
    from shadowopt.service.solve import solve

    entry = scene_entry(Path(__file__).resolve().parents[1] / "configs" / "demo_scene.usda")
    rigs = [_rig(validate_rig, p, f) for p, f in STRAFE]
    out = {"entry": entry, "rigs": rigs, "cameras": [], "light": None}
    for method in ("optimized", "path"):
        sols, prev = [], None
        for rig in rigs:
            prev = solve(entry, rig, SolveRequest(method, previous=prev if method == "path" else None))
            sols.append(prev)
        out[method] = sols
        out[method + "_maps"] = [maps_from_solution(s)[0] for s in sols]
    for rig in rigs:
        r = resolve_rig(rig, entry.loaded)
        out["cameras"].append(r.camera)
        out["light"] = r.lights[0]
    return out


def _ground_points():
    """World points on the demo's ground in front of the strafing camera (fixed: the same in every frame)."""
    x, z = np.meshgrid(np.linspace(-3.0, 4.0, 15), np.linspace(3.0, 25.0, 23))
    return np.column_stack([x.ravel(), np.zeros(x.size), z.ravel()])


def _texels(smap, pts):
    s, t, _, w = smap.map_coords(pts)
    return np.column_stack([s * smap.resolution[0], t * smap.resolution[1]]), w


def test_held_frames_move_world_points_by_whole_texels(strafe):
    pts = _ground_points()
    held_pairs, frac_path, frac_opt = 0, [], []
    for k in range(FRAMES - 1):
        a, b = (strafe["path"][i]["solver"]["path"]["cascades"][0] for i in (k, k + 1))
        ua, wa = _texels(strafe["path_maps"][k][0], pts)
        ub, wb = _texels(strafe["path_maps"][k + 1][0], pts)
        d = ub - ua
        frac = np.abs(d - np.round(d))[(wa > 0) & (wb > 0)]
        oa, _ = _texels(strafe["optimized_maps"][k][0], pts)
        ob, _ = _texels(strafe["optimized_maps"][k + 1][0], pts)
        e = ob - oa
        frac_opt.append(float(np.mean(np.abs(e - np.round(e)))))
        if b["decision"]["kept"] == "held" and a["levels"] == b["levels"]:
            held_pairs += 1
            frac_path.append(float(frac.max()))
    assert held_pairs >= 3, f"only {held_pairs} of {FRAMES - 1} frame pairs kept the grid and its scale level"
    assert max(frac_path) < 1e-4, f"held grid: world points moved by fractions of a texel: {frac_path}"
    # the per-frame optimizer refits every frame: its texels swim (what the path method removes)
    assert np.mean(frac_opt) > 0.05, f"per-frame optimized mean fractional texel motion {frac_opt}"


def test_objective_within_1_1x_of_per_frame_optimized(strafe):
    opt = [s["lights"][0]["predicted_error"]["objective"] for s in strafe["optimized"]]
    path = [s["lights"][0]["predicted_error"]["objective"] for s in strafe["path"]]
    ratio = float(np.mean(path) / np.mean(opt))
    assert ratio <= 1.1, f"path objective {np.round(path, 2)} vs per-frame optimized {np.round(opt, 2)}: {ratio:.3f}x"


def test_every_receiver_stays_inside_its_map(strafe):
    from shadowopt.renderers.coverage import outside_pixels
    from shadowopt.renderers.ground_truth import screen_camera

    for cam, maps in zip(strafe["cameras"], strafe["path_maps"]):
        got = outside_pixels(strafe["entry"].rays, screen_camera(cam, (160, 90)), strafe["light"], maps)
        assert got["receiver_pixels"] > 1000 and got["outside_pixels"] == 0, got


def test_path_flickers_less_than_per_frame_optimized(strafe):
    stability = pytest.importorskip("shadowopt.renderers.stability")
    st = {m: stability.path_stability(strafe["entry"].rays, strafe["cameras"], strafe["light"], strafe[m + "_maps"],
                                      SCREEN, depth="solution") for m in ("optimized", "path")}
    fl = {m: float(np.mean(s["flicker"])) for m, s in st.items()}
    sw = {m: float(np.mean(s["swim_texels"])) for m, s in st.items()}
    mis = {m: float(np.mean(s["misclassified"])) for m, s in st.items()}
    msg = f"flicker {fl}, swim {sw}, misclassified per frame {mis}"
    assert fl["optimized"] > 0, msg  # the per-frame maps do flicker on this path (else the test says nothing)
    assert fl["path"] <= 0.3 * fl["optimized"], msg
    assert sw["path"] < 0.5 * sw["optimized"], msg
    assert max(st["path"]["outside"]) == 0, msg


def test_whole_path_second_pass_and_keyframes(strafe):
    from shadowopt.solvers.metric import predicted_objective
    from shadowopt.service.solve import frame_problems
    from shadowopt.solvers.path_optimize import interpolated_maps, keyframes, optimize_path

    frames = frame_problems(strafe["entry"], strafe["rigs"])
    res = optimize_path(frames)
    assert set(res.passes) == {"interactive", "segments", "returned"}
    ratio = float(np.mean(res.objective) / np.mean(res.per_frame_objective))
    assert ratio <= 1.1, (res.objective, res.per_frame_objective)
    for fp, maps, f in zip(frames, res.maps, res.objective):  # the reported objectives are the maps'
        assert predicted_objective(maps, fp.samples, fp.camera.position) == pytest.approx(f, rel=1e-12)
    kf = keyframes(res, frames, 3)
    assert kf["frames"] == [0, 3, 5] and [s["frame"] for s in kf["skipped"]] == [1, 2, 4]
    # the interpolation error at frame 4, by hand: halfway between keyframes 3 and 5, each matrix scaled to a unit w row
    a, b = res.maps[3][0].matrix, res.maps[5][0].matrix
    M = 0.5 * a / np.linalg.norm(a[3]) + 0.5 * b / np.linalg.norm(b[3])
    mi = interpolated_maps(res.maps[3], res.maps[5], 0.5)[0]
    assert np.allclose(mi.matrix, M, rtol=0, atol=1e-12 * np.abs(M).max())
    f4 = predicted_objective([mi], frames[4].samples, frames[4].camera.position)
    assert kf["skipped"][-1]["objective"] == pytest.approx(f4, rel=1e-12)
    assert kf["max_objective_ratio"] == pytest.approx(max([1.0] + [s["objective"] / s["objective_chosen"] for s in kf["skipped"]]))
    assert kf["max_outside_receivers"] == max(s["outside_receivers"] for s in kf["skipped"])


def test_auto_cascade_count_is_held_unless_clearly_better():
    from shadowopt.solvers.path_optimize import HYSTERESIS, held_cascade_count

    calls = []

    def maps_for(k):
        calls.append(k)
        return [f"map{i}" for i in range(k)], {"k": k}

    state = {"cascades": [{}, {}]}  # the previous frame had two cascades

    def auto(score_1):  # auto_cascades chose one cascade, scoring score_1 x two cascades' objective x texels
        return {"chosen": 1, "rule": "least objective x texels",
                "tried": [{"cascades": 1, "objective": score_1, "texels": 100, "p95_m": 0.1},
                          {"cascades": 2, "objective": 1.0, "texels": 100, "p95_m": 0.1}]}

    maps, info, a = held_cascade_count(maps_for, ["m"], {"k": 1}, auto(0.95), state, {})
    assert a["chosen"] == 2 and len(maps) == 2 and calls == [2], a  # 5% better: the held count stays
    maps, info, a = held_cascade_count(maps_for, ["m"], {"k": 1}, auto(0.99 * HYSTERESIS), state, {})
    assert a["chosen"] == 1 and maps == ["m"] and calls == [2], a  # better by more than the hysteresis: switch
    # with a target: the held count is kept while it meets the target
    t = auto(0.5)
    maps, info, a = held_cascade_count(maps_for, ["m"], {"k": 1}, t, state, {"target_p95_m": 0.2})
    assert a["chosen"] == 2, a
    t["tried"][1]["p95_m"] = 0.3
    maps, info, a = held_cascade_count(maps_for, ["m"], {"k": 1}, t, state, {"target_p95_m": 0.2})
    assert a["chosen"] == 1, a


def test_a_malformed_previous_path_state_starts_fresh(strafe):
    """A previous solution is a client's JSON: a path state that cannot hold the receivers (zero or overflowing
    rows, a resolution beyond the rig's) is refit from scratch, giving the first frame's maps."""
    from shadowopt.service.request import SolveRequest
    from shadowopt.service.solve import solve

    first = strafe["path"][0]
    good = first["solver"]["path"]["cascades"][0]
    want = first["lights"][0]["predicted_error"]["objective"]
    for bad, fresh in (({"view": [[0] * 4] * 4, "canonical": [[0] * 4] * 3, "resolution": [MAP, MAP], "levels": [3, 4]}, True),
                       ({**good, "canonical": [[1e308] * 4] * 3}, True), ({"view": "x"}, True),
                       ({**good, "resolution": [10 ** 8, 1]}, False)):  # a sound grid: kept, at the rig's resolution
        got = solve(strafe["entry"], strafe["rigs"][0], SolveRequest("path", previous={"solver": {"x": [None], "path": {"cascades": [bad]}}}))
        c = got["solver"]["path"]["cascades"][0]
        assert (c["decision"]["kept"] == "fresh") == fresh and c["resolution"] == [MAP, MAP], c["decision"]
        # (the state's x, when kept, only warm-starts the per-frame search: the same optimum to its tolerance)
        assert got["lights"][0]["predicted_error"]["objective"] == pytest.approx(want, rel=1e-3)


def test_a_moving_sun_gets_a_new_grid(strafe):
    """A held grid projects along the light it was made for: when the sun moves, the next frame's maps look along
    the new direction (view -Z) and the grid is refit from scratch."""
    from shadowopt.api.cli import validate_rig
    from shadowopt.service.request import SolveRequest
    from shadowopt.service.solution_json import maps_from_solution
    from shadowopt.service.solve import solve

    first = strafe["path"][0]
    d = np.array([-0.45, -0.8, 0.4])
    rig = validate_rig({**strafe["rigs"][0], "lights": [{"type": "directional", "direction": d.tolist()}]})
    got = solve(strafe["entry"], rig, SolveRequest("path", previous=first))
    assert got["solver"]["path"]["cascades"][0]["decision"]["kept"] == "fresh"
    view = maps_from_solution(got)[0][0].view
    assert np.allclose(-view[2, :3], d / np.linalg.norm(d), atol=1e-9)


def test_whole_path_segments_hold_everything_but_whole_texel_moves(strafe):
    """service.solve.solve_path (method path over a path known ahead): inside each reported segment, a world point
    moves by whole texels from frame to frame (checked on the returned matrices), its stored depth and the
    bias do not change, so the ray-traced flicker of the whole-path maps is exactly 0 inside segments and,
    over the path, at most 0.3x the per-frame optimizer's at an objective within the pass's tolerance."""
    from shadowopt.service.solution_json import maps_from_solution
    from shadowopt.service.solve import solve_path
    from shadowopt.solvers.path_optimize import SEGMENT_TOLERANCE

    sols = solve_path(strafe["entry"], strafe["rigs"])
    assert [s["method"] for s in sols] == ["path"] * FRAMES
    info = sols[0]["solver"]["path"]
    assert info["mode"] == "whole path" and info["pass"] == "segments", info
    maps = [maps_from_solution(s)[0] for s in sols]
    pts = _ground_points()
    held = 0
    for k in range(FRAMES - 1):
        if sols[k]["solver"]["path"]["segments"] != sols[k + 1]["solver"]["path"]["segments"]:
            continue
        held += 1
        a, b = maps[k][0], maps[k + 1][0]
        ua, wa = _texels(a, pts)
        ub, wb = _texels(b, pts)
        d = (ub - ua)[(wa > 0) & (wb > 0)]
        assert np.abs(d - np.round(d)).max() < 1e-6, f"frames {k}, {k + 1}: fractional texel motion"
        za, zb = (m.map_coords(pts)[2] for m in (a, b))
        assert np.allclose(za, zb, rtol=0, atol=1e-9), f"frames {k}, {k + 1}: stored depth changed"
        assert a.depth["hardware"]["constant"] == b.depth["hardware"]["constant"]
    assert held >= 3, [s["solver"]["path"]["segments"] for s in sols]
    stability = pytest.importorskip("shadowopt.renderers.stability")
    st = stability.path_stability(strafe["entry"].rays, strafe["cameras"], strafe["light"], maps, SCREEN,
                                  depth="solution")
    opt = stability.path_stability(strafe["entry"].rays, strafe["cameras"], strafe["light"], strafe["optimized_maps"],
                                   SCREEN, depth="solution")
    pairs = [k for k in range(FRAMES - 1)
             if sols[k]["solver"]["path"]["segments"] == sols[k + 1]["solver"]["path"]["segments"]]
    assert all(st["flicker"][k] == 0 for k in pairs), st["flicker"]
    assert np.mean(st["flicker"]) <= 0.3 * np.mean(opt["flicker"]), (st["flicker"], opt["flicker"])
    assert max(st["outside"]) == 0
    f = sum(s["solver"]["fun"] for s in sols)
    ref = sum(s["solver"]["per_frame_objective"] for s in sols)
    assert f <= SEGMENT_TOLERANCE * ref * (1 + 1e-9), (f, ref)


def test_whole_path_keyframes_report_what_interpolation_adds(strafe):
    """solve_path(keyframes_every=K): keyframes at 0, K, ... and the last frame; each skipped frame reports the
    objective of the rule's interpolated maps there, recomputed here from the keyframes' returned matrices."""
    from shadowopt.service.solution_json import maps_from_solution
    from shadowopt.service.solve import frame_problems, solve_path
    from shadowopt.solvers.metric import predicted_objective
    from shadowopt.solvers.path_optimize import interpolated_maps

    sols = solve_path(strafe["entry"], strafe["rigs"], keyframes_every=2)
    kf = [s["solver"]["path"]["keyframes"] for s in sols]
    assert [k["is_keyframe"] for k in kf] == [True, False, True, False, True, True]
    maps = [maps_from_solution(s)[0] for s in sols]
    fp = frame_problems(strafe["entry"], strafe["rigs"][3:4])[0]
    mi = interpolated_maps(maps[2], maps[4], 0.5)
    assert kf[3]["interpolated_objective"] == pytest.approx(predicted_objective(mi, fp.samples, fp.camera.position),
                                                            rel=1e-6)
    assert kf[0]["interpolated_objective"] is None
    assert kf[0]["max_objective_ratio"] >= max(k["interpolated_objective"] / s["solver"]["fun"]
                                               for k, s in zip(kf, sols) if k["interpolated_objective"]) * (1 - 1e-9)


def test_joint_grid_is_seen_from_the_middle_frame():
    """joint_grid optimizes one canonical part for several frames, on the union of their samples and
    receivers, seen from the middle frame's camera (its splits and warp frame). So with three frames the first
    frame's camera plays no part: moving it (same samples and receivers) leaves the grid unchanged, while
    moving the middle frame's camera changes it."""
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


def test_segment_pass_finds_the_cheapest_cut(monkeypatch):
    """segment_pass cuts a path into segments (dynamic programming over segment counts) and, with the reference
    out of reach, returns the cut of least summed objective (the fewest segments among equals). The map fits
    are replaced by a table whose segment cost is g(the segment's coarsest level) x the sum of its frames'
    weights (not additive over frames, so the cut matters). Truth: every one of the 2^3 cuts of 4 frames
    evaluated by brute force."""
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


def _wide_path_frame():
    sun = DirectionalLight.make([-0.3, -0.8, 0.5])
    bounds = (np.array([-150.0, 0.0, -150.0]), np.array([150.0, 10.0, 150.0]))
    cam = Camera.look([0, 2, 0], [0, -0.1, 1], near=0.1, far=300, resolution=(640, 360))
    pts, samples = ground_samples(cam, far=120.0, grid=(32, 18))
    return cam, sun, samples, pts, bounds


def test_a_held_texel_allocation_is_kept_only_within_the_rigs_texels():
    """The next frame keeps the previous frame's resolutions (with its grids) while they fit in the texels the rig
    gives, here one 512 x 256 map (no texel_budget): a held 256 x 256 is kept, a held 512 x 512 (twice the rig's
    texels, though each side is within reason) is not."""
    import json

    from shadowopt.solvers.path_optimize import path_maps

    cam, sun, samples, pts, bounds = _wide_path_frame()
    _, sj = path_maps(cam, sun, samples, pts, bounds, None, resolution=(512, 256), cascades=1)
    for held, want in (([256, 256], (256, 256)), ([512, 512], (512, 256))):
        state = json.loads(json.dumps(sj["path"]))
        state["cascades"][0]["resolution"] = held
        maps, _ = path_maps(cam, sun, samples, pts, bounds, state, resolution=(512, 256), cascades=1)
        assert tuple(maps[0].resolution) == want, held


def test_a_path_maps_depth_is_the_warped_light_depth():
    """A grid map stores the warped light depth z / w (Lloyd et al.'s warp: depth divided by the warp's w): a point
    moved across the light and along a line of constant w (perpendicular to the light and to w's gradient) keeps
    its stored depth, for the held grid's map as for the first frame's."""
    import json

    from shadowopt.solvers.path_optimize import path_maps

    cam, sun, samples, pts, bounds = _wide_path_frame()
    first, sj = path_maps(cam, sun, samples, pts, bounds, None, resolution=(512, 512), cascades=1)
    held, _ = path_maps(cam, sun, samples, pts, bounds, json.loads(json.dumps(sj["path"])), resolution=(512, 512),
                        cascades=1)
    for smap in (first[0], held[0]):
        grad_w = smap.matrix[3, :3]
        e = np.cross(sun.direction, grad_w if np.linalg.norm(grad_w) > 1e-12 else smap.view[0, :3])
        e /= np.linalg.norm(e)
        _, _, z, w = smap.map_coords(pts)
        for step in (-7.0, 3.0, 20.0):
            _, _, z2, w2 = smap.map_coords(pts + step * e)
            assert w2 == pytest.approx(w, rel=1e-9, abs=1e-12)
            assert z2 == pytest.approx(z, rel=1e-9, abs=1e-12), step


def test_each_cascade_is_fitted_to_the_samples_and_receivers_of_its_own_split():
    """cascade_fits: cascade k gets exactly the samples whose view depth lies in its split, and (with no slack)
    the receivers whose camera depth does, the first and last cascades unbounded on their outer side."""
    from shadowopt.solvers.path_optimize import cascade_fits
    from shadowopt.solvers.shadow_map import ShadowMap

    cam = Camera.look_at([0, 2, 0], [0, 0, 20], resolution=(640, 480))
    pts, s = ground_samples(cam, far=60.0, grid=(40, 30))
    splits = [(0.1, 5.0), (5.0, 20.0), (20.0, 40.0)]
    maps = [ShadowMap(np.eye(4), np.eye(4), (64, 64), split=sp) for sp in splits]
    light = DirectionalLight(direction=np.array([-0.3, -0.8, 0.5]) / np.linalg.norm([-0.3, -0.8, 0.5]))
    fits = cascade_fits(cam, light, s, pts, (pts.min(0) - 1, pts.max(0) + 1), maps)
    depth = (pts - cam.position) @ cam.forward  # the receivers are the samples' points
    for k, ((lo, hi), cf) in enumerate(zip(splits, fits)):
        inside = (s.view_depth >= lo) & (s.view_depth <= hi)
        assert 0 < inside.sum() < len(s)
        assert np.array_equal(cf.sub.position, s.position[inside])
        r_lo, r_hi = (lo if k else -np.inf), (hi if k < 2 else np.inf)
        assert np.array_equal(cf.part, pts[(depth >= r_lo) & (depth <= r_hi)])
