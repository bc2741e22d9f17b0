"""The shading pyramid: per-sample slopes and height, seamless across blocks, mip-filtered.

Shading is decoupled from the geometric LOD (RASTeR keeps textures in a mip pyramid matched
to its M-blocks, §3 of Goswami et al. 2010): the renderer samples these maps per pixel at the
level that matches the pixel footprint, so a coarse patch still shades with fine normals and
sub-pixel triangles do not sparkle. Lighting, exaggeration and colour ramps are applied at
view time from the same maps.

``shade/<l>`` holds, for every sample of level-l block (i, j), float16 (M, M, 3):

* ``sx, sy``: the surface slope ∂h/∂x, ∂h/∂y in height units per metre, world axes (x east =
  +col, y north = −row). Level 0 uses Horn's 3 × 3 operator — the one ``gdaldem hillshade``
  uses — on the finest samples, reading the neighbouring blocks across every block border;
* ``t``: (h − zmin)/(zmax − zmin), the height as a fraction of the store's height range.

Level l+1 is level l filtered with the [1 2 1]/4 tent in both axes and decimated (the
vertex-centred box filter of a mip chain), again across block borders. Every value is computed
once on a strip of the global grid and cut into blocks, so the two copies of a shared border
sample are bit-identical. At the outer border the grid is extended by edge replication.

Since store version 3, level 0 is not stored: ``halo/0`` keeps the samples around each
level-0 block (:func:`block_halos`), and :func:`shade0_block` computes the block's level-0
shading from them and its heights on reading — the same compiled expressions on the same
values as the pass below, so bit for bit what version 2 stored. The pass still computes level 0
(the coarser levels are filtered from it) but neither encodes nor writes it.

``shade_block`` is the per-block hypsometric tint kept for stores without a pyramid.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from .store import block_view, shading_params, wide_row

__all__ = ["shade_block", "write_shading", "horn_slopes", "tent_decimate", "shade0_blocks", "shade0_block", "block_halos"]

# elevation fraction → RGB (lowland green, upland ochre, rock grey, snow)
_STOPS = np.array([0.0, 0.18, 0.42, 0.7, 0.88, 1.0])
_RGB = np.array([[64, 112, 70], [110, 150, 82], [186, 172, 120], [140, 122, 104], [170, 165, 160], [245, 245, 250]], np.float32)


def shade_block(h: np.ndarray, dx: float, dy: float, zlo: float, zhi: float, vscale: float = 1.0) -> np.ndarray:
    """(M, M, 3) uint8 hypsometric tint of a block of heights ``h`` (no baked lighting)."""
    t = np.clip((h - zlo) / max(zhi - zlo, 1e-6), 0, 1)
    return np.stack([np.interp(t, _STOPS, _RGB[:, c]) for c in range(3)], axis=-1).astype(np.uint8)


def horn_slopes(g: np.ndarray, dx: float, dy: float) -> tuple[np.ndarray, np.ndarray]:
    """Horn's slopes of the interior of a padded grid ``g`` ((R+2) × (C+2), rows southward):
    (∂h/∂x east, ∂h/∂y north), each (R, C) float32, per metre."""
    g = g.astype(np.float32, copy=False)
    a, b, c = g[:-2, :-2], g[:-2, 1:-1], g[:-2, 2:]
    d, f = g[1:-1, :-2], g[1:-1, 2:]
    gg, h, i = g[2:, :-2], g[2:, 1:-1], g[2:, 2:]
    sx = ((c + 2 * f + i) - (a + 2 * d + gg)) / (8 * dx)
    sy = ((a + 2 * b + c) - (gg + 2 * h + i)) / (8 * dy)
    return sx, sy


def tent_decimate(g: np.ndarray) -> np.ndarray:
    """[1 2 1]/4 ⊗ [1 2 1]/4 filter of the interior of a padded grid ((2R+1)+2)² … then every
    other sample: (R+1, C+1, ...) from ((2R+1)+2, (2C+1)+2, ...). Only the kept samples are
    filtered (each by the same float32 expression as filtering all and then decimating)."""
    g = g.astype(np.float32, copy=False)
    v = g[:-2:2] * 0.25 + g[1:-1:2] * 0.5 + g[2::2] * 0.25
    return v[:, :-2:2] * 0.25 + v[:, 1:-1:2] * 0.5 + v[:, 2::2] * 0.25


_LUT: list = []


def shade0_wide(prev: np.ndarray | None, cur: np.ndarray, nxt: np.ndarray | None, dx: float, dy: float, zlo: float,
                rng: float) -> np.ndarray:
    """Level-0 shading (M, W, 3) float16 of the wide height rows ``cur`` (M, W) float32, from
    the block rows above and below (None beyond the border: edge replication): Horn's slopes
    (:func:`horn_slopes`) and (h − zlo)/rng, the same float32 expressions, in one compiled pass."""
    M = cur.shape[0]
    return _shade0(prev[M - 2] if prev is not None else None, cur, nxt[1] if nxt is not None else None, dx, dy, zlo, rng)


def _shade0(above: np.ndarray | None, cur: np.ndarray, below: np.ndarray | None, dx: float, dy: float, zlo: float,
            rng: float, out: np.ndarray | None = None) -> np.ndarray:
    """:func:`shade0_wide` from the one grid row above ``cur`` and the one below (None beyond
    the border), into ``out`` (float16 (M, W, 3), C-contiguous) when given."""
    from .rowkernels import horn_row

    M = cur.shape[0]
    above = above if above is not None else cur[0]
    below = below if below is not None else cur[M - 1]
    out = np.empty(cur.shape + (3,), np.float16) if out is None else out
    horn_row(np.ascontiguousarray(above), np.ascontiguousarray(cur, np.float32), np.ascontiguousarray(below),
             np.float32(8 * dx), np.float32(8 * dy), np.float32(zlo), np.float32(rng), out.view(np.uint16))
    return out


def shade0_blocks(above: np.ndarray | None, blocks: np.ndarray, below: np.ndarray | None, dx: float, dy: float, zlo: float,
                  rng: float, out: np.ndarray | None = None) -> np.ndarray:
    """:func:`_shade0` of the wide rows the block row ``blocks`` (nb, M, M) float32,
    C-contiguous, spans — what it gives for ``wide_row(blocks)`` — read from the blocks
    (:func:`rowkernels.horn_blocks`: no wide copy of the row)."""
    from .rowkernels import _gather_row, horn_blocks

    nb, M = blocks.shape[0], blocks.shape[1]
    W = nb * (M - 1) + 1
    above = above if above is not None else _gather_row(blocks, 0, np.empty(W, np.float32))  # the row's own first
    below = below if below is not None else _gather_row(blocks, M - 1, np.empty(W, np.float32))  # and last, at the edges
    out = np.empty((M, W, 3), np.float16) if out is None else out
    horn_blocks(np.ascontiguousarray(above, np.float32), blocks, np.ascontiguousarray(below, np.float32),
                np.float32(8 * dx), np.float32(8 * dy), np.float32(zlo), np.float32(rng), out.view(np.uint16))
    return out


def grid_row(blocks: np.ndarray, r: int) -> np.ndarray:
    """Grid row ``r`` of a block row ``blocks`` (nb, M, M), any strides, as one wide float32 row
    (nb·(M-1)+1,) (blocks share their border column; numpy's :func:`rowkernels._gather_row`)."""
    return np.concatenate([blocks[:, r, :-1].reshape(-1), blocks[-1, r, -1:]]).astype(np.float32, copy=False)


def block_halos(above: np.ndarray | None, blocks: np.ndarray, below: np.ndarray | None) -> np.ndarray:
    """``halo/0``'s block row (nb, 4, M+2) float32 (the layout in :mod:`.store`) of the level-0
    block row ``blocks`` (nb, M, M), from the grid rows just above and below it (wide, (W,);
    None beyond the border, where the block row's own first or last row stands in, as the
    shading pass replicates it). Columns beyond the grid's ends are clamped to them."""
    nb, M = blocks.shape[0], blocks.shape[1]
    W = nb * (M - 1) + 1
    top = np.asarray(above, np.float32) if above is not None else grid_row(blocks, 0)
    bot = np.asarray(below, np.float32) if below is not None else grid_row(blocks, M - 1)
    c0 = np.arange(nb) * (M - 1)
    out = np.empty((nb, 4, M + 2), np.float32)
    cols = np.clip(c0[:, None] + np.arange(-1, M + 1), 0, W - 1)
    out[:, 0], out[:, 1] = top[cols], bot[cols]
    for k, c in ((2, np.clip(c0 - 1, 0, W - 1)), (3, np.clip(c0 + M, 0, W - 1))):
        out[:, k, 0], out[:, k, M + 1] = top[c], bot[c]
    out[1:, 2, 1:M + 1], out[0, 2, 1:M + 1] = blocks[:-1, :, M - 2], blocks[0, :, 0]  # column c0-1: block j-1's column M-2
    out[:-1, 3, 1:M + 1], out[-1, 3, 1:M + 1] = blocks[1:, :, 1], blocks[-1, :, M - 1]  # column c0+M: block j+1's column 1
    return out


def shade0_block(halo: np.ndarray, h: np.ndarray, dx: float, dy: float, zlo: float, rng: float,
                 out: np.ndarray | None = None) -> np.ndarray:
    """Level-0 shading (M, M, 3) float16 of one block from its heights ``h`` (M, M) and its
    halo (4, M+2) (:func:`block_halos`): Horn's operator on the padded block
    (:func:`rowkernels.horn_padded`), into ``out`` (C-contiguous) when given."""
    from .rowkernels import horn_padded

    M = h.shape[0]
    p = np.empty((M + 2, M + 2), np.float32)
    p[1:M + 1, 1:M + 1] = h
    p[0], p[M + 1] = halo[0], halo[1]
    p[1:M + 1, 0], p[1:M + 1, M + 1] = halo[2, 1:M + 1], halo[3, 1:M + 1]
    out = np.empty((M, M, 3), np.float16) if out is None else out
    horn_padded(p, np.float32(8 * dx), np.float32(8 * dy), np.float32(zlo), np.float32(rng), out.view(np.uint16))
    return out


def tent_wide(rows: dict, i: int, out: np.ndarray | None = None) -> np.ndarray:
    """Block row i of level l (M, (W-1)/2+1, 3) float16 from the float16 wide rows 2i-1 .. 2i+2
    of level l-1 (``rows``: a dict, entries beyond the border absent): :func:`tent_decimate`
    at the kept samples only, in one compiled pass; into ``out`` (C-contiguous) when given."""
    from .rowkernels import half_lut, tent_row

    if not _LUT:
        _LUT.append(half_lut())
    a, m0, m1, b = (rows.get(k) for k in (2 * i - 1, 2 * i, 2 * i + 1, 2 * i + 2))
    M, W = m0.shape[0], m0.shape[1]
    above = a[M - 2: M - 1] if a is not None else m0[:1]
    below = b[0:2] if b is not None else np.concatenate([m1[M - 1:]] * 2)  # global rows (2i+2)(M-1) + 0, 1
    out = np.empty((M, (W - 1) // 2 + 1, 3), np.float16) if out is None else out
    u = [np.ascontiguousarray(x).view(np.uint16) for x in (above, m0, m1, below)]
    tent_row(*u, _LUT[0], out.view(np.uint16))
    return out


def _shade0_row(above, cur, below, dx: float, dy: float, zlo: float, rng: float, dst, i: int, out=None) -> np.ndarray:
    """Level-0 shading of block row i (:func:`_shade0`, into ``out`` when given); writes
    ``dst[i]``, returns the row."""
    out = _shade0(above, cur, below, dx, dy, zlo, rng, out)
    M = cur.shape[0]
    dst.write(i, 0, block_view(out, (cur.shape[1] - 1) // (M - 1), M))
    return out


def _shade0_blocks_row(above, blocks, below, dx: float, dy: float, zlo: float, rng: float, dst, i: int, out=None) -> np.ndarray:
    """:func:`_shade0_row` of a block row given as its blocks (:func:`shade0_blocks`)."""
    out = shade0_blocks(above, blocks, below, dx, dy, zlo, rng, out)
    M = blocks.shape[1]
    dst.write(i, 0, block_view(out, blocks.shape[0], M))
    return out


def _tent_row(rows: dict, i: int, dst, out=None) -> np.ndarray:
    """Level-l block row i (:func:`tent_wide`, into ``out`` when given); writes ``dst[i]``,
    returns the row."""
    out = tent_wide(rows, i, out)
    M = out.shape[0]
    dst.write(i, 0, block_view(out, (out.shape[1] - 1) // (M - 1), M))
    return out


def write_shading(store, g, zlo: float, zhi: float, progress: Callable[[str, int, int], None], workers: int | None = None,
                  row_hook: Callable[[int, np.ndarray], None] | None = None, edges: dict | None = None,
                  writers: list | None = None) -> None:
    """Compute ``shade/<l>`` for every level of ``store`` into the zarr group ``g``.

    Level 0 block rows are computed by worker threads, in order; each finished row (float16, as
    stored) feeds the coarser levels in memory — block row i of level l is a task of its own,
    submitted (ahead of the next level-0 row) once the rows 2i-1 .. 2i+2 of level l-1 are
    finished (:func:`workers.run_ready`), so no worker waits for another and no level is read
    back. Every output sample is the same float32 expression as on the whole grid.
    ``row_hook(i, blocks)``, when given, also runs on the worker for every level-0 block row
    (``prepare`` computes the exact errors that need the whole level 0 there). ``edges``, when
    given ({i: (grid row 1, grid row M-2) of level-0 block row i}, what ``prepare`` keeps from
    its pyramid pass: 2 grid rows a block row), lets each worker read and decode its own row;
    without it the rows are read here, in order, and each task gets its neighbours' edge rows.
    ``writers`` (one a level, with ``write(i, j0, blocks)``) take the finished blocks instead
    of ``g``'s arrays (``verify`` compares them with the stored ones)."""
    from .workers import resolve_workers, run_ready

    sp = _ShadingPass(store, g, zlo, zhi, row_hook, edges, writers=writers)
    total = sum(sp.lay.blocks(lv) for lv in range(sp.lay.levels))
    run_ready(resolve_workers(workers), sp.first(), sp.then, lambda res: progress("shading", 1, total),
              depth=1 if edges is not None else 2)  # bounded: a float16 row is 50 MB at 32769²


class _NoWrites:
    """The level-0 "writer" of a store's own pass: level 0 is computed for the coarser levels
    and, on reading, from ``halo/0`` (written beside it), not stored."""

    def write(self, i: int, j0: int, blocks: np.ndarray) -> None:
        pass


class _ShadingPass:
    """The tasks of :func:`write_shading` (``first``: level 0, in order; ``then``: the coarser
    rows a finished row completes the inputs of; both called on the submitting thread) and the
    wide-row buffers, reused through a :class:`workers.BufferPool`: a row's buffer goes back
    once every coarser row that reads it is finished, a level-0 task's height rows once it is."""

    def __init__(self, store, g, zlo: float, zhi: float, row_hook, edges: dict | None, keep_rows: float = 3.0,
                 writers: list | None = None):
        from .store import ChunkWriter, HaloWriter
        from .workers import BufferPool

        self.store, self.lay, self.hook, self.edges = store, store.layout, row_hook, edges
        self.shade = shading_params(store.spacing, zlo, zhi)  # dx, dy, zlo, rng
        nlev = self.lay.levels
        # level 0 is not stored: its halos are (the level-0 writer only sees the rows ``verify`` compares)
        self.halos = HaloWriter(g) if writers is None else None
        self.writers = writers or [_NoWrites()] + [ChunkWriter(g, f"shade/{lv}") for lv in range(1, nlev)]
        self.rows: list[dict] = [{} for _ in range(nlev)]  # level → {row: float16 wide row}, until its readers are submitted
        self.held: list[dict] = [{} for _ in range(nlev)]  # level → {row: [its buffer, readers not yet finished]}
        self.made = [0] * nlev  # block rows submitted per level (in order)
        M, nb0 = self.lay.M, self.lay.blocks(0)
        # ``keep_rows`` level-0 tasks' buffers (decoded blocks, float16 row) wait for reuse: with one, the
        # coarser rows' and the second worker's buffers were mostly freed and made anew (1.8 GB of fresh,
        # kernel-zeroed pages at 16385²; with three ~0.5 GB, mostly the first of each shape; same peak RSS)
        self.pool = BufferPool(int(keep_rows * (nb0 * M * M * 4 + M * self._wide(0) * 6)))

    def _wide(self, lv: int) -> int:
        return self.lay.blocks(lv) * (self.lay.M - 1) + 1

    def level0(self, k: int, above, cur, below):
        M = self.lay.M
        blocks = block_view(cur, self.lay.blocks(0), M)
        if self.hook is not None:
            self.hook(k, blocks)
        out = self.pool.take((M, self._wide(0), 3), np.float16)
        if self.halos is not None:
            self.halos.write(k, block_halos(above, blocks, below))
        return 0, k, _shade0_row(above, cur, below, *self.shade, self.writers[0], k, out)

    def level0_own(self, k: int):  # reads its own row (``edges``)
        M, nb0, edges = self.lay.M, self.lay.blocks(0), self.edges
        buf = self.pool.take((nb0, M, M), np.float32)
        blocks = np.ascontiguousarray(self.store.get_block_row(0, k, out=buf), np.float32)
        if self.hook is not None:
            self.hook(k, blocks)
        above, below = edges[k - 1][1] if k > 0 else None, edges[k + 1][0] if k + 1 < nb0 else None
        out = self.pool.take((M, self._wide(0), 3), np.float16)
        if self.halos is not None:
            self.halos.write(k, block_halos(above, blocks, below))
        res = _shade0_blocks_row(above, blocks, below, *self.shade, self.writers[0], k, out)
        self.pool.give(buf)
        return 0, k, res

    def coarser(self, lv: int, i: int, inputs: dict):
        out = self.pool.take((self.lay.M, self._wide(lv), 3), np.float16)
        return lv, i, _tent_row(inputs, i, self.writers[lv], out)

    def _inputs(self, lv: int, i: int) -> range:
        """The level lv-1 rows that block row i of level lv reads."""
        return range(max(2 * i - 1, 0), min(2 * i + 3, self.lay.blocks(lv - 1)))

    def _readers(self, lv: int, q: int) -> int:
        """How many block rows of level lv+1 read row q of level lv (rows ⌈(q-2)/2⌉ .. ⌊(q+1)/2⌋)."""
        if lv + 1 >= self.lay.levels:
            return 0
        return min(self.lay.blocks(lv + 1) - 1, (q + 1) // 2) - max(0, (q - 1) // 2) + 1

    def then(self, res) -> list:
        """Book the finished row ``res`` (and free the inputs it was the last reader of); the
        coarser rows whose inputs are now all finished, in order."""
        lv, k, out = res
        if lv > 0:
            for q in self._inputs(lv, k):
                entry = self.held[lv - 1][q]
                entry[1] -= 1
                if entry[1] == 0:
                    self.pool.give(self.held[lv - 1].pop(q)[0])
        n = self._readers(lv, k)
        if n == 0:
            self.pool.give(out)
            return []
        self.held[lv][k] = [out, n]
        below, up, ready = self.rows[lv], lv + 1, []
        below[k] = out
        while self.made[up] < self.lay.blocks(up):
            i = self.made[up]
            if not all(q in below for q in self._inputs(up, i)):
                break
            ready.append(lambda up=up, i=i, inputs={q: below[q] for q in self._inputs(up, i)}: self.coarser(up, i, inputs))
            for q in [q for q in below if q < 2 * i + 1]:  # row i+1 reads rows 2i+1 .. only
                del below[q]
            self.made[up] += 1
        if self.made[up] == self.lay.blocks(up):
            below.clear()
        return ready

    def first(self):
        """Level 0's tasks, in order (without ``edges``: reading the rows here)."""
        nb0, M = self.lay.blocks(0), self.lay.M
        if self.edges is not None:
            for k in range(nb0):
                yield lambda k=k: self.level0_own(k)
            return
        grid = {}
        for i in range(nb0 + 1):
            if i < nb0:
                grid[i] = wide_row(self.store.get_block_row(0, i))
            if i >= 1:
                k, p, n = i - 1, grid.get(i - 2), grid.get(i)
                above, below = p[M - 2].copy() if p is not None else None, n[1].copy() if n is not None else None
                yield lambda k=k, a=above, c=grid[k], b=below: self.level0(k, a, c, b)
                grid.pop(k - 1, None)
