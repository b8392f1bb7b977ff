"""Start `shadowopt serve` as a real uvicorn process on 127.0.0.1 for the REST tests."""
from __future__ import annotations

import contextlib
import os
import socket
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import httpx

REPO = Path(__file__).resolve().parents[1]
DEMO = REPO / "configs" / "demo_scene.usda"
TOKENS = {"alice": "alice-token-0001", "bob": "bob-token-0002", "carol": "carol-token-0003"}
TINY_RIG = {"camera": {"usd_path": "/World/Camera", "resolution": [160, 90]},
            "lights": [{"usd_path": "/World/Sun"}],
            "shadow": {"resolution": [256, 256]}, "coarse_long_side": 48}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def auth(name: str) -> dict:
    return {"Authorization": f"Bearer {TOKENS[name]}"}


@dataclass
class Server:
    base: str
    proc: subprocess.Popen
    data_dir: Path
    log_path: Path

    def log(self) -> str:
        return self.log_path.read_text() if self.log_path.exists() else ""


def launch(data_dir: Path, env: dict | None = None, tokens: dict | None = TOKENS, port: int | None = None,
           args: tuple = (), new_session: bool = False) -> Server:
    """Start the server (not waiting for it). `env` adds SHADOWOPT_* settings. With `new_session` the
    server leads its own process group (its batch workers included), for tests that kill it."""
    port = port or free_port()
    full_env = {k: v for k, v in os.environ.items() if not k.startswith("SHADOWOPT_")}
    if tokens:
        full_env["SHADOWOPT_TOKENS"] = ",".join(f"{n}={t}" for n, t in tokens.items())
    full_env.update(env or {})
    exe = Path(sys.executable).with_name("shadowopt")
    data_dir.mkdir(parents=True, exist_ok=True)
    log_path = data_dir.parent / f"{data_dir.name}-server-{port}.log"
    log = open(log_path, "a")
    proc = subprocess.Popen([str(exe), "serve", "--host", "127.0.0.1", "--port", str(port), "--data-dir",
                             str(data_dir), *args], cwd=REPO, env=full_env, stdout=log, stderr=subprocess.STDOUT,
                            start_new_session=new_session)
    log.close()
    return Server(f"http://127.0.0.1:{port}", proc, data_dir, log_path)


def wait_ready(server: Server, timeout: float = 180.0) -> list[int]:
    """Poll /healthz until 200; the statuses seen on the way."""
    statuses = []
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if server.proc.poll() is not None:
            raise RuntimeError(f"server exited with {server.proc.returncode}:\n{server.log()[-4000:]}")
        try:
            r = httpx.get(server.base + "/healthz", timeout=2)
            statuses.append(r.status_code)
            if r.status_code == 200:
                return statuses
        except httpx.TransportError:
            pass
        time.sleep(0.05)
    raise RuntimeError(f"server not ready in {timeout} s:\n{server.log()[-4000:]}")


def stop(server: Server) -> None:
    if server.proc.poll() is None:
        server.proc.terminate()
        try:
            server.proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            server.proc.kill()
            server.proc.wait(timeout=30)


@contextlib.contextmanager
def running(data_dir: Path, env: dict | None = None, tokens: dict | None = TOKENS):
    server = launch(data_dir, env, tokens)
    try:
        server.statuses = wait_ready(server)
        yield server
    finally:
        stop(server)


def upload(base: str, who: str, path: Path = DEMO, name: str | None = None) -> httpx.Response:
    return httpx.post(f"{base}/v1/scenes", params={"filename": name or path.name}, content=path.read_bytes(),
                      headers={**auth(who), "Content-Type": "application/octet-stream"}, timeout=60)
