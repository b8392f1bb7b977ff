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


class _Entry:
    """A stand-in scene entry (the cache holds it weakly and passes .rays to camera_pass)."""

    def __init__(self, name):
        self.rays = name


@pytest.fixture
def traced(monkeypatch):
    """coarse_cache.camera_pass replaced by a recorder: each call is one trace, a new pass object."""
    from types import SimpleNamespace

    from shadowopt.service import coarse_cache

    calls = []

    def fake(rays, camera, long_side):
        calls.append((rays, long_side))
        return SimpleNamespace(n=len(calls))

    monkeypatch.setattr(coarse_cache, "camera_pass", fake)
    return calls


def _cam(**kw):
    from shadowopt.solvers.cameras import Camera

    args = dict(position=(1.0, 2.0, 3.0), forward=(0.0, -0.2, 1.0), up=(0.0, 1.0, 0.0), fov_y_deg=60.0,
                near=0.1, far=500.0, resolution=(640, 360))
    args.update(kw)
    return Camera.look(**args)


def test_camera_cache_hits_only_the_same_tenant_entry_camera_and_sizes(traced):

    from shadowopt.service.coarse_cache import CoarseCache

    cache = CoarseCache(max_cameras=64)
    entry, other = _Entry("e"), _Entry("o")
    first = cache.camera_pass("t", entry, _cam(), 96, 1)
    assert cache.camera_pass("t", entry, _cam(), 96, 1) is first  # an equal camera built again: a hit
    assert (cache.hits, cache.misses, len(traced)) == (1, 1, 1)
    x = np.nextafter(1.0, 2.0)  # one ulp: the key is exact
    variants = [("u", entry, _cam(), 96, 1), ("t", other, _cam(), 96, 1), ("t", entry, _cam(), 97, 1),
                ("t", entry, _cam(), 96, 2), ("t", entry, _cam(position=(x, 2.0, 3.0)), 96, 1),
                ("t", entry, _cam(forward=(0.0, -0.21, 1.0)), 96, 1), ("t", entry, _cam(up=(0.1, 1.0, 0.0)), 96, 1),
                ("t", entry, _cam(fov_y_deg=61.0), 96, 1), ("t", entry, _cam(near=0.2), 96, 1),
                ("t", entry, _cam(far=400.0), 96, 1), ("t", entry, _cam(resolution=(640, 480)), 96, 1),
                ("t", entry, _cam(resolution=(320, 180)), 96, 1)]
    passes = [cache.camera_pass(*v) for v in variants]
    assert cache.misses == 1 + len(variants) and cache.hits == 1 and len(traced) == 1 + len(variants)
    assert len({id(p) for p in passes + [first]}) == len(variants) + 1
    assert traced[1] == ("e", 96) and traced[2] == ("o", 96) and traced[3] == ("e", 97)  # the entry's own rays
    for v, p in zip(variants, passes):  # and each is a hit the second time
        assert cache.camera_pass(*v) is p
    assert cache.hits == 1 + len(variants)


def test_camera_cache_is_least_recently_used(traced):
    from shadowopt.service.coarse_cache import CoarseCache

    cache = CoarseCache(max_cameras=2)
    e = _Entry("e")
    a, b, c = _cam(near=0.1), _cam(near=0.2), _cam(near=0.3)
    seq = [(a, "miss"), (b, "miss"), (a, "hit"), (c, "miss"),  # c evicts b, the least recently used
           (a, "hit"), (c, "hit"), (b, "miss"), (a, "miss"), (b, "hit")]
    for cam, want in seq:
        h = cache.hits
        cache.camera_pass("t", e, cam, 96, 1)
        assert ("hit" if cache.hits > h else "miss") == want
        assert len(cache) <= 2


def test_a_dropped_scene_entry_leaves_the_cache(traced):
    import gc

    from shadowopt.service.coarse_cache import CoarseCache

    cache = CoarseCache(max_cameras=8)
    gone, kept = _Entry("g"), _Entry("k")
    cache.camera_pass("t", gone, _cam(), 96, 1)
    cache.camera_pass("t", kept, _cam(), 96, 1)
    del gone
    gc.collect()
    cache.camera_pass("t", kept, _cam(near=0.5), 96, 1)  # the next miss sweeps dead entries
    assert len(cache) == 2
    assert cache.camera_pass("t", kept, _cam(), 96, 1) is not None and cache.hits == 1


def test_receivers_memo_counts_hits_and_misses_exactly_and_keeps_eight_masks():
    import threading
    from collections import OrderedDict
    from types import SimpleNamespace


    from shadowopt.service.coarse_cache import MAX_RECEIVER_MASKS, CoarseCache

    cache = CoarseCache()
    # a pass whose camera-only receiver part is already made (service.solve.receiver_prep: not called here)
    cp = SimpleNamespace(lock=threading.Lock(), receivers=OrderedDict(), receiver_prep=object(),
                         receiver_misses=0)
    computed = []

    def compute(camera, buffers, mask, bounds, fine, **prep):
        computed.append((mask.copy(), None if fine is None else list(fine)))
        return np.arange(3.0) + len(computed), np.zeros(3)

    m1 = np.zeros((4, 4), bool)
    m2 = m1.copy()
    m2[1, 2] = True
    got = cache.receivers(cp, compute, None, None, m1, None, None)
    assert cache.receivers(cp, compute, None, None, m1.copy(), None, None) is got  # equal mask: the memo
    assert not got[0].flags.writeable and not got[1].flags.writeable  # shared: read-only
    cache.receivers(cp, compute, None, None, m2, None, None)
    cache.receivers(cp, compute, None, None, m1, None, [True, False])
    cache.receivers(cp, compute, None, None, m1, None, [True, False, False])  # same packed bits, other length
    cache.receivers(cp, compute, None, None, m1, None, [True, False])
    assert (cache.receiver_hits, cache.receiver_misses, len(computed)) == (2, 4, 4)
    for k in range(MAX_RECEIVER_MASKS + 1):  # more distinct masks than kept: the oldest go first
        m = np.zeros((4, 4), bool)
        m.flat[k] = True
        m.flat[15] = True
        cache.receivers(cp, compute, None, None, m, None, None)
    assert len(cp.receivers) == MAX_RECEIVER_MASKS and cache.receiver_misses == 4 + MAX_RECEIVER_MASKS + 1
    n = len(computed)
    cache.receivers(cp, compute, None, None, m, None, None)  # the newest is kept
    assert len(computed) == n
    m_first = np.zeros((4, 4), bool)
    m_first.flat[0] = True
    m_first.flat[15] = True
    cache.receivers(cp, compute, None, None, m_first, None, None)  # the oldest of the nine was dropped
    assert len(computed) == n + 1


def test_a_camera_pass_reports_its_own_trace_time_in_milliseconds():
    import time

    from shadowopt.service.coarse_cache import camera_pass
    from testkit import box, plane, scene_entry_of

    entry = scene_entry_of([plane(20.0), box((-1.0, 0.0, -1.0), (1.0, 2.0, 1.0))])
    t0 = time.perf_counter()
    cp = camera_pass(entry.rays, _cam(position=(0.0, 4.0, -8.0), forward=(0.0, -0.4, 1.0)), 32)
    wall_ms = (time.perf_counter() - t0) * 1e3
    assert 0.0 < cp.trace_ms <= wall_ms  # a part of the call's own wall time, in ms (the timings' camera_cached_ms)
    assert cp.hit.any() and cp.hit.shape == (cp.height, cp.width)


def test_the_light_parts_timings_are_milliseconds_that_add_up():
    import time

    from shadowopt.api import schemas as S
    from shadowopt.api.routes_solve import rig_dict
    from shadowopt.service.coarse_cache import CoarseCache, cached_coarse_pass
    from testkit import box, plane, scene_entry_of

    entry = scene_entry_of([plane(20.0), box((-1.0, 0.0, -1.0), (1.0, 2.0, 1.0))])
    rig = rig_dict(S.OptimizeRequest(scene_id="x" * 12, rig={
        "camera": {"position": [0.0, 6.0, -10.0], "target": [0.0, 0.0, 0.0], "resolution": [320, 180]},
        "lights": [{"type": "directional", "direction": [0.3, -1.0, 0.2]}],
        "shadow": {"resolution": [512, 512], "cascades": 1}, "coarse_long_side": 48}).rig)
    cache = CoarseCache()
    cached_coarse_pass(entry, rig, "t", cache)  # the camera pass
    t0 = time.perf_counter()
    _, buffers = cached_coarse_pass(entry, rig, "t", cache)  # a hit: only the light part runs
    wall_ms = (time.perf_counter() - t0) * 1e3
    t = buffers.timings_ms
    assert cache.hits == 1 and t["trace"] > 0 and t["convert"] > 0
    assert t["trace"] + t["convert"] == pytest.approx(t["total"], rel=1e-9, abs=1e-9)  # its parts, in ms
    assert t["total"] <= wall_ms
