"""`shadowopt tune`'s search over the knobs an engine's users set (service.tune), scored by service.tune_score.

three.js (CSM addon): two stages, each candidate scored at every pose with the bias constant found exactly
(tune_score.best_constant: shadowBias = -c, one for every cascade):
1. the split: cascades 1-4 x maxFar (1, 1/2, 1/4 of the scene's reach,
   the camera's distance to the farthest point of the scene capped by its far plane), each with the map size the
   budget allows (the defaults' total texels: 3 maps of the rig's resolution, so cascades x size^2 <= 3 x rig^2,
   a multiple of 16, at most MAX_SIZE), lightMargin the scene's diagonal (every caster of a receiver lies within it
   towards the light) and lightFar the deepest slice's reach (three_csm.light_depth_reach) so no receiver falls
   past the map's far plane; lightNear 1 (the default); mode practical;
2. the KEEP best so far x the other modes (uniform, logarithmic);
3. the KEEP best so far x shadowNormalBias (0.5, 1, 2 of the first cascade's texel side).
About 22 candidates, ~50 ms each on this project's machine for the demo's pose (the depth probe's texel rays
dominate, more with more receivers and texels); a time budget (service.tune: SEARCH_BUDGET_S per pose) stops
the search early, stage 1 ordered by cascade count (3, CSM's default, then 4, 2, 1); the answer's `search.complete` says whether
every planned candidate was scored.
Knobs the caller pins keep their value throughout. The chosen candidate's prediction is cross-fitted
(bias_fit.cross_fitted), as the solve's fitted constant is; the defaults' is their own bias's, no fit.
"""
from __future__ import annotations

import json
import math
import time

from .tune_score import best_constant, predict, probe_pose

MAX_SIZE = 8192  # a map side WebGL 2 renderers take everywhere (MAX_TEXTURE_SIZE >= 8192 on desktop GPUs)
STAGE1_CASCADES = (3, 4, 2, 1)
MODES = ("practical", "uniform", "logarithmic")
FAR_FRACTIONS = (1.0, 0.5, 0.25)
NORMAL_TEXELS = (0.0, 0.5, 1.0, 2.0)
KEEP = 2


def rig_size(poses) -> int:
    """The solution's map side: the rig's shadow.resolution (its larger side) or sqrt(texel_budget)."""
    shadow = poses[0].shadow
    if shadow.get("resolution"):
        return int(max(shadow["resolution"]))
    return int(math.isqrt(int(shadow.get("texel_budget") or 2048 * 2048)))


def budget_size(cascades: int, budget: int) -> int:
    return int(max(16, min(MAX_SIZE, (math.isqrt(budget // cascades) // 16) * 16)))


def defaults(mod, poses, size: int) -> dict:
    """The engine's defaults with maxFar = the scene's reach and the solution's map size (issue 26)."""
    reach = max(p.scene_far for p in poses)
    return mod.validate({"maxFar": reach, "shadowMapSize": size})


def score(mod, poses, settings: dict, fixed: dict) -> tuple[float, float, list]:
    """(in-sample wrong pixels, constant, probes) of a candidate: its bias fitted unless pinned."""
    probes = [probe_pose(mod, p, settings)[1] for p in poses]
    lo, hi = mod.KNOBS["shadowBias"].domain
    if "shadowBias" in fixed:
        c = -mod.effective(settings)["shadowBias"]
        wrong = predict(mod, probes, poses, c, False)["misclassified_pixels"]
    else:
        c, wrong = best_constant(mod, probes, poses, -hi, -lo)
    return wrong, c, probes


SEARCH_ENGINES = ("three",)  # the engines whose knobs this module searches (solvers.engine_fits has more emulations)


def search(mod, poses, fixed: dict, budget_s: float | None = None) -> dict:
    """The best candidate (module doc) and the defaults' prediction. `budget_s`: the search stops taking new
    candidates once it has run this long (at least one is scored); the answer says how many it scored."""
    t0 = time.perf_counter()
    if mod.ENGINE not in SEARCH_ENGINES:  # service.tune refuses these first
        raise ValueError(f"engine: no search for {mod.ENGINE!r}")
    size0 = rig_size(poses)
    budget = 3 * size0 * size0
    reach = max(p.scene_far for p in poses)
    diag = max(max(p.scene_diagonal for p in poses), 1.0)
    base = defaults(mod, poses, size0)
    d_probes = [probe_pose(mod, p, base) for p in poses]  # the engine's defaults: the caller's pins left out
    d_settings = base
    d_pred = predict(mod, [pr for _, pr in d_probes], poses, -mod.effective(d_settings)["shadowBias"], False)

    def candidate(**knobs) -> dict:
        s = {**base, "lightMargin": diag, **knobs}
        s = {**s, **fixed}
        if "shadowMapSize" not in fixed:  # the budget shared by the cascades the candidate has (pinned or not)
            s["shadowMapSize"] = budget_size(s["cascades"], budget)
        if "lightFar" not in fixed:
            need = max(mod.light_depth_reach(p.camera, p.light, {**s, "lightFar": 1e7}) for p in poses)
            s["lightFar"] = float(min(mod.KNOBS["lightFar"].domain[1], math.ceil(need * 1.02 + s["lightNear"])))
        return mod.validate(s)

    tried, seen, planned = [], set(), []

    def run(s: dict) -> None:
        key = json.dumps(s, sort_keys=True)
        planned.append(key)
        if key in seen or (tried and budget_s is not None and time.perf_counter() - t0 > budget_s):
            return
        seen.add(key)
        wrong, c, probes = score(mod, poses, s, fixed)
        tried.append((wrong, c, s, probes))

    for n in STAGE1_CASCADES:  # CSM's own count first, for a search the budget cuts short
        for frac in FAR_FRACTIONS:
            run(candidate(cascades=n, mode=MODES[0], maxFar=max(reach * frac, 0.02)))
    if "mode" not in fixed:
        for _, _, s, _ in sorted(tried, key=lambda t: t[0])[:KEEP]:
            for mode in MODES[1:]:
                run(mod.validate({**s, "mode": mode}))
    if "shadowNormalBias" not in fixed:
        for _, _, s, _ in sorted(tried, key=lambda t: t[0])[:KEEP]:
            first = mod.fit(poses[0].camera, poses[0].light, s)[0]
            tau = 2.0 / (first.projection[0, 0] * first.resolution[0])  # the first cascade's texel side, metres
            for k in NORMAL_TEXELS[1:]:
                run(mod.validate({**s, "shadowNormalBias": float(k * tau)}))
    wrong, c, best, probes = min(tried, key=lambda t: t[0])
    if "shadowBias" not in fixed:  # the bias changes no map: the candidate's probes serve
        best = mod.validate({**best, "shadowBias": -c if c != 0 else mod.KNOBS["shadowBias"].default})
    pred = predict(mod, probes, poses, -mod.effective(best)["shadowBias"], "shadowBias" not in fixed)
    return {"settings": best, "predicted": pred, "candidates": len(tried),
            "complete": len(seen) == len(set(planned)),
            "defaults": {"settings": d_settings, "predicted": d_pred}}
