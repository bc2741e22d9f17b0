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
from .meta import DiamondAccumulator, block_errors_from, saturate
from .sources import RasterSource
from .store import TerrainStore
from .workers import resolve_workers, run_ordered

__all__ = ["Metadata", "MetadataBuilder", "compute_metadata", "write_metadata"]

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
    row (nb, M, M); with ``zacc`` (level 0) also the z-ranges of its squares, folded in as
    :meth:`DiamondAccumulator.put_zrange` folds a block's (the same ``np.minimum``/``np.maximum``,
    once for the row's band); all in one compiled call (:func:`rowkernels.row_stats`) on the
    blocks in place: a C-contiguous row, or the blocks :func:`store.block_view` cuts from a
    C-contiguous float32 wide row (anything else is copied first)."""
    from .rowkernels import row_stats

    nb, M = row.shape[0], row.shape[1]
    f = 2**zacc.lay.k if zacc is not None else 0
    n = (M - 1) // f if f else 0
    mm, dm = np.empty((nb, 2), np.float32), np.empty(nb, np.float32)
    lo, hi = np.empty((n, nb * n), np.float32), np.empty((n, nb * n), np.float32)
    row_stats(*_stats_base(row), f, lo, hi, mm, dm)
    if zacc is not None:
        J, sl = zacc.lay.J, (slice(i * n, i * n + n), slice(0, nb * n))
        zacc.zmin[J][sl] = np.minimum(zacc.zmin[J][sl], lo)
        zacc.zmax[J][sl] = np.maximum(zacc.zmax[J][sl], hi)
    return mm, dm


def _stats_base(row: np.ndarray) -> tuple:
    """(w, nb, M, dr, dc) of :func:`rowkernels.row_stats` for a block row (nb, M, M): the wide
    row a :func:`store.block_view` of a C-contiguous float32 wide row was cut from (a view of
    the same memory), else the row's blocks stacked (C-contiguous float32, copied if need be)."""
    nb, M = row.shape[0], row.shape[1]
    s0, s1, s2 = row.strides
    if row.dtype == np.float32 and s2 == 4 and s0 == (M - 1) * 4 and s1 == (nb * (M - 1) + 1) * 4:
        w = np.lib.stride_tricks.as_strided(row, (M, nb * (M - 1) + 1), (s1, 4), writeable=False)
        return w, nb, M, 0, M - 1
    blocks = np.ascontiguousarray(row, np.float32)
    return blocks.reshape(nb * M, M), nb, M, M, 0


class MetadataBuilder:
    """Every block's metadata, fed block row by block row from any number of threads at once
    (rows write disjoint entries; each thread takes its own exact-error accumulator from a
    pool, merged by max at the end — max is exact, so the result does not depend on how rows
    were shared out). ``part`` splits the exact K-patch errors of a level-0 row into the
    levels a block alone determines ("grid") and those over lattice squares larger than a
    block ("window"), which need the coarse lattice (:meth:`set_coarse`)."""

    def __init__(self, lay: TerrainLayout, workers: int, coarse: np.ndarray | None = None):
        self.lay = lay
        self.acc = DiamondAccumulator(lay)  # square z-ranges (level 0): each block writes only its own squares
        self.all_devs = [DeviationAccumulator(lay, coarse) for _ in range(max(workers, 1))]
        self.devs: queue.SimpleQueue = queue.SimpleQueue()
        for d in self.all_devs:
            self.devs.put(d)
        self.minmax = [np.zeros((lay.blocks(lv), lay.blocks(lv), 2), np.float32) for lv in range(lay.levels)]
        self.dmax = [np.zeros((lay.blocks(lv), lay.blocks(lv)), np.float32) for lv in range(lay.levels)]

    def set_coarse(self, coarse: np.ndarray) -> None:
        for d in self.all_devs:
            d.coarse = np.asarray(coarse, np.float32)

    def row(self, lv: int, i: int, row: np.ndarray, part: str = "all") -> None:
        """Block row ``i`` of level ``lv`` (nb, M, M) float32: min/max and dropped-sample δ;
        at level 0 also the square z-ranges and the ``part`` of the exact errors."""
        self.minmax[lv][i], self.dmax[lv][i] = _row_stats(row, self.acc if lv == 0 else None, i)
        if lv == 0:
            self.errors(i, row, part)

    def errors(self, i: int, row: np.ndarray, part: str) -> None:
        """The ``part`` of the exact errors of level-0 block row ``i``; its min/max must be in
        ``minmax[0][i]`` already (:meth:`row` puts it there first; the shading pass's rows were
        all through :meth:`row` in the pyramid pass), which gives each block's largest |height|
        without two more passes over it."""
        mm = self.minmax[0][i]
        zabs = np.maximum(mm[:, 1], -mm[:, 0]).tolist()
        dev = self.devs.get()
        try:
            for j in range(row.shape[0]):
                dev.add_block(i, j, row[j], part, zabs[j])
        finally:
            self.devs.put(dev)

    @property
    def zlo_zhi(self) -> tuple[float, float]:
        """The data's height range (level 0)."""
        return float(self.minmax[0][..., 0].min()), float(self.minmax[0][..., 1].max())

    def finish(self) -> Metadata:
        zmin, zmax = self.acc.zranges()
        dev = self.all_devs[0]
        for other in self.all_devs[1:]:
            for a, b in zip(dev.sq + dev.dg, other.sq + other.dg):
                np.maximum(a, b, out=a)
        sq, dg = saturate(dev.sq, dev.dg)
        return Metadata(self.minmax, block_errors_from(self.dmax), sq, dg, zmin, zmax, *self.zlo_zhi)


def compute_metadata(store: TerrainStore, prog: Progress, write_color: bool = False, ortho: RasterSource | None = None,
                     vertical_scale: float = 1.0, workers: int | None = None) -> Metadata:
    """Read every block once and derive all metadata (what ``verify`` and ``upgrade``
    recompute; ``prepare`` feeds a :class:`MetadataBuilder` during its own passes)."""
    lay = store.layout
    nw = resolve_workers(workers)
    build = MetadataBuilder(lay, nw, coarse_lattice(store))
    total = sum(lay.blocks(lv) ** 2 for lv in range(lay.levels))

    def tasks():
        for lv in range(lay.levels):
            for i in range(lay.blocks(lv)):
                yield lambda lv=lv, i=i, row=store.get_block_row(lv, i): (build.row(lv, i, row), lv)[1]

    run_ordered(nw, tasks(), lambda lv: prog("metadata", lay.blocks(lv), total))
    meta = build.finish()
    if write_color:
        write_colors(store, lay, meta.zlo, meta.zhi, ortho, vertical_scale, prog)
    return meta


def write_colors(store: TerrainStore, lay: TerrainLayout, zlo: float, zhi: float, ortho, vscale: float, prog: Progress,
                 place=None) -> None:
    """The colour pyramid from the orthophoto ``ortho``, placed by ``place`` (None: stretched
    over the DEM's extent)."""
    import zarr

    if place is None:
        from .sources import OrthoPlacement

        place = OrthoPlacement.stretched(lay.rows, lay.cols, ortho)

    g = zarr.open_group(str(store.path), mode="r+")
    total = sum(lay.blocks(lv) ** 2 for lv in range(lay.levels))
    for lv in range(lay.levels):
        nb = lay.blocks(lv)
        dst = g[f"color/{lv}"]
        for i in range(nb):
            dst[i] = np.stack([_ortho_block(ortho, lay, lv, i, j, place) for j in range(nb)])
            prog("colour", nb, total)


def _ortho_block(ortho, lay: TerrainLayout, lv: int, i: int, j: int, place) -> np.ndarray:
    """Orthophoto pixels for a block, resampled (nearest) as ``place`` (a
    :class:`sources.OrthoPlacement`) says: stretched over the DEM's extent, or by georeference."""
    M = lay.M
    step = 2**lv
    rows = (i * (M - 1) + np.arange(M)) * step
    cols = (j * (M - 1) + np.arange(M)) * step
    ry = np.clip(np.floor(np.minimum(rows, lay.rows - 1) * place.sy + place.ty).astype(int), 0, ortho.rows - 1)
    rx = np.clip(np.floor(np.minimum(cols, lay.cols - 1) * place.sx + place.tx).astype(int), 0, ortho.cols - 1)
    r0, r1, c0, c1 = ry.min(), ry.max() + 1, rx.min(), rx.max() + 1
    rgb = ortho.read_rgb(r0, r1, c0, c1)
    return rgb[np.ix_(ry - r0, rx - c0)]


def write_metadata(g, lay: TerrainLayout, meta: Metadata) -> None:
    """The metadata arrays (``blocks/<l>/minmax``, ``blocks/<l>/error``, ``lod/…``: one chunk
    each, zarr's default zstd) into the store's group ``g``, replacing any old ones: created as
    one family (:class:`store._ArraysLike`: the first through zarr, the others from its
    ``zarr.json``), every chunk encoded and written directly (:class:`store.ArrayChunkWriter`):
    the files ``create_array`` + ``arr[...] = a`` write (tests/test_direct_chunks.py), without
    zarr's ~5 ms event-loop round trip for each of the ~60 arrays (0.3 s at the end of every
    prepare)."""
    from .store import CHUNK_KEYS, _ArraysLike, array_chunk_writer

    items = []
    for lv in range(lay.levels):
        items += [(f"blocks/{lv}/minmax", meta.minmax[lv]), (f"blocks/{lv}/error", meta.block_error[lv])]
    for j in range(lay.J):
        items += [(f"lod/square_error/{j}", meta.sq[j]), (f"lod/edge_error/{j}", meta.dg[j])]
    for j in range(lay.J + 1):
        items += [(f"lod/zmin/{j}", meta.zmin[j]), (f"lod/zmax/{j}", meta.zmax[j])]
    new, first = _ArraysLike(g), None  # first: the chunk writer of the first array that has one
    for name, a in items:
        arr = new.create(name, "metadata", shape=a.shape, chunks=a.shape, dtype="float32", overwrite=True,
                         chunk_key_encoding=CHUNK_KEYS)
        if arr is None and first is not None:  # made from the first's zarr.json
            w = first.like(new.folder(name), a.shape, a.shape)
        else:
            arr = g[name] if arr is None else arr
            w = array_chunk_writer(arr)
            first = first or w
        if w is None or a.dtype != w.dtype:
            (g[name] if arr is None else arr)[...] = a
        else:
            w.write(a, [(0,) * a.ndim])
