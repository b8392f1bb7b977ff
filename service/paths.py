"""Path jobs: a camera path (and lights animated along it) as the ordered frames of a batch.

A path request is a base `rig` with either
- `camera_path`: the batches' form (service.batches: `poses`, or `keyframes` + `samples`), optionally with
  `light_directions` / `sun_arc` giving one light direction per frame (or one for all), or
- `usd_camera` (a UsdGeom.Camera prim path; default rig.camera.usd_path) and `time` {start, end, step}: the
  camera's world transform, field of view (vertical aperture and focal length) and clipping range read at
  each time code t = start + k * step (USD's own interpolation of the time samples), and every rig light
  given by usd_path whose transform is animated read at the same time codes (a DistantLight's direction:
  a sun moving through the day).
Frames are {"rig": RIG, "frame": k, "time": t or None} in order; a path job is a batch over them (the Store,
resume, crash safety and streamed results of service.batches), each result line carrying "frame" and "time".
On a stage whose geometry has transform or point time samples (a moving vehicle), each frame also carries
"scene_time": t and its worker solves on the stage loaded at that time code (service.scenes.SCENES.get
time_code; one load per frame: an upload's in an isolated child under the server's load limits), so a moving
caster casts a moving shadow; the loader's warnings for that time code go on the frame's line ("warnings").
With `coherent`, frames are solved one after another and each solve receives the previous frame's solution
as `previous=` (service.solve.solve): coherent_outcomes. Method path without `coherent` solves the frames
together (is_whole_path: tasks of batches.WHOLE_PATH_FRAMES consecutive frames, service.solve.solve_path).
"""
from __future__ import annotations

import json
import math
import os
import tempfile
import time

from .batches import MAX_CONFIGURATIONS, BatchError, BatchRunner, _camera_path, _light_set, _light_slot, _NoBar
from .store import UNFINISHED, Store

MAX_FRAMES = MAX_CONFIGURATIONS  # like a batch's configurations
MAX_TIME_FRAMES = 10_000  # time codes read from a stage per request (one transform cache each), as keyframe samples
COHERENT_METHODS = ()  # methods that always get the previous frame (none: method path sees the whole path)
WHOLE_PATH_METHODS = ("path",)  # methods whose frames are solved together (service.solve.solve_path)
PATH_FIELDS = ("rig", "camera_path", "usd_camera", "time", "light_directions", "sun_arc", "light_index")
_RESULT_EXTRAS = ("index", "frame", "time")


class PathError(BatchError):
    """A path request is malformed (`field` e.g. `time.step`)."""

    code = "invalid_path"


def expand_path(request: dict, *, scene_path=None, reader=None) -> list[dict]:
    """The frames of a path request in order, each {"rig": RIG, "frame": k, "time": t or None}
    (see the module doc). The `usd_camera` form reads the stage: `reader(camera_path, times, light_paths)`
    returns renderers.usd_loader.read_animation's dict (the server runs it isolated for uploads), or
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
        cams = _camera_path(request["camera_path"], base.get("camera"))
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
    dirs = _light_set(request, base)
    if dirs is None:
        return frames
    key = "sun_arc" if "sun_arc" in request else "light_directions"
    if len(dirs) not in (1, len(frames)):
        raise PathError(key, f"{len(dirs)} light directions for {len(frames)} frames: give one per frame, or one")
    slot = _light_slot(request, base)
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
        from ..renderers.usd_animation import read_animation

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
    import numpy as np

    return (np.allclose(a.position, b.position) and np.allclose(a.forward, b.forward) and np.allclose(a.up, b.up)
            and math.isclose(a.fov_y_deg, b.fov_y_deg) and math.isclose(a.near, b.near) and math.isclose(a.far, b.far))


def _same_light(a, b) -> bool:
    import numpy as np

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


# -- coherence: the previous frame's solution -----------------------------------------------------

def previous_of(line: dict | None) -> dict | None:
    """A stored result line as the next frame's `previous` (None for a failed or missing frame)."""
    if not line or "error" in line:
        return None
    return {k: v for k, v in line.items() if k not in _RESULT_EXTRAS}


MIN_CHUNK_FRAMES = 16  # a coherent chunk is at least this long (shorter paths stay one chunk)


def chunk_starts(total: int, chunks: int | None) -> list[int]:
    """The first frames of a coherent path's chunks: `chunks` (settings["coherent_chunks"], the workers that
    share the path) contiguous runs of equal length, each at least MIN_CHUNK_FRAMES. Each chunk is coherent
    within itself and its first frame starts fresh (no previous): one fresh start per chunk is the price of
    solving them in parallel. Fixed by the batch's total and settings, so a resumed path keeps them."""
    k = max(1, min(int(chunks or 1), total // MIN_CHUNK_FRAMES))
    return sorted({(j * total) // k for j in range(k)})


class _Chains:
    """A coherent path's worker tasks (service.batches.TaskQueue's protocol): per chunk, runs of up to
    batches.CHUNK consecutive frames, one task in flight per chunk; a task's first frame brings the previous
    frame's solution (from the task before it, or from the store after a resume), the worker chains the
    rest (batches.solve_group)."""

    def __init__(self, store: Store, batch_id: str, items: list, starts: list[int], pause, chunk: int):
        import bisect
        import collections

        self.store, self.batch_id, self.starts, self.chunk = store, batch_id, set(starts), chunk
        self.pause = pause or (lambda: False)
        self.chains = collections.defaultdict(collections.deque)
        for i, c in sorted(items, key=lambda ic: ic[0]):
            self.chains[bisect.bisect_right(starts, i) - 1].append((i, c))
        self.of = {}  # first index of a task in flight -> chain
        self.busy, self.last = set(), {}  # chain -> (index, previous) of its last solved frame

    def _previous(self, ch, i: int):
        if i in self.starts or i == 0:
            return None
        if ch in self.last and self.last[ch][0] == i - 1:
            return self.last[ch][1]
        owner = self.store.batch_owner(self.batch_id)
        rows = self.store.results(owner, self.batch_id, offset=i - 1, limit=1) if owner is not None else []
        return previous_of(rows[0]) if rows and rows[0]["index"] == i - 1 else None

    def take(self):
        if self.pause():
            return None
        for ch in sorted(self.chains):
            q = self.chains[ch]
            if ch in self.busy or not q:
                continue
            i, c = q.popleft()
            prev = self._previous(ch, i)
            group = [(i, {**c, "previous": prev} if prev is not None else c)]
            while q and len(group) < self.chunk and q[0][0] == group[-1][0] + 1 and q[0][0] not in self.starts:
                group.append(q.popleft())
            self.busy.add(ch)
            self.of[i] = ch
            return group
        return None

    def finished(self) -> bool:
        return self.pause() or not any(self.chains.values())

    def done(self, outs) -> None:
        ch = self.of.pop(outs[0][0], None)
        if ch is None:
            return
        self.busy.discard(ch)
        i, out = outs[-1]
        self.last[ch] = (i, previous_of(out.get("result")))


def coherent_outcomes(store: Store, backend, batch_id: str, job, items: list, settings: dict, should_stop,
                      pause=None, total: int | None = None):
    """The batch runner's outcomes for a coherent path, one worker task's [(index, outcome), ...] at a time:
    within each chunk (chunk_starts: settings["coherent_chunks"], default one) frames one after another in
    index order, each configuration given "previous" = the previous frame's solution (from the store after
    a resume), which service.batches._solve_with passes to solve(..., previous=...); the chunks in parallel."""
    from .batches import CHUNK

    if total is None:
        owner = store.batch_owner(batch_id)
        st = store.batch(owner, batch_id, max_errors=0) if owner is not None else None
        total = st["total"] if st else max((i for i, _ in items), default=-1) + 1
    starts = chunk_starts(total, settings.get("coherent_chunks"))
    # tasks of up to CHUNK frames, at least 8 per chunk (a short path streams, and is stored, frame by frame)
    chunk = max(1, min(CHUNK, total // len(starts) // 8))
    chains = _Chains(store, batch_id, items, starts, pause, chunk)
    yield from backend.run_groups(job, chains, settings, should_stop)


def is_coherent(method: str | None, coherent: bool | None) -> bool:
    return bool(coherent) or method in COHERENT_METHODS


def is_whole_path(method: str | None, coherent: bool | None) -> bool:
    """Method path over a path job: the frames solved together in tasks of batches.WHOLE_PATH_FRAMES
    (service.solve.solve_path: segments that hold their texel grid), unless `coherent` asks for the editor's
    form (each frame given the previous one's solution)."""
    return method in WHOLE_PATH_METHODS and not coherent


# -- the CLI's path -------------------------------------------------------------------------------

def run_path(scene_path, frames: list[dict], *, method: str = "optimized", coherent: bool = False,
             workers: int = 2, on_line=None, progress: bool = True, solver: str | None = None,
             time_budget_ms: float | None = None, backend: str = "local", ray_address: str | None = None) -> dict:
    """Solve the frames (validated {"rig", "frame", "time"}) as a batch in a temporary Store; call
    `on_line(line)` for each result line in frame order as soon as it and every frame before it are done.
    A coherent path runs as `workers` coherent chunks in parallel (chunk_starts: one fresh start per chunk;
    a path shorter than MIN_CHUNK_FRAMES per worker stays one chunk). Returns a summary {state, total,
    done, failed, errors, seconds}."""
    from .progress import progress_bar
    from ..renderers.scene_data import SceneError

    if not os.path.isfile(scene_path):
        raise SceneError("not_found", f"cannot open scene {os.fspath(scene_path)!r}: no such file")
    settings = {"method": method, "solver": solver, "time_budget_ms": time_budget_ms,
                "coherent": is_coherent(method, coherent), "whole_path": is_whole_path(method, coherent)}
    if settings["coherent"] and workers > 1:
        settings["coherent_chunks"] = workers
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="shadowopt-path-") as tmp:
        store = Store(tmp)
        runner = BatchRunner(store, backend=backend, workers=workers, ray_address=ray_address)
        bar = progress_bar(len(frames), "path", unit="frame", enabled=progress) or _NoBar()
        try:
            scene_id = store.link_scene("local", scene_path)
            batch_id = store.create_batch("local", scene_id, frames, settings)
            runner.submit("local", batch_id)
            nxt = 0
            while True:
                state = runner.wait(batch_id, timeout=0.25)
                st = store.batch("local", batch_id, max_errors=0)
                bar.update(st["done"] + st["failed"] - bar.n)
                for line in store.results("local", batch_id, offset=nxt):
                    nxt = line["index"] + 1
                    if on_line is not None:
                        on_line(line)
                if state not in UNFINISHED:
                    break
            st = store.batch("local", batch_id)
        finally:
            bar.close()
            runner.shutdown()
            store.close()
    return {"state": st["state"], "total": st["total"], "done": st["done"], "failed": st["failed"],
            "errors": st["errors"], "seconds": round(time.perf_counter() - t0, 3)}


def line_json(line: dict) -> str:
    """A result line as the CLI prints it: frame and time first, then the solution (or the error)."""
    head = {"frame": line.get("frame", line["index"]), "time": line.get("time")}
    return json.dumps({**head, **{k: v for k, v in line.items() if k not in head}})
