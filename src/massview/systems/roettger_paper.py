"""The paper's own data partition (Gouranton et al. §3.1), behind ``--paper-partition``.

Given a height field of SzX × SzY samples and CN computation ranks, m is the smallest number
with ``2^(m-1) + 1 < max(SzX, SzY) · 2 / CN <= 2^m + 1``; every rank gets a portion of
``P = 2^m + 1`` samples per side (here never larger than the smallest 2^k+1 covering the whole
DEM, and enlarged when the portions would not cover it), overlapping its neighbours where
needed. Portions are laid out on a gx × gy grid (gx · gy = CN, nearest to square, more along
the longer axis) with evenly spaced origins. Each portion is its *own* Röttger quadtree (its
table is computed from its heights when it is loaded), so the triangulations of two
portions do not agree in the overlap: the border artefacts the paper reports (§4). A rank
skips the fans lying wholly inside a lower rank's portion ("the first sender sends all its
visible data, including overlapped; the second all overlapped that are not sent by the
first"); fans partly in the overlap are sent by both.

The vertex index is global, ``row · D + col`` with D = the largest origin + P (≥ the store's
padded size), so the visualization ranks draw these fans like the exact partition's.
"""

from __future__ import annotations

import math

import numpy as np

from ..data.terrain import TerrainStore
from ..data.terrain.roettger import table_from_grid
from ..lod.roettger import Fans, LodResult, RoettgerParams, emit_fans, select_leaves
from .roettger_portion import LayerInfo, range_pyramid

__all__ = ["paper_layout", "PaperPortion"]


def _grid_shape(C: int, rows: int, cols: int) -> tuple[int, int]:
    best = min(((a, C // a) for a in range(1, C + 1) if C % a == 0), key=lambda p: (abs(p[0] - p[1]), p))
    a, b = sorted(best)
    return (b, a) if cols >= rows else (a, b)  # (gx, gy): more portions along the longer axis


def paper_layout(rows: int, cols: int, C: int, S: int = 0) -> tuple[int, list[tuple[int, int]], int]:
    """(P, [(row origin, col origin) per rank], D) of the paper's rule; D >= S (the store's
    padded size, so that the serial reference's vertices index into the same grid)."""
    big = max(rows, cols)
    target = big * 2 / C
    m = 1
    while not (2 ** (m - 1) + 1 < target <= 2**m + 1) and 2**m + 1 < target:
        m += 1
    m = min(m, max(1, math.ceil(math.log2(big - 1))))
    gx, gy = _grid_shape(C, rows, cols)
    while gx * 2**m < cols - 1 or gy * 2**m < rows - 1:
        m += 1
    P = 2**m + 1

    def origins(n: int, g: int) -> list[int]:
        if g == 1 or n <= P:
            return [0] * g
        return [round(k * (n - P) / (g - 1)) for k in range(g)]

    oy, ox = origins(rows, gy), origins(cols, gx)
    layout = [(oy[k // gx], ox[k % gx]) for k in range(C)]
    D = max(max(o for o, _ in layout), max(o for _, o in layout)) + P
    D = max(D, S)
    return P, layout, D


class PaperPortion:
    """One rank's overlapping (2^m+1)² portion, with its own quadtree and table."""

    def __init__(self, info: LayerInfo, k: int, C: int):
        self.P, layout, self.D = paper_layout(info.rows, info.cols, C, info.S)
        self.oy, self.ox = layout[k]
        self.lower = layout[:k]
        self.info, self.m = info, int(math.log2(self.P - 1))
        store = TerrainStore(info.path)
        self.heights, self.bytes_read = self._read(store)
        self.d2 = table_from_grid(self.heights, info.C_min)
        self.tb = max(self.m - 4, 0)
        self.zmin, self.zmax = range_pyramid(self.heights, self.m, 0, self.tb)

    def _read(self, store: TerrainStore) -> tuple[np.ndarray, int]:
        lay, P = store.layout, self.P
        span = lay.M - 1
        r1, c1 = min(self.oy + P, lay.S), min(self.ox + P, lay.S)
        h = np.empty((P, P), np.float32)
        nbytes = 0
        for bi in range(self.oy // span, (r1 - 2) // span + 1):
            for bj in range(self.ox // span, (c1 - 2) // span + 1):
                b = store.get_block(0, bi, bj)
                nbytes += b.nbytes
                a0, a1 = max(self.oy, bi * span), min(r1, bi * span + span + 1)
                e0, e1 = max(self.ox, bj * span), min(c1, bj * span + span + 1)
                h[a0 - self.oy: a1 - self.oy, e0 - self.ox: e1 - self.ox] = b[a0 - bi * span: a1 - bi * span, e0 - bj * span: e1 - bj * span]
        h[r1 - self.oy:, :] = h[r1 - self.oy - 1]  # beyond the store's grid: edge replication
        h[:, c1 - self.ox:] = h[:, c1 - self.ox - 1: c1 - self.ox]
        return h, nbytes

    def zrange(self, t, r, c):
        lo, hi = np.empty(len(t), np.float32), np.empty(len(t), np.float32)
        for d in np.unique(t):
            s, u = t == d, min(int(d), self.tb)
            lo[s], hi[s] = self.zmin[u][r[s] >> (int(d) - u), c[s] >> (int(d) - u)], self.zmax[u][r[s] >> (int(d) - u), c[s] >> (int(d) - u)]
        return lo, hi

    def select(self, eye, params: RoettgerParams) -> LodResult:
        i = self.info
        dx, dy = i.spacing
        local = (eye[0] - self.ox * dx, eye[1] + self.oy * dy, eye[2])
        off = i.zoffset / i.vscale
        p = RoettgerParams(params.C, params.c, 0)
        return select_leaves(np.zeros((1, 2), np.int64), self.m, self.d2, local, i.spacing, i.vscale,
                             (i.zrange[0] + off, i.zrange[1] + off), p, (i.rows - self.oy, i.cols - self.ox))

    def fans(self, leaves: LodResult) -> tuple[Fans, np.ndarray]:
        i, P, D = self.info, self.P, self.D
        keep = np.ones(len(leaves), bool)
        d = 2 ** (self.m - leaves.depth)
        r0, c0 = self.oy + leaves.row * d, self.ox + leaves.col * d
        for oy, ox in self.lower:  # wholly inside a lower rank's portion: that rank sends it
            keep &= ~((r0 >= oy) & (r0 + d <= oy + P - 1) & (c0 >= ox) & (c0 + d <= ox + P - 1))
        lv = LodResult(leaves.depth[keep], leaves.row[keep], leaves.col[keep], leaves.mask[keep])
        f = emit_fans(lv, self.m, P, i.spacing, i.vscale, self.zrange)
        local = f.index.astype(np.int64)
        heights = self.heights.reshape(-1)[local]
        f.index = ((local // P + self.oy) * D + local % P + self.ox).astype(np.uint32)
        f.centre = (f.centre // P + self.oy) * D + f.centre % P + self.ox
        f.sphere[:, 0] += self.ox * i.spacing[0]
        f.sphere[:, 1] -= self.oy * i.spacing[1]
        f.sphere[:, 2] += i.zoffset
        return f, heights
