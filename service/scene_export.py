"""A loaded scene's triangles as binary glTF 2.0 (GLB) for the browser inspector.

The mesh is written by trimesh (its glTF exporter) in the solutions' world frame: right-handed, +Y up,
metres, which is glTF's own frame (glTF 2.0 specification, section 3.4: +Y up, metres). The vertices are
re-centred on the bounds' centre before the float32 conversion, as the ray scene does
(renderers.ray_scene), and the centre is the root node's translation, so a viewer that applies the node
transform sees world coordinates and one that re-centres (the inspector, for float32 precision) reads it
from the node.

Above `max_triangles` the mesh is decimated by quadric edge collapse (Garland and Heckbert 1997; the
pyfqmr package, Fast-Quadric-Mesh-Simplification) to at most that many triangles, open borders kept (a
ground plane's quad is planar, so collapsing its corners costs no quadric error: without the border rule
a decimated scene loses its ground); `ExportInfo` says how many the scene has and how many were served.
A decimated mesh is a preview: its shadows are not the scene's.
"""
from __future__ import annotations

import io
import threading
from collections import OrderedDict
from dataclasses import asdict, dataclass

import numpy as np
import pyfqmr

from ..renderers.scene_data import LoadedScene

__all__ = ["DEFAULT_TRIANGLE_BUDGET", "MAX_TRIANGLE_BUDGET", "ExportInfo", "scene_glb"]

DEFAULT_TRIANGLE_BUDGET = 300_000
MAX_TRIANGLE_BUDGET = 2_000_000
_CACHE_ENTRIES = 8


@dataclass(frozen=True)
class ExportInfo:
    triangles: int  # the scene's
    served_triangles: int  # in the GLB
    budget: int  # max_triangles asked for
    decimated: bool
    origin: tuple[float, float, float]  # the root node's translation (world metres)
    bytes: int

    def to_json(self) -> dict:
        return asdict(self)


_cache: OrderedDict[tuple, tuple[bytes, ExportInfo]] = OrderedDict()
_lock = threading.Lock()


def scene_glb(loaded: LoadedScene, max_triangles: int = DEFAULT_TRIANGLE_BUDGET) -> tuple[bytes, ExportInfo]:
    """(GLB bytes, ExportInfo) of the scene's triangles, decimated to at most `max_triangles`.
    Kept per (scene hash, time code, budget) for the few last scenes asked for."""
    if not isinstance(max_triangles, int) or max_triangles < 1:
        raise ValueError(f"max_triangles must be a positive integer, got {max_triangles!r}")
    key = (loaded.scene_hash, loaded.time_code, loaded.geometry.triangle_count, max_triangles)
    with _lock:
        hit = _cache.get(key)
        if hit is not None:
            _cache.move_to_end(key)
            return hit
    out = _export(loaded, max_triangles)
    with _lock:
        _cache[key] = out
        while len(_cache) > _CACHE_ENTRIES:
            _cache.popitem(last=False)
    return out


def _export(loaded: LoadedScene, max_triangles: int) -> tuple[bytes, ExportInfo]:
    import trimesh  # lazy: seconds to import; loaded on the first GLB export, not at server start

    g = loaded.geometry
    lo, hi = g.bounds()
    origin = (lo + hi) / 2.0  # the ray scene's re-centring (renderers.ray_scene)
    vertices = np.asarray(g.vertices, dtype=np.float64) - origin
    faces = np.asarray(g.faces, dtype=np.int64).reshape(-1, 3)
    n = int(faces.shape[0])
    decimated = n > max_triangles
    if decimated:
        simplify = pyfqmr.Simplify()
        simplify.setMesh(vertices, faces)
        simplify.simplify_mesh(target_count=max_triangles, aggressiveness=7, preserve_border=True, verbose=False)
        vertices, faces, _ = simplify.getMesh()
        faces = np.asarray(faces, dtype=np.int64)[:max_triangles]  # the collapse stops at or near the target
    mesh = trimesh.Trimesh(vertices=vertices, faces=faces, process=False, validate=False)
    mesh.vertices = np.asarray(mesh.vertices, dtype=np.float32).astype(np.float64)
    scene = trimesh.Scene()
    transform = np.eye(4)
    transform[:3, 3] = origin
    scene.add_geometry(mesh, node_name="scene", geom_name="triangles", transform=transform)
    buf = io.BytesIO()
    scene.export(buf, file_type="glb", include_normals=False)
    data = buf.getvalue()
    info = ExportInfo(n, int(len(mesh.faces)), max_triangles, decimated, tuple(float(v) for v in origin), len(data))
    return data, info
