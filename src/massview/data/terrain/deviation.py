"""Exact K-patch errors: how far the drawn surface of a diamond's patches lies from the
finest samples it covers (RASTeR's object-space patch error made a true bound).

When a diamond D is not split, its two triangles are drawn as K-patches, whose surface is
the regular 4-8 mesh of one resolution restricted to D's area (see :mod:`layout`):

* a square-level-j patch uses the **square mesh** Q_l, l = J - j: the lattice of spacing
  s = 2^l, every lattice square cut by one diagonal (the parity rule: from (u, v) to
  (u+1, v+1) when u + v is even, global lattice indices);
* a diagonal-level-j patch uses the **centred mesh** C_l, l = J - j: the same lattice plus
  the square centres, every lattice square cut into four triangles by both diagonals.

The local error of D is the exact maximum of |mesh(x, y) − h(x, y)| over the finest samples
(x, y) of D's closed area (squares of side A = s·2^k; an edge diamond is the rotated square
made of the four A-square triangles beside its edge). The A-square diagonals cut lattice
squares only along their own diagonals, so every quarter triangle of a lattice square lies in
exactly one edge diamond; errors are reduced per lattice square and quarter first.

:func:`saturate` (in :mod:`meta`) then makes the errors monotone over the diamond DAG, so a
drawn triangle's hypotenuse diamond bounds the deviation of every sample under the triangle.
Samples beyond the input extent (padding, never drawn) are left out. Work is done per
level-0 block (M × M float32, its shared border included); coarse lattice vertices outside
the block come from ``coarse``, the finest samples at spacing 2^m.
"""

from __future__ import annotations

import numpy as np
from .layout import TerrainLayout

__all__ = ["DeviationAccumulator", "coarse_lattice"]

_NO_MASK = np.ones((1, 1), np.bool_)  # grid_level's ``valid`` where the block has no padding
_CENTROIDS = ((0.5, 1 / 6), (0.5, 5 / 6), (1 / 6, 0.5), (5 / 6, 0.5))  # top, bottom, left, right (x, y)


def coarse_lattice(store) -> np.ndarray:
    """Finest samples at spacing 2^m (the corners of every level-0 block): (2^L+1)² float32."""
    lay = store.layout
    m, L = lay.m, lay.L
    if L <= m:
        top = store.get_block(L, 0, 0)
        return np.ascontiguousarray(top[:: 2 ** (m - L), :: 2 ** (m - L)])
    nb = lay.blocks(m)  # level m samples are exactly the lattice: assemble its blocks
    out = np.empty((2**L + 1, 2**L + 1), np.float32)
    for i in range(nb):
        row = store.get_block_row(m, i)
        for j in range(nb):
            out[i * (lay.M - 1): (i + 1) * (lay.M - 1) + 1, j * (lay.M - 1): (j + 1) * (lay.M - 1) + 1] = row[j]
    return out


def _region_table(f: int) -> np.ndarray:
    """(4, f, f) int: which triangle of its A-square (0 top, 1 bottom, 2 left, 3 right) the
    quarter q of lattice square (v mod f, u mod f) lies in (f = lattice squares per A side)."""
    out = np.empty((4, f, f), np.int8)
    b, a = np.meshgrid(np.arange(f), np.arange(f), indexing="ij")
    for q, (ox, oy) in enumerate(_CENTROIDS):
        px, py = a + ox, b + oy
        top = (py < px) & (py < f - px)
        bottom = (py > px) & (py > f - px)
        left = ~top & ~bottom & (px < py)
        out[q] = np.where(top, 0, np.where(bottom, 1, np.where(left, 2, 3)))
    return out


def grid_error_args(b: np.ndarray, s: int, m: int, f: int, bi: int, bj: int, tab: np.ndarray) -> tuple[tuple, int]:
    """The arguments of :func:`kernels.grid_errors` after the block ``b`` and before the (n, n)
    square and (4, n, n) region maxima it folds into, for lattice stride ``s`` ≤ 2**m of block
    (bi, bj) with patch width ``f`` and region table ``tab``; and n."""
    nq = 2**m // s
    lat, cc = b[::s, ::s], b[s // 2::s, s // 2::s]
    corners = [np.ascontiguousarray(x) for x in (lat[:-1, :-1], lat[:-1, 1:], lat[1:, :-1], lat[1:, 1:], cc)]
    fx = np.arange(s + 1, dtype=np.float32) / s
    v0, u0 = bi * nq, bj * nq
    return (s, nq, fx, *corners, (v0 + u0) % 2, tab, f, v0, u0, v0 // f, u0 // f), max(nq // f, 1)


class DeviationAccumulator:
    """Local (unsaturated) exact errors ``sq[j]`` (2^j, 2^j) and ``dg[j]`` (2, 2^j+1, 2^j+1),
    float32 height units, filled by :meth:`add_block` over every level-0 block."""

    def __init__(self, layout: TerrainLayout, coarse: np.ndarray | None):
        self.lay = layout
        self._eps = np.float32(0)
        self.coarse = None if coarse is None else np.asarray(coarse, np.float32)
        J = layout.J
        self.sq = [np.zeros((2**j, 2**j), np.float32) for j in range(J)]
        self.dg = [np.zeros((2, 2**j + 1, 2**j + 1), np.float32) for j in range(J)]
        self._tables = {}
        # the layout's sizes once (its properties recompute them: ~40 calls a block before), and
        # the compiled kernels, imported on first use (numba) rather than by every level's call
        self._J, self._m, self._f, self._kern = J, layout.m, 2**layout.k, None

    def _lattice(self, l: int) -> np.ndarray:
        return self.coarse[:: 2 ** (l - self.lay.m), :: 2 ** (l - self.lay.m)]

    def add_block(self, bi: int, bj: int, b: np.ndarray, part: str = "all", zabs: float | None = None) -> None:
        """Fold in level-0 block (bi, bj): float32 (M, M) heights. ``part``: "all" levels, or
        only the "grid" levels (lattice spacing ≤ the block span: the block alone decides them)
        or the "window" ones (lattice squares larger than a block: they need ``coarse``).
        ``zabs``: the block's largest |height| where the caller has it (its min/max), else
        computed here."""
        lay, J, m = self.lay, self._J, self._m
        b = np.ascontiguousarray(b, np.float32)
        valid = None
        if (bi + 1) * (lay.M - 1) >= lay.rows or (bj + 1) * (lay.M - 1) >= lay.cols:  # the block may hold padding
            r = bi * (lay.M - 1) + np.arange(lay.M)
            c = bj * (lay.M - 1) + np.arange(lay.M)
            valid = np.ascontiguousarray((r[:, None] < lay.rows) & (c[None, :] < lay.cols))
            if valid.all():
                valid = None
        if zabs is None:
            zabs = max(float(b.max()), -float(b.min()))  # = float(np.abs(b).max()), without the block-sized temporary
        self._eps = np.float32(8 * np.finfo(np.float32).eps * zabs)  # float32 rounding of z
        for j in range(J):
            if part == "all" or (part == "grid") == (J - j <= m):
                self._add_level(j, b, valid, bi, bj, J - j)

    def _add_level(self, j: int, b: np.ndarray, valid: np.ndarray | None, bi: int, bj: int, l: int) -> None:
        """Square-mesh and centred-mesh errors of patch level j (lattice spacing 2^l) over the
        block, by the compiled kernels of :mod:`kernels` (square mesh z = c00 + x·(c10 − c00) +
        y·(c01 − c00) + w·D with w = min(x, y) or max(0, x + y − 1) by the parity rule; the
        centred mesh's four quarter triangles), max-reduced per patch square and per region of
        :func:`_region_table`, then folded in with the float32 rounding margin."""
        if self._kern is None:
            from .kernels import _valid_extent, grid_level  # noqa: I001  (numba: loaded on first use)
            from .windowkernels import window_level

            self._kern = grid_level, window_level, _valid_extent
        grid_level, window_level, valid_extent = self._kern
        m, s, f = self._m, 2**l, self._f
        tab = self._tables.get(f)
        if tab is None:
            tab = self._tables[f] = _region_table(f)
        if l <= m:  # corners, kernel and folds in one compiled call
            grid_level(b, _NO_MASK if valid is None else valid, valid is not None, s, m, f, bi, bj, tab, self._eps,
                       self.sq[j], self.dg[j])
            return
        y0, x0 = bi * 2**m, bj * 2**m
        v0, u0 = y0 // s, x0 // s
        G, H = self._lattice(l), self._lattice(l - 1)
        t = np.arange(b.shape[0], dtype=np.float32)
        fx, fy = (x0 - u0 * s + t) / s, (y0 - v0 * s + t) / s
        hv, wv = b.shape if valid is None else valid_extent(valid)  # valid: the rectangle [0:hv, 0:wv]
        window_level(b, hv, wv, fx, fy, G[v0, u0], G[v0, u0 + 1], G[v0 + 1, u0], G[v0 + 1, u0 + 1],
                     H[2 * v0 + 1, 2 * u0 + 1], (v0 + u0) % 2, tab, f, v0, u0, self._eps, self.sq[j], self.dg[j])
