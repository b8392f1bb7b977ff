"""Engine emulations: each engine's own cascade fit, from the options its users set, as pure math
(DESIGN.md, "engine emulations"; issue 26 part 2, `shadowopt tune`). One module per engine; every module has
exactly this interface, which service.tune relies on:

- `ENGINE: str`: the engine's name as `--engine` takes it ("three", "babylon", "filament").
- `VERSION: str`: the npm version the emulation was read from and is tested against (pinned by `make setup`).
- `KNOBS: dict[str, Knob]`: option name, under the engine's own spelling (e.g. three's CSM `shadowMapSize`) ->
  `knobs.Knob(default, kind, domain, doc)`: `kind` "int" | "float" | "choice" | "bool"; `domain` the inclusive
  (lo, hi) for numbers, the tuple of accepted values otherwise (values the emulation does not model are left
  out and the doc says so).
- `validate(settings: dict) -> dict`: the settings completed with KNOBS' defaults (`knobs.validate_settings`);
  an unknown knob, a wrong type or a value out of range is a ValueError whose text starts with the field
  (`settings.<knob>: ...`) and lists what is accepted (the caller maps it to HTTP 422 / CLI exit 2).
- `fit(camera, light, settings: dict) -> list[ShadowMap]`: the engine's own maps for one directional light
  (solvers.lights.DirectionalLight) seen from one camera pose (solvers.cameras.Camera), with validated settings:
  per cascade a solvers.shadow_map.ShadowMap whose `view` and `projection` are the matrices the engine builds
  (world -> light view looking down -Z, OpenGL clip z in [-1, 1]), `split` the camera view-depth range in which
  the engine's shader selects that cascade (not the slice it was fitted to, where the two differ),
  `resolution` the map size, `light_depth` (near, far) of its light camera, and `depth` the bias terms the
  engine applies, in the product's stored-depth units (solvers.depth_modes, solvers.bias_fit):
  {"mode": "hardware" | "linear", "format": "float32" | "unorm24" | "unorm16", "chosen_by": "engine",
   "<mode>": {"constant", "slope", "normal_offset", "slope_scaled", "slope_clamp"}} with the product's
  conventions (receiver shadowed iff D_rec - constant > stored + min(slope_scaled DZ, slope_clamp);
  normal_offset in metres along the receiver's normal).
- `fit(..., casters_box=None)`: the casters' world (min, max) box where the engine fits depth to its render list
  (Babylon.js); other engines ignore it. `pancakes(settings) -> bool`: whether casters in front of a map's near
  plane are pancaked onto it (the engine clamps depth) or clipped.
- `faces(settings) -> "both" | "back"`: the faces the engine draws into its maps with these settings (the
  scoring casts double-sided rays: "both" only, so far).
- `DEPTH_FORMAT` (the depth block's format) and `SHADOW_MAP_TYPE` (the engine's filter the module sets, the one
  the emulation scores: nearest-texel where the engine offers it).
- Used by the search (service.tune_search, engine-specific): `effective(settings)` (the values the engine really
  holds, e.g. three's `||` defaults) and, for three, `light_depth_reach(camera, light, settings)`.
Register a module in ENGINE_MODULES below (a static import: tests/test_layout.py follows imports).

Where an emulation is approximate, its module says so in a comment at that step, and docs/tune.md lists it.
"""
from __future__ import annotations

from . import babylon, three_csm
from .knobs import Knob, validate_settings

# --engine name -> module; a new engine's module is imported above and added here (filament: to come)
ENGINE_MODULES = {three_csm.ENGINE: three_csm, babylon.ENGINE: babylon}
ENGINES = tuple(ENGINE_MODULES)


def engine_module(engine: str):
    """The emulation module of `engine` (ValueError naming `engine` and listing the accepted ones otherwise)."""
    if engine not in ENGINE_MODULES:
        raise ValueError(f"engine: {engine!r} has no emulation (accepted: {', '.join(ENGINES)})")
    return ENGINE_MODULES[engine]


__all__ = ["Knob", "validate_settings", "ENGINE_MODULES", "ENGINES", "engine_module"]
