"""The REST service's shared state (`Service`): settings, store, batch runner, rate limit, admission, metrics,
readiness; its start-up (native stack, scene cache, store, warm-up scenes) and shutdown."""

import asyncio
import concurrent.futures
import contextlib
import hmac
import json
import logging
import os
import threading
import time
from collections import OrderedDict
from pathlib import Path

from fastapi import Request
from starlette.concurrency import run_in_threadpool

from ..renderers.mitsuba_setup import mitsuba
from ..service.job_runner import BatchRunner
from ..service.evaluation import evaluate_solution
from ..service.coarse_cache import COARSE
from ..service.scene_export import GLB_CACHE
from ..service.scenes import SCENES
from ..service.request import SolveRequest
from ..service.solve import solve
from ..service.packing import sweep_system_temp
from ..service.rig_bounds import DISTANCE_ENV
from ..service.store import Store
from .admission import Admission, Refused
from .errors import ApiError
from .metrics import ServerMetrics
from .rate_limit import RateLimiter
from .responses import REDACT
from .schemas import validate_rig
from .settings import Settings

log = logging.getLogger("shadowopt.server")
REPO = Path(__file__).resolve().parents[1]
DEMO_SCENE = REPO / "configs" / "demo_scene.usda"
DEMO_RIG = REPO / "configs" / "demo_rig.json"
LOCAL_TENANT = "local"  # the tenant of every request when no tokens are configured (loopback only)


class Service:
    """What the routes share: settings, store, batch runner, limits, metrics, readiness."""

    def __init__(self, settings: Settings):
        self.settings = settings
        self.store = None
        self.runner = None
        self.ready = threading.Event()
        self.stopping = threading.Event()
        self.warm_errors: dict[str, str] = {}
        self.warm_s: float | None = None
        self.limiter = RateLimiter(settings.rate_limit_per_s, settings.rate_limit_burst)
        self.admission = Admission(settings.max_inflight, settings.tenant_max_inflight, settings.solve_threads,
                                   settings.load_threads, settings.download_threads)
        self.metrics = ServerMetrics(self.queue_length, lambda: self.admission.inflight, admission=self.admission,
                                     scene_stats=scene_cache_stats, cache_stats=tenant_cache_stats)
        self.tokens = dict(settings.tokens)
        self.batch_lock = threading.Lock()
        # /healthz and /metrics read the database here, never on the event loop nor in the request threadpool
        self.probe_pool = concurrent.futures.ThreadPoolExecutor(2, thread_name_prefix="probe")
        self.reserved: dict[str, int] = {}  # tenant -> bytes of uploads being stored (tenant_max_stored_bytes)
        self.reserved_lock = threading.Lock()
        # (path, tenant, sandboxed) -> (when, ApiError) of a scene reload that failed: the requests that waited
        # for that load get its answer instead of loading again (event loop only)
        self.failed_loads: "OrderedDict[tuple, tuple[float, ApiError]]" = OrderedDict()
        REDACT.add(settings.data_dir)

    # lifecycle
    def start(self) -> None:
        # the distance bound of rigs (service.rig_bounds), for this process and the batch workers it starts
        os.environ[DISTANCE_ENV] = repr(float(self.settings.max_rig_distance_m))
        import_native_stack()
        configure_scene_cache(self.settings)
        Path(self.settings.data_dir).mkdir(parents=True, exist_ok=True)
        self.store = Store(self.settings.data_dir, retention_days=self.settings.retention_days,
                           max_bytes=self.settings.max_data_bytes)
        swept = self.store.sweep_partial_uploads()  # before any request: what a killed upload left behind
        old_temp = sweep_system_temp()  # and what older servers' killed zip uploads left in the system temp dir
        if swept["rows"] or swept["files"] or old_temp:
            log.warning("swept partial uploads", extra={"fields": {"rows": len(swept["rows"]),
                                                                   "files": len(swept["files"]),
                                                                   "system_temp_folders": old_temp}})
        limits = load_limits(self.settings)  # also a path frame's load of an upload at its time code
        self.runner = BatchRunner(self.store, backend=self.settings.batch_backend,
                                  workers=self.settings.batch_workers, ray_address=self.settings.ray_address,
                                  max_triangles=self.settings.max_triangles,
                                  load_limits={"max_triangles": limits.max_triangles,
                                               "memory_bytes": limits.memory_bytes, "timeout_s": limits.timeout_s},
                                  worker_cache={"max_bytes": self.settings.worker_cache_bytes,
                                                "tenant_share": self.settings.tenant_cache_share})
        log.info("store ready", extra={"fields": {"data_dir": str(self.settings.data_dir)}})
        threading.Thread(target=self.warm_up_then_resume, daemon=True, name="warm-up").start()

    def warm_up_then_resume(self) -> None:
        self.warm_up()
        resumed = self.runner.resume()
        log.info("resumed unfinished batches", extra={"fields": {"resumed_batches": _count(resumed)}})
        if self.settings.retention_days is not None or self.settings.max_data_bytes is not None:
            threading.Thread(target=self.retention_loop, daemon=True, name="retention").start()

    def retention_loop(self) -> None:
        """Apply the retention settings at start and then every `retention_interval_s`."""
        while not self.stopping.is_set():
            try:
                removed = self.store.enforce_retention()
                if removed.get("batches") or removed.get("scenes"):
                    log.info("retention", extra={"fields": {"removed_batches": len(removed["batches"]),
                                                            "removed_scenes": len(removed["scenes"])}})
            except Exception as e:  # a failed sweep is retried at the next interval
                log.error("retention failed", extra={"fields": {"error": f"{type(e).__name__}: {e}"}})
            self.stopping.wait(self.settings.retention_interval_s)

    def stop(self) -> None:
        self.stopping.set()
        if self.runner is not None:
            self.runner.shutdown()
        self.probe_pool.shutdown(wait=False, cancel_futures=True)

    def warm_up(self) -> None:
        """Load the warm-up scenes, run one optimize and one small evaluate each, so the kernels are compiled
        (or loaded from Dr.Jit's disk cache) before /healthz is 200."""
        t0 = time.perf_counter()
        for path in self.settings.warm_scenes or [str(DEMO_SCENE)]:
            try:
                entry = SCENES.get(path)  # the operator's own files: local mode, not the upload sandbox
                rig = warm_rig(entry.loaded, path)
                if rig is not None:
                    sol = solve(entry, rig, SolveRequest(method="optimized"))
                    evaluate_solution(entry, rig, sol, screen=(160, 90))  # the ground-truth kernels too
            except Exception as e:  # a bad warm-up scene must not take the service down
                self.warm_errors[str(path)] = f"{type(e).__name__}: {e}"
                log.error("warm-up failed", extra={"fields": {"scene": str(path), "error": str(e)}})
        self.warm_s = round(time.perf_counter() - t0, 3)
        log.info("warm", extra={"fields": {"seconds": self.warm_s}})
        self.ready.set()

    # limits
    @contextlib.asynccontextmanager
    async def heavy(self, tenant: str, request: Request | None = None, watch: bool = True):
        """Admission of a heavy request, answered at once: 429 when this tenant has `tenant_max_inflight` in,
        503 when `max_inflight` heavy requests are in and this tenant has one of them. The request counts as
        in flight until it leaves; its work then waits for a slot (`in_slot`) on the event loop. With
        `request` (and `watch`) the ticket watches for the client disconnecting: a wait for a slot then ends
        at once (ClientGone, answered 499) and the ticket is released; `watch=False` when the route still has
        the body to read (it calls ticket.watch(request.receive) afterwards)."""
        try:
            ticket = self.admission.admit(tenant)
        except Refused as e:
            self.metrics.refusals.inc(e.code)
            raise ApiError(e.status, e.code, e.message, headers={"Retry-After": str(e.retry_after)}) from None
        try:
            if request is not None and watch:
                ticket.watch(request.receive)
            yield ticket
        finally:
            ticket.release()

    def admit(self, tenant: str):
        """A ticket for a heavy request that outlives its route (a streamed response releases it when the
        stream ends), or the 429/503 refusal at once (as `heavy`)."""
        try:
            return self.admission.admit(tenant)
        except Refused as e:
            self.metrics.refusals.inc(e.code)
            raise ApiError(e.status, e.code, e.message, headers={"Retry-After": str(e.retry_after)}) from None

    async def in_slot(self, pool, ticket, fn, *args, **kwargs):
        """`fn(*args, **kwargs)` in a worker thread once `pool` (admission.solve or .load) gives the ticket's
        tenant a slot; ClientGone (never run) when the client left while it waited."""
        async with ticket.slot(pool):
            return await run_in_threadpool(fn, *args, **kwargs)

    def note_failed_load(self, key: tuple, error: "ApiError", keep: int = 256) -> None:
        self.failed_loads.pop(key, None)
        self.failed_loads[key] = (time.monotonic(), error)
        while len(self.failed_loads) > keep:
            self.failed_loads.popitem(last=False)

    async def probe(self, fn, timeout: float = 2.0):
        """`fn()` on the probe executor (database reads for /healthz and /metrics), within `timeout` seconds."""
        loop = asyncio.get_running_loop()
        return await asyncio.wait_for(loop.run_in_executor(self.probe_pool, fn), timeout)

    def probe_database(self) -> int:
        """The queue length after a cheap check that the database answers (raises sqlite3.DatabaseError)."""
        self.store.check_database()
        return self.store.pending_configurations()

    def time_budget(self, requested: float | None) -> float:
        """A request's time budget in ms, capped by the server's max_time_budget_ms (the cap when none is asked)."""
        cap = self.settings.max_time_budget_ms
        return min(requested or cap, cap)

    def queue_length(self) -> int:
        if self.store is None:
            return 0
        return self.store.pending_configurations()

    def tenant_for(self, token: str | None) -> str | None:
        if not self.tokens:
            return LOCAL_TENANT
        if not token:
            return None
        found = None
        for name, tok in self.tokens.items():  # compare with every token: no timing hint which one matched
            if hmac.compare_digest(tok.encode(), token.encode()):
                found = name
        return found


def scene_cache_stats() -> dict:
    return SCENES.stats()


def tenant_cache_stats() -> dict[str, dict]:
    return {"coarse": COARSE.stats(), "geometry": GLB_CACHE.stats()}


def configure_scene_cache(settings: Settings) -> None:
    """Size the process-wide caches of tenant data from the settings (bytes, one tenant's share): the scene
    cache (also in entries), the coarse cache and the geometry cache; the batch workers' scene caches get
    theirs from the runner (worker_cache). Settings.check bounds their sum by cache_bytes."""
    SCENES.configure(capacity=settings.scene_cache_entries, max_bytes=settings.scene_cache_bytes,
                     tenant_share=settings.tenant_cache_share)
    COARSE.configure(max_bytes=settings.coarse_cache_bytes, tenant_share=settings.tenant_cache_share)
    GLB_CACHE.configure(max_bytes=settings.geometry_cache_bytes, tenant_share=settings.tenant_cache_share)


def import_native_stack() -> None:
    """Import USD, Mitsuba/Dr.Jit and the process-pool machinery on one thread before any other starts:
    two threads loading native extensions at once (USD's static initialisers in one, multiprocessing's
    in the other) were seen to deadlock in the dynamic loader."""
    import concurrent.futures.process  # noqa: F401  # lazy: the native stack loads here, on one thread at start
    import multiprocessing.resource_tracker  # noqa: F401  # lazy: the native stack, on one thread at start-up
    import multiprocessing.synchronize  # noqa: F401  # lazy: the native stack, on one thread at start-up

    from pxr import Sdf, Usd, UsdGeom  # noqa: F401  # lazy: USD's native libraries, on one thread at start-up

    mitsuba()  # mitsuba and drjit with the LLVM variant set


def _count(x) -> int:
    try:
        return len(x)
    except TypeError:
        return int(x or 0)


def warm_rig(loaded, path) -> dict | None:
    """The demo rig for the demo scene, else the scene's first camera and light at a small size."""
    if Path(path).resolve() == DEMO_SCENE.resolve():
        return validate_rig(json.loads(DEMO_RIG.read_text()))
    lights = [{"usd_path": l.usd_path} for l in loaded.lights if l.type != "ignored"][:1]
    if not loaded.cameras or not lights:
        return None
    return validate_rig({"camera": {"usd_path": loaded.cameras[0].usd_path, "resolution": [1280, 720]},
                         "lights": lights})


def load_limits(settings: Settings):
    return settings.load_limits()
