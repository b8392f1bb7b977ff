"""The one error metric (DESIGN.md, "Metric"): used by the optimizer (with gradients), the
prediction in every response, the heatmap and the benchmark.

Per sample X seen by full-resolution pixel x, with map texel coordinates u = (s * width, t' * height):
  J = du/dx (2x2, texels per pixel) = (du/dX) (dX/dx), du/dX from the 4x4 matrix P analytically
      (Chong & Gortler 2007 eq. 8 in our notation), dX/dx from solvers.samples.pixel_derivatives;
  F = J^-1 (the texel's footprint in pixels; columns ds, dt);
  h = ||F||_F^2 = sum of squares / det(J)^2       (Chong & Gortler 2007 eqs. 6 and 9);
  m = max(|ds + dt|, |ds - dt|)                   (Lloyd et al. 2007 eq. 85: the longer diagonal).
The objective is the weighted mean of h. Written once in Dr.Jit (float64) so that AD gives exact
gradients with respect to P; a NumPy entry point wraps it for prediction and pictures.
"""
from __future__ import annotations

import math
import threading
from contextlib import contextmanager
from functools import lru_cache
from types import SimpleNamespace

import numpy as np

from .jit import aligned
from .jit import llvm_ad as _llvm_ad
from .samples import Samples
from .shadow_map import ShadowMap, map_for_depth

DET_FLOOR = 1e-18  # |det J| below this counts as degenerate (the sample sees no texel change)
W_FLOOR = 1e-12  # clip w below this: the point is behind a perspective light's centre of projection
ERROR_FIELDS = ("objective", "mean_m", "median_m", "p95_m", "max_m", "frac_m_gt_1", "samples", "limit",
                "ratio_to_limit", "misclassified_pixels")
# K of predicted_misclassified: measured misclassified pixels per unit of Σ a_i √h_i. Calibrated on the
# corpus (10 scenes x 6 suns x 5 methods, one 400² map, 500² screen, exact ray-traced visibility):
# the median over scenes of each scene's median measured/Σ a √h (scene medians 0.004-0.016).
MISCLASSIFIED_K = 0.0098


_ad_module = []


def llvm_ad():
    """solvers.jit.llvm_ad(), looked up once (it reads the environment each call)."""
    if not _ad_module:
        _ad_module.append(_llvm_ad())
    return _ad_module[0]


_serial = {"depth": 0, "saved": 0}
_serial_lock = threading.Lock()


@contextmanager
def serial_kernels():
    """Run Dr.Jit's kernels on the calling thread while inside (process-wide, nestable, thread-safe:
    the pool comes back when the last user leaves). The metric's kernels are small (hundreds to a few
    thousand samples): Dr.Jit splits each over the pool, and the workers' wake-ups and spinning cost
    more than they save and compete with NumPy for the cores (a demo-scene solve: 62 -> 33 ms CPU)."""
    import drjit as dr  # lazy: drjit reads DRJIT_LIBLLVM_PATH on import (solvers.jit.llvm_ad sets it)

    llvm_ad()
    with _serial_lock:
        if _serial["depth"] == 0:
            _serial["saved"] = dr.thread_count()
            dr.set_thread_count(1)
        _serial["depth"] += 1
    try:
        yield
    finally:
        with _serial_lock:
            _serial["depth"] -= 1
            if _serial["depth"] == 0:
                dr.set_thread_count(_serial["saved"])


class DeviceSamples:
    """Samples uploaded once as Dr.Jit float64 arrays, re-centred on `origin` for conditioning."""

    def __init__(self, samples: Samples, origin: np.ndarray | None = None):
        ad = llvm_ad()
        self.origin = np.zeros(3) if origin is None else np.asarray(origin, dtype=np.float64)
        self.count = len(samples)
        rel = samples.position - self.origin
        f64 = lambda col: ad.Float64(aligned(col, np.float64))  # noqa: E731 (aligned: no recompiles)
        self.X = ad.Array3f64(*(f64(rel[:, k]) for k in range(3)))
        self.dx = ad.Array3f64(*(f64(samples.dx[:, k]) for k in range(3)))
        self.dy = ad.Array3f64(*(f64(samples.dy[:, k]) for k in range(3)))
        self.w = f64(samples.weight)


def device_samples(samples: Samples, origin: np.ndarray | None = None) -> DeviceSamples:
    """The samples on the device, uploaded once per Samples object and origin."""
    origin = np.zeros(3) if origin is None else np.asarray(origin, dtype=np.float64)
    key = origin.tobytes()
    ds = samples._device.get(key)
    if ds is None:
        ds = samples._device[key] = DeviceSamples(samples, origin)
    return ds


def recentre(matrix: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """P acting on points relative to `origin`: P @ T(origin)."""
    t = np.eye(4)
    t[:3, 3] = origin
    return matrix @ t


def footprint(P, resolution, log_warp, ds: DeviceSamples):
    """Per-sample (h, m, valid) as Dr.Jit Float64 arrays.

    P: 16 Dr.Jit Float64 values, row-major, acting on re-centred points (may carry gradients).
    log_warp: (c0, c1, c2) as Dr.Jit Float64 or None.
    """
    ad = llvm_ad()
    import drjit as dr  # lazy: drjit reads DRJIT_LIBLLVM_PATH on import (solvers.jit.llvm_ad sets it)

    if not isinstance(resolution[0], ad.Float64):  # opaque: a new map size does not recompile
        resolution = (dr.opaque(ad.Float64, float(resolution[0])), dr.opaque(ad.Float64, float(resolution[1])))
    c, cw, valid, inv_w2, ns, nt = _clip_gradients(P, ds.X)
    # s = (x_ndc + 1)/2 -> u = s * width.
    gs = ns * (inv_w2 * 0.5 * resolution[0])
    gt = nt * (inv_w2 * 0.5 * resolution[1])
    if log_warp is not None:
        c0, c1, c2 = log_warp
        t = (c[1] / cw + 1.0) * 0.5
        arg = c1 * t + c2
        valid &= arg > 0
        gt = gt * (c0 * c1 / dr.select(arg > 0, arg, 1.0))
    j00, j01 = dr.dot(gs, ds.dx), dr.dot(gs, ds.dy)
    j10, j11 = dr.dot(gt, ds.dx), dr.dot(gt, ds.dy)
    det = j00 * j11 - j01 * j10
    valid &= dr.abs(det) > DET_FLOOR
    det = dr.select(dr.abs(det) > DET_FLOOR, det, DET_FLOOR)
    inv_det = 1.0 / det
    # F = J^-1: ds = (j11, -j10)/det, dt = (-j01, j00)/det.
    h = (j00 * j00 + j01 * j01 + j10 * j10 + j11 * j11) * inv_det * inv_det
    a = dr.sqrt(dr.square(j11 - j01) + dr.square(j00 - j10)) * dr.abs(inv_det)  # |ds + dt|
    b = dr.sqrt(dr.square(j11 + j01) + dr.square(-j10 - j00)) * dr.abs(inv_det)  # |ds - dt|
    return h, dr.maximum(a, b), valid


def _clip_gradients(P, X):
    """The one projective gradient both kernels use: clip coordinates c_i = row_i . X + P_i3 of the
    points X, c_w kept above W_FLOOR (`valid` where it was), 1 / c_w^2, and the numerators of
    d(c_i / c_w)/dX = (row_i c_w - c_i row_w) / c_w^2 for i = 0 (s) and 1 (t)."""
    import drjit as dr  # lazy: drjit reads DRJIT_LIBLLVM_PATH on import (solvers.jit.llvm_ad sets it)

    ad = llvm_ad()
    rows = [ad.Array3f64(P[4 * i], P[4 * i + 1], P[4 * i + 2]) for i in range(4)]
    c = [dr.dot(rows[i], X) + P[4 * i + 3] for i in range(4)]
    cw = c[3]
    valid = cw > W_FLOOR
    cw = dr.select(valid, cw, W_FLOOR)
    inv_w2 = 1.0 / (cw * cw)
    return c, cw, valid, inv_w2, rows[0] * cw - c[0] * rows[3], rows[1] * cw - c[1] * rows[3]


def warped_moments_kernel(P, ds: DeviceSamples):
    """(Σ w G00, Σ w G01, Σ w G11, Σ w, lost weight) for the 2D map q = (c0/cw, c1/cw) of P (acting on
    re-centred points): G = (J_q J_q^T)^-1, J_q = dq/dx per full-resolution pixel. For any affine map
    u = A q + b of those coordinates, J = A J_q and h = ||J^-1||_F^2 = tr(G (A^T A)^-1), so the weighted
    mean h of every affine part follows from these three sums (solvers.optimize's "objective" fit)."""
    import drjit as dr  # lazy: drjit reads DRJIT_LIBLLVM_PATH on import (solvers.jit.llvm_ad sets it)

    _, _, valid, inv_w2, ns, nt = _clip_gradients(P, ds.X)
    gs = ns * inv_w2
    gt = nt * inv_w2
    a, b = dr.dot(gs, ds.dx), dr.dot(gs, ds.dy)
    cc, d = dr.dot(gt, ds.dx), dr.dot(gt, ds.dy)
    det = a * d - b * cc
    ok = valid & (dr.abs(det) > 0.0) & dr.isfinite(det)
    inv2 = dr.select(ok, 1.0 / dr.select(ok, det * det, 1.0), 0.0)
    w = dr.select(ok, ds.w, 0.0)
    return (dr.sum(w * (cc * cc + d * d) * inv2), dr.sum(-w * (a * cc + b * d) * inv2),
            dr.sum(w * (a * a + b * b) * inv2), dr.sum(w), dr.sum(dr.select(ok, 0.0, ds.w)))


def warped_moments(matrix: np.ndarray, ds: DeviceSamples) -> np.ndarray:
    """warped_moments_kernel of a recentred NumPy matrix as five floats (frozen kernels, replayed)."""
    import drjit as dr  # lazy: drjit reads DRJIT_LIBLLVM_PATH on import (solvers.jit.llvm_ad sets it)

    if ds.count < 2:
        out = dr.concat(list(warped_moments_kernel(matrix_to_device(matrix), ds)))
    else:
        out = _replay("moments", _moments_of_arrays, matrix, (2.0, 2.0), ds)
    dr.eval(out)
    return np.array(out, dtype=np.float64)  # one array, one read (five reads cost ~3 ms)


def _moments_of_arrays(P16, res2, X, dx, dy, w):
    import drjit as dr  # lazy: drjit reads DRJIT_LIBLLVM_PATH on import (solvers.jit.llvm_ad sets it)

    return dr.concat(list(warped_moments_kernel(_gathered(P16, res2)[0], SimpleNamespace(X=X, dx=dx, dy=dy, w=w))))


def matrix_to_device(matrix: np.ndarray):
    ad = llvm_ad()
    import drjit as dr  # lazy: drjit reads DRJIT_LIBLLVM_PATH on import (solvers.jit.llvm_ad sets it)

    return [dr.opaque(ad.Float64, float(v)) for v in np.asarray(matrix, dtype=np.float64).ravel()]


def log_to_device(smap: ShadowMap):
    if smap.log_warp is None:
        return None
    ad = llvm_ad()
    import drjit as dr  # lazy: drjit reads DRJIT_LIBLLVM_PATH on import (solvers.jit.llvm_ad sets it)

    lw = smap.log_warp
    return tuple(dr.opaque(ad.Float64, float(v)) for v in (lw.c0, lw.c1, lw.c2))


def per_sample(smap: ShadowMap, ds: DeviceSamples):
    """NumPy (h, m, valid) for one map over device samples."""
    import drjit as dr  # lazy: drjit reads DRJIT_LIBLLVM_PATH on import (solvers.jit.llvm_ad sets it)

    M = recentre(smap.matrix, ds.origin)
    if smap.log_warp is None and ds.count >= 2:
        h, m, valid = _replay("footprint", _footprint_of_arrays, M, smap.resolution, ds)
    else:
        h, m, valid = footprint(matrix_to_device(M), smap.resolution, log_to_device(smap), ds)
    dr.eval(h, m, valid)  # one kernel for the three
    return np.array(h), np.array(m), np.array(valid, dtype=bool)


def per_sample_maps(maps: list[ShadowMap], samples: Samples, origin: np.ndarray | None = None):
    """Per-sample h, m for a set of cascades: each sample is scored on the map serving its view depth.

    Returns (h, m, map_index); samples no map serves get h = m = inf and index -1.
    """
    n = len(samples)
    h = np.full(n, np.inf)
    m = np.full(n, np.inf)
    idx = map_for_depth(maps, samples.view_depth) if maps and maps[0].face is None else _cube_index(maps, samples)
    for k, smap in enumerate(maps):
        sel = idx == k
        if not sel.any():
            continue
        ds = device_samples(samples if sel.all() else samples.subset(sel), origin)
        hk, mk, ok = per_sample(smap, ds)
        hk[~ok] = np.inf
        mk[~ok] = np.inf
        h[sel], m[sel] = hk, mk
    return h, m, idx


def _cube_index(maps: list[ShadowMap], samples: Samples) -> np.ndarray:
    """For cube faces: the face whose map contains the sample (first match)."""
    idx = np.full(len(samples), -1, dtype=np.int64)
    for k in range(len(maps) - 1, -1, -1):
        s, t, z, w = maps[k].map_coords(samples.position)
        inside = (w > 0) & (s >= 0) & (s <= 1) & (t >= 0) & (t <= 1)
        idx[inside] = k
    return idx


def predicted_misclassified(h: np.ndarray, pixels: np.ndarray | None = None,
                            weight: np.ndarray | None = None) -> float:
    """Predicted misclassified full-resolution pixels: K Σ_i a_i w'_i √h_i, a_i = full-resolution pixels
    each sample stands for (Samples.pixels), w'_i = w_i Σa / Σ a w (the weights, normalised so that
    uniform weights give 1), K = MISCLASSIFIED_K.

    √h = ||F||_F is the texel footprint's size in pixels (Chong & Gortler 2007 eqs. 6 and 9): along a
    shadow edge the band of wrongly shadowed pixels is about one footprint wide, so the count grows
    with the boundary pixels times the footprint. A count, unlike the objective (a mean), ranks
    solutions across suns with different amounts of shadow boundary: pooled Spearman against
    measured misclassified pixels on the corpus 0.80 (the objective: 0.41). inf if any h is not finite."""
    h = np.asarray(h, dtype=np.float64)
    if len(h) == 0:
        return 0.0
    if not np.isfinite(h).all():
        return float("inf")
    a = np.ones(len(h)) if pixels is None else np.asarray(pixels, dtype=np.float64)
    w = np.ones(len(h)) if weight is None else np.asarray(weight, dtype=np.float64)
    aw = float(np.sum(a * w))
    if aw <= 0:
        return 0.0
    return float(MISCLASSIFIED_K * np.sum(a * w * np.sqrt(np.maximum(h, 0.0))) * float(np.sum(a)) / aw)


def error_stats(h: np.ndarray, m: np.ndarray, weight: np.ndarray | None = None,
                pixels: np.ndarray | None = None) -> dict:
    """The predicted_error / measured_error fields. `objective` is the weighted mean of h;
    `misclassified_pixels` (predicted_misclassified) only when `pixels` (a_i) is given."""
    n = int(len(m))
    if n == 0:
        out = {"objective": 0.0, "mean_m": 0.0, "median_m": 0.0, "p95_m": 0.0, "max_m": 0.0,
               "frac_m_gt_1": 0.0, "samples": 0}
        if pixels is not None:
            out["misclassified_pixels"] = 0.0
        return out
    finite = np.isfinite(h) & np.isfinite(m)
    out = {
        "objective": objective_of(h, m, weight),
        "mean_m": float(np.mean(m)) if finite.all() else float("inf"),
        "median_m": float(np.median(m)),
        "p95_m": float(np.percentile(m, 95)),
        "max_m": float(np.max(m)),
        "frac_m_gt_1": float(np.mean(m > 1.0)),
        "samples": n,
    }
    if pixels is not None:
        out["misclassified_pixels"] = predicted_misclassified(h, pixels, weight)
    return out


def objective_of(h: np.ndarray, m: np.ndarray, weight: np.ndarray | None = None) -> float:
    """The `objective` field: the weighted mean of h (inf if any sample's h or m is not finite)."""
    if len(m) == 0:
        return 0.0
    w = np.ones(len(m)) if weight is None else np.asarray(weight, dtype=np.float64)
    if not (np.isfinite(h) & np.isfinite(m)).all():
        return float("inf")
    return float(np.sum(w * h) / np.sum(w))


def texel_limit(samples: Samples, texels: int) -> float:
    """The least weighted mean h any map of `texels` texels (any warp, projective or not) can reach on
    these samples: 2 (Σ a_i √w_i)² / (T Σ a_i w_i), a_i = samples.pixels (full-resolution pixels each
    sample stands for), w_i = samples.weight, T = texels.

    Derivation, checked against the metric above (Chong & Gortler 2007 eqs. 6 and 9): J = du/dx is in
    texels per full-resolution pixel, so det J is the texel area one pixel covers, and
    h = ||J^-1||_F^2 = ||J||_F^2 / det(J)^2 >= 2 |det J| / det(J)^2 = 2 / |det J|
    (||J||_F^2 = σ1² + σ2² >= 2 σ1 σ2 = 2 |det J|, equal for a conformal J). The pixels a sample stands
    for cover about a_i |det J_i| texels, and pixels seeing distinct light-space points use distinct
    texels, so Σ a_i |det J_i| <= T. Minimising Σ a_i w_i 2/d_i under Σ a_i d_i = T (Lagrange:
    w_i / d_i² equal) gives d_i = T √w_i / Σ a_j √w_j and Σ a_i w_i h_i >= 2 (Σ a_i √w_i)² / T; the
    objective is the mean weighted by w_i, so with a_i equal for all samples (one coarse pixel each,
    the service's case) this bounds it. Uniform weights over N pixels: 2N/T, which the
    constant-footprint map reaches on a plane (Chong 2003 Theorem 1). It stays a lower bound when the
    map also covers receivers that are not samples. It assumes the samples' pixels do not share
    texels: visible receivers behind one another along the light (a shadowed floor under its caster)
    may share them, and there a map could beat it by at most the depth complexity.
    Grazing rule: where samples.py turned a normal, the metric's J is that of the turned tangent plane,
    which claims f_i = samples.light_area_factor times the light-space area per pixel the surface
    really covers, so the pixel spends d_i / f_i texels; the same Lagrange step with Σ a_i d_i / f_i = T
    gives 2 (Σ a_i √(w_i / f_i))² / (T Σ a_i w_i). Discretisation: a map has to contain the sample
    centres only, which lie half a sample spacing inside the area their pixels cover, so on a plane
    the optimum sits up to about one sample spacing per side below the bound (measured 0.977 of it for
    a 64-sample-wide view at 512²)."""
    n = len(samples)
    if n == 0 or texels <= 0:
        return 0.0
    w = np.asarray(samples.weight, dtype=np.float64)
    a = np.ones(n) if samples.pixels is None else np.asarray(samples.pixels, dtype=np.float64)
    f = getattr(samples, "light_area_factor", None)
    f = np.ones(n) if f is None else np.maximum(np.asarray(f, dtype=np.float64), 1e-300)
    den = float(np.sum(a * w))
    return 2.0 * float(np.sum(a * np.sqrt(w / f))) ** 2 / (float(texels) * den) if den > 0 else 0.0


def with_limit(stats: dict, samples: Samples, texels: int) -> dict:
    """stats (error_stats' dict) with `limit` (texel_limit) and `ratio_to_limit` (objective / limit)."""
    lim = texel_limit(samples, texels)
    stats["limit"] = lim
    obj = stats.get("objective", 0.0)
    stats["ratio_to_limit"] = float(obj / lim) if lim > 0 and math.isfinite(obj) else (
        None if lim <= 0 else float("inf"))
    return stats


def sample_pixels(samples: Samples) -> np.ndarray:
    """a_i: full-resolution pixels each sample stands for (one each when Samples.pixels is None)."""
    return np.ones(len(samples)) if samples.pixels is None else np.asarray(samples.pixels, dtype=np.float64)


def map_texels(maps: list[ShadowMap]) -> int:
    return int(sum(int(m.resolution[0]) * int(m.resolution[1]) for m in maps))


def predicted_objective(maps: list[ShadowMap], samples: Samples, origin: np.ndarray | None = None) -> float:
    """predicted_error(...)["objective"] alone (no percentiles): to score candidate maps."""
    h, m, _ = per_sample_maps(maps, samples, origin)
    return objective_of(h, m, samples.weight)


def predicted_error(maps: list[ShadowMap], samples: Samples, origin: np.ndarray | None = None) -> dict:
    """`predicted_error` of a solution's maps for one light's samples."""
    h, m, idx = per_sample_maps(maps, samples, origin)
    stats = error_stats(h, m, samples.weight, sample_pixels(samples))
    stats["unserved_samples"] = int(np.sum(idx < 0))
    return with_limit(stats, samples, map_texels(maps))


def objective(P, resolution, log_warp, ds: DeviceSamples):
    """Weighted mean h as a Dr.Jit Float64 (differentiable with respect to P and log_warp); infinite
    when a weighted sample has no valid footprint (behind the projection's centre, a degenerate J),
    as objective_of() says for the prediction: a map cannot lower its score by losing samples."""
    import drjit as dr  # lazy: drjit reads DRJIT_LIBLLVM_PATH on import (solvers.jit.llvm_ad sets it)

    h, _, valid = footprint(P, resolution, log_warp, ds)
    w = dr.select(valid, ds.w, 0.0)
    lost = dr.sum(dr.select(valid, 0.0, ds.w))
    mean = dr.sum(w * h) / dr.maximum(dr.sum(w), 1e-300)
    return dr.select(lost > 0.0, dr.inf, mean)


_frozen = {"lock": threading.Lock()}


def objective_value(matrix: np.ndarray, resolution, ds: DeviceSamples) -> float:
    """float(objective(...)) of a recentred matrix without a log warp, as the optimizer's inner loop
    needs it: the kernels are traced once and replayed (dr.freeze, the matrix and resolution passed
    as device arrays), the same operations, so the same value; half the time of tracing each call."""
    if ds.count < 2:  # a one-sample (scalar) or empty configuration: trace as usual
        return float(objective(matrix_to_device(matrix), resolution, None, ds)[0])
    return float(_replay("objective", _objective_of_arrays, matrix, resolution, ds)[0])


def _replay(name: str, fn, matrix: np.ndarray, resolution, ds: DeviceSamples):
    """fn(matrix entries, resolution, ds.X, ds.dx, ds.dy, ds.w) frozen (dr.freeze): traced on the
    first call for a configuration, replayed after. One replay at a time: solves run in threads."""
    P16 = llvm_ad().Float64(aligned(np.asarray(matrix, dtype=np.float64).ravel(), np.float64))
    res2 = _resolution_array(float(resolution[0]), float(resolution[1]))
    with _frozen["lock"]:
        if name not in _frozen:
            import drjit as dr  # lazy: drjit reads DRJIT_LIBLLVM_PATH on import (solvers.jit.llvm_ad sets it)

            _frozen[name] = dr.freeze(fn, limit=8)
        return _frozen[name](P16, res2, ds.X, ds.dx, ds.dy, ds.w)


@lru_cache(maxsize=16)
def _resolution_array(width: float, height: float):
    return llvm_ad().Float64(aligned(np.array([width, height]), np.float64))


def _objective_of_arrays(P16, res2, X, dx, dy, w):
    """objective() with the 16 matrix entries and the resolution read from device arrays."""
    return objective(*_gathered(P16, res2), None, SimpleNamespace(X=X, dx=dx, dy=dy, w=w))


def _footprint_of_arrays(P16, res2, X, dx, dy, w):
    """footprint() with the 16 matrix entries and the resolution read from device arrays."""
    return footprint(*_gathered(P16, res2), None, SimpleNamespace(X=X, dx=dx, dy=dy, w=w))


def _gathered(P16, res2):
    import drjit as dr  # lazy: drjit reads DRJIT_LIBLLVM_PATH on import (solvers.jit.llvm_ad sets it)

    ad = llvm_ad()
    return ([dr.gather(ad.Float64, P16, i) for i in range(16)],
            (dr.gather(ad.Float64, res2, 0), dr.gather(ad.Float64, res2, 1)))
