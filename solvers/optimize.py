"""Scene-optimized light matrices: one entry point in the spirit of scipy.optimize.minimize.

Parameterization (Chong & Gortler 2007, directional light). The light position is the point at
infinity [l, 0], so rows 1, 2 and 4 of P annihilate it: the fourth (projective) row's normal is
perpendicular to l, which leaves two projective degrees of freedom besides the six affine ones:
- φ, the warp axis angle in the light's image plane (rotation about l; 0 = the view direction
  projected into the image plane, LiSPSM's axis, solvers.light_frames.directional_view);
- the warp strength u = log(1 + D/n'), n' the distance from the receivers' near end to the warp
  centre along the axis (LiSPSM's n is one choice) and D the receivers' depth along the axis.
  u = 0 is no warp (n' = ∞, the focused map), u > 0 a perspective warp (u ≈ D/n' for weak warps,
  ≈ log(D/n') for strong ones), u < 0 a warp centred beyond the far end. Unlike log n' this
  variable is smooth through the no-warp map, so a gradient step can leave the focused start.
Given (φ, u) the six affine degrees of freedom are not searched: they are fitted around every
receiver and sample in warped space, so that no receiver leaves the map, then padded PAD_TEXELS
texels in map space (after the warp). Default `affine="objective"`: among the parallelograms with
sides along two of the warped hull's edge normals or their perpendiculars (both s/t assignments), the
one with the least objective, exact from one metric pass (solvers.metric.warped_moments:
h = tr(Ḡ A^-1 A^-T) for the affine part A); "parallelogram" (minimum area), "rectangle" and "axis"
also exist. Only the vertices of the points' hull in the light plane
(solvers.fitting.light_plane_hull) and the two depth extremes enter the fit: the warp is a 2D
projective map of light-plane coordinates, so hulls are kept. The family contains focused (u = 0,
φ = its minimum-area rectangle's angle), LiSPSM (φ = 0, n' = n_opt), LogPSM's perspective part
(φ = 0, n' from η) and the constant-footprint map of the receivers' best plane (Chong 2003
Theorem 1, Problem.plane_x); those are the starting points, and the baseline maps themselves are
candidates, so the result is never worse than the best of them.

Objective: solvers.metric.objective (the weighted mean of Chong & Gortler's h), the number the
solution predicts. Gradient with respect to (φ, u), `gradient="ad"` (default): Dr.Jit AD gives
df/dP exactly for the 16 entries of P (affine part fixed, as the paper does for its step); the
refit's dependence dP/d(φ, u) comes from central differences of the NumPy fit (no metric
evaluation), and the chain rule joins them: one metric pass per gradient. `gradient="fd"`:
central differences of f (four metric passes). The fit is a min/max over the receivers' hull and a
minimum over the candidate parallelograms, so f is continuous but only piecewise smooth; both
gradients agree away from the kinks (tests/test_optimize.py). The searches over (φ, u) (NLopt, torch,
Chong & Gortler's line search) are in solvers.search_methods.
"""
from __future__ import annotations

import copy
import math
import time
from dataclasses import dataclass, field

import numpy as np

from .baselines import PAD, SPOT_AS_CUBE_DEG, baseline
from .cameras import Camera
from .depth_modes import with_bias
from .fitting import (box_corners, convex_hull_2d, extent_floor, frustum, light_plane_hull, min_area_rectangle, ortho,
                      padded, padded_range, perspective_near, rotation_z, to_view)
from .light_frames import directional_view, look_matrix, spot_view
from .lights import DirectionalLight, PointLight, SpotLight
from .metric import (device_samples, log_to_device, matrix_to_device, objective, objective_value, recentre,
                     serial_kernels, warped_moments)
from .samples import Samples
from .search_methods import DEFAULT_METHOD, EXTRA_METHODS, METHODS, TimeBudgetReached, search
from .shadow_map import ShadowMap
from .warp import log_warp, padded_log

PHI_MAX = math.pi / 2
# n' from D/1e4 before the receivers' near end (u = U_MAX) through no warp (u = 0) to D/1e4 beyond their
# far end (u = U_MIN: n' = -D (1 + 1e-4)): the warp centre may lie next to either end of the receivers
# (a camera just above a plane needs it at the near end; a light behind a camera looking down, whose
# warp axis points from the far receivers to the near ones, needs it beyond the far end).
U_MAX = math.log1p(1e4)
U_MIN = -U_MAX
PAD_TEXELS = 1.0  # map-space padding: texels kept free on each side of the fitted box, after the warp (the
# baselines' rule, fitting.texel_margin, in Python floats for the inner loop)
U_LOG_MIN = math.log1p(1e-3)  # the log warp needs a finite n' before the receivers (n' <= 1000 D)
START_NAMES = ("focused", "lispsm", "logpsm-perspective")
FIT_STEP = 1e-6  # central-difference step of the refit dP/d(φ, u) (NumPy only, no metric pass)
FD_STEP = 1e-4  # central-difference step of f for gradient="fd"


@dataclass
class OptimizeResult:
    x: np.ndarray  # (φ, u)
    fun: float  # the metric's objective (weighted mean h) of `map`
    nit: int
    nfev: int  # metric evaluations (values and gradient passes)
    time_ms: float
    success: bool
    message: str
    map: ShadowMap | None = None
    start: str = ""  # the starting point the optimizer ran from (or the baseline returned)
    starts: dict = field(default_factory=dict)  # objective of every start (baseline maps)
    njev: int = 0

    def to_json(self) -> dict:
        return {"x": [float(v) for v in self.x], "fun": self.fun, "nit": self.nit, "nfev": self.nfev,
                "njev": self.njev, "time_ms": round(self.time_ms, 3), "success": self.success,
                "converged": self.success, "message": self.message, "start": self.start,
                "starts": {k: float(v) for k, v in self.starts.items()}}


def robust_difference(fm, f0, fp, h):
    """Central difference, or the one-sided one with the smaller change when the two sides disagree
    (the fit switches hull edges: the other side jumps)."""
    dp, dm = (fp - f0) / h, (f0 - fm) / h
    scale = max(float(np.max(np.abs(dp))), float(np.max(np.abs(dm))), 1e-300)
    if float(np.max(np.abs(dp - dm))) <= 1e-2 * scale + 1e-12:
        return 0.5 * (dp + dm)
    return dp if float(np.sum(dp * dp)) < float(np.sum(dm * dm)) else dm


AFFINE_FITS = ("axis", "rectangle", "parallelogram", "objective")


def _hull_normals(q: np.ndarray, is_hull: bool):
    """(hull, unit normals): each hull edge's normal and its perpendicular (2k normals)."""
    hull = _ccw(q) if is_hull else convex_hull_2d(q)
    e = _next(hull) - hull
    length = np.sqrt(e[:, 0] * e[:, 0] + e[:, 1] * e[:, 1])
    e, length = e[length > 0], length[length > 0]
    n = np.column_stack([-e[:, 1], e[:, 0]]) / length[:, None]
    return hull, np.vstack([n, np.column_stack([-n[:, 1], n[:, 0]])])


def _objective_affine(hn, G: np.ndarray, resolution):
    """The affine part that minimises the weighted mean h among the parallelograms around q with
    sides along two of the hull's edge normals or their perpendiculars (the minimum-area
    parallelogram and every flush rectangle included), both assignments of the two to s and t: with
    u = A q + b and A = diag(α, β) N (N the two unit normals, α, β texels per unit across the hull's
    widths), h = tr(Ḡ A^-1 A^-T) = c0ᵀḠc0/α² + c1ᵀḠc1/β², c0, c1 the columns of N^-1, Ḡ the samples'
    mean (J_q J_q^T)^-1 (solvers.metric.warped_moments). hn: _hull_normals of the warped fit points
    (None: fewer than three). Returns ((i, j) or None, value)."""
    g00, g01, g11, wsum, lost = (float(v) for v in G)
    if hn is None or lost > 0 or not wsum > 0:
        return None, math.inf
    hull, n = hn
    if len(hull) < 3 or len(n) < 2:
        return None, math.inf
    g00, g01, g11 = g00 / wsum, g01 / wsum, g11 / wsum
    proj = hull @ n.T
    width = proj.max(0) - proj.min(0)
    W, H = float(resolution[0]), float(resolution[1])
    a = (W - 2 * PAD_TEXELS) / np.maximum(width, 1e-300)  # texels per unit across each width, along s
    b = (H - 2 * PAD_TEXELS) / np.maximum(width, 1e-300)  # ... along t
    # N^-1 = [[nj1, -ni1], [-nj0, ni0]] / det: c0 = ±n_j⊥ / det, c1 = ±n_i⊥ / det (⊥: a quarter turn), so
    # h(i, j) = (Q(n_j⊥) / a_i² + Q(n_i⊥) / b_j²) / det_ij², Q(v) = vᵀḠv
    nx, ny = n[:, 0], n[:, 1]
    qp = g00 * ny * ny - 2.0 * g01 * nx * ny + g11 * nx * nx
    det = np.outer(nx, ny) - np.outer(ny, nx)
    d2 = det * det
    ok = d2 > 1e-18
    val = np.where(ok, (qp[None, :] / (a * a)[:, None] + qp[:, None] / (b * b)[None, :]) / np.where(ok, d2, 1.0), np.inf)
    i, j = np.unravel_index(int(np.argmin(val)), val.shape)
    v = float(val[i, j])
    return ((int(i), int(j)), v) if math.isfinite(v) else (None, math.inf)


def _affine_from_choice(q: np.ndarray, hn, choice, is_hull: bool):
    """affine_fit's (C, lo, hi) for the normals `choice` = (i, j) of hn = _hull_normals(q) (the
    minimum-area parallelogram when choice is None)."""
    if choice is None or hn is None:
        return affine_fit(q, "parallelogram", (1, 1), is_hull)
    n = hn[1]
    if max(choice) >= len(n):
        return affine_fit(q, "parallelogram", (1, 1), is_hull)
    a, b = n[choice[0]], n[choice[1]]
    C = np.eye(4)
    C[:2, :2] = [a if a[0] >= 0 else -a, b if b[1] >= 0 else -b]  # signs do not change h
    r = q @ C[:2, :2].T
    return C, r.min(0), r.max(0)


def _padded_box(lo: list, hi: list, resolution, pad_t: bool = True) -> tuple[tuple[float, float], tuple[float, float]]:
    """The fitted 2D box (warped, after the affine part) grown so that PAD_TEXELS texels of the map
    lie outside it on each side (padding in map space, after the warp: a world-space pad before the
    warp would be magnified at the dense end and would keep the warp centre away from the receivers),
    each side at least the extent floor. pad_t=False leaves t unpadded (the log family pads t after
    its log step, warp.padded_log, as the LogPSM baseline does)."""
    floor = extent_floor(max(abs(v) for v in lo + hi))
    out = []
    for k in (0, 1):
        a, b = lo[k], hi[k]
        size = max(b - a, floor)
        n = float(resolution[k])
        margin = size * PAD_TEXELS / max(n - 2.0 * PAD_TEXELS, 1.0) if (k == 0 or pad_t) else 0.0
        pad = margin + max(floor - (b - a), 0.0) / 2 + 1e-12 * size
        out.append((a - pad, b + pad))
    return out[0], out[1]


def _finite_rows(p: np.ndarray) -> np.ndarray:
    """The rows of p without a NaN or infinity (p itself when all are finite, the usual case)."""
    return p if np.isfinite(p).all() else p[np.all(np.isfinite(p), axis=1)]


def _next(a: np.ndarray) -> np.ndarray:
    """np.roll(a, -1, axis=0) (each vertex's successor), without roll's overhead."""
    return np.concatenate((a[1:], a[:1]))


def _ccw(hull: np.ndarray) -> np.ndarray:
    """Hull vertices in counter-clockwise order (reversed if given clockwise)."""
    x, y = hull[:, 0], hull[:, 1]
    area2 = float(np.dot(x, _next(y)) - np.dot(y, _next(x)))
    return hull if area2 >= 0 else hull[::-1]


def affine_fit(q: np.ndarray, how: str, resolution, is_hull: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The affine part, fitted in warped space to the points q (N, 2): a 4x4 C acting on warped
    homogeneous coordinates (x, y only) and the box [lo, hi] the map's s, t span after it.
    axis: the axis-aligned box (solvers.baselines._fit_warped); rectangle: the minimum-area rectangle
    (Chong & Gortler 2007 §2.3); parallelogram: the minimum-area enclosing parallelogram (two pairs
    of parallel lines, each flush with a hull edge), which also fits the skew: on a planar receiver
    with the right warp the visible region is then the whole map (Chong 2003 Theorem 1)."""
    C = np.eye(4)
    if how == "axis" or len(q) < 3:
        return C, q.min(0), q.max(0)
    hull = _ccw(q) if is_hull else convex_hull_2d(q)  # q: hull vertices in order (light_plane_hull)
    if len(hull) < 3:
        return C, q.min(0), q.max(0)
    if how == "rectangle":
        a, lo, hi = min_area_rectangle(hull)
        ext = hi - lo
        if (ext[0] < ext[1]) != (resolution[0] < resolution[1]) and resolution[0] != resolution[1]:
            a += math.pi / 2
        c, s = math.cos(a), math.sin(a)
        C[:2, :2] = [[c, s], [-s, c]]
    elif how == "parallelogram":
        e = _next(hull) - hull
        length = np.sqrt(e[:, 0] * e[:, 0] + e[:, 1] * e[:, 1])  # np.linalg.norm(e, axis=1), bit for bit
        if not (length > 0).all():
            e, length = e[length > 0], length[length > 0]
        n = np.column_stack([-e[:, 1], e[:, 0]]) / length[:, None]
        proj = hull @ n.T  # (hull, edges)
        width = proj.max(0) - proj.min(0)
        sin = np.abs(n[:, 0, None] * n[None, :, 1] - n[:, 1, None] * n[None, :, 0])
        area = np.divide(width[:, None] * width[None, :], sin, out=np.full(sin.shape, np.inf), where=sin > 1e-9)
        i, j = np.unravel_index(int(np.argmin(area)), area.shape)
        if not np.isfinite(area[i, j]):
            return C, q.min(0), q.max(0)
        a, b = n[i], n[j]
        # Canonical order and signs (h does not change under them, the chain-rule gradient would):
        # s along the normal nearer warped x, both rows with a positive diagonal.
        if resolution[0] != resolution[1]:  # s along the wider normal when the map is wider
            if (width[i] < width[j]) != (resolution[0] < resolution[1]):
                a, b = b, a
        elif abs(a[0]) < abs(b[0]):
            a, b = b, a
        C[:2, :2] = [a if a[0] >= 0 else -a, b if b[1] >= 0 else -b]
    else:
        raise ValueError(f"affine must be one of {', '.join(AFFINE_FITS)}, got {how!r}")
    r = q @ C[:2, :2].T
    return C, r.min(0), r.max(0)


class Problem:
    """f(φ, u) for one directional light, one map, fixed samples and receivers."""

    def __init__(self, camera: Camera, light: DirectionalLight, samples: Samples, receivers: np.ndarray,
                 casters_bounds, resolution, deadline: float | None = None, gradient: str = "ad",
                 affine: str = "objective", log: bool = False, fit_points: tuple | None = None):
        if log:  # LogPSM's family: t along the warp axis, the log warp on it, finite differences
            affine, gradient = "axis", "fd"
        if gradient not in ("ad", "fd"):
            raise ValueError(f"gradient must be 'ad' or 'fd', got {gradient!r}")
        self.camera, self.light, self.resolution = camera, light, (int(resolution[0]), int(resolution[1]))
        hull, extremes = fit_points if fit_points is not None else self._hull(light, samples, receivers)
        self.n_hull = len(hull) if len(extremes) else 0  # 0: no ordered hull (few or degenerate points)
        self.fit_pts = np.vstack([hull, extremes])
        self.corners = box_corners(np.asarray(casters_bounds[0], float), np.asarray(casters_bounds[1], float))
        self.ds = device_samples(samples, camera.position)
        self.sample_pos, self.sample_w = samples.position, samples.weight
        self.view0 = directional_view(light, camera)
        self.deadline = deadline
        self.gradient_mode = gradient
        if affine not in AFFINE_FITS:
            raise ValueError(f"affine must be one of {', '.join(AFFINE_FITS)}, got {affine!r}")
        self.affine = affine
        self.last_choice, self.last_value, self.choices = None, math.inf, {}
        self.nfev = 0
        self.njev = 0
        self.seen: dict = {}  # f at each point evaluated
        self.best = (math.inf, None, None)
        self.lower, self.upper = np.array([-PHI_MAX, U_LOG_MIN if log else U_MIN]), np.array([PHI_MAX, U_MAX])
        self.log = log

    @staticmethod
    def _hull(light, samples: Samples, receivers) -> tuple[np.ndarray, np.ndarray]:
        """light_plane_hull of the finite receivers and samples (what the fit needs of them)."""
        receivers = np.asarray(receivers, dtype=np.float64).reshape(-1, 3)
        fit = _finite_rows(np.vstack([receivers, samples.position]) if len(samples) else receivers)
        if len(fit) == 0:
            raise ValueError("no receivers and no samples to fit the map to")
        return light_plane_hull(light.direction, fit)

    def plane_x(self) -> np.ndarray | None:
        """The start for the receivers' best plane: the family member whose projective divisor w' is
        the camera's view depth as fitted over the samples, view depth ≈ a x + b y + c in light-view
        coordinates (weighted least squares). On a planar receiver that is the map whose texel
        coordinates are an affine image of the screen's, the constant footprint of Chong 2003
        Theorem 1 (its vanishing line is where the plane meets the camera's view-depth-0 plane); w'
        must annihilate the light direction, and an affine function of (x, y) does. The warp axis is
        the fitted depth gradient (φ = atan2(-a, b) for view = rotation_z(φ) @ view0, folded into
        [-π/2, π/2] by reversing the axis, which turns u into -u), and e^u is the ratio of the fitted
        depths at the fit points' far and near ends along it. None without three samples."""
        pts = self.sample_pos
        if len(pts) < 3:
            return None
        v = to_view(self.view0, pts)
        depth = (pts - self.camera.position) @ self.camera.forward
        sw = np.sqrt(np.asarray(self.sample_w, float))
        A = np.column_stack([v[:, 0], v[:, 1], np.ones(len(v))]) * sw[:, None]
        (a, b, c), *_ = np.linalg.lstsq(A, depth * sw, rcond=None)
        g = math.hypot(a, b)
        scale = max(float(np.abs(depth).max()), 1e-300)
        if not math.isfinite(g) or g * max(float(np.ptp(v[:, 0])), float(np.ptp(v[:, 1]))) < 1e-6 * scale:
            return None  # depth does not vary across the light's image plane: no warp (focused)
        phi = math.atan2(-a, b)
        y0, y1 = self._warp_range(to_view(rotation_z(phi) @ self.view0, self.fit_pts))
        d0, d1 = g * y0 + c, g * y1 + c  # rotation_z(φ) has y' = (a x + b y) / g, depth = g y' + c
        u = math.log(d1 / d0) if d0 > 0 else self.upper[1]
        sign = 1.0
        if phi > PHI_MAX:
            phi, sign = phi - math.pi, -1.0
        elif phi < -PHI_MAX:
            phi, sign = phi + math.pi, -1.0
        return self.clip([phi, sign * u])

    # -------------------------------------------------------------- the family
    def fit(self, x):
        """(view, projection, content depth, n') of the map with projective parameters x = (φ, u): the content
        depth is [nearest fit point or scene corner, farthest fit point] along the light's -Z (the map's
        light_depth is its frustum's range, map_for)."""
        view, proj, v, dv = self._fit(x)
        d = np.concatenate([-v[:, 2], -dv[:, 2]])
        u = float(x[1])
        y0, y1 = self._warp_range(v)
        n_prime = math.inf if abs(u) < 1e-12 else (y1 - y0) / math.expm1(u)
        return view, proj, (float(d.min()), float(-v[:, 2].min())), n_prime

    def _fit(self, x, choice=None, fresh=False, value_only=False):
        """(view, projection, fit points and corners in the view) for x = (φ, u). affine="objective":
        `choice` (the two hull normals of the affine part) as chosen at x, or None to choose it (one
        metric pass: solvers.metric.warped_moments; the choice made at an x before is reused unless
        `fresh`); the chosen value is left in last_value. `value_only` (affine="objective"): stop once
        the choice and its value are made (the objective evaluation needs no matrix); returns None."""
        phi, u = float(x[0]), float(x[1])
        view = rotation_z(phi) @ self.view0  # warp axis: +Y of the rotated frame
        v = to_view(view, self.fit_pts)
        dv = to_view(view, self.corners)
        y0, y1 = self._warp_range(v)
        k = math.expm1(u) / (y1 - y0)  # w' = 1 + k (y - y0): 1 at the near end, e^u at the far end
        W = np.array([[1.0, 0, 0, 0], [0, 1.0, 0, -y0], [0, 0, 1.0, 0], [0, k, 0, 1.0 - k * y0]])
        wv = 1.0 + k * (v[:, 1] - y0)
        if not value_only:
            near, far = self._depth_range(v, dv, wv, k, y0, y1)
        h = self.n_hull or len(v)
        q = np.column_stack([v[:h, 0] / wv[:h], (v[:h, 1] - y0) / wv[:h]])
        if self.affine == "objective":
            hn = _hull_normals(q, self.n_hull > 0) if len(q) >= 3 else None
            key = (phi, u)
            if choice is None and not fresh:
                choice = self.choices.get(key)
            if choice is None:
                G = warped_moments(recentre(W @ view, self.ds.origin), self.ds)
                self.nfev += 1
                choice, self.last_value = _objective_affine(hn, G, self.resolution)
                self.choices[key] = choice
            if value_only:
                self.last_choice = choice
                return None
            C, lo, hi = _affine_from_choice(q, hn, choice, self.n_hull > 0)
            self.last_choice = choice
        else:
            C, lo, hi = affine_fit(q, self.affine, self.resolution, self.n_hull > 0)
        (s0, s1), (t0, t1) = _padded_box(lo.tolist(), hi.tolist(), self.resolution, pad_t=not self.log)
        span = max(far - near, 1e-9 * max(abs(near), abs(far), 1.0))
        proj = ortho(s0, s1, t0, t1, near - 0.01 * span, far + 0.01 * span) @ C @ W
        return view, proj, v, dv

    @staticmethod
    def _warp_range(v: np.ndarray) -> tuple[float, float]:
        """[y0, y1]: the fit points' extent along the warp axis (light-view +Y), not padded (the map is
        padded after the warp, _padded_box), at least the extent floor."""
        lo, hi = float(v[:, 1].min()), float(v[:, 1].max())
        return padded_range(lo, hi, 0.0, extent_floor(float(np.abs(v[:, 1]).max())))

    @staticmethod
    def _depth_range(v, dv, wv, k: float, y0: float, y1: float) -> tuple[float, float]:
        """Warped depth extremes: the fit points and the scene corners slid along y to y0 and y1 (a
        caster that shadows a receiver lies on the receiver's light ray, so within that range); depth
        z / w' is linear along each light ray (w' is constant on it)."""
        zv = v[:, 2] / wv
        hi, lo = [float(zv.max())], [float(zv.min())]
        zc_hi, zc_lo = float(dv[:, 2].max()), float(dv[:, 2].min())
        for w in (1.0 + k * (y0 - y0), 1.0 + k * (y1 - y0)):
            if w > 0:  # division by a positive number keeps the order: the extremes' quotients
                hi.append(zc_hi / w)
                lo.append(zc_lo / w)
            else:
                hi.append(float((dv[:, 2] / w).max()))
                lo.append(float((dv[:, 2] / w).min()))
        return -max(hi), -min(lo)

    def matrix(self, x, choice=None) -> np.ndarray:
        view, proj, _, _ = self._fit(x, choice)
        return recentre(proj @ view, self.ds.origin)

    def map_for(self, x) -> ShadowMap:
        view, proj, ld, n_prime = self.fit(x)
        warped = math.isfinite(n_prime)
        smap = ShadowMap(view, proj, self.resolution, light_depth=ld,
                         warp_kind="perspective" if warped else "none", n_prime=n_prime if warped else None)
        if self.log and warped:
            smap.log_warp, smap.warp_kind = self.log_warp_for(x), "log"
        smap.light_depth = smap.frustum_depth_range() or ld  # what the (warped) frustum covers
        return smap

    def log_warp_for(self, x):
        """LogPSM's log step for the perspective part with parameters x (Lloyd et al. 2007 eq. 78,
        solvers.warp.log_warp): a = n', W = D, the receivers' depth along the warp axis. The perspective
        part's t spans the receivers exactly (t_p = 0 at y0), and the PAD_TEXELS margin is added after the
        log step (warp.padded_log), so the strong warps' dense end keeps its rows (padding before
        the log left up to 18% of them unused)."""
        u = float(self.clip(x)[1])
        n_prime = self.fit(x)[3]
        return padded_log(log_warp(n_prime * math.expm1(u), n_prime), self.resolution[1])

    # -------------------------------------------------------------- objective and gradient
    def check_deadline(self):
        if self.deadline is not None and time.perf_counter() > self.deadline:
            raise TimeBudgetReached()

    def clip(self, x) -> np.ndarray:
        return np.clip(np.asarray(x, dtype=np.float64)[:2], self.lower, self.upper)

    def _record(self, x, f):
        if not math.isfinite(f):
            f = 1e300
        if f < self.best[0]:
            self.best = (f, np.array(x, float), None)
        return f

    def eval_matrix(self, M: np.ndarray) -> float:
        """The metric's objective of a recentred matrix (parameters opaque: no recompiles)."""
        self.nfev += 1
        return objective_value(M, self.resolution, self.ds)

    def eval_map(self, smap: ShadowMap) -> float:
        """The metric's objective of a map (its log warp included)."""
        self.nfev += 1
        M = recentre(smap.matrix, self.ds.origin)
        if smap.log_warp is None:
            return objective_value(M, smap.resolution, self.ds)
        return float(objective(matrix_to_device(M), smap.resolution, log_to_device(smap), self.ds)[0])

    def value(self, x) -> float:
        """f(x), each point evaluated once (solvers revisit points: BOBYQA starts at a start)."""
        self.check_deadline()
        x = self.clip(x)
        key = (float(x[0]), float(x[1]))
        if key not in self.seen:
            self.seen[key] = self._evaluate(x)
        return self._record(x, self.seen[key])

    def _evaluate(self, x) -> float:
        if self.affine == "objective" and not self.log:
            self.last_value = math.inf
            self._fit(x, fresh=True, value_only=True)  # the moments pass: the objective of the best affine part
            return self.last_value
        if self.log:
            self.nfev += 1
            return float(objective(matrix_to_device(self.matrix(x)), self.resolution,
                                   log_to_device(self.map_for(x)), self.ds)[0])
        return self.eval_matrix(self.matrix(x))

    def value_and_grad(self, x):
        self.check_deadline()
        x = self.clip(x)
        self.njev += 1
        if self.gradient_mode == "fd":
            f = self.value(x)
            g = np.zeros(2)
            for i in range(2):
                e = np.zeros(2)
                e[i] = FD_STEP
                g[i] = robust_difference(self.value(x - e), f, self.value(x + e), FD_STEP)
            return f, g
        import drjit as dr  # lazy: drjit reads DRJIT_LIBLLVM_PATH on import (solvers.jit.llvm_ad sets it)

        M = self.matrix(x)
        choice = self.last_choice if self.affine == "objective" else None  # the fit's choice held for dP/dx
        P = matrix_to_device(M)
        for p in P:
            dr.enable_grad(p)
        obj = objective(P, self.resolution, None, self.ds)
        dr.backward(obj)
        dfdM = np.array([dr.grad(p)[0] for p in P]).reshape(4, 4)
        f = self._record(x, float(obj[0]))
        self.nfev += 1
        g = np.zeros(2)
        for i in range(2):
            e = np.zeros(2)
            e[i] = FIT_STEP
            g[i] = float(np.sum(dfdM * robust_difference(self.matrix(x - e, choice), M, self.matrix(x + e, choice),
                                                          FIT_STEP)))
        if not np.all(np.isfinite(g)):
            g = np.zeros(2)
        return f, g

    def gradient(self, x) -> np.ndarray:
        return self.value_and_grad(x)[1]


class SpotProblem(Problem):
    """f(α, β) for a spot light's single perspective map: the projective part is the optical axis p₄
    (Chong & Gortler 2007 §2.2, a unit vector), tilted from the spot's axis a by α, β along the axis
    frame's right and up vectors, axis = normalise(a + α r + β u). Given the axis, the affine part is
    fitted as for directional lights (the minimum-area parallelogram of the receivers' projections
    x/w, y/w), and near/far cover every receiver and caster in front of the light. The gradient is
    by central differences (the fit is NumPy); an axis that leaves a receiver within MAX_OFF_AXIS_DEG
    of the image plane is refused (f = inf)."""

    MAX_OFF_AXIS_DEG = 80.0
    TILT_MAX = 1.0  # |α|, |β| (tan of the tilt per axis)

    def __init__(self, camera: Camera, light, samples: Samples, receivers: np.ndarray, casters_bounds, resolution,
                 deadline: float | None = None, affine: str = "parallelogram", **_):
        self.camera, self.light, self.resolution = camera, light, (int(resolution[0]), int(resolution[1]))
        receivers = np.asarray(receivers, dtype=np.float64).reshape(-1, 3)
        fit = np.vstack([receivers, samples.position]) if len(samples) else receivers
        fit = _finite_rows(fit)
        if len(fit) == 0:
            raise ValueError("no receivers and no samples to fit the map to")
        self.fit_pts = fit
        self.corners = box_corners(np.asarray(casters_bounds[0], float), np.asarray(casters_bounds[1], float))
        self.ds = device_samples(samples, camera.position)
        self.view0 = spot_view(light, camera)
        self.deadline, self.gradient_mode = deadline, "fd"
        self.affine = "parallelogram" if affine == "objective" else affine  # the projected fit: min area
        self.nfev = self.njev = 0
        self.seen: dict = {}
        self.best = (math.inf, None, None)
        self.lower, self.upper = np.full(2, -self.TILT_MAX), np.full(2, self.TILT_MAX)
        self.n_hull = 0

    def fit(self, x):
        r0, u0, a0 = self.view0[0, :3], self.view0[1, :3], -self.view0[2, :3]
        axis = a0 + float(x[0]) * r0 + float(x[1]) * u0
        axis /= np.linalg.norm(axis)
        view = look_matrix(self.light.position, axis, u0)
        v = to_view(view, self.fit_pts)
        d = -v[:, 2]
        rel = self.fit_pts - self.light.position
        cos = d / np.maximum(np.linalg.norm(rel, axis=1), 1e-300)
        if float(cos.min()) < math.cos(math.radians(self.MAX_OFF_AXIS_DEG)):
            return None
        dc = -to_view(view, self.corners)[:, 2]
        far = float(max(d.max(), dc[dc > 0].max() if (dc > 0).any() else 0.0, 1e-3)) * 1.01
        near = perspective_near(d, far)
        q = v[:, :2] / d[:, None]
        C, lo, hi = affine_fit(q, self.affine, self.resolution)
        lo, hi = padded(lo, hi, PAD, 1e-6)
        A = np.eye(4)
        A[:2, :2] = np.diag(2.0 / (hi - lo)) @ C[:2, :2]
        A[:2, 3] = -2.0 * lo / (hi - lo) - 1.0
        proj = A @ frustum(-near, near, -near, near, near, far)  # clip-space affine: NDC x, y = A (x/w, y/w)
        return view, proj, (near, far), None

    def matrix(self, x):
        fitted = self.fit(x)
        return None if fitted is None else recentre(fitted[1] @ fitted[0], self.ds.origin)

    def map_for(self, x) -> ShadowMap:
        view, proj, ld, _ = self.fit(x)
        return ShadowMap(view, proj, self.resolution, light_depth=ld)

    def _evaluate(self, x) -> float:
        M = self.matrix(x)
        return math.inf if M is None else self.eval_matrix(M)


# ------------------------------------------------------------------ starting points
def _angle_of(view: np.ndarray, view0: np.ndarray, square: bool) -> float:
    """φ with view = rotation_z(φ) @ view0 (folded by the rectangle's symmetry into the bounds)."""
    a = math.atan2(float(view[0, :3] @ view0[1, :3]), float(view[0, :3] @ view0[0, :3]))
    period = math.pi / 2 if square else math.pi
    return (a + period / 2) % period - period / 2


def start_maps(camera: Camera, light: DirectionalLight, receivers: np.ndarray, casters_bounds, resolution,
               names=START_NAMES) -> dict:
    """The baselines that lie in this family, as single maps: focused, LiSPSM, LogPSM's perspective part."""
    out = {}
    for name in names:
        base = "logpsm" if name in ("logpsm", "logpsm-perspective") else name
        if base not in ("focused", "lispsm", "logpsm"):
            raise ValueError(f"starts: unknown start {name!r} (known: {', '.join(START_NAMES)})")
        out[name] = baseline(base, camera, light, receivers, casters_bounds, resolution, allow_log=False)[0]
    return out


def start_x(prob: Problem, smap: ShadowMap) -> np.ndarray:
    square = prob.resolution[0] == prob.resolution[1]
    if smap.n_prime is None or not math.isfinite(smap.n_prime):
        return np.array([_angle_of(smap.view, prob.view0, square), 0.0])
    y0, y1 = prob._warp_range(to_view(prob.view0, prob.fit_pts))  # the fit's own warp range
    D = y1 - y0
    return prob.clip([_angle_of(smap.view, prob.view0, False), math.log1p(D / smap.n_prime)])


# ------------------------------------------------------------------ entry point
@serial_kernels()
def minimize(camera: Camera, light: DirectionalLight | SpotLight, samples: Samples, receivers: np.ndarray, casters_bounds,
             resolution=(2048, 2048), method: str = DEFAULT_METHOD, x0=None, time_budget_ms: float | None = None,
             starts=START_NAMES, maxiter: int = 30, gradient: str = "ad", affine: str = "objective",
             start_maps_given: dict | None = None, log: bool = False, bias: bool = True,
             fit_points: tuple | None = None) -> OptimizeResult:
    """Minimise the metric's objective over the light's projective parameters x = (φ, u).

    Every start (and `x0`, a previous solution's x, when given) is evaluated first, even past the
    time budget; the optimizer runs from the best one. The result is the best map seen, baseline
    maps included. `time_budget_ms`: stop early, return the best so far with success=False.
    `start_maps_given`: {name: ShadowMap} baseline maps already fitted to these receivers (used as the
    starts instead of fitting them again). `log`: search LogPSM's family instead (the perspective
    part's (φ, u) with the log warp on t, Lloyd et al. 2007 eq. 78; engines must apply it in a shader).
    `bias=False`: the map is returned without its depth bias (a caller that biases what it keeps).
    `fit_points`: light_plane_hull of the receivers and samples when the caller has it (directional)."""
    if method not in METHODS + EXTRA_METHODS:
        raise ValueError(f"method: unknown solver {method!r} (known: {', '.join(METHODS + EXTRA_METHODS)})")
    if not optimizable(light):
        raise ValueError("minimize: directional lights and spot lights (one map, cone <= 80 deg) have this "
                         "parameterization; point lights use cube maps")
    t0 = time.perf_counter()
    deadline = None if time_budget_ms is None else t0 + float(time_budget_ms) / 1e3
    if isinstance(light, SpotLight):
        return _minimize_spot(camera, light, samples, receivers, casters_bounds, resolution, method, x0, deadline,
                              maxiter, affine, t0, bias)
    prob = Problem(camera, light, samples, receivers, casters_bounds, resolution, gradient=gradient, affine=affine,
                   log=log, fit_points=fit_points)
    # The starts fit the same hull vertices as the problem: the same min/max, a fraction of the points.
    if start_maps_given:
        bases = {name: m for name, m in start_maps_given.items() if m.face is None and (log or m.log_warp is None)}
    else:
        bases = start_maps(camera, light, prob.fit_pts, casters_bounds, prob.resolution, starts)
    base_vals = {name: prob.eval_map(m) for name, m in bases.items()}
    xs = {name: start_x(prob, m) for name, m in bases.items()}
    xp = prob.plane_x()
    if xp is not None:
        xs["plane"] = xp
    if x0 is not None:
        xs = {"warm": prob.clip(np.asarray(x0, float)), **xs}
    fam_vals = {name: prob.value(x) for name, x in xs.items()}
    best_start = min(fam_vals, key=fam_vals.get)
    prob.deadline = deadline
    nit, success, message = search(prob, method, xs[best_start].copy(), maxiter, len(samples))
    f, xb, _ = prob.best
    smap = prob.map_for(xb)
    same_kind = {n: v for n, v in base_vals.items() if (bases[n].log_warp is not None) == log}  # log: stay log
    bname = min(same_kind, key=same_kind.get) if same_kind else None
    start = best_start
    if bname is not None and base_vals[bname] < f:  # a baseline map itself is best (fit details differ)
        # a copy: the caller's baseline map (start_maps_given) keeps its own split and bias
        f, smap, xb, start = base_vals[bname], copy.deepcopy(bases[bname]), start_x(prob, bases[bname]), bname
        if success:
            message = f"converged; the {bname} baseline map is best"
    smap.split = (0.0, float(camera.far))
    if bias and len(receivers):
        with_bias(smap, np.asarray(receivers, float).reshape(-1, 3), light)
    return OptimizeResult(np.asarray(xb, float), float(f), int(nit), prob.nfev, (time.perf_counter() - t0) * 1e3,
                          success, message, smap, start, {**base_vals, **{f"{k}@family": v for k, v in fam_vals.items()}},
                          prob.njev)


SINGLE_MAP_CONE_DEG = 70.0  # a point light's receivers within this half-angle of one axis get one map


def single_map_spot(light, receivers: np.ndarray):
    """For a point light: a spot light with the receivers' mean direction as its axis and a cone just
    covering them, when that cone is at most SINGLE_MAP_CONE_DEG; else None."""
    if not isinstance(light, PointLight) or len(receivers) < 3:
        return None
    d = np.asarray(receivers, float).reshape(-1, 3) - light.position
    d = d[np.linalg.norm(d, axis=1) > 0]
    if len(d) < 3:
        return None
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    axis = d.mean(0)
    if np.linalg.norm(axis) < 1e-6:
        return None
    axis /= np.linalg.norm(axis)
    cone = float(np.degrees(np.arccos(np.clip(d @ axis, -1.0, 1.0))).max()) + 1.0
    return SpotLight.make(light.position, axis, cone, light.usd_path) if cone <= SINGLE_MAP_CONE_DEG else None


def optimizable(light) -> bool:
    """Lights with projective parameters to optimize: directional, and spots drawn as one map."""
    return isinstance(light, DirectionalLight) or (isinstance(light, SpotLight) and light.cone_deg <= SPOT_AS_CUBE_DEG)


def _minimize_spot(camera, light, samples, receivers, casters_bounds, resolution, method, x0, deadline, maxiter,
                   affine, t0, bias=True) -> OptimizeResult:
    """minimize() for a spot light: starts are the spot's own axis (the focused baseline's map, the
    family's x = 0) and the axis through the receivers' centroid."""
    prob = SpotProblem(camera, light, samples, receivers, casters_bounds, resolution, affine=affine)
    base = baseline("focused", camera, light, np.asarray(receivers, float).reshape(-1, 3), casters_bounds, resolution)[0]
    base_val = prob.eval_matrix(recentre(base.matrix, prob.ds.origin))
    r0, u0, a0 = prob.view0[0, :3], prob.view0[1, :3], -prob.view0[2, :3]
    c = prob.fit_pts.mean(0) - light.position
    c /= max(np.linalg.norm(c), 1e-300)
    xs = {"axis": np.zeros(2), "centroid": prob.clip([c @ r0 / max(c @ a0, 1e-3), c @ u0 / max(c @ a0, 1e-3)])}
    if x0 is not None:
        xs = {"warm": prob.clip(np.asarray(x0, float)), **xs}
    fam_vals = {name: prob.value(x) for name, x in xs.items()}
    best_start = min(fam_vals, key=fam_vals.get)
    prob.deadline = deadline
    # derivative-free on this family (its gradient would be finite differences of the fit)
    free = method == "none" or method.startswith("nlopt:LN")
    nit, success, message = search(prob, method if free else DEFAULT_METHOD, xs[best_start].copy(), maxiter,
                                     len(samples))
    if not free and success:
        message = f"converged ({DEFAULT_METHOD}: spot lights use a derivative-free solver)"
    f, xb, _ = prob.best
    if xb is None or not math.isfinite(f) or base_val < f:  # every tilt refused: the spot's own map
        f, smap, xb, start = base_val, base, np.zeros(2), "focused"
    else:
        smap, start = prob.map_for(xb), best_start
    smap.split = (0.0, float(camera.far))
    if bias and len(receivers):
        with_bias(smap, np.asarray(receivers, float).reshape(-1, 3), light)
    return OptimizeResult(np.asarray(xb, float), float(f), int(nit), prob.nfev, (time.perf_counter() - t0) * 1e3,
                          success, message, smap, start, {"focused": base_val, **{f"{k}@family": v for k, v in fam_vals.items()}},
                          prob.njev)
