"""The REST service's camera-path route (POST /v1/paths) and its cache of the stage animations it reads."""

import asyncio
import os
import time
from collections import OrderedDict

from fastapi import FastAPI, Request
from fastapi.responses import Response
from starlette.concurrency import run_in_threadpool

from . import schemas as S
from ..renderers.scene_data import SceneError
from ..renderers.usd_animation import read_animation
from ..service.isolation import run_isolated
from ..service.method_options import check_options
from ..service.paths import PathError, expand_path_with_notes, is_coherent, is_whole_path
from .errors import AUTHED, ApiError, error_responses, scene_error, solver_errors
from .responses import json_response
from .routes_batches import store_batch
from .scene_loading import scene_entry_for, scene_not_found
from .service_state import Service, load_limits


def add_path_routes(app: FastAPI, svc: Service, Tenant) -> None:
    @app.post("/v1/paths", summary="Solve a camera path frame by frame; answers 202 with the batch id (results: "
              "the batch's, one line per frame in order with frame and time)",
              response_model=S.BatchCreated, status_code=202, tags=["batches"],
              responses=error_responses(*AUTHED, 404, 413, 422, 503))
    async def create_path(req: S.PathRequest, tenant: Tenant, request: Request):
        body = req.model_dump(by_alias=True, exclude_none=True,
                              exclude={"scene_id", "method", "solver", "time_budget_ms", "coherent"})
        with solver_errors():  # a solver or time budget the method would ignore: 422 naming the field
            check_options(req.method, None, solver=req.solver, time_budget_ms=req.time_budget_ms)
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
    """renderers.usd_animation.read_animation on a stored scene: an upload in a child under the load limits (as
    its load), a local scene in this process."""
    if not sandboxed:
        return read_animation(os.fspath(path), camera, times, light_paths=light_paths)

    limits = load_limits(svc.settings)
    return run_isolated(read_animation, (os.fspath(path), camera, times), {"light_paths": light_paths, "sandbox": True},
                        memory_bytes=limits.memory_bytes, timeout_s=limits.timeout_s,
                        what=f"scene {os.path.basename(os.fspath(path))!r}")
