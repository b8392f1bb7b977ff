"""`shadowopt tune`'s search over the knobs an engine's users set (service.tune), scored by service.tune_score.

One search for every engine, its knobs named by the engine's EngineSearch (SEARCHES below). Each candidate is
scored at every pose with the bias constant found exactly (tune_score.best_constant: one value for every cascade,
converted to the engine's bias knob by EngineSearch.bias_value):
1. the split: cascade counts (the engine's default first, for a search the budget cuts short) x the shadow distance
   (1, 1/2, 1/4 of the scene's reach, the camera's distance to the farthest point of the scene capped by its far
   plane), each with the map size the budget allows (the defaults' total texels: the engine's default cascade count
   x the rig's resolution squared, shared by the candidate's cascades, a multiple of 16, at most MAX_SIZE), plus the
   engine's own per-candidate knobs (EngineSearch.complete);
2. the KEEP best so far x each variant of the engine's other split knobs (EngineSearch.variants);
3. the KEEP best so far x the normal bias at 0.5, 1 and 2 of the first cascade's texel side (where it is modelled).
three.js (CSM addon): cascades 3, 4, 2, 1 x maxFar; lightMargin the scene's diagonal (every caster of a receiver lies
within it towards the light) and lightFar the deepest slice's reach (three_csm.light_depth_reach) so no receiver falls
past the map's far plane; lightNear 1 (the default); variants: mode uniform, logarithmic; shadowNormalBias. About 22
candidates, ~50 ms each for the demo's pose (the depth probe's texel rays dominate).
Babylon.js (CascadedShadowGenerator): numCascades 4, 3, 2 x shadowMaxZ, filter NONE (nearest texel, the test scored),
cascadeBlendPercentage 0 (the emitted module's); variants: lambda 0.25, 0.75, 1, stabilizeCascades, no depthClamp;
normalBias is not modelled (0). About 19 candidates.
A time budget (service.tune: SEARCH_BUDGET_S per pose) stops the search early; the answer's `search.complete` says
whether every planned candidate was scored. Knobs the caller pins keep their value throughout. The chosen
candidate's prediction is cross-fitted (bias_fit.cross_fitted), as the solve's fitted constant is; the defaults'
is their own bias's, no fit.
"""
from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field
from typing import Callable

from .tune_score import best_constant, predict, probe_pose

MAX_SIZE = 8192  # a map side WebGL 2 renderers take everywhere (MAX_TEXTURE_SIZE >= 8192 on desktop GPUs)
FAR_FRACTIONS = (1.0, 0.5, 0.25)
NORMAL_TEXELS = (0.0, 0.5, 1.0, 2.0)
KEEP = 2


@dataclass(frozen=True)
class EngineSearch:
    """One engine's knobs as the search moves them (engine_fits: the module's KNOBS names).
    count / far / size / bias / normal: the knobs of the cascade count, the shadow distance, the map side, the bias
    and the normal bias (None: not modelled); counts: stage 1's counts, the engine's default first; base: knobs every
    candidate sets (not the defaults'); variants: (knob, values) tried on the KEEP best in stage 2;
    constant(mod, s) / bias_value(mod, s, c) / constant_range(mod, s): the product's receiver constant of a setting,
    the bias knob's value for a constant, and the constants the knob's domain reaches; complete(mod, s, poses, fixed):
    the engine's own per-candidate knobs (three's light depth range)."""

    count: str
    far: str
    size: str
    bias: str
    normal: str | None
    counts: tuple
    constant: Callable
    bias_value: Callable
    constant_range: Callable
    base: dict = field(default_factory=dict)
    variants: tuple = ()
    complete: Callable = lambda mod, s, poses, fixed, diag: s


def _three_complete(mod, s: dict, poses, fixed: dict, diag: float) -> dict:
    s = {**s, "lightMargin": diag, **{k: v for k, v in fixed.items() if k == "lightMargin"}}
    if "lightFar" not in fixed:  # the deepest slice's reach (three_csm.light_depth_reach), so no receiver is lost
        need = max(mod.light_depth_reach(p.camera, p.light, {**s, "lightFar": 1e7}) for p in poses)
        s["lightFar"] = float(min(mod.KNOBS["lightFar"].domain[1], math.ceil(need * 1.02 + s["lightNear"])))
    return s


def _three_bias_value(mod, s: dict, c: float) -> float:
    return -c if c != 0 else mod.KNOBS["shadowBias"].default  # CSM reads shadowBias with `||`: 0 is its default


THREE = EngineSearch(
    count="cascades", far="maxFar", size="shadowMapSize", bias="shadowBias", normal="shadowNormalBias",
    counts=(3, 4, 2, 1), base={"mode": "practical"},
    variants=(("mode", ("uniform", "logarithmic")),),
    constant=lambda mod, s: -mod.effective(s)["shadowBias"],  # shadowBias is added to the receiver's depth
    bias_value=_three_bias_value,
    constant_range=lambda mod, s: (-mod.KNOBS["shadowBias"].domain[1], -mod.KNOBS["shadowBias"].domain[0]),
    complete=_three_complete)

BABYLON = EngineSearch(
    count="numCascades", far="shadowMaxZ", size="mapSize", bias="bias", normal=None,
    counts=(4, 3, 2), base={"filter": "NONE"},
    variants=(("lambda", (0.25, 0.75, 1.0)), ("stabilizeCascades", (True,)), ("depthClamp", (False,))),
    constant=lambda mod, s: float(s["bias"]) * mod.bias_factor(s),  # babylon.py step 6: bias x 1, 1.5 or 0.5
    bias_value=lambda mod, s, c: float(c) / mod.bias_factor(s),
    constant_range=lambda mod, s: tuple(v * mod.bias_factor(s) for v in mod.KNOBS["bias"].domain))

SEARCHES = {"three": THREE, "babylon": BABYLON}
SEARCH_ENGINES = tuple(SEARCHES)  # the engines whose knobs this module searches


def rig_size(poses) -> int:
    """The solution's map side: the rig's shadow.resolution (its larger side) or sqrt(texel_budget)."""
    shadow = poses[0].shadow
    if shadow.get("resolution"):
        return int(max(shadow["resolution"]))
    return int(math.isqrt(int(shadow.get("texel_budget") or 2048 * 2048)))


def budget_size(cascades: int, budget: int) -> int:
    return int(max(16, min(MAX_SIZE, (math.isqrt(budget // cascades) // 16) * 16)))


def default_count(mod, spec: EngineSearch) -> int:
    """The cascades the engine's defaults draw (Babylon clamps numCascades: mod.effective)."""
    return int(mod.effective(mod.validate({}))[spec.count])


def defaults(mod, poses, size: int) -> dict:
    """The engine's defaults with the shadow distance = the scene's reach and the solution's map size (issue 26)."""
    spec = SEARCHES[mod.ENGINE]
    reach = max(p.scene_far for p in poses)
    return mod.validate({spec.far: reach, spec.size: size})


def score(mod, poses, settings: dict, fixed: dict) -> tuple[float, float, list]:
    """(in-sample wrong pixels, constant, probes) of a candidate: its bias fitted unless pinned."""
    spec = SEARCHES[mod.ENGINE]
    probes = [probe_pose(mod, p, settings)[1] for p in poses]
    if spec.bias in fixed:
        c = spec.constant(mod, settings)
        wrong = predict(mod, probes, poses, c, False)["misclassified_pixels"]
    else:
        lo, hi = spec.constant_range(mod, settings)
        c, wrong = best_constant(mod, probes, poses, lo, hi)
    return wrong, c, probes


def search(mod, poses, fixed: dict, budget_s: float | None = None) -> dict:
    """The best candidate (module doc) and the defaults' prediction. `budget_s`: the search stops taking new
    candidates once it has run this long (at least one is scored); the answer says how many it scored."""
    t0 = time.perf_counter()
    if mod.ENGINE not in SEARCHES:  # service.tune refuses these first
        raise ValueError(f"engine: no search for {mod.ENGINE!r}")
    spec = SEARCHES[mod.ENGINE]
    size0 = rig_size(poses)
    budget = default_count(mod, spec) * size0 * size0
    reach = max(p.scene_far for p in poses)
    diag = max(max(p.scene_diagonal for p in poses), 1.0)
    base = defaults(mod, poses, size0)
    d_probes = [probe_pose(mod, p, base)[1] for p in poses]  # the engine's defaults: the caller's pins left out
    d_pred = predict(mod, d_probes, poses, spec.constant(mod, base), False)

    def candidate(**knobs) -> dict:
        s = {**base, **spec.base, **knobs, **fixed}
        if spec.size not in fixed:  # the budget shared by the cascades the candidate has (pinned or not)
            s[spec.size] = budget_size(int(mod.effective(mod.validate(s))[spec.count]), budget)
        return mod.validate(spec.complete(mod, s, poses, fixed, diag))

    tried, seen, planned = [], set(), []

    def run(s: dict) -> None:
        key = json.dumps(s, sort_keys=True)
        planned.append(key)
        if key in seen or (tried and budget_s is not None and time.perf_counter() - t0 > budget_s):
            return
        seen.add(key)
        wrong, c, probes = score(mod, poses, s, fixed)
        tried.append((wrong, c, s, probes))

    def best(k: int = KEEP) -> list[dict]:
        return [s for _, _, s, _ in sorted(tried, key=lambda t: t[0])[:k]]

    for n in spec.counts:  # the engine's own count first, for a search the budget cuts short
        for frac in FAR_FRACTIONS:
            run(candidate(**{spec.count: n, spec.far: max(reach * frac, 0.02)}))
    for knob, values in spec.variants:
        if knob not in fixed:
            for s in best():
                for v in values:
                    run(mod.validate({**s, knob: v}))
    if spec.normal is not None and spec.normal not in fixed:
        for s in best():
            first = mod.fit(poses[0].camera, poses[0].light, s, casters_box=poses[0].scene_box)[0]
            tau = 2.0 / (first.projection[0, 0] * first.resolution[0])  # the first cascade's texel side, metres
            for k in NORMAL_TEXELS[1:]:
                run(mod.validate({**s, spec.normal: float(k * tau)}))
    wrong, c, chosen, probes = min(tried, key=lambda t: t[0])
    if spec.bias not in fixed:  # the bias changes no map: the candidate's probes serve
        chosen = mod.validate({**chosen, spec.bias: spec.bias_value(mod, chosen, c)})
    pred = predict(mod, probes, poses, spec.constant(mod, chosen), spec.bias not in fixed)
    return {"settings": chosen, "predicted": pred, "candidates": len(tried),
            "complete": len(seen) == len(set(planned)),
            "defaults": {"settings": base, "predicted": d_pred}}
