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


@pytest.mark.parametrize("soft", [False, True])  # F16C (where the CPU has it) and the software rounding
def test_float16_bits_match_numpy_everywhere_that_matters(soft):
    rng = np.random.default_rng(1)
    bits = np.concatenate([rng.integers(0, 2**32, 2_000_000, dtype=np.uint64).astype(np.uint32),
                           np.arange(0x33000000 - 4096, 0x38800000 + 4096, 97, dtype=np.uint32),  # subnormal halves
                           np.arange(0x477FE000 - 70000, 0x47800000 + 70000, 3, dtype=np.uint32),  # overflow edge
                           np.array([0, 0x80000000, 0x7F800000, 0xFF800000, 0x3F800000, 0x00000001], np.uint32)])
    bits = np.concatenate([bits, bits | np.uint32(0x80000000)])
    f = bits.view(np.float32)
    f = f[~np.isnan(f)]  # NaN payloads: hardware and software paths of numpy differ; ingest never has NaN
    got = np.empty(f.shape, np.uint16)
    rk.to_half(f, got, soft)
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


@pytest.mark.parametrize("edges", [(True, True), (False, True), (True, False), (False, False)])
@pytest.mark.parametrize("nb", [1, 3])
def test_horn_blocks_matches_numpy(edges, nb):
    """shade0_blocks reads the block row's blocks (shared borders) in place of its wide rows:
    the same bits as the numpy code on the wide rows (the prepare's shading pass, round 10)."""
    from massview.data.terrain.store import block_view

    rng = np.random.default_rng(7 + nb)
    M, W = 33, nb * 32 + 1
    rows = [_terrain(rng, (M, W)) for _ in range(3)]
    prev, cur, nxt = rows[0] if edges[0] else None, rows[1], rows[2] if edges[1] else None
    dx, dy, zlo, zhi = 30.0, 27.5, float(cur.min()) - 3.1, float(cur.max()) + 7.3
    want = _numpy_shade0(prev, cur, nxt, dx, dy, zlo, max(zhi - zlo, 1e-6))
    blocks = np.ascontiguousarray(block_view(cur, nb, M))
    above, below = prev[M - 2] if prev is not None else None, nxt[1] if nxt is not None else None
    got = colors.shade0_blocks(above, blocks, below, dx, dy, zlo, max(zhi - zlo, 1e-6))
    assert got.dtype == np.float16 and np.array_equal(got.view(np.uint16), want.view(np.uint16))


@pytest.mark.parametrize("edges", [(False, False), (True, True), (True, False), (False, True)])
@pytest.mark.parametrize("nb", [1, 3])
def test_level0_shading_from_halos_matches_the_wide_rows(edges, nb):
    """Store format 3: each block's level-0 shading computed on reading from its heights and
    its halo (block_halos → shade0_block) is, bit for bit, the block's part of what the
    shading pass computes over the whole row with its neighbours (and what the numpy code
    gives), at the grid's edges (clamped) and inside it."""
    from massview.data.terrain.store import block_view

    rng = np.random.default_rng(17 + nb)
    M, W = 33, nb * 32 + 1
    rows = [_terrain(rng, (M, W), scale=4000.0) for _ in range(3)]
    prev, cur, nxt = rows[0] if edges[0] else None, rows[1], rows[2] if edges[1] else None
    dx, dy, zlo, zhi = 30.0, 27.5, float(cur.min()) - 3.1, float(cur.max()) + 7.3
    want = _numpy_shade0(prev, cur, nxt, dx, dy, zlo, max(zhi - zlo, 1e-6))
    blocks = np.ascontiguousarray(block_view(cur, nb, M))
    above, below = prev[M - 2] if prev is not None else None, nxt[1] if nxt is not None else None
    halos = colors.block_halos(above, blocks, below)
    assert halos.shape == (nb, 4, M + 2) and halos.dtype == np.float32
    for j in range(nb):
        got = colors.shade0_block(halos[j], blocks[j], dx, dy, zlo, max(zhi - zlo, 1e-6))
        assert got.dtype == np.float16 and np.array_equal(got.view(np.uint16), want[:, j * (M - 1): j * (M - 1) + M].view(np.uint16))
        out = np.empty((M, M, 3), np.float16)
        assert colors.shade0_block(halos[j], blocks[j], dx, dy, zlo, max(zhi - zlo, 1e-6), out=out) is out
        assert np.array_equal(out.view(np.uint16), got.view(np.uint16))


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
    from massview.data.terrain import kernels, refkernels

    rng = np.random.default_rng(m * 100 + bi * 10 + bj)
    M = 2**m + 1
    b = _terrain(rng, (M, M), scale=3000.0)
    b[rng.random((M, M)) < 0.05] = np.float32(1e4)  # spikes: the maxima come from single samples
    for l in range(1, m + 1):
        want, got = _grid_inputs(b, 2**l, f, bi, bj, m), _grid_inputs(b, 2**l, f, bi, bj, m)
        refkernels._grid_squares(*want)
        kernels.grid_errors(*got)
        assert np.array_equal(got[-2], want[-2]) and np.array_equal(got[-1], want[-1]), f"stride {2**l}"


@pytest.mark.parametrize("m,f", [(8, 16), (5, 4)])
@pytest.mark.parametrize("cm", [True, False])
def test_both_row_layouts_match_the_per_square_reference(m, f, cm):
    """latticekernels._lattice_maxima in either layout (c-major, square-major) at every stride, not
    only the one grid_errors picks, folds to _grid_squares' maxima bit for bit; and
    latticekernels._direct_maxima gives the same maxima at every stride."""
    from massview.data.terrain import kernels, latticekernels, refkernels

    rng = np.random.default_rng(m * 10 + f + cm)
    M = 2**m + 1
    b = _terrain(rng, (M, M), scale=3000.0)
    b[rng.random((M, M)) < 0.05] = np.float32(-2e4)  # spikes below
    for l in range(1, m + 1):
        want, got = _grid_inputs(b, 2**l, f, 1, 2, m), _grid_inputs(b, 2**l, f, 1, 2, m)
        refkernels._grid_squares(*want)
        s, nq, fx, c00, c10, c01, c11, cc, parity, tab, f_, v0, u0, V0, U0 = got[1:-2]
        m5 = latticekernels._lattice_maxima(b, s, nq, fx, c00, c10, c01, c11, cc, parity, cm)
        kernels._fold_rows(m5, tab, f_, v0, u0, V0, U0, got[-2], got[-1])
        assert np.array_equal(got[-2], want[-2]) and np.array_equal(got[-1], want[-1]), f"stride {2**l}"
        direct = latticekernels._direct_maxima(b, s, nq, fx, c00, c10, c01, c11, cc, parity)
        assert np.array_equal(direct, m5), f"_direct_maxima, stride {2**l}"


@pytest.mark.parametrize("m,f,masked", [(8, 16, False), (8, 16, True), (5, 32, False), (5, 32, True)])
def test_grid_level_is_the_python_fold_of_grid_errors(m, f, masked):
    """kernels.grid_level (corners, kernel and eps folds in one call) leaves the accumulators
    as grid_error_args + grid_errors / masked_grid_errors + np.maximum(sl, e + eps) did."""
    from massview.data.terrain import kernels, refkernels
    from massview.data.terrain.deviation import _region_table, grid_error_args

    rng = np.random.default_rng(m + f + masked)
    M, tab, bi, bj, size = 2**m + 1, _region_table(f), 3, 2, 64
    b = _terrain(rng, (M, M), scale=3000.0)
    valid = np.ones((M, M), np.bool_)
    if masked:
        valid[:, M - 37:] = False
        valid[M - 5:, :] = False
    eps = np.float32(8 * np.finfo(np.float32).eps * float(np.abs(b).max()))
    for l in range(1, m + 1):
        s = 2**l
        want_sq, want_dg = rng.random((size, size), np.float32), rng.random((2, size + 1, size + 1), np.float32)
        got_sq, got_dg = want_sq.copy(), want_dg.copy()
        args, n = grid_error_args(b, s, m, f, bi, bj, tab)
        sq, per = np.zeros((n, n), np.float32), np.zeros((4, n, n), np.float32)
        if masked:
            refkernels.masked_grid_errors(b, valid, *args, sq, per)
        else:
            kernels.grid_errors(b, *args, sq, per)
        V0, U0 = args[-2], args[-1]
        sl = want_sq[V0: V0 + n, U0: U0 + n]
        np.maximum(sl, sq + eps, out=sl)
        for (o, dv, du), e in zip(((0, 0, 0), (0, 1, 0), (1, 0, 0), (1, 0, 1)), per):
            sl = want_dg[o, V0 + dv: V0 + dv + n, U0 + du: U0 + du + n]
            np.maximum(sl, e + eps, out=sl)
        kernels.grid_level(b, valid, masked, s, m, f, bi, bj, tab, eps, got_sq, got_dg)
        assert np.array_equal(got_sq, want_sq) and np.array_equal(got_dg, want_dg), f"stride {s}"


@pytest.mark.parametrize("s,off,masked,parity", [(512, 0, False, 0), (512, 256, True, 1), (1024, 768, False, 1), (2048, 512, True, 0)])
def test_window_errors_match_the_per_sample_masked_loop(s, off, masked, parity):
    """refkernels.window_errors (a row at a time, vectorized) gives _masked_maxima's maxima (the
    per-sample loop with masks it replaced), folded the same way, bit for bit."""
    from massview.data.terrain import kernelbase, refkernels, windowkernels
    from massview.data.terrain.deviation import _region_table

    rng = np.random.default_rng(s + off + masked)
    M = 257
    b = _terrain(rng, (M, M), scale=3000.0)
    b[rng.random((M, M)) < 0.05] = np.float32(1e4)
    valid = np.ones((M, M), np.bool_)
    if masked:
        valid[:, M - 40:] = False
        valid[M - 100:, :] = False
    t = np.arange(M, dtype=np.float32)
    fx, fy = (off + t) / s, (s - M + 1 + t) / s  # the window's fractional coordinates, up to 1
    corners = [np.full((1, 1), v, np.float32) for v in rng.normal(size=5).astype(np.float32) * 3000]
    tab, f, v0, u0 = _region_table(16), 16, 5, 9
    want = np.zeros((1, 1), np.float32), np.zeros((4, 1, 1), np.float32)
    got = np.zeros((1, 1), np.float32), np.zeros((4, 1, 1), np.float32)
    k = kernelbase._corners(*corners, 0, 0)
    m5 = windowkernels._masked_maxima(b, valid, 0, 0, fy, fx, parity % 2 == 0, k)
    kernelbase._fold(*want, tab, f, v0, u0, v0 // f, u0 // f, 0, 0, *m5)
    refkernels.window_errors(b, valid, fx, fy, *corners, parity, tab, f, v0, u0, *got)
    assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1])
    assert want[1].max() > 0


def _padded_cases(rng, M, s):
    """Valid extents (hv, wv) for stride s: random ones, ones smaller than a square, ones exactly
    on a lattice line (hv − 1 a multiple of s), one past it, and the whole block."""
    n = M - 1
    on = min(n, s * int(rng.integers(1, max(n // s, 1) + 1))) + 1  # a lattice line
    cases = [(int(rng.integers(1, M + 1)), int(rng.integers(1, M + 1))) for _ in range(3)]
    cases += [(int(rng.integers(1, min(s, M) + 1)), int(rng.integers(1, M + 1))),  # hv within one square
              (int(rng.integers(1, M + 1)), int(rng.integers(1, min(s, M) + 1))),  # wv within one square
              (on, int(rng.integers(1, M + 1))), (int(rng.integers(1, M + 1)), on), (on, on),
              (min(on + 1, M), on), (on - 1, M), (M, max(on - 1, 1)),  # the last valid sample just before a line
              (1, 1), (M, int(rng.integers(1, M))), (M, M)]
    return cases


@pytest.mark.parametrize("m,f", [(8, 16), (6, 4), (5, 32)])
@pytest.mark.parametrize("bi,bj", [(0, 0), (3, 2), (1, 6)])
def test_padded_grid_errors_match_the_masked_per_square_loop(m, f, bi, bj):
    """kernels.padded_grid_errors (whole squares by the vectorized row kernels, only those on
    the valid edge masked) folds to masked_grid_errors' maxima bit for bit, for random padding
    extents (hv, wv) at every stride and both parities, including extents within one square
    and exactly on a lattice line."""
    from massview.data.terrain import kernels, refkernels

    rng = np.random.default_rng(m * 1000 + bi * 10 + bj + f)
    M = 2**m + 1
    b = _terrain(rng, (M, M), scale=3000.0)
    b[rng.random((M, M)) < 0.05] = np.float32(1e4)  # spikes: the maxima come from single samples
    r, c = np.arange(M)[:, None], np.arange(M)[None, :]
    checked = 0
    for l in range(1, m + 1):
        s = 2**l
        for hv, wv in _padded_cases(rng, M, s):
            valid = np.ascontiguousarray((r < hv) & (c < wv))
            b_pad = b.copy()
            b_pad[~valid] = rng.normal(size=int((~valid).sum())).astype(np.float32) * 5e4  # padding must not count
            want, got = _grid_inputs(b_pad, s, f, bi, bj, m), _grid_inputs(b_pad, s, f, bi, bj, m)
            start = want[-1].copy()
            refkernels.masked_grid_errors(b_pad, valid, *want[1:])
            kernels.padded_grid_errors(b_pad, valid, *got[1:])
            assert np.array_equal(got[-2], want[-2]) and np.array_equal(got[-1], want[-1]), f"stride {s}, hv {hv}, wv {wv}"
            checked += not np.array_equal(want[-1], start)
    assert checked > 0  # the maxima did change the accumulators somewhere


def _old_window_fold(b, valid, fx, fy, g, parity, tab, f, v0, u0, eps, SQ, DG):
    """The window level of DeviationAccumulator._add_level before issue 20's eighth round:
    refkernels.window_errors (masked per row) into (1, 1) maxima, then np.maximum folds with eps."""
    from massview.data.terrain import refkernels

    corners = [np.full((1, 1), v, np.float32) for v in g]
    sq, per = np.zeros((1, 1), np.float32), np.zeros((4, 1, 1), np.float32)
    refkernels.window_errors(b, valid, fx, fy, *corners, parity, tab, f, v0, u0, sq, per)
    V0, U0 = v0 // f, u0 // f
    sl = SQ[V0: V0 + 1, U0: U0 + 1]
    np.maximum(sl, sq + eps, out=sl)
    for (o, dv, du), e in zip(((0, 0, 0), (0, 1, 0), (1, 0, 0), (1, 0, 1)), per):
        sl = DG[o, V0 + dv: V0 + dv + 1, U0 + du: U0 + du + 1]
        np.maximum(sl, e + eps, out=sl)


@pytest.mark.parametrize("s", [512, 1024, 2048, 4096])
@pytest.mark.parametrize("parity", [0, 1])
def test_window_level_matches_the_masked_row_kernel(s, parity):
    """windowkernels.window_level (quarter ranges by binary search, unmasked vectorized rows, the
    folds compiled) leaves the accumulators as window_errors + the Python np.maximum folds did,
    bit for bit: every block position of a 257² block inside a lattice square of stride s
    (fractions as _add_level computes them), both parities, and valid rectangles [0:hv, 0:wv]
    (random, within one row or column, empty, whole) with large padding values that must not count."""
    from massview.data.terrain import windowkernels
    from massview.data.terrain.deviation import _region_table

    rng = np.random.default_rng(s + parity)
    M, f = 257, 16
    tab = _region_table(f)
    r, c = np.arange(M)[:, None], np.arange(M)[None, :]
    t = np.arange(M, dtype=np.float32)
    changed = 0
    for pos in range(s // (M - 1)):  # the block's offset inside the square, in blocks
        b = _terrain(rng, (M, M), scale=3000.0)
        b[rng.random((M, M)) < 0.05] = np.float32(1e4)  # spikes: the maxima come from single samples
        offx, offy = pos * (M - 1), (s // (M - 1) - 1 - pos) * (M - 1)
        fx, fy = (offx + t) / s, (offy + t) / s
        g = tuple(rng.normal(size=5).astype(np.float32) * 3000)
        extents = [(M, M), (int(rng.integers(1, M + 1)), int(rng.integers(1, M + 1))), (1, M), (M, 1), (0, 0), (M, 200)]
        for hv, wv in extents:
            valid = np.ascontiguousarray((r < hv) & (c < wv))
            bp = b.copy()
            bp[~valid] = np.float32(-9e4)
            v0, u0 = 2 * int(rng.integers(0, 50)) + parity, 2 * int(rng.integers(0, 50))
            eps = np.float32(8 * np.finfo(np.float32).eps * 1e4)
            SQ0, DG0 = rng.random((8, 8), np.float32), rng.random((2, 9, 9), np.float32)
            want_sq, want_dg, got_sq, got_dg = SQ0.copy(), DG0.copy(), SQ0.copy(), DG0.copy()
            vv, uu = v0 % 8 * f, u0 % 8 * f  # lattice indices whose patch squares lie inside the 8 × 8 arrays
            _old_window_fold(bp, valid, fx, fy, g, parity, tab, f, vv + v0 % f, uu + u0 % f, eps, want_sq, want_dg)
            windowkernels.window_level(bp, hv, wv, fx, fy, *g, parity, tab, f, vv + v0 % f, uu + u0 % f, eps, got_sq, got_dg)
            assert np.array_equal(got_sq, want_sq) and np.array_equal(got_dg, want_dg), f"pos {pos}, hv {hv}, wv {wv}"
            changed += not (np.array_equal(want_sq, SQ0) and np.array_equal(want_dg, DG0))
    assert changed > 0


@pytest.mark.parametrize("m", [5, 8, 9])
@pytest.mark.parametrize("s", [2, 4])
@pytest.mark.parametrize("parity", [0, 1])
def test_fine_maxima_match_the_per_square_reference(m, s, parity):
    """finekernels._fine_maxima (strides 2 and 4: a square's samples unrolled, its maxima in
    registers) gives every lattice square's five maxima exactly as _grid_squares computes them
    (with one lattice square per patch, f = 1, its folds are the maxima themselves): whole
    blocks up to 513² (256 squares a row) and the (nv, nu) sub-grids padded blocks pass."""
    from massview.data.terrain import finekernels, refkernels
    from massview.data.terrain.deviation import _region_table

    rng = np.random.default_rng(m * 10 + s + parity)
    M, nq = 2**m + 1, 2**m // s
    b = _terrain(rng, (M, M), scale=3000.0)
    b[rng.random((M, M)) < 0.05] = np.float32(-2e4)  # spikes: the maxima come from single samples
    lat, cc = b[::s, ::s], b[s // 2::s, s // 2::s]
    corners = [np.ascontiguousarray(x) for x in (lat[:-1, :-1], lat[:-1, 1:], lat[1:, :-1], lat[1:, 1:], cc)]
    fx = np.arange(s + 1, dtype=np.float32) / s
    sq, per = np.zeros((nq, nq), np.float32), np.zeros((4, nq, nq), np.float32)
    refkernels._grid_squares(b, s, nq, fx, *corners, parity, _region_table(1), 1, 0, 0, 0, 0, sq, per)
    want = np.concatenate([sq[None], per])
    assert np.array_equal(finekernels._fine_maxima(b, s, *corners, parity), want)
    for nv, nu in ((nq - 1, nq), (3, nq - 2), (nq, 1), (1, 5)):
        sub = [np.ascontiguousarray(x[:nv, :nu]) for x in corners]
        assert np.array_equal(finekernels._fine_maxima(b, s, *sub, parity), want[:, :nv, :nu]), (nv, nu)
