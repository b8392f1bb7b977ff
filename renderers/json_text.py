"""The one writer of the JSON the product hands out (CLI output and files, batch and path lines, REST bodies):
standard JSON only (RFC 8259: no NaN, Infinity or -Infinity). `finite` maps a non-finite float to None
(null) and NumPy values to Python ones; `dumps` applies it and then refuses anything non-finite left
(json.dumps with allow_nan=False), so a value JSON cannot hold never reaches a reader as `Infinity`.
Where a field can carry null for a non-finite value its schema description says what null means there
(e.g. a candidate score of the solver's report that is infinite: the candidate leaves a receiver outside
its map)."""
from __future__ import annotations

import json
import math


def finite(obj):
    """NaN/inf -> None (JSON has neither), NumPy scalars -> Python numbers, tuples -> lists."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {str(k): finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [finite(v) for v in obj]
    if obj is None or isinstance(obj, (str, int, bool)):
        return obj
    if hasattr(obj, "tolist"):  # numpy scalar or array
        return finite(obj.tolist())
    return str(obj)


def dumps(obj, **kwargs) -> str:
    """json.dumps of finite(obj), strict: standard JSON (kwargs: indent, separators ...)."""
    return json.dumps(finite(obj), allow_nan=False, **kwargs)
