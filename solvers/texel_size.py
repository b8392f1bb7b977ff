"""How large a shadow map's texels are in the world, per point: metres per unit s and t in the plane
perpendicular to the light ray (texel_extents), and a map's 95th-percentile texel size over its receivers
(texel_world_size, the scale of the depth bias: solvers.depth_modes)."""
from __future__ import annotations

import numpy as np

from .lights import DirectionalLight
from .samples import seeded_rows
from .shadow_map import ShadowMap


def _light_dirs(light, pts: np.ndarray) -> np.ndarray:
    if isinstance(light, DirectionalLight):
        return np.broadcast_to(light.direction, pts.shape)
    v = pts - light.position
    return v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-300)


def texel_extents(smap: ShadowMap, pts: np.ndarray, light) -> tuple[np.ndarray, np.ndarray]:
    """Per point: world metres per unit s and per unit t of the map, measured in the plane through
    the point perpendicular to the light ray (the columns of the inverse of d(s, t)/d(world), by
    central differences, so warped and log maps are measured as they are). Points outside the map
    (or behind its centre of projection) get NaN."""
    pts = np.asarray(pts, dtype=np.float64).reshape(-1, 3)
    if len(pts) == 0:
        return np.zeros(0), np.zeros(0)
    ldir = _light_dirs(light, pts)
    e1 = np.cross(ldir, [0.0, 1.0, 0.0])
    bad = np.linalg.norm(e1, axis=1) < 1e-6
    e1[bad] = np.cross(ldir[bad], [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(ldir, e1)
    c = pts.mean(0)
    extent = float(np.abs(pts - c).max()) if len(pts) > 1 else 0.0
    eps = max(1e-6 * extent, 1e-10 * float(np.abs(pts).max()), 1e-9)
    with np.errstate(all="ignore"):
        s0, t0, z0, w0 = smap.map_coords(pts)
        cols = []
        for e in (e1, e2):
            sp, tp, _, _ = smap.map_coords(pts + eps * e)
            sm, tm, _, _ = smap.map_coords(pts - eps * e)
            cols.append(np.stack([(sp - sm), (tp - tm)], axis=-1) / (2 * eps))
        J = np.stack(cols, axis=-1)  # (N, 2, 2): d(s, t)/d(e1, e2)
        det = J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0]
        # inverse columns: d(e1, e2)/ds = (J11, -J10)/det, d(e1, e2)/dt = (-J01, J00)/det
        per_s = np.hypot(J[:, 1, 1], J[:, 1, 0]) / np.abs(det)
        per_t = np.hypot(J[:, 0, 1], J[:, 0, 0]) / np.abs(det)
        inside = (w0 > 0) & (s0 >= -1e-6) & (s0 <= 1 + 1e-6) & (t0 >= -1e-6) & (t0 <= 1 + 1e-6)
    ok = inside & np.isfinite(per_s) & np.isfinite(per_t) & (det != 0)
    return np.where(ok, per_s, np.nan), np.where(ok, per_t, np.nan)


def texel_world_size(smap: ShadowMap, pts: np.ndarray, light) -> float:
    """95th percentile over the points inside the map of the world size of one texel (its longer
    side, perpendicular to the light); 0 when no point is inside."""
    pts = np.asarray(pts, dtype=np.float64).reshape(-1, 3)
    if len(pts) > 512:  # a percentile of a random sample
        pts = pts[seeded_rows(len(pts), 512)]
    per_s, per_t = texel_extents(smap, pts, light)
    size = np.maximum(per_s / smap.resolution[0], per_t / smap.resolution[1])
    size = size[np.isfinite(size)]
    if len(size):
        return float(np.percentile(size, 95))
    # No receiver inside this map (an empty cube face, no visible receiver): the texel size at the
    # far end of the map's central light ray, a conservative value for whatever it may receive.
    with np.errstate(all="ignore"):
        near_pt, far_pt = smap.texel_rays(np.array([0.5]), np.array([0.5]))
        per_s, per_t = texel_extents(smap, 0.999 * far_pt + 0.001 * near_pt, light)
        size = np.maximum(per_s / smap.resolution[0], per_t / smap.resolution[1])
    return float(size[0]) if len(size) and np.isfinite(size[0]) else 0.0
