"""Pixel kernels of the sub-image codec and depth compositing, compiled with numba.

Each kernel is one pass over its pixels with no temporaries: it reads the source arrays and
writes straight into a preallocated destination (the wire buffer when encoding, the
accumulating band when combining, the display tile when pasting). Images are handled as 2-D
views — depth ``(h, w) float32`` and color as ``(h, w) uint32`` (one RGBA8 pixel per word) —
with any row stride, so row bands and tile crops are never copied first.

A received sub-image is its run list (``uint32``, alternating background/active starting with
background, over the row-major pixels of its viewport; see :mod:`.codec`) and the color and
depth of its active pixels only; the kernels walk the active runs directly. The combine rule is
:func:`.composite.combine`'s, bit for bit: a part behind the accumulator (a higher rank) wins
where ``d < acc``; a part in front (a lower rank) wins unless ``acc < d``. Background pixels
(depth exactly 1.0, background color, the :class:`~massview.core.image.Image` contract) are
skipped: against any depth in [0, 1] they change nothing.

Why numba (``massview bench kernels`` is the measurement, figures in the README): the
vectorized in-place numpy version of these loops needs index arrays and boolean masks the
size of the image, and was 3–8× slower on 1280×1024 frames here; numexpr evaluates
element-wise expressions only (no runs, no gather/scatter). numba costs ~0.2 s of import and,
with ``cache=True``, ~0.1 s to load the compiled kernels on later runs (the first run on a
machine compiles them once, a few seconds, into ``__pycache__`` or ``NUMBA_CACHE_DIR``).
Kernels release the GIL (``nogil``) so a communication thread can run beside them.
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["count_runs", "fill_runs", "merge_runs", "paste_runs"]


@njit(cache=True, nogil=True)
def count_runs(depth):
    """(number of runs, number of active pixels) of a 2-D float32 depth view. Branch-free
    sums over each row, so that the loop vectorizes."""
    h, w = depth.shape
    one = np.float32(1.0)
    changes, nact, prev = 0, 0, False
    for y in range(h):
        row = depth[y]
        if w:
            changes += (row[0] != one) != prev
        for x in range(1, w):
            changes += (row[x] != one) != (row[x - 1] != one)
        for x in range(w):
            nact += row[x] != one
        if w:
            prev = row[w - 1] != one
    return changes + 1, nact


@njit(cache=True, nogil=True)
def fill_runs(depth, color, runs, out_color, out_depth):
    """Write the runs and the active pixels' color (uint32) and depth of a 2-D view into the
    preallocated ``runs``/``out_color``/``out_depth`` (sized by :func:`count_runs`)."""
    h, w = depth.shape
    r, k, length, prev = 0, 0, 0, False
    for y in range(h):
        for x in range(w):
            d = depth[y, x]
            a = d != np.float32(1.0)
            if a != prev:
                runs[r] = length
                r += 1
                length = 0
                prev = a
            length += 1
            if a:
                out_color[k] = color[y, x]
                out_depth[k] = d
                k += 1
    runs[r] = length


@njit(cache=True, nogil=True)
def merge_runs(runs, c_in, d_in, acc_color, acc_depth, front):
    """Depth-combine a run-coded part into the 2-D ``acc_*`` views in place. ``front``: the
    part comes from a lower rank (it wins ties)."""
    w = acc_depth.shape[1]
    p, k = 0, 0
    for r in range(runs.size):
        n = np.int64(runs[r])
        if r & 1:
            y, x = p // w, p % w
            for _ in range(n):
                d = d_in[k]
                a = acc_depth[y, x]
                if (not (a < d)) if front else (d < a):
                    acc_depth[y, x] = d
                    acc_color[y, x] = c_in[k]
                k += 1
                x += 1
                if x == w:
                    x = 0
                    y += 1
        p += n


@njit(cache=True, nogil=True)
def paste_runs(runs, c_in, d_in, out_color, out_depth):
    """Copy a run-coded part's active pixels into the 2-D ``out_*`` views (background pixels
    are left as they are: the destination starts as background)."""
    w = out_depth.shape[1]
    p, k = 0, 0
    for r in range(runs.size):
        n = np.int64(runs[r])
        if r & 1:
            y, x = p // w, p % w
            for _ in range(n):
                out_depth[y, x] = d_in[k]
                out_color[y, x] = c_in[k]
                k += 1
                x += 1
                if x == w:
                    x = 0
                    y += 1
        p += n
