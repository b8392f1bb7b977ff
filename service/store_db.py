"""The SQLite database of a Store's data directory (service.store.Store builds on it): one connection per
thread (WAL), the schema and its migrations (SCHEMA_VERSION), transactions, the check that the file is still
a database, compaction, and the lock file by which other Stores see that this one is alive."""
from __future__ import annotations

import contextlib
import fcntl
import hashlib
import logging
import os
import sqlite3
import threading
import uuid
from pathlib import Path

log = logging.getLogger("shadowopt.store")

DB_NAME = "shadowopt.db"
LOCKS_DIR = ".locks"  # <data_dir>/.locks/<instance>.lock: held (flock) by each open Store, released when it dies
SCHEMA_VERSION = 1  # PRAGMA user_version: 1 = upload paths relative to the scenes folder

_SCHEMA = """
CREATE TABLE IF NOT EXISTS scenes (
    tenant TEXT NOT NULL, scene_id TEXT NOT NULL, filename TEXT NOT NULL, bytes INTEGER NOT NULL,
    path TEXT NOT NULL, source TEXT NOT NULL, created_at REAL NOT NULL, info TEXT,
    PRIMARY KEY (tenant, scene_id));
CREATE TABLE IF NOT EXISTS batches (
    batch_id TEXT PRIMARY KEY, tenant TEXT NOT NULL, scene_id TEXT NOT NULL, state TEXT NOT NULL,
    total INTEGER NOT NULL, settings TEXT NOT NULL, created_at REAL NOT NULL, updated_at REAL NOT NULL);
CREATE INDEX IF NOT EXISTS batches_tenant ON batches (tenant);
CREATE INDEX IF NOT EXISTS batches_state ON batches (state);
CREATE TABLE IF NOT EXISTS configurations (
    batch_id TEXT NOT NULL, idx INTEGER NOT NULL, config TEXT NOT NULL, PRIMARY KEY (batch_id, idx));
CREATE TABLE IF NOT EXISTS results (
    batch_id TEXT NOT NULL, idx INTEGER NOT NULL, result TEXT NOT NULL, created_at REAL NOT NULL,
    PRIMARY KEY (batch_id, idx));
CREATE TABLE IF NOT EXISTS errors (
    batch_id TEXT NOT NULL, idx INTEGER NOT NULL, code TEXT NOT NULL, message TEXT NOT NULL,
    created_at REAL NOT NULL, PRIMARY KEY (batch_id, idx));
"""


def tenant_dir_name(tenant: str) -> str:
    """Tenants' folders are named by a hash: a tenant name never becomes a path."""
    return hashlib.sha256(tenant.encode()).hexdigest()[:16]


class Database:
    """The database and data directory of a Store; see the module docstring."""

    def __init__(self, data_dir: str | Path):
        self.data_dir = Path(os.path.abspath(data_dir))  # pinned: a later chdir changes nothing
        self.scenes_dir = self.data_dir / "scenes"
        self.scenes_dir.mkdir(parents=True, exist_ok=True)
        self.tmp_dir = self.data_dir / "tmp"  # uploads' scratch folders (Store.work_dir), swept at start
        self.db_path = self.data_dir / DB_NAME
        self._local = threading.local()
        self._conns: list[sqlite3.Connection] = []
        self._conns_lock = threading.Lock()
        self._write_lock = threading.Lock()  # one writer at a time within this process
        self._header_fds: list[int] = []  # descriptors _check_file reads the header through (closed by close())
        self._fd_lock = threading.Lock()
        self._lock_file = None
        self._hold_instance_lock()
        self._init_schema()
        self._migrate_paths()

    # -- connections -----------------------------------------------------------------------------
    def _conn(self) -> sqlite3.Connection:
        conn = getattr(self._local, "conn", None)
        if conn is None:
            conn = sqlite3.connect(self.db_path, timeout=30.0, isolation_level=None, check_same_thread=False)
            conn.row_factory = sqlite3.Row
            conn.execute("PRAGMA auto_vacuum=INCREMENTAL")  # takes effect only on a new, empty database
            conn.execute("PRAGMA journal_mode=WAL")
            conn.execute("PRAGMA synchronous=NORMAL")  # WAL + NORMAL: durable against process crashes
            conn.execute("PRAGMA busy_timeout=30000")
            self._local.conn = conn
            with self._conns_lock:
                self._conns.append(conn)
        return conn

    def _init_schema(self) -> None:
        conn = self._conn()
        with self._write_lock:
            conn.executescript(_SCHEMA)

    def _migrate_paths(self) -> None:
        """Rows from before SCHEMA_VERSION 1 hold absolute or working-directory-relative paths: each becomes
        relative to the scenes folder, taken from the old path when that file is inside this store's scenes
        folder, else rebuilt from tenant, scene_id and filename (the layout write_upload always used)."""
        conn = self._conn()
        if conn.execute("PRAGMA user_version").fetchone()[0] >= SCHEMA_VERSION:
            return
        with self._write_lock:
            conn.execute("BEGIN IMMEDIATE")
            try:
                if conn.execute("PRAGMA user_version").fetchone()[0] < SCHEMA_VERSION:  # another process did it
                    rows = conn.execute("SELECT tenant, scene_id, filename, path FROM scenes "
                                        "WHERE source = 'upload'").fetchall()
                    for r in rows:
                        rel = self._migrated_path(r["tenant"], r["scene_id"], r["filename"], r["path"])
                        conn.execute("UPDATE scenes SET path = ? WHERE tenant = ? AND scene_id = ?",
                                     (rel, r["tenant"], r["scene_id"]))
                    conn.execute(f"PRAGMA user_version = {SCHEMA_VERSION}")
                conn.execute("COMMIT")
            except BaseException:
                conn.execute("ROLLBACK")
                raise

    def _migrated_path(self, tenant: str, scene_id: str, filename: str, old: str) -> str:
        canonical = f"{tenant_dir_name(tenant)}/{scene_id}/{filename}"
        p = Path(old)
        if p.is_file():  # absolute, or relative to this process's working directory
            rel = self._relative(p)
            if rel is not None:
                return rel
        if not (self.scenes_dir / canonical).is_file():
            log.warning("scene %s of a tenant: its file is missing (kept; recorded as %s)", scene_id, canonical)
        return canonical

    def _relative(self, path: Path) -> str | None:
        """`path` relative to the scenes folder (posix), or None when it is not inside it."""
        for base, p in ((self.scenes_dir, Path(os.path.abspath(path))),
                        (Path(os.path.realpath(self.scenes_dir)), Path(os.path.realpath(path)))):
            try:
                rel = p.relative_to(base)
            except ValueError:
                continue
            if rel.parts and ".." not in rel.parts:
                return rel.as_posix()
        return None


    # -- this process's claim on the data directory (for the sweep) -------------------------------
    def _hold_instance_lock(self) -> None:
        """Create and flock <data_dir>/.locks/<uuid>.lock for the Store's lifetime: the kernel releases it when
        the process dies, however it dies, so the sweep can tell a live server from a dead one."""
        d = self.data_dir / LOCKS_DIR
        d.mkdir(parents=True, exist_ok=True)
        path = d / f"{uuid.uuid4().hex}.lock"
        f = open(path, "w")  # not inherited across exec (PEP 446)
        fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        f.write(f"{os.getpid()}\n")
        f.flush()
        self._lock_file = f

    def _release_instance_lock(self) -> None:
        f, self._lock_file = self._lock_file, None
        if f is not None:
            with contextlib.suppress(OSError):
                os.unlink(f.name)
            with contextlib.suppress(OSError):
                fcntl.flock(f.fileno(), fcntl.LOCK_UN)
            f.close()

    def other_live_stores(self) -> int:
        """How many other Stores (in this or another process) hold the data directory open now; lock files
        of dead ones are removed on the way."""
        live = 0
        own = self._lock_file.name if self._lock_file is not None else None
        for path in sorted((self.data_dir / LOCKS_DIR).glob("*.lock")):
            if str(path) == own:
                continue
            try:
                f = open(path, "r+")
            except OSError:
                continue
            with f:
                try:
                    fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
                except BlockingIOError:
                    live += 1
                    continue
                with contextlib.suppress(OSError):
                    path.unlink()  # its owner is gone
        return live

    def _check_file(self) -> None:
        """sqlite3.DatabaseError when the database file's header is not SQLite's: an open connection keeps
        answering from its page cache after the file was damaged, a new one would fail (16 bytes read).

        Read through a descriptor kept open until close(), never one opened and closed per check: closing
        any descriptor of a file drops every POSIX lock this process holds on it (fcntl semantics), SQLite's
        included, and another process's Store then took itself for the last one, checkpointed and deleted
        the WAL and its index under this process's open connections ("file is not a database" on every
        read of theirs afterwards; seen with two concurrent results downloads, issue 27)."""
        try:
            st = os.stat(self.db_path)
            with self._fd_lock:
                fd = self._header_fds[-1] if self._header_fds else None
                if fd is None or os.fstat(fd).st_ino != st.st_ino:  # a new file at the path: keep the old fd open
                    fd = os.open(self.db_path, os.O_RDONLY | os.O_CLOEXEC)
                    self._header_fds.append(fd)
            head = os.pread(fd, 16, 0)
        except OSError as e:
            raise sqlite3.DatabaseError(f"cannot read the database file ({e.strerror})") from e
        if head != b"SQLite format 3\x00":
            raise sqlite3.DatabaseError("file is not a database (its header is damaged)")

    def _write(self, statements: list[tuple[str, tuple]]) -> list[int]:
        """Run statements in one transaction; the rowcount of each."""
        self._check_file()
        conn = self._conn()
        counts = []
        with self._write_lock:
            conn.execute("BEGIN IMMEDIATE")
            try:
                for sql, params in statements:
                    counts.append(conn.execute(sql, params).rowcount)
                conn.execute("COMMIT")
            except BaseException:
                conn.execute("ROLLBACK")
                raise
        return counts

    def _query(self, sql: str, params: tuple = ()) -> list[sqlite3.Row]:
        self._check_file()
        return self._conn().execute(sql, params).fetchall()

    def close(self) -> None:
        self._release_instance_lock()
        with self._conns_lock:
            for c in self._conns:
                try:
                    c.close()
                except sqlite3.ProgrammingError:
                    pass
            self._conns.clear()
        with self._fd_lock:  # after the connections: nothing of SQLite's is left to lose its locks
            for fd in self._header_fds:
                os.close(fd)
            self._header_fds.clear()
        self._local = threading.local()

    def check_database(self) -> None:
        """A cheap check that the database answers (its header and one query); raises sqlite3.DatabaseError
        naming the reason."""
        self._query("SELECT COUNT(*) FROM (SELECT 1 FROM scenes LIMIT 1)")  # _query checks the header first

    def _compact(self) -> None:
        """Give freed database pages back to the file system."""
        conn = self._conn()
        with self._write_lock:
            if conn.execute("PRAGMA auto_vacuum").fetchone()[0] != 2:  # a database from before: convert it once
                conn.executescript("PRAGMA auto_vacuum=INCREMENTAL; VACUUM;")
            conn.executescript("PRAGMA incremental_vacuum;")  # executescript steps it to the end
            conn.execute("PRAGMA wal_checkpoint(TRUNCATE)")
