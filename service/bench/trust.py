"""`shadowopt bench trust`: does the predicted objective rank configurations as measured
misclassified pixels do (Spearman within a rig and pooled)?"""
from __future__ import annotations

import numpy as np

from ...renderers.ground_truth import evaluate_buffers
from ..rigs import resolve_rig
from ..scenes import SceneCache
from ..request import SolveRequest
from ..solution_json import maps_from_solution
from ..solve import solve
from .definitions import ROOT, definitions, hemisphere_directions
from .output import machine, progress, write_section
from .quality_report import spearman


def bench_trust(validate_rig, rigs: int | None = None, write: bool = True) -> dict:
    """Trust in the prediction: per rig (a sun direction on the demo scene), every method at several
    map resolutions ranked by predicted `objective` and by measured misclassified pixels; the
    within-rig Spearman correlation, its mean, and the pooled (across-rig) correlation."""
    spec = definitions()["trust"]
    n = rigs or spec["rigs"]
    entry = SceneCache().get(ROOT / spec["scene"])
    dirs = hemisphere_directions(n, spec["min_elevation_deg"], spec["seed"])
    per_rig, pooled = [], []
    bar = progress(n * len(spec["methods"]) * len(spec["resolutions"]), "trust")
    for d in dirs:
        pred, meas, bnd = [], [], 0
        screen = None  # the camera, screen and light are the rig's whatever the map: its pixels are traced once
        for res in spec["resolutions"]:
            rig = validate_rig({"camera": {**spec["camera"], "resolution": spec["screen"]},
                                "lights": [{"type": "directional", "direction": d.tolist()}],
                                "shadow": {"resolution": [res, res], "cascades": 1}})
            resolved = resolve_rig(rig, entry.loaded)
            for m in spec["methods"]:
                sol = solve(entry, rig, SolveRequest(method=m))
                ev = evaluate_buffers(entry.rays, resolved.camera, resolved.lights[0], maps_from_solution(sol)[0],
                                      screen_buffers=screen)
                screen, gt = ev.screen, ev.result
                pred.append(sol["lights"][0]["predicted_error"]["objective"])
                meas.append(gt["misclassified_pixels"])
                bnd = max(gt["boundary_pixels"], 1)
                bar.update(1)
        rho = spearman(pred, meas)
        per_rig.append({"direction": [round(float(v), 4) for v in d], "spearman": rho,
                        "predicted": pred, "misclassified": meas, "boundary_pixels": bnd})
        pooled += [(p, m, m / bnd) for p, m in zip(pred, meas)]
    bar.close()
    rhos = np.array([r["spearman"] for r in per_rig], float)
    pooled = np.array(pooled)
    across = spearman(pooled[:, 0], pooled[:, 1])
    across_norm = spearman(pooled[:, 0], pooled[:, 2])
    mean_rho = float(np.nanmean(rhos))
    undefined = int(np.sum(~np.isfinite(rhos)))  # a rig where one side ranks nothing (all equal)
    configs = [f"{m}@{r}" for r in spec["resolutions"] for m in spec["methods"]]
    table = "\n".join([
        f"Scene {spec['scene']}, screen {spec['screen'][0]}x{spec['screen'][1]}, {n} sun directions; per rig "
        f"{len(configs)} configurations ({', '.join(spec['methods'])} at {', '.join(map(str, spec['resolutions']))}²) "
        "ranked by predicted objective and by measured misclassified pixels.", "",
        "| statistic | value |", "|---|---:|",
        f"| mean within-rig Spearman (target >= 0.8) | **{mean_rho:.3f}** |",
        f"| median within-rig Spearman | {float(np.nanmedian(rhos)):.3f} |",
        f"| lowest within-rig Spearman | {float(np.nanmin(rhos)):.3f} |",
        f"| across rigs, pooled: objective vs misclassified | {across:.3f} |",
        f"| across rigs, pooled: objective vs misclassified per boundary pixel | {across_norm:.3f} |",
        f"| rigs | {n} ({undefined} without a defined correlation, left out of the mean) |"])
    out = {"benchmark": "trust", "machine": machine(), "rigs": per_rig, "mean_within_rig_spearman": mean_rho,
           "across_rig_spearman": across, "across_rig_spearman_per_boundary_pixel": across_norm,
           "configurations": configs, "table": table}
    if write:
        write_section("trust", table, f"shadowopt bench trust --lights {n}")
    return out
