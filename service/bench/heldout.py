"""The corpus protocol (Chong & Gortler 2007 §3, as `service.bench.quality.quality_scene` runs it) on the
HELD-OUT scenes (configs/heldout.json, built by renderers.heldout): scenes of kinds the development
corpus does not have, which nobody tunes on, with suns from a seed other than the corpus's.

Per scene rig it prints, one map: misclassified pixels per method (summed over suns), optimized over
the best baseline (the best of focused, LiSPSM, LogPSM by total), the suns where optimized is worse
than 1.25x that sun's best baseline + 50 pixels (the per-sun bound of the quality targets), the suns where it is not
the lowest of all methods, and outside pixels per method; with cascades (on `cascade_scenes`): the
totals of configs/benchmarks.json's cascade configurations (4 x 400^2 texels: practical splits +
LiSPSM, optimized with practical splits, optimized splits/allocation) and their ratios to the reference.

Each scene rig's raw measurements go to out/heldout/results/<scene>--<rig>.json (with the code's
commit), the table to out/heldout/results.md. `reuse` takes a stored scene rig measured with the same
settings instead of measuring again (so disjoint scene lists may run in separate processes and be
merged by a last run). `shadowopt bench heldout` prints the table and writes it into BENCHMARKS.md:

  shadowopt bench heldout --scenes colonnade --lights 2 --screen 300x300 --part single
"""
from __future__ import annotations

import hashlib
import json
import os
import re
import statistics
import subprocess
import time
from pathlib import Path

import numpy as np

from ...renderers.heldout import ensure_scene
from ..scenes import SceneCache
from .definitions import definitions, hemisphere_directions, quality_configs
from .output import machine, write_section
from .quality import quality_scene

ROOT = Path(__file__).resolve().parents[2]
CONFIG = ROOT / "configs" / "heldout.json"
OUT = ROOT / "out" / "heldout"


def heldout_definitions() -> dict:
    return json.loads(CONFIG.read_text())


def heldout_scenes(names=None, folder=None) -> dict:
    """{name: (path, scene spec)} for the held-out scenes (all, or `names` in that order), built into
    `folder` (default out/heldout/)."""
    spec = heldout_definitions()["scenes"]
    wanted = list(names) if names else list(spec)
    unknown = [n for n in wanted if n not in spec]
    if unknown:
        raise ValueError(f"unknown held-out scene {unknown[0]!r} (known: {', '.join(spec)})")
    return {n: (ensure_scene(spec[n]["build"], folder), spec[n]) for n in wanted}


def _commit() -> str:
    """The code's commit (git at the repository root), or SHADOWOPT_CODE_COMMIT for a run from an
    exported tree that is not a git checkout."""
    if os.environ.get("SHADOWOPT_CODE_COMMIT"):
        return os.environ["SHADOWOPT_CODE_COMMIT"]
    try:
        head = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "HEAD"], capture_output=True, text=True,
                              timeout=10).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(ROOT), "status", "--porcelain", "--untracked-files=no"],
                               capture_output=True, text=True, timeout=10).stdout.strip()
        return (head + (" (+ uncommitted changes)" if dirty else "")) if head else "unknown (not a git checkout)"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def configurations(map_res, parts) -> dict:
    """The corpus's configurations (service.bench.definitions.quality_configs on configs/benchmarks.json's
    `quality`), one map at `map_res`."""
    q = definitions()["quality"]
    return quality_configs({**q, "map": list(map_res)}, parts)


def scene_summary(rec: dict, dirs, protocol: dict) -> dict:
    """What the table prints for one scene rig, from quality_scene's record."""
    out = {}
    base = protocol["baselines"]
    if "single" in rec["misclassified"]:
        mis = {m: np.asarray(v, float) for m, v in rec["misclassified"]["single"].items()}
        opt = mis["optimized"]
        bases = [m for m in base if m in mis]
        tot = {m: int(v.sum()) for m, v in mis.items()}
        best = min(bases, key=lambda m: tot[m])
        best_sun = np.min(np.stack([mis[m] for m in bases]), axis=0)
        others = np.min(np.stack([mis[m] for m in mis if m != "optimized"]), axis=0)
        bound = protocol["per_sun_factor"] * best_sun + protocol["per_sun_pixels"]
        over = [int(i) for i in np.nonzero(opt > bound)[0]]
        worst = int(np.argmax(opt - best_sun))
        d = dirs[worst]
        out["single"] = {
            "suns": len(opt), "totals": tot, "best_baseline": best,
            "optimized_over_best": tot["optimized"] / max(tot[best], 1),
            "suns_over_bound": over, "suns_not_lowest": int(np.sum(opt > others)),
            "outside": {m: int(np.sum(v)) for m, v in rec["outside"]["single"].items()},
            "receivers_mean": float(np.mean(rec["receivers"]["single"]["optimized"])),
            "setup_ms_p50": {m: float(statistics.median(v)) for m, v in rec["setup_ms"]["single"].items()},
            "ratio_to_limit_p50": {m: (float(statistics.median([x for x in v if x is not None]))
                                       if any(x is not None for x in v) else None)
                                   for m, v in rec["ratio_to_limit"]["single"].items()},
            "worst_sun": {"index": worst, "direction": [float(x) for x in d],
                          "elevation_deg": round(float(np.degrees(np.arcsin(-d[1]))), 1),
                          "optimized": int(opt[worst]), "best_baseline": int(best_sun[worst]),
                          "best_baseline_method": min(bases, key=lambda m: mis[m][worst]),
                          "boundary_pixels": int(rec["boundary"]["single"]["optimized"][worst])},
        }
    if "cascades" in rec["misclassified"]:
        mis = {m: np.asarray(v, float) for m, v in rec["misclassified"]["cascades"].items()}
        tot = {m: int(v.sum()) for m, v in mis.items()}
        ref = "practical+lispsm"
        out["cascades"] = {"suns": len(next(iter(mis.values()))), "totals": tot,
                           "ratios": {f"{m}/{ref}": tot[m] / max(tot[ref], 1) for m in tot if m != ref and ref in tot},
                           "suns_worse_than_ref": {m: int(np.sum(mis[m] > mis[ref])) for m in mis if m != ref and ref in mis},
                           "outside": {m: int(np.sum(v)) for m, v in rec["outside"]["cascades"].items()},
                           "setup_ms_p50": {m: float(statistics.median(v)) for m, v in rec["setup_ms"]["cascades"].items()}}
    return out


def _fingerprint(path: Path, camera: dict, screen, configs: dict, part_dirs: dict) -> str:
    h = hashlib.sha256()
    h.update(path.read_bytes())
    h.update(json.dumps([camera, list(screen), configs, {p: [list(map(float, d)) for d in v] for p, v in part_dirs.items()}],
                        sort_keys=True).encode())
    return h.hexdigest()[:16]


def run(validate_rig, scenes=None, lights: int | None = None, seed: int | None = None, screen=None, map_res=None,
        cascade_scenes=None, cascade_lights: int | None = None, cascades: bool = True, reuse: bool = False,
        store: Path | None = None, results_md: Path | None = None, log=print) -> dict:
    """The corpus protocol on the held-out rigs; prints a block per scene rig as it finishes and returns
    {"scenes": {key: summary}, "table": markdown, ...}; writes the table to `results_md` when given.
    `validate_rig(dict) -> dict` is the API's rig validation (as every bench takes it)."""
    d = heldout_definitions()
    proto = d["protocol"]
    n = lights or proto["lights"]
    seed = proto["seed"] if seed is None else seed
    screen = list(screen or proto["screen"])
    map_res = list(map_res or proto["map"])
    cascade_scenes = list(proto["cascade_scenes"] if cascade_scenes is None else cascade_scenes) if cascades else []
    n_cas = min(n, cascade_lights or proto["cascade_lights"])
    dirs = hemisphere_directions(n, proto["min_elevation_deg"], seed)
    store = Path(store) if store is not None else OUT / "results"
    store.mkdir(parents=True, exist_ok=True)
    commit = _commit()
    found = heldout_scenes(scenes.split(",") if isinstance(scenes, str) else scenes)
    summaries, raw = {}, {}
    for name, (path, sspec) in found.items():
        parts = ("single", "cascades") if name in cascade_scenes else ("single",)
        configs = configurations(map_res, parts)
        part_dirs = {"single": dirs, "cascades": dirs[:n_cas]}
        part_dirs = {p: v for p, v in part_dirs.items() if p in configs}
        entry = None
        for rig_name, rig in sspec["rigs"].items():
            key = f"{name}--{rig_name}"
            fp = _fingerprint(Path(path), rig["camera"], screen, configs, part_dirs)
            file = store / f"{key}.json"
            old = json.loads(file.read_text()) if reuse and file.exists() else None
            if old is not None and old.get("fingerprint") == fp:
                rec, wall = old["rec"], old["wall_s"]
                log(f"{key}: reused ({old.get('commit')}, {old.get('measured')})")
            else:
                if entry is None:
                    entry = SceneCache().get(path)
                t0 = time.perf_counter()
                rec = quality_scene(validate_rig, entry, rig["camera"], screen, part_dirs, configs)
                wall = round(time.perf_counter() - t0, 1)
                tmp = file.with_suffix(f".tmp{os.getpid()}")
                tmp.write_text(json.dumps({"fingerprint": fp, "commit": commit, "scene": name, "rig": rig_name,
                                           "measured": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
                                           "wall_s": wall, "screen": screen, "map": map_res, "seed": seed,
                                           "dirs": dirs.tolist(), "rec": rec}, default=float))
                os.replace(tmp, file)
            s = scene_summary(rec, dirs, proto)
            s["wall_s"] = wall
            summaries[key], raw[key] = s, rec
            log(_block(key, s, proto))
    table = tables(summaries, proto, dict(lights=n, seed=seed, screen=screen, map=map_res, cascade_lights=n_cas,
                                            commit=commit))
    if results_md is not None:
        Path(results_md).parent.mkdir(parents=True, exist_ok=True)
        Path(results_md).write_text(table + "\n")
    return {"scenes": summaries, "raw": raw, "dirs": dirs.tolist(), "table": table, "commit": commit}


def _block(key: str, s: dict, proto: dict) -> str:
    lines = [f"== {key} ({s['wall_s']:.0f} s)"]
    if "single" in s:
        p = s["single"]
        lines.append("  one map, misclassified: " + ", ".join(f"{m} {v}" for m, v in p["totals"].items()))
        lines.append(f"  optimized / best baseline ({p['best_baseline']}) = {p['optimized_over_best']:.3f}; "
                     f"suns over {proto['per_sun_factor']}x best + {proto['per_sun_pixels']}: {len(p['suns_over_bound'])} of {p['suns']} "
                     f"{p['suns_over_bound']}; not lowest: {p['suns_not_lowest']}")
        lines.append("  outside: " + ", ".join(f"{m} {v}" for m, v in p["outside"].items()))
        w = p["worst_sun"]
        lines.append(f"  worst sun #{w['index']} (elev {w['elevation_deg']} deg): optimized {w['optimized']} vs "
                     f"{w['best_baseline_method']} {w['best_baseline']}")
    if "cascades" in s:
        c = s["cascades"]
        lines.append("  4 cascades, misclassified: " + ", ".join(f"{m} {v}" for m, v in c["totals"].items()))
        lines.append("  " + ", ".join(f"{k} = {v:.3f}" for k, v in c["ratios"].items())
                     + "; outside: " + ", ".join(f"{m} {v}" for m, v in c["outside"].items()))
    return "\n".join(lines)


def tables(summaries: dict, proto: dict, settings: dict) -> str:
    methods = []
    for s in summaries.values():
        for m in s.get("single", {}).get("totals", {}):
            if m not in methods:
                methods.append(m)
    out = [f"# Held-out check (configs/heldout.json, renderers/heldout.py)\n",
           f"Code: {settings['commit']}. Measured {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}. "
           f"Protocol: service.bench.quality.quality_scene; {settings['lights']} suns uniform on the hemisphere above "
           f"{proto['min_elevation_deg']} deg (seed {settings['seed']}; the corpus uses 2), screen "
           f"{settings['screen'][0]}x{settings['screen'][1]}, one {settings['map'][0]}x{settings['map'][1]} map; "
           "misclassified pixels against exact ray-traced visibility. Best baseline: the best of "
           f"{', '.join(proto['baselines'])} by total. Per-sun bound: optimized > {proto['per_sun_factor']}x "
           f"that sun's best baseline + {proto['per_sun_pixels']} px.\n",
           "## One map\n",
           "| scene | " + " | ".join(methods) + " | optimized / best baseline | suns over bound | not lowest | outside px (per method) | optimized setup ms p50 |",
           "|---|" + "---:|" * len(methods) + "---:|---:|---:|---|---:|"]
    tot_opt = 0
    tot_base = {m: 0 for m in proto["baselines"]}
    for key, s in summaries.items():
        if "single" not in s:
            continue
        p = s["single"]
        tot_opt += p["totals"]["optimized"]
        for m in tot_base:
            tot_base[m] += p["totals"].get(m, 0)
        outside = ", ".join(f"{m} {v}" for m, v in p["outside"].items() if v) or "0"
        out.append(f"| {key} | " + " | ".join(str(p["totals"].get(m, "")) for m in methods)
                   + f" | {p['optimized_over_best']:.3f} ({p['best_baseline']}) | {len(p['suns_over_bound'])} of {p['suns']}"
                   + f" | {p['suns_not_lowest']} | {outside} | {p['setup_ms_p50']['optimized']:.0f} |")
    if tot_opt and any(tot_base.values()):
        bm = min(tot_base, key=lambda m: tot_base[m])
        out.append(f"\nAll held-out scenes together: optimized {tot_opt}, best baseline {bm} {tot_base[bm]}: "
                   f"ratio {tot_opt / max(tot_base[bm], 1):.3f}.")
    out.append("\nWorst sun per scene (largest optimized - best baseline):\n")
    out.append("| scene | sun # | elevation | direction | optimized | best baseline | boundary px (optimized) |")
    out.append("|---|---:|---:|---|---:|---|---:|")
    for key, s in summaries.items():
        if "single" in s:
            w = s["single"]["worst_sun"]
            out.append(f"| {key} | {w['index']} | {w['elevation_deg']} | [{', '.join(f'{x:.3f}' for x in w['direction'])}] | "
                       f"{w['optimized']} | {w['best_baseline_method']} {w['best_baseline']} | {w['boundary_pixels']} |")
    cas = {k: s["cascades"] for k, s in summaries.items() if "cascades" in s}
    if cas:
        names = list(next(iter(cas.values()))["totals"])
        out.append(f"\n## Four cascades (4 x {settings['map'][0]}^2 texels, configs/benchmarks.json `quality.cascades`), "
                   f"the first {settings['cascade_lights']} suns\n")
        out.append("| scene | " + " | ".join(names) + " | ratios to practical+lispsm | suns worse than practical+lispsm | outside px |")
        out.append("|---|" + "---:|" * len(names) + "---|---|---|")
        for key, c in cas.items():
            outside = ", ".join(f"{m} {v}" for m, v in c["outside"].items() if v) or "0"
            out.append(f"| {key} | " + " | ".join(str(c["totals"][m]) for m in names) + " | "
                       + ", ".join(f"{k.split('/')[0]} {v:.3f}" for k, v in c["ratios"].items()) + " | "
                       + ", ".join(f"{m} {v} of {c['suns']}" for m, v in c["suns_worse_than_ref"].items()) + f" | {outside} |")
    return "\n".join(out)


def write_rig(scene: str, sun: int, dest: Path, rig_name: str | None = None, store: Path | None = None,
              shadow: dict | None = None) -> tuple[Path, Path]:
    """A rig file for `shadowopt compare --rig` reproducing stored sun `sun` of a held-out scene rig
    (its camera at the stored screen, that sun, one map at the stored resolution): (scene path, rig file)."""
    sspec = heldout_definitions()["scenes"][scene]
    rig_name = rig_name or next(iter(sspec["rigs"]))
    store = Path(store) if store is not None else OUT / "results"
    stored = json.loads((store / f"{scene}--{rig_name}.json").read_text())
    d = stored["dirs"][sun]
    rig = {"camera": {**sspec["rigs"][rig_name]["camera"], "resolution": stored["screen"]},
           "lights": [{"type": "directional", "direction": [float(x) for x in d]}],
           "shadow": shadow or {"resolution": stored["map"], "cascades": 1}}
    dest = Path(dest)
    dest.parent.mkdir(parents=True, exist_ok=True)
    dest.write_text(json.dumps(rig, indent=1))
    return heldout_scenes([scene])[scene][0], dest


def bench_heldout(validate_rig, lights: int | None = None, scenes: str | None = None, screen=None,
                  cascade_lights: int | None = None, cascades: bool = True, reuse: bool = False, write: bool = True,
                  log=None) -> dict:
    """`shadowopt bench heldout`: `run` with configs/heldout.json's protocol (its map, seed and cascade
    scenes); the table goes into BENCHMARKS.md's `heldout` section (its title dropped, its headings one
    level down)."""
    res = run(validate_rig, scenes=scenes, lights=lights, screen=screen, cascade_lights=cascade_lights,
              cascades=cascades, reuse=reuse, log=log or (lambda m: None))
    out = {"benchmark": "heldout", "machine": machine(), **res}
    if write:
        body = re.sub(r"(?m)^## ", "### ", res["table"].split("\n", 1)[1].lstrip("\n"))
        cmd = ("shadowopt bench heldout" + (f" --scenes {scenes}" if scenes else "") + (f" --lights {lights}" if lights else "")
               + (f" --screen {screen[0]}x{screen[1]}" if screen else "")
               + (f" --cascade-lights {cascade_lights}" if cascade_lights else "")
               + ("" if cascades else " --part single") + (" --reuse" if reuse else ""))
        write_section("heldout", body, cmd)
    return out
