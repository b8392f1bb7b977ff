"""Build one Mitsuba scene from a SceneGeometry: all triangles merged into a single mesh.

One shape keeps ray casting from dispatching per object; vertices are re-centred on the scene's
bounding-box centre (`origin`) before the float32 upload, so scenes far from the world origin keep
their precision. Everything that casts rays adds `origin` back to get world coordinates.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from .mitsuba_setup import mitsuba
from .scene_data import SceneError, SceneGeometry


@dataclass
class RayScene:
    scene: object  # mi.Scene
    origin: np.ndarray  # float64 world position subtracted from every vertex
    extent: float  # bounding-box diagonal, meters
    vertices: object  # mi.Float, flat xyz (re-centred), for gathers
    faces: object  # mi.UInt32, flat vertex indices
    face_prim: object  # mi.UInt32, face -> prim index
    triangles: int
    build_s: float


def build_ray_scene(geometry: SceneGeometry) -> RayScene:
    mi = mitsuba()
    import drjit as dr  # lazy: after mitsuba(), which points Dr.Jit at its libLLVM (solvers.jit)

    t0 = time.perf_counter()
    if geometry.triangle_count == 0:
        raise SceneError("empty_stage", "the scene has no renderable triangles")
    lo, hi = geometry.bounds()
    origin = (lo + hi) / 2.0
    verts = (geometry.vertices - origin).astype(np.float32)
    faces = np.ascontiguousarray(geometry.faces, dtype=np.uint32)
    mesh = mi.Mesh("merged", verts.shape[0], faces.shape[0])
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(verts.ravel())
    params["faces"] = mi.UInt32(faces.ravel())
    params.update()
    scene = mi.load_dict({"type": "scene", "merged": mesh})
    vbuf = mi.Float(verts.ravel())
    fbuf = mi.UInt32(faces.ravel())
    pbuf = mi.UInt32(np.ascontiguousarray(geometry.face_prim, dtype=np.uint32))
    dr.eval(vbuf, fbuf, pbuf)
    return RayScene(scene, origin, float(np.linalg.norm(hi - lo)), vbuf, fbuf, pbuf,
                    geometry.triangle_count, time.perf_counter() - t0)
