"""`optimize --emit FILE.js` for output.engine "babylon": a solution as an ES module a Babylon.js page imports as it
is (issue 26). The module (service/emit_babylon.js; its header says where Babylon.js 9.35 applies each number)
exports `apply(BABYLON, ctx)`, ctx = {engine, scene, camera, light, meshes}, which installs one directional light's
map through `light.customProjectionMatrixBuilder` and returns {update(), dispose()}.

Babylon.js builds the light's view itself (Matrix.LookAtLHToRef from the light's position and direction) and asks
the builder for a projection only; the shadow transform is view · projection (Lights/Shadows/shadowGenerator.js
getTransformMatrix). The module's builder returns view⁻¹ · T, so that the transform is exactly T, the clip matrix
written here: the solution's projection · view in Babylon's frame (the `babylon` preset) with its depth row replaced
by the linear depth (2 D - 1, D = (z_view - near) / (far - near), solvers.depth_modes.linear_depth in the preset's
+Z-forward light view). Babylon stores and compares the depth row's value before the divide by w: the light pass
writes (clip z + 1) / 2 + bias as a varying (Shaders/ShadersInclude/shadowMapVertexMetric.js, directional
depthValues (1, 2): Lights/directionalLight.pure.js), and the receiver compares its own (clip z + 1) / 2
(shadowsVertex.js, shadowsFragmentFunctions.js computeShadow), so a warped map's window z has no Babylon route but
its linear depth does. The x, y and w rows are scaled together (x / w, y / w unchanged) so that w >= 1 over the
map's frustum and no caster inside it is clipped by the rasterizer (|clip z| <= 1 <= w).

What Babylon.js cannot take is refused here (EmitError: the CLI's exit 2, naming the field and what is accepted):
another output engine, several lights, a light that is not directional, cascades (Babylon's CascadedShadowGenerator
computes its cascades' matrices in a private method, _computeMatrices in Lights/Shadows/cascadedShadowGenerator.pure.js,
with no public hook; a custom matrix goes through the plain ShadowGenerator only), a non-square map (mapSize is one
number), window depth of a warped map, a slope term (none in this path), a receiver normal offset (Babylon's
normalBias moves casters: Shaders/ShadersInclude/shadowMapVertexNormalBias.js).
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .emit_three import EmitError, check_one_light

BABYLON_VERSION = "9.35.0"  # the @babylonjs/core release the module is written and tested for (Makefile: make setup)
TEMPLATE = Path(__file__).with_name("emit_babylon.js")
ZERO_TERMS = ("slope", "slope_scaled", "normal_offset")  # the depth terms Babylon's custom-matrix path cannot apply


def check_rig(rig: dict) -> None:
    """Before solving: one light, one map, and no pinned depth term Babylon's custom-matrix path cannot apply."""
    check_one_light(rig.get("lights") or [], "rig")
    shadow = rig.get("shadow") or {}
    cascades = shadow.get("cascades", 1)
    if cascades != 1:
        raise EmitError("shadow.cascades", f"Babylon.js takes a custom matrix for one map only (accepted: 1), got "
                        f"{cascades!r}: its CascadedShadowGenerator fits its cascades' matrices in the private "
                        f"_computeMatrices (Lights/Shadows/cascadedShadowGenerator.pure.js) with no public hook; set "
                        f"its own knobs instead (numCascades, lambda, shadowMaxZ, bias, normalBias)")
    depth = shadow.get("depth") or {}
    for term in ZERO_TERMS:
        if depth.get(term):
            raise EmitError(f"shadow.depth.{term}", _zero_term_reason(term, depth[term]))
    if depth.get("mode") not in (None, "linear"):
        raise EmitError("shadow.depth.mode", f"Babylon.js compares depth before the divide by w, so the module writes "
                        f"the linear depth (accepted: linear, or leave it unset), got {depth['mode']!r}")


def _zero_term_reason(term: str, value) -> str:
    if term == "normal_offset":
        return (f"Babylon.js's normalBias moves the casters inward in its light pass "
                f"(Shaders/ShadersInclude/shadowMapVertexNormalBias.js), not the receivers (accepted: 0), got {value}")
    return (f"Babylon.js's ShadowGenerator with a custom matrix has no slope-scaled or receiver slope term "
            f"(accepted: 0), got {value}")


def babylon_module(solution: dict) -> str:
    """The ES module's text for a solution solved with output.engine "babylon" (module doc; EmitError otherwise)."""
    output = (solution.get("resolved") or {}).get("output") or {}
    if output.get("engine") != "babylon":
        raise EmitError("--emit", f"the solution was not solved for output.engine 'babylon' (accepted: babylon), its "
                        f"output is {output.get('engine')!r}")
    lights = solution.get("lights") or []
    check_one_light(lights, "solution")
    light = lights[0]
    if light.get("type") != "directional":
        raise EmitError("rig lights[0]", f"--emit writes a Babylon.js module for a directional light (accepted: "
                        f"directional), got {light.get('type')!r}")
    maps = light.get("cascades") or []
    if len(maps) > 1:
        raise EmitError("lights[0].cascades", f"Babylon.js takes a custom matrix for one map only (accepted: 1 map), "
                        f"the solution has {len(maps)}: CascadedShadowGenerator's matrices are private")
    forward = (solution.get("convention") or {}).get("view_forward", "+Z")
    data = {"engine": "babylon", "babylon": BABYLON_VERSION, "method": solution.get("method"),
            "software": (solution.get("provenance") or {}).get("software"),
            "scene_hash": (solution.get("provenance") or {}).get("scene_hash"),
            "light": {k: light.get(k) for k in ("type", "usd_path")},
            "direction": _engine_direction(solution),
            "maps": [_map(m, forward) for m in maps]}
    return TEMPLATE.read_text().replace("@@BABYLON_VERSION@@", BABYLON_VERSION).replace(
        "@@SOLUTION@@", json.dumps(data, indent=1))


def _engine_direction(solution: dict) -> list | None:
    """The sun's direction in Babylon's frame (the module checks ctx.light against it): the resolved world
    direction through the preset's axes (solvers.conventions.ENGINE_PRESETS["babylon"]: x -> -x)."""
    d = next((l.get("direction") for l in (solution.get("resolved") or {}).get("lights") or []), None)
    return None if d is None else [-float(d[0]), float(d[1]), float(d[2])]


def _mat(flat) -> np.ndarray:
    return np.asarray(flat, dtype=np.float64).reshape(4, 4).T  # column-major 16 -> the column-vector matrix


def _map(smap: dict, forward: str) -> dict:
    where = "lights[0].cascades[0]"
    res = [int(v) for v in smap.get("resolution") or [0, 0]]
    if res[0] != res[1]:
        raise EmitError(f"{where}.resolution", f"Babylon.js's ShadowGenerator takes one mapSize (accepted: a square "
                        f"map), got {res[0]}x{res[1]}")
    depth = smap.get("depth") or {}
    mode = depth.get("mode")
    view, proj = _mat(smap["view_matrix"]), _mat(smap["projection_matrix"])
    clip = proj @ view
    warped = not np.allclose(proj[3], [0.0, 0.0, 0.0, 1.0])
    if mode not in ("linear", "hardware") or (mode == "hardware" and warped):
        raise EmitError(f"{where}.depth.mode", f"Babylon.js stores and compares the depth row before the divide by w "
                        f"(shadowMapVertexMetric.js, shadowsVertex.js), so a warped map's window depth has no route "
                        f"(accepted: linear, or hardware for an orthographic map), got {mode!r}")
    block = depth.get(mode) or {}
    for term in ZERO_TERMS:
        if float(block.get(term, 0.0) or 0.0) != 0.0:
            raise EmitError(f"{where}.depth.{mode}.{term}", _zero_term_reason(term, block[term]))
    if mode == "linear":
        near, far = float(block["near"]), float(block["far"])
        sign = 1.0 if forward == "+Z" else -1.0
        # D = (sign z_view - near) / (far - near) (docs/engines.md "Linear light-space depth"); clip z = 2 D - 1
        clip[2] = 2.0 * (sign * view[2] - near * np.array([0.0, 0.0, 0.0, 1.0])) / (far - near)
        clip[2, 3] -= 1.0
    w_min = _least_w(proj @ view, clip[3])
    if 0.0 < w_min < 1.0:  # x / w and y / w unchanged; |clip z| <= 1 <= w over the frustum: nothing inside it is clipped
        clip[[0, 1, 3]] /= w_min
    return {"transform": list(clip.T.ravel()), "resolution": res[0], "bias": float(block.get("constant", 0.0)),
            "mode": mode, "format": depth.get("format"), "warped": bool(warped)}


def _least_w(hardware_clip: np.ndarray, w_row: np.ndarray) -> float:
    """The least w over the map's frustum: at one of its eight corners (w is affine), the NDC cube's corners
    through the inverse of the map's own clip matrix."""
    inv = np.linalg.inv(hardware_clip)
    corners = np.array([[x, y, z, 1.0] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) @ inv.T
    pts = corners / corners[:, 3:4]
    return float(np.min(pts @ w_row))
