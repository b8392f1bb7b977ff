"""Point lights by face partitioning (Lloyd et al. 2007 FP, FP+P, FP+LogP; geometry in solvers.face_partition),
chosen against the cube map by the predicted objective.

For a point light the service fits both: the maps the method returned (the six-face cube, faces without receivers
already dropped by service.need; or optimized's single cone map) and the face partition at the same total texels.
The partition's texels are split across its faces by need with the rig's allocation (service.need.split_budget:
Chong 2003's Lagrange allocation, T_i ~ d_i^(2/3), d_i from each face's predicted misclassified pixels at an equal
share of the plain fit), each face kept at no less than a quarter of an equal share (a face with receivers but no shadow edge on
screen still shades its receivers). The one with the lower predicted objective (solvers.metric's mean h, what the
optimizer minimizes) is returned; the solution's `face_partitioning` block says which, and the faces and
resolutions of the partition.
"""
from __future__ import annotations

import math

import numpy as np

from ..solvers.depth_modes import with_bias
from ..solvers.face_partition import assign_receivers, partition_maps
from .need import split_budget

SKIP_METHODS = ("uniform", "path", "stable_csm")  # the whole cube by definition / a held texel grid
MIN_SIDE = 16
FLOOR_SHARE = 0.25  # of an equal share: the least a face with receivers gets


def warp_for(method: str, allow_log: bool) -> str:
    """The partition's warp: focused -> none (FP), the warped methods -> perspective (FP+P), or the log warp
    (FP+LogP) when the request allows it (output.allow_log_warp)."""
    if method == "focused":
        return "none"
    return "log" if allow_log else "perspective"


def face_shares(total: int, misclassified: list[float], probe: int) -> list[int]:
    """Texels per face: split_budget by need (T_i ~ d_i^(2/3)), except that a face whose share would fall below
    FLOOR_SHARE of an equal share gets exactly that floor and the rest is split by need among the others."""
    n = len(misclassified)
    floor = int(FLOOR_SHARE * total / max(n, 1))
    fixed: set[int] = set()
    while True:
        free = [i for i in range(n) if i not in fixed]
        rest = total - floor * len(fixed)
        sub = split_budget(rest, [misclassified[i] for i in free], probe) if free else []
        low = {i for i, t in zip(free, sub) if t < floor}
        if not low:
            out = [floor] * n
            for i, t in zip(free, sub):
                out[i] = t
            return out
        fixed |= low


def variant_objective(err: dict) -> float:
    o = err.get("objective")
    return float(o) if o is not None and np.isfinite(o) and err.get("unserved_samples", 0) == 0 else math.inf


def choose(method: str, camera, prob, bounds, maps: list, allow_log: bool, maps_error, origin,
           mode: str = "auto") -> tuple[list, dict | None]:
    """(maps to return, the solution's face_partitioning block) for a point light; (maps, None) otherwise.
    mode (shadow.point_light_maps): auto (the lower objective), cube (the method's maps), face_partition."""
    if prob.light.kind != "point" or method in SKIP_METHODS or not len(prob.receivers) or not maps or mode == "cube":
        return maps, None
    light = prob.light
    total = int(sum(m.resolution[0] * m.resolution[1] for m in maps))
    ref_err, _ = maps_error(maps, prob.samples, origin)
    ref_obj = variant_objective(ref_err)
    res, mis = face_resolutions(camera, light, prob, bounds, total, maps_error, origin)
    tried = []
    for warp in dict.fromkeys(("none", warp_for(method, allow_log))):  # FP, and FP+P / FP+LogP for warped methods
        fp, parts = partition_maps(camera, light, prob.receivers, bounds, res, warp)
        err, _ = maps_error(fp, prob.samples, origin)
        tried.append((variant_objective(err), warp, fp, parts, err, mis))
    best = min(tried, key=lambda c: c[0])
    fp_obj, warp, fp, parts, fp_err, mis = best
    chosen = "face_partitioning" if fp_obj < ref_obj or mode == "face_partition" else \
        "cube" if maps[0].face is not None else "single_map"
    names = {"none": "FP", "perspective": "FP+P", "log": "FP+LogP"}
    name = names[warp]
    block = {
        "chosen": chosen, "variant": name,
        "objective": fp_err.get("objective"), "unserved_samples": fp_err.get("unserved_samples"),
        "returned_objective_otherwise": ref_err.get("objective"),
        "variants_objective": {names[c[1]]: c[4].get("objective") for c in tried},
        "total_texels": total, "partition_texels": int(sum(m.resolution[0] * m.resolution[1] for m in fp)),
        "faces": [{"face": m.face, "resolution": list(m.resolution), "receivers": int(len(p)), "warp": m.warp_kind,
                   "eta": m.eta, "predicted_misclassified_at_probe": d}
                  for m, p, d in zip(fp, parts, mis)],
        "rule": ("Lloyd et al. 2007 face partitioning: maps only for the cube faces whose frusta hold visible "
                 "receivers, each fitted to its receivers (FP), and for the warped methods also warped as a "
                 "directional map (FP+P; FP+LogP with output.allow_log_warp); texels split across faces by need "
                 "(Chong 2003's Lagrange allocation) at the same total texels as the cube; the variant with the "
                 "lowest predicted objective is kept when it is lower than the cube's (shadow.point_light_maps auto)"),
    }
    if method in ("lispsm", "logpsm", "optimized") and not allow_log:
        block["log_warp"] = "FP+LogP not tried: output.allow_log_warp is false"
    if chosen != "face_partitioning":
        return maps, block
    return [with_bias(m, p, light) for m, p in zip(fp, parts)], block


def face_resolutions(camera, light, prob, bounds, total: int, maps_error, origin) -> tuple[dict, list[float]]:
    """({face: (side, side)}, per-face predicted misclassified at the probe): every face probed with the plain fit
    (FP) at an equal share of `total`, then the texels split by need (face_shares); both variants use them."""
    n = len(assign_receivers(light.position, prob.receivers))
    side = max(MIN_SIDE, math.isqrt(total // n))
    fp, _ = partition_maps(camera, light, prob.receivers, bounds, (side, side), "none")
    _, per_face = maps_error(fp, prob.samples, origin)
    mis = [float(e.get("misclassified_pixels") or 0.0) for e in per_face]
    shares = face_shares(total, mis, side * side)
    return {m.face: (max(MIN_SIDE, math.isqrt(t)),) * 2 for m, t in zip(fp, shares)}, mis
