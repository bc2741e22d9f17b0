"""Load-balanced frustum division (Revanth & Narayanan 2012, §3.4, Algorithm 1).

The server splits the screen rectangle of the frustum into one sub-rectangle (sub-frustum)
per client so that each gets about the same rendering weight (triangles). One split:

1. project every object on the split axis — x for a vertical split line, y for a horizontal
   one — as the pixel interval ``[a, b]`` of its screen footprint (bounding spheres:
   :func:`sphere_rects`), clamped to the parent rectangle;
2. sort the 2n bounds ``P`` (ties: by coordinate, then left bounds before right bounds, then
   object id — so each object's left point precedes its right point);
3. exclusive scans from both ends: ``Lw_i`` = weight of objects whose left bound comes before
   point i, ``Rw_i`` = weight of objects whose right bound comes after point i;
4. ``lower_bound`` = the first i with ``Lw_{i+1} > h_L`` and ``upper_bound`` = the last i with
   ``Rw_{i-1} > h_R`` (``Lw_n = Rw_{-1} = W``); with exact ties lower_bound can exceed
   upper_bound, and the search runs between them in either order;
5. ``divide`` = argmin over that range of the cost (ties to the lower index), and the split
   line is ``P_divide`` rounded to the nearest pixel edge;
6. recurse on both halves with the other axis (directions alternate with depth).

Algorithm 1 is written for powers of two (``h = W/2`` and ``nd/2`` clients a side). For any
client count the node's ``nd`` clients are split into ``k = ⌊nd/2⌋`` (left/top) and ``nd − k``
(right/bottom) with targets ``h_L = W·k/nd``, ``h_R = W·(nd − k)/nd`` and the cost

    |l − h_L| + |r − h_R| + (nd/2)·|l/k − r/(nd − k)|

which is the paper's ``|l − h| + |r − h| + |l − r|`` whenever nd is even.

Object lists are decided by the rounded pixel edge ``e`` so that every pixel a footprint may
cover belongs to a sub-frustum holding the object: an object goes left when ``a < e`` (or it
lies wholly at or before the edge, ``b ≤ e``) and right when ``b > e`` (or ``a ≥ e``).
Straddling objects go to both sides; every object goes to at least one. For an edge exactly
at ``P_divide`` these are the paper's lists ``∪ L_i, i < divide`` and ``∪ R_i, i > divide``
(they differ only for zero-width footprints, which go to both sides).

Pure numpy; pixel coordinates have a top-left origin (as :class:`Viewport`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..core.camera import Camera, Viewport

__all__ = ["SplitChoice", "SubFrustum", "sphere_rects", "split_cost", "choose_split", "divide_frustum", "balanced_tiles",
           "assign_to_tiles"]


@dataclass(frozen=True)
class SplitChoice:
    """One split of Algorithm 1. Indices refer to the sorted 2n bounds ``points``.

    axis: 0 = x (a vertical split line: left | right), 1 = y (top | bottom);
    nd, k: clients of the node and of its left/top child; weight: W of the node;
    position: ``P_divide`` in pixels; edge: the pixel edge the split uses.
    """

    axis: int
    nd: int
    k: int
    weight: float
    lower_bound: int
    upper_bound: int
    divide: int
    position: float
    edge: int


@dataclass(frozen=True)
class SubFrustum:
    """A client's share: its pixel rectangle, the ids of the objects it must draw
    (int64, sorted, indices into the arrays given to :func:`divide_frustum`) and their weight."""

    viewport: Viewport
    items: np.ndarray
    weight: float


def sphere_rects(camera: Camera, centers: np.ndarray, radii: np.ndarray) -> np.ndarray:
    """(n, 4) float64 pixel rectangles ``[x0, y0, x1, y1]`` (top-left origin, clipped to the
    image) bounding the exact perspective projection of each sphere (world units).

    Per axis the extremes of ``x/d`` (d = depth along the view direction) over a sphere are
    the slopes of the two planes through the eye tangent to it; a sphere reaching the eye
    plane (``d ≤ r``) covers the whole image on that axis (conservative)."""
    c = np.asarray(centers, np.float64).reshape(-1, 3)
    r = np.asarray(radii, np.float64).reshape(-1)
    if len(c) == 0:
        return np.zeros((0, 4))
    v = camera.view_matrix()
    cam = c @ v[:3, :3].T + v[:3, 3]
    d = -cam[:, 2]
    t = math.tan(math.radians(camera.fovy) / 2)
    halves = (t * camera.width / camera.height, t)  # window half extents at unit depth
    out = np.empty((len(c), 4))
    for axis, size in ((0, camera.width), (1, camera.height)):
        x = cam[:, axis]
        den = d * d - r * r
        ok = (d > r) & (den > 0)
        disc = np.sqrt(np.maximum(x * x + den, 0.0))
        with np.errstate(divide="ignore", invalid="ignore"):
            s0 = (x * d - r * disc) / den
            s1 = (x * d + r * disc) / den
        ndc0, ndc1 = s0 / halves[axis], s1 / halves[axis]
        if axis == 0:
            p0, p1 = (ndc0 + 1) * 0.5 * size, (ndc1 + 1) * 0.5 * size
        else:  # image rows grow downward
            p0, p1 = (1 - ndc1) * 0.5 * size, (1 - ndc0) * 0.5 * size
        p0 = np.where(ok, p0, 0.0)
        p1 = np.where(ok, p1, float(size))
        out[:, axis] = np.clip(p0, 0, size)
        out[:, axis + 2] = np.clip(p1, 0, size)
    return out


def split_cost(l, r, weight: float, nd: int, k: int | None = None):
    """Cost of a split leaving weight ``l`` left and ``r`` right (arrays or scalars). For even
    ``nd`` (k = nd/2) it is evaluated as the paper's ``|l − h| + |r − h| + |l − r|`` verbatim,
    so that rounding cannot move an argmin away from the paper's."""
    k = nd // 2 if k is None else k
    if 2 * k == nd:
        h = weight / 2
        return np.abs(l - h) + np.abs(r - h) + np.abs(l - r)
    hl, hr = weight * k / nd, weight * (nd - k) / nd
    return np.abs(l - hl) + np.abs(r - hr) + (nd / 2) * np.abs(l / k - r / (nd - k))


def _sorted_bounds(a: np.ndarray, b: np.ndarray, w: np.ndarray):
    """Sorted points P (2n,), per-point left/right weights, and each object's point indices."""
    n = len(a)
    pts = np.concatenate([a, b])
    side = np.concatenate([np.zeros(n, np.int8), np.ones(n, np.int8)])
    obj = np.concatenate([np.arange(n), np.arange(n)])
    order = np.lexsort((obj, side, pts))
    rank = np.empty(2 * n, np.int64)
    rank[order] = np.arange(2 * n)
    lw = np.where(side[order] == 0, w[obj[order]], 0.0)
    rw = np.where(side[order] == 1, w[obj[order]], 0.0)
    return pts[order], lw, rw, rank[:n], rank[n:]


def choose_split(a: np.ndarray, b: np.ndarray, w: np.ndarray, nd: int) -> tuple[int, int, int, np.ndarray, np.ndarray, np.ndarray]:
    """Algorithm 1, lines 12–26, on intervals ``[a, b]`` (already clamped) with weights ``w``.

    Returns ``(lower_bound, upper_bound, divide, P, Lw, Rw)`` with P, Lw, Rw (2n,) the sorted
    points and the exclusive scans. Needs n ≥ 1, nd ≥ 2 and a positive total weight."""
    k = nd // 2
    P, lw, rw, _, _ = _sorted_bounds(a, b, w)
    total = float(lw.sum())
    Lw = np.concatenate([[0.0], np.cumsum(lw)])  # Lw[i] = sum_{j<i}, Lw[n] = W
    Rw = np.concatenate([np.cumsum(rw[::-1])[::-1][1:], [0.0]])  # Rw[i] = sum_{j>i}
    Lw_pts = Lw[:-1]
    hl, hr = total * k / nd, total * (nd - k) / nd
    m = len(P)
    above = np.nonzero(Lw[1:] > hl)[0]  # i with Lw_{i+1} > h_L
    lower = int(above[0]) if len(above) else m - 1
    rprev = np.concatenate([[total], Rw[:-1]])  # Rw_{i-1}, with Rw_{-1} = W
    below = np.nonzero(rprev > hr)[0]
    upper = int(below[-1]) if len(below) else 0
    lo, hi = min(lower, upper), max(lower, upper)
    cost = split_cost(Lw_pts[lo:hi + 1], Rw[lo:hi + 1], total, nd, k)
    divide = lo + int(np.argmin(cost))
    return lower, upper, divide, P, Lw_pts, Rw


def _edge(position: float, lo: int, hi: int) -> int:
    return int(min(max(math.floor(position + 0.5), lo), hi))


def _assign(a: np.ndarray, b: np.ndarray, edge: int) -> tuple[np.ndarray, np.ndarray]:
    left = (a < edge) | (b <= edge)
    right = (b > edge) | (a >= edge)
    return left, right


def divide_frustum(rects: np.ndarray, weights: np.ndarray, viewport: Viewport, nd: int,
                   first_axis: int = 0, trace: list | None = None) -> list[SubFrustum]:
    """Split ``viewport`` into ``nd`` sub-frusta (in client order: left/top subtree first).

    rects: (n, 4) float pixel footprints ``[x0, y0, x1, y1]`` (e.g. :func:`sphere_rects` of
    the objects left by frustum culling); weights: (n,) rendering weights (triangles).
    ``trace``, when given, receives one :class:`SplitChoice` per split in pre-order."""
    rects = np.asarray(rects, np.float64).reshape(-1, 4)
    weights = np.asarray(weights, np.float64).reshape(-1)
    out: list[SubFrustum] = []

    def rec(vp: Viewport, ids: np.ndarray, nd: int, axis: int) -> None:
        if nd == 1:
            out.append(SubFrustum(vp, ids, float(weights[ids].sum())))
            return
        k = nd // 2
        lo, hi = (vp.x, vp.x + vp.w) if axis == 0 else (vp.y, vp.y + vp.h)
        a = np.clip(rects[ids, axis], lo, hi)
        b = np.clip(rects[ids, axis + 2], lo, hi)
        w = weights[ids]
        total = float(w.sum())
        if len(ids) and total > 0:
            lb, ub, div, P, _, _ = choose_split(a, b, w, nd)
            pos = float(P[div])
        else:  # nothing to balance: split the pixels in proportion to the clients
            lb = ub = div = -1
            pos = lo + (hi - lo) * k / nd
        edge = _edge(pos, lo, hi)
        if trace is not None:
            trace.append(SplitChoice(axis, nd, k, total, lb, ub, div, pos, edge))
        left, right = _assign(a, b, edge)
        if axis == 0:
            va, vb = Viewport(vp.x, vp.y, edge - vp.x, vp.h), Viewport(edge, vp.y, vp.x + vp.w - edge, vp.h)
        else:
            va, vb = Viewport(vp.x, vp.y, vp.w, edge - vp.y), Viewport(vp.x, edge, vp.w, vp.y + vp.h - edge)
        rec(va, ids[left], k, 1 - axis)
        rec(vb, ids[right], nd - k, 1 - axis)

    rec(viewport, np.arange(len(rects), dtype=np.int64), int(nd), int(first_axis))
    return out


def balanced_tiles(n: int, width: int, height: int, rects: np.ndarray, weights: np.ndarray) -> list[Viewport]:
    """The viewports of :func:`divide_frustum` over the full image (the sort-first slot)."""
    return [s.viewport for s in divide_frustum(rects, weights, Viewport(0, 0, width, height), n)]


def assign_to_tiles(rects: np.ndarray, weights: np.ndarray, tiles: list[Viewport]) -> list[SubFrustum]:
    """Fixed tiles (e.g. equal screen tiles, the baseline Algorithm 1 is measured against):
    each tile gets the objects whose footprint touches it (closed intervals: conservative)."""
    rects = np.asarray(rects, np.float64).reshape(-1, 4)
    weights = np.asarray(weights, np.float64).reshape(-1)
    out = []
    for t in tiles:
        hit = ((rects[:, 0] <= t.x + t.w) & (rects[:, 2] >= t.x) & (rects[:, 1] <= t.y + t.h) & (rects[:, 3] >= t.y))
        ids = np.flatnonzero(hit) if not t.empty else np.zeros(0, np.int64)
        out.append(SubFrustum(t, ids, float(weights[ids].sum())))
    return out
