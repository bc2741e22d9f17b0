"""Which shading-pyramid blocks a view needs (texture LOD, decoupled from the geometric LOD).

The fragment stage reads the shading maps at the pyramid level whose sample spacing matches
the pixel footprint (RASTeR's distance-dependent texture mip level, Goswami et al. 2010 §3).
A quadtree descent over the M-block pyramid finds the blocks: block (l, i, j) inside the
frustum is refined while its sample spacing 2^l (finest samples) exceeds the smallest pixel
footprint over its box, f·spacing / distance. Every rank computes the same set from the camera.
"""

from __future__ import annotations

import math

import numpy as np

from ..core.camera import Camera
from .cull import boxes_in_frustum, frustum_planes
from .kernels import lod_kernels

__all__ = ["shading_blocks", "ShadingPyramid"]


def shading_blocks(minmax: list[np.ndarray], M: int, spacing, zmap, camera: Camera, limit: int = 4096):
    """(level, i, j, priority) arrays of the blocks whose shading a view samples. ``minmax[l]``
    is the (nb, nb, 2) height range per block, ``zmap`` maps heights to world z."""
    dx, dy = (float(v) for v in spacing)
    f = camera.height / 2 / math.tan(math.radians(camera.fovy) / 2)
    planes = camera.frustum_planes()
    eye = np.asarray(camera.position)
    top = len(minmax) - 1
    lv, bi, bj = top, np.zeros(1, np.int64), np.zeros(1, np.int64)
    out = []
    while True:
        span = (M - 1) << lv
        mm = minmax[lv][bi, bj]
        lo = np.stack([bj * span * dx, -(bi + 1) * span * dy, zmap(mm[:, 0])], 1)
        hi = np.stack([(bj + 1) * span * dx, -bi * span * dy, zmap(mm[:, 1])], 1)
        vis = boxes_in_frustum(lo, hi, planes)
        bi, bj, lo, hi = bi[vis], bj[vis], lo[vis], hi[vis]
        d = np.linalg.norm(np.maximum(np.maximum(lo - eye, 0), eye - hi), axis=1)
        footprint = d / f / min(dx, dy)  # finest samples per pixel at the nearest point
        out.append((np.full(len(bi), lv), bi, bj, 1.0 / (1.0 + d)))
        finer = (2.0**lv > footprint)
        if lv == 0 or not finer.any() or sum(len(o[1]) for o in out) > limit:
            break
        bi, bj = bi[finer], bj[finer]
        bi = np.concatenate([2 * bi + a for a in (0, 0, 1, 1)])
        bj = np.concatenate([2 * bj + b for b in (0, 1, 0, 1)])
        lv -= 1
    return tuple(np.concatenate([o[k] for o in out]) for k in range(4))


class ShadingPyramid:
    """:func:`shading_blocks` for one pyramid and height map, with the per-frame work cut to a
    few whole-array operations per level: every block's box is computed once here (the same
    float64 operations on the same integers, so the same values), a level's candidates are
    gathered from it, and the distance to the eye is the norm's own sum √((d₀² + d₁²) + d₂²).
    Every value — and with it every decision and priority — is the function's (issue 20;
    tests/test_lod_stage.py compares the two)."""

    def __init__(self, minmax: list[np.ndarray], M: int, spacing, zmap):
        self.dx, self.dy = (float(v) for v in spacing)
        self.boxes, self.nb = [], []  # per level: (lo, hi), (nb², 3) float64 each, row bi·nb + bj
        for lv, mm in enumerate(minmax):
            nb, span = mm.shape[0], (M - 1) << lv
            self.nb.append(nb)
            bi, bj = (g.ravel() for g in np.meshgrid(np.arange(nb, dtype=np.int64), np.arange(nb, dtype=np.int64), indexing="ij"))
            lo = np.stack([bj * span * self.dx, -(bi + 1) * span * self.dy, zmap(mm[bi, bj, 0])], 1)
            hi = np.stack([(bj + 1) * span * self.dx, -bi * span * self.dy, zmap(mm[bi, bj, 1])], 1)
            self.boxes.append((lo, hi))
        # ... and every level's stacked, for the compiled descent (massview.data.lodkernel.shading_blocks)
        self._stacked = (np.concatenate([b[0] for b in self.boxes]), np.concatenate([b[1] for b in self.boxes]),
                         np.cumsum([0] + [n * n for n in self.nb])[:-1].astype(np.int64), np.asarray(self.nb, np.int64))

    def blocks(self, camera: Camera, limit: int = 4096):
        """(level, i, j, priority) arrays: exactly :func:`shading_blocks`'s (by the compiled
        descent once :mod:`.kernels` has it: the same arrays)."""
        f = camera.height / 2 / math.tan(math.radians(camera.fovy) / 2)
        planes = frustum_planes(camera)
        eye = np.asarray(camera.position, np.float64)
        kernel = lod_kernels()
        if kernel is not None:
            return kernel.shading_blocks(*self._stacked, planes, eye, f, min(self.dx, self.dy), limit)
        lv = len(self.boxes) - 1
        cand = np.zeros(1, np.int64)  # flat index bi·nb + bj within the level
        out, count = [], 0
        while True:
            lo, hi = (b.take(cand, axis=0) for b in self.boxes[lv])
            vis = np.flatnonzero(boxes_in_frustum(lo, hi, planes))
            g = lo - eye  # per axis max(max(lo − eye, 0), eye − hi), as the function's
            np.maximum(g, 0, out=g)
            np.maximum(g, np.subtract(eye, hi), out=g)
            g *= g
            d = g[:, 0] + g[:, 1]
            d += g[:, 2]
            d = np.sqrt(d.take(vis))
            cand = cand.take(vis)
            out.append((lv, cand, d))
            count += len(cand)
            finer = np.flatnonzero(2.0**lv > d / f / min(self.dx, self.dy))  # the footprint test, same operations
            if lv == 0 or not len(finer) or count > limit:
                break
            cand = self._children(cand.take(finer), self.nb[lv])
            lv -= 1
        return self._assemble(out, count)

    @staticmethod
    def _children(p: np.ndarray, nb: int) -> np.ndarray:
        """Flat indices one level down of the 4 children of blocks ``p`` (nb per side), in
        :func:`shading_blocks`' order: all (2i, 2j), then (2i, 2j + 1), (2i + 1, 2j), (2i + 1, 2j + 1)."""
        base = (p // nb) * (4 * nb) + 2 * (p % nb)  # child (2bi + a, 2bj + b) at 2nb per side
        c = np.empty((4, len(p)), np.int64)
        c[0] = base
        np.add(base, 1, out=c[1])
        np.add(base, 2 * nb, out=c[2])
        np.add(c[2], 1, out=c[3])
        return c.ravel()

    def _assemble(self, out, total: int):
        """(level, i, j, priority) arrays from per-level (level, flat indices, distances)."""
        lvl, bi, bj, pri = np.empty(total, np.int64), np.empty(total, np.int64), np.empty(total, np.int64), np.empty(total)
        e = 0
        for lv, c, d in out:
            b, e = e, e + len(c)
            nb = self.nb[lv]
            lvl[b:e] = lv
            np.floor_divide(c, nb, out=bi[b:e])
            np.remainder(c, nb, out=bj[b:e])
            np.add(d, 1.0, out=pri[b:e])  # 1 / (1 + d), as shading_blocks
        np.divide(1.0, pri, out=pri)
        return lvl, bi, bj, pri
