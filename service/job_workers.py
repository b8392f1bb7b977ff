"""What runs in a worker process (the local spawn pool's, or a Ray actor's): its start-up (die with the
parent, LLVM for Dr.Jit, its share of the cores), the scene loaded once per process, and one task of a job:
configurations solved one after another, a coherent path's frames chained (each given the previous one's
solution), or a whole path's run of frames solved together. Outcomes are {"result": solution} or
{"error": {"code", "message"}}; a task never raises.

Spawned workers import this module before worker_init runs: the solver stack (service.solve, service.scenes,
Dr.Jit) loads only inside the functions, after worker_init set the thread counts and LLVM path."""
from __future__ import annotations

import hashlib
import json
import os
import tempfile
from pathlib import Path

from ..renderers.scene_data import SceneError
from ..solvers.jit import pick_llvm
from .echo import resolved_echo
from .isolation import LoadLimits, die_with_parent
from .request import SolveRequest
from .rigs import RigError, SolutionError, resolve_rig

DEFAULT_METHOD = "optimized"
RESULT_EXTRAS = ("index", "frame", "time")


def previous_of(line: dict | None) -> dict | None:
    """A stored result line as the next frame's `previous` (None for a failed or missing frame)."""
    if not line or "error" in line:
        return None
    return {k: v for k, v in line.items() if k not in RESULT_EXTRAS}


def llvm_path() -> str | None:
    path = pick_llvm()
    if path:
        os.environ.setdefault("DRJIT_LIBLLVM_PATH", path)
    return path


THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def worker_init(llvm: str | None, threads: int | None = None, parent_pid: int | None = None,
                pdeathsig: bool = False) -> None:
    """Runs first in each worker: with `parent_pid` (the local pool) it exits when that process is gone
    (service.isolation.die_with_parent: a SIGKILLed server leaves no worker behind); then LLVM for
    Dr.Jit, and its share of the cores for the math libraries (as Ray does for its workers) unless the
    caller set them."""
    if parent_pid is not None:
        die_with_parent(parent_pid, pdeathsig=pdeathsig)
    if llvm:
        os.environ["DRJIT_LIBLLVM_PATH"] = llvm
    if threads:
        for var in THREAD_VARS:
            os.environ.setdefault(var, str(threads))
        _jit_threads(threads)


def _jit_threads(threads: int) -> None:
    """Dr.Jit's kernel threads in a worker: its share of the cores. Dr.Jit's pool defaults to every core in
    each process, so two workers on two cores ran four kernel threads that spun against each other and
    against NumPy (measured on the demo path: the edge-pass kernel 2.4 ms with one thread, 5-6 ms with two
    while another worker ran). Kernels are element-wise, so results are the same bits (checked on every
    method); solvers.metric.serial_kernels restores this count after its own serial sections."""
    try:
        import drjit as dr  # lazy: optional here, and it must load after worker_init set DRJIT_LIBLLVM_PATH

        dr.set_thread_count(max(1, int(threads)))
    except Exception:  # no Dr.Jit here: nothing to size
        pass


def _solve_with(get_entry, config: dict, settings: dict) -> dict:
    """One configuration: {"result": solution} or {"error": {"code", "message"}}; never raises."""
    try:
        from .solve import solve  # lazy: the solver stack loads after worker_init set the threads and LLVM

        rig = config["rig"]
        entry = get_entry()
        sol = solve(entry, rig, SolveRequest(method=config.get("method") or settings.get("method") or DEFAULT_METHOD,
                    solver=settings.get("solver"), time_budget_ms=settings.get("time_budget_ms"),
                    previous=config.get("previous")))  # a coherent path's previous frame (service.paths)
        if "resolved" not in sol:  # what this configuration was solved for (service.echo)
            sol["resolved"] = resolved_echo(resolve_rig(rig, entry.loaded), rig.get("frame", "world"))
        for k in ("frame", "time", "scene_time"):  # a path job's frame index and time codes (service.paths)
            if k in config:
                sol[k] = config[k]
        if config.get("scene_time") is not None and entry.loaded.warnings:
            # what the loader reported reading the stage at this frame's time code (a mesh skipped there for
            # NaN points, a prim invalid at t): the frame's own load, so its own line says it
            sol["warnings"] = list(entry.loaded.warnings)
        return {"result": sol}
    except SceneError as e:
        t = config.get("scene_time")
        where = f"the stage at time code {t:g}: " if isinstance(t, (int, float)) else ""
        return {"error": {"code": e.code, "message": where + e.message}}
    except (RigError, SolutionError) as e:
        return {"error": {"code": e.code, "message": str(e)}}
    except (KeyError, TypeError, ValueError, IndexError) as e:
        return {"error": {"code": "invalid_configuration", "message": f"{type(e).__name__}: {e}"}}
    except Exception as e:  # keep the batch going; the message says what broke
        return {"error": {"code": "internal_error", "message": f"{type(e).__name__}: {e}"}}


def worker_entry(scene_path: str, sandbox: bool, settings: dict, time_code: float | None = None):
    """The scene in a worker, loaded once per process by the SCENES cache, in-process (the worker is its
    own process already) but under the server's triangle limit (settings["max_triangles"], set by the
    runner from its own max_triangles, never from what was stored with the batch): a scene stored before
    the limit existed, or before it was lowered, is refused as too_many_triangles like a new upload.
    An upload read at a path frame's time code (`time_code`, the frame's "scene_time") is a new load of the
    stage, which the upload's check at its default time says nothing about (a stage can be light there and
    heavy at t = 5): it runs as an upload's load does, in an isolated child under the server's load limits
    (settings["load_limits"]: max_triangles, memory_bytes, timeout_s, set by the runner; isolation's
    defaults without them), and over one of them the frame fails with that limit's SceneError."""
    from .scenes import SCENES  # lazy: the renderers load after worker_init set the threads and LLVM

    global _WORKER_CACHE_SET
    cache = settings.get("worker_cache")
    if _WORKER_CACHE_SET != cache:  # the server's worker_cache_bytes and tenant_cache_share (issue 27: the
        # workers' caches held +2.57 GB outside scene_cache_bytes); without them, one owner and all of it
        if cache:
            SCENES.configure(max_bytes=int(cache["max_bytes"]), tenant_share=float(cache["tenant_share"]))
        else:
            SCENES.configure(tenant_share=1.0)
        _WORKER_CACHE_SET = cache
    # the batch's tenant owns its entries: it loses its own least recently used scenes first, never another
    # tenant's; a scene over its share is served uncached (reloaded per task), not refused (owner, not tenant)
    owner = {"owner": settings.get("tenant")} if cache else {}
    if time_code is not None and sandbox:
        return SCENES.get(scene_path, time_code=time_code, sandbox=sandbox, limits=frame_load_limits(settings), **owner)
    # time_code: a path frame over moving geometry (service.paths: "scene_time"), the stage read at that time
    return SCENES.get(scene_path, time_code=time_code, sandbox=sandbox, max_triangles=settings.get("max_triangles"),
                      **owner)


def frame_load_limits(settings: dict):
    """service.isolation.LoadLimits of a path frame's load of an upload: the runner's load_limits (the server's
    upload limits), the triangle limit the runner sets otherwise, isolation's defaults for the rest."""
    given = dict(settings.get("load_limits") or {})
    if settings.get("max_triangles") is not None:
        given.setdefault("max_triangles", settings["max_triangles"])
    return LoadLimits(**{k: v for k, v in given.items() if k in ("max_triangles", "memory_bytes", "timeout_s")})


_WORKER_CACHE_SET = False  # the worker_cache settings the worker's SCENES was sized from


def solve_configuration(scene_path: str, sandbox: bool, config: dict, settings: dict) -> dict:
    """Worker entry point (local pool)."""
    return _solve_with(lambda: worker_entry(scene_path, sandbox, settings, config.get("scene_time")), config, settings)


def _solve_whole_with(get_entry, group: list[tuple[int, dict]], settings: dict) -> list[tuple[int, dict]]:
    """A whole-path task (settings["whole_path"]): the group's frames solved together by service.solve.solve_path,
    each outcome with the frame's extras. Raises on any failure (solve_group then solves frame by frame)."""
    from .solve import solve_path  # lazy: the solver stack loads after worker_init set the threads and LLVM

    sols = solve_path(get_entry(), [c["rig"] for _, c in group], solver=settings.get("solver"))
    out = []
    for (i, c), sol in zip(group, sols):
        for k in ("frame", "time", "scene_time"):
            if k in c:
                sol[k] = c[k]
        out.append((i, {"result": sol}))
    return out


def solve_group(solve_one, group: list[tuple[int, dict]], settings: dict, solve_whole=None) -> list[tuple[int, dict]]:
    """A worker task: several configurations one after another, [(index, outcome), ...]. In a coherent
    path (settings["coherent"]) a frame whose configuration brings no "previous" gets the frame before it
    in this task as its previous, as previous_of reads it back from the store (a JSON round
    trip, so the same numbers as a frame solved in its own task); the task's first frame brings its own
    (or none: the first frame of a coherent chunk)."""
    if settings.get("whole_path") and solve_whole is not None and group \
            and all(c.get("scene_time") is None for _, c in group):  # moving geometry: a stage per frame
        try:
            return solve_whole(group)
        except Exception:  # a frame that fails: every frame alone, each failure on its own line
            pass
    out, prev_index, prev = [], None, None
    for i, c in group:
        if settings.get("coherent") and "previous" not in c and prev is not None and prev_index == i - 1:
            c = {**c, "previous": prev}
        o = solve_one(c)
        out.append((i, o))
        prev_index, prev = i, previous_of(json.loads(json.dumps(o["result"]))) if "result" in o else None
    return out


def solve_chunk(scene_path: str, sandbox: bool, group: list[tuple[int, dict]], settings: dict) -> list[tuple[int, dict]]:
    """Worker entry point (local pool) for a task of several configurations (solve_group)."""
    return solve_group(lambda c: solve_configuration(scene_path, sandbox, c, settings), group, settings,
                       lambda g: _solve_whole_with(lambda: worker_entry(scene_path, sandbox, settings), g, settings))


class SceneSolver:
    """A Ray actor body: receives the scene file's bytes once, loads it once, solves configurations."""

    def __init__(self, data: bytes, path: str, filename: str, sandbox: bool, llvm: str | None):
        worker_init(llvm, threads=1)  # an actor holds one CPU (num_cpus=1): one kernel thread, as Ray's OMP_NUM_THREADS
        if not sandbox and os.path.isfile(path):
            self.path = path  # same machine, a local file: keep its relative asset references working
        else:
            # One copy per distinct file on this node, reused by later actors (no pile of temp folders).
            folder = Path(tempfile.gettempdir()) / "shadowopt-ray-scenes" / hashlib.sha256(data).hexdigest()[:16]
            folder.mkdir(parents=True, exist_ok=True)
            self.path = str(folder / filename)
            if not os.path.isfile(self.path) or os.path.getsize(self.path) != len(data):
                tmp = f"{self.path}.{os.getpid()}.tmp"
                Path(tmp).write_bytes(data)
                os.replace(tmp, self.path)
        self.sandbox = sandbox

    def solve(self, config: dict, settings: dict) -> dict:
        return _solve_with(lambda: worker_entry(self.path, self.sandbox, settings, config.get("scene_time")), config,
                           settings)

    def solve_chunk(self, group: list, settings: dict) -> list:
        return solve_group(lambda c: self.solve(c, settings), group, settings,
                           lambda g: _solve_whole_with(lambda: worker_entry(self.path, self.sandbox, settings), g,
                                                       settings))

    def pid(self) -> int:
        return os.getpid()

    def getenv(self, name: str) -> str | None:
        return os.environ.get(name)
