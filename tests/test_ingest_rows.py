"""Issue 20, eighth round: the ingest's row work around the exact-error kernels, each proven
against what it replaced.

* ``metadata._row_stats`` reads a row's blocks in place (one compiled call over the strided
  view of a wide row, or over stacked blocks) and gives the very bytes of the per-block loop it
  replaced (a contiguous copy of each block through ``rowkernels.block_stats`` as it was,
  kept here verbatim, then ``DiamondAccumulator.put_zrange``), signed zeros included;
* ``rowkernels.tent_row`` converts float16 by the hardware (``h2f``) and skips the clamping in
  the interior columns: the same float16 bits as the numpy tent (``colors.tent_decimate``)
  over every float16 bit pattern but NaN;
* the pyramid pass's done flags, written together (every ``_FLAG_EVERY`` seconds and when the
  pass ends or is interrupted): the same store whether they are written after every row or
  only at the end, and an interrupted run flags exactly the rows it wrote.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from numba import njit

from conftest import FlakySource
from massview.data.terrain import ArraySource, TerrainStore, prepare_terrain
from massview.data.terrain import colors, ingest
from massview.data.terrain import rowkernels as rk
from massview.data.terrain.layout import TerrainLayout
from massview.data.terrain.meta import DiamondAccumulator
from massview.data.terrain.metadata import _row_stats
from massview.data.terrain.store import block_view
from massview.data.terrain.synthetic import SyntheticSource


_HALF = np.float32(0.5)


@njit(nogil=True, boundscheck=False)
def _block_stats_de2dcc1(b, f, lo, hi):  # rowkernels.block_stats as it was (de2dcc1), verbatim
    M = b.shape[0]
    mn, mx, dm = b[0, 0], b[0, 0], np.float32(0.0)
    if f == 0:  # (with z-ranges, the block's min/max are theirs: every sample lies in a square)
        for r in range(M):
            for c in range(M):
                v = b[r, c]
                mn = min(mn, v)
                mx = max(mx, v)
    h = (M - 1) // 2
    for i in range(h + 1):
        for j in range(h + 1):
            if i < h and j < h:
                if (i + j) % 2 == 0:
                    diag = (b[2 * i, 2 * j] + b[2 * i + 2, 2 * j + 2]) * _HALF
                else:
                    diag = (b[2 * i, 2 * j + 2] + b[2 * i + 2, 2 * j]) * _HALF
                dm = max(dm, abs(b[2 * i + 1, 2 * j + 1] - diag))
            if j < h:
                dm = max(dm, abs(b[2 * i, 2 * j + 1] - (b[2 * i, 2 * j] + b[2 * i, 2 * j + 2]) * _HALF))
            if i < h:
                dm = max(dm, abs(b[2 * i + 1, 2 * j] - (b[2 * i, 2 * j] + b[2 * i + 2, 2 * j]) * _HALF))
    if f > 0:
        n = (M - 1) // f
        for a in range(n):
            for q in range(n):
                zl, zh = b[a * f, q * f], b[a * f, q * f]
                for r in range(a * f, a * f + f + 1):
                    for c in range(q * f, q * f + f + 1):
                        zl = min(zl, b[r, c])
                        zh = max(zh, b[r, c])
                lo[a, q], hi[a, q] = zl, zh
                mn, mx = min(mn, zl), max(mx, zh)
    return mn, mx, dm


def _per_block(row, zacc=None, i=0):
    """The per-block loop ``_row_stats`` was before (de2dcc1), with that tree's kernel."""
    nb, M = row.shape[0], row.shape[1]
    f = 2**zacc.lay.k if zacc is not None else 0
    n = (M - 1) // f if f else 0
    mm, dm = np.empty((nb, 2), np.float32), np.empty(nb, np.float32)
    for j in range(nb):
        lo, hi = np.empty((n, n), np.float32), np.empty((n, n), np.float32)
        mn, mx, d = _block_stats_de2dcc1(np.ascontiguousarray(row[j], np.float32), f, lo, hi)
        mm[j], dm[j] = (mn, mx), d
        if zacc is not None:
            zacc.put_zrange(i, j, lo, hi)
    return mm, dm


def _wide(rng, M, nb):
    w = (rng.normal(size=(M, nb * (M - 1) + 1)).cumsum(axis=1) * 20).astype(np.float32)
    # signed zeros tie with each other: which one a min/max keeps shows in the bytes
    w[16:33, 16:50] = np.abs(w[16:33, 16:50]) + 1  # squares whose minimum is a tie of 0.0 and -0.0
    w[20:30, 20:40] = 0.0
    w[25, 22] = w[21, 35] = np.float32(-0.0)
    w[48:65, 48:82] = -np.abs(w[48:65, 48:82]) - 1  # and whose maximum is
    w[50:60, 50:70] = np.float32(-0.0)
    w[55, 52] = w[51, 66] = 0.0
    b = slice(2 * (M - 1), 3 * (M - 1) + 1)  # a block whose minimum is a tie (level > 0 takes it from every sample)
    w[:, b] = np.abs(w[:, b]) + 1
    w[M // 3, b] = np.float32(-0.0)
    w[M // 4, b] = 0.0
    w[M // 2, : 2 * (M - 1)] = -np.abs(w[M // 2, : 2 * (M - 1)]) - 500  # a row of minima across the first blocks
    return w


@pytest.mark.parametrize("level0", [True, False])
def test_row_stats_in_place_give_the_per_block_loops_bytes(level0):
    rng = np.random.default_rng(11)
    lay = TerrainLayout(4 * 128 + 1, 4 * 128 + 1, 129, 9)  # 4 × 4 level-0 blocks, z-range squares of f = 2^k samples
    M, nb = lay.M, lay.blocks(0)
    for wide in (_wide(rng, M, nb), _wide(rng, M, nb)):
        views = {"strided": block_view(wide, nb, M), "stacked": np.ascontiguousarray(block_view(wide, nb, M)),
                 "float64": block_view(wide, nb, M).astype(np.float64), "non-wide": block_view(wide, nb, M)[1:]}
        for name, row in views.items():
            ref_acc, acc = (DiamondAccumulator(lay), DiamondAccumulator(lay)) if level0 else (None, None)
            want, got = _per_block(row, ref_acc, 2), _row_stats(row, acc, 2)
            assert [a.tobytes() for a in got] == [a.tobytes() for a in want], name
            if level0:
                assert [a.tobytes() for a in acc.zmin + acc.zmax] == [a.tobytes() for a in ref_acc.zmin + ref_acc.zmax], name
                n = (M - 1) // 2**lay.k
                assert np.isfinite(acc.zmin[lay.J][2 * n: 3 * n, : row.shape[0] * n]).all()


def _numpy_tent(rows, i):
    a, m0, m1, b = (rows.get(k) for k in (2 * i - 1, 2 * i, 2 * i + 1, 2 * i + 2))
    M = m0.shape[0]
    above = a[M - 2: M - 1] if a is not None else m0[:1]
    below = b[0:2] if b is not None else np.concatenate([m1[M - 1:]] * 2)
    g = np.concatenate([above, m0[:M - 1], m1[:M - 1], below]).astype(np.float32)
    g = np.concatenate([g[:, :1], g, g[:, -1:]], axis=1)
    return colors.tent_decimate(g).astype(np.float16)


@pytest.mark.parametrize("i", [0, 1])
def test_tent_row_over_every_float16_but_nan(i):
    M, W = 33, 32 * 32 + 1
    every = np.arange(65536, dtype=np.uint32).astype(np.uint16).view(np.float16)
    every = every[~np.isnan(every)]
    rng = np.random.default_rng(5)
    rows = {k: rng.permutation(np.resize(every, M * W * 3)).reshape(M, W, 3) for k in range(2 * i - 1, 2 * i + 3) if k >= 0}
    assert np.isin(every.view(np.uint16), np.concatenate([r.view(np.uint16).ravel() for r in rows.values()])).all()
    with np.errstate(over="ignore", invalid="ignore"):
        want = _numpy_tent(rows, i)
    got = colors.tent_wide(rows, i)
    nan = np.isnan(want)
    assert np.array_equal(np.isnan(got), nan)
    assert np.array_equal(got.view(np.uint16)[~nan], want.view(np.uint16)[~nan])


def test_h2f_matches_numpy_for_every_float16():
    bits = np.arange(65536, dtype=np.uint32).astype(np.uint16)
    rows = {0: np.repeat(bits.view(np.float16)[None, :, None], 3, axis=2).reshape(1, 65536, 3)}
    want = rows[0].astype(np.float32)
    got = np.empty_like(want)
    rk.from_half(rows[0].view(np.uint16), rk.half_lut(), got)
    nan = np.isnan(want)
    assert np.array_equal(np.isnan(got), nan) and np.array_equal(got.view(np.uint32)[~nan], want.view(np.uint32)[~nan])


_GEO = (0.0, 30.0, 0.0, 0.0, 0.0, -30.0)


def _interrupting(arr, fail_after):
    return FlakySource(arr, fail_after, "flags", transform=_GEO)


def _files(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def test_done_flags_written_per_row_or_at_the_end_give_the_same_store(tmp_path, monkeypatch):
    a = SyntheticSource(700, seed=3).read(0, 700, 0, 650)
    a[100:120, 30:90] = np.nan  # filled samples: the nodata count goes with the flags
    src = lambda: ArraySource(a.copy(), "flags", transform=_GEO)  # noqa: E731
    monkeypatch.setattr(ingest, "_FLAG_EVERY", 0.0)  # after every row
    prepare_terrain(src(), tmp_path / "each.zarr", block=129, K=5, workers=2)
    monkeypatch.setattr(ingest, "_FLAG_EVERY", 1e9)  # only when the pass ends
    prepare_terrain(src(), tmp_path / "end.zarr", block=129, K=5, workers=2)
    each, end = _files(tmp_path / "each.zarr"), _files(tmp_path / "end.zarr")
    assert sorted(each) == sorted(end) and [k for k in each if each[k] != end[k]] == []

    for every in (0.0, 1e9):  # interrupted while reading strip 3: strips 0–2 and what they completed are flagged
        monkeypatch.setattr(ingest, "_FLAG_EVERY", every)
        out = tmp_path / f"cut{every:g}.zarr"
        with pytest.raises(KeyboardInterrupt):
            prepare_terrain(_interrupting(a.copy(), 3 + 2), out, block=129, K=5, workers=2)  # (+ the void fill's pass over the input and its window, at strip 0)
        import zarr

        g = zarr.open_group(str(out), mode="r")
        assert g["blocks/0/done"][...].all(axis=1).tolist() == [True] * 3 + [False] * 5
        assert g["blocks/1/done"][...].all(axis=1).tolist() == [True, False, False, False]
        assert g.attrs["nodata"]["filled"] == int(np.isnan(a).sum())  # (all in strip 0)
        resumed = _interrupting(a.copy(), 10**9)
        res = prepare_terrain(resumed, out, block=129, K=5, workers=2)
        assert res.resumed and resumed.reads == 3 and res.filled == int(np.isnan(a).sum())
        TerrainStore(out)
        got = _files(out)
        assert [k for k in end if k != "zarr.json" and got.get(k) != end[k]] == []
