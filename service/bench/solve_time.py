"""`shadowopt bench solve-time`: optimize's time per light on 12 rigs (the demo, closeup, interior and street canyon
corpus scenes, 3 suns each: 15-90 degrees elevation, seed 25; 640x360, one 1024² map), median of 3 warm solves per rig
(`timings_ms.optimize`: the maps, the bias search, the prediction and the engine check; the coarse pass excluded),
for optimized with the fitted bias and with the fixed rule (the bias search's share, same run)."""
from __future__ import annotations

import statistics

from ..request import SolveRequest
from ..scenes import SceneCache
from ..solve import solve
from .definitions import corpus_scenes, hemisphere_directions
from .output import write_section

SCENES = ("demo", "closeup", "interior", "street_canyon")


def bench_solve_time(validate_rig, runs: int = 3, write: bool = True) -> dict:
    found, _ = corpus_scenes(list(SCENES))
    dirs = hemisphere_directions(3, 15.0, 25)
    cache = SceneCache()
    rows = []
    for name, (path, spec) in found.items():
        entry = cache.get(path)
        camera = next(iter(spec["rigs"].values()))["camera"]
        for i, d in enumerate(dirs):
            times = {}
            for bias in ("fitted", "rule"):
                rig = validate_rig({"camera": {**camera, "resolution": [640, 360]},
                                    "lights": [{"type": "directional", "direction": [float(v) for v in d]}],
                                    "shadow": {"resolution": [1024, 1024], "cascades": 1, "bias": bias}})
                solve(entry, rig, SolveRequest(method="optimized"))  # warm: kernels compiled, caches filled
                times[bias] = statistics.median(solve(entry, rig, SolveRequest(method="optimized"))["timings_ms"]["optimize"]
                                                for _ in range(runs))
            rows.append((f"{name}/{i}", times["fitted"], times["rule"]))
    lines = ["| rig | optimize ms, fitted bias | optimize ms, rule | fitted / rule |", "|---|---:|---:|---:|"]
    lines += [f"| {r} | {f:.1f} | {u:.1f} | {f / u:.2f} |" for r, f, u in rows]
    med_f = statistics.median(r[1] for r in rows)
    med_r = statistics.median(r[2] for r in rows)
    lines.append(f"| **median** | {med_f:.1f} | {med_r:.1f} | {statistics.median(r[1] / r[2] for r in rows):.2f} |")
    table = "\n".join(lines)
    if write:
        write_section("solve-time", table, "shadowopt bench solve-time" + (f" --runs {runs}" if runs != 3 else ""))
    return {"table": table, "rows": rows}
