"""A server killed with SIGKILL in the middle of a batch resumes it on restart: every configuration index
ends up exactly once and the results reported before the kill are unchanged (not recomputed)."""
from __future__ import annotations

import json
import os
import signal
import time

import httpx
import pytest
from serverkit import TINY_RIG, auth, launch, stop, upload, wait_ready

pytestmark = pytest.mark.server

ENV = {"SHADOWOPT_BATCH_WORKERS": "1", "SHADOWOPT_RATE_LIMIT_PER_S": "0"}
N = 16


def configurations() -> list[dict]:
    # optimized at a slightly larger coarse size: a few hundred ms each, so the kill lands mid-batch
    rig = {**TINY_RIG, "coarse_long_side": 96}
    return [{"rig": {**rig, "lights": [{"type": "directional", "direction": [0.2 + 0.05 * k, -1.0, 0.3]}]}}
            for k in range(N)]


def results(base: str, batch_id: str) -> list[dict]:
    r = httpx.get(f"{base}/v1/batches/{batch_id}/results", headers=auth("alice"), timeout=30)
    assert r.status_code == 200, r.text
    return [json.loads(line) for line in r.text.splitlines()]


def kill_group(server) -> None:
    """SIGKILL the server process, then its orphaned batch workers (its own process group)."""
    os.kill(server.proc.pid, signal.SIGKILL)
    server.proc.wait(timeout=30)
    try:
        os.killpg(server.proc.pid, signal.SIGKILL)
    except ProcessLookupError:
        pass


def submit_and_kill_midway(server, scene_id: str) -> tuple[str, list[dict]] | None:
    """Submit the batch, SIGKILL the server once some but not all results are in; (batch id, results
    read before the kill), or None when the batch finished before a kill could land."""
    r = httpx.post(f"{server.base}/v1/batches", json={"scene_id": scene_id, "configurations": configurations()},
                   headers=auth("alice"), timeout=60)
    assert r.status_code == 202, r.text
    bid = r.json()["batch_id"]
    deadline = time.monotonic() + 180
    while time.monotonic() < deadline:
        before = results(server.base, bid)
        if 2 <= len(before) <= N // 2:  # well before the end: the kill cannot race the last results
            kill_group(server)
            return bid, before
        if len(before) > N // 2:
            return None
        time.sleep(0.02)
    pytest.fail("the batch made no progress in 180 s:\n" + server.log()[-3000:])


def test_sigkill_mid_batch_then_restart_resumes(tmp_path):
    data = tmp_path / "data"
    server = launch(data, env=ENV, new_session=True)
    try:
        wait_ready(server)
        scene_id = upload(server.base, "alice").json()["scene_id"]
        for _ in range(3):
            killed = submit_and_kill_midway(server, scene_id)
            if killed:
                break
        else:
            pytest.fail("every batch finished before the kill could land")
    finally:
        if server.proc.poll() is None:
            kill_group(server)
    bid, before = killed
    print(f"killed with {len(before)} of {N} results reported")
    assert [x["index"] for x in before] == list(range(len(before)))

    restarted = launch(data, env=ENV, new_session=True)
    try:
        wait_ready(restarted)
        deadline = time.monotonic() + 180
        while True:
            st = httpx.get(f"{restarted.base}/v1/batches/{bid}", headers=auth("alice")).json()
            if st["state"] not in ("queued", "running"):
                break
            assert time.monotonic() < deadline, st
            time.sleep(0.1)
        assert (st["state"], st["done"], st["failed"], st["total"]) == ("done", N, 0, N)
        after = results(restarted.base, bid)
        assert [x["index"] for x in after] == list(range(N))  # each index exactly once, in order
        for old in before:  # byte-for-byte the same result: stored once, never recomputed
            assert after[old["index"]] == old
        assert '"resumed_batches": 1' in restarted.log()
    finally:
        stop(restarted)
        try:
            os.killpg(restarted.proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
