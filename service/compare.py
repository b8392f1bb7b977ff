"""Compare methods on one scene and rig: predicted error, measured error and time, side by side."""
from __future__ import annotations

import time
from pathlib import Path

from ..renderers.ground_truth import evaluate_buffers
from ..renderers.heatmap import ground_truth_heatmap, side_by_side
from .request_cost import WorkLimit, check_eval_work, check_solve_work, flush_if_large, light_faces, map_texels
from .rigs import RigError, SolutionError, resolve_rig
from .scenes import SceneEntry
from .solve import maps_from_solution, solve


def compare(entry: SceneEntry, rig: dict, methods: list[str], screen=None, report_dir=None, grid_every=None,
            solve_options: dict | None = None) -> dict:
    """{"methods": {NAME: {"solution", "predicted_error", "evaluation", "setup_ms"}}} (first light)."""
    if screen:  # predicted and measured error in the same pixels
        rig = {**rig, "camera": {**rig["camera"], "resolution": tuple(screen)}}
    resolved = resolve_rig(rig, entry.loaded)
    try:  # the API's CompareRequest checks this too (before the scene is loaded)
        check_solve_work(rig, solves=len(methods) + 1, kinds=[l.kind for l in resolved.lights], prefix="")
    except WorkLimit as e:
        raise RigError(e.field, e.message, code="too_costly") from None
    w, h = resolved.camera.resolution
    screen_field = "screen" if screen else "rig.camera.resolution"
    try:  # one ground truth per method, of the first light's maps
        texels = map_texels(rig.get("shadow") or {}) * light_faces(None, resolved.lights[0].kind)
        work = check_eval_work([(w * h, texels)] * len(methods), screen_field, f"compare of {len(methods)} methods")
    except WorkLimit as e:
        raise SolutionError(e.field, e.message, code="too_costly") from None
    try:
        return _compare(entry, rig, resolved, methods, report_dir, grid_every, solve_options)
    finally:
        flush_if_large(work)


def _compare(entry, rig, resolved, methods, report_dir, grid_every, solve_options) -> dict:
    out, images = {}, []
    solve(entry, rig, method=methods[0], **(solve_options or {}))  # warm-up: kernels compile once, not in a method's time
    for name in methods:
        t0 = time.perf_counter()
        sol = solve(entry, rig, method=name, **(solve_options or {}))
        setup_ms = (time.perf_counter() - t0) * 1e3
        maps = maps_from_solution(sol)[0]
        gt = evaluate_buffers(entry.rays, resolved.camera, resolved.lights[0], maps)
        out[name] = {"solution": sol, "predicted_error": sol["lights"][0]["predicted_error"],
                     "evaluation": gt.result, "setup_ms": round(setup_ms, 3)}
        if report_dir:
            images.append(ground_truth_heatmap(gt, grid_every))
    result = {"methods": out}
    if report_dir:
        d = Path(report_dir)
        d.mkdir(parents=True, exist_ok=True)
        side_by_side(images, list(methods), str(d / "heatmaps.png"))
        (d / "compare.md").write_text(markdown_table(result))
        result["report"] = {"heatmaps": str(d / "heatmaps.png"), "table": str(d / "compare.md")}
    return result


def markdown_table(result: dict) -> str:
    lines = ["| method | setup (ms) | predicted objective | predicted p95 m | measured p95 m | misclassified | "
             "outside | receivers |", "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for name, r in result["methods"].items():
        p, e = r["predicted_error"], r["evaluation"]
        lines.append(f"| {name} | {r['setup_ms']:.1f} | {p['objective']:.4g} | {p['p95_m']:.3g} | "
                     f"{e['measured_error'].get('p95_m', float('nan')):.3g} | {e['misclassified_pixels']} | "
                     f"{e['outside_pixels']} | {e['receiver_pixels']} |")
    return "\n".join(lines) + "\n"
