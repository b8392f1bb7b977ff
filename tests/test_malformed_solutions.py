"""Malformed solutions and previous solutions answer a SolutionError naming the field, never an internal error
(issue 9, item 7: `"solution": {"lights": null}` was a TypeError, a cascade `"warp"` of "x", -1 or a list an
AttributeError, both 500s).

Real solutions of the demo scene (a tiny rig: 160x90 screen, 256² maps, coarse 48) are mutated systematically
(every field path x null, a string, a negative number, a boolean, a list, a nested object, NaN, inf, a wrong
shape) and by hypothesis; each mutated solution must either evaluate or raise SolutionError whose field is a
path that exists in the mutated solution and is the mutated field, one of its parents, children or siblings.
In-process (service.evaluation.evaluate_solution and service.solve.solve) for speed; a sample through a
real server asserts 422 with the exact field."""
from __future__ import annotations

import copy
import json
import math
import time

import httpx
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from serverkit import DEMO, TINY_RIG, auth, running, upload

from shadowopt.api.schemas import Rig
from shadowopt.service.evaluation import evaluate_solution
from shadowopt.service.rigs import SolutionError
from shadowopt.service.scenes import SCENES
from shadowopt.service.solution_check import validate_solution
from shadowopt.service.request import SolveRequest
from shadowopt.service.solve import solve

SCREEN = (64, 36)  # the property holds at any size; small keeps ~400 distinct evaluations fast
# Fields nobody reads whose children are not walked one by one (the key itself is mutated).
OPAQUE = {"view_matrix", "projection_matrix", "texture_matrix", "predicted_error", "settings", "timings_ms",
          "convention", "solver.cascades", "baselines", "starts", "result", "formula", "temporal"}


def _rig(**shadow) -> dict:
    r = copy.deepcopy(TINY_RIG)
    r["shadow"].update(shadow)
    return Rig.model_validate(r).model_dump(by_alias=True)


@pytest.fixture(scope="module")
def entry():
    return SCENES.get(str(DEMO))


@pytest.fixture(scope="module")
def solutions(entry):
    """name -> (rig, solution): an optimized single map (perspective warp, solver x) and LogPSM with two
    cascades (log warp, blend band), both through JSON as a client holds them (inf -> null as the server sends)."""
    out = {}
    for name, method, rig in (("optimized", "optimized", _rig()),
                              ("logpsm2", "logpsm", {**_rig(cascades=2), "output": {**_rig()["output"],
                                                                                     "allow_log_warp": True}})):
        sol = solve(entry, rig, SolveRequest(method))
        out[name] = (rig, as_client_sees(sol))
    return out


def as_client_sees(obj):
    """A solution as it reaches a client: the server's own JSON conversion (api.responses.finite: non-finite
    numbers as null, NumPy values as Python numbers), serialised as the server does."""
    from shadowopt.api.responses import finite

    return json.loads(json.dumps(finite(obj), allow_nan=False))


def walk(node, path=()):
    """Every path (tuple of keys and indices) in a solution, stopping below the OPAQUE fields and inside the
    4x4 matrices (their rows and two entries are walked)."""
    yield path
    if path and (path[-1] in OPAQUE or ".".join(map(str, path[-2:])) in OPAQUE):
        return
    if isinstance(node, dict):
        for k, v in node.items():
            yield from walk(v, path + (k,))
    elif isinstance(node, list):
        matrix = len(node) == 4 and all(isinstance(r, list) and len(r) == 4 for r in node)
        for i, v in enumerate(node):
            if matrix:  # the rows; of the entries, two
                yield path + (i,)
                yield from (path + (i, j) for j in range(4) if (i, j) in ((1, 2), (3, 3)))
            else:
                yield from walk(v, path + (i,))


def get(node, path):
    for p in path:
        node = node[p]
    return node


def replaced(sol, path, value):
    out = copy.deepcopy(sol)
    if not path:
        return value
    get(out, path[:-1])[path[-1]] = value
    return out


def mutations_of(value):
    """(kind, replacement) for one field: wrong types, non-finite numbers, wrong shapes."""
    out = [("null", None), ("string", "x"), ("negative", -1), ("bool", True), ("list", [1, 2]),
           ("nested", {"a": {"b": [1]}}), ("nan", math.nan), ("inf", math.inf)]
    if isinstance(value, list):
        out += [("empty", []), ("shorter", copy.deepcopy(value[:-1])),
                ("longer", copy.deepcopy(value + value[-1:]))]
        if len(value) == 4 and all(isinstance(r, list) for r in value):
            out.append(("3x4", copy.deepcopy(value[:3])))
            out.append(("4x3", [r[:3] for r in value]))
    if isinstance(value, dict):
        out.append(("empty_object", {}))
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        out += [("zero", 0), ("huge", 1e308)]
    return out


def field_path(field: str) -> tuple:
    parts = field.split(".")[1:]
    return tuple(int(p) if p.isdigit() else p for p in parts)


def exists(node, path) -> bool:
    for p in path:
        if isinstance(node, dict) and p in node:
            node = node[p]
        elif isinstance(node, list) and isinstance(p, int) and p < len(node):
            node = node[p]
        else:
            return False
    return True


def assert_names_the_field(err: SolutionError, mutated, path, root="solution"):
    """The error's field is a path of the mutated solution, and the mutated field itself, a parent, a child
    or a sibling of it (a consistency rule: warp.kind against warp.log)."""
    assert err.field == root or err.field.startswith(root + "."), err.field
    f = field_path(err.field)
    assert exists(mutated, f), f"{err.field} is not a path of the mutated solution ({err})"
    n = min(len(f), len(path))
    assert f[:n] == tuple(path)[:n] or f[:-1] == tuple(path)[:-1], f"{err.field} for a mutation at {path}: {err}"
    assert str(err).startswith(err.field + ": ") and len(err.message) > 5


UNREAD = ("view_matrix", "projection_matrix", "texture_matrix", "predicted_error", "blend_band")


def read_part(entry, rig, mutated) -> str | None:
    """What evaluate reads of a solution that validates (the cascades but their exported matrices and
    predictions), to evaluate each distinct one once; None when it does not validate."""
    try:
        v = validate_solution(mutated, light_kinds=["directional"] * len(rig["lights"]),
                              scene_hash=entry.loaded.scene_hash)
    except SolutionError:
        return None
    return json.dumps([[{k: c[k] for k in sorted(c) if k not in UNREAD} for c in light["cascades"]]
                       for light in v["lights"]], default=repr)


def check_case(entry, rig, mutated, path, stats, memo=None):
    key = read_part(entry, rig, mutated) if memo is not None else None
    if key is not None and key in memo:
        stats["evaluated"] += 1
        stats["same_read_part"] = stats.get("same_read_part", 0) + 1
        return None
    try:
        res = evaluate_solution(entry, rig, mutated, screen=SCREEN)
    except SolutionError as e:
        assert e.code == "invalid_solution"
        assert_names_the_field(e, mutated, path)
        stats["refused"] += 1
        return e
    assert res["receiver_pixels"] > 0 and 0 <= res["misclassified_pixels"] <= res["receiver_pixels"]
    stats["evaluated"] += 1
    if key is not None:
        memo[key] = res
    return None


def test_real_solutions_validate_unchanged(entry, solutions):
    """The validator refuses nothing /v1/optimize returns (also a point light's cube and a spot light's map)."""
    for rig, sol in solutions.values():
        assert validate_solution(sol, light_kinds=["directional"], scene_hash=entry.loaded.scene_hash)["lights"]
        assert evaluate_solution(entry, rig, sol, screen=SCREEN)["receiver_pixels"] > 0
    for light in ({"type": "point", "position": [0.0, 12.0, 0.0]},
                  {"type": "spot", "position": [0.0, 12.0, 0.0], "direction": [0.2, -1.0, 0.1], "cone_deg": 50}):
        rig = Rig.model_validate({**TINY_RIG, "lights": [light]}).model_dump(by_alias=True)
        sol = as_client_sees(solve(entry, rig, SolveRequest("focused")))
        assert validate_solution(sol, light_kinds=[light["type"]])
        assert evaluate_solution(entry, rig, sol, screen=SCREEN)["receiver_pixels"] > 0


def test_the_reproduced_500s_are_422s_naming_the_field(entry, solutions):
    rig, sol = solutions["optimized"]
    with pytest.raises(SolutionError) as e:
        evaluate_solution(entry, rig, {"lights": None}, screen=SCREEN)
    assert e.value.field == "solution.lights" and "got null" in str(e.value)
    for bad in ("x", -1, [1, 2]):
        with pytest.raises(SolutionError) as e:
            evaluate_solution(entry, rig, replaced(sol, ("lights", 0, "cascades", 0, "warp"), bad), screen=SCREEN)
        assert e.value.field == "solution.lights.0.cascades.0.warp", e.value
        assert str(e.value).startswith("solution.lights.0.cascades.0.warp: expected an object with kind")


@pytest.mark.slow
def test_every_field_times_every_malformation(entry, solutions):
    """Systematic: every field path (matrices: rows and two entries) x every kind of malformation."""
    stats = {"refused": 0, "evaluated": 0}
    fields_refused = set()
    t0 = time.perf_counter()
    for name, (rig, sol) in solutions.items():
        memo = {}  # evaluate once per distinct read part (mutations of unread fields evaluate alike)
        for path in walk(sol):
            for kind, value in mutations_of(get(sol, path) if path else sol):
                mutated = replaced(sol, path, value)
                if check_case(entry, rig, mutated, path, stats, memo) is not None:
                    fields_refused.add(".".join(map(str, path)))
    total = stats["refused"] + stats["evaluated"]
    assert total >= 110 and stats["refused"] >= 110, stats
    # what evaluate reads is among the refused fields (the null / wrong-type cases of each)
    for f in ("", "lights", "lights.0", "lights.0.cascades", "lights.0.cascades.0", "lights.0.cascades.0.internal",
              "lights.0.cascades.0.internal.view", "lights.0.cascades.0.internal.projection.1.2",
              "lights.0.cascades.1.resolution", "lights.0.cascades.1.split", "lights.0.cascades.1.split.0",
              "lights.0.cascades.0.light_depth", "lights.0.cascades.0.warp", "lights.0.cascades.0.warp.kind",
              "lights.0.cascades.0.warp.log", "lights.0.cascades.0.warp.log.c0", "lights.0.cascades.0.depth_bias",
              "lights.0.cascades.0.depth_bias.constant_texels", "lights.0.type",
              "provenance", "provenance.scene_hash", "method", "schema_version", "solver", "solver.x", "solver.x.0",
              "solver.x.0.1"):
        assert f in fields_refused, f
    print(f"{total} malformed solutions: {stats} in {time.perf_counter() - t0:.1f} s")


JSON = st.recursive(st.none() | st.booleans() | st.integers(-10**6, 10**6) | st.floats() | st.text(max_size=8),
                    lambda inner: st.lists(inner, max_size=5) | st.dictionaries(st.text(max_size=6), inner, max_size=4),
                    max_leaves=12)


@pytest.mark.slow
@settings(max_examples=60, deadline=None, derandomize=True, database=None, suppress_health_check=list(HealthCheck))
@given(data=st.data())
def test_hypothesis_drawn_malformations(entry, solutions, data):
    name = data.draw(st.sampled_from(sorted(solutions)))
    rig, sol = solutions[name]
    paths = [p for p in walk(sol) if p]
    path = data.draw(st.sampled_from(paths))
    mutated = replaced(sol, path, data.draw(JSON))
    check_case(entry, rig, mutated, path, {"refused": 0, "evaluated": 0})


PREVIOUS_PATHS = [("solver",), ("solver", "x"), ("solver", "x", 0), ("solver", "x", 0, 0), ("solver", "x", 0, 1),
                  ("lights",), ("lights", 0, "cascades", 0, "warp"), ("provenance",)]


def test_malformed_previous_solutions(entry, solutions):
    """`previous` is read for its solver's x: malformed -> SolutionError invalid_previous naming the field, before
    any work; what is accepted solves."""
    rig, sol = solutions["optimized"]
    accepted = refused = 0
    for path in PREVIOUS_PATHS:
        for kind, value in mutations_of(get(sol, path)):
            mutated = replaced(sol, path, value)
            try:
                validate_solution(mutated, "previous", n_lights=1, maps=False, code="invalid_previous")
            except SolutionError as e:
                assert e.code == "invalid_previous"
                assert_names_the_field(e, mutated, path, root="previous")
                with pytest.raises(SolutionError) as again:  # solve refuses it the same way
                    solve(entry, rig, SolveRequest("optimized", previous=mutated, time_budget_ms=50))
                assert again.value.field == e.field
                refused += 1
                continue
            accepted += 1
    assert refused >= 40, refused
    for ok in (replaced(sol, ("solver", "x", 0), None), replaced(sol, ("solver",), None), {"solver": sol["solver"]}):
        assert solve(entry, rig, SolveRequest("optimized", previous=ok, time_budget_ms=50))["lights"][0]["cascades"]
    assert accepted >= 3


# --- a sample through a real server: 422 with the exact field ---------------------------------------------

@pytest.fixture(scope="module")
def server(tmp_path_factory):
    with running(tmp_path_factory.mktemp("malformed") / "data", env={"SHADOWOPT_RATE_LIMIT_PER_S": "0"}) as s:
        yield s


C0 = ("lights", 0, "cascades", 0)
SERVER_CASES = [  # (path, value, the field the 422 names)
    (("lights",), None, "solution.lights"),
    (C0 + ("warp",), "x", "solution.lights.0.cascades.0.warp"),
    (C0 + ("warp",), -1, "solution.lights.0.cascades.0.warp"),
    (C0 + ("warp",), [1, 2], "solution.lights.0.cascades.0.warp"),
    (C0 + ("warp", "kind"), "x", "solution.lights.0.cascades.0.warp.kind"),
    (C0 + ("warp", "kind"), "log", "solution.lights.0.cascades.0.warp.log"),
    (C0 + ("internal", "view"), "3x4", "solution.lights.0.cascades.0.internal.view"),
    (C0 + ("internal", "projection", 1, 2), math.nan, "solution.lights.0.cascades.0.internal.projection.1.2"),
    (C0 + ("internal",), {"view": [[0.0] * 4] * 4, "projection": [[0.0] * 4] * 4}, "solution.lights.0.cascades.0.internal"),
    (C0 + ("resolution",), [256], "solution.lights.0.cascades.0.resolution"),
    (C0 + ("resolution",), "x", "solution.lights.0.cascades.0.resolution"),
    (C0 + ("split",), None, "solution.lights.0.cascades.0.split"),
    (C0 + ("split", 0), "x", "solution.lights.0.cascades.0.split.0"),
    (C0 + ("light_depth",), [], "solution.lights.0.cascades.0.light_depth"),
    (C0 + ("depth_bias",), "x", "solution.lights.0.cascades.0.depth_bias"),
    (C0 + ("depth_bias", "constant_texels"), "x", "solution.lights.0.cascades.0.depth_bias.constant_texels"),
    (C0 + ("face",), 7, "solution.lights.0.cascades.0.face"),
    (("lights", 0, "cascades"), [], "solution.lights.0.cascades"),
    (("lights", 0, "cascades"), {"a": 1}, "solution.lights.0.cascades"),
    (("lights", 0), "x", "solution.lights.0"),
    (("lights", 0, "type"), "spot", "solution.lights.0.type"),
    (("provenance",), "x", "solution.provenance"),
]


@pytest.mark.server
def test_server_answers_422_naming_the_field(server):
    r = upload(server.base, "alice")
    assert r.status_code in (200, 201), r.text
    sid = r.json()["scene_id"]
    with httpx.Client(base_url=server.base, headers=auth("alice"), timeout=120) as api:
        sol = api.post("/v1/optimize", json={"scene_id": sid, "rig": TINY_RIG, "method": "optimized",
                                             "time_budget_ms": 200}).json()
        assert api.post("/v1/evaluate", json={"scene_id": sid, "rig": TINY_RIG, "solution": sol}).status_code == 200
        failures = []
        for path, value, field in SERVER_CASES:
            if value == "3x4":
                value = get(sol, path)[:3]
            body = json.dumps({"scene_id": sid, "rig": TINY_RIG, "solution": replaced(sol, path, value)})
            r = api.post("/v1/evaluate", content=body, headers={"Content-Type": "application/json"})
            err = r.json().get("error", {}) if r.headers.get("content-type", "").startswith("application/json") else {}
            if not (r.status_code == 422 and err.get("code") == "invalid_solution" and err.get("field") == field
                    and err.get("message", "").startswith(field + ": ")):
                failures.append((path, value, r.status_code, r.text[:300]))
        for path, value, field in (((), "x", None), (("solver",), "x", "previous.solver"),
                                   (("solver", "x"), "x", "previous.solver.x"),
                                   (("solver", "x", 0), [1], "previous.solver.x.0"),
                                   (("solver", "x", 0, 0), math.inf, "previous.solver.x.0.0")):
            prev = replaced(sol, path, value)
            body = json.dumps({"scene_id": sid, "rig": TINY_RIG, "method": "optimized", "previous": prev})
            r = api.post("/v1/optimize", content=body, headers={"Content-Type": "application/json"})
            ok = r.status_code == 422 and (field is None or (r.json()["error"]["field"] == field
                                                               and r.json()["error"]["code"] == "invalid_previous"))
            if not ok:
                failures.append((("previous",) + path, value, r.status_code, r.text[:300]))
        assert not failures, "\n".join(map(str, failures))
        assert httpx.get(server.base + "/healthz").status_code == 200


@pytest.mark.server
def test_compare_and_evaluate_accept_what_optimize_accepts(server):
    """Issue 9, item 9: a rig with a texel budget (no resolution) was refused by /v1/compare (422 "cascades.0.
    resolution ... got None") while /v1/optimize accepted it; all three answer 200 now."""
    sid = upload(server.base, "alice").json()["scene_id"]
    rig = {**TINY_RIG, "shadow": {"texel_budget": 200_000, "cascades": 2}}
    with httpx.Client(base_url=server.base, headers=auth("alice"), timeout=120) as api:
        sol = api.post("/v1/optimize", json={"scene_id": sid, "rig": rig, "method": "focused"})
        assert sol.status_code == 200, sol.text
        texels = sum(w * h for w, h in (c["resolution"] for c in sol.json()["lights"][0]["cascades"]))
        assert 0 < texels <= 200_000
        r = api.post("/v1/evaluate", json={"scene_id": sid, "rig": rig, "solution": sol.json()})
        assert r.status_code == 200 and r.json()["receiver_pixels"] > 0, r.text
        r = api.post("/v1/compare", json={"scene_id": sid, "rig": rig, "methods": ["focused", "lispsm"]})
        assert r.status_code == 200, r.text
        assert set(r.json()["methods"]) == {"focused", "lispsm"}


def test_two_light_solutions_and_previous(entry):
    """With two lights: the count and each light's kind are checked against the rig, and a previous solution's
    per-light solver entries (solver.lights) are named one by one."""
    two = Rig.model_validate({**TINY_RIG, "lights": [TINY_RIG["lights"][0],
                                                     {"type": "directional", "direction": [0.3, -1.0, 0.2]}]}
                             ).model_dump(by_alias=True)
    sol = as_client_sees(solve(entry, two, SolveRequest("optimized", time_budget_ms=50)))
    assert evaluate_solution(entry, two, sol, screen=SCREEN)["lights"][1]["receiver_pixels"] > 0
    cases = [(replaced(sol, ("lights",), sol["lights"][:1]), "solution.lights", "has 1 lights but the rig has 2"),
             (replaced(sol, ("lights", 1, "type"), "spot"), "solution.lights.1.type", "rig's light is directional")]
    for bad, field, words in cases:
        with pytest.raises(SolutionError) as e:
            evaluate_solution(entry, two, bad, screen=SCREEN)
        assert e.value.field == field and words in str(e.value), e.value
    assert "lights" in sol["solver"] and len(sol["solver"]["lights"]) == 2
    for path, value, field in ((("solver", "lights"), sol["solver"]["lights"][:1], "previous.solver.lights"),
                               (("solver", "lights", 1), "x", "previous.solver.lights.1"),
                               (("solver", "lights", 1, "x", 0), [math.nan, 1.0], "previous.solver.lights.1.x.0.0")):
        with pytest.raises(SolutionError) as e:
            solve(entry, two, SolveRequest("optimized", previous=replaced(sol, path, value), time_budget_ms=50))
        assert e.value.code == "invalid_previous" and e.value.field == field, e.value
    again = solve(entry, two, SolveRequest("optimized", previous=sol, time_budget_ms=50))
    assert len(again["lights"]) == 2
