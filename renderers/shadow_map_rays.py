"""Shadow maps rendered by ray casting texel centres (renderers.ground_truth, step 3), and the engine's light
pass: the depth an engine's depth buffer stores, with its caster-side slope-scaled bias (device_engine_map,
NumPy engine_stored_map; step 4's engine depth).
"""
from __future__ import annotations

import numpy as np

from ..solvers.depth_modes import stored_depth
from ..solvers.engine_depth_test import DZ_CAP, stored_with_bias, unorm_steps
from ..solvers.jit import aligned
from ..solvers.lights import DirectionalLight, Light
from ..solvers.shadow_map import ShadowMap
from .mitsuba_setup import mitsuba
from .ray_scene import RayScene

RAY_CHUNK = 1 << 21  # texel rays per Dr.Jit launch


def host_geometry(rs: RayScene):
    """Float64 copies of the (re-centred) vertices and faces, cached on the RayScene."""
    cached = getattr(rs, "_gt_host_geometry", None)
    if cached is None:
        v = np.array(rs.vertices, dtype=np.float64).reshape(-1, 3)
        f = np.array(rs.faces, dtype=np.int64).reshape(-1, 3)
        cached = (v, f)
        try:
            object.__setattr__(rs, "_gt_host_geometry", cached)
        except Exception:  # pragma: no cover
            pass
    return cached


def recentre(origin: np.ndarray) -> np.ndarray:
    """Re-centred -> world: x_world = x + origin (4x4)."""
    m = np.eye(4)
    m[:3, 3] = np.asarray(origin, dtype=np.float64)
    return m


def opaque_matrix(mi, dr, m: np.ndarray):
    return [[dr.opaque(mi.Float64, float(m[r, c])) for c in range(4)] for r in range(4)]


def device_rays_through(mi, dr, smap: ShadowMap, A, s, t):
    """`ShadowMap.texel_rays` in Dr.Jit Float64: the light ray through map coordinates (s, t) (log
    warp inverted), between z_ndc = -1 and +1. A = inverse of the re-centred world -> clip matrix.
    Returns (near, direction, length) in re-centred coordinates."""
    F64 = mi.Float64
    if smap.log_warp is not None:
        lw = smap.log_warp
        c0, c1, c2 = (dr.opaque(F64, float(c)) for c in (lw.c0, lw.c1, lw.c2))
        t = (dr.exp(t / c0) - c2) / c1
    x = 2.0 * s - 1.0
    y = 2.0 * t - 1.0
    # h(z) = A @ (x, y, z, 1) = base + z * A[:, 2]
    base = [A[r][0] * x + A[r][1] * y + A[r][3] for r in range(4)]
    near_h = [base[r] - A[r][2] for r in range(4)]
    far_h = [base[r] + A[r][2] for r in range(4)]
    near = [near_h[r] / near_h[3] for r in range(3)]
    far = [far_h[r] / far_h[3] for r in range(3)]
    seg = [far[r] - near[r] for r in range(3)]
    length = dr.sqrt(seg[0] * seg[0] + seg[1] * seg[1] + seg[2] * seg[2])
    inv_len = dr.select(length > 0, 1.0 / length, 0.0)
    dirn = [seg[r] * inv_len for r in range(3)]
    return near, dirn, length


def inverse_matrix(smap: ShadowMap, origin: np.ndarray) -> np.ndarray:
    """NDC (x, y, z, 1) -> homogeneous re-centred point: inv(P V) then the re-centring (float64)."""
    return np.linalg.inv(recentre(origin)) @ np.linalg.inv(smap.matrix)


def device_texel_rays(mi, dr, smap: ShadowMap, origin: np.ndarray, first, count: int):
    """Texel-centre rays for texels first .. first + count - 1 (row-major, row j = t index).
    Every number that changes between maps (matrix, resolution, log warp, chunk start) is opaque:
    one kernel serves all maps. Returns (near, direction, length, texel index)."""
    F64 = mi.Float64
    U32 = mi.UInt32
    w, h = smap.resolution
    A = opaque_matrix(mi, dr, inverse_matrix(smap, origin))
    idx = dr.arange(U32, count) + first
    j = idx // dr.opaque(U32, int(w))
    i = idx - j * dr.opaque(U32, int(w))
    s = (F64(i) + 0.5) / dr.opaque(F64, float(w))
    t = (F64(j) + 0.5) / dr.opaque(F64, float(h))
    return device_rays_through(mi, dr, smap, A, s, t) + (idx,)


NO_PRIM = 0xFFFFFFFF  # prim index of a texel whose ray hits nothing or is pancaked


def device_map(rs: RayScene, light: Light, smap: ShadowMap, pancake: bool = True, prims: bool = False):
    """d_occluder per texel as a Dr.Jit Float64 array (row-major, row j = t index); with `prims`, also
    the hit triangle per texel (UInt32, NO_PRIM where nothing is hit or the caster is pancaked).

    One Dr.Jit launch per RAY_CHUNK texels: the texel-centre rays are generated on the device
    (float64, then the ray itself in float32), started where they enter the scene's bounding sphere,
    cast with `ray_intersect_preliminary`; for directional lights a backwards `ray_test` from the
    near plane finds casters in front of it (pancaking)."""
    mi = mitsuba()
    import drjit as dr  # lazy: after mitsuba(), which points Dr.Jit at its libLLVM (solvers.jit)

    F64 = mi.Float64
    w, h = smap.resolution
    n_total = int(w) * int(h)
    radius = scene_radius(rs)
    do_pancake = pancake and isinstance(light, DirectionalLight)
    chunk = max(int(w), (RAY_CHUNK // max(int(w), 1)) * int(w))
    # Each chunk scatters into one buffer at opaque offsets (dr.concat would compile a kernel per
    # combination of chunk sizes).
    out = dr.full(F64, dr.inf, n_total)
    prim_out = dr.full(mi.UInt32, NO_PRIM, n_total) if prims else None
    for first in range(0, n_total, chunk):
        count = min(chunk, n_total - first)
        near, dirn, length, idx = device_texel_rays(mi, dr, smap, rs.origin, dr.opaque(mi.UInt32, first), count)
        d_occ, prim = first_hits(mi, dr, rs, near, dirn, length, radius, do_pancake)
        dr.scatter(out, d_occ, idx)
        if prims:
            dr.scatter(prim_out, prim, idx)
            dr.eval(out, prim_out)
        else:
            dr.eval(out)
    return (out, prim_out) if prims else out


def first_hits(mi, dr, rs: RayScene, near, dirn, length, radius: float, pancake: bool):
    """(d_occluder, prim) of light rays given as Dr.Jit Float64 (near point, unit direction, segment length;
    re-centred): each ray starts where it enters the scene's bounding sphere (`radius` about the re-centred
    origin: nothing is hit before it, and float32 origins stay close to the geometry) and is cast with
    `ray_intersect_preliminary`; d_occluder = distance from the near point to the first hit (inf: none);
    with `pancake` (directional lights) a backwards `ray_test` from the near plane finds casters in front
    of it: d_occluder 0 and prim NO_PRIM there, as for rays that hit nothing."""
    F64 = mi.Float64
    ok = dr.isfinite(length) & (length > 0)
    for r in range(3):
        ok &= dr.isfinite(near[r])
    proj = -(near[0] * dirn[0] + near[1] * dirn[1] + near[2] * dirn[2])
    rad = dr.opaque(F64, radius)
    zero = dr.opaque(F64, 0.0)
    safe_len = dr.select(ok, length, zero)
    t0 = dr.clip(proj - rad, zero, safe_len)
    t1 = dr.minimum(safe_len, proj + rad)
    ok &= t1 > t0
    org = mi.Point3f(*(mi.Float(near[r] + t0 * dirn[r]) for r in range(3)))
    d32 = mi.Vector3f(*(mi.Float(dirn[r]) for r in range(3)))
    maxt = mi.Float(dr.select(ok, t1 - t0, zero))
    ray = mi.Ray3f(org, d32)
    ray.maxt = maxt
    active = ok & (maxt > 0)
    pi = rs.scene.ray_intersect_preliminary(ray, coherent=False, active=active)
    valid = pi.is_valid() & active
    d_occ = dr.select(valid, F64(pi.t) + t0, dr.inf)
    faced = valid
    if pancake:
        blocked = rs.scene.ray_test(mi.Ray3f(org, -d32), active & (t0 <= zero))
        d_occ = dr.select(blocked, zero, d_occ)
        faced &= ~blocked
    d_occ = dr.select(ok, d_occ, dr.inf)
    return d_occ, dr.select(faced & ok, pi.prim_index, dr.opaque(mi.UInt32, NO_PRIM))


def scene_radius(rs: RayScene) -> float:
    """The bounding sphere's radius first_hits starts rays on (a hair larger than half the extent)."""
    return 0.5 * rs.extent * (1.0 + 1e-4) + 1e-6


def texel_hits(rs: RayScene, light: Light, smap: ShadowMap, i: np.ndarray, j: np.ndarray, pancake: bool = True):
    """device_map for the given texels only: (d_occluder, prim) NumPy (float64, int64 with -1 for none or
    pancaked) of the texel-centre rays of texels (i, j) (the depth probe's sparse light pass)."""
    mi = mitsuba()
    import drjit as dr  # lazy: after mitsuba(), which points Dr.Jit at its libLLVM (solvers.jit)

    w, h = smap.resolution
    if len(i) == 0:
        return np.zeros(0), np.zeros(0, np.int64)
    A = opaque_matrix(mi, dr, inverse_matrix(smap, rs.origin))
    s = mi.Float64(aligned((np.asarray(i, np.float64) + 0.5) / w, np.float64))
    t = mi.Float64(aligned((np.asarray(j, np.float64) + 0.5) / h, np.float64))
    near, dirn, length = device_rays_through(mi, dr, smap, A, s, t)
    d_occ, prim = first_hits(mi, dr, rs, near, dirn, length, scene_radius(rs),
                             pancake and isinstance(light, DirectionalLight))
    dr.eval(d_occ, prim)
    p = np.asarray(prim.numpy(), dtype=np.int64)
    p[p == NO_PRIM] = -1
    return np.asarray(d_occ.numpy(), dtype=np.float64), p


def render_map(rs: RayScene, light: Light, smap: ShadowMap, pancake: bool = True, prims: bool = False):
    """d_occluder (m) per texel, (height, width) float64, row j = t index (t = 0 at the bottom); with
    `prims`, (d_occluder, prim) with prim the hit triangle per texel (int64, -1: none or pancaked)."""
    w, h = smap.resolution
    got = device_map(rs, light, smap, pancake, prims)
    if not prims:
        return np.asarray(got.numpy(), dtype=np.float64).reshape(h, w)
    prim = np.asarray(got[1].numpy(), dtype=np.int64).reshape(h, w)
    prim[prim == NO_PRIM] = -1
    return np.asarray(got[0].numpy(), dtype=np.float64).reshape(h, w), prim


def face_normals(rs: RayScene) -> np.ndarray:
    """(F, 3) float64 unit geometric normals of the RayScene's triangles (cached)."""
    cached = getattr(rs, "_gt_face_normals", None)
    if cached is None:
        v, f = host_geometry(rs)
        n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
        cached = n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-300)
        try:
            object.__setattr__(rs, "_gt_face_normals", cached)
        except Exception:  # pragma: no cover
            pass
    return cached


def caster_depth(rs: RayScene, smap: ShadowMap, i: np.ndarray, j: np.ndarray, d_occ: np.ndarray, prim: np.ndarray,
                 mode: str, near_d: float, far_d: float) -> tuple[np.ndarray, np.ndarray]:
    """(D(P), DZ) per texel (i, j): P the texel-centre ray's first hit (d_occ along it; 0 where nothing is
    hit), D the mode's stored depth, DZ = max(|D(P_x) - D(P)|, |D(P_y) - D(P)|) with P_x, P_y the caster's
    plane (its triangle's geometric normal through P) on the rays of texels (i + 1, j) and (i, j + 1)
    (past the last column or row too: the same projection continued); inf where that plane is edge-on."""
    w, h = smap.resolution
    occ = np.asarray(d_occ, float).ravel()
    pr = np.asarray(prim).ravel()
    hit = np.isfinite(occ)
    faced = hit & (pr >= 0)
    with np.errstate(all="ignore"):
        near, far = smap.texel_rays((i + 0.5) / w, (j + 0.5) / h)
        dirn = (far - near) / np.maximum(np.linalg.norm(far - near, axis=-1, keepdims=True), 1e-300)
        P = near + np.where(hit, occ, 0.0)[:, None] * dirn
        D = stored_depth(smap, mode, P, near_d, far_d)
        nrm = face_normals(rs)[np.where(faced, pr, 0)]
        dz = np.zeros(len(occ))
        for di, dj in ((1, 0), (0, 1)):
            n1, f1 = smap.texel_rays((i + di + 0.5) / w, (j + dj + 0.5) / h)
            d1 = f1 - n1
            a = np.sum(nrm * (P - n1), axis=-1) / np.sum(nrm * d1, axis=-1)
            step = np.abs(stored_depth(smap, mode, n1 + a[:, None] * d1, near_d, far_d) - D)
            dz = np.maximum(dz, np.where(np.isfinite(step), step, np.inf))
    return D, dz


def engine_stored_map(rs: RayScene, smap: ShadowMap, d_occ: np.ndarray, prim: np.ndarray, engine: dict) -> np.ndarray:
    """What the engine's light pass leaves in the depth buffer, (height, width) float64 (NumPy reference of
    device_engine_map): caster_depth per texel, then stored_with_bias with the engine's slope_scaled,
    slope_clamp and depth format."""
    w, h = smap.resolution
    jj, ii = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    ii, jj = ii.ravel(), jj.ravel()
    occ, pr = np.asarray(d_occ, float).ravel(), np.asarray(prim).ravel()
    D, dz = caster_depth(rs, smap, ii, jj, occ, pr, engine["mode"], engine["near"], engine["far"])
    k, m = float(engine.get("slope_scaled", 0.0)), float(engine.get("slope_clamp", np.inf))
    return stored_with_bias(D, dz, occ, pr, k, m, engine.get("format", "float32"),
                            float(engine.get("caster_constant", 0.0))).reshape(h, w)


def device_points(mi, a: np.ndarray):
    """(N, 3) float64 NumPy -> three Dr.Jit Float64 (aligned copies: no recompilation)."""
    a = np.asarray(a, dtype=np.float64)
    return [mi.Float64(aligned(a[:, k], np.float64)) for k in range(3)]


def device_stored_depth(mi, dr, smap: ShadowMap, origin: np.ndarray, engine: dict, P):
    """D(P) of the engine's mode for re-centred points P (solvers.depth_modes: hardware window z,
    linear (-z_view - near) / (far - near))."""
    F64 = mi.Float64
    if engine["mode"] == "hardware":
        M = opaque_matrix(mi, dr, smap.matrix @ recentre(origin))
        cz = M[2][0] * P[0] + M[2][1] * P[1] + M[2][2] * P[2] + M[2][3]
        cw = M[3][0] * P[0] + M[3][1] * P[1] + M[3][2] * P[2] + M[3][3]
        return 0.5 * (cz / cw + 1.0)
    V = opaque_matrix(mi, dr, smap.view @ recentre(origin))
    zv = V[2][0] * P[0] + V[2][1] * P[1] + V[2][2] * P[2] + V[2][3]
    near = dr.opaque(F64, engine["near"])
    return (-zv - near) / dr.opaque(F64, engine["far"] - engine["near"])


def _device_face_normals(mi, rs: RayScene):
    """face_normals as three Dr.Jit Float64 arrays (cached on the RayScene)."""
    cached = getattr(rs, "_gt_device_face_normals", None)
    if cached is None:
        cached = device_points(mi, face_normals(rs))
        try:
            object.__setattr__(rs, "_gt_device_face_normals", cached)
        except Exception:  # pragma: no cover
            pass
    return cached


def device_engine_map(rs: RayScene, smap: ShadowMap, d_occ, prim, engine: dict):
    """engine_stored_map in Dr.Jit: the engine's stored depth per texel (Float64 holding float32 values,
    row-major) from the map's d_occluder and hit triangles (device_map(..., prims=True))."""
    mi = mitsuba()
    import drjit as dr  # lazy: after mitsuba(), which points Dr.Jit at its libLLVM (solvers.jit)

    F64, U32 = mi.Float64, mi.UInt32
    w, h = smap.resolution
    wf, hf = dr.opaque(F64, float(w)), dr.opaque(F64, float(h))
    zero, one = dr.opaque(F64, 0.0), dr.opaque(F64, 1.0)
    k = float(engine.get("slope_scaled", 0.0))
    m = float(engine.get("slope_clamp", np.inf))
    idx = dr.arange(U32, int(w) * int(h))
    j = idx // dr.opaque(U32, int(w))
    i = idx - j * dr.opaque(U32, int(w))
    fi, fj = F64(i), F64(j)
    A = opaque_matrix(mi, dr, inverse_matrix(smap, rs.origin))
    near, dirn, _ = device_rays_through(mi, dr, smap, A, (fi + 0.5) / wf, (fj + 0.5) / hf)
    hit = dr.isfinite(d_occ)
    faced = hit & (prim != dr.opaque(U32, NO_PRIM))
    occ0 = dr.select(hit, d_occ, zero)
    P = [near[r] + occ0 * dirn[r] for r in range(3)]
    D = device_stored_depth(mi, dr, smap, rs.origin, engine, P)
    if k:
        fn = _device_face_normals(mi, rs)
        nrm = [dr.gather(F64, fn[r], dr.select(faced, prim, dr.opaque(U32, 0)), faced) for r in range(3)]
        dz = zero
        for ds_, dt_ in ((1.0, 0.0), (0.0, 1.0)):  # texels (i + 1, j), (i, j + 1): the caster's plane there
            n1, d1, _ = device_rays_through(mi, dr, smap, A, (fi + ds_ + 0.5) / wf, (fj + dt_ + 0.5) / hf)
            a = (sum(nrm[r] * (P[r] - n1[r]) for r in range(3)) / sum(nrm[r] * d1[r] for r in range(3)))
            step = dr.abs(device_stored_depth(mi, dr, smap, rs.origin, engine,
                                               [n1[r] + a * d1[r] for r in range(3)]) - D)
            dz = dr.maximum(dz, dr.select(dr.isfinite(step), step, dr.inf))
        off = dr.minimum(dr.opaque(F64, k) * dr.minimum(dz, dr.opaque(F64, DZ_CAP)), dr.opaque(F64, m))
        D = D + off
    if engine.get("caster_constant"):  # a caster-side constant, before the rounding (engine_depth_test.CONSTANT_SIDES)
        D = D + dr.opaque(F64, float(engine["caster_constant"]))
    stored = dr.select(faced, dr.clip(D, zero, one), dr.select(hit, zero, one))
    stored = device_quantize(mi, dr, stored, engine.get("format", "float32"))
    dr.eval(stored)
    return stored


def device_quantize(mi, dr, D, depth_format: str):
    """quantize_depth in Dr.Jit: float32 rounding (D32F), float16 rounding (a half-float target) or
    round(D (2^bits - 1)) / (2^bits - 1) (a normalized fixed-point depth buffer)."""
    steps = unorm_steps(depth_format)
    if steps is None:
        return mi.Float64(mi.Float16(D) if depth_format == "float16" else mi.Float(D))
    q = dr.opaque(mi.Float64, float(steps))
    return dr.round(D * q) / q
