"""The corpus benchmark's report pieces (service.bench.quality_corpus.bench_quality_corpus): each method's
objective as a ratio to the texel limit, the calibration of the predicted objective against measured
misclassified pixels, and speed against error per scene (a table and a Pillow scatter plot).

Inputs are the per-scene records `quality_scene` stores: {key: {part: {method: [one value per sun]}}}.
Records stored before a key existed simply lack it: every function here reads with .get and reports
"-" for what was not measured.
"""
from __future__ import annotations

import math
import os
import warnings
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw, ImageFont
from scipy.stats import spearmanr


def _finite(v) -> list[float]:
    return [float(x) for x in (v or []) if x is not None and math.isfinite(float(x))]


def ratio_to_limit(rec: dict, part: str) -> dict:
    """Per method: median, min and max over suns of predicted_error's ratio_to_limit (objective /
    solvers.metric.texel_limit), None for a method whose record has no ratio (measured before the
    limit existed)."""
    out = {}
    for m, v in (rec.get("ratio_to_limit", {}).get(part) or {}).items():
        f = _finite(v)
        out[m] = {"median": float(np.median(f)), "min": float(np.min(f)), "max": float(np.max(f))} if f else None
    for m in rec.get("misclassified", {}).get(part, {}):
        out.setdefault(m, None)
    return out


def spearman(a, b) -> float:
    """Spearman's rank correlation (scipy.stats.spearmanr), NaN when a side is constant or < 3 values."""
    if len(a) < 3:
        return float("nan")
    with warnings.catch_warnings():  # a constant side is NaN, reported as such
        warnings.simplefilter("ignore")
        return float(spearmanr(a, b).statistic)


def calibration(predicted, measured) -> dict:
    """How the predicted objective (a weighted mean of h, Chong & Gortler 2007 eq. 9) maps to measured
    misclassified pixels over a set of (sun, method) runs: the Spearman rank correlation (all pairs with
    a finite prediction), and the factor k in measured ≈ k · predicted fitted by least squares in log
    space with slope 1 (k = the geometric mean of measured / predicted), its median, and the spread
    p10..p90 of measured / (k · predicted) (1.0 = every run on the line). Pairs with measured 0 or
    predicted <= 0 have no log ratio and are counted in `left_out`."""
    p = np.asarray(predicted, dtype=float)
    m = np.asarray(measured, dtype=float)
    ok = np.isfinite(p) & np.isfinite(m)
    out = {"n": int(ok.sum()), "spearman": spearman(p[ok], m[ok]) if ok.sum() > 2 else float("nan")}
    pos = ok & (p > 0) & (m > 0)
    out["left_out"] = int(ok.sum() - pos.sum())
    if pos.sum() == 0:
        return {**out, "factor": None, "median": None, "p10": None, "p90": None}
    r = np.log(m[pos] / p[pos])
    k = float(np.exp(r.mean()))
    rel = np.exp(r) / k
    return {**out, "factor": k, "median": float(np.exp(np.median(r))),
            "p10": float(np.percentile(rel, 10)), "p90": float(np.percentile(rel, 90))}


PREDICTED_KEY = "predicted_misclassified"  # quality_scene's record of predicted_error.misclassified_pixels


def pixel_prediction(rec: dict, part: str) -> dict | None:
    """How predicted_error.misclassified_pixels (solvers.metric.predicted_misclassified, in the rig's
    full-resolution pixels) matches measured misclassified pixels over a scene's (sun, method) runs:
    the pooled Spearman (beside the objective's), and measured / predicted: its median and spread
    p10..p90 (1.0 = the prediction is the measured count; runs with a prediction <= 0 or not finite
    are left out of the ratio). None for a record stored before the key existed (the tables say "-")."""
    mis = rec.get("misclassified", {}).get(part) or {}
    pr = (rec.get(PREDICTED_KEY, {}) or {}).get(part) or {}
    if not mis or any(len(pr.get(m) or []) != len(v) for m, v in mis.items()):
        return None
    p = np.array([np.nan if x is None else float(x) for m in mis for x in pr[m]])
    meas = np.array([float(x) for m in mis for x in mis[m]])
    obj = np.array([np.nan if x is None else float(x) for x in pooled(rec, part, "objective")], float)
    ok = np.isfinite(p) & np.isfinite(meas)
    out = {"n": int(ok.sum()), "spearman": spearman(p[ok], meas[ok]) if ok.sum() > 2 else float("nan")}
    okb = np.isfinite(obj) & np.isfinite(meas) if len(obj) == len(meas) else np.zeros(0, bool)
    out["spearman_objective"] = spearman(obj[okb], meas[okb]) if okb.sum() > 2 else float("nan")
    pos = ok & (p > 0)
    out["left_out"] = int(ok.sum() - pos.sum())
    r = meas[pos] / p[pos]
    out.update({"median": float(np.median(r)), "p10": float(np.percentile(r, 10)), "p90": float(np.percentile(r, 90))}
               if len(r) else {"median": None, "p10": None, "p90": None})
    return out


def table_pixel_prediction(stats: dict, part: str, label: str) -> list[str]:
    """Per scene: Spearman of predicted misclassified pixels and of the objective against measured,
    and measured / predicted (median, p10..p90); "-" where the stored record has no prediction."""
    rows = [(k, s[part].get("pixel_prediction")) for k, s in stats.items() if part in s]
    if not rows:
        return []
    lines = [f"**{label}: predicted misclassified pixels** (solution `predicted_error.misclassified_pixels` = K Σ a_i √h_i "
             "over the samples, a_i = full-resolution pixels per sample, √h_i = the texel footprint in pixels, Chong & "
             "Gortler 2007; K calibrated on the corpus): Spearman against measured misclassified pixels pooled over suns "
             "and methods, beside the objective's, and measured / predicted (median, p10..p90; 1.0 = exact); `-` = not in "
             "the stored record).", "",
             "| scene | runs | Spearman predicted pixels | Spearman objective | measured / predicted median | p10..p90 |",
             "|---|---:|---:|---:|---:|---:|"]
    for k, c in rows:
        if c is None:
            lines.append(f"| {k} | - | - | - | - | - |")
            continue
        lines.append(f"| {k} | {c['n']} | {fmt_cell(c['spearman'])} | {fmt_cell(c['spearman_objective'])} | "
                     f"{fmt_cell(c['median'], '.3g')} | {fmt_cell(c['p10'], '.3g')}..{fmt_cell(c['p90'], '.3g')} |")
    return lines


def pooled(rec: dict, part: str, key: str) -> list:
    return [x for v in (rec.get(key, {}).get(part) or {}).values() for x in v]


def corpus_calibration(raws: dict, part: str) -> dict:
    """The calibration fitted on the whole corpus (every scene's (sun, method) runs pooled), and per
    scene the factor a scene would need relative to the corpus one (1.0: the corpus factor fits it)."""
    pred, meas, per = [], [], {}
    for key, rec in raws.items():
        if part not in rec.get("misclassified", {}):
            continue
        p, m = pooled(rec, part, "objective"), pooled(rec, part, "misclassified")
        pred += p
        meas += m
        per[key] = calibration(p, m)
    whole = calibration(pred, meas)
    for c in per.values():
        c["vs_corpus"] = c["factor"] / whole["factor"] if c["factor"] and whole["factor"] else None
    return {"corpus": whole, "scenes": per}


def speed_error(stats: dict, part: str = "single") -> dict:
    """Per scene and method: median setup ms and total misclassified pixels relative to the lowest
    total of any method on that scene (1.0 = the best)."""
    out = {}
    for key, s in stats.items():
        p = s.get(part)
        if not p:
            continue
        best = max(min(p["totals"].values()), 1)
        out[key] = {m: {"setup_ms": p["setup_ms_p50"][m], "setup_ms_min": p.get("setup_ms_min", {}).get(m),
                        "misclassified": p["totals"][m],
                        "vs_best": p["totals"][m] / best} for m in p["totals"]}
    return out


def fmt_cell(x, spec=".2f", none="-") -> str:
    """`x` formatted with `spec`, or `none` for None and non-finite floats (a table cell)."""
    return none if x is None or (isinstance(x, float) and not math.isfinite(x)) else format(x, spec)


def table_ratio_to_limit(stats: dict, part: str, label: str) -> list[str]:
    rows = [(k, s[part]["ratio_to_limit"]) for k, s in stats.items() if part in s]
    if not rows:
        return []
    methods = list(rows[0][1])
    lines = [f"**{label}: predicted objective as a ratio to the texel limit** (solution `predicted_error.ratio_to_limit` = "
             "objective / 2(Σ a_i√w_i)²/(T Σ a_i w_i), the least weighted mean h any map of T texels can reach on these "
             "samples; median over suns, [min, max]; 1.0 = no map can do better, `-` = not in the stored record).", "",
             "| scene | " + " | ".join(methods) + " |", "|---|" + "---:|" * len(methods)]
    for k, r in rows:
        lines.append(f"| {k} | " + " | ".join("-" if r.get(m) is None else
                                                f"{r[m]['median']:.2f} [{r[m]['min']:.2f}, {r[m]['max']:.2f}]"
                                                for m in methods) + " |")
    return lines


def table_calibration(stats: dict, cal: dict, part: str, label: str) -> list[str]:
    per = cal["scenes"]
    if not per:
        return []
    c = cal["corpus"]
    lines = [f"**{label}: calibration of the prediction** (every (sun, method) run of the scene: Spearman of predicted "
             "objective against measured misclassified pixels; the factor k in misclassified ≈ k · objective, fitted in "
             "log space with slope 1, its median, and the spread p10..p90 of misclassified / (k · objective); `k / corpus`: "
             f"this scene's k over the corpus's k = {fmt_cell(c['factor'], '.4g')} (all scenes pooled; Spearman "
             f"{fmt_cell(c['spearman'])}, spread {fmt_cell(c['p10'])}..{fmt_cell(c['p90'])}). Runs with 0 misclassified are left out "
             "of the fit).", "",
             "| scene | runs | Spearman | k | median | spread p10..p90 | k / corpus | left out |",
             "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for k, s in per.items():
        lines.append(f"| {k} | {s['n']} | {fmt_cell(s['spearman'])} | {fmt_cell(s['factor'], '.4g')} | {fmt_cell(s['median'], '.4g')} | "
                     f"{fmt_cell(s['p10'])}..{fmt_cell(s['p90'])} | {fmt_cell(s.get('vs_corpus'))} | {s['left_out']} |")
    return lines


def table_speed_error(se: dict, label: str, plot_link: str | None) -> list[str]:
    if not se:
        return []
    methods = list(next(iter(se.values())))
    lines = [f"**{label}: speed against error per scene** (median setup ms per light, `timings_ms.optimize`, the fastest "
             "sun in brackets: less sensitive to the machine's load; total misclassified over the suns relative to the "
             "lowest total of any method on the scene)"
             + (f"; plot: [{plot_link}]({plot_link})" if plot_link else "") + ".", "",
             "| scene | " + " | ".join(f"{m} ms / err" for m in methods) + " |", "|---|" + "---:|" * len(methods)]
    for k, r in se.items():
        lines.append(f"| {k} | " + " | ".join(f"{r[m]['setup_ms']:.1f} ({fmt_cell(r[m].get('setup_ms_min'), '.1f')}) / "
                                                f"{r[m]['vs_best']:.2f}" for m in methods) + " |")
    return lines


PALETTE = [(31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189), (140, 86, 75),
           (227, 119, 194), (127, 127, 127), (188, 189, 34), (23, 190, 207)]


def speed_error_plot(se: dict, path: Path, title: str = "setup ms (log) vs misclassified / best", cols: int = 4) -> Path:
    """One panel per scene: each method at (median setup ms, log x; total misclassified / the scene's
    best, log y). Pillow only (no plotting dependency)."""
    W, H, M = 330, 260, 46
    font = ImageFont.load_default(size=11)
    methods = sorted({m for r in se.values() for m in r})
    colour = {m: PALETTE[i % len(PALETTE)] for i, m in enumerate(methods)}
    n = len(se)
    rows = max(1, math.ceil(n / cols))
    legend_h = 16 * (math.ceil(len(methods) / 3) + 1)
    img = Image.new("RGB", (W * min(cols, max(n, 1)), H * rows + legend_h), "white")
    dr = ImageDraw.Draw(img)
    dr.text((8, 4), title, fill="black", font=font)
    for i, m in enumerate(methods):
        x, y = 8 + (i % 3) * 220, 20 + (i // 3) * 16
        dr.ellipse([x, y + 2, x + 8, y + 10], fill=colour[m])
        dr.text((x + 12, y), m, fill="black", font=font)
    for p, (scene, res) in enumerate(se.items()):
        x0, y0 = (p % cols) * W, legend_h + (p // cols) * H
        ts = [max(r["setup_ms"], 1e-3) for r in res.values()]
        ys = [max(r["vs_best"], 1.0) for r in res.values()]
        lx0, lx1 = math.log10(min(ts)) - 0.15, math.log10(max(ts)) + 0.15
        ly1 = max(math.log10(max(ys)), 0.05) * 1.08

        def xy(t, v):
            return (x0 + M + (math.log10(max(t, 1e-3)) - lx0) / (lx1 - lx0) * (W - M - 12),
                    y0 + H - M + 10 - math.log10(max(v, 1.0)) / ly1 * (H - M - 30))

        left, top, right, bottom = x0 + M, y0 + 20, x0 + W - 12, y0 + H - M + 10
        dr.rectangle([left, top, right, bottom], outline="black")
        dr.text((left, y0 + 4), scene, fill="black", font=font)
        for e in range(math.floor(lx0), math.ceil(lx1) + 1):
            for mant in (1, 2, 5):
                t = mant * 10.0 ** e
                if lx0 <= math.log10(t) <= lx1:
                    X, _ = xy(t, 1.0)
                    dr.line([X, bottom, X, bottom + 4], fill="black")
                    dr.text((X - 8, bottom + 6), f"{t:g}", fill="black", font=font)
        for v in (1, 1.25, 1.5, 2, 5, 10, 100):
            if math.log10(v) <= ly1:
                _, Y = xy(min(ts), v)
                dr.line([left - 4, Y, left, Y], fill="black")
                dr.text((x0 + 4, Y - 6), f"{v:g}x", fill="black", font=font)
        for m, r in res.items():
            X, Y = xy(r["setup_ms"], r["vs_best"])
            dr.ellipse([X - 4, Y - 4, X + 4, Y + 4], fill=colour[m], outline="black")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.{os.getpid()}{path.suffix}")  # parallel runs: never a half-written file
    img.save(tmp)
    os.replace(tmp, path)
    return path


def table_engine(stats: dict, part: str, label: str) -> list[str]:
    """Per scene and method: misclassified pixels summed over the suns under the idealized bias (a bias scaled by
    each texel's own world size at the receiver) and under the depth test each map states for an engine
    (`evaluate --depth solution`: hardware or linear depth, receiver constant, caster slope-scaled bias), on the
    same pixels, and their ratio; `-` where the stored record has no engine numbers."""
    rows = [(k, s[part]) for k, s in stats.items() if part in s]
    if not rows:
        return []
    methods = list(rows[0][1]["totals"])
    lines = [f"**{label}: what an engine gets** (misclassified pixels summed over the suns: idealized bias / each map's "
             "stated engine depth test, `evaluate --depth solution`, on the same pixels; engine / ideal in brackets).", "",
             "| scene | " + " | ".join(methods) + " |", "|---|" + "---:|" * len(methods)]
    for k, p in rows:
        eng = p.get("engine_totals")
        cells = []
        for m in methods:
            ideal = p["totals"][m]
            if not eng or m not in eng:
                cells.append(f"{ideal:,} / -")
            else:
                cells.append(f"{ideal:,} / {eng[m]:,} ({eng[m] / ideal:.2f})" if ideal else f"{ideal:,} / {eng[m]:,}")
        lines.append(f"| {k} | " + " | ".join(cells) + " |")
    return lines
