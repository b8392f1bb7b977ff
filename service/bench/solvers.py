"""`shadowopt bench solvers`: speed against error per solver (solvers.optimize.METHODS) on the demo
scene and the chess set, with the Pareto plot; `--corpus`: convergence of every solver on the corpus."""
from __future__ import annotations

import time

import numpy as np

from ...solvers.optimized_maps import optimized_maps
from ..pipeline import coarse_pass
from ..scenes import SceneCache
from ..receivers import light_problems
from .definitions import ROOT, corpus_scenes, definitions, hemisphere_directions
from .output import machine, progress, write_section
from .pareto_plot import pareto_plot


def bench_solvers(validate_rig, lights: int = 5, write: bool = True) -> dict:
    """Speed against error per solver (a Pareto table and plot): optimization time (coarse buffers
    excluded) and the objective reached relative to the best any solver reached, median over sun
    directions, on the demo scene and the chess set (when ../shared is present). Also the default
    solver end to end per light (`optimized_maps`: the baselines, the starts, the search and the bias;
    sample selection excluded) for one map and for 4 cascades."""
    from ...solvers.optimize import DEFAULT_METHOD, METHODS, minimize  # lazy: METHODS read at call time (a caller may narrow solvers.optimize.METHODS)

    spec = definitions()["coarse"]["scenes"]
    results, lines = {}, []
    bar = progress(lights * 2 * (len(METHODS) + 2), "solvers")
    for name in ("demo", "chess_set"):
        path = (ROOT / spec[name]["path"]).resolve()
        if not path.exists():
            continue
        entry = SceneCache().get(path)
        lo, hi = entry.loaded.geometry.bounds()
        per = {m: {"ms": [], "rel": []} for m in METHODS}
        whole = {1: [], 4: []}
        for d in hemisphere_directions(lights, 15.0, 3):
            rig = validate_rig({**spec[name]["rig"], "lights": [{"type": "directional", "direction": d.tolist()}],
                                "shadow": {"resolution": [1024, 1024], "cascades": 1}})
            resolved, buffers = coarse_pass(entry, rig)
            prob = light_problems(resolved, buffers, (lo, hi))[0]
            cam = resolved.camera
            minimize(cam, prob.light, prob.samples, prob.receivers, (lo, hi), (1024, 1024))  # warm-up
            funs = {}
            for m in METHODS:
                r = minimize(cam, prob.light, prob.samples, prob.receivers, (lo, hi), (1024, 1024), m)
                per[m]["ms"].append(r.time_ms)
                funs[m] = r.fun
                bar.update(1)
            best = min(funs.values())
            for m in METHODS:
                per[m]["rel"].append(funs[m] / best)
            for k in (1, 4):
                t0 = time.perf_counter()
                optimized_maps(cam, prob.light, prob.samples, prob.receivers, (lo, hi), (1024, 1024), cascades=k,
                               receiver_slack=prob.receiver_slack)
                whole[k].append((time.perf_counter() - t0) * 1e3)
                bar.update(1)
        results[name] = {m: {"time_ms_p50": float(np.median(v["ms"])), "objective_over_best_p50": float(np.median(v["rel"])),
                             "objective_over_best_max": float(np.max(v["rel"]))} for m, v in per.items()}
        results[name]["default_end_to_end_ms_p50"] = {str(k): float(np.median(v)) for k, v in whole.items()}
        lines.append(f"**{name}** ({lights} sun directions, one 1024² map, samples {len(prob.samples)}, "
                     f"receivers {len(prob.receivers)} for the last):\n")
        lines.append("| solver | time p50 (ms) | objective / best p50 | worst |")
        lines.append("|---|---:|---:|---:|")
        rows = {m: r for m, r in results[name].items() if m in METHODS}
        for m, r in sorted(rows.items(), key=lambda kv: kv[1]["time_ms_p50"]):
            label = f"**{m}** (default)" if m == DEFAULT_METHOD else m
            lines.append(f"| {label} | {r['time_ms_p50']:.1f} | {r['objective_over_best_p50']:.3f} | {r['objective_over_best_max']:.3f} |")
        e2e = results[name]["default_end_to_end_ms_p50"]
        lines.append(f"\nDefault solver end to end per light (baselines, starts, search, bias): one map "
                     f"**{e2e['1']:.1f} ms**, 4 cascades **{e2e['4']:.1f} ms** (median).\n")
    bar.close()
    plot = ROOT / "docs" / "bench" / "solvers_pareto.png"
    if write and results:
        pareto_plot(results, plot)
        lines.append(f"Plot: [docs/bench/solvers_pareto.png](docs/bench/solvers_pareto.png) (time against error, one panel per scene).")
    table = "\n".join(lines)
    out = {"benchmark": "solvers", "machine": machine(), "scenes": results, "table": table}
    if write:
        write_section("solvers", table, f"shadowopt bench solvers --lights {lights}")
    return out


def bench_solvers_corpus(validate_rig, lights: int = 3, scenes: str | None = None, write: bool = True,
                         log=None, tolerance: float = 0.005, screen=None) -> dict:
    """Convergence on the corpus (issue 10: within 0.5% of the best objective any solver finds): per
    scene (its first rig at the corpus screen, one map of the corpus's size) and sun, every solver of
    solvers.optimize.METHODS minimizes the same problem; each solver's objective over the lowest any
    of them reached on that sun, worst over the suns, and its median time."""
    from ...solvers.optimize import DEFAULT_METHOD, METHODS, minimize  # lazy: METHODS read at call time (a caller may narrow solvers.optimize.METHODS)

    spec = definitions()["quality_corpus"]
    res_map = tuple(spec["map"])
    screen = list(screen or spec["screen"])
    found, skipped = corpus_scenes(scenes.split(",") if scenes else None)
    dirs = hemisphere_directions(lights, spec["min_elevation_deg"], spec["seed"])
    results, warm = {}, set()
    bar = progress(len(found) * lights * len(METHODS), "solvers corpus")
    for name, (path, sspec) in found.items():
        cache = SceneCache()
        entry = cache.get(path)
        bounds = entry.loaded.geometry.bounds()
        cam_spec = next(iter(sspec["rigs"].values()))["camera"]
        rel = {m: [] for m in METHODS}
        ms = {m: [] for m in METHODS}
        for d in dirs:
            rig = validate_rig({"camera": {**cam_spec, "resolution": screen},
                                "lights": [{"type": "directional", "direction": [float(v) for v in d]}],
                                "shadow": {"resolution": list(res_map), "cascades": 1}})
            resolved, buffers = coarse_pass(entry, rig)
            prob = light_problems(resolved, buffers, bounds)[0]
            if not len(prob.samples):
                continue
            funs = {}
            for m in METHODS:
                if m not in warm:  # the first call of a solver compiles its Dr.Jit kernels: not timed
                    minimize(resolved.camera, prob.light, prob.samples, prob.receivers, bounds, res_map, m)
                    warm.add(m)
                r = minimize(resolved.camera, prob.light, prob.samples, prob.receivers, bounds, res_map, m)
                funs[m] = float(r.fun) if r.fun is not None else float("inf")
                ms[m].append(r.time_ms)
                bar.update(1)
            best = min(funs.values())
            for m in METHODS:
                rel[m].append(funs[m] / best if best > 0 and np.isfinite(best) else float("nan"))
        cache.clear()
        results[name] = {m: {"worst_over_best": float(np.nanmax(rel[m])) if rel[m] else float("nan"),
                             "median_over_best": float(np.nanmedian(rel[m])) if rel[m] else float("nan"),
                             "within": int(np.sum(np.asarray(rel[m]) <= 1 + tolerance)), "suns": len(rel[m]),
                             "time_ms_p50": float(np.median(ms[m])) if ms[m] else float("nan")} for m in METHODS}
        if log:
            log(f"{name}: {len(dirs)} suns x {len(METHODS)} solvers")
    bar.close()
    lines = [f"Corpus configs/corpus.json, screen {screen[0]}x{screen[1]}, one {res_map[0]}x{res_map[1]} map, "
             f"{lights} suns per scene (seed {spec['seed']}, above {spec['min_elevation_deg']} deg): each solver's objective "
             f"over the lowest any solver reached on the same sun, **worst over the suns** (median in brackets); "
             f"`n/N`: suns within {100 * tolerance:g}% of the best (the convergence target). Solvers: "
             "solvers.optimize.METHODS, the same starts (each solver's first call, which compiles its kernels, "
             "is not timed); the default is in bold.", "",
             "| scene | " + " | ".join(f"**{m}**" if m == DEFAULT_METHOD else m for m in METHODS) + " |",
             "|---|" + "---:|" * len(METHODS)]
    for name, r in results.items():
        lines.append(f"| {name} | " + " | ".join(
            f"{r[m]['worst_over_best']:.4f} ({r[m]['median_over_best']:.4f}) {r[m]['within']}/{r[m]['suns']}" for m in METHODS) + " |")
    lines += ["", "Median time per solve (ms, the search alone; samples and receivers excluded):", "",
              "| scene | " + " | ".join(METHODS) + " |", "|---|" + "---:|" * len(METHODS)]
    for name, r in results.items():
        lines.append(f"| {name} | " + " | ".join(f"{r[m]['time_ms_p50']:.1f}" for m in METHODS) + " |")
    ok = [n for n, r in results.items() if r[DEFAULT_METHOD]["within"] == r[DEFAULT_METHOD]["suns"]]
    lines += ["", f"Default solver {DEFAULT_METHOD} within {100 * tolerance:g}% of the best on every sun: "
              f"{len(ok)} of {len(results)} scenes" + (f" (not: {', '.join(n for n in results if n not in ok)})" if len(ok) < len(results) else "") + "."]
    for name, why in skipped.items():
        lines.append(f"Skipped {name}: {why}.")
    table = "\n".join(lines)
    out = {"benchmark": "solvers-corpus", "machine": machine(), "lights": lights, "scenes": results, "skipped": skipped,
           "default": DEFAULT_METHOD, "table": table}
    if write:
        write_section("solvers-corpus", table, f"shadowopt bench solvers --corpus --lights {lights}"
                      + (f" --scenes {scenes}" if scenes else ""))
    return out
