"""Tests written to kill the mutants of renderers/, api/ and service/ that `make mutate` (or a scratch run of
cosmic-ray's operators over the same modules) found surviving; each checks a property against an independent
truth, never the implementation's own output. Fast and pure (no Mitsuba, no server): every mutant's run of
this file takes a second or two."""
from __future__ import annotations

import os
import posixpath
import random

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


# --- api/server.py: the bearer-token tenant and the rate limit, in process -------------------------------

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

    import shadowopt.api.server as server
    from shadowopt.api.settings import Settings

    clock = FakeClock()
    monkeypatch.setattr(server, "time", SimpleNamespace(monotonic=clock.monotonic, time=__import__("time").time,
                                                        perf_counter=__import__("time").perf_counter,
                                                        strftime=__import__("time").strftime,
                                                        gmtime=__import__("time").gmtime))
    s = Settings(data_dir=str(tmp_path / "data"), **settings)
    return TestClient(server.create_app(s), raise_server_exceptions=False), clock


def _get(client, token=None):
    return client.get("/v1/scenes/00000000", headers={"Authorization": f"Bearer {token}"} if token else {})


def test_tenant_for_names_the_token_owner_and_nobody_else():
    from shadowopt.api.server import LOCAL_TENANT, Service
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
    import numpy as np

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

    import numpy as np

    from shadowopt.service.coarse_cache import MAX_RECEIVER_MASKS, CoarseCache

    cache = CoarseCache()
    # a pass whose camera-only receiver part is already made (service.solve.receiver_prep: not called here)
    cp = SimpleNamespace(lock=threading.Lock(), receivers=OrderedDict(), receiver_prep=object())
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
