"""Compact per-level columns of the K-patch hierarchy (issue 20).

The walk (:mod:`.kpatch_walk`, :mod:`.kpatch_top`) gathers float64 world values per diamond —
sphere centre height, error, z-range — as ``column[ids]``. A :class:`Lazy` column keeps the
values as stored (float32 heights and errors of the terrain store) and computes the float64
world values on indexing, with exactly the operations the eager float64 arrays were built with,
so every value is bit-identical while a 32769² hierarchy holds ~118 MiB instead of ~290.
"""

from __future__ import annotations

import numpy as np

__all__ = ["Lazy", "heights", "errors", "square_centre", "edge_centre"]

def heights(base: float, vs: float, Z: float, z) -> np.ndarray:
    """World heights (float64) of stored heights ``z``: base + Z·(z·vs − base)."""
    return base + Z * (np.asarray(z, np.float64) * vs - base)


def errors(vs: float, Z: float, e) -> np.ndarray:
    """World errors (float64) of stored errors ``e``: e·vs·Z."""
    return np.asarray(e, np.float64) * vs * Z


def square_centre(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    return (lo + hi) / 2


def edge_centre(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    valid = np.isfinite(lo)  # edges outside the lattice have no squares: centre height 0
    return np.where(valid, (np.where(valid, lo, 0) + np.where(valid, hi, 0)) / 2, 0.0)


class Lazy:
    """One level's float64 column computed on indexing: ``fn(*(s[idx] for s in src))`` over
    compact arrays ``src`` (stored float32 heights and errors), or over other :class:`Lazy`
    columns (sphere centre heights from the z-range). The operations are those of the eager
    float64 arrays it replaces, so every value is bit-identical; a 32769² hierarchy holds
    ~118 MiB instead of ~290 (issue 20). Supports what the walk and the tests use:
    ``col[idx]``, ``col.take(idx, out=, mode=)``, ``dtype`` (float64), ``ravel()``, ``shape``,
    ``len``, ``min()``, ``max()`` and ``np.asarray(col)`` (the whole level, float64)."""

    __slots__ = ("fn", "src")

    def __init__(self, fn, *src):
        self.fn, self.src = fn, src

    def __getitem__(self, idx) -> np.ndarray:
        return self.fn(*(s[idx] for s in self.src))

    dtype = np.dtype(np.float64)  # what indexing yields

    def take(self, idx, out: np.ndarray | None = None, mode: str = "raise") -> np.ndarray:
        """``ndarray.take`` semantics (``out``, ``mode``) over the computed float64 values."""
        v = self.fn(*(s.take(idx, mode=mode) for s in self.src))
        if out is None:
            return v
        out[...] = v
        return out

    def ravel(self) -> "Lazy":
        return Lazy(self.fn, *(s.ravel() for s in self.src))

    @property
    def shape(self) -> tuple[int, ...]:
        return self.src[0].shape

    def __len__(self) -> int:
        return self.shape[0]

    def __array__(self, dtype=None, copy=None) -> np.ndarray:
        a = self[...]
        return a if dtype is None else a.astype(dtype)

    def min(self) -> float:
        return self[...].min()

    def max(self) -> float:
        return self[...].max()
