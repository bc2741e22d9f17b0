"""The exact-error kernels of one lattice square that contains a whole block (the window
levels, above the block's own level) and of the squares straddling a padded block's valid edge:
a row at a time, vectorized. The bit-exactness contract is in :mod:`kernels`' docstring."""

from __future__ import annotations

import numpy as np

from .kernelbase import _F0, _F1, _corner_terms, _fold, _jit


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

