"""The runner of queued jobs (batches and paths, service.job_kinds): one queue taken in turns, a slice at a
time, on a local spawn pool or Ray (service.job_backends), writing each task's outcomes to the Store as they
arrive (idempotent by index), so a crash loses at most the configurations in flight; `BatchRunner.resume()`
re-queues only the pending indices. Rigs reach it already validated (the server and the CLI use the pydantic
Rig)."""
from __future__ import annotations

import collections
import logging
import threading
import time

from .job_backends import LocalBackend, RayBackend, SceneJob
from .job_kinds import kind_of
from .request_fields import BatchError
from .store import UNFINISHED, Store

log = logging.getLogger("shadowopt.batches")

BACKENDS = ("local", "ray")
RUNNER_RETRIES, RUNNER_RETRY_S = 3, 1.0  # a batch whose run fails as a whole is re-queued this often first
SLICE = 64  # configurations a batch runs before it lets a batch that arrived meanwhile take a turn
TURN_S = 5.0  # or seconds, whichever comes first: fair share by time, not by turns (issue 27); tasks in flight
# finish first, so a waiting batch starts within TURN_S plus one task (one frame of a path over moving geometry)


def turn_over(done: int, seconds: float) -> bool:
    """Whether a batch's turn is over (when another batch waits): SLICE configurations or TURN_S seconds."""
    return done >= SLICE or seconds >= TURN_S


class BatchRunner:
    """Runs queued batches one after another on a local spawn pool or Ray, writing each outcome to the store."""

    def __init__(self, store: Store, backend: str = "local", workers: int = 2, ray_address: str | None = None,
                 max_triangles: int | None = None, load_limits: dict | None = None,
                 worker_cache: dict | None = None):
        """max_triangles: the server's triangle limit, applied to every scene a worker loads (None: none,
        the CLI's own files). load_limits: the server's upload load limits {max_triangles, memory_bytes,
        timeout_s}, applied to an upload's load at a path frame's time code (worker_entry). worker_cache:
        {max_bytes, tenant_share} of each worker's scene cache (the server's worker_cache_bytes and
        tenant_cache_share; None: the worker keeps isolation's defaults, one owner)."""
        if backend not in BACKENDS:
            raise BatchError("backend", f"unknown backend {backend!r} (known: {', '.join(BACKENDS)})")
        if not isinstance(workers, int) or workers < 1:
            raise BatchError("workers", f"expected a positive integer, got {workers!r}")
        self.store = store
        self.backend = backend
        self.workers = workers
        self.ray_address = ray_address
        if max_triangles is not None and (isinstance(max_triangles, bool) or not isinstance(max_triangles, int)
                                          or max_triangles < 1):
            raise BatchError("max_triangles", f"expected a positive integer, got {max_triangles!r}")
        self.max_triangles = max_triangles
        self.load_limits = dict(load_limits) if load_limits else None
        self.worker_cache = dict(worker_cache) if worker_cache else None
        self.stats = {"submitted": 0, "results": 0, "errors": 0}
        self._impl = None
        self._queue: collections.deque[tuple[str, str]] = collections.deque()
        self._cv = threading.Condition()
        self._current: str | None = None
        self._cancelled: set[str] = set()
        self._runner_failures: dict[str, int] = {}
        self._stop = False
        self._thread: threading.Thread | None = None
        self._turn_done = 0  # configurations the current batch stored in this turn

    # public
    def submit(self, tenant: str, batch_id: str) -> None:
        """Queue a batch (its pending configurations) for execution."""
        with self._cv:
            if self._stop:
                raise RuntimeError("the batch runner is shut down")
            if batch_id != self._current and all(b != batch_id for _, b in self._queue):
                self._queue.append((tenant, batch_id))
            self._cv.notify_all()
            if self._thread is None:
                self._thread = threading.Thread(target=self._loop, name="batch-runner", daemon=True)
                self._thread.start()

    def resume(self) -> list[str]:
        """Re-queue the store's unfinished batches (after a restart): only their pending indices run."""
        ids = []
        for tenant, batch_id in self.store.unfinished_batches():
            self.store.set_state(batch_id, "queued", only_from=("running",))
            self.submit(tenant, batch_id)
            ids.append(batch_id)
        return ids

    def cancel(self, tenant: str, batch_id: str) -> bool:
        """Cancel a batch (False: the tenant has no such batch). Configurations in flight are abandoned."""
        if not self.store.cancel_batch(tenant, batch_id):
            return False
        with self._cv:
            self._queue = collections.deque(q for q in self._queue if q[1] != batch_id)
            self._cancelled.add(batch_id)
            self._cv.notify_all()
        return True

    def queue_length(self) -> int:
        with self._cv:
            return len(self._queue) + (self._current is not None)

    def wait(self, batch_id: str, timeout: float | None = None) -> str | None:
        """Block until the batch is no longer queued or running (or timeout); its state."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            owner = self.store.batch_owner(batch_id)
            st = self.store.batch(owner, batch_id) if owner is not None else None
            state = st["state"] if st else None
            if state not in UNFINISHED:
                return state
            left = None if deadline is None else deadline - time.monotonic()
            if left is not None and left <= 0:
                return state
            with self._cv:
                self._cv.wait(timeout=0.5 if left is None else min(0.5, left))

    def shutdown(self, wait: bool = True) -> None:
        """Stop after the configurations in flight; unfinished batches stay queued in the store for resume()."""
        with self._cv:
            self._stop = True
            self._cv.notify_all()
        if self._thread is not None and wait:
            self._thread.join(timeout=120)
        if self._impl is not None:
            self._impl.close(wait_workers=wait)
            self._impl = None

    # internals
    def _backend(self):
        if self._impl is None:
            self._impl = LocalBackend(self.workers) if self.backend == "local" else RayBackend(self.workers, self.ray_address)
        return self._impl

    def _loop(self) -> None:
        while True:
            with self._cv:
                while not self._queue and not self._stop:
                    self._cv.wait()
                if self._stop:
                    return
                tenant, batch_id = self._queue.popleft()
                self._current = batch_id
            try:
                self._run(tenant, batch_id)
            except Exception as e:
                log.exception("batch %s failed in the runner", batch_id)
                tries = self._runner_failures.get(batch_id, 0) + 1
                self._runner_failures[batch_id] = tries
                if not self._stop and tries < RUNNER_RETRIES:
                    # a passing failure (a busy database, a backend that did not start): the pending
                    # configurations stay pending and the batch goes back in the queue, after the others
                    time.sleep(RUNNER_RETRY_S)
                    with self._cv:
                        self._queue.append((tenant, batch_id))
                elif not self._stop:
                    for i in self.store.pending_indices(batch_id):
                        self.store.put_error(batch_id, i, "runner_error", f"{type(e).__name__}: {e}")
                    self.store.finish_batch(batch_id)
            finally:
                with self._cv:
                    self._current = None
                    self._cv.notify_all()

    def _should_stop(self, batch_id: str) -> bool:
        if self._stop or batch_id in self._cancelled:
            return True
        state = self.store.batch_state(batch_id)
        return state is None or state == "cancelled"

    def _run(self, tenant: str, batch_id: str) -> None:
        st = self.store.batch(tenant, batch_id, max_errors=0)
        if st is None or st["state"] not in UNFINISHED:
            return
        if not self.store.set_state(batch_id, "running", only_from=UNFINISHED):
            return
        pending = self.store.pending_indices(batch_id)
        rec = self.store.scene_record(tenant, st["scene_id"])
        path = self.store.scene_path(tenant, st["scene_id"])
        if rec is None or path is None or not path.is_file():
            for i in pending:
                self.store.put_error(batch_id, i, "scene_not_found", f"scene {st['scene_id']!r} is gone")
            self.store.finish_batch(batch_id)
            return
        configs = self.store.configurations(batch_id)
        job = SceneJob(str(path), rec["filename"], self.store.scene_sandboxed(tenant, st["scene_id"]))
        items = [(i, configs[i]) for i in pending]
        self._turn_done = 0
        started = time.monotonic()

        def pause():  # take turns: after a slice or TURN_S, a batch that arrived meanwhile goes first
            return turn_over(self._turn_done, time.monotonic() - started) and self._others_waiting()

        self._run_slice(batch_id, job, items, st["settings"], pause, total=st["total"], tenant=tenant)
        if self._stop:
            return
        if not self._should_stop(batch_id) and self.store.pending_indices(batch_id):
            with self._cv:  # paused: the rest goes behind the batches that arrived meanwhile
                self._queue.append((tenant, batch_id))
            return
        self.store.finish_batch(batch_id)

    def _others_waiting(self) -> bool:
        with self._cv:
            return bool(self._queue)

    def _run_slice(self, batch_id: str, job, items: list, settings: dict, pause=None, total: int | None = None,
                   tenant: str | None = None) -> None:
        """Run a batch's pending configurations (until `pause()`), storing each task's outcomes in one
        commit as they arrive: in the tasks its kind makes of them (service.job_kinds: independent
        configurations in tasks of chunk_size, a coherent path's in chains)."""
        self.stats["submitted"] += len(items)
        settings = {**(settings or {}), "max_triangles": self.max_triangles,  # this server's, not the stored ones
                    "load_limits": self.load_limits or (settings or {}).get("load_limits")}
        if self.worker_cache:  # the worker's scene cache: bounded in bytes, the batch's tenant its owner
            settings.update(worker_cache=self.worker_cache, tenant=tenant)
        stop = lambda: self._should_stop(batch_id)  # noqa: E731
        backend = self._backend()
        tasks = kind_of(settings).tasks(self.store, batch_id, items, settings, self.workers, pause, total)
        for outs in backend.run_groups(job, tasks, settings, stop):
            self.store.put_outcomes(batch_id, outs)
            self._turn_done += len(outs)
            for _, out in outs:
                self.stats["results" if "result" in out else "errors"] += 1
            with self._cv:
                self._cv.notify_all()
