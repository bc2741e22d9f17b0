"""A store's orthophoto at one pyramid level as one image: what a renderer drapes whole over
a mesh that carries no colour of its own (T2's fans, :mod:`massview.systems.roettger`).

The level is the finest whose image side (``2^(n-l) + 1`` samples, the padded grid at that
level) is at most ``max_side``: 4097 by default (a 50 MB RGB image, 67 MB as a mipmapped
texture), the whole orthophoto for stores up to 4097², every 4th sample of a 16385² one.
Image row ``r``, column ``c`` is finest sample row ``r·2^l``, column ``c·2^l``; samples
beyond the input's extent are padding (the renderer discards them).
"""

from __future__ import annotations

import numpy as np

__all__ = ["DRAPE_MAX_SIDE", "drape_level", "color_image"]

DRAPE_MAX_SIDE = 4097


def drape_level(layout, max_side: int = DRAPE_MAX_SIDE) -> int:
    """The finest level of ``layout`` whose image side is at most ``max_side`` (the top level
    where none is)."""
    for lv in range(layout.levels):
        if layout.blocks(lv) * (layout.M - 1) + 1 <= max_side:
            return lv
    return layout.levels - 1


def color_image(store, level: int) -> np.ndarray:
    """The orthophoto colour of ``level`` as one (side, side, 3) uint8 image, block by block
    (blocks share their border samples, which are equal in both); raises ValueError for a
    store without an orthophoto."""
    if not store.has_color:
        raise ValueError(f"{store.path} has no orthophoto (prepare it with --color IMAGE)")
    lay = store.layout
    M, nb = lay.M, lay.blocks(level)
    side = nb * (M - 1) + 1
    out = np.empty((side, side, 3), np.uint8)
    buf = np.empty((M, M, 3), np.uint8)
    for i in range(nb):
        for j in range(nb):
            out[i * (M - 1): i * (M - 1) + M, j * (M - 1): j * (M - 1) + M] = store.get_color(level, i, j, out=buf)
    return out
