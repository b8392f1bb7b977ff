"""Cascade (z-partition) splits and resolution allocation (worst case: Lloyd et al. 2007 eq. 83; mean h: allocate_mean)."""
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
    depths, kept within the near and far planes (receivers with a margin may reach beyond them); the
    camera's near..far when there is no receiver."""
    if not len(depth):
        return camera.near, camera.far
    lo = min(max(float(np.min(depth)), camera.near), camera.far)
    return lo, max(min(float(np.max(depth)), camera.far), lo * 1.001)  # nothing beyond the far plane is seen


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
    return _sides(S / S.sum() * budget, R_s / R_t, budget)


def _sides(area: np.ndarray, aspect: np.ndarray, budget: int) -> list[tuple[int, int]]:
    """(width, height) per map with width / height = aspect and width * height = area, each side kept
    in [MIN_RES, MAX_RES] (the other side then takes the map's area); when the MIN_RES floor makes the
    maps exceed `budget`, the areas of the unfloored maps shrink until the total is within it. Sides
    are rounded down."""
    area = np.asarray(area, dtype=np.float64).copy()
    aspect = np.asarray(aspect, dtype=np.float64)

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


def allocate_mean(P, Q, budget: int) -> list[tuple[int, int]]:
    """Resolutions (w_k, h_k) minimising the mean-h objective sum_k (P_k / w_k^2 + Q_k / h_k^2) under
    sum_k w_k h_k <= T: the L1 counterpart of Lloyd et al. 2007 eq. 83 (which bounds the worst case).

    Why this form: with J = diag(w, h) G (texels per pixel, G the map's matrix at resolution 1),
    h_i = ||J_i^-1||_F^2 = p_i / w^2 + q_i / h^2 (p_i, q_i the squared lengths of the footprint's
    columns at resolution 1; Chong & Gortler 2007 eqs. 6, 9), so a cascade's share of the weighted
    mean is P_k / w^2 + Q_k / h^2 with P_k = sum_i w_i p_i / sum_all w (its samples). For a map of
    area A, minimising over w/h (Lagrange on w h = A) gives w/h = sqrt(P/Q) and the value C_k / A,
    C_k = 2 sqrt(P_k Q_k). Minimising sum_k C_k / A_k under sum_k A_k = T (Lagrange: C_k / A_k^2
    equal) gives A_k = T sqrt(C_k) / S, S = sum_j sqrt(C_j), and the value S^2 / T (objective_mean).
    Maps with C_k = 0 share the budget equally when every map has C_k = 0; else they get MIN_RES."""
    area, aspect = _mean_areas(P, Q, budget)
    return _sides(area, aspect, max(int(budget), MIN_RES * MIN_RES * len(area)))


def objective_mean(P, Q, budget: int) -> float:
    """The value allocate_mean's areas reach before rounding: (sum_k sqrt(2 sqrt(P_k Q_k)))^2 / T."""
    C = _terms(P, Q)[0]
    return float(np.sum(np.sqrt(C))) ** 2 / float(budget)


def with_receivers(P, Q, W, Pr, Qr, N):
    """The terms of allocate_mean for the samples' mean h plus the receivers' mean h (each cascade's
    receivers treated as facing the camera and the light: Pr, Qr their means, N_k the cascade's share
    of the receivers), so that the texels follow all receivers beside the boundary samples (issue 10
    item 4): the samples are the shadow boundaries the coarse pass saw, and a cascade they miss or
    under-represent would get next to no texels, whose size and depth bias then lose shadows.
    The receivers' term is put on the samples' scale by kappa = sum_k C_k / sum_k W_k c_k over the
    sampled cascades (the pooled ratio of the samples' mean h to the receivers' in the same cascades,
    W_k the cascade's share of the sample weight, c_k = 2 sqrt(Pr_k Qr_k); 1 without samples): where
    the samples are the receivers (a view with no boundary) both terms agree and the allocation is
    that of the samples alone. Returns (P', Q') = (P + kappa N Pr, Q + kappa N Qr)."""
    P, Q, W, Pr, Qr, N = (np.nan_to_num(np.asarray(v, dtype=np.float64), nan=0.0) for v in (P, Q, W, Pr, Qr, N))
    C, c = _terms(P, Q)[0], _terms(Pr, Qr)[0]
    den = float(np.sum((W * c)[C > 0]))
    kappa = float(np.sum(C)) / den if den > 0 and np.sum(C) > 0 else 1.0
    return P + kappa * N * Pr, Q + kappa * N * Qr


def _terms(P, Q):
    P = np.maximum(np.nan_to_num(np.asarray(P, dtype=np.float64), nan=0.0, posinf=1e300), 0.0)
    Q = np.maximum(np.nan_to_num(np.asarray(Q, dtype=np.float64), nan=0.0, posinf=1e300), 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        aspect = np.where((P > 0) & (Q > 0), np.sqrt(P / Q), 1.0)
    return 2.0 * np.sqrt(P * Q), aspect


def _mean_areas(P, Q, budget):
    C, aspect = _terms(P, Q)
    n = len(C)
    T = float(max(int(budget), MIN_RES * MIN_RES * n))
    S = float(np.sum(np.sqrt(C)))
    area = T * np.sqrt(C) / S if S > 0 else np.full(n, T / n)
    return np.maximum(area, MIN_RES * MIN_RES), aspect


def mean_terms(smap, samples, origin=None) -> tuple[float, float]:
    """(P, Q) of allocate_mean for one map over its samples: sum_i w_i p_i and sum_i w_i q_i, where
    h_i = p_i / width^2 + q_i / height^2 (from the metric at two resolutions: h(1, 1) = p + q,
    h(2, 1) = p / 4 + q). Weights as the samples carry them (divide by the light's total weight
    for the objective's share)."""
    import copy

    from .metric import device_samples, per_sample

    if len(samples) == 0:
        return 0.0, 0.0
    ds = device_samples(samples, origin)
    one = copy.copy(smap)
    one.resolution = (1, 1)
    h11, _, ok1 = per_sample(one, ds)
    one.resolution = (2, 1)
    h21, _, ok2 = per_sample(one, ds)
    ok = ok1 & ok2 & np.isfinite(h11) & np.isfinite(h21)
    if not ok.all():
        return math.inf, math.inf
    p = np.maximum(4.0 / 3.0 * (h11 - h21), 0.0)
    q = np.maximum(h11 - p, 0.0)
    w = np.asarray(samples.weight, dtype=np.float64)
    return float(np.sum(w * p)), float(np.sum(w * q))
