"""Lloyd et al. 2007 (LogPSM, UNC TR07-005) scene-independent analysis: the critical resolution
factors R_s, R_t and the storage factor S of one shadow map (or k z-partitions) covering a view
frustum, for a directional light at angle γ to the view direction. No scene data is used.

Model (the "whole-frustum" geometry of Lloyd's eqs. 111-119, evaluated numerically)
-----------------------------------------------------------------------------------
View space: eye at the origin looking down +z (view depth d_e = z), frustum |x|, |y| <= z tan θ,
n <= z <= f (square, half field of view θ in both directions; Lloyd §4.2 uses the smaller θ when
they differ). With u = (sin φ, cos φ, 0) the side the light comes from (azimuth φ about the view
axis; φ = 0: from above, the default; φ = 45°: over a frustum edge) the light travels along
l = -sin γ u + cos γ z: γ = 0 light behind the viewer shining along the view direction,
90 = overhead, 180 = light in front shining at the viewer ("dueling frusta"). The light image plane
is perpendicular to l with axes
    x_l = (cos φ, -sin φ, 0),   y_l = cos γ u + sin γ z
y_l is the view direction projected onto the light image plane (the LiSPSM frame, digest B1: "LiSPSM's
light-space z-axis is the paper's y-axis"), written in the form that stays defined at γ = 0° and
180° (where the projection of the view direction vanishes it continues to the frustum's up axis):
this is the guard that keeps the analysis finite at and near γ = 0° and 180°; the other half of
the guard is the η shaping (eq. 79), which turns the warp off (η = -1, uniform) there.

- Bound (eqs. 45, 48-55): along the light ray L through a light-plane point, the tightest eye-side
  spacing is δ_b = min over L∩V of δ̃_e, δ̃_e = W_e n_l d_e cos φ_e / (W_l n_e d_l cos φ_l) (eq. 31).
  For a directional light n_l/d_l -> 1 and cos φ_l = 1; replacing cos φ_e by cos θ (eq. 55, tight
  within 1/cos θ) and W_e = 2 n_e tan θ gives, in light-plane world units,
      δ_b = 2 sin θ · d_min,      d_min = min view depth on L∩V,
  and d_e is linear along the ray, so d_min is at the entry or the exit face (eq. 54; eq. 53's
  printed sign is a misprint, digest C - we never use the sign, we take the min of both ends).
- Parameterization spacing δ_l = dG/dt (eq. 28), here in light-plane world units per unit of map
  coordinate, for the map fitted to the frustum's light-space bounds y in [y0, y1], W_ly = y1 - y0,
  x in [x0, x1], W_lx = x1 - x0, warp centre of projection at y_c = y0 - n' ("a" of App. A with
  y0 = 0, y1 = W_ly, a = n', digest B6 eqs. 111-119):
      uniform       δ_l,t = W_ly,                                  δ_l,s = W_lx
      perspective   δ_l,t = W_ly (y - y_c)² / ((y0 - y_c)(y1 - y_c))      (eq. 97)
                    δ_l,s = (q1 - q0)(y - y_c),  q = x/(y - y_c) over the frustum (eqs. 75, 96)
      log (LogPSM)  δ_l,t = (y - y_c) ln((y1 - y_c)/(y0 - y_c))            (eq. 102, eq. 78)
                    δ_l,s = the perspective δ_l,s (LogPSM's s is F_p,s, eq. 78)
  n' = ∞ (η = -1) is the uniform map for every method.
- Critical resolution factors (eq. 47): R_t = max δ_l,t/δ_b, R_s = max δ_l,s/δ_b, the maxima
  taken over points sampled densely on the six frustum faces, vertices and edges included (Lloyd
  §4.3 evaluates at face vertices because the error is monotonic over each face; the samples in
  between cover the warped cases where it need not be).
- Storage factor (eq. 70) S = R_s R_t; the value returned is S cos²θ: "S without the 1/cos²θ
  factor", the quantity Lloyd's Table 3 lists. k partitions (eqs. 80-82: equal far/near ratio
  r = (f/n)^(1/k)) each get their own map; S adds up over them (digest B2), R_s and R_t returned
  are the largest over the partitions.
- Warp parameter: "perspective" is Lloyd's P (improved LiSPSM) and "log" his LogP: η(γ) from the
  shaping function eq. 79 with the digest's corrections (first branch η = -1, not the printed 0;
  last branch γ > γ_c; γ_c = θ + 0.4(90° - θ) of §6.1.1, not App. B's 0.3), implemented once in
  solvers.warp.eta_shaping; then n' = n_prime_from_eta(η, n_e, f_e, W_ly) (eq. 120, digest
  reconstruction). At γ = 90° this gives η = 0 -> n' = n_e + sqrt(n_e f_e) for P (LiSPSM's a_opt =
  sqrt(y0 y1), the largest n' of the range that minimizes S_p, §5) and η = 1 -> n' = n_e for LogP.

At γ = 90° the model reduces to closed forms (a = f/n):
    uniform      R_t = (a - 1)/(2 sin θ),     R_s = a/cos θ,      S cos²θ = a(a - 1)/(2 tan θ)
    perspective  R_t = (a - 1)/(2 sin θ √a),  R_s = √a/cos θ,     S cos²θ = (a - 1)/(2 tan θ)
    log          R_t = ln a/(2 sin θ),        R_s = 1/cos θ,      S cos²θ = ln a/(2 tan θ)
which are Table 3's minima (digest B5 note: X/(2 tan θ)): 8.65e5, 865, 5.98 at f/n = 1000, θ = 30°,
and per partition ZPk = k r(r - 1), ZPk+P = k(r - 1), ZPk+Log = ln a over 2 tan θ (51.4, 12.9,
27.4, 10.2, 5.98). Table 3's ZP5+P row is internally inconsistent (max and mean copied from the
ZP5+Log row, digest [Src-defect]); its minimum 12.9 is what this gives. The products S = R_s R_t
equal Lloyd's min S_p = (f/n - 1)/sin 2θ (§5). Away from 90° the same model gives, over all γ and φ,
a largest S cos²θ of exactly 2 (f/n)² = 2.00e6 for the standard map (at γ = 0, φ = 45°), Table 3's
"Max S" of the Standard row; for P and Log it gives 2.00e6 too (their warps are off there), Table 3
lists 1.99e6 for Log and 3.65e6 for P. That P value contradicts the paper's own text next to the
table ("in contrast to Po, our improved shaping function for the warping parameter keeps the maximum
error of P below that of a standard shadow map"), which this model agrees with; the P and Po maxima
(3.65e6 vs 1.99e6) look swapped in the source. Only the minima are tested. The s-direction warp keeps its centre
at x = 0 (symmetric about the light's y axis, exact for φ = 0; slightly conservative otherwise). Note these R's are the whole-frustum factors (one map
per frustum), not the per-face factors of eqs. 87-89 (R^side_un,t = (a - 1)/sin 2θ): those describe
face partitioning (FP), which this function does not model.
"""
from __future__ import annotations

import math

import numpy as np

from .warp import eta_shaping
# Lloyd et al. 2007 eq. 120 (η -> n'), defined once in solvers.warp and re-exported here: the
# baselines (LiSPSM/LogPSM) and this analysis call the very same function. The seed prints eq. 120
# garbled ("√(α+1)" and, for η >= 0, "√(α+1)/(η√(α+1))", which would be 1/η and infinite at η = 0);
# used instead, the digest's reconstruction (B3), which reproduces the three anchors the paper states
# (n'(-1) = ∞, n'(0) = n_e + sqrt(n_e f_e), n'(1) = n_e for W_ly = f_e - n_e), with α = f_e/n_e:
#     η < 0:  n' = W_ly/(α-1) · (√α + 1 - η(α-1)) / (η + 1)
#     η >= 0: n' = W_ly/(α-1) · (√α + 1) / (η√α + 1)
from .warp import n_prime_from_eta  # noqa: F401  (public: analysis.n_prime_from_eta)

METHODS = ("uniform", "perspective", "log")
FACE_SAMPLES = 49  # samples per edge of each frustum face (vertices and edges included)


def _frustum_corners(n: float, f: float, tan_t: float) -> np.ndarray:
    """(8, 3): near face then far face, each (-,-), (+,-), (+,+), (-,+) in (x, y)."""
    sq = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], dtype=np.float64)
    out = []
    for d in (n, f):
        for sx, sy in sq:
            out.append([sx * d * tan_t, sy * d * tan_t, d])
    return np.asarray(out)


_FACES = ((0, 1, 2, 3), (4, 5, 6, 7), (0, 1, 5, 4), (1, 2, 6, 5), (2, 3, 7, 6), (3, 0, 4, 7))


def _surface_samples(corners: np.ndarray, m: int) -> np.ndarray:
    """Points on the six quad faces, an m x m bilinear grid each (corners and edges included)."""
    u = np.linspace(0.0, 1.0, m)
    uu, vv = np.meshgrid(u, u, indexing="ij")
    uu, vv = uu.reshape(-1, 1), vv.reshape(-1, 1)
    pts = []
    for a, b, c, d in _FACES:
        A, B, C, D = corners[a], corners[b], corners[c], corners[d]
        pts.append((1 - uu) * (1 - vv) * A + uu * (1 - vv) * B + uu * vv * C + (1 - uu) * vv * D)
    return np.concatenate(pts)


def _min_depth_along_light(p: np.ndarray, l: np.ndarray, n: float, f: float, tan_t: float) -> np.ndarray:
    """d_min of eqs. 45/54: the smallest view depth on the light ray through p inside the frustum.

    Liang-Barsky clip of p + μ l against the frustum's six half-spaces a·x <= b; d_e = z is linear in
    μ, so its minimum over the segment is at one of the two ends (the entry or the exit face).
    """
    planes = [((0.0, 0.0, -1.0), -n), ((0.0, 0.0, 1.0), f),
              ((1.0, 0.0, -tan_t), 0.0), ((-1.0, 0.0, -tan_t), 0.0),
              ((0.0, 1.0, -tan_t), 0.0), ((0.0, -1.0, -tan_t), 0.0)]
    lo = np.full(len(p), -np.inf)
    hi = np.full(len(p), np.inf)
    scale = max(f, 1.0)
    for a, b in planes:
        a = np.asarray(a)
        den = float(a @ l)
        num = b - p @ a + 1e-12 * scale  # p lies on the boundary: a hair of slack keeps μ = 0 inside
        if abs(den) < 1e-15:
            continue  # ray parallel to this plane; p is inside it, so it never leaves through it
        mu = num / den
        if den > 0:
            hi = np.minimum(hi, mu)
        else:
            lo = np.maximum(lo, mu)
    lo, hi = np.minimum(lo, 0.0), np.maximum(hi, 0.0)
    z0, z1 = p[:, 2] + lo * l[2], p[:, 2] + hi * l[2]
    return np.maximum(np.minimum(z0, z1), n)  # never below the near plane (rounding)


def _one_frustum(n: float, f: float, theta: float, gamma: float, method: str, theta_deg: float,
                 gamma_deg: float, azimuth: float = 0.0) -> tuple[float, float, float]:
    """(R_s, R_t, S cos²θ) for one map covering the view frustum between depths n and f."""
    tan_t = math.tan(theta)
    corners = _frustum_corners(n, f, tan_t)
    pts = _surface_samples(corners, FACE_SAMPLES)
    up = np.array([math.sin(azimuth), math.cos(azimuth), 0.0])  # the side the light comes from
    x_axis = np.array([math.cos(azimuth), -math.sin(azimuth), 0.0])
    fwd = np.array([0.0, 0.0, 1.0])
    l_dir = -math.sin(gamma) * up + math.cos(gamma) * fwd  # light travel direction
    y_axis = math.cos(gamma) * up + math.sin(gamma) * fwd  # view dir projected, continued at 0/180
    x, y = pts @ x_axis, pts @ y_axis
    x0, x1, y0, y1 = float(x.min()), float(x.max()), float(y.min()), float(y.max())
    W_lx, W_ly = x1 - x0, y1 - y0
    d_min = _min_depth_along_light(pts, l_dir, n, f, tan_t)
    delta_b = 2.0 * math.sin(theta) * d_min  # eq. 55 with W_e = 2 n_e tan θ, directional light

    n_prime = math.inf
    if method != "uniform":
        eta = eta_shaping(gamma_deg, theta_deg, "logp" if method == "log" else "p")  # eq. 79
        n_prime = n_prime_from_eta(eta, n, f, W_ly)  # eq. 120
        if not (n_prime > 0) or n_prime > 1e9 * max(W_ly, n):
            n_prime = math.inf  # a warp this weak is the uniform map (and avoids 0 * inf below)

    if math.isinf(n_prime):
        dl_t = np.full_like(y, W_ly)
        dl_s = np.full_like(y, W_lx)
    else:
        yc = y0 - n_prime  # centre of projection of the warp, behind the near end (eq. 75, App. A)
        ya = y - yc
        q = x / ya
        dl_s = (float(q.max()) - float(q.min())) * ya  # eqs. 75/96: s = (q - q0)/(q1 - q0)
        if method == "perspective":
            dl_t = W_ly * ya ** 2 / ((y0 - yc) * (y1 - yc))  # eq. 97
        else:
            dl_t = ya * math.log1p(W_ly / (y0 - yc))  # eq. 102: (y + a) ln((y1 + a)/(y0 + a))
    R_t = float(np.max(dl_t / delta_b))  # eq. 47
    R_s = float(np.max(dl_s / delta_b))
    return R_s, R_t, R_s * R_t * math.cos(theta) ** 2  # eq. 70, Table 3's "without 1/cos²θ"


def analyze(f_over_n: float, theta_deg: float, gamma_deg: float, method: str, partitions: int = 1,
            azimuth_deg: float = 0.0) -> dict:
    """{"R_s", "R_t", "S"}: Lloyd's critical resolution factors (the largest over the partitions) and
    the storage factor summed over k equal-ratio z-partitions, S without the 1/cos²θ factor (Table 3).

    f_over_n > 1 (the view frustum's far/near ratio), 0 < theta_deg < 90 (half field of view),
    0 <= gamma_deg <= 180 (angle between the light and view directions; 90 = overhead), method in
    {"uniform", "perspective", "log"}, partitions >= 1; azimuth_deg: the side the light comes from
    (0 = above the frustum, 45 = over its edge). Every γ in [0, 180] gives finite values.
    """
    if method not in METHODS:
        raise ValueError(f"method must be one of {', '.join(METHODS)}, got {method!r}")
    if not (math.isfinite(f_over_n) and f_over_n > 1):
        raise ValueError(f"f_over_n must be a finite number > 1, got {f_over_n!r}")
    if not (0 < theta_deg < 90):
        raise ValueError(f"theta_deg must be in (0, 90), got {theta_deg!r}")
    if not (0 <= gamma_deg <= 180):
        raise ValueError(f"gamma_deg must be in [0, 180], got {gamma_deg!r}")
    k = int(partitions)
    if k < 1 or k != partitions:
        raise ValueError(f"partitions must be an integer >= 1, got {partitions!r}")
    if not math.isfinite(azimuth_deg):
        raise ValueError(f"azimuth_deg must be finite, got {azimuth_deg!r}")
    theta, gamma, azimuth = math.radians(theta_deg), math.radians(gamma_deg), math.radians(azimuth_deg)
    R_s = R_t = S = 0.0
    for i in range(k):  # eqs. 80-82: n_i = n (f/n)^((i-1)/k), f_i = n (f/n)^(i/k), with n = 1
        n_i, f_i = f_over_n ** (i / k), f_over_n ** ((i + 1) / k)
        rs, rt, s = _one_frustum(n_i, f_i, theta, gamma, method, theta_deg, gamma_deg, azimuth)
        R_s, R_t, S = max(R_s, rs), max(R_t, rt), S + s
    return {"R_s": R_s, "R_t": R_t, "S": S}
