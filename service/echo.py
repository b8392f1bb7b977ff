"""What a solution was solved for: the resolved camera and lights, the frame, units and output convention,
so that a solution (or a batch result line) can be checked and replayed without the rig that made it.

Positions and directions are in the world frame (right-handed, +Y up, metres), whatever frame the rig
was given in; `rig_frame` says which one that was. A replayable rig is `{"camera": echo["camera"],
"lights": echo["lights"]}` with the rig's shadow settings (the usd_path keys are informative: the
explicit position/forward/up/fov reproduce the camera without the scene's camera).
"""
from __future__ import annotations

from .rigs import ResolvedRig


def _vec(v) -> list[float]:
    return [float(x) for x in v]


def camera_echo(camera) -> dict:
    out = {"position": _vec(camera.position), "forward": _vec(camera.forward), "up": _vec(camera.up),
           "fov_y_deg": float(camera.fov_y_deg), "near": float(camera.near), "far": float(camera.far),
           "resolution": [int(camera.resolution[0]), int(camera.resolution[1])]}
    if camera.usd_path:
        out["usd_path"] = camera.usd_path
    return out


def light_echo(light) -> dict:
    out: dict = {"type": light.kind}
    if getattr(light, "position", None) is not None:
        out["position"] = _vec(light.position)
    if getattr(light, "direction", None) is not None:
        out["direction"] = _vec(light.direction)
    if getattr(light, "cone_deg", None) is not None:
        out["cone_deg"] = float(light.cone_deg)
    if light.usd_path:
        out["usd_path"] = light.usd_path
    return out


def resolved_echo(resolved: ResolvedRig, rig_frame: str | None = None) -> dict:
    """{"camera", "lights", "frame", "units", "up_axis", "output"} for a resolved rig (service.rigs), and
    "rig_frame" (the frame the rig was given in) when known."""
    out = resolved.output or {}
    echo = {"camera": camera_echo(resolved.camera), "lights": [light_echo(l) for l in resolved.lights],
            "frame": "world", "units": "metres", "up_axis": "+Y",
            "output": {"convention": out.get("convention", "opengl"), "layout": out.get("layout", "column_major"),
                       "frame": out.get("frame", "world"), "reversed_z": bool(out.get("reversed_z", False)),
                       "engine": out.get("engine")}}
    if rig_frame is not None:
        echo["rig_frame"] = rig_frame
    return echo
