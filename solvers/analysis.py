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
face partitioning (FP), modelled by the methods "fp", "fp+p" and "fp+log" below.

Face partitioning (Lloyd's Algorithm III, §4.3; methods "fp", "fp+p", "fp+log")
------------------------------------------------------------------------------
Along every light ray the bound δ_b is attained on one face of the view frustum: the entry face when the light
is behind the eye plane (light travelling forward, l_z > 0 here), the exit face when it is in front (eq. 54; at
l_z = 0 both give the same, the entry faces are taken). FP gives each such face (outward normal n with n.l < 0,
resp. > 0; faces edge-on to the light hold no ray) its own map, so on the face's own points δ_b = 2 sin θ d_e
(eq. 55, directional light, as above). Per face, in the light image plane:
- end faces (near, far): uniform (Lloyd: "parameterize end faces uniformly"): δ_l = the extents W_lx, W_ly of
  the minimum-area rectangle of the face's projection (a fitted map; axis-aligned boxes would double S for a
  square seen over its diagonal);
- side faces: d_e is linear on the face and 0 at the eye (the face's apex), so in the light plane d_e = k y with y
  measured along the gradient of d_e from the eye's projection (Lloyd's per-face frame, Fig. 5, where the face
  is y in [y0, y1] with d_e/n_e = y/y0); the warps have their centre of projection at the eye's projection,
  a = 0 (Lloyd: "side faces with LogPSM (a = 0)"; Table 3's FP+P uses the perspective part of that map):
      fp      uniform            δ_l,t = y1 - y0,          δ_l,s = x extent
      fp+p    perspective a = 0  δ_l,t = (y1 - y0) y²/(y0 y1) (eq. 97),  δ_l,s = (q1 - q0) y, q = x/y (eq. 96)
      fp+log  LogP a = 0         δ_l,t = y ln(y1/y0) (eq. 102),           δ_l,s as fp+p (eq. 78)
- R_s, R_t = max over the face's points of δ_l/δ_b (eq. 47), S = Σ_faces R_s R_t cos²θ (eq. 70, summed over the
  partitions as for ZP), "maps" = the number of faces with a map.
Closed forms this gives (a = f/n): overhead (γ = 90°) one face (the top) with S cos²θ = (a - 1)/(2 tan θ) for
fp+p and ln a/(2 tan θ) for fp+log, Table 3's FP+P and FP+Log minima 865 and 5.98; light behind the viewer
(γ = 0) the near face (S cos²θ = 1) plus four side faces of (a - 1)/2 (fp+p) or ln a/2 (fp+log) each:
2a - 1 = 1999 and 2 ln a + 1 = 14.8, Table 3's maxima "2000" and 14.8.
"""
from __future__ import annotations

import math

import numpy as np

from .fitting import min_area_rectangle
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
FP_METHODS = ("fp", "fp+p", "fp+log")  # face partitioning (Lloyd Algorithm III): uniform, P, LogP side faces
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


def min_depth_along_light(p: np.ndarray, l: np.ndarray, n: float, f: float, tan_t: float) -> np.ndarray:
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
    d_min = min_depth_along_light(pts, l_dir, n, f, tan_t)
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
    Methods "fp", "fp+p", "fp+log": face partitioning (module doc), partitions 1, plus "maps" (faces with a map).

    f_over_n > 1 (the view frustum's far/near ratio), 0 < theta_deg < 90 (half field of view),
    0 <= gamma_deg <= 180 (angle between the light and view directions; 90 = overhead), method in
    {"uniform", "perspective", "log"}, partitions >= 1; azimuth_deg: the side the light comes from
    (0 = above the frustum, 45 = over its edge). Every γ in [0, 180] gives finite values.
    """
    if method not in METHODS + FP_METHODS:
        raise ValueError(f"method must be one of {', '.join(METHODS + FP_METHODS)}, got {method!r}")
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
    if method in FP_METHODS:
        if k != 1:
            raise ValueError(f"partitions: face partitioning ({method}) is one partition per frustum face, "
                             f"give partitions 1, got {partitions!r}")
        return _face_partitioned(f_over_n, theta, gamma, azimuth, method)
    R_s = R_t = S = 0.0
    for i in range(k):  # eqs. 80-82: n_i = n (f/n)^((i-1)/k), f_i = n (f/n)^(i/k), with n = 1
        n_i, f_i = f_over_n ** (i / k), f_over_n ** ((i + 1) / k)
        rs, rt, s = _one_frustum(n_i, f_i, theta, gamma, method, theta_deg, gamma_deg, azimuth)
        R_s, R_t, S = max(R_s, rs), max(R_t, rt), S + s
    return {"R_s": R_s, "R_t": R_t, "S": S}


def _frustum_face_normals(tan_t: float) -> list[np.ndarray]:
    """Outward unit normals of _FACES (near, far, then the sides), eye at the origin looking down +z."""
    c = _frustum_corners(1.0, 2.0, tan_t)
    centre = c.mean(0)
    out = []
    for a, b, cc, d in _FACES:
        nrm = np.cross(c[b] - c[a], c[d] - c[a])
        nrm /= np.linalg.norm(nrm)
        out.append(nrm if nrm @ (c[a] - centre) > 0 else -nrm)
    return out


def _side_face_frame(P2: np.ndarray, d_e: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(x, y) of a side face's light-plane points in Lloyd's per-face frame (Fig. 5): y along the gradient of the
    eye distance d_e, which is linear on the face and 0 at the eye's projection (d_e = g.(x, y) exactly)."""
    g, *_ = np.linalg.lstsq(P2, d_e, rcond=None)
    gy = g / np.linalg.norm(g)
    return P2 @ np.array([-gy[1], gy[0]]), P2 @ gy


def _face_partitioned(f_over_n: float, theta: float, gamma: float, azimuth: float, method: str) -> dict:
    """analyze() for face partitioning (module doc): one map per frustum face that bounds the light rays."""
    tan_t = math.tan(theta)
    n, f = 1.0, float(f_over_n)
    corners = _frustum_corners(n, f, tan_t)
    up = np.array([math.sin(azimuth), math.cos(azimuth), 0.0])
    x_axis = np.array([math.cos(azimuth), -math.sin(azimuth), 0.0])
    l_dir = -math.sin(gamma) * up + math.cos(gamma) * np.array([0.0, 0.0, 1.0])
    y_axis = np.cross(l_dir, x_axis)  # a light-plane frame (end faces are uniform: any frame fits a square)
    entry = l_dir[2] >= -1e-12  # eq. 54: light behind the eye plane (or in it) -> entry faces, else exit faces
    R_s = R_t = S = 0.0
    maps = 0
    for fi, nrm in enumerate(_frustum_face_normals(tan_t)):
        c = float(nrm @ l_dir)
        if (c > -1e-9) if entry else (c < 1e-9):
            continue  # not a face the light rays' bound lies on (or edge-on to the light)
        pts = _surface_samples(corners, FACE_SAMPLES)[fi * FACE_SAMPLES ** 2:(fi + 1) * FACE_SAMPLES ** 2]
        P2 = np.column_stack([pts @ x_axis, pts @ y_axis])
        d_e = pts[:, 2]
        delta_b = 2.0 * math.sin(theta) * d_e  # eq. 55 on the face itself (the face attains the ray's min)
        side = fi >= 2
        if side:
            x, y = _side_face_frame(P2, d_e)
        if side and method != "fp":
            y0, y1 = float(y.min()), float(y.max())
            q = x / y
            dl_s = (float(q.max()) - float(q.min())) * y  # eqs. 75/96 with a = 0
            if method == "fp+p":
                dl_t = (y1 - y0) * y ** 2 / (y0 * y1)  # eq. 97, a = 0
            else:
                dl_t = y * math.log(y1 / y0)  # eq. 102, a = 0
        else:  # uniform: end faces always (Lloyd), side faces too for plain FP
            if side:  # plain FP: the side face's own frame (the d_e gradient), as the warped faces use
                ext = np.array([x.max() - x.min(), y.max() - y.min()])
            else:  # an end face: the minimum-area rectangle of its projection (a fitted uniform map)
                _, lo, hi = min_area_rectangle(P2)
                ext = np.asarray(hi) - np.asarray(lo)
            dl_s, dl_t = np.full(len(pts), ext[0]), np.full(len(pts), ext[1])
        rs, rt = float(np.max(dl_s / delta_b)), float(np.max(dl_t / delta_b))  # eq. 47
        R_s, R_t, S = max(R_s, rs), max(R_t, rt), S + rs * rt * math.cos(theta) ** 2  # eq. 70, summed
        maps += 1
    return {"R_s": R_s, "R_t": R_t, "S": S, "maps": maps}


def direction_stats(f_over_n: float, theta_deg: float, method: str, n_gamma: int = 91, n_azimuth: int = 10) -> dict:
    """Table 3's columns over all directional-light directions: min, max and mean S (the mean over the sphere of
    directions: weight sin γ, azimuth uniform, by symmetry over [0, 45°]), and the mean number of maps (for FP).
    Midpoint rules in γ and azimuth (n_gamma x n_azimuth points); min and max include γ = 0, 90, 180."""
    g_mid = (np.arange(n_gamma) + 0.5) * 180.0 / n_gamma
    a_mid = (np.arange(n_azimuth) + 0.5) * 45.0 / n_azimuth
    vals, maps, wts = [], [], []
    for g in g_mid:
        for a in a_mid:
            r = analyze(f_over_n, theta_deg, float(g), method, azimuth_deg=float(a))
            vals.append(r["S"])
            maps.append(r.get("maps", 1))
            wts.append(math.sin(math.radians(g)))
    ext = [analyze(f_over_n, theta_deg, g, method, azimuth_deg=a)["S"] for g in (0.0, 90.0, 180.0) for a in (0.0, 45.0)]
    w = np.asarray(wts) / np.sum(wts)
    return {"min": float(min(min(vals), min(ext))), "max": float(max(max(vals), max(ext))),
            "mean": float(np.asarray(vals) @ w), "mean_maps": float(np.asarray(maps, dtype=float) @ w)}
