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
from .cull import boxes_in_frustum

__all__ = ["shading_blocks"]


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
