"""Persistence: a data directory with uploaded scene files and one SQLite database.

Layout: `<data_dir>/scenes/<tenant hash>/<scene_id>/<sanitised file name>`, `<data_dir>/shadowopt.db`
(WAL mode) and `<data_dir>/tmp/` (uploads' scratch folders while a zip is unpacked: Store.work_dir; swept at
start). Tables: scenes, batches, configurations, results, errors. An uploaded scene's row holds its
path relative to `<data_dir>/scenes` (`<tenant hash>/<scene_id>/<name>`), so the data directory can be opened
from any working directory, under any absolute path, or after it was moved or restored; rows written before
(absolute or working-directory-relative paths) are migrated when the store opens. Every write of a configuration's
outcome is `INSERT OR IGNORE` keyed by (batch_id, index): a result once stored is never overwritten or
duplicated. Each thread gets its own connection, so a Store is safe to share between server threads.
Times are stored as Unix seconds and returned as ISO 8601 UTC strings. The database itself (connections,
schema and migrations, transactions, the data directory's lock file) is service.store_db.Database.
"""
from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import math
import os
import re
import shutil
import sqlite3
import tempfile
import threading
import time
import uuid
from pathlib import Path

from .store_db import Database, tenant_dir_name

log = logging.getLogger("shadowopt.store")

STATES = ("queued", "running", "done", "failed", "cancelled")
UNFINISHED = ("queued", "running")
MAX_ERRORS_LISTED = 100
RETENTION_INTERVAL_S = 60.0  # automatic enforcement (on start, uploads, finished batches) at most this often
SWEEP_GRACE_S = 3600.0  # while another server uses the data directory, the sweep spares what is younger than this
_TMP_NAME = re.compile(r"^\..+\.[0-9a-f]{32}\.tmp$")  # write_upload's temporary files
_HEX16 = re.compile(r"^[0-9a-f]{16}$")
_STRIPES = 64  # per-(tenant, scene_id) upload locks, striped


def iso(t: float | None) -> str | None:
    return None if t is None else time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(t))


def scene_id_for(data: bytes | Path, filename: str) -> str:
    """First 16 hex digits of sha256 over the bytes (or a file's bytes, read in chunks) followed by the
    lower-case extension."""
    if isinstance(data, (bytes, bytearray, memoryview)):
        h = hashlib.sha256(data)
    else:
        h = hashlib.sha256()
        with open(data, "rb") as f:
            for chunk in iter(lambda: f.read(1 << 20), b""):
                h.update(chunk)
    h.update(Path(filename).suffix.lower().encode())
    return h.hexdigest()[:16]


def sanitise_filename(filename: str) -> str:
    """The basename with only [A-Za-z0-9._-] kept (others become `_`), no leading dots, extension lower-case."""
    base = os.path.basename(filename.replace("\\", "/")) or "scene"
    stem, ext = os.path.splitext(base)
    stem = re.sub(r"[^A-Za-z0-9._-]", "_", stem).lstrip(".")[:100] or "scene"
    ext = re.sub(r"[^A-Za-z0-9.]", "", ext.lower())[:10]
    return stem + ext


class Store(Database):
    """Scenes and batches of one data directory. See the module docstring for the layout."""

    def __init__(self, data_dir: str | Path, retention_days: float | None = None, max_bytes: int | None = None):
        self.retention_days = retention_days
        self.max_bytes = max_bytes
        self._last_retention = -math.inf
        self._retention_lock = threading.Lock()  # one retention pass at a time (writes and a server timer)
        # Uploads: write/register/discard/delete of one (tenant, scene_id) are serialised by a striped lock,
        # and the files that requests of this process are still loading are counted (never unlinked under them).
        self._stripes = [threading.RLock() for _ in range(_STRIPES)]
        self._inflight: dict[tuple[str, str, str], int] = {}
        self._own_tmp: set[str] = set()
        super().__init__(data_dir)  # the data directory, its database open (schema, migrations) and claimed
        self.auto_retention()

    def _row_path(self, row) -> Path:
        """The file of a scene row: uploads are relative to the scenes folder, linked files absolute."""
        p = Path(row["path"])
        return p if p.is_absolute() else self.scenes_dir / p

    # -- uploads, registered atomically ---------------------------------------------------------
    # An upload is written under a temporary name and renamed into its folder (never a partial file
    # there), loaded, and only then recorded, in one INSERT that carries its info. Until that INSERT the
    # file is invisible (no row); a SIGKILL at any point leaves either no row or a complete one, and
    # sweep_partial_uploads() (at server start) removes what an interrupted upload left behind.
    # Concurrent requests for the same bytes share one file: write_upload counts each request on it,
    # register_upload (when it records the row) and discard_upload release the request, and the file is
    # unlinked only by the last request to let go when no row holds it; all under the (tenant, scene_id)
    # lock, so a failed upload never removes the file of a concurrent one that succeeds.
    def scene_folder(self, tenant: str, scene_id: str) -> Path:
        return self.scenes_dir / tenant_dir_name(tenant) / scene_id

    def _stripe(self, tenant: str, scene_id: str) -> threading.RLock:
        return self._stripes[hash((tenant, scene_id)) % _STRIPES]

    def _release(self, tenant: str, scene_id: str, name: str) -> int:
        """One request less on a file (never below zero); how many are left. Caller holds the stripe."""
        k = (tenant, scene_id, name)
        left = self._inflight.get(k, 0) - 1
        if left > 0:
            self._inflight[k] = left
        else:
            self._inflight.pop(k, None)
        return max(left, 0)

    @contextlib.contextmanager
    def work_dir(self, prefix: str = "zip-"):
        """A scratch folder in `<data_dir>/tmp` (an upload's unpacking: never the system temp dir, which may be
        memory and is nobody's quota), removed on leaving; sweep_partial_uploads removes one a killed server
        left."""
        self.tmp_dir.mkdir(parents=True, exist_ok=True)
        path = Path(tempfile.mkdtemp(prefix=prefix, dir=self.tmp_dir))
        self._own_tmp.add(str(path))
        try:
            yield path
        finally:
            shutil.rmtree(path, ignore_errors=True)
            self._own_tmp.discard(str(path))

    def write_upload(self, tenant: str, data: bytes | Path, filename: str) -> tuple[str, Path, bool]:
        """Write an upload's bytes to their final path, not yet recorded: (scene_id, path, wrote). `data` is the
        bytes, or a file in this data directory (a package made from a zip in work_dir), which is moved, not
        read into memory. `wrote` is False when the same file is already there (same content hash and name),
        which is then left as is. The request counts on the file until register_upload records it or
        discard_upload lets it go."""
        scene_id = scene_id_for(data, filename)
        size = len(data) if isinstance(data, (bytes, bytearray, memoryview)) else os.path.getsize(data)
        folder = self.scene_folder(tenant, scene_id)
        path = folder / sanitise_filename(filename)
        with self._stripe(tenant, scene_id):
            wrote = False
            if not (path.is_file() and path.stat().st_size == size):
                folder.mkdir(parents=True, exist_ok=True)
                tmp = folder / f".{path.name}.{uuid.uuid4().hex}.tmp"
                self._own_tmp.add(str(tmp))
                try:
                    if isinstance(data, (bytes, bytearray, memoryview)):
                        with open(tmp, "wb") as f:
                            f.write(data)
                            f.flush()
                            os.fsync(f.fileno())
                    else:  # a file of this data directory: renamed (same file system), flushed first
                        with open(data, "rb+") as f:
                            os.fsync(f.fileno())
                        os.replace(data, tmp)
                    os.replace(tmp, path)
                except BaseException:
                    tmp.unlink(missing_ok=True)
                    raise
                finally:
                    self._own_tmp.discard(str(tmp))
                wrote = True
            k = (tenant, scene_id, path.name)
            self._inflight[k] = self._inflight.get(k, 0) + 1
        return scene_id, path, wrote

    def register_upload(self, tenant: str, scene_id: str, path: Path, nbytes: int, info: dict) -> bool:
        """Record a written and checked upload with its info in one transaction; False when it was
        recorded already (a concurrent upload of the same bytes won: call discard_upload then)."""
        path = Path(path)
        rel = self._relative(path)
        if rel is None:
            raise ValueError("register_upload: the file is not inside the store's scenes folder")
        with self._stripe(tenant, scene_id):
            if not path.is_file():
                raise FileNotFoundError(f"register_upload: the upload of scene {scene_id} has no file")
            (n,) = self._write([("INSERT OR IGNORE INTO scenes (tenant, scene_id, filename, bytes, path, source, "
                                 "created_at, info) VALUES (?, ?, ?, ?, ?, 'upload', ?, ?)",
                                 (tenant, scene_id, path.name, nbytes, rel, time.time(), json.dumps(info)))])
            if n == 1:
                self._release(tenant, scene_id, path.name)
        if n == 1:
            self.auto_retention()  # outside the stripe: retention takes stripes of the scenes it deletes
        return n == 1

    def discard_upload(self, tenant: str, scene_id: str, path: Path) -> None:
        """A request lets go of an upload's file that it did not record (its load failed, or another request
        recorded the same bytes first). The file is removed only when no other request of this store is
        still on it and no row holds it; a recorded file stays."""
        path = Path(path)
        with self._stripe(tenant, scene_id):
            if self._release(tenant, scene_id, path.name) > 0:
                return
            row = self._scene_row(tenant, scene_id)
            if row is not None and os.path.abspath(self._row_path(row)) == os.path.abspath(path):
                return
            path.unlink(missing_ok=True)
            with contextlib.suppress(OSError):
                path.parent.rmdir()  # only when empty: another name of the same bytes may be in there

    def tenant_stored_bytes(self, tenant: str) -> int:
        """Bytes of the uploaded files this tenant keeps."""
        return int(self._query("SELECT COALESCE(SUM(bytes), 0) FROM scenes WHERE tenant = ? AND source = 'upload'",
                               (tenant,))[0][0])

    def sweep_partial_uploads(self, grace_s: float = SWEEP_GRACE_S) -> dict:
        """Remove what interrupted uploads left, and nothing else. For a server's start.

        Removed: write_upload's temporary files; what work_dir holds in `<data_dir>/tmp` (a zip being unpacked);
        files in a scene folder that no row holds (written, never
        recorded: the upload was killed while loading); rows without info (from before uploads were
        recorded with their info) with their files. When no other Store holds the data directory (their
        .locks files, see other_live_stores) all of these belong to dead processes and go at once; while
        another server is alive only those older than `grace_s` go, so its uploads in progress survive.
        Never removed: a recorded scene whose file is missing (logged and listed under "missing": a data
        directory restored without its files must not lose its records), anything outside the
        <tenant hash>/<scene_id>/ layout, and this store's own uploads in progress.
        Returns {"rows": [[tenant, scene_id], ...], "files": [names], "missing": [[tenant, scene_id], ...]}."""
        removed = {"rows": [], "files": [], "missing": []}
        others = self.other_live_stores()
        min_age = grace_s if others else 0.0
        now = time.time()

        def old_enough(t: float) -> bool:
            return now - t >= min_age

        rows = self._query("SELECT tenant, scene_id, filename, path, info, created_at FROM scenes "
                           "WHERE source = 'upload'")
        keep = set()
        for r in rows:
            path = self._row_path(r)
            busy = any(k[:2] == (r["tenant"], r["scene_id"]) for k in self._inflight)
            if r["info"] is None and old_enough(r["created_at"]) and not busy:
                with self._stripe(r["tenant"], r["scene_id"]):
                    self._write([("DELETE FROM scenes WHERE tenant = ? AND scene_id = ? AND info IS NULL",
                                  (r["tenant"], r["scene_id"]))])
                removed["rows"].append([r["tenant"], r["scene_id"]])
                continue
            keep.add(os.path.abspath(path))
            if not path.is_file():
                removed["missing"].append([r["tenant"], r["scene_id"]])
        if removed["missing"]:
            log.warning("%d recorded scenes have no file (kept): %s", len(removed["missing"]),
                        ", ".join(sid for _, sid in removed["missing"][:10]))
        for tenant_dir in sorted(self.scenes_dir.iterdir()):
            if not (tenant_dir.is_dir() and _HEX16.match(tenant_dir.name)):
                continue
            for folder in sorted(tenant_dir.iterdir()):
                if not (folder.is_dir() and _HEX16.match(folder.name)):
                    continue
                for f in sorted(folder.iterdir()):
                    try:
                        st = f.lstat()
                    except OSError:
                        continue
                    if not f.is_file() or f.is_symlink() or not old_enough(st.st_mtime):
                        continue
                    if _TMP_NAME.match(f.name):
                        if str(f) in self._own_tmp:
                            continue
                    elif os.path.abspath(f) in keep or any(
                            k[2] == f.name and self.scene_folder(k[0], k[1]) == folder for k in self._inflight):
                        continue
                    f.unlink(missing_ok=True)
                    removed["files"].append(f"{folder.name}/{f.name}")
                with contextlib.suppress(OSError):
                    folder.rmdir()  # only when empty
            with contextlib.suppress(OSError):
                tenant_dir.rmdir()
        if self.tmp_dir.is_dir():  # unpacked zips (work_dir) of uploads a killed server left
            for d in sorted(self.tmp_dir.iterdir()):
                try:
                    st = d.lstat()
                except OSError:
                    continue
                if str(d) in self._own_tmp or not old_enough(st.st_mtime):
                    continue
                if d.is_dir() and not d.is_symlink():
                    shutil.rmtree(d, ignore_errors=True)
                else:
                    d.unlink(missing_ok=True)
                removed["files"].append(f"tmp/{d.name}")
        if removed["rows"] or removed["files"]:
            log.warning("swept %d partial upload records and %d stray files (%d other live stores)",
                        len(removed["rows"]), len(removed["files"]), others)
        return removed

    def link_scene(self, tenant: str, path: str | Path) -> str:
        """Record a scene file in place (not copied, loaded without the upload sandbox): for the CLI."""
        p = Path(path).resolve()
        data = p.read_bytes()
        scene_id = scene_id_for(data, p.name)
        self._write([("INSERT OR IGNORE INTO scenes (tenant, scene_id, filename, bytes, path, source, created_at) "
                      "VALUES (?, ?, ?, ?, ?, 'file', ?)", (tenant, scene_id, p.name, len(data), str(p), time.time()))])
        return scene_id

    def _scene_row(self, tenant: str, scene_id: str):
        rows = self._query("SELECT * FROM scenes WHERE tenant = ? AND scene_id = ?", (tenant, scene_id))
        return rows[0] if rows else None

    def scene_path(self, tenant: str, scene_id: str) -> Path | None:
        row = self._scene_row(tenant, scene_id)
        return self._row_path(row) if row is not None else None

    def scene_record(self, tenant: str, scene_id: str) -> dict | None:
        """{scene_id, filename, bytes, created_at, info, source} or None (also for another tenant's scene)."""
        row = self._scene_row(tenant, scene_id)
        return _scene_dict(row) if row is not None else None

    def scene_sandboxed(self, tenant: str, scene_id: str) -> bool:
        """Uploads load in the resolver's sandbox (upload) mode; linked local files do not."""
        row = self._scene_row(tenant, scene_id)
        return row is None or row["source"] == "upload"

    def delete_scene(self, tenant: str, scene_id: str) -> bool:
        """Remove a scene's row and, for an upload, its file and folder (a file another request of this store
        is uploading again stays for that request)."""
        with self._stripe(tenant, scene_id):
            row = self._scene_row(tenant, scene_id)
            if row is None:
                return False
            self._write([("DELETE FROM scenes WHERE tenant = ? AND scene_id = ?", (tenant, scene_id))])
            if row["source"] == "upload":
                folder = self.scene_folder(tenant, scene_id)
                busy = {k[2] for k in self._inflight if k[:2] == (tenant, scene_id)}
                if not busy:
                    shutil.rmtree(folder, ignore_errors=True)
                else:
                    for f in folder.iterdir() if folder.is_dir() else ():
                        if f.name not in busy and not _TMP_NAME.match(f.name):
                            f.unlink(missing_ok=True)
        return True

    def list_scenes(self, tenant: str) -> list[dict]:
        rows = self._query("SELECT * FROM scenes WHERE tenant = ? ORDER BY created_at, scene_id", (tenant,))
        return [_scene_dict(r) for r in rows]

    # -- batches ---------------------------------------------------------------------------------
    def create_batch(self, tenant: str, scene_id: str, configurations: list[dict], settings: dict) -> str:
        """A queued batch over `configurations` (each {"rig": ...}); its id (uuid4 hex)."""
        batch_id = uuid.uuid4().hex
        now = time.time()
        stmts = [("INSERT INTO batches (batch_id, tenant, scene_id, state, total, settings, created_at, updated_at) "
                  "VALUES (?, ?, ?, 'queued', ?, ?, ?, ?)",
                  (batch_id, tenant, scene_id, len(configurations), json.dumps(settings), now, now))]
        stmts += [("INSERT INTO configurations (batch_id, idx, config) VALUES (?, ?, ?)", (batch_id, i, json.dumps(c)))
                  for i, c in enumerate(configurations)]
        self._write(stmts)
        return batch_id

    def _batch_row(self, batch_id: str, tenant: str | None = None):
        rows = self._query("SELECT * FROM batches WHERE batch_id = ?", (batch_id,))
        if not rows or (tenant is not None and rows[0]["tenant"] != tenant):
            return None
        return rows[0]

    def batch(self, tenant: str, batch_id: str, max_errors: int = MAX_ERRORS_LISTED) -> dict | None:
        """{batch_id, scene_id, state, done, failed, total, errors, created_at, updated_at, settings};
        errors lists the first `max_errors` (by index); `failed` counts them all."""
        row = self._batch_row(batch_id, tenant)
        if row is None:
            return None
        done = self._query("SELECT COUNT(*) FROM results WHERE batch_id = ?", (batch_id,))[0][0]
        failed = self._query("SELECT COUNT(*) FROM errors WHERE batch_id = ?", (batch_id,))[0][0]
        errs = self._query("SELECT e.idx, e.code, e.message, c.config FROM errors e LEFT JOIN configurations c "
                           "ON c.batch_id = e.batch_id AND c.idx = e.idx WHERE e.batch_id = ? ORDER BY e.idx LIMIT ?",
                           (batch_id, max_errors))
        return {"batch_id": batch_id, "scene_id": row["scene_id"], "state": row["state"], "done": done,
                "failed": failed, "total": row["total"],
                "errors": [{"index": r["idx"], **_item_fields(r["config"]), "code": r["code"], "message": r["message"]}
                           for r in errs],
                "created_at": iso(row["created_at"]), "updated_at": iso(row["updated_at"]),
                "settings": json.loads(row["settings"])}

    def batch_state(self, batch_id: str) -> str | None:
        """The state alone (one indexed row, no counts): for the runner's polling."""
        row = self._batch_row(batch_id)
        return row["state"] if row is not None else None

    def batch_owner(self, batch_id: str) -> str | None:
        row = self._batch_row(batch_id)
        return row["tenant"] if row is not None else None

    def list_batches(self, tenant: str) -> list[dict]:
        rows = self._query("SELECT batch_id FROM batches WHERE tenant = ? ORDER BY created_at", (tenant,))
        return [self.batch(tenant, r["batch_id"]) for r in rows]

    def configurations(self, batch_id: str) -> list[dict]:
        rows = self._query("SELECT config FROM configurations WHERE batch_id = ? ORDER BY idx", (batch_id,))
        return [json.loads(r["config"]) for r in rows]

    def _check_index(self, batch_id: str, index: int) -> None:
        row = self._batch_row(batch_id)
        if row is None:
            raise KeyError(f"no batch {batch_id!r}")
        if not 0 <= index < row["total"]:
            raise IndexError(f"configuration index {index} outside [0, {row['total']})")

    def put_result(self, batch_id: str, index: int, result: dict) -> bool:
        """Store a configuration's result; False (and nothing changes) when one is already stored."""
        self._check_index(batch_id, index)
        now = time.time()
        n, _ = self._write([
            ("INSERT OR IGNORE INTO results (batch_id, idx, result, created_at) SELECT ?, ?, ?, ? "
             "WHERE NOT EXISTS (SELECT 1 FROM errors WHERE batch_id = ? AND idx = ?)",
             (batch_id, index, json.dumps(result), now, batch_id, index)),
            ("UPDATE batches SET updated_at = ? WHERE batch_id = ?", (now, batch_id))])
        return n == 1

    def put_error(self, batch_id: str, index: int, code: str, message: str) -> bool:
        """Record that a configuration failed; False when it already has a result or an error."""
        self._check_index(batch_id, index)
        now = time.time()
        n, _ = self._write([
            ("INSERT OR IGNORE INTO errors (batch_id, idx, code, message, created_at) SELECT ?, ?, ?, ?, ? "
             "WHERE NOT EXISTS (SELECT 1 FROM results WHERE batch_id = ? AND idx = ?)",
             (batch_id, index, code, message, now, batch_id, index)),
            ("UPDATE batches SET updated_at = ? WHERE batch_id = ?", (now, batch_id))])
        return n == 1

    def put_outcomes(self, batch_id: str, outcomes: list[tuple[int, dict]]) -> list[bool]:
        """put_result / put_error for several configurations in one transaction (one commit for a worker
        task's frames): each outcome is (index, {"result": solution}) or (index, {"error": {"code",
        "message"}}). Per outcome, False when that configuration already had a result or an error."""
        if not outcomes:
            return []
        row = self._batch_row(batch_id)
        if row is None:
            raise KeyError(f"no batch {batch_id!r}")
        now = time.time()
        statements = []
        for index, out in outcomes:
            if not 0 <= index < row["total"]:
                raise IndexError(f"configuration index {index} outside [0, {row['total']})")
            if "result" in out:
                statements.append((
                    "INSERT OR IGNORE INTO results (batch_id, idx, result, created_at) SELECT ?, ?, ?, ? "
                    "WHERE NOT EXISTS (SELECT 1 FROM errors WHERE batch_id = ? AND idx = ?)",
                    (batch_id, index, json.dumps(out["result"]), now, batch_id, index)))
            else:
                statements.append((
                    "INSERT OR IGNORE INTO errors (batch_id, idx, code, message, created_at) SELECT ?, ?, ?, ?, ? "
                    "WHERE NOT EXISTS (SELECT 1 FROM results WHERE batch_id = ? AND idx = ?)",
                    (batch_id, index, out["error"]["code"], out["error"]["message"], now, batch_id, index)))
        statements.append(("UPDATE batches SET updated_at = ? WHERE batch_id = ?", (now, batch_id)))
        return [n == 1 for n in self._write(statements)[:-1]]

    def _first_pending(self, batch_id: str, offset: int) -> int | None:
        return self._query(
            "SELECT MIN(c.idx) FROM configurations c WHERE c.batch_id = ? AND c.idx >= ? "
            "AND NOT EXISTS (SELECT 1 FROM results r WHERE r.batch_id = c.batch_id AND r.idx = c.idx) "
            "AND NOT EXISTS (SELECT 1 FROM errors e WHERE e.batch_id = c.batch_id AND e.idx = c.idx)",
            (batch_id, offset))[0][0]

    def results(self, tenant: str, batch_id: str, offset: int = 0, limit: int | None = None) -> list[dict]:
        """Finished configurations with index >= offset, in index order: {"index": i, **result}, or
        {"index": i, "error": {"code", "message"}} for one that failed (a path's frame also with its "frame",
        "time" and "scene_time", as a solved frame's line). While the batch is queued or
        running the list stops before the first unfinished index, so a reader that resumes at
        `offset = last index + 1` never skips a configuration that finishes later."""
        row = self._batch_row(batch_id, tenant)
        if row is None:
            return []
        offset = max(0, int(offset))
        stop = row["total"]
        if row["state"] in UNFINISHED:
            first = self._first_pending(batch_id, offset)
            stop = first if first is not None else stop
        lim = -1 if limit is None else max(0, int(limit))
        rows = self._query(
            "SELECT idx, result, NULL AS code, NULL AS message, NULL AS config FROM results "
            "WHERE batch_id = ? AND idx >= ? AND idx < ? "
            "UNION ALL SELECT e.idx, NULL, e.code, e.message, c.config FROM errors e LEFT JOIN configurations c "
            "ON c.batch_id = e.batch_id AND c.idx = e.idx WHERE e.batch_id = ? AND e.idx >= ? AND e.idx < ? "
            "ORDER BY idx LIMIT ?", (batch_id, offset, stop, batch_id, offset, stop, lim))
        out = []
        for r in rows:
            if r["result"] is not None:
                out.append({"index": r["idx"], **json.loads(r["result"])})
            else:
                out.append({"index": r["idx"], **_item_fields(r["config"]),
                            "error": {"code": r["code"], "message": r["message"]}})
        return out

    def set_state(self, batch_id: str, state: str, only_from: tuple[str, ...] | None = None) -> bool:
        """Set a batch's state (optionally only when its current state is one of `only_from`)."""
        if state not in STATES:
            raise ValueError(f"state: unknown {state!r} (known: {', '.join(STATES)})")
        sql, params = "UPDATE batches SET state = ?, updated_at = ? WHERE batch_id = ?", [state, time.time(), batch_id]
        if only_from:
            sql += f" AND state IN ({', '.join('?' * len(only_from))})"
            params += list(only_from)
        (n,) = self._write([(sql, tuple(params))])
        return n == 1

    def finish_batch(self, batch_id: str) -> str | None:
        """When every configuration has an outcome: state done (failed if none succeeded), unless the
        batch was cancelled meanwhile. The state it is in afterwards (None: no such batch)."""
        row = self._batch_row(batch_id)
        if row is None:
            return None
        if row["state"] in UNFINISHED and self._first_pending(batch_id, 0) is None:
            done = self._query("SELECT COUNT(*) FROM results WHERE batch_id = ?", (batch_id,))[0][0]
            self.set_state(batch_id, "done" if done > 0 or row["total"] == 0 else "failed", only_from=UNFINISHED)
            self.auto_retention()
        row = self._batch_row(batch_id)
        return row["state"] if row is not None else None

    def cancel_batch(self, tenant: str, batch_id: str) -> bool:
        """Cancel a queued or running batch. False when the tenant has no such batch; a finished batch
        keeps its state (True)."""
        if self._batch_row(batch_id, tenant) is None:
            return False
        self.set_state(batch_id, "cancelled", only_from=UNFINISHED)
        return True

    def delete_batch(self, tenant: str, batch_id: str) -> bool:
        """Remove a batch and its results (refused, False, while it is queued or running)."""
        row = self._batch_row(batch_id, tenant)
        if row is None or row["state"] in UNFINISHED:
            return False
        self._delete_batches([batch_id])
        return True

    def pending_indices(self, batch_id: str) -> list[int]:
        rows = self._query(
            "SELECT c.idx FROM configurations c WHERE c.batch_id = ? "
            "AND NOT EXISTS (SELECT 1 FROM results r WHERE r.batch_id = c.batch_id AND r.idx = c.idx) "
            "AND NOT EXISTS (SELECT 1 FROM errors e WHERE e.batch_id = c.batch_id AND e.idx = c.idx) ORDER BY c.idx",
            (batch_id,))
        return [r[0] for r in rows]

    def unfinished_batches(self) -> list[tuple[str, str]]:
        """(tenant, batch_id) of queued or running batches, oldest first: what to resume after a restart."""
        rows = self._query("SELECT tenant, batch_id FROM batches WHERE state IN ('queued', 'running') "
                           "ORDER BY created_at")
        return [(r["tenant"], r["batch_id"]) for r in rows]

    def queue_length(self) -> int:
        return self._query("SELECT COUNT(*) FROM batches WHERE state IN ('queued', 'running')")[0][0]

    def pending_configurations(self, tenant: str | None = None) -> int:
        """Configurations of queued or running batches (of one tenant, or all) with neither a result nor an
        error (one query)."""
        who, params = ("", ()) if tenant is None else (" AND {b}.tenant = ?", (tenant,))
        row = self._query(
            "SELECT COALESCE(SUM(b.total), 0) - "
            "(SELECT COUNT(*) FROM results r JOIN batches b2 ON r.batch_id = b2.batch_id "
            " WHERE b2.state IN ('queued', 'running')" + who.format(b="b2") + ") - "
            "(SELECT COUNT(*) FROM errors e JOIN batches b3 ON e.batch_id = b3.batch_id "
            " WHERE b3.state IN ('queued', 'running')" + who.format(b="b3") + ") "
            "FROM batches b WHERE b.state IN ('queued', 'running')" + who.format(b="b"), params * 3)[0][0]
        return max(int(row or 0), 0)

    # -- retention -------------------------------------------------------------------------------
    def disk_bytes(self) -> int:
        """Bytes the data directory takes (scene files and the database with its WAL)."""
        total = 0
        for root, _, files in os.walk(self.data_dir):
            for f in files:
                try:
                    total += os.path.getsize(os.path.join(root, f))
                except OSError:
                    pass
        return total

    def _delete_batches(self, ids: list[str]) -> None:
        stmts = []
        for b in ids:
            for table in ("results", "errors", "configurations", "batches"):
                stmts.append((f"DELETE FROM {table} WHERE batch_id = ?", (b,)))
        if stmts:
            self._write(stmts)

    def auto_retention(self) -> None:
        """enforce_retention() when a limit is set and RETENTION_INTERVAL_S has passed since the last run."""
        if self.retention_days is None and self.max_bytes is None:
            return
        now = time.monotonic()
        if now - self._last_retention < RETENTION_INTERVAL_S:
            return
        self._last_retention = now
        try:
            removed = self.enforce_retention()
            if removed["batches"] or removed["scenes"]:
                log.info("retention removed %d batches and %d scenes", len(removed["batches"]), len(removed["scenes"]))
        except (OSError, sqlite3.Error) as e:  # retention must never fail the write that triggered it
            log.warning("retention failed: %s", e)

    def enforce_retention(self) -> dict:
        """Drop finished batches and scenes older than retention_days, then the oldest until the data
        directory is under max_bytes. Never touches a queued or running batch, nor a scene one uses.
        Returns what was removed: {"batches": [...], "scenes": [[tenant, scene_id], ...]}."""
        with self._retention_lock:
            return self._enforce_retention()

    def _enforce_retention(self) -> dict:
        removed = {"batches": [], "scenes": []}
        busy = {(r["tenant"], r["scene_id"]) for r in self._query(
            "SELECT tenant, scene_id FROM batches WHERE state IN ('queued', 'running')")}
        if self.retention_days is not None:
            cutoff = time.time() - self.retention_days * 86400.0
            old = [r["batch_id"] for r in self._query(
                "SELECT batch_id FROM batches WHERE state NOT IN ('queued', 'running') AND updated_at < ?", (cutoff,))]
            self._delete_batches(old)
            removed["batches"] += old
            for r in self._query("SELECT tenant, scene_id FROM scenes WHERE created_at < ?", (cutoff,)):
                if (r["tenant"], r["scene_id"]) not in busy and self.delete_scene(r["tenant"], r["scene_id"]):
                    removed["scenes"].append([r["tenant"], r["scene_id"]])
        if self.max_bytes is not None:
            self._compact()
            size = self.disk_bytes()
            if size > self.max_bytes:
                for kind, key, est in self._by_age(busy):
                    if size <= self.max_bytes:
                        break
                    if kind == "batch":
                        self._delete_batches([key])
                        removed["batches"].append(key)
                    elif self.delete_scene(*key):
                        removed["scenes"].append(list(key))
                    size -= est
                self._compact()
        return removed

    def _by_age(self, busy: set) -> list[tuple[str, object, int]]:
        """Removable items oldest first with their estimated bytes: finished batches and idle scenes."""
        items = []
        for r in self._query(
                "SELECT b.batch_id, b.updated_at, "
                "(SELECT COALESCE(SUM(LENGTH(result)), 0) FROM results WHERE batch_id = b.batch_id) + "
                "(SELECT COALESCE(SUM(LENGTH(config)), 0) FROM configurations WHERE batch_id = b.batch_id) AS est "
                "FROM batches b WHERE b.state NOT IN ('queued', 'running')"):
            items.append((r["updated_at"], "batch", r["batch_id"], int(r["est"])))
        for r in self._query("SELECT tenant, scene_id, created_at, bytes, source FROM scenes"):
            if (r["tenant"], r["scene_id"]) not in busy:
                items.append((r["created_at"], "scene", (r["tenant"], r["scene_id"]),
                              int(r["bytes"]) if r["source"] == "upload" else 0))
        items.sort(key=lambda t: t[0])
        return [(kind, key, est) for _, kind, key, est in items]


ITEM_FIELDS = ("frame", "time", "scene_time")  # what a path's frame holds beside its rig (service.paths)


def _item_fields(config_text: str | None) -> dict:
    """A stored configuration's frame, time and scene_time (a path job's frame), for the line of a frame that
    failed: it carries them as a solved frame's line does. {} for a batch configuration (a rig only)."""
    if not config_text:
        return {}
    try:
        config = json.loads(config_text)
    except ValueError:
        return {}
    return {k: config[k] for k in ITEM_FIELDS if isinstance(config, dict) and k in config}


def _scene_dict(row) -> dict:
    return {"scene_id": row["scene_id"], "filename": row["filename"], "bytes": row["bytes"],
            "created_at": iso(row["created_at"]), "info": json.loads(row["info"]) if row["info"] else None,
            "source": row["source"]}
