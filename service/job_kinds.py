"""The kinds of job the runner queues (service.job_runner.BatchRunner), and how each one's pending items become
worker tasks: a batch's independent configurations in chunks; a path's frames in chains (coherent: each frame
given the previous one's solution), in runs solved together (method path), or in chunks like a batch's.

Every kind shares one implementation of the rest: the runner's queue, its turns (a slice at a time), resume
after a restart and cancelling; progress (the store's done and failed counts); the worker's task
(service.job_workers.solve_chunk, which reads settings["coherent"] and ["whole_path"]); and the store's rows
(one per item, written as each task comes back). A kind is found from the job's stored settings (kind_of),
so the rows a batch or a path is stored in are the same for both."""
from __future__ import annotations

import bisect
import collections
from collections.abc import Callable
from dataclasses import dataclass

from .job_backends import IN_FLIGHT_PER_WORKER, TaskQueue
from .job_workers import previous_of
from .store import Store

CHUNK = 8  # at most this many configurations per worker task (one round trip, one store commit)
WHOLE_PATH_FRAMES = 48  # method path over a path job: frames solved together per task (frame index // this)
MIN_CHUNK_FRAMES = 16  # a coherent chunk is at least this long (shorter paths stay one chunk)


def chunk_size(n: int, workers: int) -> int:
    """Configurations per task for n independent ones: up to CHUNK, but enough tasks to keep every worker
    busy (IN_FLIGHT_PER_WORKER each) to the end."""
    return max(1, min(CHUNK, n // max(1, workers * IN_FLIGHT_PER_WORKER * 2)))


def chunked(items: list, size: int) -> list[list]:
    return [items[k:k + size] for k in range(0, len(items), max(1, size))]


def chunk_starts(total: int, chunks: int | None) -> list[int]:
    """The first frames of a coherent path's chunks: `chunks` (settings["coherent_chunks"], the workers that
    share the path) contiguous runs of equal length, each at least MIN_CHUNK_FRAMES. Each chunk is coherent
    within itself and its first frame starts fresh (no previous): one fresh start per chunk is the price of
    solving them in parallel. Fixed by the batch's total and settings, so a resumed path keeps them."""
    k = max(1, min(int(chunks or 1), total // MIN_CHUNK_FRAMES))
    return sorted({(j * total) // k for j in range(k)})


class _Chains:
    """A coherent path's worker tasks (service.job_backends.TaskQueue's protocol): per chunk, runs of up to
    CHUNK consecutive frames, one task in flight per chunk; a task's first frame brings the previous
    frame's solution (from the task before it, or from the store after a resume), the worker chains the
    rest (service.job_workers.solve_group)."""

    def __init__(self, store: Store, batch_id: str, items: list, starts: list[int], pause, chunk: int):
        self.store, self.batch_id, self.starts, self.chunk = store, batch_id, set(starts), chunk
        self.pause = pause or (lambda: False)
        self.chains = collections.defaultdict(collections.deque)
        for i, c in sorted(items, key=lambda ic: ic[0]):
            self.chains[bisect.bisect_right(starts, i) - 1].append((i, c))
        self.of = {}  # first index of a task in flight -> chain
        self.busy, self.last = set(), {}  # chain -> (index, previous) of its last solved frame

    def _previous(self, ch, i: int):
        if i in self.starts or i == 0:
            return None
        if ch in self.last and self.last[ch][0] == i - 1:
            return self.last[ch][1]
        owner = self.store.batch_owner(self.batch_id)
        rows = self.store.results(owner, self.batch_id, offset=i - 1, limit=1) if owner is not None else []
        return previous_of(rows[0]) if rows and rows[0]["index"] == i - 1 else None

    def take(self):
        if self.pause():
            return None
        for ch in sorted(self.chains):
            q = self.chains[ch]
            if ch in self.busy or not q:
                continue
            i, c = q.popleft()
            prev = self._previous(ch, i)
            group = [(i, {**c, "previous": prev} if prev is not None else c)]
            while q and len(group) < self.chunk and q[0][0] == group[-1][0] + 1 and q[0][0] not in self.starts:
                group.append(q.popleft())
            self.busy.add(ch)
            self.of[i] = ch
            return group
        return None

    def finished(self) -> bool:
        return self.pause() or not any(self.chains.values())

    def done(self, outs) -> None:
        ch = self.of.pop(outs[0][0], None)
        if ch is None:
            return
        self.busy.discard(ch)
        i, out = outs[-1]
        self.last[ch] = (i, previous_of(out.get("result")))


def coherent_tasks(store: Store, batch_id: str, items: list, settings: dict, pause=None,
                   total: int | None = None) -> _Chains:
    """A coherent path's worker tasks, each [(index, config), ...]:
    within each chunk (chunk_starts: settings["coherent_chunks"], default one) frames one after another in
    index order, each configuration given "previous" = the previous frame's solution (from the store after
    a resume), which service.job_workers passes to solve(..., previous=...); the chunks in parallel."""
    if total is None:
        owner = store.batch_owner(batch_id)
        st = store.batch(owner, batch_id, max_errors=0) if owner is not None else None
        total = st["total"] if st else max((i for i, _ in items), default=-1) + 1
    starts = chunk_starts(total, settings.get("coherent_chunks"))
    # tasks of up to CHUNK frames, at least 8 per chunk (a short path streams, and is stored, frame by frame);
    # over moving geometry one frame per task (each frame loads the stage at its time code, seconds each)
    chunk = 1 if moving(items) else max(1, min(CHUNK, total // len(starts) // 8))
    return _Chains(store, batch_id, items, starts, pause, chunk)


def moving(items: list) -> bool:
    """A path over moving geometry: its frames load the stage at their own time code ("scene_time")."""
    return any(c.get("scene_time") is not None for _, c in items)


def _batch_tasks(store: Store, batch_id: str, items: list, settings: dict, workers: int, pause=None,
                 total: int | None = None) -> TaskQueue:
    """Independent configurations: tasks of chunk_size, in index order."""
    return TaskQueue(chunked(items, chunk_size(len(items), workers)), pause)


def _path_tasks(store: Store, batch_id: str, items: list, settings: dict, workers: int, pause=None,
                total: int | None = None):
    """A path's frames: coherent (settings["coherent"]) in chains (coherent_tasks); method path
    (settings["whole_path"]) in runs of consecutive frames solved together; otherwise as a batch's."""
    if settings.get("coherent"):  # a coherent path: frames in order, each given the previous one's solution
        return coherent_tasks(store, batch_id, items, settings, pause=pause, total=total)
    if settings.get("whole_path") and moving(items):  # a stage per frame: solved frame by frame anyway
        # (job_workers.solve_group), so one frame per task: a run of 48 stage loads held a worker for 823 s
        # while another tenant's batch waited (issue 27); the runner's turns now come between frames
        return TaskQueue([[ic] for ic in sorted(items, key=lambda ic: ic[0])], pause)
    if settings.get("whole_path"):  # method path: runs of consecutive frames solved together, cut at fixed
        # multiples of WHOLE_PATH_FRAMES so that a resumed path solves the same runs
        runs = collections.defaultdict(list)
        for i, c in sorted(items, key=lambda ic: ic[0]):
            runs[i // WHOLE_PATH_FRAMES].append((i, c))
        return TaskQueue([runs[k] for k in sorted(runs)], pause)
    return _batch_tasks(store, batch_id, items, settings, workers, pause, total)


@dataclass(frozen=True)
class JobKind:
    """A kind of job: `owns(settings)` says whether a stored job's settings are this kind's; `tasks(store,
    batch_id, items, settings, workers, pause, total)` gives its pending [(index, config), ...] as worker tasks,
    a TaskQueue or a queue with its protocol (take, finished, done). The rest is the runner's, the same
    for every kind (see the module doc)."""

    name: str
    owns: Callable[[dict], bool]
    tasks: Callable[..., object]


def _is_path(settings: dict) -> bool:
    """A path job's settings (service.paths: coherent or whole_path; the server's path jobs also say "path")."""
    return bool(settings.get("coherent") or settings.get("whole_path") or settings.get("path"))


KINDS = {
    "path": JobKind("path", _is_path, _path_tasks),
    "batch": JobKind("batch", lambda settings: True, _batch_tasks),
}


def kind_of(settings: dict) -> JobKind:
    """The first kind (in KINDS' order) that owns these stored settings."""
    return next(kind for kind in KINDS.values() if kind.owns(settings or {}))
