"""One computation rank's portion of one T2 layer (Gouranton et al. §3.1, made exact).

A portion is a set of quadtree nodes at the partition depth ``depth0`` (a Morton-order run,
:func:`massview.lod.roettger.portion_nodes`). :class:`LayerPortion` reads, windowed from the
store, only the heights of its nodes (the level-0 M-blocks covering them) and the Röttger
table of its nodes plus a one-node halo at every depth (to decide the shared edges), never
the rest. Arrays are indexed globally (sample ``row · S + col``, node ``[r, c]``) but
allocated lazily (``np.zeros``: untouched pages are never resident), so resident memory
scales with the portion: about 1/C of the DEM per rank. The serial reference is the portion
made of every node.

Per frame: :meth:`LayerPortion.fans` = Röttger's selection under the portion's nodes
(:func:`select_leaves`) and its fans with heights and bounding spheres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..core.errors import ConfigError
from ..data.terrain import TerrainStore
from ..data.terrain.roettger import RoettgerTable
from ..lod.roettger import Fans, LodResult, RoettgerParams, emit_fans, node_ranges, select_leaves

__all__ = ["LayerPortion", "LayerInfo", "range_pyramid"]


@dataclass(frozen=True)
class LayerInfo:
    """What every rank knows of a layer (sent by the computation leader; visualization ranks
    never open a store): grid ``n`` (S = 2^n + 1), valid rows/cols, spacing, vertical scale,
    height range, table C_min, the z offset it is drawn at (world units)."""

    path: str
    n: int
    rows: int
    cols: int
    spacing: tuple[float, float]
    vscale: float
    zrange: tuple[float, float]
    C_min: float
    zoffset: float = 0.0
    dim: int = 0  # samples per row of the vertex index (0: S; the paper partition's is larger)

    @property
    def S(self) -> int:
        return 2**self.n + 1

    @property
    def index_dim(self) -> int:
        return self.dim or self.S

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        dx, dy = self.spacing
        z0, z1 = self.zrange[0] * self.vscale + self.zoffset, self.zrange[1] * self.vscale + self.zoffset
        return np.array([0.0, -(self.rows - 1) * dy, z0]), np.array([(self.cols - 1) * dx, 0.0, z1])

    @classmethod
    def of(cls, path: str, zoffset: float = 0.0) -> "LayerInfo":
        st = TerrainStore(path)
        lay = st.layout
        zr = st.attrs.get("height_range") or [0.0, 1.0]
        table = RoettgerTable(st)  # raises the clear "no table" message
        return cls(str(path), lay.n, lay.rows, lay.cols, st.spacing, st.vertical_scale, (float(zr[0]), float(zr[1])),
                   table.C_min, zoffset)


def range_pyramid(h: np.ndarray, n: int, t0: int, tb: int) -> tuple[dict, dict]:
    """Min and max heights of the nodes of depths t0..tb of a (2^n+1)² grid ``h`` (node
    depth relative to the grid's root) → two dicts depth → (2^t, 2^t) float32."""
    lo, hi = node_ranges(h, 2 ** (n - tb))
    zmin, zmax = {tb: lo}, {tb: hi}
    for t in range(tb - 1, t0 - 1, -1):
        lo = np.minimum.reduce([lo[0::2, 0::2], lo[0::2, 1::2], lo[1::2, 0::2], lo[1::2, 1::2]])
        hi = np.maximum.reduce([hi[0::2, 0::2], hi[0::2, 1::2], hi[1::2, 0::2], hi[1::2, 1::2]])
        zmin[t], zmax[t] = lo, hi
    return zmin, zmax


class LayerPortion:
    """Heights, table windows and node height ranges of ``nodes`` (depth ``depth0``)."""

    def __init__(self, info: LayerInfo, nodes: np.ndarray, depth0: int):
        n = info.n
        if depth0 > n - 1:
            raise ConfigError(f"{info.path}: too small for this many computation ranks (partition depth {depth0}, the "
                              f"quadtree has {n} levels); use fewer --compute-ranks or a larger DEM")
        self.info, self.nodes, self.depth0, self.n = info, np.asarray(nodes, np.int64), depth0, n
        store = TerrainStore(info.path)
        table = RoettgerTable(store)
        self.bytes_read = 0
        P = 2 ** (n - depth0)  # heights of the portion's bounding box only (1/C of the DEM at C = 4^k)
        self.r0, self.c0 = int(self.nodes[:, 0].min()) * P, int(self.nodes[:, 1].min()) * P
        rows = (int(self.nodes[:, 0].max()) + 1) * P + 1 - self.r0
        cols = (int(self.nodes[:, 1].max()) + 1) * P + 1 - self.c0
        self.heights = np.zeros((rows, cols), np.float32)
        self._read_heights(store)
        self.d2: list = [None] * (n - 1)
        for t in range(depth0, n - 1):
            self.d2[t] = np.zeros((2**t, 2**t), np.float32)
            k = 2 ** (t - depth0)
            for r, c in self.nodes:
                r0, c0 = r * k - 1, c * k - 1
                w = table.window(t, r0, r0 + k + 2, c0, c0 + k + 2)
                self.d2[t][max(r0, 0): max(r0, 0) + w.shape[0], max(c0, 0): max(c0, 0) + w.shape[1]] = w
        self.bytes_read += table.bytes_read
        self._ranges()

    def _read_heights(self, store: TerrainStore) -> None:
        M, P = store.layout.M, 2 ** (self.n - self.depth0)
        span = M - 1
        cache: dict = {}
        for r, c in self.nodes:
            r0, c0 = int(r) * P, int(c) * P
            for bi in range(r0 // span, max((r0 + P - 1) // span, r0 // span) + 1):
                for bj in range(c0 // span, max((c0 + P - 1) // span, c0 // span) + 1):
                    if (bi, bj) not in cache:
                        cache[(bi, bj)] = store.get_block(0, bi, bj)
                        self.bytes_read += cache[(bi, bj)].nbytes
                    b = cache[(bi, bj)]
                    a0, a1 = max(r0, bi * span), min(r0 + P, bi * span + span) + 1
                    e0, e1 = max(c0, bj * span), min(c0 + P, bj * span + span) + 1
                    self.heights[a0 - self.r0:a1 - self.r0, e0 - self.c0:e1 - self.c0] = b[a0 - bi * span: a1 - bi * span, e0 - bj * span: e1 - bj * span]
            if len(cache) > 64:
                cache.clear()

    def _ranges(self) -> None:
        """Node min/max heights from depth ``tb`` = max(n-4, depth0) up to depth0 (finer
        leaves use their depth-tb ancestor's range: still a bounding range)."""
        n, t0 = self.n, self.depth0
        self.tb = tb = max(n - 4, t0)
        self.zmin = {t: np.zeros((2**t, 2**t), np.float32) for t in range(t0, tb + 1)}
        self.zmax = {t: np.zeros((2**t, 2**t), np.float32) for t in range(t0, tb + 1)}
        P = 2 ** (n - t0)
        for r, c in self.nodes:
            a, b = r * P - self.r0, c * P - self.c0
            lo, hi = range_pyramid(self.heights[a: a + P + 1, b: b + P + 1], n - t0, 0, tb - t0)
            for t in range(t0, tb + 1):
                m = 2 ** (t - t0)
                self.zmin[t][r * m: r * m + m, c * m: c * m + m] = lo[t - t0]
                self.zmax[t][r * m: r * m + m, c * m: c * m + m] = hi[t - t0]

    def zrange(self, t: np.ndarray, r: np.ndarray, c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        lo, hi = np.empty(len(t), np.float32), np.empty(len(t), np.float32)
        for d in np.unique(t):
            s = t == d
            u = min(int(d), self.tb)
            rr, cc = r[s] >> (int(d) - u), c[s] >> (int(d) - u)
            lo[s], hi[s] = self.zmin[u][rr, cc], self.zmax[u][rr, cc]
        return lo, hi

    def select(self, eye, params: RoettgerParams) -> LodResult:
        i = self.info
        off = i.zoffset / i.vscale
        return select_leaves(self.nodes, self.n, self.d2, eye, i.spacing, i.vscale, (i.zrange[0] + off, i.zrange[1] + off),
                             params, (i.rows, i.cols))

    def fans(self, leaves: LodResult) -> tuple[Fans, np.ndarray]:
        """Fans of ``leaves`` (bounding spheres include the layer's z offset) and the height
        of each fan vertex (float32)."""
        i = self.info
        f = emit_fans(leaves, self.n, i.S, i.spacing, i.vscale, self.zrange)
        f.sphere[:, 2] += i.zoffset
        g = f.index.astype(np.int64)
        heights = self.heights[g // i.S - self.r0, g % i.S - self.c0]
        if i.index_dim != i.S:
            f.index = ((f.index // i.S) * i.index_dim + f.index % i.S).astype(np.uint32)
            f.centre = (f.centre // i.S) * i.index_dim + f.centre % i.S
        return f, heights
