"""Cascade (z-partition) splits and resolution allocation."""
from __future__ import annotations

import math

import numpy as np

SPLIT_KINDS = ("uniform", "log", "practical")
MIN_RES, MAX_RES = 16, 16384


def split_depths(z_near: float, z_far: float, k: int, kind: str = "practical", lam: float = 0.5) -> np.ndarray:
    """k + 1 split depths over [z_near, z_far].

    uniform: z_n + (z_f - z_n) i/k; log: z_n (z_f/z_n)^(i/k) (equal far/near ratio, Lloyd et al. 2007
    eqs. 80-82, which minimises the maximum error); practical(λ) = λ log + (1 - λ) uniform (Zhang's
    PSSM, as Ogre and three.js use it)."""
    if kind not in SPLIT_KINDS:
        raise ValueError(f"splits must be one of {', '.join(SPLIT_KINDS)}, got {kind!r}")
    if k < 1:
        raise ValueError(f"cascades must be at least 1, got {k}")
    z_near = max(float(z_near), 1e-9)
    z_far = max(float(z_far), z_near * (1 + 1e-9))
    i = np.arange(k + 1) / k
    uni = z_near + (z_far - z_near) * i
    log = z_near * (z_far / z_near) ** i
    w = {"uniform": 0.0, "log": 1.0, "practical": float(lam)}[kind]
    out = w * log + (1 - w) * uni
    out[0], out[-1] = z_near, z_far
    return out


def receiver_depth_range(camera, depth: np.ndarray) -> tuple[float, float]:
    """The receivers' tight view-depth range that splits divide (SDSM): [min, max] of their view
    depths, kept beyond the near plane; the camera's near..far when there is no receiver."""
    if not len(depth):
        return camera.near, camera.far
    return max(float(np.min(depth)), camera.near), max(float(np.max(depth)), camera.near * 1.001)


def pixel_world_size(camera, pts: np.ndarray) -> np.ndarray:
    """World size (m) of one full-resolution screen pixel at each point, perpendicular to the view
    ray: view depth · 2 tan(fov_y / 2) / height."""
    pts = np.asarray(pts, dtype=np.float64).reshape(-1, 3)
    depth = (pts - camera.position) @ camera.forward
    return np.maximum(depth, camera.near) * 2.0 * camera.tan_half_fov_y / camera.resolution[1]


def critical_factors(per_s: np.ndarray, per_t: np.ndarray, pixel: np.ndarray, q: float = 95.0) -> tuple[float, float]:
    """A map's critical resolution factors (Lloyd et al. 2007 §4: the resolution along s, t at which
    no texel is larger than a pixel) estimated from its receivers: R_s = the q-th percentile over
    receivers of (metres per unit s) / (pixel world size), likewise R_t. The max of Lloyd's
    definition is replaced by a high percentile (robust to a few grazing receivers) and the cosine
    factors are dropped (receivers treated as facing the camera and the light). Non-finite entries
    (receivers outside the map) are ignored; no receiver -> (1, 1)."""
    per_s, per_t, pixel = (np.asarray(a, dtype=np.float64) for a in (per_s, per_t, pixel))
    ok = np.isfinite(per_s) & np.isfinite(per_t) & np.isfinite(pixel) & (pixel > 0)
    if not ok.any():
        return 1.0, 1.0
    rs = float(np.percentile(per_s[ok] / pixel[ok], q))
    rt = float(np.percentile(per_t[ok] / pixel[ok], q))
    return max(rs, 1e-12), max(rt, 1e-12)


def allocate(R_s: np.ndarray, R_t: np.ndarray, budget: int) -> list[tuple[int, int]]:
    """Lloyd et al. 2007 eq. 83: partition i gets σ_i = S_i / Σ S_j of the texel budget T (S = R_s R_t),
    with r_s = sqrt((R_s/R_t) σ T) and r_t = sqrt((R_t/R_s) σ T).

    Each side is kept in [MIN_RES, MAX_RES] (the other side then takes the partition's area, so the
    share σ_i T is kept where it can be); when the MIN_RES floor makes the maps exceed T, the shares
    of the unfloored maps shrink until the total is within T. Sides are rounded down."""
    R_s = np.maximum(np.nan_to_num(np.asarray(R_s, dtype=np.float64), nan=1.0, posinf=1e12), 1e-12)
    R_t = np.maximum(np.nan_to_num(np.asarray(R_t, dtype=np.float64), nan=1.0, posinf=1e12), 1e-12)
    budget = max(int(budget), MIN_RES * MIN_RES * len(R_s))
    S = R_s * R_t
    area = S / S.sum() * budget
    aspect = R_s / R_t

    def dims(a):
        w = np.clip(np.sqrt(aspect * a), MIN_RES, MAX_RES)
        h = np.clip(a / w, MIN_RES, MAX_RES)
        w = np.clip(a / h, MIN_RES, MAX_RES)  # give the area back to w if h was clamped
        return np.floor(w), np.floor(h)

    for _ in range(20):
        w, h = dims(area)
        total = float(np.sum(w * h))
        if total <= budget:
            break
        floored = (w * h) > area * (1 + 1e-9)  # maps held up by the MIN_RES floor
        free = ~floored
        if not free.any():
            break
        excess = total - budget
        area[free] *= max(1.0 - excess / float(np.sum(area[free])), 0.0) * (1 - 1e-6)
        area = np.maximum(area, MIN_RES * MIN_RES)
    return [(int(a), int(b)) for a, b in zip(w, h)]
