"""How a cascade's candidate maps are scored beside the samples: the receivers' mean h (receiver_h,
receiver_terms: Chong & Gortler's h with the cosine factors dropped, for a cascade the samples do not reach),
each cascade's (P, Q) terms for solvers.cascades.allocate_mean (cascade_terms) and each cascade's share of the
receivers by view depth (depth_shares). Shared by the split search (solvers.split_search) and the per-cascade
choice of solvers.optimized_maps."""
from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

from .cameras import Camera
from .cascades import map_gradients, mean_terms, pixel_world_size, with_receivers
from .lights import DirectionalLight
from .samples import seeded_rows
from .texel_size import texel_extents

RECEIVER_SCORE_POINTS = 2000  # receivers kept to score a cascade that has no sample


def receiver_h(smap, pts: np.ndarray, camera: Camera, light) -> float:
    """Mean over receivers of Chong & Gortler's h = ||F||_F^2 (eq. 9) with each receiver treated as
    facing the camera and the light (the cosine factors dropped, as solvers.cascades.critical_factors
    does): ((metres per texel along s)^2 + (along t)^2) / (world size of a full-resolution pixel)^2.
    Scores a cascade the samples do not reach (no shadow boundary in its depth range): there the
    metric has no sample, so every candidate would score 0. inf when a receiver is outside the map."""
    p, q = receiver_terms(smap, pts, camera, light)
    return p / smap.resolution[0] ** 2 + q / smap.resolution[1] ** 2


@lru_cache(maxsize=64)
def _light_plane_axes(d: tuple) -> tuple[np.ndarray, np.ndarray]:
    """Two unit axes perpendicular to the light direction d (texel_size.texel_extents' e1, e2)."""
    d = np.asarray(d, float)
    e1 = np.cross(d, [0.0, 1.0, 0.0])
    if np.linalg.norm(e1) < 1e-6:
        e1 = np.cross(d, [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(d, e1)


_SCORED: dict = {}  # id(pts) -> (pts, camera, n, subset, pixel sizes): the split search and the cascades'
                    # candidates score many maps on the same receivers (speed only: the same numbers)


def _scored_receivers(pts, camera, n: int):
    """(subset, pixel_world_size there) of receiver_terms, kept for the last few receiver arrays."""
    hit = _SCORED.get(id(pts))
    if hit is not None and hit[0] is pts and hit[1] is camera and hit[2] == n:
        return hit[3], hit[4]
    sub = np.asarray(pts, dtype=np.float64).reshape(-1, 3)
    if len(sub) > n:
        sub = sub[seeded_rows(len(sub), n)]
    pix = pixel_world_size(camera, sub) if len(sub) else np.zeros(0)
    if len(_SCORED) >= 32:
        _SCORED.pop(next(iter(_SCORED)))
    _SCORED[id(pts)] = (pts, camera, n, sub, pix)
    return sub, pix


def receiver_terms(smap, pts: np.ndarray, camera: Camera, light, n: int = RECEIVER_SCORE_POINTS) -> tuple[float, float]:
    """(P, Q) of receiver_h: its mean h is P / width^2 + Q / height^2 (means over the receivers of
    (metres per unit s / pixel size)^2 and likewise t, measured in the plane perpendicular to the light
    as texel_size.texel_extents does, from the map's analytic gradients; at most n receivers, a seeded
    random subset; inf when one is outside the map)."""
    pts, pix = _scored_receivers(pts, camera, n)
    if not len(pts):
        return 0.0, 0.0
    if not isinstance(light, DirectionalLight):
        per_s, per_t = texel_extents(smap, pts, light)
    else:
        e1, e2 = _light_plane_axes(tuple(float(v) for v in light.direction))
        gs, gt, s, t, w = map_gradients(smap, pts)
        j00, j01, j10, j11 = gs @ e1, gs @ e2, gt @ e1, gt @ e2
        det = np.abs(j00 * j11 - j01 * j10)
        eps = 1e-6
        inside = (w > 0) & (s >= -eps) & (s <= 1 + eps) & (t >= -eps) & (t <= 1 + eps) & (det > 0)
        with np.errstate(divide="ignore", invalid="ignore"):
            per_s = np.where(inside, np.hypot(j11, j10) / det, np.nan)
            per_t = np.where(inside, np.hypot(j01, j00) / det, np.nan)
    p, q = (per_s / pix) ** 2, (per_t / pix) ** 2
    if not (np.isfinite(p).all() and np.isfinite(q).all()):
        return math.inf, math.inf
    return float(np.mean(p)), float(np.mean(q))


def cascade_terms(maps, subs, parts, camera, light, total_weight: float, shares=None,
                  n_receivers: int = RECEIVER_SCORE_POINTS):
    """Per cascade, (P, Q) for solvers.cascades.allocate_mean: the samples' terms (weights over the
    light's total) plus the receivers' (cascades.with_receivers; `shares`: each cascade's share of
    the receivers, default from len(parts))."""
    P, Q, W, Pr, Qr = [], [], [], [], []
    for smap, sub, pts in zip(maps, subs, parts):
        p, q = mean_terms(smap, sub, camera.position) if len(sub) else (0.0, 0.0)
        P.append(p / total_weight), Q.append(q / total_weight)
        W.append(float(np.sum(sub.weight)) / total_weight if len(sub) else 0.0)
        pr, qr = receiver_terms(smap, pts, camera, light, n_receivers)
        Pr.append(pr), Qr.append(qr)
    if shares is None:
        n = np.array([len(p) for p in parts], float)
        shares = n / max(n.sum(), 1.0)
    if not all(math.isfinite(v) for v in P + Q + Pr + Qr):
        return None  # a sample or receiver outside a map
    return with_receivers(P, Q, W, Pr, Qr, shares)


def depth_shares(maps, depth: np.ndarray) -> np.ndarray:
    """Each cascade's share of the receivers by view depth (map_for_depth's rule: the first cascade
    whose [near, far] split holds the depth; `depth` sorted or not)."""
    if not len(depth):
        return np.full(len(maps), 1.0 / max(len(maps), 1))
    d = depth if np.all(depth[:-1] <= depth[1:]) else np.sort(depth)
    bounds = np.searchsorted(d, [m.split[1] for m in maps], side="right")
    counts = np.diff(np.concatenate([[0], np.maximum.accumulate(bounds)]))
    return counts / float(len(d))
