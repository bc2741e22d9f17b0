"""``massview verify`` on stores made by the real commands and then damaged on disk: it names
the file or array at fault and what to do, exits non-zero, prints no traceback; an undamaged
store verifies OK. (Each damage here once verified "OK" or ended in a traceback.)"""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from conftest import run_cli


@pytest.fixture(scope="module")
def terrain(tmp_path_factory):
    """A 300² synthetic terrain in 129² blocks: 4×4 blocks at level 0, 3 levels, with T2's table."""
    out = tmp_path_factory.mktemp("vterrain") / "t.zarr"
    run_cli("generate", "terrain", "-o", out, "--size", 300, "--block", 129, "-q")
    return out


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    from massview.data.generators.scenes import generate_scene

    out = tmp_path_factory.mktemp("vscene") / "city.scene"
    generate_scene("city", out, size=0.1)
    return out


def _copy(src, tmp_path):
    dst = tmp_path / src.name
    shutil.copytree(src, dst)
    return dst


def _fails(store, *named, cmd=("verify",)):
    proc = run_cli(*cmd, store, *(("-q",) if cmd == ("verify",) else ()), check=False)
    err = proc.stderr
    assert proc.returncode != 0, proc.stdout[-800:]
    assert "Traceback" not in err, err[-3000:]
    for n in named:
        assert n in err, (n, err[-3000:])
    return err


def test_undamaged_stores_verify_ok(terrain, scene):
    assert "OK" in run_cli("verify", terrain, "-q").stdout
    assert "OK" in run_cli("verify", scene, "-q").stdout


@pytest.mark.parametrize("f,said", [("halo/0/c/3/0/0/0", "the halo file of level-0 block row 3 is missing"),
                                    ("shade/1/c/1/1/0/0/0", "shading block (level 1, 1, 1) is missing")])
def test_terrain_missing_shading_chunk(terrain, tmp_path, f, said):
    """A missing shading chunk, or (level 0, format 3) a missing halo file of a block row: named
    once (not once per block of its row), with ``upgrade``, which writes it again."""
    st = _copy(terrain, tmp_path)
    (st / f).unlink()
    err = _fails(st, said, f, "--overwrite")
    if f.startswith("halo"):
        assert err.count(f) == 1 and "massview upgrade" in err
        proc = run_cli("upgrade", st)
        assert "wrote the halos of 1 level-0 block row(s) again from the heights" in proc.stderr
        assert "OK" in run_cli("verify", st, "-q").stdout


@pytest.mark.parametrize("dst,src", [("halo/0/c/3/0/0/0", "halo/0/c/1/0/0/0"), ("shade/1/c/1/1/0/0/0", "shade/1/c/0/0/0/0/0")])
def test_terrain_shading_chunk_of_another_block(terrain, tmp_path, dst, src):
    """walk9 M4: a shading chunk replaced by another block's decodes fine, so verify said OK
    while the render showed a wrongly lit square; the shading is now computed again from the
    heights and compared bit for bit (at level 0 that of the block row's halo file: another
    row's halos give another row's border shading)."""
    st = _copy(terrain, tmp_path)
    shutil.copy(st / src, st / dst)
    level, i, j = (0, 3, 0) if dst.startswith("halo") else (1, 1, 1)
    _fails(st, f"shading block (level {level}, {i}, {j}) is not what its heights give", dst, "--overwrite")
    if level == 0:  # upgrade writes the halo row again from the heights
        assert "wrote the halos of 1 level-0 block row(s)" in run_cli("upgrade", st).stderr
        assert "OK" in run_cli("verify", st, "-q").stdout


def test_terrain_one_changed_halo_sample(terrain, tmp_path):
    """One sample of one halo changed (a float32 in the raw file): the block's border shading
    differs, verify names the block and the file."""
    st = _copy(terrain, tmp_path)
    f = st / "halo/0/c/2/0/0/0"
    a = np.frombuffer(f.read_bytes(), "<f4").copy()
    M2 = a.size // (4 * 4)  # (nb = 4 blocks a row: 4 halos of M + 2 samples each)
    a[1 * 4 * M2 + 2 * M2 + 7] += 1.0  # block (2, 1), its left column, row 6 of the block
    f.write_bytes(a.tobytes())
    _fails(st, "shading block (level 0, 2, 1) is not what its heights give", "halo/0/c/2/0/0/0", "halo", "massview upgrade")


def test_terrain_truncated_halo_file_and_leftover_shade0(terrain, tmp_path):
    """A truncated halo file is named once, with its size; a ``shade/0`` folder in a format-3
    store (an upgrade stopped while deleting it: chunk files without their zarr.json) is
    reported, and ``upgrade`` removes it."""
    st = _copy(terrain, tmp_path)
    f = st / "halo/0/c/1/0/0/0"
    f.write_bytes(f.read_bytes()[:100])
    (st / "shade/0/c/0/0/0/0").mkdir(parents=True)
    (st / "shade/0/c/0/0/0/0/0").write_bytes(b"old level-0 chunk")
    err = _fails(st, "the halo file of level-0 block row 1", "has 100 bytes", "halo/0/c/1/0/0/0", "massview upgrade")
    assert err.count("halo/0/c/1/0/0/0") == 1 and "left from an interrupted `massview upgrade`" in err
    said = run_cli("upgrade", st).stderr
    assert "wrote the halos of 1 level-0 block row(s)" in said and "removed shade/0" in said
    assert not (st / "shade/0").exists() and "OK" in run_cli("verify", st, "-q").stdout
    assert "is current already" in run_cli("upgrade", st).stderr


def test_terrain_truncated_roettger_chunk_in_verify_and_render(terrain, tmp_path):
    st = _copy(terrain, tmp_path)
    f = st / "roettger/d2/3/c/0/0"
    f.write_bytes(f.read_bytes()[:100])
    _fails(st, "roettger/d2/3", "roettger/d2/3/c/0/0", "does not decode", "massview prepare roettger")
    err = _fails(st, "roettger/d2/3", "roettger/d2/3/c/0/0", "massview prepare roettger",
                 cmd=("render", "--system", "roettger", "--ranks", 2, "--compute-ranks", 1, "--frames", 1,
                      "--size", "64x48", "-o", tmp_path / "r", "-q"))
    line = next(x for x in err.splitlines() if "roettger/d2/3/c/0/0" in x)
    assert line.startswith("massview: error") and "damaged" in line, err


def test_terrain_array_shape_edited(terrain, tmp_path):
    st = _copy(terrain, tmp_path)
    doc = json.loads((st / "heights/0/zarr.json").read_text())
    assert doc["shape"] == [4, 4, 129, 129]
    doc["shape"] = [3, 4, 129, 129]
    (st / "heights/0/zarr.json").write_text(json.dumps(doc))
    _fails(st, "heights/0", "[3, 4, 129, 129]", "[4, 4, 129, 129]", "--overwrite")


def test_terrain_shading_shape_edited(terrain, tmp_path):
    st = _copy(terrain, tmp_path)
    doc = json.loads((st / "shade/1/zarr.json").read_text())
    doc["shape"][0] = 1
    (st / "shade/1/zarr.json").write_text(json.dumps(doc))
    _fails(st, "the array shade/1 has shape", "shade/1/zarr.json")


def test_terrain_block_size_attribute_edited(terrain, tmp_path):
    st = _copy(terrain, tmp_path)
    doc = json.loads((st / "zarr.json").read_text())
    doc["attributes"]["M"] = 257
    (st / "zarr.json").write_text(json.dumps(doc))
    err = _fails(st, "its attributes (M 257", "129×129 chunks", "--overwrite")
    assert "does not open" not in err


def test_scene_array_zarr_json_does_not_parse(scene, tmp_path):
    st = _copy(scene, tmp_path)
    (st / "geometry/crc/zarr.json").write_text("{\n")
    for cmd in (("verify",), ("info",), ("render", "--frames", 1, "--size", "64x48", "-o", tmp_path / "r", "-q")):
        _fails(st, "geometry/crc", "JSONDecodeError", "massview prepare scene", "--overwrite", cmd=cmd)


def test_scene_missing_shard_is_reported_once(scene, tmp_path):
    st = _copy(scene, tmp_path)
    shard = st / "geometry/data/0/c/0"
    shard.unlink()
    err = _fails(st, "missing file", "geometry/data/0/c/0")
    assert err.count("missing file") == 1 and "checksum mismatch" not in err, err


def test_scene_truncated_shard_names_the_file(scene, tmp_path):
    st = _copy(scene, tmp_path)
    shard = st / "geometry/data/0/c/0"
    shard.write_bytes(shard.read_bytes()[:100000])
    err = _fails(st, "geometry/data/0/c/0", "truncated")
    assert "MemoryError" not in err and "OverflowError" not in err and err.count("massview: verify:") == 1, err


def test_scene_object_count_attribute_edited(scene, tmp_path):
    st = _copy(scene, tmp_path)
    doc = json.loads((st / "zarr.json").read_text())
    n = doc["attributes"]["objects"]
    doc["attributes"]["objects"] = n + 2
    (st / "zarr.json").write_text(json.dumps(doc))
    _fails(st, f"objects {n + 2}", f"hold {n}", "zarr.json")
