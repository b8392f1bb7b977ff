"""Ground-truth evaluation of a solution JSON against exact ray-traced shadows."""
from __future__ import annotations

import time

from ..renderers.ground_truth import evaluate as evaluate_maps
from .request_cost import WorkLimit, check_eval_work, flush_if_large
from .rigs import SolutionError, resolve_rig
from .scenes import SceneEntry
from .solution_check import validate_solution
from .solve import maps_from_solution


def evaluate_solution(entry: SceneEntry, rig: dict, solution: dict, screen=None, heatmap_path=None,
                      grid_every=None) -> dict:
    t0 = time.perf_counter()
    resolved = resolve_rig(rig, entry.loaded)
    # Every field read below is checked first: a malformed one is a SolutionError naming it (422, exit 2).
    solution = validate_solution(solution, "solution", light_kinds=[l.kind for l in resolved.lights],
                                 scene_hash=entry.loaded.scene_hash)
    per_light_maps = maps_from_solution(solution)
    w, h = screen or resolved.camera.resolution
    screen_field = "screen" if screen else "rig.camera.resolution"
    try:  # one ground truth per light: its screen pixels and the texels of its maps
        work = check_eval_work([(int(w) * int(h), sum(m.resolution[0] * m.resolution[1] for m in maps))
                                for maps in per_light_maps[:len(resolved.lights)]], screen_field, "evaluate")
    except WorkLimit as e:
        raise SolutionError(e.field, e.message, code="too_costly") from None
    try:
        return _evaluate(entry, resolved, solution, per_light_maps, screen, heatmap_path, grid_every, t0)
    finally:
        flush_if_large(work)


def _evaluate(entry, resolved, solution, per_light_maps, screen, heatmap_path, grid_every, t0) -> dict:
    results = []
    for k, (light, maps) in enumerate(zip(resolved.lights, per_light_maps)):
        path = heatmap_path
        if heatmap_path and len(resolved.lights) > 1:
            stem, dot, ext = heatmap_path.rpartition(".")
            path = f"{stem}.light{k}.{ext}" if dot else f"{heatmap_path}.light{k}"
        results.append(evaluate_maps(entry.rays, resolved.camera, light, maps, screen=screen,
                                     heatmap_path=path, grid_every=grid_every))
    out = dict(results[0]) if len(results) == 1 else {"lights": results}
    out["method"] = solution.get("method")
    out.setdefault("timings_ms", {})["total"] = round((time.perf_counter() - t0) * 1e3, 3)
    return out
