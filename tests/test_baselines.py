"""Baselines: geometry against closed forms, the classic ordering, and the hard cases end to end
(service solve -> ground-truth evaluation with exact ray-traced visibility)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from shadowopt.renderers.ray_scene import build_ray_scene
from shadowopt.renderers.scene_data import LoadedScene, SceneGeometry
from shadowopt.service.evaluation import evaluate_solution
from shadowopt.service.scenes import SceneEntry
from shadowopt.service.solve import maps_from_solution, solve
from shadowopt.solvers.baselines import baseline
from shadowopt.solvers.cameras import Camera
from shadowopt.solvers.cascades import allocate, split_depths
from shadowopt.solvers.fitting import min_area_rectangle
from shadowopt.solvers.frames import stage_to_world
from shadowopt.solvers.lights import DirectionalLight
from shadowopt.solvers.metric import predicted_error
from shadowopt.solvers.samples import Samples, pixel_derivatives

METHODS = ("uniform", "focused", "lispsm", "logpsm")


def test_min_area_rectangle_beats_every_rotation():
    rng = np.random.default_rng(3)
    for _ in range(5):
        p = rng.normal(size=(200, 2)) * rng.uniform(0.1, 5, 2)
        ang, lo, hi = min_area_rectangle(p)
        area = np.prod(hi - lo)
        for a in np.linspace(0, np.pi, 360):
            c, s = np.cos(a), np.sin(a)
            r = p @ np.array([[c, -s], [s, c]])
            assert area <= np.prod(r.max(0) - r.min(0)) * (1 + 1e-9)
    a = 0.7
    corners = np.array([[-3, -1], [3, -1], [3, 1], [-3, 1.0]]) @ np.array([[np.cos(a), np.sin(a)], [-np.sin(a), np.cos(a)]])
    _, lo, hi = min_area_rectangle(corners)
    assert np.prod(hi - lo) == pytest.approx(12.0)


def test_split_formulas():
    z = split_depths(1, 1000, 3, "log")
    assert np.allclose(z, [1, 10, 100, 1000])  # n (f/n)^(i/k), Lloyd eqs. 80-82
    assert np.allclose(split_depths(1, 1000, 3, "practical", 0.0), [1, 334, 667, 1000])
    assert np.allclose(split_depths(1, 1000, 3, "practical", 1.0), z)
    r = allocate(np.array([2.0, 1.0]), np.array([1.0, 1.0]), 3 * 512 * 512)
    assert r[0][0] * r[0][1] == pytest.approx(2 * r[1][0] * r[1][1], rel=0.01)  # σ_i ∝ S_i (eq. 83)


def ground_samples(cam, far=150.0):
    d = cam.ray_directions(96, 54).reshape(-1, 3)
    t = -cam.position[1] / d[:, 1]
    ok = (t > 0) & (t < far)
    pts = cam.position + t[ok, None] * d[ok]
    n = np.tile([0, 1.0, 0], (len(pts), 1))
    dx, dy, dep = pixel_derivatives(cam, pts, n)
    return pts, Samples(pts, n, dx, dy, dep, np.ones(len(pts)), np.zeros((len(pts), 2), int), "all_facing")


def test_classic_ordering_for_an_overhead_sun():
    cam = Camera.look_at([0, 2, 0], [0, 0, 30], near=0.1, far=200, resolution=(1280, 720))
    pts, s = ground_samples(cam)
    bounds = (np.array([-150, 0, -150.0]), np.array([150, 10, 150.0]))
    err = {m: predicted_error(baseline(m, cam, DirectionalLight.make([0, -1, 0]), pts, bounds), s)["objective"]
           for m in METHODS}
    assert err["logpsm"] < err["lispsm"] < err["focused"] < err["uniform"]


def test_lispsm_warp_distance_for_an_overhead_light_is_the_closed_form():
    # Camera looking horizontally, light straight down: sin γ = 1 and n' = z_n + sqrt(z_n z_f).
    cam = Camera.look([0, 2, 0], [0, 0, 1], near=0.1, far=200, resolution=(1280, 720))
    pts, _ = ground_samples(cam)
    m = baseline("lispsm", cam, DirectionalLight.make([0, -1, 0]), pts, None)[0]
    depth = (pts - cam.position) @ cam.forward
    zn, zf = depth.min(), depth.max()
    assert m.warp_kind == "perspective" and m.n_prime == pytest.approx(zn + math.sqrt(zn * zf))


def entry_from(parts, cameras=(), lights=()) -> SceneEntry:
    verts, faces, prims, off = [], [], [], 0
    for k, (v, f) in enumerate(parts):
        verts.append(np.asarray(v, float))
        faces.append(np.asarray(f) + off)
        prims.append(np.full(len(f), k))
        off += len(v)
    g = SceneGeometry(np.vstack(verts), np.vstack(faces).astype(np.int32), np.concatenate(prims).astype(np.int32),
                      [f"/p{k}" for k in range(len(parts))])
    loaded = LoadedScene("mem", "hash", g, list(cameras), list(lights), "Y", 1.0, stage_to_world("Y", 1.0), None)
    return SceneEntry(loaded, build_ray_scene(g), 0.0, 0.0)


def plane(size, off=(0, 0, 0)):
    return (np.array([[-size, 0, -size], [size, 0, -size], [size, 0, size], [-size, 0, size]]) + off,
            np.array([[0, 2, 1], [0, 3, 2]]))


def box(lo, hi):
    v = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])], float)
    f = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                  [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    return v, f


def scene(off=(0.0, 0.0, 0.0)):
    o = np.asarray(off)
    return entry_from([plane(100, o), box(o + [-1, 0, 8], o + [1, 3, 10]), box(o + [3, 0, 20], o + [5, 6, 23])])


def rig(camera, light, res=512, **shadow):
    return {"camera": {"resolution": (320, 180), "fov_y_deg": 60, **camera}, "lights": [light],
            "shadow": {"resolution": (res, res), "cascades": 1, "splits": "practical", "lambda": 0.5, **shadow},
            "output": {"convention": "opengl", "layout": "column_major", "frame": "world"}, "frame": "world",
            "coarse_long_side": 120}


CAM = {"position": (0, 1.7, 0), "forward": (0, -0.15, 1.0), "near": 0.1, "far": 300}
HARD = {
    "light_along_view": (CAM, {"type": "directional", "direction": tuple(
        np.array([0, -0.15, 1.0]) / np.linalg.norm([0, -0.15, 1.0]) + [0, -0.01, 0.005])}),
    "light_against_view": (CAM, {"type": "directional", "direction": (0.005, 0.16, -1.0)}),
    "light_behind_camera": (CAM, {"type": "directional", "direction": (0.1, -0.5, 1.0)}),
    "grazing_1deg": (CAM, {"type": "directional", "direction": (0.6, -math.tan(math.radians(1)), 0.8)}),
    "point_in_view": (CAM, {"type": "point", "position": (0.5, 4.0, 14.0)}),
    "spot_in_view": (CAM, {"type": "spot", "position": (0.0, 5.0, 12.0), "direction": (0.0, -1.0, 0.2), "cone_deg": 40}),
    "f_over_n_1e5": ({**CAM, "near": 0.003, "far": 300}, {"type": "directional", "direction": (-0.3, -0.8, 0.5)}),
    "f_over_n_10": ({**CAM, "near": 3.0, "far": 30}, {"type": "directional", "direction": (-0.3, -0.8, 0.5)}),
    "no_receiver": ({**CAM, "forward": (0, 1, 0.2)}, {"type": "directional", "direction": (-0.3, -0.8, 0.5)}),
}


@pytest.mark.parametrize("case", sorted(HARD))
@pytest.mark.parametrize("method", METHODS)
def test_hard_cases_give_finite_maps_that_keep_every_receiver(case, method):
    cam, light = HARD[case]
    entry = scene()
    r = rig(cam, light)
    sol = solve(entry, r, method)
    for maps in maps_from_solution(sol):
        for m in maps:
            assert np.all(np.isfinite(m.matrix)), (case, method)
    res = evaluate_solution(entry, r, sol, screen=(320, 180))
    # Maps are fit to the coarse receivers extended by 1.5 coarse pixels along their planes; a surface
    # seen as a sliver thinner than a coarse pixel can still lose a pixel (the light-against-view case
    # loses 1 of 138 on a box face 0.3 degrees from edge-on to the light).
    assert res["outside_pixels"] <= 0.01 * res["receiver_pixels"], (case, method, res)
    if case == "no_receiver":
        assert res["receiver_pixels"] == 0


@pytest.mark.parametrize("method", METHODS)
def test_scene_far_from_the_origin_and_one_triangle(method):
    off = (1e5, 0.0, -1e5)
    entry = scene(off)
    c = {**CAM, "position": tuple(np.add(CAM["position"], off))}
    r = rig(c, {"type": "directional", "direction": (-0.3, -0.8, 0.5)})
    res = evaluate_solution(entry, r, solve(entry, r, method), screen=(320, 180))
    assert res["outside_pixels"] == 0 and res["misclassified_fraction"] < 0.01
    tri = entry_from([(np.array([[-5, 0, 5], [5, 0, 5], [0, 0, 15.0]]), np.array([[0, 2, 1]]))])
    r = rig(CAM, {"type": "directional", "direction": (-0.3, -0.8, 0.5)})
    res = evaluate_solution(tri, r, solve(tri, r, method), screen=(320, 180))
    assert res["outside_pixels"] == 0 and res["misclassified_pixels"] == 0 and res["receiver_pixels"] > 0


@pytest.mark.parametrize("splits", ["uniform", "log", "practical"])
def test_cascades_cover_the_view_and_shrink_the_error(splits):
    entry = scene()
    light = {"type": "directional", "direction": (-0.3, -0.8, 0.5)}
    one = solve(entry, rig(CAM, light), "focused")
    three = solve(entry, rig(CAM, light, cascades=3, splits=splits), "focused")
    maps = maps_from_solution(three)[0]
    assert len(maps) == 3 and maps[0].split[0] == 0.0
    assert all(a.split[1] == pytest.approx(b.split[0]) for a, b in zip(maps, maps[1:]))
    assert three["lights"][0]["predicted_error"]["objective"] < one["lights"][0]["predicted_error"]["objective"]
    assert evaluate_solution(entry, rig(CAM, light, cascades=3, splits=splits), three, screen=(320, 180))["outside_pixels"] == 0


def test_texel_budget_allocation_spends_the_budget():
    entry = scene()
    r = rig(CAM, {"type": "directional", "direction": (-0.3, -0.8, 0.5)}, cascades=3)
    r["shadow"].pop("resolution")
    r["shadow"]["texel_budget"] = 3 * 512 * 512
    maps = maps_from_solution(solve(entry, r, "focused"))[0]
    total = sum(m.resolution[0] * m.resolution[1] for m in maps)
    assert 0.9 * 3 * 512 * 512 <= total <= 3 * 512 * 512
    assert maps[0].resolution[0] * maps[0].resolution[1] != maps[2].resolution[0] * maps[2].resolution[1]


def test_auto_cascades_pick_the_smallest_k_meeting_the_target():
    entry = scene()
    light = {"type": "directional", "direction": (-0.3, -0.8, 0.5)}
    errs = [solve(entry, rig(CAM, light, cascades=k), "focused")["lights"][0]["predicted_error"]["p95_m"]
            for k in (1, 2, 3)]
    target = (errs[1] + errs[0]) / 2 if errs[1] < errs[0] else errs[1] * 1.01
    r = rig(CAM, light, cascades="auto", max_cascades=3, target_p95_m=target)
    sol = solve(entry, r, "focused")
    auto = sol["lights"][0]["auto_cascades"]
    expected = next(k for k, e in zip((1, 2, 3), errs) if e <= target)
    assert auto["chosen"] == expected == len(sol["lights"][0]["cascades"])
    assert [t["cascades"] for t in auto["tried"]] == list(range(1, expected + 1))
