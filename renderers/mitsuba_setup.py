"""Mitsuba's LLVM variant, set once per process (libLLVM choice: solvers.jit)."""
from __future__ import annotations

from ..solvers.jit import JitUnavailable, ensure_llvm

VARIANT = "llvm_ad_rgb"
RendererUnavailable = JitUnavailable


def mitsuba():
    """Import Mitsuba with the LLVM variant set. Raises RendererUnavailable with a fix when it cannot."""
    path = ensure_llvm()
    import mitsuba as mi  # lazy: after ensure_llvm(), which points Dr.Jit at its libLLVM

    if mi.variant() != VARIANT:
        try:
            mi.set_variant(VARIANT)
        except Exception as e:  # pragma: no cover - depends on the machine
            raise RendererUnavailable(f"Mitsuba variant {VARIANT} unavailable with {path}: {e}") from e
    return mi
