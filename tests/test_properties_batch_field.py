"""A bad batch configuration is named by its index in the request, in the error's `field`.

Independent truth: the position of the bad item in the list the client sent. `field` is what a program reads
(the API's 422 body, ConfigurationError.field); the message is text for a person and is built separately, so
it is not checked in place of the field."""
from __future__ import annotations

import pytest
from serverkit import DEMO, TINY_RIG, TOKENS

from shadowopt.api.schemas import ConfigurationError, validate_configurations

BAD_LAMBDA = {**TINY_RIG, "shadow": {"resolution": [256, 256], "lambda": 2}}  # lambda must lie in [0, 1]
POSE = {"position": [0, 5, 10], "forward": [0, 0, -1]}


@pytest.mark.parametrize("k", [0, 1, 3])
def test_validate_configurations_names_the_bad_index_in_the_field(k):
    configs = [{"rig": TINY_RIG} for _ in range(4)]
    configs[k] = {"rig": BAD_LAMBDA}
    with pytest.raises(ConfigurationError) as e:
        validate_configurations(configs)
    assert e.value.field == f"configurations.{k}.rig.shadow.lambda"
    assert e.value.message.startswith(f"configurations.{k}.rig.shadow.lambda")


@pytest.mark.filterwarnings("ignore:Using `httpx` with `starlette.testclient`")
def test_the_rest_422_for_a_bad_configuration_at_index_1_names_configurations_1(tmp_path):
    from starlette.testclient import TestClient

    from shadowopt.api.server import create_app
    from shadowopt.api.settings import Settings

    app = create_app(Settings(data_dir=str(tmp_path / "data"), tokens={"alice": TOKENS["alice"]}))
    with TestClient(app) as client:
        headers = {"Authorization": f"Bearer {TOKENS['alice']}"}
        up = client.post("/v1/scenes", params={"filename": DEMO.name}, content=DEMO.read_bytes(),
                         headers={**headers, "Content-Type": "application/octet-stream"})
        assert up.status_code in (200, 201), up.text
        scene_id = up.json()["scene_id"]
        for body, field in [
            ({"configurations": [{"rig": TINY_RIG}, {"rig": BAD_LAMBDA}, {"rig": TINY_RIG}]},
             "configurations.1.rig.shadow.lambda"),
            ({"configurations": [{"rig": TINY_RIG}, {"rig": {**TINY_RIG, "camera": {"position": [0, 1, 0]}}}]},
             "configurations.1.rig.camera"),
            # the camera-path form, expanded on the server: its configuration 1 (the second pose) is checked after
            # the expansion (api.schemas.validate_configurations), not by the request's model
            ({"rig": {**TINY_RIG, "camera": {**POSE, "resolution": [160, 90]}},
              "camera_path": {"poses": [POSE, {**POSE, "fov_y_deg": 500}]}},
             "configurations.1.rig.camera.fov_y_deg"),
        ]:
            r = client.post("/v1/batches", json={"scene_id": scene_id, "method": "focused", **body}, headers=headers)
            assert r.status_code == 422, r.text
            err = r.json()["error"]
            assert err["field"] == field or err["field"].startswith(field + "."), (field, err)
            assert err["field"].split(".")[:2] == ["configurations", "1"], err
