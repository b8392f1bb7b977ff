"""Server settings: defaults, then a TOML/JSON config file, then `SHADOWOPT_*` environment variables.

Every field can be set in the config file under its own name (TOML: top level or a `[server]` table)
and in the environment as `SHADOWOPT_<NAME>` (upper case). Tokens: `SHADOWOPT_TOKENS="name=token,..."`
or a `tokens = {name = "token"}` table; the tenant of a request is the name of its token.
"""
from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field, fields
from pathlib import Path

from ..service.isolation import LoadLimits  # stdlib only at import: no native stack pulled in

LOOPBACK_HOSTS = ("127.0.0.1", "::1", "localhost")


class SettingsError(ValueError):
    """A setting has a bad value; the message names it."""


@dataclass
class Settings:
    data_dir: str = "data"  # relative to the working directory (git-ignored in the repository)
    host: str = "127.0.0.1"
    port: int = 8000
    tokens: dict[str, str] = field(default_factory=dict)  # name -> token
    max_upload_bytes: int = 64 * 1024 * 1024
    max_body_bytes: int = 16 * 1024 * 1024  # JSON requests
    max_triangles: int = 5_000_000
    max_time_budget_ms: float = 10_000.0
    max_eval_pixels: int = 3840 * 2160 * 2  # evaluate/compare: screen pixels
    max_eval_texels: int = 8192 * 8192  # evaluate/compare: texels per shadow map
    max_rig_distance_m: float = 1e6  # how far from the scene's bounds a camera or light may stand (world metres)
    max_queue: int = 100_000  # configurations waiting or running over all batches
    max_inflight: int = 64  # heavy requests (uploads, optimize, evaluate, compare, batch creation) admitted at
    # once, running or waiting for a slot; one more is refused at once with 503 busy, except for a tenant with
    # nothing in flight, which is always admitted (headroom: tenants at their quota cannot lock another out;
    # the total can exceed max_inflight by at most the number of tenants)
    solve_threads: int = 2  # solves running at the same time
    load_threads: int = 1  # scene loads (uploads and cache-miss reloads) running at the same time: own slots,
    # so an upload never holds a solver slot
    load_memory_bytes: int = 3 * 1024 ** 3  # address-space limit of the process loading an uploaded scene (the
    # floor is service.isolation.MEMORY_FLOOR_BYTES, checked by LoadLimits)
    load_timeout_s: float = 20.0  # wall-clock limit of one uploaded scene's load (finite, > 0)
    scene_cache_entries: int = 8  # loaded scenes kept in memory
    scene_cache_bytes: int = 2 * 1024 ** 3  # bytes of loaded scenes kept in memory
    tenant_cache_share: float = 0.5  # fraction of each cache of tenant data (entries and bytes) one tenant may hold
    coarse_cache_bytes: int = 256 * 1024 ** 2  # camera passes kept for light-only changes (service.coarse_cache)
    geometry_cache_bytes: int = 256 * 1024 ** 2  # GLB files of GET /v1/scenes/{id}/geometry.glb kept in memory
    worker_cache_bytes: int = 512 * 1024 ** 2  # loaded scenes kept by each batch worker
    cache_bytes: int = 4 * 1024 ** 3  # the one total of tenant data held by every cache: scene_cache_bytes +
    # coarse_cache_bytes + geometry_cache_bytes + batch_workers x worker_cache_bytes must fit in it (checked at start)
    max_export_triangles: int = 2_000_000  # geometry.glb: a scene with more triangles is refused (413) before any work
    max_export_bytes: int = 64 * 1024 ** 2  # geometry.glb: an export whose GLB could be larger is refused (413)
    download_threads: int = 2  # GET /v1/batches/{id}/results streams at the same time (own slots); more wait
    tenant_max_inflight: int = 32  # one tenant's heavy requests admitted at once (half of max_inflight); more get 429
    tenant_max_queued: int = 25_000  # one tenant's batch configurations waiting or running; more get 429
    tenant_max_stored_bytes: int = 1024 ** 3  # bytes of uploaded files one tenant may keep; more get 429 (413 when
    # one upload alone is larger)
    rate_limit_per_s: float = 50.0  # per token; 0 turns the limit off
    rate_limit_burst: int = 100
    batch_backend: str = "local"
    batch_workers: int = 2
    ray_address: str | None = None
    retention_days: float | None = None
    max_data_bytes: int | None = None
    retention_interval_s: float = 600.0  # how often retention_days / max_data_bytes are applied
    warm_scenes: list[str] = field(default_factory=list)  # loaded and solved once before /healthz is 200
    allowed_hosts: list[str] = field(default_factory=list)  # no tokens: Host names (no port) accepted besides
    # the loopback ones (localhost, 127.0.0.1, [::1]); needed to serve on another address without tokens
    allowed_origins: list[str] = field(default_factory=list)  # no tokens: Origin values (scheme://host[:port])
    # accepted besides the server's own; a request with any other Origin (a web page's) is refused 403
    log_level: str = "INFO"

    @property
    def auth_enabled(self) -> bool:
        return bool(self.tokens)

    def load_limits(self):
        """The limits of an uploaded scene's isolated load (service.isolation.LoadLimits, which validates
        them); SettingsError naming the setting when one is out of range."""
        for name, field_ in (("max_triangles", "max_triangles"), ("load_memory_bytes", "memory_bytes"),
                             ("load_timeout_s", "timeout_s")):
            try:
                LoadLimits(**{field_: getattr(self, name)})
            except ValueError as e:
                raise SettingsError(f"{name}: {e}") from None
        return LoadLimits(self.max_triangles, self.load_memory_bytes, self.load_timeout_s)

    def cache_parts(self) -> dict[str, int]:
        """The bytes of tenant data each cache may hold; their sum is bounded by cache_bytes."""
        return {"scene_cache_bytes": self.scene_cache_bytes, "coarse_cache_bytes": self.coarse_cache_bytes,
                "geometry_cache_bytes": self.geometry_cache_bytes,
                f"batch_workers x worker_cache_bytes ({self.batch_workers} x {self.worker_cache_bytes})":
                    self.batch_workers * self.worker_cache_bytes}

    def check(self) -> "Settings":
        for name in ("max_upload_bytes", "max_body_bytes", "max_triangles", "max_eval_pixels", "max_eval_texels",
                     "max_queue", "max_inflight", "solve_threads", "load_threads", "load_memory_bytes",
                     "scene_cache_entries", "scene_cache_bytes", "coarse_cache_bytes", "geometry_cache_bytes",
                     "worker_cache_bytes", "cache_bytes", "max_export_triangles", "max_export_bytes",
                     "download_threads", "tenant_max_inflight", "tenant_max_queued",
                     "tenant_max_stored_bytes", "batch_workers", "rate_limit_burst"):
            if getattr(self, name) < 1:
                raise SettingsError(f"{name}: must be at least 1, got {getattr(self, name)}")
        if not (math.isfinite(self.max_rig_distance_m) and self.max_rig_distance_m > 0):
            raise SettingsError(f"max_rig_distance_m: must be a finite number > 0, got {self.max_rig_distance_m}")
        for name in ("max_time_budget_ms", "rate_limit_per_s", "retention_interval_s", "tenant_cache_share",
                     "retention_days"):  # load_timeout_s: LoadLimits checks it (below)
            value = getattr(self, name)
            if value is not None and not math.isfinite(value):
                raise SettingsError(f"{name}: must be a finite number, got {value}")
        if self.max_time_budget_ms <= 0 or self.rate_limit_per_s < 0 or self.retention_interval_s <= 0:
            raise SettingsError("max_time_budget_ms and retention_interval_s must be > 0, rate_limit_per_s >= 0")
        self.load_limits()  # the floors and bounds of the loader's limits live in one place: LoadLimits
        if not 0 < self.tenant_cache_share <= 1:
            raise SettingsError(f"tenant_cache_share: must be in (0, 1], got {self.tenant_cache_share}")
        parts = self.cache_parts()
        if sum(parts.values()) > self.cache_bytes:
            raise SettingsError(f"cache_bytes: the caches of tenant data need {sum(parts.values())} bytes ("
                                + " + ".join(f"{k} {v}" for k, v in parts.items())
                                + f"), more than cache_bytes = {self.cache_bytes}; raise it or lower a part")
        if self.batch_backend not in ("local", "ray"):
            raise SettingsError(f"batch_backend: 'local' or 'ray', got {self.batch_backend!r}")
        if not 0 < self.port < 65536:
            raise SettingsError(f"port: must be in 1..65535, got {self.port}")
        for name, tok in self.tokens.items():
            if not name or not tok or len(tok) < 8:
                raise SettingsError(f"tokens: {name or '(empty name)'!r} needs a token of at least 8 characters")
        for name in ("allowed_hosts", "allowed_origins"):
            for item in getattr(self, name):
                bad = host_entry_problem(item) if name == "allowed_hosts" else origin_entry_problem(item)
                if bad:
                    raise SettingsError(f"{name}: {item!r} {bad}")
        if len(set(self.tokens.values())) != len(self.tokens):
            raise SettingsError("tokens: two tenants share a token")
        return self


def parse_tokens(text: str) -> dict[str, str]:
    """`"name=token,name2=token2"` -> {name: token}."""
    out = {}
    for pair in (p.strip() for p in text.split(",")):
        if not pair:
            continue
        name, eq, tok = pair.partition("=")
        if not eq or not name.strip() or not tok.strip():
            raise SettingsError(f"SHADOWOPT_TOKENS: expected name=token pairs separated by commas, got {pair!r}")
        out[name.strip()] = tok.strip()
    return out


def read_config_file(path: str | os.PathLike) -> dict:
    p = Path(path)
    try:
        text = p.read_text()
    except OSError as e:
        raise SettingsError(f"--config: cannot read {str(p)!r}: {e.strerror}") from e
    try:
        if p.suffix.lower() == ".json":
            data = json.loads(text)
        else:
            import tomllib  # lazy: Python 3.11+ (requires-python >= 3.10); only a TOML config file needs it

            data = tomllib.loads(text)
    except (ValueError, json.JSONDecodeError) as e:
        raise SettingsError(f"--config: {p} does not parse: {e}") from e
    if not isinstance(data, dict):
        raise SettingsError(f"--config: {p} must hold a table/object")
    return {**{k: v for k, v in data.items() if k != "server"}, **data.get("server", {})}


def _coerce(name: str, value, kind):
    kind = str(kind)
    try:
        if value is None or (isinstance(value, str) and value.strip().lower() in ("", "none", "null")):
            if "None" in kind:
                return None
            raise ValueError("a value is required")
        if name == "tokens":
            return parse_tokens(value) if isinstance(value, str) else {str(k): str(v) for k, v in dict(value).items()}
        if kind.startswith("list"):  # warm_scenes, allowed_hosts, allowed_origins
            items = value.split(",") if isinstance(value, str) else [str(s) for s in value]
            return [s.strip() for s in items if s.strip()]
        if kind.startswith("int"):
            return int(value)
        if kind.startswith("float"):
            return float(value)
        return str(value)
    except (TypeError, ValueError) as e:
        raise SettingsError(f"{name}: cannot use {value!r} ({e})") from e


def load_settings(config: str | os.PathLike | None = None, env: dict | None = None, **overrides) -> Settings:
    """Defaults < config file (`config` or $SHADOWOPT_CONFIG) < environment < explicit overrides (CLI flags)."""
    env = os.environ if env is None else env
    values: dict = {}
    config = config or env.get("SHADOWOPT_CONFIG")
    if config:
        values.update(read_config_file(config))
    known = {f.name: f.type for f in fields(Settings)}
    unknown = sorted(set(values) - set(known))
    if unknown:
        raise SettingsError(f"config: unknown setting(s) {', '.join(unknown)} (known: {', '.join(known)})")
    for name in known:
        if f"SHADOWOPT_{name.upper()}" in env:
            values[name] = env[f"SHADOWOPT_{name.upper()}"]
    values.update({k: v for k, v in overrides.items() if v is not None})
    return Settings(**{k: _coerce(k, v, known[k]) for k, v in values.items()}).check()


def is_loopback(host: str) -> bool:
    return host in LOOPBACK_HOSTS or host.startswith("127.")


def host_entry_problem(item: str) -> str | None:
    """Why an allowed_hosts entry is not a bare host name or address (no scheme, port or path), or None."""
    if not item or any(c in item for c in "/:@ ") and not (item.startswith("[") and item.endswith("]")):
        return "is not a bare host name or address (no scheme, port or path; an IPv6 address in [brackets])"
    return None


def origin_entry_problem(item: str) -> str | None:
    """Why an allowed_origins entry is not an origin (scheme://host[:port], as browsers send it), or None."""
    scheme, sep, rest = item.partition("://")
    if scheme not in ("http", "https") or not sep or not rest or "/" in rest or "@" in rest:
        return "is not an origin: http(s)://host[:port], no path"
    return None
