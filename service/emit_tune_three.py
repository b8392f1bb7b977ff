"""`tune --engine three --emit FILE.js`: the tuned CSM settings as an ES module a three.js page imports as it is
(service/emit_tune_three.js, whose header says what goes where in three.js r187): `export default function
apply(THREE, ctx)`, ctx = {renderer, scene, camera, light, materials, CSM}, building a CSM instance from ctx.CSM
with the tuned options and returning {update(), dispose()} (the contract of service/emit_three.py's module)."""
from __future__ import annotations

import json
from pathlib import Path

TEMPLATE = Path(__file__).with_name("emit_tune_three.js")


def tune_module(result: dict) -> str:
    """The module's text for a `tune --engine three` result."""
    if result.get("engine") != "three":
        raise ValueError(f"engine: --emit writes a module for three.js (accepted: three), got {result.get('engine')!r}")
    data = {"engine": "three", "three": result["engine_version"], "settings": result["settings"],
            "direction": result["light_direction"], "shadow_map_type": result["emulated"]["shadow_map_type"],
            "predicted": {k: result["predicted"][k] for k in ("misclassified_pixels", "wrongly_lit", "wrongly_shadowed")}}
    return TEMPLATE.read_text().replace("@@THREE_VERSION@@", result["engine_version"]).replace(
        "@@TUNED@@", json.dumps(data, indent=1))
