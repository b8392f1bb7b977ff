"""Compute a shadow setup for a scene and rig, and express it as the solution schema.

scene (cached) -> rig -> coarse buffers -> per light: samples + receivers (service.receivers) -> maps (a
baseline, the optimizer or the path's held grids: the method's MethodKind) -> predicted error (solvers.metric,
the one metric) -> JSON in the requested matrix convention, layout and frame (service.solution_json).

_solve runs its steps in order, each a short function named after what it does (as Filament's
ShadowMap.cpp does for a shadow map): check the request, the coarse pass, the lights' problems, the rig's
texel split, then per light the maps at its cascade count, refined, snapped and scored, and the solution.
What differs between methods is gathered in one MethodKind per method (METHOD_KINDS).
"""
from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass
from typing import Callable

from ..solvers.baselines import baseline
from ..solvers.cascades import MAX_RES
from ..solvers.depth_modes import with_bias
from ..solvers.fitting import snap_to_texels
from ..solvers.optimize import DEFAULT_METHOD as DEFAULT_SOLVER
from ..solvers.optimized_maps import optimized_maps
from ..solvers.path_optimize import (FrameProblem, held_cascade_count, keyframes, optimize_path, path_maps,
                                     previous_state)
from ..solvers.shadow_map import ShadowMap
from ..solvers.split_search import optimize_splits
from ..solvers.stable_csm import stable_csm_maps
from . import point_faces
from .bias import choose_bias, set_blend_bands
from .coarse_cache import cached_coarse_pass
from .map_sizing import auto_cascades, rig_budget_split, smaller_resolution
from .methods import BASELINE_METHODS, METHODS  # kept importable from here
from .need import drop_empty_maps, light_need, receivers_per_map
from .pipeline import coarse_pass
from .receivers import LightProblem, light_problems
from .request import SolveRequest
from .request_cost import flush_if_large, solve_work
from .rigs import ResolvedRig
from .scenes import SceneEntry
from .solution_check import validate_solution
from .solution_json import jsonable, light_json, maps_error, no_map_json, solution_json



@dataclass
class LightJob:
    """One light of a solve that gets a map, as its method's steps see it (MethodKind)."""

    kind: "MethodKind"
    request: SolveRequest
    previous: dict | None  # the request's previous solution, validate_solution's normalized copy
    light_index: int
    prob: LightProblem
    camera: object
    bounds: tuple
    shadow: dict
    common: dict  # map_options: the fit's keywords every method takes
    allow_log: bool
    budget_left: Callable[[], float | None]  # search_clock: the search time left of the whole solve's budget
    rays: object = None  # the scene's RayScene (service.bias: the depth probe casts its texels' rays)
    buffers: object = None  # the coarse pass (service.bias: its light-facing receivers and their visibility)

    def maps_for(self, k: int):
        """(maps, solver report or None) with k cascades."""
        return self.kind.fit(self, {**self.common, "cascades": k})


class MethodKind:
    """What one method does with a light's maps, step by step (_light_solution runs the steps): the baselines'
    fits (solvers.baselines) by default; the other kinds override the steps that differ."""

    searches = False  # a solver search: the settings name its solver and the solution carries its report
    rivals: tuple = ()  # methods whose maps are returned instead where they predict fewer wrong pixels (_engine_check)

    def __init__(self, method: str):
        self.method = method

    def fit(self, job: LightJob, opts: dict):
        """(maps, solver report or None) for the fit's keywords `opts` (the cascade count included)."""
        self.split_search(job, opts)
        method, allow_log, prob = self.method, job.allow_log, job.prob
        return baseline(method, job.camera, prob.light, prob.receivers, job.bounds,
                        allow_log=allow_log or method == "logpsm", **opts), None

    def split_search(self, job: LightJob, opts: dict) -> None:
        """splits "optimized" with a fitted method: the split search's splits (solvers.split_search), in `opts`."""
        method, prob, (lo, hi) = self.method, job.prob, job.bounds
        if opts["splits"] == "optimized":  # a baseline method with optimized splits: the search's splits
            opts["splits"] = "practical"
            if opts["cascades"] > 1 and prob.light.kind == "directional":
                opts["split_at"] = optimize_splits(
                    job.camera, prob.light, prob.samples, prob.receivers, (lo, hi), opts["resolution"],
                    opts["cascades"], texel_budget=opts["texel_budget"], receiver_slack=prob.receiver_slack,
                    method=method if method in ("focused", "lispsm") else
                    "focused" if method == "stable_csm" else "lispsm").split_at  # stable_csm: unwarped maps

    def maps(self, job: LightJob):
        """(maps, solver report or None, auto_cascades report or None): at the rig's cascade count, or at the
        count `cascades: "auto"` chooses."""
        if job.shadow.get("cascades") == "auto":
            return self.auto_maps(job)
        (maps, info), auto = job.maps_for(job.common["cascades"]), None
        return maps, info, auto

    def auto_maps(self, job: LightJob):
        return auto_cascades(job.maps_for, job.prob, job.camera.position, job.shadow, job.camera, drop=True)

    def refine(self, job: LightJob, maps: list[ShadowMap], notes: list):
        """(maps, face_partitioning block or None): the cascades with no receivers dropped, a point light's cube
        partitioned by objective, the resolution lowered to what meets target_p95_m; `notes` get what changed."""
        prob, shadow, allow_log = job.prob, job.shadow, job.allow_log
        n_fitted = len(maps)
        maps, dropped = drop_empty_maps(maps, prob.receivers, prob.receiver_slack, job.camera)
        notes += dropped
        if dropped and job.common.get("texel_budget") and len(maps) < n_fitted:
            notes.append(respend_budget(maps, n_fitted, prob))
        # A point light: Lloyd et al. 2007 face partitioning against the cube, by objective (service.point_faces)
        maps, fp_block = point_faces.choose(self.method, job.camera, prob, job.bounds, maps, allow_log, maps_error,
                                            job.camera.position, shadow.get("point_light_maps", "auto"))
        if shadow.get("target_p95_m") is not None and not shadow.get("fixed_resolution"):
            maps, note = smaller_resolution(maps, prob, job.camera.position, float(shadow["target_p95_m"]))
            if note:
                notes.append(note)
        return maps, fp_block


class StableCsmKind(MethodKind):
    """stable_csm: the engines' bounding sphere per cascade, texel-snapped (solvers.stable_csm, Valient 2008)."""

    def fit(self, job: LightJob, opts: dict):
        self.split_search(job, opts)
        return stable_csm_maps(job.camera, job.prob.light, job.prob.receivers, job.bounds, **opts), None


class OptimizedKind(MethodKind):
    """optimized: the projective search (solvers.optimized_maps), with a previous solution's x kept by hysteresis."""

    searches = True
    rivals = ("lispsm", "focused")

    def fit(self, job: LightJob, opts: dict):
        prob, li = job.prob, job.light_index
        return optimized_maps(job.camera, prob.light, prob.samples, prob.receivers, job.bounds,
                              allow_log=job.allow_log, solver=job.request.solver or DEFAULT_SOLVER,
                              time_budget_ms=job.budget_left(), previous_x=_previous_x(job.previous, li),
                              hysteresis=job.request.hysteresis, sample_rows=prob.sample_rows, **opts)


class PathKind(MethodKind):
    """path: coherent with the previous frame (solvers.path_optimize): a held world-fixed texel grid per cascade."""

    searches = True

    def fit(self, job: LightJob, opts: dict):
        prob, li = job.prob, job.light_index
        return path_maps(job.camera, prob.light, prob.samples, prob.receivers, job.bounds,
                         previous_state=previous_state(job.previous, li), solver=job.request.solver or DEFAULT_SOLVER,
                         time_budget_ms=job.budget_left(), sample_rows=prob.sample_rows, **opts)

    def auto_maps(self, job: LightJob):
        """auto_cascades keeping every cascade, then the previous frame's cascade count, with hysteresis."""
        maps, info, auto = auto_cascades(job.maps_for, job.prob, job.camera.position, job.shadow, job.camera,
                                         drop=False)
        return held_cascade_count(job.maps_for, maps, info, auto, previous_state(job.previous, job.light_index),
                                  job.shadow)

    def refine(self, job: LightJob, maps: list[ShadowMap], notes: list):
        return maps, None  # each cascade holds its world-fixed grid from frame to frame, none is dropped


METHOD_KINDS = {**{m: MethodKind(m) for m in BASELINE_METHODS}, "optimized": OptimizedKind("optimized"),
                "stable_csm": StableCsmKind("stable_csm"), "path": PathKind("path")}


def solve(entry: SceneEntry, rig: dict, request: SolveRequest = SolveRequest()) -> dict:
    """The solution for `request.method` (a baseline name or "optimized"; "path": coherent with `previous`, the
    previous frame's solution, solvers.path_optimize) on a scene entry and validated rig dict.

    `request.time_budget_ms` bounds the optimizer's search (method optimized) over the whole solve: it is counted from
    the start of the solve (the coarse pass included) and shared by all lights and cascades, each search
    getting what is left (at least 1 ms); when it runs out, each remaining light's search returns its start
    maps. The coarse pass, the baselines' fits and the error statistics are not interruptible; their cost is
    bounded by the rig's work limit (service.request_cost). After a large request, Dr.Jit's cached
    allocations are returned to the system."""
    try:
        return _solve(entry, rig, request)
    finally:
        flush_if_large(solve_work(rig))


def _solve(entry: SceneEntry, rig: dict, request: SolveRequest) -> dict:
    kind = method_kind(request.method)
    previous = checked_previous(request.previous, rig)
    t0, c0 = time.perf_counter(), time.thread_time()
    resolved, buffers = _coarse_pass(entry, rig, request.cache_tenant)
    t1 = time.perf_counter()
    lo, hi = entry.loaded.geometry.bounds()
    probs = light_problems(resolved, buffers, (lo, hi))
    t_receivers = time.perf_counter()
    split = rig_budget_split(resolved, buffers, probs, (lo, hi)) if resolved.shadow.get("budget_scope") == "rig" else None
    per_light, reports = [], []
    for li, prob in enumerate(probs):
        need = light_need(buffers, li)
        if not need.needs_map:  # no visible receiver: no map, nothing beyond the coarse pass (service.need)
            per_light.append(no_map_json(prob, need, (buffers.width, buffers.height)))
            if kind.searches:
                reports.append(None)
            continue
        job = LightJob(kind, request, previous, li, prob, resolved.camera, (lo, hi), resolved.shadow,
                       map_options(resolved.shadow, prob, split, li),
                       bool(resolved.output.get("allow_log_warp", False)), search_clock(request.time_budget_ms, t0),
                       entry.rays, buffers)
        light, info = _light_solution(job, need, resolved.output, entry.loaded.stage_to_world)
        per_light.append(light)
        if info is not None:
            reports.append(info)
    t2 = time.perf_counter()
    # receivers: of optimize, the lights' samples and receivers (light_problems); total_cpu: this thread's CPU
    timings = {"coarse": (t1 - t0) * 1e3, "optimize": (t2 - t1) * 1e3, "receivers": (t_receivers - t1) * 1e3,
               "total": (t2 - t0) * 1e3, "total_cpu": (time.thread_time() - c0) * 1e3}
    return _solution(entry, resolved, request, kind, per_light, reports, split, timings)


def method_kind(method: str) -> MethodKind:
    if method not in METHODS:
        raise ValueError(f"method: unknown method {method!r} (known: {', '.join(METHODS)})")
    return METHOD_KINDS[method]


def checked_previous(previous: dict | None, rig: dict) -> dict | None:
    """validate_solution's normalized copy of a previous solution, or None."""
    if previous is not None:  # only its solver's x is read; a malformed field is a SolutionError naming it
        previous = validate_solution(previous, "previous", n_lights=len(rig["lights"]), maps=False,
                                     code="invalid_previous")
    return previous


def _coarse_pass(entry: SceneEntry, rig: dict, cache_tenant):
    if cache_tenant is not None:  # the camera part cached per tenant and scene (service.coarse_cache)
        return cached_coarse_pass(entry, rig, cache_tenant)
    return coarse_pass(entry, rig)


def search_clock(time_budget_ms: float | None, t0: float) -> Callable[[], float | None]:
    """budget_left(): the search time left of the whole solve's budget, counted from t0 (perf_counter)."""
    def budget_left():
        if time_budget_ms is None:
            return None
        return max(1.0, float(time_budget_ms) - (time.perf_counter() - t0) * 1e3)

    return budget_left


def map_options(shadow: dict, prob: LightProblem, split: dict | None = None, light_index: int = 0) -> dict:
    """The fit's keywords every method takes for one light: the rig's resolution, cascade count (1 for
    "auto"), splits and texel budget (under budget_scope rig, this light's share of the rig's texels)."""
    common = dict(resolution=tuple(shadow.get("resolution") or (2048, 2048)),
                  cascades=shadow.get("cascades") if isinstance(shadow.get("cascades"), int) else 1,
                  splits=shadow.get("splits", "practical"),
                  split_lambda=shadow.get("lambda", 0.5), texel_budget=shadow.get("texel_budget"),
                  receiver_slack=prob.receiver_slack)
    if split is not None:  # budget_scope rig: this light's share of the rig's texels
        common["texel_budget"] = max(1, split["lights"][light_index]["texels"])
    return common


@dataclass
class ScoredMaps:
    """A light's maps after MethodKind.maps, refine and snapping, with their bias chosen and the engine's count
    predicted (service.bias.choose_bias)."""

    maps: list
    info: dict | None
    auto: dict | None
    notes: list
    fp_block: dict | None
    prediction: dict


def _scored_maps(job: LightJob, output: dict) -> ScoredMaps:
    maps, info, auto = job.kind.maps(job)
    notes = list(auto.pop("notes", [])) if auto is not None else []
    maps, fp_block = job.kind.refine(job, maps, notes)
    if job.shadow.get("snap_to_texels"):
        snap_maps(maps, job.prob)
    prediction = choose_bias(job.rays, job.prob.light, maps, job.buffers, job.light_index, job.shadow,
                             output.get("engine"))
    return ScoredMaps(maps, info, auto, notes, fp_block, prediction)


def _engine_check(job: LightJob, output: dict, best: ScoredMaps) -> ScoredMaps:
    """The search minimizes the aliasing metric; what the user sees is the engine's depth test. A method with
    rivals (optimized: LiSPSM and focused, fitted as fairly, with the same bias chooser) returns the rival's maps
    where those predict fewer wrong pixels under that test, and says so in a note and in its report. Directional
    lights only (a spot's or a point light's baselines are the same perspective maps the search starts from)."""
    rivals = {}
    if job.prob.light.kind != "directional":  # a spot's or point light's rivals are the same kind of perspective map
        return best
    common = dict(job.common)
    if common.get("splits") == "optimized" and len(best.maps) > 1 and best.maps[0].face is None:
        # the rivals take the search's splits: the comparison is of the maps, and the report's splits stay true
        common.update(splits="practical", split_at=[float(m.split[1]) for m in best.maps[:-1]])
    for name in job.kind.rivals:
        rival = _scored_maps(dataclasses.replace(job, kind=METHOD_KINDS[name], common=common), output)
        rivals[name] = rival.prediction["misclassified_pixels"]
        if rival.prediction["misclassified_pixels"] < best.prediction["misclassified_pixels"]:
            note = (f"the {name} baseline's maps predict fewer wrong pixels under the engine's depth test "
                    f"({rival.prediction['misclassified_pixels']:.0f} against the search's "
                    f"{best.prediction['misclassified_pixels']:.0f}): returned")
            best = ScoredMaps(rival.maps, best.info, rival.auto, rival.notes + [note], rival.fp_block,
                              rival.prediction)
    if rivals and best.info is not None:
        best.info["engine_check"] = {"predicted_misclassified_pixels": rivals}
    return best


def _light_solution(job: LightJob, need, output: dict, stage_to_world) -> tuple[dict, dict | None]:
    """One light that gets a map: its maps (MethodKind.maps), refined (MethodKind.refine), snapped when asked,
    its bias chosen and scored, checked against the method's rivals; (its solution entry, its solver report or
    None)."""
    scored = _engine_check(job, output, _scored_maps(job, output))
    maps, info, auto, notes = scored.maps, scored.info, scored.auto, scored.notes
    if info is not None and auto is not None:
        info["auto_cascades"] = auto
    total, per_map = maps_error(maps, job.prob.samples, job.camera.position)
    notes += unsampled_notes(maps, per_map, job.prob, job.camera)
    for err in (total, *per_map):  # the aliasing estimate (solvers.metric.predicted_misclassified) keeps its own name
        err["aliasing_pixels"] = err.pop("misclassified_pixels", None)
    total.update(scored.prediction)  # misclassified_pixels: the engine's depth test's count (service.bias)
    out = light_json(job.prob.light, maps, total, per_map, output, stage_to_world, job.prob.samples)
    out["shadow"] = "map"
    out["need"] = need.to_json()
    if scored.fp_block is not None:
        out["face_partitioning"] = scored.fp_block
    if notes:
        out["notes"] = notes
    if auto is not None:
        out["auto_cascades"] = auto
    return out, info


def respend_budget(maps: list[ShadowMap], n_fitted: int, prob: LightProblem) -> str:
    """The texels of the cascades dropped under a texel budget given to the kept ones: each side scaled by
    sqrt(fitted / kept) (the shared size grows, its aspect kept; sides rounded down, at most MAX_RES), the depth
    bias refitted to the new texels; maps snapped to a world texel grid (stable_csm) keep their size. Returns the
    note saying so."""
    before = tuple(maps[0].resolution)
    if any(m.snapped for m in maps):  # stable_csm: the texel grid is fixed in the world at the fitted size
        return (f"the {n_fitted - len(maps)} dropped cascades' texels are not used: the kept maps' texel grids are "
                f"snapped in the world at their {before[0]}x{before[1]} texels")
    grow = math.sqrt(n_fitted / len(maps))
    for m in maps:
        m.resolution = tuple(min(MAX_RES, int(r * grow)) for r in m.resolution)
        with_bias(m, prob.receivers, prob.light)
    w, h = maps[0].resolution
    return (f"the {n_fitted - len(maps)} dropped cascades' texels go to the {len(maps)} kept: {w}x{h} each "
            f"(from {before[0]}x{before[1]}), within the texel budget")


def unsampled_notes(maps: list[ShadowMap], per_map: list[dict], prob: LightProblem, camera) -> list[str]:
    """A note per cascade that no sample reaches (its predicted error counts nothing there) and per cascade kept
    with no receiver (method path keeps every cascade's grid; a cascade count the target needs): what is served."""
    if len(maps) < 2 or maps[0].face is not None:
        return []
    counts = receivers_per_map(maps, prob.receivers, prob.receiver_slack, camera)
    out = []
    for k, (m, err) in enumerate(zip(maps, per_map)):
        if err.get("samples"):
            continue
        lo, hi = m.split
        what = (f"{int(counts[k])} of the light's {len(prob.receivers)} visible receiver points are at that depth"
                if counts[k] else "no visible receiver point is at that depth either: kept empty (method path "
                "holds every cascade's texel grid from frame to frame)")
        out.append(f"cascade {k} (view depth {lo:.4g}-{hi:.4g}) has no shadow-boundary sample of the coarse pass, so "
                   f"its predicted error counts nothing there; {what}; it has the light's shared size "
                   f"{m.resolution[0]}x{m.resolution[1]}")
    return out


def _solution(entry: SceneEntry, resolved: ResolvedRig, request: SolveRequest, kind: MethodKind, per_light: list,
              reports: list, split: dict | None, timings: dict) -> dict:
    """The solution JSON: the lights, the settings, the rig's texel split with what each light returned, the
    search's report (one light: its own; more: per light)."""
    method, solver = request.method, request.solver
    settings = {"method": method, "solver": solver or (DEFAULT_SOLVER if kind.searches else None),
                "time_budget_ms": request.time_budget_ms, "coarse_long_side": resolved.coarse_long_side,
                "shadow": jsonable(resolved.shadow)}
    sol = solution_json(entry, resolved, method, per_light, timings, settings)
    if split is not None:
        for li, light in enumerate(per_light):
            split["lights"][li]["returned_texels"] = sum(c["resolution"][0] * c["resolution"][1]
                                                         for c in light["cascades"])
        split["returned_texels"] = sum(l["returned_texels"] for l in split["lights"])
        sol["texel_budget_split"] = split
    if kind.searches and any(s is not None for s in reports):
        sol["solver"] = reports[0] if len(reports) == 1 else {"lights": reports}
    return sol


def snap_maps(maps: list[ShadowMap], prob: LightProblem) -> None:
    """`shadow.snap_to_texels`: unwarped directional maps get a world-fixed texel grid
    (solvers.fitting.snap_to_texels); warped and perspective maps are left as they are, each with the
    reason in `snap_note` (the solution's `texel_snap_note`), so a request for snapping is never
    ignored silently."""
    for smap in maps:
        note = _snap_refusal(smap, prob.light)
        P = None if note else snap_to_texels(smap.view, smap.projection, smap.resolution)
        if P is None:
            smap.snap_note = note or ("not snapped: the map is perspective-warped (its texels move with the "
                                      "camera's view of the receivers; only unwarped directional maps have a "
                                      "world-fixed texel grid)")
            continue
        smap.projection = P
        smap.snapped = True
        if len(prob.receivers):
            with_bias(smap, prob.receivers, prob.light)


def _snap_refusal(smap: ShadowMap, light) -> str | None:
    """Why a map cannot get a world-fixed texel grid, or None when snap_to_texels may try."""
    if light.kind != "directional":
        return "not snapped: a spot or point light's perspective map has no world-fixed texel grid"
    if smap.face is not None:
        return "not snapped: a cube-map face has no world-fixed texel grid"
    if smap.log_warp is not None:
        return "not snapped: the map is log-warped (its texels move with the camera)"
    return None


def _previous_x(previous: dict | None, light_index: int):
    """The projective parameters per cascade of a previous `optimized` solution for one light."""
    if not previous or previous.get("solver") is None:  # previous: validate_solution's normalized copy
        return None
    s = previous["solver"]
    s = s["lights"][light_index] if "lights" in s else (s if light_index == 0 else None)
    if not s:
        return None
    return [x if x else None for x in s.get("x", [])]


def _path_options(shadow: dict, prob: LightProblem, solver: str | None) -> dict:
    """optimized_maps' keywords for one light of a path frame (FrameProblem.opts)."""
    return dict(map_options(shadow, prob), sample_rows=prob.sample_rows, solver=solver or DEFAULT_SOLVER)


def frame_problems(entry: SceneEntry, rigs: list[dict], light_index: int = 0, solver: str | None = None):
    """solvers.path_optimize.FrameProblems of validated rigs (one light): each frame's coarse pass and light
    problem, as solve() makes them."""
    return [fp for fp, _, _ in _path_frames(entry, rigs, solver, light_index)]


def _path_frames(entry: SceneEntry, rigs: list[dict], solver: str | None, light_index: int | None = None):
    lo, hi = entry.loaded.geometry.bounds()
    out = []
    for rig in rigs:
        t0 = time.perf_counter()
        resolved, buffers = coarse_pass(entry, rig)
        probs = light_problems(resolved, buffers, (lo, hi))
        fps = [FrameProblem(resolved.camera, p.light, p.samples, p.receivers, (lo, hi),
                            _path_options(resolved.shadow, p, solver)) for p in probs]
        out.append((fps[light_index] if light_index is not None else fps, resolved,
                    (time.perf_counter() - t0) * 1e3))
    return out


def whole_path_eligible(resolved: ResolvedRig) -> bool:
    """A frame the whole-path pass can solve with the others (solvers.path_optimize.optimize_path): every
    light directional and a fixed cascade count (not "auto"); other paths run frame after frame (previous=)."""
    return bool(resolved.lights) and all(l.kind == "directional" for l in resolved.lights) \
        and isinstance(resolved.shadow.get("cascades", 1), int)


def solve_path(entry: SceneEntry, rigs: list[dict], solver: str | None = None,
               keyframes_every: int | None = None) -> list[dict]:
    """Method "path" over a path known ahead (a path job, a batch precomputation): the solutions of the frames
    of `rigs` (validated rig dicts, in order), each in the optimize schema. Every directional light's maps come
    from solvers.path_optimize.optimize_path over all frames (segments holding one world-fixed grid, scale
    level, depth and bias: no texel changes inside a segment); the frame's solver report says which pass was
    returned and its segment per cascade. timings_ms: the frame's own coarse pass; optimize is the whole-path
    pass's time divided by the frame count. Paths that are not whole_path_eligible (a spot or point light,
    cascades "auto") are solved frame after frame with previous= (the interactive form).
    `keyframes_every` K: for engines that interpolate, every frame's report also says whether it is a keyframe
    (frames 0, K, 2K, ... and the last), the interpolation rule, and what interpolating the keyframes' matrices
    adds on these frames (solvers.path_optimize.keyframes: the objective of the interpolated maps at each skipped
    frame, the worst ratio to the chosen maps' and the receivers left outside)."""
    if not rigs:
        return []
    frames = _path_frames(entry, rigs, solver)
    if not all(whole_path_eligible(f[1]) for f in frames) or len({len(f[0]) for f in frames}) != 1:
        out, prev = [], None
        for rig in rigs:
            prev = solve(entry, rig, SolveRequest("path", solver=solver, previous=prev))
            out.append(prev)
        return out
    n, n_lights = len(frames), len(frames[0][0])
    t0 = time.perf_counter()
    results = [optimize_path([f[0][li] for f in frames]) for li in range(n_lights)]
    kfs = [keyframes(res, [f[0][li] for f in frames], keyframes_every) if keyframes_every else None
           for li, res in enumerate(results)]
    per_frame_ms = (time.perf_counter() - t0) * 1e3 / n
    out = []
    for i, (fps, resolved, coarse_ms) in enumerate(frames):
        per_light, infos = [], []
        for li, (fp, res) in enumerate(zip(fps, results)):
            maps = res.maps[i]
            set_blend_bands(maps)  # the path's held depth blocks stay (one bias per segment: no flicker)
            total, per_map = maps_error(maps, fp.samples, fp.camera.position)
            per_light.append(light_json(fp.light, maps, total, per_map, resolved.output,
                                        entry.loaded.stage_to_world, fp.samples))
            returned = res.passes["returned"]
            segs = [next([a, b] for a, b in c["segments"] if a <= i <= b)
                    for c in res.passes.get("segments", {}).get("cascades", [])] if returned == "segments" else None
            infos.append({"fun": float(res.objective[i]), "per_frame_objective": float(res.per_frame_objective[i]),
                          "path": {"mode": "whole path", "pass": returned, "segments": segs,
                                   "grid_changes": res.grid_changes, "level_changes": res.level_changes,
                                   "frames": n}})
            if kfs[li] is not None:
                kf = kfs[li]
                skipped = {d["frame"]: d for d in kf["skipped"]}
                infos[-1]["path"]["keyframes"] = {
                    "every": kf["every"], "is_keyframe": i in kf["frames"], "rule": kf["rule"],
                    "max_objective_ratio": kf["max_objective_ratio"], "max_objective_added": kf["max_objective_added"],
                    "max_outside_receivers": kf["max_outside_receivers"],
                    "interpolated_objective": skipped[i]["objective"] if i in skipped else None,
                    "interpolated_outside_receivers": skipped[i]["outside_receivers"] if i in skipped else None}
        timings = {"coarse": coarse_ms, "optimize": per_frame_ms, "total": coarse_ms + per_frame_ms}
        settings = {"method": "path", "solver": solver or DEFAULT_SOLVER, "time_budget_ms": None,
                    "coarse_long_side": resolved.coarse_long_side, "shadow": jsonable(resolved.shadow),
                    "whole_path": True}
        sol = solution_json(entry, resolved, "path", per_light, timings, settings)
        sol["solver"] = infos[0] if len(infos) == 1 else {"lights": infos}
        out.append(sol)
    return out
