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
    out["table"] = "\n\n".join(sections)
    if write:
        write_section("quality", out["table"], f"shadowopt bench quality --lights {n}")
    return out


def bench_solvers(validate_rig, lights: int = 5, write: bool = True) -> dict:
    """Speed against error per solver (a Pareto table): optimization time (coarse buffers excluded)
    and the objective reached relative to the best any solver reached, median over sun directions,
    on the demo scene and the chess set (when ../shared is present)."""
    import numpy as np

    from ..service.rigs import resolve_rig
    from ..service.scenes import SceneCache
    from ..service.solve import light_problems
    from ..service.pipeline import coarse_pass
    from ..solvers.optimize import METHODS, minimize

    spec = definitions()["coarse"]["scenes"]
    results, lines = {}, []
    for name in ("demo", "chess_set"):
        path = (ROOT / spec[name]["path"]).resolve()
        if not path.exists():
            continue
        entry = SceneCache().get(path)
        lo, hi = entry.loaded.geometry.bounds()
        per = {m: {"ms": [], "rel": []} for m in METHODS}
        for d in hemisphere_directions(lights, 15.0, 3):
            rig = validate_rig({**spec[name]["rig"], "lights": [{"type": "directional", "direction": d.tolist()}],
                                "shadow": {"resolution": [1024, 1024], "cascades": 1}})
            resolved, buffers = coarse_pass(entry, rig)
            prob = light_problems(resolved, buffers, (lo, hi))[0]
            minimize(resolved.camera, prob.light, prob.samples, prob.receivers, (lo, hi), (1024, 1024))  # warm-up
            funs = {}
            for m in METHODS:
                r = minimize(resolved.camera, prob.light, prob.samples, prob.receivers, (lo, hi), (1024, 1024), m)
                per[m]["ms"].append(r.time_ms)
                funs[m] = r.fun
            best = min(funs.values())
            for m in METHODS:
                per[m]["rel"].append(funs[m] / best)
        results[name] = {m: {"time_ms_p50": float(np.median(v["ms"])), "objective_over_best_p50": float(np.median(v["rel"])),
                             "objective_over_best_max": float(np.max(v["rel"]))} for m, v in per.items()}
        lines.append(f"**{name}** ({lights} sun directions, one 1024² map):\n")
        lines.append("| solver | time p50 (ms) | objective / best p50 | worst |")
        lines.append("|---|---:|---:|---:|")
        for m, r in sorted(results[name].items(), key=lambda kv: kv[1]["time_ms_p50"]):
            lines.append(f"| {m} | {r['time_ms_p50']:.1f} | {r['objective_over_best_p50']:.3f} | {r['objective_over_best_max']:.3f} |")
        lines.append("")
    table = "\n".join(lines)
    out = {"benchmark": "solvers", "machine": machine(), "scenes": results, "table": table}
    if write:
        write_section("solvers", table, f"shadowopt bench solvers --lights {lights}")
    return out
