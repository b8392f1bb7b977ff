"""Admission control and fair sharing (issue 9): heavy requests wait on the event loop, the tenants taking
turns; /healthz and /metrics answer at once while 48 heavy requests are queued; per-tenant quotas (heavy
requests in flight, queued batch configurations, stored bytes) answer 429 naming the quota while the other
tenants proceed. The pools in process, the rest on a real server with small limits."""
from __future__ import annotations

import asyncio
import random
import re
import socket
import time
from concurrent.futures import ThreadPoolExecutor

import httpx
import pytest
from serverkit import auth, running
from test_security import BOX, BOX_RIG, post_scene, slow_configurations

from shadowopt.api.admission import Admission, FairPool, Refused

FLOOD = 48  # heavy requests one tenant has in flight (issue 9's number)
LIMITS = {"SHADOWOPT_MAX_INFLIGHT": "60", "SHADOWOPT_TENANT_MAX_INFLIGHT": str(FLOOD), "SHADOWOPT_SOLVE_THREADS": "2",
          "SHADOWOPT_RATE_LIMIT_PER_S": "0", "SHADOWOPT_MAX_TIME_BUDGET_MS": "300", "SHADOWOPT_BATCH_WORKERS": "1",
          "SHADOWOPT_MAX_QUEUE": "20", "SHADOWOPT_TENANT_MAX_QUEUED": "6",
          "SHADOWOPT_TENANT_MAX_STORED_BYTES": "3000", "SHADOWOPT_SCENE_CACHE_ENTRIES": "4",
          "SHADOWOPT_TENANT_CACHE_SHARE": "0.5", "SHADOWOPT_LOAD_THREADS": "2"}


# --- the pools in process -------------------------------------------------------------------------

async def request(pool: FairPool, order: list, tenant: str, i: int) -> None:
    """One request in process: it takes a slot of `pool`, writes down that it ran, and gives the slot back."""
    async with pool.slot(tenant):
        order.append(f"{tenant}{i}")
        await asyncio.sleep(0.001)


def test_slots_go_to_the_tenants_in_turn_and_a_cancelled_waiter_gives_its_place_back():
    async def main():
        pool, order = FairPool("solve", 1), []
        tasks = [asyncio.create_task(request(pool, order, "a", i)) for i in range(6)]
        await asyncio.sleep(0)  # a0 runs, a1..a5 wait
        tasks += [asyncio.create_task(request(pool, order, "b", i)) for i in range(2)]
        gone = asyncio.create_task(request(pool, order, "c", 0))
        await asyncio.sleep(0)
        gone.cancel()
        await asyncio.gather(*tasks)
        return order, pool

    order, pool = asyncio.run(main())
    # b's two requests arrived after a's six, yet b0 runs as soon as a0 frees the slot and b1 right after a1:
    # turns, not arrival order (the tenant just served is last among equals)
    assert order == ["a0", "b0", "a1", "b1", "a2", "a3", "a4", "a5"], order
    assert pool.busy == 0 and pool.waiting == 0  # c's cancelled wait left nothing behind


def test_a_tenant_holding_every_slot_gives_the_next_one_to_a_newcomer():
    async def main():
        pool, order = FairPool("solve", 2), []
        tasks = [asyncio.create_task(request(pool, order, "a", i)) for i in range(5)]
        await asyncio.sleep(0)  # a0 and a1 run, a2..a4 wait
        tasks.append(asyncio.create_task(request(pool, order, "b", 0)))
        await asyncio.gather(*tasks)
        return order, pool

    order, pool = asyncio.run(main())
    assert order[:3] == ["a0", "a1", "b0"], order  # a was first in line, but b held no slot
    assert pool.busy == 0 and pool.held == {}


def test_a_tenant_active_a_moment_ago_finds_a_slot_kept_for_it_while_another_floods():
    """Pool of 2: while b is active (asked within recent_s), a may hold only one slot, so b's next request
    starts at once instead of waiting for a's running work; once b has been idle for recent_s, a gets both."""
    async def hold(pool, tenant, started, done):
        async with pool.slot(tenant):
            started.set()
            await done.wait()

    async def main():
        pool = FairPool("solve", 2, recent_s=0.3)
        ev = {k: (asyncio.Event(), asyncio.Event()) for k in ("b0", "a0", "a1", "b1")}
        b0 = asyncio.create_task(hold(pool, "b", *ev["b0"]))
        await ev["b0"][0].wait()
        ev["b0"][1].set()
        await b0  # b was served a moment ago and holds nothing now
        a0 = asyncio.create_task(hold(pool, "a", *ev["a0"]))
        a1 = asyncio.create_task(hold(pool, "a", *ev["a1"]))
        await asyncio.sleep(0.05)
        a1_kept_waiting = ev["a0"][0].is_set() and not ev["a1"][0].is_set() and pool.busy == 1
        b1 = asyncio.create_task(hold(pool, "b", *ev["b1"]))
        await asyncio.sleep(0.05)
        b1_at_once = ev["b1"][0].is_set() and not ev["a1"][0].is_set()  # a0 and a1 are still waiting to end
        ev["b1"][1].set()
        await b1
        await asyncio.wait_for(ev["a1"][0].wait(), 2.0)  # b idle for recent_s: a may take the second slot
        both_for_a = pool.held.get("a") == 2
        for k in ("a0", "a1"):
            ev[k][1].set()
        await asyncio.gather(a0, a1)
        return a1_kept_waiting, b1_at_once, both_for_a, pool

    a1_kept_waiting, b1_at_once, both_for_a, pool = asyncio.run(main())
    assert a1_kept_waiting, "a took both slots although b had asked a moment ago"
    assert b1_at_once, "b's request waited behind a's running work"
    assert both_for_a, "the kept slot was not handed out after b went idle"
    assert pool.busy == 0 and pool.waiting == 0 and pool.held == {}


def test_admission_refuses_at_once_naming_the_limit_and_two_tenants_cannot_lock_a_third_out():
    """review of issue 9: with tenant_max_inflight = max_inflight / 2, two tenants at their quota refused
    everyone else 503 busy. A tenant with nothing in flight is always admitted (headroom); busy refuses only
    tenants that already have a request in."""
    adm = Admission(max_inflight=4, tenant_max_inflight=2, solve_threads=1, load_threads=1)
    first = adm.admit("a")
    adm.admit("a")
    with pytest.raises(Refused) as e:
        adm.admit("a")
    assert e.value.status == 429 and "tenant_max_inflight = 2" in e.value.message
    adm.admit("b")
    adm.admit("b")  # a and b hold max_inflight = 4 between them
    adm.admit("c")  # c has nothing in flight: admitted all the same
    assert adm.inflight == 5  # over max_inflight by at most one per tenant
    with pytest.raises(Refused) as e:
        adm.admit("c")
    assert e.value.status == 503 and e.value.code == "busy" and "max_inflight = 4" in e.value.message
    first.release()
    first.release()  # releasing twice counts once
    assert adm.inflight == 4 and adm.by_tenant == {"a": 1, "b": 2, "c": 1}
    with pytest.raises(Refused):  # still at max_inflight: c's second waits its turn
        adm.admit("c")
    adm.admit("d")


# --- a real server ----------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def server(tmp_path_factory):
    with running(tmp_path_factory.mktemp("adm") / "data", env=LIMITS) as s:
        yield s


def box_scene(server, who: str, extra: str = "") -> str:
    r = post_scene(server.base, who, BOX % extra)
    assert r.status_code in (200, 201), r.text
    return r.json()["scene_id"]


def gauge(base: str, name: str) -> float:
    m = re.search(rf"^{name} (\S+)$", httpx.get(base + "/metrics").text, re.M)
    return float(m.group(1)) if m else float("nan")


def quantile(values: list[float], q: float) -> float:
    v = sorted(values)
    return v[min(len(v) - 1, round(q * (len(v) - 1)))]


PROBES = 40  # /healthz and /metrics probes each while the flood is queued


@pytest.mark.server
@pytest.mark.slow
def test_probes_answer_at_once_and_another_tenant_gets_its_turn_while_one_floods(server):
    """48 heavy requests from alice in flight (2 running, the rest queued): /healthz and /metrics answer
    without waiting for the queue (40 probes each, all answered while most of the flood is still queued; their
    latency is `shadowopt bench security`'s), alice's 49th is refused (429 naming tenant_max_inflight), and bob's
    optimize is served before most of alice's requests that were queued before it (fair turns), not after all
    of them."""
    alice, bob = box_scene(server, "alice"), box_scene(server, "bob")
    body = {"scene_id": alice, "rig": BOX_RIG, "screen": [160, 90], "methods": ["uniform"]}
    done: list[float] = []  # completion times of alice's requests
    statuses: list[int] = []
    # two slow ones hold both solver slots while the rest (one cheap method each: what they hold is a place in
    # the queue) line up
    blocker = {**body, "rig": {**BOX_RIG, "coarse_long_side": 96}, "screen": [960, 540],
               "methods": ["uniform", "focused", "lispsm", "optimized"]}

    def one(i):
        r = httpx.post(server.base + "/v1/compare", json=blocker if i < 2 else body, headers=auth("alice"),
                       timeout=300)
        done.append(time.monotonic())
        statuses.append(r.status_code)

    def wait_for(name: str, value: int) -> None:
        deadline = time.monotonic() + 60
        while gauge(server.base, name) < value:
            assert time.monotonic() < deadline, f"{name} never reached {value}"
            time.sleep(0.01)

    pool = ThreadPoolExecutor(FLOOD)
    futures = [pool.submit(one, i) for i in range(2)]
    try:
        wait_for("shadowopt_solve_slots_busy", 2)
        futures += [pool.submit(one, i) for i in range(2, FLOOD)]
        wait_for("shadowopt_inflight_requests", FLOOD)
        assert gauge(server.base, "shadowopt_solve_waiting") >= FLOOD - 4  # queued, not running: the case of issue 9
        health, metrics = [], []
        with httpx.Client(base_url=server.base, timeout=30) as c:
            t0 = time.perf_counter()
            refused = c.post("/v1/compare", json=body, headers=auth("alice"))
            refusal_s = time.perf_counter() - t0
            for _ in range(PROBES):
                t0 = time.perf_counter()
                assert c.get("/healthz").status_code == 200
                health.append(time.perf_counter() - t0)
                t0 = time.perf_counter()
                assert c.get("/metrics").status_code == 200
                metrics.append(time.perf_counter() - t0)
                time.sleep(0.02)
            answered_by = len(done)  # alice's requests finished by the time the last probe was answered
        assert refused.status_code == 429, refused.text[:300]
        assert refused.json()["error"]["code"] == "tenant_quota" and "tenant_max_inflight" in refused.text
        assert int(refused.headers["retry-after"]) >= 1
        p95 = {"healthz": quantile(health, 0.95), "metrics": quantile(metrics, 0.95)}
        print(f"\n/healthz p50 {quantile(health, 0.5) * 1e3:.1f} ms p95 {p95['healthz'] * 1e3:.1f} ms p99 "
              f"{quantile(health, 0.99) * 1e3:.1f} ms, /metrics p50 {quantile(metrics, 0.5) * 1e3:.1f} ms p95 "
              f"{p95['metrics'] * 1e3:.1f} ms, refusal {refusal_s * 1e3:.1f} ms under {FLOOD} heavy requests")
        # Issue 9: the probes waited for the solver queue (12.8 s). They do not wait for it: every probe was answered
        # while most of the flood was still queued. How fast (the < 100 ms bar) is `shadowopt bench security`'s.
        assert answered_by <= FLOOD // 2, f"{answered_by} of alice's {FLOOD} were done before the probes were"

        t0 = time.monotonic()
        r = httpx.post(server.base + "/v1/optimize", json={"scene_id": bob, "rig": BOX_RIG, "method": "focused"},
                       headers=auth("bob"), timeout=300)
        t1 = time.monotonic()
        assert r.status_code == 200, r.text
        in_flight = FLOOD - sum(1 for t in done if t < t0)  # alice's queued (or running) when bob asked
        assert in_flight >= 20, "the flood ended before bob asked: the test measured nothing"
    finally:
        for f in futures:
            f.result(timeout=600)
        pool.shutdown()
    after = sum(1 for t in done if t > t1)  # alice's queued before bob's yet answered after his
    print(f"bob's optimize {(t1 - t0) * 1e3:.0f} ms while alice floods; {in_flight} of alice's were in flight "
          f"when bob asked, {after} of them answered after bob")
    # first come, first served would answer all of them before bob; fair turns serve him next
    assert after > in_flight // 2, f"bob was served after {in_flight - after} of alice's {in_flight}"
    assert statuses.count(200) == FLOOD, statuses
    assert gauge(server.base, "shadowopt_inflight_requests") == 0


@pytest.mark.server
def test_one_tenant_over_its_queue_quota_gets_429_while_another_proceeds(server):
    """issue 9: a batch as large as the whole queue from one tenant made the next tenant's small batch fail
    with 503 queue_full. Now the first is refused with 429 naming tenant_max_queued and the second queues."""
    alice, bob = box_scene(server, "alice"), box_scene(server, "bob")
    hog = httpx.post(server.base + "/v1/batches", json={"scene_id": alice, "configurations": slow_configurations(20),
                                                         "method": "optimized"}, headers=auth("alice"), timeout=60)
    assert hog.status_code == 429, hog.text
    err = hog.json()["error"]
    assert err["code"] == "tenant_quota" and err["field"] == "configurations"
    assert "tenant_max_queued = 6" in err["message"]
    assert int(hog.headers["retry-after"]) >= 1
    first = httpx.post(server.base + "/v1/batches", json={"scene_id": alice, "configurations": slow_configurations(5),
                                                           "method": "optimized"}, headers=auth("alice"), timeout=60)
    assert first.status_code == 202, first.text
    more = httpx.post(server.base + "/v1/batches", json={"scene_id": alice, "configurations": slow_configurations(5),
                                                          "method": "optimized"}, headers=auth("alice"), timeout=60)
    assert more.status_code == 429 and "tenant_max_queued" in more.text, more.text  # 5 queued + 5 > 6
    other = httpx.post(server.base + "/v1/batches", json={"scene_id": bob, "configurations": slow_configurations(5),
                                                           "method": "optimized"}, headers=auth("bob"), timeout=60)
    assert other.status_code == 202, other.text  # bob's turn is his own
    for who, r in (("alice", first), ("bob", other)):
        httpx.delete(f"{server.base}/v1/batches/{r.json()['batch_id']}", headers=auth(who))


@pytest.mark.server
def test_stored_bytes_quota_per_tenant(server):
    """tenant_max_stored_bytes = 3000: carol's uploads stop with 429 naming the quota once her stored scenes
    would exceed it (413 for one file larger than the quota), bob's go on, and deleting makes room."""
    sizes, ids, k = 0, [], 0
    while True:
        k += 1
        text = BOX % f"    # scene {k}\n"
        r = post_scene(server.base, "carol", text)
        if r.status_code != 201:
            break
        ids.append(r.json()["scene_id"])
        sizes += len(text.encode())
        assert k < 20, "the quota never applied"
    assert r.status_code == 429, r.text
    err = r.json()["error"]
    assert err["code"] == "tenant_quota" and err["field"] == "file"
    assert "tenant_max_stored_bytes = 3000" in err["message"]
    assert int(r.headers["retry-after"]) >= 1 and sizes + len(text.encode()) > 3000 >= sizes
    listed = httpx.get(server.base + "/v1/scenes", headers=auth("carol")).json()["scenes"]
    assert sorted(s["scene_id"] for s in listed) == sorted(ids)  # the refused one left no record
    big = post_scene(server.base, "bob", BOX % ("    #" + "x" * 3000 + "\n"))
    assert big.status_code == 413 and "tenant_max_stored_bytes" in big.text, big.text
    assert post_scene(server.base, "bob", BOX % "    # bob's own\n").status_code == 201  # his own quota
    assert httpx.delete(f"{server.base}/v1/scenes/{ids[0]}", headers=auth("carol")).status_code == 200
    assert post_scene(server.base, "carol", text).status_code == 201  # room again
    for s in httpx.get(server.base + "/v1/scenes", headers=auth("carol")).json()["scenes"]:
        httpx.delete(f"{server.base}/v1/scenes/{s['scene_id']}", headers=auth("carol"))


@pytest.mark.server
def test_an_evicted_scene_is_reloaded_once_for_six_concurrent_optimizes(server):
    """issue 9: after a tenant's uploads evicted a scene, 6 concurrent optimizes did 6 full reloads and
    shadowopt_inflight_requests stayed 0. The reload runs under the requests' admission, in a scene-load slot,
    and single flight: one load for all six, although two load slots (load_threads = 2) would let two
    requests load at once; the others wait for that load holding no load slot (review item 8)."""
    first = box_scene(server, "carol", "    # first\n")
    fillers = [box_scene(server, "carol", f"    # filler {k}\n") for k in range(3)]  # her share: 2 entries
    loads = gauge(server.base, "shadowopt_scene_cache_loads_total")
    followers = counter(server.base, "shadowopt_scene_load_followers_total")
    body = {"scene_id": first, "rig": BOX_RIG, "method": "focused"}
    with ThreadPoolExecutor(6) as pool:
        answers = list(pool.map(lambda _: httpx.post(server.base + "/v1/optimize", json=body, headers=auth("carol"),
                                                     timeout=120), range(6)))
    assert [r.status_code for r in answers] == [200] * 6, [r.text[:200] for r in answers]
    assert gauge(server.base, "shadowopt_scene_cache_loads_total") - loads == 1  # evicted, then loaded once
    # the others took the leader's entry: at least one of them waited for the load without a load slot
    assert counter(server.base, "shadowopt_scene_load_followers_total") - followers >= 1
    for sid in [first, *fillers]:
        httpx.delete(f"{server.base}/v1/scenes/{sid}", headers=auth("carol"))


@pytest.mark.server
def test_requests_that_waited_for_a_failed_reload_get_its_answer_without_loading_again(server):
    """Single flight for failures: an evicted scene whose file was damaged on disk meanwhile fails to reload;
    the six concurrent optimizes that asked for it all get the leader's 422 (naming the file), and the file is
    loaded once, not once per request."""
    first = box_scene(server, "carol", "    # damaged later\n")
    fillers = [box_scene(server, "carol", f"    # evicts {k}\n") for k in range(3)]  # her share: 2 entries
    [stored] = [p for p in server.data_dir.rglob("box.usda") if first in str(p)]
    # damaged at its end: the reload parses 200,000 points (a while) before it fails, so all six ask during it
    points = ", ".join(f"({k % 97}, 0, {k // 97})" for k in range(200_000))
    stored.write_text(f'#usda 1.0\ndef Xform "World" {{\n    def Mesh "M" {{\n        point3f[] points = [{points}]\n'
                      '        int[] faceVertexCounts = [3\n')
    loads = gauge(server.base, "shadowopt_scene_cache_loads_total")
    body = {"scene_id": first, "rig": BOX_RIG, "method": "focused"}
    with ThreadPoolExecutor(6) as pool:
        answers = list(pool.map(lambda _: httpx.post(server.base + "/v1/optimize", json=body, headers=auth("carol"),
                                                     timeout=120), range(6)))
    assert [r.status_code for r in answers] == [422] * 6, [r.text[:200] for r in answers]
    assert {r.json()["error"]["code"] for r in answers} == {answers[0].json()["error"]["code"]}
    assert "box.usda" in answers[0].json()["error"]["message"]
    assert gauge(server.base, "shadowopt_scene_cache_loads_total") - loads == 1
    for sid in [first, *fillers]:
        httpx.delete(f"{server.base}/v1/scenes/{sid}", headers=auth("carol"))


# --- a server with room for three heavy requests and one solver slot --------------------------------

SMALL = {"SHADOWOPT_MAX_INFLIGHT": "3", "SHADOWOPT_TENANT_MAX_INFLIGHT": "3", "SHADOWOPT_SOLVE_THREADS": "1",
         "SHADOWOPT_RATE_LIMIT_PER_S": "0", "SHADOWOPT_MAX_TIME_BUDGET_MS": "300", "SHADOWOPT_BATCH_WORKERS": "1",
         "SHADOWOPT_SCENE_CACHE_BYTES": "40000"}  # one tenant's share: 20000 bytes (a box scene: ~8 KB)
SLOW_SCREEN = [1280, 720]  # a compare at this size runs for seconds on the box scene


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    with running(tmp_path_factory.mktemp("small") / "data", env=SMALL) as s:
        yield s


def counter(base: str, name: str, labels: str = "") -> float:
    """A counter's value from /metrics (0 before it was first counted)."""
    m = re.search(rf"^{re.escape(name + labels)} (\S+)$", httpx.get(base + "/metrics").text, re.M)
    return float(m.group(1)) if m else 0.0


def wait_until(check, what: str, timeout: float = 60.0) -> None:
    deadline = time.monotonic() + timeout
    while not check():
        assert time.monotonic() < deadline, what
        time.sleep(0.02)


def slow_compare(base: str, scene: str, who: str, timeout: float) -> httpx.Response | str:
    body = {"scene_id": scene, "rig": {**BOX_RIG, "coarse_long_side": 96}, "screen": SLOW_SCREEN,
            "methods": ["uniform", "focused", "lispsm", "optimized"]}
    try:
        return httpx.post(base + "/v1/compare", json=body, headers=auth(who), timeout=timeout)
    except httpx.TimeoutException:
        return "gave up"


@pytest.mark.server
def test_a_client_that_gives_up_while_waiting_frees_its_place_at_once(small):
    """review of issue 9: requests whose clients had gone away stayed admitted, used the tenant's quota
    (its next request got 429) and all ran for nobody. Alice sends three slow compares (one runs, two wait
    for the only solver slot) and gives up after a second: the two waiting ones are dropped at once (never
    run: counted as abandoned, answered 499), so her next request is admitted while the first still runs."""
    alice = box_scene(small, "alice", "    # gives up\n")
    abandoned = counter(small.base, "shadowopt_abandoned_requests_total", '{stage="waiting"}')
    pool = ThreadPoolExecutor(3)
    running_one = pool.submit(slow_compare, small.base, alice, "alice", 300)  # this one waits for its answer
    wait_until(lambda: gauge(small.base, "shadowopt_solve_slots_busy") == 1, "the first compare never ran")
    quitters = [pool.submit(slow_compare, small.base, alice, "alice", 1.0) for _ in range(2)]
    try:
        assert [q.result(timeout=30) for q in quitters] == ["gave up"] * 2
        # the two waiting requests are dropped within moments of their clients leaving, not after the solve
        wait_until(lambda: gauge(small.base, "shadowopt_inflight_requests") == 1,
                   "the abandoned requests kept their admission", timeout=10)
        assert not running_one.done(), "the first compare ended before the test could tell: make it slower"
        assert gauge(small.base, "shadowopt_solve_waiting") == 0
        assert counter(small.base, "shadowopt_abandoned_requests_total", '{stage="waiting"}') - abandoned == 2
        assert counter(small.base, "shadowopt_requests_total",
                       '{route="/v1/compare",method="POST",status="499"}') >= 2
        # her quota is free again: the next request is admitted (it waits for the running compare), not 429
        r = httpx.post(small.base + "/v1/optimize", json={"scene_id": alice, "rig": BOX_RIG, "method": "focused"},
                       headers=auth("alice"), timeout=300)
        assert r.status_code == 200, r.text
        first = running_one.result(timeout=300)
        assert first.status_code == 200, first.text
    finally:
        pool.shutdown(wait=True)
    assert gauge(small.base, "shadowopt_inflight_requests") == 0


@pytest.mark.server
@pytest.mark.slow
def test_two_tenants_at_max_inflight_do_not_lock_a_third_out(small):
    """review of issue 9: alice holds max_inflight = 3 heavy requests; bob and carol, with nothing in flight,
    are admitted all the same (and answered), while bob's second request at the same time is refused 503
    busy naming max_inflight. (Alice gives up after a while: her waiting compares are dropped.)"""
    alice, bob, carol = (box_scene(small, who, "    # headroom\n") for who in ("alice", "bob", "carol"))
    pool = ThreadPoolExecutor(6)
    hers = [pool.submit(slow_compare, small.base, alice, "alice", 8) for _ in range(3)]
    try:
        wait_until(lambda: gauge(small.base, "shadowopt_inflight_requests") == 3, "alice never had 3 in flight")
        body = {"rig": BOX_RIG, "method": "focused"}
        bobs = pool.submit(httpx.post, small.base + "/v1/optimize", json={**body, "scene_id": bob},
                           headers=auth("bob"), timeout=300)
        wait_until(lambda: gauge(small.base, "shadowopt_inflight_requests") == 4, "bob was not admitted")
        second = httpx.post(small.base + "/v1/optimize", json={**body, "scene_id": bob}, headers=auth("bob"),
                            timeout=30)
        assert second.status_code == 503, second.text
        assert second.json()["error"]["code"] == "busy" and "max_inflight = 3" in second.text
        carols = pool.submit(httpx.post, small.base + "/v1/optimize", json={**body, "scene_id": carol},
                             headers=auth("carol"), timeout=300)
        wait_until(lambda: gauge(small.base, "shadowopt_inflight_requests") == 5 or carols.done(),
                   "carol was not admitted")
        assert carols.result(timeout=300).status_code == 200, carols.result().text
        assert bobs.result(timeout=300).status_code == 200, bobs.result().text
        for f in hers:
            r = f.result(timeout=300)
            assert r == "gave up" or r.status_code == 200, r.text
    finally:
        pool.shutdown(wait=True)


def raw_upload_start(base: str, who: str, length: int, sent: bytes) -> socket.socket:
    """An upload whose headers say `length` bytes and whose body has only `sent` so far (the rest never comes)."""
    host, port = base.removeprefix("http://").split(":")
    s = socket.create_connection((host, int(port)), timeout=10)
    head = (f"POST /v1/scenes?filename=slow.usda HTTP/1.1\r\nHost: {host}\r\nAuthorization: "
            f"{auth(who)['Authorization']}\r\nContent-Type: application/octet-stream\r\n"
            f"Content-Length: {length}\r\n\r\n")
    s.sendall(head.encode() + sent)
    return s


@pytest.mark.server
def test_an_upload_is_admitted_before_its_body_is_read(small):
    """review of issue 9: upload bodies (up to max_upload_bytes each) were read into memory before admission,
    so one token could hold rate_limit_burst of them. Now an upload is admitted first: three uploads whose
    bodies are still arriving count as carol's three heavy requests in flight, and her fourth is refused at
    once (429 naming tenant_max_inflight) without the server waiting for its body."""
    wait_until(lambda: gauge(small.base, "shadowopt_inflight_requests") == 0,
               "earlier tests' requests still in flight", timeout=120)  # the count below is carol's alone
    slow = [raw_upload_start(small.base, "carol", 50_000, b"#usda 1.0\n") for _ in range(3)]
    try:
        wait_until(lambda: gauge(small.base, "shadowopt_inflight_requests") == 3,
                   "uploads still sending their bodies were not admitted", timeout=10)
        fourth = raw_upload_start(small.base, "carol", 50_000, b"#usda 1.0\n")
        try:
            fourth.settimeout(10)
            answer = b""  # read before the rest of its body was sent
            while b"\r\n\r\n" not in answer or len(answer.partition(b"\r\n\r\n")[2]) < int(
                    re.search(rb"content-length: (\d+)", answer, re.I).group(1) if b"\r\n\r\n" in answer else 1):
                chunk = fourth.recv(4096)
                if not chunk:
                    break
                answer += chunk
            answer = answer.decode("latin-1")
        finally:
            fourth.close()
        assert answer.startswith("HTTP/1.1 429"), answer[:300]
        assert "tenant_max_inflight = 3" in answer and "retry-after" in answer.lower()
    finally:
        for s in slow:
            s.close()
    # clients that left in the middle of their bodies leave nothing in flight
    wait_until(lambda: gauge(small.base, "shadowopt_inflight_requests") == 0, "abandoned uploads stayed admitted",
               timeout=10)
    assert "slow.usda" not in httpx.get(small.base + "/v1/scenes", headers=auth("carol")).text


@pytest.mark.server
def test_a_batch_is_validated_in_a_solver_slot(small):
    """review of issue 9: a batch's per-configuration validation (up to tenant_max_queued rigs resolved against
    the scene) ran in the shared threadpool beside the solves. It takes a solver slot: while a slow compare
    holds the only one, the batch request waits for it (counted as waiting) and is answered after the compare."""
    alice = box_scene(small, "alice", "    # batch\n")
    pool = ThreadPoolExecutor(2)
    try:
        cmp = pool.submit(slow_compare, small.base, alice, "alice", 300)
        wait_until(lambda: gauge(small.base, "shadowopt_solve_slots_busy") == 1, "the compare never ran")
        batch = pool.submit(httpx.post, small.base + "/v1/batches", json={
            "scene_id": alice, "configurations": slow_configurations(2), "method": "focused"},
            headers=auth("alice"), timeout=300)
        wait_until(lambda: gauge(small.base, "shadowopt_solve_waiting") == 1 or batch.done(),
                   "the batch request never arrived")
        assert not batch.done(), "the batch was answered while the compare held the only solver slot"
        compared = cmp.result(timeout=300)
        created = batch.result(timeout=300)
        assert compared.status_code == 200 and created.status_code == 202, (compared.text, created.text)
        httpx.delete(f"{small.base}/v1/batches/{created.json()['batch_id']}", headers=auth("alice"))
    finally:
        pool.shutdown(wait=True)


def grid_scene(n: int) -> str:
    """A ground made of n x n quads (2 n^2 triangles)."""
    pts = ", ".join(f"({x - n / 2}, 0, {z - n / 2})" for z in range(n + 1) for x in range(n + 1))
    idx = ", ".join(f"{z * (n + 1) + x}, {z * (n + 1) + x + 1}, {(z + 1) * (n + 1) + x + 1}, {(z + 1) * (n + 1) + x}"
                    for z in range(n) for x in range(n))
    return ('#usda 1.0\n(\n    defaultPrim = "World"\n    upAxis = "Y"\n)\ndef Xform "World" {\n'
            f'    def Mesh "Ground" {{\n        int[] faceVertexCounts = [{", ".join(["4"] * n * n)}]\n'
            f'        int[] faceVertexIndices = [{idx}]\n        point3f[] points = [{pts}]\n    }}\n}}\n')


@pytest.mark.server
def test_a_scene_over_the_tenants_cache_share_is_refused_413(small):
    """review of issue 9: a scene whose loaded size is over one tenant's share of the scene cache was served
    uncached and reloaded on every request. Its upload is refused, 413 too_large_for_cache, the message naming
    the settings and field `file`; nothing is stored, and a small scene is still accepted."""
    r = post_scene(small.base, "bob", grid_scene(40), "grid.usda")  # 3,200 triangles: ~0.4 MB estimated
    assert r.status_code == 413, r.text
    err = r.json()["error"]
    assert err["code"] == "too_large_for_cache" and err["field"] == "file"
    assert "scene_cache_bytes" in err["message"] and "tenant_cache_share" in err["message"]
    assert "grid.usda" not in httpx.get(small.base + "/v1/scenes", headers=auth("bob")).text
    assert post_scene(small.base, "bob", BOX % "    # fits\n").status_code in (200, 201)


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
