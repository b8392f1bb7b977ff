"""The depth probe: the engine's depth test at sample points, with rays for the texels they fall in only.

`evaluate` renders every texel of every map and tests every screen pixel (renderers.ground_truth). The
solve needs the same test at the coarse pass's receivers, for each bias it considers: per point and
depth mode, `depth_probe` finds the serving map as the engine's lookup does (renderers.depth_tests:
engine_cascades, or the first cube face containing the point), the point's texel, and casts that texel's
centre ray (renderers.shadow_map_rays.texel_hits: the light pass's first hit, pancaked as evaluate
pancakes); caster_depth gives the caster's stored depth D(P) and its slope DZ. What the bias does with
them is arithmetic (solvers.engine_depth_test.DepthProbe, solvers.bias_fit), so every bias is scored
without casting again, and a point's classification is exactly evaluate's for the same maps and bias
(tests/test_depth_probe.py).
"""
from __future__ import annotations

import numpy as np

from ..solvers.depth_modes import MODES, linear_range, stored_depth, window_depth
from ..solvers.engine_depth_test import DepthProbe
from ..solvers.lights import Light
from ..solvers.shadow_map import ShadowMap
from .depth_tests import engine_cascades, tan_psi_clamped
from .ray_scene import RayScene
from .shadow_map_rays import caster_depth, texel_hits


def depth_probe(rs: RayScene, light: Light, maps: list[ShadowMap], positions: np.ndarray, normals: np.ndarray,
                view_depth: np.ndarray, mode: str | list[str], normal_offset: float = 0.0,
                pancake: bool = True) -> DepthProbe:
    """The engine depth test's inputs (DepthProbe) at world points with unit normals (on their light-facing
    side) and view depths in the camera the maps serve, in depth mode `mode` (solvers.depth_modes.MODES;
    linear with each map's own near and far, linear_range; a list: one mode per map, as evaluate --depth
    solution reads each map's own), the lookup point moved by `normal_offset` along the normal as the
    engine moves it."""
    per_mode = [mode] * len(maps) if isinstance(mode, str) else list(mode)
    for md in per_mode:
        if md not in MODES:
            raise ValueError(f"depth mode must be one of {', '.join(MODES)}, got {md!r}")
    X = np.asarray(positions, float).reshape(-1, 3)
    N = np.asarray(normals, float).reshape(-1, 3)
    Xp = X + float(normal_offset) * N
    n = len(X)
    d_rec = np.full(n, np.nan)
    contains, per_map = [], []
    for smap, md in zip(maps, per_mode):
        near, far = linear_range(smap) if md == "linear" else (None, None)
        s, t, z, cw = smap.map_coords(Xp)
        with np.errstate(invalid="ignore"):  # hardware: window z (depth_modes.hardware_depth) of these coordinates
            D = window_depth(z) if md == "hardware" else stored_depth(smap, md, Xp, near, far)
            ok = (cw > 0) & (s >= 0) & (s <= 1) & (t >= 0) & (t <= 1) & (D >= 0) & (D <= 1)
        ok &= np.isfinite(s) & np.isfinite(t) & np.isfinite(D)
        contains.append(ok)
        per_map.append((s, t, D, near, far))
    if maps and maps[0].face is None:
        idx = engine_cascades(maps, np.asarray(view_depth, float), contains)
    else:
        idx = np.full(n, -1, np.int64)
        for k in range(len(maps) - 1, -1, -1):
            idx[contains[k]] = k
    inside = np.zeros(n, bool)
    d_cast, dz, d_occ = np.zeros(n), np.zeros(n), np.full(n, np.inf)
    prim = np.full(n, -1, np.int64)
    for k, smap in enumerate(maps):
        sel = np.nonzero((idx == k) & contains[k])[0]
        inside[sel] = True
        s, t, D, near, far = per_map[k]
        d_rec[idx == k] = D[idx == k]
        if len(sel) == 0:
            continue
        w, h = smap.resolution
        i = np.clip(np.floor(s[sel] * w).astype(np.int64), 0, w - 1)
        j = np.clip(np.floor(t[sel] * h).astype(np.int64), 0, h - 1)
        texel, back = np.unique(j * w + i, return_inverse=True)  # one ray per texel
        ti, tj = texel % w, texel // w
        occ, pr = texel_hits(rs, light, smap, ti, tj, pancake)
        Dc, dzc = caster_depth(rs, smap, ti, tj, occ, pr, per_mode[k], near if near is not None else 0.0,
                               far if far is not None else 1.0)
        d_cast[sel], dz[sel], d_occ[sel], prim[sel] = Dc[back], dzc[back], occ[back], pr[back]
    return DepthProbe(mode if isinstance(mode, str) else "solution", np.asarray(idx, np.int64), inside, d_rec, d_cast, dz, d_occ, prim,
                      tan_psi_clamped(light, Xp, N))
