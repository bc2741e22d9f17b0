"""Issue 20: the parallel ingest writes exactly what the serial ingest wrote before it.

* every array of a prepared store (decoded values, dtype, shape; level 0's shading as computed
  from ``halo/0`` since format version 3) and its attributes (but the version) match the
  digests recorded with the previous, single-threaded ingest (tests/ingest_golden.py, recorded
  before the change) on a real DEM and on synthetic non-2^n+1 ones (the case with nodata holes
  recorded again when void filling changed, with 1 and with 2 workers alike);
* 1 worker and several workers give identical stores, to the byte of every chunk file;
* the direct chunk writer produces the very bytes zarr writes.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from ingest_golden import CASES, prepare_case, recorded_for, recorded_version, store_digest


@pytest.mark.parametrize("name", sorted(CASES))
def test_prepare_reproduces_the_recorded_stores(tmp_path, name):
    from massview.data.terrain import FORMAT_VERSION, TerrainStore

    prepare_case(name, tmp_path / "s.zarr")
    got = store_digest(tmp_path / "s.zarr", as_version=recorded_version())
    want = recorded_for(name, got)  # the recording of this host's input (see ingest_golden)
    assert TerrainStore(tmp_path / "s.zarr").attrs["format_version"] == FORMAT_VERSION
    assert sorted(got) == sorted(want)
    assert [k for k in want if got[k] != want[k]] == [], f"input heights/0 {got['heights/0'][:16]}"


def _files(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file() and p.name != "zarr.json"}


def test_one_and_many_workers_write_identical_stores(tmp_path):
    prepare_case("synthetic_700x700_b129_K5", tmp_path / "one.zarr", workers=1)
    prepare_case("synthetic_700x700_b129_K5", tmp_path / "many.zarr", workers=3)
    assert store_digest(tmp_path / "one.zarr") == store_digest(tmp_path / "many.zarr")
    one, many = _files(tmp_path / "one.zarr"), _files(tmp_path / "many.zarr")
    assert sorted(one) == sorted(many)
    assert [k for k in one if one[k] != many[k]] == []


def test_chunk_writer_writes_the_bytes_zarr_writes(tmp_path):
    import zarr

    from massview.data.terrain.store import ChunkWriter, _compressor

    rng = np.random.default_rng(0)
    data = {"h": rng.normal(size=(2, 2, 129, 129)).astype(np.float32).cumsum(axis=3),
            "s": rng.normal(size=(2, 2, 129, 129, 3)).astype(np.float16)}
    for d in ("a", "b"):
        g = zarr.open_group(str(tmp_path / d), mode="w", zarr_format=3)
        for k, a in data.items():
            g.create_array(k, shape=a.shape, chunks=(1, 1) + a.shape[2:], dtype=a.dtype, compressors=_compressor(a.dtype.itemsize))
    ga, gb = zarr.open_group(str(tmp_path / "a"), mode="r+"), zarr.open_group(str(tmp_path / "b"), mode="r+")
    for k, a in data.items():
        ga[k][...] = a
        w = ChunkWriter(gb, k)
        for i in range(2):
            w.write(i, 0, a[i])
        assert np.array_equal(zarr.open_group(str(tmp_path / "b"), mode="r")[k][...], a)
    assert _files(tmp_path / "a") == _files(tmp_path / "b")
