"""Terrain store: round trips, formats, georeference, nodata, resume, verify, pyramid invariants."""

import json
import os
import shutil

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from conftest import FlakySource, run_cli
from massview.core.errors import IngestError, StoreError
from massview.data.generators import synthetic_heights
from massview.data.terrain import ArraySource, TerrainStore, open_source, prepare_terrain
from massview.data.terrain.meta import reduce_max
from massview.data.terrain.synthetic import SyntheticSource


def finest(store: TerrainStore) -> np.ndarray:
    lay = store.layout
    M = lay.M
    out = np.full((lay.S, lay.S), np.nan, np.float32)
    for i in range(lay.blocks(0)):
        for j in range(lay.blocks(0)):
            b = store.get_block(0, i, j)
            sl = out[i * (M - 1): i * (M - 1) + M, j * (M - 1): j * (M - 1) + M]
            seen = ~np.isnan(sl)
            assert np.array_equal(sl[seen], b[seen]), "shared block borders disagree"
            sl[:] = b
    return out


def prepare(arr, tmp_path, name="t.zarr", **kw):
    kw.setdefault("color", None)
    kw.setdefault("block", 129)
    prepare_terrain(ArraySource(arr, "test"), tmp_path / name, **kw)
    return TerrainStore(tmp_path / name)


@pytest.mark.parametrize("shape", [(1000, 760), (130, 2000), (2, 2), (129, 129)])
def test_float_round_trip_awkward_sizes(tmp_path, shape):
    rng = np.random.default_rng(shape[0])
    a = (rng.standard_normal(shape) * 100).astype(np.float32)
    st_ = prepare(a, tmp_path)
    assert np.array_equal(finest(st_)[: shape[0], : shape[1]], a)


@pytest.mark.slow
def test_round_trip_4097(tmp_path):
    # every sample distinct noise on a 2600 m ramp: as hard for the store as terrain, and ~0.7 CPU-s
    # to make where synthetic_heights at 4097² takes ~25 (this host)
    a = (np.random.default_rng(11).normal(0, 30, (4097, 4097)) + np.linspace(0, 2600, 4097)[:, None]).astype(np.float32)
    np.save(tmp_path / "dem.npy", a)
    run_cli("prepare", "terrain", tmp_path / "dem.npy", "-o", tmp_path / "s.zarr", "--no-color", "-q")
    st_ = TerrainStore(tmp_path / "s.zarr")
    assert st_.layout.levels == 5 and st_.layout.S == 4097
    assert np.array_equal(finest(st_), a)


def test_one_row_is_rejected(tmp_path):
    np.save(tmp_path / "line.npy", np.zeros((1, 500), np.float32))
    proc = run_cli("prepare", "terrain", tmp_path / "line.npy", "-o", tmp_path / "x.zarr", check=False)
    assert proc.returncode != 0 and "at least 2 × 2 samples, got 1 × 500" in proc.stderr
    assert "Traceback" not in proc.stderr and not (tmp_path / "x.zarr").exists()


@pytest.mark.parametrize("dtype", [np.int16, np.uint16, np.int32])
def test_integer_inputs_exact_after_conversion(tmp_path, dtype):
    rng = np.random.default_rng(3)
    a = rng.integers(-300 if dtype != np.uint16 else 0, 9000, (300, 200)).astype(dtype)
    np.save(tmp_path / "i.npy", a)
    prepare_terrain(open_source(tmp_path / "i.npy"), tmp_path / "i.zarr", block=129, color=None)
    assert np.array_equal(finest(TerrainStore(tmp_path / "i.zarr"))[:300, :200], a.astype(np.float32))


@given(st.integers(2, 300), st.integers(2, 300), st.integers(0, 2**31))
@settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
def test_pyramid_invariants(tmp_path, rows, cols, seed):
    a = (np.random.default_rng(seed).random((rows, cols)) * 50).astype(np.float32)
    path = tmp_path / f"p{rows}_{cols}_{seed}"
    prepare_terrain(ArraySource(a, "h"), path, block=129, color=None)
    s = TerrainStore(path)
    lay, M = s.layout, s.layout.M
    fine = finest(s)
    for lv in range(1, lay.levels):  # coarse samples equal the fine samples they coincide with
        step = 2**lv
        for i in range(lay.blocks(lv)):
            for j in range(lay.blocks(lv)):
                r0, c0 = lay.block_origin(lv, i, j)
                assert np.array_equal(s.get_block(lv, i, j), fine[r0: r0 + (M - 1) * step + 1: step, c0: c0 + (M - 1) * step + 1: step])
        assert np.all(s.block_error(lv) >= reduce_max(s.block_error(lv - 1), 2))  # saturated blocks
    sq, dg, zmin, zmax = s.lod_arrays()
    for j in range(lay.J):  # diamond errors saturated over the DAG
        n = 2**j
        e = dg[j]
        kids = np.maximum.reduce([e[0, :n, :n], e[0, 1:, :n], e[1, :n, :n], e[1, :n, 1:]])
        assert np.all(sq[j] >= kids)
        if j + 1 < lay.J:
            c = np.pad(sq[j + 1], 1)
            assert np.all(e[0, :, :n] >= np.maximum(c[0:-1:2, 1:-1:2], c[1::2, 1:-1:2]))
        assert np.all(zmin[j] <= reduce_max(-zmin[j + 1] * -1, 1).min() + np.inf)
    J = lay.J
    for j in range(J):  # square z-ranges nest and bound the samples
        assert np.all(zmin[j] <= zmin[j + 1].reshape(2**j, 2, 2**j, 2).min(axis=(1, 3)))
    side = 2 ** (lay.n - J)
    v, u = 1, 0
    if (v + 1) * side < lay.S:
        blk = fine[v * side:(v + 1) * side + 1, u * side:(u + 1) * side + 1]
        assert zmin[J][v, u] == blk.min() and zmax[J][v, u] == blk.max()


def test_geotiff_keeps_crs_and_transform(tmp_path):
    import rasterio
    from rasterio.transform import from_origin

    a = synthetic_heights(0, 300, 0, 400, 400, 2)
    with rasterio.open(tmp_path / "dem.tif", "w", driver="GTiff", width=400, height=300, count=1, dtype="float32",
                       crs="EPSG:32632", transform=from_origin(500000, 5200000, 25, 25), tiled=True) as ds:
        ds.write(a, 1)
    run_cli("prepare", "terrain", tmp_path / "dem.tif", "-o", tmp_path / "g.zarr", "--block", "129", "-q")
    info = json.loads(run_cli("info", tmp_path / "g.zarr", "--json").stdout)
    from rasterio.crs import CRS

    assert CRS.from_wkt(info["crs"]).to_epsg() == 32632
    assert info["transform"] == [500000.0, 25.0, 0.0, 5200000.0, 0.0, -25.0]
    assert info["spacing_m"] == [25.0, 25.0] and info["samples"] == [300, 400]
    assert "EPSG:32632" in run_cli("info", tmp_path / "g.zarr").stdout
    assert np.array_equal(finest(TerrainStore(tmp_path / "g.zarr"))[:300, :400], a)


def test_nodata_and_nan_are_filled_and_recorded(tmp_path):
    a = synthetic_heights(0, 200, 0, 300, 300, 4)
    a[50:60, 70:90] = -9999
    a[150, 10] = np.nan
    a[:5, :5] = -9999
    np.save(tmp_path / "n.npy", a)
    run_cli("prepare", "terrain", tmp_path / "n.npy", "-o", tmp_path / "n.zarr", "--nodata", "-9999", "--block", "129", "-q")
    s = TerrainStore(tmp_path / "n.zarr")
    fine = finest(s)[:200, :300]
    assert s.attrs["nodata"] == {"value": -9999.0, "filled": 200 + 1 + 25}
    hole = fine[50:60, 70:90]
    assert np.all(np.isfinite(hole)) and hole.min() >= a[40:70, 60:100][a[40:70, 60:100] > -9999].min() - 1e-3
    ok = np.isfinite(a) & (a != -9999)
    assert np.array_equal(fine[ok], a[ok])


def test_other_formats(tmp_path):
    a = (np.random.default_rng(5).random((150, 140)) * 1000).astype(np.float32)
    np.savez(tmp_path / "d.npz", elevation=a, other=np.zeros(3))
    with pytest.raises(IngestError, match="name one with --array"):
        open_source(tmp_path / "d.npz")
    src = open_source(tmp_path / "d.npz", array="elevation")
    assert np.array_equal(src.read(0, 150, 0, 140), a)
    a.astype("<f4").tofile(tmp_path / "d.raw")
    src = open_source(tmp_path / "d.raw", shape=(150, 140), dtype="<f4")
    assert np.array_equal(src.read(10, 20, 5, 50), a[10:20, 5:50])
    with pytest.raises(IngestError, match="needs 168000"):
        open_source(tmp_path / "d.raw", shape=(150, 280), dtype="<f4")
    hgt = (np.arange(1201 * 1201) % 3000 - 100).astype(">i2").reshape(1201, 1201)
    hgt[0, 0] = -32768
    hgt.tofile(tmp_path / "N46E007.hgt")
    src = open_source(tmp_path / "N46E007.hgt")
    w = src.read(0, 3, 0, 3)
    assert np.isnan(w[0, 0]) and w[0, 1] == hgt[0, 1]
    dx, dy = src.spacing()
    assert 60 < dx < 70 and 90 < dy < 95  # 3 arc-seconds at 46.5°N, in metres
    with pytest.raises(IngestError, match="no such file"):
        open_source(tmp_path / "missing.tif")
    (tmp_path / "bad.tif").write_bytes(b"not a tiff")
    with pytest.raises(IngestError, match="cannot open"):
        open_source(tmp_path / "bad.tif")


def test_interrupted_prepare_resumes_and_only_then_opens(tmp_path):
    a = synthetic_heights(0, 600, 0, 500, 600, 9)
    with pytest.raises(KeyboardInterrupt):
        prepare_terrain(FlakySource(a, 2), tmp_path / "r.zarr", block=129, color="computed")
    with pytest.raises(StoreError, match="incomplete"):
        TerrainStore(tmp_path / "r.zarr")
    proc = run_cli("info", tmp_path / "r.zarr", check=False)
    assert proc.returncode != 0 and "incomplete" in proc.stderr
    src = FlakySource(a, 10**9)
    res = prepare_terrain(src, tmp_path / "r.zarr", block=129, color="computed")
    assert res.resumed and src.reads == 3  # strips 0 and 1 were not read again
    prepare_terrain(ArraySource(a, "flaky"), tmp_path / "ref.zarr", block=129, color="computed")
    s, ref = TerrainStore(tmp_path / "r.zarr"), TerrainStore(tmp_path / "ref.zarr")
    assert np.array_equal(finest(s), finest(ref))
    for j, (x, y) in enumerate(zip(s.lod_arrays()[0], ref.lod_arrays()[0])):
        assert np.array_equal(x, y), j
    run_cli("verify", tmp_path / "r.zarr", "-q")


def test_prepare_stopped_while_creating_the_arrays_starts_anew(tmp_path, monkeypatch):
    """A run stopped after the store's attributes but before all its arrays existed (the first
    ~0.1 s of a prepare) left nothing to resume: the next run makes the store anew, instead of
    failing on a missing array."""
    from massview.data.terrain import store as tstore

    a = synthetic_heights(0, 600, 0, 500, 600, 9)
    create, made = tstore._ArraysLike.create, []

    def stop_at_the_fifth(self, name, family, **kw):
        made.append(name)
        if len(made) == 5:
            raise KeyboardInterrupt
        return create(self, name, family, **kw)

    monkeypatch.setattr(tstore._ArraysLike, "create", stop_at_the_fifth)
    with pytest.raises(KeyboardInterrupt):
        prepare_terrain(ArraySource(a, "dem"), tmp_path / "p.zarr", block=129)
    monkeypatch.undo()
    res = prepare_terrain(ArraySource(a, "dem"), tmp_path / "p.zarr", block=129)
    assert not res.resumed
    ref = prepare_terrain(ArraySource(a, "dem"), tmp_path / "ref.zarr", block=129)
    assert ref.seconds > 0 and np.array_equal(finest(TerrainStore(tmp_path / "p.zarr")), finest(TerrainStore(tmp_path / "ref.zarr")))


def test_verify_names_a_damaged_or_missing_block(tmp_path):
    a = synthetic_heights(0, 300, 0, 300, 300, 6)
    s = prepare(a, tmp_path, "v.zarr")
    run_cli("verify", tmp_path / "v.zarr", "-q")
    chunk = s.chunk_path(0, 1, 2)
    data = chunk.read_bytes()
    chunk.write_bytes(data[: len(data) // 2])
    proc = run_cli("verify", tmp_path / "v.zarr", "-q", check=False)
    assert proc.returncode != 0 and "block (level 0, 1, 2)" in proc.stderr and "Traceback" not in proc.stderr
    chunk.unlink()
    proc = run_cli("verify", tmp_path / "v.zarr", "-q", check=False)
    assert proc.returncode != 0 and "block (level 0, 1, 2) is missing" in proc.stderr
    shutil.rmtree(tmp_path / "v.zarr")


def test_verify_catches_metadata_that_disagrees(tmp_path):
    import zarr

    prepare(synthetic_heights(0, 300, 0, 300, 300, 6), tmp_path, "m.zarr")
    g = zarr.open_group(str(tmp_path / "m.zarr"), mode="r+")
    mm = g["blocks/0/minmax"][...]
    mm[1, 1, 1] += 5
    g["blocks/0/minmax"][...] = mm
    proc = run_cli("verify", tmp_path / "m.zarr", "-q", check=False)
    assert proc.returncode != 0 and "level 0: block (1, 1) min/max" in proc.stderr


def test_generator_is_deterministic_at_any_tiling(tmp_path):
    whole = synthetic_heights(0, 300, 0, 300, 300, 8)
    tiles = np.block([[synthetic_heights(r, min(r + 77, 300), c, min(c + 130, 300), 300, 8) for c in range(0, 300, 130)]
                      for r in range(0, 300, 77)])
    assert np.array_equal(whole, tiles)
    assert not np.array_equal(whole, synthetic_heights(0, 300, 0, 300, 300, 9))
    run_cli("generate", "terrain", tmp_path / "g.npy", "--size", 300, "--seed", 8, "-q")
    assert np.array_equal(np.load(tmp_path / "g.npy"), whole)
    s = SyntheticSource(300, 8)
    assert np.array_equal(s.read(10, 20, 30, 40), whole[10:20, 30:40])


def test_existing_complete_store_needs_overwrite(tmp_path):
    a = synthetic_heights(0, 100, 0, 100, 100, 1)
    prepare(a, tmp_path, "o.zarr")
    with pytest.raises(StoreError, match="--overwrite"):
        prepare(a, tmp_path, "o.zarr")
    prepare(a * 2, tmp_path, "o.zarr", overwrite=True)
    assert np.array_equal(finest(TerrainStore(tmp_path / "o.zarr"))[:100, :100], a * 2)


def test_orthophoto_colours_the_pyramid(tmp_path):
    import rasterio

    a = synthetic_heights(0, 200, 0, 300, 300, 3)
    np.save(tmp_path / "d.npy", a)
    rgb = np.random.default_rng(2).integers(0, 256, (3, 200, 300), dtype=np.uint8)
    from rasterio.transform import from_origin

    with rasterio.open(tmp_path / "o.tif", "w", driver="GTiff", width=300, height=200, count=3, dtype="uint8",
                       transform=from_origin(500, 900, 2, 2)) as ds:
        ds.write(rgb)
    run_cli("prepare", "terrain", tmp_path / "d.npy", "-o", tmp_path / "c.zarr", "--color", tmp_path / "o.tif", "--block", "129", "-q")
    s = TerrainStore(tmp_path / "c.zarr")
    assert s.attrs["color"] == "orthophoto"
    c = s.get_color(0, 0, 1)  # rows 0..128, cols 128..256 of the same grid
    assert np.array_equal(c, np.moveaxis(rgb, 0, -1)[0:129, 128:257])
    coarse = s.get_color(1, 0, 0)  # level 1 samples every other pixel
    assert np.array_equal(coarse[:50, :50], np.moveaxis(rgb, 0, -1)[0:100:2, 0:100:2])
    with pytest.raises(IngestError, match="not an RGB image"):
        prepare_terrain(ArraySource(a, "x"), tmp_path / "bad.zarr", block=129, ortho=open_source(tmp_path / "d.npy"))


def _geotiff(path, a, x0, y0, px, crs="EPSG:32632"):
    """``a`` (h, w) float32 or (3, h, w) uint8 as a north-up GeoTIFF at (x0, y0) with ``px`` pixels."""
    import rasterio
    from rasterio.transform import from_origin

    bands = a if a.ndim == 3 else a[None]
    with rasterio.open(path, "w", driver="GTiff", width=bands.shape[2], height=bands.shape[1], count=bands.shape[0],
                       dtype=bands.dtype, transform=from_origin(x0, y0, px, px), crs=crs) as ds:
        ds.write(bands)
    return path


def test_orthophoto_is_placed_by_its_georeference(tmp_path):
    """A georeferenced DEM and orthophoto: each sample takes the image pixel at its place (not the
    image stretched over the DEM); an image covering half the DEM is used for that half, with a
    note; an image of another place, or in another CRS, is an error that leaves no store."""
    dem = synthetic_heights(0, 260, 0, 260, 260, 3).astype(np.float32)
    _geotiff(tmp_path / "dem.tif", dem, 500000, 4000000, 10)  # 2600 m square
    rng = np.random.default_rng(4)
    fine = rng.integers(0, 256, (3, 520, 520), dtype=np.uint8)  # the same square at 5 m
    _geotiff(tmp_path / "fine.tif", fine, 500000, 4000000, 5)
    res = prepare_terrain(open_source(tmp_path / "dem.tif"), tmp_path / "f.zarr", block=129, ortho=open_source(tmp_path / "fine.tif"))
    assert not any("cover" in w or "stretch" in w for w in res.warnings)
    c = TerrainStore(tmp_path / "f.zarr").get_color(0, 1, 0)  # rows 128..256, cols 0..128
    assert np.array_equal(c, np.moveaxis(fine, 0, -1)[256:514:2, 0:258:2])
    # east half only: DEM columns 130..259 lie in the image, at its columns 0..129 (same 10 m pixels)
    half = rng.integers(0, 256, (3, 260, 130), dtype=np.uint8)
    _geotiff(tmp_path / "half.tif", half, 501300, 4000000, 10)
    res = prepare_terrain(open_source(tmp_path / "dem.tif"), tmp_path / "h.zarr", block=129, ortho=open_source(tmp_path / "half.tif"))
    assert any("covers 50% of the DEM" in w for w in res.warnings), res.warnings
    s, img = TerrainStore(tmp_path / "h.zarr"), np.moveaxis(half, 0, -1)
    assert np.array_equal(s.get_color(0, 0, 1)[:, 2:], img[0:129, 0:127])  # block column 1 = DEM cols 128..256
    assert np.array_equal(s.get_color(0, 0, 1)[:, 0], img[0:129, 0])  # cols 128, 129: west of the image, its edge pixel
    # another place, another CRS: errors before anything is written
    _geotiff(tmp_path / "far.tif", half, 900000, 4000000, 10)
    with pytest.raises(IngestError, match=r"far.tif does not cover the DEM dem.tif.*x 900000\.\.901300"):
        prepare_terrain(open_source(tmp_path / "dem.tif"), tmp_path / "x.zarr", block=129, ortho=open_source(tmp_path / "far.tif"))
    _geotiff(tmp_path / "utm33.tif", fine, 500000, 4000000, 5, crs="EPSG:32633")
    with pytest.raises(IngestError, match=r"utm33.tif: its CRS \(EPSG:32633\) differs from the DEM's \(EPSG:32632\)"):
        prepare_terrain(open_source(tmp_path / "dem.tif"), tmp_path / "x.zarr", block=129, ortho=open_source(tmp_path / "utm33.tif"))
    assert not (tmp_path / "x.zarr").exists()
    # a DEM with only a spacing (no place): the image is stretched, and prepare says so
    np.save(tmp_path / "d.npy", dem)
    res = prepare_terrain(open_source(tmp_path / "d.npy", spacing="10"), tmp_path / "s.zarr", block=129,
                          ortho=open_source(tmp_path / "half.tif"))
    assert any("d.npy has no georeference, so half.tif is stretched" in w for w in res.warnings), res.warnings
    assert np.array_equal(TerrainStore(tmp_path / "s.zarr").get_color(0, 0, 0)[:, ::2][:, :5], np.moveaxis(half, 0, -1)[0:129, 0:5])


def _interrupted_prepare(monkeypatch, dem, out, **kw):
    """A real prepare of the file ``dem`` stopped (KeyboardInterrupt) after its first two strips."""
    from massview.data.terrain import ingest

    read, calls = ingest._read_strip, []

    def stop_at_the_third(*a, **k):
        calls.append(1)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return read(*a, **k)

    monkeypatch.setattr(ingest, "_read_strip", stop_at_the_third)
    with pytest.raises(KeyboardInterrupt):
        prepare_terrain(open_source(dem), out, block=129, **kw)
    monkeypatch.undo()


def test_a_resumed_prepare_starts_again_when_the_input_or_options_changed(tmp_path, monkeypatch):
    """An interrupted prepare is resumed only with the same input file (name, size,
    modification time) and the same options; otherwise it starts again and says why (it used to
    resume and keep the old file's heights, or its old spacing and vertical scale, silently)."""
    import os
    import shutil

    dem, out = tmp_path / "w.npy", tmp_path / "w.zarr"
    old, new = synthetic_heights(0, 600, 0, 500, 600, 9), synthetic_heights(0, 600, 0, 500, 600, 10)
    np.save(dem, old)
    _interrupted_prepare(monkeypatch, dem, out)
    same = prepare_terrain(open_source(dem), out, block=129)
    assert same.resumed and not same.warnings[:-1]  # (the last warning: no georeference)

    shutil.rmtree(out)  # (an interrupted --overwrite keeps the complete store: test_an_interrupted_overwrite_...)
    _interrupted_prepare(monkeypatch, dem, out)
    np.save(dem, new)  # other heights, same name and shape
    os.utime(dem, ns=(dem.stat().st_atime_ns, dem.stat().st_mtime_ns + 10**9))  # (a later mtime even on a coarse clock)
    res = prepare_terrain(open_source(dem), out, block=129)
    assert not res.resumed and any("size or modification time" in w and "started again" in w for w in res.warnings)
    assert np.array_equal(finest(TerrainStore(out))[:600, :500], new) and not np.array_equal(old, new)

    shutil.rmtree(out)  # (an interrupted --overwrite keeps the complete store: test_an_interrupted_overwrite_...)
    _interrupted_prepare(monkeypatch, dem, out)
    res = prepare_terrain(open_source(dem, spacing="10"), out, block=129, vertical_scale=3.0)
    assert not res.resumed and any("spacing, vertical scale" in w for w in res.warnings)
    s = TerrainStore(out)
    assert s.spacing == (10.0, 10.0) and s.vertical_scale == 3.0

    shutil.rmtree(out)  # one interrupted by an older massview (format 2, walk11 L4): started again, and said why
    _interrupted_prepare(monkeypatch, dem, out)
    import zarr

    zarr.open_group(str(out), mode="r+").attrs["format_version"] = 2
    res = prepare_terrain(open_source(dem), out, block=129)
    assert not res.resumed and any("store format (version 2" in w and "started again" in w for w in res.warnings)
    assert TerrainStore(out).attrs["format_version"] == 3


def test_bad_dtype_and_workers_are_one_line_errors_before_any_store(tmp_path):
    raw = tmp_path / "d.raw"
    np.zeros((30, 40), np.float32).tofile(raw)
    proc = run_cli("prepare", "terrain", raw, "--shape", "30x40", "--dtype", "foo", "-o", tmp_path / "d.zarr", check=False)
    assert proc.returncode != 0 and "--dtype 'foo'" in proc.stderr and "Traceback" not in proc.stderr
    proc = run_cli("prepare", "terrain", raw, "--shape", "30x40", "--dtype", "float32", "--workers", "-2", "-o", tmp_path / "w.zarr",
                   check=False)
    assert proc.returncode != 0 and "--workers" in proc.stderr and "Traceback" not in proc.stderr
    assert not (tmp_path / "d.zarr").exists() and not (tmp_path / "w.zarr").exists()


@pytest.mark.parametrize("damage", ["root layout", "heights/1", "lod/zmin/0"])
def test_a_damaged_zarr_json_is_a_one_line_error_naming_it(tmp_path, damage):
    """A store whose root attributes lack the layout, or whose array metadata does not parse:
    info, verify and render say which and what to do, no traceback (they raised KeyError and
    JSONDecodeError)."""
    prepare(synthetic_heights(0, 300, 0, 300, 300, 6), tmp_path, "d.zarr", color="computed")
    store = tmp_path / "d.zarr"
    if damage == "root layout":
        doc = json.loads((store / "zarr.json").read_text())
        del doc["attributes"]["rows"]
        (store / "zarr.json").write_text(json.dumps(doc))
        named = "no valid layout"
    else:
        (store / damage / "zarr.json").write_text('{"shape": [1, ')  # cut short
        named = damage
    for cmd in (["info", store], ["verify", store, "-q"], ["render", store, "--frames", 1, "--size", "64x48", "-o", tmp_path / "r", "-q"]):
        proc = run_cli(*cmd, check=False)
        if damage == "lod/zmin/0" and cmd[0] == "info":
            continue  # (info reads no metadata array)
        assert proc.returncode != 0, (cmd[0], proc.stdout[-500:])
        assert named in proc.stderr and "Traceback" not in proc.stderr, (cmd[0], proc.stderr[-1500:])


def test_verify_of_an_interrupted_store_says_to_finish_it_not_to_overwrite_it(tmp_path):
    a = synthetic_heights(0, 600, 0, 500, 600, 9)
    with pytest.raises(KeyboardInterrupt):
        prepare_terrain(FlakySource(a, 2), tmp_path / "r.zarr", block=129, color="computed")
    proc = run_cli("verify", tmp_path / "r.zarr", "-q", check=False)
    assert proc.returncode != 0 and "re-run the same prepare command" in proc.stderr + proc.stdout
    assert "--overwrite" not in proc.stderr + proc.stdout


def test_info_and_verify_say_what_the_store_holds(tmp_path):
    """``info`` gives the world box keyframe files use and says what ``color: computed`` means;
    on an interrupted store it gives no compression ratio (it printed 7258 for a store with no
    heights written); ``verify`` names colour only where the store has it; ``prepare`` says
    "1 level" (walk5 L2, L3, L4, L6, L7)."""
    a = synthetic_heights(0, 200, 0, 250, 250, 3)
    np.save(tmp_path / "d.npy", a)
    proc = run_cli("prepare", "terrain", tmp_path / "d.npy", "-o", tmp_path / "s.zarr", "--block", 257, "--spacing", 10)
    assert " 1 level of 257² blocks" in proc.stdout
    info = json.loads(run_cli("info", tmp_path / "s.zarr", "--json").stdout)
    assert info["world_box"][0][:2] == [0.0, -1990.0] and info["world_box"][1][:2] == [2490.0, 0.0]
    out = run_cli("info", tmp_path / "s.zarr").stdout
    assert "keyframe files" in out and "colour map at render time" in out
    proc = run_cli("verify", tmp_path / "s.zarr", "-q")
    assert "(heights, shading)" in proc.stdout and "colour" not in proc.stdout
    with pytest.raises(KeyboardInterrupt):
        prepare_terrain(FlakySource(synthetic_heights(0, 600, 0, 500, 600, 9), 0), tmp_path / "r.zarr", block=129)
    info = json.loads(run_cli("info", tmp_path / "r.zarr", "--json", check=False).stdout)
    assert not info["complete"] and info["compression_ratio"] is None and info["world_box"] is None


def test_geotiff_scale_offset_south_up_feet_and_rotation(tmp_path):
    """GeoTIFF georeference and band tags a user's file may carry: the band's scale and offset
    are applied (they were ignored: relief 10× too high), a south-up raster is read north-up (it
    was stored as is: mirrored north-south), a CRS in feet has its spacing converted to metres
    with a note about the heights' unit, and a rotated grid is refused with what to do."""
    import rasterio
    from rasterio.transform import Affine, from_origin

    h = synthetic_heights(0, 130, 0, 130, 130, 5).astype(np.float32)
    counts = np.round((h - 100.0) / 0.1).astype(np.int32)
    metres = counts.astype(np.float32) * np.float32(0.1) + np.float32(100.0)  # (float32 arithmetic, as the reader does)

    def write(name, a, transform, crs="EPSG:32632", **kw):
        with rasterio.open(tmp_path / name, "w", driver="GTiff", width=a.shape[1], height=a.shape[0], count=1, dtype=a.dtype,
                           transform=transform, crs=crs) as ds:
            ds.write(a, 1)
            if kw:
                ds.scales, ds.offsets = (kw["scale"],), (kw["offset"],)
        return open_source(tmp_path / name)

    ref = write("n.tif", metres, from_origin(500000, 4000000, 30, 30))
    prepare_terrain(ref, tmp_path / "n.zarr", block=129)
    expect = finest(TerrainStore(tmp_path / "n.zarr"))
    prepare_terrain(write("s.tif", counts, from_origin(500000, 4000000, 30, 30), scale=0.1, offset=100.0), tmp_path / "s.zarr", block=129)
    assert np.array_equal(finest(TerrainStore(tmp_path / "s.zarr")), expect)
    south = write("south.tif", metres[::-1].copy(),
                  Affine(30, 0, 500000, 0, 30, 4000000 - 30 * 130))  # row 0 = the southern edge
    assert south.transform == pytest.approx(ref.transform)
    prepare_terrain(south, tmp_path / "south.zarr", block=129)
    assert np.array_equal(finest(TerrainStore(tmp_path / "south.zarr")), expect)
    res = prepare_terrain(write("ft.tif", h, from_origin(2_000_000, 200_000, 100, 100), crs="EPSG:2272"), tmp_path / "ft.zarr", block=129)
    assert TerrainStore(tmp_path / "ft.zarr").spacing == pytest.approx((30.48006, 30.48006), rel=1e-5)
    assert any("US survey foot" in w and "--vertical-scale 0.304801" in w for w in res.warnings), res.warnings
    with pytest.raises(IngestError, match="rotated or sheared.*gdalwarp"):
        write("rot.tif", h, Affine(21.2, 21.2, 500000, 21.2, -21.2, 4000000))


def test_single_block_reads_are_zarrs_values_and_fall_back_on_damage(tmp_path):
    """get_block / get_shade / get_color decode a block's chunk file directly (no zarr event
    loop): the same values, bit for bit, as zarr's own read of every block at every level; a
    truncated chunk still fails with the file named and a missing one still reads as missing,
    through zarr's read."""
    from massview.core.errors import BlockNotFoundError, CorruptBlockError

    a = synthetic_heights(0, 400, 0, 400, 400, 5)
    np.save(tmp_path / "d.npy", a)
    _geotiff(tmp_path / "o.tif", np.random.default_rng(3).integers(0, 256, (3, 400, 400), dtype=np.uint8), 0, 400, 1)
    run_cli("prepare", "terrain", tmp_path / "d.npy", "-o", tmp_path / "s.zarr", "--color", tmp_path / "o.tif", "--block", "129", "-q")
    s = TerrainStore(tmp_path / "s.zarr")
    n = 0
    for lv in range(s.layout.levels):
        for i in range(s.layout.blocks(lv)):
            for j in range(s.layout.blocks(lv)):
                if lv == 0:  # (level 0's shading is computed from the heights and the halo, read directly)
                    halo = (s.get_halo(i, j), np.asarray(s.group["halo/0"][i, j]))
                    assert halo[0].dtype == halo[1].dtype and halo[0].tobytes() == halo[1].tobytes()
                shade = (s._direct_block("shade", lv, i, j, "<f2", (3,)), np.asarray(s.group[f"shade/{lv}"][i, j])) if lv else (
                    s.get_shade(0, i, j),) * 2
                direct = [s._direct_block("heights", lv, i, j, "<f4"), shade[0], s._direct_block("color", lv, i, j, "u1", (3,))]
                assert all(d is not None for d in direct)  # (the fast path is taken)
                got = [s.get_block(lv, i, j), s.get_shade(lv, i, j), s.get_color(lv, i, j)]
                want = [np.asarray(s.group[f"heights/{lv}"][i, j]), shade[1], np.asarray(s.group[f"color/{lv}"][i, j])]
                for g, d, w in zip(got, direct, want):
                    assert g.dtype == w.dtype and g.shape == w.shape and g.tobytes() == w.tobytes() == d.tobytes()
                n += 1
    assert n >= 15  # (4×4 + 2×2 + 1 blocks)
    chunk = s.chunk_path(0, 1, 2)
    chunk.write_bytes(chunk.read_bytes()[:100])
    with pytest.raises(CorruptBlockError, match=r"block \(level 0, 1, 2\).*" + str(chunk.name)):
        TerrainStore(tmp_path / "s.zarr").get_block(0, 1, 2)
    chunk.unlink()
    with pytest.raises(BlockNotFoundError, match=r"block \(level 0, 1, 2\) is missing"):
        TerrainStore(tmp_path / "s.zarr").get_block(0, 1, 2)
    halo = s.chunk_path(0, 2, 0, "halo")  # level-0 shading needs its block row's halo file: damage is named
    assert halo == tmp_path / "s.zarr/halo/0/c/2/0/0/0"
    halo.write_bytes(halo.read_bytes()[:100])
    with pytest.raises(CorruptBlockError, match=r"halo of block \(level 0, 2, 1\) does not decode.*" + str(halo)):
        TerrainStore(tmp_path / "s.zarr").get_shade(0, 2, 1)
    halo.unlink()
    with pytest.raises(BlockNotFoundError, match=r"halo of block \(level 0, 2, 1\) is missing.*" + str(halo)):
        TerrainStore(tmp_path / "s.zarr").get_shade(0, 2, 1)


def test_int16_voids_without_nodata_get_a_hint(tmp_path):
    """A raw int16 DEM whose lowest sample is −32768 (SRTM's void marker) prepared without
    --nodata keeps those as heights; the run now says so and names the option (walk5 L9); with
    --nodata −32768 the samples are filled and nothing is said."""
    a = (np.random.default_rng(0).random((300, 400)) * 600).astype("<i2")
    a[100:110, 50:60] = -32768
    a.tofile(tmp_path / "v.raw")
    proc = run_cli("prepare", "terrain", tmp_path / "v.raw", "--shape", "300x400", "--dtype", "<i2", "-o", tmp_path / "a.zarr")
    assert "its lowest height is -32768" in proc.stderr and "--nodata -32768" in proc.stderr
    proc = run_cli("prepare", "terrain", tmp_path / "v.raw", "--shape", "300x400", "--dtype", "<i2", "--nodata", "-32768",
                   "-o", tmp_path / "b.zarr")
    assert "lowest height" not in proc.stderr and "100 nodata samples filled" in proc.stdout


def test_an_interrupted_overwrite_keeps_the_complete_store(tmp_path, monkeypatch):
    """walk6 #6: --overwrite removed a complete store first, so a rebuild stopped half-way left
    an incomplete one where a good one had been. The new store is built beside it and swapped
    in only when complete; stopped, the old store is as it was and nothing is left beside it;
    finished, the new store is in its place (and nothing beside it either)."""
    a = synthetic_heights(0, 600, 0, 500, 600, 9)
    np.save(tmp_path / "new.npy", (a * 2).astype(np.float32))
    out = tmp_path / "s.zarr"
    prepare_terrain(ArraySource(a, "dem"), out, block=129)
    before = finest(TerrainStore(out))
    _interrupted_prepare(monkeypatch, tmp_path / "new.npy", out, overwrite=True)
    assert np.array_equal(finest(TerrainStore(out)), before)  # opens: complete, the old heights
    assert sorted(p.name for p in tmp_path.iterdir()) == ["new.npy", "s.zarr"]
    proc = run_cli("prepare", "terrain", tmp_path / "new.npy", "-o", out, "--overwrite", "--spacing", "10", "-q", check=False)
    assert proc.returncode == 0, proc.stderr
    assert np.allclose(finest(TerrainStore(out)), 2 * before)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["new.npy", "s.zarr"]
    (tmp_path / "s.zarr.rebuild").mkdir()  # a user's folder where the rebuild goes: named, not removed
    (tmp_path / "s.zarr.rebuild" / "mine.txt").write_text("x")
    with pytest.raises(StoreError, match="s.zarr.rebuild is in the way"):
        prepare_terrain(ArraySource(a, "dem"), out, block=129, overwrite=True)
    assert (tmp_path / "s.zarr.rebuild" / "mine.txt").exists()


def test_overwrite_through_a_symlink_rebuilds_where_it_points(tmp_path):
    """walk9 H3: a store kept on another disk behind a symlink. --overwrite replaced the link by
    a new folder on the link's disk, left the old store and a dangling ``.replaced`` link, and
    the next --overwrite failed on that link. Now the store is rebuilt at the link's target,
    the link stays, and nothing is left beside either; a leftover link is unlinked, its target
    kept."""
    a = synthetic_heights(0, 300, 0, 260, 300, 4)
    (tmp_path / "disk").mkdir()
    (tmp_path / "here").mkdir()
    target, link = tmp_path / "disk" / "data.zarr", tmp_path / "here" / "dem.zarr"
    prepare_terrain(ArraySource(a, "dem"), target, block=129)
    link.symlink_to(target)
    for k in (2, 3):
        prepare_terrain(ArraySource(a * k, "dem"), link, block=129, overwrite=True)
        assert link.is_symlink() and np.allclose(finest(TerrainStore(target))[:300, :260], a * k)
        assert sorted(p.name for p in (tmp_path / "disk").iterdir()) == ["data.zarr"]
        assert sorted(p.name for p in (tmp_path / "here").iterdir()) == ["dem.zarr"]
    keep = tmp_path / "disk" / "keep.zarr"
    prepare_terrain(ArraySource(a, "dem"), keep, block=129)
    (tmp_path / "disk" / "data.zarr.replaced").symlink_to(keep)  # what the old code left
    prepare_terrain(ArraySource(a, "dem"), link, block=129, overwrite=True)
    assert not (tmp_path / "disk" / "data.zarr.replaced").exists() and TerrainStore(keep).attrs["complete"]


def test_flat_chunk_keys_read_as_the_nested_ones(tmp_path, monkeypatch):
    """A store written with zarr's nested chunk keys (``c/i/j/0/0``, what prepare writes) and one
    with flat keys (``c.i.j.0.0``, a "." separator: tried as prepare's default, see
    store.CHUNK_KEYS): the same decoded blocks, block rows, shading and Röttger table through
    the direct reads (each array's chunk names from its own zarr.json), both verify clean, and
    a chunk rewritten into the flat store keeps its name and bytes."""
    import zarr

    from massview.data.terrain.store import CHUNK_KEYS, ChunkWriter
    from massview.data.terrain.verify import verify_store

    h = np.random.default_rng(11).standard_normal((600, 500)).astype(np.float32).cumsum(axis=0).cumsum(axis=1)
    nested = prepare(h, tmp_path, "nested.zarr", workers=2)
    monkeypatch.setitem(CHUNK_KEYS, "separator", ".")
    flat = prepare(h, tmp_path, "flat.zarr", workers=2)
    monkeypatch.undo()
    assert (tmp_path / "nested.zarr/heights/0/c/1/2/0/0").is_file() and (tmp_path / "nested.zarr/shade/1/c/1/0/0/0/0").is_file()
    assert (tmp_path / "nested.zarr/halo/0/c/1/0/0/0").is_file() and (tmp_path / "flat.zarr/halo/0/c.1.0.0.0").is_file()
    assert (tmp_path / "flat.zarr/heights/0/c.1.2.0.0").is_file() and not (tmp_path / "flat.zarr/heights/0/c").exists()
    assert not [p for p in (tmp_path / "flat.zarr").rglob("c") if p.is_dir()]  # no chunk folders at all
    lay = flat.layout
    for lv in range(lay.levels):
        for i in range(lay.blocks(lv)):
            np.testing.assert_array_equal(flat.get_block_row(lv, i), nested.get_block_row(lv, i))
            for j in range(lay.blocks(lv)):
                for s in (flat, nested):
                    assert s.chunk_path(lv, i, j).is_file() and s.shade_file(lv, i, j).is_file()
                    assert s._direct_block("heights", lv, i, j, "<f4") is not None  # read directly, not through zarr
                np.testing.assert_array_equal(flat.get_block(lv, i, j), nested.get_block(lv, i, j))
                np.testing.assert_array_equal(flat.get_shade(lv, i, j), nested.get_shade(lv, i, j))
                np.testing.assert_array_equal(flat.get_block(lv, i, j), np.asarray(flat._heights[lv][i, j]))
    for t in range(flat.attrs["roettger"]["depths"]):
        np.testing.assert_array_equal(flat.group[f"roettger/d2/{t}"][...], nested.group[f"roettger/d2/{t}"][...])
    assert verify_store(tmp_path / "flat.zarr") == [] and verify_store(tmp_path / "nested.zarr") == []
    f, row = tmp_path / "flat.zarr/heights/0/c.1.0.0.0", flat.get_block_row(0, 1).copy()
    before = f.read_bytes()
    f.unlink()
    ChunkWriter(zarr.open_group(str(tmp_path / "flat.zarr"), mode="r+"), "heights/0").write(1, 0, row[:1])
    assert f.read_bytes() == before


def test_one_writer_at_a_time_and_readers_are_told_it_is_being_written(tmp_path):
    """walk9 M3: two prepares into one output deleted each other's arrays, or the first reported
    success for a store holding the second's input. A writer holds a lock beside the store
    (here this test process holds it, as a running prepare would): a second prepare or generate
    fails at once naming it, and info/verify/render of the half-written store say it is being
    written rather than "interrupted: re-run" (which would start that race). Released, the
    same command runs, and the lock file goes with it."""
    from massview.data.rebuild import writing

    a = synthetic_heights(0, 300, 0, 300, 300, 4)
    np.save(tmp_path / "d.npy", a)
    out = tmp_path / "s.zarr"
    first = prepare_terrain(ArraySource(a, "dem"), out, block=129)  # a complete store, to be rebuilt
    with writing(out):
        proc = run_cli("prepare", "terrain", tmp_path / "d.npy", "-o", out, "--overwrite", "-q", check=False)
        assert proc.returncode == 1 and f"{out} is being written by another massview right now (pid {os.getpid()}" in proc.stderr
        proc = run_cli("generate", "scene", "forest", "--size", "0.05", "-o", tmp_path / "f.zarr", "-q", check=False)
        assert proc.returncode == 0  # (another output: not held)
        with writing(tmp_path / "f2.zarr"):
            proc = run_cli("generate", "scene", "forest", "--size", "0.05", "-o", tmp_path / "f2.zarr", "-q", check=False)
            assert proc.returncode == 1 and "being written by another massview" in proc.stderr
    assert first.layout.rows == 300 and not (tmp_path / ".s.zarr.lock").exists()
    import zarr

    zarr.open_group(str(out), mode="r+").attrs["complete"] = False  # as while a prepare writes it
    with writing(out):
        for cmd in (("info", out), ("render", out, "--frames", "1", "--size", "64x48", "--out", tmp_path / "r")):
            proc = run_cli(*cmd, check=False)
            assert proc.returncode == 1 and "being written by a prepare running now" in proc.stderr, proc.stderr
        proc = run_cli("verify", out, "-q", check=False)  # (one line for it, not its unfinished rows as problems: walk10 L5)
        assert proc.returncode == 1 and proc.stderr.count("massview: verify:") == 1 and "a prepare is writing it now" in proc.stderr
    proc = run_cli("info", out, check=False)
    assert "interrupted" in proc.stderr or "incomplete" in proc.stdout + proc.stderr
    assert run_cli("prepare", "terrain", tmp_path / "d.npy", "-o", out, "-q").returncode == 0


def test_an_existing_empty_folder_takes_a_new_store(tmp_path):
    """walk9 L2: terrain refused an empty folder made by hand (or a mount point), scenes took it."""
    out = tmp_path / "empty.zarr"
    out.mkdir()
    assert run_cli("generate", "terrain", "-o", out, "--size", "300", "-q").returncode == 0
    assert TerrainStore(out).attrs["complete"]
