"""`shadowopt bench coarse`: scene load time (cold, cached) and coarse-pass time per scene.

Timings are medians of warm runs; the first (compiling) run is reported apart.
"""
from __future__ import annotations

import statistics
import time

from ...renderers.coarse import render_coarse
from ..rigs import resolve_rig
from ..scenes import SceneCache
from .definitions import ROOT, definitions
from .output import machine, progress, write_section


def bench_coarse(validate_rig, runs: int | None = None, scenes: str | None = None, write: bool = True) -> dict:
    """Load time (cold, cached) and coarse-pass time (first and median of warm runs) per scene.

    `validate_rig(dict) -> dict` is the API's rig validation (benchmark rigs are ordinary rigs).
    """
    spec = definitions()["coarse"]
    runs = runs or spec["runs"]
    wanted = scenes.split(",") if scenes else list(spec["scenes"])
    results, skipped = {}, {}
    for name in wanted:
        if name not in spec["scenes"]:
            raise ValueError(f"--scenes: unknown scene {name!r} (known: {', '.join(spec['scenes'])})")
        sdef = spec["scenes"][name]
        path = (ROOT / sdef["path"]).resolve()
        if not path.exists():
            skipped[name] = f"{sdef['path']} is absent"
            continue
        cache = SceneCache()
        t0 = time.perf_counter()
        entry = cache.get(path)
        cold = time.perf_counter() - t0
        t0 = time.perf_counter()
        cache.get(path)
        cached = time.perf_counter() - t0
        rig = resolve_rig(validate_rig(sdef["rig"]), entry.loaded)
        t0 = time.perf_counter()
        first = render_coarse(entry.rays, rig.camera, rig.lights, spec["long_side"])
        first_ms = (time.perf_counter() - t0) * 1e3
        times, traces = [], []
        bar = progress(runs, f"coarse {name}")
        for _ in range(runs):
            t0 = time.perf_counter()
            cb = render_coarse(entry.rays, rig.camera, rig.lights, spec["long_side"])
            times.append((time.perf_counter() - t0) * 1e3)
            traces.append(cb.timings_ms["trace"])
            bar.update(1)
        bar.close()
        results[name] = {
            "triangles": entry.loaded.geometry.triangle_count,
            "load_s": round(cold, 3), "usd_load_s": round(entry.load_s, 3), "mitsuba_build_s": round(entry.build_s, 3),
            "load_cached_s": round(cached, 6),
            "coarse_first_ms": round(first_ms, 2),
            "coarse_ms_p50": round(statistics.median(times), 3),
            "coarse_ms_min": round(min(times), 3), "coarse_ms_max": round(max(times), 3),
            "trace_ms_p50": round(statistics.median(traces), 3),
            "pixels": cb.width * cb.height, "hit_pixels": int(first.hit.sum()), "runs": runs,
        }
    table = _table_coarse(results, skipped)
    out = {"benchmark": "coarse", "machine": machine(), "scenes": results, "skipped": skipped,
           "table": table}
    if write:
        write_section("coarse", table, "shadowopt bench coarse")
    return out


def _table_coarse(results: dict, skipped: dict) -> str:
    lines = ["| scene | triangles | load cold (s) | USD load (s) | Mitsuba build (s) | load cached (ms) "
             "| coarse first (ms) | coarse p50 (ms) | min | max | of which ray casting p50 (ms) | pixels |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for name, r in results.items():
        lines.append(f"| {name} | {r['triangles']:,} | {r['load_s']:.2f} | {r['usd_load_s']:.2f} | "
                     f"{r['mitsuba_build_s']:.2f} | {r['load_cached_s'] * 1e3:.3f} | {r['coarse_first_ms']:.1f} | "
                     f"**{r['coarse_ms_p50']:.2f}** | {r['coarse_ms_min']:.2f} | {r['coarse_ms_max']:.2f} | "
                     f"{r['trace_ms_p50']:.2f} | {r['pixels']} |")
    for name, why in skipped.items():
        lines.append(f"| {name} | skipped: {why} |")
    return "\n".join(lines)
