"""The browser inspector: the page at /inspect (static files of this package, api/static/inspect, served
by Starlette's StaticFiles; nothing is fetched from elsewhere) and the endpoint it reads a scene's
geometry from, GET /v1/scenes/{scene_id}/geometry.glb: the scene's triangles as binary glTF
(service.scene_export), decimated above `max_triangles`, with the same bearer-token authentication,
admission and tenant isolation as every other scene endpoint (another tenant's scene id is a 404).

The page itself is public (it holds no data); every request it makes carries the token the user typed,
kept in the tab's sessionStorage.
"""

from pathlib import Path
from typing import Annotated

from fastapi import APIRouter, FastAPI, Query, Request
from fastapi.responses import FileResponse, Response
from fastapi.staticfiles import StaticFiles

from . import schemas as S
from ..service.scene_export import DEFAULT_TRIANGLE_BUDGET, MAX_TRIANGLE_BUDGET, scene_glb
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
                          "X-Triangle-Budget, X-Decimated (true: a preview whose shadows are not the scene's)"},
                    **error_responses(*AUTHED, 404, 413, 422, 503)})
    async def scene_geometry(scene_id: S.ObjectId, tenant: Tenant, request: Request,
                             max_triangles: Annotated[int, Query(ge=1000, le=MAX_TRIANGLE_BUDGET, description=(
                                 "the triangle budget: a scene with more is decimated (quadric edge collapse, "
                                 "Garland and Heckbert 1997) to at most this many"))] = DEFAULT_TRIANGLE_BUDGET):
        try:  # the glTF writer and the decimation are the requirements' trimesh and pyfqmr
            import pyfqmr  # noqa: F401  # lazy: optional; a server without it answers 503, not an import error
            import trimesh  # noqa: F401  # lazy: optional; a server without it answers 503, not an import error
        except ImportError as e:
            raise ApiError(503, "geometry_export_unavailable", f"this server cannot write glTF: {e.name} is not "
                           "installed (requirements.lock)") from e
        async with svc.heavy(tenant, request) as ticket:
            entry = await scene_entry_for(svc, ticket, scene_id)
            with solver_errors():
                data, info = await svc.in_slot(svc.admission.solve, ticket, scene_glb, entry.loaded, max_triangles)
        return Response(data, media_type="model/gltf-binary", headers={
            "X-Scene-Triangles": str(info.triangles), "X-Served-Triangles": str(info.served_triangles),
            "X-Triangle-Budget": str(info.budget), "X-Decimated": "true" if info.decimated else "false",
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
