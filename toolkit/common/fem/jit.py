"""Optional compilation of the explicit solver's per-point and per-element loops with numba.

An explicit step touches every integration point once, and the J2 update needs a 3x3
eigen-decomposition there: numpy's batched ``eigh`` costs many times what a compiled
Jacobi sweep does per point. :data:`HAVE_NUMBA` says whether numba is importable; without it
the numpy implementations (always kept as the readable reference) are used.
``TOOLKIT_JIT=0`` in the environment disables compilation (for debugging or comparison).

Compiled functions are cached on disk next to the module (``cache=True``), so the
first-call compilation (a few seconds) happens once per machine.
"""

from __future__ import annotations

import os

__all__ = ["HAVE_NUMBA", "njit", "use_jit"]

try:  # pragma: no cover - depends on the environment
    import numba as _numba

    HAVE_NUMBA = True
except ImportError:  # pragma: no cover
    _numba = None
    HAVE_NUMBA = False


def use_jit() -> bool:
    """True when compiled kernels should run: numba importable and ``TOOLKIT_JIT`` not ``0``."""
    return HAVE_NUMBA and os.environ.get("TOOLKIT_JIT", "1") != "0"


def njit(fn):
    """``numba.njit(cache=True, fastmath=False)`` when numba is available, else ``fn`` unchanged
    (the caller then never runs it: it checks :func:`use_jit` first)."""
    if _numba is None:  # pragma: no cover
        return fn
    return _numba.njit(cache=True, fastmath=False, nogil=True)(fn)
