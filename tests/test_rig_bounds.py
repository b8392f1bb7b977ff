"""The bounds of a rig's numbers (service/rig_bounds.py, api/schemas.py): every shipped rig (configs/, the
corpus, held-out and contact scenes, the camera paths) passes them, the schema and the resolved checks state
the same numbers, and a number past a bound is refused naming its field."""
from __future__ import annotations

import json
import math

import pytest
from pydantic import ValidationError

from shadowopt.api import schemas
from shadowopt.api.schemas import CameraSpec, format_validation_error, validate_rig
from shadowopt.renderers.contact_scenes import CAMERAS as CONTACT_CAMERAS
from shadowopt.service import rig_bounds
from shadowopt.service.rig_bounds import BoundError, check_camera, check_cone, check_near_scene, distance_to_box
from serverkit import REPO

SUN = [{"type": "directional", "direction": [-0.4, -0.8, 0.3]}]
RIG_KEYS = ("camera", "lights", "shadow", "output", "frame", "coarse_long_side")
POSE_KEYS = set(CameraSpec.model_fields) - {"resolution"}


def shipped_rigs() -> list[tuple[str, dict]]:
    """(where, rig) for every rig in configs/*.json and the contact scenes' cameras; (where, camera) for every
    pose or keyframe of a camera path, as a camera of its own."""
    found = []

    def walk(node, where):
        if isinstance(node, dict):
            if isinstance(node.get("camera"), dict):
                rig = {k: node[k] for k in RIG_KEYS if k in node and (k != "lights" or isinstance(node[k], list))}
                found.append((where, {"lights": SUN, **rig}))  # (a benchmark's "lights" may be a count)
            elif "position" in node and ("target" in node or "forward" in node):  # a pose or keyframe
                cam = {k: v for k, v in node.items() if k in POSE_KEYS}
                found.append((where, {"camera": cam, "lights": SUN}))
            for k, v in node.items():
                walk(v, f"{where}.{k}")
        elif isinstance(node, list):
            for i, v in enumerate(node):
                walk(v, f"{where}.{i}")

    for path in sorted((REPO / "configs").glob("*.json")):
        walk(json.loads(path.read_text()), path.name)
    for name, cam in CONTACT_CAMERAS.items():
        found.append((f"contact_scenes.{name}", {"camera": cam, "lights": SUN}))
    return found


def test_every_shipped_rig_passes_the_bounds():
    rigs = shipped_rigs()
    assert len(rigs) >= 30 and any(w.startswith("heldout") for w, _ in rigs) and any(
        w.startswith("paths") for w, _ in rigs)
    for where, rig in rigs:
        try:
            cam = validate_rig(rig)["camera"]
        except ValidationError as e:
            pytest.fail(f"{where}: {format_validation_error(e)}")
        near = cam["near"] or 0.1
        far = cam["far"] or near * 10
        check_camera(cam["fov_y_deg"] or 60.0, near, far, {"fov_y_deg": where, "near": where, "far": where})


def test_the_schema_and_the_resolved_checks_state_the_same_bounds():
    for name in ("FOV_Y_DEG", "CONE_DEG", "NEAR_M", "MAX_FAR", "MAX_FAR_OVER_NEAR", "MAX_COORDINATE"):
        assert getattr(schemas, name) == getattr(rig_bounds, name), name


@pytest.mark.parametrize("camera, field", [
    ({"fov_y_deg": 1e-300}, "camera.fov_y_deg"), ({"fov_y_deg": 179.5}, "camera.fov_y_deg"),
    ({"near": 1e-300}, "camera.near"), ({"far": 1e300}, "camera.far"), ({"near": 1e-4, "far": 1e4}, "camera"),
    ({"position": [1e12, 0, 0]}, "camera.position.0"), ({"target": [0, float("nan"), 0]}, "camera.target.1"),
])
def test_a_camera_number_past_its_bound_is_refused_naming_it(camera, field):
    rig = {"camera": {"position": [0, 1.7, 0], "target": [0, 1, 10], **camera}, "lights": SUN}
    with pytest.raises(ValidationError) as e:
        validate_rig(rig)
    text = format_validation_error(e.value)
    assert text.startswith(field + ":"), text
    assert "far / near" in text if field == "camera" else True


def test_the_resolved_checks_name_the_field_and_measure_from_the_scene():
    with pytest.raises(BoundError) as e:  # a USD camera's own clipping range: named by its usd_path
        check_camera(60.0, 1e-3, 1e5, {"fov_y_deg": "camera.usd_path", "near": "camera.usd_path",
                                       "far": "camera.usd_path"})
    assert e.value.field == "camera.usd_path" and "far / near = 1e+08" in e.value.message
    with pytest.raises(BoundError, match="cone half-angle 0.001"):
        check_cone(0.001, "lights.0.cone_deg")
    assert distance_to_box([0, 0, 0], [-1, -1, -1], [1, 1, 1]) == 0.0
    assert distance_to_box([4, 5, 1], [-1, -1, -1], [1, 1, 1]) == 5.0  # (3, 4, 0) from the corner
    check_near_scene([1e6 + 1, 0, 0], [-1, -1, -1], [1, 1, 1], "lights.0.position", "point light")
    with pytest.raises(BoundError) as e:
        check_near_scene([1e6 + 2, 0, 0], [-1, -1, -1], [1, 1, 1], "lights.0.position", "point light")
    assert e.value.field == "lights.0.position" and "max_rig_distance_m = 1e+06" in e.value.message
    assert not math.isnan(rig_bounds.max_distance_m())


def test_the_distance_bound_is_configured_through_the_environment(monkeypatch):
    monkeypatch.setenv(rig_bounds.DISTANCE_ENV, "50")
    with pytest.raises(BoundError, match="max_rig_distance_m = 50"):
        check_near_scene([0, 0, 100], [-1, -1, -1], [1, 1, 1], "camera.position", "camera")
    monkeypatch.setenv(rig_bounds.DISTANCE_ENV, "nan")  # never a bound that passes everything
    assert rig_bounds.max_distance_m() == rig_bounds.MAX_DISTANCE_M
