"""`shadowopt bench engine-truth`: what an engine shows, scene by scene (issue: the depth bias as an optimized
parameter). On the corpus (configs/corpus.json) and the contact scenes (renderers.contact_scenes), N suns
each, every method is solved twice, with the fitted bias and with the fixed rule (`shadow.bias`), and scored
against exact ray-traced visibility under the engine's depth test (`evaluate --depth solution`) at the rig's
resolution; optimized is also scored with the idealized per-texel rule (`--depth ideal`). Per scene: the
misclassified pixels per method and bias, optimized / the best baseline (fitted, and against the baselines'
fixed rule), optimized's engine / ideal count, the prediction's Spearman rank correlation and median
measured / predicted over suns x methods (pairs measured under 20 pixels are left out of the ratio, not of
the ranking), receiver pixels outside every map, and optimize's time per light (median).
"""
from __future__ import annotations

import json
import statistics
import time
from pathlib import Path

import numpy as np
from scipy.stats import spearmanr

from ...renderers.contact_scenes import CAMERAS as CONTACT_CAMERAS
from ...renderers.contact_scenes import ensure_scene as ensure_contact_scene
from ...renderers.ground_truth import evaluate_buffers
from ..request import SolveRequest
from ..rigs import resolve_rig
from ..scenes import SceneCache
from ..solution_json import maps_from_solution
from ..solve import solve
from .definitions import ROOT, corpus_scenes, hemisphere_directions
from .output import progress, write_section

METHODS = ("optimized", "lispsm", "focused", "uniform")
BASELINES = ("lispsm", "focused", "uniform")
CORPUS = ("demo", "street_canyon", "terrain", "interior", "closeup")
SMALL = 20  # pairs measured under this many pixels are left out of the measured / predicted ratio


def _scenes(names):
    """{name: (path, camera dict)}: the corpus's (its first rig's camera) and the contact scenes."""
    found, skipped = corpus_scenes([n for n in CORPUS if not names or n in names])
    out = {n: (p, next(iter(s["rigs"].values()))["camera"]) for n, (p, s) in found.items()}
    for n, cam in CONTACT_CAMERAS.items():
        if not names or n in names:
            out[n] = (ensure_contact_scene(n), cam)
    return out, skipped


def measure_scene(validate_rig, entry, camera: dict, screen, dirs, log=None) -> dict:
    """Per sun and (method, bias): measured engine count (wrongly lit, wrongly shadowed), the prediction, outside
    pixels, optimize ms; optimized's ideal-depth count."""
    rows = []
    for i, d in enumerate(dirs):
        light = [{"type": "directional", "direction": [float(v) for v in d]}]
        for bias in ("fitted", "rule"):
            rig = validate_rig({"camera": {**camera, "resolution": list(screen)}, "lights": light,
                                "shadow": {"resolution": [1024, 1024], "cascades": 1, "bias": bias}})
            r = resolve_rig(rig, entry.loaded)
            screen_bufs = None
            for method in METHODS:
                sol = solve(entry, rig, SolveRequest(method=method))
                maps = maps_from_solution(sol)[0]
                gt = evaluate_buffers(entry.rays, r.camera, r.lights[0], maps, depth="solution",
                                      screen_buffers=screen_bufs)
                screen_bufs = gt.screen
                res = gt.result
                wl = int(np.sum(gt.misclassified & ~gt.exact_shadowed))
                pe = sol["lights"][0]["predicted_error"]
                row = {"sun": i, "method": method, "bias": bias, "measured": res["misclassified_pixels"],
                       "wrongly_lit": wl, "wrongly_shadowed": res["misclassified_pixels"] - wl,
                       "predicted": pe.get("misclassified_pixels"), "outside": res["outside_pixels"],
                       "optimize_ms": sol["timings_ms"]["optimize"]}
                if method == "optimized" and bias == "fitted":
                    ideal = evaluate_buffers(entry.rays, r.camera, r.lights[0], maps, depth="ideal",
                                             screen_buffers=screen_bufs).result
                    row["ideal"] = ideal["misclassified_pixels"]
                rows.append(row)
                if log:
                    log(f"sun {i} {bias} {method}: measured {row['measured']} predicted {row['predicted']:.0f}")
    return {"rows": rows}


def _total(rows, method, bias):
    return sum(r["measured"] for r in rows if r["method"] == method and r["bias"] == bias)


def scene_summary(rows) -> dict:
    """The per-scene figures of the module doc."""
    opt = _total(rows, "optimized", "fitted")
    best_fit = min(_total(rows, m, "fitted") for m in BASELINES)
    best_rule = min(_total(rows, m, "rule") for m in BASELINES)
    ideal = sum(r.get("ideal", 0) for r in rows if r["method"] == "optimized" and r["bias"] == "fitted")
    fitted = [r for r in rows if r["bias"] == "fitted"]
    suns = sorted({r["sun"] for r in rows})
    worst = 0.0
    for s in suns:  # per sun: optimized against the best baseline (+50 pixels of slack)
        o = next(r["measured"] for r in fitted if r["sun"] == s and r["method"] == "optimized")
        b = min(r["measured"] for r in fitted if r["sun"] == s and r["method"] in BASELINES)
        worst = max(worst, (o - 50) / max(b, 1))
    meas = np.array([r["measured"] for r in fitted], float)
    pred = np.array([r["predicted"] for r in fitted], float)
    rho = float(spearmanr(meas, pred).statistic) if len(set(meas)) > 1 and len(set(pred)) > 1 else float("nan")
    big = meas >= SMALL
    ratio = float(np.median(meas[big] / np.maximum(pred[big], 1e-9))) if big.any() else float("nan")
    t = [r["optimize_ms"] for r in fitted if r["method"] == "optimized"]
    return {"optimized": opt, "best_baseline_fitted": best_fit, "best_baseline_rule": best_rule,
            "ratio_fitted": opt / max(best_fit, 1), "ratio_vs_rule": opt / max(best_rule, 1),
            "ideal": ideal, "engine_over_ideal": (opt - 50 * len(suns)) / max(ideal, 1), "worst_sun": worst,
            "spearman": rho, "median_measured_over_predicted": ratio,
            "outside": sum(r["outside"] for r in rows), "optimize_ms": statistics.median(t) if t else float("nan"),
            "rule_optimized": _total(rows, "optimized", "rule")}


def table(per_scene: dict) -> str:
    lines = ["| scene | optimized (fitted) | best baseline fitted | opt / best fitted | worst sun (opt-50)/best | "
             "best baseline rule | opt fitted / best rule | optimized rule | optimized ideal depth | "
             "Spearman pred-meas | median meas/pred | outside | optimize ms |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    pooled = {"optimized": 0, "best_baseline_fitted": 0, "best_baseline_rule": 0}
    for name, s in per_scene.items():
        for k in pooled:
            pooled[k] += s[k]
        lines.append(f"| {name} | {s['optimized']} | {s['best_baseline_fitted']} | {s['ratio_fitted']:.2f} | "
                     f"{s['worst_sun']:.2f} | {s['best_baseline_rule']} | {s['ratio_vs_rule']:.2f} | "
                     f"{s['rule_optimized']} | {s['ideal']} | {s['spearman']:.2f} | "
                     f"{s['median_measured_over_predicted']:.2f} | {s['outside']} | {s['optimize_ms']:.0f} |")
    lines.append(f"| **pooled** | {pooled['optimized']} | {pooled['best_baseline_fitted']} | "
                 f"{pooled['optimized'] / max(pooled['best_baseline_fitted'], 1):.2f} | | {pooled['best_baseline_rule']} | "
                 f"{pooled['optimized'] / max(pooled['best_baseline_rule'], 1):.2f} | | | | | | |")
    return "\n".join(lines)


def bench_engine_truth(validate_rig, lights: int | None = None, scenes: str | None = None, screen=None,
                       write: bool = True, log=None) -> dict:
    n = lights or 6
    screen = tuple(screen or (640, 360))
    names = scenes.split(",") if scenes else None
    found, skipped = _scenes(names)
    dirs = hemisphere_directions(n, 15.0, 25)
    cache = SceneCache()
    per_scene, raw = {}, {}
    bar = progress(len(found), "engine-truth")
    t0 = time.perf_counter()
    for name, (path, camera) in found.items():
        entry = cache.get(path)
        raw[name] = measure_scene(validate_rig, entry, camera, screen, dirs, log)
        per_scene[name] = scene_summary(raw[name]["rows"])
        if log:
            log(f"{name}: {json.dumps({k: round(v, 3) if isinstance(v, float) else v for k, v in per_scene[name].items()})}")
        bar.update(1)
    bar.close()
    text = table(per_scene)
    if skipped:
        text += "\n\nSkipped: " + "; ".join(f"{k} ({v})" for k, v in skipped.items())
    text += (f"\n\n{n} suns per scene (15-90 degrees elevation, seed 25), one 1024² map, {screen[0]}x{screen[1]} rig, "
             f"engine depth test (`evaluate --depth solution`); wall {time.perf_counter() - t0:.0f} s.")
    out_dir = ROOT / "out" / "bench"
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "engine-truth.json").write_text(json.dumps({"scenes": per_scene, "raw": raw}, indent=1))
    if write:
        cmd = "shadowopt bench engine-truth" + (f" --lights {lights}" if lights else "") + (
            f" --scenes {scenes}" if scenes else "")
        write_section("engine-truth", text, cmd)
    return {"scenes": per_scene, "table": text}
