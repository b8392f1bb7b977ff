"""`tune --engine babylon --emit FILE.js`: the tuned CascadedShadowGenerator settings as an ES module a Babylon.js page
imports as it is (service/emit_tune_babylon.js, whose header says what goes where in @babylonjs/core): `export default
function apply(BABYLON, ctx)`, ctx = {engine, scene, camera, light, meshes}, building a CascadedShadowGenerator with the
tuned settings and returning {update(), dispose()} (the contract of service/emit_babylon.py's module)."""
from __future__ import annotations

import json
from pathlib import Path

TEMPLATE = Path(__file__).with_name("emit_tune_babylon.js")


def tune_module(result: dict) -> str:
    """The module's text for a `tune --engine babylon` result."""
    if result.get("engine") != "babylon":
        raise ValueError(f"engine: this module is for Babylon.js (accepted: babylon), got {result.get('engine')!r}")
    data = {"engine": "babylon", "babylon": result["engine_version"], "settings": result["settings"],
            "direction": result["light_direction"], "shadow_map_type": result["emulated"]["shadow_map_type"],
            "predicted": {k: result["predicted"][k] for k in ("misclassified_pixels", "wrongly_lit", "wrongly_shadowed")}}
    return TEMPLATE.read_text().replace("@@BABYLON_VERSION@@", result["engine_version"]).replace(
        "@@TUNED@@", json.dumps(data, indent=1))
