"""Baseline shadow setups: what engines do today, each returning per-map matrices and resolutions.

Entry point: `baseline(method, camera, light, receivers, casters_bounds, resolution, cascades,
splits, split_lambda, texel_budget, allow_log) -> list[ShadowMap]`.

- uniform  ("Normal" in Chong & Gortler 2007): the light frustum fit to the whole scene bounds
  (orthographic for a directional light, the whole cone for a spot). With cascades every cascade
  is that same map (it does not depend on the split).
- focused: fit to the visible receivers by the minimum-area rectangle of their light-space convex
  hull (Chong & Gortler 2007 §2.3, solvers.fitting.min_area_rectangle); the longer side goes to
  the larger map dimension.
- lispsm: Wimmer et al. 2004, n_opt = (z_n + sqrt(z_f z_n)) / sin γ, z_n, z_f the receivers' (or
  the cascade's) view-depth range, the warp along the view direction projected into the light's
  image plane (solvers.light_frames), then an orthographic fit in warped space. No warp (the
  focused map, eta = -1) when sin γ < 0.02 (Filament's guard, about 1°, either sign), when n'
  exceeds 1e3 body depths (no warp in effect), or when the receivers are flat along the warp axis
  (extent < 1e-4 of the depth range: nothing to redistribute). eta records n_opt on Lloyd's scale
  (solvers.warp.eta_from_n_prime; 0 at γ = 90°).
- logpsm: Lloyd et al. 2007 LogP (eq. 78): the perspective warp with n' from η (eq. 79 shaping as
  corrected, eq. 120 conversion, θ the smaller half-angle of the view frustum, W_ly the receivers'
  extent along the warp axis) plus the log warp on t, carried as LogWarp(c0, c1, c2), not folded.
  allow_log=False returns the perspective part alone (warp_kind "perspective"). η = -1 -> no warp.
- Cascades (directional lights): z-partitions over the TIGHT view-depth range of the visible
  receivers (SDSM min/max, clamped below at the camera's near plane), `uniform`, `log` (equal
  ratio, Lloyd eqs. 80-82) or `practical` (λ log + (1 - λ) uniform); each map's `split` is
  [near, far] view depth (the first starts at 0, the last ends at the camera's far plane, so an
  engine's selection covers everything) and it is fit to the receivers whose depth (± slack) meets
  its split. Resolution: `resolution` each, or with `texel_budget` Lloyd's eq. 83 with per-map
  critical factors R_s, R_t estimated from the receivers (solvers.cascades.critical_factors: the
  95th percentile over its receivers of world metres per unit s (t) / world size of a
  full-resolution pixel). Point and spot lights ignore `cascades` (one map / one cube map); a
  budget gives a spot map sqrt(T) squared and each cube face sqrt(T/6) squared.
- Point lights: a cube map (six 90° faces, `face` = +x, -x, +y, -y, +z, -z, OpenGL orientation),
  so a light inside the view frustum is covered. Spot lights: a perspective frustum from the light,
  fit to the receivers in its cone (uniform: the whole cone; receivers outside the cone are unlit,
  so they are not fitted); a cone wider than 80° uses the cube map. Near plane of both: 1e-4 of
  the far distance, pulled in to half the nearest receiver's depth (Lloyd §B4: casters between the
  light and that plane are lost, the price of a light inside the view).

Depth range (no pancaking needed): for directional lights light_depth.near is the scene bounds'
nearest corner along the light, so every caster between the light and the receivers, on screen or
off, is inside the depth range (engines that pancake, clamping casters in front of the near plane to
it, may tighten the near plane to the receivers; the evaluator can pancake as well); far is the
farthest receiver or bounds corner. Warped maps are clipped in warped space by planes through the
warp centre, fit to the receivers and to the bounds' corners slid into the receivers' range along
the warp axis, which contains every caster on a receiver's light ray; their light_depth is that
frustum's range along the light's -Z (ShadowMap.frustum_depth_range), which widens towards the far end.

Depth bias, one rule for every method (the evaluator applies exactly this): with d the distance in
metres along the texel's light ray, a receiver is shadowed iff
    d_receiver > d_occluder + τ (constant_texels + slope_texels min(tan ψ, 10)),
ψ the angle between the receiver normal and the direction to the light and τ the world size of the
serving texel at the receiver: a bias in texel units, as a hardware slope-scaled depth bias or a
normal-offset bias is, which follows a warped map's varying texel size (one constant bias in
metres is wrong for warped maps, Lloyd et al. §7.1); constant_texels = 1.5, slope_texels = 1.
For engines that can only set a bias in metres, fixed_constant_m and fixed_slope_m are those units
times the 95th percentile of the texel size (the longer side of a texel in the plane perpendicular
to the light, from the map's own Jacobian) over the map's receivers (`texel_world_size`).
A map with no receiver inside (an empty cube face) uses the size at the far end of its central ray.
What an engine applies instead (no per-texel τ): each map's `depth` block (solvers.depth_modes.depth_block,
set with depth_bias by depth_modes.with_bias): hardware or linear stored depth with a constant and slope bias in
stored units covering this rule's requirement at the 95th percentile of the map's receivers.

Fallbacks (documented, never an exception): no receivers -> fit to the scene bounds (for any
method; no bounds either -> a 2 m box around the camera); casters_bounds None -> the receivers'
bounds; non-finite receivers are dropped; light within about 1° of the view direction (either
sign) -> no warp; degenerate extents (one point, a line) are padded to a minimum size.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .cameras import Camera
from .cascades import (ONE_SIZE_PER_LIGHT, allocate, critical_factors, pixel_world_size, receiver_depth_range,
                       split_depths)
from .depth_modes import with_bias
from .fitting import (PAD_TEXELS, box_corners, depth_range, extent_floor, frustum, light_plane_hull, min_area_rectangle,
                      ortho, padded, perspective_near, rotation_z, texel_margin, to_view)
from .light_frames import cube_face_views, directional_view, spot_view
from .lights import DirectionalLight, PointLight, SpotLight
from .samples import seeded_rows
from .shadow_map import ShadowMap
from .texel_size import texel_extents
from .warp import (MAX_N_OVER_DEPTH, NO_WARP_SIN, eta_from_n_prime, eta_shaping, gamma_deg, lispsm_n, log_warp,
                   n_prime_from_eta, padded_log, warp_matrix)

METHODS = ("uniform", "focused", "lispsm", "logpsm")
PAD = 0.005  # the former world-space fraction, kept for importers (solvers.optimize's spot fit); the baselines pad in texels
SPOT_AS_CUBE_DEG = 80.0
FLAT_BODY = 1e-4  # no warp when the receivers' extent along the warp axis is below this x the split's depth range
__all__ = ["METHODS", "baseline", "fit_baseline"]


# ------------------------------------------------------------------ helpers
def _min_extent(points: np.ndarray) -> float:
    if len(points) == 0:
        return 1e-3
    return extent_floor(float(np.abs(points).max()))


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
    lo, hi = texel_margin(v[:, :2].min(0), v[:, :2].max(0), resolution, PAD_TEXELS, _min_extent(v[:, :2]))
    d = -to_view(view, depth_pts)[:, 2]
    near, far = depth_range(d, 0.01, _min_extent(d))
    return view, ortho(lo[0], hi[0], lo[1], hi[1], near, far), (near, far)


def _fit_warped(view: np.ndarray, receivers: np.ndarray, depth_pts: np.ndarray, n_prime: float, resolution,
                pad_t: bool = True):
    """Perspective warp along light-view +Y (LiSPSM frame) with its centre n' before the receivers,
    then an orthographic fit in warped space, padded there by PAD_TEXELS texels (fitting.texel_margin:
    after the warp, so the margin is a margin of texels at the dense end too; pad_t=False leaves t
    unpadded, for a log warp that pads after itself). [y0, y1] is the receivers' own extent along the
    warp axis (at least the extent floor). Returns (projection, (y0, y1), light_depth)."""
    v = to_view(view, receivers)
    y0, y1 = padded(v[:, 1].min(keepdims=True), v[:, 1].max(keepdims=True), 0.0, _min_extent(v[:, 1:2]))
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
    xlo, xhi = texel_margin(Xr.min(keepdims=True), Xr.max(keepdims=True), resolution[0], PAD_TEXELS, _min_extent(Xr[:, None]))
    Ylo, Yhi = -1.0 / (y0 - yc), -1.0 / (y1 - yc)
    if pad_t:
        (Ylo,), (Yhi,) = texel_margin(np.array([Ylo]), np.array([Yhi]), resolution[1], PAD_TEXELS, 0.0)
    near, far = float((-Z).min()), float((-Z).max())
    span = max(far - near, 1e-9 * max(abs(near), abs(far), 1.0))
    proj = ortho(float(xlo[0]), float(xhi[0]), Ylo, Yhi, near - 0.01 * span, far + 0.01 * span) @ W
    d = -dv[:, 2]
    dr = -v[:, 2]
    return proj, (y0, y1), (float(min(d.min(), dr.min())), float(dr.max()))


def _directional_map(method: str, camera: Camera, light: DirectionalLight, receivers: np.ndarray,
                     corners: np.ndarray, resolution, allow_log: bool, z_range: tuple[float, float],
                     view: np.ndarray | None = None) -> ShadowMap:
    view = directional_view(light, camera) if view is None else view
    fit_pts = corners if method == "uniform" or len(receivers) == 0 else receivers
    depth_pts = np.vstack([corners, fit_pts])
    warp_n = None
    eta = None
    if method in ("lispsm", "logpsm") and len(receivers) >= 3:
        sin_g = float(np.linalg.norm(np.cross(camera.forward, light.direction)))
        zn, zf = z_range
        body = to_view(view, receivers)[:, 1]
        depth_y = float(body.max() - body.min())
        # A receiver set (nearly) flat along the warp axis, e.g. a wall facing the camera under an
        # overhead light, has no depth to redistribute: no warp (and eq. 120's n', proportional to
        # the extent, would fall below the float resolution of the fit).
        flat = depth_y <= max(_min_extent(body[:, None]), FLAT_BODY * (zf - zn))
        if sin_g >= NO_WARP_SIN and not flat:
            if method == "lispsm":
                warp_n = lispsm_n(zn, zf, sin_g)
                eta = eta_from_n_prime(warp_n, zn, zf, depth_y)  # LiSPSM's n_opt on Lloyd's η scale
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
        use_log = method == "logpsm" and allow_log
        proj, (y0, y1), ld = _fit_warped(view, receivers, depth_pts, warp_n, resolution, pad_t=not use_log)
        smap = ShadowMap(view, proj, tuple(resolution), light_depth=ld, warp_kind="perspective",
                         eta=eta if eta is not None else 0.0, n_prime=float(warp_n))
        if use_log:
            smap.log_warp = padded_log(log_warp(y1 - y0, warp_n), resolution[1])
            smap.warp_kind = "log"
        smap.light_depth = smap.frustum_depth_range() or ld  # the warped frustum widens towards its far end
    return smap


# ------------------------------------------------------------------ spot and point lights
def _spot_map(method: str, light: SpotLight, camera: Camera, receivers: np.ndarray, corners: np.ndarray,
              resolution) -> ShadowMap:
    view = spot_view(light, camera)
    far_pts = receivers if len(receivers) else corners
    d_all = -to_view(view, far_pts)[:, 2]
    far = float(max(d_all.max(), 1e-3)) * 1.01
    near = perspective_near(d_all, far)
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
        proj2 = np.clip(v[:, :2] / np.maximum(-v[:, 2], near)[:, None], -tan_c * 1.5, tan_c * 1.5)
        lo, hi = texel_margin(proj2.min(0), proj2.max(0), resolution, PAD_TEXELS, 1e-4)
    return ShadowMap(view, frustum(lo[0] * near, hi[0] * near, lo[1] * near, hi[1] * near, near, far),
                     tuple(resolution), light_depth=(near, far))


def _cube_maps(light, corners: np.ndarray, receivers: np.ndarray, resolution) -> list[ShadowMap]:
    pts = np.vstack([corners, receivers]) if len(receivers) else corners
    far = float(np.linalg.norm(pts - light.position, axis=1).max()) * 1.01 + 1e-3
    cheb = np.abs(receivers - light.position).max(1) if len(receivers) else np.zeros(0)
    near = perspective_near(cheb, far)
    side = max(resolution)
    return [ShadowMap(view, frustum(-near, near, -near, near, near, far), (side, side), light_depth=(near, far), face=face)
            for face, view in cube_face_views(light.position).items()]


# ------------------------------------------------------------------ entry point
def baseline(method: str, camera: Camera, light, receivers: np.ndarray, casters_bounds=None,
             resolution=(2048, 2048), cascades: int = 1, splits: str = "practical", split_lambda: float = 0.5,
             texel_budget: int | None = None, allow_log: bool = True,
             receiver_slack: np.ndarray | None = None, split_at=None, hull_cache: dict | None = None) -> list[ShadowMap]:
    """The maps of one baseline method for one light (see the module doc for every choice).

    method: uniform | focused | lispsm | logpsm. receivers: (N, 3) world points the camera sees
    that could be in shadow (all visible receiver pixels' positions, empty allowed);
    casters_bounds: the scene's AABB (lo, hi), so the depth range covers off-screen casters;
    resolution: (width, height) per map unless texel_budget (total texels, Lloyd eq. 83) is given;
    cascades/splits/split_lambda: z-partitions over the receivers' tight view-depth range;
    allow_log: False -> logpsm returns its perspective part only; receiver_slack: per receiver,
    how far in view depth the surface around it reaches (a cascade fits every receiver whose
    [depth - slack, depth + slack] meets its split, so the split boundary is covered);
    split_at: the k - 1 inner split depths, given explicitly (optimized splits) instead of `splits`;
    hull_cache: a dict shared by calls with the same camera, light, receivers, slack and splits
    (several methods), so the receivers are filtered and each cascade's selected and reduced to its
    light-plane hull once.

    Each map's depth_bias follows the one rule the evaluator applies (renderers/ground_truth.py):
    with d the distance along the texel's light ray, a receiver is shadowed iff
    d_receiver > d_occluder + τ (constant_texels + slope_texels min(tan ψ, 10)), ψ the angle between
    the receiver normal and the direction to the light and τ the serving texel's world size at the
    receiver (a hardware slope-scaled or normal-offset bias in texel units); constant_texels = 1.5,
    slope_texels = 1. For engines with a fixed bias in metres, fixed_constant_m and fixed_slope_m
    are those units times the 95th-percentile texel world size of the map at its receivers."""
    return fit_baseline(method, camera, light, receivers, casters_bounds, resolution, cascades, splits, split_lambda,
                        texel_budget, allow_log, receiver_slack, split_at, hull_cache).biased(light)


@dataclass
class Fitted:
    """A baseline's maps before their depth bias, with the receivers each covers."""

    maps: list[ShadowMap]
    parts: list[np.ndarray]  # per map: the receivers it was fitted to (its bias is measured on them)
    fit_points: list[tuple | None]  # per directional map: light_plane_hull of those receivers (hull, extremes)

    def biased(self, light) -> list[ShadowMap]:
        return [with_bias(m, p, light) for m, p in zip(self.maps, self.parts)]


def fit_baseline(method: str, camera: Camera, light, receivers: np.ndarray, casters_bounds=None,
                 resolution=(2048, 2048), cascades: int = 1, splits: str = "practical", split_lambda: float = 0.5,
                 texel_budget: int | None = None, allow_log: bool = True,
                 receiver_slack: np.ndarray | None = None, split_at=None, hull_cache: dict | None = None) -> Fitted:
    """baseline() without the depth bias (the metric does not depend on it: a caller that scores
    several candidates biases only the one it keeps, Fitted.biased or depth_modes.with_bias on Fitted.parts)."""
    if method not in METHODS:
        raise ValueError(f"method must be one of {', '.join(METHODS)}, got {method!r}")
    receivers, slack, depth = _finite_receivers(camera, receivers, receiver_slack, hull_cache)
    if casters_bounds is None:
        casters_bounds = (receivers.min(0), receivers.max(0)) if len(receivers) else (camera.position - 1, camera.position + 1)
    corners = box_corners(np.asarray(casters_bounds[0], float), np.asarray(casters_bounds[1], float))
    res = (int(resolution[0]), int(resolution[1]))
    if texel_budget and not isinstance(light, DirectionalLight):
        # one spot map gets the budget (square), a cube map's six faces share it equally
        n_maps = 6 if isinstance(light, PointLight) or light.cone_deg > SPOT_AS_CUBE_DEG else 1
        side = int(max(16, math.isqrt(int(texel_budget) // n_maps)))
        res = (side, side)
    if isinstance(light, PointLight) or (isinstance(light, SpotLight) and light.cone_deg > SPOT_AS_CUBE_DEG):
        maps = _cube_maps(light, corners, receivers, res)
    elif isinstance(light, SpotLight):
        maps = [_spot_map(method, light, camera, receivers, corners, res)]
    else:
        maps = None
    if maps is not None:
        for m in maps:
            m.split = (0.0, float(camera.far))
        return Fitted(maps, [receivers] * len(maps), [None] * len(maps))

    z_lo, z_hi = receiver_depth_range(camera, depth)
    k = max(1, int(cascades))
    z = split_depths(z_lo, z_hi, k, "practical" if split_at is not None else splits, split_lambda)
    if split_at is not None:
        inner = np.sort(np.asarray(split_at, dtype=np.float64).ravel())
        if len(inner) != k - 1 or not np.all(np.isfinite(inner)):
            raise ValueError(f"split_at: need {k - 1} finite inner split depths, got {len(inner)}")
        z[1:-1] = np.clip(inner, z_lo, z_hi)
    maps, parts, fits = [], [], []
    view = _light_view(camera, light, hull_cache)
    for i in range(k):
        part, hull = _cascade_part(camera, light, receivers, slack, depth, z, i, hull_cache)
        smap = _directional_map(method, camera, light, np.vstack(hull), corners, res, allow_log, (z[i], z[i + 1]), view)
        smap.split = (0.0 if i == 0 else float(z[i]), float(camera.far if i == k - 1 else z[i + 1]))
        maps.append(smap)
        parts.append(part)
        fits.append(hull)
    if texel_budget:
        _allocate(maps, camera, receivers, depth, texel_budget, light)
    return Fitted(maps, parts, fits)


def _light_view(camera: Camera, light, cache: dict | None) -> np.ndarray:
    """directional_view(light, camera), once per shared cache."""
    if cache is None:
        return directional_view(light, camera)
    if "view" not in cache:
        cache["view"] = directional_view(light, camera)
    return cache["view"]


def _finite_receivers(camera: Camera, receivers, receiver_slack, cache: dict | None):
    """(receivers, slack, view depth) of the finite receivers, once per shared cache."""
    if cache is not None and "finite" in cache:
        return cache["finite"]
    receivers = np.asarray(receivers, dtype=np.float64).reshape(-1, 3)
    slack = np.zeros(len(receivers)) if receiver_slack is None else np.asarray(receiver_slack, dtype=np.float64)
    if not np.isfinite(receivers).all():
        keep = np.all(np.isfinite(receivers), axis=1)
        receivers, slack = receivers[keep], slack[keep]
    depth = (receivers - camera.position) @ camera.forward if len(receivers) else np.zeros(0)
    if cache is not None:
        cache["finite"] = (receivers, slack, depth)
    return receivers, slack, depth


def _cascade_part(camera: Camera, light, receivers, slack, depth, z, i: int, cache: dict | None):
    """Cascade i's receivers (depth +- slack meets its split; the frustum slice when none does) and
    their light-plane hull vertices and depth extremes, once per shared cache."""
    key = ("part", i, float(z[i]), float(z[i + 1]))
    if cache is not None and key in cache:
        return cache[key]
    lo_z = -np.inf if i == 0 else z[i]
    hi_z = np.inf if i == len(z) - 2 else z[i + 1]
    sel = (depth + slack >= lo_z * (1 - 1e-9)) & (depth - slack <= hi_z * (1 + 1e-9))
    part = receivers if sel.all() else receivers[sel]
    if len(part) == 0 and len(receivers):
        part = _frustum_slice(camera, z[i], z[i + 1])
    out = part, light_plane_hull(light.direction, part)
    if cache is not None:
        cache[key] = out
    return out


def _frustum_slice(camera: Camera, z0: float, z1: float) -> np.ndarray:
    th = camera.tan_half_fov_y
    tw = th * camera.aspect
    pts = []
    for z in (z0, z1):
        for sx in (-1, 1):
            for sy in (-1, 1):
                pts.append(camera.position + z * (camera.forward + sx * tw * camera.right + sy * th * camera.up))
    return np.array(pts)


def _allocate(maps: list[ShadowMap], camera: Camera, receivers: np.ndarray, depth: np.ndarray, budget: int,
              light) -> None:
    """Lloyd's eq. 83 under the texel budget, with each map's critical resolution factors R_s, R_t
    estimated from its receivers (solvers.cascades.critical_factors): the resolution along s (t) at
    which its texels are no larger than a full-resolution screen pixel at 95% of its receivers."""
    R_s, R_t = [], []
    for smap in maps:
        sel = (depth >= smap.split[0]) & (depth <= smap.split[1]) if len(receivers) else np.zeros(0, bool)
        pts = receivers[sel] if sel.any() else receivers
        if len(pts) > 4000:
            pts = pts[seeded_rows(len(pts), 4000)]
        per_s, per_t = texel_extents(smap, pts, light)
        pix = pixel_world_size(camera, pts)
        rs, rt = critical_factors(per_s, per_t, pix)
        R_s.append(rs)
        R_t.append(rt)
    for smap, r in zip(maps, allocate(np.array(R_s), np.array(R_t), budget, shared=ONE_SIZE_PER_LIGHT)):
        smap.resolution = r
