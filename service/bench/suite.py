"""Benchmarks: measured on this machine, printed as a table and written into BENCHMARKS.md.

Definitions (scenes, rigs, run counts) live in configs/benchmarks.json. Paths there are relative
to the repository root. Timings are medians of warm runs; the first (compiling) run is reported apart.
"""
from __future__ import annotations

import json
import math
import os
import platform
import statistics
import sys
import time
from pathlib import Path

from . import quality_report
from .quality_report import spearman  # noqa: F401  (bench_trust and the corpus tables use it)

ROOT = Path(__file__).resolve().parents[2]
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
    from ...renderers.coarse import render_coarse
    from ..rigs import resolve_rig
    from ..scenes import SceneCache

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


def quality_configs(spec: dict, parts=("single", "cascades")) -> dict:
    """The configurations of Chong & Gortler's protocol, per part: `single`: one map per method;
    `cascades`: 4 cascades under one texel budget (configs/benchmarks.json's `quality`)."""
    configs = {}
    if "single" in parts:
        configs["single"] = {m: {"method": m, "shadow": {"resolution": spec["map"], "cascades": 1}} for m in spec["methods"]}
    if "cascades" in parts:
        configs["cascades"] = spec["cascades"]["configs"]
    return configs


def _coverage():
    """renderers.coverage.outside_pixels (the full-resolution outside-pixel count without shadow
    rays), or None where that module is absent."""
    try:
        from ...renderers.coverage import outside_pixels
    except ImportError:
        return None
    return outside_pixels


# The keys of quality_scene's record (per part, method and sun); part of the corpus fingerprint, so a
# record stored before a key existed is measured again by --reuse (--reuse any takes it, "-" in the tables).
RECORD_KEYS = ("misclassified", "outside", "boundary", "receivers", "setup_ms", "objective", "limit", "ratio_to_limit",
               "run_s", "predicted_misclassified", "misclassified_engine")


def quality_scene(validate_rig, entry, camera: dict, screen, dirs, configs: dict, bar=None, hd: dict | None = None) -> dict:
    """One scene and camera under Chong & Gortler 2007 §3's protocol: for every light direction and
    every configuration, the solution (`solve`) scored against exact ray-traced visibility
    (`evaluate_buffers` at the rig's resolution `screen`). Per part and configuration, one entry per
    direction: misclassified (idealized bias), misclassified_engine (each map's stated engine depth test,
    `evaluate --depth solution`, on the same pixels), outside and boundary pixels, setup time (ms, coarse pass excluded),
    the predicted objective with its texel limit and ratio to it (None where the solution has none),
    and the wall time of the run (solve and evaluation, s). `dirs`: one array for every part, or {part: array}.

    `hd` = {"screen": [W, H], "lights": k}: for the first k directions, the same configuration solved
    again for a rig of that resolution and its receivers left outside every map counted at full
    resolution by renderers.coverage.outside_pixels (no shadow rays): `outside_hd`, `receivers_hd`,
    `setup_ms_hd`. Skipped when renderers.coverage is absent."""
    from ...renderers.ground_truth import evaluate_buffers, render_screen
    from ..rigs import resolve_rig
    from ..request import SolveRequest
    from ..solution_json import maps_from_solution
    from ..solve import solve

    keys = RECORD_KEYS
    outside_pixels = _coverage() if hd and hd.get("lights") else None
    if outside_pixels is not None:
        keys += ("outside_hd", "receivers_hd", "setup_ms_hd")
    rec = {k: {part: {name: [] for name in c} for part, c in configs.items()} for k in keys}
    per_part = dirs if isinstance(dirs, dict) else {part: dirs for part in configs}
    for i in range(max(len(v) for v in per_part.values())):
        resolved, resolved_hd = {}, {}  # camera and light do not depend on the shadow settings: resolved once per direction
        for part, cfgs in configs.items():
            if i >= len(per_part[part]):
                continue
            d = per_part[part][i]
            for name, c in cfgs.items():
                light = [{"type": "directional", "direction": [float(v) for v in d]}]
                rig = validate_rig({"camera": {**camera, "resolution": list(screen)}, "lights": light, "shadow": c["shadow"]})
                key = tuple(rig["lights"][0]["direction"])
                if key not in resolved:
                    resolved[key] = resolve_rig(rig, entry.loaded)
                r = resolved[key]
                t0 = time.perf_counter()
                sol = solve(entry, rig, SolveRequest(method=c["method"]))
                maps = maps_from_solution(sol)[0]
                ideal = evaluate_buffers(entry.rays, r.camera, r.lights[0], maps)
                gt = ideal.result
                rec["run_s"][part][name].append(time.perf_counter() - t0)
                # What an engine gets: each map's stated depth test and biases (evaluate --depth solution), on the same pixels.
                engine = evaluate_buffers(entry.rays, r.camera, r.lights[0], maps, depth="solution",
                                          screen_buffers=ideal.screen).result
                pe = sol["lights"][0]["predicted_error"]
                for k, v in (("misclassified", gt["misclassified_pixels"]), ("outside", gt["outside_pixels"]),
                             ("misclassified_engine", engine["misclassified_pixels"]),
                             ("boundary", gt["boundary_pixels"]), ("receivers", gt["receiver_pixels"]),
                             ("setup_ms", sol["timings_ms"]["optimize"]), ("objective", pe["objective"]),
                             ("limit", pe.get("limit")), ("ratio_to_limit", pe.get("ratio_to_limit")),
                             (quality_report.PREDICTED_KEY, pe.get("misclassified_pixels"))):
                    rec[k][part][name].append(v)
                if outside_pixels is not None and i < hd["lights"]:
                    rig_hd = validate_rig({"camera": {**camera, "resolution": list(hd["screen"])}, "lights": light,
                                           "shadow": c["shadow"]})
                    if key not in resolved_hd:  # the full-resolution primary rays: traced once per sun, every configuration checked on them
                        rh = resolve_rig(rig_hd, entry.loaded)
                        resolved_hd[key] = (rh, render_screen(entry.rays, rh.camera, rh.lights[0], shadow_rays=False))
                    rh, screen_hd = resolved_hd[key]
                    sol_hd = solve(entry, rig_hd, SolveRequest(method=c["method"]))
                    cov = outside_pixels(entry.rays, rh.camera, rh.lights[0], maps_from_solution(sol_hd)[0], screen=screen_hd)
                    rec["outside_hd"][part][name].append(int(cov["outside_pixels"]))
                    rec["receivers_hd"][part][name].append(int(cov["receiver_pixels"]))
                    rec["setup_ms_hd"][part][name].append(sol_hd["timings_ms"]["optimize"])
                if bar is not None:
                    bar.update(1)
    return rec


def bench_quality(validate_rig, lights: int | None = None, write: bool = True, parts=("single", "cascades")) -> dict:
    """Chong & Gortler 2007 §3's protocol on the demo scene: N light directions on the upper hemisphere,
    misclassified pixels per method against exact ray-traced visibility; totals, the worst-10% rows,
    setup time. `single`: one map per method; `cascades`: 4 cascades under one texel budget
    (configs/benchmarks.json). `bench_quality_corpus` runs the same per-scene loop on the corpus."""
    import numpy as np

    from ..scenes import SceneCache

    spec = definitions()["quality"]
    n = lights or spec["lights"]
    entry = SceneCache().get(ROOT / spec["scene"])
    dirs = hemisphere_directions(n, spec["min_elevation_deg"], spec["seed"])
    configs = quality_configs(spec, parts)
    bar = _progress(n * sum(len(c) for c in configs.values()), "quality")
    rec = quality_scene(validate_rig, entry, spec["camera"], spec["screen"], dirs, configs, bar)
    bar.close()
    mis, setup = rec["misclassified"], rec["setup_ms"]
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


def corpus_definitions() -> dict:
    return json.loads((ROOT / definitions()["quality_corpus"]["corpus"]).read_text())


def corpus_scenes(names=None, cache_dir=None) -> tuple[dict, dict]:
    """The corpus's scenes (configs/corpus.json) as {name: (path, scene spec)}, generated ones built
    into the cache folder (renderers.corpus.ensure_scene), plus {name: why} for those that are absent
    (../shared/usd-assets not mounted). `names` picks some, in the given order."""
    from ...renderers.corpus import ensure_scene

    spec = corpus_definitions()["scenes"]
    wanted = list(names) if names else list(spec)
    unknown = [n for n in wanted if n not in spec]
    if unknown:
        raise ValueError(f"--scenes: unknown corpus scene {unknown[0]!r} (known: {', '.join(spec)})")
    found, skipped = {}, {}
    for name in wanted:
        s = spec[name]
        if "build" in s:
            found[name] = (ensure_scene(s["build"], cache_dir), s)
        else:
            path = (ROOT / s["path"]).resolve()
            if path.exists():
                found[name] = (path, s)
            else:
                skipped[name] = f"{s['path']} is absent"
    return found, skipped


def _scene_stats(rec: dict, dirs, spec: dict) -> dict:
    """Per scene and rig: what the corpus tables print (totals, ratios, losses, worst suns, outside
    pixels, setup medians, the pooled Spearman) and the verdict per target."""
    import numpy as np

    t = spec["targets"]
    out = {}
    for part in rec["misclassified"]:
        mis = {m: np.asarray(v, float) for m, v in rec["misclassified"][part].items()}
        p = {"suns": len(next(iter(mis.values()))), "totals": {m: int(v.sum()) for m, v in mis.items()},
             "outside": {m: int(np.sum(v)) for m, v in rec["outside"][part].items()},
             "outside_max": {m: int(np.max(v)) for m, v in rec["outside"][part].items()},
             "setup_ms_p50": {m: float(statistics.median(v)) for m, v in rec["setup_ms"][part].items()},
             "setup_ms_min": {m: float(np.min(v)) for m, v in rec["setup_ms"][part].items()},
             "run_s_p50": {m: float(statistics.median(v)) for m, v in rec["run_s"][part].items()}}
        pred = np.concatenate([np.asarray(rec["objective"][part][m], float) for m in mis])
        meas = np.concatenate([mis[m] for m in mis])
        p["spearman_pooled"] = spearman(pred, meas) if len(pred) > 2 else float("nan")
        p["calibration"] = quality_report.calibration(pred, meas)
        p["pixel_prediction"] = quality_report.pixel_prediction(rec, part)  # None: stored before misclassified_pixels
        p["ratio_to_limit"] = quality_report.ratio_to_limit(rec, part)
        eng = rec.get("misclassified_engine", {}).get(part)
        p["engine_totals"] = ({m: int(np.sum(v)) for m, v in eng.items()}
                              if eng and all(len(v) == p["suns"] and None not in v for v in eng.values()) else None)
        hd = rec.get("outside_hd", {}).get(part)
        if hd and all(len(v) for v in hd.values()):
            p["outside_hd"] = {m: int(np.sum(v)) for m, v in hd.items()}
            p["outside_hd_max"] = {m: int(np.max(v)) for m, v in hd.items()}
            p["hd_suns"] = len(next(iter(hd.values())))
            p["setup_ms_hd_p50"] = {m: float(statistics.median(v)) for m, v in rec["setup_ms_hd"][part].items()}
        else:
            p["outside_hd"] = p["outside_hd_max"] = p["setup_ms_hd_p50"] = None
            p["hd_suns"] = 0
        per_sun = [spearman([rec["objective"][part][m][i] for m in mis], [mis[m][i] for m in mis]) for i in range(p["suns"])]
        p["spearman_within_sun_mean"] = float(np.nanmean(per_sun)) if np.isfinite(per_sun).any() else float("nan")
        out[part] = p
    if "single" in out:
        p, mis = out["single"], {m: np.asarray(v, float) for m, v in rec["misclassified"]["single"].items()}
        opt, base = mis["optimized"], [m for m in t["baselines"] if m in mis]
        tot = p["totals"]
        best_name = min(base, key=lambda m: tot[m])
        best_per_sun = np.min(np.stack([mis[m] for m in base]), axis=0)
        others = np.min(np.stack([mis[m] for m in mis if m != "optimized"]), axis=0)
        p["best_baseline"] = best_name
        p["ratios"] = {f"optimized/{m}": tot["optimized"] / max(tot[m], 1) for m in ("focused", "lispsm", "logpsm") if m in tot}
        p["ratios"]["optimized/best_baseline"] = tot["optimized"] / max(tot[best_name], 1)
        p["suns_not_lowest"] = int(np.sum(opt > others))
        bound = t["per_sun_factor"] * best_per_sun + t["per_sun_pixels"]
        p["suns_over_per_sun_bound"] = int(np.sum(opt > bound))
        order = np.argsort(-(opt - best_per_sun))[:spec["worst_suns"]]
        p["worst_suns"] = [{"index": int(i), "elevation_deg": round(float(np.degrees(np.arcsin(-dirs[i][1]))), 1),
                            "azimuth_deg": round(float(np.degrees(np.arctan2(dirs[i][2], dirs[i][0])) % 360), 1),
                            "optimized": int(opt[i]), "best_baseline": int(best_per_sun[i]),
                            "best_baseline_method": min(base, key=lambda m: mis[m][i]),
                            "boundary_pixels": int(rec["boundary"]["single"]["optimized"][i])} for i in order]
    if "cascades" in out:
        c = out["cascades"]
        ref = t["cascades_reference"]
        c["ratios"] = {f"{m}/{ref}": c["totals"][m] / max(c["totals"][ref], 1) for m in c["totals"] if m != ref}
    out["verdicts"] = _verdicts(out, t)
    return out


def _verdicts(s: dict, t: dict) -> dict:
    """True/False per target of issue 10 (None when the part was not run)."""
    v = {}
    v["outside_0"] = all(n == 0 for p in ("single", "cascades") if p in s for n in s[p]["outside"].values())
    hd = [s[p]["outside_hd"] for p in ("single", "cascades") if p in s and s[p].get("outside_hd") is not None]
    v["outside_0_hd"] = all(n == 0 for h in hd for n in h.values()) if hd else None
    one, cas = s.get("single"), s.get("cascades")
    v["one_map_vs_best"] = None if one is None else one["ratios"]["optimized/best_baseline"] <= t["one_map_vs_best_baseline"]
    v["per_sun_bound"] = None if one is None else one["suns_over_per_sun_bound"] == 0
    v["cascades"] = None if cas is None else (
        cas["totals"][t["cascades_optimized"]] <= t["cascades_vs_reference"] * max(cas["totals"][t["cascades_reference"]], 0))
    v["spearman"] = None if one is None else bool(one["spearman_pooled"] >= t["spearman"])
    pp = None if one is None else one.get("pixel_prediction")
    v["spearman_pixels"] = None if pp is None or not math.isfinite(pp["spearman"]) else bool(pp["spearman"] >= t["spearman"])
    v["speed_one_map"] = None if one is None else one["setup_ms_p50"]["optimized"] <= t["setup_ms_one_map"]
    v["speed_cascades_practical"] = None if cas is None else (
        cas["setup_ms_p50"][t["cascades_practical_optimized"]] <= t["setup_ms_cascades_practical"])
    v["speed_cascades_optimized_splits"] = None if cas is None else (
        cas["setup_ms_p50"][t["cascades_optimized"]] <= t["setup_ms_cascades_optimized_splits"])
    return v


def _mark(ok) -> str:
    return "n/a" if ok is None else ("yes" if ok else "**no**")


def _tables_corpus(stats: dict, skipped: dict, spec: dict, corpus_ratio, corpus_ok, calib: dict | None = None,
                   plot_link: dict | None = None, hd_screen=None) -> str:
    t = spec["targets"]
    calib, plot_link = calib or {}, plot_link or {}
    hd_name = f"{hd_screen[0]}x{hd_screen[1]}" if hd_screen else "1920x1080"
    rows_single = [(k, s["single"]) for k, s in stats.items() if "single" in s]
    rows_cas = [(k, s["cascades"]) for k, s in stats.items() if "cascades" in s]
    lines = []
    if rows_single:
        methods = list(rows_single[0][1]["totals"])
        lines += ["**One map: misclassified pixels summed over the suns**, the ratios of optimized's total, the suns "
                  "where optimized is not the lowest of all methods, and the Spearman correlation against measured "
                  "misclassified pixels pooled over suns and methods of the predicted objective (within one sun: the mean) "
                  "and of the predicted misclassified pixels (`predicted_error.misclassified_pixels`; `-` = not in the "
                  "stored record).", "",
                  "| scene | " + " | ".join(methods) + " | opt/focused | opt/lispsm | opt/best baseline | not lowest "
                  "| Spearman objective pooled | objective within sun | Spearman predicted pixels pooled |",
                  "|---|" + "---:|" * (len(methods) + 7)]
        for k, p in rows_single:
            r = p["ratios"]
            lines.append(f"| {k} | " + " | ".join(f"{p['totals'][m]:,}" for m in methods) +
                         f" | {r.get('optimized/focused', float('nan')):.3f} | {r.get('optimized/lispsm', float('nan')):.3f} | "
                         f"{r['optimized/best_baseline']:.3f} ({p['best_baseline']}) | {p['suns_not_lowest']} of {p['suns']} | "
                         f"{p['spearman_pooled']:.2f} | {p['spearman_within_sun_mean']:.2f} | "
                         f"{quality_report._fmt((p.get('pixel_prediction') or {}).get('spearman'))} |")
        lines += ["", "**One map: outside pixels** (receiver pixels outside every map; summed over the suns, the worst "
                  "sun in brackets), **setup time** (median ms per light, `timings_ms.optimize`: coarse pass excluded) "
                  "and the benchmark's cost: wall seconds of one (scene, sun, method) run, solve and evaluation, median over methods.", "",
                  "| scene | triangles | " + " | ".join(f"outside {m}" for m in methods) + " | " + " | ".join(f"ms {m}" for m in methods)
                  + " | s per run |",
                  "|---|" + "---:|" * (2 * len(methods) + 2)]
        for k, p in rows_single:
            lines.append(f"| {k} | {stats[k]['triangles']:,} | " + " | ".join(f"{p['outside'][m]} ({p['outside_max'][m]})" for m in methods)
                         + " | " + " | ".join(f"{p['setup_ms_p50'][m]:.1f}" for m in methods)
                         + f" | {statistics.median(p['run_s_p50'].values()):.2f} |")
        lines += ["", *quality_report.table_engine(stats, "single", "One map")]
        lines += ["", *_table_outside_hd(stats, "single", f"One map at {hd_name}", hd_name)]
        lines += ["", *quality_report.table_ratio_to_limit(stats, "single", "One map")]
        if calib.get("single"):
            lines += ["", *quality_report.table_calibration(stats, calib["single"], "single", "One map")]
        lines += ["", *quality_report.table_pixel_prediction(stats, "single", "One map")]
        lines += ["", *quality_report.table_speed_error(quality_report.speed_error(stats, "single"), "One map",
                                                        plot_link.get("single"))]
        lines += ["", f"**One map: the worst suns** (largest excess of optimized over the best of "
                  f"{', '.join(t['baselines'])} on that sun; elevation and azimuth of the light's travel direction).", "",
                  "| scene | sun | elevation | azimuth | optimized | best baseline | boundary pixels |", "|---|---:|---:|---:|---:|---|---:|"]
        for k, p in rows_single:
            for w in p["worst_suns"]:
                lines.append(f"| {k} | {w['index']} | {w['elevation_deg']:.1f} | {w['azimuth_deg']:.1f} | {w['optimized']:,} | "
                             f"{w['best_baseline']:,} ({w['best_baseline_method']}) | {w['boundary_pixels']:,} |")
    if rows_cas:
        names = list(rows_cas[0][1]["totals"])
        ref = t["cascades_reference"]
        lines += ["", f"**Four cascades** ({spec['cascades_note']}): misclassified pixels summed over the suns, ratio to {ref}, "
                  "outside pixels (sum), setup ms (median), pooled Spearman of the objective and of predicted misclassified pixels.", "",
                  "| scene | " + " | ".join(names) + " | " + " | ".join(f"/{ref}: {m}" for m in names if m != ref) + " | "
                  + " | ".join(f"outside {m}" for m in names) + " | " + " | ".join(f"ms {m}" for m in names) + " | Spearman objective | Spearman predicted pixels |",
                  "|---|" + "---:|" * (len(names) * 4 + 1)]
        for k, c in rows_cas:
            lines.append(f"| {k} | " + " | ".join(f"{c['totals'][m]:,}" for m in names) + " | "
                         + " | ".join(f"{c['ratios'][f'{m}/{ref}']:.3f}" for m in names if m != ref) + " | "
                         + " | ".join(f"{c['outside'][m]}" for m in names) + " | "
                         + " | ".join(f"{c['setup_ms_p50'][m]:.1f}" for m in names) + f" | {c['spearman_pooled']:.2f} | "
                         + f"{quality_report._fmt((c.get('pixel_prediction') or {}).get('spearman'))} |")
        lines += ["", *quality_report.table_engine(stats, "cascades", "Four cascades")]
        lines += ["", *_table_outside_hd(stats, "cascades", f"Four cascades at {hd_name}", hd_name)]
        lines += ["", *quality_report.table_ratio_to_limit(stats, "cascades", "Four cascades")]
        if calib.get("cascades"):
            lines += ["", *quality_report.table_calibration(stats, calib["cascades"], "cascades", "Four cascades")]
        lines += ["", *quality_report.table_pixel_prediction(stats, "cascades", "Four cascades")]
        lines += ["", *quality_report.table_speed_error(quality_report.speed_error(stats, "cascades"), "Four cascades",
                                                        plot_link.get("cascades"))]
    cols = [("outside_0", "outside pixels 0"), ("outside_0_hd", f"outside 0 at {hd_name}"),
            ("one_map_vs_best", f"1 map: opt <= {t['one_map_vs_best_baseline']}x best baseline"),
            ("per_sun_bound", f"1 map: no sun > {t['per_sun_factor']}x best + {t['per_sun_pixels']}"),
            ("cascades", f"4 cascades: opt <= {t['cascades_vs_reference']}x {t['cascades_reference']}"),
            ("spearman", f"Spearman objective >= {t['spearman']}"),
            ("spearman_pixels", f"Spearman predicted pixels >= {t['spearman']}"),
            ("speed_one_map", f"setup 1 map <= {t['setup_ms_one_map']:g} ms"),
            ("speed_cascades_practical", f"4 cascades practical <= {t['setup_ms_cascades_practical']:g} ms"),
            ("speed_cascades_optimized_splits", f"optimized splits <= {t['setup_ms_cascades_optimized_splits']:g} ms")]
    lines += ["", "**Verdicts per target** (the quality targets of the corpus benchmark; `yes` = met on this scene).", "",
              "| scene | " + " | ".join(c for _, c in cols) + " |", "|---|" + "---|" * len(cols)]
    for k, s in stats.items():
        lines.append(f"| {k} | " + " | ".join(_mark(s["verdicts"][key]) for key, _ in cols) + " |")
    if corpus_ratio is not None:
        lines.append(f"| **whole corpus** | {_mark(all(s['verdicts']['outside_0'] for s in stats.values()))} | "
                     f"{_mark(all(s['verdicts']['outside_0_hd'] is not False for s in stats.values()))} | "
                     f"opt / best baseline pooled {corpus_ratio:.3f}: {_mark(corpus_ok)} (target <= {t['corpus_vs_best_baseline']}) | | | | | | | |")
    for name, why in skipped.items():
        lines.append(f"| {name} | skipped: {why} |")
    return "\n".join(lines)


def _table_outside_hd(stats: dict, part: str, label: str, hd_name: str) -> list[str]:
    """Outside pixels with the rig at hd_name (solved again at that resolution; renderers.coverage)."""
    rows = [(k, s[part]) for k, s in stats.items() if part in s]
    if not rows:
        return []
    methods = list(rows[0][1]["totals"])
    lines = [f"**{label}: outside pixels** (the same configurations solved for a {hd_name} rig, receivers outside every "
             "map counted at full resolution by renderers.coverage.outside_pixels; summed over the suns checked, the worst "
             "sun in brackets; setup ms median at that resolution; `-`: not measured).", "",
             "| scene | suns | " + " | ".join(f"outside {m}" for m in methods) + " | " + " | ".join(f"ms {m}" for m in methods) + " |",
             "|---|" + "---:|" * (2 * len(methods) + 1)]
    for k, p in rows:
        if p.get("outside_hd") is None:
            lines.append(f"| {k} | 0 | " + " | ".join("-" for _ in methods) + " | " + " | ".join("-" for _ in methods) + " |")
            continue
        lines.append(f"| {k} | {p['hd_suns']} | " + " | ".join(f"{p['outside_hd'][m]} ({p['outside_hd_max'][m]})" for m in methods)
                     + " | " + " | ".join(f"{p['setup_ms_hd_p50'][m]:.1f}" for m in methods) + " |")
    return lines


def _loadavg() -> float | None:
    import os

    try:
        return round(os.getloadavg()[0], 2)
    except OSError:
        return None


def _read_json(file: Path):
    """A stored scene result, or None when absent or unreadable (another process writing it)."""
    try:
        return json.loads(file.read_text())
    except (OSError, ValueError):
        return None


def _write_atomic(file: Path, text: str) -> None:
    """Write via a temporary file and rename, so a parallel merge run never reads half a file."""
    import os

    tmp = file.with_suffix(f".tmp{os.getpid()}")
    tmp.write_text(text)
    os.replace(tmp, file)


def _corpus_fingerprint(path: Path, camera: dict, screen, configs: dict, part_dirs: dict, hd: dict | None = None) -> str:
    """What a scene's corpus result depends on: the scene file, the rig, the protocol's settings and
    the code that solves and evaluates (solvers/, the renderers' ray casting and ground truth, the
    solve step). `--reuse` takes a stored result only when this matches."""
    import hashlib

    import numpy as np

    h = hashlib.sha256()
    st = path.stat()
    h.update(json.dumps([str(path), st.st_size, st.st_mtime_ns, camera, list(screen), configs, RECORD_KEYS,
                         {p: np.asarray(v).round(12).tolist() for p, v in part_dirs.items()}]
                        + ([hd] if hd and hd.get("lights") else []),
                        sort_keys=True, default=str).encode())
    code = sorted((ROOT / "solvers").glob("*.py")) + [
        ROOT / "renderers" / f for f in ("ground_truth.py", "coarse.py", "ray_scene.py", "mitsuba_setup.py", "coverage.py",
                                         "scene_data.py")] + [
        ROOT / "service" / f for f in ("solve.py", "receivers.py", "map_sizing.py", "solution_json.py", "rigs.py", "pipeline.py")]
    for f in code:
        if f.exists():
            h.update(f.read_bytes())
    return h.hexdigest()[:16]


def code_state() -> str:
    """The commit measured, and the files the working tree changes (other engineers' work in progress)."""
    import subprocess

    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                              timeout=10).stdout.strip()
        dirty = subprocess.run(["git", "status", "--short", "--untracked-files=no"], cwd=ROOT, capture_output=True,
                               text=True, timeout=10).stdout.split("\n")
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    changed = [ln[3:] for ln in dirty if ln.strip() and ln[3:].endswith(".py")]
    return f"commit {head}" + (f" (working tree also changes {', '.join(changed)})" if changed else "")


def bench_quality_corpus(validate_rig, lights: int | None = None, scenes: str | None = None, write: bool = True,
                         parts=("single", "cascades"), screen=None, log=None, reuse: bool | str = False,
                         store: Path | None = None, cascade_lights: int | None = None, hd_lights: int | None = None,
                         hd_screen=None, plot: Path | None = None) -> dict:
    """Chong & Gortler's protocol on every corpus scene (configs/corpus.json) with the same
    configurations as `bench_quality` (one map per method, 4 cascades), the same seeded suns on every
    scene (4 cascades: the first `cascade_lights`); per scene and rig: totals, ratios, losses, worst
    suns, outside pixels, setup time, the pooled Spearman, and a verdict per target of issue 10
    (configs/benchmarks.json `quality_corpus`). Each scene's measurements are stored in
    out/bench/quality-corpus/; `reuse` takes them instead of measuring again when the scene, rig,
    settings and code are unchanged (a long run split over processes, or resumed); `reuse="any"` takes
    them whatever code measured them, and the section names those measured with other code.

    Beside the verdicts: every method's objective as a ratio to the texel limit, the calibration of
    the prediction per scene and on the whole corpus (service.bench.quality_report), outside pixels for a
    rig at `hd_screen` (default 1920x1080) on the first `hd_lights` suns (renderers.coverage; 0 turns
    it off), and speed against error per scene with a plot (`plot`; default docs/bench/ when writing,
    the store folder otherwise).

    Parallel runs: processes with disjoint `scenes` (and write=False) each store their scenes' files
    (written atomically); a last run over all scenes with reuse=True measures nothing that is stored
    and writes the merged section."""
    from ..scenes import SceneCache

    qspec, spec = definitions()["quality"], definitions()["quality_corpus"]
    n = lights or spec["lights"]
    screen = list(screen or spec["screen"])
    qspec = {**qspec, "map": spec.get("map", qspec["map"]), "methods": spec.get("methods", qspec["methods"])}
    configs = quality_configs(qspec, parts)
    n_cascades = min(n, spec["cascade_lights"] if cascade_lights is None else cascade_lights)
    hd_spec = spec.get("outside_check", {})
    hd = {"screen": list(hd_screen or hd_spec.get("screen", [1920, 1080])),
          "lights": min(n, hd_spec.get("lights", 10) if hd_lights is None else hd_lights)}
    if _coverage() is None:
        hd["lights"] = 0  # renderers.coverage absent: not measured, the tables say "-"
    dirs = hemisphere_directions(n, spec["min_elevation_deg"], spec["seed"])
    part_dirs = {p: v for p, v in {"single": dirs, "cascades": dirs[:n_cascades]}.items() if p in configs}
    found, skipped = corpus_scenes(scenes.split(",") if scenes else None)
    spec = {**spec, "cascades_note": qspec["cascades"]["note"]}
    stats, raw, timing, load_s, reused, other_code, loads = {}, {}, {}, {}, [], {}, {}
    store = Path(store) if store is not None else ROOT / "out" / "bench" / "quality-corpus"
    store.mkdir(parents=True, exist_ok=True)
    total_rigs = sum(len(s["rigs"]) for _, s in found.values())
    bar = _progress(total_rigs * sum(len(part_dirs[p]) * len(c) for p, c in configs.items()), "quality corpus")
    for name, (path, sspec) in found.items():
        cache = entry = None
        for rig_name, rig in sspec["rigs"].items():
            key = name if len(sspec["rigs"]) == 1 else f"{name}/{rig_name}"
            fp = _corpus_fingerprint(Path(path), rig["camera"], screen, configs, part_dirs, hd)
            file = store / f"{key.replace('/', '--')}.json"
            old = _read_json(file) if reuse else None
            if old is not None and (old.get("fingerprint") == fp or reuse == "any"):
                rec, timing[key], triangles = old["rec"], old["wall_s"], old["triangles"]
                if old.get("loadavg"):
                    loads[key] = old["loadavg"]
                load_s.setdefault(name, old.get("load_s"))
                reused.append(key)
                if old.get("fingerprint") != fp:
                    other_code[key] = f"{old.get('measured', '?')}, {old.get('code', 'code not recorded')}"
            else:
                if entry is None:
                    t0 = time.perf_counter()
                    cache = SceneCache()
                    entry = cache.get(path)
                    load_s[name] = round(time.perf_counter() - t0, 2)
                t1, load0 = time.perf_counter(), _loadavg()
                rec = quality_scene(validate_rig, entry, rig["camera"], screen, part_dirs, configs, bar, hd=hd)
                timing[key] = round(time.perf_counter() - t1, 1)
                loads[key] = [load0, _loadavg()]
                triangles = entry.loaded.geometry.triangle_count
                _write_atomic(file, json.dumps({"fingerprint": fp, "code": code_state(), "scene": name, "rig": rig_name, "rec": rec,
                                            "wall_s": timing[key], "load_s": load_s[name], "triangles": triangles, "loadavg": loads[key],
                                            "measured": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())}, default=float))
            raw[key] = rec
            stats[key] = {**_scene_stats(rec, dirs, spec), "dirs": dirs.tolist(), "triangles": triangles}
            if log:
                log(f"{key}: " + ", ".join(f"{len(part_dirs[p])} suns x {len(c)} ({p})" for p, c in configs.items())
                    + (" reused" if key in reused else f" in {timing[key]:.0f} s"))
        if cache is not None:
            cache.clear()  # one scene in memory at a time (the chess set is 1.4M triangles)
        del entry, cache
    bar.close()
    corpus_ratio = corpus_ok = None
    if stats and "single" in parts:
        base = spec["targets"]["baselines"]
        opt = sum(s["single"]["totals"]["optimized"] for s in stats.values())
        per_method = {m: sum(s["single"]["totals"][m] for s in stats.values()) for m in base}
        corpus_ratio = opt / max(min(per_method.values()), 1)
        corpus_ok = bool(corpus_ratio <= spec["targets"]["corpus_vs_best_baseline"])
    head = (f"Corpus configs/corpus.json ({len(stats)} scene rigs: {', '.join(stats)}), screen {screen[0]}x{screen[1]} "
            f"(the rig's resolution), one {qspec['map'][0]}x{qspec['map'][1]} map; {n} sun directions uniform on the "
            f"hemisphere above {spec['min_elevation_deg']} deg (seed {spec['seed']}, the same on every scene; 4 cascades: "
            f"the first {n_cascades} of them); "
            "misclassified pixels against exact ray-traced visibility (renderers.ground_truth.evaluate_buffers). "
            f"Best baseline: the best of {', '.join(spec['targets']['baselines'])} by total. Code: {code_state()}.")
    if reused:
        head += (f" Taken from this code's stored runs (`--reuse`, out/bench/quality-corpus/): {', '.join(reused)}; "
                 "wall seconds per scene rig: " + ", ".join(f"{k} {v:.0f}" for k, v in timing.items()) + ".")
    if other_code:
        head += (" Measured with code other than the current (`--reuse any`; their fingerprint of scene, rig, settings "
                 "and solving/evaluating code differs): " + "; ".join(f"{k} ({v})" for k, v in other_code.items()) + ".")
    if loads:
        vals = [x for v in loads.values() for x in v if x is not None]
        lo_l, hi_l = (min(vals), max(vals)) if vals else (float("nan"), float("nan"))
        head += (f" Machine load (1-min load average at the start and end of each scene, {os.cpu_count()} cores): "
                 f"{lo_l:.1f}-{hi_l:.1f}: setup times are wall-clock medians under that load.")
    if hd["lights"]:
        head += (f" Outside pixels at {hd['screen'][0]}x{hd['screen'][1]}: the first {hd['lights']} suns, every "
                 "configuration solved again for a rig of that resolution.")
    else:
        head += " Outside pixels at 1920x1080: not measured (renderers.coverage absent or turned off)."
    calib = {p: quality_report.corpus_calibration(raw, p) for p in configs}
    se = {p: quality_report.speed_error(stats, p) for p in configs}
    plot_link = {}
    base_plot = Path(plot) if plot is not None else (ROOT / "docs" / "bench" / "quality_corpus_speed_error.png" if write
                                                      else store / "speed_error.png")
    for p, what in (("single", "one map"), ("cascades", "4 cascades")):
        if not se.get(p):
            continue
        path_p = base_plot if p == "single" else base_plot.with_name(base_plot.stem + "_cascades" + base_plot.suffix)
        quality_report.speed_error_plot(se[p], path_p, f"{what}: setup ms (log) vs total misclassified / the scene's best (log)")
        try:
            plot_link[p] = str(path_p.resolve().relative_to(ROOT))
        except ValueError:
            plot_link[p] = path_p.name
    table = head + "\n\n" + _tables_corpus(stats, skipped, spec, corpus_ratio, corpus_ok, calib, plot_link, hd["screen"])
    out = {"benchmark": "quality-corpus", "machine": machine(), "lights": n, "screen": screen, "map": qspec["map"],
           "cascade_lights": n_cascades, "scenes": stats, "skipped": skipped, "raw": raw,
           "corpus_optimized_over_best_baseline": corpus_ratio, "wall_s": timing, "load_s": load_s, "reused": reused,
           "other_code": other_code, "loadavg": loads, "calibration": calib, "speed_error": se, "outside_check": hd, "plot": plot_link,
           "table": table}
    if write:
        cmd = ("shadowopt bench quality --corpus" + (f" --scenes {scenes}" if scenes else "")
               + (f" --lights {n}" if lights else "") + (f" --screen {screen[0]}x{screen[1]}" if list(screen) != list(spec["screen"]) else "")
               + (f" --cascade-lights {cascade_lights}" if cascade_lights is not None else "")
               + (f" --hd-lights {hd_lights}" if hd_lights is not None else "") + (" --reuse any" if reuse == "any" else " --reuse" if reuse else ""))
        write_section("quality-corpus", table, cmd)
        _dump_corpus(out, "quality-corpus.json")
    return out


def _dump_corpus(obj: dict, name: str) -> None:
    dest = ROOT / "out" / "bench"
    dest.mkdir(parents=True, exist_ok=True)
    (dest / name).write_text(json.dumps(obj, indent=1, default=float))


def bench_solvers(validate_rig, lights: int = 5, write: bool = True) -> dict:
    """Speed against error per solver (a Pareto table and plot): optimization time (coarse buffers
    excluded) and the objective reached relative to the best any solver reached, median over sun
    directions, on the demo scene and the chess set (when ../shared is present). Also the default
    solver end to end per light (`optimized_maps`: the baselines, the starts, the search and the bias;
    sample selection excluded) for one map and for 4 cascades."""
    import numpy as np

    from ..pipeline import coarse_pass
    from ..scenes import SceneCache
    from ..receivers import light_problems
    from ...solvers.optimize import DEFAULT_METHOD, METHODS, minimize
    from ...solvers.optimized_maps import optimized_maps

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


def bench_solvers_corpus(validate_rig, lights: int = 3, scenes: str | None = None, write: bool = True,
                         log=None, tolerance: float = 0.005, screen=None) -> dict:
    """Convergence on the corpus (issue 10: within 0.5% of the best objective any solver finds): per
    scene (its first rig at the corpus screen, one map of the corpus's size) and sun, every solver of
    solvers.optimize.METHODS minimizes the same problem; each solver's objective over the lowest any
    of them reached on that sun, worst over the suns, and its median time."""
    import numpy as np

    from ..pipeline import coarse_pass
    from ..scenes import SceneCache
    from ..receivers import light_problems
    from ...solvers.optimize import DEFAULT_METHOD, METHODS, minimize

    spec = definitions()["quality_corpus"]
    res_map = tuple(spec["map"])
    screen = list(screen or spec["screen"])
    found, skipped = corpus_scenes(scenes.split(",") if scenes else None)
    dirs = hemisphere_directions(lights, spec["min_elevation_deg"], spec["seed"])
    results, warm = {}, set()
    bar = _progress(len(found) * lights * len(METHODS), "solvers corpus")
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




def bench_trust(validate_rig, rigs: int | None = None, write: bool = True) -> dict:
    """Trust in the prediction: per rig (a sun direction on the demo scene), every method at several
    map resolutions ranked by predicted `objective` and by measured misclassified pixels; the
    within-rig Spearman correlation, its mean, and the pooled (across-rig) correlation."""
    import numpy as np

    from ...renderers.ground_truth import evaluate_buffers
    from ..rigs import resolve_rig
    from ..scenes import SceneCache
    from ..request import SolveRequest
    from ..solution_json import maps_from_solution
    from ..solve import solve

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
                sol = solve(entry, rig, SolveRequest(method=m))
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
