"""Flat ids for the blocks of the M-block pyramid, so per-frame block sets (residency, the
blocks a front draws from, shading blocks, wanted loads) are boolean arrays instead of Python
sets of (level, i, j) tuples.

Block (l, i, j) has id ``offset[l] + i·nb[l] + j`` with ``nb[l] = 2^(L−l)`` blocks per side,
levels stacked finest first — the order in which per-level (nb, nb) grids concatenate.
"""

from __future__ import annotations

import numpy as np

__all__ = ["BlockIndex", "KeepSet"]


class BlockIndex:
    def __init__(self, levels: int, top: int):
        self.nb = [2 ** (top - lv) for lv in range(levels)]
        self.offset = np.cumsum([0] + [n * n for n in self.nb])
        self.size = int(self.offset[-1])
        self._nb = np.asarray(self.nb, np.int64)
        self._keys = [(lv, i, j) for lv, n in enumerate(self.nb) for i in range(n) for j in range(n)]

    def ids(self, level, bi, bj) -> np.ndarray:
        """(n,) int64 ids of blocks (level, bi, bj) (arrays)."""
        level = np.asarray(level, np.int64)
        return self.offset[level] + np.asarray(bi, np.int64) * self._nb[level] + np.asarray(bj, np.int64)

    def id(self, key) -> int:
        lv, i, j = key
        return int(self.offset[lv]) + i * self.nb[lv] + j

    def keys(self, ids) -> list[tuple[int, int, int]]:
        """The (level, i, j) tuples of ``ids``."""
        k = self._keys
        return [k[i] for i in np.asarray(ids).tolist()]

    def mask(self, ids) -> np.ndarray:
        """(size,) bool with ``ids`` set."""
        m = np.zeros(self.size, bool)
        m[ids] = True
        return m

    def grids(self, flat: np.ndarray) -> list[np.ndarray]:
        """Per-level (nb, nb) views of a flat per-block array."""
        return [flat[self.offset[lv]:self.offset[lv + 1]].reshape(n, n) for lv, n in enumerate(self.nb)]

    @staticmethod
    def flat(grids: list[np.ndarray]) -> np.ndarray:
        return np.concatenate([np.asarray(g).ravel() for g in grids])


class KeepSet:
    """``key in keep`` for (level, i, j) keys, over a flat mask plus extra ids (what the GL pool
    must not evict: the blocks the current fronts and shading use)."""

    def __init__(self, index: BlockIndex, mask: np.ndarray, extra_ids: np.ndarray):
        self.index, self.mask = index, mask.copy()
        self.mask[extra_ids] = True

    def __contains__(self, key) -> bool:
        return bool(self.mask[self.index.id(key)])
