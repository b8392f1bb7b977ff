"""Coarse buffers: what the camera sees at ~180 px, and what each light sees of it.

One Dr.Jit pass: camera rays generated from opaque camera parameters (a new camera does not
recompile the kernel), `ray_intersect_preliminary` for hit distance and primitive, the geometric
normal gathered from the merged mesh, one `ray_test` shadow ray per pixel and light, and a single
evaluation before the NumPy conversion. Neighbour tests (shadow boundaries) run in NumPy.
"""
from __future__ import annotations

import pathlib
import time
from dataclasses import dataclass, field

import numpy as np

from ..solvers.cameras import Camera
from ..solvers.lights import DirectionalLight, Light, PointLight, SpotLight
from .json_text import dumps
from .mitsuba_setup import mitsuba
from .previews import save_previews
from .ray_scene import RayScene

DEFAULT_LONG_SIDE = 180
DEFAULT_BOUNDARY_RADIUS = 1  # coarse pixels the shadow-boundary mask is dilated by
DEPTH_CONTINUITY = 0.05  # neighbours whose view depths differ by more than this fraction are on different surfaces
FINE_MAX = 6  # at most this many fine rays per coarse pixel side in the edge pass (fine_points)
SHADOW_RAY_EPSILON = 2e-5  # shadow-ray origin offset along the normal, times (1 + max |p|), in scene units


@dataclass
class LightBuffers:
    """Per-light coarse buffers, all (h, w) bool."""

    visible: np.ndarray  # faces the light and its shadow ray reaches the light (exact, ray-traced)
    facing: np.ndarray  # the camera-facing side of the surface faces the light (n . to_light > 0)
    in_light: np.ndarray  # inside the light's cone (spot) / everywhere (directional, point)
    boundary: np.ndarray  # lit state differs from a 4-neighbour's on the same surface, dilated

    @property
    def lit(self) -> np.ndarray:
        return self.visible & self.facing & self.in_light


@dataclass
class FinePoints:
    """The edge pass (fine_points): hits of rays through the corners of a finer grid (`factor` per
    coarse pixel side) over the coarse pixels next to a geometric edge (hit/miss, a view-depth
    discontinuity) and along the screen's border. (M,) arrays over the hits only."""

    factor: int
    position: np.ndarray  # (M, 3) float64 world
    normal: np.ndarray  # (M, 3) float32, towards the camera
    depth: np.ndarray  # (M,) float64 view depth
    receiver: list[np.ndarray] = field(default_factory=list)  # per light: (M,) facing & in_light
    rays: int = 0  # rays traced (hits or not)
    grid_shape: tuple = (0, 0)  # the fine corner grid, (factor h + 1, factor w + 1)
    flat: np.ndarray | None = None  # (M,) each hit's flat index in that grid (row-major)
    traced: np.ndarray | None = None  # (rays,) flat indices of every traced corner

    def uv(self) -> tuple[np.ndarray, np.ndarray]:
        """Each hit's screen position in coarse-pixel units (u right, v down; pixel centres at i + 0.5)."""
        vj, vi = np.divmod(self.flat, self.grid_shape[1])
        return vi / self.factor, vj / self.factor

    def neighbours(self) -> np.ndarray:
        """(4, M) int64: each hit's 4-neighbours in the fine grid (right, left, down, up) as hit indices;
        -1 a traced corner that missed, -2 a corner not traced or off the grid. Depends on the camera
        alone (service.coarse_cache keeps it with the camera pass)."""
        H, W = self.grid_shape
        idx = np.full(H * W, -2, dtype=np.int64)
        idx[self.traced] = -1
        idx[self.flat] = np.arange(len(self.flat))
        f = self.flat
        col = f % W
        out = np.empty((4, len(f)), dtype=np.int64)
        for s, (step, ok) in enumerate(((1, col < W - 1), (-1, col > 0), (W, f + W < H * W), (-W, f - W >= 0))):
            out[s] = np.where(ok, idx[np.where(ok, f + step, 0)], -2)
        return out

    def edges(self, receiver: np.ndarray, continuity: float = DEPTH_CONTINUITY,
              neighbours: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Per hit, (edge, slack): edge = a receiver with a 4-neighbour in the fine grid that was traced
        and is not a receiver, or is one at a view depth more than `continuity` away (corners not
        traced lie inside coarse pixels without a geometric edge: not an edge); slack = the largest
        view-depth change to a receiver 4-neighbour (full-resolution pixels between fine rays have depths
        within it: cascade overlap, as service.receivers.depth_slack for the coarse pixels). 0 for non-receivers.
        `neighbours`: self.neighbours(), when kept."""
        nb = self.neighbours() if neighbours is None else neighbours
        receiver = np.asarray(receiver, dtype=bool)
        ri = np.nonzero(receiver)[0]
        d = self.depth[ri]
        out = np.zeros(len(ri), dtype=bool)
        slack = np.zeros(len(ri))
        for s in range(4):
            j = nb[s, ri]
            hit = j >= 0
            jj = np.where(hit, j, 0)
            rec = hit & receiver[jj]  # a receiver neighbour
            dn = self.depth[jj]
            dd = np.abs(dn - d)
            out |= (j == -1) | (hit & ~receiver[jj]) | (rec & (dd > continuity * np.minimum(dn, d)))
            slack = np.where(rec, np.maximum(slack, dd), slack)
        edge, full_slack = np.zeros(len(receiver), dtype=bool), np.zeros(len(receiver))
        edge[ri], full_slack[ri] = out, slack
        return edge, full_slack


@dataclass
class CoarseBuffers:
    camera: Camera
    width: int
    height: int
    hit: np.ndarray  # (h, w) bool
    position: np.ndarray  # (h, w, 3) float64 world; NaN where no hit
    normal: np.ndarray  # (h, w, 3) float32 geometric normal, turned towards the camera; 0 where no hit
    depth: np.ndarray  # (h, w) float32 view depth (along the camera's forward axis); inf where no hit
    prim_id: np.ndarray  # (h, w) int32 index into SceneGeometry.prim_paths; -1 where no hit
    lights: list[LightBuffers] = field(default_factory=list)
    timings_ms: dict = field(default_factory=dict)
    fine: FinePoints | None = None

    def save(self, out_dir) -> list[str]:
        """Write every buffer as .npy and PNG previews into out_dir. Returns the written file names."""
        out = pathlib.Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        arrays = {"hit": self.hit, "position": self.position, "normal": self.normal, "depth": self.depth,
                  "prim_id": self.prim_id}
        for k, lb in enumerate(self.lights):
            for name in ("visible", "facing", "in_light", "boundary"):
                arrays[f"light{k}_{name}"] = getattr(lb, name)
            arrays[f"light{k}_lit"] = lb.lit
        written = []
        for name, arr in arrays.items():
            np.save(out / f"{name}.npy", arr)
            written.append(f"{name}.npy")
        written += save_previews(self, out)
        meta = {"width": self.width, "height": self.height, "lights": len(self.lights),
                "hit_pixels": int(self.hit.sum()), "timings_ms": self.timings_ms,
                "files": sorted(written)}
        (out / "coarse.json").write_text(dumps(meta, indent=2))
        written.append("coarse.json")
        return written


def opaque3(mi, dr, cls, v):
    """A 3-vector as an opaque Dr.Jit value: its numbers are kernel inputs, not baked literals."""
    return cls(*(dr.opaque(mi.Float, float(x)) for x in np.asarray(v).reshape(3)))


def camera_rays(mi, dr, camera: Camera, width: int, height: int, origin: np.ndarray):
    """Rays through coarse pixel centres (same convention as Camera.ray_directions)."""
    th = camera.tan_half_fov_y
    tw = th * camera.aspect
    o = opaque3(mi, dr, mi.Point3f, (camera.position - origin))
    fwd = opaque3(mi, dr, mi.Vector3f, camera.forward)
    right = opaque3(mi, dr, mi.Vector3f, (camera.right * tw))
    up = opaque3(mi, dr, mi.Vector3f, (camera.up * th))
    idx = dr.arange(mi.UInt32, width * height)
    w_op = dr.opaque(mi.UInt32, width)
    j = idx // w_op
    i = idx - j * w_op
    sx = dr.opaque(mi.Float, 2.0 / width)  # opaque (the packed buffer sizes still make one kernel per size)
    sy = dr.opaque(mi.Float, 2.0 / height)
    x = (mi.Float(i) + 0.5) * sx - 1.0
    y = 1.0 - (mi.Float(j) + 0.5) * sy
    d = dr.normalize(fwd + x * right + y * up)
    return mi.Ray3f(o, d), fwd


def _clipped_hits(mi, dr, pi, ray, fwd, camera: Camera):
    """Hits inside the camera's [near, far] view-depth range, as a rasterizer clips them."""
    depth = pi.t * dr.dot(ray.d, fwd)
    near = dr.opaque(mi.Float, float(camera.near))
    far = dr.opaque(mi.Float, float(camera.far))
    return pi.is_valid() & (depth >= near) & (depth <= far)


def surface_hits(mi, dr, rs: RayScene, ray, fwd, camera: Camera):
    """The camera rays' first hits within [near, far] (`_clipped_hits`): (preliminary intersection,
    hit mask, ray distance t (0 where no hit), hit points, geometric normals turned towards the camera).
    One implementation for the coarse pass, its edge pass and the full-resolution evaluator."""
    pi = rs.scene.ray_intersect_preliminary(ray, coherent=False)  # measured: faster than coherent here
    hit = _clipped_hits(mi, dr, pi, ray, fwd, camera)
    t = dr.select(hit, pi.t, 0.0)
    p = ray.o + t * ray.d
    n = _geometric_normal(mi, dr, rs, pi.prim_index, hit)
    n = dr.select(dr.dot(n, ray.d) > 0, -n, n)  # turned towards the camera
    return pi, hit, t, p, n


def _geometric_normal(mi, dr, rs: RayScene, prim, active):
    f = mi.Vector3u(*(dr.gather(mi.UInt32, rs.faces, prim * 3 + k, active) for k in range(3)))
    p = [mi.Point3f(*(dr.gather(mi.Float, rs.vertices, f[v] * 3 + k, active) for k in range(3)))
         for v in range(3)]
    return dr.normalize(dr.cross(p[1] - p[0], p[2] - p[0]))


def light_test(mi, dr, rs: RayScene, light: Light, p, n, active, shadow_rays: bool = True):
    """Returns (visible, facing, in_light) Dr.Jit masks for one light. shadow_rays=False casts no
    shadow ray: `visible` is then `facing` (the receivers alone, renderers.coverage)."""
    if isinstance(light, DirectionalLight):
        to_light = opaque3(mi, dr, mi.Vector3f, (-light.direction))
        dist = mi.Float(dr.inf)
        in_light = mi.Bool(True)
    else:
        lp = opaque3(mi, dr, mi.Point3f, (light.position - rs.origin))
        v = lp - p
        dist = dr.norm(v)
        to_light = v / dist
        if isinstance(light, SpotLight):
            axis = opaque3(mi, dr, mi.Vector3f, light.direction)
            cos_cone = dr.opaque(mi.Float, float(np.cos(np.radians(light.cone_deg))))
            in_light = dr.dot(-to_light, axis) >= cos_cone
        else:
            in_light = mi.Bool(True)
    cos_l = dr.dot(n, to_light)
    facing = cos_l > 0
    # Offset the origin to the light's side of the surface (Mitsuba's spawn_ray rule, scaled).
    eps = (1.0 + dr.max(dr.abs(p))) * SHADOW_RAY_EPSILON
    o = p + n * dr.select(facing, eps, -eps)
    ray = mi.Ray3f(o, to_light)
    # Bounded at the light: Mitsuba 3's three-argument Ray3f(o, d, x) reads x as the ray's time, not maxt.
    ray.maxt = dist * (1.0 - 1e-5)
    # Only surfaces facing the light cast a shadow ray: one facing away is in its own shadow (its
    # shadow ray would cross its own surface), which saves about half the rays of a typical view.
    occluded = rs.scene.ray_test(ray, active & facing) if shadow_rays else mi.Bool(False)
    return active & facing & ~occluded, active & facing, active & in_light


def _vec_to_numpy(v, dtype) -> np.ndarray:
    """(N, 3) from a Dr.Jit 3-vector (measured: .numpy() is the fastest conversion, np.array(v) ~20x slower)."""
    return v.numpy().T.astype(dtype, copy=False)  # a transposed view: no extra copy


def boundary_mask(lit: np.ndarray, hit: np.ndarray, depth: np.ndarray, radius: int = DEFAULT_BOUNDARY_RADIUS,
                  continuity: float = DEPTH_CONTINUITY) -> np.ndarray:
    """Pixels whose lit state differs from a 4-neighbour's on the same surface, dilated by `radius`.

    Two neighbours are on the same surface when both are hits and their view depths differ by less
    than `continuity` times the nearer depth.
    """
    h, w = lit.shape
    edge = np.zeros((h, w), dtype=bool)
    d = np.where(hit, depth, np.float32(3e38)).astype(np.float64)
    for axis in (0, 1):
        a = (slice(None, -1), slice(None)) if axis == 0 else (slice(None), slice(None, -1))
        b = (slice(1, None), slice(None)) if axis == 0 else (slice(None), slice(1, None))
        same = hit[a] & hit[b] & (np.abs(d[a] - d[b]) < continuity * np.minimum(d[a], d[b]))
        diff = same & (lit[a] != lit[b])
        edge[a] |= diff
        edge[b] |= diff
    if radius > 0 and edge.any():
        # Square dilation as two 1-D passes (rows, then columns).
        grown = edge.copy()
        for k in range(1, radius + 1):
            grown[k:, :] |= edge[:-k, :]
            grown[:-k, :] |= edge[k:, :]
        rows = grown.copy()
        for k in range(1, radius + 1):
            grown[:, k:] |= rows[:, :-k]
            grown[:, :-k] |= rows[:, k:]
        edge = grown & hit
    return edge


def camera_hits(mi, dr, rs: RayScene, camera: Camera, width: int, height: int):
    """One camera ray per coarse pixel: hit mask, hit points relative to rs.origin, normals turned towards
    the camera, view depth and primitive id (Dr.Jit arrays, not yet evaluated)."""
    ray, fwd = camera_rays(mi, dr, camera, width, height, rs.origin)
    pi, hit, t, p, n = surface_hits(mi, dr, rs, ray, fwd, camera)
    depth = dr.select(hit, t * dr.dot(ray.d, fwd), dr.inf)
    prim = dr.gather(mi.UInt32, rs.face_prim, pi.prim_index, hit)
    return hit, p, n, depth, prim


def light_buffers(masks, hit: np.ndarray, depth: np.ndarray, boundary_radius: int) -> list[LightBuffers]:
    """Each light's (visible, facing, in light) Dr.Jit masks as NumPy buffers of the coarse shape, with the
    shadow-boundary mask of the lit pixels."""
    shape, size = hit.shape, hit.size
    out = []
    for vis, fac, inl in masks:
        vis_np, fac_np, inl_np = (np.array(mask_numpy(m, size)).reshape(shape) for m in (vis, fac, inl))
        out.append(LightBuffers(vis_np, fac_np, inl_np,
                                boundary_mask(vis_np & fac_np & inl_np, hit, depth, boundary_radius)))
    return out


def render_coarse(rs: RayScene, camera: Camera, lights: list[Light], long_side: int = DEFAULT_LONG_SIDE,
                  boundary_radius: int = DEFAULT_BOUNDARY_RADIUS, fine_pass: bool = True) -> CoarseBuffers:
    """Cast one camera ray per coarse pixel and one shadow ray per hit and light, then the edge pass
    (fine_points: finer camera rays where the coarse pass saw geometric edges and along the border)."""
    mi = mitsuba()
    import drjit as dr  # lazy: after mitsuba(), which points Dr.Jit at its libLLVM (solvers.jit)

    t0 = time.perf_counter()
    width, height = camera.coarse_resolution(long_side)
    hit, p, n, depth, prim = camera_hits(mi, dr, rs, camera, width, height)
    masks = [light_test(mi, dr, rs, light, p, n, hit) for light in lights]
    flat = [hit, p, n, depth, prim] + [m for ms in masks for m in ms]
    dr.eval(*flat)
    dr.sync_thread()  # kernels run asynchronously: wait so that "trace" is the kernels' time
    t1 = time.perf_counter()
    shape = (height, width)
    size = width * height  # .numpy() below: np.array() of a Dr.Jit array is ~20x slower (the same values)
    hit_np = np.array(mask_numpy(hit, size)).reshape(shape)  # copies: owned, writable arrays as before
    pos = _vec_to_numpy(p, np.float64).reshape(height, width, 3) + rs.origin
    pos[~hit_np] = np.nan
    nrm = _vec_to_numpy(n, np.float32).reshape(height, width, 3)
    nrm[~hit_np] = 0.0
    depth_np = np.array(depth.numpy(), dtype=np.float32).reshape(shape)
    prim_np = np.where(hit_np, prim.numpy().astype(np.int64).reshape(shape), -1).astype(np.int32)
    light_bufs = light_buffers(masks, hit_np, depth_np, boundary_radius)
    t2 = time.perf_counter()
    fine = fine_points(rs, camera, lights, hit_np, depth_np) if fine_pass else None
    t3 = time.perf_counter()
    return CoarseBuffers(camera, width, height, hit_np, pos, nrm, depth_np, prim_np, light_bufs,
                         {"trace": (t1 - t0) * 1e3, "convert": (t2 - t1) * 1e3, "fine": (t3 - t2) * 1e3,
                          "total": (t3 - t0) * 1e3}, fine)


def edge_cells(hit: np.ndarray, depth: np.ndarray, continuity: float = DEPTH_CONTINUITY) -> np.ndarray:
    """(h, w) bool: coarse pixels next to a geometric edge along a row, a column or a diagonal (one of a
    neighbour pair is a hit and the other not, or their view depths differ by more than `continuity` of
    the nearer; both pixels of such a pair are marked), and every pixel on the screen's border
    (full-resolution pixels there lie up to half a coarse pixel beyond the outermost coarse ray).
    A receding plane whose depth steps exceed `continuity` is marked too: measured, leaving those out
    (a 1/depth smoothness test) lost silhouettes on the corpus (harbour, McUsd, vertical city)."""
    h, w = hit.shape
    d = np.where(hit, depth, np.float32(3e38)).astype(np.float64)
    out = np.zeros((h, w), dtype=bool)
    # neighbour pairs (a, b): right, down, down-right, down-left
    pairs = (((slice(None), slice(None, -1)), (slice(None), slice(1, None))),
             ((slice(None, -1), slice(None)), (slice(1, None), slice(None))),
             ((slice(None, -1), slice(None, -1)), (slice(1, None), slice(1, None))),
             ((slice(None, -1), slice(1, None)), (slice(1, None), slice(None, -1))))
    for a, b in pairs:
        jump = (hit[a] != hit[b]) | (hit[a] & hit[b] & (np.abs(d[a] - d[b]) > continuity * np.minimum(d[a], d[b])))
        out[a] |= jump
        out[b] |= jump
    out[0, :] = out[-1, :] = True
    out[:, 0] = out[:, -1] = True
    return out


def mask_numpy(m, size: int) -> np.ndarray:
    """A Dr.Jit mask as NumPy bool (a scalar mask, e.g. in_light of a directional light, broadcast)."""
    a = np.asarray(m.numpy(), dtype=bool).reshape(-1)
    return np.broadcast_to(a, (size,)) if a.size == 1 else a


def fine_factor(camera: Camera, width: int) -> int:
    """Fine rays per coarse pixel side: the full resolution's pixels per coarse pixel, 2..FINE_MAX."""
    return int(min(FINE_MAX, max(2, np.ceil(max(camera.resolution) / max(width, 1)))))


def fine_ray_directions(mi, camera: Camera, vj: np.ndarray, vi: np.ndarray, f: int, w: int, h: int):
    """(padded ray count, Dr.Jit directions) of the edge pass's rays through fine-grid corners (vj, vi) of a
    w x h coarse buffer refined f times."""
    size = 1 << int(np.ceil(np.log2(max(len(vj), 1024))))
    th = camera.tan_half_fov_y
    tw = th * camera.aspect
    x = (vi / f * (2.0 / w) - 1.0) * tw  # coarse-pixel units 0 .. w (the grid's corners): the convention of
    y = (1.0 - vj / f * (2.0 / h)) * th  # Camera.ray_directions at pixel corners
    fw, rt, up = camera.forward, camera.right, camera.up
    # fw + x right + y up and its norm per component, the operations (and their order) of the (n, 3) form
    # fw + x[:, None] * right + y[:, None] * up; d / np.linalg.norm(d, axis=1): the same bits, ~5x faster
    comp = [fw[k] + x * rt[k] + y * up[k] for k in range(3)]
    norm = np.sqrt(comp[0] * comp[0] + comp[1] * comp[1] + comp[2] * comp[2])
    # padded to `size` by repeating the first rays (np.resize), traced and dropped
    return size, mi.Vector3f(*(mi.Float(np.resize((c / norm).astype(np.float32), size)) for c in comp))


def fine_points(rs: RayScene, camera: Camera, lights: list[Light], hit: np.ndarray, depth: np.ndarray,
                factor: int | None = None) -> FinePoints:
    """The edge pass: one ray through every corner of a `factor`-times finer grid over the coarse
    pixels of `edge_cells` (corners shared by neighbouring cells traced once; the screen's border is
    a corner line, so the outermost full-resolution pixels are bracketed), hit point, geometric normal
    and, per light, the receiver test (facing and in the cone: coarse.light_test without shadow rays).
    Vectorized: one Dr.Jit launch, the ray count padded to a power of two (few kernel sizes: a quarter-octave ladder
    traced fewer padding rays but compiled a kernel for a new camera, measured)."""
    mi = mitsuba()
    import drjit as dr  # lazy: after mitsuba(), which points Dr.Jit at its libLLVM (solvers.jit)

    h, w = hit.shape
    f = fine_factor(camera, w) if factor is None else int(factor)
    cells = edge_cells(hit, depth)
    grid = np.zeros((f * h + 1, f * w + 1), dtype=bool)
    for dj in range(f + 1):  # every corner of every edge cell: strided views, one per corner offset
        for di in range(f + 1):
            grid[dj:dj + f * h:f, di:di + f * w:f] |= cells
    vj, vi = np.nonzero(grid)
    n = len(vj)
    if n == 0:
        return FinePoints(f, np.zeros((0, 3)), np.zeros((0, 3), np.float32), np.zeros(0), [np.zeros(0, bool)] * len(lights),
                          0, grid.shape, np.zeros(0, np.int64), np.zeros(0, np.int64))
    size, d = fine_ray_directions(mi, camera, vj, vi, f, w, h)
    o = opaque3(mi, dr, mi.Point3f, camera.position - rs.origin)
    fwd = opaque3(mi, dr, mi.Vector3f, camera.forward)
    ray = mi.Ray3f(o, d)
    pi, ok, t, p, nrm = surface_hits(mi, dr, rs, ray, fwd, camera)
    tests = [light_test(mi, dr, rs, light, p, nrm, ok, shadow_rays=False) for light in lights]
    dr.eval(ok, p, nrm, *[m for ms in tests for m in ms[1:]])
    keep = ok.numpy().astype(bool)[:n]  # .numpy(): np.array() of a Dr.Jit array is ~20x slower
    pos = p.numpy()[:, :n].T[keep].astype(np.float64) + rs.origin  # the hits only (not the padding)
    nn = nrm.numpy()[:, :n].T[keep]
    dep = (pos - camera.position) @ camera.forward
    rec = [(mask_numpy(fac, size)[:n] & mask_numpy(inl, size)[:n])[keep] for _, fac, inl in tests]
    traced = vj.astype(np.int64) * grid.shape[1] + vi
    return FinePoints(f, pos, nn, dep, rec, n, grid.shape, traced[keep], traced)


def subpixel_receivers(rs: RayScene, camera: Camera, light: Light, cells: np.ndarray, factor: int):
    """Receivers inside the coarse pixels `cells` ((h, w) bool) at factor x factor sub-pixel centres: per sample
    its cell's flat index, world position, geometric normal (towards the camera), view depth and whether its
    shadow ray reaches the light (light_test); only light-facing receivers inside the light are kept. The
    depth probe's finer samples along shadow boundaries, contacts and object edges (service.bias)."""
    mi = mitsuba()
    import drjit as dr  # lazy: after mitsuba(), which points Dr.Jit at its libLLVM (solvers.jit)

    h, w = cells.shape
    f = int(factor)
    cj, ci = np.nonzero(cells)
    if len(cj) == 0:
        z = np.zeros(0)
        return np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3)), z, np.zeros(0, bool)
    sub = (np.arange(f) + 0.5)
    sj, si = np.meshgrid(sub, sub, indexing="ij")
    vj = (cj[:, None] * f + sj.ravel()[None, :]).ravel()  # fine-grid units: f per coarse pixel
    vi = (ci[:, None] * f + si.ravel()[None, :]).ravel()
    cell = np.repeat(cj * w + ci, f * f)
    n = len(vj)
    size, d = fine_ray_directions(mi, camera, vj, vi, f, w, h)
    o = opaque3(mi, dr, mi.Point3f, camera.position - rs.origin)
    fwd = opaque3(mi, dr, mi.Vector3f, camera.forward)
    pi, ok, t, p, nrm = surface_hits(mi, dr, rs, mi.Ray3f(o, d), fwd, camera)
    visible, facing, in_light = light_test(mi, dr, rs, light, p, nrm, ok, shadow_rays=True)
    dr.eval(ok, p, nrm, visible, facing, in_light)
    keep = ok.numpy().astype(bool)[:n]
    pos = p.numpy()[:, :n].T.astype(np.float64) + rs.origin
    nn = nrm.numpy()[:, :n].T.astype(np.float64)
    rec = keep & mask_numpy(facing, size)[:n] & mask_numpy(in_light, size)[:n]
    vis = mask_numpy(visible, size)[:n]
    dep = (pos - camera.position) @ camera.forward
    return cell[rec], pos[rec], nn[rec], dep[rec], vis[rec]
