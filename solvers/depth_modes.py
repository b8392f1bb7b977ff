"""The depth an engine stores in a shadow map and the bias it applies, per map: the `depth` block.

Two stored-depth functions D(X) of a world point X, both in [0, 1] over the map's frustum:

- hardware: the window-space z of the returned projection · view, D = (z_ndc + 1) / 2 (OpenGL 4.6
  §13.8, viewport transform with glDepthRange(0, 1); the same number as D3D/Vulkan's NDC z in [0, 1]),
  what a plain depth-only light pass writes. For a warped map (solvers.warp, Z = z / (y - y_c) in
  the warped light view) it is linear along each light ray with a scale 1 / (y - y_c) that follows
  the texel size along s, so one constant window-z bias scales with the warp; for an orthographic
  map it is linear in the light-view depth everywhere.
- linear: D = (-z_view - near) / (far - near), z_view = (view · X).z (the light looks down -Z), near
  and far the least and greatest -z_view over the map's eight frustum corners (ShadowMap.texel_rays
  at the map's corners), written by a custom light pass (gl_FragDepth or an R32F target).

Bias: the idealized requirement of receiver i is tau_i (kc + ks tan psi) metres along the light ray
(solvers.baselines: tau_i the texel's world size at X_i, kc, ks = BIAS_CONSTANT_TEXELS,
BIAS_SLOPE_TEXELS). In stored units it is q_i (kc + ks tan psi), q_i = tau_i dD/dd_i, dD/dd_i the
derivative of D along the light ray at X_i. The constant is receiver-side, one per map: c = kc Q with
Q the PERCENTILE-th percentile of q_i over the map's receivers (every receiver with q_i <= Q gets at
least kc texels). The slope term is caster-side and per texel, as engines' hardware slope-scaled bias
is (OpenGL 4.6 §14.6.5 glPolygonOffsetClamp(factor, 0, clamp) with the max form of the slope; D3D11
SlopeScaledDepthBias with MaxDepthSlope and DepthBiasClamp; Vulkan depthBiasSlopeFactor/Clamp):
each light-pass fragment stores D + min(k DZ, m), DZ = max(|dD/dx|, |dD/dy|) the change of the
caster's stored depth per texel step, which is tau tan(psi) dD/dd at the caster and so follows a
warped map's texel size by itself. k = "slope_scaled" = BIAS_SLOPE_TEXELS (ks), m = "slope_clamp" =
TAN_PSI_MAX k Q (in stored units). The receiver-side "slope" is 0; normal_offset is 0. with_bias sets
both on a map: the rule's texel-unit depth_bias (recommended_bias) and this `depth` block.

Mode: hardware, unless
- the map is log-warped (t' = c0 log(c1 t + c2) is not a projective map, so its light pass is a
  custom one anyway): linear;
- a D32F depth buffer cannot hold window z finely enough: the bias kc q_i at the receivers' 5th
  percentile is below MIN_ULPS float32 steps at their stored depth (a perspective spot or cube map
  with its near plane close to the light crowds window z against 1): linear;
- hardware's spread of q (P95 / P5 over the receivers: how far one constant is from each receiver's
  need) exceeds SPREAD_MAX and is more than SPREAD_RATIO times linear's. For the perspective warp
  (Z = z / (y - y_c), dD/dd ~ 1 / (y - y_c)) and texel sides ~ (y - y_c) along s, ~ (y - y_c)^2 along t,
  q_hardware varies as 1 or (y - y_c) and q_linear as (y - y_c) or (y - y_c)^2, so hardware's spread is
  never the larger there: the rule is a guard for maps built otherwise.
"""
from __future__ import annotations

import numpy as np

from .lights import DirectionalLight
from .samples import seeded_rows
from .shadow_map import ShadowMap
from .texel_size import texel_extents, texel_world_size

BIAS_CONSTANT_TEXELS = 1.5
BIAS_SLOPE_TEXELS = 1.0
MODES = ("hardware", "linear")
PERCENTILE = 95.0  # of q_i = tau_i dD/dd_i over the map's receivers (module doc)
SPREAD_PERCENTILES = (5.0, 95.0)  # spread = P95(q) / P5(q)
SPREAD_MAX = 4.0  # hardware is kept while its spread is at most this ...
SPREAD_RATIO = 1.5  # ... or at most this times linear's
SAMPLE = 2048  # receivers measured per map (a seeded random subset of more)
SLOPE_SCALED = BIAS_SLOPE_TEXELS  # caster-side k: DZ (stored-depth change per texel step) times k
TAN_PSI_MAX = 10.0  # slope clamp m = TAN_PSI_MAX k Q (the ideal rule's tan(psi) clamp, renderers.ground_truth)
MIN_ULPS = 8.0  # hardware needs its constant bias at the 5th-percentile receiver >= this many float32 steps


def window_depth(z_ndc: np.ndarray) -> np.ndarray:
    """Window z (z_ndc + 1) / 2 (OpenGL 4.6 §13.8 with glDepthRange(0, 1))."""
    return 0.5 * (np.asarray(z_ndc) + 1.0)


def hardware_depth(smap: ShadowMap, pts: np.ndarray) -> np.ndarray:
    """window_depth of P V X."""
    _, _, z, _ = smap.map_coords(np.asarray(pts, float).reshape(-1, 3))
    return window_depth(z)


def linear_range(smap: ShadowMap) -> tuple[float, float]:
    """near, far: least and greatest -z_view over the map's eight frustum corners
    (ShadowMap.frustum_depth_range; its light_depth when no corner is finite)."""
    rng = smap.frustum_depth_range()
    if rng is None:
        return float(smap.light_depth[0]), float(smap.light_depth[1])
    return rng


def linear_depth(pts: np.ndarray, view: np.ndarray, near: float, far: float) -> np.ndarray:
    """(-z_view - near) / (far - near)."""
    p = np.asarray(pts, float).reshape(-1, 3)
    return (-(p @ view[2, :3] + view[2, 3]) - near) / max(far - near, 1e-300)


def stored_depth(smap: ShadowMap, mode: str, pts: np.ndarray, near: float | None = None,
                 far: float | None = None) -> np.ndarray:
    """D(X) of `mode` (module doc); linear uses near/far (default: linear_range)."""
    if mode == "hardware":
        return hardware_depth(smap, pts)
    if mode == "linear":
        if near is None or far is None:
            near, far = linear_range(smap)
        return linear_depth(pts, smap.view, near, far)
    raise ValueError(f"depth mode must be one of {', '.join(MODES)}, got {mode!r}")


def light_ray_dirs(light, pts: np.ndarray) -> np.ndarray:
    """Unit direction of the light ray through each point, away from the light."""
    pts = np.asarray(pts, float).reshape(-1, 3)
    if isinstance(light, DirectionalLight):
        return np.broadcast_to(np.asarray(light.direction, float), pts.shape)
    v = pts - np.asarray(light.position, float)
    return v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-300)


def depth_derivative(smap: ShadowMap, mode: str, pts: np.ndarray, dirs: np.ndarray, near: float | None = None,
                     far: float | None = None) -> np.ndarray:
    """dD/dd at each point along the unit directions `dirs` (closed forms: the quotient rule on
    c_z / c_w for hardware, the constant -view_z . u / (far - near) for linear)."""
    p = np.asarray(pts, float).reshape(-1, 3)
    u = np.asarray(dirs, float).reshape(-1, 3)
    if mode == "hardware":
        M = smap.matrix
        cz = p @ M[2, :3] + M[2, 3]
        cw = p @ M[3, :3] + M[3, 3]
        with np.errstate(all="ignore"):
            return 0.5 * ((u @ M[2, :3]) * cw - cz * (u @ M[3, :3])) / (cw * cw)
    if near is None or far is None:
        near, far = linear_range(smap)
    return -(u @ smap.view[2, :3]) / max(far - near, 1e-300)


def requirement_scale(smap: ShadowMap, mode: str, pts: np.ndarray, light, near=None, far=None) -> np.ndarray:
    """q_i = tau_i dD/dd_i per point (NaN outside the map): the stored-unit bias one texel-unit of the
    idealized rule needs there (tau_i: texel_size.texel_extents, the longer texel side)."""
    pts = np.asarray(pts, float).reshape(-1, 3)
    per_s, per_t = texel_extents(smap, pts, light)
    tau = np.maximum(per_s / smap.resolution[0], per_t / smap.resolution[1])
    g = depth_derivative(smap, mode, pts, light_ray_dirs(light, pts), near, far)
    return tau * g


def _spread(q: np.ndarray) -> float:
    lo, hi = np.percentile(q, SPREAD_PERCENTILES)
    return float(hi / lo) if lo > 0 else float("inf")


def depth_block(smap: ShadowMap, receivers: np.ndarray, light, percentile: float | None = None) -> dict:
    """The map's `depth` block: {mode, reason, hardware: {constant, slope, normal_offset, slope_scaled,
    slope_clamp}, linear: {the same keys, near, far}, spread, percentile} (module doc; percentile
    default PERCENTILE)."""
    KC = BIAS_CONSTANT_TEXELS
    percentile = PERCENTILE if percentile is None else float(percentile)

    pts = np.asarray(receivers, float).reshape(-1, 3)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    if len(pts) > SAMPLE:
        pts = pts[seeded_rows(len(pts), SAMPLE)]
    near, far = linear_range(smap)
    blocks, spreads, ulps = {}, {}, float("inf")
    for mode in MODES:
        q_all = requirement_scale(smap, mode, pts, light, near, far) if len(pts) else np.zeros(0)
        q = q_all[np.isfinite(q_all) & (q_all > 0)]
        if len(q) == 0:  # no receiver inside: the requirement at the far end of the central ray
            with np.errstate(all="ignore"):
                a, b = smap.texel_rays(np.array([0.5]), np.array([0.5]))
                q = requirement_scale(smap, mode, 0.999 * b + 0.001 * a, light, near, far)
            q = q[np.isfinite(q) & (q > 0)]
        if mode == "hardware" and len(pts):
            with np.errstate(all="ignore"):
                qi = q_all  # per receiver, unfiltered
                D = np.clip(hardware_depth(smap, pts), 0.0, 1.0)
                steps = KC * qi / np.spacing(D.astype(np.float32)).astype(np.float64)
            steps = steps[np.isfinite(steps) & (steps > 0)]
            if len(steps):
                ulps = float(np.percentile(steps, SPREAD_PERCENTILES[0]))
        Q = float(np.percentile(q, percentile)) if len(q) else 0.0
        spreads[mode] = _spread(q) if len(q) else 1.0
        # caster-side slope-scaled bias: stored = D + min(k DZ, m), DZ = max(|dD/dx|, |dD/dy|) per texel step
        # (OpenGL 4.6 §14.6.5 glPolygonOffsetClamp, max form; D3D11 SlopeScaledDepthBias x MaxDepthSlope,
        # DepthBiasClamp); k = ks: DZ is tau tan(psi) dD/dd, the ideal rule's slope term; m = the cap at
        # tan(psi) = TAN_PSI_MAX for the PERCENTILE receiver. The receiver-side slope is 0.
        blocks[mode] = {"constant": KC * Q, "slope": 0.0, "normal_offset": 0.0,
                        "slope_scaled": SLOPE_SCALED, "slope_clamp": TAN_PSI_MAX * SLOPE_SCALED * Q}
    blocks["linear"].update(near=near, far=far)
    hw, lin = spreads["hardware"], spreads["linear"]
    if smap.log_warp is not None:
        mode = "linear"
        reason = ("linear: a log-warped map needs a custom light pass (t' = c0 log(c1 t + c2) is not a projective "
                  "transform), which writes light-space distance")
    elif ulps < MIN_ULPS:
        mode = "linear"
        reason = (f"linear: window z is crowded against 1 at this map's receivers (the bias they need is {ulps:.3g} "
                  "float32 steps at the 5th percentile), too coarse for a 32-bit depth buffer")
    elif hw > SPREAD_MAX and hw > SPREAD_RATIO * lin:
        mode = "linear"
        reason = (f"linear: the bias a window-z map needs varies {hw:.3g}x over this map's receivers "
                  f"(95th/5th percentile) against {lin:.3g}x for light-space distance, too much for one constant")
    else:
        mode = "hardware"
        reason = (f"hardware: one window-z bias fits this map's receivers (their need varies {hw:.3g}x, 95th/5th "
                  f"percentile; {lin:.3g}x for light-space distance)")
    return {"mode": mode, "reason": reason, **blocks,
            "spread": {"hardware": hw, "linear": lin}, "percentile": float(percentile),
            "hardware_float32_steps": ulps if np.isfinite(ulps) else None}


def recommended_bias(texel_world_size: float) -> dict:
    """The bias in texel units (constant_texels, slope_texels: scaled by the serving texel's world size
    at each receiver, as a hardware slope-scaled or normal-offset bias is), plus, for engines that can
    only set a fixed bias in metres, {constant, slope} = those units times the map's 95th-percentile
    texel world size (informative: the evaluator's rule uses the texel units; see solvers.baselines' module doc)."""
    return {"constant_texels": BIAS_CONSTANT_TEXELS, "slope_texels": BIAS_SLOPE_TEXELS,
            "texel_world_size": texel_world_size, "fixed_constant_m": BIAS_CONSTANT_TEXELS * texel_world_size,
            "fixed_slope_m": BIAS_SLOPE_TEXELS * texel_world_size}


def with_bias(smap: ShadowMap, receivers: np.ndarray, light) -> ShadowMap:
    """The idealized texel-unit bias (depth_bias) and the engine's depth block (solvers.depth_modes:
    hardware or linear stored depth, with a constant and slope bias in stored units)."""
    smap.depth_bias = recommended_bias(texel_world_size(smap, receivers, light))
    smap.depth = depth_block(smap, receivers, light)
    return smap
