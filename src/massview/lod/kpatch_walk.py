"""The lower depths of the K-patch walk, one depth at a time (see :mod:`massview.lod.kpatch_cut`
for the rule; :mod:`massview.lod.kpatch_top` batches the depths above).

A present diamond travels as one int64 *key*: u in bits 0–29, v in bits 30–59, the edge
orientation o in bit 60 and its present halves in bits 61 (half 0) and 62 (half 1). Each
depth selects from one array instead of five, which is most of the work: numpy's masked
selections cost several ns per element on the irregular masks a cut produces.

Every depth is a fixed sequence of a few dozen whole-array operations (a third of the work
is the split test), so the cost is elements × passes plus the memory the passes touch. What
keeps both down:

* integer lattice arithmetic: sphere centres ``x = (u·a + a/2)·dx`` from integer (v, u) (the
  same float64 values as ``(u + ½)·a·dx``); the blocks a half's children draw from are
  ``(v ≫ d, u ≫ d)`` (one step up or left for half 0 of an edge), because side ``a`` divides
  the block span ``2^d·a`` — no centroid division, no clipping;
* a split diamond's children from its own (v, u) (keys shifted by one bit are the child
  squares' keys), paired by the mark array (:func:`~.kpatch_cut.merge_halves`);
* the kept patches' records from per-(depth, parity, half) tables (:func:`_vertex_tables`):
  each vertex is ``(u·a, v·a)`` plus a tabled offset, the block index the vertex sum's tabled
  share shifted down — a handful of gathers per patch instead of the geometry of
  :func:`~.kpatch_cut.patch_vertices`, which builds the tables.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

from .kpatch_cut import Residency, View, draw_level, merge_halves, patch_vertices

__all__ = ["pack", "walk", "walk_depths", "edge_children", "emit"]

_M = (1 << 30) - 1
_O, _H0, _H1 = 1 << 60, 1 << 61, 1 << 62
_VU = (1 << 60) - 1  # the (v, u) bits
_ROW = 1 << 30


def pack(o, v, u, h0, h1) -> np.ndarray:
    return (np.asarray(v, np.int64) << 30) | u | (np.asarray(o, np.int64) << 60) | (np.asarray(h0, np.int64) << 61) | (
        np.asarray(h1, np.int64) << 62)


def walk(h, view: View, res: Residency, request, t0: int, key: np.ndarray):
    """Depths t0 … 2J of the walk from the present diamonds ``key`` at depth t0. Returns the
    kept parts (per depth: t, half-0 count, ids, keys, codes; see :func:`_kept`) and the
    deferred-split count."""
    return walk_depths(h, t0, key, lambda t, k: _step(h, view, res, request, t, k), lambda k: _leaves(h, view, k))


def walk_depths(h, t0: int, key: np.ndarray, step, leaves):
    """The depth loop of a walk (numpy here, compiled in :mod:`.kpatch_compiled`): per depth
    t0 … 2J − 1 while diamonds remain, ``step(t, key)`` → (next depth's keys, kept part,
    deferred count); then ``leaves(key)`` for those reaching depth 2J. Returns (parts, deferred)."""
    parts, deferred = [], 0
    for t in range(t0, 2 * h.dims.J):
        if len(key) == 0:
            return parts, deferred
        key, kept, d = step(t, key)
        parts.append(kept)
        deferred += d
    if len(key):
        parts.append(leaves(key))
    return parts, deferred


def _step(h, view: View, res: Residency, request, t: int, key):
    lay, j = h.dims, t >> 1
    sa = lay.n - j
    a, n = 1 << sa, 1 << j
    u = key & _M
    v = (key >> 30) & _M
    hb = key >> 61  # present halves: 1 (half 0), 2 (half 1), 3 (both)
    o = None
    if t & 1:
        o = (key >> 60) & 1
        N = n + 1
        ids = (o * N + v) * N + u
        xi = (u << sa) + ((1 - o) << (sa - 1))  # (u + ½(1 − o))·a
        yi = (v << sa) + (o << (sa - 1))
        w = np.where(o == 0, v, u)  # halves exist inside the domain only
        complete = hb == (w >= 1) + 2 * (w < n)
        tab = h.dg_tab[j]
    else:
        ids = (v << j) | u
        xi = (u << sa) + (a >> 1)  # (u + ½)·a
        yi = (v << sa) + (a >> 1)
        complete = hb == 3
        tab = h.sq_tab[j]
    xyz = np.empty((3, len(key)))
    np.multiply(xi, h.dx, out=xyz[0])  # the same float64 centres as (u + ½)·a·dx
    np.multiply(yi, -h.dy, out=xyz[1])
    tab[0].take(ids, out=xyz[2], mode="clip")
    crit, pix, code = view.test(xyz, tab[1].take(ids), tab[2].take(ids))
    split = crit & complete
    if not res.all:
        split = _resident(lay, res, request, t, o, v, u, hb, crit, pix, split)
    kept, deferred = _kept(t, ids, key, code, hb, crit, split)
    s = np.flatnonzero(split)
    if t & 1:
        return edge_children(h, n, key.take(s), o.take(s), hb.take(s)), kept, deferred
    return _square_children(h, n, v.take(s), u.take(s)), kept, deferred


def _kept(t: int, ids, key, code, hb, crit, split):
    """The patches a depth keeps — the present halves of the diamonds that do not split, its
    half-0 patches first: (t, half-0 count, ids, keys, codes) — and the deferred splits
    (present halves of critical diamonds that do not split)."""
    h0, h1 = (hb & 1) != 0, hb >= 2
    stay = ~split
    wait = crit & stay
    deferred = int(np.count_nonzero(wait & h0)) + int(np.count_nonzero(wait & h1)) if wait.any() else 0
    s0 = np.flatnonzero(stay & h0)
    sel = np.concatenate([s0, np.flatnonzero(stay & h1)])
    return (t, len(s0), ids.take(sel), key.take(sel), code.take(sel)), deferred


def _square_children(h, n: int, v, u) -> np.ndarray:
    """Split squares (v, u) of a level with n per side give their 4 sides (edges, same level)
    one half each: half 0 to the edges below (o = 0) and right (o = 1), half 1 to the edges
    above and left."""
    N = n + 1
    base = (v << 30) | u
    w = v * N + u
    id0 = np.concatenate([w + N, w + (N * N + 1)])
    id1 = np.concatenate([w, w + N * N])
    in1, only1 = merge_halves(h._mark, id0, id1)
    k0 = np.concatenate([base + (_ROW | _H0), base + (1 | _O | _H0)])
    k0 |= np.left_shift(in1, 62, dtype=np.int64)
    k1 = np.concatenate([base | _H1, base | (_O | _H1)])
    return np.concatenate([k0, k1.take(np.flatnonzero(only1))])


def edge_children(h, n: int, ks, o, hb) -> np.ndarray:
    """Split edges give the 4 squares around their midpoint (one level down, 2n per side) one
    half each: rows 2v−1, 2v (o = 0) or columns 2u−1, 2u (o = 1), the first pair from the
    half above/left (half 0), the second from the half below/right; a square's half 0 comes
    from its horizontal parent edge, half 1 from its vertical one."""
    m = 2 * n
    horizontal = o == 0
    h0 = np.flatnonzero(horizontal)
    k0, id0 = _edge_kids(ks.take(h0), hb.take(h0), (_ROW, _ROW - 1, 0, -1), (m, m - 1, 0, -1), m)
    h1 = np.flatnonzero(~horizontal)
    k1, id1 = _edge_kids(ks.take(h1), hb.take(h1), (1, -_ROW + 1, 0, -_ROW), (1, -m + 1, 0, -m), m)
    in1, only1 = merge_halves(h._mark, id0, id1)
    k0 |= _H0
    k0 |= np.left_shift(in1, 62, dtype=np.int64)
    k1 = k1.take(np.flatnonzero(only1))
    k1 |= _H1
    return np.concatenate([k0, k1])


def _edge_kids(ks, hb, dk, di, m: int):
    """(keys, ids) of the child squares of split edges of one orientation: ``c − dk[0]``,
    ``c − dk[1]`` from half 0 and ``c − dk[2]``, ``c − dk[3]`` from half 1, with c = (2v, 2u)
    as a key (``di``: the same offsets in ids v·m + u)."""
    c = (ks & _VU) << 1
    w = ((c >> 30) * m) | (c & _M)
    n = len(c)
    keys, ids = np.empty(4 * n, np.int64), np.empty(4 * n, np.int64)
    for i in range(4):  # written in place: c − dk[0], c − dk[1], ... one after the other
        np.subtract(c, dk[i], out=keys[i * n:(i + 1) * n])
        np.subtract(w, di[i], out=ids[i * n:(i + 1) * n])
    if len(hb) and not (hb == 3).all():  # border edges: one half
        h0, h1 = (hb & 1) != 0, hb >= 2
        ok = np.flatnonzero(np.concatenate([h0, h0, h1, h1]))
        keys, ids = keys.take(ok), ids.take(ok)
    return keys, ids


def _resident(lay, res: Residency, request, t, o, v, u, hb, crit, pix, split):
    """``split`` further restricted to diamonds whose present halves' children have their
    blocks resident; requests the missing ones (priority: the pixel error). The children of a
    half draw from the block (at level ``blvl``) holding the half's centroid; with the square
    side ``a`` dividing the block span ``a·2^d`` that block is (v ≫ d, u ≫ d), or for half 0 of
    an edge the one above (o = 0: (v − 1) ≫ d) or left (o = 1)."""
    blvl = min(draw_level(lay.J, t + 1), lay.L)
    if res.level_resident(blvl):
        return split
    d = lay.m + blvl - (lay.n - (t >> 1))
    nb = 1 << (lay.L - blvl)
    if t & 1 == 0:
        bi, bj = v >> d, u >> d
        r = res.lookup(blvl, bi, bj, nb)
        _request(request, blvl, bi, bj, crit & ~r, pix)  # every present square has a half
        return split & r
    for k, (bi, bj) in enumerate((((v - 1 + o) >> d, (u - o) >> d), (v >> d, u >> d))):
        hk = (hb & (1 << k)) != 0
        r = res.lookup(blvl, bi, bj, nb)
        _request(request, blvl, bi, bj, crit & hk & ~r, pix)
        split = split & (r | ~hk)
    return split


def _request(request, blvl: int, bi, bj, miss, pix) -> None:
    if request is not None and miss.any():
        request(np.full(int(np.count_nonzero(miss)), blvl), bi[miss], bj[miss], np.minimum(pix[miss], 1e30))


def _leaves(h, view: View, key):
    """The deepest square level: every present half is a patch; spheres for culling only."""
    lay, J = h.dims, h.dims.J
    sa = lay.n - J
    a = 1 << sa
    v, u = (key >> 30) & _M, key & _M
    ids = (v << J) | u
    zlo, zhi = h.sq_tab[J][3].take(ids), h.sq_tab[J][4].take(ids)
    xyz = np.empty((3, len(key)))
    np.multiply((u << sa) + (a >> 1), h.dx, out=xyz[0])  # (u + ½)·a·dx
    np.multiply((v << sa) + (a >> 1), -h.dy, out=xyz[1])
    np.add(zlo, zhi, out=xyz[2])
    xyz[2] /= 2
    half = math.hypot(a / 2 * h.dx, a / 2 * h.dy)
    dz = zhi - zlo
    dz /= 2
    dz *= dz
    dz += half * half
    inside, full = view._planes(view.to_camera(xyz), np.sqrt(dz, out=dz))
    none = np.zeros(len(key), bool)
    return _kept(2 * J, ids, key, inside.view(np.int8) + full.view(np.int8), key >> 61, none, none)[0]


@lru_cache(maxsize=8)
def _vertex_tables(n: int, J: int, L: int, m: int):
    """Per (depth t, parity code c) rows, index 16·t + c with c = (u & 1) | (v & 1) << 1 |
    half << 2 | o << 3: int64 (7, 16·(2J+1)) — the six vertex offsets from (u·a, v·a) and
    log2 a — and int64 (6, …) — depth, block level, the centroid's offsets (y, x) from
    (v·a, u·a) (the vertex sums are 3·(u·a) plus the offsets' sum, so the centroid is exact),
    stride, and the block shift log2 of the block span."""
    rows = 16 * (2 * J + 1)
    verts, rec = np.zeros((7, rows), np.int64), np.zeros((6, rows), np.int64)
    c = np.arange(16)
    uu, vv, half, o = c & 1, (c >> 1) & 1, (c >> 2) & 1, (c >> 3) & 1
    for t in range(2 * J + 1):
        sa = n - t // 2
        a = 1 << sa
        oo = o if t % 2 else np.zeros(16, np.int64)
        vx = patch_vertices(t, oo, vv, uu, half.astype(bool), a)
        off = np.stack([vx[i] - (uu if i % 2 == 0 else vv) * a for i in range(6)])
        s = slice(16 * t, 16 * t + 16)
        verts[:6, s], verts[6, s] = off, sa
        lvl = draw_level(J, t)
        blvl = min(lvl, L)
        rec[:, s] = np.stack([np.full(16, t), np.full(16, blvl), (off[1] + off[3] + off[5]) // 3, (off[0] + off[2] + off[4]) // 3,
                              np.full(16, 1 << (lvl - blvl)), np.full(16, blvl + m)])
    return verts, rec


def emit(h, parts, head, head_code):
    """The Front's columns: (int64 (11, n): ax … stride, float64 (2, n): zmin, zmax, int8 (n,):
    codes, int64 (n,): flat block ids) — the batched top's kept halves first (``head``: positions in its half records,
    ``head_code``: its diamonds' codes), then the kept halves of ``parts``
    (square depths, then edge depths; in each depth its half-0 patches before its half-1
    patches), each column written once."""
    parts = [p for p in parts if p[0] % 2 == 0] + [p for p in parts if p[0] % 2 == 1]
    top, m = h.top, len(head)
    total = m + sum(len(p[2]) for p in parts)
    cols, zs, code = np.empty((11, total), np.int64), np.empty((2, total)), np.empty(total, np.int8)
    bid = np.empty(total, np.int64)  # flat block ids (Front.block_ids)
    top.rec_bid.take(head, out=bid[:m])
    cols[:, :m] = top.rec_int.take(head, axis=1)
    top.rec_flt[0].take(head, out=zs[0, :m], mode="clip")
    top.rec_flt[1].take(head, out=zs[1, :m], mode="clip")
    head_code.take(head, out=code[:m], mode="wrap")  # half records: size + i is diamond i's half 1
    if total == m:
        return cols, zs, code, bid
    key = np.concatenate([p[3] for p in parts])
    np.concatenate([p[4] for p in parts], out=code[m:])
    e = m
    for t, n0, ids, _, _ in parts:
        b, e = e, e + len(ids)
        tab = h.dg_tab[t // 2] if t % 2 else h.sq_tab[t // 2]
        _take_into(tab[3], ids, zs[0, b:e])
        _take_into(tab[4], ids, zs[1, b:e])
    row = np.repeat(np.array([[16 * p[0], 16 * p[0] + 4] for p in parts]).ravel(),
                    np.array([[p[1], len(p[2]) - p[1]] for p in parts]).ravel())
    row |= key & 1
    row |= (key >> 29) & 2
    row |= (key >> 57) & 8
    spans, e = [], 0
    for p in parts:
        b, e = e, e + len(p[2])
        spans.append((b, e, p[0]))
    _patch_records(h.dims, key, row, cols[:, m:], spans)
    lay, L = h.dims, h.dims.L
    for b, e, t in spans:  # one block level per depth
        blvl = min(draw_level(lay.J, t), L)
        o = bid[m + b:m + e]
        np.left_shift(cols[8, m + b:m + e], L - blvl, out=o)
        o += cols[9, m + b:m + e]
        o += int(top.block_offsets[blvl])
    return cols, zs, code, bid


def _take_into(src: np.ndarray, idx, dst: np.ndarray) -> None:
    if src.dtype == dst.dtype:  # float64 columns and Lazy ones (computed in place)
        src.take(idx, out=dst, mode="clip")
    else:  # a narrower table (the hierarchy may keep float32 heights)
        dst[...] = src.take(idx)


def _patch_records(lay, key, row, out, spans) -> None:
    """Write the 11 integer Front columns (``out``, (11, n)) of the patches ``key`` (table rows
    ``row``): vertices (u·a, v·a) + offset, depth, level, block (centroid ≫ shift), stride.
    ``spans``: (begin, end, depth t) of each depth's patches, whose depth, level, stride, side
    and block shift are the depth's constants (the tables' values for t), so those columns are
    filled and shifted per span rather than gathered per patch."""
    verts, rec = _vertex_tables(lay.n, lay.J, lay.L, lay.m)
    x0 = key & _M
    y0 = key >> 30
    y0 &= _M
    for b, e, t in spans:
        r = 16 * t
        sa = int(verts[6, r])
        x0[b:e] <<= sa
        y0[b:e] <<= sa
        out[6, b:e] = rec[0, r]
        out[7, b:e] = rec[1, r]
        out[10, b:e] = rec[4, r]
    for i in range(6):  # row by row: a take into a contiguous row needs no buffer (a (k, n) slice of out would)
        o = out[i]
        verts[i].take(row, out=o, mode="clip")
        o += x0 if i % 2 == 0 else y0
    rec[2].take(row, out=out[8], mode="clip")
    rec[3].take(row, out=out[9], mode="clip")
    out[8] += y0
    out[9] += x0
    for b, e, t in spans:
        sh = int(rec[5, 16 * t])
        out[8, b:e] >>= sh
        out[9, b:e] >>= sh
