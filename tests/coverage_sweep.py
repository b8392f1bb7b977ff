"""Outside pixels over the corpus: are the receivers the camera sees at full resolution inside the maps
that serve them, for every corpus rig, sun, method and cascade count (renderers.coverage.outside_mask
per configuration). Used by tests/test_receivers.py (no benchmark section: a test helper)."""
from __future__ import annotations

from shadowopt.renderers.coverage import outside_mask
from shadowopt.renderers.ground_truth import render_screen
from shadowopt.service.bench.definitions import corpus_scenes, hemisphere_directions
from shadowopt.service.rigs import resolve_rig
from shadowopt.service.scenes import SceneCache
from shadowopt.service.request import SolveRequest
from shadowopt.service.solution_json import maps_from_solution
from shadowopt.service.solve import solve


CASCADE_CONFIGS = {1: {"resolution": [400, 400], "cascades": 1},
                   4: {"resolution": [400, 400], "cascades": 4, "splits": "practical", "lambda": 0.5}}


def coverage_sweep(validate_rig, scenes=None, suns: int = 4, methods=("uniform", "focused", "lispsm", "logpsm", "optimized"),
                   cascades=(1, 4), screens=((750, 750), (1920, 1080)), seed: int = 2, min_elevation_deg: float = 5.0,
                   log=print) -> list[dict]:
    """Outside pixels on the corpus (configs/corpus.json): per scene rig, screen (the rig's resolution:
    each solve sees that camera), sun (service.bench.definitions.hemisphere_directions, the corpus benchmark's
    seed), method and cascade count, one row {scene, screen, sun, method, cascades, outside_pixels,
    receiver_pixels}. `validate_rig`: api.schemas.validate_rig (as every bench takes it). `log` gets one line per (scene, screen) with the totals per method."""
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
                            maps = maps_from_solution(solve(entry, rig, SolveRequest(method=method)))[0]
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
