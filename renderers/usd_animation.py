"""Cameras and lights at time codes (their time samples), and what of the geometry moves or changes its
triangle count, read without reading geometry (read_animation).
"""
from __future__ import annotations

import os

import numpy as np
from pxr import Usd, UsdGeom, UsdLux

from ..solvers.frames import stage_to_world as _stage_to_world
from .implicit_prims import implicit_triangle_count
from .redaction import PathRedactor
from .scene_data import SceneError
from .stage_units import stage_frame
from .usd_cameras_lights import read_camera, read_light
from .usd_diagnostics import dedupe
from .usd_loader import MAX_WARNINGS, load_stage
from .usd_meshes import face_triangles
from .usd_traversal import Budget
from .usd_values import as_array, attr_value


def read_animation(path, camera_path: str | None, time_codes: list[float], *, light_paths: list[str] | None = None,
                   asset_root: str | None = None, sandbox: bool = False, max_prims: int | None = None) -> dict:
    """A camera and lights read at each of `time_codes` (their time samples, USD's interpolation), the stage
    opened as load_scene opens it (same checks in the restricted modes), without reading geometry.

    Returns {"camera": [UsdCamera per time] or None when `camera_path` is None, "camera_type": the prim's
    type name ("" when there is no such prim), "lights": {usd_path: [UsdLight per time]} for `light_paths`
    (default: every light of the stage), "moving": prim paths (up to 20) of geometry whose transform or
    points have time samples, "time_range": [start, end] time codes of the stage or None, "warnings", "camera_problems":
    the camera values replaced by fallbacks (not finite or not positive) or a non-finite transform, per time code,
    "triangles_added": per time code the triangles the geometry's sampled topology adds to the default time's
    count (_triangle_change; None when no prim's count changes), "growing": up to 5 of those prims}.
    A time code is read as Usd.TimeCode(t): world transforms from UsdGeom.XformCache(t)."""
    path = os.fspath(path)
    scrub = PathRedactor([os.path.dirname(os.path.abspath(path)), asset_root]).text
    times = [float(t) for t in time_codes]

    def read(stage, warnings):
        up, mpu = stage_frame(stage, warnings)
        s2w = _stage_to_world(up, mpu)
        out = {"camera": None, "camera_type": "", "lights": {}, "moving": [], "time_range": None,
               "camera_problems": []}
        if stage.HasAuthoredTimeCodeRange():
            out["time_range"] = [float(stage.GetStartTimeCode()), float(stage.GetEndTimeCode())]
        caches = [UsdGeom.XformCache(Usd.TimeCode(t)) for t in times]
        if camera_path is not None:
            prim = stage.GetPrimAtPath(camera_path) if camera_path.startswith("/") else None
            out["camera_type"] = str(prim.GetTypeName()) if prim else ""
            if prim and prim.IsA(UsdGeom.Camera):
                out["camera"] = [read_camera(prim, Usd.TimeCode(t), xc, s2w, mpu, warnings, out["camera_problems"])
                                 for t, xc in zip(times, caches)]
        budget = Budget(None, max_prims)
        extra, growing = None, []
        for prim in Usd.PrimRange.Stage(stage, Usd.TraverseInstanceProxies(Usd.PrimDefaultPredicate)):
            budget.prim(prim)
            p = str(prim.GetPath())
            if prim.HasAPI(UsdLux.LightAPI) or "Light" in prim.GetTypeName():
                if light_paths is None or p in light_paths:
                    ls = [read_light(prim, Usd.TimeCode(t), xc, s2w) for t, xc in zip(times, caches)]
                    if ls and ls[0] is not None:
                        out["lights"][p] = ls
            elif prim.IsA(UsdGeom.Gprim) or prim.IsA(UsdGeom.PointInstancer):
                if _changes_over_time(prim):
                    if len(out["moving"]) < 20:
                        out["moving"].append(p)
                    delta = _triangle_change(prim, times)
                    if delta is not None:
                        extra = [a + b for a, b in zip(extra, delta)] if extra else delta
                        growing.append(p)
        out["triangles_added"] = extra  # per time code, or None when no prim's triangle count changes
        out["growing"] = growing[:5]
        out["warnings"] = [scrub(w) for w in dedupe(warnings)][:MAX_WARNINGS]
        out["camera_problems"] = [scrub(w) for w in out["camera_problems"][:MAX_WARNINGS]]
        return out

    try:
        return load_stage(path, None, asset_root, sandbox, None, max_prims, read=read)
    except SceneError as e:
        raise SceneError(e.code, scrub(e.message)) from e.__cause__


def _changes_over_time(prim) -> bool:
    """Whether what the loader reads of a Gprim or PointInstancer can change with the time code: its transform
    or an ancestor's, its own or an ancestor's visibility, or any of its own attributes (points, topology, an
    instancer's positions, orientations, scales, protoIndices, invisibleIds) having time samples."""
    def varies(attr) -> bool:  # one sample and no default reads the same at every time code (attr_value)
        n = attr.GetNumTimeSamples()
        return n > 1 or (n == 1 and attr.Get(Usd.TimeCode.Default()) is not None)

    chain = [prim, *_ancestors(prim)]
    if any(UsdGeom.Xformable(a).TransformMightBeTimeVarying() for a in chain if a.IsA(UsdGeom.Xformable)):
        return True
    if any(varies(UsdGeom.Imageable(a).GetVisibilityAttr()) for a in chain if a.IsA(UsdGeom.Imageable)):
        return True
    return any(varies(attr) for attr in prim.GetAttributes())


def _held(attr, times: list[float]) -> list:
    """attr's value at each time code for an attribute USD holds rather than interpolates (integer arrays:
    topology, protoIndices), read once per time sample it lands on (its lower bracketing sample)."""
    values, out = {}, []
    for t in times:
        bracket = attr.GetBracketingTimeSamples(t)  # (lower, upper), empty without samples
        key = float(bracket[0]) if bracket else None
        if key not in values:
            values[key] = attr.Get(Usd.TimeCode(key)) if key is not None else attr.Get(Usd.TimeCode(t))
        out.append(values[key])
    return out


def _triangle_change(prim, times: list[float]) -> list[int] | None:
    """What a Mesh with sampled faceVertexCounts, or a PointInstancer with sampled protoIndices, adds at each
    time code to the triangles the loader counts at the default time (a stage light there and heavy at t = 5);
    None when its triangle count cannot change. Instances counted whatever their mask (an upper bound);
    prototypes' triangles as at the default time."""
    default = Usd.TimeCode.Default()
    if prim.IsA(UsdGeom.Mesh):
        attr = UsdGeom.Mesh(prim).GetFaceVertexCountsAttr()
        if attr.GetNumTimeSamples() == 0:
            return None
        base = face_triangles(attr_value(attr, default))
        return [face_triangles(v) - base for v in _held(attr, times)]
    if not prim.IsA(UsdGeom.PointInstancer):
        return None
    inst = UsdGeom.PointInstancer(prim)
    attr = inst.GetProtoIndicesAttr()
    if attr.GetNumTimeSamples() == 0:
        return None
    stage = prim.GetStage()
    proto_tris = []
    for target in inst.GetPrototypesRel().GetTargets():
        root, n = stage.GetPrimAtPath(target), 0
        if root:
            for q in Usd.PrimRange(root, Usd.TraverseInstanceProxies(Usd.PrimDefaultPredicate)):
                if q.IsA(UsdGeom.Mesh):
                    n += face_triangles(attr_value(UsdGeom.Mesh(q).GetFaceVertexCountsAttr(), default))
                elif q.IsA(UsdGeom.Gprim):
                    n += implicit_triangle_count(q.GetTypeName())
        proto_tris.append(n)
    tris = np.asarray(proto_tris + [0], np.int64)  # an index naming no prototype: no triangles

    def count(v) -> int:
        idx = as_array(v, None, np.int64)
        if idx is None or not len(idx):
            return 0
        idx = np.where((idx >= 0) & (idx < len(proto_tris)), idx, len(proto_tris))
        return int(tris[idx].sum())

    base = count(attr_value(attr, default))
    return [count(v) - base for v in _held(attr, times)]


def _ancestors(prim):
    p = prim.GetParent()
    while p and not p.IsPseudoRoot():
        yield p
        p = p.GetParent()
