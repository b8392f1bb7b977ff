"""Progress bars that behave in a log file: a live tqdm bar on a terminal; elsewhere (stderr redirected to
a file or a pipe) at most one line every LOG_INTERVAL_S seconds, each ending in a newline, or none.

Needs nothing but the standard library (tqdm is optional: without it no bar is drawn)."""
from __future__ import annotations

import os
import sys
import time

LOG_INTERVAL_S = 10.0  # seconds between two progress lines when stderr is not a terminal


def _is_terminal(stream) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):
        return False


def progress_mode(enabled: bool | str = True, stream=None) -> str:
    """"bar" (a terminal), "log" (not a terminal: a line every LOG_INTERVAL_S s) or "off".

    `enabled`: True (the default: bar or log, as the stream is), False / "off", or "bar" / "log" to force one.
    The environment variable SHADOWOPT_PROGRESS (off, log, bar) overrides True."""
    stream = sys.stderr if stream is None else stream
    if enabled is True:
        env = os.environ.get("SHADOWOPT_PROGRESS", "").strip().lower()
        if env in ("off", "0", "false", "no"):
            return "off"
        if env in ("log", "bar"):
            return env
        return "bar" if _is_terminal(stream) else "log"
    if enabled in ("bar", "log"):
        return enabled
    return "off"


class _LogLines:
    """The log-file form: `desc: done/total state` on its own line, at most once per interval, and once
    at the end (tqdm's interface as far as the callers use it: n, total, update, set_postfix_str, close)."""

    def __init__(self, total: int, desc: str, unit: str, stream, interval_s: float, clock):
        self.total, self.desc, self.unit, self.stream = total, desc, unit, stream
        self.interval_s, self.clock = interval_s, clock
        self.n, self.postfix, self._last, self._printed = 0, "", None, None

    def _line(self) -> str:
        tail = f" {self.postfix}" if self.postfix else ""
        return f"{self.desc}: {self.n}/{self.total} {self.unit}{tail}"

    def _maybe_print(self, force: bool = False) -> None:
        now = self.clock()
        if force or self._last is None or now - self._last >= self.interval_s:
            line = self._line()
            if line != self._printed or not force:
                print(line, file=self.stream, flush=True)
                self._printed = line
            self._last = now

    def update(self, k: int = 1) -> None:
        self.n += k
        self._maybe_print()

    def set_postfix_str(self, s: str = "", refresh: bool = True) -> None:
        self.postfix = s

    def set_postfix(self, **kw) -> None:
        self.postfix = ", ".join(f"{k}={v}" for k, v in kw.items())

    def close(self) -> None:
        self._maybe_print(force=True)


def progress_bar(total: int, desc: str, unit: str = "conf", enabled: bool | str = True, stream=None,
                 interval_s: float = LOG_INTERVAL_S, clock=None):
    """A bar with tqdm's `n`, `total`, `update(k)`, `set_postfix_str`, `set_postfix` and `close`, or None
    when off (or, on a terminal, when tqdm is not installed)."""
    stream = sys.stderr if stream is None else stream
    mode = progress_mode(enabled, stream)
    if mode == "off":
        return None
    if mode == "log":
        return _LogLines(total, desc, unit, stream, interval_s, clock or time.monotonic)
    try:
        from tqdm import tqdm  # lazy: optional (the server extra); the client-only install draws no bar
    except ImportError:
        return None
    return tqdm(total=total, desc=desc, unit=unit, file=stream, dynamic_ncols=True)
