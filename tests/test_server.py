"""The REST service on a real uvicorn server on 127.0.0.1."""
from __future__ import annotations

import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

REPO = Path(__file__).resolve().parents[1]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def server():
    port = free_port()
    exe = Path(sys.executable).with_name("shadowopt")
    proc = subprocess.Popen([str(exe), "serve", "--host", "127.0.0.1", "--port", str(port)], cwd=REPO,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    base = f"http://127.0.0.1:{port}"
    statuses = []
    try:
        deadline = time.time() + 120
        while time.time() < deadline:
            try:
                r = httpx.get(base + "/healthz", timeout=2)
                statuses.append(r.status_code)
                if r.status_code == 200:
                    break
            except httpx.TransportError:
                pass
            assert proc.poll() is None, proc.stdout.read()
            time.sleep(0.1)
        else:
            pytest.fail("server did not become ready in 120 s")
        yield base, statuses
    finally:
        proc.terminate()
        proc.wait(timeout=30)


def test_health_scene_info_and_openapi(server):
    base, statuses = server
    assert statuses[-1] == 200 and set(statuses) <= {200, 503}
    health = httpx.get(base + "/healthz").json()
    assert health["status"] == "ok" and health["scenes"] == 1 and health["preload_errors"] == {}
    scenes = httpx.get(base + "/v1/scenes").json()["scenes"]
    assert len(scenes) == 1 and scenes[0]["source"].endswith("demo_scene.usda")
    info = httpx.get(f"{base}/v1/scenes/{scenes[0]['scene_id']}").json()
    assert info["triangles"] == scenes[0]["triangles"] > 1000
    assert [c["usd_path"] for c in info["cameras"]] == ["/World/Camera"]
    r = httpx.get(base + "/v1/scenes/0000")
    assert r.status_code == 404 and r.json()["detail"]["code"] == "scene_not_found"
    spec = httpx.get(base + "/openapi.json").json()
    assert "/healthz" in spec["paths"] and "404" in spec["paths"]["/v1/scenes/{scene_id}"]["get"]["responses"]
