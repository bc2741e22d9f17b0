"""Bad data and outputs do not pass silently (issue 8): invalid DEMs, heavy filling, the data's
own height range, spacing for inputs without a georeference, unwritable outputs."""

import json
import os
import shutil
import tempfile

import numpy as np
import pytest

from conftest import SMALL_SCENE, clean_env, run_cli
from massview.core.errors import StoreError
from massview.data.terrain import TerrainStore


@pytest.mark.parametrize("name,fill,nodata", [("nan", np.nan, None), ("inf", np.inf, None), ("neginf", -np.inf, None),
                                              ("nodata", -9999.0, "-9999"), ("i2nodata", -32768, None)])
def test_dem_without_a_valid_sample_fails_and_leaves_no_store(tmp_path, name, fill, nodata):
    dtype = np.int16 if name == "i2nodata" else np.float32
    src = tmp_path / f"{name}.npy"
    np.save(src, np.full((300, 280), fill, dtype))
    args = ["prepare", "terrain", src, "-o", tmp_path / "s.zarr", "-q"] + (["--nodata", nodata] if nodata else [])
    if name == "i2nodata":
        args += ["--nodata", "-32768"]
    proc = run_cli(*args, check=False)
    assert proc.returncode != 0 and "Traceback" not in proc.stderr
    assert f"{name}.npy: every one of its 300x280 samples is" in proc.stderr
    assert not (tmp_path / "s.zarr").exists()
    with pytest.raises(StoreError):
        TerrainStore(tmp_path / "s.zarr")


def test_mostly_filled_dem_warns_and_info_shows_the_fraction(tmp_path):
    a = np.random.default_rng(3).normal(500, 50, (300, 300)).astype(np.float32)
    a[:180] = np.nan  # 60 % missing
    np.save(tmp_path / "most.npy", a)
    proc = run_cli("prepare", "terrain", tmp_path / "most.npy", "-o", tmp_path / "m.zarr", "--spacing", "10", "-q")
    assert "warning: most.npy: 60% of the samples were nodata" in proc.stderr
    info = json.loads(run_cli("info", tmp_path / "m.zarr", "--json").stdout)
    assert info["filled_fraction"] == pytest.approx(0.6)
    assert "filled_fraction" in run_cli("info", tmp_path / "m.zarr").stdout
    a[:100] = 1.0  # 27 % missing: no warning
    np.save(tmp_path / "some.npy", a)
    proc = run_cli("prepare", "terrain", tmp_path / "some.npy", "-o", tmp_path / "s.zarr", "--spacing", "10", "-q")
    assert "warning" not in proc.stderr


def test_height_range_is_the_datas_range(tmp_path):
    """Isolated peaks and pits on odd samples: the coarse levels drop them, the range must not."""
    a = np.random.default_rng(5).normal(1000, 30, (700, 600)).astype(np.float32)
    a[301, 203], a[55, 477] = 2958.139, 71.922
    np.save(tmp_path / "d.npy", a)
    run_cli("prepare", "terrain", tmp_path / "d.npy", "-o", tmp_path / "d.zarr", "--block", 129, "--spacing", 30, "-q")
    st = TerrainStore(tmp_path / "d.zarr")
    assert st.attrs["height_range"] == [float(a.min()), float(a.max())]
    top = st.get_block(st.layout.L, 0, 0)
    assert top.max() < a.max()  # the coarsest level alone would have reported less
    info = json.loads(run_cli("info", tmp_path / "d.zarr", "--json").stdout)
    assert info["height_range"] == [float(a.min()), float(a.max())]


def test_spacing_and_crs_for_inputs_without_georeference(tmp_path):
    a = np.random.default_rng(1).normal(100, 5, (200, 200)).astype(np.float32)
    np.save(tmp_path / "d.npy", a)
    proc = run_cli("prepare", "terrain", tmp_path / "d.npy", "-o", tmp_path / "a.zarr", "-q")
    assert "no georeference: assumed 1 m sample spacing; pass --spacing" in proc.stderr
    assert TerrainStore(tmp_path / "a.zarr").spacing == (1.0, 1.0)
    proc = run_cli("prepare", "terrain", tmp_path / "d.npy", "-o", tmp_path / "b.zarr", "--spacing", "30,20",
                   "--crs", "EPSG:32632", "-q")
    assert "warning" not in proc.stderr
    st = TerrainStore(tmp_path / "b.zarr")
    assert st.spacing == (30.0, 20.0) and "32632" in st.attrs["crs"]
    for bad, needle in ((["--spacing", "0"], "--spacing '0'"), (["--spacing", "a,b"], "--spacing 'a,b'"),
                        (["--crs", "EPSG:0"], "--crs 'EPSG:0'")):
        proc = run_cli("prepare", "terrain", tmp_path / "d.npy", "-o", tmp_path / "c.zarr", *bad, "-q", check=False)
        assert proc.returncode != 0 and needle in proc.stderr and "Traceback" not in proc.stderr


def test_generate_npy_records_the_spacing_that_prepare_reads(tmp_path):
    proc = run_cli("generate", "terrain", tmp_path / "g.npy", "--size", 300, "-q")
    assert "--spacing 30" in proc.stdout and (tmp_path / "g.npy.json").exists()
    proc = run_cli("prepare", "terrain", tmp_path / "g.npy", "-o", tmp_path / "g.zarr", "-q")
    assert "warning" not in proc.stderr
    assert TerrainStore(tmp_path / "g.zarr").spacing == (30.0, 30.0)
    # a georeferenced input refuses --spacing (it has its own)
    run_cli("generate", "terrain", tmp_path / "g.tif", "--size", 300, "-q")
    proc = run_cli("prepare", "terrain", tmp_path / "g.tif", "-o", tmp_path / "t.zarr", "--spacing", 5, check=False)
    assert proc.returncode != 0 and "has its own georeference" in proc.stderr


def _readonly_dir():
    d = tempfile.mkdtemp(prefix="massview-ro-", dir="/tmp")
    os.chmod(d, 0o555)
    return d


def _as_unprivileged(args):
    """Root writes anywhere: run as nobody so that a read-only folder is read-only."""
    if os.geteuid() != 0:
        return args
    if shutil.which("setpriv") is None:
        pytest.skip("running as root without setpriv: a read-only folder cannot be tested")
    return ["setpriv", "--reuid=65534", "--regid=65534", "--clear-groups", "--", *args]


@pytest.mark.parametrize("where", ["proc", "file", "readonly"])
@pytest.mark.parametrize("command", ["render", "render2", "prepare", "generate"])
def test_unwritable_output_is_one_line_before_any_work(tmp_path, where, command):
    import subprocess
    import sys

    (tmp_path / "afile").write_text("x")
    ro = _readonly_dir() if where == "readonly" else None
    try:
        target = {"proc": "/proc/massview/out", "file": str(tmp_path / "afile"), "readonly": f"{ro}/out"}[where]
        if command.startswith("render"):
            args = ["render", SMALL_SCENE, "--frames", 1, "--size", "64x48", "--out", target] + (["--ranks", 2] if command == "render2" else [])
        elif command == "prepare":
            np.save(tmp_path / "d.npy", np.ones((50, 50), np.float32))
            args = ["prepare", "terrain", tmp_path / "d.npy", "-o", target + ("/s.zarr" if where == "file" else ".zarr")]
        else:
            args = ["generate", "terrain", target + ("/g.npy" if where == "file" else ".npy"), "--size", 64]
        cmd = [sys.executable, "-m", "massview", *map(str, args)]
        if where == "readonly":
            cmd = _as_unprivileged(cmd)
        env = clean_env()
        proc = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=300)
    finally:
        if ro:
            os.chmod(ro, 0o755)
            shutil.rmtree(ro)
    assert proc.returncode != 0
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("massview: error: ") and "rank" not in lines[0], proc.stderr
    assert target in lines[0]


def test_a_leading_nodata_region_is_filled_from_the_data_below_not_zero(tmp_path):
    """The first strips wholly nodata (a clipped raster): filled from the data below (a smooth
    surface within the data's range that meets its first row), so no 0 m cliff."""
    from massview.data.terrain import ArraySource, prepare_terrain

    a = np.tile(np.linspace(500, 900, 300, dtype=np.float32), (700, 1))
    a[:400] = np.nan
    res = prepare_terrain(ArraySource(a, "top"), tmp_path / "s.zarr", block=129, color=None)
    st = TerrainStore(tmp_path / "s.zarr")
    assert res.filled == 400 * 300 and st.attrs["height_range"] == [500.0, 900.0]
    top = np.concatenate([st.get_block(0, i, 0)[:-1, :129] for i in range(4)])  # rows 0..511
    assert np.isfinite(top).all() and top.min() >= 500.0 and top.max() <= 900.0
    assert np.abs(np.diff(top, axis=0)).max() < 16.0  # (the ramp rises 1.34 m a column; 0 m would be a 500 m step)
    assert np.abs(top[399] - a[400, :129]).max() < 16.0
