"""The lower depths of the K-patch walk, one depth at a time (see :mod:`massview.lod.kpatch_cut`
for the rule; :mod:`massview.lod.kpatch_top` batches the depths above).

A present diamond travels as one int64 *key*: u in bits 0–29, v in bits 30–59, the edge
orientation o in bit 60 and its present halves in bits 61 (half 0) and 62 (half 1). Each
depth selects from one array instead of five, which is most of the work: numpy's masked
selections cost several ns per element on the irregular masks a cut produces.
"""

from __future__ import annotations

import math

import numpy as np

from .kpatch_cut import Residency, View, draw_level, edge_halves, merge_halves, patch_vertices, square_halves

__all__ = ["pack", "walk", "emit"]

_M = (1 << 30) - 1
_O, _H0, _H1 = 1 << 60, 1 << 61, 1 << 62


def pack(o, v, u, h0, h1) -> np.ndarray:
    return (np.asarray(v, np.int64) << 30) | u | (np.asarray(o, np.int64) << 60) | (np.asarray(h0, np.int64) << 61) | (
        np.asarray(h1, np.int64) << 62)


def _unpack(key):
    return (key >> 60) & 1, (key >> 30) & _M, key & _M, (key & _H0) != 0, (key & _H1) != 0


def walk(h, view: View, res: Residency, request, t0: int, key: np.ndarray):
    """Depths t0 … 2J of the walk from the present diamonds ``key`` at depth t0. Returns the
    kept parts ((t, ids, keys, codes) per depth) and the deferred-split count."""
    parts, deferred = [], 0
    J = h.dims.J
    for t in range(t0, 2 * J):
        if len(key) == 0:
            return parts, deferred
        key, kept, d = _step(h, view, res, request, t, key)
        parts.append(kept)
        deferred += d
    if len(key):
        parts.append(_leaves(h, view, key))
    return parts, deferred


def _step(h, view: View, res: Residency, request, t: int, key):
    lay, j, edge = h.dims, t // 2, t % 2 == 1
    a, n = lay.square_side(j), 2**j
    o, v, u, h0, h1 = _unpack(key)
    tab = h.dg_tab[j] if edge else h.sq_tab[j]
    if edge:
        ids = (o * (n + 1) + v) * (n + 1) + u
        x = (u + 0.5 * (1 - o)) * a * h.dx
        y = -((v + 0.5 * o) * a) * h.dy
        w = np.where(o == 0, v, u)  # halves exist inside the domain only
        complete = (h0 == (w >= 1)) & (h1 == (w < n))
    else:
        ids = v * n + u
        x, y = (u + 0.5) * a * h.dx, -((v + 0.5) * a) * h.dy
        complete = h0 & h1
    crit, pix, code = view.test(x, y, tab[0][ids], tab[1][ids], tab[2][ids])
    split = crit & complete
    if not res.all:
        split = _resident(lay, res, request, t, o, v, u, h0, h1, crit, pix, split)
    wait = crit & ~split
    deferred = int(np.count_nonzero(wait & h0)) + int(np.count_nonzero(wait & h1))
    keep = np.flatnonzero(~split)
    kept = (t, ids.take(keep), key.take(keep), code.take(keep))
    return _children(h, t, key[split]), kept, deferred


def _children(h, t: int, ks: np.ndarray) -> np.ndarray:
    """Keys of the next depth's diamonds from the keys of those that split at depth ``t``."""
    o, v, u, h0, h1 = _unpack(ks)
    n = 2 ** (t // 2)
    if t % 2 == 0:  # squares give their 4 sides (edges, same level) one half each
        N = n + 1
        k0 = np.concatenate([((v + 1) << 30) | u, (v << 30) | (u + 1) | _O])
        k1 = np.concatenate([(v << 30) | u, (v << 30) | u | _O])
        id0 = np.concatenate([(v + 1) * N + u, N * N + v * N + u + 1])
        id1 = np.concatenate([v * N + u, N * N + v * N + u])
    else:  # edges give the 4 squares around their midpoint one level down one half each
        k0, id0 = _edge_kids(v[o == 0], u[o == 0], h0[o == 0], h1[o == 0], 0, 2 * n)
        k1, id1 = _edge_kids(v[o == 1], u[o == 1], h0[o == 1], h1[o == 1], 1, 2 * n)
    in1, only1 = merge_halves(h._mark, id0, id1)
    return np.concatenate([k0 | _H0 | (in1.astype(np.int64) << 62), k1[only1] | _H1])


def _edge_kids(v, u, h0, h1, o: int, m: int):
    """(keys, ids) of the squares (level with m per side) split edges of orientation ``o``
    give a half: rows 2v−1, 2v (o = 0) or columns 2u−1, 2u (o = 1), from the half above/left
    (h0) and below/right (h1)."""
    r, c = 2 * v, 2 * u
    if o == 0:
        rows = np.concatenate([r - 1, r - 1, r, r])
        cols = np.concatenate([c, c + 1, c, c + 1])
    else:
        rows = np.concatenate([r, r + 1, r, r + 1])
        cols = np.concatenate([c - 1, c - 1, c, c])
    ok = np.flatnonzero(np.concatenate([h0, h0, h1, h1]))
    rows, cols = rows.take(ok), cols.take(ok)
    return (rows << 30) | cols, rows * m + cols


def _resident(lay, res: Residency, request, t, o, v, u, h0, h1, crit, pix, split):
    """``split`` further restricted to diamonds whose present halves' children have their
    blocks resident; requests the missing ones (priority: the pixel error)."""
    blvl = min(draw_level(lay.J, t + 1), lay.L)
    if res.level_resident(blvl):
        return split
    a = lay.square_side(t // 2)
    span, nb = (lay.M - 1) << blvl, 2 ** (lay.L - blvl)
    ap0, ap1, pq = edge_halves(o, v, u, a) if t % 2 else square_halves(v, u, a)
    for ap, hh in ((ap0, h0), (ap1, h1)):
        bi = np.clip((pq[1] + ap[1]) // 3 // span, 0, nb - 1)
        bj = np.clip((pq[0] + ap[0]) // 3 // span, 0, nb - 1)
        r = res.lookup(blvl, bi, bj)
        miss = crit & hh & ~r
        if request is not None and miss.any():
            request(np.full(int(miss.sum()), blvl), bi[miss], bj[miss], np.minimum(pix[miss], 1e30))
        split = split & (r | ~hh)
    return split


def _leaves(h, view: View, key):
    """The deepest square level: every present half is a patch; spheres for culling only."""
    lay, J = h.dims, h.dims.J
    a, n = lay.square_side(J), 2**J
    _, v, u, _, _ = _unpack(key)
    ids = v * n + u
    zlo, zhi = h.sq_tab[J][3][ids], h.sq_tab[J][4][ids]
    half = math.hypot(a / 2 * h.dx, a / 2 * h.dy)
    dz = (zhi - zlo) / 2
    px, py, pz = view.camera_space((u + 0.5) * a * h.dx, -(v + 0.5) * a * h.dy, (zlo + zhi) / 2)
    return (2 * J, ids, key, view.code(px, py, pz, np.sqrt(half * half + dz * dz)))


def emit(h, parts, head) -> list[np.ndarray]:
    """The 13 Front columns and the codes: ``head`` (the batched top's columns and codes), then
    the kept halves of ``parts`` (square depths, then edge depths; in each depth its half-0
    patches before its half-1 patches), written once into the output arrays."""
    lay = h.dims
    groups = ([], [])
    for t, ids, key, code in parts:
        h0, h1 = (key & _H0) != 0, (key & _H1) != 0
        sel = np.concatenate([np.flatnonzero(h0), np.flatnonzero(h1)])
        if len(sel) == 0:
            continue
        n0 = int(np.count_nonzero(h0))
        tab = h.dg_tab[t // 2] if t % 2 else h.sq_tab[t // 2]
        i = ids.take(sel)
        groups[t % 2].append((t, n0, len(sel), key.take(sel), tab[3].take(i), tab[4].take(i), code.take(sel)))
    m = len(head[0][0])
    total = m + sum(g[2] for grp in groups for g in grp)
    out = [np.empty(total, np.int64) for _ in range(11)] + [np.empty(total), np.empty(total), np.empty(total, np.int8)]
    for o_, c in zip(out, (*head[0], head[1])):
        o_[:m] = c
    for kind, g in enumerate(groups):
        if not g:
            continue
        cnt = np.array([x[2] for x in g])
        ts = np.array([x[0] for x in g])
        t = np.repeat(ts, cnt)
        half = np.concatenate([np.arange(x[2]) >= x[1] for x in g])
        key = np.concatenate([x[3] for x in g])
        o, v, u, _, _ = _unpack(key)
        a = np.repeat(np.left_shift(1, lay.n - ts // 2), cnt)
        lvl = lay.J - ts // 2 - kind
        blvl = np.minimum(lvl, lay.L)
        e = m + int(cnt.sum())
        ax, ay, lx, ly, rx, ry = patch_vertices(kind, o, v, u, half, a)
        shift = np.repeat(blvl + lay.m, cnt)
        cols = (ax, ay, lx, ly, rx, ry, t, np.repeat(blvl, cnt), ((ay + ly + ry) // 3) >> shift, ((ax + lx + rx) // 3) >> shift,
                np.repeat(np.left_shift(1, lvl - blvl), cnt))
        for o_, c in zip(out, cols):
            o_[m:e] = c
        for o_, k in zip(out[11:], (4, 5, 6)):
            np.concatenate([x[k] for x in g], out=o_[m:e])
        m = e
    return out
