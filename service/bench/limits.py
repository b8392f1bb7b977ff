"""`shadowopt bench limits`: how long the requests at the service's limits take (the figures its tests no longer
assert: tests/test_request_cost.py checks that they solve and how the budget is shared, not how fast).

On the demo scene (configs/demo_scene.usda), in process (service.solve, the REST handlers' solve without HTTP):
- the demo rig (configs/demo_rig.json), method optimized;
- the largest rig within every request-cost limit: 16 suns, 4 cascades of 2048^2, the default coarse buffer
  (180 x 101 at 16:9; 1,163,520 work units), methods uniform and focused;
- the same rig, method optimized under a time budget of the focused solve's time x 1.2 + 300 ms (every light's search
  gets what is left of the solve's budget: the last lights get 1 ms).
Each solve runs once warm-up (kernels compiled), then `runs` times; the table gives the median and the slowest.
"""
from __future__ import annotations

import json
import statistics
import time

from ..pipeline import scene_entry
from ..request import SolveRequest
from ..solve import solve
from .definitions import ROOT
from .output import machine, write_section

DEMO = ROOT / "configs" / "demo_scene.usda"
SUNS = 16


def largest_rig() -> dict:
    """Near the limit: 16 suns, the default coarse buffer (180 x 101 at 16:9), 4 cascades = 1,163,520 units."""
    lights = [{"type": "directional", "direction": [-0.3 + 0.01 * i, -0.8, 0.5]} for i in range(SUNS)]
    return {"camera": {"position": [0, 1.7, 0], "target": [30, 0, 8], "resolution": [1280, 720]},
            "lights": lights, "shadow": {"resolution": [2048, 2048], "cascades": 4}, "coarse_long_side": 180}


def _timed(fn, runs: int) -> list[float]:
    fn()  # warm: kernels compiled, the coarse pass cached as in a server
    out = []
    for _ in range(runs):
        t0 = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t0)
    return out


def bench_limits(validate_rig, runs: int = 3, write: bool = True) -> dict:
    entry = scene_entry(DEMO)
    demo = validate_rig(json.loads((ROOT / "configs" / "demo_rig.json").read_text()))
    big = validate_rig(largest_rig())
    rows = {"demo rig, optimized": _timed(lambda: solve(entry, demo, SolveRequest(method="optimized")), runs),
            f"largest rig ({SUNS} suns x 4 cascades), uniform": _timed(lambda: solve(entry, big, SolveRequest(method="uniform")), runs),
            f"largest rig ({SUNS} suns x 4 cascades), focused": _timed(lambda: solve(entry, big, SolveRequest(method="focused")),
                                                                       runs)}
    focused_ms = statistics.median(rows[f"largest rig ({SUNS} suns x 4 cascades), focused"]) * 1e3
    budget = 1.2 * focused_ms + 300.0
    rows[f"largest rig, optimized within {budget:.0f} ms"] = _timed(
        lambda: solve(entry, big, SolveRequest(method="optimized", time_budget_ms=budget)), runs)
    results = {name: {"median_s": round(statistics.median(ts), 3), "max_s": round(max(ts), 3), "runs": len(ts)}
               for name, ts in rows.items()}
    lines = ["| solve (demo scene, in process) | median s | slowest s | runs |", "|---|---|---|---|"]
    lines += [f"| {name} | {r['median_s']:.2f} | {r['max_s']:.2f} | {r['runs']} |" for name, r in results.items()]
    table = "\n".join(lines)
    if write:
        write_section("limits", table, f"shadowopt bench limits --runs {runs}")
    return {"benchmark": "limits", "machine": machine(), "results": results, "table": table}
