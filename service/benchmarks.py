"""Benchmarks: measured on this machine, printed as a table and written into BENCHMARKS.md.

Definitions (scenes, rigs, run counts) live in configs/benchmarks.json. Paths there are relative
to the repository root. Timings are medians of warm runs; the first (compiling) run is reported apart.
"""
from __future__ import annotations

import json
import platform
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BENCH_FILE = ROOT / "BENCHMARKS.md"


def definitions() -> dict:
    return json.loads((ROOT / "configs" / "benchmarks.json").read_text())


def _progress(total: int, desc: str):
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, file=sys.stderr, leave=False, disable=not sys.stderr.isatty())


def machine() -> str:
    import os

    return f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}"


def bench_coarse(validate_rig, runs: int | None = None, scenes: str | None = None, write: bool = True) -> dict:
    """Load time (cold, cached) and coarse-pass time (first and median of warm runs) per scene.

    `validate_rig(dict) -> dict` is the API's rig validation (benchmark rigs are ordinary rigs).
    """
    from ..renderers.coarse import render_coarse
    from ..service.rigs import resolve_rig
    from ..service.scenes import SceneCache

    spec = definitions()["coarse"]
    runs = runs or spec["runs"]
    wanted = scenes.split(",") if scenes else list(spec["scenes"])
    results, skipped = {}, {}
    for name in wanted:
        if name not in spec["scenes"]:
            raise ValueError(f"--scenes: unknown scene {name!r} (known: {', '.join(spec['scenes'])})")
        sdef = spec["scenes"][name]
        path = (ROOT / sdef["path"]).resolve()
        if not path.exists():
            skipped[name] = f"{sdef['path']} is absent"
            continue
        cache = SceneCache()
        t0 = time.perf_counter()
        entry = cache.get(path)
        cold = time.perf_counter() - t0
        t0 = time.perf_counter()
        cache.get(path)
        cached = time.perf_counter() - t0
        rig = resolve_rig(validate_rig(sdef["rig"]), entry.loaded)
        t0 = time.perf_counter()
        first = render_coarse(entry.rays, rig.camera, rig.lights, spec["long_side"])
        first_ms = (time.perf_counter() - t0) * 1e3
        times, traces = [], []
        bar = _progress(runs, f"coarse {name}")
        for _ in range(runs):
            t0 = time.perf_counter()
            cb = render_coarse(entry.rays, rig.camera, rig.lights, spec["long_side"])
            times.append((time.perf_counter() - t0) * 1e3)
            traces.append(cb.timings_ms["trace"])
            bar.update(1)
        bar.close()
        results[name] = {
            "triangles": entry.loaded.geometry.triangle_count,
            "load_s": round(cold, 3), "usd_load_s": round(entry.load_s, 3), "mitsuba_build_s": round(entry.build_s, 3),
            "load_cached_s": round(cached, 6),
            "coarse_first_ms": round(first_ms, 2),
            "coarse_ms_p50": round(statistics.median(times), 3),
            "coarse_ms_min": round(min(times), 3), "coarse_ms_max": round(max(times), 3),
            "trace_ms_p50": round(statistics.median(traces), 3),
            "pixels": cb.width * cb.height, "hit_pixels": int(first.hit.sum()), "runs": runs,
        }
    table = _table_coarse(results, skipped)
    out = {"benchmark": "coarse", "machine": machine(), "scenes": results, "skipped": skipped,
           "table": table}
    if write:
        write_section("coarse", table, "shadowopt bench coarse")
    return out


def _table_coarse(results: dict, skipped: dict) -> str:
    lines = ["| scene | triangles | load cold (s) | USD load (s) | Mitsuba build (s) | load cached (ms) "
             "| coarse first (ms) | coarse p50 (ms) | min | max | of which ray casting p50 (ms) | pixels |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for name, r in results.items():
        lines.append(f"| {name} | {r['triangles']:,} | {r['load_s']:.2f} | {r['usd_load_s']:.2f} | "
                     f"{r['mitsuba_build_s']:.2f} | {r['load_cached_s'] * 1e3:.3f} | {r['coarse_first_ms']:.1f} | "
                     f"**{r['coarse_ms_p50']:.2f}** | {r['coarse_ms_min']:.2f} | {r['coarse_ms_max']:.2f} | "
                     f"{r['trace_ms_p50']:.2f} | {r['pixels']} |")
    for name, why in skipped.items():
        lines.append(f"| {name} | skipped: {why} |")
    return "\n".join(lines)


def write_section(name: str, table: str, command: str) -> None:
    """Replace (or append) the `name` section of BENCHMARKS.md, keeping the others."""
    begin, end = f"<!-- bench:{name}:begin -->", f"<!-- bench:{name}:end -->"
    stamp = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    body = f"{begin}\nMeasured {stamp} on {machine()} with `{command}`.\n\n{table}\n{end}"
    text = BENCH_FILE.read_text() if BENCH_FILE.exists() else "# Benchmarks\n\nNumbers measured on the project's own machines by the `shadowopt bench` commands.\n"
    if begin in text and end in text:
        pre, rest = text.split(begin, 1)
        post = rest.split(end, 1)[1]
        text = pre + body + post
    else:
        text = text.rstrip("\n") + f"\n\n## {name}\n\n{body}\n"
    BENCH_FILE.write_text(text)


def hemisphere_directions(n: int, min_elevation_deg: float, seed: int):
    """n light directions (the way light travels) uniform on the upper hemisphere above an elevation."""
    import numpy as np

    rng = np.random.default_rng(seed)
    zmin = np.sin(np.radians(min_elevation_deg))
    y = rng.uniform(zmin, 1.0, n)  # uniform in height = uniform in solid angle
    phi = rng.uniform(0, 2 * np.pi, n)
    r = np.sqrt(1 - y * y)
    return np.stack([-r * np.cos(phi), -y, -r * np.sin(phi)], axis=1)


def _table1(mis: dict, setup: dict, ref: str) -> str:
    """Chong & Gortler 2007 Table 1: total misclassified pixels per method over all lights, then over
    the worst 10% of lights by each method, with the percentage more than `ref`; median setup time."""
    import numpy as np

    methods = list(mis)
    arr = {m: np.asarray(v) for m, v in mis.items()}
    n = len(arr[ref])
    k = max(1, n // 10)
    rows = [("All %d" % n, np.arange(n))] + [(f"worst 10% by {m}", np.argsort(-arr[m])[:k]) for m in methods]
    lines = ["| lights | " + " | ".join(methods) + " |", "|---|" + "---:|" * len(methods)]
    for name, idx in rows:
        base = arr[ref][idx].sum()
        cells = []
        for m in methods:
            tot = int(arr[m][idx].sum())
            cells.append(f"**{tot}**" if m == ref else f"{tot} ({100 * (tot - base) / max(base, 1):+.1f}%)")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    lines.append("| setup ms (median) | " + " | ".join(f"{statistics.median(setup[m]):.1f}" for m in methods) + " |")
    return "\n".join(lines)


def _ratios_line(tot: dict, ref: str, others) -> str:
    return ", ".join(f"{ref}/{m} = {tot[ref] / max(tot[m], 1):.3f}" for m in others if m in tot)


def bench_quality(validate_rig, lights: int | None = None, write: bool = True, parts=("single", "cascades")) -> dict:
    """Chong & Gortler 2007 §3's protocol: N light directions on the upper hemisphere, misclassified
    pixels per method against exact ray-traced visibility; totals, the worst-10% rows, setup time.
    `single`: one map per method; `cascades`: 4 cascades under one texel budget (configs/benchmarks.json)."""
    import numpy as np

    from ..renderers.ground_truth import evaluate_buffers
    from ..service.rigs import resolve_rig
    from ..service.scenes import SceneCache
    from ..service.solve import maps_from_solution, solve

    spec = definitions()["quality"]
    n = lights or spec["lights"]
    entry = SceneCache().get(ROOT / spec["scene"])
    dirs = hemisphere_directions(n, spec["min_elevation_deg"], spec["seed"])
    configs = {}
    if "single" in parts:
        configs["single"] = {m: {"method": m, "shadow": {"resolution": spec["map"], "cascades": 1}} for m in spec["methods"]}
    if "cascades" in parts:
        configs["cascades"] = spec["cascades"]["configs"]
    mis = {part: {name: [] for name in c} for part, c in configs.items()}
    setup = {part: {name: [] for name in c} for part, c in configs.items()}
    bar = _progress(n * sum(len(c) for c in configs.values()), "quality")
    for d in dirs:
        for part, cfgs in configs.items():
            for name, c in cfgs.items():
                rig = validate_rig({"camera": {**spec["camera"], "resolution": spec["screen"]},
                                    "lights": [{"type": "directional", "direction": d.tolist()}], "shadow": c["shadow"]})
                resolved = resolve_rig(rig, entry.loaded)
                sol = solve(entry, rig, method=c["method"])
                setup[part][name].append(sol["timings_ms"]["optimize"])
                gt = evaluate_buffers(entry.rays, resolved.camera, resolved.lights[0], maps_from_solution(sol)[0])
                mis[part][name].append(gt.result["misclassified_pixels"])
                bar.update(1)
    bar.close()
    out = {"benchmark": "quality", "machine": machine(), "lights": n, "screen": spec["screen"], "map": spec["map"],
           "scene": spec["scene"], "misclassified": mis, "totals": {}, "setup_ms_p50": {}}
    sections = []
    for part in configs:
        ref = "optimized"
        tot = {m: int(np.sum(v)) for m, v in mis[part].items()}
        out["totals"][part] = tot
        out["setup_ms_p50"][part] = {m: statistics.median(v) for m, v in setup[part].items()}
        table = _table1(mis[part], setup[part], ref)
        if part == "single":
            head = (f"**One map.** Scene {spec['scene']}, screen {spec['screen'][0]}x{spec['screen'][1]}, one "
                    f"{spec['map'][0]}x{spec['map'][1]} map, {n} sun directions uniform on the hemisphere above "
                    f"{spec['min_elevation_deg']} deg; misclassified pixels (percent more than {ref}). Ratios: "
                    + _ratios_line(tot, ref, ("focused", "lispsm", "logpsm")) + " (targets: focused <= 0.75, lispsm <= 0.65).")
        else:
            head = (f"**Four cascades**, same lights and screen: {spec['cascades']['note']}. Ratios: "
                    + _ratios_line(tot, ref, [m for m in tot if m != ref]) + " (target: practical+lispsm <= 0.8).")
        sections.append(head + "\n\n" + table)
        if write:  # one section per part, so a part can be re-measured alone
            write_section("quality" if part == "single" else "quality-cascades", sections[-1],
                          f"shadowopt bench quality --lights {n} --part {part}")
    out["table"] = "\n\n".join(sections)
    return out


def bench_solvers(validate_rig, lights: int = 5, write: bool = True) -> dict:
    """Speed against error per solver (a Pareto table and plot): optimization time (coarse buffers
    excluded) and the objective reached relative to the best any solver reached, median over sun
    directions, on the demo scene and the chess set (when ../shared is present). Also the default
    solver end to end per light (`optimized_maps`: the baselines, the starts, the search and the bias;
    sample selection excluded) for one map and for 4 cascades."""
    import numpy as np

    from ..service.pipeline import coarse_pass
    from ..service.scenes import SceneCache
    from ..service.solve import light_problems
    from ..solvers.optimize import DEFAULT_METHOD, METHODS, minimize, optimized_maps

    spec = definitions()["coarse"]["scenes"]
    results, lines = {}, []
    bar = _progress(lights * 2 * (len(METHODS) + 2), "solvers")
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


def pareto_plot(results: dict, path: Path) -> None:
    """Time to solution (log x) against objective / best (y) per solver, one panel per scene, with the
    Pareto front joined (PIL only: no plotting dependency)."""
    import math

    from PIL import Image, ImageDraw, ImageFont

    W, H, M = 520, 380, 60
    font = ImageFont.load_default(size=12)
    img = Image.new("RGB", (W * len(results), H), "white")
    dr = ImageDraw.Draw(img)
    palette = [(31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189), (140, 86, 75),
               (227, 119, 194), (127, 127, 127), (188, 189, 34), (23, 190, 207)]
    for p, (scene, res) in enumerate(results.items()):
        pts = {m: (r["time_ms_p50"], r["objective_over_best_p50"]) for m, r in res.items() if isinstance(r, dict) and "time_ms_p50" in r}
        x0 = p * W
        tmin, tmax = min(t for t, _ in pts.values()), max(t for t, _ in pts.values())
        lx0, lx1 = math.log10(tmin) - 0.1, math.log10(tmax) + 0.1
        ymax = max(1.05, max(y for _, y in pts.values()) * 1.02)

        def xy(t, y):
            return (x0 + M + (math.log10(t) - lx0) / (lx1 - lx0) * (W - 2 * M),
                    H - M - (y - 1.0) / (ymax - 1.0) * (H - 2 * M))

        dr.rectangle([x0 + M, M, x0 + W - M, H - M], outline="black")
        dr.text((x0 + M, 15), f"{scene}: time p50 (ms, log) vs objective / best", fill="black", font=font)
        for e in range(math.floor(lx0), math.ceil(lx1) + 1):
            for mant in (1, 2, 5):
                t = mant * 10 ** e
                if lx0 <= math.log10(t) <= lx1:
                    X, _ = xy(t, 1.0)
                    dr.line([X, H - M, X, H - M + 4], fill="black")
                    dr.text((X - 8, H - M + 8), f"{t:g}", fill="black", font=font)
        for k in range(5):
            y = 1.0 + k * (ymax - 1.0) / 4
            _, Y = xy(tmin, y)
            dr.line([x0 + M - 4, Y, x0 + M, Y], fill="black")
            dr.text((x0 + 8, Y - 6), f"{y:.3f}", fill="black", font=font)
        front = sorted(pts.items(), key=lambda kv: kv[1][0])
        best_y, chain = math.inf, []
        for m, (t, y) in front:
            if y < best_y:
                best_y = y
                chain.append(xy(t, y))
        if len(chain) > 1:
            dr.line(chain, fill=(160, 160, 160), width=2)
        for i, (m, (t, y)) in enumerate(sorted(pts.items())):
            X, Y = xy(t, y)
            c = palette[i % len(palette)]
            dr.ellipse([X - 4, Y - 4, X + 4, Y + 4], fill=c)
            dr.text((x0 + W - M - 150, M + 8 + 13 * i), f"o {m}", fill=c, font=font)
    path.parent.mkdir(parents=True, exist_ok=True)
    img.save(path)


def spearman(a, b) -> float:
    """Spearman's rank correlation (scipy.stats.spearmanr), NaN when a side is constant."""
    from scipy.stats import spearmanr

    r = spearmanr(a, b).statistic
    return float(r)


def bench_trust(validate_rig, rigs: int | None = None, write: bool = True) -> dict:
    """Trust in the prediction: per rig (a sun direction on the demo scene), every method at several
    map resolutions ranked by predicted `objective` and by measured misclassified pixels; the
    within-rig Spearman correlation, its mean, and the pooled (across-rig) correlation."""
    import numpy as np

    from ..renderers.ground_truth import evaluate_buffers
    from ..service.rigs import resolve_rig
    from ..service.scenes import SceneCache
    from ..service.solve import maps_from_solution, solve

    spec = definitions()["trust"]
    n = rigs or spec["rigs"]
    entry = SceneCache().get(ROOT / spec["scene"])
    dirs = hemisphere_directions(n, spec["min_elevation_deg"], spec["seed"])
    per_rig, pooled = [], []
    bar = _progress(n * len(spec["methods"]) * len(spec["resolutions"]), "trust")
    for d in dirs:
        pred, meas, bnd = [], [], 0
        for res in spec["resolutions"]:
            rig = validate_rig({"camera": {**spec["camera"], "resolution": spec["screen"]},
                                "lights": [{"type": "directional", "direction": d.tolist()}],
                                "shadow": {"resolution": [res, res], "cascades": 1}})
            resolved = resolve_rig(rig, entry.loaded)
            for m in spec["methods"]:
                sol = solve(entry, rig, method=m)
                gt = evaluate_buffers(entry.rays, resolved.camera, resolved.lights[0], maps_from_solution(sol)[0]).result
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
