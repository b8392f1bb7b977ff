"""Turn a validated rig (api.schemas.Rig as a plain dict) plus a loaded scene into solver objects."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..renderers.scene_data import LoadedScene
from ..solvers.cameras import Camera
from ..solvers.frames import transform_directions, transform_points
from ..solvers.lights import DirectionalLight, Light, PointLight, SpotLight
from .request_cost import WorkLimit, check_solve_work
from .rig_bounds import BoundError, check_camera, check_cone, check_near_scene

DEFAULT_FOV_Y_DEG = 60.0
DEFAULT_NEAR = 0.1


class FieldError(ValueError):
    """Bad input that names the field at fault (a path such as `lights.0.usd_path`) and the reason;
    `code` is the machine-readable error code the API answers with."""

    code = "invalid_input"

    def __init__(self, field: str, message: str, code: str | None = None):
        super().__init__(f"{field}: {message}")
        self.field = field
        self.message = message
        if code is not None:  # e.g. invalid_previous for a SolutionError in a previous solution
            self.code = code


class RigError(FieldError):
    """The rig does not fit the scene."""

    code = "invalid_rig"


class SolutionError(FieldError):
    """A solution file cannot be used with this scene and rig."""

    code = "invalid_solution"


@dataclass
class ResolvedRig:
    camera: Camera
    lights: list[Light]
    shadow: dict
    output: dict
    coarse_long_side: int


def _far_default(position: np.ndarray, scene: LoadedScene) -> float:
    lo, hi = scene.geometry.bounds()
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    return float(max(np.linalg.norm(corners - position, axis=1).max() * 1.01, 1.0))


def resolve_camera(spec: dict, scene: LoadedScene, to_world: np.ndarray | None) -> Camera:
    pt = (lambda v: transform_points(to_world, v)) if to_world is not None else (lambda v: np.asarray(v, float))
    dr = (lambda v: transform_directions(to_world, v)) if to_world is not None else (lambda v: np.asarray(v, float))
    length = float(abs(np.linalg.det(to_world[:3, :3])) ** (1 / 3)) if to_world is not None else 1.0
    res = tuple(spec.get("resolution") or (1280, 720))
    if spec.get("usd_path"):
        found = [c for c in scene.cameras if c.usd_path == spec["usd_path"]]
        if not found:
            have = ", ".join(c.usd_path for c in scene.cameras) or "none"
            raise RigError("camera.usd_path", f"no camera {spec['usd_path']!r} in the scene (cameras: {have})")
        c = found[0]
        position, forward, up = c.position, c.forward, c.up
        fov, near, far = c.fov_y_deg, c.near, c.far
        if spec.get("position") is not None:  # a pose of its own (a camera path's) with the USD camera's intrinsics
            position = pt(spec["position"])
            forward = pt(spec["target"]) - position if spec.get("target") is not None else dr(spec["forward"])
        if spec.get("up") is not None:
            up = dr(spec["up"])
    else:
        position = pt(spec["position"])
        forward = pt(spec["target"]) - position if spec.get("target") is not None else dr(spec["forward"])
        up = dr(spec.get("up") or (0.0, 1.0, 0.0))
        fov, near, far = DEFAULT_FOV_Y_DEG, DEFAULT_NEAR, None
    if spec.get("fov_y_deg") is not None:
        fov = spec["fov_y_deg"]
    if spec.get("near") is not None:
        near = spec["near"] * length
    if spec.get("far") is not None:
        far = spec["far"] * length
    _near_scene(position, scene, "camera.position" if spec.get("position") is not None else "camera.usd_path",
                "camera")
    if far is None:
        far = max(_far_default(position, scene), near * 10.0)
    own = "camera.usd_path" if spec.get("usd_path") else "camera"  # where a value not given comes from
    try:
        check_camera(float(fov), float(near), float(far),
                     {k: f"camera.{k}" if spec.get(k) is not None else own for k in ("fov_y_deg", "near", "far")})
    except BoundError as e:
        raise RigError(e.field, e.message) from None
    try:
        return Camera.look(position, forward, up, fov, near, far, res, usd_path=spec.get("usd_path"))
    except ValueError as e:
        raise RigError("camera", str(e)) from e


def resolve_light(k: int, spec: dict, scene: LoadedScene, to_world: np.ndarray | None) -> Light:
    field = f"lights.{k}"
    if spec.get("usd_path"):
        found = [l for l in scene.lights if l.usd_path == spec["usd_path"]]
        if not found:
            have = ", ".join(l.usd_path for l in scene.lights) or "none"
            raise RigError(f"{field}.usd_path", f"no light {spec['usd_path']!r} in the scene (lights: {have})")
        u = found[0]
        if u.type == "directional":
            return DirectionalLight.make(u.direction, usd_path=u.usd_path)
        if u.type == "point":
            return PointLight.make(u.position, usd_path=u.usd_path)
        if u.type == "spot":
            _cone(u.cone_deg, f"{field}.usd_path")
            return SpotLight.make(u.position, u.direction, u.cone_deg, usd_path=u.usd_path)
        raise RigError(f"{field}.usd_path", f"{u.usd_path} is a {u.usd_type}, which casts no shadow map ({u.note})")
    pt = (lambda v: transform_points(to_world, v)) if to_world is not None else (lambda v: v)
    dr = (lambda v: transform_directions(to_world, v)) if to_world is not None else (lambda v: v)
    try:
        if spec["type"] == "directional":
            return DirectionalLight.make(dr(spec["direction"]))
        if spec["type"] == "point":
            return PointLight.make(pt(spec["position"]))
        _cone(spec["cone_deg"], f"{field}.cone_deg")
        return SpotLight.make(pt(spec["position"]), dr(spec["direction"]), spec["cone_deg"])
    except RigError:
        raise
    except ValueError as e:
        raise RigError(field, str(e)) from e


def _cone(cone_deg, field: str) -> None:
    try:
        check_cone(float(cone_deg), field)
    except BoundError as e:
        raise RigError(e.field, e.message) from None


def _near_scene(point, scene: LoadedScene, field: str, what: str) -> None:
    """RigError when `point` (world) stands farther from the scene's bounds than the server allows
    (service.rig_bounds.max_distance_m); nothing to measure from in a scene without geometry."""
    lo, hi = scene.geometry.bounds()
    if np.all(np.isfinite(lo)) and np.all(np.isfinite(hi)):
        try:
            check_near_scene(point, lo, hi, field, what)
        except BoundError as e:
            raise RigError(e.field, e.message) from None


def resolve_rig(rig: dict, scene: LoadedScene) -> ResolvedRig:
    """`rig` is `api.schemas.Rig(...).model_dump(by_alias=True)`: validated, defaults filled."""
    to_world = scene.stage_to_world if rig.get("frame") == "stage" else None
    camera = resolve_camera(rig["camera"], scene, to_world)
    lights = [resolve_light(k, l, scene, to_world) for k, l in enumerate(rig["lights"])]
    for k, (spec, light) in enumerate(zip(rig["lights"], lights)):
        if getattr(light, "position", None) is not None:
            _near_scene(light.position, scene, f"lights.{k}.usd_path" if spec.get("usd_path") else
                        f"lights.{k}.position", f"{light.kind} light")
    try:  # the work bound (the Rig model checks it too; here with the lights' real types, for every rig dict)
        check_solve_work(rig, kinds=[l.kind for l in lights], prefix="")
    except WorkLimit as e:
        raise RigError(e.field, e.message, code="too_costly") from None
    return ResolvedRig(camera, lights, dict(rig.get("shadow") or {}), dict(rig.get("output") or {}),
                       int(rig.get("coarse_long_side") or 180))
