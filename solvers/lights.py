"""Light models in the world frame. Directions are the direction light travels."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .cameras import unit_vector


@dataclass(frozen=True)
class DirectionalLight:
    direction: np.ndarray  # unit, the direction the light travels
    usd_path: str | None = None
    kind: str = "directional"

    @staticmethod
    def make(direction, usd_path=None) -> "DirectionalLight":
        return DirectionalLight(unit_vector(direction, "light direction"), usd_path)


@dataclass(frozen=True)
class PointLight:
    position: np.ndarray
    usd_path: str | None = None
    kind: str = "point"

    @staticmethod
    def make(position, usd_path=None) -> "PointLight":
        p = np.asarray(position, dtype=np.float64).reshape(3)
        if not np.all(np.isfinite(p)):
            raise ValueError(f"light position must be finite, got {p.tolist()}")
        return PointLight(p, usd_path)


@dataclass(frozen=True)
class SpotLight:
    position: np.ndarray
    direction: np.ndarray  # unit, the cone's axis (the direction light travels)
    cone_deg: float  # half-angle, as UsdLux shaping:cone:angle
    usd_path: str | None = None
    kind: str = "spot"

    @staticmethod
    def make(position, direction, cone_deg, usd_path=None) -> "SpotLight":
        p = PointLight.make(position).position
        if not (0.0 < float(cone_deg) <= 180.0):
            raise ValueError(f"cone_deg must be in (0, 180], got {cone_deg}")
        return SpotLight(p, unit_vector(direction, "light direction"), float(cone_deg), usd_path)


Light = DirectionalLight | PointLight | SpotLight
