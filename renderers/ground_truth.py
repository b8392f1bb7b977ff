"""Ground truth (DESIGN.md, "Ground truth"): score any shadow setup against ray-traced shadows.

`evaluate(rs, camera, light, maps)` does what an engine does with the maps, but with rays:

1. Screen. One camera ray per full-resolution pixel (`screen`, or the camera's own resolution)
   through the coarse pass's helpers; hit, world position, geometric normal (turned towards the
   camera), view depth, prim. Positions are refined in float64 by intersecting the exact pixel ray
   with the plane of the hit triangle (the triangle is what Embree found), so finite differences
   between neighbouring pixels are smooth. Receivers: hits whose camera-facing side faces the light
   (n . to_light > 0) and, for spot lights, inside the cone.
2. Exact visibility: one shadow ray per receiver (`coarse.light_test`).
3. Each map is "rendered" by casting one ray per texel centre along the light ray that texel is
   (`ShadowMap.texel_rays`: the segment between z_ndc = -1 and +1, i.e. clipped to the light's depth
   range as a rasterizer clips; warped and log parameterizations alike). The map stores
   d_occluder = distance (m) from the texel's near point to the first hit, +inf when none.
   The texel-centre rays are generated inside Dr.Jit (float64 inverse of P V with the RayScene's
   re-centring folded in, the log warp inverted on t; the same math as `ShadowMap.texel_rays`, which
   tests/test_ground_truth.py checks), RAY_CHUNK rays per launch, all changing numbers opaque: one
   compiled kernel serves every map and camera (a 2048^2 map is ~0.2 s on 2 cores).
   Pancaking (directional lights only, as engines clamp casters with GL_DEPTH_CLAMP / "shadow
   pancaking"): a caster between the light and the near plane is clamped to the near plane,
   d_occluder = 0. Pass `pancake=False` for a strict rasterizer clip.
4. Shadow test (in Dr.Jit float64 for every hit pixel and map: `ShadowMap.map_coords`, nearest texel,
   that texel's ray, the map's d_occluder gathered on the device; `shadow_test` is the NumPy
   reference it is tested against), as an engine does it: the cascade serving the pixel's view depth
   (`map_for_depth`; for cube faces, the first face whose map contains the point), nearest texel
   (no filtering), d_receiver = distance of X along that texel's ray from its near point, and

       THE BIAS RULE (one rule for every method; units are metres along the light ray):
       shadowed  iff  d_receiver > d_occluder + bias["constant"] + bias["slope"] * tan(psi)
                      + tau * (bias["constant_texels"] + bias["slope_texels"] * tan(psi))
                      + NUMERIC_TOLERANCE * (scene extent)
       psi = angle between the surface normal and the direction to the light, tan(psi) clamped
       at TAN_PSI_MAX = 10; tau = the world size of the serving texel at the receiver (distance
       from the receiver's point on the texel's ray to the neighbouring texels' rays): the texel
       units of a hardware slope-scaled depth bias or a normal-offset bias, which follow a warped
       map's varying texel size. Missing keys are 0. The last term (1e-6 of the scene's diagonal)
       only absorbs float32 ray casting noise; it is far below any texel.

   Receivers outside the map that serves them (s or t outside [0, 1], z_ndc outside [-1, 1], clip
   w <= 0, or a view depth no cascade's split covers) count as `outside_pixels` and are treated as
   lit, as an engine's clamp-to-border sampler with border depth 1 would: where they are exactly
   shadowed they are also misclassified. A receiver lost by its cascade counts as outside even if
   another cascade happens to cover it (the engine would not look there).
   Engine depth (`depth` = "solution" | "hardware" | "linear"; "ideal" is the rule above): what an
   engine does with each map's `depth` block (solvers.depth_modes), DEPTH_RULE_ENGINE: the lookup
   point X' = X + normal_offset N, the mode's stored depth D (hardware: window z of P V; linear:
   (-z_view - near) / (far - near)) at X' against the texel's stored D, what the light pass leaves in a
   D32F buffer with the caster-side slope-scaled bias (OpenGL 4.6 §14.6.5 polygon offset, max form;
   D3D11 SlopeScaledDepthBias / DepthBiasClamp): P the texel ray's first hit, the hit triangle's plane
   intersected with the rays of texels (i + 1, j) and (i, j + 1) at P_x, P_y, DZ = max(|D(P_x) - D(P)|,
   |D(P_y) - D(P)|), stored = clamp(D(P) + min(slope_scaled DZ, slope_clamp), 0, 1) float32-rounded
   (0 for pancaked casters; 1 where nothing is hit; `_device_engine_map`, NumPy `engine_stored_map`);
   shadowed iff D(X') - (constant + slope min(tan psi, 10)) > stored D, no tolerance term; receivers
   with s, t or D(X') outside [0, 1] are lit; cascades switch at the midpoint of each map's blend_band
   where the next cascade contains the point (`engine_cascades`). `_device_engine_lookup` and
   `shadow_test(..., engine=...)` implement the lookup.
5. misclassified = map result != exact visibility over receivers; boundary_pixels = receivers on
   the boundaries of exact visibility (`coarse.boundary_mask` at full resolution, radius 0).
6. measured_error: per pixel, the serving map's texel coordinates u = (s * width, t * height)
   (log warp applied) of the refined hit points of the pixel and its 4 neighbours; J = du/dx by
   central differences where both neighbours are on the same surface (both hits, same prim, view
   depths within coarse.DEPTH_CONTINUITY, normals within SAME_SURFACE_DEG), one-sided where only
   one is; pixels with no usable neighbour along x or y are left out. F = J^-1,
   m = max(|ds + dt|, |ds - dt|) (Lloyd et al. 2007 eq. 85), h = ||F||_F^2. Statistics via
   `solvers.metric.error_stats` over light-facing receivers on exact shadow boundaries (all
   light-facing receivers when there are none). Independent of the analytic Jacobian.
"""
from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass

import numpy as np

from ..solvers.cameras import Camera
from ..solvers.lights import DirectionalLight, Light
from ..solvers.jit import aligned
from ..solvers.metric import DET_FLOOR, error_stats
from ..solvers.shadow_map import ShadowMap, map_for_depth
from .coarse import DEPTH_CONTINUITY, boundary_mask, camera_rays, light_test, surface_hits
from .mitsuba_setup import mitsuba
from .ray_scene import RayScene

TAN_PSI_MAX = 10.0  # slope-bias clamp: tan(psi) of grazing receivers is limited to this
NUMERIC_TOLERANCE = 1e-6  # times the scene's diagonal, added to every bias (float32 ray casting noise)
SAME_SURFACE_DEG = 10.0  # neighbours whose normals differ by more are on different surfaces
RAY_CHUNK = 1 << 21  # texel rays per Dr.Jit launch
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
    "stored D = clamp(D(P) + min(slope_scaled * DZ, slope_clamp), 0, 1) rounded to float32, P the texel-centre "
    "ray's first hit, DZ = max(|D(P_x) - D(P)|, |D(P_y) - D(P)|) with P_x, P_y the caster triangle's plane on the "
    "rays of texels (i + 1, j) and (i, j + 1) (a caster-side slope-scaled bias: glPolygonOffsetClamp, D3D "
    "SlopeScaledDepthBias), 0 for pancaked casters, 1 where nothing is hit; shadowed iff D_rec - (constant + slope "
    f"* min(tan(psi), {TAN_PSI_MAX:g})) > stored D; receivers with s, t or D_rec outside [0, 1] are lit; cascades "
    "switch at the midpoint of each blend band where the next cascade contains the point")


def engine_depth(smap: ShadowMap, depth: str) -> dict | None:
    """The numbers an engine applies for `smap` under `depth` (DEPTH_CHOICES): None for "ideal", else
    {mode, constant, slope, normal_offset, near, far, slope_scaled, slope_clamp} from the map's depth block
    ("solution": the block's own mode; a block without slope_scaled has none, without slope_clamp no clamp).
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
           "slope_clamp": float(clamp) if clamp is not None else float("inf")}
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


@dataclass
class ScreenBuffers:
    width: int
    height: int
    hit: np.ndarray  # (h, w) bool
    position: np.ndarray  # (h, w, 3) float64 world (refined); NaN where no hit
    normal: np.ndarray  # (h, w, 3) float64 unit, towards the camera; 0 where no hit
    depth: np.ndarray  # (h, w) float64 view depth; inf where no hit
    prim: np.ndarray  # (h, w) int64 prim index; -1 where no hit
    visible: np.ndarray  # (h, w) bool exact: the shadow ray reaches the light
    facing: np.ndarray
    in_light: np.ndarray

    @property
    def receivers(self) -> np.ndarray:
        return self.hit & self.facing & self.in_light


@dataclass
class GroundTruth:
    """Per-pixel results of `evaluate_buffers`, (h, w) arrays."""

    screen: ScreenBuffers
    receivers: np.ndarray  # bool
    exact_shadowed: np.ndarray  # bool, receivers only
    map_shadowed: np.ndarray  # bool, receivers only
    misclassified: np.ndarray  # bool
    boundary: np.ndarray  # bool, receivers on exact-visibility boundaries (radius 0)
    outside: np.ndarray  # bool, receivers outside the map that serves them
    map_index: np.ndarray  # int, serving map (-1: none)
    texel_uv: np.ndarray  # (h, w, 2) serving map's texel coordinates; NaN where none
    m: np.ndarray  # float, measured Lloyd m (NaN where not measurable)
    h: np.ndarray  # float, measured ||F||_F^2
    sample_mask: np.ndarray  # bool, the pixels measured_error is computed over
    sample_kind: str
    result: dict


def screen_camera(camera: Camera, screen: tuple[int, int] | None) -> Camera:
    """The camera at the evaluation resolution. A `screen` of another aspect keeps the camera's aspect
    (long side = max(screen)), so the field of view is never distorted."""
    if screen is None:
        return camera
    w, h = int(screen[0]), int(screen[1])
    if w <= 0 or h <= 0:
        raise ValueError(f"screen must be positive, got {screen}")
    if abs(w / h - camera.aspect) > 1e-3 * camera.aspect:
        w, h = camera.coarse_resolution(max(w, h))
    return dataclasses.replace(camera, resolution=(w, h))


def _host_geometry(rs: RayScene):
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


def render_screen(rs: RayScene, camera: Camera, light: Light, shadow_rays: bool = True) -> ScreenBuffers:
    """Full-resolution camera pass at camera.resolution (the coarse pass's helpers at full size).
    shadow_rays=False: primary rays only, `visible` is not traced (renderers.coverage)."""
    mi = mitsuba()
    import drjit as dr

    width, height = camera.resolution
    ray, fwd = camera_rays(mi, dr, camera, width, height, rs.origin)
    pi, hit, t, p, n = surface_hits(mi, dr, rs, ray, fwd, camera)
    vis, fac, inl = light_test(mi, dr, rs, light, p, n, hit, shadow_rays)
    tri = pi.prim_index
    dr.eval(hit, tri, vis, fac, inl)
    shape = (height, width)
    hit_np = np.array(hit, dtype=bool).reshape(shape)
    tri_np = np.array(tri, dtype=np.int64).reshape(shape)
    vis_np = np.array(vis, dtype=bool).reshape(shape)
    fac_np = np.array(fac, dtype=bool).reshape(shape)
    inl_np = np.array(inl, dtype=bool).reshape(shape)

    # Float64 refinement: the exact pixel ray against the plane of the triangle Embree hit.
    verts, faces = _host_geometry(rs)
    prim_all = np.array(rs.face_prim, dtype=np.int64)
    d = camera.ray_directions(width, height)[hit_np]
    tris = tri_np[hit_np]
    fv = faces[tris]
    v0, v1, v2 = verts[fv[:, 0]], verts[fv[:, 1]], verts[fv[:, 2]]
    nrm = np.cross(v1 - v0, v2 - v0)
    nrm /= np.maximum(np.linalg.norm(nrm, axis=-1, keepdims=True), 1e-300)
    o = camera.position - rs.origin
    nd = np.sum(nrm * d, axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        tt = np.sum(nrm * (v0 - o), axis=-1) / nd
    bad = ~np.isfinite(tt) | (tt <= 0)
    if bad.any():  # edge-on triangles: keep the float32 hit distance
        t_np = np.array(t, dtype=np.float64).reshape(shape)[hit_np]
        tt = np.where(bad, t_np, tt)
    rel = o + tt[:, None] * d
    nrm = np.where((nd > 0)[:, None], -nrm, nrm)
    position = np.full((height, width, 3), np.nan)
    position[hit_np] = rel + rs.origin
    normal = np.zeros((height, width, 3))
    normal[hit_np] = nrm
    depth = np.full(shape, np.inf)
    depth[hit_np] = tt * (d @ camera.forward)
    prim = np.full(shape, -1, dtype=np.int64)
    prim[hit_np] = prim_all[tris]
    return ScreenBuffers(width, height, hit_np, position, normal, depth, prim, vis_np, fac_np, inl_np)


def _recentre(origin: np.ndarray) -> np.ndarray:
    """Re-centred -> world: x_world = x + origin (4x4)."""
    m = np.eye(4)
    m[:3, 3] = np.asarray(origin, dtype=np.float64)
    return m


def _opaque_matrix(mi, dr, m: np.ndarray):
    return [[dr.opaque(mi.Float64, float(m[r, c])) for c in range(4)] for r in range(4)]


def _device_rays_through(mi, dr, smap: ShadowMap, A, s, t):
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


def _inverse_matrix(smap: ShadowMap, origin: np.ndarray) -> np.ndarray:
    """NDC (x, y, z, 1) -> homogeneous re-centred point: inv(P V) then the re-centring (float64)."""
    return np.linalg.inv(_recentre(origin)) @ np.linalg.inv(smap.matrix)


def _device_texel_rays(mi, dr, smap: ShadowMap, origin: np.ndarray, first, count: int):
    """Texel-centre rays for texels first .. first + count - 1 (row-major, row j = t index).
    Every number that changes between maps (matrix, resolution, log warp, chunk start) is opaque:
    one kernel serves all maps. Returns (near, direction, length, texel index)."""
    F64 = mi.Float64
    U32 = mi.UInt32
    w, h = smap.resolution
    A = _opaque_matrix(mi, dr, _inverse_matrix(smap, origin))
    idx = dr.arange(U32, count) + first
    j = idx // dr.opaque(U32, int(w))
    i = idx - j * dr.opaque(U32, int(w))
    s = (F64(i) + 0.5) / dr.opaque(F64, float(w))
    t = (F64(j) + 0.5) / dr.opaque(F64, float(h))
    return _device_rays_through(mi, dr, smap, A, s, t) + (idx,)


NO_PRIM = 0xFFFFFFFF  # prim index of a texel whose ray hits nothing or is pancaked


def _device_map(rs: RayScene, light: Light, smap: ShadowMap, pancake: bool = True, prims: bool = False):
    """d_occluder per texel as a Dr.Jit Float64 array (row-major, row j = t index); with `prims`, also
    the hit triangle per texel (UInt32, NO_PRIM where nothing is hit or the caster is pancaked).

    One Dr.Jit launch per RAY_CHUNK texels: the texel-centre rays are generated on the device
    (float64, then the ray itself in float32), started where they enter the scene's bounding sphere,
    cast with `ray_intersect_preliminary`; for directional lights a backwards `ray_test` from the
    near plane finds casters in front of it (pancaking)."""
    mi = mitsuba()
    import drjit as dr

    F64 = mi.Float64
    w, h = smap.resolution
    n_total = int(w) * int(h)
    radius = 0.5 * rs.extent * (1.0 + 1e-4) + 1e-6
    do_pancake = pancake and isinstance(light, DirectionalLight)
    chunk = max(int(w), (RAY_CHUNK // max(int(w), 1)) * int(w))
    # Each chunk scatters into one buffer at opaque offsets (dr.concat would compile a kernel per
    # combination of chunk sizes).
    out = dr.full(F64, dr.inf, n_total)
    prim_out = dr.full(mi.UInt32, NO_PRIM, n_total) if prims else None
    for first in range(0, n_total, chunk):
        count = min(chunk, n_total - first)
        near, dirn, length, idx = _device_texel_rays(mi, dr, smap, rs.origin, dr.opaque(mi.UInt32, first), count)
        ok = dr.isfinite(length) & (length > 0)
        for r in range(3):
            ok &= dr.isfinite(near[r])
        # Start each ray where it enters the scene's bounding sphere (centred on the re-centred
        # origin): nothing is hit before it, and float32 origins stay close to the geometry.
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
        if do_pancake:
            blocked = rs.scene.ray_test(mi.Ray3f(org, -d32), active & (t0 <= zero))
            d_occ = dr.select(blocked, zero, d_occ)
            faced &= ~blocked
        d_occ = dr.select(ok, d_occ, dr.inf)
        dr.scatter(out, d_occ, idx)
        if prims:
            dr.scatter(prim_out, dr.select(faced & ok, pi.prim_index, dr.opaque(mi.UInt32, NO_PRIM)), idx)
            dr.eval(out, prim_out)
        else:
            dr.eval(out)
    return (out, prim_out) if prims else out


def render_map(rs: RayScene, light: Light, smap: ShadowMap, pancake: bool = True, prims: bool = False):
    """d_occluder (m) per texel, (height, width) float64, row j = t index (t = 0 at the bottom); with
    `prims`, (d_occluder, prim) with prim the hit triangle per texel (int64, -1: none or pancaked)."""
    w, h = smap.resolution
    got = _device_map(rs, light, smap, pancake, prims)
    if not prims:
        return np.asarray(got.numpy(), dtype=np.float64).reshape(h, w)
    prim = np.asarray(got[1].numpy(), dtype=np.int64).reshape(h, w)
    prim[prim == NO_PRIM] = -1
    return np.asarray(got[0].numpy(), dtype=np.float64).reshape(h, w), prim


def _face_normals(rs: RayScene) -> np.ndarray:
    """(F, 3) float64 unit geometric normals of the RayScene's triangles (cached)."""
    cached = getattr(rs, "_gt_face_normals", None)
    if cached is None:
        v, f = _host_geometry(rs)
        n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
        cached = n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-300)
        try:
            object.__setattr__(rs, "_gt_face_normals", cached)
        except Exception:  # pragma: no cover
            pass
    return cached


DZ_CAP = 1e30  # DZ of a caster seen edge-on (its plane parallel to a neighbour's ray): the clamp m applies


def engine_stored_map(rs: RayScene, smap: ShadowMap, d_occ: np.ndarray, prim: np.ndarray, engine: dict) -> np.ndarray:
    """What the engine's light pass leaves in the depth buffer, (height, width) float64 holding float32
    values (NumPy reference of _device_engine_map): per texel, P = the texel-centre ray's first hit, D(P)
    the mode's stored depth, the caster's plane (its triangle's geometric normal through P) intersected
    with the rays of texels (i + 1, j) and (i, j + 1) at P_x, P_y (past the last column or row too: the
    same projection continued), DZ = max(|D(P_x) - D(P)|, |D(P_y) - D(P)|), stored = clamp(D(P)
    + min(k DZ, m), 0, 1) (k = slope_scaled, m = slope_clamp: OpenGL 4.6 §14.6.5 polygon offset,
    D3D11 slope-scaled depth bias), 0 for a pancaked caster, 1 where nothing is hit."""
    from ..solvers.depth_modes import stored_depth

    w, h = smap.resolution
    mode, near_d, far_d = engine["mode"], engine["near"], engine["far"]
    k, m = float(engine.get("slope_scaled", 0.0)), float(engine.get("slope_clamp", np.inf))
    jj, ii = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    ii, jj = ii.ravel(), jj.ravel()
    occ = np.asarray(d_occ, float).ravel()
    pr = np.asarray(prim).ravel()
    hit = np.isfinite(occ)
    faced = hit & (pr >= 0)
    with np.errstate(all="ignore"):
        near, far = smap.texel_rays((ii + 0.5) / w, (jj + 0.5) / h)
        dirn = (far - near) / np.maximum(np.linalg.norm(far - near, axis=-1, keepdims=True), 1e-300)
        P = near + np.where(hit, occ, 0.0)[:, None] * dirn
        D = stored_depth(smap, mode, P, near_d, far_d)
        nrm = _face_normals(rs)[np.where(faced, pr, 0)]
        dz = np.zeros(len(occ))
        for di, dj in ((1, 0), (0, 1)):
            n1, f1 = smap.texel_rays((ii + di + 0.5) / w, (jj + dj + 0.5) / h)
            d1 = f1 - n1
            a = np.sum(nrm * (P - n1), axis=-1) / np.sum(nrm * d1, axis=-1)
            step = np.abs(stored_depth(smap, mode, n1 + a[:, None] * d1, near_d, far_d) - D)
            dz = np.maximum(dz, np.where(np.isfinite(step), step, np.inf))
        off = np.minimum(k * np.minimum(dz, DZ_CAP), m) if k else np.zeros(len(occ))
        stored = np.where(faced, np.clip(D + off, 0.0, 1.0), np.where(hit, 0.0, 1.0))
    return stored.astype(np.float32).astype(np.float64).reshape(h, w)


def _device_points(mi, a: np.ndarray):
    """(N, 3) float64 NumPy -> three Dr.Jit Float64 (aligned copies: no recompilation)."""
    a = np.asarray(a, dtype=np.float64)
    return [mi.Float64(aligned(a[:, k], np.float64)) for k in range(3)]


def _device_map_coords(mi, dr, smap: ShadowMap, origin: np.ndarray, X):
    """`ShadowMap.map_coords` in Dr.Jit Float64 for re-centred points X: (s, t, z_ndc, w)."""
    M = _opaque_matrix(mi, dr, smap.matrix @ _recentre(origin))
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


def _device_lookup(rs: RayScene, light: Light, smap: ShadowMap, d_occ, X, N, tolerance: float,
                   engine: dict | None = None):
    """The engine's shadow test (module doc, step 4) in Dr.Jit for re-centred points X with unit
    normals N (lists of three Float64). Returns NumPy (shadowed, inside, u, v): u, v the texel
    coordinates s * width, t * height (NaN where clip w <= 0). `engine` (engine_depth): the
    engine-faithful test of DEPTH_RULE_ENGINE instead of the idealized rule, and then `d_occ` is the
    engine's stored depth map (_device_engine_map), not d_occluder."""
    mi = mitsuba()
    import drjit as dr

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
    A = _opaque_matrix(mi, dr, _inverse_matrix(smap, rs.origin))
    near, dirn, _ = _device_rays_through(mi, dr, smap, A, (fi + 0.5) / wf, (fj + 0.5) / hf)
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
            n1, d1, _ = _device_rays_through(mi, dr, smap, A, (si + 0.5) / wf, (tj + 0.5) / hf)
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


def _device_stored_depth(mi, dr, smap: ShadowMap, origin: np.ndarray, engine: dict, P):
    """D(P) of the engine's mode for re-centred points P (solvers.depth_modes: hardware window z,
    linear (-z_view - near) / (far - near))."""
    F64 = mi.Float64
    if engine["mode"] == "hardware":
        M = _opaque_matrix(mi, dr, smap.matrix @ _recentre(origin))
        cz = M[2][0] * P[0] + M[2][1] * P[1] + M[2][2] * P[2] + M[2][3]
        cw = M[3][0] * P[0] + M[3][1] * P[1] + M[3][2] * P[2] + M[3][3]
        return 0.5 * (cz / cw + 1.0)
    V = _opaque_matrix(mi, dr, smap.view @ _recentre(origin))
    zv = V[2][0] * P[0] + V[2][1] * P[1] + V[2][2] * P[2] + V[2][3]
    near = dr.opaque(F64, engine["near"])
    return (-zv - near) / dr.opaque(F64, engine["far"] - engine["near"])


def _device_face_normals(mi, rs: RayScene):
    """_face_normals as three Dr.Jit Float64 arrays (cached on the RayScene)."""
    cached = getattr(rs, "_gt_device_face_normals", None)
    if cached is None:
        cached = _device_points(mi, _face_normals(rs))
        try:
            object.__setattr__(rs, "_gt_device_face_normals", cached)
        except Exception:  # pragma: no cover
            pass
    return cached


def _device_engine_map(rs: RayScene, smap: ShadowMap, d_occ, prim, engine: dict):
    """engine_stored_map in Dr.Jit: the engine's stored depth per texel (Float64 holding float32 values,
    row-major) from the map's d_occluder and hit triangles (_device_map(..., prims=True))."""
    mi = mitsuba()
    import drjit as dr

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
    A = _opaque_matrix(mi, dr, _inverse_matrix(smap, rs.origin))
    near, dirn, _ = _device_rays_through(mi, dr, smap, A, (fi + 0.5) / wf, (fj + 0.5) / hf)
    hit = dr.isfinite(d_occ)
    faced = hit & (prim != dr.opaque(U32, NO_PRIM))
    occ0 = dr.select(hit, d_occ, zero)
    P = [near[r] + occ0 * dirn[r] for r in range(3)]
    D = _device_stored_depth(mi, dr, smap, rs.origin, engine, P)
    if k:
        fn = _device_face_normals(mi, rs)
        nrm = [dr.gather(F64, fn[r], dr.select(faced, prim, dr.opaque(U32, 0)), faced) for r in range(3)]
        dz = zero
        for ds_, dt_ in ((1.0, 0.0), (0.0, 1.0)):  # texels (i + 1, j), (i, j + 1): the caster's plane there
            n1, d1, _ = _device_rays_through(mi, dr, smap, A, (fi + ds_ + 0.5) / wf, (fj + dt_ + 0.5) / hf)
            a = (sum(nrm[r] * (P[r] - n1[r]) for r in range(3)) / sum(nrm[r] * d1[r] for r in range(3)))
            step = dr.abs(_device_stored_depth(mi, dr, smap, rs.origin, engine,
                                               [n1[r] + a * d1[r] for r in range(3)]) - D)
            dz = dr.maximum(dz, dr.select(dr.isfinite(step), step, dr.inf))
        off = dr.minimum(dr.opaque(F64, k) * dr.minimum(dz, dr.opaque(F64, DZ_CAP)), dr.opaque(F64, m))
        D = D + off
    stored = dr.select(faced, dr.clip(D, zero, one), dr.select(hit, zero, one))
    stored = F64(mi.Float(stored))  # a D32F depth buffer
    dr.eval(stored)
    return stored


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
    d_rec = _device_stored_depth(mi, dr, smap, rs.origin, engine, Xp)
    inside = (cw > zero) & (s >= zero) & (s <= one) & (t >= zero) & (t <= one) & (d_rec >= zero) & (d_rec <= one)
    fi = dr.select(inside, dr.clip(dr.floor(s * wf), zero, wf - 1.0), zero)
    fj = dr.select(inside, dr.clip(dr.floor(t * hf), zero, hf - 1.0), zero)
    idx = mi.UInt32(fj) * dr.opaque(mi.UInt32, int(w)) + mi.UInt32(fi)
    stored = dr.gather(F64, stored_map, idx, inside)  # the light pass's depth buffer (_device_engine_map)
    tan_psi = _device_tan_psi(mi, dr, light, rs.origin, Xp, N)
    bias = dr.opaque(F64, engine["constant"]) + dr.opaque(F64, engine["slope"]) * tan_psi
    shadowed = inside & (d_rec - bias > stored)
    s0, t0, _, cw0 = _device_map_coords(mi, dr, smap, rs.origin, X)  # the metric's coordinates: X itself
    u = dr.select(cw0 > zero, s0 * wf, dr.nan)
    vv = dr.select(cw0 > zero, t0 * hf, dr.nan)
    dr.eval(shadowed, inside, u, vv)
    return shadowed.numpy().astype(bool), inside.numpy().astype(bool), u.numpy(), vv.numpy()


def _to_light(light: Light, positions: np.ndarray) -> np.ndarray:
    if isinstance(light, DirectionalLight):
        return np.broadcast_to(-light.direction, positions.shape)
    v = light.position - positions
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-300)


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
        c = np.clip(np.sum(normals[inside] * _to_light(light, X), axis=-1), 0.0, 1.0)
        with np.errstate(divide="ignore", invalid="ignore"):
            tan_psi = np.sqrt(np.maximum(1.0 - c * c, 0.0)) / c
        tan_psi = np.where(np.isfinite(tan_psi), np.minimum(tan_psi, TAN_PSI_MAX), TAN_PSI_MAX)
        bias = float(smap.depth_bias.get("constant", 0.0)) + float(smap.depth_bias.get("slope", 0.0)) * tan_psi
        kc, ks = float(smap.depth_bias.get("constant_texels", 0.0)), float(smap.depth_bias.get("slope_texels", 0.0))
        if kc or ks:
            bias = bias + (kc + ks * tan_psi) * texel_world_size_at(smap, i, j, X, near + d_rec[:, None] * dirn)
        shadowed[inside] = d_rec > d_occ[j, i] + bias + tolerance
    return shadowed, ~inside


def _engine_shadow_test(smap: ShadowMap, stored_map: np.ndarray, positions: np.ndarray, normals: np.ndarray,
                        light: Light, engine: dict):
    """DEPTH_RULE_ENGINE in NumPy (the reference of _device_engine_lookup)."""
    from ..solvers.depth_modes import stored_depth

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
        c = np.clip(np.sum(np.asarray(normals, float)[inside] * _to_light(light, X), axis=-1), 0.0, 1.0)
        with np.errstate(divide="ignore", invalid="ignore"):
            tan_psi = np.sqrt(np.maximum(1.0 - c * c, 0.0)) / c
        tan_psi = np.where(np.isfinite(tan_psi), np.minimum(tan_psi, TAN_PSI_MAX), TAN_PSI_MAX)
        shadowed[inside] = d_rec[inside] - (engine["constant"] + engine["slope"] * tan_psi) > stored
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


def _same_surface(sb: ScreenBuffers, a, b) -> np.ndarray:
    da, db = sb.depth[a], sb.depth[b]
    cos_max = np.cos(np.radians(SAME_SURFACE_DEG))
    with np.errstate(invalid="ignore"):
        return (sb.hit[a] & sb.hit[b] & (sb.prim[a] == sb.prim[b])
                & (np.abs(da - db) < DEPTH_CONTINUITY * np.minimum(da, db))
                & (np.sum(sb.normal[a] * sb.normal[b], axis=-1) > cos_max))


def _derivative(U: np.ndarray, ok_fwd: np.ndarray, ok_bwd: np.ndarray, axis: int) -> np.ndarray:
    """dU along image axis (0: y down, 1: x right); central where both neighbours usable."""
    fwd = np.full_like(U, np.nan)
    bwd = np.full_like(U, np.nan)
    if axis == 1:
        fwd[:, :-1] = U[:, 1:] - U[:, :-1]
        bwd[:, 1:] = U[:, 1:] - U[:, :-1]
        okf = np.zeros(U.shape[:2], bool)
        okb = np.zeros(U.shape[:2], bool)
        okf[:, :-1] = ok_fwd
        okb[:, 1:] = ok_bwd
    else:
        fwd[:-1] = U[1:] - U[:-1]
        bwd[1:] = U[1:] - U[:-1]
        okf = np.zeros(U.shape[:2], bool)
        okb = np.zeros(U.shape[:2], bool)
        okf[:-1] = ok_fwd
        okb[1:] = ok_bwd
    okf &= np.all(np.isfinite(fwd), axis=-1)
    okb &= np.all(np.isfinite(bwd), axis=-1)
    both = okf & okb
    out = np.full_like(U, np.nan)
    out[both] = 0.5 * (fwd[both] + bwd[both])
    only_f = okf & ~okb
    only_b = okb & ~okf
    out[only_f] = fwd[only_f]
    out[only_b] = bwd[only_b]
    return out


def measure_m(sb: ScreenBuffers, maps: list[ShadowMap], map_index: np.ndarray,
              coords: list[np.ndarray] | None = None):
    """Per-pixel (h, m, texel_uv) by finite differences of the serving map's texel coordinates.
    `coords[k]`: map k's texel coordinates (N_hit, 2) of the hit pixels in row-major order
    (computed with `texel_coords` when not given)."""
    H, W = sb.hit.shape
    same_x = _same_surface(sb, (slice(None), slice(None, -1)), (slice(None), slice(1, None)))
    same_y = _same_surface(sb, (slice(None, -1), slice(None)), (slice(1, None), slice(None)))
    m = np.full((H, W), np.nan)
    hh = np.full((H, W), np.nan)
    uv_serving = np.full((H, W, 2), np.nan)
    for k, smap in enumerate(maps):
        served = map_index == k
        if not served.any():
            continue
        # The map's coordinates of every hit pixel (neighbours are measured in the same map).
        U = np.full((H, W, 2), np.nan)
        U[sb.hit] = texel_coords(smap, sb.position[sb.hit]) if coords is None else coords[k]
        uv_serving[served] = U[served]
        dx = _derivative(U, same_x, same_x, axis=1)[served]
        dy = _derivative(U, same_y, same_y, axis=0)[served]
        j00, j10 = dx[:, 0], dx[:, 1]  # du/dx, dv/dx
        j01, j11 = dy[:, 0], dy[:, 1]  # du/dy, dv/dy
        det = j00 * j11 - j01 * j10
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / np.abs(det)
            hk = (j00 ** 2 + j01 ** 2 + j10 ** 2 + j11 ** 2) * inv * inv
            a = np.sqrt((j11 - j01) ** 2 + (j00 - j10) ** 2) * inv  # |ds + dt|
            b = np.sqrt((j11 + j01) ** 2 + (j10 + j00) ** 2) * inv  # |ds - dt|
        mk = np.maximum(a, b)
        degenerate = np.isfinite(det) & (np.abs(det) <= DET_FLOOR)
        mk[degenerate] = np.inf
        hk[degenerate] = np.inf
        m[served] = mk
        hh[served] = hk
    return hh, m, uv_serving


def evaluate_buffers(rs: RayScene, camera: Camera, light: Light, maps: list[ShadowMap],
                     screen: tuple[int, int] | None = None, pancake: bool = True, depth: str = "ideal",
                     screen_buffers: ScreenBuffers | None = None) -> GroundTruth:
    """Everything `evaluate` computes, with the per-pixel buffers (for heatmaps and reports).
    depth: "ideal" (the idealized texel-unit rule, BIAS_RULE), "solution" (each map's depth block in its
    own mode), "hardware" or "linear" (that block of every map): DEPTH_RULE_ENGINE.
    screen_buffers: a previous evaluation's `GroundTruth.screen` of the same camera, screen and light, to
    score the same pixels again (e.g. under another depth test) without tracing them again."""
    engines = [engine_depth(m, depth) for m in maps]
    t0 = time.perf_counter()
    cam = screen_camera(camera, screen)
    if screen_buffers is not None and (screen_buffers.width, screen_buffers.height) != tuple(cam.resolution):
        raise ValueError(f"screen_buffers are {screen_buffers.width}x{screen_buffers.height}, the screen is "
                         f"{cam.resolution[0]}x{cam.resolution[1]}")
    sb = render_screen(rs, cam, light) if screen_buffers is None else screen_buffers
    t1 = time.perf_counter()
    if depth == "ideal":
        d_occ = [_device_map(rs, light, smap, pancake) for smap in maps]
    else:  # the engine's light pass: stored depth with its caster-side slope-scaled bias
        d_occ = [_device_engine_map(rs, smap, *_device_map(rs, light, smap, pancake, prims=True), engines[k])
                 for k, smap in enumerate(maps)]
    if maps:
        import drjit as dr

        dr.sync_thread()  # kernels run asynchronously: wait so that "maps" is their time
    t2 = time.perf_counter()

    receivers = sb.receivers
    exact_shadowed = receivers & ~sb.visible
    H, W = receivers.shape
    hit = sb.hit
    n_hit = int(hit.sum())
    tol = NUMERIC_TOLERANCE * max(rs.extent, 1e-3)
    # Every map's lookup for every hit pixel, in Dr.Jit (float64, re-centred coordinates).
    looked = []
    if maps and n_hit:
        mi = mitsuba()
        X = _device_points(mi, sb.position[hit] - rs.origin)
        N = _device_points(mi, sb.normal[hit])
        looked = [_device_lookup(rs, light, smap, d_occ[k], X, N, tol, engines[k]) for k, smap in enumerate(maps)]
    # Serving map of every hit pixel: the cascade for its view depth, or the first cube face whose
    # map contains it.
    hit_idx = np.full(n_hit, -1, dtype=np.int64)
    if maps and n_hit:
        if maps[0].face is None:
            if depth == "ideal":
                hit_idx = map_for_depth(maps, sb.depth[hit])
            else:
                hit_idx = engine_cascades(maps, sb.depth[hit], [lk[1] for lk in looked])
        else:
            for k in range(len(maps) - 1, -1, -1):
                hit_idx[looked[k][1]] = k
    hit_shadow = np.zeros(n_hit, dtype=bool)
    hit_outside = hit_idx < 0
    for k in range(len(looked)):
        sel = hit_idx == k
        sh, inside = looked[k][0][sel], looked[k][1][sel]
        hit_shadow[sel] = sh & inside  # outside: clamp-to-border, lit
        hit_outside[sel] = ~inside
    map_shadowed = np.zeros((H, W), dtype=bool)
    map_shadowed[hit] = hit_shadow
    map_shadowed &= receivers
    outside = np.zeros((H, W), dtype=bool)
    outside[hit] = hit_outside
    outside &= receivers
    misclassified = receivers & (map_shadowed != exact_shadowed)
    lit = sb.visible & receivers
    boundary = boundary_mask(lit, sb.hit, sb.depth.astype(np.float32), radius=0) & receivers
    t3 = time.perf_counter()

    # Serving map of every hit pixel (for the metric and the grid overlay).
    map_index = np.full((H, W), -1, dtype=np.int64)
    map_index[hit] = hit_idx
    coords = [np.stack([lk[2], lk[3]], axis=-1) for lk in looked]
    hh, m, uv = measure_m(sb, maps, map_index, coords if n_hit else None)
    sample_mask, kind = receivers & boundary, "boundary"
    if not sample_mask.any():
        sample_mask, kind = receivers.copy(), "all_facing"
    sample_mask &= ~np.isnan(m)  # measurable pixels only (NaN: no neighbour on the same surface, or no map)
    if not sample_mask.any():
        kind = "none"
    stats = error_stats(hh[sample_mask], m[sample_mask])
    stats["sample_kind"] = kind
    t4 = time.perf_counter()

    n_rec = int(receivers.sum())
    result = {
        "misclassified_pixels": int(misclassified.sum()),
        "receiver_pixels": n_rec,
        "boundary_pixels": int(boundary.sum()),
        "outside_pixels": int(outside.sum()),
        "misclassified_fraction": float(misclassified.sum() / n_rec) if n_rec else 0.0,
        "measured_error": stats,
        "screen": [sb.width, sb.height],
        "bias_rule": BIAS_RULE,
        "depth": depth,
        "depth_rule": DEPTH_RULE_IDEAL if depth == "ideal" else DEPTH_RULE_ENGINE.format(which=depth),
        "timings_ms": {"screen": (t1 - t0) * 1e3, "maps": (t2 - t1) * 1e3, "shadow_test": (t3 - t2) * 1e3,
                       "measure": (t4 - t3) * 1e3, "total": (t4 - t0) * 1e3,
                       "map_rays": int(sum(mp.resolution[0] * mp.resolution[1] for mp in maps))},
    }
    if depth != "ideal":
        result["depth_modes"] = [e["mode"] for e in engines]
    return GroundTruth(sb, receivers, exact_shadowed, map_shadowed, misclassified, boundary, outside,
                       map_index, uv, m, hh, sample_mask, kind, result)


def classify_points(rs: RayScene, light: Light, maps: list[ShadowMap], positions: np.ndarray, normals: np.ndarray,
                    view_depth: np.ndarray, depth: str = "ideal", pancake: bool = True, device_maps: list | None = None) -> dict:
    """The lookup evaluate_buffers applies to its hit pixels, for arbitrary world points (N, 3) with unit
    normals (towards the camera's side) and their view depths in the camera the maps serve (cascade
    selection): {"shadowed", "outside", "map_index", "texel_uv" (N, 2; the serving map's s * width,
    t * height, NaN where none), "device_maps"}. `device_maps`: a previous call's, for the same maps, light
    and depth (each map is rendered once). Used to classify one frame's world points with another frame's
    maps (renderers.stability)."""
    engines = [engine_depth(m, depth) for m in maps]
    if device_maps is None:
        if depth == "ideal":
            device_maps = [_device_map(rs, light, smap, pancake) for smap in maps]
        else:
            device_maps = [_device_engine_map(rs, smap, *_device_map(rs, light, smap, pancake, prims=True), engines[k])
                           for k, smap in enumerate(maps)]
    P = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    n = len(P)
    out = {"shadowed": np.zeros(n, bool), "outside": np.ones(n, bool), "map_index": np.full(n, -1, np.int64),
           "texel_uv": np.full((n, 2), np.nan), "device_maps": device_maps}
    if not maps or n == 0:
        return out
    mi = mitsuba()
    X = _device_points(mi, P - rs.origin)
    N = _device_points(mi, np.asarray(normals, dtype=np.float64).reshape(-1, 3))
    tol = NUMERIC_TOLERANCE * max(rs.extent, 1e-3)
    looked = [_device_lookup(rs, light, smap, device_maps[k], X, N, tol, engines[k]) for k, smap in enumerate(maps)]
    if maps[0].face is None:
        idx = (map_for_depth(maps, np.asarray(view_depth, float)) if depth == "ideal"
               else engine_cascades(maps, np.asarray(view_depth, float), [lk[1] for lk in looked]))
    else:
        idx = np.full(n, -1, np.int64)
        for k in range(len(maps) - 1, -1, -1):
            idx[looked[k][1]] = k
    for k, lk in enumerate(looked):
        sel = idx == k
        out["shadowed"][sel] = lk[0][sel] & lk[1][sel]
        out["outside"][sel] = ~lk[1][sel]
        out["texel_uv"][sel] = np.stack([lk[2][sel], lk[3][sel]], axis=-1)
    out["map_index"] = np.asarray(idx, np.int64)
    return out


def evaluate(rs: RayScene, camera: Camera, light: Light, maps: list[ShadowMap],
             screen: tuple[int, int] | None = None, heatmap_path: str | None = None,
             grid_every: int | None = None, pancake: bool = True, depth: str = "ideal") -> dict:
    """Score `maps` (one light's cascades or cube faces) against ray-traced shadows. See the module doc
    (depth: evaluate_buffers)."""
    gt = evaluate_buffers(rs, camera, light, maps, screen, pancake, depth)
    if heatmap_path is not None:
        from .heatmap import ground_truth_heatmap

        t0 = time.perf_counter()
        ground_truth_heatmap(gt, grid_every).save(heatmap_path)
        gt.result["timings_ms"]["heatmap"] = (time.perf_counter() - t0) * 1e3
        gt.result["timings_ms"]["total"] += gt.result["timings_ms"]["heatmap"]
    return gt.result
