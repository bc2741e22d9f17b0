"""Compiled per-sample kernels of the ingest (numba, cached on disk, GIL released).

:func:`window_errors` is the inner loop of :mod:`deviation`: for every closed lattice square of
a level-0 block it evaluates the square mesh and the four quarter triangles of the centred mesh
at each finest sample and keeps the maximum deviation. It performs, per sample, exactly the
float32 operations (same operands, same order, no fused multiply-add, no fast-math) that the
numpy expressions of :class:`deviation.DeviationAccumulator` perform through broadcasting, so
its results are bit-identical to them — the golden-store test (tests/test_ingest_parallel.py)
checks this on whole stores. Maxima are exact whatever the order.

Running maxima in memory are updated as ``M[k] = v if v > o else o`` with ``o = M[k] + 0``
(issue 20, eighth round): without the ``+ 0`` LLVM turns the update into a store of v only
where v > o, which the vectorized loops did with ``vmaskmovps`` — microcoded on AMD Zen, ~3 ns
per 8 lanes, most of every loop's time. Adding +0.0 changes no value these arrays hold (they
start at +0 and only ever take an ``abs``, never −0, nor NaN: ``v > o`` is false for a NaN v),
so the maxima are the same bit for bit; LLVM may not drop the addition (it is not the identity
for −0), so the store stays a plain one.

Compilation happens once per machine (``cache=True`` writes it beside this file, or to
``NUMBA_CACHE_DIR``, or a user cache folder; where none is writable, once per process);
later processes load it in well under a second. Imported only when errors are computed, so
commands that only read stores do not load numba.
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["grid_errors", "masked_grid_errors", "padded_grid_errors", "window_errors", "window_level"]



def _jit(fn):
    """``njit`` with the compiled code cached on disk; where no cache location is writable
    (an install owned by another user, no writable home), compiled once per process instead."""
    try:
        return njit(cache=True, nogil=True, boundscheck=False)(fn)
    except RuntimeError:  # numba: "cannot cache function ...: no locator available"
        return njit(nogil=True, boundscheck=False)(fn)


def _jit_inline(fn):
    """:func:`_jit`, inlined into its callers by numba (no call, no reference counting of its
    array arguments; constant arguments stay constants, so LLVM can unroll loops over them)."""
    try:
        return njit(cache=True, nogil=True, boundscheck=False, inline="always")(fn)
    except RuntimeError:
        return njit(nogil=True, boundscheck=False, inline="always")(fn)


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
    vm, um = v % f, u % f  # (the four quarters written out: a loop over a tuple of pairs cost half the kernel)
    r = tab[0, vm, um]
    per_out[r, a, bb] = max(per_out[r, a, bb], mt)
    r = tab[1, vm, um]
    per_out[r, a, bb] = max(per_out[r, a, bb], mb)
    r = tab[2, vm, um]
    per_out[r, a, bb] = max(per_out[r, a, bb], ml)
    r = tab[3, vm, um]
    per_out[r, a, bb] = max(per_out[r, a, bb], mr)


@_jit
def _corner_terms(a00, a10, a01, a11, ac):
    """A lattice square's corners and mesh terms: (a00, a10, a01, a11, dx, dy, dd, et, eb, el,
    er, dx2, dy3), float32."""
    return (a00, a10, a01, a11, a10 - a00, a01 - a00, a00 - a10 - a01 + a11, _F2 * ac - a00 - a10,
            _F2 * ac - a01 - a11, _F2 * ac - a00 - a01, _F2 * ac - a10 - a11, a11 - a01, a11 - a10)


@_jit
def _corners(c00, c10, c01, c11, cc, iv, iu):
    return _corner_terms(c00[iv, iu], c10[iv, iu], c01[iv, iu], c11[iv, iu], cc[iv, iu])


@_jit
def grid_errors(b, s, nq, fx, c00, c10, c01, c11, cc, parity, tab, f, v0, u0, V0, U0, sq_out, per_out):  # noqa: PLR0913
    """Exact deviations of the ``nq × nq`` closed lattice squares of spacing ``s`` over a block
    whose samples are all valid; ``fx = arange(s+1)/s`` (float32). Max-folds into sq_out
    (nV, nU) and per_out (4, nV, nU), see :func:`_fold`. Every stride takes whole rows of
    squares per loop (stride 2: :func:`_direct_maxima`; then :func:`_lattice_maxima`, c-major up
    to stride 32, square-major above: the fastest of the three per stride; strides 2 and 4 by
    :func:`_fine_maxima` since the eighth round); the results are those of :func:`_grid_squares`
    bit for bit (tests/test_ingest_kernels.py)."""
    if s <= 4 and c00.shape[1] < _NUP:
        m5 = _fine_maxima(b, s, c00, c10, c01, c11, cc, parity)
    elif s == 2:
        m5 = _direct_maxima(b, s, nq, fx, c00, c10, c01, c11, cc, parity)
    else:
        m5 = _lattice_maxima(b, s, nq, fx, c00, c10, c01, c11, cc, parity, s <= 32)
    _fold_rows(m5, tab, f, v0, u0, V0, U0, sq_out, per_out)


@_jit
def _fold_rows(m5, tab, f, v0, u0, V0, U0, sq_out, per_out):
    """:func:`_fold` of every square's maxima ``m5`` (5, nq, nq); ``f`` is a power of two and
    the lattice indices are not negative, so // and % are a shift and a mask (the integer
    divisions of :func:`_fold` cost about as much as the maxima of a fine stride)."""
    sh, mask = 0, f - 1
    while (1 << sh) < f:
        sh += 1
    nv, nu = m5.shape[1], m5.shape[2]
    if nv % f == 0 and nu % f == 0 and v0 % f == 0 and u0 % f == 0:  # whole patch squares (the fine strides):
        nb = nu // f                                   # no index arithmetic or table look-up per lattice square
        for iv in range(nv):
            a, vm = iv >> sh, iv & mask  # (v0 + iv) // f - V0 and (v0 + iv) % f, as v0 = V0·f
            for um in range(f):
                r0, r1, r2, r3 = tab[0, vm, um], tab[1, vm, um], tab[2, vm, um], tab[3, vm, um]
                for bb in range(nb):  # (+ 0: plain stores, see the module docstring)
                    iu = bb * f + um
                    sq_out[a, bb] = max(sq_out[a, bb] + _F0, m5[0, iv, iu])
                    per_out[r0, a, bb] = max(per_out[r0, a, bb] + _F0, m5[1, iv, iu])
                    per_out[r1, a, bb] = max(per_out[r1, a, bb] + _F0, m5[2, iv, iu])
                    per_out[r2, a, bb] = max(per_out[r2, a, bb] + _F0, m5[3, iv, iu])
                    per_out[r3, a, bb] = max(per_out[r3, a, bb] + _F0, m5[4, iv, iu])
        return
    for iv in range(nv):
        v = v0 + iv
        a, vm = (v >> sh) - V0, v & mask
        for iu in range(nu):
            u = u0 + iu
            bb, um = (u >> sh) - U0, u & mask
            sq_out[a, bb] = max(sq_out[a, bb], m5[0, iv, iu])
            for q in range(4):
                r = tab[q, vm, um]
                per_out[r, a, bb] = max(per_out[r, a, bb], m5[q + 1, iv, iu])


@_jit
def _grid_squares(b, s, nq, fx, c00, c10, c01, c11, cc, parity, tab, f, v0, u0, V0, U0, sq_out, per_out):  # noqa: PLR0913
    """One lattice square at a time: the reference the tests compare :func:`grid_errors` with
    (the kernel before issue 20's third round). Exact deviations of the ``nq × nq`` closed lattice squares of spacing ``s`` over a block
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
def _wsq(M, X, Z, V, y, a00, dx, dy, dd, even):
    """:func:`_masked_maxima`'s square mesh over one row, per column into M (0 where not valid)."""
    for k in range(M.shape[0]):
        x = X[k]
        wgt = min(x, y) if even else max(x + y - _F1, _F0)
        v = abs(a00 + x * dx + y * dy + wgt * dd - Z[k])
        v = v if V[k] else _F0
        o = M[k]
        M[k] = v if v > o else o


@_jit
def _wtop(M, X, Z, V, y, a00, dx, et):
    for k in range(M.shape[0]):
        x = X[k]
        v = abs(a00 + x * dx + y * et - Z[k])
        v = v if V[k] and y <= x and y <= _F1 - x else _F0
        o = M[k]
        M[k] = v if v > o else o


@_jit
def _wbottom(M, X, Z, V, y, a01, dx2, eb):
    for k in range(M.shape[0]):
        x = X[k]
        v = abs(a01 + x * dx2 + (_F1 - y) * eb - Z[k])
        v = v if V[k] and y >= x and y >= _F1 - x else _F0
        o = M[k]
        M[k] = v if v > o else o


@_jit
def _wleft(M, X, Z, V, y, a00, dy, el):
    for k in range(M.shape[0]):
        x = X[k]
        v = abs(a00 + y * dy + x * el - Z[k])
        v = v if V[k] and x <= y and x <= _F1 - y else _F0
        o = M[k]
        M[k] = v if v > o else o


@_jit
def _wright(M, X, Z, V, y, a10, dy3, er):
    for k in range(M.shape[0]):
        x = X[k]
        v = abs(a10 + y * dy3 + (_F1 - x) * er - Z[k])
        v = v if V[k] and x >= y and x >= _F1 - y else _F0
        o = M[k]
        M[k] = v if v > o else o


@_jit
def _window_maxima(b, valid, r0, c0, fy, fx, even, k):
    """:func:`_masked_maxima` of the samples ``b[r0 + r, c0 + c]``, a row at a time: one loop per
    mesh over the row's columns (:func:`_wsq` …: the same expressions and masks, invalid or
    masked-out samples giving 0, never NaN; vectorized), per-column maxima reduced at the end."""
    a00, a10, a01, a11, dx, dy, dd, et, eb, el, er, dx2, dy3 = k
    w = fx.shape[0]
    Msq, Mt, Mb = np.zeros(w, np.float32), np.zeros(w, np.float32), np.zeros(w, np.float32)
    Ml, Mr = np.zeros(w, np.float32), np.zeros(w, np.float32)
    for r in range(fy.shape[0]):
        y, Z, V = fy[r], b[r0 + r, c0: c0 + w], valid[r0 + r, c0: c0 + w]
        _wsq(Msq, fx, Z, V, y, a00, dx, dy, dd, even)
        _wtop(Mt, fx, Z, V, y, a00, dx, et)
        _wbottom(Mb, fx, Z, V, y, a01, dx2, eb)
        _wleft(Ml, fx, Z, V, y, a00, dy, el)
        _wright(Mr, fx, Z, V, y, a10, dy3, er)
    return Msq.max(), Mt.max(), Mb.max(), Ml.max(), Mr.max()


@_jit
def window_errors(b, valid, fx, fy, c00, c10, c01, c11, cc, parity, tab, f, v0, u0, sq_out, per_out):  # noqa: PLR0913
    """Exact deviations of one lattice square that contains the whole block (any fractional
    coordinates fx (w,), fy (h,), float32; only ``valid`` samples count), by the masks of
    the numpy formulation. Max-folds into sq_out (1, 1) and per_out (4, 1, 1)."""
    k = _corners(c00, c10, c01, c11, cc, 0, 0)
    msq, mt, mb, ml, mr = _window_maxima(b, valid, 0, 0, fy, fx, parity % 2 == 0, k)
    _fold(sq_out, per_out, tab, f, v0, u0, v0 // f, u0 // f, 0, 0, msq, mt, mb, ml, mr)


# -- issue 20, eighth round: the window levels as whole-row vectorized loops ---------------------
# A window level's block lies inside one lattice square, so every per-square term is a scalar and
# every row's samples are contiguous in the block. The columns each quarter triangle covers are a
# contiguous range per row (fx is increasing, so ``y <= x`` holds on a suffix of the columns and
# ``y <= 1 - x`` on a prefix; float32 rounding keeps 1 − x non-increasing); the ranges are found by
# binary search with the masks' own comparisons, then one loop per mesh runs over its range with
# no mask. A valid rectangle [0:hv, 0:wv] (padding is a suffix) restricts rows and columns, which
# is what giving masked samples 0 did. Same float32 expressions, operands and order as
# :func:`_window_maxima` (the per-sample terms that depend on x alone — a00 + x·dx, x·el, … — are
# computed once per column: the same operations on the same operands).


@_jit
def _first_ge(X, n, t):
    """The first c < n with X[c] >= t (n if none); X non-decreasing."""
    lo, hi = 0, n
    while lo < hi:
        mid = (lo + hi) // 2
        if X[mid] >= t:
            hi = mid
        else:
            lo = mid + 1
    return lo


@_jit
def _count_le(X, n, t):
    """How many c < n have X[c] <= t (a prefix); X non-decreasing."""
    lo, hi = 0, n
    while lo < hi:
        mid = (lo + hi) // 2
        if X[mid] <= t:
            lo = mid + 1
        else:
            hi = mid
    return lo


@_jit
def _first_omx_le(X, n, t):
    """The first c < n with 1 − X[c] <= t (n if none)."""
    lo, hi = 0, n
    while lo < hi:
        mid = (lo + hi) // 2
        if _F1 - X[mid] <= t:
            hi = mid
        else:
            lo = mid + 1
    return lo


@_jit
def _count_omx_ge(X, n, t):
    """How many c < n have 1 − X[c] >= t (a prefix)."""
    lo, hi = 0, n
    while lo < hi:
        mid = (lo + hi) // 2
        if _F1 - X[mid] >= t:
            lo = mid + 1
        else:
            hi = mid
    return lo


@_jit
def _wrow_sq_even(M, P, X, Z, ydy, y, dd):
    for k in range(M.shape[0]):
        x = X[k]
        v = abs(P[k] + ydy + min(x, y) * dd - Z[k])
        o = M[k] + _F0  # + 0: a plain store, not a masked one (module docstring)
        M[k] = v if v > o else o


@_jit
def _wrow_sq_odd(M, P, X, Z, ydy, y, dd):
    for k in range(M.shape[0]):
        v = abs(P[k] + ydy + max(X[k] + y - _F1, _F0) * dd - Z[k])
        o = M[k] + _F0  # + 0: a plain store, not a masked one (module docstring)
        M[k] = v if v > o else o


@_jit
def _wrow_add(M, A, Z, t, c0, c1):
    """M[c] = max(M[c], |(A[c] + t) − Z[c]|) for c0 <= c < c1 (top, bottom: A[c] = a + x·d)."""
    for k in range(np.uint64(c0), np.uint64(c1)):
        v = abs(A[k] + t - Z[k])
        o = M[k] + _F0  # + 0: a plain store, not a masked one (module docstring)
        M[k] = v if v > o else o


@_jit
def _wrow_radd(M, A, Z, t, c0, c1):
    """M[c] = max(M[c], |(t + A[c]) − Z[c]|) for c0 <= c < c1 (left, right: t = a + y·d)."""
    for k in range(np.uint64(c0), np.uint64(c1)):
        v = abs(t + A[k] - Z[k])
        o = M[k] + _F0  # + 0: a plain store, not a masked one (module docstring)
        M[k] = v if v > o else o


@_jit
def _row_max(M):
    a = _F0
    for k in range(M.shape[0]):
        v = M[k]
        a = v if v > a else a
    return a


@_jit
def _window_rows(b, hv, wv, fx, fy, even, k):
    """:func:`_window_maxima` of the samples b[:hv, :wv] (all valid) at fractions fx[:wv],
    fy[:hv]: the five maxima, bit for bit (tests/test_ingest_kernels.py)."""
    a00, a10, a01, _a11, dx, dy, dd, et, eb, el, er, dx2, dy3 = k
    n = wv
    X = np.empty(n, np.float32)
    P, PB = np.empty(n, np.float32), np.empty(n, np.float32)
    XEL, OMXER = np.empty(n, np.float32), np.empty(n, np.float32)
    for c in range(n):
        x = fx[c]
        X[c] = x
        P[c] = a00 + x * dx
        PB[c] = a01 + x * dx2
        XEL[c] = x * el
        OMXER[c] = (_F1 - x) * er
    Msq, Mt, Mb = np.zeros(n, np.float32), np.zeros(n, np.float32), np.zeros(n, np.float32)
    Ml, Mr = np.zeros(n, np.float32), np.zeros(n, np.float32)
    for r in range(hv):
        y = fy[r]
        Z = b[r]  # the whole row (a C-contiguous view; the loops stop at n)
        if even:
            _wrow_sq_even(Msq, P, X, Z, y * dy, y, dd)
        else:
            _wrow_sq_odd(Msq, P, X, Z, y * dy, y, dd)
        ge_y, le_y = _first_ge(X, n, y), _count_le(X, n, y)
        omy = _F1 - y
        _wrow_add(Mt, P, Z, y * et, ge_y, _count_omx_ge(X, n, y))  # top: y <= x and y <= 1 - x
        _wrow_add(Mb, PB, Z, omy * eb, _first_omx_le(X, n, y), le_y)  # bottom: y >= x and y >= 1 - x
        _wrow_radd(Ml, XEL, Z, a00 + y * dy, 0, min(le_y, _count_le(X, n, omy)))  # left: x <= y and x <= 1 - y
        _wrow_radd(Mr, OMXER, Z, a10 + y * dy3, max(ge_y, _first_ge(X, n, omy)), n)  # right: x >= y and x >= 1 - y
    return _row_max(Msq), _row_max(Mt), _row_max(Mb), _row_max(Ml), _row_max(Mr)


@_jit
def _fold_np(acc, V0, U0, e, eps):
    """acc[V0 + i, U0 + j] = np.maximum(acc[…], e[i, j] + eps), NaN included (the window
    levels' Python folds)."""
    for i in range(e.shape[0]):
        for j in range(e.shape[1]):
            v, o = e[i, j] + eps, acc[V0 + i, U0 + j]
            acc[V0 + i, U0 + j] = o if (o >= v or np.isnan(o)) else v


@_jit
def window_level(b, hv, wv, fx, fy, g00, g10, g01, g11, gc, parity, tab, f, v0, u0, eps, SQ, DG):
    """One window level of :meth:`deviation.DeviationAccumulator._add_level` in one call: the
    block's samples [0:hv, 0:wv] (the valid ones) at fractions fx, fy of the lattice square
    (v0, u0) with corners g00, g10, g01, g11 and centre gc (float32 scalars), folded into the
    (1, 1) and (4, 1, 1) maxima as :func:`window_errors` does, and those plus ``eps`` into SQ
    and DG as the Python code's ``np.maximum`` did."""
    k = _corner_terms(g00, g10, g01, g11, gc)
    msq, mt, mb, ml, mr = _window_rows(b, hv, wv, fx, fy, parity % 2 == 0, k)
    sq, per = np.zeros((1, 1), np.float32), np.zeros((4, 1, 1), np.float32)
    V0, U0 = v0 // f, u0 // f
    _fold(sq, per, tab, f, v0, u0, V0, U0, 0, 0, msq, mt, mb, ml, mr)
    _fold_np(SQ, V0, U0, sq, eps)
    _fold_np(DG[0], V0, U0, per[0], eps)
    _fold_np(DG[0], V0 + 1, U0, per[1], eps)
    _fold_np(DG[1], V0, U0, per[2], eps)
    _fold_np(DG[1], V0, U0 + 1, per[3], eps)


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


@_jit
def _valid_extent(valid):
    """(hv, wv): the valid samples of a block are the rectangle [0:hv, 0:wv] (padding is a
    suffix in rows and columns)."""
    hv, wv = 0, 0
    while hv < valid.shape[0] and valid[hv, 0]:
        hv += 1
    while wv < valid.shape[1] and valid[0, wv]:
        wv += 1
    return hv, wv


@_jit
def padded_grid_errors(b, valid, s, nq, fx, c00, c10, c01, c11, cc, parity, tab, f, v0, u0, V0, U0, sq_out, per_out):  # noqa: PLR0913
    """:func:`masked_grid_errors` split by where the padding lies: the squares whose samples are
    all valid (the first (hv − 1) // s rows and (wv − 1) // s columns of squares) go through the
    vectorized row kernels of :func:`grid_errors`, only the squares straddling the valid edge
    through the masked per-square maxima over their valid rows and columns (:func:`_window_maxima`,
    a vectorized row at a time, from stride 16; :func:`_masked_maxima` below), squares entirely
    padding are skipped (as there). The same
    maxima, so the same folds, bit for bit (tests/test_ingest_kernels.py)."""
    hv, wv = _valid_extent(valid)
    if hv == 0 or wv == 0:
        return
    nv, nu = min((hv - 1) // s, nq), min((wv - 1) // s, nq)
    if nv > 0 and nu > 0:
        a00, a10 = np.ascontiguousarray(c00[:nv, :nu]), np.ascontiguousarray(c10[:nv, :nu])
        a01, a11 = np.ascontiguousarray(c01[:nv, :nu]), np.ascontiguousarray(c11[:nv, :nu])
        ac = np.ascontiguousarray(cc[:nv, :nu])
        if s <= 4 and nu < _NUP:
            m5 = _fine_maxima(b, s, a00, a10, a01, a11, ac, parity)
        elif s == 2:
            m5 = _direct_maxima(b, s, nq, fx, a00, a10, a01, a11, ac, parity)
        else:
            m5 = _lattice_maxima(b, s, nq, fx, a00, a10, a01, a11, ac, parity, s <= 32)
        _fold_rows(m5, tab, f, v0, u0, V0, U0, sq_out, per_out)
    for iv in range(nq):
        if iv * s >= hv:
            break
        for iu in range(nq):
            if iu * s >= wv:
                break
            if iv < nv and iu < nu:
                continue
            k = _corners(c00, c10, c01, c11, cc, iv, iu)
            even = (parity + iv + iu) % 2 == 0
            fy, fxv = fx[: min(s + 1, hv - iv * s)], fx[: min(s + 1, wv - iu * s)]  # its valid rows and columns
            if s >= 16:
                msq, mt, mb, ml, mr = _window_maxima(b, valid, iv * s, iu * s, fy, fxv, even, k)
            else:
                msq, mt, mb, ml, mr = _masked_maxima(b, valid, iv * s, iu * s, fy, fxv, even, k)
            _fold(sq_out, per_out, tab, f, v0, u0, V0, U0, iv, iu, msq, mt, mb, ml, mr)


# -- issue 20, fourth round: the lattice-square maxima as vectorizable loops ----------------------
# A row of nq squares of stride s is laid out as W = (s+1)·nq columns, the shared column of two
# squares twice: "c-major" (k = c·nq + iu: the samples c of every square together, for the fine
# strides) or "square-major" (k = iu·(s+1) + c). Per-square terms are spread over the columns
# (:func:`_spread`), each block row's samples too (:func:`_spread_row`); then one loop per mesh
# and block row folds |mesh − z| into that mesh's per-column maxima over the columns whose
# samples the mesh covers (whole ranges: no masks), and the columns are reduced per square at the
# end (:func:`_reduce`). Each loop is its own function with its arrays as arguments and one
# store array, so LLVM vectorizes it (in one big function it did not). The float32
# expressions, operands and order are those of :func:`_grid_squares`; maxima are exact in any order.


@_jit
def _sub2(out, a, b):
    n = out.shape[1]
    for i in range(out.shape[0]):
        for j in range(n):
            out[i, j] = a[i, j] - b[i, j]


@_jit
def _cross(out, a, b, c, d):
    n = out.shape[1]
    for i in range(out.shape[0]):
        for j in range(n):
            out[i, j] = a[i, j] - b[i, j] - c[i, j] + d[i, j]


@_jit
def _edge(out, cc, a, b):
    n = out.shape[1]
    for i in range(out.shape[0]):
        for j in range(n):
            out[i, j] = _F2 * cc[i, j] - a[i, j] - b[i, j]


@_jit
def _terms(c00, c10, c01, c11, cc):
    """The per-square terms of :func:`_corners` as (nq, nq) arrays, the same float32 operations
    in the same order (explicit loops: numba's array expressions took 1 ns an element)."""
    shape = c00.shape
    dx, dy, dd = np.empty(shape, np.float32), np.empty(shape, np.float32), np.empty(shape, np.float32)
    et, eb, el = np.empty(shape, np.float32), np.empty(shape, np.float32), np.empty(shape, np.float32)
    er, dx2, dy3 = np.empty(shape, np.float32), np.empty(shape, np.float32), np.empty(shape, np.float32)
    _sub2(dx, c10, c00)
    _sub2(dy, c01, c00)
    _cross(dd, c00, c10, c01, c11)
    _edge(et, cc, c00, c10)
    _edge(eb, cc, c01, c11)
    _edge(el, cc, c00, c01)
    _edge(er, cc, c10, c11)
    _sub2(dx2, c11, c01)
    _sub2(dy3, c11, c10)
    return dx, dy, dd, et, eb, el, er, dx2, dy3


@_jit
def _spread(DST, src, A, fx, s, nq, cm, lin):
    """DST[k(c, iu)] = src[iu], or A[iu] + fx[c]·src[iu] when ``lin``. (Indices here are
    unsigned: an index from a signed offset keeps numba's negative-index wraparound, which
    stops LLVM vectorizing the loop.)"""
    n, w = np.uint64(nq), np.uint64(s + 1)
    if cm:
        for c in range(s + 1):
            o, x = np.uint64(c) * n, fx[c]
            if lin:
                for k in range(o, o + n):
                    DST[k] = A[k - o] + x * src[k - o]
            else:
                for k in range(o, o + n):
                    DST[k] = src[k - o]
    else:
        for iu in range(nq):
            o, a, g = np.uint64(iu) * w, A[iu], src[iu]
            if lin:
                for k in range(o, o + w):
                    DST[k] = a + fx[k - o] * g
            else:
                for k in range(o, o + w):
                    DST[k] = g


@_jit
def _spread_row(Z, row, s, nq, cm):
    """Z[k(c, iu)] = row[iu·s + c]: one block row's samples laid out."""
    n, w, us = np.uint64(nq), np.uint64(s + 1), np.uint64(s)
    if cm:
        for c in range(s + 1):
            o, uc = np.uint64(c) * n, np.uint64(c)
            if s == 2:  # a constant stride: LLVM vectorizes the strided loads
                for k in range(n):
                    Z[o + k] = row[k * np.uint64(2) + uc]
            elif s == 4:
                for k in range(n):
                    Z[o + k] = row[k * np.uint64(4) + uc]
            elif s == 8:
                for k in range(n):
                    Z[o + k] = row[k * np.uint64(8) + uc]
            else:
                for k in range(n):
                    Z[o + k] = row[k * us + uc]
    else:
        for iu in range(nq):
            o, o2 = np.uint64(iu) * w, np.uint64(iu) * us
            for k in range(o, o + w):
                Z[k] = row[k - o + o2]


@_jit
def _reduce(out, M, s, nq, cm):
    """out[iu] = the maximum of M over square iu's columns."""
    n, w = np.uint64(nq), np.uint64(s + 1)
    if cm:
        for iu in range(nq):
            out[iu] = M[iu]
        for c in range(1, s + 1):
            o = np.uint64(c) * n
            for k in range(o, o + n):
                v, u = M[k], out[k - o] + _F0  # + 0: a plain store (module docstring)
                out[k - o] = v if v > u else u
    else:
        for iu in range(nq):
            o = np.uint64(iu) * w
            a = M[o]
            for k in range(o + np.uint64(1), o + w):
                v = M[k]
                a = v if v > a else a
            out[iu] = a


@_jit
def _fold_sq(M, X, EVN, P, GY, GD, Z, y):
    """M[k] = max(M[k], |(a00 + x·dx) + y·dy + w·dd − z|), w by the parity rule; every column."""
    for k in range(M.shape[0]):
        x = X[k]
        wgt = min(x, y) if EVN[k] != _F0 else max(x + y - _F1, _F0)
        v = abs(P[k] + y * GY[k] + wgt * GD[k] - Z[k])
        o = M[k] + _F0  # + 0: a plain store, not a masked one (module docstring)
        M[k] = v if v > o else o


@_jit
def _fold_q2(M, A, B, Z, t, c0, c1, s, nq, cm):
    """M[k] = max(M[k], |A + t·B − z|) over the columns of samples c0 <= c <= c1 (top, bottom)."""
    n, w = np.uint64(nq), np.uint64(s + 1)
    segs, step = (1, n) if cm else (nq, w)
    a, b = (np.uint64(c0) * n, np.uint64(c1 + 1) * n) if cm else (np.uint64(c0), np.uint64(c1 + 1))
    for g in range(segs):
        o = np.uint64(g) * step
        for k in range(o + a, o + b):
            v = abs(A[k] + t * B[k] - Z[k])
            u = M[k] + _F0  # + 0: a plain store (module docstring)
            M[k] = v if v > u else u


@_jit
def _fold_q3(M, A, B, C, D, Z, t, c0, c1, s, nq, cm):
    """M[k] = max(M[k], |A + t·B + C·D − z|) over the columns of samples c0 <= c <= c1 (left, right)."""
    n, w = np.uint64(nq), np.uint64(s + 1)
    segs, step = (1, n) if cm else (nq, w)
    a, b = (np.uint64(c0) * n, np.uint64(c1 + 1) * n) if cm else (np.uint64(c0), np.uint64(c1 + 1))
    for g in range(segs):
        o = np.uint64(g) * step
        for k in range(o + a, o + b):
            v = abs(A[k] + t * B[k] + C[k] * D[k] - Z[k])
            u = M[k] + _F0  # + 0: a plain store (module docstring)
            M[k] = v if v > u else u


@_jit
def _lattice_maxima(b, s, nq, fx, c00, c10, c01, c11, cc, parity, cm):  # noqa: PLR0913
    """The five maxima (square, top, bottom, left, right) of every lattice square, (5, nq, nq)
    float32, by the laid-out rows above (``cm``: c-major, else square-major); bit-identical to
    :func:`_grid_squares`'s (tests/test_ingest_kernels.py). The squares are those of the corner
    arrays, (nv, nu) = c00.shape (``nq`` × ``nq`` for a whole block; fewer in a padded block),
    the output (5, nv, nu)."""
    nv, nu = c00.shape[0], c00.shape[1]
    dx, dy, dd, et, eb, el, er, dx2, dy3 = _terms(c00, c10, c01, c11, cc)
    W = nu * (s + 1)
    X, OMX, EVN, P, PB = np.empty(W, np.float32), np.empty(W, np.float32), np.empty(W, np.float32), np.empty(W, np.float32), np.empty(W, np.float32)
    GY, GD, ET, EB, A00 = np.empty(W, np.float32), np.empty(W, np.float32), np.empty(W, np.float32), np.empty(W, np.float32), np.empty(W, np.float32)
    EL, A10, DY3, ER, Z = np.empty(W, np.float32), np.empty(W, np.float32), np.empty(W, np.float32), np.empty(W, np.float32), np.empty(W, np.float32)
    Msq, Mt, Mb, Ml, Mr = np.empty(W, np.float32), np.empty(W, np.float32), np.empty(W, np.float32), np.empty(W, np.float32), np.empty(W, np.float32)
    one, zero, ev = np.ones(nu, np.float32), np.zeros(nu, np.float32), np.empty(nu, np.float32)
    omx = _F1 - fx
    _spread(X, one, zero, fx, s, nu, cm, True)  # 0 + x·1 = x exactly
    _spread(OMX, one, zero, omx, s, nu, cm, True)
    out = np.empty((5, nv, nu), np.float32)
    for iv in range(nv):
        for iu in range(nu):
            ev[iu] = _F1 if (parity + iv + iu) % 2 == 0 else _F0
        _spread(EVN, ev, zero, fx, s, nu, cm, False)
        _spread(P, dx[iv], c00[iv], fx, s, nu, cm, True)
        _spread(PB, dx2[iv], c01[iv], fx, s, nu, cm, True)
        _spread(GY, dy[iv], zero, fx, s, nu, cm, False)
        _spread(GD, dd[iv], zero, fx, s, nu, cm, False)
        _spread(ET, et[iv], zero, fx, s, nu, cm, False)
        _spread(EB, eb[iv], zero, fx, s, nu, cm, False)
        _spread(A00, c00[iv], zero, fx, s, nu, cm, False)
        _spread(EL, el[iv], zero, fx, s, nu, cm, False)
        _spread(A10, c10[iv], zero, fx, s, nu, cm, False)
        _spread(DY3, dy3[iv], zero, fx, s, nu, cm, False)
        _spread(ER, er[iv], zero, fx, s, nu, cm, False)
        Msq[:], Mt[:], Mb[:], Ml[:], Mr[:] = _F0, _F0, _F0, _F0, _F0
        for r in range(s + 1):
            y = fx[r]
            _spread_row(Z, b[iv * s + r], s, nu, cm)
            _fold_sq(Msq, X, EVN, P, GY, GD, Z, y)
            if 2 * r <= s:  # top: r <= c <= s - r
                _fold_q2(Mt, P, ET, Z, y, r, s - r, s, nu, cm)
            if 2 * r >= s:  # bottom: s - r <= c <= r
                _fold_q2(Mb, PB, EB, Z, _F1 - y, s - r, r, s, nu, cm)
            _fold_q3(Ml, A00, GY, X, EL, Z, y, 0, min(r, s - r), s, nu, cm)  # left: c <= min(r, s - r)
            _fold_q3(Mr, A10, DY3, OMX, ER, Z, y, max(r, s - r), s, s, nu, cm)  # right: c >= max(r, s - r)
        _reduce(out[0, iv], Msq, s, nu, cm)
        _reduce(out[1, iv], Mt, s, nu, cm)
        _reduce(out[2, iv], Mb, s, nu, cm)
        _reduce(out[3, iv], Ml, s, nu, cm)
        _reduce(out[4, iv], Mr, s, nu, cm)
    return out



@_jit
def _fold_eps(acc, V0, U0, e, eps):
    """acc[V0 + i, U0 + j] = max(acc[…], e[i, j] + eps): what ``np.maximum(sl, e + eps, out=sl)``
    did (float32 sum, then the maximum; never NaN)."""
    for i in range(e.shape[0]):
        for j in range(e.shape[1]):
            v, o = e[i, j] + eps, acc[V0 + i, U0 + j]
            acc[V0 + i, U0 + j] = v if v > o else o


@_jit
def grid_level(b, valid, masked, s, m, f, bi, bj, tab, eps, SQ, DG):  # noqa: PLR0913
    """One grid level of :meth:`deviation.DeviationAccumulator._add_level` in one call: the
    lattice corners of stride ``s`` of block (bi, bj) (what ``grid_error_args`` cuts out),
    :func:`grid_errors` (or :func:`padded_grid_errors` where ``masked``) into zeroed maxima,
    then those plus ``eps`` max-folded into the level's square errors SQ and diagonal errors DG
    (the Python code's ``np.maximum`` folds: same float32 sums, exact maxima)."""
    nq = (1 << m) // s
    h = s // 2
    c00 = np.ascontiguousarray(b[0: nq * s: s, 0: nq * s: s])
    c10 = np.ascontiguousarray(b[0: nq * s: s, s: nq * s + 1: s])
    c01 = np.ascontiguousarray(b[s: nq * s + 1: s, 0: nq * s: s])
    c11 = np.ascontiguousarray(b[s: nq * s + 1: s, s: nq * s + 1: s])
    cc = np.ascontiguousarray(b[h: nq * s: s, h: nq * s: s])
    fx = np.arange(s + 1).astype(np.float32) / np.float32(s)  # exact: s is a power of two
    v0, u0 = bi * nq, bj * nq
    V0, U0 = v0 // f, u0 // f
    n = max(nq // f, 1)
    sq, per = np.zeros((n, n), np.float32), np.zeros((4, n, n), np.float32)
    if masked:
        padded_grid_errors(b, valid, s, nq, fx, c00, c10, c01, c11, cc, (v0 + u0) % 2, tab, f, v0, u0, V0, U0, sq, per)
    else:
        grid_errors(b, s, nq, fx, c00, c10, c01, c11, cc, (v0 + u0) % 2, tab, f, v0, u0, V0, U0, sq, per)
    _fold_eps(SQ, V0, U0, sq, eps)
    _fold_eps(DG[0], V0, U0, per[0], eps)
    _fold_eps(DG[0], V0 + 1, U0, per[1], eps)
    _fold_eps(DG[1], V0, U0, per[2], eps)
    _fold_eps(DG[1], V0, U0 + 1, per[3], eps)


@_jit
def _dsq(M, A, B, C, D, Z, zo, EVN, x, y, we, wo):
    """M[k] = max(M[k], |A + x·B + y·C + w·D − Z[zo + k]|), w = we or wo by EVN[k]."""
    for k in range(M.shape[0]):
        wgt = we if EVN[k] != _F0 else wo
        v = abs(A[k] + x * B[k] + y * C[k] + wgt * D[k] - Z[np.uint64(k) + zo])
        o = M[k] + _F0  # + 0: a plain store, not a masked one (module docstring)
        M[k] = v if v > o else o


@_jit
def _dlin(M, A, B, C, Z, zo, p, q):
    """M[k] = max(M[k], |A + p·B + q·C − Z[zo + k]|)."""
    for k in range(M.shape[0]):
        v = abs(A[k] + p * B[k] + q * C[k] - Z[np.uint64(k) + zo])
        o = M[k] + _F0  # + 0: a plain store, not a masked one (module docstring)
        M[k] = v if v > o else o


@_jit
def _deinterleave_block(b, s, nv, nu):
    """D[p, R, j] = b[R, j·s + p] for the block rows R = 0..nv·s (j ≤ nu where j·s + p ≤ nu·s)."""
    n = nv * s + 1
    D = np.zeros((s, n, nu + 1), np.float32)
    for p in range(s):
        cnt = (nu * s - p) // s + 1
        for R in range(n):
            d, row = D[p, R], b[R]
            if s == 2:  # constant strides: LLVM vectorizes the strided loads
                for j in range(cnt):
                    d[j] = row[2 * j + p]
            elif s == 4:
                for j in range(cnt):
                    d[j] = row[4 * j + p]
            else:
                for j in range(cnt):
                    d[j] = row[s * j + p]
    return D


@_jit
def _direct_maxima(b, s, nq, fx, c00, c10, c01, c11, cc, parity):  # noqa: PLR0913
    """The five maxima of every lattice square, (5, nq, nq), for the finest strides: for each
    sample position (r, c) of a square, one loop over the row of squares (:func:`_dsq`,
    :func:`_dlin`: per-square terms as they are, the samples from the block de-interleaved
    once by stride, unsigned offsets: vectorized). The same float32 expressions, operands and
    order as :func:`_grid_squares`; maxima are exact in any order. The squares are those of
    the corner arrays, (nv, nu) = c00.shape, the output (5, nv, nu)."""
    nv, nu = c00.shape[0], c00.shape[1]
    dx, dy, dd, et, eb, el, er, dx2, dy3 = _terms(c00, c10, c01, c11, cc)
    D = _deinterleave_block(b, s, nv, nu)
    out = np.zeros((5, nv, nu), np.float32)
    ev = np.empty(nu, np.float32)
    for iv in range(nv):
        for iu in range(nu):
            ev[iu] = _F1 if (parity + iv + iu) % 2 == 0 else _F0
        o0, o1, o2, o3, o4 = out[0, iv], out[1, iv], out[2, iv], out[3, iv], out[4, iv]
        a00, a10, a01 = c00[iv], c10[iv], c01[iv]
        gx, gy, gd, gt, gb, gl, gr, gx2, gy3 = dx[iv], dy[iv], dd[iv], et[iv], eb[iv], el[iv], er[iv], dx2[iv], dy3[iv]
        for r in range(s + 1):
            y = fx[r]
            for c in range(s + 1):
                x = fx[c]
                Z, zo = D[c % s, iv * s + r], np.uint64(c // s)
                _dsq(o0, a00, gx, gy, gd, Z, zo, ev, x, y, min(x, y), max(x + y - _F1, _F0))
                if r <= c <= s - r:  # top
                    _dlin(o1, a00, gx, gt, Z, zo, x, y)
                if s - r <= c <= r:  # bottom
                    _dlin(o2, a01, gx2, gb, Z, zo, x, _F1 - y)
                if c <= min(r, s - r):  # left
                    _dlin(o3, a00, gy, gl, Z, zo, y, x)
                if c >= max(r, s - r):  # right
                    _dlin(o4, a10, gy3, gr, Z, zo, y, _F1 - x)
    return out



# -- issue 20, eighth round: strides 2 and 4 a square at a time in registers ---------------------
# The finest strides have the most squares and the fewest samples each, so the loops above pay
# for a load and a store of each running maximum per sample and square. Here one loop over a row
# of squares evaluates all of a square's samples (S = 2 or 4: the loops over r and c are fully
# unrolled, S and r being constants where :func:`_fine_row` is inlined) with its five maxima in
# registers. Everything the loop reads besides the block's S + 1 rows, and everything it writes,
# is one scratch vector at constant offsets (segments of _NUP), so LLVM needs no run-time alias
# check between them (with ~20 separate arrays it would not vectorize the loop at all).

_NUP = 264  # scratch segment: ≥ the squares in a row (≤ 256: a 513-block at stride 2), multiple of 8
_A00, _A10, _A01, _DX, _DY, _DD, _ET, _EB, _EL, _ER, _DX2, _DY3, _EV, _OUT = range(14)  # segments
_Z = _OUT + 5  # then the block rows' samples, de-interleaved: segment _Z + r·S + p holds row r's samples S·j + p


@_jit_inline
def _seg(t, k):
    return np.uint64(t * _NUP) + k


@_jit
def _fine_terms(buf, c00, c10, c01, c11, cc, iv, nu, parity):
    """The terms of :func:`_corners` of the row iv of squares into buf's segments (same float32
    operations in the same order), and each square's parity (1: even)."""
    a00, a10, a01, a11, ac = c00[iv], c10[iv], c01[iv], c11[iv], cc[iv]
    for j in range(nu):
        k = np.uint64(j)
        p, q, u, w, e = a00[k], a10[k], a01[k], a11[k], ac[k]
        buf[_seg(_A00, k)] = p
        buf[_seg(_A10, k)] = q
        buf[_seg(_A01, k)] = u
        buf[_seg(_DX, k)] = q - p
        buf[_seg(_DY, k)] = u - p
        buf[_seg(_DD, k)] = p - q - u + w
        buf[_seg(_ET, k)] = _F2 * e - p - q
        buf[_seg(_EB, k)] = _F2 * e - u - w
        buf[_seg(_EL, k)] = _F2 * e - p - u
        buf[_seg(_ER, k)] = _F2 * e - q - w
        buf[_seg(_DX2, k)] = w - u
        buf[_seg(_DY3, k)] = w - q
        buf[_seg(_EV, k)] = _F1 if (parity + iv + j) % 2 == 0 else _F0


@_jit_inline
def _vmax(m, v):
    """The running maximum's rule everywhere here: v where v > m (never a NaN v)."""
    return v if v > m else m


@_jit_inline
def _fine_row(T, zs, r, S, m):
    """Sample row r (0..S) of one square: its samples zs (S + 1 values, c = 0..S) against the
    square mesh of terms T (:func:`_fine_terms`' order) and the quarters that hold them (the
    column ranges of :func:`_grid_squares`), folded into the maxima m = (m0, …, m4). S and r are
    constants where this is inlined, so the loop over c unrolls. (No array arguments: passing
    one adds reference counting to the caller's loop, which LLVM will not vectorize.)"""
    a00, a10, a01, dx, dy, dd, et, eb, el, er, dx2, dy3, ev = T
    m0, m1, m2, m3, m4 = m
    fs = np.float32(S)
    y = np.float32(r) / fs  # fx[r] = r / S exactly, as arange(S + 1) / S
    for c in range(S + 1):
        x = np.float32(c) / fs
        z = zs[c]
        wgt = min(x, y) if ev != _F0 else max(x + y - _F1, _F0)
        m0 = _vmax(m0, abs(a00 + x * dx + y * dy + wgt * dd - z))
        if r <= c <= S - r:  # top
            m1 = _vmax(m1, abs(a00 + x * dx + y * et - z))
        if S - r <= c <= r:  # bottom
            m2 = _vmax(m2, abs(a01 + x * dx2 + (_F1 - y) * eb - z))
        if c <= min(r, S - r):  # left
            m3 = _vmax(m3, abs(a00 + y * dy + x * el - z))
        if c >= max(r, S - r):  # right
            m4 = _vmax(m4, abs(a10 + y * dy3 + (_F1 - x) * er - z))
    return m0, m1, m2, m3, m4


@_jit
def _fine2(buf, nu):
    """Every square of the row in buf at stride 2 (the loop LLVM vectorizes)."""
    for j in range(nu):
        k = np.uint64(j)
        k1 = k + np.uint64(1)
        T = (buf[_seg(_A00, k)], buf[_seg(_A10, k)], buf[_seg(_A01, k)], buf[_seg(_DX, k)], buf[_seg(_DY, k)],
             buf[_seg(_DD, k)], buf[_seg(_ET, k)], buf[_seg(_EB, k)], buf[_seg(_EL, k)], buf[_seg(_ER, k)],
             buf[_seg(_DX2, k)], buf[_seg(_DY3, k)], buf[_seg(_EV, k)])
        m = (_F0, _F0, _F0, _F0, _F0)
        m = _fine_row(T, (buf[_seg(_Z, k)], buf[_seg(_Z + 1, k)], buf[_seg(_Z, k1)]), 0, 2, m)
        m = _fine_row(T, (buf[_seg(_Z + 2, k)], buf[_seg(_Z + 3, k)], buf[_seg(_Z + 2, k1)]), 1, 2, m)
        m = _fine_row(T, (buf[_seg(_Z + 4, k)], buf[_seg(_Z + 5, k)], buf[_seg(_Z + 4, k1)]), 2, 2, m)
        buf[_seg(_OUT, k)], buf[_seg(_OUT + 1, k)], buf[_seg(_OUT + 2, k)] = m[0], m[1], m[2]
        buf[_seg(_OUT + 3, k)], buf[_seg(_OUT + 4, k)] = m[3], m[4]


@_jit
def _fine4(buf, nu):
    """Every square of the row in buf at stride 4 (the loop LLVM vectorizes)."""
    for j in range(nu):
        k = np.uint64(j)
        k1 = k + np.uint64(1)
        T = (buf[_seg(_A00, k)], buf[_seg(_A10, k)], buf[_seg(_A01, k)], buf[_seg(_DX, k)], buf[_seg(_DY, k)],
             buf[_seg(_DD, k)], buf[_seg(_ET, k)], buf[_seg(_EB, k)], buf[_seg(_EL, k)], buf[_seg(_ER, k)],
             buf[_seg(_DX2, k)], buf[_seg(_DY3, k)], buf[_seg(_EV, k)])
        m = (_F0, _F0, _F0, _F0, _F0)
        z = _Z
        m = _fine_row(T, (buf[_seg(z, k)], buf[_seg(z + 1, k)], buf[_seg(z + 2, k)], buf[_seg(z + 3, k)], buf[_seg(z, k1)]), 0, 4, m)
        z = _Z + 4
        m = _fine_row(T, (buf[_seg(z, k)], buf[_seg(z + 1, k)], buf[_seg(z + 2, k)], buf[_seg(z + 3, k)], buf[_seg(z, k1)]), 1, 4, m)
        z = _Z + 8
        m = _fine_row(T, (buf[_seg(z, k)], buf[_seg(z + 1, k)], buf[_seg(z + 2, k)], buf[_seg(z + 3, k)], buf[_seg(z, k1)]), 2, 4, m)
        z = _Z + 12
        m = _fine_row(T, (buf[_seg(z, k)], buf[_seg(z + 1, k)], buf[_seg(z + 2, k)], buf[_seg(z + 3, k)], buf[_seg(z, k1)]), 3, 4, m)
        z = _Z + 16
        m = _fine_row(T, (buf[_seg(z, k)], buf[_seg(z + 1, k)], buf[_seg(z + 2, k)], buf[_seg(z + 3, k)], buf[_seg(z, k1)]), 4, 4, m)
        buf[_seg(_OUT, k)], buf[_seg(_OUT + 1, k)], buf[_seg(_OUT + 2, k)] = m[0], m[1], m[2]
        buf[_seg(_OUT + 3, k)], buf[_seg(_OUT + 4, k)] = m[3], m[4]


@_jit
def _fine_samples(buf, b, R, S, nu):
    """Block rows R .. R + S de-interleaved into buf: segment _Z + r·S + p, element j = b[R + r, S·j + p]."""
    for r in range(S + 1):
        row = b[R + r]
        for p in range(S):
            o = np.uint64((_Z + r * S + p) * _NUP)
            cnt = (nu * S - p) // S + 1
            if S == 2:
                for j in range(np.uint64(cnt)):
                    buf[o + j] = row[j * np.uint64(2) + np.uint64(p)]
            else:
                for j in range(np.uint64(cnt)):
                    buf[o + j] = row[j * np.uint64(4) + np.uint64(p)]


@_jit
def _fine_maxima(b, s, c00, c10, c01, c11, cc, parity):
    """The five maxima of every lattice square, (5, nv, nu) for the corner arrays' (nv, nu), at
    stride s = 2 or 4, a square at a time (above); bit-identical to :func:`_grid_squares`
    (tests/test_ingest_kernels.py)."""
    nv, nu = c00.shape[0], c00.shape[1]
    buf = np.zeros((_Z + 20) * _NUP, np.float32)
    out = np.empty((5, nv, nu), np.float32)
    for iv in range(nv):
        _fine_terms(buf, c00, c10, c01, c11, cc, iv, nu, parity)
        _fine_samples(buf, b, iv * s, s, nu)
        if s == 2:
            _fine2(buf, nu)
        else:
            _fine4(buf, nu)
        for q in range(5):
            o = out[q, iv]
            for j in range(nu):
                o[j] = buf[_seg(_OUT + q, np.uint64(j))]
    return out
