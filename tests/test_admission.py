"""Admission control and fair sharing (issue 9): heavy requests wait on the event loop, the tenants taking
turns; /healthz and /metrics answer at once while 48 heavy requests are queued; per-tenant quotas (heavy
requests in flight, queued batch configurations, stored bytes) answer 429 naming the quota while the other
tenants proceed. The pools in process, the rest on a real server with small limits."""
from __future__ import annotations

import asyncio
import re
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
          "SHADOWOPT_TENANT_CACHE_SHARE": "0.5"}


# --- the pools in process -------------------------------------------------------------------------

def test_slots_go_to_the_tenants_in_turn_and_a_cancelled_waiter_gives_its_place_back():
    async def main():
        pool, order = FairPool("solve", 1), []

        async def request(tenant, i):
            async with pool.slot(tenant):
                order.append(f"{tenant}{i}")
                await asyncio.sleep(0.001)

        tasks = [asyncio.create_task(request("a", i)) for i in range(6)]
        await asyncio.sleep(0)  # a0 runs, a1..a5 wait
        tasks += [asyncio.create_task(request("b", i)) for i in range(2)]
        gone = asyncio.create_task(request("c", 0))
        await asyncio.sleep(0)
        gone.cancel()
        await asyncio.gather(*tasks)
        return order, pool

    order, pool = asyncio.run(main())
    # b's two requests arrived after a's six, yet each goes after one more of a's: turns, not arrival order
    assert order == ["a0", "a1", "b0", "a2", "b1", "a3", "a4", "a5"], order
    assert pool.busy == 0 and pool.waiting == 0  # c's cancelled wait left nothing behind


def test_a_tenant_holding_every_slot_gives_the_next_one_to_a_newcomer():
    async def main():
        pool, order = FairPool("solve", 2), []

        async def request(tenant, i):
            async with pool.slot(tenant):
                order.append(f"{tenant}{i}")
                await asyncio.sleep(0.001)

        tasks = [asyncio.create_task(request("a", i)) for i in range(5)]
        await asyncio.sleep(0)  # a0 and a1 run, a2..a4 wait
        tasks.append(asyncio.create_task(request("b", 0)))
        await asyncio.gather(*tasks)
        return order, pool

    order, pool = asyncio.run(main())
    assert order[:3] == ["a0", "a1", "b0"], order  # a was first in line, but b held no slot
    assert pool.busy == 0 and pool.held == {}


def test_admission_refuses_at_once_naming_the_limit():
    adm = Admission(max_inflight=3, tenant_max_inflight=2, solve_threads=1, load_threads=1)
    first = adm.admit("a")
    adm.admit("a")
    with pytest.raises(Refused) as e:
        adm.admit("a")
    assert e.value.status == 429 and "tenant_max_inflight = 2" in e.value.message
    adm.admit("b")
    with pytest.raises(Refused) as e:
        adm.admit("c")
    assert e.value.status == 503 and e.value.code == "busy" and "max_inflight = 3" in e.value.message
    first.release()
    first.release()  # releasing twice counts once
    assert adm.inflight == 2 and adm.by_tenant == {"a": 1, "b": 1}
    adm.admit("c")


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


def p99(values: list[float]) -> float:
    v = sorted(values)
    return v[min(len(v) - 1, round(0.99 * (len(v) - 1)))]


@pytest.mark.slow
def test_probes_answer_at_once_and_another_tenant_gets_its_turn_while_one_floods(server):
    """48 heavy requests from alice in flight (2 running, the rest queued): /healthz and /metrics answer in
    well under 100 ms, alice's 49th is refused at once (429 naming tenant_max_inflight), and bob's optimize
    goes after at most a few of alice's (fair turns), not after all of them."""
    alice, bob = box_scene(server, "alice"), box_scene(server, "bob")
    body = {"scene_id": alice, "rig": {**BOX_RIG, "coarse_long_side": 96}, "screen": [160, 90],
            "methods": ["uniform", "focused", "lispsm", "optimized"]}
    done: list[float] = []  # completion times of alice's requests
    statuses: list[int] = []
    blocker = {**body, "screen": [960, 540]}  # two slow ones hold both solver slots while the rest queue up

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
            for _ in range(20):
                t0 = time.perf_counter()
                assert c.get("/healthz").status_code == 200
                health.append(time.perf_counter() - t0)
                t0 = time.perf_counter()
                assert c.get("/metrics").status_code == 200
                metrics.append(time.perf_counter() - t0)
                time.sleep(0.02)
        assert refused.status_code == 429, refused.text[:300]
        assert refused.json()["error"]["code"] == "tenant_quota" and "tenant_max_inflight" in refused.text
        assert int(refused.headers["retry-after"]) >= 1
        print(f"\n/healthz p50 {sorted(health)[10] * 1e3:.1f} ms p99 {p99(health) * 1e3:.1f} ms, /metrics p50 "
              f"{sorted(metrics)[10] * 1e3:.1f} ms p99 {p99(metrics) * 1e3:.1f} ms, "
              f"refusal {refusal_s * 1e3:.1f} ms under {FLOOD} heavy requests")
        # 12.8 s before (issue 9); the bound leaves room for a loaded 2-core machine, not for waiting on a solve
        assert p99(health) < 0.3 and p99(metrics) < 0.3 and refusal_s < 0.3, (health, metrics, refusal_s)

        t0 = time.monotonic()
        r = httpx.post(server.base + "/v1/optimize", json={"scene_id": bob, "rig": BOX_RIG, "method": "focused"},
                       headers=auth("bob"), timeout=300)
        t1 = time.monotonic()
        assert r.status_code == 200, r.text
        before = sum(1 for t in done if t < t0)
        during = sum(1 for t in done if t0 <= t <= t1)
        print(f"bob's optimize {(t1 - t0) * 1e3:.0f} ms while alice floods; alice finished {during} meanwhile "
              f"({FLOOD - before} of hers were in flight when bob asked)")
        assert FLOOD - before >= 20, "the flood ended before bob asked: the test measured nothing"
        assert during <= 6, f"bob waited for {during} of alice's requests: no fair turns"
    finally:
        for f in futures:
            f.result(timeout=600)
        pool.shutdown()
    assert statuses.count(200) == FLOOD, statuses
    assert gauge(server.base, "shadowopt_inflight_requests") == 0


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


def test_an_evicted_scene_is_reloaded_once_for_six_concurrent_optimizes(server):
    """issue 9: after a tenant's uploads evicted a scene, 6 concurrent optimizes did 6 full reloads and
    shadowopt_inflight_requests stayed 0. The reload runs under the requests' admission, in a scene-load slot,
    and the cache's single flight: one load for all six."""
    first = box_scene(server, "carol", "    # first\n")
    fillers = [box_scene(server, "carol", f"    # filler {k}\n") for k in range(3)]  # her share: 2 entries
    loads = gauge(server.base, "shadowopt_scene_cache_loads_total")
    body = {"scene_id": first, "rig": BOX_RIG, "method": "focused"}
    with ThreadPoolExecutor(6) as pool:
        answers = list(pool.map(lambda _: httpx.post(server.base + "/v1/optimize", json=body, headers=auth("carol"),
                                                     timeout=120), range(6)))
    assert [r.status_code for r in answers] == [200] * 6, [r.text[:200] for r in answers]
    assert gauge(server.base, "shadowopt_scene_cache_loads_total") - loads == 1  # evicted, then loaded once
    for sid in [first, *fillers]:
        httpx.delete(f"{server.base}/v1/scenes/{sid}", headers=auth("carol"))
