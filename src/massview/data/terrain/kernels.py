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
def _corners(c00, c10, c01, c11, cc, iv, iu):
    a00, a10, a01, a11, ac = c00[iv, iu], c10[iv, iu], c01[iv, iu], c11[iv, iu], cc[iv, iu]
    return (a00, a10, a01, a11, a10 - a00, a01 - a00, a00 - a10 - a01 + a11, _F2 * ac - a00 - a10,
            _F2 * ac - a01 - a11, _F2 * ac - a00 - a01, _F2 * ac - a10 - a11, a11 - a01, a11 - a10)


@_jit
def _deinterleave(row, s, out):
    """``out[p, j] = row[j·s + p]`` (s, nq+1) float32, where that sample exists."""
    n = row.shape[0]
    for j in range(out.shape[1]):
        for p in range(s):
            if j * s + p < n:
                out[p, j] = row[j * s + p]


@_jit
def _max_into(m, i, v):
    """m[i] = max(m[i], v) as a select (v >= 0, never NaN: the same value as ``max``)."""
    o = m[i]
    m[i] = v if v > o else o


@_jit
def _fine_maxima(b, s, nq, fx, c00, c10, c01, c11, cc, parity):  # noqa: PLR0913, PLR0915
    """The five maxima of every lattice square at once, (5, nq, nq) float32, for the fine
    strides (few samples per square): for each sample position (r, c) of a square, one loop
    over a whole row of squares, on the row's samples de-interleaved by stride (contiguous
    loads), with the corner terms of :func:`_corners` as arrays. The same float32 expressions
    over the same samples as :func:`_grid_squares`; a maximum does not depend on the order it
    is taken in (no NaN: the ingest fills them; every value is an ``abs``, so no −0), so the
    results are bit-identical."""
    dx, dy, dd = c10 - c00, c01 - c00, c00 - c10 - c01 + c11
    et, eb = _F2 * cc - c00 - c10, _F2 * cc - c01 - c11
    el, er = _F2 * cc - c00 - c01, _F2 * cc - c10 - c11
    dx2, dy3 = c11 - c01, c11 - c10
    out = np.zeros((5, nq, nq), np.float32)
    D = np.empty((s, nq + 1), np.float32)
    even = np.empty(nq, np.bool_)
    for iv in range(nq):
        msq, mt, mb, ml, mr = out[0, iv], out[1, iv], out[2, iv], out[3, iv], out[4, iv]
        a00, a10, a01 = c00[iv], c10[iv], c01[iv]
        gx, gy, gd, gt, gb, gl, gr, gx2, gy3 = dx[iv], dy[iv], dd[iv], et[iv], eb[iv], el[iv], er[iv], dx2[iv], dy3[iv]
        for iu in range(nq):
            even[iu] = (parity + iv + iu) % 2 == 0
        for r in range(s + 1):
            y = fx[r]
            _deinterleave(b[iv * s + r], s, D)
            for c in range(s + 1):
                x = fx[c]
                z = D[c % s, c // s: c // s + nq]  # z[iu] = b[iv·s + r, iu·s + c]
                we, wo = min(x, y), max(x + y - _F1, _F0)
                for iu in range(nq):
                    wgt = we if even[iu] else wo
                    _max_into(msq, iu, abs(a00[iu] + x * gx[iu] + y * gy[iu] + wgt * gd[iu] - z[iu]))
                if r <= c <= s - r:  # top
                    for iu in range(nq):
                        _max_into(mt, iu, abs(a00[iu] + x * gx[iu] + y * gt[iu] - z[iu]))
                if s - r <= c <= r:  # bottom
                    for iu in range(nq):
                        _max_into(mb, iu, abs(a01[iu] + x * gx2[iu] + (_F1 - y) * gb[iu] - z[iu]))
                if c <= min(r, s - r):  # left
                    for iu in range(nq):
                        _max_into(ml, iu, abs(a00[iu] + y * gy[iu] + x * gl[iu] - z[iu]))
                if c >= max(r, s - r):  # right
                    for iu in range(nq):
                        _max_into(mr, iu, abs(a10[iu] + y * gy3[iu] + (_F1 - x) * gr[iu] - z[iu]))
    return out


@_jit
def grid_errors(b, s, nq, fx, c00, c10, c01, c11, cc, parity, tab, f, v0, u0, V0, U0, sq_out, per_out):  # noqa: PLR0913
    """Exact deviations of the ``nq × nq`` closed lattice squares of spacing ``s`` over a block
    whose samples are all valid; ``fx = arange(s+1)/s`` (float32). Max-folds into sq_out
    (nV, nU) and per_out (4, nV, nU), see :func:`_fold`. The strides up to 64 (most squares,
    fewest samples each) take a whole row of squares per loop (:func:`_fine_maxima`); the
    results are those of :func:`_grid_squares` bit for bit (tests/test_ingest_kernels.py)."""
    if s > 64:
        _grid_squares(b, s, nq, fx, c00, c10, c01, c11, cc, parity, tab, f, v0, u0, V0, U0, sq_out, per_out)
        return
    _fold_rows(_fine_maxima(b, s, nq, fx, c00, c10, c01, c11, cc, parity), tab, f, v0, u0, V0, U0, sq_out, per_out)


@_jit
def _fold_rows(m5, tab, f, v0, u0, V0, U0, sq_out, per_out):
    """:func:`_fold` of every square's maxima ``m5`` (5, nq, nq); ``f`` is a power of two and
    the lattice indices are not negative, so // and % are a shift and a mask (the integer
    divisions of :func:`_fold` cost about as much as the maxima of a fine stride)."""
    sh, mask = 0, f - 1
    while (1 << sh) < f:
        sh += 1
    nq = m5.shape[1]
    for iv in range(nq):
        v = v0 + iv
        a, vm = (v >> sh) - V0, v & mask
        for iu in range(nq):
            u = u0 + iu
            bb, um = (u >> sh) - U0, u & mask
            sq_out[a, bb] = max(sq_out[a, bb], m5[0, iv, iu])
            for q in range(4):
                r = tab[q, vm, um]
                per_out[r, a, bb] = max(per_out[r, a, bb], m5[q + 1, iv, iu])


@_jit
def _grid_squares(b, s, nq, fx, c00, c10, c01, c11, cc, parity, tab, f, v0, u0, V0, U0, sq_out, per_out):  # noqa: PLR0913
    """One lattice square at a time: :func:`grid_errors` for the coarse strides (> 64: many
    samples per square), and for every stride the reference the tests compare its fine path
    with (the kernel before issue 20's third round). Exact deviations of the ``nq × nq`` closed lattice squares of spacing ``s`` over a block
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
