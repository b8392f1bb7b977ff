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
   (0 for pancaked casters; 1 where nothing is hit; `device_engine_map`, NumPy `engine_stored_map`);
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

The parts: the maps' ray casting and the engine's light pass in renderers.shadow_map_rays, the shadow
test and the cascade choice in renderers.depth_tests; the screen pass, measured_error and the evaluation here.
"""
from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass

import numpy as np

from ..solvers.cameras import Camera
from ..solvers.lights import Light
from ..solvers.metric import DET_FLOOR, error_stats
from ..solvers.shadow_map import ShadowMap, map_for_depth
from .coarse import DEPTH_CONTINUITY, boundary_mask, camera_rays, light_test, surface_hits
from .depth_tests import (BIAS_RULE, DEPTH_RULE_ENGINE, DEPTH_RULE_IDEAL, NUMERIC_TOLERANCE, device_lookup,
                          engine_cascades, engine_depth, texel_coords)
from .heatmap import ground_truth_heatmap
from .mitsuba_setup import mitsuba
from .ray_scene import RayScene
from .shadow_map_rays import device_engine_map, device_map, device_points, host_geometry

SAME_SURFACE_DEG = 10.0  # neighbours whose normals differ by more are on different surfaces


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


def render_screen(rs: RayScene, camera: Camera, light: Light, shadow_rays: bool = True) -> ScreenBuffers:
    """Full-resolution camera pass at camera.resolution (the coarse pass's helpers at full size).
    shadow_rays=False: primary rays only, `visible` is not traced (renderers.coverage)."""
    mi = mitsuba()
    import drjit as dr  # lazy: after mitsuba(), which points Dr.Jit at its libLLVM (solvers.jit)

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
    verts, faces = host_geometry(rs)
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
        d_occ = [device_map(rs, light, smap, pancake) for smap in maps]
    else:  # the engine's light pass: stored depth with its caster-side slope-scaled bias
        d_occ = [device_engine_map(rs, smap, *device_map(rs, light, smap, pancake, prims=True), engines[k])
                 for k, smap in enumerate(maps)]
    if maps:
        import drjit as dr  # lazy: after mitsuba(), which points Dr.Jit at its libLLVM (solvers.jit)

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
        X = device_points(mi, sb.position[hit] - rs.origin)
        N = device_points(mi, sb.normal[hit])
        looked = [device_lookup(rs, light, smap, d_occ[k], X, N, tol, engines[k]) for k, smap in enumerate(maps)]
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
            device_maps = [device_map(rs, light, smap, pancake) for smap in maps]
        else:
            device_maps = [device_engine_map(rs, smap, *device_map(rs, light, smap, pancake, prims=True), engines[k])
                           for k, smap in enumerate(maps)]
    P = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    n = len(P)
    out = {"shadowed": np.zeros(n, bool), "outside": np.ones(n, bool), "map_index": np.full(n, -1, np.int64),
           "texel_uv": np.full((n, 2), np.nan), "device_maps": device_maps}
    if not maps or n == 0:
        return out
    mi = mitsuba()
    X = device_points(mi, P - rs.origin)
    N = device_points(mi, np.asarray(normals, dtype=np.float64).reshape(-1, 3))
    tol = NUMERIC_TOLERANCE * max(rs.extent, 1e-3)
    looked = [device_lookup(rs, light, smap, device_maps[k], X, N, tol, engines[k]) for k, smap in enumerate(maps)]
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
        t0 = time.perf_counter()
        ground_truth_heatmap(gt, grid_every).save(heatmap_path)
        gt.result["timings_ms"]["heatmap"] = (time.perf_counter() - t0) * 1e3
        gt.result["timings_ms"]["total"] += gt.result["timings_ms"]["heatmap"]
    return gt.result
