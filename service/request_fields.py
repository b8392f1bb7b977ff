"""The field checks of a batch or path request (numbers, [x, y, z] vectors, sample counts, ranges) and
BatchError, the error naming the field that is wrong (service.batch_request, service.interpolation,
service.paths)."""
from __future__ import annotations

import math

from .rigs import FieldError

MAX_SAMPLES = 10_000


class BatchError(FieldError):
    """A batch request is malformed (`field` e.g. `sun_arc.samples`)."""

    code = "invalid_batch"


def number(v, field: str, lo: float = -math.inf, hi: float = math.inf) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise BatchError(field, f"expected a finite number, got {v!r}")
    if not lo <= v <= hi:
        raise BatchError(field, f"{v} is outside [{lo:g}, {hi:g}]")
    return float(v)


def vec3(v, field: str, nonzero: bool = False) -> list[float]:
    if not isinstance(v, (list, tuple)) or len(v) != 3:
        raise BatchError(field, f"expected [x, y, z], got {v!r}")
    out = [number(x, f"{field}.{k}") for k, x in enumerate(v)]
    if nonzero and not any(out):
        raise BatchError(field, "must not be the zero vector")
    return out


def samples(v, field: str) -> int:
    if isinstance(v, bool) or not isinstance(v, int) or not 1 <= v <= MAX_SAMPLES:
        raise BatchError(field, f"expected an integer in [1, {MAX_SAMPLES}], got {v!r}")
    return v


def value_range(v, field: str, lo: float, hi: float) -> tuple[float, float]:
    """A number (constant) or [from, to]."""
    if isinstance(v, (list, tuple)):
        if len(v) != 2:
            raise BatchError(field, f"expected a number or [from, to], got {v!r}")
        return number(v[0], f"{field}.0", lo, hi), number(v[1], f"{field}.1", lo, hi)
    x = number(v, field, lo, hi)
    return x, x
