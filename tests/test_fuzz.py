"""Schemathesis against the OpenAPI document the server serves: generated requests (valid and invalid) for
every operation get no 5xx, only documented status codes and content types, and bodies that fit the
documented schemas. Bounded: a fixed number of examples per operation. Also negative testing (schemathesis'
negative generation mode: every request violates the schema and must be refused with a 4xx) and stateful
testing over OpenAPI links added to the document here: upload -> optimize -> evaluate with the returned
solution, and optimize -> optimize with it as `previous`.

The schema is read from docs/openapi.json at collection time (schemathesis' lazy fixture loader does
not work with pytest 9); the fixture asserts that the running server serves exactly that document."""
from __future__ import annotations

import copy
import json
import time

import httpx
import pytest
import schemathesis
from hypothesis import HealthCheck, settings
from schemathesis.checks import not_a_server_error
from schemathesis.specs.openapi.checks import (content_type_conformance, negative_data_rejection,
                                               response_headers_conformance, response_schema_conformance,
                                               status_code_conformance)
from serverkit import DEMO, REPO, TINY_RIG, auth, running, upload

pytestmark = pytest.mark.server

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


# --- negative testing: every generated request violates the schema -------------------------------------------

NEGATIVE = schemathesis.openapi.from_path(DOC, config=schemathesis.config.SchemathesisConfig.from_dict(
    {"phases": {"coverage": {"enabled": False}}, "generation": {"mode": "negative"}}))


@NEGATIVE.parametrize()
@settings(max_examples=15, deadline=None, derandomize=True, database=None, suppress_health_check=list(HealthCheck))
def test_negative_requests_are_refused_with_4xx(case, fuzz_server):
    """Requests that break the documented schema (wrong types, missing fields, out-of-range values) are
    refused with a documented 4xx, never a 5xx (negative_data_rejection: 2xx to invalid data fails too)."""
    if isinstance(case.body, dict) and "scene_id" in case.body and isinstance(case.body.get("scene_id"), str):
        case.body["scene_id"] = fuzz_server.scene_id  # invalid elsewhere, but about a real scene
    case.call_and_validate(base_url=fuzz_server.base, headers=auth("alice"), timeout=120,
                           checks=[not_a_server_error, status_code_conformance, content_type_conformance,
                                   negative_data_rejection])


# --- stateful testing: links upload -> optimize -> evaluate (and -> optimize with previous) --------------------

def _op_id(raw: dict, path: str) -> str:
    return raw["paths"][path]["post"]["operationId"]


def linked_schema():
    """docs/openapi.json with OpenAPI links between the solver operations (the served document has none)."""
    raw = copy.deepcopy(json.loads(DOC.read_text()))
    optimize, evaluate = _op_id(raw, "/v1/optimize"), _op_id(raw, "/v1/evaluate")
    same = {"scene_id": "$request.body#/scene_id", "rig": "$request.body#/rig"}
    for code, resp in raw["paths"]["/v1/scenes"]["post"]["responses"].items():
        if code in ("200", "201"):
            resp["links"] = {"Optimize": {"operationId": optimize, "requestBody": {"scene_id": "$response.body#/scene_id"}}}
    exact = {"x-schemathesis": {"merge_body": False}}  # the linked body as it is (not merged into a generated one)
    raw["paths"]["/v1/optimize"]["post"]["responses"]["200"]["links"] = {
        "Evaluate": {"operationId": evaluate, "requestBody": {**same, "solution": "$response.body"}, **exact},
        "OptimizeAgain": {"operationId": optimize, "requestBody": {**same, "method": "optimized",
                                                                   "previous": "$response.body"}, **exact}}
    config = schemathesis.config.SchemathesisConfig.from_dict({"phases": {"coverage": {"enabled": False}}})
    return schemathesis.openapi.from_dict(raw, config=config).include(
        path_regex="^/v1/(scenes|optimize|evaluate)$", method="POST")


@pytest.mark.timeout(400)  # a hard stop (fails the test), not a timing bound: the elapsed time is printed (-s)
def test_stateful_upload_optimize_evaluate(fuzz_server):
    """Sequences over the links: uploads of the demo scene, optimizes with generated settings (the demo's
    camera and sun), evaluations of the returned solution and optimizes with it as previous: no 5xx,
    documented answers; and the chain really ran (evaluations of linked solutions answered 200)."""
    seen = {"evaluate_200": 0, "previous_200": 0, "calls": 0}
    base = linked_schema().as_state_machine()

    class Machine(base):
        def before_call(self, case):
            seen["calls"] += 1
            case.headers = {**(case.headers or {}), **auth("alice")}  # generated security headers: the stateless run
            if case.operation.path == "/v1/scenes":  # a real scene to chain on (random bytes: the stateless run)
                case.body = DEMO.read_bytes()
                case.query = {"filename": "demo_scene.usda"}
            elif isinstance(case.body, dict):
                if isinstance(case.body.get("solution"), dict) and "schema_version" in case.body["solution"]:
                    case.body.pop("screen", None)  # the rig's 160x90 (generated screens: the stateless run)
                rig = case.body.get("rig")
                if isinstance(rig, dict) and "solution" not in case.body:  # the evaluate's rig is the optimize's
                    rig.update(camera=TINY_RIG["camera"], lights=TINY_RIG["lights"], coarse_long_side=32)
                    rig.pop("frame", None)
                    shadow = rig.setdefault("shadow", {"resolution": [256, 256]})
                    if isinstance(shadow, dict):  # maps the evaluation may cast (the server's texel limit)
                        res = shadow.get("resolution")
                        if shadow.get("texel_budget") is None and not isinstance(res, list):
                            shadow["resolution"] = [256, 256]
                        elif isinstance(res, list):
                            shadow["resolution"] = [min(v, 512) if isinstance(v, int) else v for v in res]
                        if isinstance(shadow.get("texel_budget"), int):
                            shadow["texel_budget"] = min(shadow["texel_budget"], 500_000)

        def get_call_kwargs(self, case):
            return {"base_url": fuzz_server.base, "headers": auth("alice"), "timeout": 120}

        def after_call(self, response, case):
            super().after_call(response, case)
            if case.operation.path == "/v1/evaluate" and isinstance(case.body, dict) \
                    and "schema_version" in (case.body.get("solution") or {}):
                statuses = seen.setdefault("linked_evaluate_statuses", {})
                statuses[response.status_code] = statuses.get(response.status_code, 0) + 1
            if response.status_code == 200 and isinstance(case.body, dict):
                if case.operation.path == "/v1/evaluate" and isinstance(case.body.get("solution"), dict) \
                        and "schema_version" in case.body["solution"]:
                    seen["evaluate_200"] += 1
                if case.operation.path == "/v1/optimize" and isinstance(case.body.get("previous"), dict) \
                        and "schema_version" in case.body["previous"]:
                    seen["previous_200"] += 1

        def validate_response(self, response, case, additional_checks=None, **kwargs):
            case.validate_response(response, checks=CHECKS, transport_kwargs=kwargs or None)

    t0 = time.monotonic()
    Machine.run(settings=settings(max_examples=25, stateful_step_count=5, deadline=None, derandomize=True,
                                  database=None, suppress_health_check=list(HealthCheck)))
    elapsed = time.monotonic() - t0
    print(f"stateful: {seen} in {elapsed:.1f} s")
    assert seen["evaluate_200"] >= 1 and seen["previous_200"] >= 1, seen
