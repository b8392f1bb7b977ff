"""Model only what the scene needs (service.need): a light with no visible receiver gets no map, a cascade with
none is dropped; every reader of solutions accepts such a light."""
from __future__ import annotations

import random

import numpy as np
import pytest

from shadowopt.api.schemas import Solution
from shadowopt.renderers.ground_truth import render_screen
from shadowopt.service.evaluation import evaluate_solution
from shadowopt.service.rigs import SolutionError, resolve_rig
from shadowopt.service.scenes import SceneEntry
from shadowopt.service.solution_check import validate_solution
from shadowopt.service.request import SolveRequest
from shadowopt.service.solution_json import maps_from_solution
from shadowopt.service.solve import solve
from shadowopt.solvers.cameras import Camera
from testkit import box, plane, scene_entry_of

CAM = {"position": (0, 1.7, 0), "forward": (0, -0.15, 1.0), "near": 0.1, "far": 300}
SUN = {"type": "directional", "direction": (-0.3, -0.8, 0.5)}
UP_SPOT = {"type": "spot", "position": (0, 5, 0), "direction": (0, 1, 0), "cone_deg": 20}  # points at the sky


def entry_from(parts) -> SceneEntry:
    return scene_entry_of(parts)


@pytest.fixture(scope="module")
def scene():
    return entry_from([plane(100), box([-1, 0, 8], [1, 3, 10]), box([3, 0, 20], [5, 6, 23])])


def rig(lights, camera=CAM, res=256, **shadow):
    return {"camera": {"resolution": (320, 180), "fov_y_deg": 60, **camera}, "lights": lights,
            "shadow": {"resolution": (res, res), "cascades": 1, **shadow}, "coarse_long_side": 120}


def test_spot_light_facing_the_sky_gets_no_map_and_every_reader_accepts_it(scene):
    r = rig([SUN, UP_SPOT])
    sol = solve(scene, r, SolveRequest("focused"))
    sun, spot = sol["lights"]
    assert sun["shadow"] == "map" and len(sun["cascades"]) == 1 and sun["need"]["receiver_pixels"] > 0
    assert spot["shadow"] == "none" and spot["cascades"] == []
    assert spot["need"]["receiver_pixels"] == spot["need"]["edge_receivers"] == 0
    assert "0 are inside its 20 degree cone" in spot["reason"]
    assert spot["predicted_error"]["texels"] == 0
    # readers: the checker, maps_from_solution, the typed model (client), the evaluator
    validate_solution(sol, light_kinds=["directional", "spot"])
    assert [len(m) for m in maps_from_solution(sol)] == [1, 0]
    assert Solution.model_validate(sol).lights[1].shadow == "none"
    ev = evaluate_solution(scene, r, sol, depth="ideal")["lights"][1]
    # ray-traced truth: no pixel the camera sees is inside the upward cone, so nothing is misclassified
    assert ev["shadow"] == "none" and ev["receiver_pixels"] == 0 and ev["misclassified_pixels"] == 0


def test_checker_refuses_maps_under_shadow_none_and_an_empty_list_without_it(scene):
    sol = solve(scene, rig([SUN, UP_SPOT]), SolveRequest("focused"))
    bad = {**sol, "lights": [sol["lights"][0], {**sol["lights"][1], "cascades": sol["lights"][0]["cascades"]}]}
    with pytest.raises(SolutionError, match=r"lights\.1\.cascades"):
        validate_solution(bad)
    bad = {**sol, "lights": [{**sol["lights"][0], "shadow": None, "cascades": []}, sol["lights"][1]]}
    with pytest.raises(SolutionError, match=r"lights\.0\.cascades"):
        validate_solution(bad)
    bad = {**sol, "lights": [{**sol["lights"][0], "shadow": "some"}, sol["lights"][1]]}
    with pytest.raises(SolutionError, match=r"lights\.0\.shadow"):
        validate_solution(bad)


def test_a_light_without_a_map_casts_no_shadow_in_the_evaluator(scene):
    """Strip the sun's map: the evaluator counts exactly the receivers the sun truly shadows (ray traced)."""
    r = rig([SUN])
    sol = solve(scene, r, SolveRequest("focused"))
    stripped = {**sol, "lights": [{**sol["lights"][0], "shadow": "none", "cascades": []}]}
    ev = evaluate_solution(scene, r, stripped, depth="ideal")
    resolved = resolve_rig(r, scene.loaded)
    sb = render_screen(scene.rays, resolved.camera, resolved.lights[0])
    truth = int((sb.receivers & ~sb.visible).sum())
    assert truth > 50  # the boxes' shadows
    assert ev["misclassified_pixels"] == truth and ev["shadow"] == "none"


def test_spot_receivers_are_the_coarse_pixels_inside_its_cone():
    """On a lone ground plane, a spot pointing down: the receivers are exactly the coarse pixels whose ground
    point is within the cone (closed form: a circle of radius h tan(cone) around the spot's foot)."""
    entry = entry_from([plane(100)])
    spot = {"type": "spot", "position": (0, 4, 10), "direction": (0, -1, 0), "cone_deg": 30}
    r = rig([spot])
    sol = solve(entry, r, SolveRequest("focused"))
    need = sol["lights"][0]["need"]
    cam = resolve_rig(r, entry.loaded).camera
    w, h = 120, 68  # coarse_long_side 120 at 320x180
    d = cam.ray_directions(w, h).reshape(-1, 3)
    t = -cam.position[1] / d[:, 1]
    p = cam.position + t[:, None] * d
    on = (t > 0) & (np.abs(p[:, 0]) <= 100) & (np.abs(p[:, 2]) <= 100) & ((p - cam.position) @ cam.forward <= cam.far)
    r2 = (p[:, 0] - 0) ** 2 + (p[:, 2] - 10) ** 2
    inside = on & (r2 <= (4 * np.tan(np.radians(30))) ** 2)
    # pixels whose ground point is within 2% of the cone's edge may go either way (float32 rays)
    edge = on & np.isclose(np.sqrt(r2), 4 * np.tan(np.radians(30)), rtol=0.02)
    assert need["seen_pixels"] == int(on.sum())
    assert int(inside.sum()) - int(edge.sum()) <= need["receiver_pixels"] <= int(inside.sum()) + int(edge.sum())
    assert need["receiver_pixels"] == need["in_cone_pixels"]  # the plane faces the spot everywhere in its cone
    assert sol["lights"][0]["shadow"] == "map"


def test_cascades_in_a_depth_gap_are_dropped():
    """A 6 m ground patch near the camera and a wall 100 m away, nothing between: of 4 practical cascades over
    the receivers' depth range, those falling in the gap (closed form: between the patch's farthest corner and
    the wall's face) serve no receiver and are not returned; the kept splits stay contiguous."""
    entry = entry_from([plane(3.0), box([-20, 0, 95], [20, 15, 100])])
    cam = {"position": (0, 2.0, -4.0), "forward": (0, -0.3, 1.0), "near": 0.1, "far": 300}
    r = rig([SUN], camera=cam, cascades=4, splits="practical")
    sol = solve(entry, r, SolveRequest("focused"))
    light = sol["lights"][0]
    f = np.array(cam["forward"]) / np.linalg.norm(cam["forward"])
    corners = np.array([[x, 0, z] for x in (-3, 3) for z in (-3, 3)])
    patch_far = float(((corners - cam["position"]) @ f).max())
    wall = np.array([[x, y, 95] for x in (-20, 20) for y in (0, 15)])
    wall_near = float(((wall - cam["position"]) @ f).min())
    splits = [c["split"] for c in light["cascades"]]
    assert len(splits) + len(light["notes"]) == 4 and 2 <= len(splits) < 4
    for note in light["notes"]:  # "cascade k (view depth lo-hi) dropped: ..."
        lo, hi = (float(x) for x in note.split("view depth ")[1].split(")")[0].split("-"))
        assert patch_far * 0.97 <= lo and hi <= wall_near * 1.03, note
    for (_, b), (c, _) in zip(splits, splits[1:]):
        assert b == pytest.approx(c)
    assert all(c["predicted_error"]["samples"] > 0 for c in light["cascades"])
    assert validate_solution(sol)["lights"][0]["cascades"]
    ev = evaluate_solution(entry, r, sol, depth="ideal")
    assert ev["outside_pixels"] == 0  # every visible receiver is still served by a kept cascade


def _p95(entry, r):
    return solve(entry, r, SolveRequest("focused"))["lights"][0]["predicted_error"]["p95_m"]


def test_p95_scales_as_texels_to_the_minus_half_and_the_budget_estimate_meets_the_target(scene):
    """The exponent auto's budget estimate uses (P95_TEXEL_EXPONENT = -1/2), measured: 4x the texels halves
    p95_m; and solving at the estimated budget meets the target it was asked for."""
    from shadowopt.service.map_sizing import P95_TEXEL_EXPONENT

    a = _p95(scene, rig([SUN], res=512, fixed_resolution=True))
    b = _p95(scene, rig([SUN], res=1024, fixed_resolution=True))
    assert np.log(b / a) / np.log(4.0) == pytest.approx(P95_TEXEL_EXPONENT, abs=0.05)
    r = rig([SUN], cascades="auto", max_cascades=2, target_p95_m=a / 3, fixed_resolution=True)
    r["shadow"].pop("resolution")
    r["shadow"]["texel_budget"] = 512 * 512
    auto = solve(scene, r, SolveRequest("focused"))["lights"][0]["auto_cascades"]
    assert auto["rule"].startswith("no k met") and "texels^-0.5" in auto["budget_estimate"]
    best = min(auto["tried"], key=lambda t: t["p95_m"])
    r2 = rig([SUN], cascades=best["cascades"], fixed_resolution=True)
    r2["shadow"].pop("resolution")
    r2["shadow"]["texel_budget"] = auto["needed_texel_budget"]
    assert _p95(scene, r2) <= a / 3 * 1.1


def test_auto_takes_the_fewest_cascades_within_the_tolerance(scene):
    """Each k's scores in `tried` are those of the same solve with cascades = k; the chosen k is the fewest whose
    objective x texels is within 5% of the least."""
    r = rig([SUN], cascades="auto", max_cascades=3)
    light = solve(scene, r, SolveRequest("focused"))["lights"][0]
    auto = light["auto_cascades"]
    for t in auto["tried"]:
        fixed = solve(scene, rig([SUN], cascades=t["cascades"]), SolveRequest("focused"))["lights"][0]["predicted_error"]
        assert t["objective"] == pytest.approx(fixed["objective"])
    score = {t["cascades"]: t["objective"] * t["texels"] for t in auto["tried"]}
    assert auto["chosen"] == min(k for k, v in score.items() if v <= min(score.values()) * 1.05)
    assert auto["returned"] == len(light["cascades"])


def test_a_met_target_returns_a_smaller_resolution_unless_fixed(scene):
    p95 = _p95(scene, rig([SUN], res=2048, fixed_resolution=True))
    target = 2.5 * p95  # met at 2048: about 2048 / 2.5 per side would do
    fixed = solve(scene, rig([SUN], res=2048, target_p95_m=target, fixed_resolution=True), SolveRequest("focused"))["lights"][0]
    assert fixed["cascades"][0]["resolution"] == [2048, 2048] and not fixed.get("notes")
    light = solve(scene, rig([SUN], res=2048, target_p95_m=target), SolveRequest("focused"))["lights"][0]
    w, h = light["cascades"][0]["resolution"]
    assert w % 64 == 0 and h % 64 == 0 and w * h < 2048 * 2048 / 4
    assert light["predicted_error"]["p95_m"] <= target
    assert any("texels saved" in n for n in light["notes"])


def test_one_rig_budget_is_split_by_need_and_beats_equal_shares(scene):
    """budget_scope rig: the light with no visible receiver gets 0 texels, the others share the budget as the
    Lagrange condition says (brute force over the split agrees), and the rig's predicted misclassified pixels
    are no more than with the same total split equally per light (today's per-light budget)."""
    from shadowopt.service.need import split_budget

    spot = {"type": "spot", "position": (0.5, 5, 12), "direction": (0, -1, 0.1), "cone_deg": 25}
    lights = [SUN, UP_SPOT, spot]
    B = 3 * 512 * 512

    def run(scope, budget):
        r = rig(lights, fixed_resolution=True, budget_scope=scope)
        r["shadow"].pop("resolution")
        r["shadow"]["texel_budget"] = budget
        return solve(scene, r, SolveRequest("focused"))

    sol = run("rig", B)
    split = sol["texel_budget_split"]
    t = [l["texels"] for l in split["lights"]]
    assert t[1] == 0 and sol["lights"][1]["shadow"] == "none" and sum(t) <= B
    assert split["returned_texels"] <= B
    d = [l["predicted_misclassified_at_probe"] for l in split["lights"]]
    # brute force: the share of light 0 minimizing d0 T0^-1/2 + d2 (B - T0)^-1/2
    f = np.linspace(0.01, 0.99, 9801)
    cost = d[0] / np.sqrt(f * B) + d[2] / np.sqrt((1 - f) * B)
    assert t[0] / B == pytest.approx(f[np.argmin(cost)], abs=2e-4)
    assert split_budget(B, d, split["probe_texels"]) == t
    even = run("light", B // 2)  # the same total over the two lights with receivers
    mis = lambda s: sum(l["predicted_error"]["misclassified_pixels"] for l in s["lights"])
    assert mis(sol) <= mis(even) * 1.001


def test_a_budget_estimate_beyond_reach_is_none_not_an_overflow():
    """texels_for_p95: (p95 / target)^2 x texels, None when that is not a finite count below 2^53 (a target of
    5e-324 m once made optimize answer 500 OverflowError)."""
    from shadowopt.service.map_sizing import MAX_TEXEL_ESTIMATE, texels_for_p95

    assert texels_for_p95(4.0, 1024 * 1024, 2.0) == 4 * 1024 * 1024
    assert texels_for_p95(100.0, 1024 * 1024, 5e-324) is None
    assert texels_for_p95(float("inf"), 1024, 1.0) is None
    assert texels_for_p95(1.0, int(MAX_TEXEL_ESTIMATE), 0.5) is None


def test_split_budget_follows_the_two_thirds_power_and_floors():
    from shadowopt.service.need import split_budget

    # Chong 2003's Lagrange allocation: T_i proportional to d_i^(2/3); hand-computed cubes give the exact shares,
    # and each is rounded down (floating point may put an exact share just below its integer: one texel less)
    def near(got, exact):
        return len(got) == len(exact) and all(0 <= e - g <= 1 for g, e in zip(got, exact))

    assert near(split_budget(1000, [8.0, 1.0], 1), [800, 200])
    assert near(split_budget(1400, [27.0, 8.0, 1.0], 1), [900, 400, 100])
    assert near(split_budget(1400, [27.0, None, 8.0, 1.0], 1), [900, 0, 400, 100])  # no map: no texels
    assert split_budget(11, [1.0, 1.0, 1.0], 4) == [3, 3, 3]  # whole texels, rounded down (never over)
    assert split_budget(12, [0.0, 0.0, None], 4) == [6, 6, 0]  # no edge anywhere: equal shares
    assert split_budget(12, [-3.0, 0.0], 4) == [6, 6]  # a negative estimate counts as none
    assert near(split_budget(1000, [8.0, -1.0], 1), [1000, 0])
    assert split_budget(1000, [None, None], 4) == [0, 0]
    assert split_budget(1000, [], 4) == []


def test_split_budget_never_exceeds_the_budget_and_ignores_the_probe_and_the_scale():
    from shadowopt.service.need import split_budget

    rng = random.Random(7)
    for _ in range(300):
        n = rng.randrange(1, 6)
        mis = [None if rng.random() < 0.2 else rng.choice([0.0, rng.uniform(0, 50), rng.uniform(0, 1e4)])
               for _ in range(n)]
        budget = rng.randrange(0, 1 << 24)
        out = split_budget(budget, mis, rng.choice([1, 64 * 64, 1024 * 1024]))
        active = [i for i, m in enumerate(mis) if m is not None]
        assert all(isinstance(t, int) and t >= 0 for t in out) and len(out) == n
        assert all(out[i] == 0 for i in range(n) if mis[i] is None)
        assert budget - len(active) < sum(out) <= budget or not active
        # d_i = M_i(probe) sqrt(probe): the probe and a common factor cancel in the shares
        for probe in (4, 123456):
            assert split_budget(budget, mis, probe) == out
        scaled = [None if m is None else 3.0 * m for m in mis]
        assert all(abs(a - b) <= 1 for a, b in zip(split_budget(budget, scaled, 4), out))


class _Cam:  # a camera away from the origin, looking along +z: a point's view depth is z + 7
    position = np.array([3.0, -2.0, -7.0])
    forward = np.array([0.0, 0.0, 1.0])


class _Cascade:
    face = None

    def __init__(self, lo, hi):
        self.split = (lo, hi)


def _count_by_hand(depths, slack, lo, hi):
    return sum(1 for d, s in zip(depths, slack) if d + s >= lo and d - s <= hi)


def test_receivers_per_cascade_is_the_depth_interval_overlap_count():

    from shadowopt.service.need import receivers_per_map

    rng = np.random.default_rng(3)
    depth = np.concatenate([rng.uniform(0, 40, 200), [10.0, 20.0, 0.0, 40.0]])  # some exactly on a split
    pts = np.stack([rng.uniform(-5, 5, len(depth)), rng.uniform(-5, 5, len(depth)), depth - 7.0], axis=1)
    slack = rng.uniform(0, 2, len(depth))
    slack[-4:] = 0.0
    maps = [_Cascade(0.0, 10.0), _Cascade(10.0, 20.0), _Cascade(20.0, 30.5), _Cascade(30.5, 40.0)]
    got = receivers_per_map(maps, pts, slack, _Cam())
    assert got.tolist() == [_count_by_hand(depth, slack, *m.split) for m in maps]
    zero = [_count_by_hand(depth, np.zeros_like(depth), *m.split) for m in maps]
    assert got.tolist() != zero  # the slack matters
    for no_slack in (None, slack[:-1]):  # none, or not one per receiver: no slack
        assert receivers_per_map(maps, pts, no_slack, _Cam()).tolist() == zero
    assert receivers_per_map(maps, pts[:0], slack[:0], _Cam()).tolist() == [0, 0, 0, 0]
    assert receivers_per_map([], pts, slack, _Cam()).tolist() == []


class _Face:
    def __init__(self, face, s, t, w):
        self.face, self._c = face, (np.asarray(s), np.asarray(t), np.zeros(len(s)), np.asarray(w))

    def map_coords(self, pts):
        return self._c


def test_receivers_per_face_are_those_inside_its_map_in_front():
    from shadowopt.service.need import receivers_per_map

    pts = np.zeros((6, 3))
    # s, t on the closed unit square count (edges included); w <= 0 is behind the light's face
    f0 = _Face(0, [0.0, 1.0, 0.5, 0.5, -1e-9, 0.5], [0.0, 1.0, 0.5, 1.0000001, 0.5, 0.5], [1, 1, 1, 1, 1, 0.0])
    f1 = _Face(1, [0.2] * 6, [0.3] * 6, [-1.0] * 6)
    f2 = _Face(2, [0.2] * 6, [0.3] * 6, [1e-12] * 6)
    assert receivers_per_map([f0, f1, f2], pts, None, _Cam()).tolist() == [3, 0, 6]


def _depth_points(*depths):
    return np.array([[0.0, 0.0, d - 7.0] for d in depths])


def test_dropped_cascades_give_their_range_to_a_kept_neighbour():
    from shadowopt.service.need import drop_empty_maps

    def run(depths, n=4):
        maps = [_Cascade(10.0 * k, 10.0 * (k + 1)) for k in range(n)]
        kept, notes = drop_empty_maps(maps, _depth_points(*depths), None, _Cam())
        return [m.split for m in kept], notes

    splits, notes = run([5.0, 35.0])  # cascades 1 and 2 hold nothing: cascade 0 takes their range
    assert splits == [(0.0, 30.0), (30.0, 40.0)] and len(notes) == 2
    assert notes[0].startswith("cascade 1 (view depth 10-20) dropped") and notes[1].startswith("cascade 2 (")
    splits, notes = run([15.0, 35.0])  # the first is empty: the next kept one takes it
    assert splits == [(0.0, 30.0), (30.0, 40.0)] and [n.split(" (")[0] for n in notes] == ["cascade 0", "cascade 2"]
    splits, notes = run([5.0, 15.0])  # the last ones empty
    assert splits == [(0.0, 10.0), (10.0, 40.0)] and len(notes) == 2
    assert run([5.0, 15.0, 25.0, 35.0]) == ([(0.0, 10.0), (10.0, 20.0), (20.0, 30.0), (30.0, 40.0)], [])
    assert run([100.0]) == ([(0.0, 10.0), (10.0, 20.0), (20.0, 30.0), (30.0, 40.0)], [])  # none served: kept
    assert run([100.0], n=1) == ([(0.0, 10.0)], [])
    assert run([15.0], n=2) == ([(0.0, 20.0)], [run([15.0], n=2)[1][0]])


def test_dropped_cube_faces_keep_the_others_untouched():
    from shadowopt.service.need import drop_empty_maps

    faces = [_Face(0, [0.5], [0.5], [1.0]), _Face(3, [0.5], [0.5], [-1.0]), _Face(4, [2.0], [0.5], [1.0])]
    kept, notes = drop_empty_maps(faces, np.zeros((1, 3)), None, _Cam())
    assert [f.face for f in kept] == [0] and len(notes) == 2
    assert notes[0].startswith("cube face 3 dropped") and notes[1].startswith("cube face 4 dropped")


def test_a_lights_need_counts_its_coarse_pixels_by_hand():
    from types import SimpleNamespace

    from shadowopt.service.need import light_need

    hit = np.array([[1, 1, 1, 1], [1, 1, 0, 0]], bool)
    in_light = np.array([[1, 1, 1, 0], [1, 0, 1, 1]], bool)  # in the cone (a miss does not count)
    facing = np.array([[1, 0, 1, 1], [1, 1, 1, 1]], bool)
    visible = np.array([[1, 0, 0, 1], [0, 0, 1, 1]], bool)
    light = SimpleNamespace(in_light=in_light, facing=facing, visible=visible)
    fine = SimpleNamespace(flat=np.arange(7), receiver=[np.array([1, 0, 1, 1, 0, 0, 0], bool)])
    buffers = SimpleNamespace(hit=hit, lights=[light, light], fine=fine)
    # seen = 6; in cone = hit & in_light = (0,0),(0,1),(0,2),(1,0) = 4; receivers also facing = (0,0),(0,2),(1,0)
    # = 3; lit = receivers & visible = (0,0) = 1
    need = light_need(buffers, 0)
    assert (need.seen, need.in_cone, need.receivers, need.lit, need.edge_points, need.edge_receivers) == (6, 4, 3, 1, 7, 3)
    assert need.shadowed == 2 and need.needs_map
    assert light_need(buffers, 1).edge_receivers == 0  # no edge-pass list for that light
    none = light_need(SimpleNamespace(hit=hit, lights=[light], fine=None), 0)
    assert (none.edge_points, none.edge_receivers) == (0, 0)
    j = need.to_json()
    assert (j["receiver_pixels"], j["lit_pixels"], j["shadowed_pixels"], j["edge_receivers"]) == (3, 1, 2, 3)


def test_a_light_needs_a_map_when_any_receiver_faces_it():
    from shadowopt.service.need import Need

    # a bool, as annotated (not a count that happens to be truthy)
    assert Need(10, 10, 0, 0, 5, 0).needs_map is False
    assert Need(10, 10, 0, 0, 5, 1).needs_map is True  # only an edge-pass receiver
    assert Need(10, 10, 1, 1, 0, 0).needs_map is True and Need(10, 10, 6, 1, 0, 3).needs_map is True
    assert Need(10, 10, 4, 1, 0, 0).shadowed == 3
