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


def allocate(R_s: np.ndarray, R_t: np.ndarray, budget: int) -> list[tuple[int, int]]:
    """Lloyd et al. 2007 eq. 83: partition i gets σ_i = S_i / Σ S_j of the texel budget T (S = R_s R_t),
    with r_s = sqrt((R_s/R_t) σ T) and r_t = sqrt((R_t/R_s) σ T)."""
    R_s = np.maximum(np.asarray(R_s, dtype=np.float64), 1e-12)
    R_t = np.maximum(np.asarray(R_t, dtype=np.float64), 1e-12)
    S = R_s * R_t
    sigma = S / S.sum()
    out = []
    for rs, rt, sg in zip(R_s, R_t, sigma):
        w = math.sqrt(rs / rt * sg * budget)
        h = math.sqrt(rt / rs * sg * budget)
        out.append((int(np.clip(math.floor(w), MIN_RES, MAX_RES)), int(np.clip(math.floor(h), MIN_RES, MAX_RES))))
    return out
