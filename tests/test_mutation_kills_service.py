"""Tests written to kill the mutants of renderers/, api/ and service/ that `make mutate` (or a scratch run of
cosmic-ray's operators over the same modules) found surviving; each checks a property against an independent
truth, never the implementation's own output. Fast and pure (no Mitsuba, no server): every mutant's run of
this file takes a second or two."""
from __future__ import annotations

import os
import posixpath
import random

import numpy as np
import pytest

from shadowopt.renderers.asset_resolver import (check_asset_path, is_unsafe_entry_name, join_inside,
                                                resolve_asset_path)


# --- renderers/asset_resolver.py -------------------------------------------------------------------------

def stay_inside(folder: str, rel: str) -> str | None:
    """Independent model of joining `rel` to `folder` inside an archive: walk the components, '..' pops one and
    may not climb above the top, an absolute `rel` leaves; the top itself is '.'."""
    rel = rel.replace("\\", "/")
    if rel.startswith("/"):
        return None
    stack: list[str] = []
    for part in folder.split("/") + rel.split("/"):
        if part in ("", "."):
            continue
        if part == "..":
            if not stack:
                return None
            stack.pop()
        else:
            stack.append(part)
    return "/".join(stack) or "."


def test_join_inside_agrees_with_a_component_walk_on_random_paths():
    # names sorting before '..' ('-x', '+y', '!') and the archive's top ('.') are ordinary results, not escapes
    parts = ["a", "b", "..", ".", "-x.usda", "+y", "!", "c.usda", ""]
    rng = random.Random(15)
    cases = [("a", ".."), ("", "-x.usda"), ("", "+y/../!"), ("a/b", "../.."), ("", "a/.."), ("a", "..\\..")]
    for _ in range(3000):
        folder = "/".join(rng.choice(["a", "b", "-x"]) for _ in range(rng.randrange(0, 3)))
        rel = "/".join(rng.choice(parts) for _ in range(rng.randrange(1, 5)))
        cases.append((folder, rel))
    for folder, rel in cases:
        assert join_inside(folder, rel) == stay_inside(folder, rel), (folder, rel)
    assert join_inside("a", "..") == "." and join_inside("", "-x.usda") == "-x.usda"
    assert not is_unsafe_entry_name("-x.usda") and not is_unsafe_entry_name("!/a.usda")


@pytest.mark.parametrize("bad, reason", [("", "empty asset path"), ("a\x00.usda", "NUL"),
                                         ("anon:0x7f00:layer.usda", "anonymous")])
def test_every_refusal_says_no(tmp_path, bad, reason):
    # check_asset_path's refusals are refusals in every restricted mode (ok is False, whatever the reason)
    root = str(tmp_path)
    arc = str(tmp_path / "up.usdz")
    for args in ((bad, str(tmp_path / "s.usda"), "local", root),
                 (bad, f"{arc}[root.usda]", "sandbox", None, arc)):
        ok, why = check_asset_path(*args)
        assert ok is False and reason in why, (args, why)
        ident, why = resolve_asset_path(*args)
        assert ident is None and reason in why


def test_resolve_is_only_for_the_restricted_modes(tmp_path):
    with pytest.raises(ValueError, match="restricted modes"):
        resolve_asset_path("x.usda", str(tmp_path / "s.usda"), "local")


def _cases(tmp_path):
    """(arguments, expected result) of resolve_asset_path for a table written out by hand: anchors in and out of
    packages, both modes; identifiers are the absolute normalised layer paths (package[entry])."""
    root = tmp_path / "assets"
    root.mkdir(exist_ok=True)
    r = str(root)
    arc = str(tmp_path / "up.usdz")
    # two packages that sort before and after the uploaded archive's path
    before, after = str(tmp_path / "a-other.usdz"), str(tmp_path / "zz-other.usdz")
    entries = {"scene/root.usda", "scene/parts/chair.usda"}
    return [
        # local mode with an asset root, anchor inside a package inside the root: another entry of that package
        (("parts/c.usda", f"{r}/pkg.usdz[scene/root.usda]", "local", r), (f"{r}/pkg.usdz[scene/parts/c.usda]", "ok")),
        (("../x.usda", f"{r}/d/e/pkg.usdz[root.usda]", "local", r), (None, "'../x.usda' leaves the package 'pkg.usdz'")),
        # ... and a package outside the root is refused even for its own entries
        (("parts/c.usda", f"{tmp_path}/pkg.usdz[scene/root.usda]", "local", r),
         (None, f"'parts/c.usda' resolves outside the asset root {r!r}")),
        # local mode, plain anchor, a path naming an entry of a package
        (("sub/p.usdz[a/./b.usda]", f"{r}/s.usda", "local", r), (f"{r}/sub/p.usdz[a/b.usda]", "ok")),
        (("sub/p.usdz[../x.usda]", f"{r}/s.usda", "local", r),
         (None, "'sub/p.usdz[../x.usda]' leaves the package it names")),
        (("sub/x.usda", f"{r}/s.usda", "local", r), (f"{r}/sub/x.usda", "ok")),
        # sandbox: an entry of the uploaded archive only
        (("parts/chair.usda", f"{arc}[scene/root.usda]", "sandbox", None, arc, entries),
         (f"{arc}[scene/parts/chair.usda]", "ok")),
        (("parts/chair.usda", f"{before}[scene/root.usda]", "sandbox", None, arc, entries),
         (None, "'parts/chair.usda' is not inside the uploaded archive")),
        (("parts/chair.usda", f"{after}[scene/root.usda]", "sandbox", None, arc, entries),
         (None, "'parts/chair.usda' is not inside the uploaded archive")),
        # sandbox, a layer outside any package (the archive given): names nothing
        (("x.usda", str(tmp_path / "s.usda"), "sandbox", None, arc),
         (None, "'x.usda': only entries of the uploaded archive may be opened")),
    ]


def test_resolution_table(tmp_path):
    for args, want in _cases(tmp_path):
        assert resolve_asset_path(*args) == want, args


def test_the_mode_is_compared_by_value(tmp_path):
    # a mode read at run time (a config file, a request) is a new string object: the decisions are the same
    def fresh(s: str) -> str:
        return "".join(list(s))

    assert fresh("local") is not "local"  # noqa: F632 (the point of the test)
    for args, want in _cases(tmp_path):
        args = args[:2] + (fresh(args[2]),) + args[3:]
        assert resolve_asset_path(*args) == want, args
    anchor = str(tmp_path / "assets" / "s.usda")
    assert check_asset_path("../x.usda", anchor, fresh("local")) == (True, "ok")  # no root: anything goes
    ok, why = check_asset_path("../x.usda", anchor, fresh("local"), asset_root=str(tmp_path / "assets"))
    assert not ok and "outside the asset root" in why
    with pytest.raises(ValueError, match="restricted modes"):
        resolve_asset_path("x.usda", anchor, fresh("local"))


# --- api/server.py, api/rate_limit.py, api/service_state.py: the bearer-token tenant and the rate limit, in process

TOKENS = {"alice": "alice-token-0001", "bob": "bob-token-0002"}


class FakeClock:
    def __init__(self):
        self.now = 5000.0

    def monotonic(self):
        return self.now


def _app(tmp_path, monkeypatch, **settings):
    """The real app (create_app) without its lifespan (no store): the tenant dependency answers before any
    route body runs, so 401 / 429 are its own; a request it lets through gets past it (any other status)."""
    from types import SimpleNamespace

    from fastapi.testclient import TestClient

    import shadowopt.api.rate_limit as rate_limit
    import shadowopt.api.server as server
    from shadowopt.api.settings import Settings

    clock = FakeClock()
    monkeypatch.setattr(rate_limit, "time", SimpleNamespace(monotonic=clock.monotonic, time=__import__("time").time,
                                                            perf_counter=__import__("time").perf_counter,
                                                            strftime=__import__("time").strftime,
                                                            gmtime=__import__("time").gmtime))
    s = Settings(data_dir=str(tmp_path / "data"), **settings)
    return TestClient(server.create_app(s), raise_server_exceptions=False), clock


def _get(client, token=None):
    return client.get("/v1/scenes/00000000", headers={"Authorization": f"Bearer {token}"} if token else {})


def test_tenant_for_names_the_token_owner_and_nobody_else():
    from shadowopt.api.service_state import LOCAL_TENANT, Service
    from shadowopt.api.settings import Settings

    svc = Service(Settings(tokens=dict(TOKENS)))
    assert [svc.tenant_for(t) for t in TOKENS.values()] == list(TOKENS)  # each token -> its own name
    for bad in (None, "", "alice-token-000", "alice-token-00011", "bob-token-0001", "ALICE-TOKEN-0001"):
        assert svc.tenant_for(bad) is None, bad
    free = Service(Settings())  # no tokens configured: every request is the local tenant, token or not
    assert {free.tenant_for(t) for t in (None, "", "anything-at-all")} == {LOCAL_TENANT}


def test_the_dependency_refuses_missing_and_unknown_tokens_with_401(tmp_path, monkeypatch):
    client, _ = _app(tmp_path, monkeypatch, tokens=dict(TOKENS), rate_limit_per_s=0.0)
    for token, message in ((None, "missing bearer token"), ("nobody-token-9", "unknown bearer token")):
        r = _get(client, token)
        assert r.status_code == 401 and r.headers["www-authenticate"] == "Bearer"
        err = r.json()["error"]
        assert (err["code"], err["message"], err["field"]) == ("unauthorized", message, "Authorization")
    for token in TOKENS.values():
        assert _get(client, token).status_code not in (401, 429)


@pytest.mark.parametrize("rate, want", [(4.0, 1), (0.4, 3), (0.5, 2), (1 / 7, 7)])
def test_retry_after_is_the_whole_seconds_until_a_token_is_back(tmp_path, monkeypatch, rate, want):
    # burst 1: the first request takes the token, the second (same instant) waits 1/rate s; the header is
    # that wait rounded up to whole seconds, at least 1 (RFC 9110's Retry-After is whole seconds)
    client, clock = _app(tmp_path, monkeypatch, tokens=dict(TOKENS), rate_limit_per_s=rate, rate_limit_burst=1)
    assert _get(client, TOKENS["alice"]).status_code not in (401, 429)
    r = _get(client, TOKENS["alice"])
    assert r.status_code == 429 and r.json()["error"]["code"] == "rate_limited"
    assert r.headers["retry-after"] == str(want)
    assert _get(client, TOKENS["bob"]).status_code not in (401, 429)  # bob's bucket is his own
    clock.now += want  # after the advertised wait the request passes
    assert _get(client, TOKENS["alice"]).status_code not in (401, 429)


# --- service/coarse_cache.py: the camera-pass cache's key, LRU and the receivers memo (fake passes) --------

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


# --- service/need.py: split_budget, receivers per map, dropping empty cascades, a light's counts ---------

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


# --- api/admission.py: admission counts against a model, the fair pool's invariants under random load -----

def test_admission_matches_its_rules_on_random_admit_release_sequences():
    from shadowopt.api.admission import Admission, Refused

    rng = random.Random(9)
    for _ in range(60):
        m, q = rng.randrange(1, 6), rng.randrange(1, 4)
        adm = Admission(m, q, 1, 1)
        live: list = []
        for _ in range(80):
            if live and rng.random() < 0.4:
                t = live.pop(rng.randrange(len(live)))
                t.release()
                t.release()  # a second release changes nothing
            else:
                who = rng.choice("abc")
                mine = sum(t.tenant == who for t in live)
                # the documented rules: quota first (429), then the server limit for a tenant with one in (503);
                # a tenant with nothing in flight is always admitted
                want = 429 if mine >= q else 503 if len(live) >= m and mine > 0 else None
                try:
                    live.append(adm.admit(who))
                    got = None
                except Refused as e:
                    got = e.status
                    assert e.code == {429: "tenant_quota", 503: "busy"}[e.status] and e.retry_after >= 1
                assert got == want, (m, q, mine, len(live))
            counts = {}
            for t in live:
                counts[t.tenant] = counts.get(t.tenant, 0) + 1
            assert adm.inflight == len(live) and adm.by_tenant == counts  # no tenant kept at zero


def test_fair_pool_invariants_hold_under_random_load():
    from collections import Counter

    from shadowopt.api.admission import FairPool

    async def run(seed):
        rng = random.Random(seed)
        size = rng.randrange(1, 4)
        pool = FairPool("p", size)
        inside: Counter = Counter()
        waiting = [0]
        served = []
        violations = []

        async def req(tenant, hold):
            waiting[0] += 1
            await pool.acquire(tenant)
            waiting[0] -= 1
            inside[tenant] += 1
            served.append(tenant)
            try:
                for _ in range(hold):
                    check()
                    await asyncio.sleep(0)
            finally:
                inside[tenant] -= 1
                pool.release(tenant)

        def check():
            # each request is waiting, granted but not yet resumed, or inside: the pool's counts say the same
            assert pool.busy + pool.waiting == waiting[0] + sum(inside.values())
            assert sum(inside.values()) <= pool.busy <= size and sum(pool.held.values()) == pool.busy
            assert all(n > 0 and n >= inside[t] for t, n in pool.held.items())

        tasks = []
        for _ in range(rng.randrange(5, 25)):
            t = rng.choice("abc")
            tasks.append(asyncio.ensure_future(req(t, rng.randrange(0, 4))))
            if rng.random() < 0.5:
                await asyncio.sleep(0)
                check()
        await asyncio.wait_for(asyncio.gather(*tasks), 20)
        return pool, served, violations, len(tasks)

    import asyncio

    for seed in range(40):
        pool, served, violations, n = asyncio.run(run(seed))
        assert len(served) == n and not violations, (seed, violations)
        assert (pool.busy, pool.waiting, pool.held) == (0, 0, {}), seed  # every slot given back, nobody waits


def test_a_slot_kept_for_another_tenant_is_handed_out_when_its_activity_ages_out():
    import asyncio
    import time

    from shadowopt.api.admission import FairPool

    async def main():
        pool = FairPool("p", 2, recent_s=1.0)
        wakes = [0]
        wake = pool._wake

        def counted():
            wakes[0] += 1
            wake()

        pool._wake = counted
        await pool.acquire("a")
        t_b = time.monotonic()
        await pool.acquire("b")  # b asked at t_b
        second = asyncio.ensure_future(pool.acquire("a"))
        await asyncio.sleep(0.6)
        pool.release("b")  # a slot is free, but b was active 0.6 s ago: it stays kept for b
        await asyncio.sleep(0.1)
        kept = not second.done() and pool.busy == 1 and pool.waiting == 1
        await asyncio.wait_for(second, 5)
        return kept, time.monotonic() - t_b, pool, wakes

    kept, after, pool, wakes = asyncio.run(main())
    assert kept
    assert wakes[0] <= 2, wakes  # one timer for the age-out (not a poll every few milliseconds)
    # handed to a once b's last ask is recent_s old (1.0 s after it, not recent_s after the release)
    assert 0.95 <= after < 1.45, after
    assert pool.held == {"a": 2} and pool.busy == 2 and pool.waiting == 0


# --- renderers/redaction.py: which folders are cut -------------------------------------------------------

def test_only_the_temp_dir_is_hidden_one_level_below_root():
    import tempfile

    from shadowopt.renderers.redaction import PathRedactor

    tmp = tempfile.gettempdir().rstrip("/")
    # "/home" and "/srv" sort before "/tmp": a folder one level below / is never hidden, whatever its name
    r = PathRedactor(hidden=["/home", "/srv", "/aaa", tmp])
    assert r.text("see /home/alice/notes and /srv/x/y and /aaa/b/c") == "see /home/alice/notes and /srv/x/y and /aaa/b/c"
    assert r.text(f"at {tmp}/abc/def") == "at def"
    assert PathRedactor(hidden=["/home/alice"]).text("see /home/alice/notes") == "see notes"  # two levels: hidden


def test_a_relative_root_is_matched_as_written_only_with_two_components_or_more():
    from shadowopt.renderers.redaction import PathRedactor

    assert PathRedactor(roots=["out/data"], hidden=[]).text("at out/data/x.usda") == "at x.usda"
    # a one-word relative folder ("data") would cut the word wherever it appears: only its absolute form counts
    assert PathRedactor(roots=["data"], hidden=[]).text("at data/y.usda") == "at data/y.usda"
    assert PathRedactor(roots=["./data"], hidden=[]).text("at data/y.usda") == "at data/y.usda"


# --- service/request_cost.py: the defaults are the schema's ------------------------------------------------

def test_auto_cascades_cost_uses_the_schemas_default_max_cascades():
    from shadowopt.api.schemas import ShadowSpec
    from shadowopt.service.request_cost import _describe, maps_per_light

    k = ShadowSpec.model_fields["max_cascades"].default  # the request's default, from the schema
    fits = k * (k + 1) // 2  # auto tries 1..k cascades: k(k+1)/2 map fits
    assert maps_per_light({"cascades": "auto"}) == fits == maps_per_light({"cascades": "auto", "max_cascades": k})
    assert maps_per_light(ShadowSpec(cascades="auto")) == fits
    assert maps_per_light({"cascades": "auto", "max_cascades": 3}) == 6 and maps_per_light({"cascades": 3}) == 3
    text = _describe({"shadow": {"cascades": "auto"}, "lights": [{"type": "directional"}]})
    assert f"max_cascades {k} ({fits} map fits)" in text


# --- service/isolation.py: how a loader child's death is read -------------------------------------------

def test_a_dead_loader_child_is_classified_by_signal_and_memory():
    import math
    import signal

    from shadowopt.renderers.scene_data import SceneError
    from shadowopt.service.isolation import CRASH_MEMORY_SHARE, _crashed

    mem = 1 << 30

    def code(exitcode, peak):
        with pytest.raises(SceneError) as e:
            _crashed(exitcode, peak, mem, "x.usda")
        return e.value.code

    near = math.ceil(CRASH_MEMORY_SHARE * mem)  # the least whole byte count at the share
    assert code(-signal.SIGKILL, 0) == "memory_limit"  # the OOM killer
    assert code(-signal.SIGXCPU, 0) == "load_timeout"
    for sig in (signal.SIGABRT, signal.SIGSEGV, signal.SIGBUS, signal.SIGHUP, signal.SIGFPE):
        assert code(-sig, near - 4096) == "corrupt", sig  # a crash far from the limit: a damaged file
        assert code(-sig, near) == "memory_limit", sig  # std::bad_alloc aborts near the limit
    assert code(1, 0) == "corrupt" and code(None, 0) == "corrupt" and code(None, mem) == "memory_limit"


def test_near_the_memory_limit_is_the_documented_share_of_it(monkeypatch):
    from shadowopt.service import isolation

    monkeypatch.setattr(isolation, "_status", lambda pid="self": {"VmPeak": 800})
    assert isolation._near(1000) is True and isolation._near(999) is True  # 800 >= 0.8 x 999
    assert isolation._near(1001) is False and isolation._near(10_000) is False
    monkeypatch.setattr(isolation, "_status", lambda pid="self": {})
    assert isolation._near(1) is False  # nothing known: not near


def test_a_loader_child_limits_itself_as_documented(monkeypatch):
    import math
    import resource

    from shadowopt.service import isolation

    calls = {}
    monkeypatch.setattr(resource, "setrlimit", lambda which, lim: calls.__setitem__(which, lim))
    isolation._limit_self(3 << 30, 2.3)
    # RLIMIT_CPU = timeout x threads (rounded up) + the slack (a backstop), hard 5 s above; no core files
    cpu = math.ceil(2.3 * isolation.CHILD_THREADS) + isolation.CPU_SLACK_S
    assert calls == {resource.RLIMIT_CORE: (0, 0), resource.RLIMIT_AS: (3 << 30, 3 << 30),
                     resource.RLIMIT_CPU: (cpu, cpu + 5)}


def test_the_pool_forgets_idle_tenants_seen_long_ago_and_only_those():
    import asyncio
    import time

    from shadowopt.api.admission import FairPool

    async def churn(pool, n):
        for i in range(n):
            await pool.acquire(f"t{i}")
            pool.release(f"t{i}")  # every release dispatches (and, above 64 tenants, forgets)

    async def main():
        keep = FairPool("p", 2, recent_s=0.5)
        await churn(keep, 70)
        recent = len(keep._seen)  # all 70 asked well within recent_s: none may be forgotten yet
        old = FairPool("p", 2, recent_s=0.05)
        await churn(old, 70)
        await asyncio.sleep(0.1)
        await old.acquire("z")
        old.release("z")  # dispatches: forgets the old ones (z asked a moment ago)
        held = FairPool("p", 2, recent_s=0.05)
        await held.acquire("holder")
        await churn(held, 70)
        await asyncio.sleep(0.1)
        await held.acquire("z")
        held.release("z")
        return recent, old, held

    t0 = time.monotonic()
    recent, old, held = asyncio.run(main())
    if time.monotonic() - t0 < 0.45:  # (the churn itself takes milliseconds)
        assert recent == 70
    assert set(old._seen) == {"z"}  # the 70 idle tenants, seen > recent_s ago, are dropped
    assert "holder" in held._seen and held.held == {"holder": 1}  # a tenant holding a slot is kept


def test_the_pool_rules_hold_whatever_the_monotonic_clocks_origin(monkeypatch):
    # time.monotonic's origin is undefined (it may be small): "seen s ago" is now - seen, on a fake clock from 1.0
    import asyncio
    from types import SimpleNamespace

    from shadowopt.api import admission
    from shadowopt.api.admission import FairPool

    clock = SimpleNamespace(t=1.0)
    monkeypatch.setattr(admission, "time", SimpleNamespace(monotonic=lambda: clock.t))

    async def main():
        pool = FairPool("p", 2, recent_s=5.0)
        for i in range(70):  # 70 tenants ask at t = 1 and leave
            await pool.acquire(f"t{i}")
            pool.release(f"t{i}")
        clock.t = 100.0  # 99 s later: all of them idle for longer than recent_s
        await pool.acquire("b")
        second = asyncio.ensure_future(pool.acquire("b"))
        await asyncio.sleep(0)
        alone = second.done()  # no other tenant active: b may take both slots
        pool.release("b")
        pool.release("b")  # dispatches: the 70 are forgotten
        forgotten = set(pool._seen) == {"b"}
        # a tenant idle since t = 1, b and c active at t = 100: the slot kept for b ages out 5 s after b's ask
        clock.t = 1.0
        pool = FairPool("p", 2, recent_s=5.0)
        await pool.acquire("idle")
        pool.release("idle")
        clock.t = 100.0
        await pool.acquire("b")
        await pool.acquire("c")
        waiter = asyncio.ensure_future(pool.acquire("c"))
        await asyncio.sleep(0)
        pool.release("b")  # c may not take b's slot yet: b asked 0 s ago
        delay = pool._timer.when() - asyncio.get_running_loop().time() if pool._timer else None
        waiter.cancel()
        return alone, forgotten, delay

    alone, forgotten, delay = asyncio.run(main())
    assert alone and forgotten
    assert delay is not None and 4.0 < delay <= 5.0, delay


# --- service/point_faces.py: texels per face ---------------------------------------------------------------

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

    from shadowopt.service.point_faces import _objective, warp_for

    assert warp_for("focused", False) == warp_for("focused", True) == "none"  # FP
    assert warp_for("".join(["focu", "sed"]), True) == "none"  # a method name read at run time: compared by value
    for method in ("lispsm", "logpsm", "optimized"):
        assert warp_for(method, False) == "perspective" and warp_for(method, True) == "log"  # FP+P, FP+LogP
    assert _objective({"objective": 2.5}) == 2.5 and _objective({"objective": 2.5, "unserved_samples": 0}) == 2.5
    for bad in ({"objective": None}, {}, {"objective": float("nan")}, {"objective": math.inf},
                {"objective": 1.0, "unserved_samples": 3}, {"objective": 1.0, "unserved_samples": 1}):
        assert _objective(bad) == math.inf, bad  # unknown, not finite, or leaving samples unserved: never chosen


def test_the_spawner_runs_a_nested_call_in_place_instead_of_waiting_for_itself():
    import threading

    from shadowopt.service.isolation import _Spawner

    s = _Spawner()
    assert s.on_thread() is False  # no thread yet
    assert s.call(s.on_thread) is True and s.on_thread() is False  # on its thread / from this one
    out = []
    t = threading.Thread(target=lambda: out.append(s.call(lambda: s.call(lambda: 42))), daemon=True)
    t.start()
    t.join(10)  # a nested call queued behind itself would never return
    assert out == [42]
    assert s.call(threading.current_thread).name == "shadowopt-spawner"


def test_map_texels_is_the_resolution_times_the_maps_or_the_budget():
    from shadowopt.service.request_cost import map_texels

    assert map_texels({"resolution": [1024, 512], "cascades": 3}) == 1024 * 512 * 3
    assert map_texels({"resolution": [300, 200]}) == 60_000  # one cascade by default
    assert map_texels({}) == 2048 * 2048  # no resolution given: the service default, 2048 x 2048
    assert map_texels({"resolution": [1024, 512], "cascades": "auto", "max_cascades": 2}) == 1024 * 512 * 3
    assert map_texels({"texel_budget": 1_000_000, "cascades": 3}) == 1_000_000  # a budget is the light's total
    assert map_texels({"texel_budget": 1_000_000, "cascades": "auto", "max_cascades": 3}) == 6_000_000  # per try
    assert isinstance(map_texels({"resolution": [7, 3], "cascades": 2}), int)


def test_the_memory_floor_message_states_the_same_amount_in_bytes_and_gib():
    import re

    from shadowopt.service.isolation import MEMORY_FLOOR_BYTES, LoadLimits

    with pytest.raises(ValueError) as e:
        LoadLimits(memory_bytes=MEMORY_FLOOR_BYTES - 1)
    m = re.search(r"at least (\d+) \(([\d.]+) GiB", str(e.value))
    assert m and int(m.group(1)) == MEMORY_FLOOR_BYTES
    assert float(m.group(2)) * 2**30 == pytest.approx(MEMORY_FLOOR_BYTES, rel=1e-4)  # the two agree
    assert LoadLimits(memory_bytes=MEMORY_FLOOR_BYTES).memory_bytes == MEMORY_FLOOR_BYTES  # the floor itself is allowed


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


def test_load_isolated_passes_the_loaders_own_defaults(monkeypatch):
    import inspect

    from shadowopt.renderers.usd_loader import load_scene
    from shadowopt.service import isolation

    seen = {}
    monkeypatch.setattr(isolation, "run_isolated", lambda fn, args, **kw: seen.update(options=args[1]))
    isolation.load_isolated("/nowhere/s.usda", limits=isolation.LoadLimits())
    defaults = inspect.signature(load_scene).parameters
    for name in ("time_code", "asset_root", "sandbox"):  # "load_scene(path, ...) in a spawned child"
        assert seen["options"][name] == defaults[name].default, name


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
