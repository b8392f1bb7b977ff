"""Small geometry builders shared by the tests (importable because pytest puts tests/ on the path)."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from shadowopt.renderers.scene_data import SceneGeometry
from shadowopt.solvers.cameras import Camera
from shadowopt.solvers.samples import Samples, pixel_derivatives


def plane(size=200.0, off=(0.0, 0.0, 0.0)):
    """A square y = 0 ground of half-size `size`, shifted by `off`: (vertices, faces)."""
    v = np.array([[-size, 0.0, -size], [size, 0.0, -size], [size, 0.0, size], [-size, 0.0, size]]) + np.asarray(off)
    return v, np.array([[0, 2, 1], [0, 3, 2]])


def box(lo, hi):
    """An axis-aligned box: (vertices, faces)."""
    v = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])], float)
    f = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                  [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    return v, f


def merge(*parts) -> SceneGeometry:
    """(vertices, faces) parts merged into one SceneGeometry, prim k named /pk."""
    verts, faces, prims, off = [], [], [], 0
    for k, (v, f) in enumerate(parts):
        verts.append(np.asarray(v, float))
        faces.append(np.asarray(f) + off)
        prims.append(np.full(len(f), k))
        off += len(v)
    return SceneGeometry(np.vstack(verts), np.vstack(faces).astype(np.int32),
                         np.concatenate(prims).astype(np.int32), [f"/p{k}" for k in range(len(parts))])


def scene_entry_of(parts, cameras=(), lights=()):
    """An in-memory service SceneEntry (Y up, metres) of (vertices, faces) parts merged (merge), with its ray scene."""
    from shadowopt.renderers.ray_scene import build_ray_scene
    from shadowopt.renderers.scene_data import LoadedScene
    from shadowopt.service.scenes import SceneEntry
    from shadowopt.solvers.frames import stage_to_world

    g = merge(*parts)
    loaded = LoadedScene("mem", "hash", g, list(cameras), list(lights), "Y", 1.0, stage_to_world("Y", 1.0), None)
    return SceneEntry(loaded, build_ray_scene(g), 0.0, 0.0)


def frustum(half_w, half_h, near, far):
    """OpenGL perspective projection with a symmetric near rectangle of half-size (half_w, half_h)."""
    p = np.zeros((4, 4))
    p[0, 0], p[1, 1] = near / half_w, near / half_h
    p[2, 2], p[2, 3] = -(far + near) / (far - near), -2 * far * near / (far - near)
    p[3, 2] = -1.0
    return p


def ground_samples(cam: Camera, far=150.0, grid=(96, 54)):
    """Ground-plane (y = 0) points seen through a grid of the camera's pixels, and metric samples on them."""
    d = cam.ray_directions(*grid).reshape(-1, 3)
    with np.errstate(divide="ignore"):
        t = -cam.position[1] / d[:, 1]
    ok = (t > 0) & (t < far)
    pts = cam.position + t[ok, None] * d[ok]
    n = np.tile([0, 1.0, 0], (len(pts), 1))
    dx, dy, dep = pixel_derivatives(cam, pts, n)
    return pts, Samples(pts, n, dx, dy, dep, np.ones(len(pts)), np.zeros((len(pts), 2), int), "all_facing")


def gl_depth(tmp_path, vertices, faces, matrix, resolution, clip_z, reversed_z=False):
    """Window depth (height, width), row 0 at the bottom, rasterized by real OpenGL (Mesa through EGL) in a
    subprocess (tests/gl_check.py: Mesa loads LLVM 15, Dr.Jit in this process 19); skips without EGL."""
    import subprocess
    import sys

    import pytest

    src, out = tmp_path / "in.npz", tmp_path / "out.npz"
    np.savez(src, vertices=vertices.astype(np.float32), faces=faces.astype(np.uint32), matrix=matrix,
             resolution=np.array(resolution), depth_clamp=True, clip_z=clip_z, reversed_z=reversed_z)
    p = subprocess.run([sys.executable, str(Path(__file__).with_name("gl_check.py")), str(src), str(out)],
                       capture_output=True, text=True, timeout=300)
    if p.returncode != 0 and ("EGL" in p.stderr or "moderngl" in p.stderr):
        pytest.skip(f"no EGL/OpenGL here: {p.stderr.strip().splitlines()[-1]}")
    assert p.returncode == 0, p.stderr
    return np.load(out)["depth"]


def sun(az_deg, el_deg=50.0):
    """A sun's direction of travel (towards the ground) from the inspector's azimuth and elevation sliders."""
    a, e = math.radians(az_deg), math.radians(el_deg)
    return [-math.cos(e) * math.sin(a), -math.sin(e), -math.cos(e) * math.cos(a)]
