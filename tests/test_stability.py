"""Temporal stability (renderers.stability) against closed forms, stable CSM's snapping and coverage, and
`shadowopt bench path` on a short path."""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

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
