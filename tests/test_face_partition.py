"""Point lights by face partitioning (Lloyd et al. 2007 FP, FP+P, FP+LogP): solvers.face_partition's geometry and
the service's choice against the cube, checked against independent truths (the cube-map face rule, ray-traced
evaluation, light rays through the receivers)."""
from __future__ import annotations

import numpy as np
import pytest

from shadowopt.service.evaluation import evaluate_solution
from shadowopt.service.point_faces import face_shares
from shadowopt.service.solution_check import validate_solution
from shadowopt.service.request import SolveRequest
from shadowopt.service.solution_json import maps_from_solution
from shadowopt.service.solve import solve
from shadowopt.solvers.cameras import Camera
from shadowopt.solvers.face_partition import FACES, assign_receivers, face_frusta, fit_face
from shadowopt.solvers.light_frames import CUBE_FACES
from testkit import box, plane, scene_entry_of


@pytest.fixture(scope="module")
def scene():
    return scene_entry_of([plane(60), box([-0.2, 0, -0.2], [0.2, 0.3, 0.2]), box([-1, 0, 8], [1, 3, 10]),
                           box([3, 0, 20], [5, 6, 23])])


def rig(light_pos, camera, mode="auto", side=256):
    return {"camera": {"resolution": (320, 180), "fov_y_deg": 60, **camera},
            "lights": [{"type": "point", "position": light_pos}],
            "shadow": {"resolution": (side, side), "cascades": 1, "point_light_maps": mode}, "coarse_long_side": 120}


def test_receivers_go_to_the_face_whose_frustum_holds_them():
    rng = np.random.default_rng(3)
    light = np.array([1.0, 2.0, -3.0])
    pts = light + rng.normal(size=(4000, 3)) * rng.uniform(0.01, 50, size=(4000, 1))
    faces = assign_receivers(light, pts)
    got = np.concatenate(list(faces.values()))
    assert sorted(got.tolist()) == list(range(len(pts)))  # a partition: every receiver in exactly one face
    views, _, _ = face_frusta(light, pts, pts[:8])
    for face, idx in faces.items():
        v = pts[idx] @ views[face][:3, :3].T + views[face][:3, 3]
        d = -v[:, 2]
        # the OpenGL cube-map face's 90-degree frustum: in front of the light, |x|, |y| <= depth
        assert (d > 0).all() and (np.abs(v[:, :2]) <= d[:, None] * (1 + 1e-12)).all(), face
        fwd = np.array(CUBE_FACES[face][0], float)
        assert ((pts[idx] - light) @ fwd >= np.abs(pts[idx] - light).max(1) * (1 - 1e-12)).all()


def test_a_receiver_plane_seen_through_one_face_gets_exactly_one_map(scene):
    """Camera looking down at the ground under a point light 5 m up, 60 degree view from 3 m: every visible
    receiver's direction from the light is dominated by -y, so one map (the -y face), fitted to them."""
    r = rig((0.0, 5.0, 0.0), {"position": (0.0, 3.0, 0.0), "forward": (0.0, -1.0, 0.02), "near": 0.1, "far": 50})
    sol = solve(scene, r, SolveRequest("focused"))
    light = sol["lights"][0]
    fp = light["face_partitioning"]
    assert [f["face"] for f in fp["faces"]] == ["-y"]
    assert fp["chosen"] == "face_partitioning" and fp["variant"] == "FP"
    assert [c["face"] for c in light["cascades"]] == ["-y"]
    # the fitted face covers the receivers within a smaller angle than the 90-degree face: its objective is lower
    assert fp["objective"] < fp["returned_objective_otherwise"]
    validate_solution(sol, light_kinds=["point"])
    assert [m.face for m in maps_from_solution(sol)[0]] == ["-y"]
    ev = evaluate_solution(scene, r, sol, depth="ideal")
    assert ev["outside_pixels"] == 0


@pytest.mark.parametrize("method", ["focused", "lispsm"])
def test_face_partition_covers_every_receiver_ray_traced(scene, method):
    """A point light inside the view among boxes: forced face partitioning (FP, FP+P) leaves no ray-traced
    receiver pixel outside its map, and evaluate reads the per-face maps back from the solution."""
    r = rig((0.5, 2.0, 6.0), {"position": (0, 1.7, 0), "forward": (0, -0.15, 1.0), "near": 0.1, "far": 300},
            mode="face_partition")
    sol = solve(scene, r, SolveRequest(method))
    light = sol["lights"][0]
    fp = light["face_partitioning"]
    assert fp["chosen"] == "face_partitioning" and len(fp["faces"]) >= 3
    assert [c["face"] for c in light["cascades"]] == [f["face"] for f in fp["faces"]]
    assert [list(c["resolution"]) for c in light["cascades"]] == [f["resolution"] for f in fp["faces"]]
    assert sum(c["resolution"][0] * c["resolution"][1] for c in light["cascades"]) <= fp["total_texels"]
    ev = evaluate_solution(scene, r, sol, depth="ideal")
    assert ev["receiver_pixels"] > 1000 and ev["outside_pixels"] == 0


def test_the_cube_option_keeps_the_cube(scene):
    r = rig((0.5, 2.0, 6.0), {"position": (0, 1.7, 0), "forward": (0, -0.15, 1.0), "near": 0.1, "far": 300},
            mode="cube")
    light = solve(scene, r, SolveRequest("focused"))["lights"][0]
    assert "face_partitioning" not in light
    assert all(c["resolution"] == [256, 256] for c in light["cascades"])


@pytest.mark.parametrize("warp", ["perspective", "log"])
def test_a_warped_face_map_puts_each_receiver_on_its_own_light_ray(warp):
    """Independent of the fit's algebra: the texel ray through a receiver's map coordinates (the map's inverse,
    as the ground truth casts it) passes through the receiver and through the light, its depth range holds the
    receiver, and depth grows along the ray from the light to the receiver."""
    cam = Camera.look((0.0, 1.7, 0.0), (0.0, -0.2, 1.0), fov_y_deg=60.0, near=0.1, far=200.0, resolution=(1280, 720))
    rng = np.random.default_rng(1)
    pts = np.column_stack([rng.uniform(-8, 8, 3000), np.zeros(3000), rng.uniform(4, 60, 3000)])
    light = np.array([0.0, 30.0, 30.0])
    views, near, far = face_frusta(light, pts, pts[:8])
    idx = assign_receivers(light, pts)["-y"]
    smap = fit_face(cam, light, "-y", views["-y"], pts[idx], near, far, (512, 512), warp)
    assert smap.warp_kind == warp and smap.n_prime > 0
    s, t, z, w = smap.map_coords(pts[idx])
    assert (w > 0).all() and (s >= 0).all() and (s <= 1).all() and (t >= 0).all() and (t <= 1).all()
    assert (z > -1).all() and (z < 1).all()
    a, b = smap.texel_rays(s, t)
    ray = (b - a) / np.linalg.norm(b - a, axis=1, keepdims=True)
    off = pts[idx] - a
    dist = np.linalg.norm(off - (off * ray).sum(1, keepdims=True) * ray, axis=1)
    assert dist.max() < 1e-6 * np.linalg.norm(pts[idx] - light, axis=1).max()
    to_light = light - a
    assert (np.linalg.norm(to_light - (to_light * ray).sum(1, keepdims=True) * ray, axis=1) < 1e-5).all()
    half = light + 0.5 * (pts[idx] - light)
    assert (smap.map_coords(half)[2] < z).all()
    if warp == "log":  # the log step pads t after the warp, beyond the u range the depth is fitted to
        return
    # every texel ray's depth range holds [near, far] along the face axis, out to the map's padded border
    g = np.linspace(0.0, 1.0, 9)
    gs, gt = (v.ravel() for v in np.meshgrid(g, g))
    a, b = smap.texel_rays(gs, gt)
    depth = lambda p: -(p @ smap.view[2, :3] + smap.view[2, 3])  # noqa: E731 distance along the face axis
    assert (depth(a) <= near * (1 + 1e-9)).all() and (depth(b) >= far * (1 - 1e-9)).all()


def test_face_shares_split_by_need_with_a_floor_and_the_total():
    shares = face_shares(1_000_000, [100.0, 0.0, 800.0], 333_333)
    assert sum(shares) <= 1_000_000 and sum(shares) > 999_990
    assert shares[2] > shares[0] > shares[1] > 0
    assert shares[1] == int(0.25 * 1_000_000 / 3)  # the floor: a quarter of an equal share
    # the others by need: Chong 2003's L2 Lagrange allocation, T ~ d^(2/3)
    assert shares[2] / shares[0] == pytest.approx(8.0 ** (2 / 3), rel=1e-4)
    # equal need -> equal shares
    assert len(set(face_shares(600, [5.0, 5.0, 5.0], 200))) == 1
    assert FACES == tuple(CUBE_FACES)


def test_face_shares_split_by_need_above_a_quarter_of_an_equal_share():
    from shadowopt.service.point_faces import FLOOR_SHARE, face_shares

    def near(got, exact):
        return len(got) == len(exact) and all(0 <= e - g <= 1 for g, e in zip(got, exact))

    # floor = 1/4 of an equal share = int(1000 / 4 / 3) = 83; face 2 (no edge) gets it, the other two split the
    # remaining 917 as d^(2/3) = 4 : 1 -> 733.6, 183.4, rounded down
    assert FLOOR_SHARE == 0.25
    assert near(face_shares(1000, [8.0, 1.0, 0.0], 64), [733, 183, 83])
    assert near(face_shares(1000, [8.0, 1.0], 64), [800, 200])  # both above the floor (125): plain split
    assert face_shares(1200, [0.0, 0.0, 0.0], 64) == [400, 400, 400]  # no edges: equal shares
    # a face far below the floor is raised to it, and then a second one that the rest's split left below it
    out = face_shares(6000, [1000.0, 1.0, 0.001, 0.0, 0.0, 0.0], 64)
    floor = int(0.25 * 6000 / 6)
    assert out[2:] == [floor] * 4 and min(out) >= floor and sum(out) <= 6000
    assert out[0] > out[1] >= floor
    assert face_shares(100, [], 64) == []


def test_the_partitions_warp_and_the_objective_it_is_judged_by():
    import math

    from shadowopt.service.point_faces import variant_objective, warp_for

    assert warp_for("focused", False) == warp_for("focused", True) == "none"  # FP
    assert warp_for("".join(["focu", "sed"]), True) == "none"  # a method name read at run time: compared by value
    for method in ("lispsm", "logpsm", "optimized"):
        assert warp_for(method, False) == "perspective" and warp_for(method, True) == "log"  # FP+P, FP+LogP
    assert variant_objective({"objective": 2.5}) == 2.5 and variant_objective({"objective": 2.5, "unserved_samples": 0}) == 2.5
    for bad in ({"objective": None}, {}, {"objective": float("nan")}, {"objective": math.inf},
                {"objective": 1.0, "unserved_samples": 3}, {"objective": 1.0, "unserved_samples": 1}):
        assert variant_objective(bad) == math.inf, bad  # unknown, not finite, or leaving samples unserved: never chosen


def test_face_resolutions_split_the_texels_by_the_probed_need(monkeypatch):
    from types import SimpleNamespace

    from shadowopt.service import point_faces

    faces = [SimpleNamespace(face=0), SimpleNamespace(face=3)]
    monkeypatch.setattr(point_faces, "assign_receivers", lambda pos, rec: [[0], [1]])
    monkeypatch.setattr(point_faces, "partition_maps", lambda *a: (faces, [[0], [1]]))
    probes = []

    def maps_error(fp, samples, origin):
        probes.append(fp)
        return {}, [{"misclassified_pixels": 8.0}, {"misclassified_pixels": 1.0}]

    prob = SimpleNamespace(receivers=[0, 1], samples=None)
    res, mis = point_faces.face_resolutions(None, SimpleNamespace(position=None), prob, None, 50_000, maps_error, None)
    # shares 4 : 1 (d^(2/3) of 8 : 1) of 50,000 texels: 40,000 and 10,000 -> sides 200 and 100 (one less at most
    # when a share rounds down)
    assert mis == [8.0, 1.0] and len(probes) == 1
    assert res[0][0] in (199, 200) and res[3][0] in (99, 100) and res[0][0] == res[0][1]


def test_warp_axis_is_the_direction_the_view_depth_grows_along():
    """face_partition.warp_axis: the angle of the least-squares depth gradient in the (a, b) plane; None when
    the depth is flat. Receivers on a line b = 0 whose depth falls along +a: the axis points along -a (pi)."""
    import math

    from shadowopt.solvers.face_partition import warp_axis

    a = np.linspace(-1.0, 1.0, 9)
    ab = np.column_stack([a, np.zeros_like(a)])
    assert warp_axis(ab, 10.0 - 2.0 * a) == pytest.approx(math.pi)
    assert warp_axis(ab, 10.0 + 2.0 * a) == pytest.approx(0.0, abs=1e-12)
    ab2 = np.column_stack([a, a[::-1] * 0.5 + np.cos(3 * a)])
    g = np.array([0.3, -1.2])
    assert warp_axis(ab2, 4.0 + ab2 @ g) == pytest.approx(math.atan2(g[1], g[0]))
    assert warp_axis(ab, np.full(len(a), 10.0)) is None
