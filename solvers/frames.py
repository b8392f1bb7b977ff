"""World frame and stage-frame conversion: the one place the project's frame is defined.

World frame (everything inside shadowopt): right-handed, +Y up, meters.
Matrices act on column vectors: x_world = M @ [x_stage, 1].
A USD stage with upAxis "Z" is rotated by -90 degrees about +X, (x, y, z) -> (x, z, -y), which
keeps the frame right-handed and maps +Z up to +Y up; its metersPerUnit scales lengths to meters.
"""
from __future__ import annotations

import numpy as np

WORLD_FRAME = {"handedness": "right", "up_axis": "Y", "units": "meters", "matrix_layout": "column_vectors"}

_Z_UP_TO_Y_UP = np.array(
    [[1.0, 0.0, 0.0, 0.0],
     [0.0, 0.0, 1.0, 0.0],
     [0.0, -1.0, 0.0, 0.0],
     [0.0, 0.0, 0.0, 1.0]]
)


def stage_to_world(up_axis: str, meters_per_unit: float) -> np.ndarray:
    """4x4 matrix taking stage coordinates (its up axis, its units) to the world frame."""
    if up_axis not in ("Y", "Z"):
        raise ValueError(f"upAxis must be 'Y' or 'Z', got {up_axis!r}")
    if not (np.isfinite(meters_per_unit) and meters_per_unit > 0):
        raise ValueError(f"metersPerUnit must be a positive number, got {meters_per_unit!r}")
    rot = _Z_UP_TO_Y_UP if up_axis == "Z" else np.eye(4)
    scale = np.diag([meters_per_unit, meters_per_unit, meters_per_unit, 1.0])
    return scale @ rot


def world_to_stage(up_axis: str, meters_per_unit: float) -> np.ndarray:
    return np.linalg.inv(stage_to_world(up_axis, meters_per_unit))


def transform_points(m: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Apply a 4x4 affine matrix (column-vector convention) to (..., 3) points."""
    pts = np.asarray(pts, dtype=np.float64)
    return pts @ m[:3, :3].T + m[:3, 3]


def transform_directions(m: np.ndarray, dirs: np.ndarray, normalize: bool = True) -> np.ndarray:
    """Apply the linear part of a 4x4 matrix to (..., 3) directions."""
    out = np.asarray(dirs, dtype=np.float64) @ m[:3, :3].T
    if normalize:
        out = out / np.linalg.norm(out, axis=-1, keepdims=True)
    return out
