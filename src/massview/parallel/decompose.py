"""Decompositions: which pixels and which data each rank renders.

Sort-first layouts split the image (names as in Goswami et al. 2010, §5 / Fig. 7):

* ``horizontal`` — the screen is partitioned along the horizontal axis: N side-by-side
  columns (full height);
* ``vertical`` — partitioned along the vertical axis: N stacked rows (full width);
* ``grid`` — rows × cols tiles (chosen for N as the factorization closest to the image
  aspect, or given);
* ``kd`` — a weighted recursive split of the screen: per-item screen rectangles and weights
  (e.g. triangle counts) are spread over a grid of 8-px cells and each node is cut where the
  weight on either side matches the ranks it gets;
* ``balanced`` — the massive-model system's load-balanced frustum division (Revanth &
  Narayanan 2012, Algorithm 1, :mod:`massview.lod.split`): split-plane sweep over the items'
  screen footprints, alternating vertical/horizontal, for any rank count (``kd`` with
  ``alternate=True`` is the same).

Sort-last gives rank i the database range R_i = [i/N, (i+1)/N) over the full frame.
"""

from __future__ import annotations

import math

import numpy as np

from ..core.camera import Viewport
from ..core.errors import ConfigError
from ..lod.split import balanced_tiles

__all__ = [
    "SORT_FIRST_LAYOUTS",
    "parse_decomposition",
    "grid_shape",
    "grid_tiles",
    "sort_first_tiles",
    "kd_tiles",
    "sort_last_ranges",
    "parse_wall",
]

SORT_FIRST_LAYOUTS = ("horizontal", "vertical", "grid", "kd", "balanced")
_CELL = 8


def parse_decomposition(spec: str, sort_last_modes: tuple[str, ...] = ()) -> tuple[str, str]:
    """``sort-first[:LAYOUT]`` or ``sort-last[:MODE]`` → (kind, layout-or-mode); a bare
    ``sort-first`` is ``sort-first:horizontal``."""
    kind, _, sub = spec.partition(":")
    if kind == "sort-first" and (sub == "" or sub in SORT_FIRST_LAYOUTS):
        return kind, sub or SORT_FIRST_LAYOUTS[0]
    if kind == "sort-last" and (sub == "" or sub in sort_last_modes):
        return kind, sub or (sort_last_modes[0] if sort_last_modes else "")
    choices = [f"sort-first:{s}" for s in SORT_FIRST_LAYOUTS] + (
        [f"sort-last:{m}" for m in sort_last_modes] if sort_last_modes else ["sort-last"])
    raise ConfigError(f"--decomposition {spec!r} is not available for this scene; use one of {', '.join(choices)}")


def grid_shape(n: int, width: int, height: int) -> tuple[int, int]:
    """(rows, cols) with rows*cols == n whose tiles are closest to square."""
    best = None
    for rows in range(1, n + 1):
        if n % rows:
            continue
        cols = n // rows
        score = abs(math.log((width / cols) / (height / rows)))
        if best is None or score < best[0]:
            best = (score, rows, cols)
    return best[1], best[2]


def _cuts(lo: int, hi: int, n: int) -> list[int]:
    return [lo + ((hi - lo) * i) // n for i in range(n + 1)]


def grid_tiles(width: int, height: int, rows: int, cols: int) -> list[Viewport]:
    """Row-major tiles of a rows × cols grid covering the image."""
    ys, xs = _cuts(0, height, rows), _cuts(0, width, cols)
    return [Viewport(xs[c], ys[r], xs[c + 1] - xs[c], ys[r + 1] - ys[r]) for r in range(rows) for c in range(cols)]


def sort_first_tiles(layout: str, n: int, width: int, height: int, grid: tuple[int, int] | None = None,
                     rects: np.ndarray | None = None, weights: np.ndarray | None = None,
                     alternate: bool = False) -> list[Viewport]:
    if layout == "horizontal":
        return grid_tiles(width, height, 1, n)
    if layout == "vertical":
        return grid_tiles(width, height, n, 1)
    if layout == "grid":
        rows, cols = grid if grid else grid_shape(n, width, height)
        if rows * cols != n:
            raise ConfigError(f"--grid {rows}x{cols} has {rows * cols} tiles for {n} ranks; make rows × cols equal the rank count")
        return grid_tiles(width, height, rows, cols)
    if layout in ("kd", "balanced"):
        if rects is None or weights is None:
            rects, weights = np.zeros((0, 4)), np.zeros(0)
        if layout == "balanced" or alternate:
            return balanced_tiles(n, width, height, rects, weights)
        return kd_tiles(n, width, height, rects, weights)
    raise ConfigError(f"unknown sort-first layout {layout!r}; use one of {', '.join(SORT_FIRST_LAYOUTS)}")


def weight_grid(width: int, height: int, rects: np.ndarray, weights: np.ndarray, cell: int = _CELL) -> np.ndarray:
    """(ceil(H/cell), ceil(W/cell)) float64 grid: each item's weight spread evenly over the
    cells its screen rectangle ``[x0, y0, x1, y1)`` (pixels, top-left origin) covers."""
    gh, gw = -(-height // cell), -(-width // cell)
    acc = np.zeros((gh + 1, gw + 1))
    r = np.asarray(rects, np.float64).reshape(-1, 4)
    w = np.asarray(weights, np.float64).reshape(-1)
    x0 = np.clip(np.floor(r[:, 0] / cell), 0, gw).astype(np.int64)
    y0 = np.clip(np.floor(r[:, 1] / cell), 0, gh).astype(np.int64)
    x1 = np.clip(np.ceil(r[:, 2] / cell), 0, gw).astype(np.int64)
    y1 = np.clip(np.ceil(r[:, 3] / cell), 0, gh).astype(np.int64)
    ok = (x1 > x0) & (y1 > y0) & (w > 0)
    x0, y0, x1, y1, w = x0[ok], y0[ok], x1[ok], y1[ok], w[ok]
    dens = w / ((x1 - x0) * (y1 - y0))
    np.add.at(acc, (y0, x0), dens)
    np.add.at(acc, (y0, x1), -dens)
    np.add.at(acc, (y1, x0), -dens)
    np.add.at(acc, (y1, x1), dens)
    return acc.cumsum(0).cumsum(1)[:gh, :gw]


def kd_tiles(n: int, width: int, height: int, rects: np.ndarray, weights: np.ndarray,
             alternate: bool = False, cell: int = _CELL) -> list[Viewport]:
    """Recursive weighted split of the screen into ``n`` tiles (in rank order)."""
    g = weight_grid(width, height, rects, weights, cell)
    out: list[Viewport] = []

    def split(vp: Viewport, k: int, depth: int) -> None:
        if k == 1:
            out.append(vp)
            return
        k1 = k // 2
        along_x = (depth % 2 == 0) if alternate else vp.w >= vp.h
        lo, hi = (vp.x, vp.x + vp.w) if along_x else (vp.y, vp.y + vp.h)
        sub = g[vp.y // cell: -(-(vp.y + vp.h) // cell), vp.x // cell: -(-(vp.x + vp.w) // cell)]
        marg = sub.sum(axis=0 if along_x else 1)
        total = marg.sum()
        if total <= 0 or len(marg) < 2:
            cut = lo + ((hi - lo) * k1) // k
        else:
            cum = np.cumsum(marg)
            i = int(np.argmin(np.abs(cum[:-1] - total * k1 / k)))  # cut after cell i
            cut = min(max(((lo // cell) + i + 1) * cell, lo + 1), hi - 1) if hi - lo >= 2 else lo
        if along_x:
            a, b = Viewport(vp.x, vp.y, cut - vp.x, vp.h), Viewport(cut, vp.y, vp.x + vp.w - cut, vp.h)
        else:
            a, b = Viewport(vp.x, vp.y, vp.w, cut - vp.y), Viewport(vp.x, cut, vp.w, vp.y + vp.h - cut)
        split(a, k1, depth + 1)
        split(b, k - k1, depth + 1)

    split(Viewport(0, 0, width, height), n, 0)
    return out


def sort_last_ranges(n: int) -> list[tuple[float, float]]:
    return [(i / n, (i + 1) / n) for i in range(n)]


def parse_wall(spec: str, nranks: int, width: int, height: int) -> list[Viewport]:
    """``CxR`` → C×R wall tiles in row-major order, one per display rank 0..C*R-1."""
    try:
        c, r = (int(v) for v in spec.lower().split("x"))
    except ValueError:
        raise ConfigError(f"--wall {spec!r}: expected COLSxROWS, e.g. 2x2") from None
    if c < 1 or r < 1 or c * r > nranks:
        raise ConfigError(f"--wall {spec}: needs 1 ≤ cols×rows ≤ ranks ({nranks}); run with at least {c * r} ranks")
    if c > width or r > height:
        raise ConfigError(f"--wall {spec}: more tiles than pixels in a {width}x{height} image")
    return grid_tiles(width, height, r, c)
