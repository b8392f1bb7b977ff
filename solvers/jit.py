"""Dr.Jit's LLVM backend, loaded with a libLLVM that works (>= 16): one place for the whole project."""
from __future__ import annotations

import glob
import os
import re

import numpy as np

_LLVM_CANDIDATES = ("/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1", "/usr/lib/x86_64-linux-gnu/libLLVM-19.so",
                    "/usr/lib/aarch64-linux-gnu/libLLVM.so.19.1", "/usr/lib/aarch64-linux-gnu/libLLVM-19.so")


class JitUnavailable(RuntimeError):
    pass


def pick_llvm() -> str | None:
    """DRJIT_LIBLLVM_PATH if set, else the newest system libLLVM of version >= 16 (15 crashes, 14 is refused)."""
    if os.environ.get("DRJIT_LIBLLVM_PATH"):
        return os.environ["DRJIT_LIBLLVM_PATH"]
    for c in _LLVM_CANDIDATES:
        if os.path.exists(c):
            return c
    found = []
    for c in glob.glob("/usr/lib/*/libLLVM*.so*"):
        m = re.search(r"libLLVM(?:-|\.so\.)(\d+)", os.path.basename(c))
        if m and int(m.group(1)) >= 16:
            found.append((int(m.group(1)), c))
    return max(found)[1] if found else None


def ensure_llvm() -> str:
    path = pick_llvm()
    if path is None:
        raise JitUnavailable("no libLLVM >= 16 found: install Debian's libllvm19 (make setup does) "
                             "or set DRJIT_LIBLLVM_PATH")
    os.environ["DRJIT_LIBLLVM_PATH"] = path
    return path


def llvm_ad():
    """The drjit.llvm.ad module (Float64, Array3f64, ...), with LLVM set up."""
    ensure_llvm()
    import drjit.llvm.ad as ad  # lazy: only after ensure_llvm has set DRJIT_LIBLLVM_PATH, which drjit reads on import

    return ad


def aligned(a, dtype) -> "object":
    """A contiguous copy of `a` in a 64-byte-aligned buffer. Dr.Jit may read NumPy memory in place,
    and the buffer's alignment is then part of the kernel: unaligned data would compile a new kernel
    for the same computation. Wrap every NumPy array handed to Dr.Jit in a hot path with this."""
    a = np.asarray(a, dtype=dtype)
    flat = a.ravel()
    item = flat.itemsize
    raw = np.empty(flat.size + 64 // item, dtype=dtype)
    off = (-raw.ctypes.data % 64) // item
    buf = raw[off:off + flat.size]
    buf[:] = flat
    return buf.reshape(a.shape)
