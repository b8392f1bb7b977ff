"""Ground-truth evaluation of a solution JSON against exact ray-traced shadows.

Pixels: a solution's `predicted_error` is always in the rig's own full-resolution pixels (the solve
never sees the evaluation's screen). The ground truth is measured at `screen` (default: the rig's
resolution), so its pixel counts and its `measured_error` are in that screen's pixels; each evaluation
says so (`screen`, `rig_resolution`) and, when the two differ, adds `measured_error_rig_pixels`: the
same measurement with every footprint converted to the rig's pixels (m times s, h times s²,
s = sqrt(W H / (w h)), the rig's pixels per screen pixel along a side; screens keep the camera's aspect).

Depth (renderers.depth_tests.DEPTH_CHOICES): "solution" (default) emulates what an engine does with each
map's `depth` block in the mode the solution chose; "hardware" / "linear" force that block; "ideal" is the
idealized per-texel rule of `depth_bias`. Each evaluation says which (`depth`, `depth_rule`).

A light whose solution entry has no map (`shadow` "none": no visible receiver faces it inside its cone) casts no
shadow, as in an engine that renders no map for it: its true shadows on visible receivers are misclassified
pixels (0 by construction when the solve found none); the evaluation says so (`shadow`, `no_map_rule`).
"""
from __future__ import annotations

import math
import time

from ..renderers.depth_tests import DEPTH_CHOICES
from ..renderers.ground_truth import evaluate_buffers
from ..renderers.heatmap import HEATMAP_MODES, heatmap_with_legend, misclassified_split
from ..solvers.engine_depth_test import CONSTANT_SIDES, DEPTH_FORMATS
from ..solvers.metric import error_stats
from .request_cost import WorkLimit, check_eval_work, flush_if_large
from .rigs import SolutionError, resolve_rig
from .scenes import SceneEntry
from .solution_check import validate_solution
from .solution_json import maps_from_solution


NO_MAP_RULE = ("the light has no shadow map (shadow none): it casts no shadow, so every visible receiver it truly "
               "shadows counts as misclassified (none when the solve found no visible receiver for it)")


def pixel_units(gt, rig_resolution) -> dict:
    """Fields every evaluation carries besides `gt.result`: the misclassified split, the screen and the
    rig's resolution, and (screen != rig) the measured error in the rig's pixels (module doc)."""
    out = dict(misclassified_split(gt))
    w, h = gt.result["screen"]
    W, H = (int(v) for v in rig_resolution)
    out["rig_resolution"] = [W, H]
    out["pixels"] = (f"pixel counts and measured_error in the {w}x{h} screen's pixels; predicted_error in the "
                     f"rig's {W}x{H} pixels")
    if (w, h) != (W, H):
        s = math.sqrt(W * H / (w * h))
        mask = gt.sample_mask
        stats = error_stats(gt.h[mask] * s * s, gt.m[mask] * s)
        stats["sample_kind"] = gt.sample_kind
        out["measured_error_rig_pixels"] = stats
        out["pixels"] += f"; measured_error_rig_pixels: the same measurement in the rig's pixels (m x {s:.4g})"
    return out


def check_heatmap_mode(mode) -> str:
    if mode not in HEATMAP_MODES:
        raise SolutionError("heatmap_mode", f"must be one of {', '.join(HEATMAP_MODES)}, got {mode!r}",
                            code="invalid_input")
    return mode


def check_depth(depth) -> str:
    if depth not in DEPTH_CHOICES:
        raise SolutionError("depth", f"must be one of {', '.join(DEPTH_CHOICES)}, got {depth!r}", code="invalid_input")
    return depth


def check_depth_blocks(solution: dict, depth: str) -> None:
    """Engine depth modes read each map's `depth` block and `blend_band`: a missing or malformed one is a
    SolutionError naming it (service.solution_check's field paths)."""
    if depth == "ideal":
        return
    for i, light in enumerate(solution.get("lights") or []):
        for j, c in enumerate(light.get("cascades") or []):
            at = f"solution.lights.{i}.cascades.{j}"
            band = c.get("blend_band")
            if band is not None and not (isinstance(band, (list, tuple)) and len(band) == 2
                                         and all(_finite(v) for v in band) and band[0] <= band[1]):
                raise SolutionError(f"{at}.blend_band", f"expected null or [start, end] with start <= end, got "
                                    f"{band!r:.40}")
            b = c.get("depth")
            if b is None:
                raise SolutionError(at, f"has no engine depth block `depth` (solve it again, or evaluate with depth "
                                    f"'ideal'); depth {depth!r} reads it")
            if not isinstance(b, dict):
                raise SolutionError(f"{at}.depth", f"expected an object {{mode, hardware, linear}}, got {b!r:.40}")
            mode = b.get("mode") if depth == "solution" else depth
            if mode not in ("hardware", "linear"):
                raise SolutionError(f"{at}.depth" + (".mode" if "mode" in b and depth == "solution" else ""),
                                    f"mode: expected hardware or linear, got {mode!r:.40}")
            if not isinstance(b.get(mode), dict):
                raise SolutionError(f"{at}.depth" + (f".{mode}" if mode in b else ""),
                                    f"needs the block {mode} {{constant, slope, normal_offset"
                                    + (", near, far}" if mode == "linear" else "}"))
            for key in ("constant", "slope", "normal_offset") + (("near", "far") if mode == "linear" else ()):
                v = b[mode].get(key, 0.0 if key == "normal_offset" else None)
                if not _finite(v):
                    raise SolutionError(f"{at}.depth.{mode}" + (f".{key}" if key in b[mode] else ""),
                                        f"{key}: expected a finite number, got {v!r:.40}")
            for key in ("slope_scaled", "slope_clamp"):  # the light pass's slope-scaled bias: optional
                v = b[mode].get(key, 0.0)
                if v is None and key == "slope_clamp":  # null: no clamp (renderers.depth_tests.engine_depth)
                    continue
                if not (_finite(v) and v >= 0):
                    raise SolutionError(f"{at}.depth.{mode}.{key}", f"{key}: expected a finite number >= 0, got "
                                        f"{v!r:.40}")
            side = b[mode].get("constant_side", "receiver")
            if side not in CONSTANT_SIDES:
                raise SolutionError(f"{at}.depth.{mode}.constant_side", f"constant_side: expected one of "
                                    f"{', '.join(CONSTANT_SIDES)}, got {side!r:.40}")
            fmt = b.get("format", "float32")
            if fmt not in DEPTH_FORMATS:
                raise SolutionError(f"{at}.depth.format", f"format: expected one of {', '.join(DEPTH_FORMATS)}, got "
                                    f"{fmt!r:.40}")
            if mode == "linear" and not b[mode]["far"] > b[mode]["near"]:
                raise SolutionError(f"{at}.depth.linear", "expected far > near")


def _finite(v) -> bool:
    return not isinstance(v, bool) and isinstance(v, (int, float)) and math.isfinite(v)


def evaluate_solution(entry: SceneEntry, rig: dict, solution: dict, screen=None, heatmap_path=None,
                      grid_every=None, heatmap_mode: str = "m", depth: str = "solution") -> dict:
    t0 = time.perf_counter()
    check_heatmap_mode(heatmap_mode)
    check_depth(depth)
    resolved = resolve_rig(rig, entry.loaded)
    # Every field read below is checked first: a malformed one is a SolutionError naming it (422, exit 2).
    solution = validate_solution(solution, "solution", light_kinds=[l.kind for l in resolved.lights],
                                 scene_hash=entry.loaded.scene_hash)
    check_depth_blocks(solution, depth)
    per_light_maps = maps_from_solution(solution)
    w, h = screen or resolved.camera.resolution
    screen_field = "screen" if screen else "rig.camera.resolution"
    try:  # one ground truth per light: its screen pixels and the texels of its maps
        work = check_eval_work([(int(w) * int(h), sum(m.resolution[0] * m.resolution[1] for m in maps))
                                for maps in per_light_maps[:len(resolved.lights)]], screen_field, "evaluate")
    except WorkLimit as e:
        raise SolutionError(e.field, e.message, code="too_costly") from None
    try:
        return _evaluate(entry, resolved, solution, per_light_maps, screen, heatmap_path, grid_every,
                         heatmap_mode, t0, depth)
    finally:
        flush_if_large(work)


def _evaluate(entry, resolved, solution, per_light_maps, screen, heatmap_path, grid_every, heatmap_mode, t0,
              depth: str = "solution") -> dict:
    results = []
    for k, (light, maps) in enumerate(zip(resolved.lights, per_light_maps)):
        path = heatmap_path
        if heatmap_path and len(resolved.lights) > 1:
            stem, dot, ext = heatmap_path.rpartition(".")
            path = f"{stem}.light{k}.{ext}" if dot else f"{heatmap_path}.light{k}"
        gt = evaluate_buffers(entry.rays, resolved.camera, light, maps, screen=screen, depth=depth)
        res = gt.result
        if not maps:  # shadow "none" (service.need): what an engine does without a map
            res["shadow"] = "none"
            res["no_map_rule"] = NO_MAP_RULE
        res.update(pixel_units(gt, resolved.camera.resolution))
        if path is not None:
            t1 = time.perf_counter()
            heatmap_with_legend(gt, heatmap_mode, grid_every).save(path)
            res["heatmap_mode"] = heatmap_mode
            res["timings_ms"]["heatmap"] = (time.perf_counter() - t1) * 1e3
            res["timings_ms"]["total"] += res["timings_ms"]["heatmap"]
        results.append(res)
    out = dict(results[0]) if len(results) == 1 else {"lights": results}
    out["method"] = solution.get("method")
    out["depth"] = depth
    out.setdefault("timings_ms", {})["total"] = round((time.perf_counter() - t0) * 1e3, 3)
    return out
