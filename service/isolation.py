"""Child processes that die with the server, and USD loads of uploaded scenes in a child with limits.

- `die_with_parent(parent_pid)` runs first in every process we spawn (the loader child here, the batch
  pool's workers through service.job_workers.worker_init): a daemon thread polls os.getppid() every 0.5 s
  and os._exit()s once the parent is gone (the guarantee), and on Linux prctl(PR_SET_PDEATHSIG, SIGKILL)
  makes the kernel kill the child at once. PDEATHSIG fires when the *thread* that spawned the child
  exits, not the process, so every child we spawn is started from one long-lived thread (`SPAWNER`):
  a request thread that ends, or the batch runner's thread at shutdown, never takes a live child with
  it. The multiprocessing resource tracker needs nothing: it exits when the last holder of its pipe
  (the server and these children) is gone.
- `load_isolated(path, ..., limits=LoadLimits(...))` runs renderers.usd_loader.load_scene in a child
  started with the spawn method (never fork: the server holds LLVM and threads), with RLIMIT_AS set
  once numpy and usd-core are imported (a fixed cost the limit still counts) and before the scene's
  first byte is read, killed after `timeout_s` of wall clock (counted from when the child, its imports done,
  begins the job: a spawn slowed by a loaded machine is not the scene's cost; SPAWN_GRACE_S more to start). The
  LoadedScene comes back pickled over a pipe (40 MB for the chess set: 0.05 s), and the child's memory
  goes back to the system when it exits. Over the memory limit -> SceneError("memory_limit"), over time
  -> SceneError("load_timeout"), a child that crashes (a signal: USD segfaulting on a damaged file)
  -> SceneError("corrupt"); the loader's own SceneErrors come back with their code and message.
  Messages name the scene by its base name, never a server path.
- A warm spare (`SPARES`): after each isolated load one child is started ahead for the next, and imports
  numpy and usd-core while it waits (its limits are set when its one job arrives; it exits after it).
  Spawn + imports cost 0.5-0.7 s per load on an idle 2-core machine, 1.2-1.5 s under load; a warm
  spare leaves ~0.1-0.2 s. The first isolated load of a process spawns cold.
"""
from __future__ import annotations

import concurrent.futures
import ctypes
import math
import multiprocessing
import os
import queue
import resource
import signal
import sys
import threading
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass

from ..renderers.redaction import PathRedactor

# No numpy here (renderers.scene_data imports it): a child imports this module before its first line
# runs, and OpenBLAS sizes its thread pool (each thread maps buffers RLIMIT_AS counts) at import.

WATCH_INTERVAL_S = 0.5
# RLIMIT_AS of a loader child. A child that imported numpy and usd-core maps 0.68 GB of address space;
# the first property path (USD's path pools reserve 383 MB each) and the work threads with their malloc
# arenas take it to 1.20 GB before any scene is read (its RSS is only ~0.12 GB: reserved, not used).
# The demo scene peaks at 1.19-1.20 GB (the smallest limit it loads under: 1184 MB), the chess set
# (1.43 M triangles, 38 MB of arrays) at 1.33 GB. Measured on 2 cores; USD's work threads and malloc's
# arenas are capped (below) so the floor does not grow with the core count.
# The one place the floor is checked: LoadLimits refuses less (api.settings builds its LoadLimits from the
# settings and reports the ValueError naming the setting). 1.25 GiB: just above the measured 1.20 GB.
MEMORY_FLOOR_BYTES = 5 << 28
DEFAULT_MEMORY_BYTES = 3 << 30
DEFAULT_TIMEOUT_S = 60.0
DEFAULT_MAX_TRIANGLES = 5_000_000
CHILD_THREADS = 4  # USD's work threads in a loader child (each one maps a stack)
SPAWN_GRACE_S = 60.0  # a loader child gets this long beyond the time limit to import numpy and usd-core
CPU_SLACK_S = 10  # RLIMIT_CPU = timeout * threads + this: a backstop should the parent not kill the child
PDEATHSIG = sys.platform.startswith("linux")
PEAK_STEP, PEAK_POLL_S = 16 << 20, 0.01  # a loader child reports its mapped memory in 16 MB steps
CRASH_MEMORY_SHARE = 0.8  # a child that crashed having mapped this share of its limit ran out of memory
ALLOCATION_CODES = ("corrupt", "internal", "too_large", "not_usd")  # loader codes a failed allocation can cause


@dataclass(frozen=True)
class LoadLimits:
    """The limits of one uploaded scene's isolated load, validated here and nowhere else: max_triangles a
    positive integer, memory_bytes at least MEMORY_FLOOR_BYTES, timeout_s a finite positive number of
    seconds (nan and inf refused). ValueError naming the field otherwise."""

    max_triangles: int = DEFAULT_MAX_TRIANGLES
    memory_bytes: int = DEFAULT_MEMORY_BYTES
    timeout_s: float = DEFAULT_TIMEOUT_S

    def __post_init__(self):
        if isinstance(self.max_triangles, bool) or not isinstance(self.max_triangles, int) or self.max_triangles < 1:
            raise ValueError(f"max_triangles must be a positive integer, got {self.max_triangles!r}")
        if (isinstance(self.memory_bytes, bool) or not isinstance(self.memory_bytes, int)
                or self.memory_bytes < MEMORY_FLOOR_BYTES):
            raise ValueError(f"memory_bytes must be an integer of at least {MEMORY_FLOOR_BYTES} "
                             f"({MEMORY_FLOOR_BYTES / 2**30:g} GiB: a loader child maps ~1.2 GB of address space for "
                             f"numpy and usd-core alone), got {self.memory_bytes!r}")
        if (isinstance(self.timeout_s, bool) or not isinstance(self.timeout_s, (int, float))
                or not math.isfinite(self.timeout_s) or self.timeout_s <= 0):
            raise ValueError(f"timeout_s must be a finite positive number of seconds, got {self.timeout_s!r}")


# -- dying with the parent ---------------------------------------------------------------------------

def _set_pdeathsig() -> bool:
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        PR_SET_PDEATHSIG = 1
        return libc.prctl(PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False


def _watch(parent_pid: int, interval: float) -> None:
    while True:
        if os.getppid() != parent_pid:
            os._exit(1)  # no cleanup: the parent that would collect anything is gone
        time.sleep(interval)


def die_with_parent(parent_pid: int | None = None, *, pdeathsig: bool = False,
                    interval: float = WATCH_INTERVAL_S) -> None:
    """Make this process exit when `parent_pid` (the process that spawned it) is gone.

    `parent_pid` should come from the parent (os.getpid() there): a parent that died before this runs
    is then still noticed. `pdeathsig` only when the parent spawned this process from a thread that
    lives as long as the parent does (SPAWNER's): the kernel's signal follows the spawning thread."""
    if parent_pid is None:
        parent_pid = os.getppid()
    if pdeathsig and PDEATHSIG:
        _set_pdeathsig()
    if os.getppid() != parent_pid:  # gone already (also closes the race with prctl)
        os._exit(1)
    threading.Thread(target=_watch, args=(parent_pid, interval), name="die-with-parent", daemon=True).start()


class Spawner:
    """One long-lived daemon thread that starts every child process, so PDEATHSIG (which follows the
    spawning thread) fires only when the whole process is gone."""

    def __init__(self):
        self._q: queue.SimpleQueue = queue.SimpleQueue()
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()
        self.spawns = 0  # processes started through call() (the tests check the pool's workers are among them)

    def _run(self) -> None:
        while True:
            fn, fut = self._q.get()
            if fut.set_running_or_notify_cancel():
                try:
                    fut.set_result(fn())
                except BaseException as e:  # noqa: BLE001 - handed to the caller
                    fut.set_exception(e)

    def on_thread(self) -> bool:
        return self._thread is not None and threading.current_thread() is self._thread

    def call(self, fn):
        """fn() on the spawner thread; its result or exception."""
        if self.on_thread():
            return fn()
        with self._lock:
            if self._thread is None or not self._thread.is_alive():
                self._thread = threading.Thread(target=self._run, name="shadowopt-spawner", daemon=True)
                self._thread.start()
        fut: concurrent.futures.Future = concurrent.futures.Future()
        self._q.put((fn, fut))
        return fut.result()

    def start(self, process) -> None:
        def start():
            process.start()
            self.spawns += 1  # on the spawner thread only: no lost update

        self.call(start)


SPAWNER = Spawner()


class DyingProcessPool(ProcessPoolExecutor):
    """A spawn ProcessPoolExecutor whose workers are started on SPAWNER's thread (whichever thread
    submits), so they may use PDEATHSIG. `pdeathsig_safe()` says whether this Python's pool lets us."""

    def _spawn_process(self):
        def spawn():
            super(DyingProcessPool, self)._spawn_process()
            SPAWNER.spawns += 1

        SPAWNER.call(spawn)

    @staticmethod
    def pdeathsig_safe() -> bool:
        return PDEATHSIG and callable(getattr(ProcessPoolExecutor, "_spawn_process", None))


# -- isolated loads ------------------------------------------------------------------------------------

def memory_status(pid: int | str = "self") -> dict[str, int]:
    """VmSize/VmPeak/VmRSS/VmHWM of a process in bytes ({} once it is gone)."""
    out = {}
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                k, _, v = line.partition(":")
                if k in ("VmSize", "VmPeak", "VmRSS", "VmHWM"):
                    out[k] = int(v.split()[0]) * 1024
    except OSError:
        pass
    return out


def _cap_threads() -> None:
    """Fewer threads and malloc arenas in a loader child: each maps address space RLIMIT_AS counts
    (8 MB per stack, 64 MB per arena), so the limit means the same on 2 cores and on 64."""
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = "1"
    try:
        M_ARENA_MAX = -8
        ctypes.CDLL(None).mallopt(M_ARENA_MAX, 2)
    except (OSError, AttributeError):
        pass


def _limit_self(memory_bytes: int, timeout_s: float) -> None:
    resource.setrlimit(resource.RLIMIT_CORE, (0, 0))  # a crashing child leaves no core file behind
    resource.setrlimit(resource.RLIMIT_AS, (memory_bytes, memory_bytes))
    cpu = int(math.ceil(timeout_s * CHILD_THREADS)) + CPU_SLACK_S
    resource.setrlimit(resource.RLIMIT_CPU, (cpu, cpu + 5))


class _PeakReporter:
    """Sends ("peak", VmPeak) to the parent whenever the child's mapped memory grows by PEAK_STEP: a child
    that dies of a failed allocation (a segfault or abort rather than a MemoryError) then still reads as
    over the memory limit, even when it dies between two of the parent's polls."""

    def __init__(self, conn, lock: threading.Lock):
        self.conn, self.lock, self.done = conn, lock, False
        self.last = 0
        threading.Thread(target=self._run, name="peak-reporter", daemon=True).start()

    def _run(self) -> None:
        while not self.done:
            v = memory_status().get("VmPeak", 0)
            if v >= self.last + PEAK_STEP:
                with self.lock:
                    if self.done:
                        return
                    self.conn.send(("peak", v))
                self.last = v
            time.sleep(PEAK_POLL_S)


def _near(memory_bytes: int) -> bool:
    return memory_status().get("VmPeak", 0) >= CRASH_MEMORY_SHARE * memory_bytes


def _run_job(conn, fn, args: tuple, kwargs: dict, memory_bytes: int, timeout_s: float) -> None:
    """In the child: limits, then fn(*args, **kwargs); one answer back, then the child exits."""
    from ..renderers.scene_data import SceneError  # lazy: numpy; a loader child imports this module before _cap_threads

    conn.send(("ready", 0))  # imports done: the load's time limit starts now (run_isolated)
    lock = threading.Lock()
    reporter = _PeakReporter(conn, lock)
    _limit_self(memory_bytes, timeout_s)
    try:
        msg = ("ok", fn(*args, **kwargs))
    except SceneError as e:
        if isinstance(e.__cause__, MemoryError) or (e.code in ALLOCATION_CODES and _near(memory_bytes)):
            msg = ("memory", "")  # USD's failed allocations surface as read errors: near the limit, they are
        else:
            msg = ("error", e.code, e.message)
    except MemoryError:
        msg = ("memory", "")
    except BaseException as e:  # noqa: BLE001 - reported to the parent, which raises SceneError
        msg = ("memory", "") if _near(memory_bytes) else ("error", "internal", f"the loader failed ({type(e).__name__})")
    with lock:
        reporter.done = True
        try:
            conn.send(msg)
        except MemoryError:
            conn.send(("memory", ""))
    conn.close()


def _child_main(conn, parent_pid: int, job: tuple) -> None:
    """A child started for one job."""
    die_with_parent(parent_pid, pdeathsig=True)  # started by SPAWNER's thread
    _cap_threads()
    _preload()  # the fixed cost first (RLIMIT_AS counts it all the same): a tight limit then fails cleanly
    _run_job(conn, *job)


def _preload() -> None:
    # lazy: the child's fixed cost, loaded here after _cap_threads (and never in the server at import)
    import numpy  # noqa: F401
    from pxr import Sdf, Tf, Usd, UsdGeom, UsdLux, Work  # noqa: F401

    from ..renderers import usd_loader  # noqa: F401

    # What every load needs, once: USD's plugin, schema and file-format registries (~0.1-0.2 s), its
    # path pools (the first property path reserves 383 MB of address space, as the first prim path did
    # at import) and its work threads with their malloc arenas.
    stage = Usd.Stage.CreateInMemory()
    UsdGeom.Mesh.Define(stage, "/Warm").CreatePointsAttr([(0.0, 0.0, 0.0)])
    UsdLux.DistantLight.Define(stage, "/WarmLight")
    for fmt in ("usda", "usdc"):
        Sdf.Layer.CreateAnonymous(f"warm.{fmt}")


def _spare_main(conn, parent_pid: int) -> None:
    """A warm spare: imports numpy and usd-core ahead of time, then waits for one job (and exits after
    it, like a cold child: no state passes from one load to the next)."""
    die_with_parent(parent_pid, pdeathsig=True)
    _cap_threads()
    _preload()
    try:
        job = conn.recv()
    except (EOFError, OSError):
        os._exit(0)
    _run_job(conn, *job)


class _Spares:
    """At most one warm spare child, started after each isolated load for the next one. Spawning a child
    and importing usd-core into it costs 0.5-0.7 s on an idle 2-core machine (twice that under load);
    a spare takes that off the next load's latency for ~110 MB of RSS while it waits."""

    def __init__(self):
        self._lock = threading.Lock()
        self._spare = None  # (process, connection)
        self.enabled = True

    def take(self):
        with self._lock:
            spare, self._spare = self._spare, None
        if spare is not None and not spare[0].is_alive():
            _dispose(*spare)
            spare = None
        return spare

    def refill(self) -> None:
        if not self.enabled:
            return
        with self._lock:
            if self._spare is not None:
                return
            ctx = multiprocessing.get_context("spawn")
            mine, theirs = ctx.Pipe(duplex=True)
            try:
                proc = ctx.Process(target=_spare_main, args=(theirs, os.getpid()), name="shadowopt-load-spare",
                                   daemon=True)
                SPAWNER.start(proc)
            except Exception:  # noqa: BLE001 - no spare: the next load spawns its own child
                mine.close()
                return
            finally:
                theirs.close()
            self._spare = (proc, mine)

    def pid(self) -> int | None:
        with self._lock:
            return self._spare[0].pid if self._spare else None

    def close(self) -> None:
        spare = self.take()
        if spare is not None:
            _dispose(*spare)


def _dispose(proc, conn) -> None:
    if proc.is_alive():
        proc.kill()
    if proc.pid is not None:
        proc.join(timeout=5)
    conn.close()
    try:
        proc.close()
    except ValueError:
        pass


SPARES = _Spares()
STATS = {"jobs": 0, "warm": 0}  # isolated jobs run, of which in a warm spare
_stats_lock = threading.Lock()


def run_isolated(fn, args: tuple = (), kwargs: dict | None = None, *, memory_bytes: int = DEFAULT_MEMORY_BYTES,
                 timeout_s: float = DEFAULT_TIMEOUT_S, what: str = "the scene"):
    """fn(*args, **kwargs) in a child process (a warm spare, or one spawned for it) with RLIMIT_AS =
    memory_bytes, killed after timeout_s of wall clock from when it begins fn (its imports done). fn must be
    importable by name (the child imports its module) and return a picklable value. Raises SceneError memory_limit / load_timeout / corrupt
    (a crash), or fn's own SceneError with its code and message."""
    from ..renderers.scene_data import SceneError  # lazy: numpy; a loader child imports this module before _cap_threads

    job = (fn, args, kwargs or {}, memory_bytes, timeout_s)
    spare = SPARES.take()
    proc = conn = None
    if spare is not None:
        proc, conn = spare
        try:
            conn.send(job)
        except (OSError, ValueError):  # the spare died: a fresh child below
            _dispose(proc, conn)
            proc = conn = None
        except BaseException:  # the job does not pickle, say: the spare goes, the caller gets the error
            _dispose(proc, conn)
            raise
    warm = proc is not None
    if proc is None:
        ctx = multiprocessing.get_context("spawn")
        conn, writer = ctx.Pipe(duplex=False)
        try:
            proc = ctx.Process(target=_child_main, name="shadowopt-isolated-load", daemon=True,
                               args=(writer, os.getpid(), job))
            SPAWNER.start(proc)
        except BaseException:
            conn.close()  # no child: nothing will ever write, and the caller gets the error
            raise
        finally:
            writer.close()  # the child holds the only write end: EOF when it dies
    peak = 0
    try:
        with _stats_lock:
            STATS["jobs"] += 1
            STATS["warm"] += warm
        try:
            SPARES.refill()  # for the next load, importing while this one runs
        except Exception:  # noqa: BLE001 - no spare (out of fds or processes): this load goes on without
            pass
        # The time limit counts from the child's "ready" (numpy and usd-core imported, the job begun): a cold
        # child's spawn and imports (0.5-1.5 s idle, 5 s and more on a loaded machine) are the machine's latency,
        # not the scene's cost. A child that never gets ready is killed SPAWN_GRACE_S after the limit.
        start_by = time.monotonic() + timeout_s + SPAWN_GRACE_S
        deadline = None
        msg = None
        while True:
            left = (deadline if deadline is not None else start_by) - time.monotonic()
            if left <= 0:
                proc.kill()
                if deadline is None:
                    raise SceneError("load_timeout", f"the loader for {what} did not start within "
                                     f"{timeout_s + SPAWN_GRACE_S:g} s (the load time limit plus {SPAWN_GRACE_S:g} s "
                                     "to start); refused")
                raise SceneError("load_timeout", f"loading {what} took longer than {timeout_s:g} s (the load time "
                                 f"limit); refused")
            if conn.poll(min(left, 0.1)):
                try:
                    msg = conn.recv()
                except (EOFError, OSError):
                    msg = None
                if msg is not None and msg[0] == "peak":
                    peak = max(peak, msg[1])
                    continue
                if msg is not None and msg[0] == "ready":
                    deadline = time.monotonic() + timeout_s
                    continue
                break
            peak = max(peak, memory_status(proc.pid).get("VmPeak", 0))
        if msg is not None:
            proc.kill()  # its answer is in: no need to wait for usd-core's exit-time destructors
        proc.join(timeout=5)
        if msg is None:
            if proc.exitcode is None:
                proc.kill()
                proc.join(timeout=5)
            return crash_error(proc.exitcode, peak, memory_bytes, what)
        kind = msg[0]
        if kind == "ok":
            return msg[1]
        if kind == "memory":
            raise _memory_error(memory_bytes, what)
        raise SceneError(msg[1], msg[2])
    finally:
        _dispose(proc, conn)


def _memory_error(memory_bytes: int, what: str):
    from ..renderers.scene_data import SceneError  # lazy: numpy; a loader child imports this module before _cap_threads

    return SceneError("memory_limit", f"loading {what} needs more than {memory_bytes / 2**30:.3g} GiB of memory "
                      f"(the load memory limit); refused")


def crash_error(exitcode, peak: int, memory_bytes: int, what: str):
    """A child that died without answering: a failed allocation (std::bad_alloc aborts; the kernel's OOM
    killer sends SIGKILL) when it had mapped most of its limit, else a crash on a damaged file."""
    from ..renderers.scene_data import SceneError  # lazy: numpy; a loader child imports this module before _cap_threads

    sig = -exitcode if isinstance(exitcode, int) and exitcode < 0 else None
    if sig == signal.SIGXCPU:
        raise SceneError("load_timeout", f"loading {what} used more CPU time than the load time limit allows; refused")
    if peak >= CRASH_MEMORY_SHARE * memory_bytes or sig == signal.SIGKILL:
        raise _memory_error(memory_bytes, what)
    how = f"signal {signal.Signals(sig).name}" if sig else f"exit status {exitcode}"
    raise SceneError("corrupt", f"the loader crashed reading {what} ({how}): the file is damaged or not valid USD")


def _load_in_child(path: str, options: dict, max_triangles: int | None):
    from pxr import Work  # lazy: usd-core, in the loader child only

    from ..renderers.usd_loader import load_scene  # lazy: usd-core, in the loader child only

    Work.SetConcurrencyLimit(max(1, min(CHILD_THREADS, os.cpu_count() or 1)))
    return load_scene(path, **options, max_triangles=max_triangles)  # its messages are redacted already


def load_isolated(path, *, time_code: float | None = None, asset_root: str | None = None, sandbox: bool = False,
                  limits: LoadLimits):
    """renderers.usd_loader.load_scene(path, ..., max_triangles=limits.max_triangles) in a spawned child
    with limits.memory_bytes of address space and limits.timeout_s of wall clock; the LoadedScene."""
    from ..renderers.scene_data import SceneError  # lazy: numpy; a loader child imports this module before _cap_threads

    path = os.fspath(path)
    options = {"time_code": time_code, "asset_root": asset_root, "sandbox": sandbox}
    name = os.path.basename(path)
    try:
        return run_isolated(_load_in_child, (path, options, limits.max_triangles), memory_bytes=limits.memory_bytes,
                            timeout_s=limits.timeout_s, what=f"scene {name!r}")
    except SceneError as e:  # the one redaction of what the child reported (the loader's own pass aside)
        redactor = PathRedactor([os.path.dirname(os.path.abspath(path)), asset_root])
        raise SceneError(e.code, redactor.text(e.message)) from None
