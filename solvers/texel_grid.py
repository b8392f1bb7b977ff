"""The world-fixed texel grid of a directional map (solvers.path_optimize's module doc, "The world-fixed
grid"): a cascade's canonical projective part `Grid` in a light view anchored at a fixed world point
(anchored_view, grid_of, blend), the ladder of scale levels 2^(j / LADDER_STEPS) (tight_levels), and a
frame's map fitted on a held grid with its box snapped to whole texels (fit_on_grid)."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .fitting import PAD_TEXELS, extent_floor, to_view
from .shadow_map import ShadowMap

LADDER_STEPS = 64  # scale levels per octave: one step is 2^(1/64) - 1 = 1.1% of the map's size per axis
LEVEL_SLACK = 4  # steps a held level may exceed the tightest one before the level follows the receivers
LEVEL_HEADROOM = 1  # a new level is this many steps coarser than the tightest (room for the receivers to grow)


@dataclass
class Grid:
    """One cascade's held canonical part: `view` a world -> light view anchored at a fixed world point
    (its rotation from the map it came from), `G` (3, 4) the rows s', t', w acting on that view's
    homogeneous coordinates (no z coefficient), `levels` the scale levels (s, t) of the last fit (None:
    not fitted yet), `resolution` the map's texels."""

    view: np.ndarray
    G: np.ndarray
    resolution: tuple[int, int]
    levels: tuple[int, int] | None = None
    x: list | None = None  # the per-frame optimizer's (phi, u) it came from: the next frame's warm start

    def to_json(self) -> dict:
        return {"view": self.view.tolist(), "canonical": self.G.tolist(), "resolution": list(self.resolution),
                "levels": None if self.levels is None else list(self.levels), "x": self.x}

    @classmethod
    def from_json(cls, d: dict) -> "Grid | None":
        try:
            view, G = np.asarray(d["view"], dtype=np.float64), np.asarray(d["canonical"], dtype=np.float64)
            res = tuple(int(v) for v in d["resolution"])
        except (KeyError, TypeError, ValueError):
            return None
        if view.shape != (4, 4) or G.shape != (3, 4) or not (np.isfinite(view).all() and np.isfinite(G).all()):
            return None
        lv = d.get("levels")
        x = d.get("x")
        return cls(view, G, (res[0], res[1]), None if lv is None else (int(lv[0]), int(lv[1])),
                   [float(v) for v in x] if isinstance(x, list) and len(x) == 2 else None)

    def world(self) -> np.ndarray:
        """(3, 4): the canonical rows acting on world homogeneous coordinates."""
        return self.G @ self.view

    def in_view(self, view: np.ndarray) -> np.ndarray:
        """G expressed on another light view's coordinates (same world rows)."""
        return self.G @ self.view @ np.linalg.inv(view)


def anchored_view(rotation: np.ndarray, light, casters_bounds) -> np.ndarray:
    """World -> light view with the rotation of `rotation` (a view matrix; rows: right, up, -light) and the
    eye at a world-fixed point: the scene bounds' centre moved back along the light beyond the bounds (every
    scene point in front), so the same light and scene give the same frame whatever the camera."""
    lo, hi = (np.asarray(b, dtype=np.float64) for b in casters_bounds)
    d = np.asarray(light.direction, dtype=np.float64)
    d = d / np.linalg.norm(d)
    eye = 0.5 * (lo + hi) - d * (0.5 * float(np.linalg.norm(hi - lo)) + 1.0)
    V = np.eye(4)
    V[:3, :3] = np.asarray(rotation, dtype=np.float64)[:3, :3]
    V[:3, 3] = -V[:3, :3] @ eye
    return V


def _normalised(G: np.ndarray) -> np.ndarray:
    """G scaled to unit Frobenius norm (s', t', w keep their ratios: the same canonical coordinates)."""
    return G / max(float(np.linalg.norm(G)), 1e-300)


def grid_of(smap: ShadowMap, light, casters_bounds) -> Grid | None:
    """The canonical part of a directional map (any of this service's: focused, LiSPSM, optimized), or None
    for a map that is not a light-plane projective map (a log warp, a cube face, a z-dependent w row)."""
    if smap.face is not None or smap.log_warp is not None:
        return None
    V = anchored_view(smap.view, light, casters_bounds)
    M = smap.projection @ smap.view @ np.linalg.inv(V)
    G = M[[0, 1, 3]]
    scale = float(np.abs(G).max())
    if not scale > 0 or float(np.abs(G[:, 2]).max()) > 1e-9 * scale:
        return None
    G = G.copy()
    G[:, 2] = 0.0
    return Grid(V, _normalised(G), (int(smap.resolution[0]), int(smap.resolution[1])))


def blend(held: Grid, fresh: Grid, alpha: float) -> Grid:
    """The canonical part alpha of the way from `held` to `fresh` (entries of the normalised rows in the held
    view, the fresh one's sign aligned; Grid.in_view): a limited step of the warp and the affine directions."""
    Gf = _normalised(fresh.in_view(held.view))
    Gh = _normalised(held.G)
    if float(np.sum(Gf * Gh)) < 0:
        Gf = -Gf
    G = _normalised((1.0 - alpha) * Gh + alpha * Gf)
    G[:, 2] = 0.0
    return Grid(held.view, G, fresh.resolution, None, fresh.x)


def _level(a_max: float, held: int | None) -> int:
    """The ladder level for an NDC scale of at most a_max: the held level while it is at most LEVEL_SLACK steps
    below the largest 2^(j/LADDER_STEPS) <= a_max; a new grid's LEVEL_HEADROOM steps below that one."""
    j = math.floor(LADDER_STEPS * math.log2(a_max) + 1e-9)
    if held is None:
        return j - LEVEL_HEADROOM
    if j - LEVEL_SLACK <= held <= j:
        return held
    # the receivers shrank past the slack: the tightest level (room to shrink LEVEL_SLACK more); they grew
    # past the held level: LEVEL_SLACK steps coarser (room to grow as much): one change per band of the trend
    return j if j > held else j - LEVEL_SLACK


def _canonical(grid: Grid, pts: np.ndarray):
    """(light-view points, w, [X, Y]) of world points on the grid's canonical part, or None when a point is
    not in front of the warp's centre (w <= 0) or a coordinate is not finite."""
    v = to_view(grid.view, pts)
    ph = np.column_stack([v, np.ones(len(v))])
    with np.errstate(over="ignore", invalid="ignore"):  # a client's previous state may hold any finite numbers
        w = ph @ grid.G[2]
        ok = len(w) and np.isfinite(w).all() and float(w.min()) > 1e-12 * max(float(np.abs(w).max()), 1e-300)
        if ok:
            cs = [(ph @ grid.G[i]) / w for i in (0, 1)]
            ok = all(np.isfinite(c).all() for c in cs)
    return (v, w, cs) if ok else None


def _a_max(lo: float, hi: float, n: float) -> float:
    """The largest NDC scale whose map of n texels holds [lo, hi] with PAD_TEXELS texels and the snap's half
    texel on each side."""
    size = max(hi - lo, extent_floor(max(abs(lo), abs(hi))))
    return 2.0 * max(n - 2.0 * PAD_TEXELS - 1.0, 1.0) / (n * size)


def tight_levels(grid: Grid, fit_pts: np.ndarray) -> tuple[int, int] | None:
    """The finest ladder level per axis at which the grid holds `fit_pts` (fit_on_grid's box), or None."""
    got = _canonical(grid, fit_pts)
    if got is None:
        return None
    out = []
    for i in (0, 1):
        a = _a_max(float(got[2][i].min()), float(got[2][i].max()), float(grid.resolution[i]))
        out.append(math.floor(LADDER_STEPS * math.log2(a) + 1e-9))
    return out[0], out[1]


def fit_on_grid(grid: Grid, fit_pts: np.ndarray, corners: np.ndarray, held_levels=None, depth_origin=None,
                force_levels=None, depth_frame=None):
    """(map, levels) of the grid refit (without `held_levels`, a new grid: its s', t' rows are first rescaled
    in place so that the ladder's level 0 is this frame's tight scale) to `fit_pts` (world points the map must contain: the receivers'
    light-plane hull and depth extremes and the samples) or None when a point is not in front of the
    warp's centre (w <= 0). Per axis: the box of the canonical coordinates, a scale on the ladder at most
    the box's (padded PAD_TEXELS texels and half a texel for the snap on each side), the offset snapped so
    that canonical 0 is a texel corner; depth as solvers.optimize.Problem's fit (the fit points and the scene
    corners at the fit points' extreme w, a caster on a receiver's light ray having its w), the stored depth
    (z - z0) / w measured from `depth_origin`'s light-view depth z0 (the camera: the per-frame optimizer's
    depth, whose view is centred there; from the far anchor, z / w would spread over e^u times the range).
    `force_levels`: these levels or None when they do not hold the points (a segment's level, segment_pass);
    `depth_frame` (z0, near, far, light_depth): that depth or None when it does not hold this frame's range
    (a segment's depth: the returned map's depth_frame is what it used)."""
    got = _canonical(grid, fit_pts)
    if got is None:
        return None
    v, w, cs = got
    rows = []
    levels = []
    for i in (0, 1):
        c = cs[i]
        lo, hi = float(c.min()), float(c.max())
        n = float(grid.resolution[i])
        a_max = _a_max(lo, hi, n)
        if held_levels is None and force_levels is None:  # a new grid: its row rescaled so that level 0 is the tight scale, and recentred so
            # that canonical 0 (the pivot of later level changes) is the box's centre
            k = a_max * (1.0 - 1e-6)
            mid = 0.5 * (lo + hi)
            grid.G[i] = k * (grid.G[i] - mid * grid.G[2])
            c, lo, hi, a_max = k * (c - mid), k * (lo - mid), k * (hi - mid), 1.0 / (1.0 - 1e-6)
        if force_levels is not None:  # a segment's one level (segment_pass): it must hold this frame's points
            j = int(force_levels[i])
            if 2.0 ** (j / LADDER_STEPS) > a_max:
                return None
        else:
            j = _level(a_max, None if held_levels is None else held_levels[i])
        a = 2.0 ** (j / LADDER_STEPS)
        b = -a * 0.5 * (lo + hi)
        b = round((b + 1.0) * n / 2.0) * 2.0 / n - 1.0  # canonical 0 on a texel corner (at most half a texel)
        rows.append(a * grid.G[i] + b * grid.G[2])
        levels.append(j)
    if depth_frame is not None:
        z0 = float(depth_frame[0])
    else:
        z0 = 0.0 if depth_origin is None else float(to_view(grid.view, np.asarray(depth_origin, float)[None])[0, 2])
    zc = (v[:, 2] - z0) / w
    cz = to_view(grid.view, corners)[:, 2] - z0
    wl, wh = float(w.min()), float(w.max())
    z_hi = max(float(zc.max()), float(cz.max()) / wl, float(cz.max()) / wh)
    z_lo = min(float(zc.min()), float(cz.min()) / wl, float(cz.min()) / wh)
    near, far = -z_hi, -z_lo
    span = max(far - near, 1e-9 * max(abs(near), abs(far), 1.0))
    n_, f_ = near - 0.01 * span, far + 0.01 * span
    d = -v[:, 2]
    dc = -to_view(grid.view, corners)[:, 2]
    light_depth = (float(min(d.min(), dc.min())), float(d.max()))
    if depth_frame is not None:  # a segment's held depth: it must hold this frame's range
        if near < depth_frame[1] or far > depth_frame[2]:
            return None
        n_, f_, light_depth = float(depth_frame[1]), float(depth_frame[2]), tuple(depth_frame[3])
    ez = np.array([0.0, 0.0, 1.0, 0.0])
    alpha = -2.0 / (f_ - n_)
    P = np.vstack([rows[0], rows[1], alpha * (ez - z0 * np.array([0.0, 0.0, 0.0, 1.0])) - ((f_ + n_) / (f_ - n_)) * grid.G[2],
                   grid.G[2]])
    gw = grid.G[2, :2]
    grad = float(np.linalg.norm(gw))
    ext = float(np.ptp(v[:, :2], axis=0).max()) if len(v) > 1 else 0.0
    warped = grad * ext > 1e-6 * float(np.mean(w))
    smap = ShadowMap(grid.view.copy(), P, grid.resolution, light_depth=light_depth,
                     warp_kind="perspective" if warped else "none",
                     n_prime=float(wl / grad) if warped else None)
    smap.snapped = True
    smap.depth_frame = (z0, n_, f_, light_depth)  # what a segment holds (segment_pass)
    return smap, (levels[0], levels[1])
