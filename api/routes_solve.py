"""The REST service's solve routes: optimize, evaluate, compare, analyze."""

import base64
import math
import tempfile
import time
from pathlib import Path

from fastapi import FastAPI, Request

from . import schemas as S
from ..service.compare import compare as compare_methods
from ..service.evaluation import evaluate_solution
from ..service.method_options import check_options
from ..service.request import SolveRequest
from ..service.request_cost import WorkLimit, check_eval_work, eval_screen_pixels, map_texels
from ..service.solve import solve
from ..solvers.analysis import analyze as lloyd
from .errors import AUTHED, ApiError, error_responses, solver_errors
from .responses import json_response
from .scene_loading import scene_entry_for
from .service_state import Service


def rig_dict(rig: S.Rig) -> dict:
    return rig.model_dump(by_alias=True)


def check_eval_size(svc: Service, rig: dict, screen, solution: dict | None) -> None:
    """413 when the ground truth would cast more rays than the server's limits allow."""
    w, h = screen or rig["camera"]["resolution"]
    limit = svc.settings.max_eval_pixels
    if w * h > limit:
        field = "screen" if screen else "rig.camera.resolution"
        raise ApiError(413, "too_many_pixels", f"{field}: {w}x{h} pixels is over the limit of {limit}", field)
    limit = svc.settings.max_eval_texels
    shadow = rig.get("shadow") or {}
    cascades = shadow.get("cascades") if isinstance(shadow.get("cascades"), int) else shadow.get("max_cascades", 4)
    budget = shadow.get("texel_budget")
    if budget is not None and budget > limit * max(int(cascades or 1), 1):  # compare sizes maps from the budget
        raise ApiError(413, "too_many_texels", f"rig.shadow.texel_budget: {budget} texels is over the limit of "
                       f"{limit} per map", "rig.shadow.texel_budget")
    lights = (solution or {}).get("lights")  # other shapes: service.solution_check names the field later
    for li, light in enumerate(lights if isinstance(lights, list) else []):
        cascades = light.get("cascades") if isinstance(light, dict) else None
        for ci, c in enumerate(cascades if isinstance(cascades, list) else []):
            res = c.get("resolution") if isinstance(c, dict) else None
            field = f"solution.lights.{li}.cascades.{ci}.resolution"
            if not (isinstance(res, (list, tuple)) and len(res) == 2
                    and all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in res)):
                raise ApiError(422, "invalid_solution", f"{field}: expected two positive integers, got {res!r}", field)
            if res[0] * res[1] > limit:
                raise ApiError(413, "too_many_texels", f"{field}: {res[0]}x{res[1]} texels is over the "
                               f"limit of {limit}", field)


def check_eval_cost(rig: dict, screen, texels: list[int], what: str) -> None:
    """422 too_costly before the request is admitted (no slot taken, no scene loaded): its ground-truth
    evaluations (screen pixels and the texels of the maps each one looks up, service.request_cost.eval_work)
    over MAX_EVAL_WORK. `texels`: one entry per evaluation. service.evaluation and service.compare check the
    same again with the lights' real types."""
    field = "screen" if screen else "rig.camera.resolution"
    px = eval_screen_pixels(rig["camera"]["resolution"], screen)
    try:
        check_eval_work([(px, t) for t in texels], field, what)
    except WorkLimit as e:
        raise ApiError(422, "too_costly", e.message, e.field) from None


def solution_texels(rig: dict, solution: dict) -> list[int]:
    """The texels of each light's maps as `solution` gives them (check_eval_size checked their resolutions)."""
    lights = solution.get("lights") if isinstance(solution, dict) else None
    out = []
    for light in (lights if isinstance(lights, list) else [])[:len(rig["lights"])]:
        cascades = light.get("cascades") if isinstance(light, dict) else None
        out.append(sum(c["resolution"][0] * c["resolution"][1] for c in cascades or []
                       if isinstance(c, dict) and isinstance(c.get("resolution"), (list, tuple))))
    return out


def add_solve_routes(app: FastAPI, svc: Service, Tenant) -> None:
    @app.post("/v1/optimize", summary="Shadow setup for a scene and rig: matrices, warp, cascades, predicted error",
              response_model=S.Solution, responses=error_responses(*AUTHED, 404, 413, 422, 503), tags=["solve"])
    async def optimize(req: S.OptimizeRequest, tenant: Tenant, request: Request):
        rig = rig_dict(req.rig)
        with solver_errors():  # an option the method would ignore: 422 naming the field
            check_options(req.method, rig.get("shadow"), solver=req.solver, time_budget_ms=req.time_budget_ms,
                          previous=req.previous,
                          hysteresis=req.hysteresis if "hysteresis" in req.model_fields_set else None)
        budget = svc.time_budget(req.time_budget_ms)
        async with svc.heavy(tenant, request) as ticket:
            entry = await scene_entry_for(svc, ticket, req.scene_id)
            t0 = time.perf_counter()
            with solver_errors():
                sol = await svc.in_slot(svc.admission.solve, ticket, solve, entry, rig, SolveRequest(
                    method=req.method, solver=req.solver, time_budget_ms=budget, previous=req.previous,
                    hysteresis=req.hysteresis, cache_tenant=tenant))  # service.coarse_cache
            svc.metrics.optimize.observe(time.perf_counter() - t0, req.method)
        return json_response(sol)

    @app.post("/v1/evaluate", summary="Measure a solution against exact ray-traced shadows (optional heatmap PNG)",
              response_model=S.Evaluation, responses=error_responses(*AUTHED, 404, 413, 422, 503), tags=["solve"])
    async def evaluate(req: S.EvaluateRequest, tenant: Tenant, request: Request):
        rig = rig_dict(req.rig)
        check_eval_size(svc, rig, req.screen, req.solution)
        check_eval_cost(rig, req.screen, solution_texels(rig, req.solution), "evaluate")

        def run(entry):
            with tempfile.TemporaryDirectory(prefix="shadowopt-heatmap-") as tmp:
                path = str(Path(tmp) / "heatmap.png") if req.heatmap else None
                res = evaluate_solution(entry, rig, req.solution, screen=req.screen, heatmap_path=path,
                                        grid_every=req.grid_every, heatmap_mode=req.heatmap_mode, depth=req.depth)
                if path:
                    res["heatmap_png_base64"] = [base64.b64encode(p.read_bytes()).decode()
                                                 for p in sorted(Path(tmp).glob("heatmap*.png"))]
            return res

        async with svc.heavy(tenant, request) as ticket:
            entry = await scene_entry_for(svc, ticket, req.scene_id)
            with solver_errors():
                res = await svc.in_slot(svc.admission.solve, ticket, run, entry)
        return json_response(res)

    @app.post("/v1/compare", summary="Methods side by side: predicted and measured error, setup time",
              response_model=S.Comparison, responses=error_responses(*AUTHED, 404, 413, 422, 503), tags=["solve"])
    async def compare(req: S.CompareRequest, tenant: Tenant, request: Request):
        rig = rig_dict(req.rig)
        resolution = (rig.get("shadow") or {}).get("resolution")  # None with a texel_budget: sized from it
        check_eval_size(svc, rig, req.screen, {"lights": [{"cascades": [{"resolution": resolution}]}]}
                        if resolution is not None else None)
        methods = list(dict.fromkeys(req.methods))
        # one ground truth per method of the first light's maps, counted as one face (its type is known once the
        # scene is loaded: service.compare checks again)
        check_eval_cost(rig, req.screen, [map_texels(rig.get("shadow") or {})] * len(methods),
                        f"compare of {len(methods)} methods")
        with solver_errors():
            for m in methods:
                check_options(m, rig.get("shadow"))
        async with svc.heavy(tenant, request) as ticket:
            entry = await scene_entry_for(svc, ticket, req.scene_id)
            with solver_errors():
                res = await svc.in_slot(svc.admission.solve, ticket, compare_methods, entry, rig, methods,
                                        screen=req.screen, request=SolveRequest(time_budget_ms=svc.time_budget(None)),
                                        depth=req.depth)
        return json_response(res)

    @app.post("/v1/analyze", summary="Lloyd's scene-independent critical resolution and storage factors",
              response_model=S.Analysis, responses=error_responses(*AUTHED, 413, 422), tags=["solve"])
    def analyze(req: S.AnalyzeRequest, tenant: Tenant):
        with solver_errors():
            res = lloyd(req.f_over_n, req.theta_deg, req.gamma_deg, req.method, partitions=req.partitions,
                        azimuth_deg=req.azimuth_deg)
        res = {k: float(v) for k, v in res.items()}
        if not all(math.isfinite(v) for v in res.values()):
            raise ApiError(422, "not_finite", f"f_over_n: the factors overflow for f/n = {req.f_over_n:g}",
                           "f_over_n")
        return res
