"""The bounds of every number a rig carries once it is resolved against its scene (a USD camera's own field of
view and clipping range, a USD light's cone and position, the default far plane), and the distance of its
positions from the scene. Outside them the solve answers nonsense (a field of view of 1e-300 degrees gives
nulls, near 1e-300 with far 1e300 a split at 1e300, a light at 1e12 m an objective of 1.6e22), so such a rig
is refused naming its field. The bounds are wide enough for every shipped rig (configs/, the corpus, held-out
and contact scenes: tests/test_rig_bounds.py) and for open worlds. api/schemas.py states the same numbers
in the request schema (the bare client imports no service module; tests/test_rig_bounds.py checks that the
two agree). Standard library only."""
from __future__ import annotations

import math
import os

FOV_Y_DEG = (0.01, 179.0)  # a camera's vertical field of view, degrees
CONE_DEG = (0.01, 180.0)  # a spot light's cone half-angle, degrees (UsdLux shaping:cone:angle)
NEAR_M = (1e-6, 1e8)  # a camera's near plane
MAX_FAR = 1e9  # a camera's far plane
MAX_FAR_OVER_NEAR = 1e7  # depth precision: past it a map's depth range holds nothing useful
MAX_COORDINATE = 1e9  # any coordinate of a position or target a request gives, before the scene is known
MAX_DISTANCE_M = 1e6  # default of the server setting max_rig_distance_m: how far from the scene's bounds a
# camera or light may stand (world metres)
DISTANCE_ENV = "SHADOWOPT_MAX_RIG_DISTANCE_M"  # the setting, as the server passes it to its batch workers


class BoundError(ValueError):
    """A number out of its bounds: `field` (relative to the rig) and the message naming it."""

    def __init__(self, field: str, message: str):
        super().__init__(message)
        self.field, self.message = field, message


def max_distance_m() -> float:
    """The configured distance bound (the server's max_rig_distance_m, passed through the environment so that
    batch workers in other processes apply the same)."""
    try:
        value = float(os.environ.get(DISTANCE_ENV, MAX_DISTANCE_M))
    except ValueError:
        return MAX_DISTANCE_M
    return value if math.isfinite(value) and value > 0 else MAX_DISTANCE_M


def check_camera(fov_y_deg: float, near: float, far: float, fields: dict) -> None:
    """BoundError when the resolved camera's field of view, near or far plane is out of bounds. `fields` names
    the field each value came from ({"fov_y_deg": "camera.usd_path", ...})."""
    lo, hi = FOV_Y_DEG
    if not (math.isfinite(fov_y_deg) and lo <= fov_y_deg <= hi):
        raise BoundError(fields["fov_y_deg"], f"the camera's vertical field of view {fov_y_deg:g} degrees is "
                         f"outside [{lo:g}, {hi:g}]")
    lo, hi = NEAR_M
    if not (math.isfinite(near) and lo <= near <= hi):
        raise BoundError(fields["near"], f"the camera's near plane {near:g} is outside [{lo:g}, {hi:g}]")
    if not (math.isfinite(far) and near < far <= MAX_FAR):
        raise BoundError(fields["far"], f"the camera's far plane {far:g} must be beyond near ({near:g}) and at most "
                         f"{MAX_FAR:g}")
    if far / near > MAX_FAR_OVER_NEAR:
        raise BoundError(fields["far"], f"far / near = {far / near:.3g} (near {near:g}, far {far:g}) is over "
                         f"{MAX_FAR_OVER_NEAR:g}: no depth buffer resolves such a range; raise near or lower far")


def check_cone(cone_deg: float, field: str) -> None:
    lo, hi = CONE_DEG
    if not (math.isfinite(cone_deg) and lo <= cone_deg <= hi):
        raise BoundError(field, f"the spot light's cone half-angle {cone_deg:g} degrees is outside [{lo:g}, {hi:g}]")


def distance_to_box(point, lo, hi) -> float:
    """Euclidean distance from `point` to the axis-aligned box [lo, hi] (0 inside)."""
    return math.sqrt(sum(max(l - p, 0.0, p - h) ** 2 for p, l, h in zip(point, lo, hi)))


def check_near_scene(point, lo, hi, field: str, what: str, limit: float | None = None) -> None:
    """BoundError when `point` (world metres) is farther than `limit` (default max_distance_m()) from the scene's
    bounds [lo, hi]."""
    limit = max_distance_m() if limit is None else limit
    d = distance_to_box([float(v) for v in point], [float(v) for v in lo], [float(v) for v in hi])
    if not d <= limit:
        raise BoundError(field, f"the {what} stands {d:.3g} m from the scene's bounds, over the server's limit "
                         f"max_rig_distance_m = {limit:g}")
