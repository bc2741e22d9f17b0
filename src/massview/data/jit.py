"""numba's ``njit`` as the data layer's compiled kernels use it: cached on disk, GIL released,
no bounds checks, numpy's error model (division by zero gives inf/NaN, not an exception)."""

from __future__ import annotations

from numba import njit

__all__ = ["cached_jit"]


def cached_jit(fn):
    """``fn`` compiled lazily (on first call) and cached beside its module, or in
    ``NUMBA_CACHE_DIR``; where no cache location is writable, compiled once per process."""
    try:
        return njit(cache=True, nogil=True, boundscheck=False, error_model="numpy")(fn)
    except RuntimeError:  # numba: "cannot cache function ...: no locator available"
        return njit(nogil=True, boundscheck=False, error_model="numpy")(fn)
