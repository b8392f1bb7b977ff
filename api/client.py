"""Python client for the shadowopt REST API: `Client` (sync) and `AsyncClient` (async), both on httpx.

Needs only httpx and pydantic (tqdm, when installed, draws the progress bar of `wait` on a terminal; in
a log file `wait` writes a line every few seconds instead), so `pip install shadowopt` without the
`server` extra is enough:

    from shadowopt.api.client import Client
    with Client("http://127.0.0.1:8000", token="s3cret") as c:
        scene = c.upload_scene("configs/demo_scene.usda")
        rig = {"camera": {"usd_path": "/World/Camera"}, "lights": [{"usd_path": "/World/Sun"}]}
        solution = c.optimize(scene.scene_id, rig)  # a shadowopt.api.schemas.Solution
        print(solution.lights[0].predicted_error)

Connection errors, 503 (honouring Retry-After) and 429 are retried with exponential backoff;
any other error answer raises `ShadowoptError` (or a subclass) carrying the server's `code`,
`message` and `field`. Rigs are dicts or `shadowopt.api.schemas.Rig` models. Answers are typed models
(`SceneInfo`, `Solution`, `BatchResultLine`, ...); `solution["lights"]` reads them as the JSON too.
"""
from __future__ import annotations

import asyncio
import email.utils
import json
import os
import random
import sys
import time
import zipfile
from collections.abc import AsyncIterator, Callable, Iterator
from dataclasses import dataclass, field
from io import BytesIO
from pathlib import Path
from typing import Any

import httpx
from pydantic import BaseModel

from .progress import progress_bar
from .schemas import BatchCreated, BatchResultLine, BatchStatus, Health, PathFrame, Rig, SceneInfo, Solution

__all__ = ["Client", "AsyncClient", "SceneInfo", "Solution", "BatchResultLine", "PathFrame", "PathFrames", "BatchCreated", "BatchStatus",
           "Health",
           "ShadowoptError", "ClientError", "AuthError",
           "NotFoundError", "ServerError", "ConnectionFailed", "TERMINAL_STATES"]

TERMINAL_STATES = ("done", "failed", "cancelled")
RETRY_STATUSES = (429, 503)
MAX_RETRY_AFTER_S = 60.0
RESULTS_PAGE = 1000  # result lines per GET .../results request when iterating a batch's results
DEFAULT_URL = "http://127.0.0.1:8000"  # `shadowopt serve`'s default; SHADOWOPT_URL overrides it


# ---------------------------------------------------------------- errors

class ShadowoptError(Exception):
    """An error answer of the server (or no answer at all): HTTP status, machine-readable code,
    message, the offending request field when the server names one, and the echoed request id."""

    def __init__(self, status: int | None, code: str, message: str, field: str | None = None,
                 request_id: str | None = None):
        self.status, self.code, self.message, self.field, self.request_id = status, code, message, field, request_id
        where = f" (field {field})" if field else ""
        super().__init__(f"{status or 'no answer'} {code}: {message}{where}")


class ClientError(ShadowoptError):
    """A 4xx: the request was wrong; repeating it will not help."""


class AuthError(ClientError):
    """401/403: missing, unknown or insufficient bearer token."""


class NotFoundError(ClientError):
    """404: no such scene or batch for this token's tenant."""


class ServerError(ShadowoptError):
    """A 5xx that retries did not cure."""


class ConnectionFailed(ShadowoptError):
    """No answer from the server after the retries (connection refused, reset, ...)."""


def error_from_response(resp: httpx.Response) -> ShadowoptError:
    """Build the exception for an error answer: `{"error": {"code", "message", "field"?}}`, FastAPI's
    `{"detail": ...}`, or plain text."""
    status, code, message, fld = resp.status_code, f"http_{resp.status_code}", resp.reason_phrase, None
    try:
        body = resp.json()
    except ValueError:
        body = None
        message = resp.text.strip()[:500] or message
    err = body.get("error", body.get("detail")) if isinstance(body, dict) else None
    if isinstance(err, dict):
        code, message, fld = str(err.get("code", code)), str(err.get("message", message)), err.get("field")
    elif isinstance(err, str):
        message = err
    elif isinstance(err, list) and err:  # FastAPI's default validation error list
        first = err[0] if isinstance(err[0], dict) else {}
        code, message = "invalid_request", str(first.get("msg", message))
        fld = ".".join(str(p) for p in first.get("loc", ())[1:]) or None
    cls = (AuthError if status in (401, 403) else NotFoundError if status == 404
           else ClientError if status < 500 else ServerError)
    return cls(status, code, message, fld, resp.headers.get("x-request-id"))


# ---------------------------------------------------------------- request building (shared by both clients)

@dataclass
class _Call:
    method: str
    path: str
    json: Any = None
    params: dict | None = None
    files: dict | None = None
    parse: Callable[[httpx.Response], Any] = field(default=lambda r: _json_or_none(r))
    idempotent: bool = True  # may be resent after a connection dropped mid-request
    accept: tuple[int, ...] = ()  # error statuses returned to `parse` instead of raised or retried


def _json_or_none(resp: httpx.Response):
    return resp.json() if resp.content else None


def _drop_none(d: dict) -> dict:
    return {k: v for k, v in d.items() if v is not None}


def rig_json(rig) -> dict:
    """A rig as JSON: a `Rig` model (dumped by alias, unset optionals left out) or a dict (as given)."""
    if isinstance(rig, BaseModel):
        out = rig.model_dump(mode="json", by_alias=True, exclude_none=True)
        spec = getattr(rig, "output", None)
        if isinstance(out.get("output"), dict) and getattr(spec, "engine", None):
            # an engine preset fills convention, layout and reversed_z on the server; a bare client (no
            # rendering stack) cannot, and their defaults would contradict the preset: send what was set
            out["output"] = spec.model_dump(mode="json", by_alias=True, exclude_none=True, exclude_unset=True)
        return out
    if isinstance(rig, dict):
        return rig
    raise TypeError(f"rig: expected a dict or shadowopt.api.schemas.Rig, got {type(rig).__name__}")


def plain(obj):
    """A pydantic model (e.g. a `Solution` passed back as `previous`) as JSON data; anything else as is."""
    return obj.model_dump(mode="json", by_alias=True) if isinstance(obj, BaseModel) else obj


def configuration_json(item) -> dict:
    """A batch configuration: `{"rig": RIG, ...}` as given, or a bare rig (dict or `Rig`) wrapped."""
    if isinstance(item, dict) and "rig" in item:
        return {**item, "rig": rig_json(item["rig"])}
    return {"rig": rig_json(item)}


def time_json(time) -> dict | None:
    """A path's time codes: {"start", "end", "step"}, (start, end[, step]) or "START:END[:STEP]"."""
    if time is None or isinstance(time, dict):
        return time
    parts = [float(p) for p in time.split(":")] if isinstance(time, str) else [float(p) for p in time]
    if len(parts) not in (2, 3):
        raise ValueError(f"time: expected start, end[, step], got {time!r}")
    return {"start": parts[0], "end": parts[1], "step": parts[2] if len(parts) == 3 else 1.0}


def batch_id_of(batch) -> str:
    return batch if isinstance(batch, str) else batch.batch_id


def _scene_upload(path_or_bytes, filename: str | None, pack: bool | None = None) -> dict:
    if isinstance(path_or_bytes, (bytes, bytearray, memoryview)):
        data, name = bytes(path_or_bytes), filename or "scene.usda"
    else:
        data, name = scene_bytes(Path(path_or_bytes), pack)
        name = filename or name
    return {"file": (name, data, "application/octet-stream")}


def zip_folder_bytes(folder) -> tuple[bytes, str]:
    """A local folder as .zip bytes and its name (regular files only: symbolic links, to files or folders,
    are left out, so nothing outside the folder is sent). Standard library only: the bare client zips."""
    folder = Path(folder)
    buf = BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
        for top, dirs, files in os.walk(folder, followlinks=False):
            dirs.sort()
            for name in sorted(files):
                p = Path(top) / name
                if p.is_file() and not p.is_symlink():
                    z.write(p, p.relative_to(folder).as_posix())
    return buf.getvalue(), folder.name + ".zip"


def scene_bytes(path: Path, pack: bool | None = None) -> tuple[bytes, str]:
    """What `upload_scene` sends for a local path: a folder as a .zip (the server finds its root layer);
    a stage that names other files (references, sublayers, payloads) packed as one .usdz with usd-core's
    UsdUtils (service.packing, imported only here, when usd-core is installed); anything else as it is.
    `pack=None` packs a stage that needs it, but refuses (SceneError "outside_folder", naming them) one
    naming files outside its folder, which would be uploaded with it; `pack=True` packs whatever the stage
    names; `pack=False` sends the file as it is."""
    path = Path(path)
    if path.is_dir():
        return zip_folder_bytes(path)
    if pack is not False and path.suffix.lower() in (".usd", ".usda", ".usdc"):
        try:
            from ..renderers.scene_data import SceneError  # lazy: numpy and usd-core: the server extra
            from ..service.packing import needs_package, pack_bytes  # lazy: the bare client install lacks them
        except ImportError:  # the bare client install: no usd-core; the server says what it cannot open
            if pack:
                raise
        else:
            try:
                if pack or needs_package(path):
                    return pack_bytes(path, allow_outside=bool(pack))
            except (ImportError, SceneError) as e:  # no usd-core, or a stage it cannot read: the server says why
                if pack or getattr(e, "code", None) == "outside_folder":
                    raise
    return path.read_bytes(), path.name


class _Calls:
    """One `_Call` per endpoint; the two clients only differ in how they send it."""

    @staticmethod
    def health():
        return _Call("GET", "/healthz", accept=(503,), parse=lambda r: Health.model_validate(r.json()))

    @staticmethod
    def upload_scene(path_or_bytes, filename, pack=None):
        return _Call("POST", "/v1/scenes", files=_scene_upload(path_or_bytes, filename, pack),
                     parse=lambda r: SceneInfo.model_validate(r.json()))

    @staticmethod
    def list_scenes():
        return _Call("GET", "/v1/scenes", parse=lambda r: r.json()["scenes"])

    @staticmethod
    def get_scene(scene_id):
        return _Call("GET", f"/v1/scenes/{scene_id}", parse=lambda r: SceneInfo.model_validate(r.json()))

    @staticmethod
    def delete_scene(scene_id):
        return _Call("DELETE", f"/v1/scenes/{scene_id}", parse=lambda r: bool(r.json().get("deleted")))

    @staticmethod
    def optimize(scene_id, rig, method, solver, time_budget_ms, previous, options):
        body = _drop_none({"scene_id": scene_id, "rig": rig_json(rig), "method": method, "solver": solver,
                           "time_budget_ms": time_budget_ms, "previous": plain(previous), **options})
        return _Call("POST", "/v1/optimize", json=body, parse=lambda r: Solution.model_validate(r.json()))

    @staticmethod
    def evaluate(scene_id, rig, solution, options):
        body = _drop_none({"scene_id": scene_id, "rig": rig_json(rig), "solution": plain(solution), **options})
        return _Call("POST", "/v1/evaluate", json=body)

    @staticmethod
    def compare(scene_id, rig, methods, options):
        body = _drop_none({"scene_id": scene_id, "rig": rig_json(rig),
                           "methods": list(methods) if methods is not None else None, **options})
        return _Call("POST", "/v1/compare", json=body)

    @staticmethod
    def tune(scene_id, rig, engine, settings, poses, options):
        body = _drop_none({"scene_id": scene_id, "rig": rig_json(rig), "engine": engine, "settings": plain(settings),
                           "poses": plain(poses), **options})
        return _Call("POST", "/v1/tune", json=body)

    @staticmethod
    def analyze(options):
        return _Call("POST", "/v1/analyze", json=_drop_none(options))

    @staticmethod
    def submit_batch(scene_id, configurations, method, options):
        confs = None if configurations is None else [configuration_json(c) for c in configurations]
        body = _drop_none({"scene_id": scene_id, "configurations": confs, "method": method, **options})
        return _Call("POST", "/v1/batches", json=body, parse=lambda r: BatchCreated.model_validate(r.json()),
                     idempotent=False)

    @staticmethod
    def submit_path(scene_id, rig, camera_path, usd_camera, time, method, coherent, options):
        body = _drop_none({"scene_id": scene_id, "rig": rig_json(rig), "camera_path": plain(camera_path),
                           "usd_camera": usd_camera, "time": time_json(time), "method": method,
                           "coherent": coherent, **options})
        return _Call("POST", "/v1/paths", json=body, parse=lambda r: BatchCreated.model_validate(r.json()),
                     idempotent=False)

    @staticmethod
    def batch(batch):
        return _Call("GET", f"/v1/batches/{batch_id_of(batch)}", parse=lambda r: BatchStatus.model_validate(r.json()))

    @staticmethod
    def cancel_batch(batch):
        return _Call("DELETE", f"/v1/batches/{batch_id_of(batch)}",
                     parse=lambda r: BatchStatus.model_validate(r.json()))

    @staticmethod
    def results(batch, offset, limit=None):
        params = {"offset": offset} if limit is None else {"offset": offset, "limit": limit}
        return _Call("GET", f"/v1/batches/{batch_id_of(batch)}/results", params=params)


# ---------------------------------------------------------------- transport policy (shared)

_NOT_SENT = (httpx.ConnectError, httpx.ConnectTimeout)  # the server never saw the request
_DROPPED = (httpx.RemoteProtocolError, httpx.ReadError, httpx.WriteError)  # the connection broke midway


class PathFrames:
    """What `optimize_path` returns: an iterator of `PathFrame`s in frame order, with the job's `batch_id` and
    `created` answer (its `notes`, `total`); `resume(offset)` iterates again from frame `offset`."""

    def __init__(self, created: BatchCreated, frames):
        self.created, self.batch_id, self._frames = created, created.batch_id, frames
        self._it = frames()

    def __iter__(self):
        return self

    def __next__(self) -> PathFrame:
        return next(self._it)

    def resume(self, offset: int) -> Iterator[PathFrame]:
        return self._frames(offset)


class _Base:
    def __init__(self, base_url: str | None = None, token: str | None = None, timeout: float = 120.0,
                 retries: int = 3, backoff_s: float = 0.25):
        base_url = base_url or os.environ.get("SHADOWOPT_URL") or DEFAULT_URL
        self.base_url = base_url.rstrip("/")
        self.token = token if token is not None else os.environ.get("SHADOWOPT_TOKEN")
        self.timeout = httpx.Timeout(timeout, connect=min(10.0, timeout))
        self.retries = retries
        self.backoff_s = backoff_s

    def _headers(self) -> dict:
        h = {"Accept": "application/json", "User-Agent": "shadowopt-client"}
        if self.token:
            h["Authorization"] = f"Bearer {self.token}"
        return h

    def _delay(self, attempt: int, resp: httpx.Response | None = None) -> float:
        """Retry-After when the server sent one (seconds or an HTTP date), else exponential backoff."""
        if resp is not None and (ra := resp.headers.get("retry-after")):
            try:
                return min(max(float(ra), 0.0), MAX_RETRY_AFTER_S)
            except ValueError:
                try:
                    when = email.utils.parsedate_to_datetime(ra).timestamp()
                    return min(max(when - time.time(), 0.0), MAX_RETRY_AFTER_S)
                except (TypeError, ValueError):
                    pass
        return self.backoff_s * (2 ** attempt) * (1 + 0.25 * random.random())

    def _retryable_exc(self, call: _Call, e: Exception) -> bool:
        return isinstance(e, _NOT_SENT) or (call.idempotent and isinstance(e, _DROPPED))

    def _request(self, http, call: _Call) -> httpx.Request:
        return http.build_request(call.method, call.path, json=call.json, params=call.params, files=call.files)

    def _outcome(self, call: _Call, resp: httpx.Response, attempt: int):
        """('retry', delay) | ('ok', None) | ('error', exception) for an answer."""
        if resp.status_code in call.accept or resp.status_code < 400:
            return "ok", None
        if resp.status_code in RETRY_STATUSES and attempt < self.retries:
            return "retry", self._delay(attempt, resp)
        return "error", error_from_response(resp)

    @staticmethod
    def _connection_failed(call: _Call, e: Exception) -> ConnectionFailed:
        return ConnectionFailed(None, "connection_error", f"{call.method} {call.path}: {type(e).__name__}: {e}")


def _progress_bar(total: int, desc: str, enabled: bool | str):
    """api.progress.progress_bar: a tqdm bar on a terminal, a line every few seconds in a log file."""
    return progress_bar(total, desc, unit="conf", enabled=enabled, stream=sys.stderr)


def _finished(bar, st, deadline: float | None, timeout: float | None) -> bool:
    """One poll of wait(): draw the bar; True once the batch is done, failed or cancelled; TimeoutError
    past the deadline."""
    _update_bar(bar, st)
    if st.state in TERMINAL_STATES:
        return True
    if deadline is not None and time.monotonic() > deadline:
        raise TimeoutError(f"batch {st.batch_id} still {st.state} after {timeout} s ({st.done}/{st.total})")
    return False


def _update_bar(bar, st: BatchStatus) -> None:
    if bar is not None:
        if st.total and bar.total != st.total:
            bar.total = st.total
        bar.set_postfix_str(st.state, refresh=False)
        bar.update(st.done - bar.n)  # redraws at most as often as the bar's interval allows


# ---------------------------------------------------------------- sync

class Client(_Base):
    """Synchronous client. `Client(base_url=None, token=None, timeout=120, retries=3)`; the URL defaults to
    the environment variable SHADOWOPT_URL (else http://127.0.0.1:8000), the token to SHADOWOPT_TOKEN. Use
    as a context manager or call `close()`."""

    def __init__(self, base_url: str | None = None, token: str | None = None, timeout: float = 120.0, retries: int = 3,
                 backoff_s: float = 0.25, transport: httpx.BaseTransport | None = None):
        super().__init__(base_url, token, timeout, retries, backoff_s)
        self._http = httpx.Client(base_url=self.base_url, headers=self._headers(), timeout=self.timeout,
                                  transport=transport)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def close(self) -> None:
        self._http.close()

    def _send(self, call: _Call, stream: bool = False) -> httpx.Response:
        attempt = 0
        while True:
            try:
                resp = self._http.send(self._request(self._http, call), stream=stream)
            except httpx.TransportError as e:
                if not self._retryable_exc(call, e) or attempt >= self.retries:
                    raise self._connection_failed(call, e) from e
                time.sleep(self._delay(attempt))
                attempt += 1
                continue
            verdict, extra = self._outcome(call, resp, attempt)
            if verdict == "ok":
                return resp
            resp.read()
            resp.close()
            if verdict == "error":
                raise extra
            time.sleep(extra)
            attempt += 1

    def _call(self, call: _Call):
        return call.parse(self._send(call))

    def health(self) -> Health:
        """`GET /healthz`: `status` "ok", or "warming" (the server answers 503 until it is warm)."""
        return self._call(_Calls.health())

    def wait_ready(self, timeout: float = 120.0, poll_s: float = 0.2) -> dict:
        """Poll `/healthz` until it answers 200 (the server is up and warm); TimeoutError otherwise."""
        deadline = time.monotonic() + timeout
        while True:
            try:
                resp = self._http.get("/healthz")
                if resp.status_code == 200:
                    return resp.json()
            except httpx.TransportError:
                pass
            if time.monotonic() > deadline:
                raise TimeoutError(f"{self.base_url}/healthz not ready after {timeout} s")
            time.sleep(poll_s)

    def upload_scene(self, path_or_bytes, filename: str | None = None, pack: bool | None = None) -> SceneInfo:
        """Upload a .usd/.usda/.usdc/.usdz or a .zip of a scene's folder (a path or its bytes; give `filename`
        with bytes of another kind). A local stage that names other files is packed into one .usdz first
        (with usd-core installed; `pack=False` sends it as it is), a folder is sent as a .zip. A stage naming
        files outside its own folder is not packed unless `pack=True` (SceneError "outside_folder" naming
        them): those files would be uploaded too."""
        return self._call(_Calls.upload_scene(path_or_bytes, filename, pack))

    def list_scenes(self) -> list[dict]:
        return self._call(_Calls.list_scenes())

    def get_scene(self, scene_id: str) -> SceneInfo:
        return self._call(_Calls.get_scene(scene_id))

    def delete_scene(self, scene_id: str) -> bool:
        return self._call(_Calls.delete_scene(scene_id))

    def optimize(self, scene_id: str, rig: dict | Rig, method: str = "optimized", solver: str | None = None,
                 time_budget_ms: float | None = None, previous: dict | Solution | None = None,
                 **options) -> Solution:
        """`POST /v1/optimize`: the `Solution` (per light and cascade: matrices, resolution, warp, split,
        predicted error; timings and solver diagnostics). Extra keyword arguments go into the body."""
        return self._call(_Calls.optimize(scene_id, rig, method, solver, time_budget_ms, previous, options))

    def evaluate(self, scene_id: str, rig: dict | Rig, solution: dict | Solution, **options) -> dict:
        """`POST /v1/evaluate`: a solution against exact ray-traced shadows (misclassified pixels,
        measured error; counts and measured error at `screen`, predicted error in the rig's pixels); options
        such as `screen`, `heatmap` or `heatmap_mode` ("m" or "errors") go into the body."""
        return self._call(_Calls.evaluate(scene_id, rig, solution, options))

    def compare(self, scene_id: str, rig: dict | Rig, methods: list[str] | None = None, **options) -> dict:
        """`POST /v1/compare`: methods side by side (predicted and measured error, setup time)."""
        return self._call(_Calls.compare(scene_id, rig, methods, options))

    def tune(self, scene_id: str, rig: dict | Rig, engine: str = "three", settings: dict | None = None,
             poses: list[dict] | None = None, **options) -> dict:
        """`POST /v1/tune`: the engine's own cascade settings (its own knob names) that predict the fewest wrong
        pixels over the rig's pose and `poses`, with `predicted`, `defaults`, `emulated` cascades and a JS
        `snippet`; `settings` pins knobs (docs/tune.md)."""
        return self._call(_Calls.tune(scene_id, rig, engine, settings, poses, options))

    def analyze(self, **options) -> dict:
        """`POST /v1/analyze` (scene-independent), e.g. `analyze(f_over_n=100, theta_deg=30, gamma_deg=90,
        method="perspective")`."""
        return self._call(_Calls.analyze(options))

    def submit_batch(self, scene_id: str, configurations: list | None = None, method: str = "optimized",
                     **options) -> BatchCreated:
        """`POST /v1/batches` -> 202 `{"batch_id", ...}`. `configurations`: rigs (dicts or `Rig`) or
        `{"rig": RIG, ...}` items; the camera-path form and other settings go in as keyword arguments.
        Not resent after a connection drops midway (it could create the batch twice)."""
        return self._call(_Calls.submit_batch(scene_id, configurations, method, options))

    def submit_path(self, scene_id: str, rig: dict | Rig, *, camera_path: dict | None = None,
                    usd_camera: str | None = None, time=None, method: str = "optimized", coherent: bool = False,
                    **options) -> BatchCreated:
        """`POST /v1/paths` -> 202 `{"batch_id", "total", "coherent", "notes"}`: a camera path (`camera_path`:
        poses or keyframes + samples) or a USD camera animated by time samples (`usd_camera`, `time`:
        {"start", "end", "step"}, (start, end, step) or "START:END:STEP"), solved frame by frame as a batch."""
        return self._call(_Calls.submit_path(scene_id, rig, camera_path, usd_camera, time, method, coherent, options))

    def optimize_path(self, scene_id: str, rig: dict | Rig, *, camera_path: dict | None = None,
                      usd_camera: str | None = None, time=None, method: str = "optimized", coherent: bool = False,
                      poll_s: float = 0.5, **options) -> PathFrames:
        """Submit a path (as `submit_path`, at once) and iterate its frames in order as they finish: `PathFrame`
        (`frame`, `time` and the solution's fields, or `error`; `frame.solution()` gives a `Solution`)."""
        created = self.submit_path(scene_id, rig, camera_path=camera_path, usd_camera=usd_camera, time=time,
                                   method=method, coherent=coherent, **options)

        def frames(offset: int = 0):
            for line in self.iter_results(created, offset=offset, follow=True, poll_s=poll_s):
                yield PathFrame.model_validate(line.model_dump(mode="json", by_alias=True))
        return PathFrames(created, frames)

    def batch(self, batch) -> BatchStatus:
        """`GET /v1/batches/{id}`: state, done, total, errors."""
        return self._call(_Calls.batch(batch))

    def cancel_batch(self, batch) -> BatchStatus:
        """`DELETE /v1/batches/{id}`."""
        return self._call(_Calls.cancel_batch(batch))

    def wait(self, batch, progress: bool | str = True, poll_s: float = 0.5,
             timeout: float | None = None) -> BatchStatus:
        """Poll the batch until done, failed or cancelled; returns the final status. TimeoutError after
        `timeout` seconds. `progress`: True draws a tqdm bar on stderr when it is a terminal (and tqdm is
        installed) and otherwise writes one line every few seconds (a log file stays readable); False: nothing.
        The environment variable SHADOWOPT_PROGRESS=off|log|bar overrides True."""
        deadline = None if timeout is None else time.monotonic() + timeout
        st = self.batch(batch)
        bar = _progress_bar(st.total, f"batch {st.batch_id}", progress)
        try:
            while not _finished(bar, st, deadline, timeout):
                time.sleep(poll_s)
                st = self.batch(batch)
            return st
        finally:
            if bar is not None:
                bar.close()

    def iter_results(self, batch, offset: int = 0, follow: bool = False,
                     poll_s: float = 0.5, page: int = RESULTS_PAGE) -> Iterator[BatchResultLine]:
        """Result lines (`BatchResultLine`: `index` and the solution's fields, or `error`; in configuration
        order) from `offset` on; `line.solution()` gives a line as a `Solution`. A connection that
        breaks mid-stream is resumed after the last line received. With `follow`, keeps going until
        the batch has finished and every result has been read. Read `page` lines per request (the next
        page from the last index + 1): neither side holds more than a page, whatever the batch's size."""
        call_at = lambda off: _Calls.results(batch, off, page)  # noqa: E731
        nxt, failures = offset, 0
        while True:
            final = self.batch(batch).state in TERMINAL_STATES if follow else True
            got = 0
            try:
                resp = self._send(call_at(nxt), stream=True)
                try:
                    for line in resp.iter_lines():
                        if line.strip():
                            item = BatchResultLine.model_validate(json.loads(line))
                            nxt = item.index + 1
                            failures = 0
                            got += 1
                            yield item
                finally:
                    resp.close()
            except httpx.TransportError as e:  # mid-stream: resume after the last line received
                failures += 1
                if failures > self.retries:
                    raise self._connection_failed(call_at(nxt), e) from e
                time.sleep(self._delay(failures - 1))
                continue
            if got >= page:  # a full page: the next one at once
                continue
            if final:
                return
            time.sleep(poll_s)


# ---------------------------------------------------------------- async

class AsyncClient(_Base):
    """The same methods as `Client`, as coroutines (`iter_results` is an async iterator)."""

    def __init__(self, base_url: str | None = None, token: str | None = None, timeout: float = 120.0, retries: int = 3,
                 backoff_s: float = 0.25, transport: httpx.AsyncBaseTransport | None = None):
        super().__init__(base_url, token, timeout, retries, backoff_s)
        self._http = httpx.AsyncClient(base_url=self.base_url, headers=self._headers(), timeout=self.timeout,
                                       transport=transport)

    async def __aenter__(self):
        return self

    async def __aexit__(self, *exc):
        await self.aclose()

    async def aclose(self) -> None:
        await self._http.aclose()

    async def _send(self, call: _Call, stream: bool = False) -> httpx.Response:
        attempt = 0
        while True:
            try:
                resp = await self._http.send(self._request(self._http, call), stream=stream)
            except httpx.TransportError as e:
                if not self._retryable_exc(call, e) or attempt >= self.retries:
                    raise self._connection_failed(call, e) from e
                await asyncio.sleep(self._delay(attempt))
                attempt += 1
                continue
            verdict, extra = self._outcome(call, resp, attempt)
            if verdict == "ok":
                return resp
            await resp.aread()
            await resp.aclose()
            if verdict == "error":
                raise extra
            await asyncio.sleep(extra)
            attempt += 1

    async def _call(self, call: _Call):
        resp = await self._send(call)
        return call.parse(resp)

    async def health(self) -> Health:
        return await self._call(_Calls.health())

    async def wait_ready(self, timeout: float = 120.0, poll_s: float = 0.2) -> dict:
        deadline = time.monotonic() + timeout
        while True:
            try:
                resp = await self._http.get("/healthz")
                if resp.status_code == 200:
                    return resp.json()
            except httpx.TransportError:
                pass
            if time.monotonic() > deadline:
                raise TimeoutError(f"{self.base_url}/healthz not ready after {timeout} s")
            await asyncio.sleep(poll_s)

    async def upload_scene(self, path_or_bytes, filename: str | None = None, pack: bool | None = None) -> SceneInfo:
        return await self._call(_Calls.upload_scene(path_or_bytes, filename, pack))

    async def list_scenes(self) -> list[dict]:
        return await self._call(_Calls.list_scenes())

    async def get_scene(self, scene_id: str) -> SceneInfo:
        return await self._call(_Calls.get_scene(scene_id))

    async def delete_scene(self, scene_id: str) -> bool:
        return await self._call(_Calls.delete_scene(scene_id))

    async def optimize(self, scene_id: str, rig: dict | Rig, method: str = "optimized", solver: str | None = None,
                       time_budget_ms: float | None = None, previous: dict | Solution | None = None,
                       **options) -> Solution:
        return await self._call(_Calls.optimize(scene_id, rig, method, solver, time_budget_ms, previous, options))

    async def tune(self, scene_id: str, rig: dict | Rig, engine: str = "three", settings: dict | None = None,
                   poses: list[dict] | None = None, **options) -> dict:
        return await self._call(_Calls.tune(scene_id, rig, engine, settings, poses, options))

    async def evaluate(self, scene_id: str, rig: dict | Rig, solution: dict | Solution, **options) -> dict:
        return await self._call(_Calls.evaluate(scene_id, rig, solution, options))

    async def compare(self, scene_id: str, rig: dict | Rig, methods: list[str] | None = None, **options) -> dict:
        return await self._call(_Calls.compare(scene_id, rig, methods, options))

    async def analyze(self, **options) -> dict:
        return await self._call(_Calls.analyze(options))

    async def submit_batch(self, scene_id: str, configurations: list | None = None, method: str = "optimized",
                           **options) -> BatchCreated:
        return await self._call(_Calls.submit_batch(scene_id, configurations, method, options))

    async def batch(self, batch) -> BatchStatus:
        return await self._call(_Calls.batch(batch))

    async def cancel_batch(self, batch) -> BatchStatus:
        return await self._call(_Calls.cancel_batch(batch))

    async def wait(self, batch, progress: bool | str = True, poll_s: float = 0.5,
                   timeout: float | None = None) -> BatchStatus:
        deadline = None if timeout is None else time.monotonic() + timeout
        st = await self.batch(batch)
        bar = _progress_bar(st.total, f"batch {st.batch_id}", progress)
        try:
            while not _finished(bar, st, deadline, timeout):
                await asyncio.sleep(poll_s)
                st = await self.batch(batch)
            return st
        finally:
            if bar is not None:
                bar.close()

    async def iter_results(self, batch, offset: int = 0, follow: bool = False,
                           poll_s: float = 0.5, page: int = RESULTS_PAGE) -> AsyncIterator[BatchResultLine]:
        call_at = lambda off: _Calls.results(batch, off, page)  # noqa: E731
        nxt, failures = offset, 0
        while True:
            final = (await self.batch(batch)).state in TERMINAL_STATES if follow else True
            got = 0
            try:
                resp = await self._send(call_at(nxt), stream=True)
                try:
                    async for line in resp.aiter_lines():
                        if line.strip():
                            item = BatchResultLine.model_validate(json.loads(line))
                            nxt = item.index + 1
                            failures = 0
                            got += 1
                            yield item
                finally:
                    await resp.aclose()
            except httpx.TransportError as e:  # mid-stream: resume after the last line received
                failures += 1
                if failures > self.retries:
                    raise self._connection_failed(call_at(nxt), e) from e
                await asyncio.sleep(self._delay(failures - 1))
                continue
            if got >= page:  # a full page: the next one at once
                continue
            if final:
                return
            await asyncio.sleep(poll_s)
