"""The samples the metric is evaluated on, chosen from the coarse buffers (DESIGN.md, "Metric").

Samples: light-facing receiver pixels on shadow boundaries (the coarse buffers' boundary mask:
neighbours on the same surface that differ in ray-traced visibility, dilated by one coarse pixel),
as Chong & Gortler 2007 §3 do; all light-facing receiver pixels when a view has no boundary.

For each sample the surface's response to a one-pixel step on the *full-resolution* screen,
dX/dx and dX/dy (metres per pixel), comes from the camera ray and the surface plane (the ray-plane
intersection, no depth differencing), so the metric is in full-resolution pixels whatever the
coarse buffer's size.

Grazing rule (documented, one for all methods): a normal more than GRAZING_LIGHT_DEG from the
direction to the light is turned towards the light until it is GRAZING_LIGHT_DEG away, and a normal
more than GRAZING_VIEW_DEG from the direction to the camera likewise towards the camera. Projection
aliasing on near edge-on surfaces is then large but finite; no light matrix could fix it anyway.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

from .cameras import Camera
from .lights import DirectionalLight, Light

SUBSETS_KEPT = 16  # per Samples object, the most recent subsets (with their device copies)
GRAZING_LIGHT_DEG = 85.0
GRAZING_VIEW_DEG = 88.0


@dataclass
class Samples:
    position: np.ndarray  # (N, 3) float64 world
    normal: np.ndarray  # (N, 3) float64, after the grazing rule
    dx: np.ndarray  # (N, 3) dX per full-resolution screen pixel step in +x (right)
    dy: np.ndarray  # (N, 3) dX per full-resolution screen pixel step in +y (down the image)
    view_depth: np.ndarray  # (N,) along the camera's forward axis
    weight: np.ndarray  # (N,)
    pixel: np.ndarray  # (N, 2) coarse-buffer (row, col) each sample came from
    kind: str  # "boundary" or "all_facing" or "none"
    # (N,) full-resolution pixels each sample stands for (a_i of solvers.metric.texel_limit): a coarse
    # sample stands for (W H)/(w h) full-resolution pixels; None: one each (samples taken per pixel).
    pixels: np.ndarray | None = None
    # (N,) f_i: how much more light-space area per pixel the metric's normal (after the grazing rule)
    # claims than the surface's own normal, (|n'.l| / |n'.v|) / (|n.l| / |n.v|) (l towards the light,
    # v towards the camera): a map spends det J_i / f_i texels on the pixel (solvers.metric.texel_limit).
    # None: 1 each (no normal was turned).
    light_area_factor: np.ndarray | None = None
    # Dr.Jit copies by origin (solvers.metric.device_samples) and recent subsets by mask, so that a
    # subset taken again (a cascade's samples, scored then predicted) is uploaded once: the arrays
    # above are never modified.
    _device: dict = field(default_factory=dict, repr=False, compare=False)
    _subsets: dict = field(default_factory=dict, repr=False, compare=False)

    def __len__(self) -> int:
        return int(self.position.shape[0])

    def __getstate__(self) -> dict:
        return {**self.__dict__, "_device": {}, "_subsets": {}}  # device copies stay in their process

    def subset(self, mask: np.ndarray) -> "Samples":
        mask = np.asarray(mask)
        key = (mask.dtype.str, mask.shape, mask.tobytes())
        sub = self._subsets.get(key)
        if sub is None:
            sub = Samples(self.position[mask], self.normal[mask], self.dx[mask], self.dy[mask],
                          self.view_depth[mask], self.weight[mask], self.pixel[mask], self.kind,
                          None if self.pixels is None else self.pixels[mask],
                          None if self.light_area_factor is None else self.light_area_factor[mask])
            if len(self._subsets) >= SUBSETS_KEPT:
                self._subsets.pop(next(iter(self._subsets)))
            self._subsets[key] = sub
        return sub


def directions_to_light(light: Light, points: np.ndarray) -> np.ndarray:
    if isinstance(light, DirectionalLight):
        return np.broadcast_to(-light.direction, points.shape).copy()
    v = light.position - points
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-300)


def limit_angle(n: np.ndarray, toward: np.ndarray, max_deg: float) -> np.ndarray:
    """Turn unit normals n towards unit vectors `toward` until the angle between them is <= max_deg."""
    cos_max = np.cos(np.radians(max_deg))
    c = np.sum(n * toward, axis=-1)
    bad = c < cos_max
    if not bad.any():
        return n
    out = n.copy()
    nb, tb, cb = n[bad], toward[bad], c[bad]
    perp = nb - cb[:, None] * tb
    pn = np.linalg.norm(perp, axis=-1, keepdims=True)
    perp = np.where(pn > 1e-12, perp / np.maximum(pn, 1e-300), _any_perpendicular(tb))
    out[bad] = cos_max * tb + np.sqrt(1.0 - cos_max ** 2) * perp
    return out


def _any_perpendicular(v: np.ndarray) -> np.ndarray:
    a = np.where(np.abs(v[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    p = np.cross(v, a)
    return p / np.linalg.norm(p, axis=-1, keepdims=True)


def pixel_derivatives(camera: Camera, position: np.ndarray, normal: np.ndarray):
    """dX/dx, dX/dy for one full-resolution pixel step, from the ray-plane intersection.

    With the unnormalised ray d = f + a r + b u (a, b in tan units), the surface point is
    X = o + s d with s = n.(X0 - o) / n.d, so dX/da = s (d_a - d (n.d_a)/(n.d)).
    One pixel is da = 2 tan(fov_x/2) / W and db = -2 tan(fov_y/2) / H (y grows downwards).
    """
    w, h = camera.resolution
    th = camera.tan_half_fov_y
    tw = th * camera.aspect
    rel = position - camera.position
    depth = rel @ camera.forward
    d = rel / depth[:, None]
    nd = np.sum(normal * d, axis=-1)
    out = []
    for step in ((2.0 * tw / w) * camera.right, (-2.0 * th / h) * camera.up):
        nstep = normal @ step
        out.append(depth[:, None] * (step[None, :] - d * (nstep / nd)[:, None]))
    return out[0], out[1], depth


def select_samples(camera: Camera, light: Light, position: np.ndarray, normal: np.ndarray,
                   hit: np.ndarray, facing: np.ndarray, boundary: np.ndarray,
                   in_light: np.ndarray | None = None) -> Samples:
    """Samples for one light from coarse buffers (all (h, w) arrays; position/normal (h, w, 3))."""
    receivers = hit & facing & (in_light if in_light is not None else True)
    chosen = receivers & boundary
    kind = "boundary"
    if not chosen.any():
        chosen, kind = receivers, "all_facing"
    if not chosen.any():
        kind = "none"
    rows, cols = np.nonzero(chosen)
    p = position[rows, cols].astype(np.float64)
    n = normal[rows, cols].astype(np.float64)
    n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-300)
    to_cam = camera.position - p
    to_cam /= np.maximum(np.linalg.norm(to_cam, axis=-1, keepdims=True), 1e-300)
    n0 = n
    to_light = directions_to_light(light, p)
    n = limit_angle(n, to_cam, GRAZING_VIEW_DEG)
    n = limit_angle(n, to_light, GRAZING_LIGHT_DEG)
    area_factor = None
    if n is not n0:  # some normal was turned: light-space area per pixel is |n.l| / |n.v|
        def area(nn):
            return np.abs(np.sum(nn * to_light, -1)) / np.maximum(np.abs(np.sum(nn * to_cam, -1)), 1e-12)

        area_factor = area(n) / np.maximum(area(n0), 1e-12)
    if len(p):
        dx, dy, depth = pixel_derivatives(camera, p, n)
    else:
        dx = dy = np.zeros((0, 3))
        depth = np.zeros(0)
    per_pixel = camera.resolution[0] * camera.resolution[1] / float(hit.shape[0] * hit.shape[1])
    return Samples(p, n, dx, dy, depth, np.ones(len(p)), np.stack([rows, cols], -1), kind,
                   np.full(len(p), per_pixel), area_factor)


@lru_cache(maxsize=128)
def seeded_rows(count: int, n: int) -> np.ndarray:
    """np.random.default_rng(0).choice(count, n, replace=False): the seeded subset of n of count rows
    that the fits and scores measure on (read-only; computed once per (count, n): a permutation of
    count rows costs milliseconds and the same receivers are subsampled for every candidate map)."""
    rows = np.random.default_rng(0).choice(count, n, replace=False)
    rows.setflags(write=False)
    return rows
