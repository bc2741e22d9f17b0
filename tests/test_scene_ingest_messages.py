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


def _checker(path, n=8):
    ii, jj = np.indices((n, n))
    img = np.where(((ii + jj) % 2 == 0)[..., None], [255, 0, 0], [0, 0, 255]).astype(np.uint8)
    Image.fromarray(img).save(path)


def _textured_obj(folder, plain_triangle=False):
    """A unit quad with an 8×8 red/blue checker (map_Kd); with ``plain_triangle``, a triangle
    of a plain yellow material (Kd) beside it."""
    _checker(folder / "checker.png")
    (folder / "quad.mtl").write_text("newmtl chk\nKd 1 1 1\nmap_Kd checker.png\nnewmtl plain\nKd 1 1 0\n")
    lines = ["mtllib quad.mtl", "v 0 0 0", "v 1 0 0", "v 1 1 0", "v 0 1 0", "vt 0 0", "vt 1 0", "vt 1 1", "vt 0 1",
             "usemtl chk", "f 1/1 2/2 3/3", "f 1/1 3/3 4/4"]
    if plain_triangle:
        lines += ["v 2 0 0", "v 3 0 0", "v 3 1 0", "usemtl plain", "f 5 6 7"]
    (folder / "quad.obj").write_text("\n".join(lines) + "\n")
    return folder / "quad.obj"


def _colors(store) -> dict:
    """World x of each stored level-0 vertex -> its colours (sorted lists)."""
    st = SceneStore(store)
    out = {}
    for o in range(st.skeleton.count):
        m = st.get_mesh(int(st.skeleton.geometry[o]), 0)
        x = m.positions[:, 0].astype(np.float64) + st.skeleton.transform[o][0, 3]
        for xi, c in zip(x.round(3), m.colors.tolist()):
            out.setdefault(float(xi), []).append(c)
    return out


def test_a_textured_obj_is_baked_to_its_faces_mean_and_says_so(tmp_path):
    """The 8×8 checker on a quad was a red-blue gradient (each vertex the texel at its UV),
    silently; now every vertex is the checker's mean (purple), one warning line names the file
    and the material, and ``info`` shows it."""
    obj = _textured_obj(tmp_path)
    proc = run_cli("prepare", "scene", obj, "-o", tmp_path / "q.scene", "-q")
    warn = [ln for ln in proc.stderr.splitlines() if "textured" in ln]
    assert len(warn) == 1 and "quad.obj: 1 textured material (chk) baked to per-vertex colours" in warn[0]
    assert "detail finer than the mesh's vertices is lost" in warn[0]
    cols = [c for cs in _colors(tmp_path / "q.scene").values() for c in cs]
    assert len(cols) == 4 and all(c == PURPLE for c in cols), cols
    info = json.loads(run_cli("info", tmp_path / "q.scene", "--json").stdout)
    assert info["textures_baked"] == {str(obj): 1}


def test_a_plain_material_beside_a_textured_one_keeps_its_colour(tmp_path):
    """trimesh forced the OBJ into one mesh, packing both materials into one atlas: the plain
    Kd triangle came out transparent black (0, 0, 0, 0) and the checker at half resolution."""
    obj = _textured_obj(tmp_path, plain_triangle=True)
    a = prepare_scene([obj], tmp_path / "m.scene")
    assert any("1 textured material (chk)" in w for w in a["warnings"])
    cols = _colors(tmp_path / "m.scene")
    assert all(c == [255, 255, 0, 255] for x in (2.0, 3.0) for c in cols[x])
    assert all(c == PURPLE for x in (0.0, 1.0) for c in cols[x])


def test_a_textured_glb_is_counted_per_mesh_and_a_plain_material_keeps_its_colour(tmp_path):
    """The quad's checker is baked to its mean and counted; the box's plain baseColorFactor
    (red) came out grey (trimesh's to_color made it one malformed row)."""
    _checker(tmp_path / "c.png")
    quad = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], [[0, 1, 2], [0, 2, 3]], process=False)
    quad.visual = trimesh.visual.TextureVisuals(uv=[[0, 0], [1, 0], [1, 1], [0, 1]], image=Image.open(tmp_path / "c.png"))
    plain = trimesh.creation.box()
    plain.visual = trimesh.visual.TextureVisuals(material=trimesh.visual.material.PBRMaterial(baseColorFactor=RED))
    plain.apply_translation([3, 0, 0])
    trimesh.Scene({"quad": quad, "box": plain}).export(tmp_path / "s.glb")
    a = prepare_scene([tmp_path / "s.glb"], tmp_path / "g.scene")
    assert [w for w in a["warnings"] if "textured" in w] == [
        w for w in a["warnings"] if "s.glb: 1 textured mesh (quad) baked to per-vertex colours" in w]
    assert a["textures_baked"] == {str(tmp_path / "s.glb"): 1}
    st = SceneStore(tmp_path / "g.scene")
    meshes = [st.get_mesh(int(g), 0) for g in st.skeleton.geometry]
    assert sorted(m.triangle_count for m in meshes) == [2, 12]
    for m in meshes:
        assert (m.colors == (PURPLE if m.triangle_count == 2 else RED)).all()


def test_the_bake_keeps_a_fine_mesh_sharp_and_a_coarse_one_true_on_average():
    """A mesh finer than the texture keeps its texels (a face inside one texel reads level 0);
    the mip levels are the rounded means of 2x2 blocks."""
    from massview.data.scene.texture import bake_vertex_colors, mip_levels

    ii, jj = np.indices((8, 8))
    img = np.where(((ii + jj) % 2 == 0)[..., None], RED, BLUE).astype(np.uint8)
    n = 32  # a 32×32 grid of vertices on the 8×8 checker: 4 vertices a texel side
    u, v = np.meshgrid((np.arange(n) + 0.5) / n, (np.arange(n) + 0.5) / n)
    uv = np.stack([u.ravel(), v.ravel()], 1)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]
    faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    pos = np.column_stack([uv, np.zeros(len(uv))])
    col = bake_vertex_colors(pos, faces, uv, img)
    x, y = np.floor(uv[:, 0] * 8).astype(int), 7 - np.floor(uv[:, 1] * 8).astype(int)
    interior = ((uv * 8) % 1 > 0.2).all(1) & ((uv * 8) % 1 < 0.8).all(1)  # vertices whose faces all lie in their texel
    assert interior.sum() > 100 and (col[interior] == img[y, x][interior]).all()
    lv = mip_levels(np.arange(64, dtype=np.uint8).reshape(8, 8, 1) * 3)
    assert [m.shape[:2] for m in lv] == [(8, 8), (4, 4), (2, 2), (1, 1)]
    assert lv[1][0, 0, 0] == np.rint((0 + 3 + 24 + 27) / 4) and lv[3][0, 0, 0] == np.rint(63 * 3 / 2)


def test_small_input_mistakes_get_exact_messages(tmp_path):
    """walk6 #15: an OBJ face past the vertices said "3 vertexs"; --object-triangles 0 and
    --levels 17 gave one combined message naming neither value; a 0-byte PLY was "not a PLY file"."""
    from conftest import run_cli

    (tmp_path / "bad.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 4\n")
    proc = run_cli("prepare", "scene", tmp_path / "bad.obj", "-o", tmp_path / "a", check=False)
    assert proc.returncode != 0 and "only 3 vertices are defined before it" in proc.stderr, proc.stderr
    (tmp_path / "ok.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    proc = run_cli("prepare", "scene", tmp_path / "ok.obj", "-o", tmp_path / "b", "--object-triangles", 0, check=False)
    assert proc.returncode != 0 and "--object-triangles must be a positive triangle count, got 0" in proc.stderr, proc.stderr
    proc = run_cli("prepare", "scene", tmp_path / "ok.obj", "-o", tmp_path / "c", "--levels", 17, check=False)
    assert proc.returncode != 0 and "--levels must be between 1 and 16, got 17" in proc.stderr, proc.stderr
    (tmp_path / "empty.ply").write_bytes(b"")
    proc = run_cli("prepare", "scene", tmp_path / "empty.ply", "-o", tmp_path / "d", check=False)
    assert proc.returncode != 0 and "empty.ply: the file is empty (0 bytes)" in proc.stderr, proc.stderr


def test_inputs_in_different_units_are_warned(tmp_path):
    """walk6 #12: metre models prepared with a 2000 mm part 125 km away gave one store whose
    orbit showed specks in an empty frame, without a word. Inputs whose sizes differ over
    500-fold are warned; inputs of one scale are not, however far apart."""
    import trimesh

    from conftest import run_cli

    trimesh.creation.box([2.0, 1.0, 0.8]).export(tmp_path / "table.ply")
    trimesh.creation.icosphere(2, 0.3).export(tmp_path / "vase.ply")
    part = trimesh.creation.box([2000.0, 500.0, 300.0])
    part.apply_translation([125000.0, 48000.0, 3000.0])
    part.export(tmp_path / "part_mm.stl")
    proc = run_cli("prepare", "scene", tmp_path / "table.ply", tmp_path / "vase.ply", tmp_path / "part_mm.stl", "-o", tmp_path / "a", "-q")
    assert "warning: the inputs differ in scale: " in proc.stderr and "part_mm.stl is 2000 units across" in proc.stderr, proc.stderr
    proc = run_cli("prepare", "scene", tmp_path / "table.ply", tmp_path / "vase.ply", "-o", tmp_path / "b", "-q")
    assert "differ in scale" not in proc.stderr, proc.stderr
    far = trimesh.creation.box([2.0, 1.0, 0.8])
    far.apply_translation([5000.0, 0.0, 0.0])  # (a tile 5 km away: not a units mistake)
    far.export(tmp_path / "far.ply")
    proc = run_cli("prepare", "scene", tmp_path / "table.ply", tmp_path / "far.ply", "-o", tmp_path / "c", "-q")
    assert "differ in scale" not in proc.stderr, proc.stderr


def test_a_model_thinnest_along_y_gets_an_up_hint(tmp_path):
    """walk6 #14: a y-up PLY (a 10 × 0.2 × 10 slab with a house on it) rendered as a wall with
    no word at prepare time. Now prepare says it looks y-up; the same model z-up, or with
    --up y, gets no such line."""
    slab = trimesh.creation.box((10.0, 0.2, 10.0))
    house = trimesh.creation.box((3.0, 2.5, 3.0))
    house.apply_translation((0.0, 1.35, 0.0))
    yup = trimesh.util.concatenate([slab, house])
    zup = yup.copy()
    zup.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, (1, 0, 0)))  # y-up → z-up
    yup.export(tmp_path / "house_yup.ply")
    zup.export(tmp_path / "house_zup.ply")
    said = lambda name, **kw: [w for w in prepare_scene([tmp_path / name], tmp_path / f"{name}_{kw}.zarr",  # noqa: E731
                                                        IngestParams(**kw))["warnings"] if "--up y" in w]
    hint = said("house_yup.ply")
    assert len(hint) == 1 and "house_yup.ply: it is thinnest along y (2.7 against 10 along x and 10 along z)" in hint[0], hint
    assert said("house_zup.ply") == [] and said("house_yup.ply", up="y") == []
