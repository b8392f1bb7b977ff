"""Pinhole camera model in the world frame (see solvers.frames)."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


def unit_vector(v, name: str) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64).reshape(3)
    n = float(np.linalg.norm(v))
    if not np.isfinite(n) or n == 0.0:
        raise ValueError(f"{name} must be a finite non-zero vector, got {v.tolist()}")
    return v / n


@dataclass(frozen=True)
class Camera:
    """Perspective camera. `forward` and `up` are unit vectors; `up` is orthogonalized against forward.

    The camera looks along +forward; its image x axis is `right = forward x up`, image y is `up`.
    Pixel (i, j) with i along x (left to right) and j along y (top to bottom) has its centre at
    ndc = ((i + 0.5) / w * 2 - 1, 1 - (j + 0.5) / h * 2).
    """

    position: np.ndarray
    forward: np.ndarray
    up: np.ndarray
    fov_y_deg: float
    near: float
    far: float
    resolution: tuple[int, int]
    usd_path: str | None = None

    @staticmethod
    def look(position, forward, up=(0.0, 1.0, 0.0), fov_y_deg=60.0, near=0.1, far=1000.0,
             resolution=(1280, 720), usd_path=None) -> "Camera":
        pos = np.asarray(position, dtype=np.float64).reshape(3)
        if not np.all(np.isfinite(pos)):
            raise ValueError(f"camera position must be finite, got {pos.tolist()}")
        fwd = unit_vector(forward, "camera forward")
        up_v = unit_vector(up, "camera up")
        right = np.cross(fwd, up_v)
        if np.linalg.norm(right) < 1e-9:
            # Looking straight along `up`: pick any perpendicular up vector.
            alt = np.array([0.0, 0.0, 1.0]) if abs(fwd[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
            right = np.cross(fwd, alt)
        right /= np.linalg.norm(right)
        up_o = np.cross(right, fwd)
        if not (0.0 < fov_y_deg < 180.0):
            raise ValueError(f"fov_y_deg must be in (0, 180), got {fov_y_deg}")
        if not (0.0 < near < far and math.isfinite(far)):
            raise ValueError(f"need 0 < near < far < inf, got near={near}, far={far}")
        w, h = int(resolution[0]), int(resolution[1])
        if w <= 0 or h <= 0:
            raise ValueError(f"resolution must be positive, got {resolution}")
        return Camera(pos, fwd, up_o, float(fov_y_deg), float(near), float(far), (w, h), usd_path)

    @staticmethod
    def look_at(position, target, **kw) -> "Camera":
        pos = np.asarray(position, dtype=np.float64)
        return Camera.look(pos, np.asarray(target, dtype=np.float64) - pos, **kw)

    @property
    def right(self) -> np.ndarray:
        return np.cross(self.forward, self.up)

    @property
    def aspect(self) -> float:
        return self.resolution[0] / self.resolution[1]

    @property
    def tan_half_fov_y(self) -> float:
        return math.tan(math.radians(self.fov_y_deg) / 2.0)

    def coarse_resolution(self, long_side: int = 180) -> tuple[int, int]:
        """Resolution with the same aspect ratio whose long side is `long_side` pixels."""
        w, h = self.resolution
        if w >= h:
            return long_side, max(1, round(long_side * h / w))
        return max(1, round(long_side * w / h)), long_side

    def view_matrix(self) -> np.ndarray:
        """World -> camera view (right-handed, camera looks along -Z as in OpenGL)."""
        r, u, f = self.right, self.up, self.forward
        m = np.eye(4)
        m[0, :3], m[1, :3], m[2, :3] = r, u, -f
        m[:3, 3] = -m[:3, :3] @ self.position
        return m

    def ray_directions(self, width: int, height: int) -> np.ndarray:
        """Unit world-space directions through pixel centres, shape (height, width, 3)."""
        th = self.tan_half_fov_y
        tw = th * self.aspect
        x = ((np.arange(width) + 0.5) / width * 2.0 - 1.0) * tw
        y = (1.0 - (np.arange(height) + 0.5) / height * 2.0) * th
        d = (self.forward[None, None, :] + x[None, :, None] * self.right[None, None, :]
             + y[:, None, None] * self.up[None, None, :])
        return d / np.linalg.norm(d, axis=-1, keepdims=True)
