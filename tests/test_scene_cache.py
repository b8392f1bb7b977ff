"""The scene cache (service.scenes.SceneCache) with real USD files: single flight, failures not cached,
a per-tenant share (one tenant's uploads cannot push out another's scene), and the byte bound."""
from __future__ import annotations

import threading
from pathlib import Path

import pytest

from shadowopt.renderers.scene_data import SceneError
from shadowopt.renderers.usd_loader import load_scene
from shadowopt.service import isolation
from shadowopt.service.hostile_corpus import instanced_spheres, tiny_scene
from shadowopt.service.scenes import BYTES_FACTOR, LoadLimits, SceneCache, entry_bytes

BIG = 1 << 40


def write(folder: Path, name: str, text: str) -> Path:
    p = folder / name
    p.write_text(text)
    return p


def tinies(folder: Path, n: int, start: int = 0) -> list[Path]:
    return [write(folder, f"tiny{i}.usda", tiny_scene(i)) for i in range(start, start + n)]


def concurrently(n: int, fn) -> list:
    """fn() on n threads released together; each one's result or exception."""
    barrier = threading.Barrier(n)
    out = [None] * n

    def run(i):
        barrier.wait()
        try:
            out[i] = fn()
        except BaseException as e:  # noqa: BLE001 - the test looks at it
            out[i] = e

    threads = [threading.Thread(target=run, args=(i,)) for i in range(n)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=120)
    return out


def test_concurrent_gets_of_one_scene_share_one_isolated_load(tmp_path):
    """Six requests for a scene not yet cached: one child process loads it, all six get that entry."""
    path = write(tmp_path, "scene.usda", tiny_scene(1))
    cache = SceneCache()
    jobs = isolation.STATS["jobs"]
    got = concurrently(6, lambda: cache.get(path, sandbox=True, tenant="alice", limits=LoadLimits()))
    assert all(not isinstance(g, BaseException) for g in got), got
    assert all(g is got[0] for g in got)
    assert isolation.STATS["jobs"] - jobs == 1  # child processes that ran a load: one
    assert cache.stats()["loads"] == 1 and cache.stats()["shared"] == 5
    assert cache.get(path, sandbox=True, tenant="alice", limits=LoadLimits()) is got[0]  # then a hit
    assert cache.peek(path, sandbox=True, tenant="alice", limits=LoadLimits()) is got[0]
    assert cache.peek(path) is None  # other options: another key, and peek never loads
    assert isolation.STATS["jobs"] - jobs == 1
    assert got[0].loaded.geometry.triangle_count == load_scene(path, sandbox=True).geometry.triangle_count


def test_a_failed_load_reaches_every_waiter_and_is_not_cached(tmp_path):
    bad = tmp_path / "broken.usda"
    bad.write_bytes(b"#usda 1.0\n(\n def Mesh \"M\" {{{ \x00\xff")
    cache = SceneCache()
    jobs = isolation.STATS["jobs"]
    got = concurrently(4, lambda: cache.get(bad, sandbox=True, tenant="bob", limits=LoadLimits()))
    assert all(isinstance(g, SceneError) for g in got), got
    assert len({(g.code, g.message) for g in got}) == 1 and got[0].code in ("corrupt", "not_usd")
    assert str(tmp_path) not in got[0].message
    assert isolation.STATS["jobs"] - jobs == 1 and cache.stats()["loads"] == 1
    with pytest.raises(SceneError):  # the next get tries again (a new load), nothing was kept
        cache.get(bad, sandbox=True, tenant="bob", limits=LoadLimits())
    assert isolation.STATS["jobs"] - jobs == 2 and cache.stats()["entries"] == 0
    # the same file repaired: it loads (the key follows the file's size and mtime)
    bad.write_text(tiny_scene(2))
    assert cache.get(bad, sandbox=True, tenant="bob").loaded.geometry.triangle_count > 0


def test_a_missing_file_names_no_server_path(tmp_path):
    with pytest.raises(SceneError) as e:
        SceneCache().get(tmp_path / "gone" / "x.usda")
    assert e.value.code == "not_found" and str(tmp_path) not in e.value.message and "x.usda" in e.value.message


def test_eight_tiny_uploads_by_one_tenant_do_not_evict_another_tenants_scene(tmp_path):
    """The issue's eviction attack, with the shipped shape (8 entries, half each per tenant)."""
    cache = SceneCache(capacity=8, max_bytes=BIG, tenant_share=0.5)
    bobs = write(tmp_path, "bob.usda", tiny_scene(100))
    bob_entry = cache.get(bobs, sandbox=True, tenant="bob")
    alices = tinies(tmp_path, 8)
    for p in alices:
        cache.get(p, sandbox=True, tenant="alice")
    st = cache.stats()
    assert st["owners"]["alice"][0] == 4 and st["owners"]["bob"][0] == 1
    assert cache.owner_of(bobs, sandbox=True) == "bob"
    assert cache.get(bobs, sandbox=True, tenant="bob") is bob_entry  # a hit: not reloaded
    assert cache.stats()["loads"] == 9
    # alice lost her own oldest four, and keeps the four most recent
    kept = [p for p in alices if _cached(cache, p)]
    assert kept == alices[4:]


def _cached(cache: SceneCache, p: Path) -> bool:
    try:
        cache.owner_of(p, sandbox=True)
        return True
    except KeyError:
        return False


def test_a_tenant_loses_its_least_recently_used_entry_first(tmp_path):
    cache = SceneCache(capacity=6, max_bytes=BIG, tenant_share=0.5)  # 3 each
    a = tinies(tmp_path, 4)
    for p in a[:3]:
        cache.get(p, tenant="alice")
    cache.get(a[0], tenant="alice")  # a[0] used again: a[1] is now the oldest
    cache.get(a[3], tenant="alice")
    assert [_cached_plain(cache, p) for p in a] == [True, False, True, True]


def test_the_cli_and_warm_up_are_their_own_owner(tmp_path):
    cache = SceneCache(capacity=4, max_bytes=BIG, tenant_share=0.5)
    mine = write(tmp_path, "operator.usda", tiny_scene(50))
    cache.get(mine)  # tenant=None
    for p in tinies(tmp_path, 5):
        cache.get(p, tenant="alice")
    assert cache.owner_of(mine) is None
    assert cache.stats()["owners"] == {None: (1, cache.stats()["owners"][None][1]),
                                       "alice": (2, cache.stats()["owners"]["alice"][1])}


def test_the_cache_is_bounded_in_bytes(tmp_path):
    """Entries of the 20-instance and tiny scenes: what is cached never exceeds max_bytes, the oldest go
    first, and an entry bigger than a tenant's share of the bytes is served but not kept."""
    big = write(tmp_path, "spheres20.usda", instanced_spheres(20))
    small = tinies(tmp_path, 3)
    probe = SceneCache()
    e_big = probe.get(big)
    e_small = probe.get(small[0])
    # the estimate is the geometry arrays' nbytes times the measured factor (an independent sum here)
    g = e_big.loaded.geometry
    assert e_big.nbytes >= BYTES_FACTOR * (g.vertices.nbytes + g.faces.nbytes + g.face_prim.nbytes)
    assert e_big.nbytes == entry_bytes(e_big.loaded) and e_big.nbytes > 20 * e_small.nbytes

    limit = e_big.nbytes + 2 * e_small.nbytes + 100  # room for the big one and two small ones
    cache = SceneCache(capacity=100, max_bytes=limit, tenant_share=1.0)
    cache.get(big, tenant="alice")
    for p in small:
        cache.get(p, tenant="bob")
        assert cache.stats()["bytes"] <= limit
    # the third small one pushed out the oldest entry, the big one; the small ones all fit
    assert not _cached_plain(cache, big) and all(_cached_plain(cache, p) for p in small)

    shared = SceneCache(capacity=100, max_bytes=limit, tenant_share=0.5)  # big > half of the bytes
    for p in small[:2]:
        shared.get(p, tenant="bob")
    e = shared.get(big)  # the CLI's, warm-up's or a batch worker's (no tenant): served...
    assert e.loaded.geometry.triangle_count == g.triangle_count
    assert not _cached_plain(shared, big) and all(_cached_plain(shared, p) for p in small[:2])  # ...not kept


def test_a_tenants_scene_over_its_cache_share_is_refused_once_and_not_reloaded(tmp_path, monkeypatch):
    """Review item 6: such a scene was served uncached, i.e. fully reloaded (isolated load + Mitsuba build)
    on every request. Now: SceneError too_large_for_cache naming the two settings and the sizes, no path,
    no Mitsuba build, and the next request is refused without a load."""
    from shadowopt.service import scenes

    big = write(tmp_path, "spheres20.usda", instanced_spheres(20))
    small = write(tmp_path, "small.usda", tiny_scene(7))
    need = SceneCache().get(big).nbytes
    share_bytes = need - 1000  # the share one byte-bound tenant may hold, just under the scene's estimate
    cache = SceneCache(capacity=100, max_bytes=2 * share_bytes, tenant_share=0.5)
    builds = []
    real_build = scenes.build_ray_scene
    monkeypatch.setattr(scenes, "build_ray_scene", lambda geom: builds.append(1) or real_build(geom))
    cache.get(small, tenant="bob")
    assert builds == [1]
    for attempt in range(2):
        with pytest.raises(SceneError) as e:
            cache.get(big, sandbox=True, tenant="alice", limits=LoadLimits())
        msg = e.value.message
        assert e.value.code == "too_large_for_cache", msg
        assert "scene_cache_bytes" in msg and "tenant_cache_share" in msg, msg
        assert f"({need} bytes)" in msg and f"({share_bytes} bytes)" in msg, msg
        assert str(tmp_path) not in msg and "/" not in msg, msg
        assert cache.stats()["loads"] == 2, attempt  # the second refusal did not load it again
    assert builds == [1]  # no Mitsuba scene was built for it
    assert not cache.peek(big, sandbox=True) and _cached_plain(cache, small)  # nothing pushed out
    # concurrent requests share the one refusal too
    other = SceneCache(capacity=100, max_bytes=2 * share_bytes, tenant_share=0.5)
    got = concurrently(3, lambda: other.get(big, tenant="carol"))
    assert all(isinstance(g, SceneError) and g.code == "too_large_for_cache" for g in got), got
    assert other.stats()["loads"] == 1
    # a larger share (the operator raised scene_cache_bytes): the same scene now loads and is kept
    cache.configure(max_bytes=4 * share_bytes)
    assert cache.get(big, sandbox=True, tenant="alice", limits=LoadLimits()).nbytes == need
    assert cache.peek(big, sandbox=True) is not None


def _cached_plain(cache: SceneCache, p: Path) -> bool:
    return p in cache


def test_configure_shrinks_and_validates(tmp_path):
    cache = SceneCache(capacity=8, max_bytes=BIG, tenant_share=1.0)
    paths = tinies(tmp_path, 5)
    for p in paths:
        cache.get(p, tenant="alice")
    cache.configure(capacity=4, max_bytes=BIG, tenant_share=0.5)
    assert cache.stats()["entries"] == 2 and [_cached_plain(cache, p) for p in paths] == [False] * 3 + [True] * 2
    for bad in ({"capacity": 0}, {"max_bytes": -1}, {"tenant_share": 0}, {"tenant_share": 1.5}):
        with pytest.raises(ValueError):
            cache.configure(**{"capacity": 4, "max_bytes": BIG, "tenant_share": 0.5, **bad})


def test_loading_is_true_exactly_while_a_load_of_that_key_is_in_flight(tmp_path):
    """The server asks this to let only a load's leader hold a load slot (waiters of a shared load wait
    outside it)."""
    path = write(tmp_path, "scene.usda", tiny_scene(3))
    cache = SceneCache()
    started, release = threading.Event(), threading.Event()
    real = cache._load

    def slow(*args, **kwargs):
        started.set()
        release.wait(60)
        return real(*args, **kwargs)

    cache._load = slow
    assert not cache.loading(path, sandbox=True, tenant="alice")
    t = threading.Thread(target=lambda: cache.get(path, sandbox=True, tenant="alice"))
    t.start()
    try:
        assert started.wait(60)
        assert cache.loading(path, sandbox=True, tenant="bob", limits=LoadLimits())  # tenant, limits: not the key
        assert not cache.loading(path, sandbox=False)  # other options: another key
        assert not cache.loading(tmp_path / "gone.usda")  # no file: nothing in flight, no error
    finally:
        release.set()
        t.join(60)
    assert not cache.loading(path, sandbox=True)
    assert cache.peek(path, sandbox=True) is not None  # done and cached


def test_max_triangles_applies_to_a_fresh_load_and_to_a_cached_entry(tmp_path):
    """What a batch worker does (in-process loads, its own process being the isolation): the loader refuses
    while counting, and an entry cached under a higher limit is refused under a lower one."""
    path = write(tmp_path, "spheres20.usda", instanced_spheres(20))
    n = load_scene(path).geometry.triangle_count
    cache = SceneCache()
    with pytest.raises(SceneError) as e:
        cache.get(path, sandbox=True, max_triangles=n // 2)
    assert e.value.code == "too_many_triangles" and cache.stats()["entries"] == 0
    entry = cache.get(path, sandbox=True, max_triangles=n)
    assert entry.loaded.geometry.triangle_count == n
    with pytest.raises(SceneError) as e:
        cache.get(path, sandbox=True, max_triangles=n - 1)  # a hit, but over this get's limit
    assert e.value.code == "too_many_triangles" and f"limit of {n - 1}" in e.value.message
    with pytest.raises(SceneError):
        cache.get(path, sandbox=True, limits=LoadLimits(max_triangles=n - 1))  # the isolated limit likewise
    assert cache.get(path, sandbox=True) is entry and cache.stats()["loads"] == 2
