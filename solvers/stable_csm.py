"""Stable cascaded shadow maps: the engines' recipe against shimmering, as a baseline.

Valient 2008 ("Stable rendering of cascaded shadow maps", ShaderX6) and the engines that follow it
(three.js CSM, Bevy, Godot, Filament `stable`, O3DE): per cascade,

1. the camera frustum slice [z_i, z_{i+1}] (view depths), its bounding sphere: the centre on the view
   axis at c = (z_i + z_{i+1}) (1 + k^2) / 2, k = sqrt(tan_x^2 + tan_y^2) the slice's half-diagonal per
   unit depth, clamped to [z_i, z_{i+1}] (the far plane's circle when it encloses the near one), the
   radius the larger distance to the slice's near and far corner rings. The sphere does not turn with
   the camera, so neither does the map's size;
2. the radius rounded up onto a fixed ladder 2^(j/8) m (solvers.fitting.SNAP_STEPS_PER_OCTAVE, as the
   service's snap_to_texels does), so the texel size changes only when the splits do;
3. a light view fixed in the world (along the light, up = the world's +Z, else +X, perpendicular to it;
   never the camera's direction, which would rotate the texel grid), an orthographic box of the sphere
   (side 2 r), its centre in light space snapped to the texel grid (multiples of the texel size 2 r / n):
   every texel edge lies on a world-fixed grid and a moving camera sees the same texels;
4. depth range: the scene bounds' corners along the light (every caster, on screen or off); the same
   for every frame.

Splits: practical (lambda) or the rig's kind over [camera near, shadow distance], the shadow distance
the camera's far plane clamped to the scene bounds' diagonal (no receiver is farther from a camera inside
the bounds; from a camera outside them, the farthest corner's distance), rounded up onto the same ladder:
an engine's fixed "max shadow distance" setting, chosen as the level's size, so the splits and the
spheres, hence the texel sizes, do not change while the camera moves or turns inside the scene. Every cascade has the same square
resolution: `resolution`, or with a texel budget sqrt(budget / k) per side. Bias: the baselines' rule
(depth_modes.with_bias over each cascade's receivers).
"""
from __future__ import annotations

import math

import numpy as np

from .cameras import Camera
from .cascades import split_depths
from .depth_modes import with_bias
from .fitting import SNAP_STEPS_PER_OCTAVE, box_corners, depth_range, ortho, to_view
from .light_frames import look_matrix, perpendicular_up
from .lights import DirectionalLight
from .shadow_map import ShadowMap

METHOD = "stable_csm"


def ladder_up(x: float) -> float:
    """x rounded up onto the fixed geometric ladder 2^(j / SNAP_STEPS_PER_OCTAVE)."""
    x = max(float(x), 1e-9)
    return 2.0 ** (math.ceil(math.log2(x) * SNAP_STEPS_PER_OCTAVE - 1e-9) / SNAP_STEPS_PER_OCTAVE)


def slice_sphere(camera: Camera, z0: float, z1: float) -> tuple[np.ndarray, float]:
    """(world centre, radius) of the bounding sphere of the frustum slice [z0, z1] (module doc, step 1)."""
    k2 = camera.tan_half_fov_y ** 2 * (1.0 + camera.aspect ** 2)
    c = min(max(0.5 * (z0 + z1) * (1.0 + k2), z0), z1)
    r = math.sqrt(max((c - z0) ** 2 + z0 * z0 * k2, (z1 - c) ** 2 + z1 * z1 * k2))
    return camera.position + c * camera.forward, r


def world_light_view(light: DirectionalLight) -> np.ndarray:
    """The world-fixed light view (module doc, step 3), its origin at the world origin."""
    d = np.asarray(light.direction, dtype=np.float64)
    return look_matrix(np.zeros(3), d, perpendicular_up(d, [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]))


def shadow_distance(camera: Camera, corners: np.ndarray) -> float:
    """The far end of the cascades (module doc): the far plane, clamped to the scene bounds' diagonal (or the
    farthest corner's distance from a camera outside them), rounded up onto the ladder."""
    far = max(float(np.max(np.linalg.norm(corners - camera.position, axis=1))),
              float(np.linalg.norm(corners.max(0) - corners.min(0))))
    return ladder_up(min(camera.far, max(far, camera.near * 2.0)))


def stable_csm_maps(camera: Camera, light, receivers: np.ndarray, casters_bounds, resolution=(2048, 2048),
                    cascades: int = 1, splits: str = "practical", split_lambda: float = 0.5,
                    texel_budget: int | None = None, receiver_slack=None, split_at=None,
                    **_ignored) -> list[ShadowMap]:
    """The stable CSM maps of one directional light (module doc), biased like the baselines. `split_at`: the k - 1
    inner split depths given explicitly (splits "optimized": the split search's), kept inside the shadow distance,
    instead of `splits`."""
    if not isinstance(light, DirectionalLight):
        raise ValueError("stable_csm: only directional lights have cascades (use focused for spot and point lights)")
    receivers = np.asarray(receivers, dtype=np.float64).reshape(-1, 3)
    receivers = receivers[np.all(np.isfinite(receivers), axis=1)]
    if casters_bounds is None:
        casters_bounds = ((receivers.min(0), receivers.max(0)) if len(receivers)
                          else (camera.position - 1.0, camera.position + 1.0))
    corners = box_corners(np.asarray(casters_bounds[0], float), np.asarray(casters_bounds[1], float))
    k = max(1, int(cascades))
    if texel_budget:
        side = max(16, math.isqrt(int(texel_budget) // k))
        res = (side, side)
    else:
        res = (int(resolution[0]), int(resolution[1]))
    z = split_depths(camera.near, shadow_distance(camera, corners), k,
                     splits if splits in ("uniform", "log", "practical") else "practical", split_lambda)
    if split_at is not None and k > 1:
        inner = np.sort(np.asarray(split_at, dtype=np.float64).ravel())
        if len(inner) != k - 1 or not np.all(np.isfinite(inner)):
            raise ValueError(f"split_at: need {k - 1} finite inner split depths, got {len(inner)}")
        span = z[-1] - z[0]
        z[1:-1] = np.clip(inner, z[0] + 1e-6 * span, z[-1] - 1e-6 * span)
    view = world_light_view(light)
    near, far = depth_range(-to_view(view, corners)[:, 2], 0.01)
    depth = (receivers - camera.position) @ camera.forward if len(receivers) else np.zeros(0)
    maps = []
    for i in range(k):
        centre, r = slice_sphere(camera, float(z[i]), float(z[i + 1]))
        r = ladder_up(r)
        c = to_view(view, centre[None])[0]
        lo, hi = [], []
        for axis, n in enumerate(res):
            tau = 2.0 * r / n  # texel size
            cs = round(c[axis] / tau) * tau  # the centre on the texel grid (Valient 2008)
            if n % 2:  # an odd texel count: the centre of a texel on the grid, not an edge
                cs += 0.5 * tau
            lo.append(cs - r)
            hi.append(cs + r)
        smap = ShadowMap(view.copy(), ortho(lo[0], hi[0], lo[1], hi[1], near, far), res, light_depth=(near, far),
                         warp_kind="none")
        smap.snapped = True  # the texel grid is fixed in the world
        smap.split = (0.0 if i == 0 else float(z[i]), float(camera.far if i == k - 1 else z[i + 1]))
        sel = (depth >= smap.split[0]) & (depth <= smap.split[1])
        part = receivers[sel] if sel.any() else receivers
        maps.append(with_bias(smap, part, light))
    return maps
