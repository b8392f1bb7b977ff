"""The engine's depth test in NumPy, on numbers per texel and per receiver: what the light pass stores
(stored_with_bias, rounded to the depth buffer's format) and the lookup's comparison (engine_shadowed).
renderers.shadow_map_rays (the light pass over whole maps) and renderers.depth_probe (at sample points)
feed it; solvers.bias_fit chooses the bias with it; renderers.depth_tests' Dr.Jit lookup is checked
against it (tests/test_depth_probe.py).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

DZ_CAP = 1e30  # DZ of a caster seen edge-on (its plane parallel to a neighbour's ray): the clamp m applies

# The depth buffer's format: what the light pass's stored depth is rounded to. float32: D32F (the generic
# presets); unorm24 / unorm16: normalized fixed point with 2^bits - 1 steps (OpenGL 4.6 §2.3.5.2, D3D11 UNORM
# conversion: round(D (2^bits - 1))): three.js's WebGL depth texture (DEPTH24), Filament's DEPTH16 (ShadowMap),
# Godot's and URP's 16-bit shadow atlases by default (../shared/reference/engine-settings.md). float16: IEEE half
# precision (round to nearest), Babylon.js's default shadow map, a half-float colour target holding the depth metric
# (@babylonjs/core 9.35 Lights/Shadows/shadowGenerator.js _createInstance: TEXTURETYPE_HALF_FLOAT when the device
# renders and filters half floats).
DEPTH_FORMATS = ("float32", "unorm24", "unorm16", "float16")
FLOAT_FORMATS = {"float32": np.float32, "float16": np.float16}
# Where a depth block's constant acts (its mode entry's `constant_side`): "receiver" (default), subtracted from the
# receiver's depth at the lookup; "caster", added to the caster's stored depth before the buffer rounds it (Babylon.js:
# Shaders/ShadersInclude/shadowMapVertexMetric.js adds its bias to the stored metric; with a half-float map the
# rounding then sees D + constant: quantize(D + c) is not quantize(D) + c).
CONSTANT_SIDES = ("receiver", "caster")


def unorm_steps(depth_format: str) -> int | None:
    """2^bits - 1 of a normalized fixed-point format, None for a floating-point one (FLOAT_FORMATS)."""
    if depth_format not in DEPTH_FORMATS:
        raise ValueError(f"depth format must be one of {', '.join(DEPTH_FORMATS)}, got {depth_format!r}")
    return {"unorm24": (1 << 24) - 1, "unorm16": (1 << 16) - 1}.get(depth_format)


def quantize_depth(D: np.ndarray, depth_format: str = "float32") -> np.ndarray:
    """Stored depth rounded as the depth buffer stores it (DEPTH_FORMATS), as float64."""
    steps = unorm_steps(depth_format)
    D = np.asarray(D, dtype=np.float64)
    if steps is None:
        return D.astype(FLOAT_FORMATS[depth_format]).astype(np.float64)
    return np.rint(D * steps) / steps


def stored_with_bias(D: np.ndarray, dz: np.ndarray, d_occ: np.ndarray, prim: np.ndarray, k: float, m: float,
                     depth_format: str = "float32", caster_constant: float = 0.0) -> np.ndarray:
    """What the light pass stores per texel: clamp(D + min(k DZ, m) + caster_constant, 0, 1) for a hit caster (k =
    slope_scaled, m = slope_clamp: OpenGL 4.6 §14.6.5 polygon offset, D3D11 slope-scaled depth bias;
    caster_constant: a caster-side constant, CONSTANT_SIDES), 0 for a pancaked one, 1 where nothing is hit; rounded
    to the depth buffer's format (quantize_depth)."""
    hit = np.isfinite(np.asarray(d_occ, float))
    faced = hit & (np.asarray(prim) >= 0)
    with np.errstate(all="ignore"):
        off = np.minimum(k * np.minimum(dz, DZ_CAP), m) if k else np.zeros(len(D))
        stored = np.where(faced, np.clip(D + off + caster_constant, 0.0, 1.0), np.where(hit, 0.0, 1.0))
    return quantize_depth(stored, depth_format)



def engine_shadowed(d_rec: np.ndarray, stored: np.ndarray, constant: float, slope: float = 0.0,
                    tan_psi: np.ndarray | None = None) -> np.ndarray:
    """The lookup's comparison (renderers.depth_tests.DEPTH_RULE_ENGINE): shadowed iff
    D_rec - (constant + slope min(tan psi, 10)) > stored."""
    bias = constant + (slope * tan_psi if slope and tan_psi is not None else 0.0)
    return np.asarray(d_rec) - bias > np.asarray(stored)


@dataclass
class DepthProbe:
    """The engine depth test's inputs at sample points (renderers.depth_probe), in one depth mode: per point
    the serving map (-1: none), whether the serving map contains it (s, t and D_rec in [0, 1]), D_rec
    (the receiver's stored-depth value), and of its texel's centre ray: d_occ (inf: nothing hit, 0:
    pancaked), prim (-1: none or pancaked), D(P) and DZ (renderers.shadow_map_rays.caster_depth)."""

    mode: str
    map_index: np.ndarray
    inside: np.ndarray
    d_rec: np.ndarray
    d_cast: np.ndarray
    dz: np.ndarray
    d_occ: np.ndarray
    prim: np.ndarray
    tan_psi: np.ndarray

    def stored(self, k: float, m: float, depth_format: str, caster_constant: float = 0.0) -> np.ndarray:
        return stored_with_bias(self.d_cast, self.dz, self.d_occ, self.prim, k, m, depth_format, caster_constant)
