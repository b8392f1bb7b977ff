"""A request's camera path and light set: poses, or camera keyframes interpolated over `samples` frames
(position, target or forward, up, fov_y_deg, near, far), and light directions or a sun arc, each field checked
(BatchError naming it). Shared by a batch's configurations (service.batch_request) and a path job's frames
(service.paths)."""
from __future__ import annotations

import math

from .request_fields import BatchError, number, samples, value_range, vec3


def _merge_pose(base_cam, pose: dict) -> dict:
    """A pose over the base camera. A pose naming a usd_path replaces the base's camera (pose and source); a
    pose with a position replaces the base's position and aim but keeps its usd_path, so a USD camera keeps
    its own intrinsics (field of view, near, far, up: service.rigs.resolve_camera) along the path; fields the
    pose gives (fov_y_deg, near, far, up, resolution) win."""
    cam = dict(base_cam) if isinstance(base_cam, dict) else {}
    if "usd_path" in pose:
        for k in ("usd_path", "position", "target", "forward"):
            cam.pop(k, None)
    elif "position" in pose:
        for k in ("position", "target", "forward"):
            cam.pop(k, None)
    if "target" in pose:
        cam.pop("forward", None)
    if "forward" in pose:
        cam.pop("target", None)
    cam.update(pose)
    return cam


def camera_path(path, base_cam) -> list[dict]:
    """The cameras of a request's camera_path over the base rig's camera: its poses, or its keyframes
    interpolated over `samples` frames."""
    if not isinstance(path, dict):
        raise BatchError("camera_path", "expected {\"poses\": [...]} or {\"keyframes\": [...], \"samples\": N}")
    if ("poses" in path) == ("keyframes" in path):
        raise BatchError("camera_path", "give exactly one of poses and keyframes")
    if "poses" in path:
        poses = path["poses"]
        if not isinstance(poses, list) or not poses:
            raise BatchError("camera_path.poses", "expected a non-empty list of camera objects")
        for i, p in enumerate(poses):
            if not isinstance(p, dict):
                raise BatchError(f"camera_path.poses.{i}", "expected a camera object")
            for k in ("position", "target", "forward", "up"):
                if k in p:
                    vec3(p[k], f"camera_path.poses.{i}.{k}", nonzero=k in ("forward", "up"))
        return [_merge_pose(base_cam, p) for p in poses]
    return _keyframes(path["keyframes"], samples(path.get("samples"), "camera_path.samples"), base_cam)


_LERPED = ("fov_y_deg", "near", "far")


def _keyframes(keys, n: int, base_cam) -> list[dict]:
    field = "camera_path.keyframes"
    if not isinstance(keys, list) or len(keys) < 2:
        raise BatchError(field, "expected a list of at least 2 camera keyframes")
    aim = "target" if isinstance(keys[0], dict) and "target" in keys[0] else "forward"
    parsed = []
    for i, k in enumerate(keys):
        f = f"{field}.{i}"
        if not isinstance(k, dict):
            raise BatchError(f, "expected a camera object")
        if "usd_path" in k:
            raise BatchError(f"{f}.usd_path", "keyframes need explicit position and target (or forward)")
        if "position" not in k:
            raise BatchError(f"{f}.position", "every keyframe needs a position")
        if aim not in k or ("target" in k and "forward" in k):
            raise BatchError(f"{f}.{aim}", f"every keyframe needs {aim} (as the first keyframe), not both target and forward")
        p = {"position": vec3(k["position"], f"{f}.position"), aim: vec3(k[aim], f"{f}.{aim}", nonzero=aim == "forward")}
        if "up" in k:
            p["up"] = vec3(k["up"], f"{f}.up", nonzero=True)
        for name in _LERPED:
            if name in k and k[name] is not None:
                p[name] = number(k[name], f"{f}.{name}", 0.0)
        parsed.append((k, p))
    lerped = [name for name in ("up",) + _LERPED if all(name in p for _, p in parsed)]
    partial = [name for name in ("up",) + _LERPED if name not in lerped and any(name in p for _, p in parsed)]
    if partial:
        raise BatchError(f"{field}.{partial[0]}", "give it in every keyframe or in none (it is interpolated)")
    out = []
    for j in range(n):
        t = 0.0 if n == 1 else j * (len(parsed) - 1) / (n - 1)
        seg = min(int(t), len(parsed) - 2)
        u = t - seg
        (k0, a), (_, b) = parsed[seg], parsed[seg + 1]
        pose = {"position": _lerp(a["position"], b["position"], u)}
        pose[aim] = _lerp(a[aim], b[aim], u)
        if aim == "forward":
            pose["forward"] = _normalised(pose["forward"], a["forward"])
        if "up" in lerped:
            pose["up"] = _normalised(_lerp(a["up"], b["up"], u), a["up"])
        for name in _LERPED:
            if name in lerped:
                pose[name] = a[name] + (b[name] - a[name]) * u
        rest = {k: v for k, v in k0.items() if k not in pose and k not in ("position", "target", "forward", "up") + _LERPED}
        out.append(_merge_pose(base_cam, {**rest, **pose}))
    return out


def _lerp(a, b, u: float) -> list[float]:
    return [x + (y - x) * u for x, y in zip(a, b)]


def _normalised(v, fallback) -> list[float]:
    n = math.sqrt(sum(x * x for x in v))
    return [x / n for x in v] if n > 1e-12 else list(fallback)


def light_set(request: dict, base: dict) -> list[list[float]] | None:
    """The request's light_directions or sun_arc directions (None: it gives neither)."""
    if "light_directions" in request and "sun_arc" in request:
        raise BatchError("sun_arc", "give either light_directions or a sun_arc, not both")
    if "light_directions" in request:
        dirs = request["light_directions"]
        if not isinstance(dirs, list) or not dirs:
            raise BatchError("light_directions", "expected a non-empty list of [x, y, z] directions")
        return [vec3(d, f"light_directions.{i}", nonzero=True) for i, d in enumerate(dirs)]
    if "sun_arc" in request:
        if base.get("frame") == "stage":
            raise BatchError("sun_arc", "sun_arc directions are in the world frame (+Y up): use rig.frame \"world\"")
        return sun_arc(request["sun_arc"])
    return None


def sun_arc(arc) -> list[list[float]]:
    """Directions light travels for a sun moving from (azimuth, elevation) `from` to `to` in `samples`
    steps, linearly in both angles. World frame: +Y up; azimuth 0 puts the sun toward +Z, 90 toward +X."""
    if not isinstance(arc, dict):
        raise BatchError("sun_arc", "expected {\"azimuth_deg\", \"elevation_deg\", \"samples\"}")
    unknown = sorted(set(arc) - {"azimuth_deg", "elevation_deg", "samples"})
    if unknown:
        raise BatchError(f"sun_arc.{unknown[0]}", "unknown field (known: azimuth_deg, elevation_deg, samples)")
    az = value_range(arc.get("azimuth_deg", 0.0), "sun_arc.azimuth_deg", -720.0, 720.0)
    if "elevation_deg" not in arc:
        raise BatchError("sun_arc.elevation_deg", "required: a number or [from, to] in degrees above the horizon")
    el = value_range(arc["elevation_deg"], "sun_arc.elevation_deg", -90.0, 90.0)
    n = samples(arc.get("samples", 1), "sun_arc.samples")
    out = []
    for j in range(n):
        u = 0.0 if n == 1 else j / (n - 1)
        a = math.radians(az[0] + (az[1] - az[0]) * u)
        e = math.radians(el[0] + (el[1] - el[0]) * u)
        to_sun = (math.cos(e) * math.sin(a), math.sin(e), math.cos(e) * math.cos(a))
        out.append([-c for c in to_sun])
    return out


def light_slot(request: dict, base: dict) -> int:
    """The rig light the directions replace: light_index (default 0), checked against rig.lights."""
    k = request.get("light_index", 0)
    n = len(base.get("lights") or [])
    if isinstance(k, bool) or not isinstance(k, int) or not 0 <= k <= max(n - 1, 0):
        raise BatchError("light_index", f"expected an index into rig.lights (0..{max(n - 1, 0)}), got {k!r}")
    return k
