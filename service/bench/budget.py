"""`shadowopt bench budget`: what a rig's lights need, on the corpus rigs (configs/corpus.json).

Each rig gets four lights, some irrelevant to its view: a sun (direction (-0.3, -0.8, 0.5)), a spot 30 degrees
wide above the view's look point pointing down, a spot beside the camera pointing at the sky (20 degrees), and a
point light above the look point (the look point: the centre of the scene's bounds when it is in front of the
camera, else a point a quarter of the far plane ahead; heights a tenth of the bounds' diagonal, at most 50 m).

Two solves with the same total texels B = 4 x `map_side`^2 (focused maps, one cascade):
- per light: texel_budget B/4 for each light (today's fixed per-light budget; before the need rule every light
  got its B/4, so the rig allocated all of B);
- rig: texel_budget B with budget_scope rig (service.need.split_budget: split by need).
Per solve: the texels returned, the lights with no map, the cube faces dropped, and the misclassified pixels
measured against ray-traced shadows (service.evaluation, depth "solution": each map's engine depth block) over
all lights at the rig's screen. The target: 0 texels for lights and cascades without visible receivers, and the
rig split's misclassified pixels no more than the per-light budget's.

Part two (section budget-point-faces): a point light alone, inside the view (half the rig's height above the
look point) and outside it (behind the camera), solved with method lispsm and texel_budget `map_side`^2
(fixed_resolution) three ways: the six-face cube (shadow.point_light_maps cube: faces without receivers dropped,
the others at T/6 each), the service's choice (auto: Lloyd et al. 2007 face partitioning, FP or FP+P, at the kept
cube's total texels when its predicted objective is lower), and auto with output.allow_log_warp (FP+LogP tried
too). Measured misclassified pixels (ray-traced, depth "solution") at equal total texels.
"""
from __future__ import annotations

import time

import numpy as np

from ..evaluation import evaluate_solution
from ..rigs import resolve_rig
from ..scenes import SceneCache
from ..request import SolveRequest
from ..solve import solve
from .definitions import corpus_scenes
from .output import machine, write_section

SUN = (-0.3, -0.8, 0.5)


def _lights(entry, camera) -> list[dict]:
    lo, hi = entry.loaded.geometry.bounds()
    centre = (lo + hi) / 2.0
    pos, fwd = camera.position, camera.forward
    ahead = float((centre - pos) @ fwd)
    look = centre if 0 < ahead < camera.far else pos + fwd * camera.far * 0.25
    h = float(min(np.linalg.norm(hi - lo) * 0.1, 50.0))
    up = np.array([0.0, 1.0, 0.0])
    return [{"type": "directional", "direction": list(SUN)},
            {"type": "spot", "position": (look + up * h).tolist(), "direction": [0.0, -1.0, 0.0], "cone_deg": 30.0},
            {"type": "spot", "position": (pos + up * h * 0.5).tolist(), "direction": [0.0, 1.0, 0.0], "cone_deg": 20.0},
            {"type": "point", "position": (look + up * h * 0.5).tolist()}]


def _corpus_rigs(validate_rig, found: dict, screen):
    """Each corpus scene rig once: (scene, rig name, scene entry, the rig with the bench's sun, its camera)."""
    cache = SceneCache()
    try:
        for name, (path, spec) in found.items():
            entry = cache.get(path)
            for rig_name, part in spec.get("rigs", {}).items():
                base = {"camera": {**part["camera"], "resolution": list(screen)},
                        "lights": [{"type": "directional", "direction": list(SUN)}]}
                yield name, rig_name, entry, base, resolve_rig(validate_rig(base), entry.loaded).camera
    finally:
        cache.clear()  # the scenes' memory back before the next part


def bench_budget(validate_rig, scenes=None, screen=(320, 180), map_side: int = 1024, write: bool = True,
                 log=None) -> dict:
    found, skipped = corpus_scenes(scenes.split(",") if isinstance(scenes, str) else scenes)
    B = 4 * map_side * map_side
    rows = []
    for name, rig_name, entry, base, camera in _corpus_rigs(validate_rig, found, screen):
        lights = _lights(entry, camera)
        row = {"scene": name, "rig_name": rig_name}
        for scope, budget in (("light", B // 4), ("rig", B)):
            rig = validate_rig({**base, "lights": lights,
                                "shadow": {"texel_budget": budget, "budget_scope": scope, "cascades": 1,
                                           "fixed_resolution": True}})
            t0 = time.perf_counter()
            sol = solve(entry, rig, SolveRequest(method="focused"))
            ms = (time.perf_counter() - t0) * 1e3
            ev = evaluate_solution(entry, rig, sol, depth="solution")
            per = ev["lights"] if "lights" in ev else [ev]
            row[scope] = {
                "texels": sum(c["resolution"][0] * c["resolution"][1] for l in sol["lights"] for c in l["cascades"]),
                "no_map": [k for k, l in enumerate(sol["lights"]) if l["shadow"] == "none"],
                "dropped": sum(len(l.get("notes") or []) for l in sol["lights"]),
                "misclassified": int(sum(x["misclassified_pixels"] for x in per)),
                "per_light_misclassified": [int(x["misclassified_pixels"]) for x in per],
                "solve_ms": ms}
        if log:
            log(f"{name}/{rig_name}: per light {row['light']['texels']:,} texels, {row['light']['misclassified']} "
                f"misclassified; rig {row['rig']['texels']:,}, {row['rig']['misclassified']}")
        rows.append(row)
    table = _table(rows, skipped, B)
    pf_rows = point_faces_rows(validate_rig, found, screen, map_side, log)
    pf_table = _point_faces_table(pf_rows, skipped, map_side * map_side)
    result = {"benchmark": "budget", "machine": machine(), "total_texels": B, "screen": list(screen),
              "rows": rows, "skipped": skipped, "table": table + "\n\n" + pf_table, "point_faces": pf_rows}
    if write:
        write_section("budget", table, f"shadowopt bench budget --map {map_side}")
        write_section("budget-point-faces", pf_table, f"shadowopt bench budget --map {map_side}")
    return result


POINT_MODES = (("cube", "cube", False), ("auto", "auto", False), ("auto_log", "auto", True))


def point_faces_rows(validate_rig, found: dict, screen, map_side: int, log=None) -> list[dict]:
    """Part two (module doc): per corpus rig, a point light inside and one outside the view, cube vs face
    partitioning at equal total texels, measured misclassified pixels."""
    rows = []
    for name, rig_name, entry, base, camera in _corpus_rigs(validate_rig, found, screen):
        inside = _lights(entry, camera)[3]["position"]
        lo, hi = entry.loaded.geometry.bounds()
        h = float(min(np.linalg.norm(hi - lo) * 0.1, 50.0))
        behind = (camera.position - camera.forward * h + np.array([0.0, 0.5 * h, 0.0])).tolist()
        for where, pos in (("inside", inside), ("outside", behind)):
            row = {"scene": name, "rig_name": rig_name, "light": where, "position": pos}
            for key, mode, allow_log in POINT_MODES:
                rig = validate_rig({**base, "lights": [{"type": "point", "position": pos}],
                                    "shadow": {"texel_budget": map_side * map_side, "cascades": 1,
                                               "fixed_resolution": True, "point_light_maps": mode},
                                    "output": {"allow_log_warp": allow_log}})
                t0 = time.perf_counter()
                sol = solve(entry, rig, SolveRequest(method="lispsm"))
                ms = (time.perf_counter() - t0) * 1e3
                light = sol["lights"][0]
                if light["shadow"] == "none":
                    row[key] = {"maps": 0, "texels": 0, "misclassified": None, "chosen": "none", "solve_ms": ms}
                    continue
                ev = evaluate_solution(entry, rig, sol, depth="solution")
                ev = ev["lights"][0] if "lights" in ev else ev
                fp = light.get("face_partitioning") or {}
                row[key] = {"maps": len(light["cascades"]),
                            "faces": [c.get("face") for c in light["cascades"]],
                            "resolutions": [c["resolution"] for c in light["cascades"]],
                            "texels": sum(c["resolution"][0] * c["resolution"][1] for c in light["cascades"]),
                            "misclassified": int(ev["misclassified_pixels"]),
                            "outside": int(ev.get("outside_pixels", 0)),
                            "objective": light["predicted_error"]["objective"],
                            "chosen": fp.get("chosen", "cube"), "variant": fp.get("variant"),
                            "variants_objective": fp.get("variants_objective"), "solve_ms": ms}
            if log:
                log(f"{name}/{rig_name} point {where}: " + ", ".join(
                    f"{k} {row[k]['misclassified']} ({row[k]['chosen']})" for k, _, _ in POINT_MODES))
            rows.append(row)
    return rows


def _point_faces_table(rows, skipped, T) -> str:
    lines = [f"A point light alone, inside the view and behind the camera; method lispsm, texel_budget {T:,} "
             f"(the cube: faces without receivers dropped, the others {T // 6:,} texels each; face partitioning at "
             f"the kept cube's total). Misclassified: measured against ray-traced shadows, depth solution.", "",
             "| scene / rig | light | cube: faces, texels | misclassified | auto: returned, texels "
             "| misclassified | auto + allow_log_warp: returned | misclassified | solve ms cube / auto |",
             "|---|---|---|---:|---|---:|---|---:|---:|"]

    def ret(c):
        return "no map" if c["chosen"] == "none" else (
            f"{c['variant']}, {c['maps']} maps" if c["chosen"] == "face_partitioning" else f"cube {c['maps']} faces")

    for r in rows:
        a, b, c = r["cube"], r["auto"], r["auto_log"]
        lines.append(f"| {r['scene']} / {r['rig_name']} | {r['light']} | {a['maps']}, {a['texels']:,} | "
                     f"{a['misclassified']} | {ret(b)}, {b['texels']:,} | **{b['misclassified']}** | {ret(c)} | "
                     f"{c['misclassified']} | {a['solve_ms']:.0f} / {b['solve_ms']:.0f} |")
    for name, why in skipped.items():
        lines.append(f"| {name} | skipped: {why} |")
    ok = [r for r in rows if r["cube"]["misclassified"] is not None]
    if ok:
        sa = sum(r["cube"]["misclassified"] for r in ok)
        sb = sum(r["auto"]["misclassified"] for r in ok)
        sc = sum(r["auto_log"]["misclassified"] for r in ok)
        no_worse = sum(r["auto"]["misclassified"] <= r["cube"]["misclassified"] for r in ok)
        ms = sorted(r["auto"]["solve_ms"] / max(r["cube"]["solve_ms"], 1e-9) for r in ok)
        lines.append(f"\nSolve time of auto (the cube, FP and the warped FP fitted and scored) over the cube's: median "
                     f"{ms[len(ms) // 2]:.1f}x (one run each, under the machine's load at the time).")
        lines.append(f"\nTotal misclassified: cube {sa}, auto {sb}, auto with the log warp {sc}; auto no worse than "
                     f"the cube on {no_worse} of {len(ok)}; face partitioning chosen on "
                     f"{sum(r['auto']['chosen'] == 'face_partitioning' for r in ok)} of {len(ok)}.")
    return "\n".join(lines)


def _table(rows, skipped, B) -> str:
    lines = [f"Four lights per rig (sun, a spot over the view, a spot at the sky beside the camera, a point light); "
             f"{B:,} texels in all: per light {B // 4:,} each (before the need rule every light took its share, "
             f"{B:,} in all), or one rig budget split by need. Misclassified: measured, all lights, rig screen.",
             "", "| scene / rig | lights without a map | faces dropped | per light: texels | misclassified "
             "| rig split: texels | misclassified | per light (sun, spot, sky spot, point) |",
             "|---|---|---:|---:|---:|---:|---:|---|"]
    for r in rows:
        a, b = r["light"], r["rig"]
        lines.append(f"| {r['scene']} / {r['rig_name']} | {', '.join(map(str, a['no_map'])) or 'none'} | {a['dropped']} | "
                     f"{a['texels']:,} | {a['misclassified']} | {b['texels']:,} | **{b['misclassified']}** | "
                     f"{a['per_light_misclassified']} -> {b['per_light_misclassified']} |")
    for name, why in skipped.items():
        lines.append(f"| {name} | skipped: {why} |")
    if rows:
        la = sum(r["light"]["misclassified"] for r in rows)
        lb = sum(r["rig"]["misclassified"] for r in rows)
        lines.append(f"\nTotal misclassified: per light {la}, rig split {lb}; rigs where the split is no worse: "
                     f"{sum(r['rig']['misclassified'] <= r['light']['misclassified'] for r in rows)} of {len(rows)}.")
    return "\n".join(lines)
