"""One computation rank's portion of one T2 layer (Gouranton et al. §3.1, made exact).

A portion is a set of quadtree nodes at the partition depth ``depth0`` (a Morton-order run,
:func:`massview.lod.roettger.portion_nodes`). :class:`LayerPortion` reads, windowed from the
store, only the heights of its nodes (the level-0 M-blocks covering them) and the Röttger
table of its nodes plus a one-node halo at every depth (to decide the shared edges), never
the rest. Every array covers only the box of the portion's nodes (node tables: plus the
halo) and is indexed with global coordinates (sample ``row · S + col``; node ``[r, c]``
through :class:`NodeWindow`), so memory per rank scales with the portion: about 1/C of the
DEM's bytes (``massview bench roettger --sections rss`` measures it on a 16385² store).
The serial reference is the portion made of every node.

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

__all__ = ["LayerPortion", "LayerInfo", "NodeWindow", "range_pyramid"]


@dataclass(frozen=True)
class LayerInfo:
    """What every rank knows of a layer (sent by the computation leader; visualization ranks
    never open a store): grid ``n`` (S = 2^n + 1), valid rows/cols, spacing, vertical scale,
    height range, table C_min, the z offset it is drawn at (world units), whether the store
    holds an orthophoto."""

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
    color: bool = False  # the store holds an orthophoto (T2 drapes it: systems.roettger._share_drapes)

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
                   table.C_min, zoffset, color=st.has_color)


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


class NodeWindow:
    """A (rows, cols) float32 array of depth-``t`` node values covering global node rows
    ``r0 ..`` and cols ``c0 ..``, indexed with global node coordinates: ``w[r, c]`` (r, c int
    arrays). A computation rank keeps only its portion's box (plus a one-node halo) of every
    depth, so its memory scales with the portion, not the DEM."""

    __slots__ = ("a", "r0", "c0")

    def __init__(self, r0: int, r1: int, c0: int, c1: int):
        self.r0, self.c0 = r0, c0
        self.a = np.zeros((r1 - r0, c1 - c0), np.float32)

    def __getitem__(self, rc):
        r, c = rc
        return self.a[r - self.r0, c - self.c0]

    def put(self, r0: int, c0: int, vals: np.ndarray) -> None:
        """Write ``vals`` at global node (r0, c0) (clipped to the window)."""
        a, b = r0 - self.r0, c0 - self.c0
        h, w = vals.shape
        ra, ca = max(a, 0), max(b, 0)
        rb, cb = min(a + h, self.a.shape[0]), min(b + w, self.a.shape[1])
        if ra < rb and ca < cb:
            self.a[ra:rb, ca:cb] = vals[ra - a: rb - a, ca - b: cb - b]


class LayerPortion:
    """Heights, table windows and node height ranges of ``nodes`` (depth ``depth0``).

    Memory (float32): the heights of the nodes' bounding box ((P·k+1)² for k×k nodes of P
    samples; 1/C of the DEM when C is a power of 4), the table over the same box plus a
    one-node halo at every depth (< 1/3 of the heights), node ranges down to depth n-4
    (1/256 of it); pages of the box outside the nodes are never written, so never resident.
    Store blocks are read one at a time (each once) and copied in."""

    def __init__(self, info: LayerInfo, nodes: np.ndarray, depth0: int):
        n = info.n
        if depth0 > n - 1:
            raise ConfigError(f"{info.path}: too small for this many computation ranks (partition depth {depth0}, the "
                              f"quadtree has {n} levels); use fewer --compute-ranks or a larger DEM")
        self.info, self.nodes, self.depth0, self.n = info, np.asarray(nodes, np.int64), depth0, n
        store = TerrainStore(info.path)
        table = RoettgerTable(store)
        self.bytes_read = 0
        self.P = P = 2 ** (n - depth0)
        self.nr0, self.nc0 = int(self.nodes[:, 0].min()), int(self.nodes[:, 1].min())
        self.nr1, self.nc1 = int(self.nodes[:, 0].max()) + 1, int(self.nodes[:, 1].max()) + 1
        self.r0, self.c0 = self.nr0 * P, self.nc0 * P
        self.heights = np.zeros(((self.nr1 - self.nr0) * P + 1, (self.nc1 - self.nc0) * P + 1), np.float32)
        self._read_heights(store)
        self.d2: list = [None] * (n - 1)
        for t in range(depth0, n - 1):
            k = 2 ** (t - depth0)
            w = self.d2[t] = self._window(t, halo=1)
            for r, c in self.nodes:
                r0, c0 = r * k - 1, c * k - 1
                for s in range(r0, r0 + k + 2, 256):  # strips: the read's temporary stays small
                    w.put(max(s, 0), max(c0, 0), table.window(t, s, min(s + 256, r0 + k + 2), c0, c0 + k + 2))
        self.bytes_read += table.bytes_read
        self._ranges()

    def _window(self, t: int, halo: int) -> NodeWindow:
        """The node box of depth ``t`` under the portion's nodes, ``halo`` nodes wider (clipped)."""
        k, N = 2 ** (t - self.depth0), 2**t
        return NodeWindow(max(self.nr0 * k - halo, 0), min(self.nr1 * k + halo, N), max(self.nc0 * k - halo, 0),
                          min(self.nc1 * k + halo, N))

    def _read_heights(self, store: TerrainStore) -> None:
        """Copy the level-0 blocks overlapping the nodes (each read once, none kept)."""
        span, P = store.layout.M - 1, self.P
        nb = store.layout.blocks(0)
        nr, nc = self.nodes[:, 0] * P, self.nodes[:, 1] * P  # node origins (samples)
        for bi in range(self.r0 // span, min((self.r0 + self.heights.shape[0] - 2) // span + 1, nb)):
            for bj in range(self.c0 // span, min((self.c0 + self.heights.shape[1] - 2) // span + 1, nb)):
                y0, x0 = bi * span, bj * span
                hit = (nr < y0 + span) & (nr + P > y0) & (nc < x0 + span) & (nc + P > x0)  # more than a border line
                if not hit.any():
                    continue
                b = store.get_block(0, bi, bj)
                self.bytes_read += b.nbytes
                for r0, c0 in zip(nr[hit], nc[hit]):
                    a0, a1 = max(r0, y0), min(r0 + P, y0 + span) + 1
                    e0, e1 = max(c0, x0), min(c0 + P, x0 + span) + 1
                    self.heights[a0 - self.r0:a1 - self.r0, e0 - self.c0:e1 - self.c0] = b[a0 - y0: a1 - y0, e0 - x0: e1 - x0]

    def _ranges(self) -> None:
        """Node min/max heights from depth ``tb`` = max(n-4, depth0) up to depth0 (finer
        leaves use their depth-tb ancestor's range: still a bounding range)."""
        n, t0 = self.n, self.depth0
        self.tb = tb = max(n - 4, t0)
        self.zmin = {t: self._window(t, halo=0) for t in range(t0, tb + 1)}
        self.zmax = {t: self._window(t, halo=0) for t in range(t0, tb + 1)}
        P = self.P
        for r, c in self.nodes:
            a, b = r * P - self.r0, c * P - self.c0
            lo, hi = range_pyramid(self.heights[a: a + P + 1, b: b + P + 1], n - t0, 0, tb - t0)
            for t in range(t0, tb + 1):
                m = 2 ** (t - t0)
                self.zmin[t].put(r * m, c * m, lo[t - t0])
                self.zmax[t].put(r * m, c * m, hi[t - t0])

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
