"""Compare methods on one scene and rig: predicted error, measured error and time, side by side.

Every method is solved at the rig's own resolution (its `predicted_error` is the one `optimize` gives for
the same rig, in the rig's full-resolution pixels); `screen` only sets where the ground truth is measured,
and each evaluation names its screen and the rig's resolution (service.evaluation.pixel_units)."""
from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path

from ..renderers.ground_truth import evaluate_buffers, screen_camera
from ..renderers.heatmap import errors_image, errors_legend, ground_truth_heatmap, side_by_side
from .evaluation import check_depth, pixel_units
from .request_cost import WorkLimit, check_eval_work, check_solve_work, flush_if_large, light_faces, map_texels
from .rigs import RigError, SolutionError, resolve_rig
from .request import SolveRequest
from .scenes import SceneEntry
from .solution_json import maps_from_solution
from .solve import solve


def compare(entry: SceneEntry, rig: dict, methods: list[str], screen=None, report_dir=None, grid_every=None,
            request: SolveRequest | None = None, depth: str = "solution") -> dict:
    """{"methods": {NAME: {"solution", "predicted_error", "evaluation", "setup_ms"}}, "screen", "rig_resolution",
    "depth"} (first light). `report_dir`: heatmaps.png (m), errors.png (what went wrong) and compare.md.
    `request`: the solves' settings besides the method (service.request.SolveRequest; its method is replaced).
    depth: the evaluations' depth test (service.evaluation, default the solution's engine depth modes)."""
    check_depth(depth)
    resolved = resolve_rig(rig, entry.loaded)
    try:  # the API's CompareRequest checks this too (before the scene is loaded)
        check_solve_work(rig, solves=len(methods) + 1, kinds=[l.kind for l in resolved.lights], prefix="")
    except WorkLimit as e:
        raise RigError(e.field, e.message, code="too_costly") from None
    w, h = screen_camera(resolved.camera, screen).resolution  # the ground truth's pixels
    screen_field = "screen" if screen else "rig.camera.resolution"
    try:  # one ground truth per method, of the first light's maps
        texels = map_texels(rig.get("shadow") or {}) * light_faces(None, resolved.lights[0].kind)
        work = check_eval_work([(w * h, texels)] * len(methods), screen_field, f"compare of {len(methods)} methods")
    except WorkLimit as e:
        raise SolutionError(e.field, e.message, code="too_costly") from None
    try:
        return _compare(entry, rig, resolved, methods, screen, report_dir, grid_every, request or SolveRequest(), depth)
    finally:
        flush_if_large(work)


def _compare(entry, rig, resolved, methods, screen, report_dir, grid_every, request, depth="solution") -> dict:
    out, images, errors, titles = {}, [], [], []
    solve(entry, rig, replace(request, method=methods[0]))  # warm-up: kernels compile once, not in a method's time
    for name in methods:
        t0 = time.perf_counter()
        sol = solve(entry, rig, replace(request, method=name))  # the rig's resolution, as optimize
        setup_ms = (time.perf_counter() - t0) * 1e3
        maps = maps_from_solution(sol)[0]
        gt = evaluate_buffers(entry.rays, resolved.camera, resolved.lights[0], maps, screen=screen, depth=depth)
        evaluation = {**gt.result, **pixel_units(gt, resolved.camera.resolution)}
        out[name] = {"solution": sol, "predicted_error": sol["lights"][0]["predicted_error"],
                     "evaluation": evaluation, "setup_ms": round(setup_ms, 3)}
        if report_dir:
            images.append(ground_truth_heatmap(gt, grid_every))
            errors.append(errors_image(gt, grid_every))
            titles.append(f"{name}: {evaluation['misclassified_pixels']} misclassified = "
                          f"{evaluation['wrongly_shadowed_pixels']} wrongly shadowed + "
                          f"{evaluation['wrongly_lit_pixels']} wrongly lit")
    sw, sh = gt.result["screen"]
    result = {"methods": out, "screen": [sw, sh], "rig_resolution": [int(v) for v in resolved.camera.resolution],
              "depth": depth, "bias": (rig.get("shadow") or {}).get("bias", "fitted")}
    if report_dir:
        d = Path(report_dir)
        d.mkdir(parents=True, exist_ok=True)
        side_by_side(images, list(methods), str(d / "heatmaps.png"))
        side_by_side(errors, titles, str(d / "errors.png"), legend=errors_legend(360))
        (d / "compare.md").write_text(markdown_table(result) + "\n![measured m per method](heatmaps.png)\n\n"
                                      "![misclassified pixels per method](errors.png)\n")
        result["report"] = {"heatmaps": str(d / "heatmaps.png"), "errors": str(d / "errors.png"),
                            "table": str(d / "compare.md")}
    return result


def markdown_table(result: dict) -> str:
    """The comparison table; measured columns name the screen they were measured at, predicted ones the rig's
    resolution (the same pixels when no --screen was given)."""
    sw, sh = result.get("screen") or ["?", "?"]
    rw, rh = result.get("rig_resolution") or ["?", "?"]
    at, rig = f"{sw}x{sh}", f"{rw}x{rh}"
    converted = "" if at == rig else ", measured m also converted to the rig's pixels"
    depth = result.get("depth")
    depth_note = f" Depth test: {depth}." if depth else ""
    if result.get("bias"):
        depth_note += f" Bias: {result['bias']} (every method the same chooser)."
    lines = [f"Predicted error in the rig's {rig} pixels; measured at a {at} screen (pixel counts and measured m "
             f"in its pixels{converted}).{depth_note}", "",
             f"| method | setup (ms) | predicted objective ({rig}) | predicted p95 m ({rig}) | predicted misclassified ({rig}) | "
             f"measured p95 m ({at}) |" + ("" if at == rig else f" measured p95 m ({rig}) |")
             + f" misclassified ({at}) | wrongly shadowed | wrongly lit | outside | receivers |",
             "|---|---:|---:|---:|---:|---:|" + ("" if at == rig else "---:|") + "---:|---:|---:|---:|---:|"]
    for name, r in result["methods"].items():
        p, e = r["predicted_error"], r["evaluation"]
        conv = "" if at == rig else f" {e.get('measured_error_rig_pixels', {}).get('p95_m', float('nan')):.3g} |"
        pm = p.get("misclassified_pixels")
        lines.append(f"| {name} | {r['setup_ms']:.1f} | {p['objective']:.4g} | {p['p95_m']:.3g} | "
                     f"{'-' if pm is None else f'{pm:.0f}'} | "
                     f"{e['measured_error'].get('p95_m', float('nan')):.3g} |{conv} {e['misclassified_pixels']} | "
                     f"{e.get('wrongly_shadowed_pixels', '')} | {e.get('wrongly_lit_pixels', '')} | "
                     f"{e['outside_pixels']} | {e['receiver_pixels']} |")
    return "\n".join(lines) + "\n"
