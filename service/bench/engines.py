"""`shadowopt bench engines`: `tune` in the real engine (issue 26 part 2; three.js r187's CSM addon, and Babylon.js
9.35's CascadedShadowGenerator with `--engine babylon`) and, with --part matrix (or all, the default), the
custom-matrix modules in three.js and Babylon.js (engines_matrix.py).

On corpus scenes (configs/corpus.json, their first rig's camera at a small screen) with N seeded suns each, per sun:
`tune --engine three` (one pose), the engine's defaults (maxFar = the scene's reach, the rig's map size, as tune's
`defaults`) and a fixed grid of GRID hand settings a user might try (cascades 1-4 x shadowBias, maxFar the scene's
reach, the rig's map size, the other knobs CSM's defaults; material side: DoubleSide only, the one the emulation
offers), each emitted as tune's ES module (service/emit_tune_three.py) and rendered verbatim in three.js r187 + CSM
in Chromium (service/bench/three_page.py: a white Lambert material drawn with and without shadows, "shadowed" where
the ratio is under one half), scored against exact ray-traced visibility of the same screen on the pixels where the
rasterizer and the ray caster see the same surface (view depths within 1%). Reported per scene: the wrong pixels
three.js shows for tune, the defaults and the best grid setting, tune / defaults and tune / best grid (issue 26's
targets <= 0.7 and <= 1), and the emulation's fidelity over the grid, tune and the defaults: the share of settings
whose prediction is within 1.3x + 50 pixels of three.js's count (both ways), the median three / predicted, the median
over suns of the Spearman rank correlation; tune's time per pose (median; the whole search, not cut by tune's
time budget, coarse pass included). Raw rows: out/bench/engines.json.
Babylon.js (`--engine babylon`): the same protocol with tune's Babylon module (service/emit_tune_babylon.py) rendered
in @babylonjs/core 9.35.0 (service/bench/babylon_page.py: a white StandardMaterial with and without shadows), the
defaults Babylon's (PCF, scored by the emulation as one nearest texel), the grid GRIDS["babylon"] (numCascades 2-4 x
bias, FILTER_NONE); BENCHMARKS.md section engines-babylon, raw rows out/bench/engines-babylon.json.
"""
from __future__ import annotations

import json
import statistics
import time

import numpy as np
from scipy.stats import spearmanr

from ...renderers.ground_truth import evaluate_buffers
from ...solvers.engine_fits import engine_module
from .. import emit_tune_babylon, emit_tune_three
from ..rigs import resolve_rig
from ..scenes import SceneCache
from ..tune import tune
from ..tune_score import Pose, predict, probe_pose
from ..tune_search import SEARCHES
from .definitions import ROOT, corpus_scenes, hemisphere_directions
from .engines_matrix import bench_matrix
from .output import write_section
from . import babylon_page, three_page
from .three_page import chromium, scene_geometry

# the default scenes: SwiftShader draws the street canyon's ~361,000 triangles (split to MAX_EDGE for its precision,
# three_page.scene_geometry) ~10x slower than the demo's 38,000 (about 10 min per sun); --scenes picks others
SCENES = ("demo", "terrain", "mcusd")  # mcusd: ../shared/usd-assets (skipped when absent)
GRID_BIASES = (0.000001, -0.0001, -0.0005, -0.002, -0.01)  # CSM's default, then what users try against acne
GRID = [{"cascades": n, "shadowBias": b} for n in (1, 2, 3, 4) for b in GRID_BIASES]  # 20 settings
BABYLON_BIASES = (0.00005, 0.0005, 0.002, 0.005, 0.01, 0.03)  # Babylon's default, then what users try against acne
GRIDS = {"three": GRID,  # Babylon: its count 2-4 x bias, nearest-texel lookups (the test the emulation scores)
         "babylon": [{"numCascades": n, "bias": b, "filter": "NONE"} for n in (2, 3, 4) for b in BABYLON_BIASES]}
ENGINE_NAMES = {"three": "three.js", "babylon": "Babylon.js"}
MAP = 1024
DEPTH_TOLERANCE = 0.01
SLACK = 50  # pixels: "within 1.3x + 50"
FULL_SEARCH_MS = 60_000.0  # the whole search, whatever the machine's load (tune's own budget would cut it short)


def _module(mod, settings: dict, direction, predicted: dict) -> str:
    emitter = {"three": emit_tune_three, "babylon": emit_tune_babylon}[mod.ENGINE]
    return emitter.tune_module({"engine": mod.ENGINE, "engine_version": mod.VERSION, "settings": settings,
                        "light_direction": [float(v) for v in direction], "predicted": predicted,
                        "emulated": {"shadow_map_type": mod.SHADOW_MAP_TYPE}})


def grid_name(g: dict) -> str:
    """A grid setting's short name: cascade count and bias."""
    return "grid " + " ".join(f"{'c' if k in ('cascades', 'numCascades') else 'b'}{v:g}" for k, v in g.items()
                              if k != "filter")


def measure_sun(browser, validate_rig, entry, camera: dict, direction, screen, log=None,
                engine: str = "three") -> list[dict]:
    """One scene and sun: per setting (tune, defaults, grid) its prediction and the wrong pixels the engine shows
    (`engine`)."""
    mod = engine_module(engine)
    spec = SEARCHES[engine]
    rig = validate_rig({"camera": {**camera, "resolution": list(screen)},
                        "lights": [{"type": "directional", "direction": [float(v) for v in direction]}],
                        "shadow": {"resolution": [MAP, MAP]}})
    t0 = time.perf_counter()
    tuned = tune(entry, rig, engine, time_budget_ms=FULL_SEARCH_MS)
    tune_ms = (time.perf_counter() - t0) * 1e3
    pose = Pose(entry, rig)
    configs = [("tune", tuned["settings"], tuned["predicted"]),
               ("defaults", tuned["defaults"]["settings"], tuned["defaults"]["predicted"])]
    for g in GRIDS[engine]:
        s = mod.validate({**tuned["defaults"]["settings"], **g})
        probe = probe_pose(mod, pose, s)[1]
        configs.append((grid_name(g), s, predict(mod, [probe], [pose], spec.constant(mod, s), False)))
    modules = [_module(mod, s, tuned["light_direction"], p) for _, s, p in configs]
    resolved = resolve_rig(rig, entry.loaded)
    cam, light = resolved.camera, resolved.lights[0]
    sun = tuned["light_direction"]
    if engine == "babylon":
        outs = babylon_page.render_modules(browser, modules, babylon_page.scene_geometry(entry, sun),
                                           babylon_page.camera_json(cam),
                                           babylon_page.to_babylon(sun), tuple(screen))
    else:
        cam_json = {"position": cam.position.tolist(), "forward": cam.forward.tolist(), "up": cam.up.tolist(),
                    "fov_y_deg": cam.fov_y_deg, "near": cam.near, "far": cam.far}
        outs = three_page.render_modules(browser, modules, scene_geometry(entry, sun), cam_json, sun, "lambert",
                                         tuple(screen))
    gt = evaluate_buffers(entry.rays, cam, light, mod.fit(cam, light, configs[1][1]), screen=tuple(screen),
                          pancake=False, depth="solution")  # the exact visibility of the screen (maps: any)
    rows = []
    for (name, s, p), out in zip(configs, outs):
        z3, zr = out["depth"].astype(np.float64), gt.screen.depth
        with np.errstate(invalid="ignore"):
            same = (z3 > 0) & gt.screen.hit & (np.abs(z3 - zr) <= DEPTH_TOLERANCE * zr)
        keep = gt.receivers & same
        wrong = keep & ((out["alpha"] > 127) != gt.exact_shadowed)
        rows.append({"setting": name, "settings": s, "predicted": float(p["misclassified_pixels"]),
                     "engine": int(wrong.sum()), "engine_wrongly_lit": int((wrong & gt.exact_shadowed).sum()),
                     "compared": int(keep.sum()), "receivers": int(gt.receivers.sum()), "tune_ms": tune_ms})
        if log:
            log(f"  {name}: {engine} {rows[-1]['engine']} predicted {rows[-1]['predicted']:.0f}")
    return rows


def within(pred: float, meas: float) -> bool:
    return meas <= 1.3 * pred + SLACK and pred <= 1.3 * meas + SLACK


def scene_summary(per_sun: list[list[dict]]) -> dict:
    def total(name):
        return sum(next(r["engine"] for r in rows if r["setting"] == name) for rows in per_sun)

    grid_names = [r["setting"] for r in per_sun[0] if r["setting"].startswith("grid")]
    best_grid = min(grid_names, key=total)
    rhos, ratios, ok, n = [], [], 0, 0
    for rows in per_sun:
        pred = np.array([r["predicted"] for r in rows])
        meas = np.array([r["engine"] for r in rows], float)
        if len(set(pred)) > 1 and len(set(meas)) > 1:
            rhos.append(float(spearmanr(pred, meas).statistic))
        for r in rows:
            ok += within(r["predicted"], r["engine"])
            n += 1
            if r["engine"] >= 20:
                ratios.append(r["engine"] / max(r["predicted"], 1e-9))
    t, d, g = total("tune"), total("defaults"), total(best_grid)
    return {"tune": t, "defaults": d, "best_grid": g, "best_grid_setting": best_grid,
            "tune_over_defaults": t / max(d, 1), "tune_over_best_grid": t / max(g, 1),
            "within": ok / max(n, 1), "median_ratio": statistics.median(ratios) if ratios else float("nan"),
            "spearman": statistics.median(rhos) if rhos else float("nan"),
            "tune_ms": statistics.median(rows[0]["tune_ms"] for rows in per_sun), "suns": len(per_sun)}


def table(per_scene: dict, engine: str = "three") -> str:
    name, short = ENGINE_NAMES[engine], {"three": "three", "babylon": "Babylon"}[engine]
    lines = [f"| scene | suns | tune ({name}) | defaults | best of {len(GRIDS[engine])} grid settings | tune / defaults | "
             f"tune / best grid | emulation within 1.3x+50 | median {short}/predicted | Spearman (median over suns) | "
             "tune ms per pose |", "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for name, s in per_scene.items():
        lines.append(f"| {name} | {s['suns']} | {s['tune']} | {s['defaults']} | {s['best_grid']} "
                     f"({s['best_grid_setting'].removeprefix('grid ')}) | {s['tune_over_defaults']:.3f} | "
                     f"{s['tune_over_best_grid']:.2f} | {100 * s['within']:.0f}% | {s['median_ratio']:.2f} | "
                     f"{s['spearman']:.2f} | {s['tune_ms']:.0f} |")
    return "\n".join(lines)


def bench_engines(validate_rig, lights: int | None = None, scenes: str | None = None, screen=None,
                  write: bool = True, log=None, engine: str = "three", part: str = "all") -> dict:
    """`part`: "tune" (tune in `engine`, this module), "matrix" (the custom-matrix modules in three.js and
    Babylon.js, service/bench/engines_matrix.py) or "all" (both)."""
    n = lights or 6
    screen = tuple(screen or (320, 180))
    names = scenes.split(",") if scenes else list(SCENES)
    found, skipped = corpus_scenes(names)
    dirs = hemisphere_directions(n, 15.0, 26)
    cache = SceneCache()
    result = {}
    if part in ("matrix", "all"):
        cmd = (f"shadowopt bench engines --part matrix --lights {n} --scenes {','.join(found)} "
               f"--screen {screen[0]}x{screen[1]}")
        result["matrix"] = bench_matrix(validate_rig, found, dirs, screen, write, cmd, skipped, cache, log)
        if part == "matrix":
            return result["matrix"]
    per_scene, raw = {}, {}
    with chromium() as browser:
        for name, (path, spec) in found.items():
            entry = cache.get(str(path))
            camera = next(iter(spec["rigs"].values()))["camera"]
            per_sun = []
            for i, d in enumerate(dirs):
                if log:
                    log(f"{name} sun {i}: {[round(float(v), 3) for v in d]}")
                per_sun.append(measure_sun(browser, validate_rig, entry, camera, d, screen, log, engine))
            per_scene[name] = scene_summary(per_sun)
            raw[name] = per_sun
    out = ROOT / "out" / "bench"
    out.mkdir(parents=True, exist_ok=True)
    section = "engines" if engine == "three" else f"engines-{engine}"
    (out / f"{section}.json").write_text(json.dumps({"per_scene": per_scene, "rows": raw}, indent=1, default=str))
    text = table(per_scene, engine)
    if skipped:
        text += "\n\nSkipped: " + "; ".join(f"{k} ({v})" for k, v in skipped.items())
    if write:
        cmd = (f"shadowopt bench engines{'' if engine == 'three' else ' --engine ' + engine} --part tune --lights {n} "
               f"--scenes {','.join(found)} --screen {screen[0]}x{screen[1]}")
        write_section(section, text + "\n\n" + NOTES[engine], cmd)
    if result:
        text = result["matrix"]["table"] + "\n\n" + text
    return {"per_scene": per_scene, "table": text, **result}


NOTE = ("three.js r187's CSM addon with BasicShadowMap and DoubleSide shadows (what tune's module sets), fade off; "
        "tune searches one pose per sun; the grid: cascades 1-4 x shadowBias (1e-6 = CSM's default, -1e-4, -5e-4, "
        "-2e-3, -1e-2), maxFar the scene's reach and the rig's map size (1024) as the defaults; wrong pixels counted "
        "on the receivers where three.js and the ray caster see the same surface; the emulation's fidelity over "
        "tune, the defaults and the grid (22 settings per sun).")
NOTES = {"three": NOTE, "babylon": (
    "Babylon.js 9.35's CascadedShadowGenerator with FILTER_NONE (what tune's module sets; the defaults keep Babylon's "
    "PCF, which the emulation scores as one nearest texel), cascadeBlendPercentage 0, both faces in the shadow pass; "
    "tune searches one pose per sun; the grid: numCascades 2-4 x bias (5e-5 = Babylon's default, 5e-4, 2e-3, 5e-3, "
    "1e-2, 3e-2) with FILTER_NONE, shadowMaxZ the scene's reach and the rig's map size (1024) as the defaults; wrong "
    "pixels counted on the receivers where Babylon.js and the ray caster see the same surface; the emulation's "
    "fidelity over tune, the defaults and the grid (20 settings per sun).")}
