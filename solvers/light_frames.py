"""Light view frames (world -> light view, the light looking down -Z, OpenGL style), per light type.

- Directional: the LiSPSM frame. Looks along the direction the light travels; +Y is the camera's
  view direction projected into the light's image plane (camera up when the two are parallel, i.e.
  the light within ~1e-6 rad of the view axis), so a perspective warp along +Y (solvers.warp) is
  LiSPSM's. The translation is re-centred on `origin` (default: the camera position): a directional
  light has no position, so any origin is valid, and one near the receivers keeps light-view
  coordinates small for scenes far from the world origin (1e5 m). Everything is float64.
- Spot: from the light's position along its axis, +Y from the camera's view direction likewise.
- Point: six cube-map faces, 90° each, OpenGL cube-map orientation (face -> (forward, up)).
"""
from __future__ import annotations

import numpy as np

from .cameras import Camera
from .lights import DirectionalLight, SpotLight

# OpenGL cube-map face orientation: face -> (forward, up) of the face's view.
CUBE_FACES = {"+x": ([1, 0, 0], [0, -1, 0]), "-x": ([-1, 0, 0], [0, -1, 0]), "+y": ([0, 1, 0], [0, 0, 1]),
              "-y": ([0, -1, 0], [0, 0, -1]), "+z": ([0, 0, 1], [0, -1, 0]), "-z": ([0, 0, -1], [0, -1, 0])}


def perpendicular_up(forward: np.ndarray, *hints) -> np.ndarray:
    """The first hint with a usable component perpendicular to `forward` (unit), else any perpendicular."""
    forward = np.asarray(forward, dtype=np.float64)
    for h in hints:
        h = np.asarray(h, dtype=np.float64)
        u = h - np.dot(h, forward) * forward
        if np.linalg.norm(u) > 1e-6:
            return u / np.linalg.norm(u)
    a = np.array([1.0, 0, 0]) if abs(forward[0]) < 0.9 else np.array([0, 1.0, 0])
    u = a - np.dot(a, forward) * forward
    return u / np.linalg.norm(u)


def look_matrix(eye: np.ndarray, forward: np.ndarray, up: np.ndarray) -> np.ndarray:
    """World -> view looking along `forward` (down -Z) from `eye`, +Y = up (orthonormalised)."""
    f = np.asarray(forward, dtype=np.float64)
    f = f / np.linalg.norm(f)
    u = perpendicular_up(f, up)
    r = np.cross(f, u)
    m = np.eye(4)
    m[0, :3], m[1, :3], m[2, :3] = r, u, -f
    m[:3, 3] = -m[:3, :3] @ np.asarray(eye, dtype=np.float64)
    return m


def directional_view(light: DirectionalLight, camera: Camera, origin: np.ndarray | None = None) -> np.ndarray:
    """The LiSPSM light frame of a directional light, its translation re-centred on `origin`
    (default the camera position)."""
    eye = camera.position if origin is None else np.asarray(origin, dtype=np.float64)
    return look_matrix(eye, light.direction, perpendicular_up(light.direction, camera.forward, camera.up))


def spot_view(light: SpotLight, camera: Camera) -> np.ndarray:
    """From the spot's position along its axis; +Y from the camera's view direction."""
    return look_matrix(light.position, light.direction, perpendicular_up(light.direction, camera.forward, camera.up))


def cube_face_views(position: np.ndarray) -> dict[str, np.ndarray]:
    """The six 90° cube-map face views of a point light at `position`."""
    return {face: look_matrix(position, np.array(fwd, float), np.array(up, float))
            for face, (fwd, up) in CUBE_FACES.items()}
