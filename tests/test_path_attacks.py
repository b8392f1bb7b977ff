"""Attacks on path jobs (POST /v1/paths) with crafted stages, against a real uvicorn server (and, where the test
looks inside the process, FastAPI's TestClient): a frame whose geometry is skipped at its time code says so on
its line; a stage light at its default time and heavy at t = 10 loads at t = 10 under the upload's load limits
(memory on the server, time in the worker's entry point) and fails that frame alone; a failed frame's line keeps
frame/time; unusable camera values are named as such; the POST reads the stage's animation once, in a scene-load
slot, and refuses a stage whose sampled topology passes the triangle limit at a requested time code."""
from __future__ import annotations

import json
import math
import time
from pathlib import Path

import httpx
import pytest

from serverkit import auth, running

# Three frames of a USD camera at t = 0, 5, 10 (the camera holds still: the stage's geometry moves).
RIG = {"camera": {"usd_path": "/World/Cam", "resolution": [96, 54]}, "lights": [{"usd_path": "/World/Sun"}],
       "shadow": {"resolution": [128, 128]}, "coarse_long_side": 32}
TIMES = {"start": 0, "end": 10, "step": 5}
LOAD_MEMORY_BYTES = 1536 << 20  # the load memory limit: these stages load under it at t = 0 (~1.3 GB)

STAGE = """#usda 1.0
(
    upAxis = "Y"
    metersPerUnit = 1
    startTimeCode = 0
    endTimeCode = 10
)
def Xform "World"
{
    def Mesh "Ground"
    {
        point3f[] points = [(-5,0,-5),(5,0,-5),(5,0,5),(-5,0,5)]
        int[] faceVertexCounts = [4]
        int[] faceVertexIndices = [0,3,2,1]
    }
    def Camera "Cam"
    {
%(camera)s
        double3 xformOp:translate = (0, 2, 10)
        uniform token[] xformOpOrder = ["xformOp:translate"]
    }
%(body)s
    def DistantLight "Sun"
    {
        float3 xformOp:rotateXYZ = (-60, 20, 0)
        uniform token[] xformOpOrder = ["xformOp:rotateXYZ"]
    }
}
"""

# A triangle caster whose points are NaN at t = 5 only (USD holds the sample: no interpolation across it at 5).
NAN_CASTER = """
    def Mesh "Caster"
    {
        int[] faceVertexCounts = [3]
        int[] faceVertexIndices = [0, 1, 2]
        point3f[] points.timeSamples = {
            0: [(-1, 1, 0), (1, 1, 0), (0, 2, 0)],
            4.9: [(-1, 1, 0), (1, 1, 0), (0, 2, 0)],
            5: [(nan, nan, nan), (nan, 1, 0), (0, 2, 0)],
            5.1: [(-1, 1, 0), (1, 1, 0), (0, 2, 0)],
            10: [(-1, 1, 0), (1, 1, 0), (0, 2, 0)] }
    }
"""

def cube_crowd(n: int) -> str:
    """A PointInstancer of one cube except n cubes at t = 10: the upload's check at the default time (the first
    sample) sees one cube."""
    pos = ",".join(f"({i % 500},0.5,{i // 500})" for i in range(n))
    idx = ",".join("0" for _ in range(n))
    return f"""
    def PointInstancer "Crowd"
    {{
        point3f[] positions.timeSamples = {{ 0: [(0,0.5,0)], 5: [(1,0.5,0)], 9.9: [(1,0.5,0)], 10: [{pos}],
                                             10.1: [(1,0.5,0)] }}
        int[] protoIndices.timeSamples = {{ 0: [0], 5: [0], 9.9: [0], 10: [{idx}], 10.1: [0] }}
        rel prototypes = </World/Crowd/Proto>
        def Xform "Proto"
        {{
            def Cube "C"
            {{
                double size = 0.5
            }}
        }}
    }}
"""


BALLS = 20_000  # spheres (960 triangles each) at t = 10 only: ~0.9 GB of triangles, over the load memory limit


def ball_crowd() -> str:
    """A PointInstancer of one sphere up to t = 9.9 and BALLS spheres at t = 10 (0.3 MB of text)."""
    pos = ",".join(f"({i % 200},0.5,{i // 200})" for i in range(BALLS))
    idx = ",".join("0" for _ in range(BALLS))
    return f"""
    def PointInstancer "Balls"
    {{
        point3f[] positions.timeSamples = {{ 0: [(0,0.5,0)], 9.9: [(0,0.5,0)], 10: [{pos}] }}
        int[] protoIndices.timeSamples = {{ 0: [0], 9.9: [0], 10: [{idx}] }}
        rel prototypes = </World/Balls/Proto>
        def Xform "Proto"
        {{
            def Sphere "S"
            {{
                double radius = 0.3
            }}
        }}
    }}
"""


def stage(body: str = "", camera: str = "        float focalLength = 35") -> str:
    return STAGE % {"camera": camera, "body": body}


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    env = {"SHADOWOPT_LOAD_MEMORY_BYTES": str(LOAD_MEMORY_BYTES),
           "SHADOWOPT_MAX_TRIANGLES": "50000000", "SHADOWOPT_BATCH_WORKERS": "1"}
    with running(tmp_path_factory.mktemp("path-attacks") / "data", env=env) as s:
        yield s


def upload(server, text: str, name: str) -> str:
    r = httpx.post(f"{server.base}/v1/scenes", params={"filename": name}, content=text.encode(),
                   headers={**auth("alice"), "Content-Type": "application/octet-stream"}, timeout=120)
    assert r.status_code in (200, 201), r.text
    return r.json()["scene_id"]


def run_path(server, scene_id: str, times: dict = TIMES, timeout: float = 240.0) -> tuple[dict, list[dict]]:
    """POST the path, wait for it; (status, result lines)."""
    r = httpx.post(f"{server.base}/v1/paths", json={"scene_id": scene_id, "rig": RIG, "usd_camera": "/World/Cam",
                                                    "time": times, "method": "focused"},
                   headers=auth("alice"), timeout=120)
    assert r.status_code == 202, r.text
    batch = r.json()["batch_id"]
    deadline = time.monotonic() + timeout
    while True:
        st = httpx.get(f"{server.base}/v1/batches/{batch}", headers=auth("alice"), timeout=30).json()
        if st["state"] not in ("queued", "running") or time.monotonic() > deadline:
            break
        time.sleep(0.2)
    text = httpx.get(f"{server.base}/v1/batches/{batch}/results", headers=auth("alice"), timeout=30).text
    return st, [json.loads(x) for x in text.splitlines()]


@pytest.fixture(scope="module")
def attacked(server):
    """One path (t = 0, 5, 10) over a stage whose caster is NaN at t = 5, and which is light at its default time
    (the upload's check: 3 triangles and one sphere) but holds 19 M triangles at t = 10: (status, result lines,
    seconds the path took)."""
    sid = upload(server, stage(NAN_CASTER + ball_crowd()), "attacked.usda")
    t0 = time.monotonic()
    st, lines = run_path(server, sid)
    return st, lines, time.monotonic() - t0


@pytest.mark.server
def test_a_frame_whose_mesh_is_nan_at_its_time_code_says_so_on_its_line(attacked):
    """The caster's points are NaN at t = 5: the loader skips it there, and that frame's line (only that one)
    carries the loader's warning naming the prim and why."""
    st, lines, _ = attacked
    assert [(l["frame"], l["time"], l["scene_time"]) for l in lines] == [(k, 5 * k, 5 * k) for k in range(3)]
    assert "error" not in lines[0] and "error" not in lines[1], [l.get("error") for l in lines]
    assert any(w.startswith("/World/Caster: skipped") and "NaN" in w for w in lines[1]["warnings"]), lines[1]
    assert not any("/World/Caster" in w for w in lines[0].get("warnings") or [])


@pytest.mark.server
def test_a_frame_heavy_only_at_its_time_code_fails_alone_over_the_upload_load_memory_limit(attacked):
    """The worker's load at t = 10 (20 k instanced spheres: 19 M triangles, ~0.9 GB) runs isolated under the
    upload's memory limit and is stopped there: that frame's line (with its frame, time and scene_time, like a
    solved frame's) names the time code and the limit, the batch's errors too, and the other frames are solved."""
    st, lines, took = attacked
    assert st["state"] == "done" and st["done"] == 2 and st["failed"] == 1, st
    assert [l["index"] for l in lines] == [0, 1, 2]
    big = lines[2]
    assert (big["frame"], big["time"], big["scene_time"]) == (2, 10, 10)
    assert big["error"]["code"] == "memory_limit", big
    assert "time code 10" in big["error"]["message"] and "1.5 GiB" in big["error"]["message"]
    assert "(the load memory limit)" in big["error"]["message"]
    assert st["errors"] == [{"index": 2, "frame": 2, "time": 10, "scene_time": 10, **big["error"]}]


def test_a_frame_load_over_the_load_time_limit_fails_naming_it(tmp_path):
    """The batch worker's entry point (what the pool runs per frame) with a time limit of 0.5 s: the load of the
    spheres at t = 10 is stopped (load_timeout) and the outcome names the time code and the limit."""
    from shadowopt.service.job_workers import solve_configuration

    p = tmp_path / "balls.usda"
    p.write_text(stage(ball_crowd()))
    settings = {"method": "focused", "load_limits": {"timeout_s": 0.5, "max_triangles": 50_000_000}}
    out = solve_configuration(str(p), True, {"rig": RIG, "frame": 2, "time": 10.0, "scene_time": 10.0}, settings)
    assert out["error"]["code"] == "load_timeout", out
    assert out["error"]["message"].startswith("the stage at time code 10: loading scene 'balls.usda' took longer "
                                              "than 0.5 s (the load time limit)"), out


@pytest.mark.server
def test_a_nan_focal_length_is_refused_naming_the_attribute_and_time_code(server):
    """focalLength NaN at t = 5 (and USD's interpolation toward it between samples): a 422 naming usd_camera with
    the camera attribute, its value and the time code, not a range error on a fov_y_deg the request never gave."""
    sid = upload(server, stage(camera="        float focalLength.timeSamples = { 0: 35, 5: nan, 10: 35 }"),
                 "nan_focal.usda")
    r = httpx.post(f"{server.base}/v1/paths", json={"scene_id": sid, "rig": RIG, "usd_camera": "/World/Cam",
                                                    "time": TIMES}, headers=auth("alice"), timeout=120)
    assert r.status_code == 422, r.text
    err = r.json()["error"]
    assert err["field"] == "usd_camera"
    assert "/World/Cam: focalLength nan at time code 5 is not a finite positive number" in err["message"]
    assert "fov_y_deg" not in err["message"]


def test_the_animation_is_read_once_in_a_load_slot_not_a_solver_slot(tmp_path, monkeypatch):
    """In the server process (TestClient): the POST's read of the stage's animation holds a scene-load slot and
    no solver slot, and the same path asked again is answered from the cache (no second read). A stage whose
    instancer grows past max_triangles at one time code is refused at the POST, naming it."""
    from starlette.testclient import TestClient

    import shadowopt.api.routes_paths as routes_paths
    import shadowopt.api.server as server_mod
    from shadowopt.api.service_state import LOCAL_TENANT
    from shadowopt.api.settings import Settings

    warm = tmp_path / "warm.usda"  # no camera: the warm-up loads it and solves nothing
    warm.write_text(stage().replace('def Camera "Cam"', 'def Xform "Cam"'))
    seen = []
    real = routes_paths.read_animation_for

    def spy(svc, *args):
        seen.append((svc.admission.load.busy, svc.admission.solve.busy))
        return real(svc, *args)

    monkeypatch.setattr(routes_paths, "read_animation_for", spy)
    app = server_mod.create_app(Settings(data_dir=str(tmp_path / "data"), warm_scenes=[str(warm)], max_triangles=1000))
    svc = app.state.service
    with TestClient(app, base_url="http://localhost") as client:  # no tokens: a loopback Host
        assert svc.ready.wait(120)
        svc.runner.submit = lambda *a, **k: None  # the frames are not solved here: only the POST is looked at
        moving = tmp_path / "moving.usda"  # an operator's file (read in this process: the uploads' isolated read
        moving.write_text(stage(NAN_CASTER))  # is the same call in a child, measured on the real server above)
        scene_id = svc.store.link_scene(LOCAL_TENANT, moving)
        body = {"scene_id": scene_id, "rig": RIG, "usd_camera": "/World/Cam", "time": TIMES}
        first = client.post("/v1/paths", json=body)
        again = client.post("/v1/paths", json=body)
        other = client.post("/v1/paths", json={**body, "time": {"start": 0, "end": 10, "step": 2}})
        crowd = tmp_path / "crowd.usda"  # ground 2 + one cube 12 = 14 triangles at its default time, 2 + 100 x 12 at 10
        crowd.write_text(stage(cube_crowd(100)))
        grown = client.post("/v1/paths", json={**body, "scene_id": svc.store.link_scene(LOCAL_TENANT, crowd)})
        calm = client.post("/v1/paths", json={**body, "scene_id": svc.store.link_scene(LOCAL_TENANT, crowd),
                                              "time": {"start": 0, "end": 9}})
    assert grown.status_code == 413, grown.text  # refused before any frame is queued, naming the time code
    err = grown.json()["error"]
    assert (err["code"], err["field"]) == ("too_many_triangles", "time")
    assert "time code 10" in err["message"] and "1202 triangles" in err["message"] and "/World/Crowd" in err["message"]
    assert calm.status_code == 202, calm.text
    assert first.status_code == again.status_code == other.status_code == 202, (first.text, again.text, other.text)
    assert first.json()["total"] == 3 and other.json()["total"] == 6
    assert first.json()["notes"] == again.json()["notes"]
    assert seen[:2] == [(1, 0), (1, 0)]  # two distinct paths read, each in a load slot with no solver slot held
    assert len(seen) == 4  # and the two crowd paths


@pytest.mark.parametrize("camera, words", [
    ("        float verticalAperture.timeSamples = { 0: 24, 5: -1, 10: 24 }",
     "verticalAperture -1 at time code 5 is not a finite positive number"),
    ("        float2 clippingRange.timeSamples = { 0: (0.1, 100), 5: (0, 100), 10: (0.1, 100) }",
     "clippingRange (0, 100) at time code 5 is not 0 < near < far"),
    ("        float focalLength = inf", "focalLength inf at time code 0 is not a finite positive number"),
])
def test_unusable_camera_values_are_refused_naming_the_attribute(tmp_path, camera, words):
    """The path's expansion (what POST /v1/paths and `shadowopt path --camera` run) names the camera attribute,
    its value at the time code and why, for an aperture, a clipping range and an infinite focal length."""
    from shadowopt.service.paths import PathError, expand_path

    p = tmp_path / "cam.usda"
    p.write_text(stage(camera=camera))
    with pytest.raises(PathError) as e:
        expand_path({"rig": RIG, "usd_camera": "/World/Cam", "time": TIMES}, scene_path=p)
    assert e.value.field == "usd_camera" and words in str(e.value), str(e.value)


def test_a_camera_whose_transform_is_nan_at_a_time_code_is_refused(tmp_path):
    from shadowopt.service.paths import PathError, expand_path

    p = tmp_path / "cam.usda"
    p.write_text(stage().replace("double3 xformOp:translate = (0, 2, 10)",
                                 "double3 xformOp:translate.timeSamples = { 0: (0, 2, 10), 5: (nan, 2, 10), 10: (0, 2, 10) }"))
    with pytest.raises(PathError) as e:
        expand_path({"rig": RIG, "usd_camera": "/World/Cam", "time": {"start": 5, "end": 5}}, scene_path=p)
    assert e.value.field == "usd_camera" and "world transform at time code 5 is not finite" in str(e.value)
    assert len(expand_path({"rig": RIG, "usd_camera": "/World/Cam", "time": {"start": 0, "end": 0}}, scene_path=p)) == 1


def test_the_loader_replaces_a_nan_focal_length_by_usds_fallback_and_says_so(tmp_path):
    """At a scene's load (its default time) a NaN focalLength is USD's fallback 50 mm with the aperture kept:
    fov = 2 atan(24 / (2 x 50)) = 26.99 deg, and a warning names the attribute and its value."""
    from shadowopt.renderers.usd_loader import load_scene

    p = tmp_path / "cam.usda"
    p.write_text(stage(camera="        float focalLength = nan\n        float verticalAperture = 24"))
    scene = load_scene(p)
    assert scene.cameras[0].fov_y_deg == pytest.approx(2 * math.degrees(math.atan(24 / 100)), abs=1e-9)
    assert any(w.startswith("/World/Cam: focalLength nan is not a finite positive number") and "fallback 50" in w
               for w in scene.warnings), scene.warnings
