"""What ``prepare scene`` tells its user (walkthrough 5): textures baked to vertex colours,
triangles dropped as degenerate, resumed or started over, refused options and outputs — and
the terrain prepare's resume wording."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh
from conftest import FlakySource, run_cli
from PIL import Image

from massview.app.cli import main
from massview.data.scene import SceneStore
from massview.data.scene.ingest import IngestParams, prepare_scene

RED, BLUE, PURPLE = [255, 0, 0, 255], [0, 0, 255, 255], [128, 0, 128, 255]


def _soup(path):
    """Eight separate spheres in one PLY: eight objects at --object-triangles 320."""
    parts = [trimesh.creation.icosphere(2).apply_translation([i * 3.0, 0, 0]) for i in range(8)]
    trimesh.util.concatenate(parts).export(path)


def test_refused_options_inputs_and_outputs(tmp_path):
    """--object-size -1 (or 0, nan, inf) gave objects as if it were not given; the same file
    twice gave two coincident copies; -o inside a store wrote a store into the store. Each is
    one line naming what to change, exit 2, and nothing is written."""
    _soup(tmp_path / "soup.ply")
    run_cli("prepare", "scene", tmp_path / "soup.ply", "-o", tmp_path / "a.scene", "-q")
    before = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*"))
    cases = {("--object-size", "-1"): "--object-size must be a positive length", ("--object-size", "0"): "--object-size",
             ("--object-size", "nan"): "--object-size", ("--object-size", "inf"): "--object-size",
             ("--stream-mb", "nan"): "--stream-mb"}
    for opt, msg in cases.items():
        p = run_cli("prepare", "scene", tmp_path / "soup.ply", "-o", tmp_path / "b.scene", *opt, check=False)
        assert p.returncode == 2 and msg in p.stderr and len(p.stderr.strip().splitlines()) == 1, (opt, p.stderr)
    (tmp_path / "link.ply").symlink_to(tmp_path / "soup.ply")
    p = run_cli("prepare", "scene", tmp_path / "soup.ply", tmp_path / "link.ply", "-o", tmp_path / "b.scene", check=False)
    assert p.returncode == 2 and "link.ply is given twice (inputs 1 and 2" in p.stderr and "give it once" in p.stderr
    for out in (tmp_path / "a.scene" / "inner.scene", tmp_path / "a.scene" / "geometry" / "x" / "inner.scene"):
        p = run_cli("prepare", "scene", tmp_path / "soup.ply", "-o", out, check=False)
        assert p.returncode == 2 and f"is inside the store {tmp_path / 'a.scene'}" in p.stderr, p.stderr
    (tmp_path / "link.ply").unlink()
    assert sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*")) == before
    with pytest.raises(ValueError, match="--object-size"):
        IngestParams(object_size=-1.0)


def _interrupt_after(monkeypatch, calls: int, checkpoint: bool):
    """Ctrl-C after the writer's ``calls``-th unit (each unit checkpointed first with ``checkpoint``)."""
    from massview.data.scene import writer

    step, n = writer.SceneWriter.step, [0]

    def stop(self):
        if checkpoint:
            self.checkpoint()
        step(self)
        n[0] += 1
        if n[0] == calls:
            raise KeyboardInterrupt

    monkeypatch.setattr(writer.SceneWriter, "step", stop)


@pytest.mark.parametrize("checkpoint", [False, True])
def test_an_interrupted_prepare_says_what_it_kept_and_the_rerun_what_it_resumed(tmp_path, monkeypatch, capsys, checkpoint):
    """The re-run printed "resumed and completed" also when the interrupted run had saved no
    checkpoint (every 64 MiB of records: a small input never does) and everything was redone.
    Now the interrupted run says what it keeps and to re-run the same command, and the re-run
    says "resumed (N of M objects were already written)" only when a checkpoint was used."""
    _soup(tmp_path / "soup.ply")
    argv = ["prepare", "scene", str(tmp_path / "soup.ply"), "-o", str(tmp_path / "s.scene"), "--object-triangles", "320", "-q"]
    _interrupt_after(monkeypatch, 3, checkpoint)
    assert main(argv) == 130
    err = capsys.readouterr().err
    if checkpoint:
        assert f"massview: interrupted; {tmp_path / 's.scene'} keeps the 3 objects of its last checkpoint: re-run the same command to continue" in err
    else:
        assert "has no checkpoint yet (one is saved every 64 MiB of stored geometry), so re-running the same command starts it over" in err
    monkeypatch.undo()
    assert main(argv) == 0
    out = capsys.readouterr().out
    if checkpoint:
        assert out.startswith(f"resumed {tmp_path / 's.scene'} (3 of 8 objects were already written): 8 objects"), out
    else:
        assert out.startswith(f"started {tmp_path / 's.scene'} over (the interrupted run had saved no checkpoint"), out
    assert "resumed and completed" not in out

def test_the_terrain_prepare_says_resumed_only_when_it_kept_rows(tmp_path, monkeypatch, capsys):
    """``prepare terrain`` printed "resumed and completed" for any re-run of an interrupted
    prepare; now it names the block rows it kept, or says it started over, and the
    interrupted run says how to continue."""
    from massview.data.generators import synthetic_heights
    from massview.data.terrain import ingest, prepare_terrain

    a = synthetic_heights(0, 600, 0, 500, 600, 9)
    with pytest.raises(KeyboardInterrupt):
        prepare_terrain(FlakySource(a, 0), tmp_path / "none.zarr", block=129)
    assert prepare_terrain(FlakySource(a, 10**9), tmp_path / "none.zarr", block=129).rows_kept == 0
    np.save(tmp_path / "dem.npy", a)
    argv = ["prepare", "terrain", str(tmp_path / "dem.npy"), "-o", str(tmp_path / "t.zarr"), "--block", "129", "-q"]
    read, n = ingest._read_strip, [0]

    def stop(*args, **kw):
        n[0] += 1
        if n[0] == 3:
            raise KeyboardInterrupt
        return read(*args, **kw)

    monkeypatch.setattr(ingest, "_read_strip", stop)
    assert main(argv) == 130
    assert (f"massview: interrupted; {tmp_path / 't.zarr'} keeps the 2 of 8 block rows it finished: re-run the same "
            "command to continue") in capsys.readouterr().err
    monkeypatch.undo()
    assert main(argv) == 0
    assert capsys.readouterr().out.startswith(f"resumed {tmp_path / 't.zarr'} (2 of 8 block rows of level 0 were already written)")


def _ply(path, v, f, dtype):
    """A binary PLY of vertices ``v`` (stored as ``dtype``: 'float' or 'double') and faces ``f``."""
    hdr = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(v)}\nproperty {dtype} x\nproperty {dtype} y\n"
           f"property {dtype} z\nelement face {len(f)}\nproperty list uchar int vertex_indices\nend_header\n")
    rec = np.empty(len(f), [("n", "u1"), ("i", "<i4", (3,))])
    rec["n"], rec["i"] = 3, f
    path.write_bytes(hdr.encode() + np.asarray(v, "<f4" if dtype == "float" else "<f8").tobytes() + rec.tobytes())


def test_triangles_dropped_as_degenerate_are_counted_with_the_likely_cause(tmp_path):
    """A 6 m sphere at UTM coordinates written with float32 properties lost 64 of its 5120
    triangles to the file's own precision, silently; now one line per file says how many and,
    as more than 1 % went with float32 coordinates that coarse, why and what to do. The same
    mesh in float64 loses nothing and says nothing; a repeated face at small coordinates is
    counted without the float32 hint."""
    m = trimesh.creation.icosphere(subdivisions=4, radius=3.0)
    utm = m.vertices + [500000.0, 4000000.0, 250.0]
    _ply(tmp_path / "utm32.ply", utm, m.faces, "float")
    _ply(tmp_path / "utm64.ply", utm, m.faces, "double")
    _ply(tmp_path / "dup.ply", m.vertices, np.concatenate([m.faces, m.faces[:3]]), "float")
    proc = run_cli("prepare", "scene", tmp_path / "utm32.ply", tmp_path / "utm64.ply", tmp_path / "dup.ply",
                   "-o", tmp_path / "u.scene", "-q")
    lines = [ln for ln in proc.stderr.splitlines() if "were removed as degenerate" in ln]
    assert len(lines) == 2, proc.stderr
    assert "utm32.ply: 64 of 5,120 triangles (1.2%) were removed" in lines[0]
    assert "float32 steps by 0.25" in lines[0] and "float64 (double) coordinates or move its origin" in lines[0]
    assert "dup.ply: 3 of 5,123 triangles" in lines[1] and "likely cause" not in lines[1]
    info = json.loads(run_cli("info", tmp_path / "u.scene", "--json").stdout)
    assert list(info["triangles_removed"].values()) == [64, 0, 3]
