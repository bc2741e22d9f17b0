"""Filling nodata voids out of core: a coarse harmonic surface plus the nearby data's detail.

A DEM's voids (SRTM's radar shadows and lakes, a clipped or masked raster, a sea given as
nodata) must become heights before the pyramid is built. The fill here is one function of the
whole input, computed a strip at a time with the same result as computed at once, so a void
that crosses strips has no seam, and a void of any size has no plateau or cliff:

1. **Coarse surface** (one extra pass over the input, made only when the first void is met):
   the mean of the valid samples of every F × F cell (F = 64, doubled until the grid has at
   most 512 cells a side), the cells without one filled by the discrete Laplace equation (the
   smoothest surface through the cells around them: a soap film, never above or below its
   boundary), solved exactly with a sparse factorization. Between cell centres the surface is
   the cubic B-spline of those values (C², so no creases in the shading).
2. **Local detail**: at every valid sample its difference to that surface. The differences are
   averaged over cells of 2, 4, … F/2 samples, each cell from its four finer cells and the one
   beyond each side with weights 1, 3, 3, 1 (push), then each void sample takes the
   bilinear blend of the finest level that holds data around it, levels being blended down one
   at a time (pull); where no level up to F/2 holds data the detail is 0. So next to its rim a
   void continues the data around it, and deep inside it follows the coarse surface.

Every value depends only on the input within 2·F samples (cells aligned to the global grid),
so each strip reads its rows with that margin and gets exactly the values a whole-DEM
computation gives; work and memory are bounded by processing the void's columns in windows.
Strips without voids cost nothing.
"""

from __future__ import annotations

import numpy as np

from ...core.errors import IngestError

__all__ = ["VoidFill", "no_valid_sample"]

_MAX_COARSE = 512  # coarse cells a side at most
_WINDOW = 2048  # columns filled per window (plus margins): bounds the temporaries


def no_valid_sample(src) -> IngestError:
    """The error for an input without a single valid sample, naming the file."""
    what = "NaN or ±inf" if src.nodata is None else f"nodata ({src.nodata:g}), NaN or ±inf"
    return IngestError(f"{src.name}: every one of its {src.rows}x{src.cols} samples is {what}; there is no elevation to "
                       "build a store from (check the file, or give the right --nodata)")


def cell_size(rows: int, cols: int) -> int:
    """F: 64, doubled until the coarse grid has at most ``_MAX_COARSE`` cells a side."""
    f = 64
    while -(-max(rows, cols) // f) > _MAX_COARSE:
        f *= 2
    return f


class VoidFill:
    """The fill of one input (see the module docstring); built by one pass over ``src``
    (``progress(advance, total)`` in rows). Raises IngestError naming the file when the input
    has no valid sample at all."""

    def __init__(self, src, progress=None):
        self.src, self.rows, self.cols = src, src.rows, src.cols
        self.F = F = cell_size(self.rows, self.cols)
        self.levels = F.bit_length() - 2  # detail levels: cells of 2 .. F/2 samples
        sums, counts = self._cell_means(progress)
        if not counts.any():
            raise no_valid_sample(src)
        means = np.divide(sums, counts, out=np.zeros_like(sums), where=counts > 0).astype(np.float32).astype(np.float64)
        self.coarse = _harmonic(means, counts > 0)

    def _cell_means(self, progress):
        F, cols = self.F, self.cols
        nR, nC = -(-self.rows // F), -(-cols // F)
        sums, counts = np.zeros((nR, nC)), np.zeros((nR, nC))
        step = F * max(1, (16 << 20) // (F * cols * 4))  # ~16 MB of input a read
        buf = np.zeros((step, nC * F))
        ok = np.zeros((step, nC * F), np.bool_)
        for r in range(0, self.rows, step):
            a = self.src.read(r, min(r + step, self.rows), 0, cols)
            h = a.shape[0]
            ok[:] = False
            np.isfinite(a, out=ok[:h, :cols])
            buf[:] = 0.0
            np.copyto(buf[:h, :cols], a, where=ok[:h, :cols])
            i = r // F
            n = -(-h // F)
            s, c = buf[:n * F], ok[:n * F].astype(np.float64)
            while s.shape[0] > n:  # 2 × 2 sums, log2(F) times: the same additions in the same order on every CPU
                s, c = _pool(s), _pool(c)
            sums[i:i + n], counts[i:i + n] = s, c
            if progress is not None:
                progress(h, self.rows)
        return sums, counts

    def surface(self, r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
        """The coarse surface at rows r0..r1, columns c0..c1 (float64): the cubic B-spline of the
        cell values, the cells' centres as knots, the outermost cells repeated beyond the edge."""
        ir, wr = _bspline(np.arange(r0, r1), self.F, self.coarse.shape[0])
        ic, wc = _bspline(np.arange(c0, c1), self.F, self.coarse.shape[1])
        t = sum(wr[k][:, None] * self.coarse[ir[k]] for k in range(4))
        return sum(wc[k][None, :] * t[:, ic[k]] for k in range(4))

    def fill(self, r0: int, data: np.ndarray) -> None:
        """Replace the NaNs of ``data`` (input rows r0 .. r0 + len(data), every column) in place."""
        bad = np.isnan(data)
        if not bad.any():
            return
        F, reach = self.F, 2 * self.F
        nb = -(-self.cols // F)
        cols_bad = np.zeros(nb * F, np.bool_)
        cols_bad[: self.cols] = bad.any(axis=0)
        runs, start, prev = [], None, None  # runs of F-column blocks with voids, near ones merged
        for blk in np.flatnonzero(cols_bad.reshape(nb, F).any(axis=1)):
            if start is not None and (blk - prev > 4 or (blk - start) * F >= _WINDOW):
                runs.append((start, prev + 1))
                start = None
            start = blk if start is None else start
            prev = blk
        runs.append((start, prev + 1))
        spans = []
        for b0, b1 in runs:
            w0, w1 = b0 * F, min(self.cols, b1 * F)
            rows_bad = np.flatnonzero(bad[:, w0:w1].any(axis=1))
            a = max(0, (r0 + int(rows_bad[0]) - reach) // F * F)
            b = min(self.rows, -(-(r0 + int(rows_bad[-1]) + 1 + reach) // F) * F)
            spans.append((w0, w1, a, b))
        top, bottom = min(s[2] for s in spans), max(s[3] for s in spans)
        raw = self.src.read(top, bottom, 0, self.cols)  # (one read a strip: a row-major file reads whole rows anyway)
        for w0, w1, a, b in spans:
            c0, c1 = max(0, w0 - reach), min(self.cols, -(-(w1 + reach) // F) * F)
            filled = self._window(raw[a - top: b - top, c0:c1], a, c0)
            d0, d1 = max(0, a - r0), min(data.shape[0], b - r0)  # data's rows inside the region (every void row is)
            sub, hole = data[d0:d1, w0:w1], bad[d0:d1, w0:w1]
            sub[hole] = filled[r0 + d0 - a: r0 + d1 - a, w0 - c0: w1 - c0][hole]

    def _window(self, raw: np.ndarray, a: int, c0: int) -> np.ndarray:
        """Surface + pulled detail over the input ``raw`` (float32, NaN where void) whose first
        sample is row a, column c0 (multiples of F); float32."""
        F = self.F
        nr, nc = raw.shape
        surf = self.surface(a, a + nr, c0, c0 + nc)
        h, w = -(-nr // F) * F, -(-nc // F) * F  # padded to whole cells (weight 0)
        valid = np.zeros((h, w), np.bool_)
        np.isfinite(raw, out=valid[:nr, :nc])
        detail = np.zeros((h, w))
        np.subtract(raw, surf, out=detail[:nr, :nc], where=valid[:nr, :nc])
        sums, weights = [detail], [valid.astype(np.float64)]
        for _ in range(self.levels):  # push: cells of 2, 4, .. F/2, each from its finer cells and one beyond (tent)
            sums.append(_tent(sums[-1]))
            weights.append(_tent(weights[-1]))
        val = np.divide(sums[-1], weights[-1], out=np.zeros_like(sums[-1]), where=weights[-1] > 0)
        for s, c in zip(reversed(sums[:-1]), reversed(weights[:-1])):  # pull
            val = np.divide(s, c, out=_upsample(val), where=c > 0)
        return (surf + val[:nr, :nc]).astype(np.float32)


def _bspline(x: np.ndarray, F: int, n: int):
    """Indices (4, len(x)) and weights (4, len(x)) of the uniform cubic B-spline through cell
    centres (i·F + (F-1)/2) at sample positions x, indices clamped to 0..n-1."""
    t = (x - (F - 1) / 2.0) / F
    i = np.floor(t).astype(np.int64)
    u = t - i
    v, u2 = 1.0 - u, u * u  # (products, not **: numpy's power differs in the last bit between CPUs)
    u3 = u2 * u
    w = np.stack([v * v * v, 3.0 * u3 - 6.0 * u2 + 4.0, -3.0 * u3 + 3.0 * u2 + 3.0 * u + 1.0, u3]) / 6.0
    idx = np.clip(np.stack([i - 1, i, i + 1, i + 2]), 0, n - 1)
    return idx, w


def _pool(a: np.ndarray) -> np.ndarray:
    """Sums of the 2 × 2 cells of ``a`` (even shape), as four element-wise additions."""
    return (a[0::2, 0::2] + a[1::2, 0::2]) + (a[0::2, 1::2] + a[1::2, 1::2])


def _tent(a: np.ndarray) -> np.ndarray:
    """Cells of twice the size from ``a`` (even shape): weights 1, 3, 3, 1 over the finer cells
    2I-1 .. 2I+2 along each axis (nothing beyond the edge), element-wise in a fixed order. The
    overlap lets a coarse cell see data one finer cell past its own square, so a void whose rim
    lies on a cell border still takes the data beside it (with aligned 2 × 2 sums such a rim was
    a cliff: walk10 H1, a missing 256² tile filled as a tray with 168 m walls)."""
    def axis0(x):
        z = np.zeros((1,) + x.shape[1:])
        before = np.concatenate([z, x[1:-1:2]])  # cell 2I-1
        after = np.concatenate([x[2::2], z])  # cell 2I+2
        return (before + 3.0 * x[0::2]) + (3.0 * x[1::2] + after)
    return axis0(axis0(a).T).T


def _upsample(v: np.ndarray) -> np.ndarray:
    """Bilinear 2× upsampling of cell values to the cells of half the size (their centres at
    ¼ and ¾ of the coarse cell; the outermost cells repeated beyond the edge)."""
    def axis0(a):
        p = np.concatenate([a[:1], a, a[-1:]], axis=0)
        out = np.empty((2 * a.shape[0],) + a.shape[1:])
        out[0::2] = 0.75 * p[1:-1] + 0.25 * p[:-2]
        out[1::2] = 0.75 * p[1:-1] + 0.25 * p[2:]
        return out
    return axis0(axis0(v).T).T


def _harmonic(values: np.ndarray, known: np.ndarray) -> np.ndarray:
    """``values`` with the cells not ``known`` replaced by the solution of the 5-point discrete
    Laplace equation, the known cells as boundary values and no flux across the grid's edge
    (exact, by a sparse factorization; the unknowns are at most 512² cells)."""
    unknown = ~known
    n = int(unknown.sum())
    if n == 0:
        return values
    from scipy.sparse import coo_matrix
    from scipy.sparse.linalg import spsolve

    nR, nC = values.shape
    index = np.full(values.shape, -1, np.int64)
    index[unknown] = np.arange(n)
    rows, cols, vals = [], [], []
    rhs = np.zeros(n)
    degree = np.zeros(values.shape)
    for dr, dc in ((1, 0), (-1, 0), (0, 1), (0, -1)):  # each neighbour inside the grid
        src = (slice(max(0, -dr), nR - max(0, dr)), slice(max(0, -dc), nC - max(0, dc)))
        dst = (slice(max(0, dr), nR - max(0, -dr)), slice(max(0, dc), nC - max(0, -dc)))
        degree[src] += 1.0
        me, other = index[src], index[dst]
        both = (me >= 0) & (other >= 0)
        rows.append(me[both]); cols.append(other[both]); vals.append(-np.ones(int(both.sum())))  # noqa: E702
        edge = (me >= 0) & (other < 0)
        np.add.at(rhs, me[edge], values[dst][edge])
    idx = np.arange(n)
    rows.append(idx); cols.append(idx); vals.append(degree[unknown])  # noqa: E702
    A = coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n)).tocsc()
    out = values.copy()
    out[unknown] = spsolve(A, rhs).astype(np.float32)  # (rounded: the solver's last bits depend on the CPU's BLAS)
    return out
