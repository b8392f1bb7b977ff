"""Path jobs: a camera path (and lights animated along it) as the ordered frames of a batch.

A path request is a base `rig` with either
- `camera_path`: the batches' form (service.interpolation: `poses`, or `keyframes` + `samples`), optionally with
  `light_directions` / `sun_arc` giving one light direction per frame (or one for all), or
- `usd_camera` (a UsdGeom.Camera prim path; default rig.camera.usd_path) and `time` {start, end, step}: the
  camera's world transform, field of view (vertical aperture and focal length) and clipping range read at
  each time code t = start + k * step (USD's own interpolation of the time samples), and every rig light
  given by usd_path whose transform is animated read at the same time codes (a DistantLight's direction:
  a sun moving through the day).
Frames are {"rig": RIG, "frame": k, "time": t or None} in order; a path job is a batch over them (the Store,
resume, crash safety and streamed results of service.job_runner), each result line carrying "frame" and "time".
On a stage whose geometry has transform or point time samples (a moving vehicle), each frame also carries
"scene_time": t and its worker solves on the stage loaded at that time code (service.scenes.SCENES.get
time_code; one load per frame: an upload's in an isolated child under the server's load limits), so a moving
caster casts a moving shadow; the loader's warnings for that time code go on the frame's line ("warnings").
With `coherent`, frames are solved one after another and each solve receives the previous frame's solution
as `previous=` (service.solve.solve): service.job_kinds.coherent_tasks. Method path without `coherent` solves
the frames together (is_whole_path: tasks of job_kinds.WHOLE_PATH_FRAMES consecutive frames,
service.solve.solve_path). The CLI's path runs in service.local_jobs.
"""
from __future__ import annotations

import math

import numpy as np

from ..renderers.json_text import dumps
from .batch_request import MAX_CONFIGURATIONS
from .interpolation import camera_path, light_set, light_slot
from .request_fields import BatchError

MAX_FRAMES = MAX_CONFIGURATIONS  # like a batch's configurations
MAX_TIME_FRAMES = 10_000  # time codes read from a stage per request (one transform cache each), as keyframe samples
COHERENT_METHODS = ()  # methods that always get the previous frame (none: method path sees the whole path)
WHOLE_PATH_METHODS = ("path",)  # methods whose frames are solved together (service.solve.solve_path)
PATH_FIELDS = ("rig", "camera_path", "usd_camera", "time", "light_directions", "sun_arc", "light_index")


class PathError(BatchError):
    """A path request is malformed (`field` e.g. `time.step`)."""

    code = "invalid_path"


def expand_path(request: dict, *, scene_path=None, reader=None) -> list[dict]:
    """The frames of a path request in order, each {"rig": RIG, "frame": k, "time": t or None}
    (see the module doc). The `usd_camera` form reads the stage: `reader(camera_path, times, light_paths)`
    returns renderers.usd_animation.read_animation's dict (the server runs it isolated for uploads), or
    `scene_path` is read directly. Raises PathError naming the field."""
    return expand_path_with_notes(request, scene_path=scene_path, reader=reader)[0]


def expand_path_with_notes(request: dict, *, scene_path=None, reader=None) -> tuple[list[dict], list[str]]:
    """expand_path and the notes a user should see (moving geometry not modelled, a camera without time
    samples, time codes outside the stage's range)."""
    if not isinstance(request, dict):
        raise PathError("(root)", "expected a JSON object")
    unknown = sorted(set(request) - set(PATH_FIELDS))
    if unknown:
        raise PathError(unknown[0], f"unknown field (known: {', '.join(PATH_FIELDS)})")
    base = request.get("rig")
    if not isinstance(base, dict):
        raise PathError("rig", "expected the base rig object (shadow, output, lights; the path gives the camera)")
    has_usd = "usd_camera" in request or "time" in request
    if ("camera_path" in request) == has_usd:
        raise PathError("camera_path", "give exactly one of camera_path and usd_camera with time")
    if "camera_path" in request:
        cams = camera_path(request["camera_path"], base.get("camera"))
        if len(cams) > MAX_FRAMES:
            raise PathError("camera_path", f"{len(cams)} frames exceed the limit of {MAX_FRAMES}")
        frames = [{"rig": {**base, "camera": c}, "frame": k, "time": None} for k, c in enumerate(cams)]
        return _with_light_set(request, base, frames), []
    if "light_directions" in request or "sun_arc" in request:
        key = "sun_arc" if "sun_arc" in request else "light_directions"
        raise PathError(key, "a usd_camera path animates the rig's USD lights by their time samples; give "
                        "light_directions or sun_arc with a camera_path")
    return _usd_frames(request, base, scene_path, reader)


def _with_light_set(request: dict, base: dict, frames: list[dict]) -> list[dict]:
    """light_directions / sun_arc along a camera path: one direction per frame (or one for all frames),
    replacing the rig's light `light_index` with a directional light (as in a batch)."""
    dirs = light_set(request, base)
    if dirs is None:
        return frames
    key = "sun_arc" if "sun_arc" in request else "light_directions"
    if len(dirs) not in (1, len(frames)):
        raise PathError(key, f"{len(dirs)} light directions for {len(frames)} frames: give one per frame, or one")
    slot = light_slot(request, base)
    for k, f in enumerate(frames):
        lights = list(f["rig"].get("lights") or [])
        lights[slot:slot + 1] = [{"type": "directional", "direction": dirs[k if len(dirs) > 1 else 0]}]
        f["rig"] = {**f["rig"], "lights": lights}
    return frames


def time_codes(spec) -> list[float]:
    """start, start + step, ... up to end (inclusive within 1e-9 of a step)."""
    if not isinstance(spec, dict):
        raise PathError("time", "expected {\"start\", \"end\", \"step\"} in time codes")
    unknown = sorted(set(spec) - {"start", "end", "step"})
    if unknown:
        raise PathError(f"time.{unknown[0]}", "unknown field (known: start, end, step)")
    vals = {}
    for k in ("start", "end", "step"):
        v = spec.get(k, 1.0 if k == "step" else None)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise PathError(f"time.{k}", f"expected a finite number, got {v!r}")
        vals[k] = float(v)
    if vals["step"] <= 0:
        raise PathError("time.step", f"must be positive, got {vals['step']:g}")
    if vals["end"] < vals["start"]:
        raise PathError("time.end", f"{vals['end']:g} is before time.start {vals['start']:g}")
    q = (vals["end"] - vals["start"]) / vals["step"]  # overflows to inf for extreme ranges or tiny steps
    if not math.isfinite(q) or q + 1 > MAX_TIME_FRAMES:
        raise PathError("time", f"(end - start) / step + 1 = {q + 1:g} frames exceed the limit of {MAX_TIME_FRAMES} "
                        "time codes")
    n = int(math.floor(q + 1e-9)) + 1
    if n > MAX_TIME_FRAMES:
        raise PathError("time", f"{n} frames exceed the limit of {MAX_TIME_FRAMES} time codes")
    return [vals["start"] + k * vals["step"] for k in range(n)]


def _usd_frames(request: dict, base: dict, scene_path, reader) -> tuple[list[dict], list[str]]:
    base_cam = base.get("camera") if isinstance(base.get("camera"), dict) else {}
    cam_path = request.get("usd_camera", base_cam.get("usd_path"))
    if not isinstance(cam_path, str) or not cam_path.startswith("/"):
        raise PathError("usd_camera", f"expected a camera prim path such as /World/Camera, got {cam_path!r}")
    if "time" not in request:
        raise PathError("time", "a usd_camera path needs time {\"start\", \"end\", \"step\"}")
    times = time_codes(request["time"])
    if base.get("frame") == "stage":
        raise PathError("rig.frame", "a USD camera is read in the world frame (+Y up, metres): use rig.frame "
                        "\"world\" (output.frame sets the frame of the answer)")
    lights = base.get("lights") or []
    light_paths = [l["usd_path"] for l in lights if isinstance(l, dict) and isinstance(l.get("usd_path"), str)]
    if reader is None:
        if scene_path is None:
            raise PathError("usd_camera", "a usd_camera path needs the scene")
        from ..renderers.usd_animation import read_animation  # lazy: pxr, only for a usd_camera path read here

        def reader(c, t, lp):
            return read_animation(scene_path, c, t, light_paths=lp)
    anim = reader(cam_path, times, light_paths)
    if anim["camera"] is None:
        what = f"is a {anim['camera_type']}, not a Camera" if anim["camera_type"] else "is not a prim of the scene"
        raise PathError("usd_camera", f"{cam_path} {what}")
    problems = anim.get("camera_problems") or []
    if problems:  # a frame solved with a made-up field of view or a NaN pose would be a wrong answer
        more = f" (and {len(problems) - 1} more)" if len(problems) > 1 else ""
        raise PathError("usd_camera", f"{problems[0]}{more}: fix the camera's time samples, or give the path "
                        "as a camera_path")
    notes = []
    views = anim["camera"]
    if len(times) > 1 and all(_same_view(views[0], v) for v in views[1:]):
        notes.append(f"{cam_path} does not move over these time codes (no time samples there): every frame "
                     "has the same view")
    if anim.get("time_range") and (times[0] < anim["time_range"][0] or times[-1] > anim["time_range"][1]):
        notes.append(f"time codes {times[0]:g}..{times[-1]:g} reach outside the stage's range "
                     f"{anim['time_range'][0]:g}..{anim['time_range'][1]:g}: values there are held")
    moving = bool(anim.get("moving"))
    if moving:
        shown = ", ".join(anim["moving"][:5]) + (" ..." if len(anim["moving"]) > 5 else "")
        notes.append(f"geometry moves over time ({shown}): each frame reads the stage's geometry at its time code")
    for j, l in enumerate(lights):
        if isinstance(l, dict) and isinstance(l.get("usd_path"), str) and l["usd_path"] not in anim["lights"]:
            raise PathError(f"rig.lights.{j}.usd_path", f"{l['usd_path']} is not a light of the scene")
    # Every USD light becomes the explicit light it is at each frame's time code: a light that holds one value
    # over the frames asked for may still differ from its default-time value, which the solve would read.
    animated = dict(anim["lights"])
    notes += [str(w) for w in anim.get("warnings") or []]  # e.g. camera values USD's fallbacks replaced
    frames = []
    for k, (t, v) in enumerate(zip(times, views)):
        cam = {key: val for key, val in base_cam.items() if key not in ("usd_path", "target", "forward", "position")}
        cam.update(position=_floats(v.position), forward=_floats(v.forward), up=_floats(v.up),
                   fov_y_deg=float(v.fov_y_deg), near=float(v.near), far=float(v.far))
        rig = {**base, "camera": cam, "lights": [_light_at(l, animated, k) for l in lights]}
        frames.append({"rig": rig, "frame": k, "time": t, **({"scene_time": t} if moving else {})})
    return frames, notes


def _floats(a) -> list[float]:
    return [float(x) for x in a]


def _same_view(a, b) -> bool:
    return (np.allclose(a.position, b.position) and np.allclose(a.forward, b.forward) and np.allclose(a.up, b.up)
            and math.isclose(a.fov_y_deg, b.fov_y_deg) and math.isclose(a.near, b.near) and math.isclose(a.far, b.far))


def _same_light(a, b) -> bool:
    return all((x is None and y is None) or (x is not None and y is not None and np.allclose(x, y))
               for x, y in ((a.position, b.position), (a.direction, b.direction))) and a.cone_deg == b.cone_deg


def _light_at(light, animated: dict, k: int):
    """A rig light at frame k: a USD light becomes the explicit light it is at that frame's time code."""
    if not isinstance(light, dict) or light.get("usd_path") not in animated:
        return light
    u = animated[light["usd_path"]][k]
    if u.type == "directional":
        return {"type": "directional", "direction": _floats(u.direction)}
    if u.type == "spot":
        return {"type": "spot", "position": _floats(u.position), "direction": _floats(u.direction),
                "cone_deg": float(u.cone_deg)}
    if u.type == "point":
        return {"type": "point", "position": _floats(u.position)}
    return light


def is_coherent(method: str | None, coherent: bool | None) -> bool:
    return bool(coherent) or method in COHERENT_METHODS


def is_whole_path(method: str | None, coherent: bool | None) -> bool:
    """Method path over a path job: the frames solved together in tasks of job_kinds.WHOLE_PATH_FRAMES
    (service.solve.solve_path: segments that hold their texel grid), unless `coherent` asks for the editor's
    form (each frame given the previous one's solution)."""
    return method in WHOLE_PATH_METHODS and not coherent


def line_json(line: dict) -> str:
    """A result line as the CLI prints it: frame and time first, then the solution (or the error)."""
    head = {"frame": line.get("frame", line["index"]), "time": line.get("time")}
    return dumps({**head, **{k: v for k, v in line.items() if k not in head}})
