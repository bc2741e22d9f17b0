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

def heights(base: float, vs: float, Z: float, z, out: np.ndarray | None = None) -> np.ndarray:
    """World heights (float64) of stored heights ``z``: base + Z·(z·vs − base). With ``out``
    (float64) the same operations run in place (products and sums commute exactly in IEEE
    arithmetic, so the values are bit-identical) without temporaries."""
    if out is None:
        return base + Z * (np.asarray(z, np.float64) * vs - base)
    np.multiply(z, vs, out=out, dtype=np.float64)  # the float64 product, as asarray(z, float64) * vs
    out -= base
    out *= Z
    out += base
    return out


def errors(vs: float, Z: float, e, out: np.ndarray | None = None) -> np.ndarray:
    """World errors (float64) of stored errors ``e``: e·vs·Z (in place into ``out`` if given)."""
    if out is None:
        return np.asarray(e, np.float64) * vs * Z
    np.multiply(e, vs, out=out, dtype=np.float64)
    out *= Z
    return out


def square_centre(lo: np.ndarray, hi: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    if out is None:
        return (lo + hi) / 2
    np.add(lo, hi, out=out)
    out /= 2
    return out


def edge_centre(lo: np.ndarray, hi: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    valid = np.isfinite(lo)  # edges outside the lattice have no squares: centre height 0
    if out is not None and valid.all():  # the diamonds a walk reaches: (lo + hi) / 2, as below
        return square_centre(lo, hi, out)
    v = np.where(valid, (np.where(valid, lo, 0) + np.where(valid, hi, 0)) / 2, 0.0)
    if out is None:
        return v
    out[...] = v
    return out


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
        """``ndarray.take`` semantics (``out``, ``mode``) over the computed float64 values; with
        a float64 ``out`` the values are computed in place (the same operations, no copy)."""
        vals = [s.take(idx, mode=mode) for s in self.src]
        if out is None:
            out = np.empty(np.shape(vals[0]))
        elif out.dtype != np.float64:
            out[...] = self.fn(*vals)
            return out
        return self.fn(*vals, out=out)

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
