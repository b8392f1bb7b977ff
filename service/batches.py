"""Batch precomputation: configurations from a request, their execution on a local process pool or on
Ray, and hints for interpolating between neighbouring results.

The parent process writes each configuration's outcome to the Store as it arrives (idempotent by index),
so a crash loses at most the configurations in flight; `BatchRunner.resume()` re-queues only the
pending indices. Workers load the scene once per process (service.scenes.SCENES) and call
service.solve.solve. Rigs reach this module already validated (the server and the CLI use the pydantic
Rig); this module imports nothing of api but its progress bar (api.progress, standard library only).
"""
from __future__ import annotations

import collections
import copy
import json
import logging
import math
import os
import sys
import tempfile
import threading
import time
from concurrent.futures import FIRST_COMPLETED, wait
from dataclasses import dataclass
from pathlib import Path

from .rigs import FieldError
from .store import UNFINISHED, Store

log = logging.getLogger("shadowopt.batches")

MAX_CONFIGURATIONS = 100_000
MAX_SAMPLES = 10_000
BACKENDS = ("local", "ray")
DEFAULT_METHOD = "optimized"
IN_FLIGHT_PER_WORKER = 2  # keeps workers busy while a cancel takes effect within a configuration or two
MAX_RETRIES = 1  # a configuration in flight when a worker process dies is tried once more
RUNNER_RETRIES, RUNNER_RETRY_S = 3, 1.0  # a batch whose run fails as a whole is re-queued this often first
SLICE = 64  # configurations a batch runs before it lets a batch that arrived meanwhile take a turn
CHUNK = 8  # at most this many configurations per worker task (one round trip, one store commit)
WHOLE_PATH_FRAMES = 48  # method path over a path job: frames solved together per task (frame index // this)


class BatchError(FieldError):
    """A batch request is malformed (`field` e.g. `sun_arc.samples`)."""

    code = "invalid_batch"


# -- configurations ------------------------------------------------------------------------------

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
    cameras = _camera_path(request["camera_path"], base.get("camera")) if "camera_path" in request else None
    directions = _light_set(request, base)
    if cameras is None and directions is None:
        raise BatchError("camera_path", "give a camera_path, light_directions or a sun_arc with the base rig")
    n = len(cameras or [None]) * len(directions or [None])
    if n > MAX_CONFIGURATIONS:
        raise BatchError("camera_path" if cameras else "light_directions",
                         f"{n} configurations exceed the limit of {MAX_CONFIGURATIONS}")
    slot = _light_slot(request, base) if directions is not None else None
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
    cams = len(_camera_path(request["camera_path"], request["rig"].get("camera"))) if "camera_path" in request else 1
    dirs = _light_set(request, request["rig"])
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


def _number(v, field: str, lo: float = -math.inf, hi: float = math.inf) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise BatchError(field, f"expected a finite number, got {v!r}")
    if not lo <= v <= hi:
        raise BatchError(field, f"{v} is outside [{lo:g}, {hi:g}]")
    return float(v)


def _vec3(v, field: str, nonzero: bool = False) -> list[float]:
    if not isinstance(v, (list, tuple)) or len(v) != 3:
        raise BatchError(field, f"expected [x, y, z], got {v!r}")
    out = [_number(x, f"{field}.{k}") for k, x in enumerate(v)]
    if nonzero and not any(out):
        raise BatchError(field, "must not be the zero vector")
    return out


def _samples(v, field: str) -> int:
    if isinstance(v, bool) or not isinstance(v, int) or not 1 <= v <= MAX_SAMPLES:
        raise BatchError(field, f"expected an integer in [1, {MAX_SAMPLES}], got {v!r}")
    return v


def _range(v, field: str, lo: float, hi: float) -> tuple[float, float]:
    """A number (constant) or [from, to]."""
    if isinstance(v, (list, tuple)):
        if len(v) != 2:
            raise BatchError(field, f"expected a number or [from, to], got {v!r}")
        return _number(v[0], f"{field}.0", lo, hi), _number(v[1], f"{field}.1", lo, hi)
    x = _number(v, field, lo, hi)
    return x, x


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


def _camera_path(path, base_cam) -> list[dict]:
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
                    _vec3(p[k], f"camera_path.poses.{i}.{k}", nonzero=k in ("forward", "up"))
        return [_merge_pose(base_cam, p) for p in poses]
    return _keyframes(path["keyframes"], _samples(path.get("samples"), "camera_path.samples"), base_cam)


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
        p = {"position": _vec3(k["position"], f"{f}.position"), aim: _vec3(k[aim], f"{f}.{aim}", nonzero=aim == "forward")}
        if "up" in k:
            p["up"] = _vec3(k["up"], f"{f}.up", nonzero=True)
        for name in _LERPED:
            if name in k and k[name] is not None:
                p[name] = _number(k[name], f"{f}.{name}", 0.0)
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


def _light_set(request: dict, base: dict) -> list[list[float]] | None:
    if "light_directions" in request and "sun_arc" in request:
        raise BatchError("sun_arc", "give either light_directions or a sun_arc, not both")
    if "light_directions" in request:
        dirs = request["light_directions"]
        if not isinstance(dirs, list) or not dirs:
            raise BatchError("light_directions", "expected a non-empty list of [x, y, z] directions")
        return [_vec3(d, f"light_directions.{i}", nonzero=True) for i, d in enumerate(dirs)]
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
    az = _range(arc.get("azimuth_deg", 0.0), "sun_arc.azimuth_deg", -720.0, 720.0)
    if "elevation_deg" not in arc:
        raise BatchError("sun_arc.elevation_deg", "required: a number or [from, to] in degrees above the horizon")
    el = _range(arc["elevation_deg"], "sun_arc.elevation_deg", -90.0, 90.0)
    n = _samples(arc.get("samples", 1), "sun_arc.samples")
    out = []
    for j in range(n):
        u = 0.0 if n == 1 else j / (n - 1)
        a = math.radians(az[0] + (az[1] - az[0]) * u)
        e = math.radians(el[0] + (el[1] - el[0]) * u)
        to_sun = (math.cos(e) * math.sin(a), math.sin(e), math.cos(e) * math.cos(a))
        out.append([-c for c in to_sun])
    return out


def _light_slot(request: dict, base: dict) -> int:
    k = request.get("light_index", 0)
    n = len(base.get("lights") or [])
    if isinstance(k, bool) or not isinstance(k, int) or not 0 <= k <= max(n - 1, 0):
        raise BatchError("light_index", f"expected an index into rig.lights (0..{max(n - 1, 0)}), got {k!r}")
    return k


# -- interpolation hints ---------------------------------------------------------------------------

SMOOTH_FIELDS = [
    "lights[].cascades[].view_matrix", "lights[].cascades[].projection_matrix",
    "lights[].cascades[].texture_matrix", "lights[].cascades[].split", "lights[].cascades[].light_depth",
    "lights[].cascades[].blend_band", "lights[].cascades[].warp.eta", "lights[].cascades[].warp.n",
    "lights[].cascades[].warp.log.c0", "lights[].cascades[].warp.log.c1", "lights[].cascades[].warp.log.c2",
    "lights[].cascades[].depth_bias", "lights[].cascades[].depth.hardware", "lights[].cascades[].depth.linear",
    "lights[].cascades[].predicted_error", "lights[].predicted_error",
]
SWITCH_FIELDS = ["lights[].cascades (count)", "lights[].cascades[].warp.kind", "lights[].cascades[].resolution",
                 "lights[].cascades[].face", "lights[].cascades[].depth.mode", "lights[].type", "method"]


def _signature(result: dict) -> tuple:
    return (result.get("method"), tuple(
        (l.get("type"), len(l.get("cascades") or []),
         tuple((c.get("warp") or {}).get("kind") for c in l.get("cascades") or []),
         tuple(tuple(c.get("resolution") or ()) for c in l.get("cascades") or []),
         tuple(c.get("face") for c in l.get("cascades") or []),
         tuple((c.get("depth") or {}).get("mode") for c in l.get("cascades") or []))
        for l in result.get("lights") or []))


def _switch_reasons(a: dict, b: dict) -> list[str]:
    sa, sb = _signature(a), _signature(b)
    if sa[0] != sb[0]:
        return [f"method {sa[0]} -> {sb[0]}"]
    if len(sa[1]) != len(sb[1]):
        return [f"lights {len(sa[1])} -> {len(sb[1])}"]
    reasons = []
    for k, (la, lb) in enumerate(zip(sa[1], sb[1])):
        if la[0] != lb[0]:
            reasons.append(f"light {k}: type {la[0]} -> {lb[0]}")
        if la[1] != lb[1]:
            reasons.append(f"light {k}: cascades {la[1]} -> {lb[1]}")
        elif la[2] != lb[2]:
            reasons.append(f"light {k}: warp kind {'/'.join(map(str, la[2]))} -> {'/'.join(map(str, lb[2]))}")
        elif la[3] != lb[3] or la[4] != lb[4]:
            reasons.append(f"light {k}: cascade resolution or face changes")
        elif la[5] != lb[5]:
            reasons.append(f"light {k}: depth mode {'/'.join(map(str, la[5]))} -> {'/'.join(map(str, lb[5]))}")
    return reasons


def interpolation_hints(results: list[dict], shape: tuple[int, int] | None = None) -> dict:
    """How an engine may interpolate between neighbouring configurations' solutions.

    `results`: lines as Store.results gives them ({"index", ...solution} or {"index", "error"}).
    Neighbours are consecutive indices; with `shape = (cameras, lights)` (a camera path crossed with
    light directions, index = camera * lights + light) also the same light at consecutive cameras.
    Returns {"smooth_fields", "switch_fields", "breaks": [{"between": [i, j], "reasons": [...]}],
    "segments": [[first, last], ...]} where segments are runs of consecutive indices with no break (along
    the lights of one camera; along the cameras when there is one light), and for a grid of several cameras
    and lights also "camera_segments": the same light at consecutive cameras, [first, last] stepping by
    the number of lights. Interpolate smooth fields element-wise within a segment, never across a break.
    """
    by_index = {r["index"]: r for r in results}
    pairs = []
    if shape is None:
        idx = sorted(by_index)
        pairs = [(i, i + 1) for i in range(idx[0], idx[-1])] if idx else []
    else:
        cams, lights = shape
        for c in range(cams):
            for l in range(lights):
                i = c * lights + l
                if l + 1 < lights:
                    pairs.append((i, i + 1))
                if c + 1 < cams:
                    pairs.append((i, i + lights))
    breaks = []
    for i, j in pairs:
        a, b = by_index.get(i), by_index.get(j)
        if a is None or b is None or "error" in a or "error" in b:
            why = [f"configuration {k} has no result" for k, r in ((i, a), (j, b)) if r is None or "error" in r]
            breaks.append({"between": [i, j], "reasons": why})
            continue
        reasons = _switch_reasons(a, b)
        if reasons:
            breaks.append({"between": [i, j], "reasons": reasons})
    ok = sorted(k for k, r in by_index.items() if "error" not in r)
    broken = {tuple(b["between"]) for b in breaks}
    hints = {"smooth_fields": SMOOTH_FIELDS, "switch_fields": SWITCH_FIELDS, "breaks": breaks,
             "segments": _segments(ok, broken, shape),
             "neighbours": "consecutive indices" if shape is None else
             f"index = camera * {shape[1]} + light; neighbours along both axes"}
    if shape is not None and shape[0] > 1 and shape[1] > 1:
        hints["camera_segments"] = _camera_segments(set(ok), broken, shape)
    return hints


def _segments(ok: list[int], broken: set, shape) -> list[list[int]]:
    """Runs of consecutive successful indices along the index order: the light axis of a grid, or the
    camera axis when a camera path has one light (then consecutive indices are consecutive cameras)."""
    out = []
    for i in ok:
        same_row = shape is None or shape[1] == 1 or (i - 1) // shape[1] == i // shape[1]
        if out and out[-1][1] == i - 1 and same_row and (i - 1, i) not in broken:
            out[-1][1] = i
        else:
            out.append([i, i])
    return out


def _camera_segments(ok: set, broken: set, shape) -> list[list[int]]:
    """For a grid with several lights: runs of the same light at consecutive cameras, [first, last] indices
    (stepping by the number of lights), in the order of the light then the first camera."""
    cams, lights = shape
    out = []
    for l in range(lights):
        run = None
        for c in range(cams):
            i = c * lights + l
            if i in ok and run is not None and run[1] == i - lights and (i - lights, i) not in broken:
                run[1] = i
            elif i in ok:
                run = [i, i]
                out.append(run)
            else:
                run = None
    return out


# -- workers ---------------------------------------------------------------------------------------

def _llvm_path() -> str | None:
    from ..solvers.jit import pick_llvm

    path = pick_llvm()
    if path:
        os.environ.setdefault("DRJIT_LIBLLVM_PATH", path)
    return path


THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def _worker_init(llvm: str | None, threads: int | None = None, parent_pid: int | None = None,
                 pdeathsig: bool = False) -> None:
    """Runs first in each worker: with `parent_pid` (the local pool) it exits when that process is gone
    (service.isolation.die_with_parent: a SIGKILLed server leaves no worker behind); then LLVM for
    Dr.Jit, and its share of the cores for the math libraries (as Ray does for its workers) unless the
    caller set them."""
    if parent_pid is not None:
        from .isolation import die_with_parent

        die_with_parent(parent_pid, pdeathsig=pdeathsig)
    if llvm:
        os.environ["DRJIT_LIBLLVM_PATH"] = llvm
    if threads:
        for var in THREAD_VARS:
            os.environ.setdefault(var, str(threads))
        _jit_threads(threads)


def _jit_threads(threads: int) -> None:
    """Dr.Jit's kernel threads in a worker: its share of the cores. Dr.Jit's pool defaults to every core in
    each process, so two workers on two cores ran four kernel threads that spun against each other and
    against NumPy (measured on the demo path: the edge-pass kernel 2.4 ms with one thread, 5-6 ms with two
    while another worker ran). Kernels are element-wise, so results are the same bits (checked on every
    method); solvers.metric.serial_kernels restores this count after its own serial sections."""
    try:
        import drjit as dr

        dr.set_thread_count(max(1, int(threads)))
    except Exception:  # no Dr.Jit here: nothing to size
        pass


def _solve_with(get_entry, config: dict, settings: dict) -> dict:
    """One configuration: {"result": solution} or {"error": {"code", "message"}}; never raises."""
    from ..renderers.scene_data import SceneError
    from .rigs import RigError, SolutionError

    try:
        from .request import SolveRequest
        from .solve import solve

        rig = config["rig"]
        entry = get_entry()
        sol = solve(entry, rig, SolveRequest(method=config.get("method") or settings.get("method") or DEFAULT_METHOD,
                    solver=settings.get("solver"), time_budget_ms=settings.get("time_budget_ms"),
                    previous=config.get("previous")))  # a coherent path's previous frame (service.paths)
        if "resolved" not in sol:  # what this configuration was solved for (service.echo)
            from .echo import resolved_echo
            from .rigs import resolve_rig

            sol["resolved"] = resolved_echo(resolve_rig(rig, entry.loaded), rig.get("frame", "world"))
        for k in ("frame", "time", "scene_time"):  # a path job's frame index and time codes (service.paths)
            if k in config:
                sol[k] = config[k]
        if config.get("scene_time") is not None and entry.loaded.warnings:
            # what the loader reported reading the stage at this frame's time code (a mesh skipped there for
            # NaN points, a prim invalid at t): the frame's own load, so its own line says it
            sol["warnings"] = list(entry.loaded.warnings)
        return {"result": sol}
    except SceneError as e:
        t = config.get("scene_time")
        where = f"the stage at time code {t:g}: " if isinstance(t, (int, float)) else ""
        return {"error": {"code": e.code, "message": where + e.message}}
    except (RigError, SolutionError) as e:
        return {"error": {"code": e.code, "message": str(e)}}
    except (KeyError, TypeError, ValueError, IndexError) as e:
        return {"error": {"code": "invalid_configuration", "message": f"{type(e).__name__}: {e}"}}
    except Exception as e:  # keep the batch going; the message says what broke
        return {"error": {"code": "internal_error", "message": f"{type(e).__name__}: {e}"}}


def _worker_entry(scene_path: str, sandbox: bool, settings: dict, time_code: float | None = None):
    """The scene in a worker, loaded once per process by the SCENES cache, in-process (the worker is its
    own process already) but under the server's triangle limit (settings["max_triangles"], set by the
    runner from its own max_triangles, never from what was stored with the batch): a scene stored before
    the limit existed, or before it was lowered, is refused as too_many_triangles like a new upload.
    An upload read at a path frame's time code (`time_code`, the frame's "scene_time") is a new load of the
    stage, which the upload's check at its default time says nothing about (a stage can be light there and
    heavy at t = 5): it runs as an upload's load does, in an isolated child under the server's load limits
    (settings["load_limits"]: max_triangles, memory_bytes, timeout_s, set by the runner; isolation's
    defaults without them), and over one of them the frame fails with that limit's SceneError."""
    from .scenes import SCENES

    global _WORKER_CACHE_SET
    if not _WORKER_CACHE_SET:  # a worker's cache has one owner (None): all of it, not a tenant's share, so a
        SCENES.configure(tenant_share=1.0)  # scene over half of it is still kept rather than reloaded per item
        _WORKER_CACHE_SET = True
    if time_code is not None and sandbox:
        return SCENES.get(scene_path, time_code=time_code, sandbox=sandbox, limits=frame_load_limits(settings))
    # time_code: a path frame over moving geometry (service.paths: "scene_time"), the stage read at that time
    return SCENES.get(scene_path, time_code=time_code, sandbox=sandbox, max_triangles=settings.get("max_triangles"))


def frame_load_limits(settings: dict):
    """service.isolation.LoadLimits of a path frame's load of an upload: the runner's load_limits (the server's
    upload limits), the triangle limit the runner sets otherwise, isolation's defaults for the rest."""
    from .isolation import LoadLimits

    given = dict(settings.get("load_limits") or {})
    if settings.get("max_triangles") is not None:
        given.setdefault("max_triangles", settings["max_triangles"])
    return LoadLimits(**{k: v for k, v in given.items() if k in ("max_triangles", "memory_bytes", "timeout_s")})


_WORKER_CACHE_SET = False


def solve_configuration(scene_path: str, sandbox: bool, config: dict, settings: dict) -> dict:
    """Worker entry point (local pool)."""
    return _solve_with(lambda: _worker_entry(scene_path, sandbox, settings, config.get("scene_time")), config, settings)


def _solve_whole_with(get_entry, group: list[tuple[int, dict]], settings: dict) -> list[tuple[int, dict]]:
    """A whole-path task (settings["whole_path"]): the group's frames solved together by service.solve.solve_path,
    each outcome with the frame's extras. Raises on any failure (solve_group then solves frame by frame)."""
    from .solve import solve_path

    sols = solve_path(get_entry(), [c["rig"] for _, c in group], solver=settings.get("solver"))
    out = []
    for (i, c), sol in zip(group, sols):
        for k in ("frame", "time", "scene_time"):
            if k in c:
                sol[k] = c[k]
        out.append((i, {"result": sol}))
    return out


def solve_group(solve_one, group: list[tuple[int, dict]], settings: dict, solve_whole=None) -> list[tuple[int, dict]]:
    """A worker task: several configurations one after another, [(index, outcome), ...]. In a coherent
    path (settings["coherent"]) a frame whose configuration brings no "previous" gets the frame before it
    in this task as its previous, as service.paths.previous_of reads it back from the store (a JSON round
    trip, so the same numbers as a frame solved in its own task); the task's first frame brings its own
    (or none: the first frame of a coherent chunk)."""
    from .paths import previous_of

    if settings.get("whole_path") and solve_whole is not None and group \
            and all(c.get("scene_time") is None for _, c in group):  # moving geometry: a stage per frame
        try:
            return solve_whole(group)
        except Exception:  # a frame that fails: every frame alone, each failure on its own line
            pass
    out, prev_index, prev = [], None, None
    for i, c in group:
        if settings.get("coherent") and "previous" not in c and prev is not None and prev_index == i - 1:
            c = {**c, "previous": prev}
        o = solve_one(c)
        out.append((i, o))
        prev_index, prev = i, previous_of(json.loads(json.dumps(o["result"]))) if "result" in o else None
    return out


def solve_chunk(scene_path: str, sandbox: bool, group: list[tuple[int, dict]], settings: dict) -> list[tuple[int, dict]]:
    """Worker entry point (local pool) for a task of several configurations (solve_group)."""
    return solve_group(lambda c: solve_configuration(scene_path, sandbox, c, settings), group, settings,
                       lambda g: _solve_whole_with(lambda: _worker_entry(scene_path, sandbox, settings), g, settings))


class TaskQueue:
    """The worker tasks of a run: groups of (index, config), each one round trip to a worker and one store
    commit. `take()` gives the next group (None: none ready now), `finished()` says no group will come,
    `done(outcomes)` is told each task's outcomes (a coherent path's next task is ready once the one
    before it is back: service.paths). `pause()`: start no new task (those in flight finish)."""

    def __init__(self, groups=(), pause=None):
        self.groups = collections.deque(groups)
        self.pause = pause or (lambda: False)

    def take(self):
        return self.groups.popleft() if self.groups and not self.pause() else None

    def finished(self) -> bool:
        return not self.groups or self.pause()

    def done(self, outcomes) -> None:
        pass

    def retry(self, group) -> None:
        """A group lost with its worker, to run again (first)."""
        self.groups.appendleft(group)


def chunk_size(n: int, workers: int) -> int:
    """Configurations per task for n independent ones: up to CHUNK, but enough tasks to keep every worker
    busy (IN_FLIGHT_PER_WORKER each) to the end."""
    return max(1, min(CHUNK, n // max(1, workers * IN_FLIGHT_PER_WORKER * 2)))


def chunked(items: list, size: int) -> list[list]:
    return [items[k:k + size] for k in range(0, len(items), max(1, size))]


@dataclass
class SceneJob:
    path: str
    filename: str
    sandbox: bool


class _LocalBackend:
    """A spawn ProcessPoolExecutor; recreated when a worker process dies."""

    def __init__(self, workers: int):
        self.workers = workers
        self.llvm = _llvm_path()
        self.threads = max(1, (os.cpu_count() or 1) // workers)
        self.pool = None

    def _ensure_pool(self):
        if self.pool is None:
            import multiprocessing

            from .isolation import DyingProcessPool

            # Workers are started on service.isolation's spawner thread, which lives as long as this
            # process: their parent-death signal cannot fire because the thread that submitted ended.
            self.pool = DyingProcessPool(max_workers=self.workers, mp_context=multiprocessing.get_context("spawn"),
                                         initializer=_worker_init,
                                         initargs=(self.llvm, self.threads, os.getpid(),
                                                   DyingProcessPool.pdeathsig_safe()))
        return self.pool

    def run(self, job: SceneJob, items: list[tuple[int, dict]], settings: dict, should_stop):
        """Each configuration its own task; yields (index, outcome) as they complete."""
        for outs in self.run_groups(job, TaskQueue([[ic] for ic in items]), settings, should_stop):
            yield from outs

    def run_groups(self, job: SceneJob, tasks: TaskQueue, settings: dict, should_stop):
        """Run the queue's tasks (solve_chunk), IN_FLIGHT_PER_WORKER per worker; yields each task's
        [(index, outcome), ...] as it completes. A task lost with a dying worker runs once more (an
        independent one split into single configurations, so only a configuration that kills its worker
        again fails: worker_crashed)."""
        from concurrent.futures.process import BrokenProcessPool

        retries = collections.deque()  # (group, tries) lost with a worker
        inflight = {}
        try:
            while True:
                if should_stop():
                    return
                pool = self._ensure_pool()
                while len(inflight) < self.workers * IN_FLIGHT_PER_WORKER:
                    group, tries = retries.popleft() if retries else (tasks.take(), 0)
                    if group is None:
                        break
                    inflight[pool.submit(solve_chunk, job.path, job.sandbox, group, settings)] = (group, tries)
                if not inflight:
                    if retries or not tasks.finished():
                        time.sleep(0.01)  # nothing was ready (the queue said so): ask again
                        continue
                    return
                done, _ = wait(list(inflight), timeout=0.5, return_when=FIRST_COMPLETED)
                broken = False
                for fut in done:
                    try:
                        outs = fut.result()
                    except BrokenProcessPool:
                        broken = True
                        continue
                    except Exception as e:
                        group, _ = inflight[fut]
                        outs = [(i, {"error": {"code": "internal_error", "message": f"{type(e).__name__}: {e}"}})
                                for i, _ in group]
                    inflight.pop(fut)
                    tasks.done(outs)
                    yield outs
                if broken:
                    for lost in self._after_crash(inflight, retries, coherent=bool(settings.get("coherent"))):
                        tasks.done(lost)
                        yield lost
        finally:
            for fut in inflight:
                fut.cancel()

    def _after_crash(self, inflight: dict, retries: collections.deque, coherent: bool) -> list[list]:
        """A worker died: everything in flight is lost. Retry each task once in a new pool (independent
        configurations one by one), then give up on it; the outcomes given up, per task."""
        log.warning("a batch worker process died; restarting the pool")
        self.pool.shutdown(wait=False, cancel_futures=True)
        self.pool = None
        failed = []
        for fut, (group, tries) in sorted(inflight.items(), key=lambda kv: -kv[1][0][0][0]):
            if tries < MAX_RETRIES:
                for g in ([group] if coherent else [[ic] for ic in reversed(group)]):
                    retries.appendleft((g, tries + 1))
            else:
                failed.append([(i, {"error": {"code": "worker_crashed",
                                              "message": "the worker process died while solving this configuration"}})
                               for i, _ in group])
        inflight.clear()
        return sorted(failed, key=lambda g: g[0][0])

    def close(self, wait_workers: bool = True):
        if self.pool is not None:
            self.pool.shutdown(wait=wait_workers, cancel_futures=True)
            self.pool = None


class SceneSolver:
    """A Ray actor body: receives the scene file's bytes once, loads it once, solves configurations."""

    def __init__(self, data: bytes, path: str, filename: str, sandbox: bool, llvm: str | None):
        _worker_init(llvm, threads=1)  # an actor holds one CPU (num_cpus=1): one kernel thread, as Ray's OMP_NUM_THREADS
        if not sandbox and os.path.isfile(path):
            self.path = path  # same machine, a local file: keep its relative asset references working
        else:
            import hashlib

            # One copy per distinct file on this node, reused by later actors (no pile of temp folders).
            folder = Path(tempfile.gettempdir()) / "shadowopt-ray-scenes" / hashlib.sha256(data).hexdigest()[:16]
            folder.mkdir(parents=True, exist_ok=True)
            self.path = str(folder / filename)
            if not os.path.isfile(self.path) or os.path.getsize(self.path) != len(data):
                tmp = f"{self.path}.{os.getpid()}.tmp"
                Path(tmp).write_bytes(data)
                os.replace(tmp, self.path)
        self.sandbox = sandbox

    def solve(self, config: dict, settings: dict) -> dict:
        return _solve_with(lambda: _worker_entry(self.path, self.sandbox, settings, config.get("scene_time")), config,
                           settings)

    def solve_chunk(self, group: list, settings: dict) -> list:
        return solve_group(lambda c: self.solve(c, settings), group, settings,
                           lambda g: _solve_whole_with(lambda: _worker_entry(self.path, self.sandbox, settings), g,
                                                       settings))

    def pid(self) -> int:
        return os.getpid()

    def getenv(self, name: str) -> str | None:
        return os.environ.get(name)


class _RayBackend:
    """Ray actors (one per worker, each loading the shipped scene once), on `address` or a local instance."""

    def __init__(self, workers: int, address: str | None):
        import ray

        self.ray = ray
        self.workers = workers
        self.llvm = _llvm_path()
        self.owns = False
        if not ray.is_initialized():
            env = {"env_vars": {"DRJIT_LIBLLVM_PATH": self.llvm}} if self.llvm else None
            if address:
                ray.init(address=address, runtime_env=env, log_to_driver=False)
            else:
                ray.init(num_cpus=workers, include_dashboard=False, runtime_env=env, log_to_driver=False,
                         object_store_memory=128 * 1024 * 1024)
            self.owns = True
        self.actor_cls = ray.remote(num_cpus=1, max_restarts=0)(SceneSolver)
        self.actors: list = []
        self.actors_key = None
        self.spawn = None
        self.last_actor_pids: list[int] = []

    def _actors_for(self, job: SceneJob) -> list:
        """One actor per worker holding this scene; kept while consecutive batches use the same file."""
        st = os.stat(job.path)
        key = (job.path, st.st_size, st.st_mtime_ns, job.sandbox)
        if self.actors_key != key:
            self._kill_actors()
            data_ref = self.ray.put(Path(job.path).read_bytes())  # shipped once; each actor receives it once
            self.spawn = lambda: self.actor_cls.remote(data_ref, job.path, job.filename, job.sandbox, self.llvm)
            self.actors = [self.spawn() for _ in range(self.workers)]
            self.actors_key = key
        return self.actors

    def _kill_actors(self) -> None:
        for a in self.actors:
            self.ray.kill(a)
        self.actors, self.actors_key = [], None

    def run(self, job: SceneJob, items: list[tuple[int, dict]], settings: dict, should_stop):
        """Each configuration its own task; yields (index, outcome) as they complete."""
        for outs in self.run_groups(job, TaskQueue([[ic] for ic in items]), settings, should_stop):
            yield from outs

    def run_groups(self, job: SceneJob, tasks: TaskQueue, settings: dict, should_stop):
        """As _LocalBackend.run_groups, on the actors (IN_FLIGHT_PER_WORKER tasks each); a dead actor is
        replaced and its tasks run once more."""
        ray = self.ray
        actors = self._actors_for(job)
        retries = collections.deque()
        inflight = {}  # ObjectRef -> (group, tries, actor)
        load = {id(a): 0 for a in actors}
        coherent = bool(settings.get("coherent"))
        try:
            while True:
                if should_stop():
                    return
                while True:  # the least loaded actor first: a coherent path's chunks (one task each) spread out
                    a = min(actors, key=lambda x: load[id(x)])
                    if load[id(a)] >= IN_FLIGHT_PER_WORKER:
                        break
                    group, tries = retries.popleft() if retries else (tasks.take(), 0)
                    if group is None:
                        break
                    inflight[a.solve_chunk.remote(group, settings)] = (group, tries, a)
                    load[id(a)] += 1
                if not inflight:
                    if retries or not tasks.finished():
                        time.sleep(0.01)
                        continue
                    break
                ready, _ = ray.wait(list(inflight), num_returns=1, timeout=0.5)
                for ref in ready:
                    group, tries, a = inflight.pop(ref)
                    load[id(a)] -= 1
                    try:
                        outs = ray.get(ref)
                    except ray.exceptions.RayActorError as e:
                        pos = next((k for k, x in enumerate(actors) if x is a), None)
                        if pos is not None:  # replace the dead actor (once per death)
                            actors[pos] = self.spawn()
                            load[id(actors[pos])] = 0
                        if tries < MAX_RETRIES:
                            for g in ([group] if coherent else [[ic] for ic in reversed(group)]):
                                retries.appendleft((g, tries + 1))
                            continue
                        outs = [(i, {"error": {"code": "worker_crashed", "message": f"Ray worker died: {e}"}})
                                for i, _ in group]
                    except Exception as e:
                        outs = [(i, {"error": {"code": "internal_error", "message": f"{type(e).__name__}: {e}"}})
                                for i, _ in group]
                    tasks.done(outs)
                    yield outs
            self.last_actor_pids = ray.get([a.pid.remote() for a in actors])
        finally:
            if inflight:  # abandoned (cancel, shutdown): do not leave work queued on the actors
                for ref in inflight:
                    ray.cancel(ref, force=False)
                self._kill_actors()

    def close(self, wait_workers: bool = True):
        if self.ray.is_initialized():
            self._kill_actors()
        if self.owns and self.ray.is_initialized():
            self.ray.shutdown()


# -- the runner ------------------------------------------------------------------------------------

class BatchRunner:
    """Runs queued batches one after another on a local spawn pool or Ray, writing each outcome to the store."""

    def __init__(self, store: Store, backend: str = "local", workers: int = 2, ray_address: str | None = None,
                 max_triangles: int | None = None, load_limits: dict | None = None):
        """max_triangles: the server's triangle limit, applied to every scene a worker loads (None: none,
        the CLI's own files). load_limits: the server's upload load limits {max_triangles, memory_bytes,
        timeout_s}, applied to an upload's load at a path frame's time code (_worker_entry)."""
        if backend not in BACKENDS:
            raise BatchError("backend", f"unknown backend {backend!r} (known: {', '.join(BACKENDS)})")
        if not isinstance(workers, int) or workers < 1:
            raise BatchError("workers", f"expected a positive integer, got {workers!r}")
        self.store = store
        self.backend = backend
        self.workers = workers
        self.ray_address = ray_address
        if max_triangles is not None and (isinstance(max_triangles, bool) or not isinstance(max_triangles, int)
                                          or max_triangles < 1):
            raise BatchError("max_triangles", f"expected a positive integer, got {max_triangles!r}")
        self.max_triangles = max_triangles
        self.load_limits = dict(load_limits) if load_limits else None
        self.stats = {"submitted": 0, "results": 0, "errors": 0}
        self._impl = None
        self._queue: collections.deque[tuple[str, str]] = collections.deque()
        self._cv = threading.Condition()
        self._current: str | None = None
        self._cancelled: set[str] = set()
        self._runner_failures: dict[str, int] = {}
        self._stop = False
        self._thread: threading.Thread | None = None
        self._turn_done = 0  # configurations the current batch stored in this turn

    # public
    def submit(self, tenant: str, batch_id: str) -> None:
        """Queue a batch (its pending configurations) for execution."""
        with self._cv:
            if self._stop:
                raise RuntimeError("the batch runner is shut down")
            if batch_id != self._current and all(b != batch_id for _, b in self._queue):
                self._queue.append((tenant, batch_id))
            self._cv.notify_all()
            if self._thread is None:
                self._thread = threading.Thread(target=self._loop, name="batch-runner", daemon=True)
                self._thread.start()

    def resume(self) -> list[str]:
        """Re-queue the store's unfinished batches (after a restart): only their pending indices run."""
        ids = []
        for tenant, batch_id in self.store.unfinished_batches():
            self.store.set_state(batch_id, "queued", only_from=("running",))
            self.submit(tenant, batch_id)
            ids.append(batch_id)
        return ids

    def cancel(self, tenant: str, batch_id: str) -> bool:
        """Cancel a batch (False: the tenant has no such batch). Configurations in flight are abandoned."""
        if not self.store.cancel_batch(tenant, batch_id):
            return False
        with self._cv:
            self._queue = collections.deque(q for q in self._queue if q[1] != batch_id)
            self._cancelled.add(batch_id)
            self._cv.notify_all()
        return True

    def queue_length(self) -> int:
        with self._cv:
            return len(self._queue) + (self._current is not None)

    def wait(self, batch_id: str, timeout: float | None = None) -> str | None:
        """Block until the batch is no longer queued or running (or timeout); its state."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            owner = self.store.batch_owner(batch_id)
            st = self.store.batch(owner, batch_id) if owner is not None else None
            state = st["state"] if st else None
            if state not in UNFINISHED:
                return state
            left = None if deadline is None else deadline - time.monotonic()
            if left is not None and left <= 0:
                return state
            with self._cv:
                self._cv.wait(timeout=0.5 if left is None else min(0.5, left))

    def shutdown(self, wait: bool = True) -> None:
        """Stop after the configurations in flight; unfinished batches stay queued in the store for resume()."""
        with self._cv:
            self._stop = True
            self._cv.notify_all()
        if self._thread is not None and wait:
            self._thread.join(timeout=120)
        if self._impl is not None:
            self._impl.close(wait_workers=wait)
            self._impl = None

    # internals
    def _backend(self):
        if self._impl is None:
            self._impl = _LocalBackend(self.workers) if self.backend == "local" else _RayBackend(self.workers, self.ray_address)
        return self._impl

    def _loop(self) -> None:
        while True:
            with self._cv:
                while not self._queue and not self._stop:
                    self._cv.wait()
                if self._stop:
                    return
                tenant, batch_id = self._queue.popleft()
                self._current = batch_id
            try:
                self._run(tenant, batch_id)
            except Exception as e:
                log.exception("batch %s failed in the runner", batch_id)
                tries = self._runner_failures.get(batch_id, 0) + 1
                self._runner_failures[batch_id] = tries
                if not self._stop and tries < RUNNER_RETRIES:
                    # a passing failure (a busy database, a backend that did not start): the pending
                    # configurations stay pending and the batch goes back in the queue, after the others
                    time.sleep(RUNNER_RETRY_S)
                    with self._cv:
                        self._queue.append((tenant, batch_id))
                elif not self._stop:
                    for i in self.store.pending_indices(batch_id):
                        self.store.put_error(batch_id, i, "runner_error", f"{type(e).__name__}: {e}")
                    self.store.finish_batch(batch_id)
            finally:
                with self._cv:
                    self._current = None
                    self._cv.notify_all()

    def _should_stop(self, batch_id: str) -> bool:
        if self._stop or batch_id in self._cancelled:
            return True
        state = self.store.batch_state(batch_id)
        return state is None or state == "cancelled"

    def _run(self, tenant: str, batch_id: str) -> None:
        st = self.store.batch(tenant, batch_id, max_errors=0)
        if st is None or st["state"] not in UNFINISHED:
            return
        if not self.store.set_state(batch_id, "running", only_from=UNFINISHED):
            return
        pending = self.store.pending_indices(batch_id)
        rec = self.store.scene_record(tenant, st["scene_id"])
        path = self.store.scene_path(tenant, st["scene_id"])
        if rec is None or path is None or not path.is_file():
            for i in pending:
                self.store.put_error(batch_id, i, "scene_not_found", f"scene {st['scene_id']!r} is gone")
            self.store.finish_batch(batch_id)
            return
        configs = self.store.configurations(batch_id)
        job = SceneJob(str(path), rec["filename"], self.store.scene_sandboxed(tenant, st["scene_id"]))
        items = [(i, configs[i]) for i in pending]
        self._turn_done = 0

        def pause():  # take turns: after a slice, a batch that arrived meanwhile goes first
            return self._turn_done >= SLICE and self._others_waiting()

        self._run_slice(batch_id, job, items, st["settings"], pause, total=st["total"])
        if self._stop:
            return
        if not self._should_stop(batch_id) and self.store.pending_indices(batch_id):
            with self._cv:  # paused: the rest goes behind the batches that arrived meanwhile
                self._queue.append((tenant, batch_id))
            return
        self.store.finish_batch(batch_id)

    def _others_waiting(self) -> bool:
        with self._cv:
            return bool(self._queue)

    def _run_slice(self, batch_id: str, job, items: list, settings: dict, pause=None, total: int | None = None) -> None:
        """Run a batch's pending configurations (until `pause()`), storing each task's outcomes in one
        commit as they arrive: independent configurations in tasks of chunk_size, a coherent path's in
        chains (service.paths.coherent_outcomes)."""
        self.stats["submitted"] += len(items)
        settings = {**(settings or {}), "max_triangles": self.max_triangles,  # this server's, not the stored ones
                    "load_limits": self.load_limits or (settings or {}).get("load_limits")}
        stop = lambda: self._should_stop(batch_id)  # noqa: E731
        backend = self._backend()
        if settings.get("coherent"):  # a coherent path: frames in order, each given the previous one's solution
            from .paths import coherent_outcomes

            groups = coherent_outcomes(self.store, backend, batch_id, job, items, settings, stop, pause=pause,
                                       total=total)
        elif settings.get("whole_path"):  # method path: runs of consecutive frames solved together, cut at fixed
            # multiples of WHOLE_PATH_FRAMES so that a resumed path solves the same runs
            runs = collections.defaultdict(list)
            for i, c in sorted(items, key=lambda ic: ic[0]):
                runs[i // WHOLE_PATH_FRAMES].append((i, c))
            groups = backend.run_groups(job, TaskQueue([runs[k] for k in sorted(runs)], pause), settings, stop)
        else:
            tasks = TaskQueue(chunked(items, chunk_size(len(items), self.workers)), pause)
            groups = backend.run_groups(job, tasks, settings, stop)
        for outs in groups:
            self.store.put_outcomes(batch_id, outs)
            self._turn_done += len(outs)
            for _, out in outs:
                self.stats["results" if "result" in out else "errors"] += 1
            with self._cv:
                self._cv.notify_all()


# -- the CLI's batch -------------------------------------------------------------------------------

def run_batch(scene_path, configurations: list[dict], backend: str = "local", workers: int = 2,
              out_path=None, method: str = DEFAULT_METHOD, progress: bool = True, solver: str | None = None,
              time_budget_ms: float | None = None, ray_address: str | None = None) -> dict:
    """Run configurations (each {"rig": validated rig}) on a scene file; write JSON lines (one per
    configuration, in index order, each with "index"; failures as {"index", "error"}) to out_path as
    they complete. Uses a temporary Store, so execution is the server's. Returns a summary."""
    from ..renderers.scene_data import SceneError

    if not os.path.isfile(scene_path):
        raise SceneError("not_found", f"cannot open scene {os.fspath(scene_path)!r}: no such file")
    settings = {"method": method, "solver": solver, "time_budget_ms": time_budget_ms}
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="shadowopt-batch-") as tmp:
        store = Store(tmp)
        runner = BatchRunner(store, backend=backend, workers=workers, ray_address=ray_address)
        try:
            scene_id = store.link_scene("local", scene_path)
            batch_id = store.create_batch("local", scene_id, configurations, settings)
            runner.submit("local", batch_id)
            _stream(runner, store, batch_id, len(configurations), out_path, progress)
            st = store.batch("local", batch_id)
        finally:
            runner.shutdown()
            store.close()
    return {"state": st["state"], "total": st["total"], "done": st["done"], "failed": st["failed"],
            "errors": st["errors"], "seconds": round(time.perf_counter() - t0, 3), "out": str(out_path)}


class _NoBar:
    n = 0

    def update(self, k: int = 1) -> None:
        self.n += k

    def set_postfix(self, **kw) -> None:
        pass

    def close(self) -> None:
        pass


def _stream(runner: BatchRunner, store: Store, batch_id: str, total: int, out_path, show: bool) -> None:
    from ..api.progress import progress_bar

    bar = progress_bar(total, "batch", unit="config", enabled=show) or _NoBar()
    out = open(out_path, "w") if out_path else None
    next_index = 0
    try:
        while True:
            state = runner.wait(batch_id, timeout=0.25)
            st = store.batch("local", batch_id, max_errors=0)
            bar.update(st["done"] + st["failed"] - bar.n)
            if st["failed"]:
                bar.set_postfix(failed=st["failed"])
            lines = store.results("local", batch_id, offset=next_index)
            if out is not None and lines:
                out.writelines(json.dumps(line) + "\n" for line in lines)
                out.flush()
            if lines:
                next_index = lines[-1]["index"] + 1
            if state not in UNFINISHED:
                break
    finally:
        bar.close()
        if out is not None:
            out.close()
