"""A request's stored scene, loaded: from the scene cache when it is there, else loaded (uploads sandboxed,
under the load limits) in a scene-load slot, one load per scene at a time (the others follow it)."""

import asyncio
import os
import time

from starlette.concurrency import run_in_threadpool

from ..renderers.scene_data import SceneError
from ..service.scenes import SCENES
from .errors import ApiError, scene_error
from .service_state import Service, load_limits


def scene_not_found(scene_id: str) -> ApiError:
    return ApiError(404, "scene_not_found", f"scene_id: no scene {scene_id!r} for this token", "scene_id")


def scene_options(svc: Service, tenant: str, sandboxed: bool) -> dict:
    """SCENES.get keywords: uploads load sandboxed, in a child with the load limits, counted to the tenant."""
    opts = {"sandbox": sandboxed}
    if sandboxed:
        opts.update(tenant=tenant, limits=load_limits(svc.settings))
    return opts


def load_entry(path, opts: dict, field: str):
    """SCENES.get (cache, single flight, isolated load) in a worker thread; SceneError -> 413/422."""
    try:
        return SCENES.get(path, **opts)
    except SceneError as e:
        raise scene_error(e, field) from e


def cached_entry(path, opts: dict):
    """The loaded scene when it is in memory (no load, nothing blocks), else None."""
    return SCENES.peek(path, **opts)


def load_in_flight(path, opts: dict) -> bool:
    """True while another request loads this scene (the cache's single flight): a follower waits for it
    without a load slot. False when the cache cannot tell (then every loader takes a slot)."""
    loading = getattr(SCENES, "loading", None)
    return bool(loading(path, **opts)) if loading is not None else False


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
