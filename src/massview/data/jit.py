"""numba as the data layer imports it (every kernel module imports ``njit`` from here), and its
``njit`` as the compiled kernels use it: cached on disk, GIL released,
no bounds checks, numpy's error model (division by zero gives inf/NaN, not an exception)."""

from __future__ import annotations

import sys

from numba import njit

__all__ = ["cached_jit", "njit"]


def _arraymath_without_scipy_blas() -> None:
    """Import ``numba.np.arraymath`` (what numba's first compile or cache load imports) with
    ``scipy.linalg.cython_blas`` hidden. At import it probes for scipy's BLAS, which imports all
    of ``scipy.linalg`` (0.2–0.35 s measured here, and scipy's OpenBLAS starts its threads), only
    to pick how ``np.correlate``/``np.convolve`` take inner products inside compiled code; our
    kernels call neither (they then use numba's own loop). Nothing is hidden where scipy.linalg
    or numba's arraymath is already imported, and ``scipy.linalg`` imports as before afterwards."""
    if "numba.np.arraymath" in sys.modules or "scipy.linalg" in sys.modules:
        return
    key = "scipy.linalg.cython_blas"
    sys.modules[key] = None  # (an import of it raises ImportError while this is here)
    try:
        import numba.np.arraymath  # noqa: F401
    finally:
        if key in sys.modules and sys.modules[key] is None:
            del sys.modules[key]


_arraymath_without_scipy_blas()


def cached_jit(fn):
    """``fn`` compiled lazily (on first call) and cached beside its module, or in
    ``NUMBA_CACHE_DIR``; where no cache location is writable, compiled once per process."""
    try:
        return njit(cache=True, nogil=True, boundscheck=False, error_model="numpy")(fn)
    except RuntimeError:  # numba: "cannot cache function ...: no locator available"
        return njit(nogil=True, boundscheck=False, error_model="numpy")(fn)
