"""Void filling (data/terrain/voidfill.py): one function of the whole input, computed a strip
and a window at a time with the same bits; smooth across large voids (no plateau, no cliff, no
seam at strip borders), and what prepare stores."""

from __future__ import annotations

import numpy as np
import pytest

from massview.data.terrain import ArraySource, TerrainStore, prepare_terrain
from massview.data.terrain import voidfill
from massview.data.terrain.voidfill import VoidFill
from massview.data.terrain.synthetic import SyntheticSource


def _dem_with_voids(rows=700, cols=600):
    a = SyntheticSource(max(rows, cols), seed=11).read(0, rows, 0, cols)
    y, x = np.mgrid[0:rows, 0:cols]
    a[(y - 300) ** 2 + (x - 260) ** 2 < 140 ** 2] = np.nan  # across three 129-row strips
    a[:40, 450:] = np.nan  # at the top edge and the right
    a[500:, :3] = np.nan  # a sliver down the left edge, to the bottom
    a[rows - 90, 100:cols - 100] = np.nan  # one row
    return a


def _by_strips(fill: VoidFill, a: np.ndarray, M: int) -> np.ndarray:
    """What prepare does: strips of M rows sharing their first row with the strip above (final)."""
    out, r0 = a.copy(), 0
    while r0 < a.shape[0]:
        strip = a[r0: r0 + M].copy()
        if r0:
            strip[0] = out[r0]
        fill.fill(r0, strip)
        out[r0: r0 + strip.shape[0]] = strip
        r0 += M - 1
    return out


def test_the_fill_is_the_same_whole_by_strips_and_by_windows(monkeypatch):
    a = _dem_with_voids()
    fill = VoidFill(ArraySource(a.copy(), "voids"))
    whole = a.copy()
    fill.fill(0, whole)
    assert np.isfinite(whole).all() and np.array_equal(whole[np.isfinite(a)], a[np.isfinite(a)])
    for M in (65, 129, 257):
        assert _by_strips(fill, a, M).tobytes() == whole.tobytes(), M
    monkeypatch.setattr(voidfill, "_WINDOW", 64)  # many column windows, each with its margins
    narrow = a.copy()
    fill.fill(0, narrow)
    assert narrow.tobytes() == whole.tobytes()


def test_a_large_void_is_smooth_and_close_to_the_truth():
    y, x = np.mgrid[0:700, 0:600].astype(np.float64)
    plane = (100 + 0.8 * x + 0.5 * y).astype(np.float32)
    hole = (y - 350) ** 2 + (x - 300) ** 2 < 150 ** 2
    a = plane.copy()
    a[hole] = np.nan
    got = a.copy()
    VoidFill(ArraySource(a.copy(), "plane")).fill(0, got)
    err = np.sqrt(np.mean((got[hole] - plane[hole]) ** 2))
    mean_fill = np.sqrt(np.mean((plane[~hole].mean() - plane[hole]) ** 2))
    assert err < 0.2 * mean_fill  # (7.9 against 70.7: a tilted plane stays tilted)

    truth = SyntheticSource(700, seed=11).read(0, 700, 0, 600)
    a = truth.copy()
    a[hole] = np.nan
    got = a.copy()
    VoidFill(ArraySource(a.copy(), "terrain")).fill(0, got)
    data_step = max(np.abs(np.diff(truth, axis=0)).max(), np.abs(np.diff(truth, axis=1)).max())
    rim = hole[1:] | hole[:-1]
    assert np.abs(np.diff(got, axis=0))[rim].max() <= data_step  # no cliff at the rim or inside
    assert np.abs(np.diff(got, axis=1))[hole[:, 1:] | hole[:, :-1]].max() <= data_step
    assert got[hole].std() > 0.05 * truth.std()  # not a plateau
    assert truth[~hole].min() <= got[hole].min() and got[hole].max() <= truth[~hole].max()


def test_prepare_stores_the_whole_input_fill(tmp_path):
    a = _dem_with_voids(500, 420)
    a[np.isnan(a)] = -9999.0
    src = ArraySource(a.copy(), "voids", nodata=-9999.0)
    res = prepare_terrain(src, tmp_path / "v.zarr", block=129, K=9, color=None)
    raw = np.where(a == -9999.0, np.nan, a).astype(np.float32)
    want = raw.copy()
    VoidFill(ArraySource(raw.copy(), "voids")).fill(0, want)
    s = TerrainStore(tmp_path / "v.zarr")
    lay, M = s.layout, s.layout.M
    got = np.empty((lay.S, lay.S), np.float32)
    for i in range(lay.blocks(0)):
        for j in range(lay.blocks(0)):
            got[i * (M - 1): i * (M - 1) + M, j * (M - 1): j * (M - 1) + M] = s.get_block(0, i, j)
    assert res.filled == int(np.isnan(raw).sum())
    assert got[:500, :420].tobytes() == want.tobytes()


def test_a_void_filling_prepare_reads_the_input_once_more_only_when_there_is_a_void(tmp_path, monkeypatch):
    built = []
    real = voidfill.VoidFill.__init__

    def spy(self, *a, **k):
        built.append(1)
        real(self, *a, **k)

    monkeypatch.setattr(voidfill.VoidFill, "__init__", spy)
    a = SyntheticSource(300, seed=2).read(0, 300, 0, 300)
    prepare_terrain(ArraySource(a.copy(), "full"), tmp_path / "a.zarr", block=129, color=None)
    assert built == []
    a[10:200:7, 5:290:3] = np.nan  # voids in most strips: still one VoidFill
    prepare_terrain(ArraySource(a, "voids"), tmp_path / "b.zarr", block=129, color=None)
    assert built == [1]


@pytest.mark.parametrize("shape", [(2, 2), (3, 700), (700, 3)])
def test_tiny_and_thin_inputs(shape):
    a = np.arange(shape[0] * shape[1], dtype=np.float32).reshape(shape)
    a.flat[::2] = np.nan
    got = a.copy()
    VoidFill(ArraySource(a.copy(), "thin")).fill(0, got)
    assert np.isfinite(got).all() and np.nanmin(a) <= got.min() and got.max() <= np.nanmax(a)


def test_a_void_on_the_cell_grid_has_no_walls():
    """walk10 H1: a void whose rim lies on the push-pull's cell borders (a missing 256² mosaic
    tile) was filled as a tray with walls: with aligned 2 x 2 sums no cell spanned the rim, and
    the data's detail did not carry over it (rim steps up to 3x the data's steepest). The push's
    tent kernel reaches one finer cell past each cell's square."""
    truth = SyntheticSource(700, seed=11).read(0, 700, 0, 600)
    a = truth.copy()
    a[256:512, 128:384] = np.nan
    hole = np.isnan(a)
    got = a.copy()
    VoidFill(ArraySource(a.copy(), "tile")).fill(0, got)
    rim = np.concatenate([np.abs(np.diff(got, axis=0))[hole[1:] ^ hole[:-1]], np.abs(np.diff(got, axis=1))[hole[:, 1:] ^ hole[:, :-1]]])
    true_rim = np.concatenate([np.abs(np.diff(truth, axis=0))[hole[1:] ^ hole[:-1]],
                               np.abs(np.diff(truth, axis=1))[hole[:, 1:] ^ hole[:, :-1]]])
    assert rim.max() <= true_rim.max() and rim.mean() <= 2 * true_rim.mean(), (rim.max(), true_rim.max(), rim.mean(), true_rim.mean())
