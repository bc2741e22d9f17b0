"""Phase 3 of ``prepare``: every block's metadata and the exact K-patch errors, on all cores.

Level 0 is read block row by block row, in order, on the calling thread (zarr decodes a row's
chunks concurrently); each row is then processed by a worker thread: min/max, dropped-sample
errors (:func:`meta.vertex_deltas`), square z-ranges and the exact diamond errors
(:class:`deviation.DeviationAccumulator`, one per worker, merged by max at the end — max is
exact, so the result does not depend on how rows were shared out). Coarser levels only need
min/max and dropped-sample errors. Peak memory: (2·workers + 1) block rows plus one
accumulator per worker (~17 MB at 32769²).
"""

from __future__ import annotations

import queue
from dataclasses import dataclass
from typing import Callable

import numpy as np

from .deviation import DeviationAccumulator, coarse_lattice
from .layout import TerrainLayout
from .meta import DiamondAccumulator, block_errors_from, saturate, vertex_deltas
from .sources import RasterSource
from .store import TerrainStore
from .workers import resolve_workers, run_ordered

__all__ = ["Metadata", "compute_metadata", "write_metadata"]

Progress = Callable[[str, int, int], None]


@dataclass
class Metadata:
    minmax: list[np.ndarray]
    block_error: list[np.ndarray]
    sq: list[np.ndarray]
    dg: list[np.ndarray]
    zmin: list[np.ndarray]
    zmax: list[np.ndarray]
    zlo: float
    zhi: float


def _row_stats(row: np.ndarray, zacc: DiamondAccumulator | None = None, i: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(nb, 2) min/max and (nb,) max dropped-sample δ (:func:`meta.vertex_deltas`) of a block
    row (nb, M, M); with ``zacc`` (level 0) also the z-ranges of its squares, all in one
    compiled pass per block (:func:`rowkernels.block_stats`)."""
    from .rowkernels import block_stats

    nb, M = row.shape[0], row.shape[1]
    f = 2**zacc.lay.k if zacc is not None else 0
    n = (M - 1) // f if f else 0
    mm = np.empty((nb, 2), np.float32)
    dm = np.empty(nb, np.float32)
    for j in range(nb):
        lo, hi = np.empty((n, n), np.float32), np.empty((n, n), np.float32)
        mn, mx, d = block_stats(np.ascontiguousarray(row[j], np.float32), f, lo, hi)
        mm[j], dm[j] = (mn, mx), d
        if zacc is not None:
            zacc.put_zrange(i, j, lo, hi)
    return mm, dm


def compute_metadata(store: TerrainStore, prog: Progress, write_color: bool = False, ortho: RasterSource | None = None,
                     vertical_scale: float = 1.0, workers: int | None = None) -> Metadata:
    """Read every block once and derive all metadata (also what ``verify`` recomputes)."""
    lay = store.layout
    nw = resolve_workers(workers)
    acc = DiamondAccumulator(lay)  # square z-ranges (level 0): each block writes only its own squares
    coarse = coarse_lattice(store)
    devs: queue.SimpleQueue = queue.SimpleQueue()
    all_devs = [DeviationAccumulator(lay, coarse) for _ in range(nw)]  # exact K-patch errors (level 0)
    for d in all_devs:
        devs.put(d)
    total = sum(lay.blocks(lv) ** 2 for lv in range(lay.levels))
    minmax = [np.zeros((lay.blocks(lv), lay.blocks(lv), 2), np.float32) for lv in range(lay.levels)]
    dmax = [np.zeros((lay.blocks(lv), lay.blocks(lv)), np.float32) for lv in range(lay.levels)]

    def level0_row(i: int, row: np.ndarray):
        mm, dm = _row_stats(row, acc, i)
        dev = devs.get()
        try:
            for j in range(row.shape[0]):
                dev.add_block(i, j, row[j])
        finally:
            devs.put(dev)
        return 0, i, mm, dm

    def other_row(lv: int, i: int, row: np.ndarray):
        mm, dm = _row_stats(row)
        return lv, i, mm, dm

    def tasks():
        for lv in range(lay.levels):
            for i in range(lay.blocks(lv)):
                row = store.get_block_row(lv, i)
                yield (lambda i=i, row=row: level0_row(i, row)) if lv == 0 else (lambda lv=lv, i=i, row=row: other_row(lv, i, row))

    def done(res) -> None:
        lv, i, mm, dm = res
        minmax[lv][i], dmax[lv][i] = mm, dm
        prog("metadata", lay.blocks(lv), total)

    run_ordered(nw, tasks(), done)
    zmin, zmax = acc.zranges()
    dev = all_devs[0]
    for other in all_devs[1:]:
        for a, b in zip(dev.sq + dev.dg, other.sq + other.dg):
            np.maximum(a, b, out=a)
    sq, dg = saturate(dev.sq, dev.dg)
    zlo, zhi = float(minmax[0][..., 0].min()), float(minmax[0][..., 1].max())  # the data's range (level 0)
    if write_color:
        _write_colors(store, lay, zlo, zhi, ortho, vertical_scale, prog)
    return Metadata(minmax, block_errors_from(dmax), sq, dg, zmin, zmax, zlo, zhi)


def _write_colors(store: TerrainStore, lay: TerrainLayout, zlo: float, zhi: float, ortho, vscale: float, prog: Progress) -> None:
    import zarr

    g = zarr.open_group(str(store.path), mode="r+")
    total = sum(lay.blocks(lv) ** 2 for lv in range(lay.levels))
    for lv in range(lay.levels):
        nb = lay.blocks(lv)
        dst = g[f"color/{lv}"]
        for i in range(nb):
            dst[i] = np.stack([_ortho_block(ortho, lay, lv, i, j) for j in range(nb)])
            prog("colour", nb, total)


def _ortho_block(ortho, lay: TerrainLayout, lv: int, i: int, j: int) -> np.ndarray:
    """Orthophoto pixels for a block, resampled (nearest) from an image covering the DEM extent."""
    M = lay.M
    step = 2**lv
    rows = (i * (M - 1) + np.arange(M)) * step
    cols = (j * (M - 1) + np.arange(M)) * step
    fy, fx = ortho.rows / lay.rows, ortho.cols / lay.cols
    ry = np.clip((np.minimum(rows, lay.rows - 1) * fy).astype(int), 0, ortho.rows - 1)
    rx = np.clip((np.minimum(cols, lay.cols - 1) * fx).astype(int), 0, ortho.cols - 1)
    r0, r1, c0, c1 = ry.min(), ry.max() + 1, rx.min(), rx.max() + 1
    rgb = ortho.read_rgb(r0, r1, c0, c1)
    return rgb[np.ix_(ry - r0, rx - c0)]


def write_metadata(g, lay: TerrainLayout, meta: Metadata) -> None:
    for lv in range(lay.levels):
        for name, arr in ((f"blocks/{lv}/minmax", meta.minmax[lv]), (f"blocks/{lv}/error", meta.block_error[lv])):
            g.create_array(name, shape=arr.shape, dtype="float32", chunks=arr.shape, overwrite=True)[...] = arr
    for j in range(lay.J):
        g.create_array(f"lod/square_error/{j}", shape=meta.sq[j].shape, dtype="float32", chunks=meta.sq[j].shape, overwrite=True)[...] = meta.sq[j]
        g.create_array(f"lod/edge_error/{j}", shape=meta.dg[j].shape, dtype="float32", chunks=meta.dg[j].shape, overwrite=True)[...] = meta.dg[j]
    for j in range(lay.J + 1):
        for name, arr in ((f"lod/zmin/{j}", meta.zmin[j]), (f"lod/zmax/{j}", meta.zmax[j])):
            g.create_array(name, shape=arr.shape, dtype="float32", chunks=arr.shape, overwrite=True)[...] = arr
