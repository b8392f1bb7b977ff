"""How many texels and cascades each light's maps get: the rig's texel budget split across its lights by need
(budget_scope "rig"), the cascade count of `cascades: "auto"`, and a smaller resolution that still meets
target_p95_m. Each scores maps with the one metric (service.solution_json.maps_error).
"""
from __future__ import annotations

import math

from ..renderers.coarse import CoarseBuffers
from ..solvers.baselines import baseline
from ..solvers.depth_modes import with_bias
from ..solvers.metric import map_texels
from ..solvers.shadow_map import ShadowMap
from .need import drop_empty_maps, light_need, split_budget
from .receivers import LightProblem
from .rigs import ResolvedRig
from .solution_json import maps_error


def rig_budget_split(resolved: ResolvedRig, buffers: CoarseBuffers, probs: list[LightProblem], bounds) -> dict:
    """`budget_scope: "rig"`: the rig's texel_budget split across its lights by need (service.need.split_budget).
    Each light with visible receivers is probed with the focused baseline at an equal share (its cascade count,
    1 for auto); its predicted misclassified pixels there set its need. A light with none gets 0 texels."""
    shadow = resolved.shadow
    budget = int(shadow["texel_budget"])
    needs = [light_need(buffers, li) for li in range(len(probs))]
    n = sum(1 for nd in needs if nd.needs_map)
    probe = budget // max(n, 1)
    k = shadow.get("cascades") if isinstance(shadow.get("cascades"), int) else 1
    mis = []
    for prob, nd in zip(probs, needs):
        if not nd.needs_map:
            mis.append(None)
            continue
        maps = baseline("focused", resolved.camera, prob.light, prob.receivers, bounds, cascades=k,
                        splits=shadow.get("splits", "practical") if shadow.get("splits") != "optimized" else "practical",
                        split_lambda=shadow.get("lambda", 0.5), texel_budget=probe, receiver_slack=prob.receiver_slack)
        mis.append(float(maps_error(maps, prob.samples, resolved.camera.position)[0]["misclassified_pixels"]))
    texels = split_budget(budget, mis, probe)
    return {"scope": "rig", "budget": budget, "probe_texels": probe,
            "rule": ("T_i = budget d_i^(2/3) / sum d_j^(2/3), d_i = predicted misclassified pixels at an equal share x "
                     "sqrt(share) (Chong 2003's Lagrange allocation, generalized to lights); 0 for a light with no "
                     "visible receiver"),
            "lights": [{"texels": t, "predicted_misclassified_at_probe": m} for t, m in zip(texels, mis)]}


AUTO_TOLERANCE = 0.05  # cascades "auto": the fewest cascades whose objective x texels is within 5% of the least
# p95_m scales as texels^P95_TEXEL_EXPONENT: m is a texel's footprint in screen pixels, a texel's side is the map's
# extent over its resolution per side (the fit does not depend on it), so m ~ 1/side ~ texels^-1/2 at a fixed
# aspect (Stamminger & Drettakis 2002's texel-to-pixel ratio; checked against two resolutions in tests/test_need.py)
P95_TEXEL_EXPONENT = -0.5
ENGINE_SIZE_STEP = 64  # a smaller resolution is rounded up to a multiple of 64 texels per side


MAX_TEXEL_ESTIMATE = 2.0 ** 53  # beyond this an estimated budget is no budget (a target far below any reachable p95_m)


def texels_for_p95(p95_m: float, texels: int, target: float) -> int | None:
    """The texels at which p95_m (measured with `texels`) would meet `target` (P95_TEXEL_EXPONENT), or None when
    that is not a finite number below MAX_TEXEL_ESTIMATE."""
    try:
        v = texels * (p95_m / target) ** (1.0 / -P95_TEXEL_EXPONENT)
    except (OverflowError, ZeroDivisionError):
        return None
    return int(math.ceil(v)) if math.isfinite(v) and 0 <= v <= MAX_TEXEL_ESTIMATE else None


def auto_cascades(maps_for, prob: LightProblem, origin, shadow: dict, camera=None, drop: bool = True):
    """`cascades: "auto"`: with target_p95_m, the smallest k up to max_cascades whose predicted p95_m meets it;
    otherwise (or when none does) the fewest cascades whose objective x texels (the objective alone under a
    texel budget: every k gets the same texels) is within AUTO_TOLERANCE of the least: fewer draw calls for
    the engine. Cascades with no receivers are dropped (service.need) before k is scored (`drop`, with the
    camera), so a k that returns fewer maps counts as that many. When no k meets the target, says what texel
    budget would (texels_for_p95 from the k with the least p95_m)."""
    target = shadow.get("target_p95_m")
    kmax = int(shadow.get("max_cascades") or 4)
    tried, cands = [], []
    for k in range(1, kmax + 1):
        maps, info = maps_for(k)
        notes = []
        if drop and camera is not None:
            maps, notes = drop_empty_maps(maps, prob.receivers, prob.receiver_slack, camera)
        err, _ = maps_error(maps, prob.samples, origin)
        texels = sum(m.resolution[0] * m.resolution[1] for m in maps)
        tried.append({"cascades": k, "returned": len(maps), "p95_m": err["p95_m"], "objective": err["objective"],
                      "texels": texels})
        if target is not None and err["p95_m"] <= target:
            return maps, info, {"chosen": k, "returned": len(maps), "rule": f"smallest k with p95_m <= {target}",
                                "tried": tried, "notes": notes}
        cands.append((err["objective"] * texels, len(maps), k, maps, info, notes))
    best = min(c[0] for c in cands)
    ok = [c for c in cands if c[0] <= best * (1.0 + AUTO_TOLERANCE)]
    _, n, k, maps, info, notes = min(ok, key=lambda c: (c[1], c[2]))
    rule = f"fewest cascades with objective x texels within {AUTO_TOLERANCE:.0%} of the least"
    out = {"chosen": k, "returned": n, "rule": rule if target is None else f"no k met p95_m <= {target}: {rule}",
           "tolerance": AUTO_TOLERANCE, "tried": tried, "notes": notes}
    if target is not None:
        t = min(tried, key=lambda t: t["p95_m"])
        need = texels_for_p95(t["p95_m"], t["texels"], target)
        out["needed_texel_budget"] = need
        reach = f"about {need:,} texels would" if need is not None else \
            f"no texel budget up to {MAX_TEXEL_ESTIMATE:.3g} would"
        out["budget_estimate"] = (f"{reach} meet p95_m <= {target:g} (now {t['texels']:,}): "
                                  f"k = {t['cascades']} has p95_m {t['p95_m']:.3g}, and p95_m scales as "
                                  f"texels^{P95_TEXEL_EXPONENT:g}")
    return maps, info, out


def smaller_resolution(maps: list[ShadowMap], prob: LightProblem, origin, target: float):
    """Maps that meet p95_m <= `target` with fewer texels than given: every map's sides scaled by
    p95_m / target (P95_TEXEL_EXPONENT), rounded up to a multiple of ENGINE_SIZE_STEP (never above the given
    size), the depth bias refitted to the new texels; the scale is raised until the target is met again.
    Returns (maps, note) with the maps changed in place, or (maps, None) when nothing smaller meets it."""

    err, _ = maps_error(maps, prob.samples, origin)
    p95, before = err["p95_m"], map_texels(maps)
    if not (err["samples"] and 0 < p95 <= target):
        return maps, None
    given = [tuple(m.resolution) for m in maps]
    s = p95 / target
    while s < 1.0:
        sizes = [tuple(min(g, max(ENGINE_SIZE_STEP, ENGINE_SIZE_STEP * math.ceil(g * s / ENGINE_SIZE_STEP)))
                       for g in res) for res in given]
        if sizes == given:
            break
        for m, r in zip(maps, sizes):
            m.resolution = r
            with_bias(m, prob.receivers, prob.light)
        e2, _ = maps_error(maps, prob.samples, origin)
        if e2["p95_m"] <= target:
            after = map_texels(maps)
            return maps, (f"resolution lowered to {', '.join(f'{a}x{b}' for a, b in sizes)} (multiples of "
                          f"{ENGINE_SIZE_STEP}) from {', '.join(f'{a}x{b}' for a, b in given)}: p95_m {e2['p95_m']:.3g} "
                          f"still meets {target:g}; {before - after:,} of {before:,} texels saved "
                          f"({(before - after) / before:.0%}); shadow.fixed_resolution keeps the given size")
        s *= 1.15
    for m, r in zip(maps, given):  # nothing smaller met the target: the given sizes
        m.resolution = r
        with_bias(m, prob.receivers, prob.light)
    return maps, None
