"""The REST service's batch routes: create, status (with interpolation hints once done), results, cancel;
the queue's capacity and per-tenant quota checks shared with the path route."""

import threading
from collections import OrderedDict
from typing import Annotated

from fastapi import FastAPI, Query, Request
from fastapi.responses import Response, StreamingResponse
from starlette.concurrency import run_in_threadpool

from . import schemas as S
from ..renderers.json_text import dumps
from ..service.batch_request import expand_configurations, expansion_shape
from ..service.interpolation_hints import interpolation_hints
from ..service.method_options import check_options
from ..service.request_fields import BatchError
from ..service.rigs import resolve_rig
from .errors import AUTHED, ApiError, error_responses, solver_errors
from .responses import REDACT, finite, json_response
from .scene_loading import scene_entry_for
from .service_state import Service


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
        body = req.model_dump(by_alias=True, exclude_none=True,
                              exclude={"scene_id", "method", "solver", "time_budget_ms"})
        try:
            configs = expand_configurations(body)
            shape = expansion_shape(body)
        except BatchError as e:
            raise ApiError(422, e.code, f"{e.field}: {e.message}", e.field) from e
        with solver_errors():  # the batch's settings against each configuration's rig: 422 naming the field
            for c in configs:
                check_options(req.method or "optimized", (c.get("rig") or {}).get("shadow"), solver=req.solver,
                              time_budget_ms=req.time_budget_ms)
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
             "order from `offset`, streamed a page at a time (at most `limit` lines)", response_class=Response,
             tags=["batches"],
             responses={200: {"description": "one JSON object per line, each with its configuration `index`; "
                              "a page of `limit` lines is full when more may follow: ask again from the last "
                              "index + 1",
                              "content": {"application/x-ndjson": {"schema": {"type": "string"}}}},
                        **error_responses(*AUTHED, 404, 422, 429, 503)})
    async def batch_results(batch_id: S.ObjectId, tenant: Tenant,
                            offset: Annotated[int, Query(ge=0, le=10**9, description="first index to return")] = 0,
                            limit: Annotated[int | None, Query(ge=1, le=100_000, description=(
                                "at most this many lines (default: every line from offset, streamed)"))] = None):
        # A heavy request of its own (issue 27: four whole-batch reads at once took +1.66 GB and starved the
        # others): admitted like one (429/503 at once), then a download slot held while the body streams, read
        # and written RESULTS_PAGE lines at a time in a worker thread (the memory of one page, whatever the batch).
        ticket = svc.admit(tenant)
        slot = False
        try:
            if await run_in_threadpool(svc.store.batch, tenant, batch_id, max_errors=0) is None:
                raise batch_not_found(batch_id)
            await svc.admission.download.acquire(tenant)
            slot = True
        except BaseException:
            ticket.release()
            raise

        async def lines():
            try:
                nxt, left = offset, limit
                while left is None or left > 0:
                    n = RESULTS_PAGE if left is None else min(RESULTS_PAGE, left)
                    body, count, last = await run_in_threadpool(results_page, svc, tenant, batch_id, nxt, n)
                    if body:
                        yield body
                    if count < n:
                        return
                    nxt = last + 1
                    left = None if left is None else left - count
            finally:
                if slot:
                    svc.admission.download.release(tenant)
                ticket.release()

        return StreamingResponse(lines(), media_type="application/x-ndjson")

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


def check_tenant_queue(svc: Service, tenant: str, n: int) -> None:
    """429 when this tenant's queued configurations plus `n` are over tenant_max_queued: one tenant cannot fill
    the queue for everyone."""
    quota = svc.settings.tenant_max_queued
    mine = svc.store.pending_configurations(tenant) if n <= quota else 0
    if mine + n > quota:
        raise ApiError(429, "tenant_quota", f"configurations: this token has {mine} batch configurations queued; "
                       f"{n} more would be over the per-tenant quota tenant_max_queued = {quota}", "configurations",
                       headers={"Retry-After": str(retry_after(mine))})


RESULTS_PAGE = 64  # result lines read from the store and written at a time by GET .../results


def results_page(svc: Service, tenant: str, batch_id: str, offset: int, limit: int) -> tuple[bytes, int, int]:
    """(NDJSON of up to `limit` result lines from `offset`, how many, the last one's index)."""
    rows = svc.store.results(tenant, batch_id, offset=offset, limit=limit)
    body = "".join(dumps(REDACT.obj(finite(r)), separators=(",", ":")) + "\n" for r in rows).encode()
    return body, len(rows), rows[-1]["index"] if rows else offset - 1


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
    """service.interpolation_hints.interpolation_hints over the results, read a page at a time and cut down to the
    fields the hints compare (a big batch never sits in memory whole); cached per finished batch."""
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
