"""The CLI's batch and path: a job run by a BatchRunner on a temporary Store, so execution is the server's,
its result lines streamed (to a JSON-lines file, or to a callback in frame order) under the caller's progress bar
(`progress`: a factory (total, desc, unit) -> bar or None, as api.progress.progress_bar; service draws nothing itself)."""
from __future__ import annotations

import contextlib
import os
import tempfile
import time

from ..renderers.json_text import dumps
from ..renderers.scene_data import SceneError
from .job_runner import BatchRunner
from .job_workers import DEFAULT_METHOD
from .paths import is_coherent, is_whole_path
from .store import UNFINISHED, Store


class NullBar:
    """The bar's interface doing nothing but count: what a caller uses when progress_bar gives None."""

    n = 0

    def update(self, k: int = 1) -> None:
        self.n += k

    def set_postfix(self, **kw) -> None:
        pass

    def close(self) -> None:
        pass


@contextlib.contextmanager
def local_job(scene_path, items: list[dict], settings: dict, what: str, backend: str = "local", workers: int = 2,
              ray_address: str | None = None):
    """A job of `items` queued on a BatchRunner over a temporary Store (tenant "local"): yields (runner,
    store, batch_id); the runner is shut down and the Store removed after."""
    with tempfile.TemporaryDirectory(prefix=f"shadowopt-{what}-") as tmp:
        store = Store(tmp)
        runner = BatchRunner(store, backend=backend, workers=workers, ray_address=ray_address)
        try:
            scene_id = store.link_scene("local", scene_path)
            batch_id = store.create_batch("local", scene_id, items, settings)
            runner.submit("local", batch_id)
            yield runner, store, batch_id
        finally:
            runner.shutdown()
            store.close()


RESULTS_PAGE = 1000  # result lines read from the store at a time


def follow(runner: BatchRunner, store: Store, batch_id: str, bar, on_lines, show_failed: bool = False) -> None:
    """Until the job is finished: the bar counts its done and failed items (and, with show_failed, says how many
    failed), and `on_lines(lines)` gets the result lines stored since, in index order."""
    next_index = 0
    while True:
        state = runner.wait(batch_id, timeout=0.25)
        st = store.batch("local", batch_id, max_errors=0)
        bar.update(st["done"] + st["failed"] - bar.n)
        if show_failed and st["failed"]:
            bar.set_postfix(failed=st["failed"])
        while True:  # a page at a time: a big batch's lines never sit in memory together
            lines = store.results("local", batch_id, offset=next_index, limit=RESULTS_PAGE)
            if lines:
                on_lines(lines)
                next_index = lines[-1]["index"] + 1
            if len(lines) < RESULTS_PAGE:
                break
        if state not in UNFINISHED:
            break


def run_batch(scene_path, configurations: list[dict], backend: str = "local", workers: int = 2,
              out_path=None, method: str = DEFAULT_METHOD, progress=None, solver: str | None = None,
              time_budget_ms: float | None = None, ray_address: str | None = None) -> dict:
    """Run configurations (each {"rig": validated rig}) on a scene file; write JSON lines (one per
    configuration, in index order, each with "index"; failures as {"index", "error"}) to out_path as
    they complete. Uses a temporary Store, so execution is the server's. Returns a summary."""
    if not os.path.isfile(scene_path):
        raise SceneError("not_found", f"cannot open scene {os.fspath(scene_path)!r}: no such file")
    settings = {"method": method, "solver": solver, "time_budget_ms": time_budget_ms}
    t0 = time.perf_counter()
    with local_job(scene_path, configurations, settings, "batch", backend, workers,
                   ray_address) as (runner, store, batch_id):
        bar = (progress and progress(len(configurations), "batch", "config")) or NullBar()
        out = open(out_path, "w") if out_path else None

        def write(lines):
            if out is not None:
                out.writelines(dumps(line) + "\n" for line in lines)
                out.flush()

        try:
            follow(runner, store, batch_id, bar, write, show_failed=True)
        finally:
            bar.close()
            if out is not None:
                out.close()
        st = store.batch("local", batch_id)
    return {"state": st["state"], "total": st["total"], "done": st["done"], "failed": st["failed"],
            "errors": st["errors"], "seconds": round(time.perf_counter() - t0, 3), "out": str(out_path)}


def run_path(scene_path, frames: list[dict], *, method: str = "optimized", coherent: bool = False,
             workers: int = 2, on_line=None, progress=None, solver: str | None = None,
             time_budget_ms: float | None = None, backend: str = "local", ray_address: str | None = None) -> dict:
    """Solve the frames (validated {"rig", "frame", "time"}) as a batch in a temporary Store; call
    `on_line(line)` for each result line in frame order as soon as it and every frame before it are done.
    A coherent path runs as `workers` coherent chunks in parallel (service.job_kinds.chunk_starts: one fresh start per chunk;
    a path shorter than MIN_CHUNK_FRAMES per worker stays one chunk). Returns a summary {state, total,
    done, failed, errors, seconds}."""
    if not os.path.isfile(scene_path):
        raise SceneError("not_found", f"cannot open scene {os.fspath(scene_path)!r}: no such file")
    settings = {"method": method, "solver": solver, "time_budget_ms": time_budget_ms,
                "coherent": is_coherent(method, coherent), "whole_path": is_whole_path(method, coherent)}
    if settings["coherent"] and workers > 1:
        settings["coherent_chunks"] = workers
    t0 = time.perf_counter()
    with local_job(scene_path, frames, settings, "path", backend, workers, ray_address) as (runner, store, batch_id):
        bar = (progress and progress(len(frames), "path", "frame")) or NullBar()

        def each(lines):
            for line in lines:
                if on_line is not None:
                    on_line(line)

        try:
            follow(runner, store, batch_id, bar, each)
        finally:
            bar.close()
        st = store.batch("local", batch_id)
    return {"state": st["state"], "total": st["total"], "done": st["done"], "failed": st["failed"],
            "errors": st["errors"], "seconds": round(time.perf_counter() - t0, 3)}
