"""The K-patch walk below the batched top by the compiled kernels of
:mod:`massview.data.lodkernel`, when a :class:`~.kpatch_cut.View` has them (:mod:`.kernels`).

The same walk as :mod:`.kpatch_walk` — the reference it is tested against (tests/test_lod_kernel.py:
the stage digests with each) — with each depth's few dozen whole-array numpy passes replaced by
one kernel pass per stage: the split test straight from the packed keys and the stored
(float32) columns, the kept patches with their z-ranges, the children paired through the same
mark array, and the Front's records. Every value is computed by the same float64 operations in
the same order and every list comes out in the same order, so the front is the same bits. Only
the residency of the children's blocks, where some level is not wholly resident, is still
checked with numpy (:func:`.kpatch_walk._resident`, which also requests the missing blocks).
"""

from __future__ import annotations

import math

import numpy as np

from .kpatch_cut import Residency, View, draw_level
from .kpatch_walk import _M, _resident, _vertex_tables, walk_depths

__all__ = ["walk", "seed_children", "emit"]


def walk(h, view: View, res: Residency, request, t0: int, key: np.ndarray):
    """:func:`.kpatch_walk.walk`: depths t0 … 2J from the present diamonds ``key``; each kept
    part is (t, half-0 count, ids, keys, codes, z-ranges (2, k))."""
    return walk_depths(h, t0, key, lambda t, k: _step(h, view, res, request, t, k), lambda k: _leaves(h, view, k))


def _step(h, view: View, res: Residency, request, t: int, key):
    kernel, lay, j = view.kernel, h.dims, t >> 1
    edge = bool(t & 1)
    tab = h.dg_tab[j] if edge else h.sq_tab[j]
    n = len(key)
    ids, crit, pix, code, split = np.empty(n, np.int64), np.empty(n, bool), np.empty(n), np.empty(n, np.int8), np.empty(n, bool)
    zw = np.empty((2, n))
    kernel.diamond_test(key, edge, j, lay.n - j, h.dx, -h.dy, tab[3].src[0], tab[4].src[0], tab[1], tab[2].src[0], h.base, h.vs,
                        h.exaggeration, *view.kernel_consts, ids, crit, pix, code, split, zw)
    if not res.all:
        split = _step_resident(h, kernel, res, request, t, key, crit, pix, split)
    n0, kid, kkey, kcode, kz, deferred = kernel.kept(ids, key, code, crit, split, zw)
    if edge:
        kids = kernel.edge_children(key.take(np.flatnonzero(split)), 1 << j, h._mark)
    else:
        kids = kernel.square_children(key, split, 1 << j, h._mark)
    return kids, (t, n0, kid, kkey, kcode, kz), deferred


def _step_resident(h, kernel, res: Residency, request, t: int, key, crit, pix, split):
    """:func:`.kpatch_walk._resident` (the same flags, the same requests in the same order), by
    :func:`massview.data.lodkernel.resident` where the residency is a flat array."""
    lay = h.dims
    edge = bool(t & 1)
    if res.flat is None:  # a callable: numpy
        o = (key >> 60) & 1 if edge else None
        return _resident(lay, res, request, t, o, (key >> 30) & _M, key & _M, key >> 61, crit, pix, split)
    blvl = min(draw_level(lay.J, t + 1), lay.L)
    if res.level_resident(blvl):
        return split
    d = lay.m + blvl - (lay.n - (t >> 1))
    nb = 1 << (lay.L - blvl)
    miss = np.empty((2, len(key)), bool)
    kernel.resident(key, edge, d, nb, res.flat, int(res.offset[blvl]), crit, split, miss)
    if request is not None:
        for k in range(2 if edge else 1):  # half 0's blocks, then half 1's
            sel = np.flatnonzero(miss[k])
            if len(sel):
                ks = key.take(sel)
                v, u = (ks >> 30) & _M, ks & _M
                if k == 0 and edge:
                    o = (ks >> 60) & 1
                    v, u = v - 1 + o, u - o
                request(np.full(len(sel), blvl), v >> d, u >> d, np.minimum(pix.take(sel), 1e30))
    return split


def _leaves(h, view: View, key):
    lay, J = h.dims, h.dims.J
    sa = lay.n - J
    a = 1 << sa
    tab = h.sq_tab[J]
    half = math.hypot(a / 2 * h.dx, a / 2 * h.dy)
    n0, ids, keys, codes, zs, _ = view.kernel.leaves(key, J, sa, h.dx, -h.dy, tab[3].src[0], tab[4].src[0], h.base, h.vs,
                                                    h.exaggeration, half * half, *view.kernel_consts[:6])
    return 2 * J, n0, ids, keys, codes, zs


def seed_children(h, view: View, n: int, ks) -> np.ndarray:
    """:func:`.kpatch_walk.edge_children` of the batched top's deepest split edges ``ks``
    (their orientation and halves are in the keys' bits)."""
    return view.kernel.edge_children(ks, n, h._mark)


def emit(h, view: View, parts, head, head_code):
    """:func:`.kpatch_walk.emit`: the Front's columns, the top's kept halves first, then the
    walked depths' (square depths, then edge depths)."""
    kernel = view.kernel
    parts = [p for p in parts if p[0] % 2 == 0] + [p for p in parts if p[0] % 2 == 1]
    top, m = h.top, len(head)
    total = m + sum(len(p[2]) for p in parts)
    cols, zs, code = np.empty((11, total), np.int64), np.empty((2, total)), np.empty(total, np.int8)
    bid = np.empty(total, np.int64)
    kernel.head_records(top.rec_rows, top.rec_flt, top.rec_bid, head_code, head, cols, zs, code, bid)
    if total == m:
        return cols, zs, code, bid
    key = np.concatenate([p[3] for p in parts])
    np.concatenate([p[4] for p in parts], out=code[m:])
    np.concatenate([p[5] for p in parts], axis=1, out=zs[:, m:])
    lay = h.dims
    kernel.patch_records(key, _spans(lay, parts, top.block_offsets), *_vertex_tables(lay.n, lay.J, lay.L, lay.m), m, cols, bid)
    return cols, zs, code, bid


def _spans(lay, parts, block_offsets) -> np.ndarray:
    """Per depth of ``parts`` the row :func:`massview.data.lodkernel.patch_records` reads: begin,
    end, half-0 count, table row 16·t, side log2 a, block shift, L − block level, the block
    level's flat offset, t."""
    verts, rec = _vertex_tables(lay.n, lay.J, lay.L, lay.m)
    out, e = np.empty((len(parts), 9), np.int64), 0
    for k, p in enumerate(parts):
        t, n0 = p[0], p[1]
        b, e = e, e + len(p[2])
        blvl = min(draw_level(lay.J, t), lay.L)
        out[k] = (b, e, n0, 16 * t, verts[6, 16 * t], rec[5, 16 * t], lay.L - blvl, block_offsets[blvl], t)
    return out
