"""Reference loops of the exact-error kernels, used only by the tests
(tests/test_ingest_kernels.py): the per-square kernel the compiled row kernels replaced
(:func:`_grid_squares`), the masked per-square kernel of padded blocks
(:func:`masked_grid_errors`) and the one-square window kernel (:func:`window_errors`). The
kernels of :mod:`kernels` give their results bit for bit."""

from __future__ import annotations

from .kernelbase import _F0, _F1, _corners, _fold, _jit
from .windowkernels import _masked_maxima, _window_maxima

__all__ = ["masked_grid_errors", "window_errors"]


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
def window_errors(b, valid, fx, fy, c00, c10, c01, c11, cc, parity, tab, f, v0, u0, sq_out, per_out):  # noqa: PLR0913
    """Exact deviations of one lattice square that contains the whole block (any fractional
    coordinates fx (w,), fy (h,), float32; only ``valid`` samples count), by the masks of
    the numpy formulation. Max-folds into sq_out (1, 1) and per_out (4, 1, 1)."""
    k = _corners(c00, c10, c01, c11, cc, 0, 0)
    msq, mt, mb, ml, mr = _window_maxima(b, valid, 0, 0, fy, fx, parity % 2 == 0, k)
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

