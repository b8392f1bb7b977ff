"""Batch throughput: configurations per second on the demo scene for 1 and 2 workers, local pool and Ray.

Each (backend, workers) gets a fresh runner. The first batch ("cold") includes starting the worker
processes, imports, the scene load and the kernels' first compile; the same batch again on the same
runner ("warm", the best of `repeats` batches: the machine is shared) is the steady state a server with a
running pool sees.
"""
from __future__ import annotations

import os
import sys
import tempfile
import time

from ..batch_request import expand_configurations
from ..job_runner import BatchRunner
from ..store import Store
from .definitions import ROOT
from .output import machine, write_section

SCENE = ROOT / "configs" / "demo_scene.usda"


def sun_arc_request(samples: int) -> dict:
    """The demo camera (1280x720, coarse 180 px) with one 2048² map, a sun arc from 10 to 80 degrees."""
    return {"rig": {"camera": {"usd_path": "/World/Camera", "resolution": [1280, 720]},
                    "lights": [{"usd_path": "/World/Sun"}], "shadow": {"resolution": [2048, 2048], "cascades": 1}},
            "sun_arc": {"azimuth_deg": [200, 260], "elevation_deg": [10, 80], "samples": samples}}


def _timed_batch(runner: BatchRunner, store, scene_id: str, configs: list[dict], method: str) -> tuple[float, dict]:
    t0 = time.perf_counter()
    batch_id = store.create_batch("bench", scene_id, configs, {"method": method})
    runner.submit("bench", batch_id)
    runner.wait(batch_id)
    return time.perf_counter() - t0, store.batch("bench", batch_id)


def measure(backend: str, workers: int, configs: list[dict], method: str, repeats: int = 3) -> dict:
    with tempfile.TemporaryDirectory(prefix="shadowopt-bench-batch-") as tmp:
        store = Store(tmp)
        scene_id = store.link_scene("bench", SCENE)
        runner = BatchRunner(store, backend=backend, workers=workers)
        try:
            cold, st_cold = _timed_batch(runner, store, scene_id, configs, method)
            warm_runs = [_timed_batch(runner, store, scene_id, configs, method) for _ in range(repeats)]
            warm = min(t for t, _ in warm_runs)
        finally:
            runner.shutdown()
            store.close()
    failed = st_cold["failed"] + sum(st["failed"] for _, st in warm_runs)
    return {"backend": backend, "workers": workers, "configurations": len(configs), "cold_s": round(cold, 3),
            "warm_s": round(warm, 3), "warm_per_s": round(len(configs) / warm, 2),
            "cold_per_s": round(len(configs) / cold, 2), "failed": failed}


def bench_batch(validate_rig, configurations: int = 20, workers: tuple[int, ...] = (1, 2),
                backends: tuple[str, ...] = ("local", "ray"), method: str = "optimized", write: bool = True) -> dict:
    """Throughput table for each backend and worker count; Ray is skipped when it is not installed."""
    configs = [{"rig": validate_rig(c["rig"])} for c in expand_configurations(sun_arc_request(configurations))]
    rows, skipped = [], {}
    load_before = os.getloadavg()[0]
    for backend in backends:
        if backend == "ray":
            try:
                import ray  # noqa: F401  # lazy: the optional `ray` extra; its rows are skipped without it
            except ImportError:
                skipped["ray"] = "ray is not installed"
                continue
        for n in workers:
            print(f"bench batch: {backend}, {n} worker(s)", file=sys.stderr)
            rows.append(measure(backend, n, configs, method))
    load = (load_before, os.getloadavg()[0])
    lines = [f"Demo scene, {configurations} configurations of a sun arc (elevation 10-80 deg), method {method}, "
             "camera 1280x720 (coarse 180 px), one 2048² map. Cold: a fresh runner (process or actor start-up, "
             "imports, scene load, first compile) included; warm: the same batch again on that runner, best of 3. "
             f"Load average {load[0]:.1f} before, {load[1]:.1f} after (other work shares these {os.cpu_count()} cores).\n",
             "| backend | workers | cold (s) | cold configs/s | warm (s) | **warm configs/s** | failed |",
             "|---|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['backend']} | {r['workers']} | {r['cold_s']:.2f} | {r['cold_per_s']:.2f} | "
                     f"{r['warm_s']:.2f} | **{r['warm_per_s']:.2f}** | {r['failed']} |")
    for name, why in skipped.items():
        lines.append(f"| {name} | skipped: {why} |||||")
    table = "\n".join(lines)
    if write:
        write_section("batch", table, f"shadowopt bench batch --lights {configurations}")
    return {"benchmark": "batch", "machine": machine(), "rows": rows, "skipped": skipped, "load_average": load,
            "table": table}
