"""``prepare``: build a terrain store from any :class:`RasterSource`, out of core.

Phases (each resumable — a block is flagged ``done`` only after it is written, and the store
is marked ``complete`` last, so an interrupted prepare re-run with the same arguments
continues where it stopped and a half-written store never opens as a good one):

1. **the pyramid, in one pass over the input**: level 0 in strips of M rows (one block row):
   windowed read, nodata/NaN/±inf voids filled (:mod:`voidfill`: a coarse harmonic surface
   made by one more pass over the input when the first void is met, plus the detail of the
   data round the void; the same values whichever strip computes them, never a made-up 0),
   padded by edge replication at the outer border only, cut into blocks. The
   shared row between strips is taken from the strip above, so borders are bit-identical in
   both blocks. Levels 1..L by vertex decimation, in memory, as soon as the two finer block
   rows exist. Every row, on a worker: compressed and written, its blocks' metadata
   (:mod:`metadata`: min/max, dropped-sample errors, square z-ranges (:mod:`meta`), the exact
   K-patch errors a block alone decides (:mod:`deviation`, compiled: :mod:`kernels`)) and its
   Röttger local d2 (:class:`roettger.TableBuilder`), each in one compiled pass
   (:mod:`rowkernels`);
2. **the Röttger table**'s propagation, finest depth first, written as it is made (and freed);
3. **shading pyramid** (:mod:`colors`): level 0 read back once; slopes and height fractions
   (they need the data's height range, known only now), seamless and mip-filtered, the coarser
   levels made in memory from the finer rows; the same workers compute the exact errors over
   lattice squares larger than a block (they need the finished coarse lattice);
4. **orthophoto colour** (if any) and the metadata arrays.
   ``height_range`` is the full-resolution (level 0) min/max, i.e. the data's own range.

Every phase runs on ``workers`` threads (:mod:`workers`; default every core): rows are read in
order on the calling thread and processed, compressed (blosc releases the GIL; chunks are
written by :class:`store.ChunkWriter`) and written by the workers; results are combined only
by exact operations, so the store is the same for any number of workers, and the same as the
single-threaded ingest wrote before issue 20 (tests/test_ingest_parallel.py).

``overwrite`` of a complete store builds the new one beside it and swaps it in when complete
(:func:`massview.data.rebuild.rebuild_beside`): an interrupted rebuild leaves the old store as
it was.

Bad data does not pass silently: an input with no valid sample at all (all nodata, NaN or
±inf) raises :class:`IngestError` naming the file (while reading the first strip, which looks
ahead for a valid row), and the store this run created is removed (a resumed one stays incomplete, so it never opens). More than half the
samples filled, or no georeference (1 m spacing assumed), is reported in
``PrepareResult.warnings`` (the CLI prints them).

Peak memory: a few block rows per worker (17 MB each at 16385², 34 MB at 32769²; float16
shading rows 1.5× that), the metadata accumulators and, during the pyramid pass, every depth
of the Röttger table (4/3 of its finest stored depth: 85 MiB at 16385², 341 MiB at 32769²),
freed before the shading pass.
"""

from __future__ import annotations

import math
import shutil
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from ...core.errors import IngestError
from .colors import write_shading
from .deviation import coarse_lattice
from .layout import TerrainLayout
from .metadata import Metadata, MetadataBuilder, compute_metadata, write_colors, write_metadata
from .sources import RasterSource, place_ortho
from ..rebuild import is_complete_store, rebuild_beside, writing
from .inputchecks import check_padding, looks_like_degrees, marker_hints
from .voidfill import VoidFill, no_valid_sample
from .store import FORMAT, ChunkWriter, TerrainStore, block_view, create_store, rows_done, wide_row
from .workers import BufferPool, resolve_workers, run_ordered

__all__ = ["prepare_terrain", "PrepareResult", "compute_metadata", "write_metadata", "Metadata"]

Progress = Callable[[str, int, int], None]  # (phase, advance, phase_total)
_FLAG_EVERY = 1.0  # seconds between writes of the pyramid pass's done flags (each a zarr round trip)
_TABLE_BESIDE_SHADING = 128 << 20  # a Röttger table up to this size (16385²: 85 MiB) is written beside the shading pass


@dataclass
class PrepareResult:
    path: Path
    layout: TerrainLayout
    seconds: float
    filled: int
    resumed: bool
    input_bytes: int
    warnings: list[str]
    stages: dict = field(default_factory=dict)  # {stage: (wall s, CPU s, system s, minor faults) of the whole process}
    rows_kept: int = 0  # level-0 block rows an interrupted run had finished (resumed: not read or written again)

    @property
    def filled_fraction(self) -> float:
        """Filled (nodata/NaN/±inf) samples over all input samples."""
        return self.filled / max(self.layout.rows * self.layout.cols, 1)


def _read_strip(src: RasterSource, lay: TerrainLayout, bi: int, prev_row: np.ndarray | None,
                out: np.ndarray | None = None, voids: Callable[[], VoidFill] | None = None) -> tuple[np.ndarray, int]:
    """Rows bi·(M-1) .. +M of the padded grid, voids filled (:mod:`voidfill`; ``voids`` gives
    the input's :class:`VoidFill`, built on first use) and padded (M × S float32, into ``out``
    when given: C-contiguous, its contents overwritten), and how many nodata samples of the
    rows new to this strip were filled."""
    M, cols = lay.M, src.cols
    r0 = bi * (M - 1)
    strip = np.empty((M, lay.S), np.float32) if out is None else out
    filled = 0
    if r0 < src.rows and _read_strip_finite(src, strip, r0, prev_row):
        pass
    elif r0 < src.rows:
        nv = min(M, src.rows - r0)
        data = src.read(r0, r0 + nv, 0, cols)
        first_new = 0
        if prev_row is not None:  # the shared row is final already: keep it bit-identical
            data[0] = prev_row[:cols]
            first_new = 1
        filled = int(np.count_nonzero(np.isnan(data[first_new:])))
        if filled:
            (voids or (lambda: VoidFill(src)))().fill(r0, data)
        strip[:nv, :cols] = data
        strip[nv:, :cols] = data[nv - 1]
    else:  # a strip wholly in the bottom padding repeats the last row
        strip[:, :cols] = prev_row[:cols]
    strip[:, cols:] = strip[:, cols - 1: cols]
    return strip, filled


def _read_strip_finite(src: RasterSource, strip: np.ndarray, r0: int, prev_row: np.ndarray | None) -> bool:
    """The fast path of :func:`_read_strip`: a float32 file with no nodata value is read
    straight into the strip (no copies); when every sample new to the strip is finite there is
    nothing to fill, and the strip is what the general path makes (which only ever changes
    non-finite samples). False when it does not apply (the caller reads it the general way)."""
    M, cols = strip.shape[0], src.cols
    nv = min(M, src.rows - r0)
    reader = getattr(src, "read_float32_into", None)
    whole = cols == strip.shape[1]
    dst = strip[:nv] if whole else np.empty((nv, cols), np.float32)
    if reader is None or not reader(r0, dst):
        return False
    from .rowkernels import all_finite

    first_new = 0 if prev_row is None else 1
    if not all_finite(dst[first_new:].reshape(-1).view(np.uint32)):  # (np.isfinite(...).all(), without its temporary)
        return False
    if not whole:
        strip[:nv, :cols] = dst
    if prev_row is not None:
        strip[0, :cols] = prev_row[:cols]
    strip[nv:, :cols] = strip[nv - 1, :cols]
    return True


def prepare_terrain(src: RasterSource, out: Path, block: int = 257, K: int = 17, vertical_scale: float = 1.0,
                    color: str | None = "computed", ortho: RasterSource | None = None, overwrite: bool = False,
                    progress: Progress | None = None, workers: int | None = None) -> PrepareResult:
    """Build the store at ``out`` from ``src`` (see the module docstring); ``workers`` threads
    (None/0: every core this process may use) share the work, with identical output. One
    writer at a time: a second prepare into the same ``out`` fails at once (StoreError)."""
    with writing(out):
        return _prepare_terrain(src, out, block, K, vertical_scale, color, ortho, overwrite, progress, workers)


def _prepare_terrain(src: RasterSource, out: Path, block: int, K: int, vertical_scale: float, color: str | None,
                     ortho: RasterSource | None, overwrite: bool, progress: Progress | None, workers: int | None) -> PrepareResult:
    t0 = time.perf_counter()
    if src.rows < 2 or src.cols < 2:
        raise IngestError(f"{src.name}: a terrain needs at least 2 × 2 samples, got {src.rows} × {src.cols}")
    lay = TerrainLayout(src.rows, src.cols, block, K)
    check_padding(src, lay)
    if not (math.isfinite(vertical_scale) and vertical_scale > 0):
        raise IngestError(f"--vertical-scale must be a positive number, got {vertical_scale}")
    dx, dy = src.spacing()
    attrs = {"spacing": [dx, dy], "vertical_scale": float(vertical_scale), "crs": src.crs,
             "transform": list(src.transform) if src.transform else None,
             "nodata": {"value": None if src.nodata is None else float(src.nodata), "filled": 0},
             "source": src.name, "source_stamp": src.stamp, "source_dtype": str(src.dtype), "color": None}
    workers = resolve_workers(workers)  # (a bad count is an error before the store exists)
    place = place_ortho(src, ortho) if ortho is not None else None  # (so is an orthophoto of another place)
    if overwrite and is_complete_store(out, FORMAT):  # built beside it and swapped in: a stopped rebuild loses nothing
        res = rebuild_beside(out, FORMAT, lambda p: prepare_terrain(src, p, block, K, vertical_scale, color, ortho, False,
                                                                    progress, workers))
        res.path = Path(out)
        return res
    restarted: list[str] = []
    g, resumed = create_store(out, lay, attrs, ortho is not None, overwrite, restarted)
    kept = (rows_done(out) or (0, 0))[0] if resumed else 0
    prog = progress or (lambda phase, adv, total: None)
    from .roettger import DEFAULT_C_MIN, TableBuilder  # T2's per-node table (Röttger d2)

    build, table, stages, edges = MetadataBuilder(lay, workers), TableBuilder(lay, DEFAULT_C_MIN), {}, {}
    with _old_objects_frozen():
        try:
            with _stage(stages, "pyramid, metadata, local d2"):
                filled = _level0(g, src, lay, block, resumed, prog, workers, (build, table), edges)
        except IngestError:
            if not resumed:  # created by this run, nothing of value in it: leave no store behind
                shutil.rmtree(out, ignore_errors=True)
            raise
        meta = _shading_and_tables(g, out, lay, build, table, stages, prog, workers, ortho, vertical_scale, edges, place)
    g.attrs.update({"height_range": [meta.zlo, meta.zhi], "color": None if color is None else ("orthophoto" if ortho else "computed")})
    g.attrs["complete"] = True
    seconds = time.perf_counter() - t0
    res = PrepareResult(Path(out), lay, seconds, filled, resumed, src.rows * src.cols * src.dtype.itemsize, [], stages, kept)
    if restarted:
        res.warnings.append(f"{out}: an interrupted prepare was there, but its {', '.join(restarted)} differed from this run's; "
                            "it was started again from the beginning")
    if place is not None and place.note:
        res.warnings.append(place.note)
    if res.filled_fraction > 0.5:
        res.warnings.append(f"{src.name}: {res.filled_fraction:.0%} of the samples were nodata/NaN/inf and were filled from their "
                            "neighbours; check the nodata value (--nodata) and the extent")
    if src.bands > 1:
        res.warnings.append(f"{src.name} has {src.bands} bands; band 1 was used as the elevation")
    res.warnings += marker_hints(src, meta.zlo, meta.zhi)
    unit, factor = src.linear_unit()
    if factor != 1.0:
        res.warnings.append(f"{src.name}: its CRS measures in {unit} ({factor:.6g} m), so the sample spacing was converted to metres; "
                            f"heights are taken as they are — if they are in {unit} too, prepare again with --vertical-scale {factor:.6g}")
    if src.transform is None:
        tile = (" (an SRTM tile is placed by its file name, such as N45E006.hgt: give it its own name back)"
                if src.name.lower().endswith(".hgt") else "")
        res.warnings.append(f"{src.name} has no georeference: assumed 1 m sample spacing; pass --spacing DX[,DY] (and --crs) "
                            f"if the samples are further apart{tile}")
    elif not src.crs and looks_like_degrees(src, meta.zhi - meta.zlo):
        res.warnings.append(f"{src.name} has no CRS, and its transform looks like degrees (a {abs(src.transform[1]):.6g} sample "
                            f"spacing at {src.transform[0]:.4g}, {src.transform[3]:.4g}, heights spanning {meta.zhi - meta.zlo:.4g}): "
                            "it was taken as metres, so the terrain is a needle; prepare again with --crs EPSG:4326 --overwrite "
                            "(or the CRS it was made in: an ESRI grid's .prj beside it)")
    return res


@contextmanager
def _old_objects_frozen():
    """Every object alive on entry (numba's, zarr's, the modules': ~10⁵–10⁶) moved out of the
    cyclic garbage collector's reach (``gc.freeze``) until exit, also on error: the prepare
    makes many small objects (tasks, futures, chunk keys), and each full collection they
    trigger walked all the old ones too. Unchanged where the caller has frozen objects itself
    or turned the collector off."""
    import gc

    mine = gc.isenabled() and gc.get_freeze_count() == 0
    if mine:
        gc.freeze()
    try:
        yield
    finally:
        if mine:
            gc.unfreeze()


@contextmanager
def _stage(stages: dict, name: str):
    """Record a stage's wall time, the process's CPU time (every thread), and of that CPU time
    the system part and the minor page faults (``getrusage``): (wall s, CPU s, system s, faults)."""
    import resource

    w, r0 = time.perf_counter(), resource.getrusage(resource.RUSAGE_SELF)
    yield
    r1 = resource.getrusage(resource.RUSAGE_SELF)
    user, system = r1.ru_utime - r0.ru_utime, r1.ru_stime - r0.ru_stime
    stages[name] = (time.perf_counter() - w, user + system, system, r1.ru_minflt - r0.ru_minflt)


def _shading_and_tables(g, out: Path, lay: TerrainLayout, build: MetadataBuilder, table, stages: dict, prog: Progress,
                        workers: int, ortho, vertical_scale: float, edges: dict, place=None) -> Metadata:
    """Phases 3–5 after the pyramid pass: the Röttger table, the shading pyramid (its level-0
    pass also computes the exact errors over lattice squares larger than a block, which need
    the coarse lattice of the finished pyramid), the orthophoto colour and the metadata arrays."""
    from .roettger import DEFAULT_C_MIN, TableWriter, write_table

    beside = None  # a small table is written beside the shading pass; a large one first, alone, which frees
    if table.nbytes <= _TABLE_BESIDE_SHADING:  # its arrays (341 MiB at 32769²) before the shading pass
        beside = TableWriter(g, table.depths(prog), DEFAULT_C_MIN, workers)
    else:
        with _stage(stages, "Röttger table"):
            write_table(g, table.depths(prog), DEFAULT_C_MIN, workers)
            table.top = None
    store = TerrainStore(out, require_complete=False)
    zlo, zhi = build.zlo_zhi
    hook = None
    with _stage(stages, "shading, window errors" if beside is None else "shading, window errors, Röttger table"):
        try:
            if lay.J > lay.m:
                build.set_coarse(coarse_lattice(store))
                hook = lambda i, row: build.errors(i, row, "window")  # noqa: E731
            write_shading(store, g, zlo, zhi, prog, workers, row_hook=hook, edges=edges)
        finally:
            if beside is not None:
                beside.join()
                table.top = None
    with _stage(stages, "colour, metadata"):
        meta = build.finish()
        if ortho is not None:
            write_colors(store, lay, zlo, zhi, ortho, vertical_scale, prog, place)
        write_metadata(g, lay, meta)
    return meta


def _level0(g, src: RasterSource, lay: TerrainLayout, block: int, resumed: bool, prog: Progress, workers: int,
            builders: tuple, edges: dict) -> int:
    """Phases 1 and 2 in one pass; returns the number of filled samples (all runs). Raises
    IngestError when no input sample is valid. Strips are read and filled in order here (each
    needs the row above it), and every coarser level's block row is decimated here, in memory,
    as soon as its two finer rows exist (every other sample of both: what decimating their
    2 × 2 child blocks gives); worker threads compress and write the rows, and a block row is
    flagged done, in order, only once its chunks are on disk (the flags of the rows finished
    since the last write are written together, at most every ``_FLAG_EVERY`` seconds, and when
    the pass ends or is interrupted). Rows done in an earlier run are
    read back (level 0) or re-made (coarser levels) to feed the levels above, not rewritten.
    ``edges`` receives grid rows 1 and M-2 of every level-0 block row (for the shading pass)."""
    M, nlev = lay.M, lay.levels
    build, table = builders  # MetadataBuilder, roettger.TableBuilder: fed every row on the workers
    dones = [g[f"blocks/{lv}/done"] for lv in range(nlev)]
    flags = [np.array(d[...]) for d in dones]  # (updated as rows finish; written by flush)
    heights0 = g["heights/0"]
    writers = [ChunkWriter(g, f"heights/{lv}") for lv in range(nlev)]
    state = {"filled": int(g.attrs.get("nodata", {}).get("filled", 0)) if resumed else 0}
    # The level-0 strips (17 MB at 16385²) come from a pool and go back once nothing reads them
    # any more: a fresh strip is a new mapping whose every page the kernel zeroes when first
    # written (return_freed_memory). ``users[(0, i)]`` = [strip, readers left]: its task, and
    # the decimation into level 1 (a one-level store has none: its strip, the top row, is kept
    # by the Röttger table and never given back).
    pool = BufferPool(2 * M * lay.S * 4)  # (at most two free strips wait in it)
    users: dict = {}

    def release(key) -> None:
        entry = users.get(key)
        if entry is not None:
            entry[1] -= 1
            if entry[1] == 0:
                pool.give(users.pop(key)[0])

    def book(lv: int, i: int, wide: np.ndarray) -> np.ndarray:
        if lv == 0 and nlev > 1:  # (not coarser rows: one would wait in the pool for the next of its level, raising the peak)
            users[(lv, i)] = [wide, 2]
        return wide

    def write(lv: int, i: int, wide: np.ndarray, keep: bool, nfill: int):
        if lv == 0:
            edges[i] = (wide[1].copy(), wide[M - 2].copy())
        blocks = block_view(wide, lay.blocks(lv), M)
        if keep:
            writers[lv].write(i, 0, blocks)
        build.row(lv, i, blocks, "grid")
        table.strip(lv, i * (M - 1), wide)
        return lv, i, keep, nfill

    fills: list = []  # the input's VoidFill, made when the first void is met (one more pass over the input)

    def voids() -> VoidFill:
        if not fills:
            fills.append(VoidFill(src, lambda adv, total: prog("nodata fill: coarse surface", adv, total)))
        return fills[0]

    def tasks():
        prev_row, waiting = None, {}  # waiting: level → its even wide row, until the odd one comes
        for bi in range(lay.blocks(0)):
            if flags[0][bi].all():  # done in an earlier run: read it back for the levels above
                strip = book(0, bi, wide_row(np.asarray(heights0[bi]), pool.take((M, lay.S), np.float32)))
                yield lambda bi=bi, strip=strip: write(0, bi, strip, False, 0)
            else:
                strip, nfill = _read_strip(src, lay, bi, prev_row, pool.take((M, lay.S), np.float32), voids=voids)
                book(0, bi, strip)
                yield lambda bi=bi, strip=strip, nfill=nfill: write(0, bi, strip, True, nfill)
            prev_row = strip[-1].copy()
            lv, i, wide = 0, bi, strip
            while lv + 1 < nlev and i % 2 == 1:
                up = np.concatenate([waiting.pop(lv)[0::2, ::2], wide[2::2, ::2]])  # rows 0..M-1 of 2i, 2..M-1 of 2i+1
                release((lv, i - 1))
                release((lv, i))
                lv, i, wide = lv + 1, i // 2, book(lv + 1, i // 2, up)
                yield lambda lv=lv, i=i, wide=wide, keep=not flags[lv][i].all(): write(lv, i, wide, keep, 0)
            if lv + 1 < nlev:
                waiting[lv] = wide

    unflagged, last = set(), [time.perf_counter()]  # levels with rows on disk not yet flagged done; last flush

    def flush() -> None:  # each such level's done flags in one write, then the filled count of the rows flagged
        for lv in sorted(unflagged):
            dones[lv][...] = flags[lv]
        if 0 in unflagged:
            g.attrs["nodata"] = {**g.attrs["nodata"], "filled": state["filled"]}
        unflagged.clear()
        last[0] = time.perf_counter()

    def done(res) -> None:
        lv, i, wrote, nfill = res
        release((lv, i))
        if wrote:
            flags[lv][i, :] = 1
            unflagged.add(lv)
            state["filled"] += nfill if lv == 0 else 0
        if time.perf_counter() - last[0] >= _FLAG_EVERY:
            flush()
        prog(f"level {lv}", lay.blocks(lv), lay.blocks(lv) ** 2)

    try:
        run_ordered(workers, tasks(), done)
    finally:  # (also when interrupted: every row handed to ``done`` is on disk)
        flush()
    if state["filled"] >= src.rows * src.cols:  # (a fresh run fails in the first strip already; this catches resumed ones)
        raise no_valid_sample(src)
    return state["filled"]



