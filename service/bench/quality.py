"""`shadowopt bench quality`: Chong & Gortler 2007 §3's protocol (`quality_scene`: every sun and
configuration solved and scored against exact ray-traced visibility) on the demo scene, with their
Table 1 (totals, the worst-10% rows, setup time). The corpus runs the same loop (quality_corpus)."""
from __future__ import annotations

import statistics
import time

import numpy as np

from ...renderers.ground_truth import evaluate_buffers, render_screen
from ..rigs import resolve_rig
from ..scenes import SceneCache
from ..request import SolveRequest
from ..solution_json import maps_from_solution
from ..solve import solve
from . import quality_report
from .definitions import ROOT, definitions, hemisphere_directions, quality_configs
from .output import machine, progress, write_section


def _table1(mis: dict, setup: dict, ref: str) -> str:
    """Chong & Gortler 2007 Table 1: total misclassified pixels per method over all lights, then over
    the worst 10% of lights by each method, with the percentage more than `ref`; median setup time."""
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


def coverage_outside_pixels():
    """renderers.coverage.outside_pixels (the full-resolution outside-pixel count without shadow
    rays), or None where that module is absent."""
    try:
        from ...renderers.coverage import outside_pixels  # lazy: optional: None where the module is absent
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
    and the wall time of the run (solve and evaluation, s; the screen pass is traced once per direction, and its
    time counted in each run). `dirs`: one array for every part, or {part: array}.

    `hd` = {"screen": [W, H], "lights": k}: for the first k directions, the same configuration solved
    again for a rig of that resolution and its receivers left outside every map counted at full
    resolution by renderers.coverage.outside_pixels (no shadow rays): `outside_hd`, `receivers_hd`,
    `setup_ms_hd`. Skipped when renderers.coverage is absent."""
    keys = RECORD_KEYS
    outside_pixels = coverage_outside_pixels() if hd and hd.get("lights") else None
    if outside_pixels is not None:
        keys += ("outside_hd", "receivers_hd", "setup_ms_hd")
    rec = {k: {part: {name: [] for name in c} for part, c in configs.items()} for k in keys}
    per_part = dirs if isinstance(dirs, dict) else {part: dirs for part in configs}
    for i in range(max(len(v) for v in per_part.values())):
        resolved, resolved_hd = {}, {}  # camera and light do not depend on the shadow settings: resolved once per direction
        screens = {}  # and neither do the screen's pixels: traced once per direction, (ScreenBuffers, seconds it took)
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
                traced = screens.get(key)
                ideal = evaluate_buffers(entry.rays, r.camera, r.lights[0], maps,
                                         screen_buffers=traced[0] if traced else None)
                gt = ideal.result
                if traced is None:
                    screens[key] = (ideal.screen, gt["timings_ms"]["screen"] / 1e3)
                # every run counts the screen pass, whether it traced it or took the direction's first one
                rec["run_s"][part][name].append(time.perf_counter() - t0 + (traced[1] if traced else 0.0))
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
    spec = definitions()["quality"]
    n = lights or spec["lights"]
    entry = SceneCache().get(ROOT / spec["scene"])
    dirs = hemisphere_directions(n, spec["min_elevation_deg"], spec["seed"])
    configs = quality_configs(spec, parts)
    bar = progress(n * sum(len(c) for c in configs.values()), "quality")
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
