"""View-dependent K-patch selection over the M-block pyramid (RASTeR, Bösch et al. 2009;
Goswami et al. 2010 §3), vectorized level by level.

The front is cut top-down through the patch bintree (see :mod:`massview.data.terrain.layout`
for the diamonds). A triangle splits when its hypotenuse diamond D is *active*:

* its saturated object-space error e(D) — a true bound on the vertical distance between
  D's drawn patches and every finest sample under them (:mod:`massview.data.terrain.deviation`)
  — can move a projected point by more than τ pixels anywhere in D's bounding sphere.
  A vertical segment of length e at camera coordinates (x, y, depth z) moves in the image by
  f·|J·u|·e with J = (1/z)[I | −(x/z, y/z)] (f = (H/2)/tan(fovy/2), u = world up in camera
  axes); over the sphere |x/z| ≤ a = (|x_c| + r)/(z_c − r), |y/z| ≤ b likewise, so the
  displacement is at most f·e·√((|u_x| + a|u_z|)² + (|u_y| + b|u_z|)²)/(z_c − r). This keeps
  the off-axis stretch (up to 1.44× at the corners of a 45° frame) that a distance-only test
  misses, and is monotone under sphere nesting;
* its sphere touches the view frustum;
* the blocks its children draw from are resident (agreed by every rank), and
* every triangle of D is present at this depth (1 on the domain border, else 2).

Errors are saturated over the diamond DAG at ingest and spheres are nested here (r(D) ≥
|c(D) − c(child)| + r(child)), so the first two tests are monotone: an active diamond's
parents are active, both triangles of an active diamond exist, and the cut is conforming —
crack- and T-junction-free — without any runtime propagation. The last two tests only hold
refinement back where data is missing, and the presence test keeps that conforming too.

The result is backend-free: a :class:`Front` of patch records (integer vertex coordinates in
finest-sample units, the block each patch draws from and its sample stride) that the renderer
turns into one multi-draw call.

The walk itself decides once per diamond, not per triangle (:mod:`.kpatch_cut` for the rule and
the split test, :mod:`.kpatch_top` for the first depths as one precomputed batch,
:mod:`.kpatch_walk` for the lower depths as packed int64 keys). It selects exactly the
patches of the triangle-by-triangle walk it replaced (``massview.app.bench.lod_baseline``;
tests/test_lod_stage.py), and it can be restricted to a sort-first tile's sub-frustum.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import partial
from typing import Callable

import numpy as np

from ..core.camera import Camera, Viewport
from ..data.terrain.layout import TerrainLayout
from . import kpatch_compiled, kpatch_walk
from .kpatch_top import TopBatch
from .cull import frustum_planes
from .columns import Lazy, edge_centre, errors, heights, square_centre
from .kpatch_cut import Dims, Residency, View

__all__ = ["PatchHierarchy", "Lazy", "world_box", "Front", "select_front", "visible_patches", "patch_boxes", "lookup_blocks", "refine_uniform",
           "watertight_problems"]

TOP_LEVELS = 7  # square/edge levels walked as one batch (kpatch_top)
Resident = Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]  # (level, bi, bj) -> bool
Request = Callable[[np.ndarray, np.ndarray, np.ndarray, np.ndarray], None]  # (level, bi, bj, priority)



class PatchHierarchy:
    """Per-diamond saturated errors, height ranges and nested bounding spheres (world units:
    x = col·dx, y = −row·dy, z = base + Z·(h·vertical_scale − base) with Z the view-time
    exaggeration and base the lowest scaled height, so errors scale by vertical_scale·Z)."""

    def __init__(self, layout: TerrainLayout, sq_err, dg_err, zmin, zmax, spacing=(1.0, 1.0), vscale: float = 1.0,
                 exaggeration: float = 1.0):
        self.lay = layout
        self.dims = Dims(layout)
        self.dx, self.dy = (float(v) for v in spacing)
        self.vs = float(vscale)
        self.exaggeration = Z = float(exaggeration)
        J = layout.J
        self.base = float(np.min(zmin[0])) * self.vs
        # compact storage (issue 20): the heights and errors stay in their stored dtype (float32)
        # and become float64 world values on indexing (:class:`Lazy`, bit-identical to eager
        # float64 arrays); only the radii, which nest, are float64 arrays
        H, E = partial(heights, self.base, self.vs, Z), partial(errors, self.vs, Z)
        self.sq_err = [Lazy(E, np.asarray(e)) for e in sq_err]
        self.dg_err = [Lazy(E, np.asarray(e)) for e in dg_err]
        self.zmin = [Lazy(H, np.asarray(z)) for z in zmin]
        self.zmax = [Lazy(H, np.asarray(z)) for z in zmax]
        # edge-diamond height ranges: the union of the two squares beside the edge (taken on the
        # stored values: the world transform is monotone, increasing for vertical_scale > 0)
        lo_op, hi_op = (np.minimum, np.maximum) if self.vs >= 0 else (np.maximum, np.minimum)
        self.dg_zmin, self.dg_zmax = [], []
        for j in range(J):
            zlo, zhi = self.zmin[j].src[0], self.zmax[j].src[0]
            self.dg_zmin.append(Lazy(H, self._edge_range(zlo, np.inf if lo_op is np.minimum else -np.inf, lo_op)))
            self.dg_zmax.append(Lazy(H, self._edge_range(zhi, -np.inf if hi_op is np.maximum else np.inf, hi_op)))
        self._spheres()
        self._tables()

    def _tables(self) -> None:
        """Flat per-level columns the walk gathers from (:mod:`.kpatch_cut`): sphere centre
        height, radius, error and z-range of every square diamond (index v·2^j + u) and edge
        diamond (index (o·(2^j+1) + v)·(2^j+1) + u); the (…, 3) centres are dropped (x and y
        follow from the indices)."""
        J = self.lay.J
        self.sq_tab, self.dg_tab = [], []
        for j in range(J):
            lo, hi = self.zmin[j].ravel(), self.zmax[j].ravel()
            self.sq_tab.append((Lazy(square_centre, lo, hi), self.sq_r[j].ravel(), self.sq_err[j].ravel(), lo, hi))
            lo, hi = self.dg_zmin[j].ravel(), self.dg_zmax[j].ravel()
            self.dg_tab.append((Lazy(edge_centre, lo, hi), self.dg_r[j].ravel(), self.dg_err[j].ravel(), lo, hi))
        self.sq_tab.append((None, None, None, self.zmin[J].ravel(), self.zmax[J].ravel()))
        del self.sq_c, self.dg_c
        self._mark = np.zeros(max(4**J, 2 * (2 ** max(J - 1, 0) + 1) ** 2), np.uint8)
        self.top = TopBatch(self, min(J, TOP_LEVELS))

    @staticmethod
    def _edge_range(sq: np.ndarray, fill: float, op) -> np.ndarray:
        n = sq.shape[0]
        p = np.pad(sq, 1, constant_values=fill)
        out = np.full((2, n + 1, n + 1), fill, sq.dtype if sq.dtype.kind == 'f' else np.float64)
        out[0, :, :n] = op(p[:-1, 1:-1], p[1:, 1:-1])  # horizontal edge v: squares v-1 and v
        out[1, :n, :] = op(p[1:-1, :-1], p[1:-1, 1:])  # vertical edge u: squares u-1 and u
        return out

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """World box of the valid (non-padding) terrain."""
        return world_box(self.lay, self.zmin[0].src[0], self.zmax[0].src[0], (self.dx, self.dy), self.vs, self.exaggeration)

    def _world(self, x, y, z):
        return np.stack([np.asarray(x, np.float64) * self.dx, -np.asarray(y, np.float64) * self.dy, z], axis=-1)

    def _spheres(self) -> None:
        lay, J = self.lay, self.lay.J
        half = lambda a: math.hypot(a / 2 * self.dx, a / 2 * self.dy)  # noqa: E731
        self.sq_c, self.sq_r, self.dg_c, self.dg_r = [None] * J, [None] * J, [None] * J, [None] * J
        for j in range(J - 1, -1, -1):
            a = lay.square_side(j)
            n = 2**j
            # edge diamonds (children: the 4 squares of level j+1 meeting at the midpoint)
            idx = np.arange(n + 1)
            dg_zmin, dg_zmax, zmin, zmax = (z[...] for z in (self.dg_zmin[j], self.dg_zmax[j], self.zmin[j], self.zmax[j]))
            valid = np.isfinite(dg_zmin)
            zc = np.where(valid, (np.where(valid, dg_zmin, 0) + np.where(valid, dg_zmax, 0)) / 2, 0.0)
            xs = np.stack([np.broadcast_to((idx[None, :] + 0.5) * a, (n + 1, n + 1)), np.broadcast_to(idx[None, :] * a, (n + 1, n + 1))])
            ys = np.stack([np.broadcast_to(idx[:, None] * a, (n + 1, n + 1)), np.broadcast_to((idx[:, None] + 0.5) * a, (n + 1, n + 1))])
            c = self._world(xs, ys, zc)
            r = np.sqrt(half(a) ** 2 + np.where(valid, (np.where(valid, dg_zmax, 0) - np.where(valid, dg_zmin, 0)) / 2, 0.0) ** 2)
            if j + 1 < J:
                r = np.maximum(r, self._edge_child_bound(c, n, self.sq_c[j + 1], self.sq_r[j + 1]))
            self.dg_c[j], self.dg_r[j] = c, r
            # square diamonds (children: the edge diamonds on their 4 sides)
            uu, vv = np.meshgrid(np.arange(n), np.arange(n))
            zc = (zmin + zmax) / 2
            c = self._world((uu + 0.5) * a, (vv + 0.5) * a, zc)
            r = np.sqrt(half(a) ** 2 + ((zmax - zmin) / 2) ** 2)
            for o, dv, du in ((0, 0, 0), (0, 1, 0), (1, 0, 0), (1, 0, 1)):
                cc, rr = self.dg_c[j][o, dv:dv + n, du:du + n], self.dg_r[j][o, dv:dv + n, du:du + n]
                r = np.maximum(r, np.linalg.norm(c - cc, axis=-1) + rr)
            self.sq_c[j], self.sq_r[j] = c, r

    @staticmethod
    def _edge_child_bound(c: np.ndarray, n: int, kc: np.ndarray, kr: np.ndarray) -> np.ndarray:
        out = np.zeros(c.shape[:3])
        m = kc.shape[0]  # 2n
        for o in (0, 1):
            v, u = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
            if o == 0:  # horizontal edge (v, u): midpoint row 2v, col 2u+1 -> squares rows 2v-1..2v, cols 2u..2u+1
                rows, cols = (2 * v - 1, 2 * v), (2 * u, 2 * u + 1)
            else:
                rows, cols = (2 * v, 2 * v + 1), (2 * u - 1, 2 * u)
            for rr_ in rows:
                for cc_ in cols:
                    ok = (rr_ >= 0) & (rr_ < m) & (cc_ >= 0) & (cc_ < m)
                    ri, ci = np.clip(rr_, 0, m - 1), np.clip(cc_, 0, m - 1)
                    d = np.linalg.norm(c[o] - kc[ri, ci], axis=-1) + kr[ri, ci]
                    out[o] = np.maximum(out[o], np.where(ok, d, 0.0))
        return out


def world_box(layout: TerrainLayout, zmin0, zmax0, spacing=(1.0, 1.0), vscale: float = 1.0,
              exaggeration: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """World box (lo, hi), float64 (3,), of the valid terrain from the stored whole-domain height
    range (``lod/zmin/0``, ``lod/zmax/0``, (1, 1) each): exactly :meth:`PatchHierarchy.bounds`
    of a hierarchy built with these arguments, without building it (the parent of a job fits
    paths and clip planes with it)."""
    dx, dy = (float(v) for v in spacing)
    vs = float(vscale)
    H = partial(heights, float(np.min(zmin0)) * vs, vs, float(exaggeration))
    lo = np.array([0.0, -(layout.rows - 1) * dy, H(zmin0).min()])
    hi = np.array([(layout.cols - 1) * dx, 0.0, H(zmax0).max()])
    return lo, hi


@dataclass
class Front:
    """Selected patches (one row each): apex/left/right vertices in finest-sample units
    (x = col, y = row), bintree depth, the block (level, bi, bj) they draw from, the sample
    stride inside that block, and the diamond z-range for culling. ``code`` (int8, optional)
    says where each patch's diamond sphere lies against the frustum the cut was taken for
    (``code_vp``: None = the camera's whole frame): 0 outside, 1 crossing a plane, 2 inside."""

    ax: np.ndarray
    ay: np.ndarray
    lx: np.ndarray
    ly: np.ndarray
    rx: np.ndarray
    ry: np.ndarray
    depth: np.ndarray
    level: np.ndarray
    bi: np.ndarray
    bj: np.ndarray
    stride: np.ndarray
    zmin: np.ndarray
    zmax: np.ndarray
    deferred: int = 0  # diamonds that wanted to split but waited for data
    code: np.ndarray | None = None
    code_vp: Viewport | None = None
    bid: np.ndarray | None = field(default=None, repr=False, compare=False)  # flat block ids (:meth:`block_ids`), as the walk wrote them
    bid_offsets: np.ndarray | None = field(default=None, repr=False, compare=False)  # ... for these per-level offsets

    FIELDS = ("ax", "ay", "lx", "ly", "rx", "ry", "depth", "level", "bi", "bj", "stride", "zmin", "zmax")

    def __len__(self) -> int:
        return len(self.ax)

    def take(self, idx) -> "Front":
        f = {k: getattr(self, k)[idx] for k in self.FIELDS}
        return Front(**f, deferred=self.deferred, code=None if self.code is None else self.code[idx], code_vp=self.code_vp,
                     bid=None if self.bid is None else self.bid[idx], bid_offsets=self.bid_offsets)

    @classmethod
    def empty(cls) -> "Front":
        return cls(*(np.zeros(0, np.int64) for _ in range(11)), np.zeros(0), np.zeros(0), code=np.zeros(0, np.int8))

    def block_ids(self, offsets: np.ndarray, nb: list[int]) -> np.ndarray:
        """Flat ids of the blocks the patches draw from (``offsets[level] + bi·nb[level] + bj``,
        levels stacked finest first with ``nb[level] = 2^(top − level)`` blocks per side; the walk
        writes them as it emits the front, then they are returned as they are)."""
        if self.bid is not None and np.array_equal(self.bid_offsets, offsets[:len(self.bid_offsets)]):
            return self.bid
        ids = np.asarray(offsets).take(self.level)
        ids += self.bi * np.asarray(nb).take(self.level)
        ids += self.bj
        return ids


def lookup_blocks(grids: list[np.ndarray], level: np.ndarray, bi: np.ndarray, bj: np.ndarray) -> np.ndarray:
    """``grids[level[n]][bi[n], bj[n]]`` for every n: per-block values kept as one (nb, nb)
    grid per pyramid level (residency flags, GL slots ...)."""
    if not grids or len(level) == 0:
        return np.empty(len(level), grids[0].dtype if grids else bool)
    if len(grids) == 1 or level.min() == level.max():  # one level: one gather
        return grids[int(level[0])][bi, bj]
    flat = np.concatenate([g.ravel() for g in grids])  # every level's grid, flattened end to end
    offset = np.cumsum([0] + [g.size for g in grids[:-1]])
    cols = np.array([g.shape[1] for g in grids])
    return flat[offset[level] + bi * cols[level] + bj]


def select_front(h: PatchHierarchy, camera: Camera, tau: float = 1.0, resident=None, request: Request | None = None,
                 viewport: Viewport | None = None) -> Front:
    """The conforming K-patch cut for ``camera`` (a pure function of the camera, the data and
    ``resident``: None = all blocks, per-level (nb, nb) bool grids, or a callable (level, bi,
    bj) -> bool). Missing blocks are passed to ``request(level, bi, bj, priority)``. Patches
    outside the frustum are kept (their parents decide conformity) but not refined; cull them
    per viewport with :func:`visible_patches`.

    With ``viewport`` (a sort-first tile) only diamonds whose sphere touches the tile's
    sub-frustum refine. The split test is per diamond and does not depend on the frustum
    otherwise, so every diamond the tile's walk reaches inside its sub-frustum gets the whole
    frame's decision (its ancestors' spheres contain its own, so they touch the sub-frustum
    too): the patches visible in the tile are exactly the whole-frame cut's, in the same
    relative order; only patches the tile cannot see stay coarser."""
    lay = h.dims
    view = View(camera, tau, None if viewport is None or viewport == camera.viewport else viewport)
    res = Residency(resident, lay.levels, lay.L)
    top = h.top
    split, H0, H1, code, deferred = top.walk(view, res, request)
    if view.kernel is None:  # numpy
        head = top.kept(split, H0, H1)
        seed = kpatch_walk.edge_children(h, 2 ** (top.depths // 2 - 1), *top.seeds(split, H0, H1))
        parts, d = kpatch_walk.walk(h, view, res, request, top.depths, seed)
        cols, zs, codes, bid = kpatch_walk.emit(h, parts, head, code)
    else:  # the compiled kernels: the same front
        head, seed_keys = top.kept_and_seeds(view.kernel, split, H0, H1)
        seed = kpatch_compiled.seed_children(h, view, 2 ** (top.depths // 2 - 1), seed_keys)
        parts, d = kpatch_compiled.walk(h, view, res, request, top.depths, seed)
        cols, zs, codes, bid = kpatch_compiled.emit(h, view, parts, head, code)
    return Front(*cols, *zs, deferred=deferred + d, code=codes, code_vp=view_vp(camera, viewport), bid=bid, bid_offsets=top.block_offsets)


def view_vp(camera: Camera, vp: Viewport | None) -> Viewport | None:
    """The frustum key of a cut or cull: None for the whole frame."""
    return None if vp is None or vp == camera.viewport else vp


def visible_patches(h: PatchHierarchy, f: Front, camera: Camera, vp: Viewport | None = None) -> np.ndarray:
    """Indices of the patches whose box touches the frustum of ``vp`` (None: the whole frame).
    Boxes lie inside their diamond's sphere, so where the cut was taken for the same frustum
    only patches whose sphere crosses a plane need the box test."""
    key = view_vp(camera, vp)
    if f.code is None:
        maybe, sure = np.arange(len(f)), np.zeros(len(f), bool)
    elif key == f.code_vp:
        maybe, sure = np.flatnonzero(f.code == 1), f.code == 2
    else:  # a tile of a whole-frame cut: outside the frame is outside the tile
        maybe, sure = np.flatnonzero(f.code >= 1), np.zeros(len(f), bool)
    out = sure.copy()
    if len(maybe):
        out[maybe] = boxes_touch(h, f, maybe, frustum_planes(camera, vp))
    return np.flatnonzero(out)


def boxes_touch(h: PatchHierarchy, f: Front, idx: np.ndarray, planes: np.ndarray) -> np.ndarray:
    """(len(idx),) bool: the world box of each patch ``idx`` is not entirely outside any plane
    (the p-vertex test of :func:`massview.lod.cull.boxes_in_frustum`, all six planes as one (6, n)
    array, each distance summed in the same order as one plane at a time)."""
    ax, lx, rx, ay, ly, ry = (getattr(f, k)[idx] for k in ("ax", "lx", "rx", "ay", "ly", "ry"))
    x0, x1 = np.minimum(np.minimum(ax, lx), rx) * h.dx, np.maximum(np.maximum(ax, lx), rx) * h.dx
    y0, y1 = -np.maximum(np.maximum(ay, ly), ry) * h.dy, -np.minimum(np.minimum(ay, ly), ry) * h.dy
    z0, z1 = f.zmin[idx], f.zmax[idx]
    p = planes[:, :, None]
    pos = p[:, :3] >= 0
    d = np.where(pos[:, 0], x1, x0) * p[:, 0]  # the p-vertex against every plane at once: (6, n)
    d += np.where(pos[:, 1], y1, y0) * p[:, 1]
    d += np.where(pos[:, 2], z1, z0) * p[:, 2]
    d += p[:, 3]
    return (d >= 0).all(axis=0)


def patch_boxes(h: PatchHierarchy, f: Front) -> tuple[np.ndarray, np.ndarray]:
    """World-space axis-aligned boxes (lo, hi), (n, 3) each, bounding every patch."""
    xs = np.stack([f.ax, f.lx, f.rx]) * h.dx
    ys = -np.stack([f.ay, f.ly, f.ry]) * h.dy
    lo = np.stack([xs.min(0), ys.min(0), f.zmin], axis=1)
    hi = np.stack([xs.max(0), ys.max(0), f.zmax], axis=1)
    return lo, hi


def refine_uniform(ax, ay, lx, ly, rx, ry, levels: int):
    """Split every triangle ``levels`` times at its hypotenuse midpoint (the mesh of a
    K-patch with K = 2^(levels/2) + 1). Integer inputs; returns (n·2^levels, 3, 2) int64
    vertices (apex, left, right), in order."""
    a = [np.asarray(v, np.int64) for v in (ax, ay, lx, ly, rx, ry)]
    for _ in range(levels):
        ax, ay, lx, ly, rx, ry = a
        mx, my = (lx + rx) // 2, (ly + ry) // 2
        # interleave children so that each parent's children stay together
        a = [np.stack(p, axis=1).ravel() for p in ((mx, mx), (my, my), (lx, ax), (ly, ay), (ax, rx), (ay, ry))]
    ax, ay, lx, ly, rx, ry = a
    return np.stack([np.stack([ax, ay], 1), np.stack([lx, ly], 1), np.stack([rx, ry], 1)], axis=1)


def watertight_problems(tris: np.ndarray, side: int) -> list[str]:
    """Check a triangulation of the square [0, side]² given as (n, 3, 2) integer vertices:
    every edge inside the square is shared by exactly two triangles and every edge on its
    border by one (so there are no cracks and no T-junctions), and the areas add up."""
    e = np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]])  # (3n, 2, 2)
    a, b = e[:, 0], e[:, 1]
    swap = (a[:, 0] > b[:, 0]) | ((a[:, 0] == b[:, 0]) & (a[:, 1] > b[:, 1]))
    p, q = np.where(swap[:, None], b, a), np.where(swap[:, None], a, b)
    code = ((p[:, 0] * (side + 1) + p[:, 1]) * (side + 1) + q[:, 0]) * (side + 1) + q[:, 1]
    uniq, counts = np.unique(code, return_counts=True)
    q1 = uniq % (side + 1)
    q0 = (uniq // (side + 1)) % (side + 1)
    p1 = (uniq // (side + 1) ** 2) % (side + 1)
    p0 = uniq // (side + 1) ** 3
    border = ((p0 == q0) & ((p0 == 0) | (p0 == side))) | ((p1 == q1) & ((p1 == 0) | (p1 == side)))
    out = []
    bad_inner = (~border) & (counts != 2)
    bad_border = border & (counts != 1)
    if bad_inner.any():
        out.append(f"{int(bad_inner.sum())} interior edges not shared by exactly two triangles (cracks or T-junctions)")
    if bad_border.any():
        out.append(f"{int(bad_border.sum())} border edges used more than once")
    d1, d2 = tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]
    area2 = np.abs(d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0]).sum()
    if area2 != 2 * side * side:
        out.append(f"triangles cover {area2 / 2} of {side * side} square units")
    return out
