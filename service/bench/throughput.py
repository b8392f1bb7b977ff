"""Path throughput: frames per second of a path job on the demo scene, per method, on the local pool and on
Ray with 1 and 2 workers, and where each frame's time goes.

The path is the demo's walk (configs/demo_scene.usda, its camera and sun; keyframes from (0, 1.7, 0) to
(6, 1.7, 2) looking at (0, 1, 20)) sampled at `frames` frames, solved as a path job is (service.paths:
a batch in a Store, results streamed in frame order as run_path streams them), with one map of
`map_side`² texels on a 320x180 rig: the path benchmark's screen and texel budget (`shadowopt bench path`),
and for the coarse pass the same work as any rig up to 360 px wide (180 coarse pixels, an edge pass at
2 fine rays per coarse pixel side); a 1280x720 rig traces 6 per side (about 8x the edge pass's rays).

Each (backend, workers) gets a fresh runner. Its first run ("cold") includes starting the workers
(imports, the scene load, the kernels' first compile from Dr.Jit's disk cache); the runs after it reuse
the workers, as a server with a running pool does. Per method: `repeats` runs of `short` frames (their
median frames/s), and on the local pool with the most workers one run of the whole `frames`-frame path
(and the first CHUNK_COMPARE frames of it in tasks of several frames and in tasks of one).
Method path is solved as a path job solves it: runs of up to job_kinds.WHOLE_PATH_FRAMES consecutive frames,
each run solved together by one worker (service.solve.solve_path), the runs in parallel.

Stages, per frame: the coarse pass and the rest of the solve as each solution's timings_ms reports them
(in the worker), the time outside any solve (workers x wall - the solves' sum: task round trips, idle
workers at the ends, cores taken by the parent or other processes), the parent's store commits
(Store.put_outcomes), its creating the batch (Store.create_batch), and the streaming reader (the result
lines read back in frame order and encoded as run_path's on_line sees them).
"""
from __future__ import annotations

import os
import statistics
import sys
import tempfile
import time

from .. import job_kinds
from ..job_kinds import WHOLE_PATH_FRAMES
from ..job_runner import BatchRunner
from ..job_workers import llvm_path
from ..paths import expand_path, is_coherent, is_whole_path, line_json
from ..scenes import SceneCache
from ..store import Store, UNFINISHED
from .definitions import ROOT
from .output import machine, write_section

SCENE = ROOT / "configs" / "demo_scene.usda"
METHODS = ("focused", "stable_csm", "optimized", "path")
SCREEN = (320, 180)
KEYFRAMES = [{"position": [0.0, 1.7, 0.0], "target": [0.0, 1.0, 20.0]},
             {"position": [6.0, 1.7, 2.0], "target": [0.0, 1.0, 20.0]}]
TARGET_FPS = 50.0
CHUNK_COMPARE = 240  # frames of the run with tasks of several frames against one frame per task


def path_frames(validate_rig, frames: int, screen=SCREEN, map_side: int = 1024) -> list[dict]:
    """The demo walk as validated path frames ({"rig", "frame", "time"})."""
    base = {"camera": {"usd_path": "/World/Camera", "resolution": list(screen)},
            "lights": [{"usd_path": "/World/Sun"}], "shadow": {"resolution": [map_side, map_side], "cascades": 1}}
    out = expand_path({"rig": base, "camera_path": {"keyframes": KEYFRAMES, "samples": frames}})
    return [{**f, "rig": validate_rig(f["rig"])} for f in out]


class _Clock:
    """Seconds spent in wrapped callables."""

    def __init__(self):
        self.s = {}

    def wrap(self, name: str, fn):
        def timed(*a, **k):
            t = time.perf_counter()
            try:
                return fn(*a, **k)
            finally:
                self.s[name] = self.s.get(name, 0.0) + time.perf_counter() - t
        return timed


def _settings(method: str, workers: int) -> dict:
    s = {"method": method, "coherent": is_coherent(method, False), "whole_path": is_whole_path(method, False)}
    if s["coherent"] and workers > 1:
        s["coherent_chunks"] = workers
    return s


def _run_path(runner, store, clock: _Clock, scene_id: str, frames: list[dict], method: str, workers: int) -> dict:
    """One path job, streamed in frame order like run_path; its wall time and stages."""
    clock.s.clear()
    t0 = time.perf_counter()
    batch_id = store.create_batch("bench", scene_id, frames, _settings(method, workers))
    runner.submit("bench", batch_id)
    nxt, streamed = 0, 0
    while True:
        state = runner.wait(batch_id, timeout=0.25)
        ts = time.perf_counter()
        for line in store.results("bench", batch_id, offset=nxt):
            nxt = line["index"] + 1
            line_json(line)
            streamed += 1
        clock.s["stream"] = clock.s.get("stream", 0.0) + time.perf_counter() - ts
        if state not in UNFINISHED:
            break
    wall = time.perf_counter() - t0
    st = store.batch("bench", batch_id)
    lines = store.results("bench", batch_id)
    times = [l["timings_ms"] for l in lines if "timings_ms" in l]
    n = len(frames)
    coarse = sum(t.get("coarse", 0.0) for t in times)
    total = sum(t.get("total", 0.0) for t in times)
    return {"frames": n, "wall_s": wall, "fps": n / wall, "failed": st["failed"], "streamed": streamed,
            "ms": {"coarse": coarse / n, "solve": (total - coarse) / n,
                   "outside": max(0.0, wall * 1e3 * workers - total) / n,
                   "store": clock.s.get("put_outcomes", 0.0) * 1e3 / n,
                   "submit": clock.s.get("create_batch", 0.0) * 1e3 / n,
                   "stream": clock.s.get("stream", 0.0) * 1e3 / n}}


def measure(backend: str, workers: int, methods, short: list[dict], repeats: int, long: list[dict] | None,
            log=None) -> dict:
    """One fresh runner: a cold run, then per method `repeats` short runs (and the long path when given)."""
    log = log or (lambda m: None)
    rows = {}
    with tempfile.TemporaryDirectory(prefix="shadowopt-bench-throughput-") as tmp:
        store = Store(tmp)
        clock = _Clock()
        store.put_outcomes = clock.wrap("put_outcomes", store.put_outcomes)
        store.create_batch = clock.wrap("create_batch", store.create_batch)
        scene_id = store.link_scene("bench", SCENE)
        runner = BatchRunner(store, backend=backend, workers=workers)
        try:
            cold = _run_path(runner, store, clock, scene_id, short, methods[0], workers)
            for m in methods:
                log(f"bench throughput: {backend}, {workers} worker(s), {m}")
                runs = [_run_path(runner, store, clock, scene_id, short, m, workers) for _ in range(repeats)]
                med = sorted(runs, key=lambda r: r["fps"])[len(runs) // 2]
                rows[m] = {"fps_runs": [round(r["fps"], 2) for r in runs], "fps": med["fps"], "ms": med["ms"],
                           "failed": sum(r["failed"] for r in runs)}
                if long is not None:
                    log(f"bench throughput: {backend}, {workers} worker(s), {m}, {len(long)} frames")
                    rows[m]["long"] = _run_path(runner, store, clock, scene_id, long, m, workers)
            if backend == "local" and long is not None and methods[0] != "path":
                part = long[:CHUNK_COMPARE]  # tasks of several frames against one frame per task
                rows["chunked"] = _run_path(runner, store, clock, scene_id, part, methods[0], workers)
                saved = job_kinds.CHUNK
                job_kinds.CHUNK = 1
                try:
                    rows["chunk1"] = _run_path(runner, store, clock, scene_id, part, methods[0], workers)
                finally:
                    job_kinds.CHUNK = saved
        finally:
            runner.shutdown()
            store.close()
    return {"backend": backend, "workers": workers, "cold_s": cold["wall_s"],
            "startup_s": max(0.0, cold["wall_s"] - len(short) / rows[methods[0]]["fps"]), "methods": rows}


def _scene_load_s() -> float:
    """Loading the demo scene into a fresh cache (what each worker does once): seconds."""
    t = time.perf_counter()
    SceneCache().get(str(SCENE))
    return time.perf_counter() - t


def bench_throughput(validate_rig, frames: int = 1000, short_frames: int = 40, repeats: int = 3, methods=None,
                     screen=SCREEN, map_side: int = 1024, backends=("local", "ray"), workers=(1, 2),
                     write: bool = True, log=None) -> dict:
    log = log or (lambda m: print(m, file=sys.stderr))
    methods = tuple(methods or METHODS)
    short = path_frames(validate_rig, short_frames, screen, map_side)
    long = path_frames(validate_rig, frames, screen, map_side)
    load_before = os.getloadavg()[0]
    t_start = time.perf_counter()
    results, skipped = [], {}
    for backend in backends:
        ray = None
        if backend == "ray":
            try:
                import ray  # lazy: the optional `ray` extra; its rows are skipped without it
            except ImportError:
                skipped["ray"] = "ray is not installed"
                continue
            if not ray.is_initialized():  # one local instance with a CPU per worker, for every worker count
                llvm = llvm_path()
                ray.init(num_cpus=max(workers), include_dashboard=False, log_to_driver=False,
                         object_store_memory=128 * 1024 * 1024,
                         runtime_env={"env_vars": {"DRJIT_LIBLLVM_PATH": llvm}} if llvm else None)
            else:
                ray = None  # someone else's instance: left running
        try:
            for n in workers:
                results.append(measure(backend, n, methods, short, repeats,
                                       long if backend == "local" and n == max(workers) else None, log))
        finally:
            if ray is not None:
                ray.shutdown()
    load_s = _scene_load_s()
    seconds = time.perf_counter() - t_start
    load = (load_before, os.getloadavg()[0])
    table = _table(results, skipped, methods, frames, short_frames, repeats, screen, map_side, load, load_s, seconds)
    if write:
        write_section("throughput", table, "shadowopt bench throughput"
                      + (f" --frames {frames}" if frames != 1000 else ""))
    return {"benchmark": "throughput", "machine": machine(), "results": results, "skipped": skipped,
            "load_average": load, "scene_load_s": load_s, "seconds": seconds, "table": table}


def _table(results, skipped, methods, frames, short_frames, repeats, screen, map_side, load, load_s, seconds) -> str:
    by = {(r["backend"], r["workers"]): r for r in results}
    top = max((r["workers"] for r in results), default=1)
    lines = [f"Demo scene, a walk of {frames} frames (and {short_frames}-frame runs, median of {repeats}), "
             f"{screen[0]}x{screen[1]} rig, one {map_side}² map; method path in runs of up to {WHOLE_PATH_FRAMES} frames solved together (the whole-path pass), runs in parallel. "
             f"Load average {load[0]:.1f} before, {load[1]:.1f} after on {os.cpu_count()} cores; "
             f"{seconds:.0f} s in all; one scene load {load_s * 1e3:.0f} ms.\n"]
    local = by.get(("local", top))
    if local and any("long" in local["methods"].get(m, {}) for m in methods):
        lines += [f"**{frames}-frame path, local pool, {top} workers** (warm pool; target {TARGET_FPS:g} frames/s):\n",
                  "| method | frames/s | s | with start-up: frames/s | coarse ms/frame | solve ms/frame | outside solves "
                  "| store | submit | stream | failed |",
                  "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
        for m in methods:
            r = local["methods"][m].get("long")
            if r:
                ms = r["ms"]
                cold_fps = r["frames"] / (r["wall_s"] + local["startup_s"])
                lines.append(f"| {m} | **{r['fps']:.1f}** | {r['wall_s']:.1f} | {cold_fps:.1f} | {ms['coarse']:.1f} | {ms['solve']:.1f} | "
                             f"{ms['outside']:.1f} | {ms['store']:.2f} | {ms['submit']:.2f} | {ms['stream']:.2f} | {r['failed']} |")
        for key, what in (("chunked", "tasks of up to 8 frames"), ("chunk1", "one frame per task")):
            c1 = local["methods"].get(key)
            if c1:
                lines.append(f"| {methods[0]}, {c1['frames']} frames, {what} | {c1['fps']:.1f} | {c1['wall_s']:.1f} | | "
                             f"{c1['ms']['coarse']:.1f} | {c1['ms']['solve']:.1f} | {c1['ms']['outside']:.1f} | "
                             f"{c1['ms']['store']:.2f} | {c1['ms']['submit']:.2f} | {c1['ms']['stream']:.2f} | {c1['failed']} |")
        lines.append("")
    lines += [f"**Scaling** ({short_frames}-frame paths, median frames/s of {repeats}; cold: the first run on a fresh "
              "runner, start-up included):\n",
              "| backend | workers | cold (s) | start-up (s) | " + " | ".join(methods) + " |",
              "|---|---:|---:|---:|" + "---:|" * len(methods)]
    for r in results:
        lines.append(f"| {r['backend']} | {r['workers']} | {r['cold_s']:.1f} | {r['startup_s']:.1f} | "
                     + " | ".join(f"{r['methods'][m]['fps']:.1f}" for m in methods) + " |")
    for b in sorted({r["backend"] for r in results}):
        one, two = by.get((b, 1)), by.get((b, top))
        if one and two and top > 1:
            lines.append(f"| {b} | {top} / 1 | | | " + " | ".join(
                f"{two['methods'][m]['fps'] / one['methods'][m]['fps']:.2f}x" for m in methods) + " |")
    for name, why in skipped.items():
        lines.append(f"| {name} | skipped: {why} |||" + "|" * len(methods))
    lines.append("\nWith start-up: the same path on a fresh pool (the cold run's start-up added: spawning the workers, "
                 "imports, one scene load each, the kernels from Dr.Jit's disk cache), as `shadowopt path` pays it. "
                 "Stages per frame (ms): coarse and solve are the workers' own (each solution's timings_ms); "
                 "outside solves = workers x wall - the solves' sum (round trips, workers idle at the ends, cores "
                 "taken by the parent or other processes); store = the parent's commits, one per task of up to "
                 "8 frames; submit = creating the batch; stream = reading the lines back in frame order.")
    return "\n".join(lines)
