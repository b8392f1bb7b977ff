"""The REST service's system routes: /healthz (readiness) and /metrics (Prometheus); the package version."""

import asyncio
import sqlite3
from importlib.metadata import version

from fastapi import FastAPI
from fastapi.responses import JSONResponse, Response

from . import schemas as S
from .errors import database_message, error_responses
from .responses import REDACT, json_response
from .service_state import Service


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
                "warm_errors": svc.warm_errors, "queue_length": queued, "version": package_version()}
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


def package_version() -> str:
    try:
        return version("shadowopt")
    except Exception:
        return "0+unknown"
