"""Issue 20: the compiled row kernels of the ingest give exactly what the numpy expressions
they replace give (same float32 operations; float16 with numpy's rounding), on random data
with awkward values, so the stores stay bit-identical (the whole-store check is
tests/test_ingest_parallel.py)."""

from __future__ import annotations

import numpy as np
import pytest

from massview.data.terrain import colors, meta, roettger
from massview.data.terrain import rowkernels as rk


def _terrain(rng, shape, scale=1000.0):
    a = rng.normal(size=shape).astype(np.float32).cumsum(axis=0).cumsum(axis=1) * np.float32(scale / 50)
    return a + rng.normal(size=shape).astype(np.float32) * np.float32(3)


def test_float16_bits_match_numpy_everywhere_that_matters():
    rng = np.random.default_rng(1)
    bits = np.concatenate([rng.integers(0, 2**32, 2_000_000, dtype=np.uint64).astype(np.uint32),
                           np.arange(0x33000000 - 4096, 0x38800000 + 4096, 97, dtype=np.uint32),  # subnormal halves
                           np.arange(0x477FE000 - 70000, 0x47800000 + 70000, 3, dtype=np.uint32),  # overflow edge
                           np.array([0, 0x80000000, 0x7F800000, 0xFF800000, 0x3F800000, 0x00000001], np.uint32)])
    bits = np.concatenate([bits, bits | np.uint32(0x80000000)])
    f = bits.view(np.float32)
    f = f[~np.isnan(f)]  # NaN payloads: hardware and software paths of numpy differ; ingest never has NaN
    got = np.empty(f.shape, np.uint16)
    rk.to_half(f.view(np.uint32), got)
    with np.errstate(over="ignore"):
        want = f.astype(np.float16).view(np.uint16)
    assert np.array_equal(got, want)


@pytest.mark.parametrize("M,f", [(129, 16), (257, 16), (33, 4)])
def test_block_stats_match_numpy(M, f):
    rng = np.random.default_rng(M)
    b = _terrain(rng, (M, M))
    lo, hi = np.empty(((M - 1) // f,) * 2, np.float32), np.empty(((M - 1) // f,) * 2, np.float32)
    mn, mx, dm = rk.block_stats(b, f, lo, hi)
    assert (mn, mx) == (b.min(), b.max())
    assert dm == max(float(x.max()) for x in meta.vertex_deltas(b))
    want_lo = np.minimum.reduce([meta.reduce_min(b[dy:dy + M - 1, dx:dx + M - 1], f) for dy in (0, 1) for dx in (0, 1)])
    want_hi = np.maximum.reduce([meta.reduce_max(b[dy:dy + M - 1, dx:dx + M - 1], f) for dy in (0, 1) for dx in (0, 1)])
    assert np.array_equal(lo, want_lo) and np.array_equal(hi, want_hi)


# -- the numpy code the kernels replaced (colors.py before issue 20's second round) --------------
def _padded(above, mid, below, c0, c1):
    W = mid.shape[1]
    lo, hi = max(c0 - 1, 0), min(c1 + 1, W)
    g = np.concatenate([x[:, lo:hi] for x in (above, mid, below)], axis=0)
    if c0 == 0 or c1 == W:
        g = np.concatenate(([g[:, :1]] if c0 == 0 else []) + [g] + ([g[:, -1:]] if c1 == W else []), axis=1)
    return g


def _numpy_shade0(prev, cur, nxt, dx, dy, zlo, rng_):
    M, W = cur.shape
    above = prev[M - 2: M - 1] if prev is not None else cur[:1]
    below = nxt[1:2] if nxt is not None else cur[M - 1:]
    out = np.empty((M, W, 3), np.float16)
    s = _padded(above, cur, below, 0, W)
    sx, sy = colors.horn_slopes(s, dx, dy)
    for ch, v in enumerate((sx, sy, (s[1:-1, 1:-1] - zlo) / rng_)):
        out[:, :, ch] = v
    return out


def _numpy_tent(rows, i):
    a, m0, m1, b = (rows.get(k) for k in (2 * i - 1, 2 * i, 2 * i + 1, 2 * i + 2))
    M, W = m0.shape[0], m0.shape[1]
    above = a[M - 2: M - 1] if a is not None else m0[:1]
    below = b[0:2] if b is not None else np.concatenate([m1[M - 1:]] * 2)
    mid = np.concatenate([m0[:M - 1], m1[:M - 1]])
    g = _padded(above, mid, below, 0, W).astype(np.float32)
    return colors.tent_decimate(g).astype(np.float16)


@pytest.mark.parametrize("edges", [(True, True), (False, True), (True, False), (False, False)])
def test_horn_row_matches_numpy(edges):
    rng = np.random.default_rng(3)
    M, W = 33, 3 * 32 + 1
    rows = [_terrain(rng, (M, W)) for _ in range(3)]
    prev, cur, nxt = rows[0] if edges[0] else None, rows[1], rows[2] if edges[1] else None
    dx, dy, zlo, zhi = 30.0, 27.5, float(cur.min()) - 3.1, float(cur.max()) + 7.3
    want = _numpy_shade0(prev, cur, nxt, dx, dy, zlo, max(zhi - zlo, 1e-6))
    got = colors.shade0_wide(prev, cur, nxt, dx, dy, zlo, max(zhi - zlo, 1e-6))
    assert got.dtype == np.float16 and np.array_equal(got.view(np.uint16), want.view(np.uint16))


@pytest.mark.parametrize("i,last", [(1, False), (1, True), (0, False), (0, True)])
def test_tent_row_matches_numpy(i, last):
    rng = np.random.default_rng(4)
    M, W = 33, 4 * 32 + 1
    keys = [k for k in range(2 * i - 1, 2 * i + 3) if k >= 0 and not (last and k == 2 * i + 2)]
    rows = {k: (rng.normal(size=(M, W, 3)) * 40).astype(np.float16) for k in keys}
    want, got = _numpy_tent(rows, i), colors.tent_wide(rows, i)
    assert got.dtype == np.float16 and np.array_equal(got.view(np.uint16), want.view(np.uint16))


def test_local_d2_matches_numpy():
    rng = np.random.default_rng(5)
    g = _terrain(rng, (65, 129))
    out = np.empty((32, 64), np.float32)
    rk.local_d2(g, 8, out)
    assert np.array_equal(out, roettger.local_d2(g, 8))


@pytest.mark.parametrize("N,row0,h", [(1, 0, 2), (8, 0, 16), (8, 4, 6), (16, 14, 4), (16, 30, 2), (16, 8, 512)])
def test_propagate_max_matches_numpy(N, row0, h):
    rng = np.random.default_rng(N + row0)
    fine = np.abs(rng.normal(size=(min(h, 2 * N - row0), 2 * N))).astype(np.float32)
    start = np.abs(rng.normal(size=(N, N))).astype(np.float32) * np.float32(0.5)
    want, got = start.copy(), start.copy()
    roettger.propagate_into(want, fine, row0, roettger.k_factor(4.0))
    roettger._propagate_compiled(got, fine, row0, roettger.k_factor(4.0))
    assert np.array_equal(got, want) and not np.array_equal(got, start)


# -- the exact K-patch error kernel (kernels.grid_errors) against the per-square loop it replaced --
def _grid_inputs(b, s, f, bi, bj, m):
    from massview.data.terrain.deviation import _region_table, grid_error_args

    args, n = grid_error_args(b, s, m, f, bi, bj, _region_table(f))
    # start from random maxima: the kernels fold into what is there
    rng = np.random.default_rng(s * 7 + bi)
    sq, per = rng.random((n, n), np.float32) * 5, rng.random((4, n, n), np.float32) * 5
    return [b, *args, sq, per]


@pytest.mark.parametrize("m,f", [(8, 16), (6, 4), (5, 32)])
@pytest.mark.parametrize("bi,bj", [(0, 0), (3, 2), (1, 6)])
def test_grid_errors_match_the_per_square_reference(m, f, bi, bj):
    from massview.data.terrain import kernels

    rng = np.random.default_rng(m * 100 + bi * 10 + bj)
    M = 2**m + 1
    b = _terrain(rng, (M, M), scale=3000.0)
    b[rng.random((M, M)) < 0.05] = np.float32(1e4)  # spikes: the maxima come from single samples
    for l in range(1, m + 1):
        want, got = _grid_inputs(b, 2**l, f, bi, bj, m), _grid_inputs(b, 2**l, f, bi, bj, m)
        kernels._grid_squares(*want)
        kernels.grid_errors(*got)
        assert np.array_equal(got[-2], want[-2]) and np.array_equal(got[-1], want[-1]), f"stride {2**l}"


@pytest.mark.parametrize("m,f", [(8, 16), (5, 4)])
@pytest.mark.parametrize("cm", [True, False])
def test_both_row_layouts_match_the_per_square_reference(m, f, cm):
    """kernels._lattice_maxima in either layout (c-major, square-major) at every stride, not
    only the one grid_errors picks, folds to _grid_squares' maxima bit for bit."""
    from massview.data.terrain import kernels

    rng = np.random.default_rng(m * 10 + f + cm)
    M = 2**m + 1
    b = _terrain(rng, (M, M), scale=3000.0)
    b[rng.random((M, M)) < 0.05] = np.float32(-2e4)  # spikes below
    for l in range(1, m + 1):
        want, got = _grid_inputs(b, 2**l, f, 1, 2, m), _grid_inputs(b, 2**l, f, 1, 2, m)
        kernels._grid_squares(*want)
        s, nq, fx, c00, c10, c01, c11, cc, parity, tab, f_, v0, u0, V0, U0 = got[1:-2]
        m5 = kernels._lattice_maxima(b, s, nq, fx, c00, c10, c01, c11, cc, parity, cm)
        kernels._fold_rows(m5, tab, f_, v0, u0, V0, U0, got[-2], got[-1])
        assert np.array_equal(got[-2], want[-2]) and np.array_equal(got[-1], want[-1]), f"stride {2**l}"
