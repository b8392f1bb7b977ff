"""Prometheus metrics in the text exposition format (0.0.4), written by hand: counters, histograms, gauges."""
from __future__ import annotations

import bisect
import math
import threading
from typing import Callable

LATENCY_BUCKETS = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0)


def _labels(names: tuple[str, ...], values: tuple) -> str:
    if not names:
        return ""
    esc = (str(v).replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n") for v in values)
    return "{" + ",".join(f'{n}="{v}"' for n, v in zip(names, esc)) + "}"


def _num(v: float) -> str:
    if math.isinf(v):
        return "+Inf" if v > 0 else "-Inf"
    return repr(float(v)) if not float(v).is_integer() else str(int(v))


class Counter:
    def __init__(self, name: str, help: str, labels: tuple[str, ...] = ()):
        self.name, self.help, self.labels = name, help, labels
        self._values: dict[tuple, float] = {}
        self._lock = threading.Lock()

    def inc(self, *labels, by: float = 1.0) -> None:
        with self._lock:
            self._values[labels] = self._values.get(labels, 0.0) + by

    def render(self) -> list[str]:
        out = [f"# HELP {self.name} {self.help}", f"# TYPE {self.name} counter"]
        with self._lock:
            out += [f"{self.name}{_labels(self.labels, k)} {_num(v)}" for k, v in sorted(self._values.items())]
        return out


class Histogram:
    def __init__(self, name: str, help: str, labels: tuple[str, ...] = (), buckets=LATENCY_BUCKETS):
        self.name, self.help, self.labels, self.buckets = name, help, labels, tuple(buckets)
        self._values: dict[tuple, list] = {}  # labels -> [bucket counts..., sum, count]
        self._lock = threading.Lock()

    def observe(self, value: float, *labels) -> None:
        i = bisect.bisect_left(self.buckets, value)
        with self._lock:
            v = self._values.setdefault(labels, [0] * len(self.buckets) + [0.0, 0])
            if i < len(self.buckets):
                v[i] += 1
            v[-2] += value
            v[-1] += 1

    def render(self) -> list[str]:
        out = [f"# HELP {self.name} {self.help}", f"# TYPE {self.name} histogram"]
        names = self.labels + ("le",)
        with self._lock:
            for k, v in sorted(self._values.items()):
                cum = 0
                for b, n in zip(self.buckets, v):
                    cum += n
                    out.append(f"{self.name}_bucket{_labels(names, k + (_num(b),))} {cum}")
                out.append(f"{self.name}_bucket{_labels(names, k + ('+Inf',))} {v[-1]}")
                out.append(f"{self.name}_sum{_labels(self.labels, k)} {_num(v[-2])}")
                out.append(f"{self.name}_count{_labels(self.labels, k)} {v[-1]}")
        return out


class Gauge:
    """A value read when scraped (a callback), e.g. the batch queue length."""

    def __init__(self, name: str, help: str, read: Callable[[], float]):
        self.name, self.help, self.read = name, help, read

    def render(self) -> list[str]:
        try:
            value = float(self.read())
        except Exception:  # a gauge that cannot be read is left out of this scrape, never an error
            return []
        return [f"# HELP {self.name} {self.help}", f"# TYPE {self.name} gauge", f"{self.name} {_num(value)}"]


class _StatMetric(Gauge):
    """One number read when scraped, exposed as a gauge or a counter."""

    def __init__(self, name: str, help: str, kind: str, read: Callable[[], float]):
        super().__init__(name, help, read)
        self.kind = kind

    def render(self) -> list[str]:
        return [line.replace("# TYPE " + self.name + " gauge", f"# TYPE {self.name} {self.kind}")
                for line in super().render()]


class Registry:
    def __init__(self):
        self.metrics: list = []

    def add(self, metric):
        self.metrics.append(metric)
        return metric

    def render(self) -> str:
        return "\n".join(line for m in self.metrics for line in m.render()) + "\n"


class ServerMetrics:
    """The metrics the REST service exports."""

    def __init__(self, queue_length: Callable[[], float], inflight: Callable[[], float], admission=None,
                 scene_stats: Callable[[], dict] | None = None,
                 cache_stats: Callable[[], dict[str, dict]] | None = None):
        self.registry = r = Registry()
        self.requests = r.add(Counter("shadowopt_requests_total", "HTTP requests by route, method and status",
                                      ("route", "method", "status")))
        self.latency = r.add(Histogram("shadowopt_request_duration_seconds", "HTTP request latency by route",
                                       ("route", "method")))
        self.optimize = r.add(Histogram("shadowopt_optimize_seconds", "time spent in solve() per optimize "
                                        "request, by method", ("method",)))
        self.queue = r.add(Gauge("shadowopt_batch_queue_length", "batch configurations waiting or running",
                                 queue_length))
        self.inflight = r.add(Gauge("shadowopt_inflight_requests", "heavy requests (upload loads, optimize, "
                                    "evaluate, compare, batch creation) admitted: running or waiting for a slot",
                                    inflight))
        self.refusals = r.add(Counter("shadowopt_admission_refusals_total", "heavy requests refused at admission, "
                                      "by code (busy: max_inflight; tenant_quota: tenant_max_inflight)", ("code",)))
        self.abandoned = r.add(Counter("shadowopt_abandoned_requests_total", "heavy requests dropped because "
                                       "their client disconnected before they ran, by stage (waiting: for a "
                                       "slot; body: while sending its upload)", ("stage",)))
        self.load_followers = r.add(Counter("shadowopt_scene_load_followers_total", "requests that waited for "
                                            "another request's load of their scene without holding a load slot"))
        if admission is not None:
            for pool in (admission.solve, admission.load, admission.download):
                r.add(Gauge(f"shadowopt_{pool.name}_slots_busy", f"{pool.name} slots in use",
                            lambda p=pool: p.busy))
                r.add(Gauge(f"shadowopt_{pool.name}_waiting", f"admitted requests waiting for a {pool.name} slot",
                            lambda p=pool: p.waiting))

        if scene_stats is not None:  # the scene cache: what it holds and how often it loaded
            for key, kind, help in (("entries", "gauge", "loaded scenes held in memory"),
                                    ("bytes", "gauge", "bytes of loaded scenes held in memory (estimated)"),
                                    ("loads", "counter", "scene loads (uploads and reloads after eviction)"),
                                    ("shared", "counter", "requests that shared another request's load"),
                                    ("evictions", "counter", "scenes evicted from memory")):
                name = f"shadowopt_scene_cache_{key}" + ("_total" if kind == "counter" else "")
                r.add(_StatMetric(name, help, kind, lambda k=key: scene_stats()[k]))
        if cache_stats is not None:  # the other caches of tenant data (service.tenant_lru): coarse, geometry
            for cache in ("coarse", "geometry"):
                for key, kind, help in (("bytes", "gauge", f"bytes held by the {cache} cache (estimated)"),
                                        ("max_bytes", "gauge", f"the {cache} cache's bound in bytes"),
                                        ("entries", "gauge", f"entries held by the {cache} cache"),
                                        ("hits", "counter", f"{cache} cache hits"),
                                        ("misses", "counter", f"{cache} cache misses"),
                                        ("evictions", "counter", f"{cache} cache evictions")):
                    name = f"shadowopt_{cache}_cache_{key}" + ("_total" if kind == "counter" else "")
                    r.add(_StatMetric(name, help, kind, lambda c=cache, k=key: cache_stats()[c][k]))

    def render(self, skip_slow: bool = False) -> str:
        """The exposition text; `skip_slow` leaves out the gauges that query the database."""
        if skip_slow:
            return "\n".join(line for m in self.registry.metrics if m is not self.queue for line in m.render()) + "\n"
        return self.registry.render()
