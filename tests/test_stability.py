"""Temporal stability (renderers.stability) against closed forms, stable CSM's snapping and coverage, and
`shadowopt bench path` on a short path."""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from shadowopt.solvers.cameras import Camera
from shadowopt.solvers.lights import DirectionalLight
from testkit import ground_samples

ROOT = Path(__file__).resolve().parents[1]
SCREEN = (240, 135)
SUN = [-0.45, -0.8, 0.4]


@pytest.fixture(scope="module")
def demo():
    from shadowopt.service.scenes import SceneCache
    from shadowopt.solvers.cameras import Camera
    from shadowopt.solvers.lights import DirectionalLight

    entry = SceneCache().get(ROOT / "configs" / "demo_scene.usda")
    light = DirectionalLight.make(SUN)
    cam = Camera.look_at([0.0, 1.7, 0.0], [0.0, 0.9, 20.0], fov_y_deg=60.0, near=0.1, far=300.0, resolution=SCREEN)
    return entry, light, cam


def _world_map(entry, light, cam, side=512):
    """One orthographic map on a world-fixed light view covering the whole scene, biased as the baselines."""
    from shadowopt.renderers.ground_truth import render_screen
    from shadowopt.solvers.depth_modes import with_bias
    from shadowopt.solvers.fitting import box_corners, depth_range, ortho, to_view
    from shadowopt.solvers.shadow_map import ShadowMap
    from shadowopt.solvers.stable_csm import world_light_view

    lo, hi = entry.loaded.geometry.bounds()
    view = world_light_view(light)
    v = to_view(view, box_corners(np.asarray(lo, float), np.asarray(hi, float)))
    tau = float((v[:, :2].max() - v[:, :2].min()) * 1.1 / side)  # texel size
    x0 = np.floor(v[:, 0].min() / tau - 4) * tau  # map edges on multiples of tau: a world-fixed grid
    y0 = np.floor(v[:, 1].min() / tau - 4) * tau
    near, far = depth_range(-v[:, 2], 0.01)
    smap = ShadowMap(view, ortho(x0, x0 + side * tau, y0, y0 + side * tau, near, far), (side, side),
                     light_depth=(near, far), warp_kind="none")
    smap.split = (0.0, cam.far)
    sb = render_screen(entry.rays, cam, light, shadow_rays=False)
    return with_bias(smap, sb.position[sb.hit & sb.facing], light), tau


def _shifted(smap, du: float, dv: float = 0.0):
    """The map moved by (du, dv) texels in the light's image plane (same texel size, depth and bias)."""
    P = smap.projection.copy()
    P[0, 3] -= 2.0 * du / smap.resolution[0]
    P[1, 3] -= 2.0 * dv / smap.resolution[1]
    return dataclasses.replace(smap, projection=P)


def test_snapped_map_under_a_translating_camera_neither_swims_nor_flickers(demo):
    """A map on a world-fixed texel grid, moved by whole texels (as a snapped map follows the camera),
    under a camera stepping sideways: every world point keeps its texel, so swim is 0 and no classification
    changes; the pairs are many pixels."""
    from shadowopt.renderers.stability import frame_pair_stability

    entry, light, cam = demo
    smap, _ = _world_map(entry, light, cam)
    cam_b = dataclasses.replace(cam, position=cam.position + np.array([0.37, 0.0, 0.21]))
    st = frame_pair_stability(entry.rays, cam, cam_b, light, [smap], [_shifted(smap, 3.0, -2.0)], SCREEN)
    assert st["pixels"] > 0.5 * SCREEN[0] * SCREEN[1] * 0.5
    assert st["swim_pixels"] == st["pixels"]
    assert st["swim_texels"] < 1e-6
    assert st["flicker"] == 0.0


def test_half_texel_shift_swims_half_a_texel_and_flickers_at_shadow_edges(demo):
    """The same camera, the map moved by half a texel along s: every point moves 0.5 texels modulo the grid
    (closed form), and points near shadow edges change their classification (flicker > 0), while the same
    maps twice give flicker 0 over the same pixels."""
    from shadowopt.renderers.ground_truth import evaluate_buffers
    from shadowopt.renderers.stability import frame_pair_stability

    entry, light, cam = demo
    smap, _ = _world_map(entry, light, cam, side=256)
    gt = evaluate_buffers(entry.rays, cam, light, [smap], SCREEN, depth="solution")
    half = frame_pair_stability(entry.rays, cam, cam, light, [smap], [_shifted(smap, 0.5)], SCREEN, gt_a=gt)
    assert half["swim_texels"] == pytest.approx(0.5, abs=1e-6)
    assert half["pixels"] == int(gt.receivers.sum())
    assert half["flicker"] > 0.0
    still = frame_pair_stability(entry.rays, cam, cam, light, [smap], [smap], SCREEN, gt_a=gt, gt_b=gt)
    assert still["pixels"] == half["pixels"]
    assert still["flicker"] == 0.0 and still["swim_texels"] == 0.0


@pytest.mark.parametrize("cascades", [1, 4])
def test_stable_csm_is_texel_snapped_and_covers_every_receiver_along_a_strafe(cascades):
    """stable_csm along the corpus's strafe path (street_canyon): swim 0 between frames (texel grid fixed in
    the world, same texel size), no receiver outside its cascade in any frame, and the world origin on a
    texel corner of every map."""
    from shadowopt.api.schemas import validate_rig
    from shadowopt.renderers.stability import path_stability
    from shadowopt.service.bench.path import frame_cameras, path_corpus
    from shadowopt.service.bench.definitions import corpus_scenes
    from shadowopt.service.rigs import resolve_rig
    from shadowopt.service.scenes import SceneCache
    from shadowopt.service.request import SolveRequest
    from shadowopt.service.solution_json import maps_from_solution
    from shadowopt.service.solve import solve

    spec = path_corpus()["paths"]["strafe"]
    scenes, _ = corpus_scenes([spec["scene"]])
    path, sspec = scenes[spec["scene"]]
    entry = SceneCache().get(Path(path))
    shadow = {"resolution": [256, 256], "cascades": 1} if cascades == 1 else {"texel_budget": 512 * 512, "cascades": 4}
    cams, maps = [], []
    for c in frame_cameras(spec, sspec["rigs"][spec["rig"]]["camera"], 3):
        rig = validate_rig({"camera": {**c, "resolution": list(SCREEN)},
                            "lights": [{"type": "directional", "direction": spec["sun"]}], "shadow": shadow})
        r = resolve_rig(rig, entry.loaded)
        cams.append(r.camera)
        light = r.lights[0]
        maps.append(maps_from_solution(solve(entry, rig, SolveRequest(method="stable_csm")))[0])
    assert [len(m) for m in maps] == [cascades] * 3
    for mp in maps:
        for smap in mp:
            s, t, _, _ = smap.map_coords(np.zeros((1, 3)))
            u = np.array([s[0] * smap.resolution[0], t[0] * smap.resolution[1]])
            assert np.abs(u - np.round(u)).max() < 1e-6
    st = path_stability(entry.rays, cams, light, maps, SCREEN)
    assert min(st["receivers"]) > 1000
    assert st["outside"] == [0, 0, 0]
    assert max(st["swim_texels"]) < 1e-6
    assert min(st["pixels"]) > 1000


def test_bench_path_runs_a_three_frame_path_without_writing(capsys):
    from shadowopt.api.cli import main

    before = (ROOT / "BENCHMARKS.md").read_text()
    assert main(["bench", "path", "--frames", "3", "--paths", "strafe", "--methods", "stable_csm,focused",
                 "--map", "256", "--screen", "240x135", "--no-write"]) == 0
    out = capsys.readouterr().out
    rows = [ln for ln in out.splitlines() if ln.startswith("| strafe |")]
    assert len(rows) == 4  # 2 cascade counts x 2 methods
    stable = [ln for ln in rows if "| stable_csm |" in ln]
    assert all(ln.split("|")[5].strip() == "0.000" for ln in stable)  # stable CSM does not swim
    assert (ROOT / "BENCHMARKS.md").read_text() == before


def test_stable_csm_cascade_bias_comes_from_its_own_depth_slice():
    """stable_csm's maps do not depend on the receivers (world-fixed spheres and grid); only each cascade's
    bias does, from the receivers in its view-depth slice (baselines' rule). Truth: cascade i's bias and depth
    block equal those of the same call given only the receivers of slice i, with the camera far from the world
    origin (position . forward = -60 m) so that depths measured from the wrong point pick other receivers."""
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


def test_stable_csm_slice_sphere_encloses_the_slice_and_touches_a_corner():
    """slice_sphere (Valient 2008): the bounding sphere of the view-frustum slice [z0, z1]. Truth: the slice's
    eight corners from the camera's field of view (depth z, +-z tan(fov_x / 2) right, +-z tan(fov_y / 2) up) lie
    inside it, and the farthest one lies on it (radius = the larger corner distance from the centre)."""
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


def test_stable_csm_takes_explicit_inner_splits_inside_its_shadow_distance():
    """stable_csm_maps(split_at=...) (splits "optimized": the split search's depths): the cascades end at the
    given inner depths, in order, whatever order they come in; a depth beyond the shadow distance is pulled
    just inside it (1e-6 of the span), and a wrong count or a non-finite depth is refused."""
    from shadowopt.solvers.fitting import box_corners
    from shadowopt.solvers.stable_csm import shadow_distance, stable_csm_maps

    cam = Camera.look([0, 2, 0], [0, -0.1, 1], near=0.1, far=300, resolution=(1280, 720))
    sun = DirectionalLight.make([-0.3, -0.8, 0.5])
    bounds = (np.array([-150.0, 0.0, -150.0]), np.array([150.0, 10.0, 150.0]))
    pts, _ = ground_samples(cam, far=150.0)
    maps = stable_csm_maps(cam, sun, pts, bounds, (512, 512), cascades=3, split_at=[40.0, 7.5])
    assert [m.split for m in maps] == [(0.0, 7.5), (7.5, 40.0), (40.0, 300.0)]
    dist = shadow_distance(cam, box_corners(*bounds))
    assert 40.0 < dist < 1e4
    maps = stable_csm_maps(cam, sun, pts, bounds, (512, 512), cascades=3, split_at=[10.0, 2 * dist])
    span = dist - cam.near
    assert maps[1].split == (10.0, pytest.approx(dist - 1e-6 * span, rel=1e-12))
    for bad in ([10.0], [10.0, np.nan]):
        with pytest.raises(ValueError, match="split_at: need 2 finite inner split depths"):
            stable_csm_maps(cam, sun, pts, bounds, (512, 512), cascades=3, split_at=bad)
