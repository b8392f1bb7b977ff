"""Mesh prims -> (points, triangles) in their local frame: the arrays checked (a mesh that cannot be
read is skipped with a warning saying why), faces of fewer than 3 corners dropped, the rest triangulated
(renderers.triangulation); with a budget, the faces are charged from faceVertexCounts first.
"""
from __future__ import annotations

import numpy as np
from pxr import UsdGeom

from .triangulation import triangulate
from .usd_values import as_array, attr_value


def face_triangles(counts) -> int:
    """Triangles a faceVertexCounts array stands for: n - 2 per face of n >= 3 corners."""
    c = as_array(counts, None, np.int64)
    if c is None or not len(c):
        return 0
    c = c[c >= 3]
    return int(np.sum(c - 2)) if len(c) else 0


def mesh_triangles(prim, time_code, warnings, charge=None):
    """(points, triangles) of a Mesh or None; with `charge`, its faces are charged from
    faceVertexCounts before points and indices are read or anything is triangulated."""
    if charge is None:
        return _mesh_geometry(prim, time_code, warnings)
    est = face_triangles(attr_value(UsdGeom.Mesh(prim).GetFaceVertexCountsAttr(), time_code))
    charge(est, str(prim.GetPath()))
    r = _mesh_geometry(prim, time_code, warnings)
    charge((len(r[1]) if r is not None else 0) - est, str(prim.GetPath()))  # what it really made
    return r


def _mesh_geometry(prim, time_code, warnings):
    path = str(prim.GetPath())
    mesh = UsdGeom.Mesh(prim)
    raw_pts = attr_value(mesh.GetPointsAttr(), time_code, warnings)
    raw_counts = attr_value(mesh.GetFaceVertexCountsAttr(), time_code, warnings)
    raw_idx = attr_value(mesh.GetFaceVertexIndicesAttr(), time_code, warnings)
    if raw_pts is None or raw_counts is None or raw_idx is None:
        missing = [n for n, v in (("points", raw_pts), ("faceVertexCounts", raw_counts),
                                  ("faceVertexIndices", raw_idx)) if v is None]
        warnings.append(f"{path}: skipped, no {', '.join(missing)}")
        return None
    pts = as_array(raw_pts, 3, np.float64)
    counts = as_array(raw_counts, None, np.int64)
    idx = as_array(raw_idx, None, np.int64)
    if pts is None:
        warnings.append(f"{path}: skipped, its points are not an array of 3-vectors "
                        f"(got a {type(raw_pts).__name__})")
        return None
    if counts is None or idx is None:
        warnings.append(f"{path}: skipped, faceVertexCounts/faceVertexIndices are not integer arrays")
        return None
    if len(pts) == 0 or len(counts) == 0:
        warnings.append(f"{path}: skipped, the mesh is empty")
        return None
    if not np.all(np.isfinite(pts)):
        warnings.append(f"{path}: skipped, its points contain NaN or infinite values")
        return None
    if np.any(counts < 0) or counts.sum() != len(idx):
        warnings.append(f"{path}: skipped, faceVertexCounts sum to {int(counts.sum())} but there are "
                        f"{len(idx)} faceVertexIndices")
        return None
    if len(idx) and (idx.min() < 0 or idx.max() >= len(pts)):
        warnings.append(f"{path}: skipped, faceVertexIndices range over [{int(idx.min())}, {int(idx.max())}] "
                        f"but there are {len(pts)} points")
        return None
    small = counts < 3
    if small.any():
        warnings.append(f"{path}: {int(small.sum())} faces with fewer than 3 vertices dropped")
        keep = np.repeat(~small, counts)
        idx, counts = idx[keep], counts[~small]
        if len(counts) == 0:
            return None
    tris = triangulate(pts, counts, idx)
    if mesh.GetOrientationAttr().Get() == UsdGeom.Tokens.leftHanded:
        tris = tris[:, ::-1]  # keep every triangle counter-clockwise about its outward normal
    return pts, tris
