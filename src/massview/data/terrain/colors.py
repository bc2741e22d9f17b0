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
    other sample: (R+1, C+1, ...) from ((2R+1)+2, (2C+1)+2, ...)."""
    g = g.astype(np.float32, copy=False)
    v = g[:-2] * 0.25 + g[1:-1] * 0.5 + g[2:] * 0.25
    h = v[:, :-2] * 0.25 + v[:, 1:-1] * 0.5 + v[:, 2:] * 0.25
    return h[::2, ::2]


def _strip(rows_of: Callable[[int], np.ndarray], nb: int, M: int, i: int, rows: tuple[int, int]) -> np.ndarray:
    """Global-grid rows [r0, r1) relative to block row i's first row (reaching into the block
    rows before and after, clamped at the domain border = edge replication), full width, with
    one edge-replicated column on both sides."""
    span = M - 1
    gr = np.clip(i * span + np.arange(*rows), 0, nb * span)
    bi = np.minimum(gr // span, nb - 1)
    s = np.stack([rows_of(b)[r - b * span] for b, r in zip(bi.tolist(), gr.tolist())])
    return np.concatenate([s[:, :1], s, s[:, -1:]], axis=1)


class _RowCache:
    """Block rows of one pyramid level as wide arrays (M, nb·(M-1)+1, ...), read once each."""

    def __init__(self, read: Callable[[int], np.ndarray]):
        self.read, self.rows = read, {}

    def __call__(self, bi: int) -> np.ndarray:
        if bi not in self.rows:
            if len(self.rows) > 3:
                self.rows.pop(min(self.rows))
            blocks = self.read(bi)
            self.rows[bi] = np.concatenate([blocks[j, :, :-1] for j in range(len(blocks))] + [blocks[-1, :, -1:]], axis=1)
        return self.rows[bi]


def _cut(strip: np.ndarray, nb: int, M: int) -> np.ndarray:
    """(M, W, ...) global rows of one block row → (nb, M, M, ...) blocks."""
    return np.stack([strip[:, j * (M - 1): j * (M - 1) + M] for j in range(nb)])


def write_shading(store, g, zlo: float, zhi: float, progress: Callable[[str, int, int], None]) -> None:
    """Compute ``shade/<l>`` for every level of ``store`` into the zarr group ``g``."""
    lay = store.layout
    M, dx, dy = lay.M, *store.spacing
    rng = max(zhi - zlo, 1e-6)
    total = sum(lay.blocks(lv) for lv in range(lay.levels))
    nb = lay.blocks(0)
    rows = _RowCache(lambda bi: store.get_block_row(0, bi))
    dst = g["shade/0"]
    for i in range(nb):
        s = _strip(rows, nb, M, i, (-1, M + 1))  # (M+2, W+2)
        sx, sy = horn_slopes(s, dx, dy)
        t = (s[1:-1, 1:-1] - zlo) / rng
        dst[i] = _cut(np.stack([sx, sy, t], axis=-1), nb, M).astype(np.float16)
        progress("shading", 1, total)
    for lv in range(1, lay.levels):
        nb, src, dst = lay.blocks(lv), g[f"shade/{lv - 1}"], g[f"shade/{lv}"]
        rows = _RowCache(lambda bi, src=src: np.asarray(src[bi]).astype(np.float32))
        for i in range(nb):
            s = _strip(rows, 2 * nb, M, 2 * i, (-1, 2 * (M - 1) + 2))  # level lv-1 rows around block row i
            dst[i] = _cut(tent_decimate(s), nb, M).astype(np.float16)
            progress("shading", 1, total)
