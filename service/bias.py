"""The depth bias of a light's maps and the misclassification the engine's depth test predicts for them.

`shadow.bias` "fitted" (default): each map's depth block is chosen by solvers.bias_fit at the coarse pass's
light-facing receivers (renderers.depth_probe: the engine's test there, exactly as `evaluate` runs it); the
rig's `shadow.depth` pins any term. "rule": the fixed rule every fit attaches (solvers.depth_modes), what
an engine user sets by hand. Either way the prediction is the same probe's count of wrong answers, in the
rig's full-resolution pixels: each coarse receiver stands for (W H) / (w h) of them.
"""
from __future__ import annotations

import numpy as np

from ..renderers.coarse import CoarseBuffers, subpixel_receivers
from ..renderers.depth_probe import depth_probe
from ..renderers.ray_scene import RayScene
from ..solvers.bias_fit import bias_target, fit_bias, probe_wrong
from ..solvers.depth_modes import linear_range
from ..solvers.shadow_map import ShadowMap

BIAS_CHOICES = ("fitted", "rule")
REFINE = 3  # sub-pixel samples per side in the coarse pixels refine_cells picks
BLEND_FRACTION = 0.1  # a cascade blends into the next over the last 10% of its depth range
PREDICTION_MODEL = ("the engine's depth test (evaluate --depth solution) at the coarse pass's light-facing receivers "
                    "(3 x 3 sub-pixel samples along shadow boundaries and object edges), each standing for its share "
                    "of the rig's full-resolution pixels; wrongly lit + wrongly shadowed; a fitted constant is scored "
                    "cross-fitted (two folds, each with the constant fitted on the other)")


def set_blend_bands(maps: list[ShadowMap]) -> None:
    """Each cascade but the last blends into the next over the last BLEND_FRACTION of its depth range (engines:
    three.js CSM, Bevy's overlap 0.2); none for single maps and cube faces."""
    for smap in maps:
        lo_z, hi_z = smap.split
        if smap.face is None and len(maps) > 1 and smap is not maps[-1]:
            smap.blend_band = (float(hi_z - BLEND_FRACTION * (hi_z - lo_z)), float(hi_z))
        else:
            smap.blend_band = None


def refine_cells(buffers: CoarseBuffers, light_index: int) -> np.ndarray:
    """The coarse receivers the probe samples finer: on a shadow boundary (the light's boundary mask) or next to
    another object or the background (a 4-neighbour with another prim_id: contacts, creases between objects,
    silhouettes), dilated by one pixel."""
    lb = buffers.lights[light_index]
    mask = buffers.hit & lb.facing & lb.in_light
    prim = np.where(buffers.hit, buffers.prim_id, -1)
    p = np.pad(prim, 1, mode="edge")
    edge = np.zeros(prim.shape, bool)
    for q in (p[:-2, 1:-1], p[2:, 1:-1], p[1:-1, :-2], p[1:-1, 2:]):
        edge |= q != prim
    cells = lb.boundary | edge
    c = np.pad(cells, 1)
    cells = cells | c[:-2, 1:-1] | c[2:, 1:-1] | c[1:-1, :-2] | c[1:-1, 2:]
    return cells & mask


def receivers_of(rays: RayScene, light, buffers: CoarseBuffers, light_index: int):
    """(positions, normals, view depths, lit, pixels) of the probe's samples: the coarse pass's light-facing
    receivers on a checkerboard of the coarse pixels (each standing for two pixels' share), and in the pixels
    refine_cells picks REFINE x REFINE sub-pixel samples instead (renderers.coarse.subpixel_receivers); their exact visibility; the rig's full-resolution pixels
    each stands for ((W H) / (w h) per coarse pixel, shared by its samples)."""
    memo = buffers.__dict__.setdefault("_probe_receivers", {})  # the same samples for every candidate's maps
    if light_index not in memo:
        memo[light_index] = _receivers(rays, light, buffers, light_index)
    return memo[light_index]


def _receivers(rays: RayScene, light, buffers: CoarseBuffers, light_index: int):
    lb = buffers.lights[light_index]
    mask = buffers.hit & lb.facing & lb.in_light
    W, H = (int(v) for v in buffers.camera.resolution)
    per_cell = W * H / float(buffers.width * buffers.height)
    fine = refine_cells(buffers, light_index)
    jj, ii = np.indices(mask.shape)
    plain = mask & ~fine & ((jj + ii) % 2 == 0)  # away from edges: every other pixel (a checkerboard), twice the weight
    cell, pos, nrm, dep, vis = subpixel_receivers(rays, buffers.camera, light, fine, REFINE)
    a = np.concatenate([np.full(int(plain.sum()), 2.0 * per_cell), np.full(len(cell), per_cell / REFINE ** 2)])
    return (np.concatenate([buffers.position[plain], pos]),
            np.concatenate([np.asarray(buffers.normal[plain], np.float64), nrm]),
            np.concatenate([buffers.depth[plain].astype(np.float64), dep]),
            np.concatenate([lb.visible[plain], vis]), a)


def choose_bias(rays: RayScene, light, maps: list[ShadowMap], buffers: CoarseBuffers, light_index: int,
                shadow: dict, engine: str | None) -> dict:
    """Set each map's depth block (module doc) and return the light's prediction: {misclassified_pixels,
    wrongly_lit_pixels, wrongly_shadowed_pixels, outside_pixels, bias, model}."""
    set_blend_bands(maps)
    choice = shadow.get("bias", "fitted")
    pinned = {k: v for k, v in (shadow.get("depth") or {}).items() if v is not None}
    target = bias_target(engine)
    pos, nrm, depth, lit, a = receivers_of(rays, light, buffers, light_index)
    offset = float(pinned.get("normal_offset") or 0.0)
    rule_modes = sorted({m.depth["mode"] for m in maps if isinstance(m.depth, dict)}) or ["hardware"]
    if choice == "rule":
        modes = rule_modes
    elif pinned.get("mode"):
        modes = [pinned["mode"]]
    else:  # the rule's reasons for linear (a log warp, window z crowded in float32) hold for a fitted bias too
        modes = [m for m in rule_modes if m in target["modes"]] or [target["modes"][0]]
    probes = {mode: depth_probe(rays, light, maps, pos, nrm, depth, mode, offset) for mode in modes}
    if choice == "fitted" and maps:
        fits = fit_bias(probes, lit, a, len(maps), engine, pinned)
        for smap, fit in zip(maps, fits):
            _fitted_block(smap, fit, target["format"], target.get("constant_side"))
    fmt = maps[0].depth.get("format", "float32") if maps and isinstance(maps[0].depth, dict) else "float32"
    own = [m.depth["mode"] for m in maps]  # evaluate --depth solution: each map in its own mode
    probe = probes[own[0]] if len(set(own)) == 1 and own[0] in probes else depth_probe(rays, light, maps, pos, nrm,
                                                                                        depth, own, offset)
    wrong = probe_wrong(probe, lit, a, [m.depth[md] for m, md in zip(maps, own)], fmt)
    if choice == "fitted" and maps:  # the fitted constant's optimism on its own receivers (bias_fit.cross_fitted)
        wrong["wrongly_lit"] += sum(f.optimism[0] for f in fits)
        wrong["wrongly_shadowed"] += sum(f.optimism[1] for f in fits)
    return {"misclassified_pixels": wrong["wrongly_lit"] + wrong["wrongly_shadowed"],
            "wrongly_lit_pixels": wrong["wrongly_lit"], "wrongly_shadowed_pixels": wrong["wrongly_shadowed"],
            "outside_pixels": wrong["outside"], "bias": choice, "model": PREDICTION_MODEL}


def _fitted_block(smap: ShadowMap, fit, depth_format: str, constant_side: str | None = None) -> None:
    """The map's depth block from the fit: both modes' terms (each mode's own best), the chosen mode, the format,
    and where the constant acts when the target says (solvers.engine_depth_test.CONSTANT_SIDES)."""
    block = dict(smap.depth) if isinstance(smap.depth, dict) else {}
    for mode, (c, k, m, wrong) in fit.per_mode.items():
        entry = dict(block.get(mode) or {})
        # no clamp: 1, the whole stored range (the same stored depth: the sum is clamped to [0, 1] anyway)
        entry.update(constant=float(c), slope=0.0, normal_offset=fit.normal_offset, slope_scaled=float(k),
                     slope_clamp=1.0 if m is None else min(float(m), 1.0))
        if mode == "linear":
            entry["near"], entry["far"] = linear_range(smap)
        if constant_side:
            entry["constant_side"] = constant_side
        block[mode] = entry
    block["mode"] = fit.mode
    block["format"] = depth_format
    block["chosen_by"] = "fitted"
    block["reason"] = (f"{fit.mode}: of the bias terms the output engine applies, these predict the fewest wrong pixels "
                       f"at the coarse receivers ({fit.wrong:.0f} full-resolution pixels)")
    smap.depth = block
