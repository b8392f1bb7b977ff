"""What a shadow setup is: per light, per cascade, a view matrix, a (possibly warped) projection,
an optional logarithmic warp, a resolution and ranges. One mapping from world points to map
coordinates, and its inverse (the light ray through a texel), used by everything else.

Conventions (see also solvers.conventions for what engines receive):
- Matrices act on column vectors. `view` maps world -> light view space, where the light looks
  down -Z (OpenGL style). `projection` maps light view -> canonical clip space: OpenGL NDC
  x, y, z in [-1, 1]; a perspective warp (LiSPSM, η) is folded into it.
- Map coordinates: s, t in [0, 1] with s = (x_ndc + 1)/2, t = (y_ndc + 1)/2 (t = 0 at the bottom);
  texels u = s * width, v = t * height. Depth: z_ndc in [-1, 1].
- The log warp (LogPSM, Lloyd et al. 2007 eq. 78) acts on t after the projection:
  t' = c0 * log(c1 * t + c2); it is not a matrix, so it is carried as parameters.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class LogWarp:
    """t' = c0 * log(c1 * t + c2) on the map's t axis (Lloyd et al. 2007 eq. 78)."""

    c0: float
    c1: float
    c2: float

    def apply(self, t):
        return self.c0 * np.log(self.c1 * t + self.c2)

    def derivative(self, t):
        return self.c0 * self.c1 / (self.c1 * t + self.c2)

    def invert(self, tw):
        # Exact inverse of the log step (digest note to eq. 84): t = (exp(t'/c0) - c2) / c1.
        return (np.exp(tw / self.c0) - self.c2) / self.c1

    def to_json(self) -> dict:
        return {"c0": self.c0, "c1": self.c1, "c2": self.c2, "axis": "t",
                "formula": "t' = c0 * log(c1 * t + c2), t = (y_ndc + 1) / 2 after the perspective divide"}


@dataclass
class ShadowMap:
    """One shadow map (one cascade, or one cube face)."""

    view: np.ndarray  # 4x4 world -> light view
    projection: np.ndarray  # 4x4 light view -> canonical clip (warp folded in)
    resolution: tuple[int, int]  # texels (width, height)
    split: tuple[float, float] = (0.0, float("inf"))  # camera view-depth range this map serves
    # near, far distance along the light's -Z axis covered by the map: the least and greatest light-view depth
    # over its frustum (frustum_depth_range; a warped map's frustum widens in depth towards its far end)
    light_depth: tuple[float, float] = (0.0, 1.0)
    warp_kind: str = "none"  # none | perspective | log
    eta: float | None = None  # Lloyd's η (-1 uniform, 0 LiSPSM, 1 PSM-like)
    n_prime: float | None = None  # the perspective warp's near distance n' (None: no warp)
    log_warp: LogWarp | None = None
    depth_bias: dict = field(default_factory=lambda: {"constant": 0.0, "slope": 0.0})
    face: str | None = None  # cube-map face (+x, -x, ...) for point lights
    snapped: bool = False  # texel grid fixed in the world (solvers.fitting.snap_to_texels)
    # What an engine stores and compares, with its bias (solvers.depth_modes.depth_block; None: not computed)
    depth: dict | None = None
    # [start, end] camera depth where this cascade blends into the next (read from a solution; the
    # engine-faithful evaluation switches cascades at its midpoint). Written by the service, not to_json.
    blend_band: tuple[float, float] | None = None

    @property
    def matrix(self) -> np.ndarray:
        """World -> canonical clip."""
        return self.projection @ self.view

    def map_coords(self, points: np.ndarray):
        """World points (N, 3) -> (s, t, z_ndc, w). s, t in [0, 1] inside the map (log warp applied)."""
        p = np.asarray(points, dtype=np.float64)
        c = p @ self.matrix[:3, :3].T + self.matrix[:3, 3]
        cw = p @ self.matrix[3, :3] + self.matrix[3, 3]
        with np.errstate(divide="ignore", invalid="ignore"):
            s = (c[:, 0] / cw + 1.0) * 0.5
            t = (c[:, 1] / cw + 1.0) * 0.5
            z = c[:, 2] / cw
            if self.log_warp is not None:
                t = self.log_warp.apply(t)
        return s, t, z, cw

    def texel_rays(self, s: np.ndarray, t: np.ndarray):
        """The light ray through map coordinates (s, t): world points on the near and far planes.

        Returns (near_points, far_points), each (N, 3): the segment a rasterizer would cover between
        z_ndc = -1 and +1 for that texel. Works for warped and log parameterizations alike.
        """
        t = np.asarray(t, dtype=np.float64)
        if self.log_warp is not None:
            t = self.log_warp.invert(t)
        x = 2.0 * np.asarray(s, dtype=np.float64) - 1.0
        y = 2.0 * t - 1.0
        inv = np.linalg.inv(self.matrix)
        ends = []
        for z in (-1.0, 1.0):
            h = np.stack([x, y, np.full_like(x, z), np.ones_like(x)], axis=-1) @ inv.T
            ends.append(h[:, :3] / h[:, 3:4])
        return ends[0], ends[1]

    def frustum_depth_range(self) -> tuple[float, float] | None:
        """near, far: the least and greatest light-view depth -z_view over the map's eight frustum corners
        (the rays through the map's corner texels between z_ndc = -1 and +1; the frustum is convex, so the
        linear function -z_view is extreme at its corners). None when no corner is finite."""
        s = np.array([0.0, 1.0, 0.0, 1.0])
        t = np.array([0.0, 0.0, 1.0, 1.0])
        with np.errstate(all="ignore"):
            a, b = self.texel_rays(s, t)
        pts = np.vstack([a, b])
        d = -(pts @ self.view[2, :3] + self.view[2, 3])
        d = d[np.isfinite(d)]
        if len(d) == 0:
            return None
        return float(d.min()), float(d.max())

    def to_json(self) -> dict:
        warp = {"kind": self.warp_kind, "eta": self.eta, "n": self.n_prime,
                "log": self.log_warp.to_json() if self.log_warp else None}
        d = {"split": list(self.split), "light_depth": list(self.light_depth),
             "resolution": list(self.resolution), "warp": warp, "depth_bias": dict(self.depth_bias),
             "view_matrix": self.view.tolist(), "projection_matrix": self.projection.tolist()}
        if self.face is not None:
            d["face"] = self.face
        d["texel_snapped"] = self.snapped
        if self.depth is not None:
            d["depth"] = _plain(self.depth)
        return d

    @staticmethod
    def from_json(d: dict) -> "ShadowMap":
        """A map from its JSON (service.solution_check.validate_solution checks user input first; a wrong
        type that reaches here is a ValueError naming the key, not an AttributeError)."""
        w = d.get("warp") or {}
        if not isinstance(w, dict):
            raise ValueError(f"warp: expected an object with kind, eta, n and log, got {w!r:.60}")
        lw = w.get("log")
        if lw is not None and not isinstance(lw, dict):
            raise ValueError(f"warp.log: expected an object {{c0, c1, c2}}, got {lw!r:.60}")
        depth = d.get("depth")
        if depth is not None and not isinstance(depth, dict):
            raise ValueError(f"depth: expected an object {{mode, reason, hardware, linear}}, got {depth!r:.60}")
        band = d.get("blend_band")
        if band is not None:
            try:
                band = (float(band[0]), float(band[1]))
            except (TypeError, ValueError, IndexError, KeyError):
                raise ValueError(f"blend_band: expected [start, end], got {band!r:.60}") from None
        smap = ShadowMap(np.asarray(d["view_matrix"], float), np.asarray(d["projection_matrix"], float),
                         tuple(d["resolution"]), tuple(d["split"]), tuple(d["light_depth"]),
                         w.get("kind", "none"), w.get("eta"), w.get("n"),
                         LogWarp(lw["c0"], lw["c1"], lw["c2"]) if lw else None,
                         dict(d.get("depth_bias") or {"constant": 0.0, "slope": 0.0}), d.get("face"),
                         bool(d.get("texel_snapped", False)))
        smap.depth = dict(depth) if depth is not None else None
        smap.blend_band = band
        return smap


def _plain(x):
    """JSON-ready copy (NumPy scalars -> float)."""
    if isinstance(x, dict):
        return {k: _plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_plain(v) for v in x]
    if isinstance(x, np.generic):
        return x.item()
    return x


def map_for_depth(maps: list[ShadowMap], view_depth: np.ndarray) -> np.ndarray:
    """Index of the cascade serving each camera view depth, as an engine selects it (-1: none)."""
    idx = np.full(np.shape(view_depth), -1, dtype=np.int64)
    for k in range(len(maps) - 1, -1, -1):
        lo, hi = maps[k].split
        idx[(view_depth >= lo) & (view_depth <= hi)] = k
    return idx


def serving_maps(maps: list[ShadowMap], positions: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """Index of the map serving each point (-1: none): the cascade for its camera view depth (map_for_depth),
    or, for cube faces, the first face whose map contains it."""
    if not maps:
        return np.full(len(depth), -1, dtype=np.int64)
    if maps[0].face is None:
        return map_for_depth(maps, depth)
    idx = np.full(len(depth), -1, dtype=np.int64)
    for k in range(len(maps) - 1, -1, -1):
        s, t, z, w = maps[k].map_coords(positions)
        inside = (w > 0) & (s >= 0) & (s <= 1) & (t >= 0) & (t <= 1) & (z >= -1) & (z <= 1)
        idx[inside] = k
    return idx
