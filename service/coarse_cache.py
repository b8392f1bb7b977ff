"""The coarse pass split in its camera part and its light part, with the camera part cached in the
server process: when only the light changes (the inspector's sun slider, a sun sweep over one camera),
the camera rays, their hits, normals and view depths, the edge pass's fine rays (renderers.coarse),
receiver_points' camera-only part (service.receivers.receiver_prep: edge cells, cell table, tangent-plane
reach of every pixel) and the receivers of a receiver mask (service.receivers.receiver_points) are the same,
and only the shadow rays, the facing tests, the shadow-boundary mask and the new mask's receivers are
computed again.

Exact, not an approximation: the light part runs renderers.coarse's own kernels (light_test) on the
camera part's Dr.Jit values as they were computed (float32, before any conversion), so the buffers equal
renderers.coarse.render_coarse's bit for bit (tests/test_coarse_cache.py compares every array).

Keyed by (tenant, the scene entry, coarse size, boundary radius, the camera's every parameter): one
tenant's entries are never another's, and a re-uploaded or reloaded scene is a new entry object (the
cache holds only a weak reference to it, so a changed scene can never hit). An LRU bounded in bytes with a
per-tenant share (service.tenant_lru.TenantLRU; issue 27: bounded by count only and shared, it kept +0.82 GB).
"""
from __future__ import annotations

import threading
import time
import weakref
from collections import OrderedDict
from dataclasses import dataclass, field, replace

import numpy as np

from ..renderers.coarse import (DEFAULT_BOUNDARY_RADIUS, CoarseBuffers, FinePoints, camera_hits, fine_points,
                                fine_ray_directions, light_buffers, light_test, mask_numpy, opaque3, surface_hits)
from ..renderers.mitsuba_setup import mitsuba
from .receivers import receiver_prep
from .rigs import resolve_rig
from .tenant_lru import TenantLRU

MAX_CAMERAS = 16  # camera entries kept (each ~8 MB at the 180 px default, ~4 MB more with a receiver prep, ~2-4 MB per receiver mask memo)
MAX_RECEIVER_MASKS = 8  # receiver sets kept per camera entry (one per distinct receiver mask)
DEFAULT_BYTES = 256 << 20  # the server sizes it from coarse_cache_bytes (api.service_state)
DEFAULT_TENANT_SHARE = 0.5


@dataclass
class CameraPass:
    """What renderers.coarse.render_coarse computes before any light: NumPy buffers (read-only: shared by
    every solve that hits) and the raw float32 Dr.Jit values the light tests start from."""

    width: int
    height: int
    hit: np.ndarray
    position: np.ndarray
    normal: np.ndarray
    depth: np.ndarray
    prim_id: np.ndarray
    p32: np.ndarray  # (3, w h) float32 hit points relative to the ray scene's origin, as traced
    n32: np.ndarray  # (3, w h) float32 normals turned towards the camera, as computed
    fine: FinePoints | None
    fine_p32: np.ndarray | None  # the edge pass's (padded) rays: hit points, normals, hit mask, count
    fine_n32: np.ndarray | None
    fine_ok: np.ndarray | None
    trace_ms: float = 0.0
    receivers: OrderedDict = field(default_factory=OrderedDict)  # mask key -> (points, slack)
    receiver_prep: object = None  # service.receivers.ReceiverPrep: receiver_points' camera-only part, made on a second mask
    receiver_misses: int = 0
    lock: threading.Lock = field(default_factory=threading.Lock)
    cache_key: tuple | None = None  # (tenant, key) in the CoarseCache that holds it


def _readonly(*arrays):
    for a in arrays:
        if isinstance(a, np.ndarray):
            a.flags.writeable = False


def camera_pass(rs, camera, long_side: int) -> CameraPass:
    """render_coarse's camera rays and hits, and the edge pass (renderers.coarse.fine_points) traced with
    no light; the same kernels and operations."""
    mi = mitsuba()
    import drjit as dr  # lazy: loaded after mitsuba() has set its LLVM variant (renderers.mitsuba_setup)

    t0 = time.perf_counter()
    width, height = camera.coarse_resolution(long_side)
    hit, p, n, depth, prim = camera_hits(mi, dr, rs, camera, width, height)
    dr.eval(hit, p, n, depth, prim)
    shape = (height, width)
    size = width * height
    hit_np = np.array(mask_numpy(hit, size)).reshape(shape)
    p32 = np.ascontiguousarray(p.numpy(), dtype=np.float32)
    n32 = np.ascontiguousarray(n.numpy(), dtype=np.float32)
    pos = p32.T.astype(np.float64).reshape(height, width, 3) + rs.origin  # render_coarse's conversion
    pos[~hit_np] = np.nan
    nrm = n32.T.astype(np.float32).reshape(height, width, 3)
    nrm[~hit_np] = 0.0
    depth_np = np.array(depth.numpy(), dtype=np.float32).reshape(shape)
    prim_np = np.where(hit_np, prim.numpy().astype(np.int64).reshape(shape), -1).astype(np.int32)
    # the edge pass with no light: its receiver lists are computed per light (light_part)
    fine = fine_points(rs, camera, [], hit_np, depth_np)
    fp = fn = fo = None
    if fine.rays:
        fp, fn, fo = _fine_rays(mi, dr, rs, camera, fine, hit_np.shape)
    cp = CameraPass(width, height, hit_np, pos, nrm, depth_np, prim_np, p32, n32, fine, fp, fn, fo,
                    trace_ms=(time.perf_counter() - t0) * 1e3)
    _readonly(hit_np, pos, nrm, depth_np, prim_np, p32, n32, fp, fn, fo, fine.position, fine.normal, fine.depth,
              fine.flat, fine.traced)
    return cp


def _fine_rays(mi, dr, rs, camera, fine: FinePoints, shape):
    """The edge pass's padded rays again (fine_points' own construction) to keep their float32 hit points
    and normals for the per-light receiver test."""
    h, w = shape
    f = fine.factor
    vj, vi = np.divmod(fine.traced, fine.grid_shape[1])
    _, d = fine_ray_directions(mi, camera, vj, vi, f, w, h)
    o = opaque3(mi, dr, mi.Point3f, camera.position - rs.origin)
    fwd = opaque3(mi, dr, mi.Vector3f, camera.forward)
    pi, ok, t, p, nrm = surface_hits(mi, dr, rs, mi.Ray3f(o, d), fwd, camera)
    dr.eval(ok, p, nrm)
    return (np.ascontiguousarray(p.numpy(), dtype=np.float32), np.ascontiguousarray(nrm.numpy(), dtype=np.float32),
            np.asarray(ok.numpy(), dtype=bool).copy())


def _vec(mi, cls, a: np.ndarray):
    return cls(*(mi.Float(a[k]) for k in range(3)))


def light_part(rs, camera, cp: CameraPass, lights, boundary_radius: int = DEFAULT_BOUNDARY_RADIUS) -> CoarseBuffers:
    """The lights' coarse buffers over a camera pass: render_coarse's shadow rays and tests, its boundary
    mask, and the edge pass's per-light receiver test (fine_points: light_test without shadow rays)."""
    mi = mitsuba()
    import drjit as dr  # lazy: loaded after mitsuba() has set its LLVM variant (renderers.mitsuba_setup)

    t0 = time.perf_counter()
    p, n, hit = _vec(mi, mi.Point3f, cp.p32), _vec(mi, mi.Vector3f, cp.n32), mi.Bool(cp.hit.ravel())
    masks = [light_test(mi, dr, rs, light, p, n, hit) for light in lights]
    fine = cp.fine
    fine_tests = []
    if fine is not None and cp.fine_p32 is not None:
        fp, fn, fo = _vec(mi, mi.Point3f, cp.fine_p32), _vec(mi, mi.Vector3f, cp.fine_n32), mi.Bool(cp.fine_ok)
        fine_tests = [light_test(mi, dr, rs, light, fp, fn, fo, shadow_rays=False) for light in lights]
    dr.eval(*[m for ms in masks for m in ms], *[m for ms in fine_tests for m in ms[1:]])
    dr.sync_thread()
    t1 = time.perf_counter()
    light_bufs = light_buffers(masks, cp.hit, cp.depth, boundary_radius)
    if fine is not None:
        if fine_tests:
            n_rays, fsize = fine.rays, len(cp.fine_ok)
            keep = cp.fine_ok[:n_rays]
            rec = [(mask_numpy(fac, fsize)[:n_rays] & mask_numpy(inl, fsize)[:n_rays])[keep]
                   for _, fac, inl in fine_tests]
        else:
            rec = [np.zeros(0, bool)] * len(lights)
        fine = replace(fine, receiver=rec)
    t2 = time.perf_counter()
    return CoarseBuffers(camera, cp.width, cp.height, cp.hit, cp.position, cp.normal, cp.depth, cp.prim_id,
                         light_bufs, {"camera_cached_ms": cp.trace_ms, "trace": (t1 - t0) * 1e3,
                                      "convert": (t2 - t1) * 1e3, "total": (t2 - t0) * 1e3}, fine)


def camera_key(camera, long_side: int, boundary_radius: int) -> tuple:
    """Every camera parameter the camera pass reads, exactly (bytes of the float64 values)."""
    vec = tuple(np.asarray(getattr(camera, k), dtype=np.float64).tobytes() for k in ("position", "forward", "up", "right"))
    return vec + (float(camera.fov_y_deg), float(camera.near), float(camera.far), tuple(int(v) for v in camera.resolution),
                  float(camera.tan_half_fov_y), float(camera.aspect), int(long_side), int(boundary_radius))


def pass_bytes(cp: CameraPass) -> int:
    """What a camera pass holds: its arrays' bytes (the receivers' memo is counted as it grows)."""
    arrays = tuple(getattr(cp, k, None) for k in ("hit", "position", "normal", "depth", "prim_id", "p32", "n32",
                                                  "fine_p32", "fine_n32", "fine_ok"))
    fine = getattr(cp, "fine", None)
    if fine is not None:
        arrays += tuple(getattr(fine, k, None) for k in ("position", "normal", "depth", "flat", "traced"))
    return sum(int(getattr(a, "nbytes", 0)) for a in arrays) + 4096


def _memo_bytes(out) -> int:
    return sum(int(getattr(a, "nbytes", 0)) for a in (out if isinstance(out, tuple) else (out,))) + 256


class CoarseCache:
    """LRU of camera passes, keyed per tenant and scene entry (held weakly), bounded in bytes (`max_bytes`,
    the server's coarse_cache_bytes) with a per-tenant share (service.tenant_lru: one tenant's cameras never
    push out another's) and in entries (`max_cameras`)."""

    def __init__(self, max_cameras: int = MAX_CAMERAS, max_bytes: int = DEFAULT_BYTES,
                 tenant_share: float = DEFAULT_TENANT_SHARE):
        self.max_cameras = int(max_cameras)
        self._lru = TenantLRU(max_bytes, tenant_share, name="coarse cache", max_entries=self.max_cameras)
        self.hits = 0
        self.misses = 0
        self.receiver_hits = 0
        self.receiver_misses = 0

    def configure(self, *, max_bytes: int | None = None, tenant_share: float | None = None) -> None:
        self._lru.configure(max_bytes=max_bytes, tenant_share=tenant_share)

    def stats(self) -> dict:
        """The byte accounting (service.tenant_lru) with this cache's camera-pass hits and misses."""
        return {**self._lru.stats(), "hits": self.hits, "misses": self.misses}

    def clear(self) -> None:
        self._lru.clear()

    def passes(self) -> list[CameraPass]:
        """The camera passes held, least recently used first."""
        return [cp for _, cp in self._lru.values()]

    def __len__(self) -> int:
        return len(self._lru)

    def camera_pass(self, tenant, entry, camera, long_side: int, boundary_radius: int) -> CameraPass:
        key = (id(entry),) + camera_key(camera, long_side, boundary_radius)
        got = self._lru.get(tenant, key)
        if got is not None and got[0]() is entry:  # the same live entry object (an id can be reused)
            self.hits += 1
            return got[1]
        cp = camera_pass(entry.rays, camera, long_side)
        cp.cache_key = (tenant, key)  # the receivers' memo counts what it adds against this entry
        self.misses += 1
        self._lru.put(tenant, key, (weakref.ref(entry), cp), pass_bytes(cp))
        self._lru.drop(lambda v: v[0]() is None)  # entries of dropped scenes
        return cp

    def receivers(self, cp: CameraPass, compute, camera, buffers, mask, bounds, fine_receivers):
        """service.receivers.receiver_points(camera, buffers, mask, bounds, fine_receivers) of this camera pass,
        memoized per (mask, fine receivers): a function of those and of the camera pass alone. A miss
        computes only the mask's share: the camera-only part (service.receivers.receiver_prep) is kept with
        the camera pass. What the memo adds is counted in the pass's bytes."""
        fr = None if fine_receivers is None else np.packbits(np.asarray(fine_receivers, bool)).tobytes()
        key = (np.packbits(mask).tobytes(), fr, None if fine_receivers is None else len(fine_receivers))
        with cp.lock:
            got = cp.receivers.get(key)
            if got is not None:
                cp.receivers.move_to_end(key)
                self.receiver_hits += 1
                return got
        prep = cp.receiver_prep
        grown = 0
        if prep is None and cp.receiver_misses:  # a second mask (a light moved): once per camera pass (two
            prep = cp.receiver_prep = receiver_prep(camera, buffers)  # threads may both make it: the same values)
            grown += sum(int(getattr(v, "nbytes", 0)) for v in vars(prep).values()) if hasattr(prep, "__dict__") else 0
        cp.receiver_misses += 1  # a camera seen once (an orbit or fly step) never pays for the prep
        out = compute(camera, buffers, mask, bounds, fine_receivers, prep=prep)
        _readonly(*out)
        with cp.lock:
            self.receiver_misses += 1
            cp.receivers[key] = out
            grown += _memo_bytes(out)
            while len(cp.receivers) > MAX_RECEIVER_MASKS:
                grown -= _memo_bytes(cp.receivers.popitem(last=False)[1])
        if getattr(cp, "cache_key", None) is not None:  # a pass of this cache's (not one made elsewhere)
            self._lru.grow(*cp.cache_key, grown)
        return out


COARSE = CoarseCache()


def cached_coarse_pass(entry, rig: dict, tenant, cache: CoarseCache | None = None,
                       boundary_radius: int = DEFAULT_BOUNDARY_RADIUS):
    """service.pipeline.coarse_pass with the camera part from `cache` (default: the process's): (resolved
    rig, buffers); the buffers carry `receivers_memo` for service.receivers.light_problems."""
    cache = COARSE if cache is None else cache
    resolved = resolve_rig(rig, entry.loaded)
    cp = cache.camera_pass(tenant, entry, resolved.camera, resolved.coarse_long_side, boundary_radius)
    buffers = light_part(entry.rays, resolved.camera, cp, resolved.lights, boundary_radius)
    buffers.receivers_memo = lambda compute, *a: cache.receivers(cp, compute, *a)
    return resolved, buffers
