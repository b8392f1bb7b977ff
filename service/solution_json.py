"""The solution JSON (the optimize schema, service.solution_check) of a solve's maps, and back.

maps_error: a light's and each map's predicted_error (solvers.metric); light_json: one light's maps in the
output's convention, layout, frame and length unit (solvers.conventions), with the exact internal matrices;
no_map_json: a light that gets no map (service.need); solution_json: the whole solution with its echo,
timings and provenance; maps_from_solution: the maps of a solution JSON again, in the world frame and metres.
"""
from __future__ import annotations

import copy
from functools import lru_cache
from importlib.metadata import PackageNotFoundError, version

import numpy as np

from ..solvers.conventions import convention_info, export_matrices, output_frame
from ..solvers.metric import error_stats, map_texels, per_sample_maps, sample_pixels, with_limit
from ..solvers.samples import Samples
from ..solvers.shadow_map import ShadowMap
from .echo import resolved_echo
from .need import no_shadow_reason
from .receivers import LightProblem
from .rigs import ResolvedRig
from .scenes import SceneEntry
from .solution_check import SCHEMA_VERSION


def maps_error(maps: list[ShadowMap], samples: Samples, origin) -> tuple[dict, list[dict]]:
    """predicted_error for the whole light and for each map (over the samples it serves)."""
    h, m, idx = per_sample_maps(maps, samples, origin)
    a = sample_pixels(samples)  # misclassified_pixels: solvers.metric.predicted_misclassified
    total = error_stats(h, m, samples.weight, a)
    total["unserved_samples"] = int(np.sum(idx < 0))
    with_limit(total, samples, map_texels(maps))  # limit, ratio_to_limit: solvers.metric.texel_limit
    if len(maps) == 1 and total["unserved_samples"] == 0:  # one map serving every sample: its stats are the light's
        return total, [{k: v for k, v in total.items() if k != "unserved_samples"}]
    per_map = [with_limit(error_stats(h[idx == k], m[idx == k], samples.weight[idx == k], a[idx == k]),
                          samples.subset(idx == k), map_texels([smap])) for k, smap in enumerate(maps)]
    return total, per_map


@lru_cache(maxsize=1)
def software_version() -> str:
    try:
        return version("shadowopt")
    except PackageNotFoundError:
        return "0+unknown"


def solution_json(entry: SceneEntry, resolved: ResolvedRig, method: str, per_light: list[dict],
                  timings: dict, settings: dict) -> dict:
    ver = software_version()
    convention = convention_info(resolved.output or {}, entry.loaded.stage_to_world)
    convention["world_frame"] = "right-handed, +Y up, meters; matrices act on column vectors"
    return {
        "schema_version": SCHEMA_VERSION,
        "method": method,
        "convention": convention,
        "lights": per_light,
        "resolved": resolved_echo(resolved),
        "timings_ms": {k: round(v, 3) for k, v in timings.items()},
        "provenance": {"scene_hash": entry.loaded.scene_hash, "software": f"shadowopt {ver}",
                       "settings": settings, "seed": settings.get("seed", 0)},
    }


# The lengths of a map's JSON an engine uses, expressed in the output's length unit (convention
# .length_unit: the engine preset's, else metres; with frame "stage" too, only the matrices take stage
# coordinates: solvers.conventions.output_frame). depth_bias (the idealized texel rule, keys in metres)
# and predicted_error (metres, its keys say so) stay in metres.
LENGTH_PAIRS = ("split", "light_depth", "blend_band")
DEPTH_LENGTHS = {"hardware": ("normal_offset",), "linear": ("normal_offset", "near", "far")}


def _in_units(x, metres_per_unit: float):
    return x / metres_per_unit if isinstance(x, (int, float)) and not isinstance(x, bool) and np.isfinite(x) else x


def scale_lengths(d: dict, metres_per_unit: float) -> dict | None:
    """Express the map JSON `d`'s lengths (LENGTH_PAIRS, warp.n, DEPTH_LENGTHS) in units of
    `metres_per_unit` metres, in place; returns the fields as they were (world metres) for `internal`,
    or None when the unit is the metre (nothing changes)."""
    if metres_per_unit == 1.0:
        return None
    metres = {k: copy.deepcopy(d[k]) for k in (*LENGTH_PAIRS, "warp", "depth") if d.get(k) is not None}
    for k in LENGTH_PAIRS:
        if d.get(k) is not None:
            d[k] = [_in_units(x, metres_per_unit) for x in d[k]]
    if isinstance(d.get("warp"), dict) and d["warp"].get("n") is not None:
        d["warp"]["n"] = _in_units(d["warp"]["n"], metres_per_unit)
    for mode, keys in DEPTH_LENGTHS.items():
        block = (d.get("depth") or {}).get(mode)
        if isinstance(block, dict):
            for k in keys:
                if k in block:
                    block[k] = _in_units(block[k], metres_per_unit)
    return metres


def light_json(light, maps: list[ShadowMap], total: dict, per_map: list[dict], output: dict,
               stage_to_world: np.ndarray, samples: Samples) -> dict:
    _, metres_per_unit = output_frame(output, stage_to_world)
    cascades = []
    for smap, err in zip(maps, per_map):
        d = smap.to_json()
        d.update(export_matrices(smap.view, smap.projection, output.get("convention", "opengl"),
                                 output.get("layout", "column_major"), output.get("frame", "world"),
                                 stage_to_world, reversed_z=bool(output.get("reversed_z", False)),
                                 engine=output.get("engine")))
        d["predicted_error"] = err
        if getattr(smap, "snap_note", None):
            d["texel_snap_note"] = smap.snap_note
        # service.bias.set_blend_bands: into the next cascade over the last 10% of this one's depth range
        d["blend_band"] = None if smap.blend_band is None else [float(v) for v in smap.blend_band]
        # Exact (world, column-vector, canonical OpenGL) matrices so `evaluate` reads back what was chosen,
        # and the lengths in world metres when the output's unit is another (maps_from_solution).
        d["internal"] = {"view": smap.view.tolist(), "projection": smap.projection.tolist()}
        metres = scale_lengths(d, metres_per_unit)
        if metres is not None:
            d["internal"]["metres"] = metres
        cascades.append(d)
    return {"type": light.kind, "usd_path": light.usd_path, "samples_kind": samples.kind,
            "cascades": cascades, "predicted_error": total}

def no_map_json(prob: LightProblem, need, size: tuple[int, int]) -> dict:
    """The solution entry of a light that gets no map (service.need): `shadow` "none", the reason, no
    cascades; its predicted error is that of no samples, 0 texels."""
    total = error_stats(np.zeros(0), np.zeros(0), pixels=np.zeros(0))
    total.update(unserved_samples=int(len(prob.samples)), limit=None, ratio_to_limit=None, texels=0)
    return {"type": prob.light.kind, "usd_path": prob.light.usd_path, "samples_kind": prob.samples.kind,
            "shadow": "none", "reason": no_shadow_reason(prob.light, need, size), "need": need.to_json(),
            "cascades": [], "predicted_error": total}

def jsonable(d):
    if isinstance(d, dict):
        return {k: jsonable(v) for k, v in d.items()}
    if isinstance(d, (list, tuple)):
        return [jsonable(v) for v in d]
    return d

def maps_from_solution(solution: dict) -> list[list[ShadowMap]]:
    """Per light, the maps of a solution JSON in the world frame and metres, whatever its output
    convention, frame or engine preset: the exact internal matrices and, when the solution's lengths
    are in another unit, the internal copy of them in metres."""
    out = []
    for light in solution["lights"]:
        maps = []
        for c in light["cascades"]:
            d = dict(c)
            d.update(c["internal"].get("metres") or {})
            if d.get("split") is not None and d["split"][1] is None:  # an unbounded split's hi (JSON null)
                d["split"] = [d["split"][0], float("inf")]
            d["view_matrix"] = c["internal"]["view"]
            d["projection_matrix"] = c["internal"]["projection"]
            maps.append(ShadowMap.from_json(d))
        out.append(maps)
    return out
