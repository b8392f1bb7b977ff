"""`optimize --emit FILE.js`: the rig's output.engine picks the module writer (service/emit_three.py for three.js,
service/emit_babylon.py for Babylon.js, service/emit_filament.py for Filament's web build: settings, no matrices). check_rig refuses before solving what no module can take; module writes
the text for a solved solution. Both raise EmitError (the CLI's exit 2, naming the field and what is accepted)."""
from __future__ import annotations

from .emit_babylon import babylon_module
from .emit_babylon import check_rig as check_babylon_rig
from .emit_filament import check_rig as check_filament_rig
from .emit_filament import filament_module
from .emit_three import EmitError, check_one_light, three_module

EMIT_ENGINES = ("three", "babylon", "filament")
ENGINE_NAMES = {"three": "three.js", "babylon": "Babylon.js", "filament": "Filament"}


def check_rig(rig: dict) -> str:
    """Before solving: the rig's output.engine is one --emit writes code for, and the rig is one its module takes.
    Returns the engine."""
    engine = (rig.get("output") or {}).get("engine")
    if engine not in EMIT_ENGINES:
        raise EmitError("--emit", f"writes code for output.engine {' or '.join(map(repr, EMIT_ENGINES))} only "
                        f"(accepted: {', '.join(EMIT_ENGINES)}); the rig's output.engine is {engine!r}")
    if engine == "babylon":
        check_babylon_rig(rig)
    elif engine == "filament":
        check_one_light(rig.get("lights") or [], "rig")
        check_filament_rig(rig)
    else:
        check_one_light(rig.get("lights") or [], "rig")
    return engine


def module(solution: dict) -> str:
    """The ES module's text for a solved solution, by the engine it was solved for."""
    engine = ((solution.get("resolved") or {}).get("output") or {}).get("engine")
    writers = {"babylon": babylon_module, "filament": filament_module}
    return writers.get(engine, three_module)(solution)
