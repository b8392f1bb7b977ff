"""service.coarse_cache: the camera part of the coarse pass cached per tenant, scene entry and camera. A cached
re-solve after a light change must return what an uncached solve returns (render_coarse's buffers bit for
bit, the same matrices), and another tenant or a changed scene must never be served a cached camera pass."""
import json
from pathlib import Path

import numpy as np
import pytest

from shadowopt.api import schemas as S
from shadowopt.api.routes_solve import rig_dict
from shadowopt.renderers.coarse import render_coarse
from shadowopt.service import coarse_cache
from shadowopt.service.coarse_cache import CoarseCache, cached_coarse_pass
from shadowopt.service.pipeline import coarse_pass
from shadowopt.service.scenes import SceneCache
from shadowopt.service.request import SolveRequest
from shadowopt.service.solve import solve

from testkit import box, plane, scene_entry_of, sun

DEMO = Path(__file__).resolve().parents[1] / "configs" / "demo_scene.usda"


def demo_rig(az, coarse=96):  # the inspector's request (api/static/inspect/inspect.js rig())
    return rig_dict(S.OptimizeRequest(scene_id="x" * 12, rig={
        "camera": {"usd_path": "/World/Camera", "resolution": [640, 360]},
        "lights": [{"type": "directional", "direction": sun(az)}],
        "shadow": {"resolution": [2048, 2048], "cascades": 1}, "coarse_long_side": coarse}).rig)


def orbit_rig(az, coarse=64):
    return rig_dict(S.OptimizeRequest(scene_id="x" * 12, rig={
        "camera": {"position": [0.0, 12.0, 30.0], "target": [0.0, 0.0, 0.0], "fov_y_deg": 60, "near": 0.1,
                   "far": 200.0, "resolution": [320, 180]},
        "lights": [{"type": "directional", "direction": sun(az)}],
        "shadow": {"resolution": [1024, 1024], "cascades": 1}, "coarse_long_side": coarse}).rig)


def without_times(sol: dict) -> str:
    def strip(v):
        if isinstance(v, dict):
            return {k: strip(x) for k, x in v.items() if k not in ("timings_ms", "time_ms")}
        if isinstance(v, list):
            return [strip(x) for x in v]
        return v
    return json.dumps(strip(sol), sort_keys=True)


@pytest.fixture(scope="module")
def demo():
    return SceneCache().get(DEMO)


@pytest.fixture()
def cache(monkeypatch):
    c = CoarseCache()
    monkeypatch.setattr(coarse_cache, "COARSE", c)
    return c


def test_cached_buffers_equal_render_coarse_bit_for_bit(demo):
    c = CoarseCache()
    for az in (-120.0, 30.0, 95.0):  # one camera pass, three suns
        rig = demo_rig(az)
        _, ref = coarse_pass(demo, rig)
        _, got = cached_coarse_pass(demo, rig, "a", c)
        for k in ("hit", "position", "normal", "depth", "prim_id"):
            assert np.array_equal(getattr(ref, k), getattr(got, k), equal_nan=True), k
        for lr, lg in zip(ref.lights, got.lights, strict=True):
            for k in ("visible", "facing", "in_light", "boundary"):
                assert np.array_equal(getattr(lr, k), getattr(lg, k)), k
        for k in ("position", "normal", "depth", "flat", "traced"):
            assert np.array_equal(getattr(ref.fine, k), getattr(got.fine, k)), k
        assert len(got.fine.receiver) == 1 and np.array_equal(ref.fine.receiver[0], got.fine.receiver[0])
        assert ref.lights[0].visible.any() and not ref.lights[0].visible.all()
    assert (c.misses, c.hits) == (1, 2)


def test_cached_resolve_returns_the_same_matrices(demo, cache):
    first = solve(demo, demo_rig(-60.0), SolveRequest("optimized", cache_tenant="a"))  # fills the cache
    assert (cache.misses, cache.hits) == (1, 0)
    for az in (-60.0, 40.0):  # the same sun again (receivers memo), then a sun move (camera pass only)
        cached = solve(demo, demo_rig(az), SolveRequest("optimized", cache_tenant="a"))
        plain = solve(demo, demo_rig(az), SolveRequest("optimized"))
        assert without_times(cached) == without_times(plain)
        assert cached["lights"][0]["cascades"][0] == plain["lights"][0]["cascades"][0]
    assert (cache.misses, cache.hits) == (1, 2)
    assert cache.receiver_hits >= 1  # -60 twice: the same receiver mask
    assert without_times(first) != without_times(cached)  # the sun moved: other matrices


def test_another_tenant_or_a_changed_scene_misses(cache):
    def scene(x):
        return scene_entry_of([plane(60.0), box((x - 3.0, 0.0, -3.0), (x + 3.0, 8.0, 3.0))])

    one, moved = scene(0.0), scene(6.0)
    rig = orbit_rig(30.0)
    a = solve(one, rig, SolveRequest("focused", cache_tenant="a"))
    solve(one, orbit_rig(60.0), SolveRequest("focused", cache_tenant="a"))
    assert (cache.misses, cache.hits) == (1, 1)
    b = solve(one, rig, SolveRequest("focused", cache_tenant="b"))  # another tenant, the same scene object and rig
    assert (cache.misses, cache.hits) == (2, 1)
    assert without_times(a) == without_times(b)
    m = solve(moved, rig, SolveRequest("focused", cache_tenant="a"))  # a changed scene: its own camera pass
    assert (cache.misses, cache.hits) == (3, 1)
    assert without_times(m) == without_times(solve(moved, rig, SolveRequest("focused")))
    assert without_times(m) != without_times(a)
    again = scene(0.0)  # the same geometry reloaded: a new entry, never the old one's buffers
    solve(again, rig, SolveRequest("focused", cache_tenant="a"))
    assert (cache.misses, cache.hits) == (4, 1)
    _, ref = coarse_pass(moved, rig)
    assert not np.array_equal(ref.depth, render_coarse(one.rays, ref.camera, [], ref.width).depth)  # it did change


def test_the_cache_is_bounded(cache):
    small = CoarseCache(max_cameras=2)
    entry = scene_entry_of([plane(60.0), box((-3.0, 0.0, -3.0), (3.0, 8.0, 3.0))])
    for z in (30.0, 31.0, 32.0):
        rig = orbit_rig(30.0)
        rig["camera"]["position"] = [0.0, 12.0, z]
        cached_coarse_pass(entry, rig, "a", small)
    assert len(small) == 2 and small.misses == 3
