"""Scenes loaded once, their Mitsuba ray scene built once, both kept in a process-wide cache.

- Single flight: concurrent gets of one key share one load; a failure reaches every waiter, is not
  cached, and the next get tries again.
- Bounded in entries and in bytes (an entry's bytes: its geometry arrays' nbytes times BYTES_FACTOR,
  which covers the Mitsuba copy of the mesh and its acceleration structure; measured below), and each
  owner (a tenant; None is the CLI and warm-up; in a batch worker, the batch's tenant) holds at most `tenant_share` of
  either: an owner inserting past its share loses its own least recently used entries first, so one
  tenant's many small uploads cannot push out another tenant's scene. A tenant's scene whose entry
  would exceed that share is refused, SceneError("too_large_for_cache") (the server answers 413), before
  the Mitsuba build and without a reload on the next request (the refusal is remembered by file
  identity); the other owners' are served uncached.
- With `limits` (uploaded scenes) the USD load runs in a spawned child with a memory and a wall-clock
  limit (service.isolation.load_isolated); the Mitsuba scene is then built here, in the parent.
"""
from __future__ import annotations

import logging
import os
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass

from ..renderers.ray_scene import RayScene, build_ray_scene
from ..renderers.scene_data import LoadedScene, SceneError
from ..renderers.usd_loader import load_scene
from .isolation import LoadLimits, load_isolated

__all__ = ["SCENES", "BYTES_FACTOR", "LoadLimits", "SceneCache", "SceneEntry", "entry_bytes"]

log = logging.getLogger("shadowopt.scenes")

# Process RSS growth for a cached entry over its geometry arrays' nbytes (vertices float64, faces and
# face_prim int32). Measured on the chess set (1.43 M triangles, 38.2 MB of arrays), three entries in a
# row: loaded in a child (limits) and the Mitsuba scene built in the parent, the parent grew by 180, 178
# and 162 MB (ratios 4.7, 4.7, 4.2); loaded in-process, by 204, 163, 179 MB (5.3, 4.3, 4.7). The
# LoadedScene's arrays, Mitsuba's float32/uint32 copies and its acceleration structure. Rounded up.
BYTES_FACTOR = 5.0
DEFAULT_CAPACITY = 8
DEFAULT_MAX_BYTES = 2 << 30
DEFAULT_TENANT_SHARE = 0.5
TOO_LARGE_MEMO = 256  # scenes remembered as too large for the cache (a refusal repeated without a load)


def _mib(n: int) -> str:
    return f"{n / 2**20:.1f} MiB ({n} bytes)"


@dataclass
class SceneEntry:
    loaded: LoadedScene
    rays: RayScene
    load_s: float  # USD load + triangulation (in the child, spawn included, when isolated)
    build_s: float  # Mitsuba scene build
    nbytes: int = 0  # the cache's estimate of what the entry holds (entry_bytes)


def entry_bytes(loaded: LoadedScene) -> int:
    g = loaded.geometry
    arrays = sum(int(getattr(a, "nbytes", 0)) for a in (g.vertices, g.faces, g.face_prim))
    return int(arrays * BYTES_FACTOR) + 64 * len(g.prim_paths) + 4096


def _check_triangles(entry: SceneEntry, max_triangles: int | None) -> None:
    n = entry.loaded.geometry.triangle_count
    if max_triangles is not None and n > max_triangles:
        raise SceneError("too_many_triangles", f"the scene has {n} triangles, more than the limit of "
                         f"{max_triangles}; refused")


@dataclass
class _Slot:
    entry: SceneEntry
    owner: str | None
    nbytes: int


class _Flight:
    def __init__(self):
        self.done = threading.Event()
        self.entry: SceneEntry | None = None
        self.error: BaseException | None = None
        self.waiters = 0


class SceneCache:
    """LRU cache keyed by file identity (path, size, mtime) and load options."""

    def __init__(self, capacity: int = DEFAULT_CAPACITY, max_bytes: int = DEFAULT_MAX_BYTES,
                 tenant_share: float = DEFAULT_TENANT_SHARE):
        self._entries: OrderedDict[tuple, _Slot] = OrderedDict()
        self._inflight: dict[tuple, _Flight] = {}
        self._too_large: OrderedDict[tuple, int] = OrderedDict()  # keys refused as too_large_for_cache -> bytes
        self._lock = threading.Lock()
        self.loads = 0  # loads started (a hit or a shared load does not count)
        self.hits = 0
        self.shared = 0  # gets that waited for another get's load
        self.evictions = 0
        self.configure(capacity=capacity, max_bytes=max_bytes, tenant_share=tenant_share)

    # configuration and introspection
    def configure(self, *, capacity: int | None = None, max_bytes: int | None = None,
                  tenant_share: float | None = None) -> None:
        """Set the bounds (the server calls this at start); entries over the new bounds are evicted."""
        capacity = self.__dict__.get("capacity") if capacity is None else capacity
        max_bytes = self.__dict__.get("max_bytes") if max_bytes is None else max_bytes
        tenant_share = self.__dict__.get("tenant_share") if tenant_share is None else tenant_share
        if not isinstance(capacity, int) or isinstance(capacity, bool) or capacity < 1:
            raise ValueError(f"capacity must be a positive integer, got {capacity!r}")
        if not isinstance(max_bytes, int) or isinstance(max_bytes, bool) or max_bytes < 1:
            raise ValueError(f"max_bytes must be a positive integer, got {max_bytes!r}")
        if not isinstance(tenant_share, (int, float)) or not 0 < tenant_share <= 1:
            raise ValueError(f"tenant_share must be in (0, 1], got {tenant_share!r}")
        with self._lock:
            self.capacity, self.max_bytes, self.tenant_share = capacity, max_bytes, float(tenant_share)
            for owner in {s.owner for s in self._entries.values()}:
                self._trim_owner(owner, 0, keep_room=False)
            self._trim_all(0, keep_room=False)

    def owner_limits(self) -> tuple[int, int]:
        """(entries, bytes) one owner may hold."""
        return max(1, int(self.capacity * self.tenant_share)), int(self.max_bytes * self.tenant_share)

    def stats(self) -> dict:
        with self._lock:
            owners: dict = {}
            for s in self._entries.values():
                n, b = owners.get(s.owner, (0, 0))
                owners[s.owner] = (n + 1, b + s.nbytes)
            return {"entries": len(self._entries), "bytes": sum(s.nbytes for s in self._entries.values()),
                    "loads": self.loads, "hits": self.hits, "shared": self.shared, "evictions": self.evictions,
                    "loading": len(self._inflight), "owners": owners}

    def owner_of(self, path, **options) -> str | None:
        """The owner of the cached entry for (path, options); KeyError when not cached."""
        key = self._key(path, **options)
        with self._lock:
            return self._entries[key].owner

    def __contains__(self, path) -> bool:
        try:
            key = self._key(path)
        except SceneError:
            return False
        with self._lock:
            return key in self._entries

    # the cache
    @staticmethod
    def _key(path, time_code: float | None = None, asset_root: str | None = None, sandbox: bool = False) -> tuple:
        try:
            st = os.stat(path)
        except OSError as e:
            name = os.path.basename(os.fspath(path))
            raise SceneError("not_found", f"cannot open scene {name!r}: {e.strerror}") from None
        return (os.path.realpath(path), st.st_size, st.st_mtime_ns, time_code, asset_root, sandbox)

    def loading(self, path, *, time_code: float | None = None, asset_root: str | None = None, sandbox: bool = False,
                tenant: str | None = None, limits: LoadLimits | None = None) -> bool:
        """True while a load of this key is in flight (a get now would wait for it instead of loading):
        the server lets only a load's leader hold a load slot. tenant and limits are not part of the key."""
        try:
            key = self._key(path, time_code, asset_root, sandbox)
        except SceneError:
            return False
        with self._lock:
            return key in self._inflight

    def peek(self, path, *, time_code: float | None = None, asset_root: str | None = None, sandbox: bool = False,
             tenant: str | None = None, limits: LoadLimits | None = None) -> SceneEntry | None:
        """The cached entry (counted as a use), or None: never loads, never waits for a load."""
        try:
            key = self._key(path, time_code, asset_root, sandbox)
        except SceneError:
            return None
        with self._lock:
            slot = self._entries.get(key)
            if slot is None:
                return None
            self._entries.move_to_end(key)
            self.hits += 1
            return slot.entry

    def get(self, path, *, time_code: float | None = None, asset_root: str | None = None, sandbox: bool = False,
            tenant: str | None = None, limits: LoadLimits | None = None,
            max_triangles: int | None = None, owner: str | None = None) -> SceneEntry:
        """The entry for (path, options), loaded once. `limits`: the load runs isolated (see the module
        docstring). `max_triangles` (without limits: an in-process load, as in a batch worker, which is its
        own process already): the loader refuses the scene while counting; with limits, theirs applies.
        A cached entry over the triangle limit of this get (loaded before the limit was lowered) is
        refused too, SceneError("too_many_triangles"). `owner` (without `tenant`: a batch worker's) owns the
        entry in the cache's per-owner share without the tenant's refusal: over the share it is served uncached."""
        if limits is not None:
            max_triangles = limits.max_triangles
        key = self._key(path, time_code, asset_root, sandbox)
        with self._lock:
            slot = self._entries.get(key)
            if slot is not None:
                self._entries.move_to_end(key)
                self.hits += 1
                _check_triangles(slot.entry, max_triangles)
                return slot.entry
            if tenant is not None and key in self._too_large:  # refused before: do not load it again
                refusal = self._too_large_error(self._too_large[key])
                if refusal is not None:
                    raise refusal
            flight = self._inflight.get(key)
            leader = flight is None
            if leader:
                flight = self._inflight[key] = _Flight()
                self.loads += 1
            else:
                flight.waiters += 1
                self.shared += 1
        if not leader:
            flight.done.wait()
            if flight.error is not None:
                e = flight.error
                if isinstance(e, SceneError):
                    raise SceneError(e.code, e.message) from None
                raise RuntimeError(f"the shared load failed: {type(e).__name__}: {e}") from e
            _check_triangles(flight.entry, max_triangles)  # the leader's limit may have been another
            return flight.entry
        try:
            entry = self._load(path, time_code, asset_root, sandbox, limits, tenant, max_triangles)
        except BaseException as e:
            if isinstance(e, SceneError) and e.code == "too_large_for_cache":
                with self._lock:
                    self._too_large[key] = e.nbytes
                    while len(self._too_large) > TOO_LARGE_MEMO:
                        self._too_large.popitem(last=False)
            with self._lock:
                flight.error = e
                del self._inflight[key]
            flight.done.set()
            raise
        with self._lock:
            flight.entry = entry
            del self._inflight[key]
            self._insert(key, entry, tenant if tenant is not None else owner)
        flight.done.set()
        return entry

    def _too_large_error(self, nbytes: int) -> SceneError | None:
        """The refusal of a tenant's scene whose entry would not fit in one tenant's share of the cache."""
        _, max_b = self.owner_limits()
        if nbytes <= max_b:
            return None
        e = SceneError("too_large_for_cache",
                       f"the scene needs about {_mib(nbytes)} in the scene cache, more than one tenant's share of it, "
                       f"{_mib(max_b)} (scene_cache_bytes {self.max_bytes} x tenant_cache_share "
                       f"{self.tenant_share:g}); refused, as it would be loaded again for every request")
        e.nbytes = nbytes
        return e

    def _load(self, path, time_code, asset_root, sandbox, limits, tenant=None, max_triangles=None) -> SceneEntry:
        t0 = time.perf_counter()
        if limits is not None:
            loaded = load_isolated(path, time_code=time_code, asset_root=asset_root, sandbox=sandbox, limits=limits)
        else:
            loaded = load_scene(path, time_code=time_code, asset_root=asset_root, sandbox=sandbox,
                                max_triangles=max_triangles)
        t1 = time.perf_counter()
        nbytes = entry_bytes(loaded)
        if tenant is not None:  # before the Mitsuba build: a tenant's scene is cached or refused, never rebuilt
            refusal = self._too_large_error(nbytes)
            if refusal is not None:
                raise refusal
        rays = build_ray_scene(loaded.geometry)
        return SceneEntry(loaded, rays, t1 - t0, time.perf_counter() - t1, nbytes)

    # eviction (the lock held)
    def _owner_usage(self, owner) -> tuple[int, int]:
        n = b = 0
        for s in self._entries.values():
            if s.owner == owner:
                n += 1
                b += s.nbytes
        return n, b

    def _evict(self, key) -> None:
        del self._entries[key]
        self.evictions += 1

    def _trim_owner(self, owner, nbytes: int, keep_room: bool = True) -> None:
        """Evict `owner`'s least recently used entries until one more of `nbytes` fits in its share."""
        max_n, max_b = self.owner_limits()
        extra = 1 if keep_room else 0
        n, b = self._owner_usage(owner)
        for key in [k for k, s in self._entries.items() if s.owner == owner]:  # oldest first
            if n + extra <= max_n and b + nbytes <= max_b:
                break
            b -= self._entries[key].nbytes
            n -= 1
            self._evict(key)

    def _trim_all(self, nbytes: int, keep_room: bool = True) -> None:
        extra = 1 if keep_room else 0
        total = sum(s.nbytes for s in self._entries.values())
        while self._entries and (len(self._entries) + extra > self.capacity or total + nbytes > self.max_bytes):
            key = next(iter(self._entries))
            total -= self._entries[key].nbytes
            self._evict(key)

    def _insert(self, key, entry: SceneEntry, owner: str | None) -> None:
        nbytes = entry.nbytes or entry_bytes(entry.loaded)
        _, max_b = self.owner_limits()
        if nbytes > max_b:
            # the CLI, warm-up and batch workers only (a tenant's is refused in _load): served to the caller
            # for this request, as caching it would push out everything else
            log.info("scene not cached: %d estimated bytes over the per-owner cache share of %d", nbytes, max_b)
            return
        self._trim_owner(owner, nbytes)
        self._trim_all(nbytes)
        self._entries[key] = _Slot(entry, owner, nbytes)

    def clear(self) -> None:
        with self._lock:
            self._entries.clear()


SCENES = SceneCache()
