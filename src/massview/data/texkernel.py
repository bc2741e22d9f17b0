"""The shading-block descent's compiled kernel (part of :mod:`.lodkernel`, which re-exports it;
the same exactness contract): :func:`shading_blocks` is
:meth:`massview.lod.texlod.ShadingPyramid.blocks` as one loop per level."""

from __future__ import annotations

import numpy as np

from .jit import cached_jit as _jit

__all__ = ["shading_blocks"]


@_jit
def _max(a, b):
    """np.maximum of two floats (NaN propagates)."""
    m = a if a >= b else b
    return m if a == a else a


@_jit
def shading_blocks(lo, hi, offsets, nbs, planes, eye, f, step, limit):
    """texlod.ShadingPyramid.blocks: the quadtree descent from the top block over the boxes
    ``lo``/``hi`` ((N, 3) float64, every level's nb² boxes stacked from ``offsets[level]``, row
    bi·nb + bj). A candidate is kept when its box is not outside any of the six ``planes`` (the
    p-vertex distance summed as cull.boxes_in_frustum's einsum does: ((0 + x·n₀) + y·n₁) + z·n₂,
    then + w), and refined while 2^level > d / f / ``step`` (d: the distance from ``eye`` to the
    box, √((d₀² + d₁²) + d₂²)); the descent stops at level 0, when nothing refines, or past
    ``limit`` blocks. Returns (level, bi, bj, priority 1 / (1 + d)) in the same order."""
    top = len(nbs) - 1
    cap = min(len(lo), 5 * limit + 1)
    olv, obi, obj, opr = np.empty(cap, np.int64), np.empty(cap, np.int64), np.empty(cap, np.int64), np.empty(cap)
    lv, cand, count = top, np.zeros(1, np.int64), 0
    while True:
        nb, base = nbs[lv], offsets[lv]
        finer = np.empty(len(cand), np.int64)
        nf = 0
        for q in range(len(cand)):
            c = cand[q]
            row = base + c
            inside = True
            for p in range(6):
                acc = 0.0
                for k in range(3):
                    acc += (hi[row, k] if planes[p, k] >= 0 else lo[row, k]) * planes[p, k]
                inside &= (acc + 0.0) + planes[p, 3] >= 0
            if not inside:
                continue
            g0 = _max(_max(lo[row, 0] - eye[0], 0.0), eye[0] - hi[row, 0])
            g1 = _max(_max(lo[row, 1] - eye[1], 0.0), eye[1] - hi[row, 1])
            g2 = _max(_max(lo[row, 2] - eye[2], 0.0), eye[2] - hi[row, 2])
            d = np.sqrt((g0 * g0 + g1 * g1) + g2 * g2)
            olv[count], obi[count], obj[count], opr[count] = lv, c // nb, c % nb, 1.0 / (d + 1.0)
            count += 1
            if 2.0 ** lv > d / f / step:
                finer[nf] = c
                nf += 1
        if lv == 0 or nf == 0 or count > limit:
            break
        kids = np.empty(4 * nf, np.int64)  # texlod._children's order: every (2i, 2j), then (2i, 2j + 1), ...
        for q in range(nf):
            b = (finer[q] // nb) * (4 * nb) + 2 * (finer[q] % nb)
            kids[q], kids[nf + q], kids[2 * nf + q], kids[3 * nf + q] = b, b + 1, b + 2 * nb, b + 2 * nb + 1
        cand = kids
        lv -= 1
    return olv[:count], obi[:count], obj[:count], opr[:count]
