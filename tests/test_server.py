"""The REST service as a process: readiness, OpenAPI document, request ids, logs, metrics, settings and
the loopback rule without tokens. A real `shadowopt serve` (uvicorn) on 127.0.0.1."""
from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest
from serverkit import REPO, TINY_RIG, auth, launch, running, stop, upload, wait_ready

from shadowopt.api.settings import Settings, SettingsError, is_loopback, load_settings, parse_tokens


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    with running(tmp_path_factory.mktemp("srv") / "data") as s:
        yield s


@pytest.mark.server
def test_ready_after_warm_up(server):
    assert server.statuses[-1] == 200 and set(server.statuses) <= {200, 503}
    health = httpx.get(server.base + "/healthz").json()
    assert health["status"] == "ok" and health["warm_errors"] == {} and health["warm_s"] > 0
    assert health["queue_length"] == 0
    # the warm-up solved the demo rig once: a first optimize on an uploaded demo needs no kernel compile
    sid = upload(server.base, "alice").json()["scene_id"]
    r = httpx.post(server.base + "/v1/optimize", json={"scene_id": sid, "rig": TINY_RIG, "method": "focused"},
                   headers=auth("alice"), timeout=60)
    assert r.status_code == 200, r.text


@pytest.mark.server
def test_served_openapi_is_the_repository_document(server):
    served = httpx.get(server.base + "/openapi.json").json()
    kept = json.loads((REPO / "docs" / "openapi.json").read_text())
    assert served == kept, "docs/openapi.json is stale: run `python -m shadowopt.api.server`"
    ops = [(p, m, o) for p, item in served["paths"].items() for m, o in item.items()]
    assert {p for p, _, _ in ops} >= {"/v1/scenes", "/v1/scenes/{scene_id}", "/v1/optimize", "/v1/evaluate",
                                     "/v1/compare", "/v1/analyze", "/v1/batches", "/v1/batches/{batch_id}",
                                     "/v1/batches/{batch_id}/results", "/healthz", "/metrics"}
    for path, method, op in ops:
        if path.startswith("/v1/"):
            assert {"401", "429"} <= set(op["responses"]), (method, path)
            assert op["responses"]["401"]["content"]["application/json"]["schema"]["$ref"].endswith("/ErrorResponse")
            assert op.get("security") == [{"HTTPBearer": []}], (method, path)
    assert "422" in served["paths"]["/v1/optimize"]["post"]["responses"]
    assert "Retry-After" in served["paths"]["/v1/batches"]["post"]["responses"]["503"]["headers"]


@pytest.mark.server
def test_request_id_is_echoed_generated_and_logged(server):
    r = httpx.get(server.base + "/v1/scenes", headers={**auth("alice"), "X-Request-ID": "trace-42.a"})
    assert r.status_code == 200 and r.headers["x-request-id"] == "trace-42.a"
    generated = httpx.get(server.base + "/v1/scenes/nope", headers=auth("alice")).headers["x-request-id"]
    assert re.fullmatch(r"[0-9a-f]{32}", generated)
    bad = httpx.get(server.base + "/healthz", headers={"X-Request-ID": "a b\"c"}).headers["x-request-id"]
    assert re.fullmatch(r"[0-9a-f]{32}", bad)  # an unsafe id is replaced, never copied into logs
    lines = [json.loads(line) for line in server.log().splitlines() if line.startswith("{")]
    mine = [e for e in lines if e.get("request_id") == "trace-42.a"]
    assert mine and mine[0]["route"] == "/v1/scenes" and mine[0]["status"] == 200 and mine[0]["tenant"] == "alice"
    miss = [e for e in lines if e.get("request_id") == generated]
    assert miss and miss[0]["status"] == 404 and miss[0]["error_code"] == "scene_not_found"


@pytest.mark.server
def test_metrics_count_requests_latency_optimize_and_queue(server):
    for _ in range(3):
        httpx.get(server.base + "/v1/scenes", headers=auth("bob"))
    text = httpx.get(server.base + "/metrics").text
    count = re.search(r'^shadowopt_requests_total\{route="/v1/scenes",method="GET",status="200"\} (\d+)$', text, re.M)
    assert count and int(count.group(1)) >= 3
    assert re.search(r'^shadowopt_request_duration_seconds_bucket\{route="/v1/scenes",method="GET",le="\+Inf"\} \d+$',
                     text, re.M)
    assert re.search(r'^shadowopt_optimize_seconds_count\{method="focused"\} [1-9]\d*$', text, re.M)
    assert re.search(r"^shadowopt_batch_queue_length 0$", text, re.M)
    assert "# TYPE shadowopt_request_duration_seconds histogram" in text


@pytest.mark.server
def test_no_tokens_means_loopback_only_and_open(tmp_path):
    exe = Path(sys.executable).with_name("shadowopt")
    env = {k: v for k, v in os.environ.items() if not k.startswith("SHADOWOPT_")}
    refused = subprocess.run([str(exe), "serve", "--host", "0.0.0.0", "--data-dir", str(tmp_path / "d")],
                             env=env, capture_output=True, text=True, timeout=60)
    assert refused.returncode == 2
    assert "no tokens are configured" in refused.stderr and "Traceback" not in refused.stderr
    server = launch(tmp_path / "open", tokens=None)
    try:
        wait_ready(server)
        assert httpx.get(server.base + "/v1/scenes").status_code == 200  # no token needed on loopback
        starts = [json.loads(l) for l in server.log().splitlines() if l.startswith("{")]
        assert any("no tokens configured" in e["msg"] and e.get("host") == "127.0.0.1" for e in starts)
    finally:
        stop(server)


@pytest.mark.server
def test_retention_removes_old_scenes(tmp_path):
    env = {"SHADOWOPT_RETENTION_DAYS": str(1.0 / 86400), "SHADOWOPT_RETENTION_INTERVAL_S": "0.3"}
    with running(tmp_path / "data", env=env) as server:
        sid = upload(server.base, "alice").json()["scene_id"]
        assert httpx.get(f"{server.base}/v1/scenes/{sid}", headers=auth("alice")).status_code == 200
        deadline = time.monotonic() + 20
        while httpx.get(f"{server.base}/v1/scenes/{sid}", headers=auth("alice")).status_code == 200:
            assert time.monotonic() < deadline, "the scene outlived its one-second retention"
            time.sleep(0.2)
        assert not list((tmp_path / "data" / "scenes").rglob("*.usda"))


def test_settings_from_file_env_and_flags(tmp_path):
    toml = tmp_path / "s.toml"
    toml.write_text('data_dir = "/x"\nrate_limit_per_s = 3\n[server]\nmax_queue = 7\n[server.tokens]\nann = "ann-token-1"\n')
    s = load_settings(toml, env={"SHADOWOPT_MAX_QUEUE": "9"}, port=9000)
    assert (s.data_dir, s.rate_limit_per_s, s.max_queue, s.port, s.tokens) == ("/x", 3.0, 9, 9000, {"ann": "ann-token-1"})
    js = tmp_path / "s.json"
    js.write_text(json.dumps({"tokens": {"a": "aaaaaaaa"}, "batch_backend": "ray", "retention_days": None}))
    assert load_settings(js, env={}).batch_backend == "ray"
    assert load_settings(env={"SHADOWOPT_TOKENS": "a=tok-aaaa, b=tok-bbbb"}).tokens == {"a": "tok-aaaa", "b": "tok-bbbb"}
    for env, words in [({"SHADOWOPT_TOKENS": "justatoken"}, "name=token"), ({"SHADOWOPT_MAX_QUEUE": "lots"}, "max_queue"),
                       ({"SHADOWOPT_TOKENS": "a=short"}, "at least 8"), ({"SHADOWOPT_BATCH_BACKEND": "dask"}, "batch_backend"),
                       ({"SHADOWOPT_TENANT_CACHE_SHARE": "1.5"}, "tenant_cache_share"),
                       ({"SHADOWOPT_LOAD_MEMORY_BYTES": "1000000"}, "load_memory_bytes"),
                       ({"SHADOWOPT_LOAD_TIMEOUT_S": "0"}, "load_timeout_s"),
                       ({"SHADOWOPT_TENANT_MAX_QUEUED": "0"}, "tenant_max_queued"),
                       ({"SHADOWOPT_LOAD_THREADS": "0"}, "load_threads")]:
        with pytest.raises(SettingsError, match=words):
            load_settings(env=env)
    (tmp_path / "bad.toml").write_text("max_qeue = 3\n")
    with pytest.raises(SettingsError, match="unknown setting.*max_qeue"):
        load_settings(tmp_path / "bad.toml", env={})
    assert parse_tokens("") == {} and not Settings().auth_enabled
    q = load_settings(env={"SHADOWOPT_TENANT_MAX_INFLIGHT": "3", "SHADOWOPT_TENANT_MAX_STORED_BYTES": "5000",
                           "SHADOWOPT_SCENE_CACHE_BYTES": "1000"})
    assert (q.tenant_max_inflight, q.tenant_max_stored_bytes, q.scene_cache_bytes, q.load_threads) == (3, 5000, 1000, 1)
    assert is_loopback("127.0.0.1") and is_loopback("::1") and not is_loopback("0.0.0.0")


@pytest.mark.server
def test_serve_bad_config_exits_2(tmp_path):
    exe = Path(sys.executable).with_name("shadowopt")
    (tmp_path / "c.toml").write_text("max_queue = 0\n")
    env = {k: v for k, v in os.environ.items() if not k.startswith("SHADOWOPT_")}
    r = subprocess.run([str(exe), "serve", "--config", str(tmp_path / "c.toml")], env=env, capture_output=True,
                       text=True, timeout=60)
    assert r.returncode == 2 and "max_queue: must be at least 1" in r.stderr


@pytest.mark.server
def test_load_limits_are_checked_once_with_the_loaders_own_floor(tmp_path):
    """review of issue 9: SHADOWOPT_LOAD_TIMEOUT_S=nan (or inf) was accepted and then every upload answered
    500; the memory floor was checked twice with different numbers. The server now refuses to start naming
    the setting, and the floor is the loader's own (service.isolation.LoadLimits)."""
    from shadowopt.service.isolation import MEMORY_FLOOR_BYTES

    exe = Path(sys.executable).with_name("shadowopt")
    env = {k: v for k, v in os.environ.items() if not k.startswith("SHADOWOPT_")}
    for value in ("nan", "inf"):
        r = subprocess.run([str(exe), "serve", "--data-dir", str(tmp_path / "d")], capture_output=True, text=True,
                           env={**env, "SHADOWOPT_LOAD_TIMEOUT_S": value}, timeout=60)
        assert r.returncode == 2 and "load_timeout_s" in r.stderr and "Traceback" not in r.stderr, r.stderr
    for value in ("-inf", "nan"):
        with pytest.raises(SettingsError, match="^load_timeout_s: "):
            load_settings(env={"SHADOWOPT_LOAD_TIMEOUT_S": value})
    assert MEMORY_FLOOR_BYTES >= 1.2 * 2 ** 30  # usd-core alone maps ~1.2 GB in a loader child
    with pytest.raises(SettingsError, match=f"^load_memory_bytes: .*{MEMORY_FLOOR_BYTES}"):
        load_settings(env={"SHADOWOPT_LOAD_MEMORY_BYTES": str(MEMORY_FLOOR_BYTES - 1)})
    ok = load_settings(env={"SHADOWOPT_LOAD_MEMORY_BYTES": str(MEMORY_FLOOR_BYTES), "SHADOWOPT_LOAD_TIMEOUT_S": "5"})
    assert (ok.load_limits().memory_bytes, ok.load_limits().timeout_s) == (MEMORY_FLOOR_BYTES, 5.0)


def test_health_is_503_with_retry_after_until_warm(tmp_path):
    import asyncio

    from shadowopt.api.server import create_app

    app = create_app(Settings(data_dir=str(tmp_path / "d")))  # in process, no lifespan: nothing has warmed up

    async def health():
        async with httpx.AsyncClient(transport=httpx.ASGITransport(app=app), base_url="http://localhost") as c:  # no tokens: a loopback Host
            return await c.get("/healthz")

    r = asyncio.run(health())
    assert r.status_code == 503 and r.headers["retry-after"] == "1"
    assert r.json()["status"] == "warming" and r.json()["error"]["code"] == "warming_up"
    app.state.service.ready.set()
    assert asyncio.run(health()).status_code == 200


def test_a_bug_under_a_previous_solution_is_a_500_with_the_request_id_not_a_422(tmp_path, monkeypatch, caplog):
    """review of issue 9: the server turned any KeyError/TypeError/IndexError of a solve with a `previous`
    into 422 invalid_previous, hiding real bugs (service.solution_check names malformed previous fields
    itself). A bug is now a 500 internal_error whose message carries the request id, and it is logged."""
    import asyncio

    import shadowopt.api.routes_solve as routes_solve
    from shadowopt.api.server import create_app

    def buggy_solve(*args, **kwargs):
        return {}["a bug"]

    async def any_entry(svc, ticket, scene_id):
        return object()

    monkeypatch.setattr(routes_solve, "solve", buggy_solve)
    monkeypatch.setattr(routes_solve, "scene_entry_for", any_entry)
    app = create_app(Settings(data_dir=str(tmp_path / "d")))

    async def optimize():
        async with httpx.AsyncClient(transport=httpx.ASGITransport(app=app), base_url="http://localhost") as c:  # no tokens: a loopback Host
            return await c.post("/v1/optimize", json={"scene_id": "0123456789abcdef", "rig": TINY_RIG,
                                                      "previous": {"lights": []}}, headers={"X-Request-ID": "bug-1"})

    with caplog.at_level("ERROR", logger="shadowopt.server"):
        r = asyncio.run(optimize())
    assert r.status_code == 500, r.text
    err = r.json()["error"]
    assert err["code"] == "internal_error" and "KeyError" in err["message"] and "bug-1" in err["message"]
    assert any(getattr(rec, "fields", {}).get("request_id") == "bug-1" for rec in caplog.records)
