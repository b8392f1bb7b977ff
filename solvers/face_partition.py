"""Face partitioning of a point light (Lloyd et al. 2007, LogPSM TR07-005, Algorithm III "FP"), pure geometry.

Instead of the six fixed 90-degree faces of a cube map (Kozlov's PSM cube map, solvers.light_frames), only the
faces whose frusta hold visible receivers get a map, and each is fitted to its own receivers and warped as a
directional map is (Lloyd §6.1 "FP+P", "FP+LogP"). The steps, one function each:

1. `face_frusta`: the six 90-degree face frusta from the light (OpenGL cube-map orientation) and one depth range
   [near, far] shared by all (solvers.baselines' cube rule: far past every receiver and scene corner, near 1e-4 of
   far, pulled in to half the nearest receiver: Lloyd §B4, a light inside the view).
2. `assign_receivers`: each receiver to the face its light direction leaves the cube through, the face of the
   largest |component| of X - l: the cube-map selection rule (Lloyd's "small index cube map", Kozlov's lookup), so
   the faces' frusta partition the directions and every receiver lies in exactly one face frustum.
3. `face_coords`: a face's projective coordinates (a, b) = (x, y)/d of a point in the face's view, d its
   distance along the face axis; inside the face |a|, |b| <= 1. Light rays are lines of constant (a, b): after the
   face's perspective divide the point light is a directional light along the face axis (Lloyd §4, the light's
   post-perspective space), which is what lets a face be warped "like a directional map".
4. `warp_axis`: the direction in the (a, b) plane along which the receivers' camera view depth grows (the least
   squares gradient), the analogue of LiSPSM's "view direction projected into the light's image plane"
   (Wimmer et al. 2004; Lloyd's y axis, digest B1); None when the receivers are flat along it.
5. `face_warp_n`: the warp distance n' in face coordinates: η from Lloyd's shaping function (eq. 79, as corrected
   in solvers.warp.eta_shaping: "p" for FP+P, "logp" for FP+LogP) at γ = angle between the camera's view direction
   and the face's mean light direction to its receivers, then n' = n_prime_from_eta (eq. 120) with the receivers'
   view-depth range (n_e, f_e) and W_ly = their extent along the warp axis; η = -1 (γ near 0 or 180 degrees) means
   no warp.
6. `fit_face`: the face's map. Without a warp: the focused fit, the minimum-area rectangle of the receivers' (a, b)
   (Chong & Gortler 2007 §2.3), padded by PAD_TEXELS texels, as an off-centre frustum (solvers.baselines' spot
   fit). With a warp: the perspective warp of solvers.warp.warp_matrix applied after the face's perspective divide
   (X = a'/(b' - y_c), Y = -1/(b' - y_c), y_c = y0 - n', Lloyd eq. 75 with a = n'), then a box fit in warped
   space; light rays stay lines of constant (X, Y) and depth (z_ndc = A + B/w') is monotonic along each of them.
   FP+LogP adds Lloyd's log warp on t (eq. 78, c0, c1, c2: solvers.warp.log_warp), carried as the map's LogWarp.
   Depth covers each receiver's light ray from the near plane to the receiver, so every caster on it is inside.

Resolution across the faces (by need) and the choice between the partition and the plain cube are made by the
service (service.need.split_budget, service.solve): this module only fits maps at the resolutions it is given.
"""
from __future__ import annotations

import math

import numpy as np

from .cameras import Camera
from .fitting import box_corners, frustum, min_area_rectangle, perspective_near, rotation_z, texel_margin, to_view
from .light_frames import CUBE_FACES, cube_face_views
from .shadow_map import ShadowMap
from .warp import MAX_N_OVER_DEPTH, NO_WARP_SIN, eta_shaping, gamma_deg, log_warp, n_prime_from_eta, padded_log, warp_matrix

FACES = tuple(CUBE_FACES)  # +x, -x, +y, -y, +z, -z
WARPS = ("none", "perspective", "log")
FLAT_DEPTH = 1e-3  # no warp when the view depth explains less than this fraction of its range along the axis
MIN_EXTENT = 1e-6  # smallest fitted extent in face coordinates (a receiver set that is one point or a line)


def face_frusta(position: np.ndarray, receivers: np.ndarray, corners: np.ndarray) -> tuple[dict, float, float]:
    """({face: world -> face view}, near, far): the six 90-degree faces and their shared depth range."""
    position = np.asarray(position, dtype=np.float64)
    pts = np.vstack([corners, receivers]) if len(receivers) else np.asarray(corners, dtype=np.float64)
    far = float(np.linalg.norm(pts - position, axis=1).max()) * 1.01 + 1e-3
    cheb = np.abs(receivers - position).max(1) if len(receivers) else np.zeros(0)
    return cube_face_views(position), perspective_near(cheb, far), far


def assign_receivers(position: np.ndarray, receivers: np.ndarray) -> dict[str, np.ndarray]:
    """{face: indices of the receivers in that face's frustum}: the face of the largest |component| of X - l
    (ties to the first axis), faces without receivers omitted."""
    rec = np.asarray(receivers, dtype=np.float64).reshape(-1, 3)
    if not len(rec):
        return {}
    v = rec - np.asarray(position, dtype=np.float64)
    axis = np.argmax(np.abs(v), axis=1)
    positive = v[np.arange(len(v)), axis] >= 0
    out = {}
    for k, face in enumerate(FACES):
        sel = np.flatnonzero((axis == k // 2) & (positive == (k % 2 == 0)))
        if len(sel):
            out[face] = sel
    return out


def face_coords(view: np.ndarray, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """((N, 2) projective coordinates (x, y)/d, (N,) distance d along the face axis) of world points."""
    v = to_view(view, pts)
    d = np.maximum(-v[:, 2], 1e-300)
    return v[:, :2] / d[:, None], d


def warp_axis(ab: np.ndarray, view_depth: np.ndarray) -> float | None:
    """The angle in the (a, b) plane of the direction along which the camera view depth grows (least squares
    d ~ c + g.(a, b)), or None when the receivers are too few or the depth is flat along every direction."""
    if len(ab) < 3:
        return None
    A = np.column_stack([np.ones(len(ab)), ab])
    coef, *_ = np.linalg.lstsq(A, view_depth, rcond=None)
    g = coef[1:]
    span = float(view_depth.max() - view_depth.min())
    reach = float(np.linalg.norm(g)) * float(np.ptp(ab @ (g / max(np.linalg.norm(g), 1e-300))))
    if not (span > 0) or not np.isfinite(reach) or reach < FLAT_DEPTH * span:
        return None
    return math.atan2(g[1], g[0])


def _axis_view(view: np.ndarray, angle: float) -> np.ndarray:
    """The face view turned about its axis so that +Y points along `angle` in the (a, b) plane."""
    return rotation_z(angle - math.pi / 2) @ view


def face_warp_n(camera: Camera, light_dirs: np.ndarray, view_depth: np.ndarray, extent_y: float,
                kind: str) -> tuple[float | None, float]:
    """(n', η) of a face's warp in face coordinates (module doc, step 5); n' None means no warp (η = -1)."""
    d = np.asarray(light_dirs, dtype=np.float64).mean(0)
    if not np.linalg.norm(d) > 0 or not extent_y > 0:
        return None, -1.0
    sin_g = float(np.linalg.norm(np.cross(camera.forward, d / np.linalg.norm(d))))
    if sin_g < NO_WARP_SIN:  # the warp axis is undefined within about 1 degree of the view axis
        return None, -1.0
    theta = math.degrees(min(math.atan(camera.tan_half_fov_y), math.atan(camera.tan_half_fov_y * camera.aspect)))
    eta = eta_shaping(gamma_deg(camera.forward, d), theta, "logp" if kind == "log" else "p")  # Lloyd eq. 79
    z_n = max(float(view_depth.min()), float(camera.near), 1e-9)
    z_f = max(float(view_depth.max()), z_n * (1 + 1e-9))
    n = n_prime_from_eta(eta, z_n, z_f, extent_y)  # Lloyd eq. 120
    if not math.isfinite(n) or n <= 0 or n > MAX_N_OVER_DEPTH * extent_y:
        return None, eta
    return float(n), eta


def _fit_plain(view: np.ndarray, receivers: np.ndarray, near: float, far: float, resolution) -> tuple:
    """The focused fit of a face without a warp: (view, projection)."""
    ab, _ = face_coords(view, receivers)
    if len(ab) >= 3:
        angle, _, _ = min_area_rectangle(ab)
        view = rotation_z(angle) @ view
        ab, _ = face_coords(view, receivers)
    lo, hi = texel_margin(ab.min(0), ab.max(0), resolution, 1.0, MIN_EXTENT)
    return view, frustum(lo[0] * near, hi[0] * near, lo[1] * near, hi[1] * near, near, far)


def _fit_warped(view: np.ndarray, receivers: np.ndarray, near: float, far: float, n_prime: float, resolution,
                pad_t: bool) -> tuple:
    """(projection, (y0, y1)) of a warped face: view +Y is the warp axis (module doc, step 6).

    x, y: solvers.warp.warp_matrix after the face's perspective divide, then a box fit in warped space. Depth:
    the warped w' = d (b - y_c) (d the distance along the face axis) is positive and grows along every light
    ray, so clip z = A w' + B (z_ndc = A + B/w') is monotonic along each ray and never wraps through infinity;
    A, B put z_ndc = -1 at w' = near u0 and +1 at w' = far u1 (u = b - y_c over the map), so every ray's depth
    range holds [near, far]."""
    ab, _ = face_coords(view, receivers)
    y0, y1 = float(ab[:, 1].min()), float(ab[:, 1].max())
    yc = y0 - n_prime
    M = warp_matrix(yc) @ frustum(-near, near, -near, near, near, far)  # eq. 75 after the face's divide
    hv = np.column_stack([to_view(view, receivers), np.ones(len(receivers))]) @ M.T
    X = hv[:, 0] / hv[:, 3]
    xlo, xhi = texel_margin(X.min(keepdims=True), X.max(keepdims=True), resolution[0], 1.0, MIN_EXTENT)
    Ylo, Yhi = -1.0 / (y0 - yc), -1.0 / (y1 - yc)
    if pad_t:
        (Ylo,), (Yhi,) = texel_margin(np.array([Ylo]), np.array([Yhi]), resolution[1], 1.0, 0.0)
    u0, u1 = -1.0 / Ylo, -1.0 / min(Yhi, -1e-300)  # Y = -1/u
    if not (0 < u0 < u1):
        u0, u1 = y0 - yc, y1 - yc
    w_lo, w_hi = near * u0, far * u1
    B = 2.0 / (1.0 / w_hi - 1.0 / w_lo)
    A = 1.0 - B / w_hi
    P = np.zeros((4, 4))
    sx, sy = 2.0 / (xhi[0] - xlo[0]), 2.0 / (Yhi - Ylo)
    P[0] = sx * M[0] - sx * 0.5 * (xhi[0] + xlo[0]) * M[3]
    P[1] = sy * M[1] - sy * 0.5 * (Yhi + Ylo) * M[3]
    P[2] = A * M[3]
    P[2, 3] += B
    P[3] = M[3]
    return P, (y0, y1)


def fit_face(camera: Camera, position: np.ndarray, face: str, view: np.ndarray, receivers: np.ndarray,
             near: float, far: float, resolution, warp: str = "perspective") -> ShadowMap:
    """One face's map fitted to its receivers (module doc, step 6), warp in WARPS (the shaping can still turn
    it off: warp_kind says what was applied), without its depth bias."""
    if warp not in WARPS:
        raise ValueError(f"warp must be one of {', '.join(WARPS)}, got {warp!r}")
    res = (int(resolution[0]), int(resolution[1]))
    receivers = np.asarray(receivers, dtype=np.float64).reshape(-1, 3)
    n_prime, eta, angle = None, None, None
    if warp != "none" and len(receivers) >= 3:
        ab, _ = face_coords(view, receivers)
        depth = (receivers - camera.position) @ camera.forward
        angle = warp_axis(ab, depth)
        if angle is not None:
            yy = face_coords(_axis_view(view, angle), receivers)[0][:, 1]
            dirs = receivers - position
            dirs /= np.maximum(np.linalg.norm(dirs, axis=1, keepdims=True), 1e-300)
            n_prime, eta = face_warp_n(camera, dirs, depth, float(np.ptp(yy)), warp)
    if n_prime is None:
        v, proj = _fit_plain(view, receivers, near, far, res)
        smap = ShadowMap(v, proj, res, light_depth=(near, far), face=face,
                         eta=-1.0 if warp != "none" else None)
    else:
        v = _axis_view(view, angle)
        use_log = warp == "log"
        proj, (y0, y1) = _fit_warped(v, receivers, near, far, n_prime, res, pad_t=not use_log)
        smap = ShadowMap(v, proj, res, light_depth=(near, far), warp_kind="perspective", eta=eta,
                         n_prime=n_prime, face=face)
        if use_log:
            smap.log_warp = padded_log(log_warp(y1 - y0, n_prime), res[1])
            smap.warp_kind = "log"
    smap.split = (0.0, float(camera.far))
    return smap


def partition_maps(camera: Camera, light, receivers: np.ndarray, casters_bounds, resolutions: dict,
                   warp: str = "perspective") -> tuple[list[ShadowMap], list[np.ndarray]]:
    """The face-partitioned maps of a point light, in cube-face order, for the faces with receivers, and per map
    the receivers fitted. `resolutions`: {face: (w, h)}, or one (w, h) for every face."""
    receivers = np.asarray(receivers, dtype=np.float64).reshape(-1, 3)
    receivers = receivers[np.all(np.isfinite(receivers), axis=1)]
    corners = box_corners(np.asarray(casters_bounds[0], float), np.asarray(casters_bounds[1], float))
    views, near, far = face_frusta(light.position, receivers, corners)
    maps, parts = [], []
    for face, idx in assign_receivers(light.position, receivers).items():
        res = resolutions[face] if isinstance(resolutions, dict) else resolutions
        fit = with_border_receivers(views[face], receivers, idx)
        maps.append(fit_face(camera, light.position, face, views[face], fit, near, far, res, warp))
        parts.append(receivers[idx])
    return maps, parts


BORDER_REACH = 1.25  # face coordinate |a|, |b| up to which a neighbour face's receivers pull the fit to the border


def with_border_receivers(view: np.ndarray, receivers: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """A face's receivers plus, for the neighbouring faces' receivers just across its border (|a|, |b| <=
    BORDER_REACH), their points clamped onto the border: the receivers are samples (coarse pixels), and the
    full-resolution pixels between the last sample on this side of the border and the first on the other side
    are this face's, so its fit must reach the border wherever the receivers cross it (the cube's faces always
    do)."""
    ab, d = face_coords(view, receivers)
    v = to_view(view, receivers)
    mine = np.zeros(len(receivers), dtype=bool)
    mine[idx] = True
    near_border = ~mine & (v[:, 2] < 0) & (np.abs(ab) <= BORDER_REACH).all(1)
    if not near_border.any():
        return receivers[idx]
    c = np.clip(ab[near_border], -1.0, 1.0) * d[near_border, None]
    local = np.column_stack([c, -d[near_border], np.ones(len(c))])
    world = local @ np.linalg.inv(view).T
    return np.vstack([receivers[idx], world[:, :3]])
