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


def _axis_matrix(axes) -> np.ndarray:
    """3x3 signed permutation R with engine = R @ world, from axes like ("x", "z", "y") or ("x", "y", "-z")."""
    r = np.zeros((3, 3))
    for i, a in enumerate(axes):
        sign, name = (-1.0, a[1:]) if a.startswith("-") else (1.0, a.lstrip("+"))
        r[i, "xyz".index(name)] = sign
    if sorted(np.nonzero(r)[1].tolist()) != [0, 1, 2]:
        raise ValueError(f"axes must name x, y and z once each, got {axes!r}")
    return r


def engine_from_world(axes, metres_per_unit: float) -> np.ndarray:
    """4x4 taking world points (right-handed, +Y up, metres) to an engine's frame: its axes (each engine
    coordinate a signed world coordinate, solvers.conventions.ENGINE_PRESETS) and its length unit.
    A signed permutation with an odd number of swaps or sign flips is a mirror (a left-handed engine)."""
    m = np.eye(4)
    m[:3, :3] = _axis_matrix(axes) / float(metres_per_unit)
    return m


def world_from_engine(axes, metres_per_unit: float) -> np.ndarray:
    """The inverse of engine_from_world, built exactly (transpose of the permutation, times the unit)."""
    m = np.eye(4)
    m[:3, :3] = _axis_matrix(axes).T * float(metres_per_unit)
    return m


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
