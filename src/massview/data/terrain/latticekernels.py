"""The exact-error kernels of whole rows of lattice squares at strides 8 and up (and any stride,
as the tests use them): laid-out rows (:func:`_lattice_maxima`) and per-sample loops over
de-interleaved rows (:func:`_direct_maxima`). The bit-exactness contract is in :mod:`kernels`'
docstring; :mod:`refkernels` holds the per-square loop they are compared with."""

from __future__ import annotations

import numpy as np

from .kernelbase import _F0, _F1, _jit, _terms

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



# -- per sample position, one loop over the row of squares (any stride; grid_errors no longer picks it) --


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

