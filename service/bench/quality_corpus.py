"""`shadowopt bench quality --corpus`: Chong & Gortler's protocol on every corpus scene, each scene's
measurements stored (and reused when scene, rig, settings and code are unchanged), then the tables
(corpus_tables) and the speed-against-error plots (quality_report)."""
from __future__ import annotations

import hashlib
import json
import os
import subprocess
import time
from pathlib import Path

import numpy as np

from ..scenes import SceneCache
from . import quality_report
from .corpus_tables import scene_stats, tables_corpus
from .definitions import ROOT, corpus_scenes, definitions, hemisphere_directions, quality_configs
from .output import machine, progress, write_section
from .quality import RECORD_KEYS, coverage_outside_pixels, quality_scene


def _loadavg() -> float | None:
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
    tmp = file.with_suffix(f".tmp{os.getpid()}")
    tmp.write_text(text)
    os.replace(tmp, file)


def _corpus_fingerprint(path: Path, camera: dict, screen, configs: dict, part_dirs: dict, hd: dict | None = None) -> str:
    """What a scene's corpus result depends on: the scene file, the rig, the protocol's settings and
    the code that solves and evaluates (solvers/, the renderers' ray casting and ground truth, the
    solve step). `--reuse` takes a stored result only when this matches."""
    h = hashlib.sha256()
    st = path.stat()
    h.update(json.dumps([str(path), st.st_size, st.st_mtime_ns, camera, list(screen), configs, RECORD_KEYS,
                         {p: np.asarray(v).round(12).tolist() for p, v in part_dirs.items()}]
                        + ([hd] if hd and hd.get("lights") else []),
                        sort_keys=True, default=str).encode())
    code = sorted((ROOT / "solvers").glob("*.py")) + [
        ROOT / "renderers" / f for f in ("ground_truth.py", "shadow_map_rays.py", "depth_tests.py", "coarse.py", "ray_scene.py", "mitsuba_setup.py", "coverage.py",
                                         "scene_data.py")] + [
        ROOT / "service" / f for f in ("solve.py", "receivers.py", "map_sizing.py", "solution_json.py", "rigs.py", "pipeline.py")]
    for f in code:
        if f.exists():
            h.update(f.read_bytes())
    return h.hexdigest()[:16]


def code_state() -> str:
    """The commit measured, and the files the working tree changes (other engineers' work in progress)."""
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
    qspec, spec = definitions()["quality"], definitions()["quality_corpus"]
    n = lights or spec["lights"]
    screen = list(screen or spec["screen"])
    qspec = {**qspec, "map": spec.get("map", qspec["map"]), "methods": spec.get("methods", qspec["methods"])}
    configs = quality_configs(qspec, parts)
    n_cascades = min(n, spec["cascade_lights"] if cascade_lights is None else cascade_lights)
    hd_spec = spec.get("outside_check", {})
    hd = {"screen": list(hd_screen or hd_spec.get("screen", [1920, 1080])),
          "lights": min(n, hd_spec.get("lights", 10) if hd_lights is None else hd_lights)}
    if coverage_outside_pixels() is None:
        hd["lights"] = 0  # renderers.coverage absent: not measured, the tables say "-"
    dirs = hemisphere_directions(n, spec["min_elevation_deg"], spec["seed"])
    part_dirs = {p: v for p, v in {"single": dirs, "cascades": dirs[:n_cascades]}.items() if p in configs}
    found, skipped = corpus_scenes(scenes.split(",") if scenes else None)
    spec = {**spec, "cascades_note": qspec["cascades"]["note"]}
    stats, raw, timing, load_s, reused, other_code, loads = {}, {}, {}, {}, [], {}, {}
    store = Path(store) if store is not None else ROOT / "out" / "bench" / "quality-corpus"
    store.mkdir(parents=True, exist_ok=True)
    total_rigs = sum(len(s["rigs"]) for _, s in found.values())
    bar = progress(total_rigs * sum(len(part_dirs[p]) * len(c) for p, c in configs.items()), "quality corpus")
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
            stats[key] = {**scene_stats(rec, dirs, spec), "dirs": dirs.tolist(), "triangles": triangles}
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
    table = head + "\n\n" + tables_corpus(stats, skipped, spec, corpus_ratio, corpus_ok, calib, plot_link, hd["screen"])
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
