"""Durability around the edges (issue 9): an upload is recorded in one transaction with its info after its
file was written and checked, so a SIGKILL at any moment leaves either nothing or a complete scene, and a
restarted server sweeps what an interrupted upload left; /healthz checks the database and a damaged one is
a clean 503 everywhere. The Store on a real SQLite file, the rest on a real server killed with SIGKILL."""
from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import sqlite3
import subprocess
import sys
import threading
import time
from pathlib import Path

import httpx
import pytest
from serverkit import auth, launch, running, stop, upload, wait_ready

from shadowopt.service import hostile_corpus as H
from shadowopt.service.store import Store, scene_id_for
from shadowopt.service.store_db import tenant_dir_name

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


def _killed_mid_upload(data_dir: Path) -> Path:
    """A real process opens the store, writes an upload (file in place, no row: its load would run now) and a
    temporary file, then is killed with SIGKILL: what a server killed mid-upload leaves. The upload's path."""
    script = ("import os, signal, sys\n"
              "from shadowopt.service.store import Store\n"
              "s = Store(sys.argv[1])\n"
              "sid, path, _ = s.write_upload('dave', b'#usda 1.0\\n#killed\\n', 'k.usda')\n"
              "(path.parent / ('.k.usda.' + 'ab' * 16 + '.tmp')).write_bytes(b'half')\n"
              "print(path, flush=True)\n"
              "os.kill(os.getpid(), signal.SIGKILL)\n")
    proc = subprocess.run([sys.executable, "-c", script, str(data_dir)], capture_output=True, text=True, timeout=60)
    assert proc.returncode == -signal.SIGKILL, proc.stderr
    return Path(proc.stdout.strip())


def _old_style_row(store: Store, tenant: str, data: bytes, name: str, age_s: float = 0.0) -> Path:
    """A row without info and its file, as uploads were stored before they were recorded with their info."""
    sid = scene_id_for(data, name)
    path = store.scene_folder(tenant, sid) / name
    path.parent.mkdir(parents=True)
    path.write_bytes(data)
    with sqlite3.connect(store.db_path) as c:
        c.execute("INSERT INTO scenes (tenant, scene_id, filename, bytes, path, source, created_at) "
                  "VALUES (?, ?, ?, ?, ?, 'upload', ?)",
                  (tenant, sid, name, len(data), f"{tenant_dir_name(tenant)}/{sid}/{name}", time.time() - age_s))
    return path


def _age_file(path: Path, seconds: float) -> None:
    t = time.time() - seconds
    os.utime(path, (t, t))


@pytest.mark.server
def test_sweep_removes_what_a_killed_upload_left_and_keeps_every_recorded_scene(tmp_path):
    d = tmp_path / "data"
    store = Store(d)
    data = DEMO.read_bytes()
    sid, path, _ = store.write_upload("alice", data, "demo_scene.usda")
    store.register_upload("alice", sid, path, len(data), {"triangles": 2442})  # complete: kept
    killed = _killed_mid_upload(d)  # its flock died with it: what it left goes at once
    assert killed.is_file() and len(list(killed.parent.glob(".*.tmp"))) == 1
    old_path = _old_style_row(store, "bob", b"#usda 1.0\n#2\n", "b.usda")
    tmp = path.parent / f".demo_scene.usda.{'0' * 32}.tmp"  # a temporary file a kill interrupted
    tmp.write_bytes(data[:100])
    stray = path.parent / "other-name.usda"  # the same bytes under a name no row has
    stray.write_bytes(data)
    gone_sid, gone_path, _ = store.write_upload("carol", b"#usda 1.0\n#3\n", "c.usda")
    store.register_upload("carol", gone_sid, gone_path, 13, {"triangles": 0})
    gone_path.unlink()  # a recorded scene whose file is gone (a restore without it, say): never dropped
    store.close()
    store = Store(d)  # the restarted server
    removed = store.sweep_partial_uploads()
    assert removed["rows"] == [["bob", scene_id_for(b"#usda 1.0\n#2\n", "b.usda")]]
    assert removed["missing"] == [["carol", gone_sid]]
    assert not killed.exists() and not killed.parent.exists() and not old_path.exists()
    assert not tmp.exists() and not stray.exists() and path.read_bytes() == data
    assert [s["scene_id"] for s in store.list_scenes("alice")] == [sid]
    assert store.list_scenes("bob") == [] and [s["scene_id"] for s in store.list_scenes("carol")] == [gone_sid]
    assert _stored_files(d) == [path]
    again = store.sweep_partial_uploads()
    assert (again["rows"], again["files"]) == ([], [])  # nothing left to sweep
    assert list((d / ".locks").glob("*.lock")) == [Path(store._lock_file.name)]  # the dead one's lock went
    store.close()


def test_sweep_spares_a_live_servers_uploads_in_progress_and_removes_stale_leftovers(tmp_path):
    """issue 9 review 1: two servers on one data directory deleted each other's uploads in progress. While
    another store holds the directory, only leftovers older than the grace period go."""
    d = tmp_path / "data"
    live = Store(d)  # another server, uploading right now
    data = DEMO.read_bytes()
    sid, path, _ = live.write_upload("alice", data, "demo_scene.usda")  # loading: not recorded yet
    young_tmp = path.parent / f".x.usda.{'1' * 32}.tmp"
    young_tmp.write_bytes(b"being written")
    stale_tmp = path.parent / f".y.usda.{'2' * 32}.tmp"
    stale_tmp.write_bytes(b"left by a kill long ago")
    _age_file(stale_tmp, 2 * 3600)
    young_row = _old_style_row(live, "bob", b"#usda 1.0\n#young\n", "young.usda")
    stale_row = _old_style_row(live, "bob", b"#usda 1.0\n#stale\n", "stale.usda", age_s=2 * 3600)
    _age_file(stale_row, 2 * 3600)
    restarted = Store(d)
    removed = restarted.sweep_partial_uploads()
    assert path.read_bytes() == data and young_tmp.exists() and young_row.exists()
    assert removed["rows"] == [["bob", scene_id_for(b"#usda 1.0\n#stale\n", "stale.usda")]]
    assert not stale_tmp.exists() and not stale_row.exists()
    assert restarted.other_live_stores() == 1
    assert live.register_upload("alice", sid, path, len(data), {"triangles": 2442})  # the upload completes
    assert restarted.scene_path("alice", sid).read_bytes() == data
    live.close()
    restarted.close()


def test_a_restart_from_another_working_directory_keeps_every_scene(tmp_path, monkeypatch):
    """issue 9 review 1: with the default data_dir "data" the stored path was relative to the working
    directory, and a server started elsewhere swept every upload as partial."""
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    data = DEMO.read_bytes()
    monkeypatch.chdir(tmp_path / "a")
    first = Store("data")
    sid, path, _ = first.write_upload("alice", data, "demo_scene.usda")
    assert first.register_upload("alice", sid, path, len(data), {"triangles": 2442})
    first.close()
    monkeypatch.chdir(tmp_path / "b")
    for opened in (tmp_path / "a" / "data", Path("../a/data")):
        store = Store(opened)
        removed = store.sweep_partial_uploads()
        assert [s["scene_id"] for s in store.list_scenes("alice")] == [sid]
        assert store.scene_path("alice", sid).read_bytes() == data
        assert store.scene_record("alice", sid)["info"] == {"triangles": 2442}
        assert (removed["rows"], removed["files"], removed["missing"]) == ([], [], [])
        store.close()


def test_a_moved_data_directory_keeps_its_scenes(tmp_path):
    data = DEMO.read_bytes()
    store = Store(tmp_path / "old" / "data")
    sid, path, _ = store.write_upload("alice", data, "demo_scene.usda")
    store.register_upload("alice", sid, path, len(data), {"triangles": 2442})
    store.close()
    shutil.move(tmp_path / "old", tmp_path / "restored")
    store = Store(tmp_path / "restored" / "data")
    removed = store.sweep_partial_uploads()
    assert store.scene_path("alice", sid) is not None and store.scene_path("alice", sid).read_bytes() == data
    assert (removed["rows"], removed["files"], removed["missing"]) == ([], [], [])
    assert store.scene_path("alice", sid) == tmp_path / "restored" / "data" / "scenes" / path.relative_to(
        tmp_path / "old" / "data" / "scenes")
    assert store.scene_path("alice", sid).read_bytes() == data
    store.close()


def test_rows_with_absolute_or_working_directory_paths_are_migrated_on_open(tmp_path, monkeypatch):
    """A database written before paths were relative: absolute paths (one of a directory since moved) and a
    path relative to the old working directory become relative to the scenes folder; nothing is lost."""
    monkeypatch.chdir(tmp_path)
    store = Store("data")
    ids = {}
    for tenant in ("alice", "bob", "carol"):
        body = f"#usda 1.0\n#{tenant}\n".encode()
        sid, path, _ = store.write_upload(tenant, body, f"{tenant}.usda")
        store.register_upload(tenant, sid, path, len(body), {"triangles": 1})
        ids[tenant] = (sid, path, body)
    store.close()
    old = {"alice": str(tmp_path / "data" / "scenes" / ids["alice"][1].relative_to(tmp_path / "data" / "scenes")),
           "bob": f"data/scenes/{tenant_dir_name('bob')}/{ids['bob'][0]}/bob.usda",  # relative to the old cwd
           "carol": f"/somewhere/else/data/scenes/{tenant_dir_name('carol')}/{ids['carol'][0]}/carol.usda"}
    with sqlite3.connect(tmp_path / "data" / "shadowopt.db") as c:
        for tenant, p in old.items():
            c.execute("UPDATE scenes SET path = ? WHERE tenant = ?", (p, tenant))
        c.execute("PRAGMA user_version = 0")
    store = Store(tmp_path / "data")  # opened the new way, from the same directory (bob's path resolves)
    with sqlite3.connect(tmp_path / "data" / "shadowopt.db") as c:
        stored = dict(c.execute("SELECT tenant, path FROM scenes").fetchall())
    for tenant, (sid, _, body) in ids.items():
        assert stored[tenant] == f"{tenant_dir_name(tenant)}/{sid}/{tenant}.usda"
        assert store.scene_path(tenant, sid).read_bytes() == body
    store.close()
    monkeypatch.chdir(tmp_path / "data")  # and from elsewhere afterwards
    store = Store(".")
    assert all(store.scene_path(t, sid).read_bytes() == body for t, (sid, _, body) in ids.items())
    assert store.sweep_partial_uploads()["rows"] == []
    store.close()


def test_a_failed_upload_never_removes_the_file_of_a_concurrent_successful_one(tmp_path):
    """issue 9 review 1, item 5: two requests upload the same bytes; one's load fails (discard) before the
    other records it (register). The recorded scene keeps its file; when both fail, the file goes."""
    store = Store(tmp_path / "data")
    data = DEMO.read_bytes()
    sid, path_a, wrote_a = store.write_upload("alice", data, "demo_scene.usda")
    _, path_b, wrote_b = store.write_upload("alice", data, "demo_scene.usda")
    assert path_a == path_b and (wrote_a, wrote_b) == (True, False)
    store.discard_upload("alice", sid, path_a)  # A's load failed (a timeout, say)
    assert path_b.is_file()  # B is still loading it
    assert store.register_upload("alice", sid, path_b, len(data), {"triangles": 2442})
    assert store.scene_path("alice", sid).read_bytes() == data
    # both fail: the last to let go removes the file and its folder
    sid2, p1, _ = store.write_upload("bob", data, "demo_scene.usda")
    store.write_upload("bob", data, "demo_scene.usda")
    store.discard_upload("bob", sid2, p1)
    assert p1.is_file()
    store.discard_upload("bob", sid2, p1)
    assert not p1.parent.exists()
    store.close()


def test_threads_uploading_the_same_bytes_where_one_fails_keep_the_recorded_file(tmp_path):
    store = Store(tmp_path / "data")
    data = DEMO.read_bytes()
    for k in range(40):
        tenant = f"t{k}"
        go = threading.Barrier(2)
        sid = []

        def upload(succeeds: bool, tenant=tenant, go=go):
            s, path, _ = store.write_upload(tenant, data, "demo_scene.usda")
            sid.append(s)
            go.wait()
            if succeeds:
                if not store.register_upload(tenant, s, path, len(data), {"triangles": 2442}):
                    store.discard_upload(tenant, s, path)
            else:
                store.discard_upload(tenant, s, path)

        threads = [threading.Thread(target=upload, args=(ok,)) for ok in (k % 2 == 0, k % 2 == 1)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        path = store.scene_path(tenant, sid[0])
        assert path is not None and path.read_bytes() == data, k
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


@pytest.mark.server
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


@pytest.mark.server
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
