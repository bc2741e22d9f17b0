"""Compiled kernels that write the K-patch Front's records (part of :mod:`.lodkernel`, which
re-exports them; the same exactness contract): the batched top's kept halves and seeds, the
top's records gathered, and the walked patches' integer columns and block ids."""

from __future__ import annotations

import numpy as np

from .jit import cached_jit as _jit

__all__ = ["head_records", "patch_records", "top_kept_seeds"]


@_jit
def head_records(rec_rows, rec_flt, rec_bid, head_code, head, cols, zs, code, bid):
    """The batched top's kept halves: column k of records ``head`` (``rec_rows``: (2·size, 11),
    one record per row) into ``cols[k, :m]``,
    ``zs[k, :m]``, their block ids and codes (``head_code`` indexed modulo its length: half
    record size + i is diamond i's half 1), m = len(head)."""
    nc = len(head_code)
    for i in range(len(head)):
        h = head[i]
        for k in range(rec_rows.shape[1]):
            cols[k, i] = rec_rows[h, k]
        zs[0, i] = rec_flt[0, h]
        zs[1, i] = rec_flt[1, h]
        bid[i] = rec_bid[h]
        code[i] = head_code[h % nc]


@_jit
def patch_records(key, spans, verts, rec, m, cols, bid):
    """The integer Front columns and flat block ids of the walked patches ``key`` (packed
    (half 1 ≪ 62 | o ≪ 60 | v ≪ 30 | u), written from position ``m`` on) — kpatch_walk's
    _patch_records and block ids, one depth span at a time. ``spans`` (k, 9) int64 rows: begin,
    end, half-0 count, table row 16·t, side log2 a, block shift, the level shift L − block level,
    the block level's flat offset, and t; ``verts``/``rec``: the per-(depth, parity, half) tables."""
    M = (1 << 30) - 1
    for s in range(spans.shape[0]):
        b, e, n0, r0, sa, sh, ls, boff = spans[s, 0], spans[s, 1], spans[s, 2], spans[s, 3], spans[s, 4], spans[s, 5], spans[s, 6], spans[s, 7]
        c6, c7, c10 = rec[0, r0], rec[1, r0], rec[4, r0]
        for i in range(b, e):
            k = key[i]
            row = r0 + (4 if i - b >= n0 else 0)
            row |= (k & 1) | ((k >> 29) & 2) | ((k >> 57) & 8)
            x0 = (k & M) << sa
            y0 = ((k >> 30) & M) << sa
            j = m + i
            cols[0, j] = verts[0, row] + x0
            cols[1, j] = verts[1, row] + y0
            cols[2, j] = verts[2, row] + x0
            cols[3, j] = verts[3, row] + y0
            cols[4, j] = verts[4, row] + x0
            cols[5, j] = verts[5, row] + y0
            cols[6, j] = c6
            cols[7, j] = c7
            bi = (rec[2, row] + y0) >> sh
            bj = (rec[3, row] + x0) >> sh
            cols[8, j] = bi
            cols[9, j] = bj
            cols[10, j] = c10
            bid[j] = (bi << ls) + bj + boff


@_jit
def top_kept_seeds(split, H0, H1, first, keys):
    """kpatch_top.TopBatch.kept and seeds: positions in the (2·size) half records of the kept
    halves (half 0's, then size + half 1's), and the keys (with their present halves in bits
    61–62) of the deepest batched depth's diamonds that split (``first``: its first position,
    ``keys``: its packed keys)."""
    size = len(split)
    head = np.empty(2 * size, np.int64)
    c = 0
    for i in range(size):  # written always, kept by advancing (no branch to mispredict)
        head[c] = i
        c += H0[i] & (not split[i])
    for i in range(size):
        head[c] = size + i
        c += H1[i] & (not split[i])
    seeds = np.empty(len(keys), np.int64)
    s = 0
    for q in range(len(keys)):
        i = first + q
        seeds[s] = keys[q] | ((np.int64(H0[i]) + 2 * np.int64(H1[i])) << 61)
        s += split[i]
    return head[:c], seeds[:s]
