"""The REST service's errors: ApiError and the `{"error": {"code", "message", "field"}}` body, the OpenAPI
`responses=` of each route, FastAPI's validation errors in that shape, the exception handlers, and the
library errors (SceneError, RigError, SolutionError, a solver's ValueError) as HTTP errors."""

import contextlib
import logging
import sqlite3

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.requests import ClientDisconnect

from . import schemas as S
from ..renderers.scene_data import SceneError
from ..service.method_options import OptionError
from ..service.rigs import RigError, SolutionError
from .admission import ClientGone
from .responses import redact

log = logging.getLogger("shadowopt.server")

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


# over a resource limit: too large (too_large_for_cache: one scene's estimated bytes over the tenant's share of
# the scene cache, scene_cache_bytes * tenant_cache_share)
SCENE_413 = ("too_many_triangles", "too_many_prims", "memory_limit", "load_timeout", "too_large_for_cache",
             "export_too_large")


def scene_error(e, field: str) -> ApiError:
    """A SceneError as the HTTP error: 413 over a resource limit (triangles, load memory or time), else 422
    (sandbox limits, damaged or unsupported files); the message names the field and no server path."""
    status = 413 if e.code in SCENE_413 else 422
    return ApiError(status, e.code, f"{field}: {e.message}", field)


@contextlib.contextmanager
def solver_errors():
    """RigError/SolutionError/OptionError/SceneError and the solvers' ValueErrors -> 422 naming the field. Anything else
    (a KeyError, TypeError, ... from a bug) is a 500 internal_error with the request id, logged."""
    try:
        yield
    except RigError as e:
        raise ApiError(422, e.code, f"rig.{e.field}: {e.message}", f"rig.{e.field}") from e
    except (SolutionError, OptionError) as e:
        raise ApiError(422, e.code, str(e), e.field) from e
    except SceneError as e:
        raise scene_error(e, "scene_id") from e
    except ValueError as e:
        text = str(e)
        head, sep, rest = text.partition(": ")
        field = head if sep and head.replace(".", "").replace("_", "").isalnum() else None
        log.warning("solver refused the input", extra={"fields": {"error": text}})
        raise ApiError(422, "unsolvable", text, field) from e
