"""Pixel kernels of the sub-image codec and depth compositing: vectorized numpy, in place.

Images are handled as 2-D views — depth ``(h, w) float32`` and color ``(h, w) uint32`` (one
RGBA8 pixel per word) — so row bands and tile crops are never copied first. Every kernel
writes straight into a preallocated destination: the wire buffer when packing (runs, colors
and depths land in their final places with ``np.compress(out=)``), the accumulating band when
merging, the display tile when pasting. The only temporaries are one boolean mask per image
(1 B a pixel) and the gathered active pixels of a received part.

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
kernels here beat both. The byte codecs run on one thread per rank (see :mod:`.codec`).
"""

from __future__ import annotations

import numpy as np

__all__ = ["pack_runs", "active_mask", "merge_runs", "paste_runs"]

_ONE = np.float32(1.0)


def pack_runs(depth: np.ndarray, color: np.ndarray) -> tuple[np.ndarray, int, int]:
    """The body of a wire message for a 2-D view: ``runs uint32 | color uint32[active] |
    depth float32[active]`` in one new uint8 buffer; returns (buffer, run count, active count)."""
    active = depth != _ONE
    flat = active.reshape(-1)
    nact = int(np.count_nonzero(flat))
    edges = np.flatnonzero(flat[1:] != flat[:-1]) + 1
    lead = int(flat.size > 0 and bool(flat[0]))  # an empty background run first
    nruns = edges.size + 1 + lead
    raw = np.empty(nruns * 4 + nact * 8, np.uint8)
    bounds = np.concatenate(([0] * (1 + lead), edges, [flat.size]))
    np.subtract(bounds[1:], bounds[:-1], out=raw[: nruns * 4].view(np.uint32), casting="unsafe")
    a, b = nruns * 4, nruns * 4 + nact * 4
    np.compress(flat, color.reshape(-1), out=raw[a:b].view(np.uint32))
    np.compress(flat, depth.reshape(-1), out=raw[b:].view(np.float32))
    return raw, nruns, nact


def active_mask(runs: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """The ``(h, w)`` boolean mask of the active pixels a run list describes."""
    flags = np.zeros(runs.size, bool)
    flags[1::2] = True
    return np.repeat(flags, runs).reshape(shape)


def merge_runs(runs, c_in, d_in, acc_color, acc_depth, front: bool) -> None:
    """Depth-combine a run-coded part into the 2-D ``acc_*`` views in place, at its active
    pixels only. ``front``: the part comes from a lower rank (it wins ties)."""
    if not d_in.size:
        return
    mask = active_mask(runs, acc_depth.shape)
    depth, color = acc_depth[mask], acc_color[mask]
    take = ~(depth < d_in) if front else d_in < depth
    np.copyto(depth, d_in, where=take)
    np.copyto(color, c_in, where=take)
    acc_depth[mask] = depth
    acc_color[mask] = color


def paste_runs(runs, c_in, d_in, out_color, out_depth) -> None:
    """Write a run-coded part's active pixels into the 2-D ``out_*`` views; background
    pixels are left as they are."""
    if d_in.size:
        mask = active_mask(runs, out_depth.shape)
        out_depth[mask] = d_in
        out_color[mask] = c_in
