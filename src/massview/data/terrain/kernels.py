"""Compiled per-sample kernels of the ingest (numba, cached on disk, GIL released).

:func:`window_errors` is the inner loop of :mod:`deviation`: for every closed lattice square of
a level-0 block it evaluates the square mesh and the four quarter triangles of the centred mesh
at each finest sample and keeps the maximum deviation. It performs, per sample, exactly the
float32 operations (same operands, same order, no fused multiply-add, no fast-math) that the
numpy expressions of :class:`deviation.DeviationAccumulator` perform through broadcasting, so
its results are bit-identical to them — the golden-store test (tests/test_ingest_parallel.py)
checks this on whole stores. Maxima are exact whatever the order.

Compilation happens once per machine (``cache=True`` writes it beside this file, or to
``NUMBA_CACHE_DIR``, or a user cache folder; where none is writable, once per process);
later processes load it in well under a second. Imported only when errors are computed, so
commands that only read stores do not load numba.
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["grid_errors", "masked_grid_errors", "window_errors"]



def _jit(fn):
    """``njit`` with the compiled code cached on disk; where no cache location is writable
    (an install owned by another user, no writable home), compiled once per process instead."""
    try:
        return njit(cache=True, nogil=True, boundscheck=False)(fn)
    except RuntimeError:  # numba: "cannot cache function ...: no locator available"
        return njit(nogil=True, boundscheck=False)(fn)


_F0 = np.float32(0.0)
_F1 = np.float32(1.0)
_F2 = np.float32(2.0)


@_jit
def _fold(sq_out, per_out, tab, f, v0, u0, V0, U0, iv, iu, msq, mt, mb, ml, mr):
    """Max-fold one lattice square's maxima into its patch square (v//f, u//f) and its
    quarters into the edge diamonds their region ``tab[q, v % f, u % f]`` names (deviation.py)."""
    v, u = v0 + iv, u0 + iu
    a, bb = v // f - V0, u // f - U0
    sq_out[a, bb] = max(sq_out[a, bb], msq)
    vm, um = v % f, u % f
    for q, e in ((0, mt), (1, mb), (2, ml), (3, mr)):
        r = tab[q, vm, um]
        per_out[r, a, bb] = max(per_out[r, a, bb], e)


@_jit
def _corners(c00, c10, c01, c11, cc, iv, iu):
    a00, a10, a01, a11, ac = c00[iv, iu], c10[iv, iu], c01[iv, iu], c11[iv, iu], cc[iv, iu]
    return (a00, a10, a01, a11, a10 - a00, a01 - a00, a00 - a10 - a01 + a11, _F2 * ac - a00 - a10,
            _F2 * ac - a01 - a11, _F2 * ac - a00 - a01, _F2 * ac - a10 - a11, a11 - a01, a11 - a10)


@_jit
def grid_errors(b, s, nq, fx, c00, c10, c01, c11, cc, parity, tab, f, v0, u0, V0, U0, sq_out, per_out):  # noqa: PLR0913
    """Exact deviations of the ``nq × nq`` closed lattice squares of spacing ``s`` over a block
    whose samples are all valid; ``fx = arange(s+1)/s`` (float32). The quarter triangles are
    visited over their exact column ranges (``y <= x`` ⇔ ``r <= c`` for these dyadic
    fractions), the same samples the masks of the numpy formulation select. Max-folds into
    sq_out (nV, nU) and per_out (4, nV, nU), see :func:`_fold`."""
    for iv in range(nq):
        for iu in range(nq):
            a00, a10, a01, a11, dx, dy, dd, et, eb, el, er, dx2, dy3 = _corners(c00, c10, c01, c11, cc, iv, iu)
            even = (parity + iv + iu) % 2 == 0
            msq, mt, mb, ml, mr = _F0, _F0, _F0, _F0, _F0
            for r in range(s + 1):
                y = fx[r]
                row = b[iv * s + r, iu * s: iu * s + s + 1]
                for c in range(s + 1):
                    x = fx[c]
                    wgt = min(x, y) if even else max(x + y - _F1, _F0)
                    msq = max(msq, abs(a00 + x * dx + y * dy + wgt * dd - row[c]))
                for c in range(r, s - r + 1):  # top: r <= c <= s - r
                    mt = max(mt, abs(a00 + fx[c] * dx + y * et - row[c]))
                for c in range(s - r, r + 1):  # bottom: s - r <= c <= r
                    mb = max(mb, abs(a01 + fx[c] * dx2 + (_F1 - y) * eb - row[c]))
                for c in range(0, min(r, s - r) + 1):  # left: c <= min(r, s - r)
                    ml = max(ml, abs(a00 + y * dy + fx[c] * el - row[c]))
                for c in range(max(r, s - r), s + 1):  # right: c >= max(r, s - r)
                    mr = max(mr, abs(a10 + y * dy3 + (_F1 - fx[c]) * er - row[c]))
            _fold(sq_out, per_out, tab, f, v0, u0, V0, U0, iv, iu, msq, mt, mb, ml, mr)


@_jit
def _masked_maxima(b, valid, r0, c0, fy, fx, even, k):
    """Maxima (square, top, bottom, left, right) of the deviations of the valid samples
    ``b[r0 + r, c0 + c]`` at fractional coordinates (fx[c], fy[r]) from one lattice square's
    meshes, ``k`` being its :func:`_corners`; the masks of the numpy formulation."""
    a00, a10, a01, a11, dx, dy, dd, et, eb, el, er, dx2, dy3 = k
    msq, mt, mb, ml, mr = _F0, _F0, _F0, _F0, _F0
    for r in range(fy.shape[0]):
        y = fy[r]
        for c in range(fx.shape[0]):
            if not valid[r0 + r, c0 + c]:
                continue
            x = fx[c]
            z0 = b[r0 + r, c0 + c]
            wgt = min(x, y) if even else max(x + y - _F1, _F0)
            msq = max(msq, abs(a00 + x * dx + y * dy + wgt * dd - z0))
            if y <= x and y <= _F1 - x:
                mt = max(mt, abs(a00 + x * dx + y * et - z0))
            if y >= x and y >= _F1 - x:
                mb = max(mb, abs(a01 + x * dx2 + (_F1 - y) * eb - z0))
            if x <= y and x <= _F1 - y:
                ml = max(ml, abs(a00 + y * dy + x * el - z0))
            if x >= y and x >= _F1 - y:
                mr = max(mr, abs(a10 + y * dy3 + (_F1 - x) * er - z0))
    return msq, mt, mb, ml, mr


@_jit
def window_errors(b, valid, fx, fy, c00, c10, c01, c11, cc, parity, tab, f, v0, u0, sq_out, per_out):  # noqa: PLR0913
    """Exact deviations of one lattice square that contains the whole block (any fractional
    coordinates fx (w,), fy (h,), float32; only ``valid`` samples count), by the masks of
    the numpy formulation. Max-folds into sq_out (1, 1) and per_out (4, 1, 1)."""
    k = _corners(c00, c10, c01, c11, cc, 0, 0)
    msq, mt, mb, ml, mr = _masked_maxima(b, valid, 0, 0, fy, fx, parity % 2 == 0, k)
    _fold(sq_out, per_out, tab, f, v0, u0, v0 // f, u0 // f, 0, 0, msq, mt, mb, ml, mr)


@_jit
def masked_grid_errors(b, valid, s, nq, fx, c00, c10, c01, c11, cc, parity, tab, f, v0, u0, V0, U0, sq_out, per_out):  # noqa: PLR0913
    """:func:`grid_errors` for a block with padding samples (``valid`` false): masked."""
    for iv in range(nq):
        for iu in range(nq):
            if not valid[iv * s, iu * s]:
                continue  # the square's first sample is padding: so is every later one (padding is a suffix)
            k = _corners(c00, c10, c01, c11, cc, iv, iu)
            msq, mt, mb, ml, mr = _masked_maxima(b, valid, iv * s, iu * s, fx, fx, (parity + iv + iu) % 2 == 0, k)
            _fold(sq_out, per_out, tab, f, v0, u0, V0, U0, iv, iu, msq, mt, mb, ml, mr)
