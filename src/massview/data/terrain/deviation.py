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
from numpy.lib.stride_tricks import as_strided

from .layout import TerrainLayout

__all__ = ["DeviationAccumulator", "coarse_lattice"]

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


def _closed_max(dev: np.ndarray, mask: np.ndarray) -> np.ndarray:
    return np.where(mask, dev, 0.0).max(axis=(-2, -1))


class DeviationAccumulator:
    """Local (unsaturated) exact errors ``sq[j]`` (2^j, 2^j) and ``dg[j]`` (2, 2^j+1, 2^j+1),
    float32 height units, filled by :meth:`add_block` over every level-0 block."""

    def __init__(self, layout: TerrainLayout, coarse: np.ndarray):
        self.lay = layout
        self._eps = np.float32(0)
        self.coarse = np.asarray(coarse, np.float32)
        J = layout.J
        self.sq = [np.zeros((2**j, 2**j), np.float32) for j in range(J)]
        self.dg = [np.zeros((2, 2**j + 1, 2**j + 1), np.float32) for j in range(J)]
        self._tables = {}

    def _lattice(self, l: int) -> np.ndarray:
        return self.coarse[:: 2 ** (l - self.lay.m), :: 2 ** (l - self.lay.m)]

    def _windows(self, b: np.ndarray, valid: np.ndarray, bi: int, bj: int, l: int):
        """Closed lattice squares of spacing 2^l over the block: heights (nv, nu, w, w), valid
        mask, corner/centre heights (nv, nu, 1, 1), fractional coords fx (…, w), fy (…, w, 1),
        and the global index of the first lattice square."""
        m, s = self.lay.m, 2**l
        if l <= m:
            nq = 2**m // s
            rs, cs = b.strides
            shape, strides = (nq, nq, s + 1, s + 1), (s * rs, s * cs, rs, cs)
            win = as_strided(b, shape, strides)
            vwin = as_strided(valid, shape, (s * valid.strides[0], s * valid.strides[1], *valid.strides))
            lat = b[::s, ::s]
            cc = b[s // 2::s, s // 2::s]
            t = np.arange(s + 1, dtype=np.float32) / s
            corners = [x[:, :, None, None] for x in (lat[:-1, :-1], lat[:-1, 1:], lat[1:, :-1], lat[1:, 1:], cc)]
            return win, vwin, corners, t[None, None, None, :], t[None, None, :, None], bi * nq, bj * nq
        y0, x0 = bi * 2**m, bj * 2**m
        V, U = y0 // s, x0 // s
        G, H = self._lattice(l), self._lattice(l - 1)
        corners = [np.float32(v).reshape(1, 1, 1, 1) for v in (G[V, U], G[V, U + 1], G[V + 1, U], G[V + 1, U + 1], H[2 * V + 1, 2 * U + 1])]
        t = np.arange(b.shape[0], dtype=np.float32)
        fx, fy = (x0 - U * s + t) / s, (y0 - V * s + t) / s
        return b[None, None], valid[None, None], corners, fx[None, None, None, :], fy[None, None, :, None], V, U

    def add_block(self, bi: int, bj: int, b: np.ndarray) -> None:
        """Fold in level-0 block (bi, bj): float32 (M, M) heights."""
        lay = self.lay
        b = np.ascontiguousarray(b, np.float32)
        r = bi * (lay.M - 1) + np.arange(lay.M)
        c = bj * (lay.M - 1) + np.arange(lay.M)
        valid = np.ascontiguousarray((r[:, None] < lay.rows) & (c[None, :] < lay.cols))
        self._eps = np.float32(8 * np.finfo(np.float32).eps * float(np.abs(b).max()))  # float32 rounding of z
        for j in range(lay.J):
            win, vwin, corners, fx, fy, v0, u0 = self._windows(b, valid, bi, bj, lay.J - j)
            if valid.all():
                vwin = None
            self._add_squares(j, win, vwin, corners, fx, fy, v0, u0)
            self._add_edges(j, win, vwin, corners, fx, fy, v0, u0)

    def _add_squares(self, j, win, vwin, corners, fx, fy, v0, u0) -> None:
        """Square mesh: per lattice square z = c00 + x·(c10 − c00) + y·(c01 − c00) + w·D with
        D = c00 − c10 − c01 + c11 and w = min(x, y) (diagonal (0,0)-(1,1), u + v even) or
        max(0, x + y − 1) (the other diagonal): both triangles in one expression."""
        c00, c10, c01, c11, _ = corners
        nv, nu = win.shape[:2]
        even = (((v0 + np.arange(nv))[:, None] + (u0 + np.arange(nu))[None, :]) % 2 == 0)[:, :, None, None]
        w = np.where(even, np.minimum(fx, fy), np.maximum(fx + fy - 1, 0))
        z = c00 + fx * (c10 - c00) + fy * (c01 - c00) + w * (c00 - c10 - c01 + c11)
        dev = np.abs(z - win)
        if vwin is not None:
            dev = np.where(vwin, dev, 0)
        self._put(self.sq[j], dev.max(axis=(2, 3)), v0, u0)

    def _add_edges(self, j, win, vwin, corners, fx, fy, v0, u0) -> None:
        """Centred mesh: the four quarter triangles of every lattice square, each evaluated on
        the half of the square it lies in."""
        c00, c10, c01, c11, cc = corners
        hx, hy = fx.shape[-1], fy.shape[-2]
        ly, lx = (slice(0, hy // 2 + 1), slice(hy // 2, hy)), (slice(0, hx // 2 + 1), slice(hx // 2, hx))
        if hx != hy or fx[..., 0] != 0 or fx[..., -1] != 1:  # a block inside one lattice square: whole window
            ly = lx = (slice(None), slice(None))
        quarters = (  # (rows, cols, formula, closed mask)
            (ly[0], slice(None), lambda x, y: c00 + x * (c10 - c00) + y * (2 * cc - c00 - c10), lambda x, y: (y <= x) & (y <= 1 - x)),
            (ly[1], slice(None), lambda x, y: c01 + x * (c11 - c01) + (1 - y) * (2 * cc - c01 - c11), lambda x, y: (y >= x) & (y >= 1 - x)),
            (slice(None), lx[0], lambda x, y: c00 + y * (c01 - c00) + x * (2 * cc - c00 - c01), lambda x, y: (x <= y) & (x <= 1 - y)),
            (slice(None), lx[1], lambda x, y: c10 + y * (c11 - c10) + (1 - x) * (2 * cc - c10 - c11), lambda x, y: (x >= y) & (x >= 1 - y)),
        )
        t4 = []
        for rows, cols, z, m in quarters:
            x, y, h = fx[..., cols], fy[..., rows, :], win[:, :, rows, cols]
            mask = m(x, y) if vwin is None else m(x, y) & vwin[:, :, rows, cols]
            t4.append(_closed_max(np.abs(z(x, y) - h), mask))
        t4 = np.stack(t4)  # (4, nv, nu)
        f = 2**self.lay.k
        tab = self._tables.get(f)
        if tab is None:
            tab = self._tables[f] = _region_table(f)
        nv, nu = t4.shape[1:]
        dg = self.dg[j]
        V0, U0 = v0 // f, u0 // f
        if nv >= f:
            nV, nU = nv // f, nu // f
            t = t4.reshape(4, nV, f, nU, f)
            per = [np.where((tab == r)[:, None, :, None, :], t, 0).max(axis=(0, 2, 4)) for r in range(4)]
        else:
            sub = tab[:, v0 % f: v0 % f + nv, u0 % f: u0 % f + nu]
            per = [np.array([[np.where(sub == r, t4, 0).max()]]) for r in range(4)]
            nV = nU = 1
        for (o, dv, du), e in zip(((0, 0, 0), (0, 1, 0), (1, 0, 0), (1, 0, 1)), per):
            sl = dg[o, V0 + dv: V0 + dv + nV, U0 + du: U0 + du + nU]
            np.maximum(sl, e + self._eps, out=sl)

    def _put(self, grid: np.ndarray, d: np.ndarray, v0: int, u0: int) -> None:
        f = 2**self.lay.k
        nv, nu = d.shape
        if nv >= f:
            d = d.reshape(nv // f, f, nu // f, f).max(axis=(1, 3))
            sl = grid[v0 // f: v0 // f + d.shape[0], u0 // f: u0 // f + d.shape[1]]
        else:
            d = d.max()
            sl = grid[v0 // f: v0 // f + 1, u0 // f: u0 // f + 1]
        np.maximum(sl, d + self._eps, out=sl)
