"""A byte-bounded LRU of tenant data with a per-tenant share: the bound of the caches that hold what a tenant
computed (service.coarse_cache's camera passes, service.scene_export's GLB files).

- The whole cache holds at most `max_bytes` (the entries' own estimates, `put(..., nbytes)`);
- one owner (a tenant) holds at most `max_bytes x tenant_share`: an owner inserting past its share loses
  its own least recently used entries first, so one tenant's many requests cannot push out another
  tenant's working set; only when the whole cache is full does the least recently used entry of any owner
  go (and then only that of an owner over its fair part, `max_bytes / owners`, when there is one);
- optionally at most `max_entries` entries (the oldest go first, on the same rule);
- an entry over one owner's share is not kept at all (`put` answers False): caching it would push out
  everything else of its owner.
service.scenes.SceneCache keeps its own bookkeeping (single flight, too-large memo) on the same rule.
"""
from __future__ import annotations

import threading
from collections import OrderedDict
from typing import Any, Hashable


class TenantLRU:
    """LRU of (owner, key) -> value, bounded in bytes in total and per owner."""

    def __init__(self, max_bytes: int, tenant_share: float = 0.5, name: str = "cache", max_entries: int | None = None):
        self.name, self.max_entries = name, max_entries
        self._d: OrderedDict[tuple, tuple[Any, int]] = OrderedDict()  # (owner, key) -> (value, nbytes)
        self._lock = threading.Lock()
        self.hits = self.misses = self.evictions = self.refused = 0
        self.configure(max_bytes=max_bytes, tenant_share=tenant_share)

    def configure(self, *, max_bytes: int | None = None, tenant_share: float | None = None) -> None:
        max_bytes = self.__dict__.get("max_bytes") if max_bytes is None else max_bytes
        tenant_share = self.__dict__.get("tenant_share") if tenant_share is None else tenant_share
        if not isinstance(max_bytes, int) or isinstance(max_bytes, bool) or max_bytes < 1:
            raise ValueError(f"{self.name}: max_bytes must be a positive integer, got {max_bytes!r}")
        if not isinstance(tenant_share, (int, float)) or not 0 < tenant_share <= 1:
            raise ValueError(f"{self.name}: tenant_share must be in (0, 1], got {tenant_share!r}")
        with self._lock:
            self.max_bytes, self.tenant_share = max_bytes, float(tenant_share)
            for owner in {o for o, _ in self._d}:
                self._trim_owner(owner, 0)
            self._trim_all(0)

    @property
    def owner_bytes(self) -> int:
        return int(self.max_bytes * self.tenant_share)

    def get(self, owner, key: Hashable):
        with self._lock:
            got = self._d.get((owner, key))
            if got is None:
                self.misses += 1
                return None
            self._d.move_to_end((owner, key))
            self.hits += 1
            return got[0]

    def put(self, owner, key: Hashable, value, nbytes: int) -> bool:
        """Keep `value` (about `nbytes`); False when it is over one owner's share (not kept)."""
        nbytes = max(1, int(nbytes))
        with self._lock:
            self._d.pop((owner, key), None)
            if nbytes > self.owner_bytes:
                self.refused += 1
                return False
            self._trim_owner(owner, nbytes)
            self._trim_all(nbytes, extra=1)
            self._d[(owner, key)] = (value, nbytes)
            return True

    def grow(self, owner, key: Hashable, extra: int) -> None:
        """An entry grew by `extra` bytes (a memo inside it): counted, and the bounds applied again (the
        entry itself is kept if it alone still fits its owner's share)."""
        with self._lock:
            got = self._d.get((owner, key))
            if got is None:
                return
            self._d[(owner, key)] = (got[0], got[1] + int(extra))
            self._d.move_to_end((owner, key))
            self._trim_owner(owner, 0, keep=(owner, key))
            self._trim_all(0, keep=(owner, key))

    def drop(self, predicate) -> None:
        """Remove the entries whose value satisfies predicate(value) (a dropped scene's, say)."""
        with self._lock:
            for k in [k for k, (v, _) in self._d.items() if predicate(v)]:
                del self._d[k]

    def values(self) -> list:
        """The values held, least recently used first."""
        with self._lock:
            return [v for v, _ in self._d.values()]

    def clear(self) -> None:
        with self._lock:
            self._d.clear()

    def __len__(self) -> int:
        return len(self._d)

    def stats(self) -> dict:
        with self._lock:
            owners: dict = {}
            for (o, _), (_, b) in self._d.items():
                owners[o] = owners.get(o, 0) + b
            return {"entries": len(self._d), "bytes": sum(owners.values()), "max_bytes": self.max_bytes,
                    "owner_bytes": self.owner_bytes, "hits": self.hits, "misses": self.misses,
                    "evictions": self.evictions, "refused": self.refused, "owners": owners}

    # eviction (the lock held)
    def _usage(self, owner) -> int:
        return sum(b for (o, _), (_, b) in self._d.items() if o == owner)

    def _trim_owner(self, owner, nbytes: int, keep=None) -> None:
        used = self._usage(owner)
        for k in [k for k in self._d if k[0] == owner and k != keep]:  # oldest first
            if used + nbytes <= self.owner_bytes:
                break
            used -= self._d.pop(k)[1]
            self.evictions += 1

    def _trim_all(self, nbytes: int, keep=None, extra: int = 0) -> None:
        total = sum(b for _, b in self._d.values())
        cap = self.max_entries if self.max_entries is not None else len(self._d) + extra
        while total + nbytes > self.max_bytes or len(self._d) + extra > cap:
            owners: dict = {}
            for (o, _), (_, b) in self._d.items():
                owners[o] = owners.get(o, 0) + b
            fair = self.max_bytes / max(1, len(owners))
            over = {o for o, b in owners.items() if b > fair}
            victim = next((k for k in self._d if k != keep and (not over or k[0] in over)), None)
            if victim is None:
                return
            total -= self._d.pop(victim)[1]
            self.evictions += 1
