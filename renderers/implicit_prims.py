"""UsdGeom implicit prims tessellated in their local frame.

- Implicit prims (Cube, Sphere, Cylinder, Cone, Capsule, Plane, and the *_1 variants) are tessellated.
"""
from __future__ import annotations

import math

import numpy as np

from .usd_values import attr_value

SEGMENTS = 32  # tessellation of implicit round prims (around), half of it along


def _axis_matrix(axis: str) -> np.ndarray:
    """Rotation taking +Z to the given axis (a cyclic permutation of coordinates)."""
    if axis == "X":
        return np.array([[0, 0, 1], [1, 0, 0], [0, 1, 0]], float)
    if axis == "Y":
        return np.array([[0, 1, 0], [0, 0, 1], [1, 0, 0]], float)
    return np.eye(3)


def _revolve(profile: list[tuple[float, float]], seg: int = SEGMENTS):
    """Surface of revolution about +Z of a (radius, z) profile; zero radius collapses to a point."""
    ang = np.linspace(0, 2 * np.pi, seg, endpoint=False)
    verts, faces = [], []
    rings = []
    for r, z in profile:
        if r == 0:
            rings.append([len(verts)])
            verts.append((0.0, 0.0, z))
        else:
            rings.append(list(range(len(verts), len(verts) + seg)))
            verts += [(r * math.cos(a), r * math.sin(a), z) for a in ang]
    for ra, rb in zip(rings[:-1], rings[1:]):
        for i in range(seg):
            j = (i + 1) % seg
            a0, a1 = ra[i % len(ra)], ra[j % len(ra)]
            b0, b1 = rb[i % len(rb)], rb[j % len(rb)]
            if len(ra) > 1:
                faces.append((a0, a1, b1) if len(rb) == 1 else (a0, a1, b0))
            if len(rb) > 1:
                faces.append((a1, b1, b0) if len(ra) > 1 else (a0, b1, b0))
    return np.array(verts, float), np.array(faces, np.int64)


def implicit_triangle_count(type_name: str) -> int:
    """Triangles implicit_mesh makes for a prim of this type (0: not an implicit prim), known without
    tessellating: a revolved profile of k points whose ends are poles gives 2 * SEGMENTS * (k - 2)."""
    half = SEGMENTS // 2
    profile = {"Sphere": half + 1, "Cylinder": 4, "Cylinder_1": 4, "Cone": 3,
               "Capsule": 2 * (max(half // 2, 2) + 1), "Capsule_1": 2 * (max(half // 2, 2) + 1)}
    if type_name == "Cube":
        return 12
    if type_name == "Plane":
        return 2
    k = profile.get(type_name)
    return 2 * SEGMENTS * (k - 2) if k else 0


def implicit_mesh(prim, time_code, warnings: list[str] | None = None):
    """Tessellate a UsdGeom implicit prim in its local frame. Returns (points, triangles) or None."""
    t = prim.GetTypeName()

    def get(name, default):
        a = prim.GetAttribute(name)
        v = attr_value(a, time_code, warnings) if a else None
        return default if v is None else v

    half = SEGMENTS // 2
    if t == "Cube":
        s = float(get("size", 2.0)) / 2
        v = np.array([[x, y, z] for x in (-s, s) for y in (-s, s) for z in (-s, s)], float)
        f = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                      [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
        return v, f
    if t == "Sphere":
        r = float(get("radius", 1.0))
        prof = [(r * math.sin(th), -r * math.cos(th)) for th in np.linspace(0, np.pi, half + 1)]
        prof[0], prof[-1] = (0.0, -r), (0.0, r)
        return _revolve(prof)
    if t in ("Cylinder", "Cone", "Capsule", "Cylinder_1", "Capsule_1"):
        capsule = t.startswith("Capsule")
        r = float(get("radius", 1.0 if not capsule else 0.5))
        if t.endswith("_1"):  # the newer schemas: one radius per end
            rt, rb = float(get("radiusTop", r)), float(get("radiusBottom", r))
        else:
            rt = rb = r
        h = float(get("height", 2.0 if not capsule else 1.0))
        axis = str(get("axis", "Z"))
        if t.startswith("Cylinder"):
            prof = [(0.0, -h / 2), (rb, -h / 2), (rt, h / 2), (0.0, h / 2)]
        elif t == "Cone":
            prof = [(0.0, -h / 2), (r, -h / 2), (0.0, h / 2)]
        else:
            q = max(half // 2, 2)
            bottom = [(rb * math.sin(a), -h / 2 - rb * math.cos(a)) for a in np.linspace(0, np.pi / 2, q + 1)]
            top = [(rt * math.cos(a), h / 2 + rt * math.sin(a)) for a in np.linspace(0, np.pi / 2, q + 1)]
            bottom[0], top[-1] = (0.0, -h / 2 - rb), (0.0, h / 2 + rt)
            prof = bottom + top
        v, f = _revolve(prof)
        return v @ _axis_matrix(axis).T, f
    if t == "Plane":
        w, l = float(get("width", 2.0)) / 2, float(get("length", 2.0)) / 2
        axis = str(get("axis", "Z"))
        v = np.array([[-w, -l, 0], [w, -l, 0], [w, l, 0], [-w, l, 0]], float)
        return v @ _axis_matrix(axis).T, np.array([[0, 1, 2], [0, 2, 3]])
    return None
