"""A batch request's configurations: an explicit list, or a base rig crossed with a camera path and a light
set (service.interpolation), each {"rig": RIG}; the grid's shape for the interpolation hints."""
from __future__ import annotations

import copy

from .interpolation import camera_path, light_set, light_slot
from .request_fields import BatchError

MAX_CONFIGURATIONS = 100_000


def expand_configurations(request: dict) -> list[dict]:
    """The configurations of a batch request, each {"rig": RIG}.

    Either {"configurations": [{"rig": RIG}, ...]}, or a base {"rig": RIG} with a camera path
    ({"camera_path": {"poses": [CameraSpec, ...]}} or {"keyframes": [...], "samples": N}: position,
    target or forward, up, fov_y_deg, near and far interpolated linearly) crossed with light directions
    ({"light_directions": [[x, y, z], ...]} or {"sun_arc": {"azimuth_deg", "elevation_deg", "samples"}}).
    Index = camera_index * n_lights + light_index. A direction replaces the base rig's light
    `light_index` (default 0) with a directional light.
    """
    if not isinstance(request, dict):
        raise BatchError("(root)", "expected a JSON object")
    if "configurations" in request:
        extra = [k for k in ("camera_path", "light_directions", "sun_arc") if k in request]
        if extra:
            raise BatchError(extra[0], "give either configurations or the camera-path form, not both")
        return _explicit(request["configurations"])
    base = request.get("rig")
    if not isinstance(base, dict):
        raise BatchError("rig", "give configurations, or a base rig object with a camera_path and/or light set")
    cameras = camera_path(request["camera_path"], base.get("camera")) if "camera_path" in request else None
    directions = light_set(request, base)
    if cameras is None and directions is None:
        raise BatchError("camera_path", "give a camera_path, light_directions or a sun_arc with the base rig")
    n = len(cameras or [None]) * len(directions or [None])
    if n > MAX_CONFIGURATIONS:
        raise BatchError("camera_path" if cameras else "light_directions",
                         f"{n} configurations exceed the limit of {MAX_CONFIGURATIONS}")
    slot = light_slot(request, base) if directions is not None else None
    out = []
    for cam in cameras or [None]:
        for d in directions or [None]:
            rig = copy.deepcopy(base)
            if cam is not None:
                rig["camera"] = cam
            if d is not None:
                lights = list(rig.get("lights") or [])
                light = {"type": "directional", "direction": d}
                lights[slot:slot + 1] = [light]
                rig["lights"] = lights
            out.append({"rig": rig})
    return out


def expansion_shape(request: dict) -> tuple[int, int] | None:
    """(cameras, lights) of a camera-path request (index = camera * lights + light), None for an explicit list."""
    if not isinstance(request, dict) or "configurations" in request or not isinstance(request.get("rig"), dict):
        return None
    cams = len(camera_path(request["camera_path"], request["rig"].get("camera"))) if "camera_path" in request else 1
    dirs = light_set(request, request["rig"])
    return cams, len(dirs) if dirs is not None else 1


def _explicit(configs) -> list[dict]:
    if not isinstance(configs, list) or not configs:
        raise BatchError("configurations", "expected a non-empty list of {\"rig\": ...} objects")
    if len(configs) > MAX_CONFIGURATIONS:
        raise BatchError("configurations", f"{len(configs)} configurations exceed the limit of {MAX_CONFIGURATIONS}")
    out = []
    for i, c in enumerate(configs):
        if not isinstance(c, dict) or not isinstance(c.get("rig"), dict):
            raise BatchError(f"configurations.{i}.rig", "expected an object {\"rig\": RIG}")
        unknown = sorted(set(c) - {"rig"})
        if unknown:
            raise BatchError(f"configurations.{i}.{unknown[0]}", "unknown field (a configuration holds a rig)")
        out.append({"rig": c["rig"]})
    return out
