"""Fair share by time between a long path job and another tenant's small batch, on the batch runner's real
worker pool (issue 27, item 3: one tenant's `method: path` job over an animated stage held a worker for a
48-frame task, 823 s, while another tenant's batch waited). A path over moving geometry loads the stage at
each frame's time code: its frames are now one task each and a turn ends after TURN_S seconds, so the small
batch finishes while the path is still running."""
from __future__ import annotations

import time
from pathlib import Path

import pytest

from shadowopt.api.cli import validate_rig
from shadowopt.service import job_runner
from shadowopt.service.job_kinds import kind_of
from shadowopt.service.job_runner import BatchRunner
from shadowopt.service.store import Store
from storekit import add_upload

REPO = Path(__file__).resolve().parents[1]
DEMO = REPO / "configs" / "demo_scene.usda"
TINY = {"camera": {"usd_path": "/World/Camera", "resolution": [160, 90]}, "lights": [{"usd_path": "/World/Sun"}],
        "shadow": {"resolution": [256, 256]}, "coarse_long_side": 48}
FRAMES = 16
MOVING = """#usda 1.0
(
    upAxis = "Y"
    metersPerUnit = 1
    startTimeCode = 0
    endTimeCode = %(end)d
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
        double3 xformOp:translate = (0, 2, 10)
        uniform token[] xformOpOrder = ["xformOp:translate"]
    }
    def Cube "Car"
    {
        double size = 1
        double3 xformOp:translate.timeSamples = {0: (-3, 0.5, 0), %(end)d: (3, 0.5, 0)}
        uniform token[] xformOpOrder = ["xformOp:translate"]
    }
    def DistantLight "Sun"
    {
        float3 xformOp:rotateXYZ = (-60, 20, 0)
        uniform token[] xformOpOrder = ["xformOp:rotateXYZ"]
    }
}
"""
RIG = {"camera": {"usd_path": "/World/Cam", "resolution": [96, 54]}, "lights": [{"usd_path": "/World/Sun"}],
       "shadow": {"resolution": [128, 128]}, "coarse_long_side": 32}
PATH_SETTINGS = {"method": "focused", "whole_path": True, "path": True}


def moving_frames(n: int) -> list[dict]:
    return [{"rig": validate_rig(RIG), "frame": k, "time": float(k), "scene_time": float(k)} for k in range(n)]


def test_a_path_over_moving_geometry_runs_a_frame_per_task():
    items = list(enumerate(moving_frames(5)))
    tasks = kind_of(PATH_SETTINGS).tasks(None, "b", items, PATH_SETTINGS, 2, None, 5)
    assert [[i for i, _ in g] for g in tasks.groups] == [[0], [1], [2], [3], [4]]


def test_turns_end_after_a_slice_or_turn_seconds():
    assert not job_runner.turn_over(0, 0.0)
    assert job_runner.turn_over(job_runner.SLICE, 0.0) and job_runner.turn_over(1, job_runner.TURN_S)


@pytest.mark.server
@pytest.mark.slow
def test_a_small_batch_finishes_while_a_long_path_over_moving_geometry_runs(tmp_path, monkeypatch):
    monkeypatch.setattr(job_runner, "TURN_S", 1.0)  # the mechanism, at the scale of a test
    store = Store(tmp_path / "data")
    runner = BatchRunner(store, backend="local", workers=1)
    try:
        sid, _ = add_upload(store, "alice", (MOVING % {"end": FRAMES}).encode(), "moving.usda")
        path = store.create_batch("alice", sid, moving_frames(FRAMES), PATH_SETTINGS)
        runner.submit("alice", path)
        deadline = time.monotonic() + 180
        while store.batch("alice", path)["done"] < 1:  # the path is under way
            assert time.monotonic() < deadline
            time.sleep(0.05)
        bob_sid, _ = add_upload(store, "bob", DEMO.read_bytes(), "demo_scene.usda")
        small = store.create_batch("bob", bob_sid, [{"rig": validate_rig(TINY)}], {"method": "focused"})
        runner.submit("bob", small)
        assert runner.wait(small, timeout=180) == "done"
        then = store.batch("alice", path)
        assert then["state"] == "running" and then["done"] < FRAMES, then  # bob did not wait for the whole path
        assert runner.wait(path, timeout=300) == "done"
        assert [r["frame"] for r in store.results("alice", path)] == list(range(FRAMES))
    finally:
        runner.shutdown()
        store.close()
