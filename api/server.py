"""The REST service (FastAPI on uvicorn). At this stage: health and scene information."""
from __future__ import annotations

import logging
import sys
import threading

from fastapi import FastAPI, HTTPException
from fastapi.responses import JSONResponse

log = logging.getLogger("shadowopt.server")


def create_app(scenes: list[str]) -> FastAPI:
    from ..service.scenes import SCENES

    app = FastAPI(title="shadowopt", version=_version(),
                  description="Scene-optimized shadow-map parameters: light matrices, warp and cascades.")
    state = {"ready": False, "scenes": {}, "errors": {}}

    def warm():
        # Load each preloaded scene once and run one coarse pass so the kernels are compiled.
        from ..renderers.coarse import render_coarse
        from ..service.rigs import resolve_rig

        for path in scenes:
            try:
                entry = SCENES.get(path)
                info = entry.loaded.info()
                sid = info["scene_hash"][:16]
                state["scenes"][sid] = (path, info)
                if entry.loaded.cameras and entry.loaded.lights:
                    rig = {"camera": {"usd_path": entry.loaded.cameras[0].usd_path, "resolution": (1280, 720)},
                           "lights": [{"usd_path": l.usd_path} for l in entry.loaded.lights if l.type != "ignored"][:1]}
                    if rig["lights"]:
                        r = resolve_rig(rig, entry.loaded)
                        render_coarse(entry.rays, r.camera, r.lights)
            except Exception as e:  # a bad preload must not take the service down
                state["errors"][path] = f"{type(e).__name__}: {e}"
                log.error("could not preload %s: %s", path, e)
        state["ready"] = True

    threading.Thread(target=warm, daemon=True, name="warm-up").start()

    @app.get("/healthz", summary="Readiness: 200 once preloaded scenes and kernels are warm, else 503")
    def healthz():
        body = {"status": "ok" if state["ready"] else "warming", "scenes": len(state["scenes"]),
                "preload_errors": state["errors"]}
        return JSONResponse(body, status_code=200 if state["ready"] else 503)

    @app.get("/v1/scenes", summary="Scenes this server has loaded")
    def list_scenes():
        return {"scenes": [{"scene_id": sid, "source": path, "triangles": info["triangles"]}
                           for sid, (path, info) in state["scenes"].items()]}

    @app.get("/v1/scenes/{scene_id}", summary="What the loader found in one scene",
             responses={404: {"description": "no such scene"}})
    def get_scene(scene_id: str):
        if scene_id not in state["scenes"]:
            raise HTTPException(404, detail={"code": "scene_not_found", "message": f"no scene {scene_id!r}"})
        path, info = state["scenes"][scene_id]
        return {"scene_id": scene_id, **info}

    return app


def _version() -> str:
    try:
        from importlib.metadata import version

        return version("shadowopt")
    except Exception:
        return "0+unknown"


def serve(host: str = "127.0.0.1", port: int = 8000, scenes: list[str] | None = None) -> int:
    import uvicorn

    logging.basicConfig(level=logging.INFO, stream=sys.stderr, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    app = create_app(scenes or [])
    print(f"shadowopt: serving on http://{host}:{port} (health: /healthz, docs: /docs)", file=sys.stderr)
    uvicorn.run(app, host=host, port=port, log_level="info")
    return 0
