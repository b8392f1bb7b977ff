"""Durability around the edges (issue 9): an upload is recorded in one transaction with its info after its
file was written and checked, so a SIGKILL at any moment leaves either nothing or a complete scene, and a
restarted server sweeps what an interrupted upload left; /healthz checks the database and a damaged one is
a clean 503 everywhere. The Store on a real SQLite file, the rest on a real server killed with SIGKILL."""
from __future__ import annotations

import contextlib
import json
import os
import signal
import threading
import time
from pathlib import Path

import httpx
import pytest
from serverkit import auth, launch, running, stop, upload, wait_ready

from shadowopt.service import hostile_corpus as H
from shadowopt.service.store import Store, tenant_dir_name

DEMO = Path(__file__).resolve().parents[1] / "configs" / "demo_scene.usda"


# --- the Store ----------------------------------------------------------------------------------------

def test_an_upload_is_invisible_until_recorded_with_its_info(tmp_path):
    store = Store(tmp_path / "data")
    data = DEMO.read_bytes()
    sid, path, wrote = store.write_upload("alice", data, "demo_scene.usda")
    assert wrote and path.read_bytes() == data and not list(path.parent.glob("*.tmp"))
    assert store.scene_record("alice", sid) is None and store.list_scenes("alice") == []  # written, not recorded
    assert store.write_upload("alice", data, "demo_scene.usda")[2] is False  # the same file: left as is
    assert store.register_upload("alice", sid, path, len(data), {"triangles": 2442}) is True
    rec = store.scene_record("alice", sid)
    assert rec["info"] == {"triangles": 2442} and rec["bytes"] == len(data)  # the row came with its info
    assert store.register_upload("alice", sid, path, len(data), {"triangles": 1}) is False  # never overwritten
    store.discard_upload("alice", sid, path)  # a recorded file is never discarded
    assert path.is_file() and store.tenant_stored_bytes("alice") == len(data) and store.tenant_stored_bytes("bob") == 0
    # a failed upload's file goes, with its folder
    sid2, path2, _ = store.write_upload("alice", b"#usda 1.0\n", "bad.usda")
    store.discard_upload("alice", sid2, path2)
    assert not path2.parent.exists()
    store.close()


def test_sweep_removes_every_kind_of_partial_upload_and_keeps_complete_scenes(tmp_path):
    store = Store(tmp_path / "data")
    data = DEMO.read_bytes()
    sid, path, _ = store.write_upload("alice", data, "demo_scene.usda")
    store.register_upload("alice", sid, path, len(data), {"triangles": 2442})  # complete: kept
    _, unrecorded, _ = store.write_upload("alice", b"#usda 1.0\n#1\n", "a.usda")  # a file without a row
    old_sid, _ = store.put_scene("bob", b"#usda 1.0\n#2\n", "b.usda")  # a row without info (the old way)
    old_path = store.scene_path("bob", old_sid)
    tmp = path.parent / ".demo_scene.usda.0123.tmp"  # a temporary file a kill interrupted
    tmp.write_bytes(data[:100])
    stray = path.parent / "other-name.usda"  # the same bytes under a name no row has
    stray.write_bytes(data)
    gone_sid, gone_path, _ = store.write_upload("carol", b"#usda 1.0\n#3\n", "c.usda")
    store.register_upload("carol", gone_sid, gone_path, 13, {"triangles": 0})
    gone_path.unlink()  # a row whose file is gone
    removed = store.sweep_partial_uploads()
    assert sorted(map(tuple, removed["rows"])) == sorted([("bob", old_sid), ("carol", gone_sid)])
    assert not unrecorded.exists() and not unrecorded.parent.exists() and not old_path.exists()
    assert not tmp.exists() and not stray.exists() and path.read_bytes() == data
    assert [s["scene_id"] for s in store.list_scenes("alice")] == [sid]
    assert store.list_scenes("bob") == [] and store.list_scenes("carol") == []
    files = sorted(p for p in (tmp_path / "data" / "scenes").rglob("*") if p.is_file())
    assert files == [path]
    assert store.sweep_partial_uploads() == {"rows": [], "files": []}  # nothing left to sweep
    store.close()


def test_per_tenant_pending_configurations(tmp_path):
    store = Store(tmp_path / "data")
    a = store.create_batch("alice", "s", [{"rig": {}}] * 5, {})
    store.create_batch("bob", "s", [{"rig": {}}] * 3, {})
    store.put_result(a, 0, {"x": 1})
    store.put_error(a, 1, "e", "m")
    assert (store.pending_configurations("alice"), store.pending_configurations("bob"),
            store.pending_configurations()) == (3, 3, 6)
    store.set_state(a, "cancelled")
    assert store.pending_configurations("alice") == 0 and store.pending_configurations() == 3
    store.close()


# --- a real server --------------------------------------------------------------------------------

def _stored_files(data_dir: Path) -> list[Path]:
    return sorted(p for p in (data_dir / "scenes").rglob("*") if p.is_file())


@pytest.mark.slow
def test_sigkill_during_an_upload_leaves_nothing_or_a_complete_scene(tmp_path):
    """The server is killed (SIGKILL) while an upload is being loaded (its file is on disk, the load runs),
    then once more a moment later; after each restart on the same data directory the scene is either
    absent (404, not listed) or complete (triangles set), and no file is left that no scene owns."""
    data_dir = tmp_path / "data"
    text = H.instanced_spheres(300).encode()  # a valid scene that takes a moment to load
    seen = []
    for delay in (0.0, 0.8):
        server = launch(data_dir, new_session=True)
        try:
            wait_ready(server)
            before = set(_stored_files(data_dir))
            sender = threading.Thread(target=lambda: seen.append(_try_upload(server.base, text)), daemon=True)
            sender.start()
            deadline = time.monotonic() + 60
            while not (set(_stored_files(data_dir)) - before):  # the upload's file is written: the load starts
                assert time.monotonic() < deadline and sender.is_alive(), ("the upload never reached the disk", seen)
                time.sleep(0.002)
            time.sleep(delay)
            os.kill(server.proc.pid, signal.SIGKILL)
            server.proc.wait(timeout=30)
            sender.join(timeout=60)
        finally:
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(server.proc.pid, signal.SIGKILL)  # a loader child, should it outlive the server
        server = launch(data_dir, new_session=True)
        try:
            wait_ready(server)
            listed = httpx.get(server.base + "/v1/scenes", headers=auth("alice")).json()["scenes"]
            assert all(s["triangles"] is not None for s in listed), listed
            for s in listed:
                info = httpx.get(f"{server.base}/v1/scenes/{s['scene_id']}", headers=auth("alice")).json()
                assert info["triangles"] > 0 and info["bounds"], info
            files = _stored_files(data_dir)
            assert len(files) == len(listed), (files, listed)  # no stray or temporary file
            assert all(f.parent.name in {s["scene_id"] for s in listed} for f in files)
            assert tenant_dir_name("alice") in {f.parent.parent.name for f in files} or not files
            print(f"\nkilled {delay:.1f} s after the file was written: {len(listed)} scene(s) after the restart")
        finally:
            stop(server)
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(server.proc.pid, signal.SIGKILL)
    assert all(code in (None, 201) for code in seen), seen  # the killed uploads got no answer (or were done)


def _try_upload(base: str, text: bytes) -> int | None:
    try:
        return httpx.post(f"{base}/v1/scenes", params={"filename": "spheres.usda"}, content=text,
                          headers=auth("alice"), timeout=120).status_code
    except httpx.TransportError:
        return None


def test_a_damaged_database_is_a_clean_503_on_health_listing_and_upload(tmp_path):
    """issue 9: /healthz said ok on a corrupt database while /v1/scenes and uploads answered 500. With its
    header overwritten under a running server: /healthz 503 database_unavailable naming the reason, and the
    routes that read or write it 503 JSON with the same code, no traceback, no path."""
    with running(tmp_path / "data") as server:
        assert upload(server.base, "alice").status_code == 201
        assert httpx.get(server.base + "/healthz").status_code == 200
        with open(server.data_dir / "shadowopt.db", "r+b") as f:
            f.write(b"this is not a database header" * 4)
        r = httpx.get(server.base + "/healthz")
        assert r.status_code == 503 and int(r.headers["retry-after"]) >= 1, r.text
        body = r.json()
        assert body["error"]["code"] == "database_unavailable" and "not a database" in body["error"]["message"]
        assert body["status"] == "unavailable"
        for r in (httpx.get(server.base + "/v1/scenes", headers=auth("alice")),
                  upload(server.base, "bob", name="other.usda"),
                  httpx.get(server.base + "/v1/batches/0123456789abcdef", headers=auth("alice"))):
            assert r.status_code == 503, r.text
            err = r.json()["error"]
            assert err["code"] == "database_unavailable" and "Traceback" not in r.text
            assert str(server.data_dir) not in r.text
        assert httpx.get(server.base + "/metrics").status_code == 200  # still scraped
        lines = [json.loads(l) for l in server.log().splitlines() if l.startswith("{")]
        assert any(e.get("msg") == "database error" for e in lines)  # the operator sees it in the log
