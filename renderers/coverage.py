"""Coverage: are the receivers the camera sees at full resolution inside the maps that serve them?

`outside_pixels(rays, camera, light, maps)` is `ground_truth.evaluate_buffers`' outside_pixels without
the shadow rays, the maps' rendering or the metric: full-resolution primary rays only
(`ground_truth.render_screen(..., shadow_rays=False)`), receivers = hits whose camera-facing side faces
the light (and inside a spot's cone), the serving map chosen as the evaluator chooses it
(`ground_truth._serving_maps`: the cascade for the view depth, or the first cube face containing the
point), and a receiver is outside when that map does not contain it (clip w <= 0, s or t outside
[0, 1], z_ndc outside [-1, 1]) or no map serves it. Cheap enough to check many suns at 1920x1080.

`coverage_sweep(...)`: corpus rigs x suns x methods x {1, 4 cascades} x screens -> outside pixels
(the check of issue 10's "outside pixels 0 everywhere").
"""
from __future__ import annotations

import numpy as np

from ..solvers.cameras import Camera
from ..solvers.lights import Light
from ..solvers.shadow_map import ShadowMap
from .ground_truth import _serving_maps, render_screen
from .ray_scene import RayScene


def outside_mask(screen, maps: list[ShadowMap]) -> np.ndarray:
    """(h, w) bool: receivers of a ScreenBuffers that their serving map does not contain."""
    rec = screen.receivers
    out = np.zeros(rec.shape, dtype=bool)
    if not rec.any():
        return out
    pos, depth = screen.position[rec], screen.depth[rec]
    idx = _serving_maps(maps, pos, depth)
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


CASCADE_CONFIGS = {1: {"resolution": [400, 400], "cascades": 1},
                   4: {"resolution": [400, 400], "cascades": 4, "splits": "practical", "lambda": 0.5}}


def coverage_sweep(scenes=None, suns: int = 4, methods=("uniform", "focused", "lispsm", "logpsm", "optimized"),
                   cascades=(1, 4), screens=((750, 750), (1920, 1080)), seed: int = 2, min_elevation_deg: float = 5.0,
                   log=print) -> list[dict]:
    """Outside pixels on the corpus (configs/corpus.json): per scene rig, screen (the rig's resolution:
    each solve sees that camera), sun (service.bench.suite.hemisphere_directions, the corpus benchmark's
    seed), method and cascade count, one row {scene, screen, sun, method, cascades, outside_pixels,
    receiver_pixels}. `log` gets one line per (scene, screen) with the totals per method."""
    from ..api.cli import validate_rig
    from ..service.bench.suite import corpus_scenes, hemisphere_directions
    from ..service.rigs import resolve_rig
    from ..service.scenes import SceneCache
    from ..service.solve import maps_from_solution, solve

    found, _ = corpus_scenes(scenes)
    dirs = hemisphere_directions(suns, min_elevation_deg, seed)
    rows = []
    for name, (path, spec) in found.items():
        cache = SceneCache()
        entry = cache.get(path)
        for rig_name, rig_spec in spec["rigs"].items():
            for screen in screens:
                tot = {}
                for i, d in enumerate(dirs):
                    sb = None
                    for k in cascades:
                        for method in methods:
                            rig = validate_rig({"camera": {**rig_spec["camera"], "resolution": list(screen)},
                                                "lights": [{"type": "directional", "direction": [float(v) for v in d]}],
                                                "shadow": CASCADE_CONFIGS[k]})
                            if sb is None:
                                r = resolve_rig(rig, entry.loaded)
                                sb = render_screen(entry.rays, r.camera, r.lights[0], shadow_rays=False)
                            maps = maps_from_solution(solve(entry, rig, method=method))[0]
                            n = int(outside_mask(sb, maps).sum())
                            rows.append({"scene": name, "rig": rig_name, "screen": list(screen), "sun": i,
                                         "method": method, "cascades": k, "outside_pixels": n,
                                         "receiver_pixels": int(sb.receivers.sum())})
                            tot[(method, k)] = tot.get((method, k), 0) + n
                if log:
                    log(f"{name}/{rig_name} {screen[0]}x{screen[1]} {len(dirs)} suns: "
                        + ", ".join(f"{m}x{k} {v}" for (m, k), v in tot.items()))
        cache.clear()
    return rows


if __name__ == "__main__":  # python -m shadowopt.renderers.coverage [scenes] [suns] [WxH,...]
    import sys

    sc = sys.argv[1].split(",") if len(sys.argv) > 1 and sys.argv[1] != "all" else None
    n = int(sys.argv[2]) if len(sys.argv) > 2 else 4
    scr = [tuple(int(v) for v in s.split("x")) for s in sys.argv[3].split(",")] if len(sys.argv) > 3 else ((750, 750), (1920, 1080))
    coverage_sweep(sc, n, screens=scr)
