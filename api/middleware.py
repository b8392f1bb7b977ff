"""The REST service's ASGI middleware and logging: request ids (X-Request-ID), one JSON log line and the
metrics per request, the body-size limit; the JSON log format."""

import json
import logging
import sys
import time
import traceback
import uuid

from .errors import error_json
from .host_guard import refusal
from .responses import finite
from .service_state import Service

log = logging.getLogger("shadowopt.server")


class RequestContext:
    """ASGI middleware: X-Request-ID (echoed; generated when absent), a JSON log line and metrics per
    request, local mode's Host and Origin check (host_guard), and the body-size limit (413 before the body is
    read when Content-Length says so)."""

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
            refused = refusal(scope, self.service.settings)  # no tokens: a foreign Host or Origin
            if refused is not None:
                scope["state"]["error_code"] = refused[1]
                await error_json(*refused)(scope, receive, send_with_id)
            elif too_big is not None:
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
