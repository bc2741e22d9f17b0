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

``shade_block`` is the per-block hypsometric tint kept for stores without a pyramid.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from .store import block_view, wide_row

__all__ = ["shade_block", "write_shading", "horn_slopes", "tent_decimate"]

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
            rng: float) -> np.ndarray:
    """:func:`shade0_wide` from the one grid row above ``cur`` and the one below (None beyond
    the border)."""
    from .rowkernels import horn_row

    M = cur.shape[0]
    above = above if above is not None else cur[0]
    below = below if below is not None else cur[M - 1]
    out = np.empty(cur.shape + (3,), np.float16)
    horn_row(np.ascontiguousarray(above), np.ascontiguousarray(cur, np.float32), np.ascontiguousarray(below),
             np.float32(8 * dx), np.float32(8 * dy), np.float32(zlo), np.float32(rng), out.view(np.uint16))
    return out


def tent_wide(rows: dict, i: int) -> np.ndarray:
    """Block row i of level l (M, (W-1)/2+1, 3) float16 from the float16 wide rows 2i-1 .. 2i+2
    of level l-1 (``rows``: a dict, entries beyond the border absent): :func:`tent_decimate`
    at the kept samples only, in one compiled pass."""
    from .rowkernels import half_lut, tent_row

    if not _LUT:
        _LUT.append(half_lut())
    a, m0, m1, b = (rows.get(k) for k in (2 * i - 1, 2 * i, 2 * i + 1, 2 * i + 2))
    M, W = m0.shape[0], m0.shape[1]
    above = a[M - 2: M - 1] if a is not None else m0[:1]
    below = b[0:2] if b is not None else np.concatenate([m1[M - 1:]] * 2)  # global rows (2i+2)(M-1) + 0, 1
    out = np.empty((M, (W - 1) // 2 + 1, 3), np.float16)
    u = [np.ascontiguousarray(x).view(np.uint16) for x in (above, m0, m1, below)]
    tent_row(*u, _LUT[0], out.view(np.uint16))
    return out


def _shade0_row(above, cur, below, dx: float, dy: float, zlo: float, rng: float, dst, i: int) -> np.ndarray:
    """Level-0 shading of block row i (:func:`_shade0`); writes ``dst[i]``, returns the row."""
    out = _shade0(above, cur, below, dx, dy, zlo, rng)
    M = cur.shape[0]
    dst.write(i, 0, block_view(out, (cur.shape[1] - 1) // (M - 1), M))
    return out


def _tent_row(rows: dict, i: int, dst) -> np.ndarray:
    """Level-l block row i (:func:`tent_wide`); writes ``dst[i]``, returns the row."""
    out = tent_wide(rows, i)
    M = out.shape[0]
    dst.write(i, 0, block_view(out, (out.shape[1] - 1) // (M - 1), M))
    return out


def write_shading(store, g, zlo: float, zhi: float, progress: Callable[[str, int, int], None], workers: int | None = None,
                  row_hook: Callable[[int, np.ndarray], None] | None = None, edges: dict | None = None) -> None:
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
    without it the rows are read here, in order, and each task gets its neighbours' edge rows."""
    from .store import ChunkWriter
    from .workers import resolve_workers, run_ready

    lay = store.layout
    M, (dx, dy) = lay.M, store.spacing
    rng = max(zhi - zlo, 1e-6)
    total = sum(lay.blocks(lv) for lv in range(lay.levels))
    nb0 = lay.blocks(0)
    writers = [ChunkWriter(g, f"shade/{lv}") for lv in range(lay.levels)]
    rows: list[dict] = [{} for _ in range(lay.levels)]  # level → {row: its float16 wide row}, while a coarser row needs it
    made = [0] * lay.levels  # block rows submitted per level (in order)

    def level0(k: int, above, cur, below):
        if row_hook is not None:
            row_hook(k, block_view(cur, nb0, M))
        return 0, k, _shade0_row(above, cur, below, dx, dy, zlo, rng, writers[0], k)

    def level0_own(k: int):  # reads its own row (``edges``)
        blocks = store.get_block_row(0, k)
        if row_hook is not None:
            row_hook(k, blocks)
        above, below = edges[k - 1][1] if k > 0 else None, edges[k + 1][0] if k + 1 < nb0 else None
        return 0, k, _shade0_row(above, wide_row(blocks), below, dx, dy, zlo, rng, writers[0], k)

    def coarser(lv: int, i: int, inputs: dict):
        return lv, i, _tent_row(inputs, i, writers[lv])

    def then(res) -> list:
        """The coarser rows that the finished row ``res`` completes the inputs of, in order."""
        lv, k, out = res
        if lv + 1 >= lay.levels:
            return []
        below, nbp, up = rows[lv], lay.blocks(lv), lv + 1
        below[k] = out
        ready = []
        while made[up] < lay.blocks(up):
            i = made[up]
            need = range(max(2 * i - 1, 0), min(2 * i + 3, nbp))
            if not all(q in below for q in need):
                break
            ready.append(lambda up=up, i=i, inputs={q: below[q] for q in need}: coarser(up, i, inputs))
            for q in [q for q in below if q < 2 * i + 1]:  # row i+1 needs rows 2i+1 .. only
                del below[q]
            made[up] += 1
        if made[up] == lay.blocks(up):
            below.clear()
        return ready

    def first():
        if edges is not None:
            for k in range(nb0):
                yield lambda k=k: level0_own(k)
            return
        grid = {}
        for i in range(nb0 + 1):
            if i < nb0:
                grid[i] = wide_row(store.get_block_row(0, i))
            if i >= 1:
                k, p, n = i - 1, grid.get(i - 2), grid.get(i)
                above, below = p[M - 2].copy() if p is not None else None, n[1].copy() if n is not None else None
                yield lambda k=k, a=above, c=grid[k], b=below: level0(k, a, c, b)
                grid.pop(k - 1, None)

    run_ready(resolve_workers(workers), first(), then, lambda res: progress("shading", 1, total),
              depth=1 if edges is not None else 2)  # bounded: a float16 row is 50 MB at 32769²
