"""The rig schema (field names fixed by the product) and its resolution against a scene."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from pydantic import ValidationError

from shadowopt.api.schemas import Rig, format_validation_error
from shadowopt.renderers.scene_data import LoadedScene, SceneGeometry, UsdCamera, UsdLight
from shadowopt.service.rigs import RigError, resolve_rig
from shadowopt.solvers.frames import stage_to_world

ISSUE_RIG = {
    "camera": {"position": [0, 1.7, 0], "target": [30, 0, 8], "up": [0, 1, 0], "fov_y_deg": 60,
               "near": 0.1, "far": 150, "resolution": [1280, 720]},
    "lights": [{"type": "directional", "direction": [-0.3, -0.8, 0.5]}],
    "shadow": {"resolution": [2048, 2048], "cascades": 1},
}


def scene(up="Y", mpu=1.0):
    g = SceneGeometry(np.array([[-10, 0, -10], [10, 0, -10], [0, 0, 10.0]]), np.array([[0, 1, 2]], np.int32),
                      np.zeros(1, np.int32), ["/g"])
    cam = UsdCamera("/World/Camera", np.array([0, 2.0, 0]), np.array([0, 0, 1.0]), np.array([0, 1.0, 0]),
                    40.0, 0.5, 90.0, 35.0, 36.0, 24.0)
    lights = [UsdLight("/World/Sun", "DistantLight", "directional", direction=np.array([0, -1.0, 0])),
              UsdLight("/World/Sky", "DomeLight", "ignored", note="dome lights cast no shadow map")]
    return LoadedScene("mem", "0" * 64, g, [cam], lights, up, mpu, stage_to_world(up, mpu), None)


def validated(raw):
    return Rig.model_validate(raw).model_dump(by_alias=True)


def test_issue_rig_resolves_to_the_camera_and_light_it_names():
    r = resolve_rig(validated(ISSUE_RIG), scene())
    assert np.allclose(r.camera.position, [0, 1.7, 0])
    f = np.array([30, -1.7, 8.0])
    assert np.allclose(r.camera.forward, f / np.linalg.norm(f))
    assert r.camera.resolution == (1280, 720) and r.camera.far == 150
    d = np.array([-0.3, -0.8, 0.5])
    assert np.allclose(r.lights[0].direction, d / np.linalg.norm(d))
    assert r.shadow["resolution"] == (2048, 2048) and r.shadow["cascades"] == 1


def test_usd_paths_and_forward_instead_of_target():
    raw = {"camera": {"usd_path": "/World/Camera", "resolution": [640, 480]}, "lights": [{"usd_path": "/World/Sun"}]}
    r = resolve_rig(validated(raw), scene())
    assert r.camera.fov_y_deg == 40.0 and r.camera.near == 0.5 and r.camera.resolution == (640, 480)
    assert np.allclose(r.lights[0].direction, [0, -1, 0])
    raw = {"camera": {"position": [1, 2, 3], "forward": [0, 0, -2]}, "lights": [{"type": "point", "position": [0, 5, 0]}]}
    r = resolve_rig(validated(raw), scene())
    assert np.allclose(r.camera.forward, [0, 0, -1]) and r.lights[0].kind == "point"


def test_stage_frame_positions_are_converted():
    # A Z-up centimetre stage: a camera at stage (0, -500, 170) is at world (0, 1.7, 5).
    raw = {"frame": "stage", "camera": {"position": [0, -500, 170], "forward": [0, 1, 0], "up": [0, 0, 1],
                                        "near": 10, "far": 10000},
           "lights": [{"type": "directional", "direction": [0, 0, -1]}]}
    r = resolve_rig(validated(raw), scene("Z", 0.01))
    assert np.allclose(r.camera.position, [0, 1.7, 5.0])
    assert np.allclose(r.camera.forward, [0, 0, -1]) and np.allclose(r.camera.up, [0, 1, 0])
    assert r.camera.near == pytest.approx(0.1) and r.camera.far == pytest.approx(100.0)
    assert np.allclose(r.lights[0].direction, [0, -1, 0])


@pytest.mark.parametrize("raw, field, words", [
    ({"camera": {"position": [0, 0, 0]}, "lights": [{"type": "point", "position": [0, 1, 0]}]}, "camera", "target"),
    ({"camera": {"position": [0, 0, 0], "target": [1, 0, 0]}, "lights": []}, "lights", "at least 1"),
    ({"camera": {"position": [0, 0, 0], "target": [1, 0, 0]}, "lights": [{"type": "spot", "position": [0, 1, 0]}]},
     "lights.0", "direction, cone_deg"),
    ({"camera": {"position": [0, 0, "nan"], "target": [1, 0, 0]}, "lights": [{"usd_path": "/S"}]}, "camera.position.2", "finite"),
    ({"camera": {"position": [0, 0, 0], "target": [1, 0, 0], "fov_y_deg": 200}, "lights": [{"usd_path": "/S"}]},
     "camera.fov_y_deg", "less than or equal to 179"),
    ({"camera": {"position": [0, 0, 0], "target": [1, 0, 0]}, "lights": [{"usd_path": "/S"}], "shadow": {"cascade": 2}},
     "shadow.cascade", "Extra inputs"),
    ({"camera": {"position": [0, 0, 0], "target": [1, 0, 0]}, "lights": [{"usd_path": "/S"}],
      "shadow": {"resolution": [1024, 1024], "texel_budget": 100}}, "shadow", "not both"),
    ({"camera": {"position": [0, 0, 0], "target": [1, 0, 0], "near": 5, "far": 1}, "lights": [{"usd_path": "/S"}]},
     "camera", "near (5.0) must be less than far"),
])
def test_invalid_rigs_name_the_field(raw, field, words):
    with pytest.raises(ValidationError) as e:
        Rig.model_validate(raw)
    text = format_validation_error(e.value)
    assert text.startswith(field + ":") or f"; {field}:" in text, text
    assert words in text


def test_rig_that_does_not_fit_the_scene_names_the_field():
    with pytest.raises(RigError) as e:
        resolve_rig(validated({"camera": {"usd_path": "/World/Nope"}, "lights": [{"usd_path": "/World/Sun"}]}), scene())
    assert e.value.field == "camera.usd_path" and "/World/Camera" in e.value.message
    with pytest.raises(RigError) as e:
        resolve_rig(validated({"camera": {"usd_path": "/World/Camera"}, "lights": [{"usd_path": "/World/Sky"}]}), scene())
    assert e.value.field == "lights.0.usd_path" and "DomeLight" in e.value.message
    with pytest.raises(RigError) as e:
        resolve_rig(validated({"camera": {"position": [0, 1, 0], "target": [0, 1, 0]},
                               "lights": [{"usd_path": "/World/Sun"}]}), scene())
    assert e.value.field == "camera" and "non-zero" in e.value.message


def test_bundled_demo_rig_is_valid():
    raw = json.loads((Path(__file__).resolve().parents[1] / "configs" / "demo_rig.json").read_text())
    assert validated(raw)["camera"]["usd_path"] == "/World/Camera"


def test_a_camera_refuses_a_resolution_without_pixels_on_either_axis():
    """solvers.cameras.Camera.look (every rig's camera): a width or height of zero or below is refused with the
    resolution it was given; 1 x 1 is a camera."""
    from shadowopt.solvers.cameras import Camera

    for res in ((0, 720), (1280, 0), (-4, 720), (1280, -4)):
        with pytest.raises(ValueError, match=r"resolution must be positive, got \(" + str(res[0])):
            Camera.look([0, 2, 0], [0, 0, 1], resolution=res)
    assert Camera.look([0, 2, 0], [0, 0, 1], resolution=(1, 1)).resolution == (1, 1)
