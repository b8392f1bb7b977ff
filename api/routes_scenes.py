"""The REST service's scene routes: upload (raw, multipart or a zipped folder), list, describe, delete; the
per-tenant storage quota of uploads."""

import contextlib
import os
from pathlib import Path
from typing import Annotated

from fastapi import FastAPI, Header, Query, Request
from starlette.concurrency import run_in_threadpool

from . import schemas as S
from ..renderers.scene_data import SceneError
from ..service.packing import MAX_UNPACKED_BYTES, zip_declared_bytes, zip_to_usdz_file
from ..service.store import scene_id_for
from .errors import AUTHED, ApiError, error_responses
from .responses import finite, json_response, redact
from .scene_loading import load_entry, scene_not_found, scene_options
from .service_state import Service

SCENE_SUFFIXES = (".usda", ".usdc", ".usdz", ".usd", ".zip")  # .zip: a scene's folder, stored as a .usdz


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
                info, created = await store_zip(svc, ticket, data, name)
            else:
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


def zip_limit(svc: Service) -> int:
    """The most bytes a zip upload may unpack to: 4 x max_upload_bytes, within the packing module's own cap."""
    return min(MAX_UNPACKED_BYTES, 4 * svc.settings.max_upload_bytes)


def zip_error(e: SceneError) -> ApiError:
    """A refused entry, limit or damaged zip: 422 naming the entry as the zip names it (413 over a limit)."""
    status = 413 if e.code == "sandbox_limit" else 422
    return ApiError(status, e.code, f"file: {redact(e.message)}", "file")


async def store_zip(svc: Service, ticket, data: bytes, name: str) -> tuple[dict, bool]:
    """A .zip of a scene's folder, stored as a .usdz. Before anything is unpacked, the bytes its entries declare
    are checked against the server's limit and reserved against the tenant's quota (413/429 as an upload of that
    size); unpacking then runs in a scene-load slot (one of `load_threads`: concurrent zips unpack one after
    another), counting the bytes it writes (never past the declared total), into a scratch folder of the data
    directory (Store.work_dir, swept at start), and the package is moved into the store, never read into
    memory."""
    limit = zip_limit(svc)
    try:
        declared = await run_in_threadpool(zip_declared_bytes, data, name, limit)
    except SceneError as e:
        raise zip_error(e) from e
    await run_in_threadpool(reserve_upload, svc, ticket.tenant, declared, "declared by the zip's files")
    try:
        with svc.store.work_dir() as work:
            try:
                package, pkg_name = await svc.in_slot(svc.admission.load, ticket, zip_to_usdz_file, data, name,
                                                      work, limit)
            except SceneError as e:
                raise zip_error(e) from e
            unreserve_upload(svc, ticket.tenant, declared)
            declared = 0
            return await store_and_load(svc, ticket, package, pkg_name)
    finally:
        unreserve_upload(svc, ticket.tenant, declared)


async def store_and_load(svc: Service, ticket, data: bytes | Path, name: str) -> tuple[dict, bool]:
    """Store the file (`data`: its bytes, or a package in the data directory, which is moved into the store),
    load it in upload mode (nothing outside the upload is read, limits enforced while loading), then record it
    with what was found in one transaction; a load that fails leaves nothing. Runs under the request's
    admission: the write in a worker thread, the load in a scene-load slot."""
    tenant = ticket.tenant
    nbytes = len(data) if isinstance(data, bytes) else os.path.getsize(data)

    def prepare():
        scene_id = scene_id_for(data, name)
        rec = svc.store.scene_record(tenant, scene_id)
        if rec is not None and rec.get("info"):
            return scene_id, rec, None
        reserve_upload(svc, tenant, nbytes)
        try:
            _, path, _ = svc.store.write_upload(tenant, data, name)
        except BaseException:
            unreserve_upload(svc, tenant, nbytes)
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
            created = await run_in_threadpool(svc.store.register_upload, tenant, scene_id, path, nbytes, info)
        except BaseException:
            with contextlib.suppress(Exception):  # a database that fails here: the start-up sweep removes it
                await run_in_threadpool(svc.store.discard_upload, tenant, scene_id, path)
            raise
    finally:
        unreserve_upload(svc, tenant, nbytes)
    if not created:  # a concurrent upload of the same bytes was recorded first
        await run_in_threadpool(svc.store.discard_upload, tenant, scene_id, path)
        rec = await run_in_threadpool(svc.store.scene_record, tenant, scene_id)
        return scene_info(rec or {"info": info, "filename": path.name}, scene_id), False
    return scene_info({"info": info, "filename": path.name}, scene_id), True


def reserve_upload(svc: Service, tenant: str, nbytes: int, what: str = "") -> None:
    """Count an upload's bytes to the tenant's quota (stored plus being stored); 413/429 when over it. `what`
    says where the count comes from in the message (a zip's declared size). Reads the database: a worker
    thread's call."""
    quota = svc.settings.tenant_max_stored_bytes
    if nbytes > quota:
        raise ApiError(413, "tenant_quota", f"file: {nbytes} bytes{' unpacked, ' + what + ',' if what else ''} "
                       f"over the per-tenant storage quota tenant_max_stored_bytes = {quota}", "file")
    with svc.reserved_lock:
        stored = svc.store.tenant_stored_bytes(tenant) + svc.reserved.get(tenant, 0)
        if stored + nbytes > quota:
            raise ApiError(429, "tenant_quota", f"file: this token stores {stored} bytes of scenes; {nbytes} more "
                           f"{'(unpacked, ' + what + ') ' if what else ''}"
                           f"would be over the per-tenant quota tenant_max_stored_bytes = {quota}; delete scenes "
                           f"to make room", "file", headers={"Retry-After": "60"})
        svc.reserved[tenant] = svc.reserved.get(tenant, 0) + nbytes


def unreserve_upload(svc: Service, tenant: str, nbytes: int) -> None:
    with svc.reserved_lock:
        left = svc.reserved.get(tenant, 0) - nbytes
        if left > 0:
            svc.reserved[tenant] = left
        else:
            svc.reserved.pop(tenant, None)
