"""Load benchmark of the REST service (issue 5): latency end to end and throughput under load.

Starts `shadowopt serve` in a subprocess (temporary data directory, one token, the per-token rate
limit turned off so the benchmark measures the service and not the limiter), uploads the demo scene,
warms every workload, then for each workload (optimize, optimize with 4 cascades, evaluate):
one client sending requests back to back, and 4 concurrent clients for `seconds`. Every request
carries a light direction no earlier request had, so nothing can come from a result cache.
Talks HTTP with httpx directly (the service layer does not import the api package's client).
"""
from __future__ import annotations

import json
import math
import os
import secrets
import socket
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import httpx

from .output import write_section

ROOT = Path(__file__).resolve().parents[2]
DEMO_SCENE = ROOT / "configs" / "demo_scene.usda"
DEMO_RIG = ROOT / "configs" / "demo_rig.json"
TARGET_P50_MS, TARGET_P99_MS = 30.0, 250.0  # optimize, from issue 5
GOLDEN = (math.sqrt(5) - 1) / 2


def light_direction(i: int) -> list[float]:
    """The i-th sun direction (the way light travels): azimuth by the golden angle, elevation 20-75 deg
    by a second irrational sequence, so no two requests share a direction."""
    az = 2 * math.pi * ((i * GOLDEN) % 1.0)
    el = math.radians(20 + 55 * ((i * math.sqrt(2)) % 1.0))
    return [-math.cos(el) * math.cos(az), -math.sin(el), -math.cos(el) * math.sin(az)]


@dataclass
class Stats:
    latencies_ms: list[float] = field(default_factory=list)
    server_ms: list[float] = field(default_factory=list)
    overhead_ms: list[float] = field(default_factory=list)  # end to end minus the answer's own timings_ms.total
    errors: dict[str, int] = field(default_factory=dict)
    elapsed_s: float = 0.0

    def add_error(self, what: str) -> None:
        self.errors[what] = self.errors.get(what, 0) + 1

    def summary(self) -> dict:
        lat = sorted(self.latencies_ms)
        n_err = sum(self.errors.values())
        return {"requests": len(lat) + n_err, "ok": len(lat), "errors": n_err, "error_kinds": dict(self.errors),
                "p50_ms": percentile(lat, 50), "p95_ms": percentile(lat, 95), "p99_ms": percentile(lat, 99),
                "max_ms": round(lat[-1], 2) if lat else None, "elapsed_s": round(self.elapsed_s, 2),
                "throughput_rps": round(len(lat) / self.elapsed_s, 2) if self.elapsed_s else None,
                "server_p50_ms": percentile(sorted(self.server_ms), 50),
                "overhead_p50_ms": percentile(sorted(self.overhead_ms), 50)}


def percentile(sorted_values: list[float], q: float) -> float | None:
    """Nearest-rank percentile of an ascending list."""
    if not sorted_values:
        return None
    k = max(0, math.ceil(q / 100 * len(sorted_values)) - 1)
    return round(sorted_values[k], 2)


# ---------------------------------------------------------------- the server under test

def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start_server(data_dir: Path, token: str | None, port: int, tokens: dict | None = None) -> subprocess.Popen:
    """`shadowopt serve` with the bench token (or `tokens`, name -> token) and the rate limit off."""
    tokens = tokens or {"bench": token}
    env = {**os.environ, "SHADOWOPT_TOKENS": ",".join(f"{n}={t}" for n, t in tokens.items()),
           "SHADOWOPT_RATE_LIMIT_PER_S": "0"}
    exe = Path(sys.executable).with_name("shadowopt")
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "shadowopt.api.cli"]
    log = open(data_dir / "server.log", "w")
    return subprocess.Popen(cmd + ["serve", "--host", "127.0.0.1", "--port", str(port), "--data-dir", str(data_dir)],
                            cwd=ROOT, env=env, stdout=log, stderr=subprocess.STDOUT)


def wait_healthy(base: str, proc: subprocess.Popen, log_path: Path, timeout: float = 300.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"server exited with {proc.returncode}:\n{log_path.read_text()[-3000:]}")
        try:
            if httpx.get(base + "/healthz", timeout=2).status_code == 200:
                return
        except httpx.TransportError:
            pass
        time.sleep(0.2)
    raise RuntimeError(f"server not ready after {timeout} s:\n{log_path.read_text()[-3000:]}")


def stop_server(proc: subprocess.Popen) -> None:
    proc.terminate()
    try:
        proc.wait(timeout=30)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


# ---------------------------------------------------------------- workloads

class Workload:
    """Builds the i-th request body of one kind; every body has its own light direction."""

    def __init__(self, name: str, path: str, scene_id: str, cascades: int, solutions: list | None = None):
        self.name, self.path, self.scene_id, self.cascades, self.solutions = name, path, scene_id, cascades, solutions
        base = json.loads(DEMO_RIG.read_text())
        base["shadow"]["cascades"] = cascades
        self.base_rig = base

    def rig(self, direction: list[float]) -> dict:
        return {**self.base_rig, "lights": [{"type": "directional", "direction": direction}]}

    def body(self, i: int) -> dict:
        if self.solutions is None:
            return {"scene_id": self.scene_id, "rig": self.rig(light_direction(i))}
        # evaluate: a solution of the pool, for a rig whose sun is turned by a small, request-unique angle
        direction, solution = self.solutions[i % len(self.solutions)]
        return {"scene_id": self.scene_id, "rig": self.rig(jitter(direction, i)), "solution": solution}


def jitter(d: list[float], i: int, max_deg: float = 0.5) -> list[float]:
    """`d` turned by up to `max_deg` degrees about an axis that depends on i (a unique direction per i)."""
    a = math.radians(max_deg) * ((i * GOLDEN) % 1.0 + 1e-3)
    t = [d[1], -d[0], 0.0] if abs(d[2]) > 0.5 else [0.0, d[2], -d[1]]
    n = math.sqrt(sum(v * v for v in t))
    t = [v / n for v in t]
    b = [d[1] * t[2] - d[2] * t[1], d[2] * t[0] - d[0] * t[2], d[0] * t[1] - d[1] * t[0]]
    phi = 2 * math.pi * ((i * math.sqrt(3)) % 1.0)
    off = [math.cos(phi) * t[k] + math.sin(phi) * b[k] for k in range(3)]
    return [math.cos(a) * d[k] + math.sin(a) * off[k] for k in range(3)]


class Counter:
    """Request numbers shared by all client threads (a fresh direction per request)."""

    def __init__(self, start: int):
        self._n, self._lock = start, threading.Lock()

    def next(self) -> int:
        with self._lock:
            self._n += 1
            return self._n


def one_request(http: httpx.Client, work: Workload, i: int, stats: Stats) -> None:
    t0 = time.perf_counter()
    try:
        r = http.post(work.path, json=work.body(i))
    except httpx.HTTPError as e:
        stats.add_error(type(e).__name__)
        return
    ms = (time.perf_counter() - t0) * 1e3
    if r.status_code != 200:
        try:
            code = r.json()["error"]["code"]
        except Exception:
            code = ""
        stats.add_error(f"{r.status_code} {code}".strip())
        return
    stats.latencies_ms.append(ms)
    server = (r.json().get("timings_ms") or {}).get("total")
    if server is not None:
        stats.server_ms.append(float(server))
        stats.overhead_ms.append(ms - float(server))


def run_sequential(client_args: dict, work: Workload, counter: Counter, max_requests: int, max_s: float) -> Stats:
    stats = Stats()
    with httpx.Client(**client_args) as http:
        t0 = time.perf_counter()
        for _ in range(max_requests):
            one_request(http, work, counter.next(), stats)
            if time.perf_counter() - t0 > max_s:
                break
        stats.elapsed_s = time.perf_counter() - t0
    return stats


def run_concurrent(client_args: dict, work: Workload, counter: Counter, clients: int, seconds: float) -> Stats:
    stats = Stats()  # list.append and the error dict update are safe enough under the GIL for counting
    lock = threading.Lock()
    t_end = time.perf_counter() + seconds

    def client_loop():
        local = Stats()
        with httpx.Client(**client_args) as http:
            while time.perf_counter() < t_end:
                one_request(http, work, counter.next(), local)
        with lock:
            stats.latencies_ms += local.latencies_ms
            stats.server_ms += local.server_ms
            stats.overhead_ms += local.overhead_ms
            for k, v in local.errors.items():
                stats.errors[k] = stats.errors.get(k, 0) + v

    threads = [threading.Thread(target=client_loop, name=f"load-client-{k}") for k in range(clients)]
    t0 = time.perf_counter()
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    stats.elapsed_s = time.perf_counter() - t0
    return stats


def solution_pool(http: httpx.Client, scene_id: str, n: int, start: int) -> list:
    """n (direction, optimized solution) pairs for the evaluate workload."""
    work = Workload("pool", "/v1/optimize", scene_id, 1)
    pool = []
    for i in range(start, start + n):
        d = light_direction(i)
        r = http.post("/v1/optimize", json={"scene_id": scene_id, "rig": work.rig(d)})
        r.raise_for_status()
        pool.append((d, r.json()))
    return pool


# ---------------------------------------------------------------- the benchmark

def bench_load(seconds: float = 60.0, clients: int = 4, sequential_requests: int = 200,
               sequential_max_s: float = 20.0, write: bool = True, log=print) -> dict:
    """Run the three workloads against a fresh server; returns {"workloads", "table"} and writes the
    table into BENCHMARKS.md (section `load`) when `write`."""
    token = secrets.token_urlsafe(16)
    port = free_port()
    base = f"http://127.0.0.1:{port}"
    client_args = {"base_url": base, "headers": {"Authorization": f"Bearer {token}"}, "timeout": 120.0}
    results, load_avg = {}, [os.getloadavg()[0]]
    with tempfile.TemporaryDirectory(prefix="shadowopt-load-") as tmp:
        data_dir = Path(tmp)
        t0 = time.perf_counter()
        proc = start_server(data_dir, token, port)
        try:
            wait_healthy(base, proc, data_dir / "server.log")
            ready_s = time.perf_counter() - t0
            with httpx.Client(**client_args) as http:
                up = http.post("/v1/scenes", files={"file": (DEMO_SCENE.name, DEMO_SCENE.read_bytes())})
                up.raise_for_status()
                scene_id = up.json()["scene_id"]
                log(f"load: server ready in {ready_s:.1f} s, demo scene {scene_id}; building the evaluate pool")
                pool = solution_pool(http, scene_id, 16, start=10_000_000)
            workloads = [Workload("optimize", "/v1/optimize", scene_id, 1),
                         Workload("optimize, 4 cascades", "/v1/optimize", scene_id, 4),
                         Workload("evaluate", "/v1/evaluate", scene_id, 1, solutions=pool)]
            counter = Counter(0)
            for work in workloads:  # warm: kernels for every coarse size and cascade count compile here
                run_sequential(client_args, work, counter, 5, 60.0)
            for work in workloads:
                log(f"load: {work.name}: 1 client back to back")
                seq = run_sequential(client_args, work, counter, sequential_requests, sequential_max_s)
                log(f"load: {work.name}: {clients} clients for {seconds:g} s")
                conc = run_concurrent(client_args, work, counter, clients, seconds)
                results[work.name] = {"sequential": seq.summary(), "concurrent": conc.summary()}
                load_avg.append(os.getloadavg()[0])
        finally:
            stop_server(proc)
    table = load_table(results, clients, seconds, sequential_requests, sequential_max_s, load_avg)
    table += f" Code: the working tree at commit {git_commit()}." if git_commit() else ""
    command = "shadowopt bench load" + (f" --seconds {seconds:g}" if seconds != 60 else "")
    if write:
        write_section("load", table, command)
    return {"workloads": results, "table": table, "ready_s": round(ready_s, 2)}


def git_commit() -> str | None:
    try:
        out = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                             timeout=10)
    except (OSError, subprocess.TimeoutExpired):
        return None
    return out.stdout.strip() or None


def load_table(results: dict, clients: int, seconds: float, seq_n: int = 200, seq_s: float = 20.0,
               load_avg: list[float] | None = None) -> str:
    head = ("| workload | clients | requests | errors | p50 ms | p95 ms | p99 ms | max ms | req/s | "
            "server p50 ms | queue + HTTP p50 ms | target |\n|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|")
    rows = []
    for name, r in results.items():
        for kind, s in (("sequential", r["sequential"]), ("concurrent", r["concurrent"])):
            n = 1 if kind == "sequential" else clients
            rows.append(f"| {name} | {n} | {s['requests']} | {s['errors']} | {_f(s['p50_ms'])} | {_f(s['p95_ms'])} | "
                        f"{_f(s['p99_ms'])} | {_f(s['max_ms'])} | {_f(s['throughput_rps'])} | "
                        f"{_f(s['server_p50_ms'])} | {_f(s['overhead_p50_ms'])} | {_verdict(name, kind, s)} |")
    errors = {f"{name} ({kind})": s["error_kinds"] for name, r in results.items()
              for kind, s in r.items() if s["error_kinds"]}
    notes = (f"\n\nThe demo scene and rig (`configs/demo_rig.json`: 1280x720 camera, one 2048² map, coarse long side "
             f"180), method `optimized` (default solver); every request has its own sun direction (evaluate: a "
             f"solution for a nearby direction, the rig's sun turned by < 0.5°). 1 client: {seq_n} requests back to "
             f"back (or as many as fit in {seq_s:g} s); {clients} clients: {seconds:g} s of back-to-back requests each. "
             f"End to end = HTTP request to parsed answer on 127.0.0.1, measured by the client; server p50 = the "
             f"answer's own `timings_ms.total` (the solve or evaluation); queue + HTTP = end to end minus that, per "
             f"request: waiting for one of the server's solver threads (`solve_threads`, 2) plus HTTP and JSON. The "
             f"per-token rate limit is off for the run. The load generator, the server and other agents' jobs share the "
             f"machine's cores"
             + (f" (1-minute load average {', '.join(f'{v:.1f}' for v in load_avg)} at the start and after each "
                f"workload)" if load_avg else "") + ", so these numbers are upper bounds for a dedicated machine.")
    if errors:
        notes += f"\n\nErrors: {json.dumps(errors)}"
    return head + "\n" + "\n".join(rows) + notes


def _f(v) -> str:
    return "-" if v is None else f"{v:.1f}" if isinstance(v, float) else str(v)


def _verdict(name: str, kind: str, s: dict) -> str:
    """Issue 5's targets are for optimize requests (1 or 4 cascades); evaluate is reported."""
    if not name.startswith("optimize"):
        return "reported"
    if kind == "sequential":
        ok = s["p50_ms"] is not None and s["p50_ms"] <= TARGET_P50_MS
        return f"p50 ≤ {TARGET_P50_MS:g} ms: {'met' if ok else 'NOT met'}"
    ok = s["errors"] == 0 and s["p99_ms"] is not None and s["p99_ms"] <= TARGET_P99_MS
    return f"0 errors, p99 ≤ {TARGET_P99_MS:g} ms: {'met' if ok else 'NOT met'}"
