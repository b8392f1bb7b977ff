"""UsdGeom cameras and UsdLux lights read from their prims, in the world frame."""
from __future__ import annotations

import math

import numpy as np
from pxr import UsdGeom, UsdLux

from ..solvers.frames import transform_directions, transform_points
from .scene_data import UsdCamera, UsdLight
from .usd_values import attr_value, np_matrix

CAMERA_FALLBACKS = {"focalLength": 50.0, "horizontalAperture": 20.955, "verticalAperture": 15.2908}  # USD's
CLIPPING_FALLBACK = (1.0, 1e6)  # UsdGeom.Camera's clippingRange fallback, stage units


def read_camera(prim, tc, xcache, s2w, mpu, warnings, problems: list | None = None) -> UsdCamera:
    """Position and axes from the camera's transform (it looks along local -Z, up is local +Y);
    clipping range from stage units to meters; fov from the vertical aperture and focal length.
    A focalLength or aperture that is not a finite positive number (NaN, inf, 0, negative), or a clipping
    range that is not 0 < near < far (finite), is replaced by USD's fallback with a warning naming the
    attribute, its value and the time code; with `problems` (read_animation) the same text is appended there
    too, so a path can refuse the frame instead of solving it with a made-up field of view."""
    cam = UsdGeom.Camera(prim)
    at = "" if tc.IsDefault() else f" at time code {tc.GetValue():g}"

    def bad(text: str, fallback: str) -> None:
        warnings.append(f"{text}; USD's fallback {fallback} used")
        if problems is not None:
            problems.append(text)

    vals = {}
    for name, attr in (("focalLength", cam.GetFocalLengthAttr()), ("horizontalAperture", cam.GetHorizontalApertureAttr()),
                       ("verticalAperture", cam.GetVerticalApertureAttr())):
        v = attr_value(attr, tc)
        try:
            v = CAMERA_FALLBACKS[name] if v is None else float(v)
        except (TypeError, ValueError):
            v = math.nan
        if not (math.isfinite(v) and v > 0):
            bad(f"{prim.GetPath()}: {name} {v:g}{at} is not a finite positive number (the field of view is "
                f"2 atan(verticalAperture / (2 focalLength)))", f"{CAMERA_FALLBACKS[name]:g}")
            v = CAMERA_FALLBACKS[name]
        vals[name] = v
    focal, hap, vap = vals["focalLength"], vals["horizontalAperture"], vals["verticalAperture"]
    clip = attr_value(cam.GetClippingRangeAttr(), tc)
    try:
        near, far = (float(clip[0]), float(clip[1])) if clip is not None else CLIPPING_FALLBACK
    except (TypeError, ValueError, IndexError):
        near, far = math.nan, math.nan
    if not (math.isfinite(near) and math.isfinite(far) and 0 < near < far):
        bad(f"{prim.GetPath()}: clippingRange ({near:g}, {far:g}){at} is not 0 < near < far (finite)",
            f"({CLIPPING_FALLBACK[0]:g}, {CLIPPING_FALLBACK[1]:g})")
        near, far = CLIPPING_FALLBACK
    m = s2w @ np_matrix(xcache.GetLocalToWorldTransform(prim))
    pos = transform_points(m, np.zeros(3))
    fwd = transform_directions(m, np.array([0.0, 0.0, -1.0]))
    up = transform_directions(m, np.array([0.0, 1.0, 0.0]))
    if problems is not None and not (np.all(np.isfinite(m)) and np.linalg.norm(fwd) > 1e-12 and np.linalg.norm(up) > 1e-12):
        problems.append(f"{prim.GetPath()}: its world transform{at} is not finite or collapses the view axes "
                        "(NaN, infinite or zero scale)")
    fov = math.degrees(2.0 * math.atan(vap / (2.0 * focal)))
    return UsdCamera(str(prim.GetPath()), pos, fwd, up, fov, near * mpu, far * mpu, focal, hap, vap)


def read_light(prim, tc, xcache, s2w) -> UsdLight | None:
    t = prim.GetTypeName()
    path = str(prim.GetPath())
    m = s2w @ np_matrix(xcache.GetLocalToWorldTransform(prim))
    pos = transform_points(m, np.zeros(3))
    axis = transform_directions(m, np.array([0.0, 0.0, -1.0]))
    cone = None
    if prim.HasAPI(UsdLux.ShapingAPI):
        a = UsdLux.ShapingAPI(prim).GetShapingConeAngleAttr().Get(tc)
        cone = float(a) if a is not None else 90.0
    if t == "DistantLight":
        return UsdLight(path, t, "directional", direction=axis)
    if t == "SphereLight":
        if cone is not None and cone < 180.0:
            return UsdLight(path, t, "spot", position=pos, direction=axis, cone_deg=cone,
                            note="sphere light with a shaping cone")
        return UsdLight(path, t, "point", position=pos)
    if t in ("DiskLight", "RectLight"):
        c = cone if cone is not None and cone < 90.0 else 90.0
        return UsdLight(path, t, "spot", position=pos, direction=axis, cone_deg=c,
                        note=f"{t} emits into the hemisphere along its -Z: a spot of half-angle {c:g} deg")
    if t == "DomeLight" or t == "DomeLight_1":
        return UsdLight(path, t, "ignored", note="dome lights light from everywhere: no shadow map, ignored")
    if prim.HasAPI(UsdLux.LightAPI) or t.endswith("Light"):
        return UsdLight(path, t, "ignored", note=f"{t} is not modelled: ignored")
    return None
