"""The REST service (FastAPI on uvicorn): scenes, optimize, evaluate, compare, analyze, batches.

Every request is authenticated by a bearer token (the tenant is the token's name), rate-limited per
token, logged as one JSON line with its request id (echoed in X-Request-ID) and counted in /metrics.
Every 4xx is `{"error": {"code", "message", "field"}}` and is listed in the route's OpenAPI responses.
Heavy requests (uploads, optimize, evaluate, compare, batch creation) pass admission control on the event
loop (api/admission.py) before any body of theirs is read (uploads): refused at once when the tenant is at
its quota or the server at max_inflight (a tenant with nothing in flight is always admitted), else they
wait as asyncio futures for a slot, the tenants taking turns, and only then run in a worker thread (at
most `solve_threads` solves, batch validations included, and `load_threads` scene loads at a time; only
the leader of a scene load holds a load slot, requests for the same scene wait for it slotless). A
request whose client disconnects while it waits is dropped at once (499, never run). /healthz and
/metrics are async and read the database on their own small executor: they never wait behind queued work.
Every free-text field a client sees (error messages, warnings, batch error messages, warm-up errors) has
server paths (data directory, scene storage, repository, Python prefix) cut down to file names (`redact`);
identifiers (prim paths, usd_path, scene ids, file names) are never rewritten.
"""

import asyncio
import base64
import concurrent.futures
import contextlib
import hmac
import json
import logging
import math
import os
import sqlite3
import sys
import tempfile
import threading
import time
import traceback
import uuid
from collections import OrderedDict
from pathlib import Path
from typing import Annotated

from fastapi import Depends, FastAPI, Header, Query, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from starlette.concurrency import run_in_threadpool
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.requests import ClientDisconnect

from . import schemas as S
from ..renderers.redaction import PathRedactor
from .admission import Admission, ClientGone, Refused
from .metrics import ServerMetrics
from .settings import Settings, is_loopback, load_settings

log = logging.getLogger("shadowopt.server")
REPO = Path(__file__).resolve().parents[1]
DEMO_SCENE = REPO / "configs" / "demo_scene.usda"
DEMO_RIG = REPO / "configs" / "demo_rig.json"
SCENE_SUFFIXES = (".usda", ".usdc", ".usdz", ".usd", ".zip")  # .zip: a scene's folder, stored as a .usdz
LOCAL_TENANT = "local"  # the tenant of every request when no tokens are configured (loopback only)

# --- errors -------------------------------------------------------------------------------------

DESCRIPTIONS = {
    400: "malformed request", 401: "missing or unknown bearer token", 404: "no such resource for this tenant",
    409: "the resource is in a state that does not allow this", 413: "too large (upload size, triangles, "
    "load memory or time, pixels or texels over the server's limits)",
    422: "invalid request: the message names the field",
    429: "rate limit or a per-tenant quota of this token exceeded (the message names the quota setting); "
    "retry after Retry-After seconds",
    503: "busy (max_inflight heavy requests in, queue full), warming up or the database unavailable; retry "
    "after Retry-After seconds",
}
RETRY_AFTER = {"Retry-After": {"description": "seconds to wait before retrying", "schema": {"type": "integer"}}}


def error_responses(*codes: int) -> dict:
    """OpenAPI `responses=` for the given 4xx/5xx codes, all with the ErrorResponse body."""
    out = {}
    for c in codes:
        out[c] = {"model": S.ErrorResponse, "description": DESCRIPTIONS[c]}
        if c in (429, 503):
            out[c]["headers"] = RETRY_AFTER
    return out


AUTHED = (401, 429)


class ApiError(StarletteHTTPException):
    """An error answered as {"error": {"code", "message", "field"}}."""

    def __init__(self, status: int, code: str, message: str, field: str | None = None,
                 headers: dict | None = None):
        super().__init__(status, detail=message, headers=headers)
        self.code, self.message, self.field = code, message, field

    def body(self) -> dict:
        return {"error": {"code": self.code, "message": redact(self.message), "field": self.field}}


def error_json(status: int, code: str, message: str, field: str | None = None, headers=None) -> JSONResponse:
    return JSONResponse({"error": {"code": code, "message": redact(message), "field": field}}, status_code=status,
                        headers=headers)


class _Errors:
    """Adapter so format_validation_error reads FastAPI's errors with the `body`/`query` prefix dropped."""

    def __init__(self, errors: list[dict]):
        self._errors = errors

    def errors(self):
        return self._errors


def _strip_loc(e: dict) -> dict:
    loc = tuple(e.get("loc", ()))
    if len(loc) > 1 and loc[0] in ("body", "query", "path", "header"):
        loc = loc[1:]
    return {**e, "loc": loc}


def validation_error_response(exc) -> JSONResponse:
    errors = [_strip_loc(e) for e in exc.errors()]
    if not errors:
        return error_json(422, "invalid_request", "invalid request")
    first = errors[0]
    if first.get("type") == "json_invalid":
        why = (first.get("ctx") or {}).get("error", "does not parse")
        return error_json(422, "invalid_json", f"body: not valid JSON ({why}, at character {first['loc'][-1]})",
                          "body")
    field = ".".join(str(p) for p in first.get("loc", ())) or None
    return error_json(422, "invalid_request", S.format_validation_error(_Errors(errors)), field)


# --- no server paths in what a client sees -------------------------------------------------------

class Redactor:
    """The server's redaction of client-visible JSON: renderers.redaction.PathRedactor (the one path
    redactor: server folders - the data directory, repository, Python prefixes, working, temporary and home
    folders - and any absolute file path cut to base names) applied to the free-text fields only."""

    def __init__(self):
        self.paths = PathRedactor()

    def add(self, root) -> None:
        """Hide one more server folder (the data directory)."""
        self.paths.add(root)

    def text(self, value: str) -> str:
        return self.paths.text(value)

    def obj(self, obj, _free: bool = False):
        """A JSON-ready object with the free text redacted: the strings under a FREE_TEXT key (error
        messages, warnings, batch error messages, warm-up errors, at any depth). Identifiers (prim paths,
        camera and light usd_path, scene ids, file names) are the caller's own data and pass unchanged,
        even when they look like a server path (a prim `/tmp/Camera`)."""
        if isinstance(obj, str):
            return self.text(obj) if _free else obj
        if isinstance(obj, dict):
            return {(self.text(k) if _free and isinstance(k, str) else k):
                    self.obj(v, _free or (isinstance(k, str) and k in FREE_TEXT)) for k, v in obj.items()}
        if isinstance(obj, list):
            return [self.obj(v, _free) for v in obj]
        return obj


# the keys whose strings are free text a message writer may have put a server path in (only these are redacted)
FREE_TEXT = frozenset({"message", "warnings", "warning", "warm_errors", "note", "notes", "reasons"})


REDACT = Redactor()


def redact(text: str) -> str:
    """`text` with every server path cut to its file name (the one function every client message goes through)."""
    return REDACT.text(text)


# --- JSON output --------------------------------------------------------------------------------

def finite(obj):
    """NaN/inf -> None (JSON has neither), NumPy scalars -> Python numbers, tuples -> lists."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {str(k): finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [finite(v) for v in obj]
    if obj is None or isinstance(obj, (str, int, bool)):
        return obj
    if hasattr(obj, "tolist"):  # numpy scalar or array
        return finite(obj.tolist())
    return str(obj)


def json_response(obj, status: int = 200, headers=None) -> Response:
    body = json.dumps(REDACT.obj(finite(obj)), separators=(",", ":"), allow_nan=False)
    return Response(body, status_code=status, media_type="application/json", headers=headers)


# --- rate limit ---------------------------------------------------------------------------------

class RateLimiter:
    """A token bucket per tenant: `rate` requests per second, bursts up to `burst`."""

    def __init__(self, rate: float, burst: int):
        self.rate, self.burst = rate, burst
        self._buckets: dict[str, tuple[float, float]] = {}
        self._lock = threading.Lock()

    def take(self, tenant: str) -> float:
        """0 when the request may go ahead, else the seconds until it may."""
        if self.rate <= 0:
            return 0.0
        now = time.monotonic()
        with self._lock:
            tokens, last = self._buckets.get(tenant, (float(self.burst), now))
            tokens = min(float(self.burst), tokens + (now - last) * self.rate)
            if tokens >= 1.0:
                self._buckets[tenant] = (tokens - 1.0, now)
                return 0.0
            self._buckets[tenant] = (tokens, now)
            return (1.0 - tokens) / self.rate


# --- the service object -------------------------------------------------------------------------

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
                                   settings.load_threads)
        self.metrics = ServerMetrics(self.queue_length, lambda: self.admission.inflight, admission=self.admission,
                                     scene_stats=scene_cache_stats)
        self.tokens = dict(settings.tokens)
        self.batch_lock = threading.Lock()
        # /healthz and /metrics read the database here, never on the event loop nor in the request threadpool
        self.probe_pool = concurrent.futures.ThreadPoolExecutor(2, thread_name_prefix="probe")
        self._reserved: dict[str, int] = {}  # tenant -> bytes of uploads being stored (tenant_max_stored_bytes)
        self._reserved_lock = threading.Lock()
        # (path, tenant, sandboxed) -> (when, ApiError) of a scene reload that failed: the requests that waited
        # for that load get its answer instead of loading again (event loop only)
        self.failed_loads: "OrderedDict[tuple, tuple[float, ApiError]]" = OrderedDict()
        REDACT.add(settings.data_dir)

    # lifecycle
    def start(self) -> None:
        from ..service.batches import BatchRunner
        from ..service.store import Store

        import_native_stack()
        configure_scene_cache(self.settings)
        Path(self.settings.data_dir).mkdir(parents=True, exist_ok=True)
        self.store = Store(self.settings.data_dir, retention_days=self.settings.retention_days,
                           max_bytes=self.settings.max_data_bytes)
        swept = self.store.sweep_partial_uploads()  # before any request: what a killed upload left behind
        if swept["rows"] or swept["files"]:
            log.warning("swept partial uploads", extra={"fields": {"rows": len(swept["rows"]),
                                                                   "files": len(swept["files"])}})
        limits = load_limits(self.settings)  # also a path frame's load of an upload at its time code
        self.runner = BatchRunner(self.store, backend=self.settings.batch_backend,
                                  workers=self.settings.batch_workers, ray_address=self.settings.ray_address,
                                  max_triangles=self.settings.max_triangles,
                                  load_limits={"max_triangles": limits.max_triangles,
                                               "memory_bytes": limits.memory_bytes, "timeout_s": limits.timeout_s})
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
        from ..service.evaluation import evaluate_solution
        from ..service.scenes import SCENES
        from ..service.request import SolveRequest
        from ..service.solve import solve

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
    from ..service.scenes import SCENES

    return SCENES.stats()


def configure_scene_cache(settings: Settings) -> None:
    """Size the process-wide scene cache from the settings (entries, bytes, one tenant's share)."""
    from ..service.scenes import SCENES

    SCENES.configure(capacity=settings.scene_cache_entries, max_bytes=settings.scene_cache_bytes,
                     tenant_share=settings.tenant_cache_share)


def import_native_stack() -> None:
    """Import USD, Mitsuba/Dr.Jit and the process-pool machinery on one thread before any other starts:
    two threads loading native extensions at once (USD's static initialisers in one, multiprocessing's
    in the other) were seen to deadlock in the dynamic loader."""
    import concurrent.futures.process  # noqa: F401
    import multiprocessing.resource_tracker  # noqa: F401
    import multiprocessing.synchronize  # noqa: F401

    from pxr import Sdf, Usd, UsdGeom  # noqa: F401

    from ..renderers.mitsuba_setup import mitsuba
    from ..service.solve import solve  # noqa: F401

    mitsuba()  # mitsuba and drjit with the LLVM variant set


def _count(x) -> int:
    try:
        return len(x)
    except TypeError:
        return int(x or 0)


def warm_rig(loaded, path) -> dict | None:
    """The demo rig for the demo scene, else the scene's first camera and light at a small size."""
    from .schemas import validate_rig

    if Path(path).resolve() == DEMO_SCENE.resolve():
        return validate_rig(json.loads(DEMO_RIG.read_text()))
    lights = [{"usd_path": l.usd_path} for l in loaded.lights if l.type != "ignored"][:1]
    if not loaded.cameras or not lights:
        return None
    return validate_rig({"camera": {"usd_path": loaded.cameras[0].usd_path, "resolution": [1280, 720]},
                         "lights": lights})


# --- request context: request id, structured log, metrics, body size ----------------------------

class RequestContext:
    """ASGI middleware: X-Request-ID (echoed; generated when absent), a JSON log line and metrics per
    request, and the body-size limit (413 before the body is read when Content-Length says so)."""

    def __init__(self, app, service: Service):
        self.app, self.service = app, service

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        rid = _request_id(scope)
        scope.setdefault("state", {})["request_id"] = rid
        t0 = time.perf_counter()
        status = {"code": 500, "started": False}

        async def send_with_id(message):
            if message["type"] == "http.response.start":
                status["code"], status["started"] = message["status"], True
                message["headers"] = list(message.get("headers", [])) + [(b"x-request-id", rid.encode())]
            await send(message)

        try:
            too_big = self._too_big(scope)
            if too_big is not None:
                await too_big(scope, receive, send_with_id)
            elif self._uncounted(scope):  # a JSON body without Content-Length (chunked): read it within the limit
                replay = await self._buffered(receive, self.service.settings.max_body_bytes)
                if replay is None:
                    limit = self.service.settings.max_body_bytes
                    await error_json(413, "body_too_large", f"request body is over the limit of {limit} bytes",
                                     "body")(scope, receive, send_with_id)
                else:
                    await self.app(scope, replay, send_with_id)
            else:
                await self.app(scope, receive, send_with_id)
        except Exception as e:
            log.error("unhandled error", extra={"fields": {"request_id": rid, "error": f"{type(e).__name__}: {e}",
                                                           "traceback": traceback.format_exc()}})
            if not status["started"]:
                await error_json(500, "internal_error", f"internal error ({type(e).__name__}); "
                                 f"request id {rid}")(scope, receive, send_with_id)
        finally:
            self._record(scope, rid, status["code"], time.perf_counter() - t0)

    @staticmethod
    def _uncounted(scope) -> bool:
        """A request body whose size Content-Length does not state (uploads count their own bytes)."""
        headers = dict(scope.get("headers") or [])
        upload = scope["method"] == "POST" and scope["path"].rstrip("/") == "/v1/scenes"
        return b"content-length" not in headers and not upload and scope["method"] in ("POST", "PUT", "PATCH")

    @staticmethod
    async def _buffered(receive, limit: int):
        """Read the whole body (at most `limit` bytes); a receive() that replays it, or None when it is larger."""
        messages, size = [], 0
        while True:
            message = await receive()
            messages.append(message)
            if message.get("type") != "http.request":
                break
            size += len(message.get("body", b""))
            if size > limit:
                return None
            if not message.get("more_body", False):
                break
        pending = iter(messages)

        async def replay():
            return next(pending, None) or await receive()

        return replay

    def _too_big(self, scope):
        length = dict(scope.get("headers") or []).get(b"content-length")
        if length is None:
            return None
        upload = scope["method"] == "POST" and scope["path"].rstrip("/") == "/v1/scenes"
        limit = self.service.settings.max_upload_bytes if upload else self.service.settings.max_body_bytes
        try:
            n = int(length)
        except ValueError:
            return error_json(400, "bad_content_length", "Content-Length is not an integer", "Content-Length")
        if n > limit:
            what = "upload" if upload else "request body"
            return error_json(413, "upload_too_large" if upload else "body_too_large",
                              f"{what} of {n} bytes is over the limit of {limit} bytes", "body")
        return None

    def _record(self, scope, rid: str, status: int, seconds: float) -> None:
        route = scope.get("route")
        template = getattr(route, "path", None) or "unmatched"
        m = self.service.metrics
        m.requests.inc(template, scope["method"], str(status))
        m.latency.observe(seconds, template, scope["method"])
        state = scope.get("state") or {}
        log.info("request", extra={"fields": {
            "request_id": rid, "method": scope["method"], "path": scope["path"], "route": template,
            "status": status, "duration_ms": round(seconds * 1e3, 3), "tenant": state.get("tenant"),
            **({"error_code": state["error_code"]} if state.get("error_code") else {})}})


def _request_id(scope) -> str:
    for k, v in scope.get("headers") or []:
        if k == b"x-request-id":
            text = v.decode("latin-1").strip()
            if 0 < len(text) <= 128 and all(c.isalnum() or c in "-_.:" for c in text):
                return text
            break
    return uuid.uuid4().hex


class JsonLogFormatter(logging.Formatter):
    """One JSON object per line: ts, level, logger, msg and the record's `fields`."""

    def format(self, record: logging.LogRecord) -> str:
        out = {"ts": round(record.created, 3), "level": record.levelname, "logger": record.name,
               "msg": record.getMessage()}
        out.update(getattr(record, "fields", {}) or {})
        if record.exc_info:
            out["traceback"] = self.formatException(record.exc_info)
        return json.dumps(finite(out), default=str)


def configure_logging(level: str = "INFO") -> None:
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(JsonLogFormatter())
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(level.upper())


# --- the app ------------------------------------------------------------------------------------

bearer = HTTPBearer(auto_error=False, description="`Authorization: Bearer <token>`; the tenant is the token's name")


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or load_settings()
    svc = Service(settings)

    @contextlib.asynccontextmanager
    async def lifespan(app):
        await run_in_threadpool(svc.start)
        try:
            yield
        finally:
            await run_in_threadpool(svc.stop)

    app = FastAPI(title="shadowopt", version=_version(), lifespan=lifespan,
                  description="Scene-optimized shadow-map parameters: light matrices, warp and cascades. "
                  "Errors are `{\"error\": {\"code\", \"message\", \"field\"}}`.")
    app.state.service = svc
    app.add_middleware(RequestContext, service=svc)
    install_error_handlers(app)

    async def tenant(request: Request,
                     cred: Annotated[HTTPAuthorizationCredentials | None, Depends(bearer)] = None) -> str:
        name = svc.tenant_for(cred.credentials if cred else None)
        if name is None:
            raise ApiError(401, "unauthorized", "missing bearer token" if cred is None else "unknown bearer token",
                           "Authorization", headers={"WWW-Authenticate": "Bearer"})
        request.state.tenant = name
        wait = svc.limiter.take(name)
        if wait > 0:
            raise ApiError(429, "rate_limited", f"rate limit of {settings.rate_limit_per_s:g} requests/s "
                           f"(burst {settings.rate_limit_burst}) exceeded for this token",
                           headers={"Retry-After": str(max(1, math.ceil(wait)))})
        return name

    Tenant = Annotated[str, Depends(tenant)]
    add_system_routes(app, svc)
    add_scene_routes(app, svc, Tenant)
    add_solve_routes(app, svc, Tenant)
    add_batch_routes(app, svc, Tenant)
    add_path_routes(app, svc, Tenant)
    from .inspect import add_inspect_routes; add_inspect_routes(app, svc, Tenant)  # /inspect and the scene's glTF
    return app


def install_error_handlers(app: FastAPI) -> None:
    @app.exception_handler(ApiError)
    async def api_error(request: Request, exc: ApiError):
        request.state.error_code = exc.code
        return JSONResponse(exc.body(), status_code=exc.status_code, headers=exc.headers)

    @app.exception_handler(ClientGone)
    @app.exception_handler(ClientDisconnect)
    async def client_gone(request: Request, exc: Exception):
        """The client disconnected while its request waited for a slot (ClientGone: dropped, never run) or
        while it sent its upload (ClientDisconnect): nobody reads the answer; logged and counted as 499."""
        request.state.error_code = "client_closed"
        request.app.state.service.metrics.abandoned.inc("waiting" if isinstance(exc, ClientGone) else "body")
        return error_json(499, "client_closed", "the client closed the connection before the request ran")

    @app.exception_handler(RequestValidationError)
    async def invalid(request: Request, exc: RequestValidationError):
        request.state.error_code = "invalid_request"
        return validation_error_response(exc)

    @app.exception_handler(sqlite3.DatabaseError)
    async def database_error(request: Request, exc: sqlite3.DatabaseError):
        request.state.error_code = "database_unavailable"
        log.error("database error", extra={"fields": {"error": f"{type(exc).__name__}: {exc}"}})
        return error_json(503, "database_unavailable", database_message(exc), None, {"Retry-After": "5"})

    @app.exception_handler(StarletteHTTPException)
    async def http_error(request: Request, exc: StarletteHTTPException):
        if exc.status_code == 400:  # FastAPI's "error parsing the body" (e.g. bytes that are not UTF-8)
            request.state.error_code = "invalid_json"
            return error_json(422, "invalid_json", f"body: not valid JSON ({exc.detail})", "body")
        codes = {404: "not_found", 405: "method_not_allowed", 400: "bad_request", 413: "too_large"}
        code = codes.get(exc.status_code, f"http_{exc.status_code}")
        request.state.error_code = code
        return error_json(exc.status_code, code, str(exc.detail), None, getattr(exc, "headers", None))


def database_message(exc: BaseException) -> str:
    return redact(f"the database is unavailable ({exc or type(exc).__name__}); retry later or ask the operator")


def add_system_routes(app: FastAPI, svc: Service) -> None:
    @app.get("/healthz", summary="Readiness: 200 once the scene cache and the Dr.Jit kernels are warm and the "
             "database answers, else 503", response_model=S.Health, responses=error_responses(503), tags=["system"])
    async def healthz():
        queued, db_error = 0, None
        if svc.store is not None:
            try:
                queued = await svc.probe(svc.probe_database)
            except asyncio.TimeoutError:
                db_error = "the database did not answer within 2 s"
            except (sqlite3.Error, OSError) as e:
                db_error = database_message(e)
        body = {"status": "ok" if svc.ready.is_set() else "warming", "warm_s": svc.warm_s,
                "warm_errors": svc.warm_errors, "queue_length": queued, "version": _version()}
        if db_error is not None:
            body["status"] = "unavailable"
            return JSONResponse(REDACT.obj({"error": {"code": "database_unavailable", "message": db_error,
                                                      "field": None}, **body}), status_code=503,
                                headers={"Retry-After": "5"})
        if not svc.ready.is_set():
            return JSONResponse(REDACT.obj({"error": {"code": "warming_up", "message": "the scene cache and "
                                                      "kernels are warming up", "field": None}, **body}),
                                status_code=503, headers={"Retry-After": "1"})
        return json_response(body)

    @app.get("/metrics", summary="Prometheus metrics: request counts and latencies per route, optimize time, "
             "queue length, heavy requests in flight and waiting, admission refusals", response_class=Response,
             tags=["system"], responses={200: {"content": {"text/plain": {"schema": {"type": "string"}}}}})
    async def metrics():
        try:
            text = await svc.probe(svc.metrics.render)
        except asyncio.TimeoutError:  # the queue gauge's query hung: the rest without it
            text = svc.metrics.render(skip_slow=True)
        return Response(text, media_type="text/plain; version=0.0.4; charset=utf-8")


# --- scenes -------------------------------------------------------------------------------------

UPLOAD_BODY = {"requestBody": {"required": True, "description": "the USD file (a multi-file scene as one package: "
               "a .usdz, or a .zip of its folder): the raw bytes (filename in the "
               "`filename` query parameter or the X-Filename header) or multipart/form-data with a `file` part",
               "content": {"application/octet-stream": {"schema": {"type": "string", "format": "binary"}},
                           "multipart/form-data": {"schema": {
                               "type": "object", "required": ["file"],
                               "properties": {"file": {"type": "string", "format": "binary"}}}}}}}


def add_scene_routes(app: FastAPI, svc: Service, Tenant) -> None:
    @app.post("/v1/scenes", summary="Upload a .usda/.usdc/.usdz scene (or a .zip of a scene's folder); answers "
              "what the loader found",
              response_model=S.SceneInfo, status_code=201, openapi_extra=UPLOAD_BODY, tags=["scenes"],
              responses={200: {"model": S.SceneInfo, "description": "the same file was uploaded before"},
                         **error_responses(*AUTHED, 413, 422, 503)})
    async def upload_scene(request: Request, tenant: Tenant,
                           filename: Annotated[str | None, Query(max_length=255, description="the file's name "
                                                                 "(its extension says the format)")] = None,
                           x_filename: Annotated[str | None, Header(max_length=255)] = None):
        # admitted before the body is read: max_inflight / tenant_max_inflight bound the upload bytes in memory
        async with svc.heavy(tenant, request, watch=False) as ticket:
            data, name = await read_upload(request, svc.settings.max_upload_bytes, filename or x_filename)
            ticket.watch(request.receive)
            if name.lower().endswith(".zip"):  # a scene's folder: checked entry by entry, stored as a .usdz
                data, name = await run_in_threadpool(zip_upload, data, name, svc.settings.max_upload_bytes)
            info, created = await store_and_load(svc, ticket, data, name)
        return json_response({**info, "created": created}, status=201 if created else 200)

    @app.get("/v1/scenes", summary="This tenant's scenes", response_model=S.SceneList, tags=["scenes"],
             responses=error_responses(*AUTHED))
    def list_scenes(tenant: Tenant):
        return json_response({"scenes": [_scene_summary(r) for r in svc.store.list_scenes(tenant)]})

    @app.get("/v1/scenes/{scene_id}", summary="What the loader found in one scene", response_model=S.SceneInfo,
             responses=error_responses(*AUTHED, 404, 422), tags=["scenes"])
    def get_scene(scene_id: S.ObjectId, tenant: Tenant):
        rec = svc.store.scene_record(tenant, scene_id)
        if rec is None:
            raise scene_not_found(scene_id)
        return json_response(scene_info(rec, scene_id))

    @app.delete("/v1/scenes/{scene_id}", summary="Delete a scene (its file and record)", response_model=S.Deleted,
                responses=error_responses(*AUTHED, 404, 422), tags=["scenes"])
    def delete_scene(scene_id: S.ObjectId, tenant: Tenant):
        if not svc.store.delete_scene(tenant, scene_id):
            raise scene_not_found(scene_id)
        return {"deleted": True}


def scene_not_found(scene_id: str) -> ApiError:
    return ApiError(404, "scene_not_found", f"scene_id: no scene {scene_id!r} for this token", "scene_id")


def _scene_summary(rec: dict) -> dict:
    info = rec.get("info") or {}
    return {"scene_id": rec.get("scene_id"), "filename": rec.get("filename"), "triangles": info.get("triangles"),
            "created_at": rec.get("created_at")}


def scene_info(rec: dict, scene_id: str) -> dict:
    info = dict(rec.get("info") or {})
    info.pop("source", None)  # the server's file path is none of the caller's business
    return {**info, "scene_id": scene_id, "filename": rec.get("filename")}


async def read_upload(request: Request, limit: int, name: str | None) -> tuple[bytes, str]:
    """The uploaded bytes and file name, raw or multipart; 413 past `limit` bytes."""
    chunks, size = [], 0
    async for chunk in request.stream():
        size += len(chunk)
        if size > limit:
            raise ApiError(413, "upload_too_large", f"upload is over the limit of {limit} bytes", "body")
        chunks.append(chunk)
    body = b"".join(chunks)
    ctype = request.headers.get("content-type", "")
    if ctype.startswith("multipart/form-data"):
        request._body = body  # starlette reads the form from the cached body
        try:
            form = await request.form(max_files=1, max_fields=4)
        except Exception as e:
            raise ApiError(422, "invalid_multipart", f"file: the multipart body does not parse ({e})", "file") from e
        part = form.get("file")
        if part is None or isinstance(part, str):
            raise ApiError(422, "invalid_request", "file: a multipart upload needs a `file` part with the USD file",
                           "file")
        body, name = await part.read(), name or part.filename
    if not name:
        raise ApiError(422, "invalid_request", "filename: give the file name (query parameter `filename`, "
                       "header X-Filename, or the multipart part's filename)", "filename")
    name = os.path.basename(name.replace("\\", "/"))
    if not name.lower().endswith(SCENE_SUFFIXES):
        raise ApiError(422, "unsupported_format", f"filename: {name!r} is not a .usd, .usda, .usdc or .usdz file "
                       "or a .zip of a scene's folder",
                       "filename")
    if not body:
        raise ApiError(422, "invalid_request", "body: the upload is empty", "body")
    return body, name


def zip_upload(data: bytes, name: str, max_upload_bytes: int) -> tuple[bytes, str]:
    """service.packing.zip_to_usdz, unpacking at most 4 x max_upload_bytes (and the packing module's own cap);
    a refused entry, limit or damaged zip is a 422 naming the entry as the zip names it (413 over the
    unpacked-size limit)."""
    from ..renderers.scene_data import SceneError
    from ..service.packing import MAX_UNPACKED_BYTES, zip_to_usdz

    try:
        return zip_to_usdz(data, name, max_unpacked=min(MAX_UNPACKED_BYTES, 4 * max_upload_bytes))
    except SceneError as e:
        status = 413 if e.code == "sandbox_limit" else 422
        raise ApiError(status, e.code, f"file: {redact(e.message)}", "file") from e


# over a resource limit: too large (too_large_for_cache: one scene's estimated bytes over the tenant's share of
# the scene cache, scene_cache_bytes * tenant_cache_share)
SCENE_413 = ("too_many_triangles", "too_many_prims", "memory_limit", "load_timeout", "too_large_for_cache")


def scene_error(e, field: str) -> ApiError:
    """A SceneError as the HTTP error: 413 over a resource limit (triangles, load memory or time), else 422
    (sandbox limits, damaged or unsupported files); the message names the field and no server path."""
    status = 413 if e.code in SCENE_413 else 422
    return ApiError(status, e.code, f"{field}: {e.message}", field)


def load_limits(settings: Settings):
    return settings.load_limits()


def scene_options(svc: Service, tenant: str, sandboxed: bool) -> dict:
    """SCENES.get keywords: uploads load sandboxed, in a child with the load limits, counted to the tenant."""
    opts = {"sandbox": sandboxed}
    if sandboxed:
        opts.update(tenant=tenant, limits=load_limits(svc.settings))
    return opts


def load_entry(path, opts: dict, field: str):
    """SCENES.get (cache, single flight, isolated load) in a worker thread; SceneError -> 413/422."""
    from ..renderers.scene_data import SceneError
    from ..service.scenes import SCENES

    try:
        return SCENES.get(path, **opts)
    except SceneError as e:
        raise scene_error(e, field) from e


def cached_entry(path, opts: dict):
    """The loaded scene when it is in memory (no load, nothing blocks), else None."""
    from ..service.scenes import SCENES

    return SCENES.peek(path, **opts)


def load_in_flight(path, opts: dict) -> bool:
    """True while another request loads this scene (the cache's single flight): a follower waits for it
    without a load slot. False when the cache cannot tell (then every loader takes a slot)."""
    from ..service.scenes import SCENES

    loading = getattr(SCENES, "loading", None)
    return bool(loading(path, **opts)) if loading is not None else False


async def store_and_load(svc: Service, ticket, data: bytes, name: str) -> tuple[dict, bool]:
    """Store the file, load it in upload mode (nothing outside the upload is read, limits enforced while
    loading), then record it with what was found in one transaction; a load that fails leaves nothing.
    Runs under the request's admission: the write in a worker thread, the load in a scene-load slot."""
    from ..service.store import scene_id_for

    tenant = ticket.tenant

    def prepare():
        scene_id = scene_id_for(data, name)
        rec = svc.store.scene_record(tenant, scene_id)
        if rec is not None and rec.get("info"):
            return scene_id, rec, None
        reserve_upload(svc, tenant, len(data))
        try:
            _, path, _ = svc.store.write_upload(tenant, data, name)
        except BaseException:
            unreserve_upload(svc, tenant, len(data))
            raise
        return scene_id, None, path

    scene_id, rec, path = await run_in_threadpool(prepare)
    if rec is not None:
        return scene_info(rec, scene_id), False
    try:
        try:
            entry = await svc.in_slot(svc.admission.load, ticket, load_entry, path,
                                      scene_options(svc, tenant, True), "file")
            info = finite(entry.loaded.info())
            if info["triangles"] > svc.settings.max_triangles:  # the loader stops at the limit; a safety net
                raise ApiError(413, "too_many_triangles", f"file: the scene has {info['triangles']} triangles, "
                               f"over the limit of {svc.settings.max_triangles}", "file")
            created = await run_in_threadpool(svc.store.register_upload, tenant, scene_id, path, len(data), info)
        except BaseException:
            with contextlib.suppress(Exception):  # a database that fails here: the start-up sweep removes it
                await run_in_threadpool(svc.store.discard_upload, tenant, scene_id, path)
            raise
    finally:
        unreserve_upload(svc, tenant, len(data))
    if not created:  # a concurrent upload of the same bytes was recorded first
        await run_in_threadpool(svc.store.discard_upload, tenant, scene_id, path)
        rec = await run_in_threadpool(svc.store.scene_record, tenant, scene_id)
        return scene_info(rec or {"info": info, "filename": path.name}, scene_id), False
    return scene_info({"info": info, "filename": path.name}, scene_id), True


def reserve_upload(svc: Service, tenant: str, nbytes: int) -> None:
    """Count an upload's bytes to the tenant's quota (stored plus being stored); 413/429 when over it."""
    quota = svc.settings.tenant_max_stored_bytes
    if nbytes > quota:
        raise ApiError(413, "tenant_quota", f"file: {nbytes} bytes is over the per-tenant storage quota "
                       f"tenant_max_stored_bytes = {quota}", "file")
    with svc._reserved_lock:
        stored = svc.store.tenant_stored_bytes(tenant) + svc._reserved.get(tenant, 0)
        if stored + nbytes > quota:
            raise ApiError(429, "tenant_quota", f"file: this token stores {stored} bytes of scenes; {nbytes} more "
                           f"would be over the per-tenant quota tenant_max_stored_bytes = {quota}; delete scenes "
                           f"to make room", "file", headers={"Retry-After": "60"})
        svc._reserved[tenant] = svc._reserved.get(tenant, 0) + nbytes


def unreserve_upload(svc: Service, tenant: str, nbytes: int) -> None:
    with svc._reserved_lock:
        left = svc._reserved.get(tenant, 0) - nbytes
        if left > 0:
            svc._reserved[tenant] = left
        else:
            svc._reserved.pop(tenant, None)


FOLLOW_POLL_S = 0.02  # how often a request waiting for another request's load of its scene looks again


async def scene_entry_for(svc: Service, ticket, scene_id: str):
    """The loaded scene or 404. From memory when it is there; else reloaded (an evicted upload) under the
    request's admission in a scene-load slot, never a solver slot. Only the leader of a load holds a load
    slot: while another request loads the same scene (single flight) this one waits on the event loop,
    holding no slot and no thread, then takes the entry from the cache."""
    tenant, since = ticket.tenant, time.monotonic()

    def lookup():
        path = svc.store.scene_path(tenant, scene_id)
        return path, (svc.store.scene_sandboxed(tenant, scene_id) if path is not None else True)

    path, sandboxed = await run_in_threadpool(lookup)
    if path is None:
        raise scene_not_found(scene_id)
    opts = scene_options(svc, tenant, sandboxed)
    key, followed = (os.fspath(path), tenant, sandboxed), None
    while True:
        entry = cached_entry(path, opts)
        if entry is not None:
            if followed is not None:
                svc.metrics.load_followers.inc()
            return entry
        if load_in_flight(path, opts):  # a follower: no slot while the leader loads
            followed = followed or time.monotonic()
            await ticket.wait(asyncio.sleep(FOLLOW_POLL_S))
            continue
        failed = svc.failed_loads.get(key)
        if failed is not None and failed[0] >= since:  # a load that began while this request waited failed:
            svc.metrics.load_followers.inc()  # the same answer, no second load
            e = failed[1]
            raise ApiError(e.status_code, e.code, e.message, e.field)
        async with ticket.slot(svc.admission.load):
            failed = svc.failed_loads.get(key)
            if load_in_flight(path, opts) or cached_entry(path, opts) is not None or (
                    failed is not None and failed[0] >= since):
                followed = followed or time.monotonic()
                continue  # another request started (or finished) the load while this one waited: follow it
            try:
                entry = await run_in_threadpool(load_entry, path, opts, "scene_id")
            except ApiError as e:
                svc.note_failed_load(key, e)
                raise
        if followed is not None:
            svc.metrics.load_followers.inc()
        return entry


# --- optimize, evaluate, compare, analyze -------------------------------------------------------

def rig_dict(rig: S.Rig) -> dict:
    return rig.model_dump(by_alias=True)


@contextlib.contextmanager
def solver_errors():
    """RigError/SolutionError/SceneError and the solvers' ValueErrors -> 422 naming the field. Anything else
    (a KeyError, TypeError, ... from a bug) is a 500 internal_error with the request id, logged."""
    from ..renderers.scene_data import SceneError
    from ..service.rigs import RigError, SolutionError

    try:
        yield
    except RigError as e:
        raise ApiError(422, e.code, f"rig.{e.field}: {e.message}", f"rig.{e.field}") from e
    except SolutionError as e:
        raise ApiError(422, e.code, str(e), e.field) from e
    except SceneError as e:
        raise scene_error(e, "scene_id") from e
    except ValueError as e:
        text = str(e)
        head, sep, rest = text.partition(": ")
        field = head if sep and head.replace(".", "").replace("_", "").isalnum() else None
        log.warning("solver refused the input", extra={"fields": {"error": text}})
        raise ApiError(422, "unsolvable", text, field) from e


def check_eval_size(svc: Service, rig: dict, screen, solution: dict | None) -> None:
    """413 when the ground truth would cast more rays than the server's limits allow."""
    w, h = screen or rig["camera"]["resolution"]
    limit = svc.settings.max_eval_pixels
    if w * h > limit:
        field = "screen" if screen else "rig.camera.resolution"
        raise ApiError(413, "too_many_pixels", f"{field}: {w}x{h} pixels is over the limit of {limit}", field)
    limit = svc.settings.max_eval_texels
    shadow = rig.get("shadow") or {}
    cascades = shadow.get("cascades") if isinstance(shadow.get("cascades"), int) else shadow.get("max_cascades", 4)
    budget = shadow.get("texel_budget")
    if budget is not None and budget > limit * max(int(cascades or 1), 1):  # compare sizes maps from the budget
        raise ApiError(413, "too_many_texels", f"rig.shadow.texel_budget: {budget} texels is over the limit of "
                       f"{limit} per map", "rig.shadow.texel_budget")
    lights = (solution or {}).get("lights")  # other shapes: service.solution_check names the field later
    for li, light in enumerate(lights if isinstance(lights, list) else []):
        cascades = light.get("cascades") if isinstance(light, dict) else None
        for ci, c in enumerate(cascades if isinstance(cascades, list) else []):
            res = c.get("resolution") if isinstance(c, dict) else None
            field = f"solution.lights.{li}.cascades.{ci}.resolution"
            if not (isinstance(res, (list, tuple)) and len(res) == 2
                    and all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in res)):
                raise ApiError(422, "invalid_solution", f"{field}: expected two positive integers, got {res!r}", field)
            if res[0] * res[1] > limit:
                raise ApiError(413, "too_many_texels", f"{field}: {res[0]}x{res[1]} texels is over the "
                               f"limit of {limit}", field)


def add_solve_routes(app: FastAPI, svc: Service, Tenant) -> None:
    from ..service.request import SolveRequest
    from ..service.solve import solve

    @app.post("/v1/optimize", summary="Shadow setup for a scene and rig: matrices, warp, cascades, predicted error",
              response_model=S.Solution, responses=error_responses(*AUTHED, 404, 413, 422, 503), tags=["solve"])
    async def optimize(req: S.OptimizeRequest, tenant: Tenant, request: Request):
        rig = rig_dict(req.rig)
        budget = svc.time_budget(req.time_budget_ms)
        async with svc.heavy(tenant, request) as ticket:
            entry = await scene_entry_for(svc, ticket, req.scene_id)
            t0 = time.perf_counter()
            with solver_errors():
                sol = await svc.in_slot(svc.admission.solve, ticket, solve, entry, rig, SolveRequest(
                    method=req.method, solver=req.solver, time_budget_ms=budget, previous=req.previous,
                    hysteresis=req.hysteresis, cache_tenant=tenant))  # service.coarse_cache
            svc.metrics.optimize.observe(time.perf_counter() - t0, req.method)
        return json_response(sol)

    @app.post("/v1/evaluate", summary="Measure a solution against exact ray-traced shadows (optional heatmap PNG)",
              response_model=S.Evaluation, responses=error_responses(*AUTHED, 404, 413, 422, 503), tags=["solve"])
    async def evaluate(req: S.EvaluateRequest, tenant: Tenant, request: Request):
        from ..service.evaluation import evaluate_solution

        rig = rig_dict(req.rig)
        check_eval_size(svc, rig, req.screen, req.solution)

        def run(entry):
            with tempfile.TemporaryDirectory(prefix="shadowopt-heatmap-") as tmp:
                path = str(Path(tmp) / "heatmap.png") if req.heatmap else None
                res = evaluate_solution(entry, rig, req.solution, screen=req.screen, heatmap_path=path,
                                        grid_every=req.grid_every, heatmap_mode=req.heatmap_mode, depth=req.depth)
                if path:
                    res["heatmap_png_base64"] = [base64.b64encode(p.read_bytes()).decode()
                                                 for p in sorted(Path(tmp).glob("heatmap*.png"))]
            return res

        async with svc.heavy(tenant, request) as ticket:
            entry = await scene_entry_for(svc, ticket, req.scene_id)
            with solver_errors():
                res = await svc.in_slot(svc.admission.solve, ticket, run, entry)
        return json_response(res)

    @app.post("/v1/compare", summary="Methods side by side: predicted and measured error, setup time",
              response_model=S.Comparison, responses=error_responses(*AUTHED, 404, 413, 422, 503), tags=["solve"])
    async def compare(req: S.CompareRequest, tenant: Tenant, request: Request):
        from ..service.compare import compare as compare_methods

        rig = rig_dict(req.rig)
        resolution = (rig.get("shadow") or {}).get("resolution")  # None with a texel_budget: sized from it
        check_eval_size(svc, rig, req.screen, {"lights": [{"cascades": [{"resolution": resolution}]}]}
                        if resolution is not None else None)
        methods = list(dict.fromkeys(req.methods))
        async with svc.heavy(tenant, request) as ticket:
            entry = await scene_entry_for(svc, ticket, req.scene_id)
            with solver_errors():
                res = await svc.in_slot(svc.admission.solve, ticket, compare_methods, entry, rig, methods,
                                        screen=req.screen, request=SolveRequest(time_budget_ms=svc.time_budget(None)),
                                        depth=req.depth)
        return json_response(res)

    @app.post("/v1/analyze", summary="Lloyd's scene-independent critical resolution and storage factors",
              response_model=S.Analysis, responses=error_responses(*AUTHED, 413, 422), tags=["solve"])
    def analyze(req: S.AnalyzeRequest, tenant: Tenant):
        from ..solvers.analysis import analyze as lloyd

        with solver_errors():
            res = lloyd(req.f_over_n, req.theta_deg, req.gamma_deg, req.method, partitions=req.partitions,
                        azimuth_deg=req.azimuth_deg)
        res = {k: float(v) for k, v in res.items()}
        if not all(math.isfinite(v) for v in res.values()):
            raise ApiError(422, "not_finite", f"f_over_n: the factors overflow for f/n = {req.f_over_n:g}",
                           "f_over_n")
        return res


# --- batches ------------------------------------------------------------------------------------

def add_batch_routes(app: FastAPI, svc: Service, Tenant) -> None:
    @app.post("/v1/batches", summary="Precompute many camera/light configurations; answers 202 with the batch id",
              response_model=S.BatchCreated, status_code=202, tags=["batches"],
              responses=error_responses(*AUTHED, 404, 413, 422, 503))
    async def create_batch(req: S.BatchRequest, tenant: Tenant, request: Request):
        async with svc.heavy(tenant, request) as ticket:
            entry = await scene_entry_for(svc, ticket, req.scene_id)
            # the per-configuration validation (up to tenant_max_queued rigs resolved against the scene) is
            # solver-bound work: it runs in a solve slot like a solve, never beside solve_threads of them
            return await svc.in_slot(svc.admission.solve, ticket, queue_batch, svc, tenant, req, entry)

    def queue_batch(svc: Service, tenant: str, req: S.BatchRequest, entry) -> Response:
        from ..service.batches import BatchError, expand_configurations, expansion_shape

        body = req.model_dump(by_alias=True, exclude_none=True,
                              exclude={"scene_id", "method", "solver", "time_budget_ms"})
        try:
            configs = expand_configurations(body)
            shape = expansion_shape(body)
        except BatchError as e:
            raise ApiError(422, e.code, f"{e.field}: {e.message}", e.field) from e
        settings = {"method": req.method, "solver": req.solver, "time_budget_ms": svc.time_budget(req.time_budget_ms),
                    "shape": list(shape) if shape else None}
        batch_id, configs = store_batch(svc, tenant, req.scene_id, configs, settings, entry)
        return json_response({"batch_id": batch_id, "scene_id": req.scene_id, "state": "queued",
                              "total": len(configs), "shape": settings["shape"]}, status=202)

    @app.get("/v1/batches/{batch_id}", summary="State, progress and errors of a batch",
             response_model=S.BatchStatus, responses=error_responses(*AUTHED, 404, 422), tags=["batches"])
    def batch_status(batch_id: S.ObjectId, tenant: Tenant):
        b = svc.store.batch(tenant, batch_id)
        if b is None:
            raise batch_not_found(batch_id)
        return json_response(status_json(svc, tenant, b))

    @app.get("/v1/batches/{batch_id}/results", summary="Results as JSON lines, one per configuration, in index "
             "order from `offset`", response_class=Response, tags=["batches"],
             responses={200: {"description": "one JSON object per line, each with its configuration `index`",
                              "content": {"application/x-ndjson": {"schema": {"type": "string"}}}},
                        **error_responses(*AUTHED, 404, 422)})
    def batch_results(batch_id: S.ObjectId, tenant: Tenant,
                      offset: Annotated[int, Query(ge=0, le=10**9, description="first index to return")] = 0,
                      limit: Annotated[int | None, Query(ge=1, le=100_000)] = None):
        if svc.store.batch(tenant, batch_id) is None:
            raise batch_not_found(batch_id)
        rows = svc.store.results(tenant, batch_id, offset=offset, limit=limit)
        body = "".join(json.dumps(REDACT.obj(finite(r)), separators=(",", ":")) + "\n" for r in rows)
        return Response(body, media_type="application/x-ndjson")

    @app.delete("/v1/batches/{batch_id}", summary="Cancel a batch (results so far are kept)",
                response_model=S.BatchStatus, responses=error_responses(*AUTHED, 404, 422), tags=["batches"])
    def cancel_batch(batch_id: S.ObjectId, tenant: Tenant):
        if svc.store.batch(tenant, batch_id) is None:
            raise batch_not_found(batch_id)
        svc.runner.cancel(tenant, batch_id)
        return json_response(status_json(svc, tenant, svc.store.batch(tenant, batch_id)))


def store_batch(svc: Service, tenant: str, scene_id: str, configs: list[dict], settings: dict, entry,
                what: str = "configurations") -> tuple[str, list[dict]]:
    """Check expanded configurations (capacity, the tenant's quota, each rig validated and resolved against
    the scene; `what` names them in errors: configurations or frames), store them as a queued batch and hand
    it to the runner; (batch id, the validated configurations). Items with more than a rig (a path's frames:
    frame, time) keep those fields in the store."""
    from ..service.rigs import resolve_rig

    stored = configs if any(set(c) - {"rig"} for c in configs) else None
    limit = svc.settings.max_queue
    if len(configs) > limit:  # before the per-configuration validation: its cost grows with the count
        raise ApiError(413, "too_many_configurations", f"configurations: {len(configs)} configurations is "
                       f"over the queue's capacity of {limit}", "configurations")
    check_tenant_queue(svc, tenant, len(configs))  # also before the validation
    try:
        checked = S.validate_configurations([{"rig": c["rig"]} for c in configs] if stored else configs)
    except S.ConfigurationError as e:
        raise ApiError(422, "invalid_request", e.message.replace("configurations.", f"{what}."),
                       e.field.replace("configurations.", f"{what}.", 1)) from e
    configs = checked
    if stored:  # a path's frames keep their frame index and time beside the validated rig
        stored = [{**f, "rig": c["rig"]} for f, c in zip(stored, checked)]
    for k, c in enumerate(configs):  # a rig that does not fit the scene is refused now, not per result
        try:
            resolve_rig(c["rig"], entry.loaded)
        except ValueError as e:
            field = f"{what}.{k}.rig" + (f".{e.field}" if getattr(e, "field", None) else "")
            raise ApiError(422, "invalid_rig", f"{field}: {getattr(e, 'message', e)}", field) from e
    with svc.batch_lock:  # the check and the insert together: two requests cannot both take the last room
        check_tenant_queue(svc, tenant, len(configs))
        queued = svc.queue_length()
        if queued + len(configs) > limit:
            raise ApiError(503, "queue_full", f"the batch queue holds {queued} of {limit} configurations; "
                           f"{len(configs)} more do not fit", headers={"Retry-After": str(retry_after(queued))})
        batch_id = svc.store.create_batch(tenant, scene_id, stored or configs, settings)
    svc.runner.submit(tenant, batch_id)
    return batch_id, configs


def add_path_routes(app: FastAPI, svc: Service, Tenant) -> None:
    @app.post("/v1/paths", summary="Solve a camera path frame by frame; answers 202 with the batch id (results: "
              "the batch's, one line per frame in order with frame and time)",
              response_model=S.BatchCreated, status_code=202, tags=["batches"],
              responses=error_responses(*AUTHED, 404, 413, 422, 503))
    async def create_path(req: S.PathRequest, tenant: Tenant, request: Request):
        from ..service.paths import PathError

        body = req.model_dump(by_alias=True, exclude_none=True,
                              exclude={"scene_id", "method", "solver", "time_budget_ms", "coherent"})
        async with svc.heavy(tenant, request) as ticket:
            entry = await scene_entry_for(svc, ticket, req.scene_id)
            # A usd_camera path reads the stage's animation: a stage load (an upload's in an isolated child
            # under the load limits), so it runs in a scene-load slot, never a solver slot, and once per
            # (scene, camera, time codes, lights) (path_animation). The expansion runs twice: first to learn
            # what to read (and refuse a malformed request before any read), then with what was read.
            anim = None
            try:
                for _ in range(2):
                    try:
                        frames, notes = await run_in_threadpool(expand_path_request, body, anim)
                        break
                    except _NeedAnimation as need:
                        if anim is not None:  # pragma: no cover - the second expansion reads what the first asked
                            raise ApiError(500, "internal_error", "the path's animation was not read") from None
                        anim = await path_animation(svc, ticket, req.scene_id, *need.args)
            except PathError as e:
                raise ApiError(422, e.code, f"{e.field}: {e.message}", e.field) from e
            check_path_triangles(svc, entry, anim, frames)
            # the per-frame validation (every frame's rig resolved against the scene) is solver-bound work
            return await svc.in_slot(svc.admission.solve, ticket, queue_path, svc, tenant, req, frames, notes, entry)

    def queue_path(svc: Service, tenant: str, req: S.PathRequest, frames: list, notes: list, entry) -> Response:
        from ..service.paths import is_coherent, is_whole_path

        limits = load_limits(svc.settings)  # a frame's load of the stage at its time code runs under these (the
        # runner passes the server's own at run time; these are the fallback it keeps when it has none)
        settings = {"method": req.method, "solver": req.solver, "time_budget_ms": svc.time_budget(req.time_budget_ms),
                    "shape": None, "coherent": is_coherent(req.method, req.coherent), "path": True,
                    "whole_path": is_whole_path(req.method, req.coherent),
                    "load_limits": {"max_triangles": limits.max_triangles, "memory_bytes": limits.memory_bytes,
                                    "timeout_s": limits.timeout_s}}
        batch_id, _ = store_batch(svc, tenant, req.scene_id, frames, settings, entry, what="frames")
        return json_response({"batch_id": batch_id, "scene_id": req.scene_id, "state": "queued", "total": len(frames),
                              "coherent": settings["coherent"], "notes": notes}, status=202)


def check_path_triangles(svc: Service, entry, anim: dict | None, frames: list) -> None:
    """413 too_many_triangles (field time) when the stage's sampled topology (read_animation's triangles_added:
    a mesh's faceVertexCounts, an instancer's protoIndices) puts it over max_triangles at one of the path's time
    codes: a stage light at its default time (the upload's check) and heavy at t = 5 is refused before any
    frame is queued. An estimate from topology alone; each frame's load checks the real count again."""
    added = (anim or {}).get("triangles_added")
    if not added:
        return
    k = max(range(len(added)), key=added.__getitem__)
    total, limit = entry.loaded.geometry.triangle_count + added[k], svc.settings.max_triangles
    if total > limit:
        grow = ", ".join(anim.get("growing") or [])
        raise ApiError(413, "too_many_triangles", f"time: at time code {frames[k]['time']:g} the stage has about "
                       f"{total} triangles ({grow} grow there), over the limit of {limit}; refused before any frame "
                       "is solved", "time")


class _NeedAnimation(Exception):
    """expand_path_request without the animation it needs: args (camera, times, light_paths)."""


def expand_path_request(body: dict, anim: dict | None) -> tuple[list, list]:
    """service.paths.expand_path_with_notes with `anim` as the reader's answer; _NeedAnimation(camera, times,
    light_paths) when the request needs the stage's animation and `anim` is None. PathError as the paths
    module raises it."""
    from ..service.paths import expand_path_with_notes

    def reader(camera, times, light_paths):
        if anim is None:
            raise _NeedAnimation(camera, tuple(times), tuple(light_paths))
        return anim

    return expand_path_with_notes(body, reader=reader)


# (tenant, scene file identity, sandboxed, camera, time codes, light paths) -> (when, animation dict or ApiError):
# what read_animation_for returned, so the same path asked again (or resumed by a client) does not read the
# stage again; failures are kept ANIMATION_ERROR_TTL_S. Event loop only.
_ANIMATIONS: "OrderedDict[tuple, tuple[float, object]]" = OrderedDict()
_ANIMATIONS_LOADING: dict[tuple, asyncio.Event] = {}
ANIMATION_CACHE_ENTRIES = 32
ANIMATION_CACHE_FRAMES = 50_000  # time codes over all cached animations (a camera and its lights per code)
ANIMATION_ERROR_TTL_S = 60.0
ANIMATION_STATS = {"reads": 0, "hits": 0}


def _animation_key(tenant: str, path, sandboxed: bool, camera: str, times: tuple, light_paths: tuple) -> tuple:
    st = os.stat(path)
    return (tenant, os.path.realpath(path), st.st_size, st.st_mtime_ns, sandboxed, camera, times, light_paths)


def _cached_animation(key: tuple):
    got = _ANIMATIONS.get(key)
    if got is None:
        return None
    when, value = got
    if isinstance(value, ApiError) and time.monotonic() - when > ANIMATION_ERROR_TTL_S:
        del _ANIMATIONS[key]
        return None
    _ANIMATIONS.move_to_end(key)
    return got


def _keep_animation(key: tuple, value) -> None:
    _ANIMATIONS[key] = (time.monotonic(), value)
    _ANIMATIONS.move_to_end(key)
    while len(_ANIMATIONS) > ANIMATION_CACHE_ENTRIES or (
            len(_ANIMATIONS) > 1 and sum(len(k[6]) for k in _ANIMATIONS) > ANIMATION_CACHE_FRAMES):
        _ANIMATIONS.popitem(last=False)


async def path_animation(svc: Service, ticket, scene_id: str, camera: str, times: tuple, light_paths: tuple) -> dict:
    """The stage's animation for a usd_camera path (read_animation_for), cached per (scene, camera, time codes,
    lights): read in a scene-load slot by one request while the others asking for the same wait for it holding
    no slot. A read that fails is the same ApiError for ANIMATION_ERROR_TTL_S."""
    from ..renderers.scene_data import SceneError

    tenant = ticket.tenant

    def lookup():
        path = svc.store.scene_path(tenant, scene_id)
        if path is None:
            return None, True, None
        sandboxed = svc.store.scene_sandboxed(tenant, scene_id)
        try:
            key = _animation_key(tenant, path, sandboxed, camera, times, light_paths)
        except OSError:
            return None, True, None
        return path, sandboxed, key

    path, sandboxed, key = await run_in_threadpool(lookup)
    if path is None:
        raise scene_not_found(scene_id)
    while True:
        got = _cached_animation(key)
        if got is not None:
            ANIMATION_STATS["hits"] += 1
            if isinstance(got[1], ApiError):
                e = got[1]
                raise ApiError(e.status_code, e.code, e.message, e.field)
            return got[1]
        loading = _ANIMATIONS_LOADING.get(key)
        if loading is not None:  # another request reads it: wait without a slot, then take it from the cache
            await ticket.wait(loading.wait())
            continue  # cached now; or the reader left (its client went away) without an answer: read it here
        break
    done = _ANIMATIONS_LOADING[key] = asyncio.Event()
    try:
        async with ticket.slot(svc.admission.load):
            ANIMATION_STATS["reads"] += 1
            try:
                anim = await run_in_threadpool(read_animation_for, svc, path, sandboxed, camera, list(times),
                                               list(light_paths))
            except SceneError as e:
                err = scene_error(e, "usd_camera")
                _keep_animation(key, err)
                raise err from e
        _keep_animation(key, anim)
        return anim
    finally:
        del _ANIMATIONS_LOADING[key]
        done.set()


def read_animation_for(svc: Service, path, sandboxed: bool, camera: str, times: list, light_paths: list) -> dict:
    """renderers.usd_loader.read_animation on a stored scene: an upload in a child under the load limits (as
    its load), a local scene in this process."""
    from ..renderers.usd_loader import read_animation

    if not sandboxed:
        return read_animation(os.fspath(path), camera, times, light_paths=light_paths)
    from ..service.isolation import run_isolated

    limits = load_limits(svc.settings)
    return run_isolated(read_animation, (os.fspath(path), camera, times), {"light_paths": light_paths, "sandbox": True},
                        memory_bytes=limits.memory_bytes, timeout_s=limits.timeout_s,
                        what=f"scene {os.path.basename(os.fspath(path))!r}")


def check_tenant_queue(svc: Service, tenant: str, n: int) -> None:
    """429 when this tenant's queued configurations plus `n` are over tenant_max_queued: one tenant cannot fill
    the queue for everyone."""
    quota = svc.settings.tenant_max_queued
    mine = svc.store.pending_configurations(tenant) if n <= quota else 0
    if mine + n > quota:
        raise ApiError(429, "tenant_quota", f"configurations: this token has {mine} batch configurations queued; "
                       f"{n} more would be over the per-tenant quota tenant_max_queued = {quota}", "configurations",
                       headers={"Retry-After": str(retry_after(mine))})


def batch_not_found(batch_id: str) -> ApiError:
    return ApiError(404, "batch_not_found", f"batch_id: no batch {batch_id!r} for this token", "batch_id")


def retry_after(queued: int) -> int:
    return int(min(60, max(1, queued // 10)))


_HINTS: "OrderedDict[tuple, dict]" = OrderedDict()  # (tenant, batch_id) -> hints of a finished batch
_HINTS_LOCK = threading.Lock()  # routes run on threadpool threads
HINTS_KEPT = 256
HINTS_PAGE = 1000


def status_json(svc: Service, tenant: str, b: dict) -> dict:
    out = {k: v for k, v in b.items() if k not in ("configurations", "tenant")}
    total = int(b.get("total") or 0)
    out["progress"] = round((int(b.get("done") or 0) + int(b.get("failed") or 0)) / total, 6) if total else 1.0
    out.setdefault("errors", [])
    if b.get("state") == "done" and out.get("interpolation") is None:
        out["interpolation"] = batch_hints(svc, tenant, b)
    return out


def batch_hints(svc: Service, tenant: str, b: dict) -> dict:
    """service.batches.interpolation_hints over the results, read a page at a time and cut down to the
    fields the hints compare (a big batch never sits in memory whole); cached per finished batch."""
    from ..service.batches import interpolation_hints

    key = (tenant, b["batch_id"])
    with _HINTS_LOCK:
        if key in _HINTS:
            _HINTS.move_to_end(key)
            return _HINTS[key]
    rows, offset = [], 0
    while True:
        page = svc.store.results(tenant, b["batch_id"], offset=offset, limit=HINTS_PAGE)
        rows += [_skeleton(r) for r in page]
        if len(page) < HINTS_PAGE:
            break
        offset = page[-1]["index"] + 1
    shape = (b.get("settings") or {}).get("shape")
    hints = interpolation_hints(rows, tuple(shape) if shape else None)
    with _HINTS_LOCK:
        _HINTS[key] = hints
        while len(_HINTS) > HINTS_KEPT:
            _HINTS.popitem(last=False)
    return hints


def _skeleton(r: dict) -> dict:
    if "error" in r:
        return {"index": r["index"], "error": r["error"]}
    keep = ("kind",)
    return {"index": r["index"], "method": r.get("method"), "lights": [
        {"type": l.get("type"), "cascades": [
            {"resolution": c.get("resolution"), "face": c.get("face"),
             "warp": {k: (c.get("warp") or {}).get(k) for k in keep}} for c in l.get("cascades") or []]}
        for l in r.get("lights") or []]}


# --- serve --------------------------------------------------------------------------------------

def _version() -> str:
    try:
        from importlib.metadata import version

        return version("shadowopt")
    except Exception:
        return "0+unknown"


def check_host(settings: Settings) -> str | None:
    """Why the server must not start on this host, or None."""
    if not settings.auth_enabled and not is_loopback(settings.host):
        return (f"--host {settings.host}: no tokens are configured (SHADOWOPT_TOKENS or `tokens` in the config "
                f"file), so the server only listens on 127.0.0.1; configure tokens to serve on other addresses")
    return None


def serve(settings: Settings) -> int:
    import uvicorn

    configure_logging(settings.log_level)
    refusal = check_host(settings)
    if refusal:
        print(f"shadowopt: error: {refusal}", file=sys.stderr)
        return 2
    if not settings.auth_enabled:
        log.warning("no tokens configured: authentication is off and the server listens on loopback only",
                    extra={"fields": {"host": settings.host}})
    app = create_app(settings)
    log.info("serving", extra={"fields": {"url": f"http://{settings.host}:{settings.port}", "health": "/healthz",
                                          "docs": "/docs", "auth": settings.auth_enabled}})
    uvicorn.run(app, host=settings.host, port=settings.port, log_config=None, access_log=False)
    return 0


def openapi_document() -> dict:
    """The OpenAPI document the app serves (independent of the settings)."""
    return create_app(Settings()).openapi()


def write_openapi(path: str | os.PathLike = REPO / "docs" / "openapi.json") -> Path:
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(json.dumps(openapi_document(), indent=2, sort_keys=True) + "\n")
    return p


if __name__ == "__main__":  # python -m shadowopt.api.server [PATH]: rewrite docs/openapi.json
    print(write_openapi(*sys.argv[1:2]))
