"""`optimize --emit FILE.js`: a solution as an ES module a three.js page imports as it is (issue 26, first slice).

The module (service/emit_three.js, its header says what goes where in three.js r187) exports
`apply(THREE, ctx)`, ctx = {renderer, scene, camera, light, materials, CSM}, which installs one directional light's
maps: the solution's view and projection, its depth block with three's signs and units, the map size, nearest-texel
lookups and both faces, and returns {update(), dispose()}; cascades go through three's CSM addon (ctx.CSM), whose
lights take the maps and whose shader selects them by the solution's splits. What three.js cannot take is refused
here (EmitError: the CLI's exit 2, naming the field and what is accepted): another output engine, more than one
light, a light that is not directional, the linear depth mode, a receiver-side slope term, a clamped caster slope
term (three has neither) and cascades with different caster slope terms (one depth material per mesh).
"""
from __future__ import annotations

import json
from pathlib import Path

THREE_VERSION = "0.187.0"  # the three.js release the module is written and tested for (Makefile: make setup)
EMIT_ENGINES = ("three", "filament")  # filament: service.emit_filament (settings, no matrices)
TEMPLATE = Path(__file__).with_name("emit_three.js")
MAP_FIELDS = ("view_matrix", "projection_matrix", "texture_matrix", "resolution", "split", "blend_band", "light_depth")
DEPTH_FIELDS = ("constant", "slope", "normal_offset", "slope_scaled", "slope_clamp")


class EmitError(ValueError):
    def __init__(self, field: str, message: str):
        super().__init__(f"{field}: {message}")
        self.field = field
        self.message = message


def check_engine(rig: dict) -> None:
    """Before solving: the rig's output.engine must be one --emit writes code for, with one light."""
    engine = (rig.get("output") or {}).get("engine")
    if engine not in EMIT_ENGINES:
        raise EmitError("--emit", f"writes code for output.engine {' or '.join(map(repr, EMIT_ENGINES))} only "
                        f"(accepted: {', '.join(EMIT_ENGINES)}); the rig's output.engine is {engine!r}")
    check_one_light(rig.get("lights") or [], "rig")


def check_one_light(lights: list, what: str) -> None:
    """The rig's or the solution's lights: --emit writes a module for one light (ctx.light)."""
    if len(lights) != 1:
        raise EmitError("rig lights", f"--emit writes a module for one light (ctx.light; accepted: 1), the {what} "
                        f"has {len(lights)}")


def three_module(solution: dict) -> str:
    """The ES module's text for a solution solved with output.engine "three" (module doc; EmitError otherwise)."""
    output = (solution.get("resolved") or {}).get("output") or {}
    if output.get("engine") != "three":
        raise EmitError("--emit", f"the solution was not solved for output.engine 'three' (accepted: three), its "
                        f"output is {output.get('engine')!r}")
    lights = solution.get("lights") or []
    check_one_light(lights, "solution")
    light = lights[0]
    if light.get("type") != "directional":
        raise EmitError("rig lights[0]", f"--emit writes a module for a directional light (accepted: directional), "
                        f"got {light.get('type')!r}")
    maps = light.get("cascades") or []
    slopes = sorted({float(((m.get("depth") or {}).get("hardware") or {}).get("slope_scaled", 0.0)) for m in maps})
    if len(slopes) > 1:
        raise EmitError("lights[0].cascades[].depth.hardware.slope_scaled", f"three.js's light pass takes one "
                        f"polygon offset per mesh for every cascade (accepted: one value), got {slopes}")
    data = {"engine": "three", "three": THREE_VERSION, "method": solution.get("method"),
            "software": (solution.get("provenance") or {}).get("software"),
            "scene_hash": (solution.get("provenance") or {}).get("scene_hash"),
            "light": {k: light.get(k) for k in ("type", "usd_path")},
            "direction": next((l.get("direction") for l in (solution.get("resolved") or {}).get("lights") or []), None),
            "maps": [_map(m, k) for k, m in enumerate(maps)]}
    return TEMPLATE.read_text().replace("@@THREE_VERSION@@", THREE_VERSION).replace(
        "@@SOLUTION@@", json.dumps(data, indent=1))


def _map(smap: dict, k: int) -> dict:
    depth = smap.get("depth") or {}
    where = f"lights[0].cascades[{k}].depth"
    if depth.get("mode") != "hardware":
        raise EmitError(f"{where}.mode", f"three.js stores window depth only (accepted: hardware), got "
                        f"{depth.get('mode')!r}: the linear mode has no three.js route")
    block = depth.get("hardware") or {}
    terms = {f: float(block.get(f, 1.0 if f == "slope_clamp" else 0.0)) for f in DEPTH_FIELDS}
    if terms["slope"] != 0.0:
        raise EmitError(f"{where}.hardware.slope", f"three.js has no receiver-side slope term (accepted: 0), got "
                        f"{terms['slope']}")
    if terms["slope_scaled"] > 0.0 and terms["slope_clamp"] < 1.0:
        raise EmitError(f"{where}.hardware.slope_clamp", f"three.js cannot clamp the casters' slope offset "
                        f"(accepted: 1, no clamp), got {terms['slope_clamp']}")
    out = {f: smap[f] for f in MAP_FIELDS if f in smap}
    out["depth"] = {"mode": "hardware", "format": depth.get("format"), **terms}
    return out
