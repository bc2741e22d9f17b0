"""Meshes without normals get normals split at creases (`prepare scene`): a cube's faces are
flat (each face's corners carry that face's normal; rendered, a face is one colour), a finely
tessellated sphere stays smooth, and a mesh that brings its own normals keeps them. (Area-
weighted normals averaged over every face round a vertex made a box a rounded pillar.)"""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from conftest import load_png, run_cli
from massview.data.scene import SceneStore
from massview.data.scene.ingest import IngestParams, prepare_scene
from massview.data.scene.normals import crease_split
from massview.data.scene.verify import verify_scene


def _level0(path):
    st = SceneStore(path)
    assert st.skeleton.count == 1
    return st.get_mesh(int(st.skeleton.geometry[0]), 0)


def _face_normals(m) -> np.ndarray:
    p = m.positions.astype(np.float64)[m.indices]
    n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def _write(box: trimesh.Trimesh, path) -> None:
    if path.suffix == ".obj":  # plain v/f lines: no vn
        path.write_text("".join(f"v {x} {y} {z}\n" for x, y, z in box.vertices) + "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in box.faces))
    else:
        box.export(path)


@pytest.mark.parametrize("suffix", [".obj", ".ply", ".stl"])
def test_a_cube_without_normals_is_flat_shaded(tmp_path, suffix):
    box = trimesh.creation.box(extents=[2.0, 3.0, 1.5])
    src = tmp_path / f"box{suffix}"
    _write(box, src)
    prepare_scene([src], tmp_path / "s")
    m = _level0(tmp_path / "s")
    assert (m.triangle_count, m.vertex_count) == (12, 24)  # 8 corners x 3 faces each
    fn = _face_normals(m)
    dots = np.einsum("tkc,tc->tk", m.normals[m.indices].astype(np.float64), fn)
    assert dots.min() > 0.9999, "a corner's normal is not its face's"
    assert SceneStore(tmp_path / "s").skeleton.occluder.all()  # still a closed surface (welded by position)
    assert verify_scene(tmp_path / "s") == []


def test_a_fine_sphere_stays_smooth_and_file_normals_are_kept(tmp_path):
    ball = trimesh.creation.icosphere(4)  # 5120 triangles, ~4° between neighbours
    ball.export(tmp_path / "ball.ply")
    prepare_scene([tmp_path / "ball.ply"], tmp_path / "s", IngestParams(object_triangles=10000))
    m = _level0(tmp_path / "s")
    assert m.vertex_count == len(ball.vertices)  # no vertex split
    radial = m.positions / np.linalg.norm(m.positions, axis=1, keepdims=True)  # (the object's origin is the centre)
    assert np.einsum("vc,vc->v", m.normals, radial).min() > 0.999
    # a cube that brings its own (smooth, diagonal) vertex normals keeps them
    box = trimesh.creation.box()
    nrm = box.vertices / np.linalg.norm(box.vertices, axis=1, keepdims=True)
    (tmp_path / "own.ply").write_bytes(trimesh.exchange.ply.export_ply(
        trimesh.Trimesh(box.vertices, box.faces, vertex_normals=nrm, process=False), vertex_normal=True))
    prepare_scene([tmp_path / "own.ply"], tmp_path / "own")
    m = _level0(tmp_path / "own")
    assert m.vertex_count == 8
    want = m.positions / np.linalg.norm(m.positions, axis=1, keepdims=True)
    assert np.einsum("vc,vc->v", m.normals, want).min() > 0.9999


def test_crease_split_of_a_cylinder():
    """Side faces of a 32-gon prism meet at 11.25° (smooth); caps meet sides at 90° (split)."""
    cyl = trimesh.creation.cylinder(radius=1.0, height=2.0, sections=32)
    src, n, tri = crease_split(cyl.vertices, cyl.faces)
    p = np.asarray(cyl.vertices)[src]
    side = np.abs(n[:, 2]) < 1e-6
    cap = np.abs(np.abs(n[:, 2]) - 1) < 1e-6
    assert (side | cap).all()
    radial = p[side, :2] / np.linalg.norm(p[side, :2], axis=1, keepdims=True)
    assert np.einsum("vc,vc->v", n[side, :2], radial).min() > 0.99  # (area-weighted over a quad's 1 or 2 triangles)
    np.testing.assert_array_equal(np.sign(n[cap, 2]), np.sign(p[cap, 2]))
    assert len(src) > len(cyl.vertices)
    np.testing.assert_array_equal(src[tri], np.asarray(cyl.faces))  # the same triangles, winding kept


def _object_pixels(img: np.ndarray) -> np.ndarray:
    bg = np.all(img == img[0, 0], axis=2)
    return img[~bg].reshape(-1, 3)


def test_rendered_cube_faces_are_one_colour_each_and_a_sphere_is_shaded_smoothly(tmp_path):
    box = trimesh.creation.box(extents=[2.0, 2.0, 2.0])
    _write(box, tmp_path / "box.obj")
    trimesh.creation.icosphere(4).export(tmp_path / "ball.ply")
    share = {}
    for name in ("box.obj", "ball.ply"):
        run_cli("prepare", "scene", tmp_path / name, "-o", tmp_path / f"{name}.scene", "-q")
        run_cli("render", tmp_path / f"{name}.scene", "--path", "orbit", "--frames", 2, "--size", "240x180", "--out", tmp_path / f"r_{name}", "-q")
        px = _object_pixels(load_png(tmp_path / f"r_{name}" / "frames" / "00000.png"))
        assert len(px) > 5000
        _, counts = np.unique(px // 4, axis=0, return_counts=True)  # colours to 4 levels of 256
        share[name] = np.sort(counts)[::-1][:3].sum() / len(px)  # at most 3 faces of a cube are seen
    assert share["box.obj"] > 0.97, f"cube faces are not flat: their 3 commonest colours cover {share['box.obj']:.1%}"
    assert share["ball.ply"] < 0.2, f"the sphere is faceted: 3 colours cover {share['ball.ply']:.1%}"


def test_weld_gives_np_unique_rows_ids():
    """normals._weld (a column lexsort) gives np.unique(p, axis=0)'s inverse ids, faster."""
    from massview.data.scene.normals import _weld

    rng = np.random.default_rng(5)
    p = rng.integers(0, 6, (5000, 3)).astype(np.float64) * 0.37  # many repeated rows
    _, want = np.unique(p, axis=0, return_inverse=True)
    assert np.array_equal(_weld(p), want.reshape(-1))
    assert len(_weld(np.zeros((0, 3)))) == 0
