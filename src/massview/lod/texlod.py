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

__all__ = ["shading_blocks"]


def shading_blocks(minmax: list[np.ndarray], M: int, spacing, zmap, camera: Camera, limit: int = 4096):
    """(level, i, j, priority) arrays of the blocks whose shading a view samples. ``minmax[l]``
    is the (nb, nb, 2) height range per block, ``zmap`` maps heights to world z.

    Per pyramid level a handful of whole-array operations: the boxes are written into two
    (n, 3) arrays (no stacking), the distance to the eye is the norm's own sum
    √((d₀² + d₁²) + d₂²) taken over every box and then selected, so every value — and with it
    every decision — is the one the earlier form computed."""
    dx, dy = (float(v) for v in spacing)
    f = camera.height / 2 / math.tan(math.radians(camera.fovy) / 2)
    planes = frustum_planes(camera)
    eye = np.asarray(camera.position, np.float64)
    lv = len(minmax) - 1
    bi, bj = np.zeros(1, np.int64), np.zeros(1, np.int64)
    out, count = [], 0
    while True:
        span = (M - 1) << lv
        mm = minmax[lv][bi, bj]
        n = len(bi)
        lo, hi = np.empty((n, 3)), np.empty((n, 3))
        x0, y0 = bj * span, bi * span
        np.multiply(x0, dx, out=lo[:, 0])  # bj·span·dx
        np.multiply(x0 + span, dx, out=hi[:, 0])  # (bj + 1)·span·dx: the same integer, then the same product
        np.multiply(-(y0 + span), dy, out=lo[:, 1])  # −(bi + 1)·span·dy
        np.multiply(-y0, dy, out=hi[:, 1])  # −bi·span·dy
        lo[:, 2], hi[:, 2] = zmap(mm[:, 0]), zmap(mm[:, 1])
        vis = np.flatnonzero(boxes_in_frustum(lo, hi, planes))
        g = lo - eye  # the nearest point's offset: max(lo − eye, 0, eye − hi) per axis
        np.maximum(g, 0, out=g)
        np.maximum(g, np.subtract(eye, hi), out=g)
        g *= g
        d = g[:, 0] + g[:, 1]
        d += g[:, 2]
        d = np.sqrt(d.take(vis))
        bi, bj = bi.take(vis), bj.take(vis)
        out.append((lv, bi, bj, d))
        count += len(bi)
        finer = np.flatnonzero(2.0**lv > d / f / min(dx, dy))  # finest samples per pixel at the nearest point
        if lv == 0 or not len(finer) or count > limit:
            break
        c = np.empty((4, len(finer)), np.int64)
        np.multiply(bi.take(finer), 2, out=c[0])
        c[1] = c[0]
        np.add(c[0], 1, out=c[2])
        c[3] = c[2]
        bi = c.ravel()
        c = np.empty((4, len(finer)), np.int64)
        np.multiply(bj.take(finer), 2, out=c[0])
        np.add(c[0], 1, out=c[1])
        c[2], c[3] = c[0], c[1]
        bj = c.ravel()
        lv -= 1
    total = sum(len(o[1]) for o in out)
    lvl, pri = np.empty(total, np.int64), np.empty(total)
    e = 0
    for o in out:
        b, e = e, e + len(o[1])
        lvl[b:e] = o[0]
        np.add(o[3], 1.0, out=pri[b:e])
    np.divide(1.0, pri, out=pri)
    return lvl, np.concatenate([o[1] for o in out]), np.concatenate([o[2] for o in out]), pri
