"""Where a job's tasks run: a local spawn process pool (LocalBackend, restarted when a worker dies) or Ray actors
(RayBackend, each holding the job's scene), both taking tasks from a TaskQueue (or a queue with its protocol:
service.job_kinds) and yielding each task's outcomes as it completes; a task lost with its worker runs once more."""
from __future__ import annotations

import collections
import logging
import multiprocessing
import os
import time
from concurrent.futures import FIRST_COMPLETED, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from pathlib import Path

from .isolation import DyingProcessPool
from .job_workers import SceneSolver, llvm_path, solve_chunk, worker_init

log = logging.getLogger("shadowopt.batches")

IN_FLIGHT_PER_WORKER = 2  # keeps workers busy while a cancel takes effect within a configuration or two
MAX_RETRIES = 1  # a configuration in flight when a worker process dies is tried once more


class TaskQueue:
    """The worker tasks of a run: groups of (index, config), each one round trip to a worker and one store
    commit. `take()` gives the next group (None: none ready now), `finished()` says no group will come,
    `done(outcomes)` is told each task's outcomes (a coherent path's next task is ready once the one
    before it is back: service.job_kinds). `pause()`: start no new task (those in flight finish)."""

    def __init__(self, groups=(), pause=None):
        self.groups = collections.deque(groups)
        self.pause = pause or (lambda: False)

    def take(self):
        return self.groups.popleft() if self.groups and not self.pause() else None

    def finished(self) -> bool:
        return not self.groups or self.pause()

    def done(self, outcomes) -> None:
        pass

    def retry(self, group) -> None:
        """A group lost with its worker, to run again (first)."""
        self.groups.appendleft(group)


@dataclass
class SceneJob:
    path: str
    filename: str
    sandbox: bool


class LocalBackend:
    """A spawn ProcessPoolExecutor; recreated when a worker process dies."""

    def __init__(self, workers: int):
        self.workers = workers
        self.llvm = llvm_path()
        self.threads = max(1, (os.cpu_count() or 1) // workers)
        self.pool = None

    def ensure_pool(self):
        if self.pool is None:
            # Workers are started on service.isolation's spawner thread, which lives as long as this
            # process: their parent-death signal cannot fire because the thread that submitted ended.
            self.pool = DyingProcessPool(max_workers=self.workers, mp_context=multiprocessing.get_context("spawn"),
                                         initializer=worker_init,
                                         initargs=(self.llvm, self.threads, os.getpid(),
                                                   DyingProcessPool.pdeathsig_safe()))
        return self.pool

    def run(self, job: SceneJob, items: list[tuple[int, dict]], settings: dict, should_stop):
        """Each configuration its own task; yields (index, outcome) as they complete."""
        for outs in self.run_groups(job, TaskQueue([[ic] for ic in items]), settings, should_stop):
            yield from outs

    def run_groups(self, job: SceneJob, tasks: TaskQueue, settings: dict, should_stop):
        """Run the queue's tasks (solve_chunk), IN_FLIGHT_PER_WORKER per worker; yields each task's
        [(index, outcome), ...] as it completes. A task lost with a dying worker runs once more (an
        independent one split into single configurations, so only a configuration that kills its worker
        again fails: worker_crashed)."""
        retries = collections.deque()  # (group, tries) lost with a worker
        inflight = {}
        try:
            while True:
                if should_stop():
                    return
                pool = self.ensure_pool()
                while len(inflight) < self.workers * IN_FLIGHT_PER_WORKER:
                    group, tries = retries.popleft() if retries else (tasks.take(), 0)
                    if group is None:
                        break
                    inflight[pool.submit(solve_chunk, job.path, job.sandbox, group, settings)] = (group, tries)
                if not inflight:
                    if retries or not tasks.finished():
                        time.sleep(0.01)  # nothing was ready (the queue said so): ask again
                        continue
                    return
                done, _ = wait(list(inflight), timeout=0.5, return_when=FIRST_COMPLETED)
                broken = False
                for fut in done:
                    try:
                        outs = fut.result()
                    except BrokenProcessPool:
                        broken = True
                        continue
                    except Exception as e:
                        group, _ = inflight[fut]
                        outs = [(i, {"error": {"code": "internal_error", "message": f"{type(e).__name__}: {e}"}})
                                for i, _ in group]
                    inflight.pop(fut)
                    tasks.done(outs)
                    yield outs
                if broken:
                    for lost in self._after_crash(inflight, retries, coherent=bool(settings.get("coherent"))):
                        tasks.done(lost)
                        yield lost
        finally:
            for fut in inflight:
                fut.cancel()

    def _after_crash(self, inflight: dict, retries: collections.deque, coherent: bool) -> list[list]:
        """A worker died: everything in flight is lost. Retry each task once in a new pool (independent
        configurations one by one), then give up on it; the outcomes given up, per task."""
        log.warning("a batch worker process died; restarting the pool")
        self.pool.shutdown(wait=False, cancel_futures=True)
        self.pool = None
        failed = []
        for fut, (group, tries) in sorted(inflight.items(), key=lambda kv: -kv[1][0][0][0]):
            if tries < MAX_RETRIES:
                for g in ([group] if coherent else [[ic] for ic in reversed(group)]):
                    retries.appendleft((g, tries + 1))
            else:
                failed.append([(i, {"error": {"code": "worker_crashed",
                                              "message": "the worker process died while solving this configuration"}})
                               for i, _ in group])
        inflight.clear()
        return sorted(failed, key=lambda g: g[0][0])

    def close(self, wait_workers: bool = True):
        if self.pool is not None:
            self.pool.shutdown(wait=wait_workers, cancel_futures=True)
            self.pool = None


class RayBackend:
    """Ray actors (one per worker, each loading the shipped scene once), on `address` or a local instance."""

    def __init__(self, workers: int, address: str | None):
        import ray  # lazy: Ray is an optional extra (shadowopt[ray])

        self.ray = ray
        self.workers = workers
        self.llvm = llvm_path()
        self.owns = False
        if not ray.is_initialized():
            env = {"env_vars": {"DRJIT_LIBLLVM_PATH": self.llvm}} if self.llvm else None
            if address:
                ray.init(address=address, runtime_env=env, log_to_driver=False)
            else:
                ray.init(num_cpus=workers, include_dashboard=False, runtime_env=env, log_to_driver=False,
                         object_store_memory=128 * 1024 * 1024)
            self.owns = True
        self.actor_cls = ray.remote(num_cpus=1, max_restarts=0)(SceneSolver)
        self.actors: list = []
        self.actors_key = None
        self.spawn = None
        self.last_actor_pids: list[int] = []

    def _actors_for(self, job: SceneJob) -> list:
        """One actor per worker holding this scene; kept while consecutive batches use the same file."""
        st = os.stat(job.path)
        key = (job.path, st.st_size, st.st_mtime_ns, job.sandbox)
        if self.actors_key != key:
            self._kill_actors()
            data_ref = self.ray.put(Path(job.path).read_bytes())  # shipped once; each actor receives it once
            self.spawn = lambda: self.actor_cls.remote(data_ref, job.path, job.filename, job.sandbox, self.llvm)
            self.actors = [self.spawn() for _ in range(self.workers)]
            self.actors_key = key
        return self.actors

    def _kill_actors(self) -> None:
        for a in self.actors:
            self.ray.kill(a)
        self.actors, self.actors_key = [], None

    def run(self, job: SceneJob, items: list[tuple[int, dict]], settings: dict, should_stop):
        """Each configuration its own task; yields (index, outcome) as they complete."""
        for outs in self.run_groups(job, TaskQueue([[ic] for ic in items]), settings, should_stop):
            yield from outs

    def run_groups(self, job: SceneJob, tasks: TaskQueue, settings: dict, should_stop):
        """As LocalBackend.run_groups, on the actors (IN_FLIGHT_PER_WORKER tasks each); a dead actor is
        replaced and its tasks run once more."""
        ray = self.ray
        actors = self._actors_for(job)
        retries = collections.deque()
        inflight = {}  # ObjectRef -> (group, tries, actor)
        load = {id(a): 0 for a in actors}
        coherent = bool(settings.get("coherent"))
        try:
            while True:
                if should_stop():
                    return
                while True:  # the least loaded actor first: a coherent path's chunks (one task each) spread out
                    a = min(actors, key=lambda x: load[id(x)])
                    if load[id(a)] >= IN_FLIGHT_PER_WORKER:
                        break
                    group, tries = retries.popleft() if retries else (tasks.take(), 0)
                    if group is None:
                        break
                    inflight[a.solve_chunk.remote(group, settings)] = (group, tries, a)
                    load[id(a)] += 1
                if not inflight:
                    if retries or not tasks.finished():
                        time.sleep(0.01)
                        continue
                    break
                ready, _ = ray.wait(list(inflight), num_returns=1, timeout=0.5)
                for ref in ready:
                    group, tries, a = inflight.pop(ref)
                    load[id(a)] -= 1
                    try:
                        outs = ray.get(ref)
                    except ray.exceptions.RayActorError as e:
                        pos = next((k for k, x in enumerate(actors) if x is a), None)
                        if pos is not None:  # replace the dead actor (once per death)
                            actors[pos] = self.spawn()
                            load[id(actors[pos])] = 0
                        if tries < MAX_RETRIES:
                            for g in ([group] if coherent else [[ic] for ic in reversed(group)]):
                                retries.appendleft((g, tries + 1))
                            continue
                        outs = [(i, {"error": {"code": "worker_crashed", "message": f"Ray worker died: {e}"}})
                                for i, _ in group]
                    except Exception as e:
                        outs = [(i, {"error": {"code": "internal_error", "message": f"{type(e).__name__}: {e}"}})
                                for i, _ in group]
                    tasks.done(outs)
                    yield outs
            self.last_actor_pids = ray.get([a.pid.remote() for a in actors])
        finally:
            if inflight:  # abandoned (cancel, shutdown): do not leave work queued on the actors
                for ref in inflight:
                    ray.cancel(ref, force=False)
                self._kill_actors()

    def close(self, wait_workers: bool = True):
        if self.ray.is_initialized():
            self._kill_actors()
        if self.owns and self.ray.is_initialized():
            self.ray.shutdown()
