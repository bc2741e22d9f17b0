"""Pixel kernels of the sub-image codec and depth compositing: vectorized numpy, in place.

Images are handled as 2-D views — depth ``(h, w) float32`` and color ``(h, w) uint32`` (one
RGBA8 pixel per word) — so row bands and tile crops are never copied first. Every kernel
writes straight into a preallocated destination: the wire buffer when packing, the
accumulating band when merging, the display tile when pasting. Work is by active-pixel index
(issue 20): packing scans the depths once (``!= 1``, then the flat indices of the active
pixels) and everything after that — run lengths from the breaks between consecutive indices,
colors and depths gathered with ``np.take(out=)`` — costs in proportion to the active pixels;
merging and pasting rebuild those indices from the runs (:func:`active_index`, a cumulative
sum) and read and write the destination only there (merging writes only where the part
wins). The temporaries are the depth mask (1 B a pixel) when packing and a few arrays of
the active pixels' size. Strided crops (a tile narrower than the band) go through a boolean
mask instead; both paths give the same bytes.

A received sub-image is its run list (``uint32``, alternating background/active starting with
background, over the row-major pixels of its viewport; see :mod:`.codec`) and the color and
depth of its active pixels only; the kernels touch the accumulator at those pixels only. The
combine rule is :func:`.composite.combine`'s, bit for bit: a part behind the accumulator (a
higher rank) wins where ``d < acc``; a part in front (a lower rank) wins unless ``acc < d``.
Background pixels of a part (depth exactly 1.0 and the background color, the
:class:`~massview.core.image.Image` contract) are skipped: against depths in [0, 1] they
change nothing.

Why numpy (``scripts/compare_kernels.py`` is the measurement, figures in the README): the
same loops compiled with numba (``scripts/numba_kernels.py``, ``cache=True``) save 0.1–0.6 ms
per band at 1280×1024 but cost 0.5–1.8 s per rank per run to import numba and load the cached
kernels (a first compile on a machine adds seconds) — more than they save in any run shorter
than a few thousand frames. numexpr evaluates element-wise expressions only (no runs, no
gather/scatter); on a dense full-band combine it halves numpy's ``where`` but the run-based
kernels here beat both. Measured again on 1280×1024 partial images (issue 20, later round):
numba loops over the runs were not faster than these kernels on the objects scene (many short
runs) and 1.5–4× faster only for pack and paste of dense terrain bands (0.1–0.4 ms), not for
merge. The byte codecs run on one thread per rank (see :mod:`.codec`); on one node none at all
(``codec="auto"``).
"""

from __future__ import annotations

import numpy as np

__all__ = ["pack_runs", "pack_dense", "active_index", "active_mask", "merge_runs", "paste_runs"]

_ONE = np.float32(1.0)


def _gather(src: np.ndarray, idx: np.ndarray, mask: np.ndarray, out: np.ndarray) -> None:
    """``out[:] = src`` at the active pixels: by flat index when ``src`` is contiguous (cost ∝
    active pixels), else by the boolean ``mask`` (a strided crop)."""
    if src.flags.c_contiguous:
        np.take(src.reshape(-1), idx, out=out, mode="clip")
    else:
        out[:] = src[mask]


def pack_runs(depth: np.ndarray, color: np.ndarray, head: int = 0,
              active: np.ndarray | None = None) -> tuple[np.ndarray, int, int]:
    """The body of a wire message for a 2-D view: ``runs uint32 | color uint32[active] |
    depth float32[active]`` in one new uint8 buffer, after ``head`` spare bytes (a multiple of
    4: room for the message header); returns (buffer, run count, active count). ``active``:
    the mask ``depth != 1`` when the caller has it already.

    One pass over the depths finds the active pixels' flat indices; runs come from the breaks
    in those indices and colors/depths are gathered by index: every step after the first costs
    in proportion to the active pixels, not the region."""
    if active is None:
        active = depth != _ONE
    idx = np.flatnonzero(active)
    nact, size = idx.size, active.size
    if nact == 0:  # one background run (also for an empty region: a run of 0)
        raw = np.empty(head + 4, np.uint8)
        raw[head:].view(np.uint32)[0] = size
        return raw, 1, 0
    brk = np.flatnonzero(np.diff(idx) != 1)  # last index of every active run but the last
    na = brk.size + 1
    tail = int(idx[-1] + 1 < size)  # a background run after the last active one
    nruns = 2 * na + tail
    out = np.empty(head + nruns * 4 + nact * 8, np.uint8)
    raw = out[head:]
    runs = raw[: nruns * 4].view(np.uint32)
    starts, ends = np.empty(na, np.intp), np.empty(na, np.intp)
    starts[0], ends[-1] = idx[0], idx[-1]
    np.take(idx, brk + 1, out=starts[1:])
    np.take(idx, brk, out=ends[:-1])
    ends += 1
    runs[0] = starts[0]
    np.subtract(starts[1:], ends[:-1], out=runs[2: 2 * na: 2], casting="unsafe")  # background runs
    np.subtract(ends, starts, out=runs[1: 2 * na: 2], casting="unsafe")  # active runs
    if tail:
        runs[-1] = size - ends[-1]
    a, b = nruns * 4, nruns * 4 + nact * 4
    _gather(color, idx, active, raw[a:b].view(np.uint32))
    _gather(depth, idx, active, raw[b:].view(np.float32))
    return out, nruns, nact


def pack_dense(depth: np.ndarray, color: np.ndarray, head: int = 0) -> tuple[np.ndarray, int, int]:
    """The same message body with every pixel active: runs ``[0, size]``, then all colors and
    all depths, copied as they are (no scan, no gather). A valid message of the same format —
    background pixels travel as active ones with depth 1.0 and the background color, which
    combine and paste to the same pixels as skipping them (a part behind never wins with depth
    1.0; a part in front wins only against background, with background) — for regions so full
    of active pixels that finding them costs more than sending the rest: ``pack_runs`` takes
    1–2 ns an active pixel, this a copy. Needs a non-empty region; ``head`` as there."""
    size = depth.size
    out = np.empty(head + 8 + size * 8, np.uint8)
    raw = out[head:]
    raw[:8].view(np.uint32)[:] = (0, size)
    np.copyto(raw[8: 8 + size * 4].view(np.uint32).reshape(depth.shape), color)
    np.copyto(raw[8 + size * 4:].view(np.float32).reshape(depth.shape), depth)
    return out, 2, size


def _all_active(runs: np.ndarray, n: int, size: int) -> bool:
    """Whether a run list is the single active run over the whole region (:func:`pack_dense`)."""
    return runs.size == 2 and n == size and int(runs[0]) == 0


def active_index(runs: np.ndarray, nact: int) -> np.ndarray:
    """Flat (row-major) indices, ``intp[nact]``, of the active pixels a run list describes
    (active runs non-empty, as :func:`pack_runs` writes them); cost ∝ active pixels + runs:
    a step of 1 between neighbours, of 1 + the background run at each run's first pixel, summed."""
    na = runs.size // 2
    steps = np.ones(nact, np.intp)
    if nact == 0:
        return steps
    steps[0] = runs[0]
    steps[np.cumsum(runs[1: 2 * na - 2: 2], dtype=np.intp)] += runs[2: 2 * na: 2]
    return np.cumsum(steps, out=steps)


def active_mask(runs: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """The ``(h, w)`` boolean mask of the active pixels a run list describes."""
    flags = np.zeros(runs.size, bool)
    flags[1::2] = True
    return np.repeat(flags, runs).reshape(shape)


def _flat(view: np.ndarray) -> np.ndarray | None:
    """A 1-D view of a 2-D array sharing its memory, or None when it is a strided crop."""
    return view.reshape(-1) if view.flags.c_contiguous else None


def merge_runs(runs, c_in, d_in, acc_color, acc_depth, front: bool) -> None:
    """Depth-combine a run-coded part into the 2-D ``acc_*`` views in place, at its active
    pixels only (read by index, written only where the part wins). ``front``: the part comes
    from a lower rank (it wins ties)."""
    if not d_in.size:
        return
    if _all_active(runs, d_in.size, acc_depth.size):  # every pixel: elementwise, no indices
        d2, c2 = d_in.reshape(acc_depth.shape), c_in.reshape(acc_depth.shape)
        take = ~(acc_depth < d2) if front else np.less(d2, acc_depth)
        np.copyto(acc_depth, d2, where=take)
        np.copyto(acc_color, c2, where=take)
        return
    fd, fc = _flat(acc_depth), _flat(acc_color)
    if fd is None or fc is None:  # a strided crop: through the mask
        mask = active_mask(runs, acc_depth.shape)
        depth, color = acc_depth[mask], acc_color[mask]
        take = ~(depth < d_in) if front else d_in < depth
        np.copyto(depth, d_in, where=take)
        np.copyto(color, c_in, where=take)
        acc_depth[mask], acc_color[mask] = depth, color
        return
    idx = active_index(runs, d_in.size)
    cur = fd.take(idx, mode="clip")
    take = ~(cur < d_in) if front else np.less(d_in, cur)
    win = idx[take]
    fd[win] = d_in[take]
    fc[win] = c_in[take]


def paste_runs(runs, c_in, d_in, out_color, out_depth) -> None:
    """Write a run-coded part's active pixels into the 2-D ``out_*`` views; background
    pixels are left as they are."""
    if not d_in.size:
        return
    if _all_active(runs, d_in.size, out_depth.size):
        np.copyto(out_depth, d_in.reshape(out_depth.shape))
        np.copyto(out_color, c_in.reshape(out_depth.shape))
        return
    fd, fc = _flat(out_depth), _flat(out_color)
    if fd is None or fc is None:
        mask = active_mask(runs, out_depth.shape)
        out_depth[mask], out_color[mask] = d_in, c_in
        return
    idx = active_index(runs, d_in.size)
    fd[idx] = d_in
    fc[idx] = c_in
