"""The corpus benchmark's per-scene statistics (`scene_stats`: totals, ratios, worst suns, outside
pixels, setup medians, the pooled Spearman), its verdicts per target of issue 10, and the Markdown
tables of its BENCHMARKS.md section (the pieces shared with the report live in quality_report)."""
from __future__ import annotations

import math
import statistics

import numpy as np

from . import quality_report
from .quality_report import spearman


def scene_stats(rec: dict, dirs, spec: dict) -> dict:
    """Per scene and rig: what the corpus tables print (totals, ratios, losses, worst suns, outside
    pixels, setup medians, the pooled Spearman) and the verdict per target."""
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


def tables_corpus(stats: dict, skipped: dict, spec: dict, corpus_ratio, corpus_ok, calib: dict | None = None,
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
                         f"{quality_report.fmt_cell((p.get('pixel_prediction') or {}).get('spearman'))} |")
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
                         + f"{quality_report.fmt_cell((c.get('pixel_prediction') or {}).get('spearman'))} |")
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
