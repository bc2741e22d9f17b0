"""The Röttger per-node table of a terrain store (T2), computed once over the whole DEM.

Layout (inside the terrain store's zarr group; ``n`` = log2(padded − 1))::

    attrs["roettger"] = {"version": 1, "C_min": C, "K": C/(2(C-1)), "depths": n-1}
    roettger/d2/<t>   float32 (2^t, 2^t), chunks ≤ 256², for node depths t = 0 .. n-2
                      (edge d = 2^(n-t) ≥ 4 samples): the propagated roughness d2 in height
                      units per sample (the finest nodes, d = 2, never subdivide: not stored)

The attribute is written last, so a store whose table was interrupted reads as "no table".
The table is computed out of core, finest depth first: the local d2 of each depth is read
from the store's decimated pyramid in block-row strips (level l of the pyramid samples every
2^l-th sample, exactly the stride the nodes of edge 2^(l+1) need) and pushed upward with
:func:`massview.lod.roettger.propagate_into`; memory peaks at one depth's array (64 MiB at
depth n-2 of a 16385² DEM) plus one strip.

:class:`RoettgerTable` reads windows of it and counts the bytes read (what a computation rank
of T2 reads: its portion plus a one-node halo).
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable, Iterator

import numpy as np

from ...core.errors import CorruptBlockError, StoreError, describe
from .store import CHUNK_KEYS, TerrainStore

__all__ = ["C_RANGE", "k_factor", "local_d2", "propagate_into", "DEFAULT_C_MIN", "compute_table", "write_table",
           "prepare_roettger", "RoettgerTable", "has_table", "table_from_grid", "iter_table", "TableBuilder",
           "TableWriter"]

DEFAULT_C_MIN = 4.0
C_RANGE = (2.0, 64.0)  # the C for which the level-difference proof holds (lod/roettger.py)


def k_factor(C: float) -> float:
    """Röttger's propagation factor K = C / (2 (C - 1)) for the minimum resolution C."""
    return C / (2.0 * (C - 1.0))


# -- roughness (pure numpy) ----------------------------------------------------------------------
def local_d2(grid: np.ndarray, d: int) -> np.ndarray:
    """Local d2 of the nodes of edge ``d`` over ``grid`` = heights sampled every ``d/2``
    samples, shape (2a+1, 2b+1) → (a, b) float32 (height units per sample)."""
    g = np.asarray(grid, np.float32)
    c00, c01, c10, c11 = g[:-2:2, :-2:2], g[:-2:2, 2::2], g[2::2, :-2:2], g[2::2, 2::2]
    ctr = g[1:-1:2, 1:-1:2]
    dev = np.abs(g[:-2:2, 1:-1:2] - (c00 + c01) * 0.5)
    np.maximum(dev, np.abs(g[2::2, 1:-1:2] - (c10 + c11) * 0.5), out=dev)
    np.maximum(dev, np.abs(g[1:-1:2, :-2:2] - (c00 + c10) * 0.5), out=dev)
    np.maximum(dev, np.abs(g[1:-1:2, 2::2] - (c01 + c11) * 0.5), out=dev)
    np.maximum(dev, np.abs(ctr - (c00 + c11) * 0.5), out=dev)
    np.maximum(dev, np.abs(ctr - (c01 + c10) * 0.5), out=dev)
    return dev / np.float32(d)


def _local_d2_compiled(grid: np.ndarray, d: int) -> np.ndarray:
    """:func:`local_d2` in one compiled pass (the same float32 operations; ingest only, so the
    renderer's use of :func:`table_from_grid` does not load numba)."""
    from .rowkernels import local_d2 as kernel

    g = np.ascontiguousarray(grid, np.float32)
    out = np.empty(((g.shape[0] - 1) // 2, (g.shape[1] - 1) // 2), np.float32)
    kernel(g, d, out)
    return out


def _propagate_compiled(coarse: np.ndarray, fine: np.ndarray, row0: int, K: float) -> None:
    """:func:`propagate_into` in one compiled pass, no temporaries (ingest only, as
    :func:`_local_d2_compiled`)."""
    from .rowkernels import propagate_max

    if coarse.dtype != np.float32 or not coarse.flags.c_contiguous or fine.shape[0] % 2 or fine.shape[1] != 2 * coarse.shape[1]:
        propagate_into(coarse, fine, row0, K)
        return
    propagate_max(coarse, np.ascontiguousarray(fine, np.float32), row0 // 2, np.float32(K))


def propagate_into(coarse: np.ndarray, fine: np.ndarray, row0: int, K: float) -> None:
    """Max-merge ``K × fine`` into ``coarse`` (in place) for every coarse node that a fine node
    lies in or touches along an edge from outside. ``fine`` holds fine node rows
    ``row0 .. row0+h`` (row0 and h even) and all 2N columns; ``coarse`` is (N, N)."""
    f = np.asarray(fine, np.float32) * np.float32(K)
    q0 = row0 // 2
    tl, tr, bl, br = f[0::2, 0::2], f[0::2, 1::2], f[1::2, 0::2], f[1::2, 1::2]
    inside = np.maximum(np.maximum(tl, tr), np.maximum(bl, br))
    _merge(coarse, q0, 0, inside)
    _merge(coarse, q0 - 1, 0, np.maximum(tl, tr))  # top children touch the node above
    _merge(coarse, q0 + 1, 0, np.maximum(bl, br))  # bottom children touch the node below
    left, right = np.maximum(tl, bl), np.maximum(tr, br)
    _merge(coarse, q0, -1, left)  # left children touch the node to the left
    _merge(coarse, q0, 1, right)


def _merge(coarse: np.ndarray, r0: int, dc: int, vals: np.ndarray) -> None:
    """coarse[r0 + i, j + dc] = max(., vals[i, j]) where inside."""
    H, W = coarse.shape
    h, w = vals.shape
    a, b = max(r0, 0), min(r0 + h, H)
    c0, c1 = max(dc, 0), min(w + dc, W)
    if a >= b or c0 >= c1:
        return
    dst = coarse[a:b, c0:c1]
    np.maximum(dst, vals[a - r0: b - r0, c0 - dc: c1 - dc], out=dst)


VERSION = 1


def table_from_grid(h: np.ndarray, C_min: float) -> list[np.ndarray]:
    """The propagated d2 of depths 0 .. m-2 of an in-memory (2^m+1)² grid (the paper's
    overlapping portions build their own quadtree this way)."""
    m = int(np.log2(h.shape[0] - 1))
    K = k_factor(C_min)
    out: list = [None] * max(m - 1, 0)
    pushed = None
    for t in range(m - 1, -1, -1):
        s = 2 ** (m - t - 1)
        cur = local_d2(h[::s, ::s], 2 * s)
        if pushed is not None:
            cur = np.maximum(cur, pushed)
        if t < m - 1:
            out[t] = cur
        pushed = np.zeros((2 ** (t - 1),) * 2, np.float32) if t >= 1 else None
        if pushed is not None:
            propagate_into(pushed, cur, 0, K)
    return out


def _grid_strips(store: TerrainStore, level: int) -> Iterator[tuple[int, np.ndarray]]:
    """(first grid row, strip) over the whole grid sampled every 2^level samples."""
    lay = store.layout
    M = lay.M
    if level > lay.L:
        step = 2 ** (level - lay.L)
        yield 0, store.get_block(lay.L, 0, 0)[::step, ::step]
        return
    for i in range(lay.blocks(level)):
        row = store.get_block_row(level, i)
        strip = np.concatenate([row[0]] + [b[:, 1:] for b in row[1:]], axis=1)
        yield i * (M - 1), strip


def iter_table(store: TerrainStore, C_min: float = DEFAULT_C_MIN,
               progress: Callable[[str, int, int], None] | None = None) -> Iterator[tuple[int, np.ndarray]]:
    """(depth t, propagated d2 (2^t, 2^t) float32) for t = n-2 .. 0, finest first.

    The propagated array of depth t is built in place: the finer depth's contribution first,
    then each strip's local d2 max-merged into its rows, so memory holds one depth's array and
    the next coarser one (320 MiB at a 32769² DEM) plus one strip."""
    lay = store.layout
    n = lay.n
    if not (C_RANGE[0] <= C_min <= C_RANGE[1]):
        raise StoreError(f"--min-C must be in [{C_RANGE[0]:g}, {C_RANGE[1]:g}], got {C_min}")
    K = k_factor(C_min)
    cur = np.zeros((2 ** (n - 2), 2 ** (n - 2)), np.float32) if n >= 2 else None
    for t in range(n - 1, -1, -1):
        d, level = 2 ** (n - t), n - t - 1
        for g0, strip in _grid_strips(store, level):
            a = _local_d2_compiled(strip, d)
            if t == n - 1:
                if cur is not None:
                    propagate_into(cur, a, g0 // 2, K)
            else:  # max(local, pushed), row band by row band
                band = cur[g0 // 2: g0 // 2 + a.shape[0]]
                np.maximum(a, band, out=band)
        if t < n - 1:
            done, cur = cur, (np.zeros((2 ** (t - 1), 2 ** (t - 1)), np.float32) if t >= 1 else None)
            if cur is not None:
                propagate_into(cur, done, 0, K)
            yield t, done
            del done
        if progress:
            progress("roettger", 1, n)


class TableBuilder:
    """The table built during ``prepare``'s pyramid pass, from the wide block rows of every
    level as they are made (no read-back): :meth:`strip` (any thread) folds a strip's local d2
    into its depth — max-merged, or pushed into depth n-2 for the level-0 strips, as
    :func:`iter_table` does, under a lock because neighbouring strips' pushes share rows; max
    is exact, so the order does not matter — and :meth:`depths` finishes the propagation,
    finest depth first. Holds every depth at once: 4/3 of depth n-2 (85 MiB at 16385²,
    341 MiB at 32769²); the propagation runs in bands of 512 rows, so its temporaries stay small
    (whole-array temporaries were 2× the finest depth)."""

    def __init__(self, layout, C_min: float = DEFAULT_C_MIN):
        import threading

        self.lay, self.C_min, self.K = layout, C_min, k_factor(C_min)
        self.d2: list = [np.zeros((2**t, 2**t), np.float32) for t in range(layout.n - 1)]
        self.top = None
        self._lock = threading.Lock()

    @property
    def nbytes(self) -> int:
        """The bytes of the depths not yet handed out by :meth:`depths`."""
        return sum(a.nbytes for a in self.d2 if a is not None)

    def strip(self, level: int, g0: int, wide: np.ndarray) -> None:
        """The wide rows of one block row of ``level`` (its first grid row ``g0``)."""
        n = self.lay.n
        t = n - 1 - level
        a = _local_d2_compiled(wide, 2 ** (level + 1))
        with self._lock:
            if t == n - 1:
                if n >= 2:
                    _propagate_compiled(self.d2[n - 2], a, g0 // 2, self.K)
            else:
                band = self.d2[t][g0 // 2: g0 // 2 + a.shape[0]]
                np.maximum(a, band, out=band)
        if level == self.lay.L:
            self.top = wide

    def depths(self, progress: Callable[[str, int, int], None] | None = None) -> Iterator[tuple[int, np.ndarray]]:
        """(depth t, propagated d2) for t = n-2 .. 0, as :func:`iter_table` gives them."""
        lay, n = self.lay, self.lay.n
        for level in range(lay.L + 1, n):  # nodes coarser than the top block: its samples, strided
            step = 2 ** (level - lay.L)
            self.strip(level, 0, np.ascontiguousarray(self.top[::step, ::step]))
        for t in range(n - 2, -1, -1):
            done, self.d2[t] = self.d2[t], None
            for r in range(0, done.shape[0] if t >= 1 else 0, 512):  # in row bands: bounded temporaries, same maxima
                _propagate_compiled(self.d2[t - 1], done[r: r + 512], r, self.K)
            if progress:
                progress("roettger", 1, n - 1)
            yield t, done
            del done


def compute_table(store: TerrainStore, C_min: float = DEFAULT_C_MIN,
                  progress: Callable[[str, int, int], None] | None = None) -> list[np.ndarray]:
    """The propagated d2 of depths 0 .. n-2 (list index = depth)."""
    out: list[np.ndarray] = [None] * max(store.layout.n - 1, 0)  # type: ignore[list-item]
    for t, a in iter_table(store, C_min, progress):
        out[t] = a
    return out


def write_table(target, d2, C_min: float, workers: int | None = None) -> None:
    """Write the table into the store ``target`` (a path, or the open zarr group of a prepare
    in progress), arrays first, the attribute last. ``d2``: the list of :func:`compute_table`
    or the (depth, array) pairs of :func:`iter_table` / :meth:`TableBuilder.depths` (written as
    they come). Each array is created through zarr, then its chunk rows are encoded and
    written by ``workers`` threads (None/0: every core) with :class:`store.ArrayChunkWriter`
    — the files ``arr[...] = a`` writes — while this thread makes the next depth (the
    propagation of :meth:`TableBuilder.depths` runs in the generator); a depth's array is
    dropped once its rows are written."""
    import zarr

    from .store import array_chunk_writer
    from .workers import resolve_workers, run_ordered

    g = zarr.open_group(str(target), mode="r+") if isinstance(target, (str, Path)) else target
    g.attrs["roettger"] = None  # "no table" until every array is written
    pairs = enumerate(d2) if isinstance(d2, list) else d2
    depths = [0]

    def tasks():
        for t, a in pairs:
            arr = _create_depth(g, t, a.shape)
            w = array_chunk_writer(arr)
            depths[0] += 1
            if w is None or a.dtype != w.dtype:  # (not a local store: through zarr)
                yield lambda arr=arr, a=a: arr.__setitem__(Ellipsis, a)
                continue
            rows, cols = w.grid
            for i in range(rows):
                yield lambda w=w, a=a, i=i, cols=cols: w.write(a, ((i, j) for j in range(cols)))
            del a

    run_ordered(resolve_workers(workers), tasks())
    g.attrs["roettger"] = {"version": VERSION, "C_min": float(C_min), "K": k_factor(C_min), "depths": depths[0]}


class TableWriter:
    """:func:`write_table` on a thread of its own, so that a prepare's shading pass runs beside
    it (the table's chunks are mostly zstd encoding, which leaves the shading pass's idle core
    time used); :meth:`join` waits for it and raises its error, if any. The resume contract is
    :func:`write_table`'s: the attribute is written last, once every array is on disk."""

    def __init__(self, target, d2, C_min: float, workers: int | None = None):
        import threading

        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, args=(target, d2, C_min, workers), name="roettger-table")
        self._thread.start()

    def _run(self, target, d2, C_min: float, workers: int | None) -> None:
        try:
            write_table(target, d2, C_min, workers)
        except BaseException as e:  # noqa: BLE001 - raised by join, on the caller's thread
            self._error = e

    def join(self) -> None:
        self._thread.join()
        if self._error is not None:
            raise self._error


TABLE_CODEC = {"cname": "zstd", "clevel": 2, "shuffle": "shuffle", "typesize": 4}  # (blosc's; see _create_depth)


def _create_depth(g, t: int, shape: tuple):
    """The (empty) array ``roettger/d2/<t>``: float32, chunks ≤ 256², blosc zstd 2 + shuffle
    (lossless; blosc's zstd 3 before issue 20's eleventh round, same decoded table: level 2
    encodes 197 vs 94 MB/s on one core, 64 chunks of the 16385² store's finest depth, for 1.7 %
    more bytes)."""
    from zarr.codecs import BloscCodec

    ch = (min(shape[0], 256), min(shape[1], 256))
    return g.create_array(f"roettger/d2/{t}", shape=shape, chunks=ch, dtype="float32", overwrite=True,
                          compressors=BloscCodec(**TABLE_CODEC), chunk_key_encoding=CHUNK_KEYS)


def prepare_roettger(path, C_min: float = DEFAULT_C_MIN, progress=None) -> dict:
    """Compute and write the table of an existing complete store; returns its attribute. Holds
    the store's writer lock (:func:`rebuild.writing`) meanwhile."""
    from ..rebuild import writing

    with writing(path):
        store = TerrainStore(path)
        write_table(path, compute_table(store, C_min, progress), C_min)
        return dict(TerrainStore(path).attrs["roettger"])


def has_table(store: TerrainStore) -> bool:
    meta = store.attrs.get("roettger")
    return bool(meta) and meta.get("version") == VERSION and meta.get("depths") == max(store.layout.n - 1, 0)


class RoettgerTable:
    """Windowed reads of a store's table; ``bytes_read`` counts the float32 bytes delivered."""

    def __init__(self, store: TerrainStore):
        if not has_table(store):
            raise StoreError(f"{store.path}: no Röttger table (T2's per-node roughness); compute it with "
                             f"`massview prepare roettger {store.path}` (stores prepared by this massview have it)")
        meta = store.attrs["roettger"]
        self.C_min, self.K = float(meta["C_min"]), float(meta["K"])
        self.depths = int(meta["depths"])
        self._arrays = [store.array(f"roettger/d2/{t}") for t in range(self.depths)]
        self.path = store.path
        self.bytes_read = 0

    def _bad_chunk(self, t: int, r0: int, r1: int, c0: int, c1: int, err: Exception) -> str:
        """The message for a window that does not decode: the first of its chunks that does not."""
        arr = self._arrays[t]
        ch, where = tuple(arr.chunks), None
        for ci in range(r0 // ch[0], -(-r1 // ch[0])):
            for cj in range(c0 // ch[1], -(-c1 // ch[1])):
                try:
                    arr[ci * ch[0]:(ci + 1) * ch[0], cj * ch[1]:(cj + 1) * ch[1]]
                except Exception as e:  # noqa: BLE001
                    where, err = (ci, cj), e
                    break
            if where:
                break
        why = describe(err)
        f = self.path / "roettger" / "d2" / str(t) / arr.metadata.encode_chunk_key(where) if where else None
        return (f"{self.path}: the Röttger table array roettger/d2/{t} does not decode "
                f"{f'at chunk {where} ({why}); the file {f} is damaged' if f else f'({why}); the store is damaged'} — "
                f"re-run `massview prepare roettger {self.path}` (or prepare with --overwrite)")

    def window(self, t: int, r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
        """d2 of depth ``t`` rows r0..r1-1, cols c0..c1-1 (clipped to the grid)."""
        N = 2**t
        r0, r1, c0, c1 = max(r0, 0), min(r1, N), max(c0, 0), min(c1, N)
        try:
            a = np.asarray(self._arrays[t][r0:r1, c0:c1])
        except Exception as e:  # noqa: BLE001 - codec errors come in many types: name the chunk file
            raise CorruptBlockError(self._bad_chunk(t, r0, r1, c0, c1, e)) from None
        self.bytes_read += a.nbytes
        return a
