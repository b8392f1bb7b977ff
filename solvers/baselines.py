"""Baseline shadow setups: what engines do today, each returning per-map matrices and resolutions.

- uniform  ("Normal" in Chong & Gortler 2007): the light frustum fit to the whole scene bounds.
- focused: fit to the visible receivers by the minimum-area rectangle of their light-space convex
  hull (Chong & Gortler 2007 §2.3); the longer side goes to the larger map dimension.
- lispsm: Wimmer et al. 2004, n_opt = (z_n + sqrt(z_f z_n)) / sin γ over the focused body; no warp
  when sin γ < 0.02 (Filament's guard) or when n' is so large the warp is no warp.
- logpsm: Lloyd et al. 2007 LogP (eq. 78): the perspective warp with n' from η (eq. 79 shaping,
  eq. 120 conversion) plus the log warp on t, returned as parameters.
- Cascades: z-partitions over the tight view-depth range of the visible receivers (SDSM), each
  fit with the method; resolutions per map, or Lloyd's eq. 83 allocation under a texel budget.
- Point lights: a cube map (six 90° faces). Spot lights: a perspective frustum from the light,
  fit to the receivers in its cone (uniform: the whole cone); a cone wider than 80° uses the cube map.

Depth range: every caster between the light and the receivers is covered: for directional lights
light_depth.near is the nearest corner of the scene's bounds along the light, so no caster is ever
in front of the near plane (engines that pancake may tighten it; the evaluator pancakes too).

Depth bias, one rule for every method (the evaluator applies exactly this): with d the distance in
metres along the texel's light ray, a receiver is shadowed iff
    d_receiver > d_occluder + constant + slope * min(tan ψ, 10),
ψ the angle between the receiver normal and the direction to the light. Each map's recommended
values come from the world-space size of its texels at its receivers (warping makes one constant
bias wrong, Lloyd et al. §7.1): constant = 1.5 x, slope = 1 x the 95th percentile texel size.

Fallbacks (documented, never an exception): no receivers -> fit to the scene bounds; light within
about 1° of the view direction (either sign) -> no warp; degenerate extents are padded to a
minimum size.
"""
from __future__ import annotations

import math

import numpy as np

from .cameras import Camera
from .cascades import allocate, split_depths
from .fitting import box_corners, frustum, min_area_rectangle, ortho, padded, rotation_z, to_view
from .lights import DirectionalLight, PointLight, SpotLight
from .shadow_map import ShadowMap
from .warp import MAX_N_OVER_DEPTH, NO_WARP_SIN, eta_shaping, gamma_deg, lispsm_n, log_warp, n_prime_from_eta, warp_matrix

METHODS = ("uniform", "focused", "lispsm", "logpsm")
PAD = 0.005  # fraction of the fitted extent added on each side (sub-sampled receivers)
BIAS_CONSTANT_TEXELS = 1.5
BIAS_SLOPE_TEXELS = 1.0
SPOT_AS_CUBE_DEG = 80.0
CUBE_FACES = {"+x": ([1, 0, 0], [0, -1, 0]), "-x": ([-1, 0, 0], [0, -1, 0]), "+y": ([0, 1, 0], [0, 0, 1]),
              "-y": ([0, -1, 0], [0, 0, -1]), "+z": ([0, 0, 1], [0, -1, 0]), "-z": ([0, 0, -1], [0, -1, 0])}


# ------------------------------------------------------------------ frames
def _perpendicular_up(forward: np.ndarray, *hints) -> np.ndarray:
    for h in hints:
        u = np.asarray(h, float) - np.dot(h, forward) * forward
        if np.linalg.norm(u) > 1e-6:
            return u / np.linalg.norm(u)
    a = np.array([1.0, 0, 0]) if abs(forward[0]) < 0.9 else np.array([0, 1.0, 0])
    u = a - np.dot(a, forward) * forward
    return u / np.linalg.norm(u)


def look_matrix(eye: np.ndarray, forward: np.ndarray, up: np.ndarray) -> np.ndarray:
    """World -> view looking along `forward` (down -Z) from `eye`, +Y = up (orthonormalised)."""
    f = forward / np.linalg.norm(forward)
    u = _perpendicular_up(f, up)
    r = np.cross(f, u)
    m = np.eye(4)
    m[0, :3], m[1, :3], m[2, :3] = r, u, -f
    m[:3, 3] = -m[:3, :3] @ eye
    return m


def directional_view(light: DirectionalLight, camera: Camera) -> np.ndarray:
    """The LiSPSM light frame: looks along the light, +Y = the view direction projected into the
    light's image plane (camera up when the two are parallel), origin at the camera (re-centred)."""
    return look_matrix(camera.position, light.direction,
                       _perpendicular_up(light.direction, camera.forward, camera.up))


# ------------------------------------------------------------------ helpers
def _texel_world_size(smap: ShadowMap, pts: np.ndarray, light) -> float:
    """95th percentile over `pts` of the world size of one texel, perpendicular to the light."""
    if len(pts) == 0:
        return 0.0
    if len(pts) > 2000:
        pts = pts[np.random.default_rng(0).choice(len(pts), 2000, replace=False)]
    if isinstance(light, DirectionalLight):
        ldir = np.broadcast_to(light.direction, pts.shape)
    else:
        v = pts - light.position
        ldir = v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-300)
    e1 = np.cross(ldir, [0.0, 1.0, 0.0])
    bad = np.linalg.norm(e1, axis=1) < 1e-6
    e1[bad] = np.cross(ldir[bad], [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(ldir, e1)
    scale = max(float(np.abs(pts).max()), 1.0)
    eps = 1e-6 * scale
    s0, t0, _, _ = smap.map_coords(pts)
    w, h = smap.resolution
    sizes = []
    for e in (e1, e2):
        s1, t1, _, _ = smap.map_coords(pts + eps * e)
        texels = np.hypot((s1 - s0) * w, (t1 - t0) * h)
        sizes.append(eps / np.maximum(texels, 1e-300))
    size = np.maximum(sizes[0], sizes[1])
    size = size[np.isfinite(size)]
    return float(np.percentile(size, 95)) if len(size) else 0.0


def _with_bias(smap: ShadowMap, receivers: np.ndarray, light) -> ShadowMap:
    size = _texel_world_size(smap, receivers, light)
    smap.depth_bias = {"constant": BIAS_CONSTANT_TEXELS * size, "slope": BIAS_SLOPE_TEXELS * size,
                       "texel_world_size": size}
    return smap


def _min_extent(points: np.ndarray) -> float:
    if len(points) == 0:
        return 1e-3
    return max(1e-6, 1e-6 * float(np.abs(points).max()))


# ------------------------------------------------------------------ directional maps
def _fit_ortho(view: np.ndarray, fit_pts: np.ndarray, depth_pts: np.ndarray, resolution, rotate: bool):
    v = to_view(view, fit_pts)
    xy = v[:, :2]
    angle = 0.0
    if rotate and len(xy) >= 3:
        angle, _, _ = min_area_rectangle(xy)
        rv = xy @ np.array([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]])
        ext = rv.max(0) - rv.min(0)
        if (ext[0] < ext[1]) != (resolution[0] < resolution[1]) and resolution[0] != resolution[1]:
            angle += math.pi / 2  # the longer side to the larger map dimension
    view = rotation_z(angle) @ view
    v = to_view(view, fit_pts)
    lo, hi = padded(v[:, :2].min(0), v[:, :2].max(0), PAD, _min_extent(v[:, :2]))
    d = -to_view(view, depth_pts)[:, 2]
    near, far = float(d.min()), float(d.max())
    span = max(far - near, _min_extent(d))
    near, far = near - 0.01 * span, far + 0.01 * span
    return view, ortho(lo[0], hi[0], lo[1], hi[1], near, far), (near, far)


def _fit_warped(view: np.ndarray, receivers: np.ndarray, depth_pts: np.ndarray, n_prime: float):
    """Perspective warp along light-view +Y (LiSPSM frame) with its centre n' before the receivers,
    then an orthographic fit in warped space. Returns (projection, (y0, y1), light_depth)."""
    v = to_view(view, receivers)
    y0, y1 = padded(v[:, 1].min(keepdims=True), v[:, 1].max(keepdims=True), PAD, _min_extent(v[:, 1:2]))
    y0, y1 = float(y0[0]), float(y1[0])
    yc = y0 - n_prime
    W = warp_matrix(yc)
    # Depth extremes: receivers, and the scene corners slid along y into the receivers' y range
    # (a caster that shadows a receiver lies on the receiver's light ray, so within that range).
    dv = to_view(view, depth_pts)
    cand = [v] + [np.column_stack([dv[:, 0], np.full(len(dv), y), dv[:, 2]]) for y in (y0, y1)]
    allp = np.vstack(cand)
    wp = np.column_stack([allp, np.ones(len(allp))]) @ W.T
    X, Z = wp[:, 0] / wp[:, 3], wp[:, 2] / wp[:, 3]
    rx = v[:, 0] - 0.0
    Xr = rx / (v[:, 1] - yc)
    xlo, xhi = padded(Xr.min(keepdims=True), Xr.max(keepdims=True), PAD, _min_extent(Xr[:, None]))
    Ylo, Yhi = -1.0 / (y0 - yc), -1.0 / (y1 - yc)
    near, far = float((-Z).min()), float((-Z).max())
    span = max(far - near, 1e-9 * max(abs(near), abs(far), 1.0))
    proj = ortho(float(xlo[0]), float(xhi[0]), Ylo, Yhi, near - 0.01 * span, far + 0.01 * span) @ W
    d = -dv[:, 2]
    dr = -v[:, 2]
    return proj, (y0, y1), (float(min(d.min(), dr.min())), float(dr.max()))


def _directional_map(method: str, camera: Camera, light: DirectionalLight, receivers: np.ndarray,
                     corners: np.ndarray, resolution, allow_log: bool, z_range: tuple[float, float]) -> ShadowMap:
    view = directional_view(light, camera)
    fit_pts = corners if method == "uniform" or len(receivers) == 0 else receivers
    depth_pts = np.vstack([corners, fit_pts])
    warp_n = None
    eta = None
    if method in ("lispsm", "logpsm") and len(receivers) >= 3:
        sin_g = float(np.linalg.norm(np.cross(camera.forward, light.direction)))
        zn, zf = z_range
        body = to_view(view, receivers)[:, 1]
        depth_y = float(body.max() - body.min())
        if sin_g >= NO_WARP_SIN and depth_y > 0:
            if method == "lispsm":
                warp_n = lispsm_n(zn, zf, sin_g)
                eta = None
            else:
                theta = math.degrees(min(math.atan(camera.tan_half_fov_y),
                                         math.atan(camera.tan_half_fov_y * camera.aspect)))
                eta = eta_shaping(gamma_deg(camera.forward, light.direction), theta)
                warp_n = n_prime_from_eta(eta, zn, zf, depth_y)
            if not math.isfinite(warp_n) or warp_n > MAX_N_OVER_DEPTH * depth_y:
                warp_n = None
    if warp_n is None:
        v, proj, ld = _fit_ortho(view, fit_pts, depth_pts, resolution, rotate=method != "uniform")
        smap = ShadowMap(v, proj, tuple(resolution), light_depth=ld, warp_kind="none",
                         eta=-1.0 if method in ("lispsm", "logpsm") else None)
    else:
        proj, (y0, y1), ld = _fit_warped(view, receivers, depth_pts, warp_n)
        smap = ShadowMap(view, proj, tuple(resolution), light_depth=ld, warp_kind="perspective",
                         eta=eta if eta is not None else 0.0, n_prime=float(warp_n))
        if method == "logpsm" and allow_log:
            smap.log_warp = log_warp(y1 - y0, warp_n)
            smap.warp_kind = "log"
    return smap


# ------------------------------------------------------------------ spot and point lights
def _spot_map(method: str, light: SpotLight, camera: Camera, receivers: np.ndarray, corners: np.ndarray,
              resolution) -> ShadowMap:
    view = look_matrix(light.position, light.direction, _perpendicular_up(light.direction, camera.forward, camera.up))
    far_pts = receivers if len(receivers) else corners
    d_all = -to_view(view, far_pts)[:, 2]
    far = float(max(d_all.max(), 1e-3)) * 1.01
    near = max(far * 1e-4, 1e-4)
    tan_c = math.tan(math.radians(min(light.cone_deg, SPOT_AS_CUBE_DEG)))
    if method == "uniform" or len(receivers) < 3:
        lo, hi = np.array([-tan_c, -tan_c]), np.array([tan_c, tan_c])
    else:
        v = to_view(view, receivers)
        d = np.maximum(-v[:, 2], near)
        proj2 = np.clip(v[:, :2] / d[:, None], -tan_c, tan_c)
        angle, _, _ = min_area_rectangle(proj2)
        view = rotation_z(angle) @ view
        v = to_view(view, receivers)
        proj2 = v[:, :2] / np.maximum(-v[:, 2], near)[:, None]
        lo, hi = padded(proj2.min(0), proj2.max(0), PAD, 1e-4)
    return ShadowMap(view, frustum(lo[0] * near, hi[0] * near, lo[1] * near, hi[1] * near, near, far),
                     tuple(resolution), light_depth=(near, far))


def _cube_maps(light, corners: np.ndarray, receivers: np.ndarray, resolution) -> list[ShadowMap]:
    pts = np.vstack([corners, receivers]) if len(receivers) else corners
    far = float(np.linalg.norm(pts - light.position, axis=1).max()) * 1.01 + 1e-3
    near = max(far * 1e-5, 1e-4)
    side = max(resolution)
    maps = []
    for face, (fwd, up) in CUBE_FACES.items():
        view = look_matrix(light.position, np.array(fwd, float), np.array(up, float))
        maps.append(ShadowMap(view, frustum(-near, near, -near, near, near, far), (side, side),
                              light_depth=(near, far), face=face))
    return maps


# ------------------------------------------------------------------ entry point
def baseline(method: str, camera: Camera, light, receivers: np.ndarray, casters_bounds=None,
             resolution=(2048, 2048), cascades: int = 1, splits: str = "practical", split_lambda: float = 0.5,
             texel_budget: int | None = None, allow_log: bool = True,
             receiver_slack: np.ndarray | None = None) -> list[ShadowMap]:
    """The maps of one baseline method for one light. `receivers`: (N, 3) world points the camera
    sees that could be in shadow; `casters_bounds`: the scene's (lo, hi); `receiver_slack`: per
    receiver, how far in view depth the surface around it reaches (a cascade fits every receiver
    whose [depth - slack, depth + slack] meets its split, so the split boundary is covered)."""
    if method not in METHODS:
        raise ValueError(f"method must be one of {', '.join(METHODS)}, got {method!r}")
    receivers = np.asarray(receivers, dtype=np.float64).reshape(-1, 3)
    slack = np.zeros(len(receivers)) if receiver_slack is None else np.asarray(receiver_slack, dtype=np.float64)
    keep = np.all(np.isfinite(receivers), axis=1)
    receivers, slack = receivers[keep], slack[keep]
    if casters_bounds is None:
        casters_bounds = (receivers.min(0), receivers.max(0)) if len(receivers) else (camera.position - 1, camera.position + 1)
    corners = box_corners(np.asarray(casters_bounds[0], float), np.asarray(casters_bounds[1], float))
    res = (int(resolution[0]), int(resolution[1]))
    if isinstance(light, PointLight) or (isinstance(light, SpotLight) and light.cone_deg > SPOT_AS_CUBE_DEG):
        maps = _cube_maps(light, corners, receivers, res)
        return [_with_bias(m, receivers, light) for m in maps]
    if isinstance(light, SpotLight):
        return [_with_bias(_spot_map(method, light, camera, receivers, corners, res), receivers, light)]

    depth = (receivers - camera.position) @ camera.forward if len(receivers) else np.zeros(0)
    if len(receivers):
        z_lo, z_hi = max(float(depth.min()), camera.near), max(float(depth.max()), camera.near * 1.001)
    else:
        z_lo, z_hi = camera.near, camera.far
    k = max(1, int(cascades))
    z = split_depths(z_lo, z_hi, k, splits, split_lambda)
    maps = []
    for i in range(k):
        lo_z = -np.inf if i == 0 else z[i]
        hi_z = np.inf if i == k - 1 else z[i + 1]
        sel = (depth + slack >= lo_z * (1 - 1e-9)) & (depth - slack <= hi_z * (1 + 1e-9))
        part = receivers[sel] if len(receivers) else receivers
        if len(part) == 0 and len(receivers):
            part = _frustum_slice(camera, z[i], z[i + 1])
        smap = _directional_map(method, camera, light, part, corners, res, allow_log, (z[i], z[i + 1]))
        smap.split = (0.0 if i == 0 else float(z[i]), float(camera.far if i == k - 1 else z[i + 1]))
        maps.append(_with_bias(smap, part, light))
    if texel_budget:
        _allocate(maps, camera, receivers, depth, texel_budget)
    return maps


def _frustum_slice(camera: Camera, z0: float, z1: float) -> np.ndarray:
    th = camera.tan_half_fov_y
    tw = th * camera.aspect
    pts = []
    for z in (z0, z1):
        for sx in (-1, 1):
            for sy in (-1, 1):
                pts.append(camera.position + z * (camera.forward + sx * tw * camera.right + sy * th * camera.up))
    return np.array(pts)


def _allocate(maps: list[ShadowMap], camera: Camera, receivers: np.ndarray, depth: np.ndarray, budget: int) -> None:
    """Lloyd's eq. 83 with a per-map estimate of the critical resolution factors: R_s (R_t) = the map's
    world extent along s (t) / the 5th-percentile world size of a full-resolution pixel among the
    receivers it serves (pixel size = view depth · 2 tan(fov_y/2) / height)."""
    R_s, R_t = [], []
    for smap in maps:
        sel = (depth >= smap.split[0]) & (depth <= smap.split[1]) if len(receivers) else np.zeros(0, bool)
        pts = receivers[sel] if sel.any() else receivers
        if len(pts) == 0:
            R_s.append(1.0)
            R_t.append(1.0)
            continue
        pix = ((pts - camera.position) @ camera.forward) * 2 * camera.tan_half_fov_y / camera.resolution[1]
        p5 = max(float(np.percentile(pix, 5)), 1e-9)
        tex = smap.depth_bias.get("texel_world_size", 0.0) or 1e-9
        # texel world size * resolution = the map's extent at its receivers
        R_s.append(tex * smap.resolution[0] / p5)
        R_t.append(tex * smap.resolution[1] / p5)
    for smap, r in zip(maps, allocate(np.array(R_s), np.array(R_t), budget)):
        tex = smap.depth_bias.get("texel_world_size", 0.0)
        scale = max(smap.resolution[0] / r[0], smap.resolution[1] / r[1])
        smap.resolution = r
        if tex:
            size = tex * scale
            smap.depth_bias = {"constant": BIAS_CONSTANT_TEXELS * size, "slope": BIAS_SLOPE_TEXELS * size,
                               "texel_world_size": size}
