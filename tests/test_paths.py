"""Paths as input: camera paths and USD time samples expanded to frames, solved as a batch in frame order
(CLI, REST on a real uvicorn server, the client), coherent frames given the previous frame's solution, resume
after a SIGKILL, errors naming the field."""
from __future__ import annotations

import json
import math
import os
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import httpx
import numpy as np
import pytest

from serverkit import TOKENS, auth, running
from shadowopt.api.schemas import validate_configurations
from shadowopt.service.job_runner import BatchRunner
from shadowopt.service.paths import PathError, expand_path, expand_path_with_notes
from shadowopt.service.store import Store
from storekit import add_upload

REPO = Path(__file__).resolve().parents[1]
DEMO = REPO / "configs" / "demo_scene.usda"
EXE = Path(sys.executable).with_name("shadowopt")
TINY = {"camera": {"usd_path": "/World/Camera", "resolution": [96, 54]}, "lights": [{"usd_path": "/World/Sun"}],
        "shadow": {"resolution": [128, 128]}, "coarse_long_side": 32}
CAM_RIG = {"camera": {"usd_path": "/World/Cam", "resolution": [96, 54]}, "lights": [{"usd_path": "/World/Sun"}],
           "shadow": {"resolution": [128, 128]}, "coarse_long_side": 32}

# A stage in centimetres (metersPerUnit 0.01): the camera slides along +X from (0, 200, 1000) cm at t = 0 to
# (1000, 200, 1000) cm at t = 10 while its focal length goes 50 -> 25 mm; the sun tilts from 30 deg below the
# horizon (rotateX -30) to straight down (-90); a box moves 3 m along +X (geometry with time samples).
ANIMATED_USDA = """#usda 1.0
(
    upAxis = "Y"
    metersPerUnit = 0.01
    startTimeCode = 0
    endTimeCode = 10
)
def Xform "World"
{
    def Mesh "Ground"
    {
        int[] faceVertexCounts = [4]
        int[] faceVertexIndices = [0, 1, 2, 3]
        point3f[] points = [(-3000, 0, -3000), (-3000, 0, 3000), (3000, 0, 3000), (3000, 0, -3000)]
    }
    def Cube "Box"
    {
        double size = 100
        double3 xformOp:translate.timeSamples = { 0: (0, 50, 0), 10: (300, 50, 0) }
        uniform token[] xformOpOrder = ["xformOp:translate"]
    }
    def Camera "Cam"
    {
        float focalLength.timeSamples = { 0: 50, 10: 25 }
        float verticalAperture = 24
        float2 clippingRange = (10, 10000)
        double3 xformOp:translate.timeSamples = { 0: (0, 200, 1000), 10: (1000, 200, 1000) }
        uniform token[] xformOpOrder = ["xformOp:translate"]
    }
    def DistantLight "Sun"
    {
        float3 xformOp:rotateXYZ.timeSamples = { 0: (-30, 0, 0), 10: (-90, 0, 0) }
        uniform token[] xformOpOrder = ["xformOp:rotateXYZ"]
    }
}
"""


def closed_form(t: float) -> dict:
    """What the stage says at time code t (USD interpolates time samples linearly): position in metres,
    fov = 2 atan(aperture / (2 focal)), near/far = clippingRange x 0.01, the sun's direction: -Z rotated about X
    by -(30 + 6 t) deg."""
    focal = 50.0 - 2.5 * t
    a = math.radians(30.0 + 6.0 * t)
    return {"position": [t, 2.0, 10.0], "fov_y_deg": math.degrees(2 * math.atan(24.0 / (2 * focal))),
            "near": 0.1, "far": 100.0, "sun": [0.0, -math.sin(a), -math.cos(a)]}


@pytest.fixture(scope="module")
def animated(tmp_path_factory) -> Path:
    p = tmp_path_factory.mktemp("paths") / "animated.usda"
    p.write_text(ANIMATED_USDA)
    return p


# -- expansion -------------------------------------------------------------------------------------

def test_keyframes_become_frames_in_order_with_one_sun_direction_each():
    req = {"rig": TINY, "camera_path": {"samples": 5, "keyframes": [
        {"position": [0, 1.7, 0], "target": [0, 1, 20]}, {"position": [8, 1.7, 0], "target": [0, 1, 20]}]},
        "sun_arc": {"azimuth_deg": 90, "elevation_deg": [10, 50], "samples": 5}}
    frames = expand_path(req)
    assert [f["frame"] for f in frames] == list(range(5)) and all(f["time"] is None for f in frames)
    assert [f["rig"]["camera"]["position"][0] for f in frames] == pytest.approx([0, 2, 4, 6, 8])
    for k, f in enumerate(frames):
        e = math.radians(10 + 10 * k)  # sun toward +X (azimuth 90), light travels away from it
        assert f["rig"]["lights"][0]["direction"] == pytest.approx([-math.cos(e), -math.sin(e), 0.0], abs=1e-12)
        assert f["rig"]["camera"]["usd_path"] == "/World/Camera"  # keeps the USD camera's intrinsics
    validate_configurations([{"rig": f["rig"]} for f in frames])  # every frame is a valid rig


def test_usd_camera_and_sun_time_samples_match_the_closed_form(animated):
    frames, notes = expand_path_with_notes({"rig": CAM_RIG, "usd_camera": "/World/Cam",
                                            "time": {"start": 0, "end": 10, "step": 2.5}}, scene_path=animated)
    assert [f["time"] for f in frames] == [0, 2.5, 5, 7.5, 10] and [f["frame"] for f in frames] == list(range(5))
    for f in frames:
        want, cam = closed_form(f["time"]), f["rig"]["camera"]
        assert cam["position"] == pytest.approx(want["position"], abs=1e-6)
        assert cam["forward"] == pytest.approx([0, 0, -1], abs=1e-9) and cam["up"] == pytest.approx([0, 1, 0], abs=1e-9)
        assert cam["fov_y_deg"] == pytest.approx(want["fov_y_deg"], abs=1e-4)
        assert (cam["near"], cam["far"]) == pytest.approx((want["near"], want["far"]), rel=1e-6)
        assert cam["resolution"] == [96, 54] and "usd_path" not in cam
        assert f["rig"]["lights"][0] == {"type": "directional", "direction": pytest.approx(want["sun"], abs=1e-6)}
    assert any("/World/Box" in n and "its time code" in n for n in notes)
    assert [f["scene_time"] for f in frames] == [f["time"] for f in frames]  # solved on the stage at that time


@pytest.mark.parametrize("change, field", [
    ({"time": {"start": 0, "end": 10, "step": 0}}, "time.step"),
    ({"time": {"start": 5, "end": 1}}, "time.end"),
    ({"time": {"start": 0, "end": 1e9, "step": 1}}, "time"),
    ({"time": None}, "time"),
    ({"usd_camera": "/World/Sun"}, "usd_camera"),
    ({"usd_camera": "/World/Nope"}, "usd_camera"),
    ({"camera_path": {"poses": [{"position": [0, 1, 0], "target": [0, 0, 5]}]}}, "camera_path"),
    ({"sun_arc": {"elevation_deg": 30}}, "sun_arc"),
    ({"rig": {**CAM_RIG, "frame": "stage"}}, "rig.frame"),
    ({"rig": {**CAM_RIG, "lights": [{"usd_path": "/World/Moon"}]}}, "rig.lights.0.usd_path"),
    ({"speed": 2}, "speed"),
])
def test_bad_path_requests_name_the_field(animated, change, field):
    req = {"rig": CAM_RIG, "usd_camera": "/World/Cam", "time": {"start": 0, "end": 10, "step": 1}, **change}
    req = {k: v for k, v in req.items() if v is not None}
    with pytest.raises(PathError) as e:
        expand_path(req, scene_path=animated)
    assert e.value.field == field


def test_a_camera_path_with_the_wrong_number_of_sun_directions_names_it():
    with pytest.raises(PathError) as e:
        expand_path({"rig": TINY, "camera_path": {"samples": 3, "keyframes": [
            {"position": [0, 1, 0], "target": [0, 0, 9]}, {"position": [1, 1, 0], "target": [0, 0, 9]}]},
            "light_directions": [[0, -1, 0], [0, -1, 0.2]]})
    assert e.value.field == "light_directions"


# -- CLI -------------------------------------------------------------------------------------------

def _cli(*args, cwd=REPO):
    return subprocess.run([str(EXE), *map(str, args)], cwd=cwd, capture_output=True, text=True, timeout=300)


@pytest.mark.server
def test_cli_usd_camera_path_coherent_json_lines_in_frame_order(animated, tmp_path):
    """--camera/--time: one JSON line per frame on stdout, in order, each with frame, time and the solution
    solved at the closed-form pose; --coherent: each frame after the first was given the previous frame's
    solution (the optimizer reports it refit the previous frame's parameters x)."""
    rig = tmp_path / "rig.json"
    rig.write_text(json.dumps(CAM_RIG))
    r = _cli("path", animated, "--rig", rig, "--camera", "/World/Cam", "--time", "0:10:5", "--coherent", "--json",
             "--no-progress", "--out", tmp_path / "o.jsonl")
    assert r.returncode == 0, r.stderr
    lines = [json.loads(x) for x in r.stdout.splitlines()]
    assert [l["frame"] for l in lines] == [0, 1, 2] and [l["time"] for l in lines] == [0, 5, 10]
    assert (tmp_path / "o.jsonl").read_text().splitlines() == r.stdout.splitlines()
    for l in lines:
        want = closed_form(l["time"])
        assert l["resolved"]["camera"]["position"] == pytest.approx(want["position"], abs=1e-5)
        assert l["resolved"]["camera"]["fov_y_deg"] == pytest.approx(want["fov_y_deg"], abs=1e-3)
        assert l["resolved"]["lights"][0]["direction"] == pytest.approx(want["sun"], abs=1e-5)
    assert "temporal" not in lines[0]["solver"]["cascades"][0]
    for a, b in zip(lines, lines[1:]):
        assert b["solver"]["cascades"][0]["temporal"]["previous_x"] == pytest.approx(a["solver"]["x"][0])
    assert "/World/Box" in r.stderr  # the moving box is named
    assert [l["scene_time"] for l in lines] == [0, 5, 10]


@pytest.mark.parametrize("args, words", [
    (["--camera", "/World/Cam", "--time", "0:10:0"], ["time.step"]),
    (["--camera", "/World/Sun", "--time", "0:1"], ["usd_camera", "DistantLight"]),
    (["--camera", "/World/Cam"], ["--time"]),
    (["--camera", "/World/Cam", "--time", "a:b"], ["--time"]),
    ([], ["--path"]),
])
def test_cli_path_bad_input_exits_2_naming_the_field(animated, tmp_path, capsys, args, words):
    from shadowopt.api.cli import main

    rig = tmp_path / "rig.json"
    rig.write_text(json.dumps(CAM_RIG))
    assert main(["path", str(animated), "--rig", str(rig), *args, "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert all(w in err for w in words) and "Traceback" not in err, err


def _readme_path_command() -> str:
    text = (REPO / "README.md").read_text()
    part = text[text.index("### Camera paths"):]
    block = part[part.index("```sh\n") + 6:]
    return block[:block.index("```")].strip()


@pytest.mark.server
def test_readme_camera_path_command_runs_verbatim(tmp_path):
    """The README's command, as printed (in a scratch folder with configs/ linked in): one line per frame of
    the keyframed path, in order, each camera at its interpolated position."""
    import shlex

    (tmp_path / "configs").symlink_to(REPO / "configs")
    cmd = _readme_path_command()
    argv = shlex.split(cmd)
    assert argv[0] == ".venv/bin/shadowopt" and argv[1] == "path"
    r = _cli(*argv[1:], cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    lines = [json.loads(x) for x in r.stdout.splitlines()]
    path = json.loads((REPO / "configs" / "demo_path.json").read_text())
    n = path["samples"]
    assert [l["frame"] for l in lines] == list(range(n))
    k0, k1 = (np.array(k["position"]) for k in path["keyframes"])
    for l in lines:
        u = l["frame"] / (n - 1)
        assert l["resolved"]["camera"]["position"] == pytest.approx(list(k0 + (k1 - k0) * u), abs=1e-6)


# -- REST and the client on a real server -------------------------------------------------------

@pytest.mark.server
def test_rest_post_paths_streams_frames_in_order_and_the_client_yields_them(animated, tmp_path, monkeypatch):
    """An uploaded stage (its animation read in the isolated loader child): 202, errors naming the field, then
    the client's optimize_path yields typed frames in order, and the batch results endpoint has the same
    lines with frame and time."""
    from shadowopt.api.client import Client, PathFrame

    with running(tmp_path / "data") as server:
        up = httpx.post(f"{server.base}/v1/scenes", params={"filename": "animated.usda"},
                        content=animated.read_bytes(), headers={**auth("alice"),
                                                                "Content-Type": "application/octet-stream"}, timeout=60)
        assert up.status_code in (200, 201), up.text
        sid = up.json()["scene_id"]
        body = {"scene_id": sid, "rig": CAM_RIG, "usd_camera": "/World/Sun", "time": {"start": 0, "end": 10, "step": 5}}
        bad = httpx.post(f"{server.base}/v1/paths", json=body, headers=auth("alice"), timeout=60)
        assert bad.status_code == 422 and bad.json()["error"]["field"] == "usd_camera", bad.text
        bad = httpx.post(f"{server.base}/v1/paths", json={**body, "time": {"start": 0, "end": 1, "step": -1}},
                         headers=auth("alice"), timeout=60)
        assert bad.status_code == 422 and "time.step" in bad.json()["error"]["message"], bad.text

        monkeypatch.setenv("SHADOWOPT_TOKEN", TOKENS["alice"])
        with Client(server.base) as c:
            run = c.optimize_path(sid, CAM_RIG, usd_camera="/World/Cam", time="0:10:5", method="focused",
                                  coherent=True, poll_s=0.2)
            got = list(run)
        assert run.created.total == 3 and any("/World/Box" in n for n in run.created.notes)
        assert all(isinstance(f, PathFrame) and f.ok for f in got)
        assert [(f.frame, f.time) for f in got] == [(0, 0.0), (1, 5.0), (2, 10.0)]
        for f in got:
            assert f.solution().resolved["camera"]["position"] == pytest.approx(closed_form(f.time)["position"], abs=1e-5)
        text = httpx.get(f"{server.base}/v1/batches/{run.batch_id}/results", headers=auth("alice")).text
        lines = [json.loads(x) for x in text.splitlines()]
        assert [(l["index"], l["frame"], l["time"]) for l in lines] == [(0, 0, 0), (1, 1, 5), (2, 2, 10)]
        assert [l["lights"][0]["cascades"][0]["view_matrix"] for l in lines] == \
            [f["lights"][0]["cascades"][0]["view_matrix"] for f in got]
    # The box moves (transform time samples): frame 2 was solved on the stage's geometry at t = 10, so its map
    # is the one an in-process solve of the same rig on the stage loaded at time code 10 gives, not the one of
    # the stage at its default time (the box at its first sample).
    from shadowopt.api.schemas import validate_rig
    from shadowopt.service.scenes import SCENES
    from shadowopt.service.request import SolveRequest
    from shadowopt.service.solve import solve

    frame = expand_path({"rig": CAM_RIG, "usd_camera": "/World/Cam", "time": {"start": 10, "end": 10}},
                        scene_path=animated)[0]
    assert frame["scene_time"] == 10
    rig = validate_rig(frame["rig"])
    at_10 = solve(SCENES.get(animated, time_code=10.0), rig, SolveRequest(method="focused"))["lights"][0]["cascades"][0]
    at_default = solve(SCENES.get(animated), rig, SolveRequest(method="focused"))["lights"][0]["cascades"][0]
    served = lines[2]["lights"][0]["cascades"][0]
    assert lines[2]["scene_time"] == 10
    assert served["projection_matrix"] == pytest.approx(at_10["projection_matrix"], abs=1e-9)
    # The sun is read at the frame's time code even for a one-frame range (rotateX -90 at t = 10: straight down),
    # not left as /World/Sun for the solve to read at the stage's default time (rotateX -30).
    assert frame["rig"]["lights"][0]["direction"] == pytest.approx([0.0, -1.0, 0.0], abs=1e-6)
    assert at_default["view_matrix"] == pytest.approx(at_10["view_matrix"], abs=1e-9)  # same explicit light


# -- resume ------------------------------------------------------------------------------------------

RUNNER_SCRIPT = """
import sys, time
from shadowopt.service.job_runner import BatchRunner
from shadowopt.service.store import Store
if __name__ == "__main__":
    runner = BatchRunner(Store(sys.argv[1]), backend="local", workers=1)
    runner.resume()
    time.sleep(600)
"""


def _stored(db: Path, batch_id: str) -> dict[int, str]:
    with sqlite3.connect(db) as c:
        return dict(c.execute("SELECT idx, result FROM results WHERE batch_id = ?", (batch_id,)).fetchall())


@pytest.mark.server
def test_a_coherent_path_resumes_after_sigkill_from_the_stored_previous_frame(tmp_path):
    """Killed mid-path (runner and workers, as a power cut): resume solves only the missing frames, and the
    first of them is given the stored solution of the frame before it."""
    data = tmp_path / "data"
    store = Store(data)
    sid, _ = add_upload(store, "t", DEMO.read_bytes(), "demo_scene.usda")
    frames = expand_path({"rig": TINY, "camera_path": {"samples": 8, "keyframes": [
        {"position": [0, 1.7, 0], "target": [0, 1, 20]}, {"position": [6, 1.7, 2], "target": [0, 1, 20]}]}})
    rigs = validate_configurations([{"rig": f["rig"]} for f in frames])
    frames = [{**f, "rig": r["rig"]} for f, r in zip(frames, rigs)]
    b = store.create_batch("t", sid, frames, {"method": "optimized", "coherent": True})
    env = {**os.environ, "DRJIT_LIBLLVM_PATH": os.environ.get("DRJIT_LIBLLVM_PATH", "")}
    proc = subprocess.Popen([sys.executable, "-c", RUNNER_SCRIPT, str(data)], env=env, start_new_session=True,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 180
        while len(_stored(store.db_path, b)) < 2 and time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.01)
    finally:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    before = _stored(store.db_path, b)
    assert 2 <= len(before) < 8, f"the kill came too late or too early: {len(before)} of 8 stored"
    assert sorted(before) == list(range(len(before)))  # a coherent path is solved in frame order

    runner = BatchRunner(store, backend="local", workers=1)
    try:
        assert runner.resume() == [b]
        assert runner.wait(b, timeout=180) == "done"
    finally:
        runner.shutdown()
    assert runner.stats["submitted"] == 8 - len(before)
    after = _stored(store.db_path, b)
    assert all(after[i] == before[i] for i in before)
    lines = store.results("t", b)
    assert [(l["index"], l["frame"], l["time"]) for l in lines] == [(k, k, None) for k in range(8)]
    for a, c in zip(lines, lines[1:]):  # every frame, the first one after the crash included, got its predecessor
        assert c["solver"]["cascades"][0]["temporal"]["previous_x"] == pytest.approx(a["solver"]["x"][0])
    store.close()


@pytest.mark.parametrize("spec", [{"start": 0, "end": 1e308, "step": 1e-300}, {"start": -1e308, "end": 1e308, "step": 1},
                                  {"start": 0, "end": 1, "step": 1e-320}])
def test_time_ranges_that_overflow_are_refused_naming_time(spec):
    from shadowopt.service.paths import PathError, time_codes

    with pytest.raises(PathError) as e:
        time_codes(spec)
    assert e.value.field == "time" and "exceed the limit" in str(e.value)


MOVING_KINDS = """
#usda 1.0
(
    upAxis = "Y"
    metersPerUnit = 1
)
def Xform "World"
{
    def Camera "Cam"
    {
        double3 xformOp:translate = (0, 2, 10)
        uniform token[] xformOpOrder = ["xformOp:translate"]
    }
    def Mesh "Ground"
    {
        point3f[] points = [(-5,0,-5),(5,0,-5),(5,0,5),(-5,0,5)]
        int[] faceVertexCounts = [4]
        int[] faceVertexIndices = [0,3,2,1]
        token visibility.timeSamples = { 0: "inherited", 5: "invisible" }
    }
    def Mesh "Static"
    {
        point3f[] points.timeSamples = { 0: [(-1,1,0),(1,1,0),(0,2,0)] }
        int[] faceVertexCounts = [3]
        int[] faceVertexIndices = [0,1,2]
    }
    def PointInstancer "Inst"
    {
        point3f[] positions.timeSamples = { 0: [(0,1,5)], 10: [(6,1,6)] }
        int[] protoIndices = [0]
        rel prototypes = </World/Inst/Proto>
        def Xform "Proto"
        {
            def Cube "C"
            {
                double size = 1
            }
        }
    }
    def DistantLight "Sun" {}
}
"""


def test_visibility_and_instancer_samples_count_as_moving_geometry(tmp_path):
    """A prim hidden at a time code and an instancer whose positions are sampled change what a frame sees; points
    with one sample and no default read the same at every time code and do not."""
    from shadowopt.renderers.usd_animation import read_animation

    stage = tmp_path / "kinds.usda"
    stage.write_text(MOVING_KINDS.lstrip())
    assert read_animation(stage, "/World/Cam", [0.0, 10.0])["moving"] == ["/World/Ground", "/World/Inst"]


# -- throughput: tasks of several frames, coherent chunks ------------------------------------------

WALK = {"keyframes": [{"position": [0, 1.7, 0], "target": [0, 1, 20]}, {"position": [6, 1.7, 2], "target": [0, 1, 20]}]}


def _walk_frames(n: int) -> list[dict]:
    frames = expand_path({"rig": TINY, "camera_path": {**WALK, "samples": n}})
    rigs = validate_configurations([{"rig": f["rig"]} for f in frames])
    return [{**f, "rig": r["rig"]} for f, r in zip(frames, rigs)]


def test_chunk_starts_split_a_long_path_evenly_and_keep_a_short_one_whole():
    from shadowopt.service.job_kinds import MIN_CHUNK_FRAMES, chunk_starts

    assert chunk_starts(1000, 2) == [0, 500] and chunk_starts(1000, 3) == [0, 333, 666]
    assert chunk_starts(1000, None) == [0] and chunk_starts(1000, 1) == [0]
    assert chunk_starts(2 * MIN_CHUNK_FRAMES - 1, 2) == [0]  # a chunk would be shorter than MIN_CHUNK_FRAMES
    assert chunk_starts(2 * MIN_CHUNK_FRAMES, 2) == [0, MIN_CHUNK_FRAMES]
    assert chunk_starts(3, 8) == [0]


@pytest.mark.slow
def test_a_path_in_tasks_of_several_frames_on_two_workers_has_each_frames_maps_bit_for_bit():
    """A path job (tasks of several frames, two workers, one Dr.Jit thread each) answers every frame with the
    maps and matrices this process computes for that frame alone, to the last bit."""
    from shadowopt.service.job_kinds import chunk_size
    from shadowopt.service.local_jobs import run_path
    from shadowopt.service.scenes import SCENES
    from shadowopt.service.request import SolveRequest
    from shadowopt.service.solve import solve

    frames = _walk_frames(24)
    assert chunk_size(len(frames), 2) > 1  # the tasks do hold several frames
    lines = []
    s = run_path(DEMO, frames, method="focused", workers=2, on_line=lines.append, progress=False)
    assert (s["done"], s["failed"]) == (24, 0)
    assert [l["frame"] for l in lines] == list(range(24))
    entry = SCENES.get(str(DEMO))
    for line, f in zip(lines, frames):
        alone = json.loads(json.dumps(solve(entry, f["rig"], SolveRequest(method="focused"))["lights"]))
        assert line["lights"] == alone, f"frame {f['frame']}"


@pytest.mark.slow
def test_a_coherent_path_on_two_workers_is_two_coherent_chunks_each_starting_fresh():
    """--coherent with two workers: frames 0-19 and 20-39 each solved in order from a fresh start, every other
    frame given its predecessor's solution; each frame equals this process's own chain, bit for bit."""
    from shadowopt.service.job_kinds import chunk_starts
    from shadowopt.service.job_workers import previous_of
    from shadowopt.service.local_jobs import run_path
    from shadowopt.service.scenes import SCENES
    from shadowopt.service.request import SolveRequest
    from shadowopt.service.solve import solve

    frames = _walk_frames(40)
    assert chunk_starts(40, 2) == [0, 20]
    lines = []
    s = run_path(DEMO, frames, method="optimized", coherent=True, workers=2, on_line=lines.append, progress=False)
    assert (s["done"], s["failed"]) == (40, 0) and [l["frame"] for l in lines] == list(range(40))
    for k in (0, 20):
        assert "temporal" not in lines[k]["solver"]["cascades"][0], k  # a fresh start
    for a, c in zip(lines, lines[1:]):
        if c["frame"] != 20:
            assert c["solver"]["cascades"][0]["temporal"]["previous_x"] == pytest.approx(a["solver"]["x"][0])
    entry = SCENES.get(str(DEMO))
    prev = None
    for line, f in zip(lines, frames):
        sol = json.loads(json.dumps(solve(entry, f["rig"], SolveRequest(method="optimized",
                                          previous=None if f["frame"] in (0, 20) else prev))))
        assert line["lights"] == sol["lights"], f"frame {f['frame']}"
        prev = previous_of(sol)


def test_method_path_in_a_path_job_solves_the_frames_together_as_solve_path_does():
    """Method path over a path job (no --coherent): each run of up to WHOLE_PATH_FRAMES frames is solved together
    by service.solve.solve_path (segments holding their texel grid), so every line has the maps solve_path gives
    those frames in this process, and says which segment of the run it belongs to."""
    from shadowopt.service.job_kinds import WHOLE_PATH_FRAMES
    from shadowopt.service.local_jobs import run_path
    from shadowopt.service.scenes import SCENES
    from shadowopt.service.solve import solve_path

    frames = _walk_frames(6)
    assert len(frames) <= WHOLE_PATH_FRAMES
    lines = []
    s = run_path(DEMO, frames, method="path", workers=2, on_line=lines.append, progress=False)
    assert (s["done"], s["failed"]) == (6, 0)
    assert [l["frame"] for l in lines] == list(range(6))
    want = solve_path(SCENES.get(str(DEMO)), [f["rig"] for f in frames])
    for line, w in zip(lines, want):
        assert line["solver"]["path"]["mode"] == "whole path", line["solver"]
        assert line["solver"]["path"]["segments"] == w["solver"]["path"]["segments"]
        assert line["lights"] == json.loads(json.dumps(w["lights"])), f"frame {line['frame']}"
