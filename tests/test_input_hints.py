"""walk9 H1, L1, M5: inputs that prepare fine but render wrong get a warning that names the fix:
untagged float fill values (±3.4e38, 1e30, −9999) and a transform in degrees without a CRS."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import run_cli
from massview.data.generators import synthetic_heights


def _dem():
    return (synthetic_heights(0, 200, 0, 240, 240, 5) * 0.5 + 400).astype(np.float32)


@pytest.mark.parametrize("marker,dtype", [(-3.4028235e38, "f4"), (3.4028235e38, "f4"), (1e30, "f4"), (-9999.0, "f4"),
                                          (-9999, "i2")])
def test_an_untagged_fill_value_gets_a_hint_and_the_command_it_gives_works(tmp_path, marker, dtype):
    a = _dem().astype(dtype)
    a[50:55, 60:65] = marker
    np.save(tmp_path / "d.npy", a)
    out = tmp_path / "a.zarr"
    proc = run_cli("prepare", "terrain", tmp_path / "d.npy", "-o", out)
    hint = [ln for ln in proc.stderr.splitlines() if "--nodata" in ln]
    assert len(hint) == 1 and "d.npy" in hint[0], proc.stderr
    given = hint[0].split("prepare again with ", 1)[1].split(" (")[0].split()  # pasted as printed (walk10 L2)
    proc = run_cli("prepare", "terrain", tmp_path / "d.npy", *given, "-o", out)
    assert "25 nodata samples filled" in proc.stdout and "--nodata" not in proc.stderr, (given, proc.stdout, proc.stderr)


def test_ordinary_heights_get_no_marker_hint(tmp_path):
    a = _dem() - 11000.0  # bathymetry, below any marker but not one
    np.save(tmp_path / "d.npy", a)
    proc = run_cli("prepare", "terrain", tmp_path / "d.npy", "-o", tmp_path / "a.zarr")
    assert "--nodata" not in proc.stderr


def test_a_transform_in_degrees_without_a_crs_gets_a_hint(tmp_path):
    import rasterio
    from rasterio.transform import from_origin

    a = _dem()
    scan = (a - a.min()) / (a.max() - a.min()) * 0.3  # a close-range scan in metres: 0.5 mm spacing, 0.3 m of relief
    for name, transform, crs in (("deg.tif", from_origin(7.7, 46.05, 0.000335, 0.000335), None),
                                 ("utm.tif", from_origin(500000.0, 5100000.0, 30.0, 30.0), None),
                                 ("wgs.tif", from_origin(7.7, 46.05, 0.000335, 0.000335), "EPSG:4326"),
                                 ("scan.tif", from_origin(0.0, 0.12, 0.0005, 0.0005), None)):
        a = scan if name == "scan.tif" else _dem()
        with rasterio.open(tmp_path / name, "w", driver="GTiff", height=a.shape[0], width=a.shape[1], count=1,
                           dtype="float32", transform=transform, crs=crs) as f:
            f.write(a, 1)
        proc = run_cli("prepare", "terrain", tmp_path / name, "-o", tmp_path / (name + ".zarr"))
        said = "looks like degrees" in proc.stderr and "--crs EPSG:4326" in proc.stderr
        assert said == (name == "deg.tif"), (name, proc.stderr)


@pytest.mark.parametrize("shape,refused", [((3, 8000), True), ((8000, 3), True), ((200, 8000), False), ((2, 1025), False)])
def test_a_strip_padded_to_a_mostly_empty_square_is_refused_before_anything_is_written(tmp_path, shape, refused):
    """walk9 H2: a 3 x 100000 strip grew towards a 131073² store of many GB. A shape whose
    padded square holds more than 64x its samples (and is larger than 4097²) is refused naming
    the square and the way out; thinner-than-square inputs within that, and small ones, work."""
    from massview.core.errors import IngestError
    from massview.data.terrain import ArraySource, prepare_terrain

    a = (np.arange(shape[0] * shape[1], dtype=np.float32).reshape(shape) % 97) + 100
    out = tmp_path / "s.zarr"
    if refused:
        with pytest.raises(IngestError, match=r"padded to a square of 8193² .* Crop it, or cut it into pieces"):
            prepare_terrain(ArraySource(a, "strip"), out)
        assert not out.exists()
    else:
        assert prepare_terrain(ArraySource(a, "strip"), out, color=None).layout.rows == shape[0]


def test_any_raster_gdal_reads_is_an_input_and_the_rest_get_the_list(tmp_path):
    """walk9 L3: .bil, NetCDF and the zipped SRTM tile a download comes as were refused as an
    unknown format although rasterio reads them; the message left out .vrt/.asc/.img."""
    import zipfile

    import rasterio
    from rasterio.transform import from_origin

    from massview.core.errors import IngestError
    from massview.data.terrain import open_source

    a = (np.random.default_rng(0).random((120, 130)) * 500 + 100).astype(np.float32)
    with rasterio.open(tmp_path / "d.bil", "w", driver="EHdr", height=120, width=130, count=1, dtype="float32",
                       transform=from_origin(500000, 5100000, 30, 30), crs="EPSG:32632") as f:
        f.write(a, 1)
    src = open_source(tmp_path / "d.bil")
    assert src.spacing() == (30.0, 30.0) and np.array_equal(src.read(0, 120, 0, 130), a)
    (np.arange(1201 * 1201) % 3000).astype(">i2").reshape(1201, 1201).tofile(tmp_path / "N45E006.hgt")
    with zipfile.ZipFile(tmp_path / "N45E006.SRTMGL3.hgt.zip", "w") as z:
        z.write(tmp_path / "N45E006.hgt", "N45E006.hgt")
    src = open_source(tmp_path / "N45E006.SRTMGL3.hgt.zip")
    assert (src.rows, src.cols) == (1201, 1201) and 60 < src.spacing()[0] < 70 and 90 < src.spacing()[1] < 95
    (tmp_path / "N45E006.hgt").rename(tmp_path / "mydem.hgt")  # misnamed: its place is lost, and the warning says why
    proc = run_cli("prepare", "terrain", tmp_path / "mydem.hgt", "-o", tmp_path / "my.zarr", "-q")
    assert "placed by its file name, such as N45E006.hgt" in proc.stderr
    (tmp_path / "junk.xyz").write_text("hello")
    with pytest.raises(IngestError, match=r"junk.xyz: unknown input format .xyz; use a raster GDAL reads \(.*\.vrt.*\.asc.*"
                                          r"gdal_translate"):
        open_source(tmp_path / "junk.xyz")
