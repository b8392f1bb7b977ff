"""Coverage: are the receivers the camera sees at full resolution inside the maps that serve them?

`outside_pixels(rays, camera, light, maps)` is `ground_truth.evaluate_buffers`' outside_pixels without
the shadow rays, the maps' rendering or the metric: full-resolution primary rays only
(`ground_truth.render_screen(..., shadow_rays=False)`), receivers = hits whose camera-facing side faces
the light (and inside a spot's cone), the serving map chosen as the evaluator chooses it
(`solvers.shadow_map.serving_maps`: the cascade for the view depth, or the first cube face containing the
point), and a receiver is outside when that map does not contain it (clip w <= 0, s or t outside
[0, 1], z_ndc outside [-1, 1]) or no map serves it. Cheap enough to check many suns at 1920x1080.

The sweep over the corpus (rigs x suns x methods x cascade counts x screens) is
`tests/coverage_sweep.py`.
"""
from __future__ import annotations

import numpy as np

from ..solvers.cameras import Camera
from ..solvers.lights import Light
from ..solvers.shadow_map import ShadowMap, serving_maps
from .ground_truth import render_screen
from .ray_scene import RayScene


def outside_mask(screen, maps: list[ShadowMap]) -> np.ndarray:
    """(h, w) bool: receivers of a ScreenBuffers that their serving map does not contain."""
    rec = screen.receivers
    out = np.zeros(rec.shape, dtype=bool)
    if not rec.any():
        return out
    pos, depth = screen.position[rec], screen.depth[rec]
    idx = serving_maps(maps, pos, depth)
    outside = idx < 0
    for k, smap in enumerate(maps):
        sel = idx == k
        if not sel.any():
            continue
        s, t, z, w = smap.map_coords(pos[sel])
        with np.errstate(invalid="ignore"):
            inside = (w > 0) & (s >= 0) & (s <= 1) & (t >= 0) & (t <= 1) & (z >= -1) & (z <= 1)
        outside[sel] = ~inside
    out[rec] = outside
    return out


def outside_pixels(rays: RayScene, camera: Camera, light: Light, maps: list[ShadowMap], screen=None) -> dict:
    """{"outside_pixels", "receiver_pixels"} at camera.resolution (see the module doc). `screen`: a
    ScreenBuffers of this camera and light already rendered (several methods' maps checked on one)."""
    sb = render_screen(rays, camera, light, shadow_rays=False) if screen is None else screen
    return {"outside_pixels": int(outside_mask(sb, maps).sum()), "receiver_pixels": int(sb.receivers.sum())}
