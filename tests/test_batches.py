"""Batches: expansion of camera paths and sun arcs, interpolation hints, and real execution on a spawn
pool (and Ray) writing to a real SQLite store, including resume after a SIGKILL."""
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

import numpy as np
import pytest

from shadowopt.api.cli import validate_rig
from shadowopt.service.batch_request import expand_configurations, expansion_shape
from shadowopt.service.interpolation import sun_arc
from shadowopt.service.interpolation_hints import interpolation_hints
from shadowopt.service.job_runner import BatchRunner
from shadowopt.service.request_fields import BatchError
from shadowopt.service.store import Store
from storekit import add_upload

REPO = Path(__file__).resolve().parents[1]
DEMO = REPO / "configs" / "demo_scene.usda"
TINY = {"camera": {"usd_path": "/World/Camera", "resolution": [160, 90]}, "lights": [{"usd_path": "/World/Sun"}],
        "shadow": {"resolution": [256, 256]}, "coarse_long_side": 48}


def arc_configs(n: int, **arc) -> list[dict]:
    req = {"rig": TINY, "sun_arc": {"azimuth_deg": 220, "elevation_deg": [20, 70], "samples": n, **arc}}
    return [{"rig": validate_rig(c["rig"])} for c in expand_configurations(req)]


# -- expansion -------------------------------------------------------------------------------------

def test_explicit_configurations_pass_through_in_order():
    cfgs = [{"rig": {**TINY, "coarse_long_side": 32 + k}} for k in range(3)]
    assert expand_configurations({"configurations": cfgs}) == cfgs
    assert expansion_shape({"configurations": cfgs}) is None


def test_keyframes_interpolate_position_target_and_fov_linearly():
    req = {"rig": TINY, "camera_path": {"samples": 5, "keyframes": [
        {"position": [0, 2, 0], "target": [0, 0, 10], "fov_y_deg": 40},
        {"position": [4, 2, 0], "target": [4, 0, 10], "fov_y_deg": 60},
        {"position": [4, 6, 0], "target": [4, 0, 10], "fov_y_deg": 60}]}}
    cams = [c["rig"]["camera"] for c in expand_configurations(req)]
    assert len(cams) == 5 and expansion_shape(req) == (5, 1)
    assert [c["position"] for c in cams] == [[0, 2, 0], [2, 2, 0], [4, 2, 0], [4, 4, 0], [4, 6, 0]]
    assert [c["target"][0] for c in cams] == [0, 2, 4, 4, 4]
    assert [c["fov_y_deg"] for c in cams] == [40, 50, 60, 60, 60]
    # the base camera's rest is kept, its usd_path too (its intrinsics, when the pose does not give them)
    assert all(c["usd_path"] == "/World/Camera" and c["resolution"] == [160, 90] for c in cams)
    validate_rig(expand_configurations(req)[1]["rig"])  # a valid rig for the API schema


def test_poses_crossed_with_light_directions_index_camera_major():
    poses = [{"position": [0, 2, -5 + k], "target": [0, 0, 10]} for k in range(3)]
    dirs = [[-0.3, -1, 0.2], [0.5, -1, 0], [0, -1, 0]]
    req = {"rig": TINY, "camera_path": {"poses": poses}, "light_directions": dirs}
    cfgs = expand_configurations(req)
    assert len(cfgs) == 9 and expansion_shape(req) == (3, 3)
    for i, c in enumerate(cfgs):
        cam, light = divmod(i, 3)
        assert c["rig"]["camera"]["position"] == poses[cam]["position"]
        assert c["rig"]["lights"] == [{"type": "directional", "direction": [float(v) for v in dirs[light]]}]
    assert TINY["lights"] == [{"usd_path": "/World/Sun"}]  # the base rig is not modified


def test_sun_arc_directions_follow_elevation_and_azimuth():
    d = np.array(sun_arc({"azimuth_deg": 90, "elevation_deg": [0, 90], "samples": 4}))
    assert d.shape == (4, 3) and np.allclose(np.linalg.norm(d, axis=1), 1)
    elev = np.degrees(np.arcsin(-d[:, 1]))  # light travels down: the sun is up
    assert np.allclose(elev, [0, 30, 60, 90])
    assert np.allclose(d[0], [-1, 0, 0], atol=1e-12)  # azimuth 90: the sun toward +X, light travels to -X
    cfgs = expand_configurations({"rig": TINY, "sun_arc": {"azimuth_deg": [0, 180], "elevation_deg": 45,
                                                           "samples": 3}})
    dirs = np.array([c["rig"]["lights"][0]["direction"] for c in cfgs])
    assert np.allclose(dirs[:, 1], -math.sqrt(0.5)) and np.allclose(dirs[1], [-math.sqrt(0.5), -math.sqrt(0.5), 0])


@pytest.mark.parametrize("request_, field", [
    ({"configurations": []}, "configurations"),
    ({"configurations": [{"rig": TINY}, {"rig": TINY, "extra": 1}]}, "configurations.1.extra"),
    ({"configurations": [{"rig": TINY}, "x"]}, "configurations.1.rig"),
    ({"rig": TINY}, "camera_path"),
    ({"rig": TINY, "sun_arc": {"elevation_deg": [10, 80], "samples": 0}}, "sun_arc.samples"),
    ({"rig": TINY, "sun_arc": {"elevation_deg": [10, 95], "samples": 3}}, "sun_arc.elevation_deg.1"),
    ({"rig": TINY, "sun_arc": {"samples": 3}}, "sun_arc.elevation_deg"),
    ({"rig": {**TINY, "frame": "stage"}, "sun_arc": {"elevation_deg": 30}}, "sun_arc"),
    ({"rig": TINY, "light_directions": [[0, -1, 0], [0, 0, 0]]}, "light_directions.1"),
    ({"rig": TINY, "light_directions": [[0, -1, float("nan")]]}, "light_directions.0.2"),
    ({"rig": TINY, "camera_path": {"keyframes": [{"position": [0, 1, 0], "target": [0, 0, 1]}], "samples": 3}},
     "camera_path.keyframes"),
    ({"rig": TINY, "camera_path": {"keyframes": [{"position": [0, 1, 0], "target": [0, 0, 1]},
                                                  {"position": [1, 1, 0], "forward": [0, 0, 1]}], "samples": 3}},
     "camera_path.keyframes.1.target"),
    ({"rig": TINY, "camera_path": {"keyframes": [{"position": [0, 1, 0], "target": [0, 0, 1], "fov_y_deg": 50},
                                                  {"position": [1, 1, 0], "target": [0, 0, 1]}], "samples": 3}},
     "camera_path.keyframes.fov_y_deg"),
    ({"rig": TINY, "camera_path": {"poses": [{"position": [0, 1]}]}}, "camera_path.poses.0.position"),
    ({"rig": TINY, "light_directions": [[0, -1, 0]], "light_index": 3}, "light_index"),
    ({"rig": TINY, "sun_arc": {"elevation_deg": 30, "samples": 101}, "camera_path": {"keyframes": [
        {"position": [0, 1, 0], "target": [0, 0, 1]}, {"position": [1, 1, 0], "target": [0, 0, 1]}],
        "samples": 1000}}, "camera_path"),
])
def test_bad_requests_raise_batch_error_naming_the_field(request_, field):
    with pytest.raises(BatchError) as e:
        expand_configurations(request_)
    assert e.value.field == field and isinstance(e.value, ValueError) and e.value.code == "invalid_batch"


# -- interpolation hints ---------------------------------------------------------------------------

def _fake(index, kinds, method="optimized"):
    return {"index": index, "method": method, "lights": [{"type": "directional", "cascades": [
        {"warp": {"kind": k}, "resolution": [256, 256]} for k in kinds]}]}


def test_interpolation_hints_break_where_warp_kind_or_cascade_count_switches():
    results = [_fake(0, ["perspective"]), _fake(1, ["perspective"]), _fake(2, ["none"]), _fake(3, ["none"]),
               _fake(4, ["none", "none"]), {"index": 5, "error": {"code": "invalid_rig", "message": "x"}},
               _fake(6, ["none", "none"])]
    h = interpolation_hints(results)
    assert [b["between"] for b in h["breaks"]] == [[1, 2], [3, 4], [4, 5], [5, 6]]
    assert "warp kind perspective -> none" in h["breaks"][0]["reasons"][0]
    assert "cascades 1 -> 2" in h["breaks"][1]["reasons"][0]
    assert h["segments"] == [[0, 1], [2, 3], [4, 4], [6, 6]]
    assert "lights[].cascades[].view_matrix" in h["smooth_fields"] and "lights[].cascades[].warp.eta" in h["smooth_fields"]
    assert "lights[].cascades[].warp.kind" in h["switch_fields"]
    # A 2 cameras x 2 lights grid: neighbours along both axes; segments stay within a camera's row.
    grid = interpolation_hints([_fake(0, ["none"]), _fake(1, ["none"]), _fake(2, ["none"]), _fake(3, ["log"])], (2, 2))
    assert sorted(b["between"] for b in grid["breaks"]) == [[1, 3], [2, 3]]
    assert grid["segments"] == [[0, 1], [2, 2], [3, 3]]


def test_hints_along_a_camera_path_with_one_light_join_consecutive_cameras():
    """One light along 6 cameras (shape (6, 1)): consecutive indices are consecutive cameras; the segments
    are the runs between the breaks (a warp-kind switch between 2 and 3, a failed configuration 5)."""
    results = [_fake(0, ["perspective"]), _fake(1, ["perspective"]), _fake(2, ["perspective"]), _fake(3, ["none"]),
               _fake(4, ["none"]), {"index": 5, "error": {"code": "invalid_rig", "message": "x"}}]
    h = interpolation_hints(results, (6, 1))
    assert [b["between"] for b in h["breaks"]] == [[2, 3], [4, 5]]
    assert h["segments"] == [[0, 2], [3, 4]]
    assert "camera_segments" not in h
    # 3 cameras x 2 lights: light 1 switches at camera 2; camera_segments run along the cameras per light.
    grid = interpolation_hints([_fake(0, ["none"]), _fake(1, ["none"]), _fake(2, ["none"]), _fake(3, ["none"]),
                                _fake(4, ["none"]), _fake(5, ["log"])], (3, 2))
    assert grid["segments"] == [[0, 1], [2, 3], [4, 4], [5, 5]]
    assert grid["camera_segments"] == [[0, 4], [1, 3], [5, 5]]


def _stage_with_camera(path: Path, fov_y_deg: float, near: float, far: float, roll_deg: float) -> Path:
    """A ground quad and a UsdGeom.Camera whose vertical fov, clipping range and roll are known."""
    from pxr import Gf, Usd, UsdGeom

    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    ground = UsdGeom.Mesh.Define(stage, "/World/Ground")
    ground.CreatePointsAttr([(-20, 0, -20), (20, 0, -20), (20, 0, 20), (-20, 0, 20)])
    ground.CreateFaceVertexCountsAttr([4])
    ground.CreateFaceVertexIndicesAttr([0, 3, 2, 1])
    cube = UsdGeom.Cube.Define(stage, "/World/Box")
    cube.AddTranslateOp().Set(Gf.Vec3d(0, 1, 0))
    cam = UsdGeom.Camera.Define(stage, "/World/Cam")
    v_ap = 24.0
    cam.CreateVerticalApertureAttr(v_ap)
    cam.CreateHorizontalApertureAttr(v_ap * 16 / 9)
    cam.CreateFocalLengthAttr(v_ap / 2 / math.tan(math.radians(fov_y_deg) / 2))
    cam.CreateClippingRangeAttr(Gf.Vec2f(near, far))
    cam.AddTranslateOp().Set(Gf.Vec3d(0, 3, 12))
    cam.AddRotateZOp().Set(roll_deg)
    stage.GetRootLayer().Save()
    return path


def test_a_camera_path_over_a_usd_camera_keeps_its_fov_near_far_and_up(tmp_path):
    """The base rig names a USD camera of known intrinsics (fov 33 deg, clip [0.5, 80], rolled 90 deg so its
    up is -X, not +Y); each pose of the path moves it but keeps them, unless the pose gives its own fov."""
    from shadowopt.renderers.usd_loader import load_scene
    from shadowopt.service.echo import resolved_echo
    from shadowopt.service.rigs import resolve_rig

    scene = load_scene(_stage_with_camera(tmp_path / "cam.usda", 33.0, 0.5, 80.0, 90.0))
    base = {"camera": {"usd_path": "/World/Cam", "resolution": [160, 90]}, "lights": [{"type": "directional",
            "direction": [0.3, -1, 0.2]}]}
    req = {"rig": base, "camera_path": {"samples": 3, "keyframes": [
        {"position": [0, 2, 10], "target": [0, 0, 0]}, {"position": [6, 2, 8], "target": [0, 0, 0]}]}}
    echoes = [resolved_echo(resolve_rig(validate_rig(c["rig"]), scene))["camera"] for c in expand_configurations(req)]
    for e, pos in zip(echoes, ([0, 2, 10], [3, 2, 9], [6, 2, 8])):
        assert e["fov_y_deg"] == pytest.approx(33.0, abs=1e-4)
        assert (e["near"], e["far"]) == pytest.approx((0.5, 80.0))
        assert e["position"] == pytest.approx(pos)
        assert np.dot(e["forward"], -np.asarray(pos) / np.linalg.norm(pos)) == pytest.approx(1.0)
        assert e["up"][0] < -0.75 and abs(np.dot(e["up"], e["forward"])) < 1e-9  # the camera's own up (rolled to -X), made perpendicular to the new forward
        assert e["usd_path"] == "/World/Cam"
    poses = {"rig": base, "camera_path": {"poses": [{"position": [0, 2, 10], "target": [0, 0, 0], "fov_y_deg": 50}]}}
    (cfg,) = expand_configurations(poses)
    assert resolved_echo(resolve_rig(validate_rig(cfg["rig"]), scene))["camera"]["fov_y_deg"] == 50


MCUSD = REPO.parent / "shared" / "usd-assets" / "full_assets" / "McUsd" / "McUsd.usda"  # read in place


@pytest.mark.skipif(not MCUSD.exists(), reason="the McUsd asset is not on this machine")
def test_mcusd_camera_keeps_its_45_7_degree_fov_along_a_path():
    from shadowopt.renderers.usd_loader import load_scene
    from shadowopt.service.echo import resolved_echo
    from shadowopt.service.rigs import resolve_rig

    scene = load_scene(MCUSD)
    cam = scene.cameras[0]
    base = {"camera": {"usd_path": cam.usd_path, "resolution": [160, 90]}, "lights": [{"type": "directional",
            "direction": [0.3, -1, 0.2]}]}
    p0 = [float(x) for x in cam.position]
    target = [float(a + b) for a, b in zip(cam.position, cam.forward)]
    req = {"rig": base, "camera_path": {"poses": [{"position": p0, "target": target},
                                                  {"position": [p0[0] + 1, p0[1], p0[2]], "target": target}]}}
    for c in expand_configurations(req):
        e = resolved_echo(resolve_rig(validate_rig(c["rig"]), scene))["camera"]
        assert e["fov_y_deg"] == pytest.approx(45.7, abs=0.05) and e["near"] == pytest.approx(cam.near)


# -- job kinds -------------------------------------------------------------------------------------

def _task_indices(queue) -> list[list[int]]:
    out = []
    while (group := queue.take()) is not None:
        out.append([i for i, _ in group])
    return out


def test_a_job_kind_is_found_from_its_stored_settings_and_splits_its_items():
    """A batch's configurations go in chunks; a path's frames (coherent, whole_path or the server's "path") by
    the path's rules: method path in runs cut at multiples of WHOLE_PATH_FRAMES, in index order."""
    from shadowopt.service.job_kinds import KINDS, WHOLE_PATH_FRAMES, chunk_size, kind_of

    assert kind_of({"method": "optimized", "shape": None}) is KINDS["batch"]
    for settings in ({"coherent": True}, {"whole_path": True}, {"path": True, "coherent": False}):
        assert kind_of(settings) is KINDS["path"]
    n = 2 * WHOLE_PATH_FRAMES + 1
    items = [(i, {"rig": {}}) for i in reversed(range(n))]
    runs = _task_indices(KINDS["path"].tasks(None, "b", items, {"whole_path": True}, 2))
    assert runs == [list(range(WHOLE_PATH_FRAMES)), list(range(WHOLE_PATH_FRAMES, 2 * WHOLE_PATH_FRAMES)), [n - 1]]
    items = [(i, {"rig": {}}) for i in range(10)]
    size = chunk_size(10, 1)
    assert _task_indices(KINDS["batch"].tasks(None, "b", items, {}, 1)) == [
        list(range(k, min(k + size, 10))) for k in range(0, 10, size)]
    assert _task_indices(KINDS["path"].tasks(None, "b", items, {"path": True}, 1)) == \
        _task_indices(KINDS["batch"].tasks(None, "b", items, {}, 1))


# -- execution on a real spawn pool ----------------------------------------------------------------

@pytest.fixture(scope="module")
def pool(tmp_path_factory):
    store = Store(tmp_path_factory.mktemp("batch-data"))
    runner = BatchRunner(store, backend="local", workers=2)
    yield store, runner
    runner.shutdown()
    store.close()


def test_a_batch_runs_to_done_in_index_order_and_a_bad_configuration_is_only_an_error(pool):
    store, runner = pool
    sid, _ = add_upload(store, "alice", DEMO.read_bytes(), "demo_scene.usda")  # an upload: sandboxed load
    configs = arc_configs(6)
    configs[3]["rig"]["camera"]["usd_path"] = "/World/NoSuchCamera"  # valid schema, not in this scene
    b = store.create_batch("alice", sid, configs, {"method": "optimized"})
    runner.submit("alice", b)
    assert runner.wait(b, timeout=180) == "done"
    st = store.batch("alice", b)
    assert (st["done"], st["failed"], st["total"]) == (5, 1, 6)
    assert st["errors"][0]["index"] == 3 and st["errors"][0]["code"] == "invalid_rig"
    assert "camera.usd_path" in st["errors"][0]["message"]
    lines = store.results("alice", b)
    assert [r["index"] for r in lines] == list(range(6))
    assert lines[3] == {"index": 3, "error": {"code": "invalid_rig", "message": st["errors"][0]["message"]}}
    ok = [r for r in lines if "error" not in r]
    assert all(r["method"] == "optimized" and r["lights"][0]["predicted_error"]["samples"] > 0 for r in ok)
    # Each result answers its own configuration: the light view follows the sun arc.
    views = [np.array(r["lights"][0]["cascades"][0]["internal"]["view"]) for r in ok]
    assert all(not np.allclose(a, c) for a, c in zip(views, views[1:]))
    # Each line echoes what it was solved for: the demo camera's own fov (2 atan(20.25 / (2 * 18)), its
    # aperture and focal length) and the arc's sun direction.
    for r in ok:
        cam = r["resolved"]["camera"]
        assert cam["fov_y_deg"] == pytest.approx(math.degrees(2 * math.atan(20.25 / 36)), abs=1e-3)
        assert cam["usd_path"] == "/World/Camera" and cam["resolution"] == [160, 90]
        want = np.asarray(configs[r["index"]]["rig"]["lights"][0]["direction"])
        assert r["resolved"]["lights"][0]["direction"] == pytest.approx((want / np.linalg.norm(want)).tolist())
    hints = interpolation_hints(lines)
    assert [2, 3] in [x["between"] for x in hints["breaks"]] and [3, 4] in [x["between"] for x in hints["breaks"]]
    worker_env = runner._impl.pool.submit(os.getenv, "DRJIT_LIBLLVM_PATH").result(timeout=60)
    assert worker_env and Path(worker_env).exists()  # spawned workers carry the LLVM path Dr.Jit needs


def test_a_passing_runner_failure_is_retried_not_turned_into_errors(pool, monkeypatch):
    """A run that fails as a whole (here: the first attempt raises, as a busy database would; a stand-in,
    the failure cannot be caused on demand) leaves its configurations pending and runs the batch again."""
    import shadowopt.service.job_runner as B

    store, runner = pool
    sid, _ = add_upload(store, "alice", DEMO.read_bytes(), "demo_scene.usda")
    real, calls = runner._run, []

    def flaky(tenant, batch_id):
        calls.append(batch_id)
        if len(calls) == 1:
            raise RuntimeError("database is locked")
        return real(tenant, batch_id)

    monkeypatch.setattr(runner, "_run", flaky)
    monkeypatch.setattr(B, "RUNNER_RETRY_S", 0.05)
    b = store.create_batch("alice", sid, arc_configs(2), {"method": "focused"})
    runner.submit("alice", b)
    assert runner.wait(b, timeout=180) == "done"
    st = store.batch("alice", b)
    assert (st["done"], st["failed"], len(calls)) == (2, 0, 2)


def test_a_small_batch_is_not_stuck_behind_a_big_one(pool, monkeypatch):
    """Batches take turns a slice at a time: a 2-configuration batch submitted while a long one runs
    finishes while the long one is still running."""
    import shadowopt.service.job_runner as B

    store, runner = pool
    monkeypatch.setattr(B, "SLICE", 4)
    sid, _ = add_upload(store, "alice", DEMO.read_bytes(), "demo_scene.usda")
    big = store.create_batch("alice", sid, arc_configs(40), {"method": "focused"})
    runner.submit("alice", big)
    deadline = time.monotonic() + 120
    while store.batch("alice", big)["done"] < 2:  # the big batch is under way
        assert time.monotonic() < deadline
        time.sleep(0.02)
    bob_sid, _ = add_upload(store, "bob", DEMO.read_bytes(), "demo_scene.usda")
    small = store.create_batch("bob", bob_sid, arc_configs(2), {"method": "focused"})
    runner.submit("bob", small)
    assert runner.wait(small, timeout=120) == "done"
    big_then = store.batch("alice", big)
    assert big_then["state"] == "running" and big_then["done"] < 40, big_then
    assert runner.wait(big, timeout=180) == "done"
    assert [r["index"] for r in store.results("alice", big)] == list(range(40))


def test_cancel_stops_a_batch_and_the_runner_goes_on(pool):
    store, runner = pool
    sid, _ = add_upload(store, "bob", DEMO.read_bytes(), "demo_scene.usda")
    big = store.create_batch("bob", sid, arc_configs(40), {"method": "optimized"})
    bob_sid, _ = add_upload(store, "bob", DEMO.read_bytes(), "demo_scene.usda")
    small = store.create_batch("bob", bob_sid, arc_configs(2), {"method": "focused"})
    runner.submit("bob", big)
    runner.submit("bob", small)
    deadline = time.monotonic() + 120
    while store.batch("bob", big)["done"] < 1 and time.monotonic() < deadline:
        time.sleep(0.02)
    assert runner.cancel("bob", big) is True and runner.cancel("eve", big) is False
    assert runner.wait(big, timeout=5) == "cancelled"
    assert runner.wait(small, timeout=120) == "done"
    time.sleep(1.0)  # configurations in flight at the cancel are abandoned, not resumed
    st = store.batch("bob", big)
    assert st["state"] == "cancelled" and 1 <= st["done"] < 40
    assert [r["index"] for r in store.results("bob", small)] == [0, 1]


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
def test_resume_after_sigkill_computes_only_what_was_missing(tmp_path):
    data = tmp_path / "data"
    store = Store(data)
    sid, _ = add_upload(store, "t", DEMO.read_bytes(), "demo_scene.usda")
    n = 16
    b = store.create_batch("t", sid, arc_configs(n), {"method": "optimized"})
    env = {**os.environ, "DRJIT_LIBLLVM_PATH": os.environ.get("DRJIT_LIBLLVM_PATH", "")}
    proc = subprocess.Popen([sys.executable, "-c", RUNNER_SCRIPT, str(data)], env=env, start_new_session=True,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 180
        while len(_stored(store.db_path, b)) < 3 and time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.01)
    finally:
        os.killpg(proc.pid, signal.SIGKILL)  # the runner and its pool workers, as a power cut would
        proc.wait()
    before = _stored(store.db_path, b)
    assert 3 <= len(before) < n, f"the kill came too late or too early: {len(before)} of {n} stored"
    assert store.batch("t", b)["state"] == "running"  # what a crash leaves behind

    runner = BatchRunner(store, backend="local", workers=1)
    try:
        assert runner.resume() == [b]
        assert runner.wait(b, timeout=180) == "done"
    finally:
        runner.shutdown()
    assert runner.stats["submitted"] == n - len(before)  # nothing done before was computed again
    after = _stored(store.db_path, b)
    assert sorted(after) == list(range(n))
    assert all(after[i] == before[i] for i in before)  # earlier results unchanged, byte for byte
    with sqlite3.connect(store.db_path) as c:
        counts = c.execute("SELECT idx, COUNT(*) FROM results WHERE batch_id = ? GROUP BY idx", (b,)).fetchall()
    assert all(k == 1 for _, k in counts) and len(counts) == n
    lines = store.results("t", b)
    assert [r["index"] for r in lines] == list(range(n)) and store.batch("t", b)["failed"] == 0
    store.close()


@pytest.mark.slow
def test_ray_backend_on_a_local_instance(tmp_path):
    try:
        import ray
    except ImportError:
        pytest.skip("ray is not importable: install the `ray` extra (pip install 'shadowopt[ray]') to test this backend")
    if ray.is_initialized():
        pytest.skip("a Ray instance is already running in this process")
    store = Store(tmp_path / "data")
    sid, _ = add_upload(store, "t", DEMO.read_bytes(), "demo_scene.usda")  # shipped to the actors as bytes
    configs = arc_configs(5)
    configs[1]["rig"]["lights"][0] = {"usd_path": "/World/NoSuchLight"}
    b = store.create_batch("t", sid, configs, {"method": "optimized"})
    runner = BatchRunner(store, backend="ray", workers=2)
    try:
        runner.submit("t", b)
        assert runner.wait(b, timeout=240) == "done"
        pids = runner._impl.last_actor_pids
        env = ray.get(runner._impl.actors[0].getenv.remote("DRJIT_LIBLLVM_PATH"))
        assert env and Path(env).exists()  # the Ray workers' environment carries the LLVM path
    finally:
        runner.shutdown()
    assert not ray.is_initialized()  # the runner started the local instance and stopped it
    assert len(set(pids)) == 2 and os.getpid() not in pids  # two actors, in other processes
    lines = store.results("t", b)
    assert [r["index"] for r in lines] == list(range(5))
    assert lines[1]["error"]["code"] == "invalid_rig" and "lights.0.usd_path" in lines[1]["error"]["message"]
    assert all(r["lights"][0]["predicted_error"]["samples"] > 0 for k, r in enumerate(lines) if k != 1)
    store.close()


# -- the CLI ---------------------------------------------------------------------------------------

def _cli(*args):
    exe = Path(sys.executable).with_name("shadowopt")
    return subprocess.run([str(exe), *map(str, args)], capture_output=True, text=True, timeout=300, cwd=REPO)


@pytest.mark.server
def test_cli_batch_writes_json_lines_in_index_order(tmp_path):
    cfg = tmp_path / "arc.json"
    cfg.write_text(json.dumps({"rig": TINY, "sun_arc": {"azimuth_deg": 220, "elevation_deg": [20, 70], "samples": 3}}))
    out = tmp_path / "out.jsonl"
    t0 = time.monotonic()
    p = _cli("batch", DEMO, "--configs", cfg, "--out", out, "--workers", "1", "--method", "focused")
    took = time.monotonic() - t0
    assert p.returncode == 0, p.stderr
    lines = [json.loads(x) for x in out.read_text().splitlines()]
    assert [x["index"] for x in lines] == [0, 1, 2] and all(x["method"] == "focused" for x in lines)
    assert "3 done, 0 failed" in p.stdout and "batch" in p.stderr  # summary, and the progress bar on stderr
    # stderr is a pipe, not a terminal: progress as whole lines (no carriage returns), few of them, the last final
    progress = [x for x in p.stderr.splitlines() if x.startswith("batch: ")]
    from shadowopt.api.progress import LOG_INTERVAL_S

    assert "\r" not in p.stderr and progress[-1] == "batch: 3/3 config"
    assert 1 <= len(progress) <= 2 + took / LOG_INTERVAL_S, progress


@pytest.mark.server
@pytest.mark.parametrize("content, words", [
    ({"rig": TINY, "sun_arc": {"elevation_deg": [20, 70], "samples": 0}}, "sun_arc.samples"),
    ({"configurations": [{"rig": TINY}, {"rig": {**TINY, "shadow": {"lambda": 2}}}]}, "configurations.1.rig.shadow.lambda"),
    ([{"rig": TINY}, {"rig": {**TINY, "camera": {"position": [0, 1, 0]}}}], "configurations.1.rig.camera"),
])
def test_cli_batch_bad_configs_exit_2_naming_the_field(tmp_path, content, words):
    cfg = tmp_path / "bad.json"
    cfg.write_text(json.dumps(content))
    p = _cli("batch", DEMO, "--configs", cfg, "--out", tmp_path / "o.jsonl")
    assert p.returncode == 2, (p.stdout, p.stderr)
    assert words in p.stderr and "Traceback" not in p.stderr
    # the error's `field` (what a program reads; the text above is built separately), from the same steps
    # the CLI takes: expand the request, then validate each configuration
    from shadowopt.api.schemas import ConfigurationError, validate_configurations

    with pytest.raises((BatchError, ConfigurationError)) as e:
        validate_configurations(expand_configurations({"configurations": content} if isinstance(content, list)
                                                      else content))
    assert e.value.field == words or e.value.field.startswith(words + "."), (e.value.field, words)


@pytest.mark.server
def test_cli_batch_on_a_file_that_is_not_usd_exits_2_with_the_loaders_reason(tmp_path):
    bad = tmp_path / "bad.usda"
    bad.write_text("not usd")
    cfg = tmp_path / "c.json"
    cfg.write_text(json.dumps([{"rig": TINY}]))
    out = tmp_path / "o.jsonl"
    p = _cli("batch", bad, "--configs", cfg, "--out", out, "--workers", "1", "--no-progress")
    assert p.returncode == 2 and "not_usd" in p.stderr and "Traceback" not in p.stderr
    assert json.loads(out.read_text())["error"]["code"] == "not_usd"  # the line is still written


def test_hints_break_where_a_map_changes_its_depth_mode():
    """An engine cannot blend a hardware-depth map into a linear-depth one: depth.mode is a switch."""
    def with_mode(index, mode):
        r = _fake(index, ["perspective"])
        r["lights"][0]["cascades"][0]["depth"] = {"mode": mode}
        return r

    h = interpolation_hints([with_mode(0, "hardware"), with_mode(1, "hardware"), with_mode(2, "linear")])
    assert [b["between"] for b in h["breaks"]] == [[1, 2]]
    assert h["breaks"][0]["reasons"] == ["light 0: depth mode hardware -> linear"]
    assert h["segments"] == [[0, 1], [2, 2]]
    assert "lights[].cascades[].depth.mode" in h["switch_fields"]


def test_put_outcomes_stores_a_tasks_results_and_errors_in_one_commit_once(tmp_path):
    store = Store(tmp_path / "data")
    sid = store.link_scene("t", DEMO)
    b = store.create_batch("t", sid, arc_configs(4), {"method": "focused"})
    got = store.put_outcomes(b, [(0, {"result": {"method": "focused", "x": 1.5}}),
                                 (2, {"error": {"code": "invalid_rig", "message": "no camera"}})])
    assert got == [True, True]
    assert store.put_outcomes(b, [(0, {"result": {"method": "focused", "x": 9.0}}),  # already stored: kept
                                  (2, {"result": {"method": "focused"}}),  # already an error: kept
                                  (1, {"result": {"method": "focused", "x": 2.5}})]) == [False, False, True]
    assert store.put_error(b, 1, "worker_crashed", "late") is False
    lines = store.results("t", b)
    assert lines[:3] == [{"index": 0, "method": "focused", "x": 1.5}, {"index": 1, "method": "focused", "x": 2.5},
                         {"index": 2, "error": {"code": "invalid_rig", "message": "no camera"}}]
    assert store.pending_indices(b) == [3]
    with pytest.raises(IndexError):
        store.put_outcomes(b, [(3, {"result": {}}), (4, {"result": {}})])
    assert store.pending_indices(b) == [3]  # nothing of a refused task is stored
    store.close()


def _kernel_threads() -> int:
    import drjit as dr

    return dr.thread_count()


def test_pool_workers_run_dr_jit_on_their_share_of_the_cores():
    """Two workers on N cores: each runs Dr.Jit's kernels on N // 2 threads (its default is every core in every
    process: two workers ran twice as many spinning kernel threads as cores), asked of a real worker."""
    from shadowopt.service.job_backends import LocalBackend

    be = LocalBackend(2)
    try:
        got = be.ensure_pool().submit(_kernel_threads).result(timeout=120)
    finally:
        be.close()
    assert got == max(1, (os.cpu_count() or 1) // 2)
