"""Shared pieces of the exact-error kernels (:mod:`kernels` and the modules it draws on):
numba's ``njit`` as they use it, the float32 constants, a lattice square's corner terms and the
fold of one square's maxima into a block's patch squares and edge diamonds. The bit-exactness
contract all of them keep is in :mod:`kernels`' docstring."""

from __future__ import annotations

import numpy as np

from ..jit import njit  # (numba, imported the data layer's way)


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

