"""The Python client (shadowopt.api.client) against a real uvicorn server on 127.0.0.1.

The server runs as `shadowopt serve` in a subprocess (tests/serverkit.py: a temporary data
directory, the tenants' tokens). Retry-After timing, giving up after the retries and a result stream
cut mid-way use a tiny stand-in HTTP server: failures the real server cannot be made to show on demand.
Server notes from writing the client: nothing the client needs is missing. A batch result line holds
the solution's fields at its top level (`{"index", "method", "lights", ...}`, not under "solution");
a failed configuration's line is `{"index", "error": {"code", "message"}}`.
"""
from __future__ import annotations

import asyncio
import json
import subprocess
import sys
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import pytest
from serverkit import DEMO, REPO, TINY_RIG, TOKENS, free_port, running

from shadowopt.api.client import (AsyncClient, AuthError, Client, ClientError, ConnectionFailed, NotFoundError,
                                  ServerError, ShadowoptError)
from shadowopt.api.schemas import Rig


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    """`shadowopt serve` (tests/serverkit.py) on a free port with a fresh data directory; its base URL."""
    with running(tmp_path_factory.mktemp("client") / "data") as srv:
        yield srv.base


@pytest.fixture(autouse=True)
def no_token_in_env(monkeypatch):
    monkeypatch.delenv("SHADOWOPT_TOKEN", raising=False)  # the client's default token


@pytest.fixture(scope="module")
def alice(server):
    with Client(server, token=TOKENS["alice"]) as c:
        yield c


@pytest.mark.server
def test_five_line_use(alice):
    scene = alice.upload_scene(DEMO)
    solution = alice.optimize(scene.scene_id, TINY_RIG)
    assert scene.triangles > 1000 and [c["usd_path"] for c in scene.cameras] == ["/World/Camera"]
    assert alice.get_scene(scene.scene_id).scene_id == scene.scene_id
    light = solution["lights"][0]
    assert solution["method"] == "optimized" and len(light["cascades"]) == 1
    err = light["predicted_error"]
    assert err["samples"] > 0 and 0 < err["p95_m"] < float("inf")


@pytest.mark.server
def test_evaluate_compare_analyze(alice):
    scene = alice.upload_scene(DEMO)
    sol = alice.optimize(scene.scene_id, TINY_RIG, method="focused")
    ev = alice.evaluate(scene.scene_id, TINY_RIG, sol)
    assert ev["method"] == "focused" and ev["receiver_pixels"] > 0
    assert 0 <= ev["misclassified_pixels"] <= ev["receiver_pixels"]
    cmp = alice.compare(scene.scene_id, TINY_RIG, methods=["uniform", "focused"])
    assert set(cmp["methods"]) == {"uniform", "focused"}
    a = alice.analyze(f_over_n=100, theta_deg=30, gamma_deg=90, method="perspective")
    assert a["R_s"] > 0 and a["S"] > 0


@pytest.mark.server
def test_error_carries_server_code_and_field(alice):
    scene = alice.upload_scene(DEMO)
    bad = {**TINY_RIG, "camera": {"usd_path": "/World/Camera", "resolution": [0, 90]}}
    with pytest.raises(ClientError) as e:
        alice.optimize(scene.scene_id, bad)
    assert (e.value.status, e.value.code) == (422, "invalid_request")
    assert e.value.field.startswith("rig.camera.resolution") and "greater than 0" in e.value.message, e.value
    assert e.value.request_id  # the server's X-Request-ID, for its logs
    with pytest.raises(NotFoundError) as e:
        alice.optimize("0123456789abcdef", TINY_RIG)
    assert (e.value.status, e.value.code, e.value.field) == (404, "scene_not_found", "scene_id")
    with pytest.raises(ClientError) as e:
        alice.optimize(scene.scene_id, {**TINY_RIG, "lights": [{"usd_path": "/World/NoSuchLight"}]})
    assert e.value.status == 422 and e.value.field.startswith("rig.lights") and "NoSuchLight" in e.value.message


@pytest.mark.server
def test_auth_and_tenants(server, alice):
    scene = alice.upload_scene(DEMO)
    for token in (None, "not-a-token-at-all"):
        with Client(server, token=token) as c, pytest.raises(AuthError) as e:
            c.get_scene(scene.scene_id)
        assert e.value.status == 401 and e.value.code
    with Client(server, token=TOKENS["bob"]) as bob:
        with pytest.raises(NotFoundError):  # another tenant's scene does not exist for bob
            bob.get_scene(scene.scene_id)
        with pytest.raises(NotFoundError):
            bob.delete_scene(scene.scene_id)
    assert alice.get_scene(scene.scene_id).scene_id == scene.scene_id


@pytest.mark.server
def test_async_client_with_typed_rig(server):
    rig = Rig.model_validate(TINY_RIG)

    async def run():
        async with AsyncClient(server, token=TOKENS["alice"]) as c:
            assert (await c.health()).status == "ok"
            scene = await c.upload_scene(DEMO.read_bytes(), filename="demo.usda")
            sols = await asyncio.gather(*(c.optimize(scene.scene_id, rig, method=m) for m in ("uniform", "lispsm")))
            batch = await c.submit_batch(scene.scene_id, [rig, {"rig": rig}], method="uniform")
            final = await c.wait(batch, progress=False, poll_s=0.1, timeout=120)
            lines = [r async for r in c.iter_results(batch)]
            return scene, sols, final, lines

    scene, sols, final, lines = asyncio.run(run())
    assert final.state == "done" and [r["index"] for r in lines] == [0, 1]
    assert scene.triangles > 1000
    assert [s["method"] for s in sols] == ["uniform", "lispsm"]
    assert all(s["lights"][0]["predicted_error"]["samples"] > 0 for s in sols)


def sun(az_deg: float, el_deg: float = 40.0) -> list[float]:
    import math

    a, e = math.radians(az_deg), math.radians(el_deg)
    return [-math.cos(e) * math.cos(a), -math.sin(e), -math.cos(e) * math.sin(a)]


@pytest.mark.server
def test_batch_submit_wait_and_results(alice, capsys):
    scene = alice.upload_scene(DEMO)
    confs = [{**TINY_RIG, "lights": [{"type": "directional", "direction": sun(az)}]} for az in (0, 60, 120, 180)]
    created = alice.submit_batch(scene.scene_id, confs, method="focused")
    assert created.batch_id and created.total == 4
    final = alice.wait(created, progress=True, poll_s=0.2, timeout=300)
    assert final.state == "done" and final.done == final.total == 4, final
    assert "4/4" in capsys.readouterr().err  # the tqdm progress bar
    lines = list(alice.iter_results(created.batch_id))
    assert [r["index"] for r in lines] == [0, 1, 2, 3]
    assert all(r["method"] == "focused" and r["lights"][0]["predicted_error"]["samples"] > 0 for r in lines)
    assert [r["index"] for r in alice.iter_results(created.batch_id, offset=2)] == [2, 3]
    with Client(alice.base_url, token=TOKENS["bob"]) as bob, pytest.raises(NotFoundError):
        bob.batch(created.batch_id)


@pytest.mark.server
def test_batch_results_followed_while_running_and_cancel(alice):
    scene = alice.upload_scene(DEMO)
    confs = [{**TINY_RIG, "lights": [{"type": "directional", "direction": sun(az, 30)}]} for az in (10, 70, 130)]
    created = alice.submit_batch(scene.scene_id, confs, method="lispsm")
    lines = list(alice.iter_results(created, follow=True, poll_s=0.1))  # starts before the batch is done
    assert [r["index"] for r in lines] == [0, 1, 2] and all(r["method"] == "lispsm" for r in lines)
    assert alice.batch(created).state == "done"
    many = [{**TINY_RIG, "lights": [{"type": "directional", "direction": sun(az, 50)}]} for az in range(0, 360, 12)]
    big = alice.submit_batch(scene.scene_id, many, method="optimized")
    assert alice.cancel_batch(big).state == "cancelled"
    final = alice.wait(big, progress=False, poll_s=0.1, timeout=120)
    assert final.state == "cancelled" and final.done < final.total == 30


@pytest.mark.server
def test_busy_server_503_is_retried(tmp_path):
    """A real server admitting one solver request at a time answers the others 503 busy with
    Retry-After; concurrent clients still all get their solutions."""
    rig = {**TINY_RIG, "camera": {"usd_path": "/World/Camera", "resolution": [1280, 720]}, "coarse_long_side": 180}
    with running(tmp_path / "data", env={"SHADOWOPT_MAX_INFLIGHT": "1"}) as srv:
        with Client(srv.base, token=TOKENS["alice"], retries=20) as c:
            scene = c.upload_scene(DEMO)
            threads, sols = [], []
            for az in (0, 90, 180, 270):
                rig_az = {**rig, "lights": [{"type": "directional", "direction": sun(az)}]}
                threads.append(threading.Thread(target=lambda r=rig_az: sols.append(c.optimize(scene.scene_id, r))))
            for t in threads:
                t.start()
            for t in threads:
                t.join()
            metrics = c._http.get("/metrics").text
    assert len(sols) == 4 and all(s["lights"][0]["predicted_error"]["samples"] > 0 for s in sols)
    busy = [line for line in metrics.splitlines()
            if line.startswith("shadowopt_requests_total") and "/v1/optimize" in line and '"503"' in line]
    assert busy and float(busy[0].rsplit(" ", 1)[1]) >= 1, metrics  # the server did refuse, the client retried


# ---------------------------------------------------------------- stand-in server for failures on demand

class StandIn:
    """A local HTTP server answering GETs from a script: each entry is (status, headers, body) or
    "cut:<body>" (send a Content-Length larger than the body, then close the connection)."""

    def __init__(self, script):
        self.script, self.paths = list(script), []
        outer = self

        class Handler(BaseHTTPRequestHandler):
            def do_GET(self):
                outer.paths.append(self.path)
                step = outer.script.pop(0)
                if isinstance(step, str) and step.startswith("cut:"):
                    body = step[4:].encode()
                    self.send_response(200)
                    self.send_header("Content-Type", "application/x-ndjson")
                    self.send_header("Content-Length", str(len(body) + 1000))
                    self.end_headers()
                    self.wfile.write(body)
                    self.wfile.flush()
                    self.close_connection = True
                    return
                status, headers, body = step
                data = body.encode() if isinstance(body, str) else json.dumps(body).encode()
                self.send_response(status)
                for k, v in headers.items():
                    self.send_header(k, v)
                self.send_header("Content-Length", str(len(data)))
                self.end_headers()
                self.wfile.write(data)

            def log_message(self, *args):
                pass

        self.httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.httpd.server_address[1]}"
        threading.Thread(target=self.httpd.serve_forever, daemon=True).start()

    def close(self):
        self.httpd.shutdown()
        self.httpd.server_close()


def test_retry_on_503_honours_retry_after_and_gives_up():
    busy = (503, {"Retry-After": "1"}, {"error": {"code": "queue_full", "message": "try again"}})
    limited = (429, {"Retry-After": "0"}, {"error": {"code": "rate_limited", "message": "slow down"}})
    ok = (200, {"Content-Type": "application/json"},
          {"batch_id": "b1", "scene_id": "s1", "state": "running", "done": 1, "total": 2, "progress": 0.5})
    busy_now = (503, {"Retry-After": "0"}, {"error": {"code": "queue_full", "message": "try again"}})
    stand_in = StandIn([busy, limited, ok] + [busy_now] * 3)
    try:
        with Client(stand_in.url, retries=2, backoff_s=0.01) as c:
            t0 = time.monotonic()
            st = c.batch("b1")
            assert st.state == "running" and st.done == 1 and time.monotonic() - t0 >= 0.9  # waited Retry-After
            assert len(stand_in.paths) == 3
            with pytest.raises(ServerError) as e:  # 503 on every try: gives up after 1 + 2 retries
                c.batch("b1")
            assert e.value.status == 503 and e.value.code == "queue_full" and len(stand_in.paths) == 6
    finally:
        stand_in.close()


def test_iter_results_resumes_after_a_cut_stream():
    line = lambda i: json.dumps({"index": i, "solution": {}}) + "\n"  # noqa: E731
    stand_in = StandIn(["cut:" + line(0) + line(1), (200, {}, line(2) + line(3))])
    try:
        with Client(stand_in.url, retries=2, backoff_s=0.01) as c:
            assert [r["index"] for r in c.iter_results("b1")] == [0, 1, 2, 3]
        # read a page at a time (api.client.RESULTS_PAGE lines), the cut page resumed after its last line
        assert stand_in.paths == ["/v1/batches/b1/results?offset=0&limit=1000",
                                  "/v1/batches/b1/results?offset=2&limit=1000"]
    finally:
        stand_in.close()


def test_connection_refused_is_retried_then_raised():
    with Client(f"http://127.0.0.1:{free_port()}", retries=2, backoff_s=0.01) as c:
        with pytest.raises(ConnectionFailed) as e:
            c.get_scene("abc")
    assert isinstance(e.value, ShadowoptError) and e.value.status is None


@pytest.mark.server
def test_client_import_needs_no_rendering_stack():
    code = ("import sys, shadowopt.api.client; "
            "print(sorted({m.split('.')[0] for m in sys.modules} & {'numpy', 'mitsuba', 'drjit', 'fastapi', "
            "'torch', 'pxr', 'scipy'}))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


# -- typed answers, the README's client examples, progress in a log file ----------------------------

@pytest.mark.server
def test_optimize_and_results_are_typed_models(alice):
    from shadowopt.api.schemas import BatchResultLine, LightSolution, Solution

    scene = alice.upload_scene(DEMO)
    sol = alice.optimize(scene.scene_id, TINY_RIG, method="focused")
    assert isinstance(sol, Solution) and isinstance(sol.lights[0], LightSolution)
    m = sol.lights[0].cascades[0]
    assert len(m.view_matrix) == len(m.projection_matrix) == len(m.texture_matrix) == 16
    assert m.resolution == (256, 256) and m.split[0] < m.split[1]
    assert sol["lights"][0]["cascades"][0]["resolution"] == [256, 256]  # read as the JSON too
    assert alice.evaluate(scene.scene_id, TINY_RIG, sol)["receiver_pixels"] > 0  # a Solution goes back in
    batch = alice.submit_batch(scene.scene_id, [TINY_RIG], method="focused")
    assert alice.wait(batch, progress=False, poll_s=0.1, timeout=120).state == "done"
    (ok,) = list(alice.iter_results(batch))
    assert isinstance(ok, BatchResultLine) and ok.ok and ok.resolved["camera"]["usd_path"] == "/World/Camera"
    failed = BatchResultLine.model_validate({"index": 1, "error": {"code": "invalid_rig", "message": "x"}})
    assert not failed.ok and failed["error"]["code"] == "invalid_rig"
    replay = ok.solution()
    assert isinstance(replay, Solution) and replay.lights[0].cascades[0].resolution == (256, 256)
    with pytest.raises(ValueError, match="configuration 1 failed"):
        failed.solution()


def _readme_python_blocks(section: str) -> list[str]:
    text = (REPO / "README.md").read_text()
    part = text[text.index(section):]
    part = part[:part.index("\n## ", 1)]
    blocks, rest = [], part
    while "```python\n" in rest:
        rest = rest[rest.index("```python\n") + len("```python\n"):]
        blocks.append(rest[:rest.index("```")])
    return blocks


@pytest.mark.server
def test_readme_client_examples_run_verbatim(server, monkeypatch, capsys):
    """The README's Python client blocks, as printed, against a real server: the camera-path batch's lines
    echo the demo USD camera's own field of view (2 atan(20.25 / 36), from its aperture and focal length; not
    the 60 deg default) at each path position, and its segments are the runs of cameras whose maps share a
    warp kind and resolution (computed here from the lines themselves)."""
    import math

    blocks = _readme_python_blocks("## Python client")
    assert len(blocks) == 2
    monkeypatch.setenv("SHADOWOPT_URL", server)
    monkeypatch.setenv("SHADOWOPT_TOKEN", TOKENS["alice"])
    monkeypatch.chdir(REPO)
    ns: dict = {}
    for block in blocks:
        exec(compile(block, "README.md", "exec"), ns)
    c, batch = ns["c"], ns["batch"]
    try:
        assert ns["solution"].lights[0].predicted_error["p95_m"] > 0
        lines = list(c.iter_results(batch))
        assert [l.index for l in lines] == [0, 1, 2, 3]
        fov = math.degrees(2 * math.atan(20.25 / 36))
        xs = [l.resolved["camera"]["position"][0] for l in lines]
        assert xs == pytest.approx([0, 2, 4, 6])
        assert all(l.resolved["camera"]["fov_y_deg"] == pytest.approx(fov, abs=1e-3) for l in lines)
        kinds = [tuple((m.warp.kind, m.resolution) for m in l.lights[0].cascades) for l in lines]
        want = [[0, 0]]
        for i in range(1, 4):
            if kinds[i] == kinds[i - 1]:
                want[-1][1] = i
            else:
                want.append([i, i])
        hints = c.batch(batch).interpolation
        assert hints["segments"] == want
        assert len(hints["breaks"]) == len(want) - 1
        out = capsys.readouterr()
        assert str(want) in out.out
    finally:
        c.close()


def test_progress_in_a_log_file_is_a_line_every_few_seconds():
    """Not a terminal: one newline-terminated line at the start, then at most one per LOG_INTERVAL_S of the
    (stand-in) clock, and the final state once; a terminal gets tqdm; off is nothing."""
    import io

    from shadowopt.api.progress import LOG_INTERVAL_S, progress_bar, progress_mode

    now = [0.0]
    log = io.StringIO()
    bar = progress_bar(200, "batch b1", enabled=True, stream=log, clock=lambda: now[0])
    for k in range(200):  # 200 updates over 50 s
        now[0] = k * 0.25
        bar.set_postfix_str("running", refresh=True)
        bar.update(1)
    bar.set_postfix_str("done")
    bar.close()
    lines = log.getvalue().splitlines()
    assert "\r" not in log.getvalue() and log.getvalue().endswith("\n")
    assert 2 <= len(lines) <= 50 / LOG_INTERVAL_S + 2, lines
    assert lines[-1] == "batch b1: 200/200 conf done"

    class Tty(io.StringIO):
        def isatty(self):
            return True

    assert progress_mode(True, Tty()) == "bar" and progress_mode(True, io.StringIO()) == "log"
    assert progress_mode(False, Tty()) == "off" and progress_bar(3, "x", enabled=False) is None
    assert type(progress_bar(3, "x", stream=Tty())).__name__ == "tqdm"


@pytest.mark.server
def test_the_server_does_not_import_the_cli():
    code = "import sys, shadowopt.api.server; print('shadowopt.api.cli' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"
