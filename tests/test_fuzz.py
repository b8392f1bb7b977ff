"""Schemathesis against the OpenAPI document the server serves: generated requests (valid and invalid) for
every operation get no 5xx, only documented status codes and content types, and bodies that fit the
documented schemas. Bounded: a fixed number of examples per operation.

The schema is read from docs/openapi.json at collection time (schemathesis' lazy fixture loader does
not work with pytest 9); the fixture asserts that the running server serves exactly that document."""
from __future__ import annotations

import httpx
import pytest
import schemathesis
from hypothesis import HealthCheck, settings
from schemathesis.checks import not_a_server_error
from schemathesis.specs.openapi.checks import (content_type_conformance, response_headers_conformance,
                                               response_schema_conformance, status_code_conformance)
from serverkit import REPO, TINY_RIG, auth, running, upload

CHECKS = [not_a_server_error, status_code_conformance, content_type_conformance, response_headers_conformance,
          response_schema_conformance]
FAST = settings(max_examples=30, deadline=None, derandomize=True, database=None,
                suppress_health_check=list(HealthCheck))


@pytest.fixture(scope="module")
def fuzz_server(tmp_path_factory):
    env = {"SHADOWOPT_RATE_LIMIT_PER_S": "0", "SHADOWOPT_MAX_TIME_BUDGET_MS": "200",
           "SHADOWOPT_MAX_EVAL_PIXELS": "100000", "SHADOWOPT_MAX_EVAL_TEXELS": "1000000",
           "SHADOWOPT_MAX_QUEUE": "50", "SHADOWOPT_MAX_TRIANGLES": "100000"}
    with running(tmp_path_factory.mktemp("fuzz") / "data", env=env) as s:
        assert httpx.get(s.base + "/openapi.json").json() == schemathesis.openapi.from_path(DOC).raw_schema
        s.scene_id = upload(s.base, "alice").json()["scene_id"]
        yield s


DOC = REPO / "docs" / "openapi.json"
# The coverage phase (boundary values of every field, hundreds of cases per operation) is left out to
# keep the suite fast; the fuzzing phase draws max_examples per operation, valid and invalid.
CONFIG = schemathesis.config.SchemathesisConfig.from_dict({"phases": {"coverage": {"enabled": False}}})
schema = schemathesis.openapi.from_path(DOC, config=CONFIG)


@schema.parametrize()
@FAST
def test_every_operation_no_5xx_and_conforming(case, fuzz_server):
    """Random scene and batch ids: the 404/422 paths of every operation, the upload's parser included."""
    case.call_and_validate(base_url=fuzz_server.base, headers=auth("alice"), checks=CHECKS)


@schema.include(path_regex="^/v1/(optimize|batches)$").parametrize()
@settings(max_examples=30, deadline=None, derandomize=True, database=None, suppress_health_check=list(HealthCheck))
def test_solver_operations_on_a_real_scene(case, fuzz_server):
    """The same with the id of an uploaded scene and the demo's camera and sun: the generated shadow and
    output settings, methods, solvers, budgets and previous solutions reach the solver (and the batch queue)."""
    if isinstance(case.body, dict):
        case.body["scene_id"] = fuzz_server.scene_id
        configs = case.body.get("configurations")
        rigs = [case.body.get("rig")] + [c.get("rig") for c in configs if isinstance(c, dict)] \
            if isinstance(configs, list) else [case.body.get("rig")]
        for rig in rigs:
            if isinstance(rig, dict):  # the demo's camera and sun, small buffers: the rest is as generated
                rig.update(camera=TINY_RIG["camera"], lights=TINY_RIG["lights"], coarse_long_side=32)
                rig.pop("frame", None)
    case.call_and_validate(base_url=fuzz_server.base, headers=auth("alice"), checks=CHECKS, timeout=120)
