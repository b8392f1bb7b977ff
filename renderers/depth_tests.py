"""The shadow test (renderers.ground_truth, step 4): the bias rule (BIAS_RULE) and the engine depth modes
(DEPTH_RULE_ENGINE, engine_depth), in Dr.Jit (device_lookup) and as their NumPy references (shadow_test), and
the cascade an engine's lookup uses (engine_cascades).
"""
from __future__ import annotations

import dataclasses

import numpy as np

from ..solvers.depth_modes import light_ray_dirs, stored_depth
from ..solvers.engine_depth_test import engine_shadowed
from ..solvers.lights import DirectionalLight, Light
from ..solvers.shadow_map import ShadowMap, map_for_depth
from .mitsuba_setup import mitsuba
from .ray_scene import RayScene
from .shadow_map_rays import device_rays_through, device_stored_depth, inverse_matrix, opaque_matrix, recentre

TAN_PSI_MAX = 10.0  # slope-bias clamp: tan(psi) of grazing receivers is limited to this
NUMERIC_TOLERANCE = 1e-6  # times the scene's diagonal, added to every bias (float32 ray casting noise)
BIAS_RULE = ("shadowed iff d_receiver > d_occluder + depth_bias.constant + depth_bias.slope * min(tan(psi), "
             f"{TAN_PSI_MAX:g}) + tau * (depth_bias.constant_texels + depth_bias.slope_texels * min(tan(psi), "
             f"{TAN_PSI_MAX:g})) + {NUMERIC_TOLERANCE:g} * scene_diagonal, tau = the serving texel's world size at "
             "the receiver; distances in metres along the texel's "
             "light ray from its near-plane point, psi = angle between the surface normal and the direction "
             "to the light; nearest texel, no filtering; receivers outside their map are lit")

DEPTH_CHOICES = ("ideal", "solution", "hardware", "linear")
DEPTH_RULE_IDEAL = "ideal: " + BIAS_RULE
DEPTH_RULE_ENGINE = (
    "{which}: what an engine does with each map's depth block: X' = X + normal_offset * N (N the receiver's "
    "geometric normal on its light-facing side), the nearest texel of X', D_rec = D(X') with D the mode's stored "
    "depth (hardware: window z (z_ndc + 1) / 2 of projection * view; linear: (-z_view - near) / (far - near)), "
    "stored D = clamp(D(P) + min(slope_scaled * DZ, slope_clamp), 0, 1) rounded to the block's depth format (float32, "
    "float16, or unorm24 / unorm16 fixed point; with constant_side caster the constant is added to D(P) before the "
    "rounding and is 0 at the lookup), P the texel-centre "
    "ray's first hit, DZ = max(|D(P_x) - D(P)|, |D(P_y) - D(P)|) with P_x, P_y the caster triangle's plane on the "
    "rays of texels (i + 1, j) and (i, j + 1) (a caster-side slope-scaled bias: glPolygonOffsetClamp, D3D "
    "SlopeScaledDepthBias), 0 for pancaked casters, 1 where nothing is hit; shadowed iff D_rec - (constant + slope "
    f"* min(tan(psi), {TAN_PSI_MAX:g})) > stored D; receivers with s, t or D_rec outside [0, 1] are lit; cascades "
    "switch at the midpoint of each blend band where the next cascade contains the point")


def engine_depth(smap: ShadowMap, depth: str) -> dict | None:
    """The numbers an engine applies for `smap` under `depth` (DEPTH_CHOICES): None for "ideal", else
    {mode, constant, slope, normal_offset, near, far, slope_scaled, slope_clamp, format, caster_constant} from the map's
    depth
    block ("solution": the block's own mode; a block without slope_scaled has none, without slope_clamp no
    clamp, without format float32: solvers.depth_modes.DEPTH_FORMATS).
    A map without a block is a ValueError."""
    if depth not in DEPTH_CHOICES:
        raise ValueError(f"depth must be one of {', '.join(DEPTH_CHOICES)}, got {depth!r}")
    if depth == "ideal":
        return None
    block = smap.depth
    if not isinstance(block, dict):
        raise ValueError("this map has no depth block (solve it again, or evaluate with depth 'ideal')")
    mode = block.get("mode") if depth == "solution" else depth
    if mode not in ("hardware", "linear") or not isinstance(block.get(mode), dict):
        raise ValueError(f"depth.{mode}: expected the block of a mode hardware or linear")
    b = block[mode]
    clamp = b.get("slope_clamp")
    out = {"mode": mode, "constant": float(b.get("constant", 0.0)), "slope": float(b.get("slope", 0.0)),
           "normal_offset": float(b.get("normal_offset", 0.0) or 0.0), "near": 0.0, "far": 1.0,
           "slope_scaled": float(b.get("slope_scaled", 0.0) or 0.0),
           "slope_clamp": float(clamp) if clamp is not None else float("inf"),
           "format": block.get("format", "float32"), "caster_constant": 0.0}
    if b.get("constant_side", "receiver") == "caster":  # added to the stored depth before rounding (CONSTANT_SIDES)
        out["caster_constant"], out["constant"] = out["constant"], 0.0
    if mode == "linear":
        out["near"], out["far"] = float(b["near"]), float(b["far"])
    return out


def engine_splits(maps: list[ShadowMap]) -> list[ShadowMap]:
    """The maps with their splits moved to the midpoints of their blend bands (an engine that blends
    cascade k into k + 1 linearly over [start, end] and thresholds the blend at 0.5 switches there)."""
    out = [dataclasses.replace(m) for m in maps]
    for k in range(len(out) - 1):
        band = out[k].blend_band
        if band is not None and out[k].face is None:
            mid = 0.5 * (float(band[0]) + float(band[1]))
            out[k].split = (out[k].split[0], mid)
            out[k + 1].split = (mid, out[k + 1].split[1])
    return out


def engine_cascades(maps: list[ShadowMap], view_depth: np.ndarray, contains: list[np.ndarray]) -> np.ndarray:
    """The cascade an engine's lookup uses per point: map_for_depth with the splits at the blend bands'
    midpoints (engine_splits), except that within cascade k's band, past its midpoint, a point that
    cascade k + 1 does not contain (contains[k + 1] false: s, t or D_rec outside [0, 1]) stays in
    cascade k (the lookup blends with k + 1 only where k + 1 contains the point)."""
    depth = np.asarray(view_depth, float)
    idx = map_for_depth(engine_splits(maps), depth)
    for k in range(len(maps) - 1):
        band = maps[k].blend_band
        if band is None or maps[k].face is not None:
            continue
        mid = 0.5 * (float(band[0]) + float(band[1]))
        back = (idx == k + 1) & (depth >= mid) & (depth <= float(band[1])) & ~np.asarray(contains[k + 1], bool)
        idx[back] = k
    return idx


def _device_map_coords(mi, dr, smap: ShadowMap, origin: np.ndarray, X):
    """`ShadowMap.map_coords` in Dr.Jit Float64 for re-centred points X: (s, t, z_ndc, w)."""
    M = opaque_matrix(mi, dr, smap.matrix @ recentre(origin))
    c = [M[r][0] * X[0] + M[r][1] * X[1] + M[r][2] * X[2] + M[r][3] for r in range(4)]
    s = (c[0] / c[3] + 1.0) * 0.5
    t = (c[1] / c[3] + 1.0) * 0.5
    z = c[2] / c[3]
    if smap.log_warp is not None:
        lw = smap.log_warp
        c0, c1, c2 = (dr.opaque(mi.Float64, float(v)) for v in (lw.c0, lw.c1, lw.c2))
        t = c0 * dr.log(c1 * t + c2)
    return s, t, z, c[3]


def _device_tan_psi(mi, dr, light: Light, origin: np.ndarray, X, N):
    """min(tan psi, TAN_PSI_MAX) in Dr.Jit Float64: psi the angle between the unit normals N and the direction
    to the light from the re-centred points X (module doc, step 4)."""
    F64 = mi.Float64
    one, zero = dr.opaque(F64, 1.0), dr.opaque(F64, 0.0)
    if isinstance(light, DirectionalLight):
        to_l = [dr.opaque(F64, float(-light.direction[r])) for r in range(3)]
    else:
        lp = np.asarray(light.position, dtype=np.float64) - origin
        v = [dr.opaque(F64, float(lp[r])) - X[r] for r in range(3)]
        inv = 1.0 / dr.maximum(dr.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]), 1e-300)
        to_l = [v[r] * inv for r in range(3)]
    c = dr.clip(N[0] * to_l[0] + N[1] * to_l[1] + N[2] * to_l[2], zero, one)
    tmax = dr.opaque(F64, TAN_PSI_MAX)
    tan_psi = dr.sqrt(dr.maximum(one - c * c, zero)) / c
    return dr.select(dr.isfinite(tan_psi), dr.minimum(tan_psi, tmax), tmax)


def device_lookup(rs: RayScene, light: Light, smap: ShadowMap, d_occ, X, N, tolerance: float,
                   engine: dict | None = None):
    """The engine's shadow test (module doc, step 4) in Dr.Jit for re-centred points X with unit
    normals N (lists of three Float64). Returns NumPy (shadowed, inside, u, v): u, v the texel
    coordinates s * width, t * height (NaN where clip w <= 0). `engine` (engine_depth): the
    engine-faithful test of DEPTH_RULE_ENGINE instead of the idealized rule, and then `d_occ` is the
    engine's stored depth map (device_engine_map), not d_occluder."""
    mi = mitsuba()
    import drjit as dr  # lazy: after mitsuba(), which points Dr.Jit at its libLLVM (solvers.jit)

    if engine is not None:
        return _device_engine_lookup(mi, dr, rs, light, smap, d_occ, X, N, engine)

    F64 = mi.Float64
    w, h = smap.resolution
    wf, hf = dr.opaque(F64, float(w)), dr.opaque(F64, float(h))
    s, t, z, cw = _device_map_coords(mi, dr, smap, rs.origin, X)
    one = dr.opaque(F64, 1.0)
    zero = dr.opaque(F64, 0.0)
    inside = (cw > zero) & (s >= zero) & (s <= one) & (t >= zero) & (t <= one) & (z >= -one) & (z <= one)
    fi = dr.select(inside, dr.clip(dr.floor(s * wf), zero, wf - 1.0), zero)
    fj = dr.select(inside, dr.clip(dr.floor(t * hf), zero, hf - 1.0), zero)
    A = opaque_matrix(mi, dr, inverse_matrix(smap, rs.origin))
    near, dirn, _ = device_rays_through(mi, dr, smap, A, (fi + 0.5) / wf, (fj + 0.5) / hf)
    d_rec = sum((X[r] - near[r]) * dirn[r] for r in range(3))
    tan_psi = _device_tan_psi(mi, dr, light, rs.origin, X, N)
    bias = (dr.opaque(F64, float(smap.depth_bias.get("constant", 0.0)))
            + dr.opaque(F64, float(smap.depth_bias.get("slope", 0.0))) * tan_psi
            + dr.opaque(F64, float(tolerance)))
    kc, ks = float(smap.depth_bias.get("constant_texels", 0.0)), float(smap.depth_bias.get("slope_texels", 0.0))
    if kc or ks:  # the texel-scaled part: tau = world size of the serving texel at X (module doc, step 4)
        on_ray = [near[r] + d_rec * dirn[r] for r in range(3)]
        tau = zero
        for ds_, dt_ in ((1.0, 0.0), (0.0, 1.0)):
            # the neighbouring texel's ray (towards the map's inside at the last row or column)
            si = dr.select(fi + ds_ < wf, fi + ds_, fi - ds_) if ds_ else fi
            tj = dr.select(fj + dt_ < hf, fj + dt_, fj - dt_) if dt_ else fj
            n1, d1, _ = device_rays_through(mi, dr, smap, A, (si + 0.5) / wf, (tj + 0.5) / hf)
            a = sum((X[r] - n1[r]) * d1[r] for r in range(3))
            q = [n1[r] + a * d1[r] - on_ray[r] for r in range(3)]
            tau = dr.maximum(tau, dr.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2]))
        bias = bias + (dr.opaque(F64, kc) + dr.opaque(F64, ks) * tan_psi) * tau
    idx = mi.UInt32(fj) * dr.opaque(mi.UInt32, int(w)) + mi.UInt32(fi)
    occ = dr.gather(F64, d_occ, idx, inside)
    shadowed = inside & (d_rec > occ + bias)
    u = dr.select(cw > zero, s * wf, dr.nan)
    vv = dr.select(cw > zero, t * hf, dr.nan)
    dr.eval(shadowed, inside, u, vv)
    return shadowed.numpy().astype(bool), inside.numpy().astype(bool), u.numpy(), vv.numpy()


def _device_engine_lookup(mi, dr, rs: RayScene, light: Light, smap: ShadowMap, stored_map, X, N, engine: dict):
    """DEPTH_RULE_ENGINE in Dr.Jit (`shadow_test(..., engine=...)` is its NumPy reference)."""
    F64 = mi.Float64
    w, h = smap.resolution
    wf, hf = dr.opaque(F64, float(w)), dr.opaque(F64, float(h))
    one = dr.opaque(F64, 1.0)
    zero = dr.opaque(F64, 0.0)
    off = dr.opaque(F64, engine["normal_offset"])
    Xp = [X[r] + off * N[r] for r in range(3)]
    s, t, z, cw = _device_map_coords(mi, dr, smap, rs.origin, Xp)
    d_rec = device_stored_depth(mi, dr, smap, rs.origin, engine, Xp)
    inside = (cw > zero) & (s >= zero) & (s <= one) & (t >= zero) & (t <= one) & (d_rec >= zero) & (d_rec <= one)
    fi = dr.select(inside, dr.clip(dr.floor(s * wf), zero, wf - 1.0), zero)
    fj = dr.select(inside, dr.clip(dr.floor(t * hf), zero, hf - 1.0), zero)
    idx = mi.UInt32(fj) * dr.opaque(mi.UInt32, int(w)) + mi.UInt32(fi)
    stored = dr.gather(F64, stored_map, idx, inside)  # the light pass's depth buffer (device_engine_map)
    tan_psi = _device_tan_psi(mi, dr, light, rs.origin, Xp, N)
    bias = dr.opaque(F64, engine["constant"]) + dr.opaque(F64, engine["slope"]) * tan_psi
    shadowed = inside & (d_rec - bias > stored)
    s0, t0, _, cw0 = _device_map_coords(mi, dr, smap, rs.origin, X)  # the metric's coordinates: X itself
    u = dr.select(cw0 > zero, s0 * wf, dr.nan)
    vv = dr.select(cw0 > zero, t0 * hf, dr.nan)
    dr.eval(shadowed, inside, u, vv)
    return shadowed.numpy().astype(bool), inside.numpy().astype(bool), u.numpy(), vv.numpy()


def tan_psi_clamped(light: Light, positions: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """min(tan psi, TAN_PSI_MAX) in NumPy, psi between the unit normals and the direction to the light (the
    reference of _device_tan_psi; TAN_PSI_MAX where the normal faces away or is edge-on)."""
    c = np.clip(-np.sum(np.asarray(normals, float) * light_ray_dirs(light, positions), axis=-1), 0.0, 1.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        tan_psi = np.sqrt(np.maximum(1.0 - c * c, 0.0)) / c
    return np.where(np.isfinite(tan_psi), np.minimum(tan_psi, TAN_PSI_MAX), TAN_PSI_MAX)


def shadow_test(smap: ShadowMap, d_occ: np.ndarray, positions: np.ndarray, normals: np.ndarray,
                light: Light, tolerance: float, engine: dict | None = None):
    """Engine-style lookup for points served by `smap`. Returns (shadowed, outside). `engine`
    (engine_depth): DEPTH_RULE_ENGINE instead of the idealized rule, and then `d_occ` is the engine's
    stored depth map (engine_stored_map), not d_occluder."""
    if engine is not None:
        return _engine_shadow_test(smap, d_occ, positions, normals, light, engine)
    w, h = smap.resolution
    s, t, z, cw = smap.map_coords(positions)
    with np.errstate(invalid="ignore"):
        inside = (cw > 0) & (s >= 0) & (s <= 1) & (t >= 0) & (t <= 1) & (z >= -1) & (z <= 1)
    inside &= np.isfinite(s) & np.isfinite(t) & np.isfinite(z)
    shadowed = np.zeros(len(positions), dtype=bool)
    if inside.any():
        si, ti = s[inside], t[inside]
        i = np.clip(np.floor(si * w).astype(np.int64), 0, w - 1)
        j = np.clip(np.floor(ti * h).astype(np.int64), 0, h - 1)
        near, far = smap.texel_rays((i + 0.5) / w, (j + 0.5) / h)
        dirn = far - near
        dirn /= np.maximum(np.linalg.norm(dirn, axis=-1, keepdims=True), 1e-300)
        X = positions[inside]
        d_rec = np.sum((X - near) * dirn, axis=-1)
        tan_psi = tan_psi_clamped(light, X, normals[inside])
        bias = float(smap.depth_bias.get("constant", 0.0)) + float(smap.depth_bias.get("slope", 0.0)) * tan_psi
        kc, ks = float(smap.depth_bias.get("constant_texels", 0.0)), float(smap.depth_bias.get("slope_texels", 0.0))
        if kc or ks:
            bias = bias + (kc + ks * tan_psi) * texel_world_size_at(smap, i, j, X, near + d_rec[:, None] * dirn)
        shadowed[inside] = d_rec > d_occ[j, i] + bias + tolerance
    return shadowed, ~inside


def _engine_shadow_test(smap: ShadowMap, stored_map: np.ndarray, positions: np.ndarray, normals: np.ndarray,
                        light: Light, engine: dict):
    """DEPTH_RULE_ENGINE in NumPy (the reference of _device_engine_lookup)."""
    w, h = smap.resolution
    mode, near_d, far_d = engine["mode"], engine["near"], engine["far"]
    Xp = np.asarray(positions, float) + engine["normal_offset"] * np.asarray(normals, float)
    s, t, z, cw = smap.map_coords(Xp)
    with np.errstate(invalid="ignore"):
        d_rec = stored_depth(smap, mode, Xp, near_d, far_d)
        inside = (cw > 0) & (s >= 0) & (s <= 1) & (t >= 0) & (t <= 1) & (d_rec >= 0) & (d_rec <= 1)
    inside &= np.isfinite(s) & np.isfinite(t) & np.isfinite(d_rec)
    shadowed = np.zeros(len(Xp), dtype=bool)
    if inside.any():
        i = np.clip(np.floor(s[inside] * w).astype(np.int64), 0, w - 1)
        j = np.clip(np.floor(t[inside] * h).astype(np.int64), 0, h - 1)
        stored = stored_map[j, i]
        X = Xp[inside]
        tan_psi = tan_psi_clamped(light, X, np.asarray(normals, float)[inside])
        shadowed[inside] = engine_shadowed(d_rec[inside], stored, engine["constant"], engine["slope"], tan_psi)
    return shadowed, ~inside


def texel_world_size_at(smap: ShadowMap, i: np.ndarray, j: np.ndarray, X: np.ndarray, on_ray: np.ndarray) -> np.ndarray:
    """tau: the world size of texel (i, j) at the points X, the larger distance from X's point on the
    texel's ray (`on_ray`) to the nearest point of the neighbouring texel's ray along s and along t
    (the neighbour towards the map's inside at the last column or row)."""
    w, h = smap.resolution
    tau = np.zeros(len(X))
    for di, dj in ((1, 0), (0, 1)):
        ii = np.where(i + di < w, i + di, i - di) if di else i
        jj = np.where(j + dj < h, j + dj, j - dj) if dj else j
        n1, f1 = smap.texel_rays((ii + 0.5) / w, (jj + 0.5) / h)
        d1 = (f1 - n1) / np.maximum(np.linalg.norm(f1 - n1, axis=-1, keepdims=True), 1e-300)
        a = np.sum((X - n1) * d1, axis=-1)
        tau = np.maximum(tau, np.linalg.norm(n1 + a[:, None] * d1 - on_ray, axis=-1))
    return tau


def texel_coords(smap: ShadowMap, positions: np.ndarray) -> np.ndarray:
    """(N, 2) texel coordinates (s * width, t * height), NaN where clip w <= 0."""
    s, t, z, cw = smap.map_coords(positions)
    uv = np.stack([s * smap.resolution[0], t * smap.resolution[1]], axis=-1)
    uv[~(cw > 0)] = np.nan
    return uv
