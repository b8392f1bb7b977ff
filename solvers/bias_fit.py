"""The bias chooser: each map's depth block chosen to minimize the misclassification the engine's depth test
predicts at the coarse pass's receivers (DESIGN.md, "Metric": bias errors are part of the score).

Input: per depth mode a DepthProbe (solvers.engine_depth_test; renderers.depth_probe casts its rays) at
the light-facing receivers the camera sees, each with its exact ray-traced visibility and the
full-resolution pixels it stands for (a_i). With a caster-side slope-scaled term (k, clamp m) fixed, the
engine shadows a receiver iff its margin D_rec - stored(k, m) exceeds the constant c
(engine_depth_test.engine_shadowed), so the weighted count of wrong answers is a step function of c:

    wrong(c) = sum_i a_i [margin_i > c] [lit_i] + sum_i a_i [margin_i <= c] [shadowed_i]

(the first sum: acne, wrongly shadowed; the second: leaks, and aliasing where the texel's ray meets another
surface than the receiver's occluder: wrongly lit). fit_constant finds its least value over c >= 0 exactly
by one sort, and takes c at the geometric middle of the best interval (the interval between two sampled
margins holds the unsampled pixels' margins too; their scale spans decades). Receivers outside every map
are lit whatever the bias. The search runs over the target's modes and slope terms (BIAS_TARGETS: what the
output engine can apply) and keeps the least count; terms the rig pins (`shadow.depth`) are kept.

Targets (output.engine; ../shared/reference/engine-settings.md): the generic presets (none, opengl, d3d,
vulkan) apply every term per map with a D32F buffer (glPolygonOffsetClamp / D3D11 DepthBias,
SlopeScaledDepthBias, DepthBiasClamp; a custom pass can write linear depth). three.js: a receiver-side
constant per shadow (LightShadow.bias, normalized depth; no slope term in its light pass), a 24-bit depth
buffer, window z only. Engines whose bias is one setting per light that they scale per cascade themselves
(Godot, Unity URP, Unreal, Bevy, Filament) get one constant for all the light's maps, in stored depth (the
emitted settings convert it), with the slope term they apply fixed (Filament polygonOffsetSlope 2; Unreal
and URP a fixed slope bias; Godot and Bevy none) and their buffer's format (16-bit for Filament, Godot and
URP by default, 32-bit float for Unreal and Bevy). Babylon.js (9.35, one map through
ShadowLight.customProjectionMatrixBuilder): a constant per map (ShadowGenerator.bias, added to the caster's stored
metric), no slope term in that path, a half-float map (Lights/Shadows/shadowGenerator.js), and the linear mode only:
Babylon stores and compares the depth row's value before the divide by w (Shaders/ShadersInclude/
shadowMapVertexMetric.js, shadowsVertex.js: (clip z + 1) / 2 interpolated as a varying), so the emitted module puts
the linear depth in the projection's depth row (service/emit_babylon.py); its normalBias moves casters, not
receivers, so the receivers' normal offset stays 0 (the module refuses another). Its constant is added to the
caster's metric before the half float rounds it (engine_depth_test.CONSTANT_SIDES), so the count is no longer a step
function of margins fixed in advance: the constant fitted as a receiver-side one is refined over CASTER_GRID times it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .engine_depth_test import DepthProbe, engine_shadowed

SLOPE_GRID = (0.0, 1.0, 2.0)  # slope_scaled factors tried where the target applies its own
CLAMP_PERCENTILES = (None, 90.0)  # slope_clamp: none, or that percentile of k DZ over the map's receivers

BIAS_TARGETS: dict[str | None, dict] = {
    None: {"modes": ("hardware", "linear"), "slopes": SLOPE_GRID, "clamps": CLAMP_PERCENTILES, "per_map": True,
           "format": "float32"},
    "three": {"modes": ("hardware",), "slopes": (0.0,), "clamps": (None,), "per_map": True, "format": "unorm24"},
    "filament": {"modes": ("hardware",), "slopes": (2.0,), "clamps": (None,), "per_map": False, "format": "unorm16"},
    "godot": {"modes": ("hardware",), "slopes": (0.0,), "clamps": (None,), "per_map": False, "format": "unorm16"},
    "unity": {"modes": ("hardware",), "slopes": (2.5,), "clamps": (None,), "per_map": False, "format": "unorm16"},
    "unreal": {"modes": ("hardware",), "slopes": (1.0,), "clamps": (None,), "per_map": False, "format": "float32"},
    "bevy": {"modes": ("hardware",), "slopes": (0.0,), "clamps": (None,), "per_map": False, "format": "float32"},
    "babylon": {"modes": ("linear",), "slopes": (0.0,), "clamps": (None,), "per_map": True, "format": "float16",
                "constant_side": "caster"},
}
for _generic in ("opengl", "d3d", "vulkan"):
    BIAS_TARGETS[_generic] = BIAS_TARGETS[None]
CASTER_GRID = tuple(2.0 ** (i / 4) for i in range(-8, 9))  # a caster-side constant: these multiples of the fitted one
PINNABLE = ("mode", "constant", "slope_scaled", "slope_clamp", "normal_offset")


def bias_target(engine: str | None) -> dict:
    if engine not in BIAS_TARGETS:
        raise ValueError(f"output.engine must be one of {', '.join(k for k in BIAS_TARGETS if k)}, got {engine!r}")
    return BIAS_TARGETS[engine]


def fit_constant(margin: np.ndarray, lit: np.ndarray, a: np.ndarray, lo: float = 0.0) -> tuple[float, float]:
    """(c, wrong(c)): the least weighted count of wrong answers over c >= lo (module doc), c at the geometric
    middle of the best interval between sampled margins (the arithmetic one where it starts at or below 0;
    twice the largest margin, or lo + 1e-7, past the last).

    Only margins in (lo, L] can change with c, L the largest margin of a lit receiver: at or below lo a
    receiver is lit for every c (wrong if shadowed), and past L raising c only adds leaks, so the best c is
    at most L, where every margin above it is a shadowed receiver answered right. Those few are sorted."""
    margin = np.asarray(margin, float)
    lit = np.asarray(lit, bool)
    a = np.asarray(a, float)
    ok = np.isfinite(margin)
    # a non-finite margin: +inf (stored 0: a pancaked caster) is shadowed at every c, -inf / NaN never
    always = np.sum(a[~ok & (margin > 0) & lit]) + np.sum(a[~ok & ~(margin > 0) & ~lit])
    margin, lit, a = margin[ok], lit[ok], a[ok]
    always += float(np.sum(a[(margin <= lo) & ~lit]))  # lit by the engine at every c >= lo, truly shadowed
    top = float(np.max(margin[lit])) if lit.any() else lo
    above = margin > max(top, lo)
    keep = (margin > lo) & ~above
    if above.any():  # the first margin past L closes the last interval
        keep[np.flatnonzero(above)[np.argmin(margin[above])]] = True
    m, L, w = margin[keep], lit[keep], a[keep]
    order = np.argsort(m, kind="stable")
    m, L, w = m[order], L[order], w[order]
    n = len(m)
    # cost[j]: exactly the first j (sorted) at or below c: shadowed ones among them wrong (lit), lit ones above wrong
    shadow_below = np.concatenate([[0.0], np.cumsum(np.where(L, 0.0, w))])
    lit_above = np.sum(np.where(L, w, 0.0)) - np.concatenate([[0.0], np.cumsum(np.where(L, w, 0.0))])
    cost = shadow_below + lit_above
    cost[1:n][m[1:] <= m[:-1]] = np.inf  # no c separates equal margins
    j = int(np.argmin(cost))
    left = max(lo, float(m[j - 1])) if j > 0 else lo
    if j < n:
        right = float(m[j])
        c = math.sqrt(left * right) if left > 0 and right > 0 else 0.5 * (left + right) if right > left else left
    else:
        c = max(2.0 * left, lo + 1e-7) if left > 0 else lo + 1e-7
    return float(c), float(cost[j] + always)


FOLD_BLOCK = 16  # cross-fitting folds alternate in blocks of this many consecutive receivers (a refined pixel's)


def cross_fitted(margin: np.ndarray, lit: np.ndarray, a: np.ndarray) -> tuple[float, float]:
    """(wrongly lit, wrongly shadowed) that a constant fitted without each receiver gets there: two folds
    (alternate blocks of FOLD_BLOCK receivers), each scored with the constant fit_constant finds on the other.
    A count of wrong answers scored on the receivers the constant was fitted to is optimistic; this one is
    not (the prediction uses it for a fitted constant)."""
    fold = (np.arange(len(margin)) // FOLD_BLOCK) % 2 == 1
    wl = ws = 0.0
    for f in (False, True):
        train, test = fold != f, fold == f
        if not train.any() or not test.any():
            continue
        c, _ = fit_constant(margin[train], lit[train], a[train])
        shadowed = margin[test] > c
        wl += float(np.sum(a[test][~shadowed & ~lit[test]]))
        ws += float(np.sum(a[test][shadowed & lit[test]]))
    return wl, ws


@dataclass
class BiasChoice:
    """One map's (or a light's) fitted terms and the count they predict."""

    mode: str
    constant: float
    slope_scaled: float
    slope_clamp: float | None
    wrong: float
    normal_offset: float = 0.0
    per_mode: dict = field(default_factory=dict)  # mode -> (constant, slope_scaled, slope_clamp, wrong)
    optimism: tuple = (0.0, 0.0)  # (wrongly lit, wrongly shadowed) cross_fitted adds to the in-sample count (per group)


def _clamp_values(kdz: np.ndarray, clamps) -> list[float | None]:
    out = []
    finite = kdz[np.isfinite(kdz) & (kdz > 0)]
    for p in clamps:
        if p is None:
            out.append(None)
        elif len(finite):
            out.append(float(np.percentile(finite, p)))
    return out


def _best_terms(probe: DepthProbe, sel: np.ndarray, lit: np.ndarray, a: np.ndarray, target: dict, pinned: dict,
                depth_format: str):
    """(constant, k, m, wrong) of one mode over the receivers `sel` (served and inside)."""
    slopes = (float(pinned["slope_scaled"]),) if pinned.get("slope_scaled") is not None else target["slopes"]
    best = None
    for k in slopes:
        if "slope_clamp" in pinned:
            clamps = [pinned["slope_clamp"]]
        else:
            clamps = _clamp_values(k * probe.dz[sel], target["clamps"]) if k else [None]
        for m in clamps:
            stored = probe.stored(k, np.inf if m is None else m, depth_format)[sel]
            margin = probe.d_rec[sel] - stored
            if target.get("constant_side") == "caster":
                c, wrong = _caster_constant(probe, sel, lit, a, k, m, depth_format, pinned.get("constant"),
                                            None if pinned.get("constant") is not None else
                                            fit_constant(margin, lit[sel], a[sel])[0])
            elif pinned.get("constant") is not None:
                c = float(pinned["constant"])
                wrong = float(np.sum(a[sel] * (engine_shadowed(probe.d_rec[sel], stored, c) != ~lit[sel])))
            else:
                c, wrong = fit_constant(margin, lit[sel], a[sel])
            if best is None or wrong < best[3] - 1e-9:
                best = (c, float(k), m, wrong)
    return best


def _caster_constant(probe: DepthProbe, sel: np.ndarray, lit: np.ndarray, a: np.ndarray, k: float, m, depth_format: str,
                     pinned: float | None, fitted: float | None) -> tuple[float, float]:
    """(c, wrong) of a caster-side constant (CONSTANT_SIDES): the pinned one, or the best of CASTER_GRID times the
    receiver-side fit, each scored with c added before the rounding and a comparison without bias."""
    cands = [float(pinned)] if pinned is not None else [fitted * g for g in CASTER_GRID]
    best = None
    for c in cands:
        stored = probe.stored(k, np.inf if m is None else m, depth_format, c)[sel]
        wrong = float(np.sum(a[sel] * ((probe.d_rec[sel] > stored) != ~lit[sel])))
        if best is None or wrong < best[1] - 1e-9:
            best = (c, wrong)
    return best


def fit_bias(probes: dict[str, DepthProbe], lit: np.ndarray, pixels: np.ndarray, n_maps: int,
             engine: str | None = None, pinned: dict | None = None) -> list[BiasChoice]:
    """One BiasChoice per map (module doc), in the best of the probes' modes the target applies: `probes` per
    depth mode at the receivers, `lit` their exact
    visibility, `pixels` the full-resolution pixels each stands for; `pinned` the rig's shadow.depth terms."""
    target = bias_target(engine)
    pinned = dict(pinned or {})
    fmt = target["format"]
    modes = (pinned["mode"],) if pinned.get("mode") else tuple(m for m in target["modes"] if m in probes)
    lit = np.asarray(lit, bool)
    a = np.asarray(pixels, float)
    groups = [[k] for k in range(n_maps)] if target["per_map"] else [list(range(n_maps))]
    choices: list[BiasChoice | None] = [None] * n_maps
    for group in groups:
        per_mode = {}
        for mode in modes:
            p = probes[mode]
            sel = np.isin(p.map_index, group) & p.inside
            per_mode[mode] = _best_terms(p, sel, lit, a, target, pinned, fmt)
        mode = min(per_mode, key=lambda md: per_mode[md][3])
        c, k, m, wrong = per_mode[mode]
        optimism = (0.0, 0.0)
        if pinned.get("constant") is None:
            p = probes[mode]
            sel = np.isin(p.map_index, group) & p.inside
            margin = p.d_rec[sel] - p.stored(k, np.inf if m is None else m, fmt)[sel]
            cl, cs = cross_fitted(margin, lit[sel], a[sel])
            shadowed = margin > c
            il = float(np.sum(a[sel][~shadowed & ~lit[sel]]))
            ish = float(np.sum(a[sel][shadowed & lit[sel]]))
            optimism = (max(cl - il, 0.0), max(cs - ish, 0.0))
        for n, gk in enumerate(group):
            choices[gk] = BiasChoice(mode, c, k, m, wrong, float(pinned.get("normal_offset") or 0.0), per_mode,
                                     optimism if n == 0 else (0.0, 0.0))
    return choices


def probe_shadowed(probe: DepthProbe, terms: list[dict], depth_format: str) -> np.ndarray:
    """The engine's answer at the probe's receivers for each map's terms ({constant, slope, slope_scaled,
    slope_clamp, constant_side}: a depth block's mode entry): shadowed or not (receivers no map serves: lit)."""
    shadowed = np.zeros(len(probe.map_index), bool)
    for k, t in enumerate(terms):
        sel = (probe.map_index == k) & probe.inside
        if not sel.any():
            continue
        m = t.get("slope_clamp")
        caster = t.get("constant_side", "receiver") == "caster"  # engine_depth_test.CONSTANT_SIDES
        c = float(t.get("constant", 0.0))
        stored = probe.stored(float(t.get("slope_scaled") or 0.0), np.inf if m is None else float(m), depth_format,
                              c if caster else 0.0)
        shadowed[sel] = engine_shadowed(probe.d_rec[sel], stored[sel], 0.0 if caster else c,
                                        float(t.get("slope", 0.0)), probe.tan_psi[sel])
    return shadowed


def probe_wrong(probe: DepthProbe, lit: np.ndarray, pixels: np.ndarray, terms: list[dict], depth_format: str) -> dict:
    """probe_shadowed against the receivers' exact visibility `lit`: {"wrongly_lit", "wrongly_shadowed",
    "outside"} in pixels (outside: receivers no map serves, lit by the engine)."""
    lit = np.asarray(lit, bool)
    a = np.asarray(pixels, float)
    shadowed = probe_shadowed(probe, terms, depth_format)
    return {"wrongly_lit": float(np.sum(a[~shadowed & ~lit])), "wrongly_shadowed": float(np.sum(a[shadowed & lit])),
            "outside": float(np.sum(a[~probe.inside]))}
