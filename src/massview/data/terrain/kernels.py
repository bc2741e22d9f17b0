"""Compiled per-sample kernels of the ingest's exact K-patch errors (numba, cached on disk,
GIL released): the entry points :mod:`deviation` calls.

For every closed lattice square of a block they evaluate the square mesh and the four quarter
triangles of the centred mesh at each finest sample and keep the maximum deviation. They
perform, per sample, exactly the float32 operations (same operands, same order, no fused
multiply-add, no fast-math) that the numpy expressions of :class:`deviation.DeviationAccumulator`
performed through broadcasting, so their results are bit-identical to them — the golden-store
test (tests/test_ingest_parallel.py) checks this on whole stores, tests/test_ingest_kernels.py
each kernel against the per-square reference loops. Maxima are exact whatever the order.

Where they live: here :func:`grid_errors`, :func:`padded_grid_errors` and :func:`grid_level`
(the grid levels, strides up to the block's size) and the fold of per-square maxima into patch
squares and diamonds; :mod:`finekernels` strides 2 and 4 (a square at a time in registers);
:mod:`latticekernels` strides 8 and up (laid-out rows) and the per-sample-position loops;
:mod:`windowkernels` the window levels (:func:`windowkernels.window_level`) and the masked
per-square maxima of a padded block's edge squares; :mod:`kernelbase` the shared pieces
(``_jit``, constants, corner terms, ``_fold``); :mod:`refkernels` the reference loops only the
tests use (``_grid_squares``, ``masked_grid_errors``, ``window_errors``).

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

from .finekernels import _NUP, _fine_maxima
from .kernelbase import _F0, _corners, _fold, _jit, _jit_inline  # noqa: F401  (_jit, _jit_inline: rowkernels' import)
from .latticekernels import _direct_maxima, _lattice_maxima
from .windowkernels import _masked_maxima, _window_maxima

__all__ = ["grid_errors", "grid_level", "padded_grid_errors"]


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

