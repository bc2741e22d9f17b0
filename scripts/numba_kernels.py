"""The compositing kernels compiled with numba: the alternative measured by compare_kernels.py
(not used by massview; see massview.parallel.kernels for why).

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
    preallocated ``runs``/``out_color``/``out_depth`` (sized by :func:`count_runs`). Each run
    is found by a tight scan that copies its active pixels as it goes."""
    h, w = depth.shape
    one = np.float32(1.0)
    r, k, length, active = 0, 0, 0, False
    for y in range(h):
        x = 0
        while x < w:
            x0 = x
            if active:
                while x < w and depth[y, x] != one:
                    out_depth[k] = depth[y, x]
                    out_color[k] = color[y, x]
                    k += 1
                    x += 1
            else:
                while x < w and depth[y, x] == one:
                    x += 1
            length += x - x0
            if x < w:  # the run ends inside this row
                runs[r] = length
                r += 1
                length = 0
                active = not active
    runs[r] = length


@njit(cache=True, nogil=True, inline="always")
def _merge_segment(d_in, c_in, k, acc_depth, acc_color, y, x, n, front):
    if front:  # the part is from a lower rank: it wins unless the accumulator is nearer
        for i in range(n):
            d, a = d_in[k + i], acc_depth[y, x + i]
            if not (a < d):
                acc_depth[y, x + i] = d
                acc_color[y, x + i] = c_in[k + i]
    else:
        for i in range(n):
            if d_in[k + i] < acc_depth[y, x + i]:
                acc_depth[y, x + i] = d_in[k + i]
                acc_color[y, x + i] = c_in[k + i]


@njit(cache=True, nogil=True)
def merge_runs(runs, c_in, d_in, acc_color, acc_depth, front):
    """Depth-combine a run-coded part into the 2-D ``acc_*`` views in place, one row segment
    of an active run at a time. ``front``: the part comes from a lower rank (it wins ties)."""
    w = acc_depth.shape[1]
    y, x, k = 0, 0, 0  # (y, x): where the run starts; no division per run
    for r in range(runs.size):
        rem = np.int64(runs[r])
        if r & 1:
            while rem:
                seg = min(rem, w - x)
                _merge_segment(d_in, c_in, k, acc_depth, acc_color, y, x, seg, front)
                k += seg
                rem -= seg
                x += seg
                if x == w:
                    x, y = 0, y + 1
        else:
            x += rem
            while x >= w and w:
                x -= w
                y += 1


@njit(cache=True, nogil=True)
def paste_runs(runs, c_in, d_in, out_color, out_depth):
    """Copy a run-coded part's active pixels into the 2-D ``out_*`` views, one row segment at
    a time; background pixels are left as they are (clear them first: a vectorized fill beats
    interleaving the short background runs here)."""
    w = out_depth.shape[1]
    y, x, k = 0, 0, 0  # (y, x): where the run starts; no division per run
    for r in range(runs.size):
        rem = np.int64(runs[r])
        if r & 1:
            while rem:
                seg = min(rem, w - x)
                for i in range(seg):
                    out_depth[y, x + i] = d_in[k + i]
                    out_color[y, x + i] = c_in[k + i]
                k += seg
                rem -= seg
                x += seg
                if x == w:
                    x, y = 0, y + 1
        else:
            x += rem
            while x >= w and w:
                x -= w
                y += 1
