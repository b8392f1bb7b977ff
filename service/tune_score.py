"""Scoring one candidate setting of an engine's own cascades for `shadowopt tune` (service.tune): the engine's maps
(solvers.engine_fits) and the product's one metric at the coarse pass's receivers, exactly as a solve's
prediction does (service.bias): renderers.depth_probe, solvers.bias_fit.fit_constant / cross_fitted / probe_wrong.
"""
from __future__ import annotations

import time

import numpy as np

from ..renderers.depth_probe import depth_probe
from ..solvers.bias_fit import cross_fitted, fit_constant, probe_wrong
from ..solvers.lights import DirectionalLight
from .bias import PREDICTION_MODEL, receivers_of
from .pipeline import coarse_pass


class TuneError(ValueError):
    """Bad tune input: `field` and a message listing what is accepted (HTTP 422 / CLI exit 2)."""

    def __init__(self, field: str, message: str):
        super().__init__(f"{field}: {message}")
        self.field = field
        self.message = message


class Pose:
    """One camera pose's coarse pass and receivers (what every candidate is scored on)."""

    def __init__(self, entry, rig: dict):
        t0 = time.perf_counter()
        resolved, buffers = coarse_pass(entry, rig)
        if len(resolved.lights) != 1 or not isinstance(resolved.lights[0], DirectionalLight):
            raise TuneError("rig.lights", "tune fits an engine's cascades for one directional light (accepted: one "
                            f"light of type directional), the rig has {len(resolved.lights)} light(s) of type "
                            f"{', '.join(l.kind for l in resolved.lights) or 'none'}")
        self.rays, self.camera, self.light, self.buffers = entry.rays, resolved.camera, resolved.lights[0], buffers
        self.shadow = resolved.shadow
        self.receivers = receivers_of(entry.rays, self.light, buffers, 0)
        self.coarse_ms = (time.perf_counter() - t0) * 1e3
        lo, hi = entry.loaded.geometry.bounds()
        self.scene_far = scene_far(lo, hi, self.camera)
        self.scene_box = (np.asarray(lo, float), np.asarray(hi, float))  # the casters' box (Babylon's render list)
        self.scene_diagonal = float(np.linalg.norm(np.asarray(hi) - np.asarray(lo)))


def scene_far(lo, hi, camera) -> float:
    """The camera's distance to the farthest point of the scene (its bounding box lo..hi), capped by its far plane:
    the shadow distance of the engines' defaults (issue 26)."""
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    return float(min(np.linalg.norm(corners - camera.position, axis=1).max(), camera.far))


def probe_pose(mod, pose: Pose, settings: dict):
    """(maps, probe) of one candidate at one pose: the engine's maps (mod.fit, the scene's box as the casters' box)
    and its depth test's inputs at the pose's receivers, casters in front of the light camera's near plane pancaked
    where the engine clamps depth (mod.pancakes: Babylon's depthClamp), clipped otherwise (three.js)."""
    pos, nrm, depth, lit, a = pose.receivers
    maps = mod.fit(pose.camera, pose.light, settings, casters_box=pose.scene_box)
    offset = float(maps[0].depth["hardware"]["normal_offset"]) if maps else 0.0
    probe = depth_probe(pose.rays, pose.light, maps, pos, nrm, depth, "hardware", offset,
                        pancake=mod.pancakes(settings))
    probe.depth_block = maps[0].depth if maps else {"format": mod.DEPTH_FORMAT, "hardware": {}}
    return maps, probe


def depth_format(mod, probe) -> str:
    """The format of the candidate's maps (Babylon's depends on its filter), the module's own without maps."""
    return getattr(probe, "depth_block", {}).get("format", mod.DEPTH_FORMAT)


def constant_side(probe) -> str:
    """Where the candidate's engine adds its constant (engine_depth_test.CONSTANT_SIDES): receiver (three.js) or
    caster (Babylon.js, before the map's rounding)."""
    return getattr(probe, "depth_block", {}).get("hardware", {}).get("constant_side", "receiver")


def margins(mod, probe, pose: Pose):
    """Per receiver D_rec - stored (the engine's caster term, none for three) and whether a map serves it. A
    caster-side constant is rounded with the stored depth: the margin is exact up to that rounding (predict scores
    the chosen constant exactly)."""
    stored = probe.stored(0.0, np.inf, depth_format(mod, probe))
    return probe.d_rec - stored, probe.inside


def best_constant(mod, probes: list, poses: list[Pose], lo: float, hi: float) -> tuple[float, float]:
    """(c, in-sample wrong pixels): fit_constant's least count over one constant for every map and pose, in
    [lo, hi] (the engine's accepted range for -bias); receivers no map serves are lit whatever c."""
    m, L, A, outside = [], [], [], 0.0
    for probe, pose in zip(probes, poses):
        _, _, _, lit, a = pose.receivers
        mg, inside = margins(mod, probe, pose)
        m.append(mg[inside]), L.append(lit[inside]), A.append(a[inside])
        outside += float(np.sum(a[~inside & ~lit]))
    m, L, A = np.concatenate(m), np.concatenate(L), np.concatenate(A)
    c, wrong = fit_constant(m, L, A, lo=max(lo, 0.0)) if len(m) else (max(lo, 0.0), 0.0)
    if c > hi:
        c = hi
        wrong = float(np.sum(A[(m > c) & L]) + np.sum(A[(m <= c) & ~L]))
    return float(c), float(wrong + outside)


def predict(mod, probes: list, poses: list[Pose], constant: float, cross_fit: bool) -> dict:
    """The prediction of one candidate with the bias constant `constant` in every map: per pose and summed,
    {misclassified_pixels, wrongly_lit, wrongly_shadowed} in the rig's full-resolution pixels (probe_wrong); with
    `cross_fit`, each pose's fitted constant's optimism on its own receivers added (bias_fit.cross_fitted)."""
    per_pose = []
    for probe, pose in zip(probes, poses):
        _, _, _, lit, a = pose.receivers
        terms = [{"constant": constant, "slope": 0.0, "slope_scaled": 0.0, "slope_clamp": 1.0,
                  "constant_side": constant_side(probe)}] * max(
            1, int(probe.map_index.max()) + 1 if len(probe.map_index) else 1)
        w = probe_wrong(probe, lit, a, terms, depth_format(mod, probe))
        if cross_fit:
            mg, inside = margins(mod, probe, pose)
            cl, cs = cross_fitted(mg[inside], lit[inside], a[inside])
            shadowed = mg[inside] > constant
            il = float(np.sum(a[inside][~shadowed & ~lit[inside]]))
            ish = float(np.sum(a[inside][shadowed & lit[inside]]))
            w["wrongly_lit"] += max(cl - il, 0.0)
            w["wrongly_shadowed"] += max(cs - ish, 0.0)
        per_pose.append({"misclassified_pixels": w["wrongly_lit"] + w["wrongly_shadowed"],
                         "wrongly_lit": w["wrongly_lit"], "wrongly_shadowed": w["wrongly_shadowed"],
                         "outside_pixels": w["outside"]})
    total = {k: float(sum(p[k] for p in per_pose)) for k in ("misclassified_pixels", "wrongly_lit", "wrongly_shadowed")}
    total["model"] = PREDICTION_MODEL
    if len(per_pose) > 1:
        total["per_pose"] = per_pose
    return total


def cascades_json(maps) -> list[dict]:
    """`emulated.cascades`: each cascade's selection range (near, far view depth, metres) and light matrices."""
    return [{"near": float(m.split[0]), "far": float(m.split[1]), "resolution": list(m.resolution),
             "light_near": float(m.light_depth[0]), "light_far": float(m.light_depth[1]),
             "view_matrix": m.view.tolist(), "projection_matrix": m.projection.tolist()} for m in maps]
