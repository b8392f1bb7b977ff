"""USD attribute values and matrices as NumPy.

- At the default time code, attributes with time samples but no default are read at their first sample.
"""
from __future__ import annotations

import numpy as np


def np_matrix(gf) -> np.ndarray:
    """Gf.Matrix4d (row-vector convention) -> NumPy 4x4 acting on column vectors."""
    return np.array(gf, dtype=np.float64).T


def attr_value(attr, time_code, warnings: list[str] | None = None):
    """attr's value at time_code. At the default time, an attribute with time samples but no default
    value gives its first sample (USD would give nothing), so animated points are not lost."""
    v = attr.Get(time_code)
    if v is None and time_code.IsDefault() and attr.GetNumTimeSamples() > 0:
        samples = attr.GetTimeSamples()
        v = attr.Get(samples[0])
        if warnings is not None:
            warnings.append(f"{attr.GetPath()}: only time samples, no default value: read at its first sample "
                            f"t={samples[0]:g}")
    return v


def as_array(value, cols: int | None, dtype):
    """A USD array value -> NumPy of shape (N, cols) / (N,), or None when it has another shape or type."""
    if value is None or isinstance(value, (str, bytes)) or not hasattr(value, "__len__"):
        return None
    try:
        arr = np.asarray(value, dtype=dtype)
    except (TypeError, ValueError):
        return None
    if cols is None:
        return arr if arr.ndim == 1 else None
    if arr.ndim == 2 and arr.shape[1] == cols:
        return arr
    if arr.size == 0:
        return arr.reshape(0, cols)
    return None
