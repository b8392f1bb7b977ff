"""`optimize --emit FILE.js` for output.engine "filament": a solution as the settings of Filament's web build.

Filament builds its light matrices itself (ShadowMap.cpp, per cascade every frame) and its JS API takes no matrix,
so the module (service/emit_filament.js, its header says where Filament applies each setting) carries the
solution's SETTINGS in Filament's names and units: `export default function apply(Filament, ctx)`,
ctx = {engine, scene, view, camera, light, lightManager?, entities?}, sets the light's LightManager ShadowOptions
and returns {update(), dispose()}.

The mapping, per the depth block solvers.bias_fit fitted for BIAS_TARGETS["filament"] (one constant for the
light, stored depth of a unorm16 map, caster slope term fixed at Filament's polygonOffsetSlope):
- resolution -> mapSize (square, a power of two: LightManager.h ShadowOptions::mapSize);
- the number of maps -> shadowCascades (1..4);
- depth.hardware.constant (stored depth) -> polygonOffsetConstant = constant x 65535, in the DEPTH16 map's
  resolvable units (LightManager.h: "in depth-resolution units"; ShadowMapManager.cpp negates both polygon offset
  terms for its reversed Z, so both push casters away from the light, as the product's constant does);
  constantBias (metres, casters moved along the light) = 0, since the constant is already carried;
- depth.hardware.slope_scaled -> polygonOffsetSlope;
- depth.hardware.normal_offset (metres along the receiver's normal) -> normalBias = normal_offset /
  (0.5 x texel world size), Filament's receiver offset being 0.5 normalBias texel sin(theta) along the normal
  (engine-settings.md, Filament "Bias"): exact where the light grazes the receiver, less elsewhere;
- the solution's texel snapping -> stable; its warp -> lispsm (only where the JS binding takes it: the
  1.53.4 filament.d.ts declares no lispsm); the last split's far end -> shadowFar when it ends before the
  camera's far plane (0 = the camera's far plane).

Not applied, by construction: the light matrices (Filament fits its own) and the warp's parameters. Refused here
(EmitError: the CLI's exit 2, naming the field and listing what is accepted), because the web build cannot apply
them and the solution relies on them: more than one light or another light type; several cascades (the web
build's ShadowOptions has no cascadeSplitPositions: Filament would split at its own default positions); the
linear depth mode; a receiver-side slope term; a clamped slope term; maps with different depth blocks (one
ShadowOptions per light); a depth format other than unorm16; a map size that is not a square power of two.

Filament.js 1.53.4 (the npm release this module is written and tested for) cannot take ShadowOptions at all:
LightManager.setShadowOptions throws embind's UnboundTypeError (google/filament issue 10043, fixed by pull
request 10116 in no npm release up to 1.53.4). The module detects that at run time: it throws an Error saying so,
or, with ctx.acceptDefaults, keeps Filament's defaults and reports `applied: false` (module header).
"""
from __future__ import annotations

import json
from pathlib import Path

from ..solvers.engine_fits import filament as filament_fit
from .emit_three import EmitError, check_one_light

FILAMENT_VERSION = "1.53.4"  # the Filament.js release the module is written and tested for (Makefile: make setup)
TEMPLATE = Path(__file__).with_name("emit_filament.js")
UNORM16_STEPS = 65535.0  # DEPTH16's resolvable depth step, 1 / (2^16 - 1) (Filament's shadow map format)
MAX_CASCADES = 1  # the web build cannot set cascadeSplitPositions (module doc); the C++ API takes 1..4
DEPTH_FIELDS = ("constant", "slope", "normal_offset", "slope_scaled", "slope_clamp")


def check_rig(rig: dict) -> None:
    """Before solving: a rig asking for several cascades gets a solution the web build cannot apply (its splits)."""
    cascades = (rig.get("shadow") or {}).get("cascades", 1)
    if isinstance(cascades, int) and not isinstance(cascades, bool) and cascades > MAX_CASCADES:
        raise EmitError("rig shadow.cascades", f"Filament's web build cannot set cascadeSplitPositions (filament.d.ts "
                        f"{FILAMENT_VERSION}), so a cascaded solution cannot be applied (accepted: {MAX_CASCADES}), "
                        f"got {cascades}")


def filament_module(solution: dict) -> str:
    """The ES module's text for a solution solved with output.engine "filament" (module doc; EmitError otherwise)."""
    output = (solution.get("resolved") or {}).get("output") or {}
    if output.get("engine") != "filament":
        raise EmitError("--emit", f"the solution was not solved for output.engine 'filament' (accepted: filament), "
                        f"its output is {output.get('engine')!r}")
    lights = solution.get("lights") or []
    check_one_light(lights, "solution")
    light = lights[0]
    if light.get("type") != "directional":
        raise EmitError("rig lights[0]", f"--emit writes Filament settings for a directional light (accepted: "
                        f"directional), got {light.get('type')!r}")
    maps = light.get("cascades") or []
    data = {"engine": "filament", "filament": FILAMENT_VERSION, "method": solution.get("method"),
            "software": (solution.get("provenance") or {}).get("software"),
            "scene_hash": (solution.get("provenance") or {}).get("scene_hash"),
            "light": {k: light.get(k) for k in ("type", "usd_path")},
            "direction": next((l.get("direction") for l in (solution.get("resolved") or {}).get("lights") or []), None),
            "shadowOptions": shadow_options(maps, (solution.get("resolved") or {}).get("camera") or {}),
            "notApplied": ["light matrices (Filament fits its own every frame: ShadowMap.cpp)",
                           "the warp's parameters (at most LiSPSM on or off)"]}
    return TEMPLATE.read_text().replace("@@FILAMENT_VERSION@@", FILAMENT_VERSION).replace(
        "@@SOLUTION@@", json.dumps(data, indent=1))


def shadow_options(maps: list[dict], camera: dict) -> dict | None:
    """Filament's ShadowOptions (its field names and units) for the light's maps; None for no map (shadow "none":
    the module turns the light's shadows off). EmitError names what the web build cannot apply."""
    if not maps:
        return None
    if len(maps) > MAX_CASCADES:
        raise EmitError("lights[0].cascades", f"Filament's web build cannot set cascadeSplitPositions (filament.d.ts "
                        f"{FILAMENT_VERSION}: ShadowOptions has no such field), so its cascades would split at "
                        f"Filament's own positions, not the solution's (accepted: {MAX_CASCADES} map; set the rig's "
                        f"shadow.cascades to 1), got {len(maps)}")
    blocks = [_depth(m, k) for k, m in enumerate(maps)]
    if any(b != blocks[0] for b in blocks[1:]):
        raise EmitError("lights[0].cascades[].depth.hardware", "Filament takes one ShadowOptions per light, the "
                        "same bias for every cascade (accepted: one depth block), got different ones per map")
    sizes = {tuple(m.get("resolution") or ()) for m in maps}
    size = next(iter(sizes))
    if len(sizes) != 1 or len(size) != 2 or size[0] != size[1] or size[0] < 8 or size[0] & (size[0] - 1):
        raise EmitError("lights[0].cascades[].resolution", f"Filament's mapSize is one square power of two >= 8 "
                        f"for the light (LightManager.h; accepted: e.g. [1024, 1024]), got {sorted(sizes)}")
    depth = blocks[0]
    texel = float((maps[0].get("depth_bias") or {}).get("texel_world_size") or 0.0)
    if depth["normal_offset"] and texel <= 0.0:
        raise EmitError("lights[0].cascades[0].depth_bias.texel_world_size", "a normal offset converts to "
                        "Filament's normalBias through the map's texel size (accepted: > 0), which is missing")
    far = float(camera.get("far") or 0.0)
    split_far = float((maps[-1].get("split") or [0.0, 0.0])[1])
    warp = (maps[0].get("warp") or {}).get("kind")
    options = {"mapSize": int(size[0]), "shadowCascades": len(maps),
            "constantBias": 0.0,
            "polygonOffsetConstant": depth["constant"] * UNORM16_STEPS,
            "polygonOffsetSlope": depth["slope_scaled"],
            "normalBias": depth["normal_offset"] / (0.5 * texel) if depth["normal_offset"] else 0.0,
            "stable": bool(maps[0].get("texel_snapped")),
            "lispsm": warp not in (None, "none"),
            "shadowFar": split_far if 0.0 < split_far < far else 0.0,
            "screenSpaceContactShadows": False}
    try:  # the ranges Filament accepts, as the emulation of its fit (solvers.engine_fits.filament) knows them
        filament_fit.validate({k: v for k, v in options.items() if k in filament_fit.KNOBS})
    except ValueError as e:
        knob, message = str(e).split(": ", 1)
        raise EmitError(f"shadowOptions.{knob.removeprefix('settings.')}", message) from None
    return options


def _depth(smap: dict, k: int) -> dict:
    depth = smap.get("depth") or {}
    where = f"lights[0].cascades[{k}].depth"
    if depth.get("mode") != "hardware":
        raise EmitError(f"{where}.mode", f"Filament's shadow map stores window depth (accepted: hardware), got "
                        f"{depth.get('mode')!r}: the linear mode has no Filament route")
    if depth.get("format") not in (None, "unorm16"):
        raise EmitError(f"{where}.format", f"Filament's shadow map is DEPTH16 and the constant converts in its "
                        f"steps (accepted: unorm16), got {depth.get('format')!r}")
    block = depth.get("hardware") or {}
    terms = {f: float(block.get(f, 1.0 if f == "slope_clamp" else 0.0)) for f in DEPTH_FIELDS}
    if terms["slope"] != 0.0:
        raise EmitError(f"{where}.hardware.slope", f"Filament has no receiver-side slope term (accepted: 0), got "
                        f"{terms['slope']}")
    if terms["slope_scaled"] > 0.0 and terms["slope_clamp"] < 1.0:
        raise EmitError(f"{where}.hardware.slope_clamp", f"Filament cannot clamp its polygon offset (accepted: 1, "
                        f"no clamp), got {terms['slope_clamp']}")
    if terms["constant"] < 0.0 or terms["normal_offset"] < 0.0:
        raise EmitError(f"{where}.hardware", "Filament's polygon offset and normal bias push shadows away from the "
                        f"light only (accepted: constant >= 0, normal_offset >= 0), got {terms}")
    return terms
