"""Issue 20, tenth round: the prepare's overheads around its kernels, with unchanged output.

* a level-0 strip read into a reused buffer (holding another strip's samples) is the strip
  read into a fresh one, on every read path (straight into the strip, narrower input, nodata
  filled, bottom padding);
* the pyramid pass reuses its strip buffers (the store itself is compared with digests in
  tests/test_ingest_parallel.py and between read paths in tests/test_ingest_fastpaths.py);
* ``rowkernels.all_finite`` is ``np.isfinite(a).all()``;
* ``prepare`` freezes the objects alive before it (``gc.freeze``) only while it runs, also
  when it fails, and leaves a caller's own freeze alone;
* (eleventh round) numba's first kernel load does not import scipy.linalg.
"""

from __future__ import annotations

import gc

import numpy as np
import pytest

from massview.core.errors import IngestError
from massview.data.terrain import ArraySource, ingest, open_source, prepare_terrain
from massview.data.terrain import rowkernels as rk
from massview.data.terrain.layout import TerrainLayout
from massview.data.terrain.synthetic import SyntheticSource


def _dem(rows: int, cols: int) -> np.ndarray:
    return np.ascontiguousarray(SyntheticSource(max(rows, cols), seed=5).read(0, rows, 0, cols).astype(np.float32))


@pytest.mark.parametrize("kind", ["npy", "npy-narrow", "nodata"])
def test_strip_read_into_a_used_buffer_is_the_fresh_strip(tmp_path, kind):
    a = _dem(*((300, 513) if kind == "npy" else (300, 277)))  # (npy: as wide as the padded grid, S = 513)
    if kind == "nodata":
        a[140, 3:60] = -9999.0
        src = ArraySource(a, "nodata", nodata=-9999.0)
    else:
        np.save(tmp_path / "d.npy", a)
        src = open_source(tmp_path / "d.npy")
        assert hasattr(src, "read_float32_into")
    lay = TerrainLayout(src.rows, src.cols, 129, 5)
    rng = np.random.default_rng(0)
    prev_fresh = prev_used = None
    for bi in range(lay.blocks(0)):  # (the last strips lie partly or wholly in the bottom padding)
        fresh, n_fresh = ingest._read_strip(src, lay, bi, prev_fresh)
        used = (rng.normal(size=(lay.M, lay.S)) * 1e4).astype(np.float32)
        used[rng.random(used.shape) < 0.01] = np.nan
        got, n_used = ingest._read_strip(src, lay, bi, prev_used, out=used)
        assert got is used and n_used == n_fresh
        assert got.tobytes() == fresh.tobytes()
        prev_fresh, prev_used = fresh[-1].copy(), got[-1].copy()


def test_pyramid_pass_reuses_its_strip_buffers(tmp_path, monkeypatch):
    a = _dem(1025, 1025)  # 8 strips of 129-sample blocks
    outs = []
    read = ingest._read_strip

    def spy(src, lay, bi, prev_row, out=None, **kw):
        outs.append(out)
        return read(src, lay, bi, prev_row, out, **kw)

    monkeypatch.setattr(ingest, "_read_strip", spy)
    prepare_terrain(ArraySource(a, "dem"), tmp_path / "s.zarr", block=129, K=5, workers=2)
    assert len(outs) == 8 and all(o is not None for o in outs)
    assert len({id(o) for o in outs}) < len(outs)  # (each strip a fresh buffer before: 8)


def test_all_finite_is_numpys():
    rng = np.random.default_rng(2)
    base = np.clip(rng.normal(size=4099), -3, 3).astype(np.float32) * np.float32(1e38)
    base[::7] = np.float32(1e-45)  # subnormals, the largest finite value
    base[5] = np.finfo(np.float32).max
    assert rk.all_finite(base.view(np.uint32)) == bool(np.isfinite(base).all()) is True
    for bad in (np.inf, -np.inf, np.nan, -np.nan):
        for at in (0, 1, 2048, 4098):
            b = base.copy()
            b[at] = bad
            assert rk.all_finite(b.view(np.uint32)) is bool(np.isfinite(b).all()) is False
    assert rk.all_finite(np.empty(0, np.uint32)) is True


def test_prepare_freezes_the_old_objects_only_while_it_runs(tmp_path):
    a = _dem(300, 300)
    seen = []
    assert gc.get_freeze_count() == 0 and gc.isenabled()
    prepare_terrain(ArraySource(a, "dem"), tmp_path / "s.zarr", block=129, K=5, workers=2,
                    progress=lambda *p: seen.append(gc.get_freeze_count()))
    assert seen and min(seen) > 0  # frozen while it ran ...
    assert gc.get_freeze_count() == 0 and gc.isenabled()  # ... and not after
    with pytest.raises(IngestError):
        prepare_terrain(ArraySource(np.full((300, 300), np.nan, np.float32), "nan"), tmp_path / "n.zarr", block=129, K=5)
    assert gc.get_freeze_count() == 0  # also after an error
    gc.freeze()  # a caller's own freeze stays
    try:
        n = gc.get_freeze_count()
        prepare_terrain(ArraySource(a, "dem"), tmp_path / "t.zarr", block=129, K=5, workers=2)
        assert gc.get_freeze_count() > n // 2  # not unfrozen (frozen objects freed meanwhile leave the count)
    finally:
        gc.unfreeze()


def test_kernels_load_without_scipy_linalg_which_imports_afterwards():
    """numba's first kernel load does not import scipy.linalg (data/jit.py hides its BLAS
    probe, 0.2–0.35 s of every prepare's start); scipy.linalg still imports afterwards, whole."""
    import subprocess
    import sys

    code = ("import sys, numpy as np\n"
            "from massview.data.terrain import rowkernels\n"
            "from massview.data import skykernel, lodkernel\n"
            "assert rowkernels.all_finite(np.zeros(4, np.uint32))\n"
            "assert 'scipy.linalg' not in sys.modules, 'scipy.linalg imported by the kernels'\n"
            "import scipy.linalg, scipy.linalg.cython_blas\n"
            "assert scipy.linalg.cython_blas is not None and 'scipy.linalg.cython_blas' in sys.modules\n"
            "print(float(scipy.linalg.det(np.eye(2) * 2)))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["4.0"]
