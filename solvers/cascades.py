"""Cascade (z-partition) splits and resolution allocation (worst case: Lloyd et al. 2007 eq. 83; mean h: allocate_mean)."""
from __future__ import annotations

import math

import numpy as np

SPLIT_KINDS = ("uniform", "log", "practical")
MIN_RES, MAX_RES = 16, 16384
# The cascades of one light share one texture size: every engine preset's target keeps a light's cascades in
# one texture array or in equal atlas tiles (three.js CSM's shadowMapSize, Babylon's mapSize layers,
# Filament's mapSize, Godot's and Unity's atlas tiles, Unreal's and Bevy's arrays:
# ../shared/reference/engine-settings.md), and the generic presets' own light passes (docs/engine-integration.md)
# sample a sampler2DArray / Texture2DArray, whose layers have one size. No preset states per-cascade sizes, so a
# texel budget buys k equal maps (allocate(..., shared=True), allocate_mean(..., shared=True)); the per-cascade
# allocations stay here as the math they are (Lloyd et al. 2007 eq. 83, the mean-h optimum) for a target that
# could take them.
ONE_SIZE_PER_LIGHT = True


def _nan_to_num(x, **kw):
    """np.nan_to_num(x, **kw), skipped when every value is finite (the usual case: the allocation's
    bisection calls it on a few values per step, where nan_to_num's own overhead dominates)."""
    x = np.asarray(x)
    return x if np.isfinite(x).all() else np.nan_to_num(x, **kw)


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


def allocate(R_s: np.ndarray, R_t: np.ndarray, budget: int, shared: bool = False) -> list[tuple[int, int]]:
    """Lloyd et al. 2007 eq. 83: partition i gets σ_i = S_i / Σ S_j of the texel budget T (S = R_s R_t),
    with r_s = sqrt((R_s/R_t) σ T) and r_t = sqrt((R_t/R_s) σ T).

    Each side is kept in [MIN_RES, MAX_RES] (the other side then takes the partition's area, so the
    share σ_i T is kept where it can be); when the MIN_RES floor makes the maps exceed T, the shares
    of the unfloored maps shrink until the total is within T. Sides are rounded down.
    `shared` (ONE_SIZE_PER_LIGHT): every map gets T / k texels at one aspect, max R_s / max R_t (the worst
    map along s and along t then meet the same ratio of resolution to critical resolution)."""
    R_s = np.maximum(_nan_to_num(np.asarray(R_s, dtype=np.float64), nan=1.0, posinf=1e12), 1e-12)
    R_t = np.maximum(_nan_to_num(np.asarray(R_t, dtype=np.float64), nan=1.0, posinf=1e12), 1e-12)
    budget = max(int(budget), MIN_RES * MIN_RES * len(R_s))
    if shared:  # one size for every map: the worst R_s / w and R_t / h over the maps are equalised
        n = len(R_s)
        return _sides(np.full(n, budget / n), np.full(n, float(R_s.max() / R_t.max())), budget)
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


def allocate_mean(P, Q, budget: int, shared: bool = False) -> list[tuple[int, int]]:
    """Resolutions (w_k, h_k) minimising the mean-h objective sum_k (P_k / w_k^2 + Q_k / h_k^2) under
    sum_k w_k h_k <= T: the L1 counterpart of Lloyd et al. 2007 eq. 83 (which bounds the worst case).

    Why this form: with J = diag(w, h) G (texels per pixel, G the map's matrix at resolution 1),
    h_i = ||J_i^-1||_F^2 = p_i / w^2 + q_i / h^2 (p_i, q_i the squared lengths of the footprint's
    columns at resolution 1; Chong & Gortler 2007 eqs. 6, 9), so a cascade's share of the weighted
    mean is P_k / w^2 + Q_k / h^2 with P_k = sum_i w_i p_i / sum_all w (its samples). For a map of
    area A, minimising over w/h (Lagrange on w h = A) gives w/h = sqrt(P/Q) and the value C_k / A,
    C_k = 2 sqrt(P_k Q_k). Minimising sum_k C_k / A_k under sum_k A_k = T (Lagrange: C_k / A_k^2
    equal) gives A_k = T sqrt(C_k) / S, S = sum_j sqrt(C_j), and the value S^2 / T (objective_mean).
    A side the ideal aspect puts below MIN_RES stays at MIN_RES; that map's cost is then
    Q MIN^2 / A^2 + P / MIN^2, its Lagrange area (2 Q MIN^2 / lam)^(1/3), and lam is found by
    bisection so that the areas sum to T. No terms at all: the budget in equal squares.
    `shared` (ONE_SIZE_PER_LIGHT): one size (w, h) for every map, w h = T / k: the objective is then
    sum P / w^2 + sum Q / h^2, least at w / h = sqrt(sum P / sum Q), value 2 k sqrt(sum P sum Q) / T."""
    area, aspect = (_shared_areas if shared else _mean_areas)(P, Q, budget)
    return _sides(area, aspect, max(int(budget), MIN_RES * MIN_RES * len(area)))


def objective_mean(P, Q, budget: int, shared: bool = False) -> float:
    """The value allocate_mean's areas reach before rounding: (sum_k sqrt(2 sqrt(P_k Q_k)))^2 / T when
    no side is held at MIN_RES (shared: 2 k sqrt(sum P sum Q) / T, one size for every map)."""
    P = np.maximum(_nan_to_num(np.asarray(P, dtype=np.float64), nan=0.0, posinf=1e300), 0.0)
    Q = np.maximum(_nan_to_num(np.asarray(Q, dtype=np.float64), nan=0.0, posinf=1e300), 0.0)
    return _value_at(P, Q, *(_shared_areas if shared else _mean_areas)(P, Q, budget))


def _shared_areas(P, Q, budget):
    """allocate_mean's areas and aspects with one size for every map: T / k each, w / h = sqrt(sum P / sum Q)."""
    P = np.maximum(_nan_to_num(np.asarray(P, dtype=np.float64), nan=0.0, posinf=1e300), 0.0)
    Q = np.maximum(_nan_to_num(np.asarray(Q, dtype=np.float64), nan=0.0, posinf=1e300), 0.0)
    n = len(P)
    T = float(max(int(budget), MIN_RES * MIN_RES * n))
    sp, sq = float(np.sum(P)), float(np.sum(Q))
    aspect = math.sqrt(sp / sq) if sq > 0 and sp > 0 else 1.0
    return np.full(n, T / n), np.full(n, min(max(aspect, 1e-12), 1e12))


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
    P, Q, W, Pr, Qr, N = (_nan_to_num(np.asarray(v, dtype=np.float64), nan=0.0) for v in (P, Q, W, Pr, Qr, N))
    C, c = _terms(P, Q)[0], _terms(Pr, Qr)[0]
    den = float(np.sum((W * c)[C > 0]))
    kappa = float(np.sum(C)) / den if den > 0 and np.sum(C) > 0 else 1.0
    return P + kappa * N * Pr, Q + kappa * N * Qr


def _terms(P, Q):
    P = np.maximum(_nan_to_num(np.asarray(P, dtype=np.float64), nan=0.0, posinf=1e300), 0.0)
    Q = np.maximum(_nan_to_num(np.asarray(Q, dtype=np.float64), nan=0.0, posinf=1e300), 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        aspect = np.where(Q > 0, np.sqrt(P / np.where(Q > 0, Q, 1.0)), np.where(P > 0, np.inf, 1.0))
    return 2.0 * np.sqrt(P * Q), aspect


def _area_at(lam: float, P, Q, C, aspect) -> np.ndarray:
    """Each map's area where the marginal gain of a texel is lam: sqrt(C / lam) (the aspect free);
    a side the ideal aspect would take below MIN_RES stays there, and then the map's cost is
    Q MIN^2 / A^2 (+ P / MIN^2) with A = (2 Q MIN^2 / lam)^(1/3) (likewise for the other side)."""
    A = np.sqrt(C / lam)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        w_low = np.sqrt(A * aspect) < MIN_RES
        h_low = np.sqrt(A / aspect) < MIN_RES
        m2 = float(MIN_RES) ** 2
        A = np.where(w_low, np.cbrt(2.0 * Q * m2 / lam), A)
        A = np.where(h_low & ~w_low, np.cbrt(2.0 * P * m2 / lam), A)
    return np.maximum(_nan_to_num(A, nan=0.0, posinf=0.0), m2)


def _mean_areas(P, Q, budget):
    """Areas and aspects of allocate_mean: sum_k A_k(lam) = T, A_k(lam) by _area_at, lam by bisection
    (in the unclamped case A_k = T sqrt(C_k) / S exactly)."""
    C, aspect = _terms(P, Q)
    P = np.maximum(_nan_to_num(np.asarray(P, dtype=np.float64), nan=0.0, posinf=1e300), 0.0)
    Q = np.maximum(_nan_to_num(np.asarray(Q, dtype=np.float64), nan=0.0, posinf=1e300), 0.0)
    n = len(C)
    T = float(max(int(budget), MIN_RES * MIN_RES * n))
    if not np.any((P > 0) | (Q > 0)):
        return np.full(n, T / n), np.ones(n)
    S = float(np.sum(np.sqrt(C)))
    if S > 0:  # the closed form, when no side falls below MIN_RES
        area = T * np.sqrt(C) / S
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            ok = np.all(np.sqrt(area * aspect) >= MIN_RES) and np.all(np.sqrt(area / aspect) >= MIN_RES)
        if ok:
            return area, aspect
    lo, hi = -200.0, 200.0  # log lam
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if float(np.sum(_area_at(math.exp(mid), P, Q, C, aspect))) > T:
            lo = mid
        else:
            hi = mid
    area = _area_at(math.exp(hi), P, Q, C, aspect)
    area *= T / max(float(np.sum(area)), 1e-300) if float(np.sum(area)) > T else 1.0
    return area, _nan_to_num(aspect, posinf=1e12)


def _value_at(P, Q, area, aspect) -> float:
    w = np.clip(np.sqrt(area * aspect), MIN_RES, MAX_RES)
    h = np.clip(area / w, MIN_RES, MAX_RES)
    w = np.clip(area / h, MIN_RES, MAX_RES)
    return float(np.sum(np.asarray(P, float) / w ** 2 + np.asarray(Q, float) / h ** 2))


def map_gradients(smap, points: np.ndarray):
    """(ds/dX, dt/dX, s, t, w) at world points: the map's coordinate gradients (N, 3) per unit s and t
    (s, t in [0, 1], the log warp on t included), as solvers.metric.footprint computes them in
    Dr.Jit (d(c_i / c_w)/dX = (row_i c_w - c_i row_w) / c_w^2, s = (x_ndc + 1) / 2), in NumPy for
    the allocation's terms (a few hundred points, where a kernel launch costs more than the math;
    tests check the two against each other)."""
    X = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    M = smap.matrix
    c = X @ M[:3, :3].T + M[:3, 3]
    cw = (X @ M[3, :3] + M[3, 3])[:, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / (cw * cw)
        gs = (M[0, :3][None] * cw - c[:, 0:1] * M[3, :3][None]) * (0.5 * inv)
        gt = (M[1, :3][None] * cw - c[:, 1:2] * M[3, :3][None]) * (0.5 * inv)
        s = (c[:, 0] / cw[:, 0] + 1.0) * 0.5
        t = (c[:, 1] / cw[:, 0] + 1.0) * 0.5
        if smap.log_warp is not None:
            gt = gt * smap.log_warp.derivative(t)[:, None]
            t = smap.log_warp.apply(t)
    return gs, gt, s, t, cw[:, 0]


def mean_terms(smap, samples, origin=None) -> tuple[float, float]:
    """(P, Q) of allocate_mean for one map over its samples: sum_i w_i p_i and sum_i w_i q_i, where
    h_i = p_i / width^2 + q_i / height^2: with J at resolution 1 (rows ds/dX (dX/dx, dX/dy) and
    likewise t), F = J^-1 has columns (j11, -j10) / det and (-j01, j00) / det, and a resolution
    (width, height) scales J's rows by width and height, so p = (j10^2 + j11^2) / det^2 and
    q = (j00^2 + j01^2) / det^2 (solvers.metric's h at any resolution; inf when a sample has no
    valid footprint, as the metric says). Weights as the samples carry them (divide by the light's
    total weight for the objective's share). `origin` is accepted for the metric's signature."""
    if len(samples) == 0:
        return 0.0, 0.0
    gs, gt, _, _, w = map_gradients(smap, samples.position)
    j00, j01 = np.sum(gs * samples.dx, 1), np.sum(gs * samples.dy, 1)
    j10, j11 = np.sum(gt * samples.dx, 1), np.sum(gt * samples.dy, 1)
    det = j00 * j11 - j01 * j10
    with np.errstate(divide="ignore", invalid="ignore"):
        p = (j10 * j10 + j11 * j11) / (det * det)
        q = (j00 * j00 + j01 * j01) / (det * det)
    if not (np.all(w > 0) and np.all(np.isfinite(p)) and np.all(np.isfinite(q))):
        return math.inf, math.inf
    wt = np.asarray(samples.weight, dtype=np.float64)
    return float(np.sum(wt * p)), float(np.sum(wt * q))
