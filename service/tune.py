"""`shadowopt tune`: the settings of an engine's own cascades that predict the fewest wrong pixels (issue 26, part 2).

An engine user who does not install a custom matrix sets the engine's knobs by hand. Tune emulates the engine's
own fit from those knobs (solvers.engine_fits: one module per engine) and scores each candidate by the product's one
metric, exactly as a solve's prediction does (service.bias): the engine's depth test (renderers.depth_probe) at the
coarse pass's light-facing receivers (service.bias.receivers_of), each standing for its share of the rig's
full-resolution pixels, wrong answers counted by solvers.bias_fit.probe_wrong. The bias constant is found exactly
by solvers.bias_fit.fit_constant over one value for every cascade (three's CSM sets one shadowBias for all its
lights, Babylon's CascadedShadowGenerator one bias) and scored cross-fitted (bias_fit.cross_fitted), as the solve's fitted constant is. One setting serves every pose (a
setting holds for a whole level): the score is the sum over the poses. The search itself: service.tune_search.
"""
from __future__ import annotations

import time

from ..solvers.engine_fits import engine_module
from .interpolation import camera_path as path_cameras
from .interpolation import sun_arc as arc_directions
from .request_fields import BatchError
from .tune_score import Pose, TuneError, cascades_json
from .tune_search import SEARCH_ENGINES, search

MAX_POSES = 16  # cameras x suns scored per request (each ~1-2 s)
SEARCH_BUDGET_S = 1.6  # per pose: the search takes no new candidate past it (the answer within ~2 s per pose)


def pose_rigs(rig: dict, poses: list[dict] | None, camera_path: dict | None = None,
              sun_arc: dict | None = None) -> list[dict]:
    """The rig itself, then one rig per extra pose (its camera replaced): `poses` (camera objects), a
    `camera_path` (poses, or keyframes + samples, over the rig's camera: service.interpolation), each for every
    direction of a `sun_arc` (the rig's light replaced by a directional light) when one is given."""
    cams = [rig["camera"]]
    for k, cam in enumerate(poses or []):
        if not isinstance(cam, dict):
            raise TuneError(f"poses[{k}]", f"expected a camera object like the rig's camera, got {cam!r:.60}")
        cams.append(cam)
    try:
        if camera_path is not None:
            cams += path_cameras(camera_path, rig["camera"])
        suns = arc_directions(sun_arc) if sun_arc is not None else None
    except BatchError as e:
        raise TuneError(e.field, e.message) from None
    lights = [rig["lights"]] if suns is None else [[{"type": "directional", "direction": d}] for d in suns]
    if len(cams) * len(lights) > MAX_POSES:
        raise TuneError("poses", f"tune scores at most {MAX_POSES} poses (cameras x suns) per request (accepted: "
                        f"1-{MAX_POSES}), got {len(cams)} x {len(lights)}")
    return [{**rig, "camera": cam, "lights": ls} for ls in lights for cam in cams]


def tune(entry, rig: dict, engine: str, poses: list[dict] | None = None, fixed: dict | None = None,
         camera_path: dict | None = None, sun_arc: dict | None = None, time_budget_ms: float | None = None) -> dict:
    """The engine's settings that predict the fewest wrong pixels over the rig's pose, `poses` (camera dicts,
    validated like the rig's camera), a `camera_path` and a `sun_arc` (pose_rigs), the engine's defaults beside
    them, and what the engine fits (module doc). `fixed`: knobs the caller pins (validated; the search leaves
    them). `time_budget_ms`: the search's time (default SEARCH_BUDGET_S per pose, less the coarse passes); past
    it no new candidate is scored."""
    try:
        mod = engine_module(engine)
    except ValueError as e:
        raise TuneError("engine", str(e).split(": ", 1)[1]) from None
    if mod.ENGINE not in SEARCH_ENGINES:  # an emulation without a search yet
        raise TuneError("engine", f"{engine!r} has an emulation of its cascade fit but no search yet (accepted: "
                        f"{', '.join(SEARCH_ENGINES)})")
    try:
        fixed_settings = {k: v for k, v in mod.validate(fixed or {}).items() if k in (fixed or {})}
    except ValueError as e:
        field, msg = str(e).split(": ", 1)
        raise TuneError(field, msg) from None
    rigs = pose_rigs(rig, poses, camera_path, sun_arc)
    t0 = time.perf_counter()
    ps = [Pose(entry, r) for r in rigs]
    t1 = time.perf_counter()
    budget = time_budget_ms / 1e3 if time_budget_ms is not None else SEARCH_BUDGET_S * len(ps) - (t1 - t0)
    result = search(mod, ps, fixed_settings, budget)
    t2 = time.perf_counter()
    maps = mod.fit(ps[0].camera, ps[0].light, result["settings"], casters_box=ps[0].scene_box)
    emulated = {"cascades": cascades_json(maps), "shadow_map_type": mod.SHADOW_MAP_TYPE,
                "faces": mod.faces(result["settings"])}
    if len(ps) > 1:
        emulated["poses"] = [{"cascades": cascades_json(mod.fit(p.camera, p.light, result["settings"], casters_box=p.scene_box))} for p in ps]
    direction = [float(v) for v in ps[0].light.direction]
    return {"engine": mod.ENGINE, "engine_version": mod.VERSION, "settings": result["settings"],
            "predicted": result["predicted"], "defaults": result["defaults"], "emulated": emulated,
            "light_direction": direction, "poses": len(ps),
            "search": {"candidates": result["candidates"], "complete": result["complete"],
                       "budget_ms": budget * 1e3},
            "snippet": snippet(mod, result["settings"], direction),
            "timings_ms": {"coarse": (t1 - t0) * 1e3, "search": (t2 - t1) * 1e3, "total": (t2 - t0) * 1e3,
                           "per_pose": (t2 - t0) * 1e3 / len(ps)}}


def snippet(mod, settings: dict, direction: list[float]) -> str:
    """A few lines of JS that set the engine's knobs (three.js: a CSM instance; Babylon.js: a
    CascadedShadowGenerator)."""
    s = settings
    if mod.ENGINE == "babylon":
        return "\n".join([
            "import { CascadedShadowGenerator, ShadowGenerator } from '@babylonjs/core';",
            f"const csm = new CascadedShadowGenerator({s['mapSize']}, light, undefined, camera);",
            f"csm.numCascades = {s['numCascades']}; csm.lambda = {s['lambda']:.6g}; "
            f"csm.stabilizeCascades = {str(s['stabilizeCascades']).lower()}; "
            f"csm.depthClamp = {str(s['depthClamp']).lower()}; csm.cascadeBlendPercentage = 0;",
            f"csm.shadowMaxZ = {s['shadowMaxZ']:.6g}; csm.filter = ShadowGenerator.FILTER_{s['filter']}; "
            f"csm.bias = {s['bias']:.6g}; csm.normalBias = {s['normalBias']:.6g};",
            "for (const m of meshes) { csm.addShadowCaster(m); m.receiveShadows = true; "
            "if (m.material) m.material.backFaceCulling = false; }",
        ])
    if mod.ENGINE != "three":  # pragma: no cover - two engines so far
        return ""
    d = ", ".join(f"{v:.6g}" for v in direction)
    return "\n".join([
        "import { CSM } from 'three/addons/csm/CSM.js';",
        "renderer.shadowMap.enabled = true; renderer.shadowMap.type = THREE.BasicShadowMap;",
        f"const csm = new CSM({{ camera, parent: scene, cascades: {s['cascades']}, mode: '{s['mode']}', "
        f"maxFar: {s['maxFar']:.6g}, shadowMapSize: {s['shadowMapSize']}, shadowBias: {s['shadowBias']:.6g}, "
        f"lightNear: {s['lightNear']:.6g}, lightFar: {s['lightFar']:.6g}, lightMargin: {s['lightMargin']:.6g}, "
        f"lightDirection: new THREE.Vector3({d}) }});",
        f"csm.fade = false; csm.lights.forEach((l) => {{ l.shadow.normalBias = {s['shadowNormalBias']:.6g}; }});",
        "scene.traverse((o) => { if (!o.isMesh) return; o.castShadow = o.receiveShadow = true;",
        f"  o.material.shadowSide = THREE.{s['shadowSide']}; csm.setupMaterial(o.material); }});",
        "// each frame, before renderer.render(scene, camera): csm.update();",
    ])
