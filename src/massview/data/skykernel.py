"""The sky painter's compiled kernel (numba, cached on disk, GIL released).

:func:`paint` does in one pass over the depths what :func:`massview.render.colormaps.paint_sky`
does with numpy: at every background pixel (depth ≥ 1) the sine of the view ray's elevation
from the separable row and column terms, then the smoothstep between horizon and zenith and
the rounding to 8 bits. It performs exactly the float64 operations of the numpy path (same
operands, same order, no fused multiply-add, no fast-math), so its bytes are the same —
tests/test_sky_paint.py checks both against the whole-image reference. The numpy path builds
index arrays and float64 temporaries and makes several passes (9–12 ms a 1280×1024 frame with
~40 % sky, measured idle); this one evaluates each row with sky once, vectorised, and writes only its sky pixels: 2.0 ms, idle (issue 20: the ``finish`` stage of
``massview bench frame``).

It lives in ``data/`` because numba is that layer's dependency (DESIGN.md: each heavy dependency
lives in one layer; the ingest kernels are numba too). Imported only by
:func:`massview.render.colormaps.load_sky_kernel`, which loads it on a thread
so that no frame waits for numba (compiled once per machine and cached beside this file, or in
``NUMBA_CACHE_DIR``; where no cache location is writable, once per process).
"""

from __future__ import annotations

import math

import numpy as np

from .jit import cached_jit

__all__ = ["paint"]


@cached_jit
def paint(color, depth, a_row, a_col, n_row, n_col, r22, hor, zen):
    """Paint ``color`` ((h, w, 4) uint8, in place) with the sky at the pixels where ``depth``
    ((h, w) float32) is ≥ 1; the terms are :func:`massview.render.colormaps.paint_sky`'s.
    Returns the number of pixels painted. A row with any sky is evaluated densely without
    branches (the loop vectorises: sqrt and division are exact per lane), then written at its
    sky pixels; rows without sky cost one scan of their depths."""
    h, w = depth.shape
    s_row = np.empty(w)
    d0, d1, d2 = zen[0] - hor[0], zen[1] - hor[1], zen[2] - hor[2]
    h0, h1, h2 = hor[0], hor[1], hor[2]
    painted = 0
    for r in range(h):
        dep = depth[r]
        sky = 0
        for c in range(w):
            sky += dep[c] >= 1.0
        if sky == 0:
            continue
        painted += sky
        ar, nr = a_row[r], n_row[r]
        for c in range(w):  # vectorised (numpy's error model: no zero-division branch)
            dz = ar + a_col[c]
            dz -= r22
            norm = n_col[c] + nr
            norm += 1.0
            e = dz / math.sqrt(norm)
            e += 0.05
            e /= 0.65
            e = 0.0 if e < 0.0 else e  # np.clip(e, 0, 1)
            e = 1.0 if e > 1.0 else e
            s_row[c] = (e * e) * (3.0 - 2.0 * e)
        out = color[r]
        for c in range(w):
            if dep[c] >= 1.0:
                s = s_row[c]
                out[c, 0] = np.uint8((s * d0 + h0) * 255.0 + 0.5)
                out[c, 1] = np.uint8((s * d1 + h1) * 255.0 + 0.5)
                out[c, 2] = np.uint8((s * d2 + h2) * 255.0 + 0.5)
                out[c, 3] = 255
    return painted
