"""The browser inspector: the page at /inspect (static files of this package, api/static/inspect, served
by Starlette's StaticFiles; nothing is fetched from elsewhere) and the endpoint it reads a scene's
geometry from, GET /v1/scenes/{scene_id}/geometry.glb: the scene's triangles as binary glTF
(service.scene_export), decimated above `max_triangles`, with the same bearer-token authentication,
admission and tenant isolation as every other scene endpoint (another tenant's scene id is a 404). The
export is refused with 413 before any work over `max_export_triangles` (the scene's) or `max_export_bytes`
(the GLB's bound), runs in a child process under the load limits in a solver slot, and is kept in the
geometry cache (`geometry_cache_bytes`, a per-tenant share).

The page itself is public (it holds no data); every request it makes carries the token the user typed,
kept in the tab's sessionStorage.
"""

import importlib.util
from pathlib import Path
from typing import Annotated

from fastapi import APIRouter, FastAPI, Query, Request
from fastapi.responses import FileResponse, Response
from fastapi.staticfiles import StaticFiles

from . import schemas as S
from ..service.scene_export import (DEFAULT_TRIANGLE_BUDGET, MAX_TRIANGLE_BUDGET, cached_glb, export_estimate,
                                    glb_isolated)
from .errors import AUTHED, ApiError, error_responses, solver_errors
from .scene_loading import scene_entry_for

STATIC = Path(__file__).resolve().parent / "static" / "inspect"
DEMO_SCENE = Path(__file__).resolve().parents[1] / "configs" / "demo_scene.usda"
DEMO_RIG = Path(__file__).resolve().parents[1] / "configs" / "demo_rig.json"


def add_inspect_routes(app: FastAPI, svc, Tenant) -> None:
    """The inspector's routes on `app` (svc: the server's Service; Tenant: its authenticated-tenant
    dependency)."""
    router = APIRouter()

    @router.get("/v1/scenes/{scene_id}/geometry.glb", tags=["scenes"],
                summary="The scene's triangles as binary glTF (world frame: +Y up, metres; the root node's "
                "translation is the re-centring origin), decimated above max_triangles",
                response_class=Response, responses={
                    200: {"content": {"model/gltf-binary": {}},
                          "description": "GLB; headers X-Scene-Triangles (the scene's), X-Served-Triangles, "
                          "X-Triangle-Budget, X-Decimated (true: a preview whose shadows are not the scene's), X-Geometry-Cache "
                          "(hit: from the geometry cache)"},
                    **error_responses(*AUTHED, 404, 413, 422, 503)})
    async def scene_geometry(scene_id: S.ObjectId, tenant: Tenant, request: Request,
                             max_triangles: Annotated[int, Query(ge=1000, le=MAX_TRIANGLE_BUDGET, description=(
                                 "the triangle budget: a scene with more is decimated (quadric edge collapse, "
                                 "Garland and Heckbert 1997) to at most this many"))] = DEFAULT_TRIANGLE_BUDGET):
        for name in ("pyfqmr", "trimesh"):  # the decimation and the glTF writer, imported in the export child only
            if importlib.util.find_spec(name) is None:
                raise ApiError(503, "geometry_export_unavailable", f"this server cannot write glTF: {name} is not "
                               "installed (requirements.lock)")
        st = svc.settings
        async with svc.heavy(tenant, request) as ticket:
            entry = await scene_entry_for(svc, ticket, scene_id)
            n, size = export_estimate(entry.loaded, max_triangles)  # the bounds before any work: 413 at once
            if n > st.max_export_triangles:
                raise ApiError(413, "too_many_triangles", f"scene_id: the scene has {n} triangles, more than the "
                               f"geometry export's limit of {st.max_export_triangles} (max_export_triangles); "
                               "refused before any work", "scene_id")
            if size > st.max_export_bytes:
                raise ApiError(413, "export_too_large", f"max_triangles: the GLB at max_triangles {max_triangles} "
                               f"could take {size} bytes, more than the limit of {st.max_export_bytes} "
                               "(max_export_bytes); ask for a smaller max_triangles", "max_triangles")
            got = cached_glb(entry.loaded, max_triangles, tenant)  # a hit takes no solver slot
            with solver_errors():
                data, info, hit = (*got, True) if got is not None else await svc.in_slot(
                    svc.admission.solve, ticket, glb_isolated, entry.loaded, max_triangles, tenant=tenant,
                    max_export_triangles=st.max_export_triangles, max_export_bytes=st.max_export_bytes,
                    memory_bytes=st.load_memory_bytes, timeout_s=st.load_timeout_s, what=f"scene {scene_id!r}")
        return Response(data, media_type="model/gltf-binary", headers={
            "X-Scene-Triangles": str(info.triangles), "X-Served-Triangles": str(info.served_triangles),
            "X-Triangle-Budget": str(info.budget), "X-Decimated": "true" if info.decimated else "false",
            "X-Geometry-Cache": "hit" if hit else "miss",
            "Cache-Control": "private, no-store"})

    @router.get("/inspect", include_in_schema=False)
    def inspect_page():
        return FileResponse(STATIC / "index.html", media_type="text/html")

    @router.get("/inspect/demo/scene.usda", include_in_schema=False)
    def demo_scene():
        """The bundled demo scene, for the page's "demo scene" button (uploaded like any other file)."""
        return FileResponse(DEMO_SCENE, media_type="application/octet-stream", filename="demo_scene.usda")

    @router.get("/inspect/demo/rig.json", include_in_schema=False)
    def demo_rig():
        return FileResponse(DEMO_RIG, media_type="application/json")

    app.include_router(router)
    app.mount("/inspect/static", StaticFiles(directory=STATIC), name="inspect-static")
