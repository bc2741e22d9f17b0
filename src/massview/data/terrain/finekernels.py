"""The exact-error kernels of strides 2 and 4, a square at a time in registers (issue 20,
eighth round). The bit-exactness contract is in :mod:`kernels`' docstring."""

from __future__ import annotations

import numpy as np

from .kernelbase import _F0, _F1, _F2, _jit, _jit_inline

# -- issue 20, eighth round: strides 2 and 4 a square at a time in registers ---------------------
# The finest strides have the most squares and the fewest samples each, so the row loops of
# :mod:`latticekernels` pay for a load and a store of each running maximum per sample and square.
# Here one loop over a row
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

