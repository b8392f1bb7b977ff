"""The Store: scene files and one SQLite database in a data directory (a real file in tmp_path)."""
from __future__ import annotations

import json
import sqlite3
import threading
import time
from pathlib import Path

import pytest

from storekit import add_upload

from shadowopt.service.store import Store
from shadowopt.service.store_db import tenant_dir_name

DEMO = Path(__file__).resolve().parents[1] / "configs" / "demo_scene.usda"


@pytest.fixture
def store(tmp_path):
    s = Store(tmp_path / "data")
    yield s
    s.close()


def _age(store: Store, table: str, days: float) -> None:
    """Make every row of `table` look `days` old (as if written then)."""
    with sqlite3.connect(store.db_path) as c:
        col = "updated_at" if table == "batches" else "created_at"
        c.execute(f"UPDATE {table} SET {col} = {col} - ?", (days * 86400.0,))


def test_scene_round_trip_on_disk_and_in_the_database(store, tmp_path):
    data = DEMO.read_bytes()
    sid, created = add_upload(store, "alice", data, "demo_scene.usda", {"triangles": 2442})
    assert created and len(sid) == 16 and all(c in "0123456789abcdef" for c in sid)
    path = store.scene_path("alice", sid)
    assert path == tmp_path / "data" / "scenes" / tenant_dir_name("alice") / sid / "demo_scene.usda"
    assert path.read_bytes() == data
    rec = store.scene_record("alice", sid)
    assert rec["scene_id"] == sid and rec["filename"] == "demo_scene.usda" and rec["bytes"] == len(data)
    assert rec["info"] == {"triangles": 2442} and rec["created_at"].endswith("Z")
    assert add_upload(store, "alice", data, "renamed.usda") == (sid, False)  # same bytes: same id, no new record
    assert sorted(p.name for p in path.parent.iterdir()) == ["demo_scene.usda"]  # and no second file
    assert [s["scene_id"] for s in store.list_scenes("alice")] == [sid]
    # Same bytes with another extension are another scene (the loader reads the format from it).
    other, _ = add_upload(store, "alice", data, "demo_scene.usd")
    assert other != sid
    assert store.delete_scene("alice", sid) and not path.exists()
    assert store.scene_record("alice", sid) is None and store.delete_scene("alice", sid) is False


def test_a_tenant_never_sees_another_tenants_scene_or_batch(store):
    data = DEMO.read_bytes()
    sid, _ = add_upload(store, "alice", data, "demo_scene.usda")
    assert store.scene_record("bob", sid) is None and store.scene_path("bob", sid) is None
    assert store.list_scenes("bob") == [] and store.delete_scene("bob", sid) is False
    # Bob uploading the same bytes gets his own record and file; deleting it leaves Alice's.
    sid_b, created = add_upload(store, "bob", data, "demo_scene.usda")
    assert created and sid_b == sid and store.scene_path("bob", sid) != store.scene_path("alice", sid)
    assert store.delete_scene("bob", sid)
    assert store.scene_path("alice", sid).read_bytes() == data
    b = store.create_batch("alice", sid, [{"rig": {}}], {})
    store.put_result(b, 0, {"x": 1})
    assert store.batch("bob", b) is None and store.results("bob", b) == []
    assert store.cancel_batch("bob", b) is False and store.batch("alice", b)["state"] == "queued"


def test_upload_names_cannot_leave_the_scene_folder(store):
    sid, _ = add_upload(store, "t", b"#usda 1.0\n", "../../../etc/pass wd.usda")
    path = store.scene_path("t", sid)
    assert path.parent == store.scenes_dir / tenant_dir_name("t") / sid
    assert path.name == "pass_wd.usda"
    sid2, _ = add_upload(store, "t", b"#usda 1.0\n#x\n", ".hidden.USDA")
    assert store.scene_path("t", sid2).name == "hidden.usda"


def test_put_result_is_idempotent_by_index_and_never_overwrites(store):
    b = store.create_batch("t", "s", [{"rig": {"k": i}} for i in range(4)], {"method": "focused"})
    assert store.configurations(b) == [{"rig": {"k": i}} for i in range(4)]
    assert store.put_result(b, 2, {"v": "first"}) is True
    assert store.put_result(b, 2, {"v": "second"}) is False
    assert store.put_error(b, 2, "x", "late error") is False  # a result stays the outcome
    assert store.put_error(b, 1, "invalid_rig", "camera.usd_path: no camera") is True
    assert store.put_result(b, 1, {"v": "late"}) is False
    with pytest.raises(IndexError):
        store.put_result(b, 4, {})
    assert store.pending_indices(b) == [0, 3]
    st = store.batch("t", b)
    assert (st["done"], st["failed"], st["total"], st["state"]) == (1, 1, 4, "queued")
    assert st["errors"] == [{"index": 1, "code": "invalid_rig", "message": "camera.usd_path: no camera"}]
    assert st["settings"] == {"method": "focused"}
    with sqlite3.connect(store.db_path) as c:
        assert c.execute("SELECT COUNT(*) FROM results WHERE batch_id = ?", (b,)).fetchone()[0] == 1
        assert json.loads(c.execute("SELECT result FROM results WHERE idx = 2").fetchone()[0]) == {"v": "first"}


def test_results_come_in_index_order_and_resume_at_an_offset(store):
    b = store.create_batch("t", "s", [{"rig": {}}] * 5, {})
    store.set_state(b, "running")
    for i in (4, 0, 1, 3):
        store.put_result(b, i, {"v": i})
    # While running, the lines stop before the first unfinished index (2), so offset=2 later misses nothing.
    assert [r["index"] for r in store.results("t", b)] == [0, 1]
    store.put_error(b, 2, "invalid_rig", "bad")
    lines = store.results("t", b)
    assert [r["index"] for r in lines] == [0, 1, 2, 3, 4]
    assert lines[2] == {"index": 2, "error": {"code": "invalid_rig", "message": "bad"}}
    assert lines[3] == {"index": 3, "v": 3}
    assert [r["index"] for r in store.results("t", b, offset=3)] == [3, 4]
    assert [r["index"] for r in store.results("t", b, offset=1, limit=2)] == [1, 2]
    assert store.finish_batch(b) == "done"


def test_batch_states_and_what_resume_finds(store):
    a = store.create_batch("t", "s", [{"rig": {}}] * 2, {})
    b = store.create_batch("t", "s", [{"rig": {}}] * 2, {})
    c = store.create_batch("u", "s", [{"rig": {}}], {})
    assert store.unfinished_batches() == [("t", a), ("t", b), ("u", c)]
    store.set_state(a, "running")
    assert store.cancel_batch("t", b) and store.batch("t", b)["state"] == "cancelled"
    assert store.set_state(b, "running", only_from=("queued", "running")) is False  # cancelled stays cancelled
    for i in range(2):
        store.put_error(a, i, "invalid_rig", "bad")
    assert store.finish_batch(a) == "failed"  # nothing succeeded
    assert store.cancel_batch("t", a) and store.batch("t", a)["state"] == "failed"  # finished stays finished
    assert store.unfinished_batches() == [("u", c)]
    with pytest.raises(ValueError, match="state"):
        store.set_state(c, "paused")


def test_pending_configurations_count_what_unfinished_batches_still_owe(tmp_path):
    st = Store(tmp_path / "d")
    a = st.create_batch("t", "s", [{"rig": {}}] * 3, {})
    b = st.create_batch("u", "s", [{"rig": {}}] * 2, {})
    assert st.pending_configurations() == 5
    st.put_result(a, 0, {"x": 1})
    st.put_error(a, 1, "invalid_rig", "bad")
    assert st.pending_configurations() == 3  # a owes 1, b owes 2
    assert st.cancel_batch("u", b)
    assert st.pending_configurations() == 1  # a cancelled batch owes nothing
    st.put_result(a, 2, {"x": 3})
    st.finish_batch(a)
    assert st.pending_configurations() == 0
    st.close()


def test_the_database_survives_reopening_and_uses_wal(tmp_path):
    s1 = Store(tmp_path / "d")
    sid, _ = add_upload(s1, "t", DEMO.read_bytes(), "demo_scene.usda")
    b = s1.create_batch("t", sid, [{"rig": {"n": 1}}, {"rig": {"n": 2}}], {"method": "optimized"})
    s1.set_state(b, "running")
    s1.put_result(b, 0, {"v": 0})
    s1.close()
    s2 = Store(tmp_path / "d")
    assert s2.scene_record("t", sid)["bytes"] == DEMO.stat().st_size
    assert s2.unfinished_batches() == [("t", b)] and s2.pending_indices(b) == [1]
    assert s2.results("t", b) == [{"index": 0, "v": 0}]
    with sqlite3.connect(s2.db_path) as c:
        assert c.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    s2.close()


def test_concurrent_writers_from_threads_store_each_index_once(store):
    b = store.create_batch("t", "s", [{"rig": {}}] * 50, {})
    wins = []
    lock = threading.Lock()

    def writer(k):
        for i in range(50):
            if store.put_result(b, i, {"writer": k}):
                with lock:
                    wins.append(i)

    threads = [threading.Thread(target=writer, args=(k,)) for k in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert sorted(wins) == list(range(50))
    assert [r["index"] for r in store.results("t", b)] == list(range(50))


def test_retention_by_age_keeps_running_batches_and_their_scenes(tmp_path):
    s = Store(tmp_path / "d", retention_days=7)
    old_scene, _ = add_upload(s, "t", b"#usda 1.0\n#old\n", "old.usda")
    busy_scene, _ = add_upload(s, "t", b"#usda 1.0\n#busy\n", "busy.usda")
    done = s.create_batch("t", old_scene, [{"rig": {}}], {})
    s.put_result(done, 0, {"v": 1})
    s.finish_batch(done)
    running = s.create_batch("t", busy_scene, [{"rig": {}}], {})
    s.set_state(running, "running")
    _age(s, "batches", 10)
    _age(s, "scenes", 10)
    fresh, _ = add_upload(s, "t", b"#usda 1.0\n#fresh\n", "fresh.usda")
    removed = s.enforce_retention()
    assert removed["batches"] == [done] and removed["scenes"] == [["t", old_scene]]
    assert s.batch("t", done) is None and s.batch("t", running)["state"] == "running"
    assert s.scene_record("t", busy_scene) is not None and s.scene_record("t", fresh) is not None
    s.close()


def test_retention_by_size_drops_the_oldest_until_under_the_limit(tmp_path):
    s = Store(tmp_path / "d", max_bytes=None)
    ids = []
    for k in range(5):
        sid, _ = add_upload(s, "t", bytes([k]) * 200_000, f"s{k}.usdc")
        ids.append(sid)
        time.sleep(0.01)
    s.max_bytes = 450_000 + s.disk_bytes() - 5 * 200_000  # room for two scenes plus the database
    removed = s.enforce_retention()
    assert removed["scenes"] == [["t", i] for i in ids[:3]]
    assert [r["scene_id"] for r in s.list_scenes("t")] == ids[3:]
    assert s.disk_bytes() <= s.max_bytes
    s.close()


def test_a_size_limit_is_enforced_when_the_store_opens(tmp_path):
    s = Store(tmp_path / "d")
    ids = [add_upload(s, "t", bytes([k]) * 300_000, f"s{k}.usdc")[0] for k in range(3)]
    s.close()
    s = Store(tmp_path / "d", max_bytes=400_000)  # a server restarted with a tighter limit
    assert [r["scene_id"] for r in s.list_scenes("t")] == ids[2:]
    assert s.disk_bytes() <= 400_000
    s.close()


def test_dropping_old_batches_gives_the_database_space_back(tmp_path):
    s = Store(tmp_path / "d")
    old = s.create_batch("t", "s", [{"rig": {}}] * 400, {})
    for i in range(400):
        s.put_result(old, i, {"pad": "x" * 5000})
    s.finish_batch(old)
    new = s.create_batch("t", "s", [{"rig": {}}], {})
    s.put_result(new, 0, {"v": 1})
    s.finish_batch(new)
    assert s.disk_bytes() > 2_000_000
    s.max_bytes = 500_000
    assert s.enforce_retention()["batches"] == [old]
    assert s.disk_bytes() <= 500_000 and s.results("t", new) == [{"index": 0, "v": 1}]
    s.close()
