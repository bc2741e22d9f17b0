"""Per-block and per-patch metadata of a terrain pyramid, computed block by block.

Vertex errors (RTIN). Every sample of level l that is not a sample of level l+1 is the
midpoint of a hypotenuse in the 4-8 mesh: a square centre (its square's diagonal, per the
parity rule in :mod:`layout`) or an edge midpoint (its edge). Its error δ is the height
difference to the mean of that hypotenuse's end points.

Patch diamonds. Splitting a K-patch diamond of patch level j inserts exactly the δ vertices
of pyramid level l = J-1-j lying in the diamond's area, so its *local* error is their maximum:
2^k × 2^k blocks of square-centre δs for square diamonds, the edge-midpoint δs falling in the
rotated square around the edge for edge diamonds. ``saturate`` then makes errors monotone over
the diamond DAG (a square's children are the diamonds on its four edges; an edge's children
are the four next-level squares meeting at its midpoint), so a top-down cut driven by them is
conforming (Lindstrom & Pascucci 2001; RASTeR's saturated patch error).

Per block: min/max height, the maximum δ of the samples the block drops relative to level
l-1, and the saturated block error (≥ every block beneath it). Z-ranges of squares of every
patch level come from the finest samples.
"""

from __future__ import annotations

import numpy as np

from .layout import TerrainLayout

__all__ = ["vertex_deltas", "DiamondAccumulator", "saturate", "block_errors_from", "reduce_max", "reduce_min"]


def reduce_max(a: np.ndarray, f: int) -> np.ndarray:
    h, w = a.shape
    return a.reshape(h // f, f, w // f, f).max(axis=(1, 3))


def reduce_min(a: np.ndarray, f: int) -> np.ndarray:
    h, w = a.shape
    return a.reshape(h // f, f, w // f, f).min(axis=(1, 3))


def vertex_deltas(b: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """δ of the samples of an (2h+1)² block that the next coarser level drops:
    square centres (h, h), horizontal-edge midpoints (h+1, h), vertical-edge midpoints (h, h+1).
    Rows are y, columns x; blocks start at even global square indices (parity is local)."""
    b = b.astype(np.float32, copy=False)
    c00, c02, c20, c22 = b[0:-1:2, 0:-1:2], b[0:-1:2, 2::2], b[2::2, 0:-1:2], b[2::2, 2::2]
    h = c00.shape[0]
    even = ((np.arange(h)[:, None] + np.arange(h)[None, :]) % 2) == 0
    diag = np.where(even, (c00 + c22) * 0.5, (c02 + c20) * 0.5)
    dsq = np.abs(b[1::2, 1::2] - diag)
    dgh = np.abs(b[0::2, 1::2] - (b[0::2, 0:-1:2] + b[0::2, 2::2]) * 0.5)
    dgv = np.abs(b[1::2, 0::2] - (b[0:-1:2, 0::2] + b[2::2, 0::2]) * 0.5)
    return dsq, dgh, dgv


class DiamondAccumulator:
    """Collects local diamond errors and square z-ranges over all blocks (held in RAM:
    about 24 bytes per finest-level patch square, ~25 MB for a 16k² terrain)."""

    def __init__(self, layout: TerrainLayout):
        self.lay = layout
        J = layout.J
        self.sq = [np.zeros((2**j, 2**j), np.float32) for j in range(J)]
        self.dg = [np.zeros((2, 2**j + 1, 2**j + 1), np.float32) for j in range(J)]
        self.zmin = [np.full((2**j, 2**j), np.inf, np.float32) for j in range(J + 1)]
        self.zmax = [np.full((2**j, 2**j), -np.inf, np.float32) for j in range(J + 1)]

    def add_block(self, level: int, bi: int, bj: int, b: np.ndarray, deltas=None) -> None:
        """Fold in block (level, bi, bj) (a virtual level above L passes the strided top block
        with bi = bj = 0). ``deltas`` may pass precomputed :func:`vertex_deltas`."""
        lay = self.lay
        j = lay.J - 1 - level
        if level == 0:
            self._add_zrange(bi, bj, b)
        if not 0 <= j < lay.J:
            return
        dsq, dgh, dgv = deltas if deltas is not None else vertex_deltas(b)
        f = 2**lay.k
        h = dsq.shape[0]
        r0, c0 = bi * h // f, bj * h // f
        red = reduce_max(dsq, f)
        np.maximum(self.sq[j][r0:r0 + red.shape[0], c0:c0 + red.shape[1]], red, out=self.sq[j][r0:r0 + red.shape[0], c0:c0 + red.shape[1]])
        span = b.shape[0] - 1
        A = 2 * f
        for o, d in ((0, dgh), (1, dgv)):
            if o == 0:
                y = bi * span + 2 * np.arange(d.shape[0])[:, None]
                x = bj * span + 2 * np.arange(d.shape[1])[None, :] + 1
            else:
                y = bi * span + 2 * np.arange(d.shape[0])[:, None] + 1
                x = bj * span + 2 * np.arange(d.shape[1])[None, :]
            y, x = np.broadcast_to(y, d.shape), np.broadcast_to(x, d.shape)
            U, V = x // A, y // A
            px, py = x - U * A, y - V * A
            top = (py < px) & (py < A - px)
            bottom = (py > px) & (py > A - px)
            left = ~top & ~bottom & (px < py) & (px < A - py)
            oo = np.where(top | bottom, 0, 1)
            vv = np.where(bottom, V + 1, V)
            uu = np.where(top | bottom | left, U, U + 1)
            np.maximum.at(self.dg[j], (oo.ravel(), vv.ravel(), uu.ravel()), d.ravel())

    def add_zrange(self, bi: int, bj: int, b: np.ndarray) -> None:
        """Fold in the z-ranges of level-0 block (bi, bj) only (writes only that block's own
        squares, so blocks may be added from several threads at once)."""
        self._add_zrange(bi, bj, b)

    def put_zrange(self, bi: int, bj: int, lo: np.ndarray, hi: np.ndarray) -> None:
        """Fold in the square z-ranges ``lo``/``hi`` (n, n) of level-0 block (bi, bj), computed
        elsewhere (:func:`rowkernels.block_stats`); thread-safe like :meth:`add_zrange`."""
        n = lo.shape[0]
        sl = (slice(bi * n, bi * n + n), slice(bj * n, bj * n + n))
        J = self.lay.J
        self.zmin[J][sl] = np.minimum(self.zmin[J][sl], lo)
        self.zmax[J][sl] = np.maximum(self.zmax[J][sl], hi)

    def zranges(self) -> tuple[list[np.ndarray], list[np.ndarray]]:
        """The z-ranges of every square level (what :meth:`finish` returns, without the errors)."""
        for j in range(self.lay.J - 1, -1, -1):
            self.zmin[j] = reduce_min(self.zmin[j + 1], 2)
            self.zmax[j] = reduce_max(self.zmax[j + 1], 2)
        return self.zmin, self.zmax

    def _add_zrange(self, bi: int, bj: int, b: np.ndarray) -> None:
        f = 2**self.lay.k
        lo = np.minimum.reduce([reduce_min(b[dy:dy + b.shape[0] - 1, dx:dx + b.shape[1] - 1], f) for dy in (0, 1) for dx in (0, 1)])
        hi = np.maximum.reduce([reduce_max(b[dy:dy + b.shape[0] - 1, dx:dx + b.shape[1] - 1], f) for dy in (0, 1) for dx in (0, 1)])
        n = lo.shape[0]
        sl = (slice(bi * n, bi * n + n), slice(bj * n, bj * n + n))
        J = self.lay.J
        self.zmin[J][sl] = np.minimum(self.zmin[J][sl], lo)
        self.zmax[J][sl] = np.maximum(self.zmax[J][sl], hi)

    def finish(self):
        """Saturated errors and the z-ranges of every square level."""
        J = self.lay.J
        for j in range(J - 1, -1, -1):
            self.zmin[j] = reduce_min(self.zmin[j + 1], 2)
            self.zmax[j] = reduce_max(self.zmax[j + 1], 2)
        sq, dg = saturate(self.sq, self.dg)
        return sq, dg, self.zmin, self.zmax


def saturate(sq_local: list[np.ndarray], dg_local: list[np.ndarray]) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Errors monotone over the diamond DAG, deepest level first (see module docstring)."""
    J = len(sq_local)
    sq = [a.copy() for a in sq_local]
    dg = [a.copy() for a in dg_local]
    for j in range(J - 1, -1, -1):
        n = 2**j
        if j + 1 < J:  # edge diamonds take the max of the 4 next-level squares at their midpoint
            c = np.pad(sq[j + 1], 1)  # (2n+2)², index +1
            # horizontal edge (v, u): midpoint (row 2v, col 2u+1) at level j+1
            v, u = np.arange(n + 1)[:, None], np.arange(n)[None, :]
            hmax = np.maximum.reduce([c[2 * v - 1 + 1 + dr, 2 * u + 1 + dc] for dr in (0, 1) for dc in (0, 1)])
            dg[j][0, :, :n] = np.maximum(dg[j][0, :, :n], hmax)
            v, u = np.arange(n)[:, None], np.arange(n + 1)[None, :]
            vmax = np.maximum.reduce([c[2 * v + 1 + dr, 2 * u - 1 + 1 + dc] for dr in (0, 1) for dc in (0, 1)])
            dg[j][1, :n, :] = np.maximum(dg[j][1, :n, :], vmax)
        e = dg[j]
        kids = np.maximum.reduce([e[0, :n, :n], e[0, 1:n + 1, :n], e[1, :n, :n], e[1, :n, 1:n + 1]])
        sq[j] = np.maximum(sq[j], kids)
    return sq, dg


def block_errors_from(dmax: list[np.ndarray]) -> list[np.ndarray]:
    """Saturated block errors: level 0 is exact (0); level l is the max over its four
    children of (their dropped-sample δ max, their own error)."""
    err = [np.zeros_like(dmax[0])]
    for lv in range(1, len(dmax)):
        err.append(reduce_max(np.maximum(dmax[lv - 1], err[lv - 1]), 2))
    return err
