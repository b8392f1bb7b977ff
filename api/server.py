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

This module assembles the app (create_app, the bearer-token tenant) and serves it; the parts live beside it:
errors.py (ApiError, the error body, handlers), responses.py (redaction, finite JSON), rate_limit.py,
service_state.py (the Service object the routes share, warm-up), middleware.py (request ids, JSON log),
scene_loading.py (a request's scene from the cache or loaded), routes_system.py, routes_scenes.py,
routes_solve.py, routes_batches.py, routes_paths.py and inspect.py (the routes).
"""

import contextlib
import json
import logging
import math
import os
import sys
from pathlib import Path
from typing import Annotated

import uvicorn
from fastapi import Depends, FastAPI, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from starlette.concurrency import run_in_threadpool

from .errors import ApiError, install_error_handlers
from .inspect import add_inspect_routes
from .middleware import RequestContext, configure_logging
from .routes_batches import add_batch_routes
from .routes_paths import add_path_routes
from .routes_scenes import add_scene_routes
from .routes_solve import add_solve_routes
from .routes_system import add_system_routes, package_version
from .service_state import REPO, Service
from .settings import Settings, is_loopback, load_settings

log = logging.getLogger("shadowopt.server")


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

    app = FastAPI(title="shadowopt", version=package_version(), lifespan=lifespan,
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
    add_inspect_routes(app, svc, Tenant)  # /inspect and the scene's glTF
    return app


# --- serve --------------------------------------------------------------------------------------


def check_host(settings: Settings) -> str | None:
    """Why the server must not start on this host, or None."""
    if not settings.auth_enabled and not is_loopback(settings.host) and not settings.allowed_hosts:
        return (f"--host {settings.host}: no tokens are configured (SHADOWOPT_TOKENS or `tokens` in the config "
                f"file), so the server only listens on 127.0.0.1; configure tokens to serve on other addresses "
                f"(or, to serve them without authentication, list the names clients reach it by in allowed_hosts)")
    return None


def serve(settings: Settings) -> int:
    configure_logging(settings.log_level)
    refusal = check_host(settings)
    if refusal:
        print(f"shadowopt: error: {refusal}", file=sys.stderr)
        return 2
    if not settings.auth_enabled:
        log.warning("no tokens configured: authentication is off; only loopback names and allowed_hosts are "
                    "answered, and only requests without a foreign Origin",
                    extra={"fields": {"host": settings.host, "allowed_hosts": settings.allowed_hosts,
                                      "allowed_origins": settings.allowed_origins}})
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
