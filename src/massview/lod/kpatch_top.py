"""The top of the K-patch walk as one batch (see :mod:`massview.lod.kpatch_cut`).

The first bintree depths hold few diamonds (1, 4, 4, 16, 16, 64 ...), so walking them one
depth at a time costs a hundred numpy calls per depth for a handful of elements. Here every
diamond of depths 0 … T−1 (all square and edge levels below ``levels``) is laid out once, at
ingest of the hierarchy, in one flat batch with its static attributes — sphere, error, the
blocks each half's children need, its parents' positions in the batch, and the patch record
each half would be. A frame then evaluates the split test on the whole batch at once and runs
the top-down rule (split ⇔ critical ∧ children resident ∧ every existing half present) with a
few array operations per depth; what it keeps and what splits at depth T−1 are exactly the
level-by-level walk's.

How deep the batch goes is a trade (``TOP_LEVELS`` in :mod:`massview.lod.kpatch`): a batched
diamond costs a fraction of a walked one (no unpacking, children or pairing), but every one is
tested each frame. With 7 levels (depths 0–13, 16.6 k diamonds) the demo's orbit at 20 k
front patches has 83 % of depth 12 and 63 % of depth 13 present; against the stage before this
change, measured in one process under load, the whole LOD stage ran 1.35× faster with 7 levels
and 1.24× with 6 at 20 k (1.24× and 1.18× at 5 k, 1.24× both at 80 k).
"""

from __future__ import annotations

import numpy as np

from .kpatch_cut import Residency, View, draw_level, edge_exists, edge_halves, patch_vertices, square_halves

__all__ = ["TopBatch"]


class TopBatch:
    """Depths 0 … 2·levels − 1 of hierarchy ``h`` as one batch (built once per hierarchy)."""

    def __init__(self, h, levels: int):
        lay = h.lay
        self.depths = 2 * levels
        cols = {k: [] for k in ("x", "y", "cz", "r", "err", "ex0", "ex1", "par0", "par1", "o", "v", "u", "t")}
        self.offsets = [0]
        for t in range(self.depths):
            j, edge = t // 2, t % 2 == 1
            a, n = lay.square_side(j), 2**j
            if edge:
                o, v, u = (g.ravel() for g in np.meshgrid(np.arange(2), np.arange(n + 1), np.arange(n + 1), indexing="ij"))
                keep = np.where(o == 0, u < n, v < n)  # edges inside the square lattice
                o, v, u = o[keep], v[keep], u[keep]
                tab, ids = h.dg_tab[j], (o * (n + 1) + v) * (n + 1) + u
                ex0, ex1 = edge_exists(o, v, u, n)
                x, y = (u + 0.5 * (1 - o)) * a * h.dx, -((v + 0.5 * o) * a) * h.dy
            else:
                v, u = (g.ravel() for g in np.meshgrid(np.arange(n), np.arange(n), indexing="ij"))
                o = np.zeros(len(v), np.int64)
                tab, ids = h.sq_tab[j], v * n + u
                ex0 = ex1 = np.ones(len(v), bool)
                x, y = (u + 0.5) * a * h.dx, -((v + 0.5) * a) * h.dy
            par0, par1 = self._parents(t, o, v, u, n, ex0, ex1)
            for k, val in (("x", x), ("y", y), ("cz", tab[0][ids]), ("r", tab[1][ids]), ("err", tab[2][ids]), ("ex0", ex0),
                           ("ex1", ex1), ("par0", par0), ("par1", par1), ("o", o), ("v", v), ("u", u), ("t", np.full(len(v), t))):
                cols[k].append(val)
            self.offsets.append(self.offsets[-1] + len(v))
        for k, val in cols.items():
            setattr(self, k, np.concatenate(val))
        self.size = self.offsets[-1]
        self.xyz = np.stack([self.x, self.y, self.cz])
        self.p0, self.p1 = (np.where(p == -2, self.size + 1, np.where(p < 0, self.size, p)) for p in (self.par0, self.par1))
        self._blocks(h)
        self._records(h)
        self.no0, self.no1 = ~self.ex0, ~self.ex1
        self.nblocks = nb = sum(4 ** (lay.L - lv) for lv in range(lay.levels))  # the agreed residency's flat length
        self.bid_or_true = np.stack([np.where(self.ex0, self.bid[0], nb), np.where(self.ex1, self.bid[1], nb)])
        self.p01 = np.stack([self.p0, self.p1])
        self._levels = [(slice(a, b), np.stack([self.p0[a:b], self.p1[a:b]]), np.stack([self.ex0[a:b], self.ex1[a:b]]))
                        for a, b in zip(self.offsets[:-1], self.offsets[1:])]
        last = slice(self.offsets[-2], self.offsets[-1])  # the deepest batched depth (edges): the walk's seeds
        self._last = (last, (self.v[last] << 30) | self.u[last] | (self.o[last] << 60), self.o[last])
        del self.x, self.y, self.cz, self.par0, self.par1, self.t, self.o, self.v, self.u  # build-time only

    def _parents(self, t, o, v, u, n, ex0, ex1):
        """Batch positions of each diamond's half-0 and half-1 parents; ``size`` (a False
        sentinel) where the half does not exist, ``size + 1`` (True) for the root."""
        if t == 0:
            return np.array([-2]), np.array([-2])  # root: patched to size + 1 below
        start = self.offsets[-2]  # first diamond of depth t − 1
        if t % 2 == 0:  # square (v, u) at level j: parents are level j−1 edges
            m = n // 2
            N = m + 1
            def pos(oo, vv, uu):  # position of edge (oo, vv, uu) in depth t−1's list (u < m for o=0, v < m for o=1)
                return start + np.where(oo == 0, vv * m + uu, N * m + vv * N + uu)
            return pos(np.zeros_like(v), v // 2 + v % 2, u // 2), pos(np.ones_like(v), v // 2, u // 2 + u % 2)
        # edge (o, v, u) at level j: parents are the squares on either side at level j
        p0 = start + np.where(o == 0, (v - 1) * n + u, v * n + u - 1)
        p1 = start + v * n + u
        return np.where(ex0, p0, -1), np.where(ex1, p1, -1)

    def _blocks(self, h) -> None:
        """Flat block ids (agreed-residency index) of each half's children, and their keys."""
        lay = h.lay
        nb = [2 ** (lay.L - lv) for lv in range(lay.levels)]
        off = np.cumsum([0] + [b * b for b in nb])
        self.bid = [np.zeros(self.size, np.int64) for _ in range(2)]
        self.bkey = [np.zeros((3, self.size), np.int32) for _ in range(2)]
        for t in range(self.depths):
            s = slice(self.offsets[t], self.offsets[t + 1])
            a = lay.square_side(t // 2)
            blvl = min(draw_level(lay.J, t + 1), lay.L)
            span = (lay.M - 1) << blvl
            o, v, u = self.o[s], self.v[s], self.u[s]
            ap0, ap1, pq = edge_halves(o, v, u, a) if t % 2 else square_halves(v, u, a)
            for k, ap in enumerate((ap0, ap1)):
                bi = np.clip((pq[1] + ap[1]) // 3 // span, 0, nb[blvl] - 1)
                bj = np.clip((pq[0] + ap[0]) // 3 // span, 0, nb[blvl] - 1)
                self.bid[k][s] = off[blvl] + bi * nb[blvl] + bj
                self.bkey[k][0, s], self.bkey[k][1, s], self.bkey[k][2, s] = blvl, bi, bj

    def _records(self, h) -> None:
        """The patch record (13 Front columns) each half would be, per half."""
        lay = h.lay
        self.rec = []
        for k in (0, 1):
            cols = [[] for _ in range(13)]
            for t in range(self.depths):
                s = slice(self.offsets[t], self.offsets[t + 1])
                a = lay.square_side(t // 2)
                o, v, u = self.o[s], self.v[s], self.u[s]
                ax, ay, lx, ly, rx, ry = patch_vertices(t, o, v, u, np.full(len(v), bool(k)), a)
                lvl = draw_level(lay.J, t)
                blvl = min(lvl, lay.L)
                span = (lay.M - 1) << blvl
                n = 2 ** (t // 2)
                tab = h.dg_tab[t // 2] if t % 2 else h.sq_tab[t // 2]
                ids = (o * (n + 1) + v) * (n + 1) + u if t % 2 else v * n + u
                cx, cy = (ax + lx + rx) // 3, (ay + ly + ry) // 3
                m = len(v)
                for c, val in zip(cols, (ax, ay, lx, ly, rx, ry, np.full(m, t), np.full(m, blvl), cy // span, cx // span,
                                         np.full(m, 2 ** (lvl - blvl)), tab[3][ids], tab[4][ids])):
                    c.append(val)
            self.rec.append([np.concatenate(c) for c in cols])
        rec = np.stack([np.concatenate([self.rec[0][i], self.rec[1][i]]) for i in range(11)])
        self.rec_int = rec.astype(np.int32 if rec.max() < 2**31 else np.int64)  # vertices ≤ 2^n: int32 halves the table
        self.rec_rows = np.ascontiguousarray(self.rec_int.T)  # one record per row, for the compiled gather
        self.rec_flt = np.stack([np.concatenate([self.rec[0][i], self.rec[1][i]]) for i in (11, 12)])
        # flat block id of each half record (Front.block_ids: offset[level] + bi·2^(L − level) + bj)
        lay = h.lay
        self.block_offsets = np.cumsum([0] + [4 ** (lay.L - lv) for lv in range(lay.levels)])
        lvl, bi, bj = (rec[i].astype(np.int64) for i in (7, 8, 9))
        self.rec_bid = self.block_offsets.take(lvl) + (bi << (lay.L - lvl)) + bj
        del self.rec

    def walk(self, view: View, res: Residency, request):
        """Decide the batch for one view: returns (split flags, half-0 present, half-1 present,
        culling codes, deferred splits)."""
        crit, pix, code = view.test(self.xyz, self.r, self.err)
        ok = crit
        r0 = r1 = None
        if not res.all:
            r0, r1 = self._resident(res)  # a half that does not exist reads True
            ok = crit & r0
            ok &= r1
        if view.kernel is not None:  # the same rule in one compiled pass
            S, H0, H1 = np.empty(self.size + 2, bool), np.empty(self.size, bool), np.empty(self.size, bool)
            deferred = view.kernel.top_rule(ok, crit, self.p0, self.p1, self.ex0, self.ex1, S, H0, H1)
            split = S[:self.size]
            self._request(request, r0, r1, ok, crit, pix, H0, H1)
            return split, H0, H1, code, deferred
        S = np.zeros(self.size + 2, bool)
        S[self.size + 1] = True  # the root's halves are always present
        for s, q, e in self._levels:
            bad = S.take(q)
            bad ^= e  # a half differs from what exists: absent where it exists, or the reverse
            np.greater(ok[s], bad[0] | bad[1], out=S[s])  # ok and no half is wrong
        H0, H1 = S.take(self.p01)
        split = S[:self.size]
        self._request(request, r0, r1, ok, crit, pix, H0, H1)
        wait = crit & ~split
        deferred = int(np.count_nonzero(wait & H0)) + int(np.count_nonzero(wait & H1))
        return split, H0, H1, code, deferred

    def _request(self, request, r0, r1, ok, crit, pix, H0, H1) -> None:
        """Request the blocks of present halves of critical diamonds that are missing."""
        if r0 is not None and request is not None and not np.array_equal(ok, crit):  # some critical half's blocks missing
            for rk, Hk, key in ((r0, H0, self.bkey[0]), (r1, H1, self.bkey[1])):
                miss = crit & Hk & ~rk
                if miss.any():
                    request(key[0][miss], key[1][miss], key[2][miss], np.minimum(pix[miss], 1e30))

    def kept(self, split, H0, H1):
        """Positions in the (2·size) half records (:attr:`rec_int`, :attr:`rec_flt`) of the
        patches the batch keeps, half-0 patches first."""
        return np.concatenate([np.flatnonzero(H0 > split), self.size + np.flatnonzero(H1 > split)])

    def kept_and_seeds(self, kernel, split, H0, H1):
        """(:meth:`kept`, the keys of :meth:`seeds`) by the compiled ``kernel``."""
        last, key, _ = self._last
        return kernel.top_kept_seeds(split, H0, H1, last.start, key)

    def seeds(self, split, H0, H1):
        """(keys, o, present halves) of the diamonds of the deepest batched depth that split."""
        s, key, o = self._last
        i = np.flatnonzero(split[s])
        hb = H0[s].take(i) + 2 * H1[s].take(i).astype(np.int64)
        return key.take(i) | (hb << 61), o.take(i), hb

    def _resident(self, res: Residency):
        """Per half: its children's blocks are agreed resident, or the half does not exist."""
        if res.fn is not None or len(res.flat) != self.nblocks:
            if res.fn is None:
                return res.flat[self.bid[0]] | self.no0, res.flat[self.bid[1]] | self.no1
            return tuple(np.asarray(res.fn(k[0], k[1], k[2]), bool) | no for k, no in zip(self.bkey, (self.no0, self.no1)))
        flat = np.empty(len(res.flat) + 1, bool)  # + a True sentinel that absent halves read
        flat[:-1] = res.flat
        flat[-1] = True
        both = flat.take(self.bid_or_true)
        return both[0], both[1]
