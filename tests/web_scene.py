"""The scene's triangles as Filament's web build loads them in tests/test_filament_module.py: a binary glTF (the form
its glTF loader draws with its built-in materials) of the same triangles three.js draws
(shadowopt.service.bench.three_page.scene_geometry: split into small coplanar pieces, flat normals on the light's
side)."""
from __future__ import annotations

import json
import struct

import numpy as np

from shadowopt.service.bench.three_page import scene_geometry


def scene_triangles(entry, sun_direction) -> tuple[np.ndarray, np.ndarray]:
    """(triangles (n, 3, 3), flat unit normals (n, 3)), float64 from three_page.scene_geometry's float32 stream."""
    v = np.frombuffer(scene_geometry(entry, sun_direction), np.float32).reshape(-1, 3, 6).astype(np.float64)
    return v[:, :, :3], v[:, 0, 3:]


def glb(tri: np.ndarray, nrm: np.ndarray, ids: bool = False) -> bytes:
    """A binary glTF 2.0 of the triangles (one mesh, unshared vertices, flat normals, indexed 0..3n-1), double-sided.
    ids False: a white, fully rough dielectric (lit by the scene's lights, receiving shadows). ids True: unlit
    (KHR_materials_unlit) with each triangle's index + 1 in its vertex colour (r + 256 g + 65536 b, unsigned bytes),
    so that a render without post-processing reads back which triangle covers each pixel."""
    n = len(tri)
    pos = tri.reshape(-1, 3).astype(np.float32)
    nor = np.repeat(nrm, 3, axis=0).astype(np.float32)
    index = np.arange(3 * n, dtype=np.uint32)
    arrays = [(pos, 5126, "VEC3", 34962), (nor, 5126, "VEC3", 34962), (index, 5125, "SCALAR", 34963)]
    if ids:
        k = np.arange(1, n + 1, dtype=np.uint32)
        rgba = np.stack([k & 255, (k >> 8) & 255, (k >> 16) & 255, np.full(n, 255, np.uint32)], axis=1).astype(np.uint8)
        arrays.append((np.repeat(rgba, 3, axis=0), 5121, "VEC4", 34962))
    blob, views, accessors = b"", [], []
    for a, ctype, kind, target in arrays:
        views.append({"buffer": 0, "byteOffset": len(blob), "byteLength": a.nbytes, "target": target})
        acc = {"bufferView": len(views) - 1, "componentType": ctype, "count": len(a), "type": kind}
        if kind == "VEC3" and ctype == 5126 and not accessors:
            acc |= {"min": pos.min(axis=0).tolist(), "max": pos.max(axis=0).tolist()}
        if ctype == 5121:
            acc["normalized"] = True
        accessors.append(acc)
        blob += a.tobytes() + b"\0" * (-a.nbytes % 4)
    attributes = {"POSITION": 0, "NORMAL": 1} | ({"COLOR_0": 3} if ids else {})
    material = {"pbrMetallicRoughness": {"baseColorFactor": [1, 1, 1, 1], "metallicFactor": 0.0,
                                         "roughnessFactor": 1.0}, "doubleSided": True}
    doc = {"asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0}],
           "meshes": [{"primitives": [{"attributes": attributes, "indices": 2, "material": 0}]}],
           "materials": [material | ({"extensions": {"KHR_materials_unlit": {}}} if ids else {})],
           "accessors": accessors, "bufferViews": views, "buffers": [{"byteLength": len(blob)}]}
    if ids:
        doc["extensionsUsed"] = ["KHR_materials_unlit"]
    js = json.dumps(doc).encode()
    js += b" " * (-len(js) % 4)
    body = struct.pack("<II", len(js), 0x4E4F534A) + js + struct.pack("<II", len(blob), 0x004E4942) + blob
    return struct.pack("<III", 0x46546C67, 2, 12 + len(body)) + body
