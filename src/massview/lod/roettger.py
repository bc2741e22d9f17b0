"""Röttger's continuous LOD for height fields, vectorized level by level (T2; Röttger, Heidrich,
Slusallek, Seidel 1998, "Real-time generation of continuous levels of detail for height
fields"; Gouranton et al. §2).

Grid and quadtree. The terrain store's padded grid has ``S = 2^n + 1`` samples per side. A
quadtree node at depth ``t`` (0 = root) has edge length ``d = 2^(n-t)`` samples; node
``(t, r, c)`` spans rows ``r·d .. r·d+d`` and cols ``c·d .. c·d+d``; its centre sample is
``(r·d + d/2, c·d + d/2)``. The finest nodes (``d = 2``) are always leaves.

Roughness d2 (:func:`local_d2`, :func:`propagate`). A node's local d2 is the largest absolute
difference between the height at its four edge midpoints and its centre, and the mean of the
two samples they interpolate (edges; the two diagonals for the centre), divided by ``d``.
As in Röttger's original, d2 is propagated upward: a node's d2 is at least
``K = C_min / (2 (C_min - 1))`` times the d2 of every node one level finer that lies in it
*or touches it along an edge from outside* (children alone leave neighbouring leaves two and
more levels apart). The table is valid for every ``C >= C_min`` (K decreases with C).

Subdivision. A node is subdivided when ``f = l / (d · C · max(c · d2, 1)) < 1`` (world units:
``d`` times the larger grid spacing, d2 times vertical scale / that spacing), where

    l = |x_eye - x_centre| + |y_eye - y_centre| + dz,
    dz = the eye's distance to the layer's height slab [z_min, z_max] (0 inside it).

Why this distance: the level-difference proof compares the distances of two nodes whose
centres are at most ``2d`` apart in x+y; with the constant ``dz`` the difference of their
``l`` is at most ``2d`` (the node-centre height of Röttger's 3D L1 distance can differ by any
amount across a cliff, which breaks the proof near C = 2). Then for ``C >= 2`` and the
propagated d2: (a) if a node is subdivided so is its parent (``f`` is monotone up the tree, so
"its parent was subdivided" holds by itself), and (b) if a node of edge ``d`` is subdivided,
every node of edge ``2d`` touching it along an edge is subdivided: ``l_Q <= l_X + 2d <
d C m_X + 2d <= 2d C m_Q`` with ``m = max(c d2, 1)``, using ``m_Q >= 1`` when
``m_X <= 2 - 2/C`` and ``m_Q >= K m_X`` otherwise. So neighbouring leaves differ by at most
one level for every camera; C is restricted to ``[2, 64]``.

Error bound. A leaf's own midpoint deviations are ``Δ = d · d2 <= l / (C c)``; with the
propagation the deviations one level finer are at most ``Δ (C-1)/C``, two levels ``Δ
((C-1)/C)^2``, …, so the vertical (object-space, world units) error of any sample under a
leaf is at most ``C Δ <= l / c`` — an angular error of at most ``√3 / c`` radians seen from
the eye (``l`` is an L1 distance, at most √3 times the Euclidean one). The default ``c`` is
chosen from the pixel tolerance τ so that this is about τ pixels (:func:`default_c`).

Fans (:func:`emit_fans`). Leaves emit a triangle fan: centre, then the ring of corners and
edge midpoints; the midpoint towards a neighbour is skipped when the neighbour of the same
size does not exist (its parent is a leaf, i.e. it is coarser). A node exists when its parent
is subdivided, so the decision needs only the d2 of the same-depth-minus-one node across the
edge: a one-node halo.

Everything is numpy over arrays of nodes, one depth at a time; no per-node Python.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..core.errors import ConfigError
from ..data.terrain.roettger import C_RANGE, k_factor, local_d2, propagate_into

__all__ = ["RoettgerParams", "Fans", "LodResult", "C_RANGE", "k_factor", "default_c", "local_d2", "propagate_into",
           "select_leaves", "emit_fans", "morton2", "node_ranges", "partition_depth", "data_nodes", "portion_nodes", "portion_owner"]

def default_c(tau: float, fovy_deg: float, height_px: int) -> float:
    """The desired resolution c for a pixel tolerance τ: c = √3 / (τ · pixel angle), so that
    the stated error bound √3/c radians is τ pixels."""
    return math.sqrt(3.0) / (tau * math.radians(fovy_deg) / height_px)


@dataclass(frozen=True)
class RoettgerParams:
    """C: minimum global resolution (>= the table's C_min, in [2, 64]); c: desired global
    resolution (> 0); depth0: nodes shallower than this are always subdivided (the partition
    level, the same in the serial and the parallel run)."""

    C: float = 4.0
    c: float = 2000.0
    depth0: int = 0

    def __post_init__(self) -> None:
        if not (C_RANGE[0] <= self.C <= C_RANGE[1]):
            raise ConfigError(f"--roettger-C must be in [{C_RANGE[0]:g}, {C_RANGE[1]:g}] (the level-difference proof needs C >= 2), got {self.C}")
        if not (self.c >= 0 and math.isfinite(self.c)):
            raise ConfigError(f"--roettger-c must be a finite number >= 0, got {self.c}")


# -- node ranges (bounding spheres) -------------------------------------------------------------
def node_ranges(h: np.ndarray, d: int) -> tuple[np.ndarray, np.ndarray]:
    """Min and max height of each node of edge ``d`` over a window of heights (k·d+1, l·d+1),
    border samples included → two (k, l) float32 arrays. Works in strips of node rows so that
    its temporaries stay near 16 MiB whatever the window's size."""
    h = np.asarray(h, np.float32)
    k = (h.shape[0] - 1) // d
    step = max(1, (1 << 22) // (d * h.shape[1]))  # node rows per strip (~4 M samples)
    parts = [_strip_ranges(h[i * d: min(i + step, k) * d + 1], d) for i in range(0, k, step)]
    if not parts:
        return np.zeros((0, (h.shape[1] - 1) // d), np.float32), np.zeros((0, (h.shape[1] - 1) // d), np.float32)
    return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])


def _strip_ranges(h: np.ndarray, d: int) -> tuple[np.ndarray, np.ndarray]:
    idx_r = np.arange(0, h.shape[0] - 1, d)
    idx_c = np.arange(0, h.shape[1] - 1, d)
    out = []
    for red in (np.minimum, np.maximum):
        rows = red.reduceat(h[:-1], idx_r, axis=0)
        rows = red(rows, h[idx_r + d])  # the shared bottom row of each node
        both = red.reduceat(rows[:, :-1], idx_c, axis=1)
        out.append(red(both, rows[:, idx_c + d]))
    return out[0], out[1]


# -- selection -----------------------------------------------------------------------------------
@dataclass
class LodResult:
    """Leaves of one selection: depth, row, col (int64 arrays, same length) and the 4-bit
    midpoint mask (1 top, 2 right, 4 bottom, 8 left: include that edge's midpoint)."""

    depth: np.ndarray
    row: np.ndarray
    col: np.ndarray
    mask: np.ndarray
    nodes_visited: int = 0

    def __len__(self) -> int:
        return len(self.depth)

    def triangles(self) -> int:
        return int(4 * len(self.mask) + _popcount4(self.mask).sum())


def _popcount4(m: np.ndarray) -> np.ndarray:
    m = np.asarray(m, np.int64)
    return (m & 1) + ((m >> 1) & 1) + ((m >> 2) & 1) + ((m >> 3) & 1)


class _Frame:
    """Per-frame constants of the subdivision test for one layer (world units)."""

    def __init__(self, eye, n: int, spacing, vscale: float, zslab, params: RoettgerParams):
        self.ex, self.ey, ez = (float(v) for v in eye)
        self.dx, self.dy = float(spacing[0]), float(spacing[1])
        g = max(self.dx, self.dy)
        self.g = g
        z0, z1 = zslab[0] * vscale, zslab[1] * vscale
        self.dz = max(0.0, ez - max(z0, z1), min(z0, z1) - ez)
        self.d2w = vscale / g  # raw d2 (height / sample) → world (dimensionless)
        self.n, self.p = n, params

    def subdivided(self, t: int, r: np.ndarray, c: np.ndarray, d2: np.ndarray) -> np.ndarray:
        """Röttger's test f < 1 for nodes (t, r, c) with table values d2 (raw)."""
        d = 2 ** (self.n - t)
        cx = (c * d + d // 2) * self.dx
        cy = -(r * d + d // 2) * self.dy
        l1 = np.abs(self.ex - cx) + np.abs(self.ey - cy) + self.dz
        res = d * self.g * self.p.C * np.maximum(self.p.c * self.d2w * d2, 1.0)
        return l1 < res


def select_leaves(roots: np.ndarray, n: int, d2: list, eye, spacing, vscale: float, zslab, params: RoettgerParams,
                  extent: tuple[int, int]) -> LodResult:
    """Leaves under ``roots`` ((k, 2) int64 rows/cols of nodes at depth ``params.depth0``).

    ``d2[t]`` is indexable by [r, c] for depths 0..n-2 (it must hold the roots' subtrees and a
    one-node halo around them at every depth); ``extent`` = (rows, cols) of valid samples:
    nodes wholly in the padding are dropped."""
    fr = _Frame(eye, n, spacing, vscale, zslab, params)
    t0 = params.depth0
    r, c = roots[:, 0].astype(np.int64), roots[:, 1].astype(np.int64)
    out_t, out_r, out_c, out_m = [], [], [], []
    visited = 0
    for t in range(t0, n):
        d = 2 ** (n - t)
        keep = (r * d < extent[0] - 1) & (c * d < extent[1] - 1)
        r, c = r[keep], c[keep]
        visited += len(r)
        if len(r) == 0:
            break
        sub = fr.subdivided(t, r, c, d2[t][r, c]) if t < n - 1 else np.zeros(len(r), bool)
        lr, lc = r[~sub], c[~sub]
        if len(lr):
            out_t.append(np.full(len(lr), t, np.int64))
            out_r.append(lr)
            out_c.append(lc)
            out_m.append(_midpoint_mask(fr, t, lr, lc, d2, t0))
        r, c = r[sub], c[sub]
        r = np.concatenate([2 * r, 2 * r, 2 * r + 1, 2 * r + 1])
        c = np.concatenate([2 * c, 2 * c + 1, 2 * c, 2 * c + 1])
    cat = lambda xs: np.concatenate(xs) if xs else np.zeros(0, np.int64)  # noqa: E731
    return LodResult(cat(out_t), cat(out_r), cat(out_c), cat(out_m), visited)


_DIRS = ((1, -1, 0), (2, 0, 1), (4, 1, 0), (8, 0, -1))  # bit, drow, dcol: top, right, bottom, left


def _midpoint_mask(fr: _Frame, t: int, r: np.ndarray, c: np.ndarray, d2: list, t0: int) -> np.ndarray:
    """Bit set when the same-size neighbour across that edge exists (its parent is subdivided)."""
    N = 2**t
    mask = np.zeros(len(r), np.int64)
    for bit, dr, dc in _DIRS:
        nr, nc = r + dr, c + dc
        inside = (nr >= 0) & (nr < N) & (nc >= 0) & (nc < N)
        if t <= t0:
            exists = inside
        else:
            pr, pc = np.clip(nr, 0, N - 1) // 2, np.clip(nc, 0, N - 1) // 2
            sibling = (pr == r // 2) & (pc == c // 2)
            exists = inside & (sibling | fr.subdivided(t - 1, pr, pc, d2[t - 1][pr, pc]))
        mask |= np.where(exists, bit, 0)
    return mask


# -- fans ----------------------------------------------------------------------------------------
@dataclass
class Fans:
    """Triangle fans: ``lengths`` (k,) uint32 vertices per fan; ``index`` (sum,) uint32 global
    sample index ``row · dim + col`` (centre first, then the closed ring); ``centre`` (k,) int64
    centre sample index (unique per fan, the sort and identity key with ``mask``); ``mask``
    (k,) the midpoint mask; bounding spheres ``sphere`` (k, 4) float64 world (x, y, z, radius)."""

    lengths: np.ndarray
    index: np.ndarray
    centre: np.ndarray
    mask: np.ndarray
    sphere: np.ndarray

    def __len__(self) -> int:
        return len(self.lengths)

    def take(self, sel: np.ndarray) -> "Fans":
        sel = np.asarray(sel)
        if sel.dtype == bool:
            sel = np.flatnonzero(sel)
        starts = np.concatenate([[0], np.cumsum(self.lengths, dtype=np.int64)])[:-1]
        lens = self.lengths[sel].astype(np.int64)
        idx = np.repeat(starts[sel] - np.concatenate([[0], np.cumsum(lens)])[:-1], lens) + np.arange(lens.sum())
        return Fans(self.lengths[sel], self.index[idx], self.centre[sel], self.mask[sel], self.sphere[sel])

    def triangles(self) -> int:
        return int(self.lengths.astype(np.int64).sum() - 2 * len(self.lengths))


# ring order: (drow, dcol) in units of the half edge, and the mask bit that gates a midpoint
_RING = ((-1, -1, 0), (0, -1, 8), (1, -1, 0), (1, 0, 4), (1, 1, 0), (0, 1, 2), (-1, 1, 0), (-1, 0, 1), (-1, -1, 0))


def emit_fans(leaves: LodResult, n: int, dim: int, spacing, vscale: float, zrange) -> Fans:
    """Fans of ``leaves`` in Morton order of their centres. ``zrange(depth, row, col)`` gives
    (zmin, zmax) height arrays of the leaves (for bounding spheres)."""
    t, r, c, m = leaves.depth, leaves.row, leaves.col, leaves.mask
    order = np.argsort(morton2(r * 2 ** (n - t) + 2 ** (n - t - 1), c * 2 ** (n - t) + 2 ** (n - t - 1)), kind="stable")
    t, r, c, m = t[order], r[order], c[order], m[order]
    half = (2 ** (n - t - 1)).astype(np.int64)
    cr, cc = r * 2 * half + half, c * 2 * half + half
    k = len(t)
    cols = [cr * dim + cc]
    valid = [np.ones(k, bool)]
    for dr, dc, bit in _RING:
        cols.append((cr + dr * half) * dim + (cc + dc * half))
        valid.append(np.ones(k, bool) if bit == 0 else (m & bit) != 0)
    idx, ok = np.stack(cols, 1), np.stack(valid, 1)
    lengths = ok.sum(1).astype(np.uint32)
    zmin, zmax = zrange(t, r, c)
    dx, dy = spacing
    sphere = np.empty((k, 4))
    sphere[:, 0], sphere[:, 1] = cc * dx, -cr * dy
    sphere[:, 2] = (zmin.astype(np.float64) + zmax) * 0.5 * vscale
    sphere[:, 3] = np.sqrt((half * dx) ** 2 + (half * dy) ** 2 + ((zmax.astype(np.float64) - zmin) * 0.5 * vscale) ** 2) * (1 + 1e-6)
    return Fans(lengths, idx[ok].astype(np.uint32), cr * dim + cc, m, sphere)


def morton2(row: np.ndarray, col: np.ndarray) -> np.ndarray:
    """Morton (Z-order) code interleaving row (odd bits) and col (even bits), int64."""
    def spread(v):
        v = np.asarray(v, np.int64) & 0xFFFFFFFF
        v = (v | (v << 16)) & 0x0000FFFF0000FFFF
        v = (v | (v << 8)) & 0x00FF00FF00FF00FF
        v = (v | (v << 4)) & 0x0F0F0F0F0F0F0F0F
        v = (v | (v << 2)) & 0x3333333333333333
        return (v | (v << 1)) & 0x5555555555555555
    return spread(col) | (spread(row) << 1)


# -- exact partition (T2, Gouranton et al. §3.1 made exact) ------------------------------------
def partition_depth(C: int, extent: tuple[float, float] = (1.0, 1.0), max_depth: int | None = None) -> int:
    """The smallest depth L with 4^L >= C, one deeper when C is not a power of 4; for a DEM
    that fills only ``extent`` (rows, cols fractions) of its padded square, deeper until as
    many nodes hold data as the square would have (at most ``max_depth``), so the portions
    still split the data finely enough to share it among C ranks."""
    L = 0
    while 4**L < C:
        L += 1
    L = L if 4**L == C else L + 1
    want = 4**L
    while int(data_nodes(L, extent).sum()) < want and (max_depth is None or L < max_depth):
        L += 1
    return L


def data_nodes(depth: int, extent: tuple[float, float] = (1.0, 1.0)) -> np.ndarray:
    """(2^depth, 2^depth) bool: the depth-``depth`` nodes that hold data of a DEM filling the
    fractions ``extent`` = ((rows−1)/(S−1), (cols−1)/(S−1)) of its padded square (the rest is
    edge-replicated padding, never drawn)."""
    N = 2**depth
    k = np.arange(N, dtype=np.float64) / N
    return (k[:, None] < float(extent[0])) & (k[None, :] < float(extent[1]))


def portion_nodes(depth: int, C: int, extent: tuple[float, float] = (1.0, 1.0)) -> list[np.ndarray]:
    """The depth-``depth`` nodes of each of C computation ranks: contiguous Morton-order runs
    holding near-equal counts of the nodes with data (:func:`data_nodes`; padding-only nodes go
    with the run they fall in; for a square DEM that fills its square, near-equal node counts);
    rank k gets run k; each (m, 2) int64 rows/cols."""
    N = 2**depth
    rr, cc = np.meshgrid(np.arange(N, dtype=np.int64), np.arange(N, dtype=np.int64), indexing="ij")
    rr, cc = rr.ravel(), cc.ravel()
    order = np.argsort(morton2(rr, cc), kind="stable")
    nodes = np.stack([rr[order], cc[order]], 1)
    pos = np.flatnonzero(data_nodes(depth, extent)[nodes[:, 0], nodes[:, 1]])
    D = len(pos)
    cuts = [0] + [int(pos[i]) if (i := round(k * D / C)) < D else len(nodes) for k in range(1, C)] + [len(nodes)]
    return [nodes[cuts[k]: cuts[k + 1]] for k in range(C)]


def portion_owner(depth: int, C: int, extent: tuple[float, float] = (1.0, 1.0)) -> np.ndarray:
    """(2^depth, 2^depth) int64: the computation rank owning each depth-``depth`` node."""
    N = 2**depth
    own = np.zeros((N, N), np.int64)
    for k, nodes in enumerate(portion_nodes(depth, C, extent)):
        own[nodes[:, 0], nodes[:, 1]] = k
    return own
