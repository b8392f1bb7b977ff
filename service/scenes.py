"""Scenes loaded once, their Mitsuba ray scene built once, both kept in a process-wide cache."""
from __future__ import annotations

import os
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass

from ..renderers.ray_scene import RayScene, build_ray_scene
from ..renderers.scene_data import LoadedScene, SceneError
from ..renderers.usd_loader import load_scene


@dataclass
class SceneEntry:
    loaded: LoadedScene
    rays: RayScene
    load_s: float  # USD load + triangulation
    build_s: float  # Mitsuba scene build


class SceneCache:
    """LRU cache keyed by file identity (path, size, mtime) and load options."""

    def __init__(self, capacity: int = 8):
        self.capacity = capacity
        self._entries: OrderedDict[tuple, SceneEntry] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, path, *, time_code: float | None = None, asset_root: str | None = None,
            sandbox: bool = False) -> SceneEntry:
        try:
            st = os.stat(path)
        except OSError as e:
            raise SceneError("not_found", f"cannot open scene {os.fspath(path)!r}: {e.strerror}") from e
        key = (os.path.realpath(path), st.st_size, st.st_mtime_ns, time_code, asset_root, sandbox)
        with self._lock:
            if key in self._entries:
                self._entries.move_to_end(key)
                return self._entries[key]
        t0 = time.perf_counter()
        loaded = load_scene(path, time_code=time_code, asset_root=asset_root, sandbox=sandbox)
        t1 = time.perf_counter()
        rays = build_ray_scene(loaded.geometry)
        entry = SceneEntry(loaded, rays, t1 - t0, time.perf_counter() - t1)
        with self._lock:
            self._entries[key] = entry
            while len(self._entries) > self.capacity:
                self._entries.popitem(last=False)
        return entry

    def clear(self) -> None:
        with self._lock:
            self._entries.clear()


SCENES = SceneCache()
