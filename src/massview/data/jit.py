"""numba as the data layer imports it (every kernel module imports ``njit`` from here), and its
``njit`` as the compiled kernels use it: cached on disk, GIL released,
no bounds checks, numpy's error model (division by zero gives inf/NaN, not an exception)."""

from __future__ import annotations

import sys
import threading
import time
from contextlib import contextmanager

from numba import njit
from numba.core import event

__all__ = ["CompileClock", "cached_jit", "compile_clock", "njit", "on_first_compile"]


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


class _FirstCompile(event.Listener):
    """Calls ``callback()`` at the start of the first compile it hears of, once."""

    def __init__(self, callback):
        self._callback, self._lock, self._fired = callback, threading.Lock(), False

    def on_start(self, ev) -> None:
        with self._lock:
            if self._fired:
                return
            self._fired = True
        self._callback()

    def on_end(self, ev) -> None:
        pass


@contextmanager
def on_first_compile(callback):
    """Within the block, ``callback()`` (no arguments) is called once, in whichever thread, when
    numba starts compiling a kernel for a signature it has neither in memory nor in its disk
    cache: before the compile, so a note printed by it comes before the wait. Never called when
    every kernel the block runs loads from the cache."""
    with event.install_listener("numba:compile", _FirstCompile(callback)):
        yield


class CompileClock(event.Listener):
    """What numba compiled while it listened: ``kernels``, the signatures compiled (a kernel's
    callees compiled with it count too; a signature loaded from the disk cache does not), and
    ``seconds``, the wall time during which at least one compile ran (nested and concurrent
    compiles counted once)."""

    def __init__(self):
        self._lock, self._active, self._since = threading.Lock(), 0, 0.0
        self.kernels, self.seconds = 0, 0.0

    def on_start(self, ev) -> None:
        with self._lock:
            if self._active == 0:
                self._since = time.perf_counter()
            self._active += 1
            self.kernels += 1

    def on_end(self, ev) -> None:
        with self._lock:
            self._active -= 1
            if self._active == 0:
                self.seconds += time.perf_counter() - self._since

    def _close(self) -> None:  # (a compile still open when the block ends: counted up to now)
        with self._lock:
            if self._active > 0:
                self.seconds += time.perf_counter() - self._since
                self._active = 0


@contextmanager
def compile_clock():
    """Yields a :class:`CompileClock` that counts numba's compiles within the block, in every
    thread (``prepare terrain`` records it in ``MASSVIEW_STAGES_FILE`` for ``bench ingest``,
    which warns when its figure includes compiling)."""
    clock = CompileClock()
    try:
        with event.install_listener("numba:compile", clock):
            yield clock
    finally:
        clock._close()
