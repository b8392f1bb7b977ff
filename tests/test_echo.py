"""service/echo.py: what a solution says it was solved for, in the world frame (+Y up, metres), checked
against the frame's definition (solvers/frames.py: a Z-up stage maps (x, y, z) -> (x, z, -y), scaled by
metersPerUnit) on a centimetre, Z-up stage."""
from __future__ import annotations

import numpy as np
import pytest

from shadowopt.api.schemas import validate_rig
from shadowopt.service.echo import resolved_echo
from shadowopt.service.rigs import resolve_rig


def _cm_z_up_stage(path):
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 0.01)
    ground = UsdGeom.Mesh.Define(stage, "/World/Ground")
    ground.CreatePointsAttr([(-2000, -2000, 0), (2000, -2000, 0), (2000, 2000, 0), (-2000, 2000, 0)])
    ground.CreateFaceVertexCountsAttr([4])
    ground.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    stage.GetRootLayer().Save()
    return path


def test_a_stage_frame_rig_is_echoed_in_world_metres(tmp_path):
    from shadowopt.renderers.usd_loader import load_scene

    scene = load_scene(_cm_z_up_stage(tmp_path / "cm.usda"))
    rig = validate_rig({"frame": "stage",
                        "camera": {"position": [100, -1000, 300], "target": [0, 0, 0], "up": [0, 0, 1], "near": 10,
                                   "far": 5000, "fov_y_deg": 40, "resolution": [320, 180]},
                        "lights": [{"type": "spot", "position": [0, 0, 500], "direction": [0, 0, -1], "cone_deg": 30},
                                   {"type": "directional", "direction": [0, 1, -1]}]})
    echo = resolved_echo(resolve_rig(rig, scene), rig["frame"])
    cam = echo["camera"]
    assert cam["position"] == pytest.approx([1.0, 3.0, 10.0])  # (x, z, -y) / 100
    want = -np.array([1.0, 3.0, 10.0]) / np.linalg.norm([1.0, 3.0, 10.0])
    assert cam["forward"] == pytest.approx(want.tolist())
    assert (cam["near"], cam["far"], cam["fov_y_deg"]) == pytest.approx((0.1, 50.0, 40.0)) and cam["resolution"] == [320, 180]
    assert np.dot(cam["up"], [0, 1, 0]) > 0.9 and abs(np.dot(cam["up"], cam["forward"])) < 1e-9
    spot, sun = echo["lights"]
    assert spot == {"type": "spot", "position": pytest.approx([0.0, 5.0, 0.0]), "direction": pytest.approx([0.0, -1.0, 0.0]),
                    "cone_deg": 30.0}
    assert sun["type"] == "directional" and sun["direction"] == pytest.approx([0.0, -np.sqrt(0.5), -np.sqrt(0.5)])
    assert (echo["frame"], echo["units"], echo["up_axis"], echo["rig_frame"]) == ("world", "metres", "+Y", "stage")
    assert echo["output"] == {"convention": "opengl", "layout": "column_major", "frame": "world", "reversed_z": False,
                              "engine": None}
