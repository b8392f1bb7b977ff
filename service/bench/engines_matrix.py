"""`shadowopt bench engines` (part matrix): the custom-matrix modules (`optimize --emit` for output.engine three and
babylon) in the real engines against what the engines' users get without them (issue 26's first targets).

On corpus scenes (configs/corpus.json, their first rig's camera at a small screen) with N seeded suns each, per sun
and engine (three.js r187, Babylon.js 9.35 in Chromium: service/bench/three_page.py, babylon_page.py):
- custom: `optimize` (method optimized, one map of MAP texels, the rig's output.engine) and its emitted module
  (service/emit.py) rendered verbatim; `evaluate`'s count for the same solution and screen on the same pixels
  (target: the engine's count <= 1.25 x evaluate's + 50);
- plain: the engine's single shadow map of the same size fitted by hand to a tight box around the scene, the best of
  3 biases x front/double-sided (service/bench/engine_baselines.py; target: custom <= 0.5 x its best);
- cascades: the engine's own cascades with their defaults, the shadow distance the camera's distance to the scene's
  farthest point capped by its far plane (service.tune_score.scene_far), maps of MAP texels (target: custom <= it).
Every render is scored against exact ray-traced visibility of the same screen on the receivers where the engine and
the ray caster see the same surface (service/bench/screen_score.py); three.js classifies through a white Lambert
material drawn with and without shadows ("shadowed": the ratio under one half), Babylon.js through a white
StandardMaterial the same way. Raw rows: out/bench/engines-matrix.json.
"""
from __future__ import annotations

import json

import numpy as np

from ...renderers.ground_truth import evaluate_buffers
from ...solvers.engine_fits import engine_module
from ..emit import module as emitted_module
from ..emit_tune_three import tune_module
from ..request import SolveRequest
from ..rigs import resolve_rig
from ..solution_json import maps_from_solution
from ..solve import solve
from ..tune_score import scene_far
from . import babylon_page, three_page
from .engine_baselines import (babylon_cascades_module, babylon_plain_module, grid, light_box,
                               three_plain_module)
from .definitions import ROOT
from .output import write_section
from .screen_score import score_screen

ENGINES = ("three", "babylon")
MAP = 1024
SLACK = 50  # pixels: "within 1.25x + 50"


def _three_cascades(cam, sun, size: int, reach: float) -> str:
    """three.js's CSM addon with its defaults (maxFar = reach, the map size) through tune's module writer."""
    mod = engine_module("three")
    s = mod.validate({"maxFar": reach, "shadowMapSize": size})
    return tune_module({"engine": mod.ENGINE, "engine_version": mod.VERSION, "settings": s,
                        "light_direction": [float(v) for v in sun], "predicted": dict.fromkeys(("misclassified_pixels", "wrongly_lit", "wrongly_shadowed"), 0),  # not predicted here
                        "emulated": {"shadow_map_type": mod.SHADOW_MAP_TYPE}})


def measure_engine(browser, validate_rig, entry, engine: str, camera: dict, direction, screen, log=None) -> dict:
    """One scene, sun and engine: the custom module's, evaluate's, each plain setting's and the cascades' counts."""
    rig = validate_rig({"camera": {**camera, "resolution": list(screen)},
                        "lights": [{"type": "directional", "direction": [float(v) for v in direction]}],
                        "shadow": {"resolution": [MAP, MAP], "cascades": 1}, "output": {"engine": engine}})
    sol = solve(entry, rig, SolveRequest(method="optimized"))
    resolved = resolve_rig(rig, entry.loaded)
    cam, light = resolved.camera, resolved.lights[0]
    gt = evaluate_buffers(entry.rays, cam, light, maps_from_solution(sol)[0], screen=tuple(screen), depth="solution")
    sun = sol["resolved"]["lights"][0]["direction"]
    cam_json = sol["resolved"]["camera"]
    lo, hi = entry.loaded.geometry.bounds()
    reach = scene_far(lo, hi, cam)
    corners, extents = light_box(entry.loaded.geometry.vertices, sun)
    settings = grid(extents, MAP)
    if engine == "three":
        modules = [emitted_module(sol)] + [three_plain_module(corners, MAP, s) for s in settings]
        modules.append(_three_cascades(cam, sun, MAP, reach))
        outs = three_page.render_modules(browser, modules, three_page.scene_geometry(entry, sun), cam_json, sun,
                                         "lambert", tuple(screen))
    else:
        mirrored = np.asarray(corners) * np.asarray(babylon_page.TO_BABYLON)
        modules = [emitted_module(sol)] + [babylon_plain_module(mirrored, MAP, s) for s in settings]
        modules.append(babylon_cascades_module(MAP, reach))
        outs = babylon_page.render_modules(browser, modules, babylon_page.scene_geometry(entry, sun),
                                           babylon_page.camera_json(cam), babylon_page.to_babylon(sun),
                                           tuple(screen))
    scores = [score_screen(gt, o) for o in outs]
    custom, plain, cascades = scores[0], scores[1:-1], scores[-1]
    best = min(range(len(plain)), key=lambda k: plain[k]["engine_wrong"])
    row = {"engine": engine, "custom": custom["engine_wrong"], "custom_wrongly_lit": custom["engine_wrongly_lit"],
           "evaluate": custom["evaluate_wrong_compared"], "evaluate_screen": custom["evaluate_wrong"],
           "compared": custom["compared"], "receivers": custom["receivers"],
           "plain": [{**s, "wrong": p["engine_wrong"], "wrongly_lit": p["engine_wrongly_lit"]}
                     for s, p in zip(settings, plain)],
           "plain_best": plain[best]["engine_wrong"], "plain_best_setting": settings[best],
           "cascades": cascades["engine_wrong"], "cascades_wrongly_lit": cascades["engine_wrongly_lit"],
           "shadow_distance": reach, "box_extents": [float(v) for v in extents],
           "method": sol.get("method"), "depth": sol["lights"][0]["cascades"][0]["depth"]["mode"]}
    if log:
        log(f"  {engine}: custom {row['custom']} (evaluate {row['evaluate']}), plain best {row['plain_best']} "
            f"({settings[best]['bias_texels']:g} texels, {settings[best]['side']}; all "
            f"{[p['engine_wrong'] for p in plain]}), cascades {row['cascades']}")
    return row


def scene_summary(rows: list[dict]) -> dict:
    """Per engine, sums over suns and the targets' ratios."""
    out = {}
    for engine in ENGINES:
        r = [x for x in rows if x["engine"] == engine]
        if not r:
            continue
        c, e, p, k = (sum(x[key] for x in r) for key in ("custom", "evaluate", "plain_best", "cascades"))
        out[engine] = {"suns": len(r), "custom": c, "evaluate": e, "plain_best": p, "cascades": k,
                       "custom_over_evaluate": c / max(e, 1), "custom_over_plain": c / max(p, 1),
                       "custom_over_cascades": c / max(k, 1),
                       "suns_within_evaluate": sum(x["custom"] <= 1.25 * x["evaluate"] + SLACK for x in r),
                       "suns_half_plain": sum(x["custom"] <= 0.5 * x["plain_best"] for x in r),
                       "suns_under_cascades": sum(x["custom"] <= x["cascades"] for x in r)}
    return out


NAMES = {"three": "three.js r187", "babylon": "Babylon.js 9.35"}


def table(per_scene: dict) -> str:
    lines = ["| scene | engine | suns | custom module (engine) | evaluate (same pixels) | custom / evaluate "
             "| suns within 1.25x+50 | plain single map, best of 6 | custom / plain | suns <= 0.5x plain "
             "| engine's cascades, defaults | custom / cascades | suns <= cascades |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for name, per_engine in per_scene.items():
        for engine, s in per_engine.items():
            n = s["suns"]
            lines.append(f"| {name} | {NAMES[engine]} | {n} | {s['custom']} | {s['evaluate']} | "
                         f"{s['custom_over_evaluate']:.2f} | {s['suns_within_evaluate']}/{n} | {s['plain_best']} | "
                         f"{s['custom_over_plain']:.3f} | {s['suns_half_plain']}/{n} | {s['cascades']} | "
                         f"{s['custom_over_cascades']:.3f} | {s['suns_under_cascades']}/{n} |")
    return "\n".join(lines)


def bench_matrix(validate_rig, found: dict, dirs, screen, write: bool, cmd: str, skipped: dict, cache, log=None) -> dict:
    """The part's rows over `found` scenes (definitions.corpus_scenes) and sun directions; writes its section."""
    per_scene, raw = {}, {}
    with three_page.chromium() as browser:
        for name, (path, spec) in found.items():
            entry = cache.get(str(path))
            camera = next(iter(spec["rigs"].values()))["camera"]
            rows = []
            for i, d in enumerate(dirs):
                if log:
                    log(f"{name} sun {i}: {[round(float(v), 3) for v in d]}")
                for engine in ENGINES:
                    rows.append({"sun": i, **measure_engine(browser, validate_rig, entry, engine, camera, d, screen,
                                                            log)})
            per_scene[name] = scene_summary(rows)
            raw[name] = rows
            out = ROOT / "out" / "bench"
            out.mkdir(parents=True, exist_ok=True)
            (out / "engines-matrix.json").write_text(json.dumps({"per_scene": per_scene, "rows": raw}, indent=1,
                                                                default=str))
    text = table(per_scene)
    if skipped:
        text += "\n\nSkipped: " + "; ".join(f"{k} ({v})" for k, v in skipped.items())
    if write:
        write_section("engines-matrix", text + "\n\n" + NOTE, cmd)
    return {"per_scene": per_scene, "table": text}


NOTE = ("Wrong pixels summed over the suns (320x180 screens, maps of 1024 texels), on the receivers where the engine "
        "and the ray caster see the same surface. Custom module: `optimize` (method optimized, one map, the rig's "
        "output.engine) and its `--emit` module run verbatim; evaluate: `evaluate --depth solution`'s count for the "
        "same solution on the same pixels. Plain single map: the engine's own directional shadow with an orthographic "
        "camera on a tight box around the scene (service/bench/engine_baselines.py), nearest-texel lookups, the best "
        "per sun of 3 constant biases (0.5, 1.5, 4.5 texels of depth) x front-only / both faces in the light pass. Engine's "
        "cascades: three.js's CSM addon (BasicShadowMap, both faces, as tune's module sets them) and Babylon.js's "
        "CascadedShadowGenerator (4 cascades, PCF), each with its defaults, the shadow distance the camera's distance "
        "to the scene's farthest point capped by its far plane, blending off. Targets (issue 26): custom <= 1.25 x "
        "evaluate + 50, <= 0.5 x plain, <= cascades.")
