"""Plain data objects a loaded scene is made of (no USD, no Mitsuba here)."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


class SceneError(ValueError):
    """A scene cannot be loaded or used. `code` is machine-readable, the message names the problem."""

    def __init__(self, code: str, message: str):
        super().__init__(message)
        self.code = code
        self.message = message


@dataclass
class SceneGeometry:
    """All renderable triangles of a stage merged into one mesh, in the world frame (solvers.frames)."""

    vertices: np.ndarray  # (V, 3) float64, world frame, meters
    faces: np.ndarray  # (F, 3) int32 vertex indices
    face_prim: np.ndarray  # (F,) int32 index into prim_paths
    prim_paths: list[str]  # USD path of the prim each face came from

    @property
    def triangle_count(self) -> int:
        return int(self.faces.shape[0])

    _bounds: tuple | None = field(default=None, init=False, repr=False, compare=False)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(min, max) corners of the vertices the faces use, computed once per (vertices, faces) pair
        (the chess set's 4.3 M face indices took ~4 s per call with np.unique, inside every solve's timing).
        Copies are returned so a caller cannot change the cached corners."""
        key = (id(self.vertices), id(self.faces), self.vertices.shape, self.faces.shape)
        if self._bounds is None or self._bounds[0] != key:
            if self.vertices.shape[0] == 0:
                lo = hi = np.zeros(3)
            else:
                if self.faces.size:  # a mask, O(F), not np.unique's sort
                    used = np.zeros(self.vertices.shape[0], bool)
                    used[self.faces.ravel()] = True
                    pts = self.vertices[used]
                else:
                    pts = self.vertices
                lo, hi = pts.min(axis=0), pts.max(axis=0)
            self._bounds = (key, lo, hi)
        return self._bounds[1].copy(), self._bounds[2].copy()


@dataclass
class UsdCamera:
    """A UsdGeom.Camera converted to the world frame. Resolution is not in USD: the rig gives it."""

    usd_path: str
    position: np.ndarray
    forward: np.ndarray
    up: np.ndarray
    fov_y_deg: float  # from the vertical aperture and focal length
    near: float  # meters
    far: float  # meters
    focal_length_mm: float
    horizontal_aperture_mm: float
    vertical_aperture_mm: float

    def to_json(self) -> dict:
        return {
            "usd_path": self.usd_path, "position": self.position.tolist(), "forward": self.forward.tolist(),
            "up": self.up.tolist(), "fov_y_deg": self.fov_y_deg, "near": self.near, "far": self.far,
            "focal_length_mm": self.focal_length_mm, "horizontal_aperture_mm": self.horizontal_aperture_mm,
            "vertical_aperture_mm": self.vertical_aperture_mm,
        }


@dataclass
class UsdLight:
    """A UsdLux light converted to the world frame.

    `type` is the rig light type it maps to ("directional", "point", "spot") or "ignored" (DomeLight).
    """

    usd_path: str
    usd_type: str  # DistantLight, SphereLight, DiskLight, RectLight, DomeLight, ...
    type: str
    position: np.ndarray | None = None
    direction: np.ndarray | None = None  # the direction light travels
    cone_deg: float | None = None  # spot half-angle
    note: str = ""

    def to_json(self) -> dict:
        d = {"usd_path": self.usd_path, "usd_type": self.usd_type, "type": self.type}
        if self.position is not None:
            d["position"] = self.position.tolist()
        if self.direction is not None:
            d["direction"] = self.direction.tolist()
        if self.cone_deg is not None:
            d["cone_deg"] = self.cone_deg
        if self.note:
            d["note"] = self.note
        return d


@dataclass
class LoadedScene:
    source: str  # the file that was opened
    scene_hash: str  # sha256 of the root file's bytes plus every layer it composed
    geometry: SceneGeometry
    cameras: list[UsdCamera]
    lights: list[UsdLight]
    up_axis: str  # the stage's own
    meters_per_unit: float  # the stage's own
    stage_to_world: np.ndarray  # 4x4, solvers.frames.stage_to_world
    time_code: float | None  # the time code attributes were read at (None: default)
    warnings: list[str] = field(default_factory=list)
    load_s: float = 0.0

    def info(self) -> dict:
        lo, hi = self.geometry.bounds()
        return {
            "source": self.source,
            "scene_hash": self.scene_hash,
            "triangles": self.geometry.triangle_count,
            "vertices": int(self.geometry.vertices.shape[0]),
            "prims": len(self.geometry.prim_paths),
            "bounds": {"min": lo.tolist(), "max": hi.tolist()},
            "frame": {"world": "right-handed, +Y up, meters", "stage_up_axis": self.up_axis,
                      "stage_meters_per_unit": self.meters_per_unit,
                      "stage_to_world": self.stage_to_world.tolist()},
            "time_code": self.time_code,
            "cameras": [c.to_json() for c in self.cameras],
            "lights": [l.to_json() for l in self.lights],
            "warnings": list(self.warnings),
            "load_s": round(self.load_s, 4),
        }
