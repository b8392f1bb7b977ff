"""Ground-truth evaluation of a solution JSON against exact ray-traced shadows."""
from __future__ import annotations

import time

from ..renderers.ground_truth import evaluate as evaluate_maps
from .rigs import SolutionError, resolve_rig
from .scenes import SceneEntry
from .solve import maps_from_solution


def check_solution(solution: dict, entry: SceneEntry, n_lights: int) -> None:
    if not isinstance(solution, dict) or "lights" not in solution:
        raise SolutionError("solution", "not a shadowopt solution (no 'lights')")
    if len(solution["lights"]) != n_lights:
        raise SolutionError("solution.lights", f"has {len(solution['lights'])} lights but the rig has {n_lights}")
    prov = solution.get("provenance") or {}
    if prov.get("scene_hash") and prov["scene_hash"] != entry.loaded.scene_hash:
        raise SolutionError("solution.provenance.scene_hash", "the solution was computed for another scene")


def evaluate_solution(entry: SceneEntry, rig: dict, solution: dict, screen=None, heatmap_path=None,
                      grid_every=None) -> dict:
    t0 = time.perf_counter()
    resolved = resolve_rig(rig, entry.loaded)
    check_solution(solution, entry, len(resolved.lights))
    try:
        per_light_maps = maps_from_solution(solution)
    except (KeyError, TypeError, ValueError) as e:
        raise SolutionError("solution.lights", f"malformed cascade: {e}") from e
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
