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

The export is a heavy derivation of a tenant's scene (4.95 M triangles: 21.6 s and +2.66 GB in the
server process, issue 27), so `glb_isolated` bounds it first and runs it as a scene load runs:
- `export_estimate` gives its size before any work: a scene over `max_export_triangles`, or whose GLB
  would be over `max_export_bytes`, is refused (the server answers 413) without starting;
- the decimation and the glTF writer run in a child process (service.isolation.run_isolated) with the
  load memory and time limits, in a solver slot of the request's admission;
- the GLB is kept per (tenant, scene, budget) in `GLB_CACHE`, a service.tenant_lru.TenantLRU bounded in
  bytes (`geometry_cache_bytes`, part of the server's `cache_bytes`) with a per-tenant share.
"""
from __future__ import annotations

import io
from dataclasses import asdict, dataclass

import numpy as np

from ..renderers.scene_data import LoadedScene, SceneError
from .isolation import DEFAULT_MEMORY_BYTES, DEFAULT_TIMEOUT_S, run_isolated
from .tenant_lru import TenantLRU

__all__ = ["DEFAULT_TRIANGLE_BUDGET", "MAX_TRIANGLE_BUDGET", "GLB_CACHE", "ExportInfo", "cached_glb",
           "export_estimate", "glb_arrays", "glb_isolated"]

DEFAULT_TRIANGLE_BUDGET = 300_000
MAX_TRIANGLE_BUDGET = 2_000_000
GLB_HEADER_BYTES = 4096  # the GLB and glTF JSON headers, rounded up
GLB_CACHE = TenantLRU(256 << 20, 0.5, name="geometry cache")  # sized by the server (api.service_state)


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


def export_estimate(loaded: LoadedScene, max_triangles: int) -> tuple[int, int]:
    """(the scene's triangles, an upper bound of the GLB's bytes) before any work: float32 positions
    (12 bytes a vertex, at most three per served triangle) and uint32 indices (12 bytes a triangle)."""
    g = loaded.geometry
    n = g.triangle_count
    served = min(n, max_triangles)
    vertices = min(int(g.vertices.shape[0]), 3 * served)
    return n, 12 * vertices + 12 * served + GLB_HEADER_BYTES


def _check_budget(max_triangles) -> None:
    if isinstance(max_triangles, bool) or not isinstance(max_triangles, int) or max_triangles < 1:
        raise ValueError(f"max_triangles must be a positive integer, got {max_triangles!r}")


def _cache_key(loaded: LoadedScene, max_triangles: int) -> tuple:
    return (loaded.scene_hash, loaded.time_code, loaded.geometry.triangle_count, max_triangles)


def cached_glb(loaded: LoadedScene, max_triangles: int, tenant) -> tuple[bytes, ExportInfo] | None:
    """The tenant's GLB of this scene and budget from GLB_CACHE, or None (nothing is made)."""
    return GLB_CACHE.get(tenant, _cache_key(loaded, max_triangles))


def glb_isolated(loaded: LoadedScene, max_triangles: int, *, tenant, max_export_triangles: int,
                 max_export_bytes: int, memory_bytes: int = DEFAULT_MEMORY_BYTES,
                 timeout_s: float = DEFAULT_TIMEOUT_S, what: str = "the scene") -> tuple[bytes, ExportInfo, bool]:
    """(GLB bytes, ExportInfo, from the cache) of the scene: from GLB_CACHE, else refused over the bounds
    (SceneError too_many_triangles / too_large, before any work), else made in a child process with
    `memory_bytes` of address space and `timeout_s` of wall clock, and kept in GLB_CACHE."""
    _check_budget(max_triangles)
    hit = cached_glb(loaded, max_triangles, tenant)
    if hit is not None:
        return hit[0], hit[1], True
    key = _cache_key(loaded, max_triangles)
    n, size = export_estimate(loaded, max_triangles)
    if n > max_export_triangles:
        raise SceneError("too_many_triangles", f"the scene has {n} triangles, more than the geometry export's "
                         f"limit of {max_export_triangles} (max_export_triangles); refused before any work")
    if size > max_export_bytes:
        raise SceneError("export_too_large", f"the scene's GLB at max_triangles {max_triangles} would take up to {size} "
                         f"bytes, more than the geometry export's limit of {max_export_bytes} "
                         "(max_export_bytes); ask for a smaller max_triangles")
    g = loaded.geometry
    lo, hi = g.bounds()
    try:
        data, info = run_isolated(glb_arrays, (g.vertices, g.faces, (lo + hi) / 2.0, max_triangles),
                                  memory_bytes=memory_bytes, timeout_s=timeout_s, what=f"the geometry export of {what}")
    except SceneError as e:  # run_isolated words its limits for a load: this is an export
        raise SceneError(e.code, e.message.replace("loading the geometry export", "exporting the geometry")
                         .replace("(the load memory limit)", "(load_memory_bytes)")
                         .replace("(the load time limit)", "(load_timeout_s)")) from None
    GLB_CACHE.put(tenant, key, (data, info), len(data))
    return data, info, False


def glb_arrays(vertices: np.ndarray, faces: np.ndarray, origin: np.ndarray,
               max_triangles: int) -> tuple[bytes, ExportInfo]:
    """The GLB of a triangle mesh re-centred on `origin` (the root node's translation), decimated above
    `max_triangles`. Runs in a child process in the server (glb_isolated)."""
    import pyfqmr  # lazy: the decimation runs in an export child, not in the server process
    import trimesh  # lazy: seconds to import; loaded in an export child, not at server start

    origin = np.asarray(origin, dtype=np.float64)  # the ray scene's re-centring (renderers.ray_scene)
    vertices = np.asarray(vertices, dtype=np.float64) - origin
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
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
