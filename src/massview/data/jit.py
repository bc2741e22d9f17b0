"""numba as the data layer imports it (every kernel module imports ``njit`` from here), and its
``njit`` as the compiled kernels use it: cached on disk, GIL released,
no bounds checks, numpy's error model (division by zero gives inf/NaN, not an exception)."""

from __future__ import annotations

import sys

from numba import njit

__all__ = ["cached_jit", "njit"]


def _arraymath_without_scipy_blas() -> None:
    """Import ``numba.np.arraymath`` (what numba's first compile or cache load imports) with its
    BLAS probe answering "none". The probe (``numba.np.linalg.ensure_blas``) imports all of
    ``scipy.linalg`` (0.2–0.35 s measured here, and scipy's OpenBLAS starts its threads) only to
    pick how ``np.correlate``/``np.convolve`` take inner products inside compiled code; our
    kernels call neither (they would use numba's own loop). The probe is numba's module
    attribute, put back right after, so no other thread's imports are touched, and ``np.dot``
    and ``np.linalg`` in compiled code still find scipy's BLAS. Nothing changes where numba's
    arraymath is already imported."""
    if "numba.np.arraymath" in sys.modules:
        return
    import numba.np.linalg as linalg

    probe = linalg.ensure_blas

    def no_blas():
        raise ImportError("massview: BLAS probe skipped at import")

    linalg.ensure_blas = no_blas
    try:
        import numba.np.arraymath as arraymath
    finally:
        linalg.ensure_blas = probe
    arraymath.ensure_blas = probe  # (arraymath imported the name)


_arraymath_without_scipy_blas()


def cached_jit(fn):
    """``fn`` compiled lazily (on first call) and cached beside its module, or in
    ``NUMBA_CACHE_DIR``; where no cache location is writable, compiled once per process."""
    try:
        return njit(cache=True, nogil=True, boundscheck=False, error_model="numpy")(fn)
    except RuntimeError:  # numba: "cannot cache function ...: no locator available"
        return njit(nogil=True, boundscheck=False, error_model="numpy")(fn)
