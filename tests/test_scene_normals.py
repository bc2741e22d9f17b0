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
from massview.data.scene.sources import Y_TO_Z
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
    """normals.weld (a column lexsort) gives np.unique(p, axis=0)'s inverse ids, faster."""
    from massview.data.scene.normals import weld

    rng = np.random.default_rng(5)
    p = rng.integers(0, 6, (5000, 3)).astype(np.float64) * 0.37  # many repeated rows
    _, want = np.unique(p, axis=0, return_inverse=True)
    assert np.array_equal(weld(p), want.reshape(-1))
    assert len(weld(np.zeros((0, 3)))) == 0


# -- normals from the file: OBJ vn, glTF NORMAL; the crease angle option -------------------------------------------

_AXES = [np.eye(3)[d] * s for d in range(3) for s in (-1, 1)]


def _cube_obj(path, normals: str = "all") -> None:
    """A 2-unit cube as 6 quads (negative indices, ``f v//vn``), one flat ``vn`` per face;
    ``normals``: "all", "none" or "partial" (the +z face has no vn)."""
    v = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
    lines = [f"v {x:g} {y:g} {z:g}" for x, y, z in v] + [f"vn {a:g} {b:g} {c:g}" for a, b, c in _AXES]
    for k, n in enumerate(_AXES):
        ids = [i for i in range(8) if v[i] @ n > 0]
        u = np.cross(n, [1.0, 0, 0] if abs(n[0]) < 0.9 else [0, 1.0, 0])
        c = v[ids].mean(0)
        ids = [ids[i] for i in np.argsort([np.arctan2((v[i] - c) @ np.cross(n, u), (v[i] - c) @ u) for i in ids])]  # counter-clockwise
        plain = normals == "none" or (normals == "partial" and n[2] > 0)
        lines.append("f " + " ".join(f"{i - 8}" if plain else f"{i - 8}//{k + 1}" for i in ids))
    path.write_text("\n".join(lines) + "\n")


def _uv_sphere_obj(path, rings=8, segments=12) -> tuple[np.ndarray, np.ndarray]:
    """A coarse UV sphere with exact radial normals (``f v/vt/vn``, normals indexed apart from
    the positions: listed in reverse). Returns (vertices, their unit normals)."""
    th, ph = np.meshgrid(np.linspace(0, np.pi, rings + 1)[1:-1], np.linspace(0, 2 * np.pi, segments, endpoint=False), indexing="ij")
    v = np.concatenate([[[0, 0, 1.0]], np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1).reshape(-1, 3),
                        [[0, 0, -1.0]]])
    n = len(v)
    ring = lambda r, s: 2 + r * segments + s % segments  # 1-based  # noqa: E731
    faces = [[1, ring(0, s + 1), ring(0, s)] for s in range(segments)]
    faces += [[ring(r, s), ring(r, s + 1), ring(r + 1, s + 1), ring(r + 1, s)] for r in range(rings - 2) for s in range(segments)]
    faces += [[n, ring(rings - 2, s), ring(rings - 2, s + 1)] for s in range(segments)]
    faces = [f[::-1] for f in faces]  # outward winding
    lines = [f"v {x!r} {y!r} {z!r}" for x, y, z in v.tolist()] + ["vt 0 0"] + [f"vn {x!r} {y!r} {z!r}" for x, y, z in v[::-1].tolist()]
    lines += ["f " + " ".join(f"{i}/1/{n + 1 - i}" for i in f) for f in faces]
    path.write_text("\n".join(lines) + "\n")
    return v, v / np.linalg.norm(v, axis=1, keepdims=True)


def _colours(path) -> int:
    px = _object_pixels(load_png(path))
    return len(np.unique(px, axis=0))


def test_obj_vn_per_face_renders_as_the_computed_creases_do(tmp_path):
    _cube_obj(tmp_path / "vn.obj")
    _cube_obj(tmp_path / "plain.obj", "none")
    frames = {}
    for name in ("vn", "plain"):
        a = prepare_scene([tmp_path / f"{name}.obj"], tmp_path / f"{name}.scene")
        assert a["warnings"] == [] and a["triangles"] == 12
        m = _level0(tmp_path / f"{name}.scene")
        assert (m.vertex_count, m.triangle_count) == (24, 12)
        dots = np.einsum("tkc,tc->tk", m.normals[m.indices].astype(np.float64), _face_normals(m))
        assert dots.min() > 0.9999  # the file's normals are the faces' (quads fanned, winding kept)
        run_cli("render", tmp_path / f"{name}.scene", "--path", "orbit", "--frames", 3, "--size", "200x150", "--out", tmp_path / f"r_{name}", "-q")
        frames[name] = sorted((tmp_path / f"r_{name}" / "frames").glob("*.png"))
    counts = [(_colours(a), _colours(b)) for a, b in zip(frames["vn"], frames["plain"])]
    assert len(counts) == 3 and all(a == b for a, b in counts) and max(a for a, _ in counts) == 3, counts  # one shade per face seen
    for a, b in zip(frames["vn"], frames["plain"]):
        assert np.abs(load_png(a).astype(int) - load_png(b)).max() <= 1


def test_obj_smooth_vn_are_kept_not_recomputed(tmp_path):
    v, want = _uv_sphere_obj(tmp_path / "ball.obj")
    a = prepare_scene([tmp_path / "ball.obj"], tmp_path / "s")
    assert a["warnings"] == []
    m = _level0(tmp_path / "s")
    st = SceneStore(tmp_path / "s")
    world = m.positions.astype(np.float64) + st.skeleton.transform[0][:3, 3]
    k = np.argmin(np.linalg.norm(world[:, None] - v[None], axis=2), axis=1)  # stored vertex -> file vertex
    assert np.linalg.norm(world - v[k], axis=1).max() < 1e-6
    assert m.vertex_count == len(v)  # one normal per position: nothing split
    np.testing.assert_allclose(m.normals, want[k], atol=1e-4)  # (stored octahedral int16)
    _, n_computed, _ = crease_split(m.positions, m.indices.astype(np.int64))  # (area-weighted: not the exact radial ones)
    assert np.abs(n_computed - want[k]).max() > 1e-2


def test_partial_vn_fall_back_to_computed_normals_with_a_warning(tmp_path):
    _cube_obj(tmp_path / "part.obj", "partial")
    a = prepare_scene([tmp_path / "part.obj"], tmp_path / "s")
    assert len(a["warnings"]) == 1 and "part.obj: 1 of 1 objects have faces without a usable normal" in a["warnings"][0]
    m = _level0(tmp_path / "s")
    assert m.vertex_count == 24 and np.einsum("tkc,tc->tk", m.normals[m.indices].astype(np.float64), _face_normals(m)).min() > 0.9999
    # in a grouped OBJ only the group with a corner lacking vn is computed; the CLI prints the warning
    src = tmp_path / "groups.obj"
    src.write_text("o a\nv 0 0 0\nv 1 0 0\nv 0 1 0\nvn 0.3 0 2\nf 1//1 2//1 3//1\n"
                   "o b\nv 5 0 0\nv 6 0 0\nv 5 1 0\nf 4 5 6\n")
    proc = run_cli("prepare", "scene", src, "-o", tmp_path / "g", "-q")
    assert "warning: " in proc.stderr and "1 of 2 objects" in proc.stderr
    st = SceneStore(tmp_path / "g")
    got = {round(float(st.skeleton.center[o][0])): st.get_mesh(int(st.skeleton.geometry[o]), 0).normals for o in range(2)}
    np.testing.assert_allclose(got[0], np.tile(np.array([0.3, 0, 2]) / np.hypot(0.3, 2), (3, 1)), atol=1e-4)  # the file's, unit (stored octahedral)
    np.testing.assert_allclose(got[6], np.tile([0, 0, 1.0], (3, 1)), atol=1e-4)  # computed


@pytest.mark.parametrize("line,what", [("f 1//1 2//1 3//9", "refers to normal 9 but only 1 normal is defined"),
                                       ("f 1 2 0", "refers to vertex 0"), ("f 1//1 2//x 3//1", "normal index 'x'"),
                                       ("f -1 -2 -4", "refers to vertex -4"), ("vn 0 1", "needs three numbers"),
                                       ("f 1 2", "face has 2 corners")])
def test_malformed_obj_indices_name_the_file_and_line(tmp_path, capsys, line, what):
    from massview.app.cli import main

    src = tmp_path / "bad.obj"
    src.write_text(f"v 0 0 0\nv 1 0 0\nv 0 1 0\nvn 0 0 1\n{line}\n")
    assert main(["prepare", "scene", str(src), "-o", str(tmp_path / "s"), "-q"]) != 0
    err = capsys.readouterr().err
    assert f"{src}:5: " in err and what in err and "Traceback" not in err and len(err.strip().splitlines()) == 1


def _gltf_with_normals(path, xf: np.ndarray, second: np.ndarray | None = None) -> np.ndarray:
    """A glTF of a box whose NORMAL are its corners' diagonals (not what massview would compute),
    placed by ``xf`` (and ``second``, the same mesh again). Returns the file's unit normals."""
    box = trimesh.creation.box()
    nrm = box.vertices / np.linalg.norm(box.vertices, axis=1, keepdims=True)
    mesh = trimesh.Trimesh(box.vertices, box.faces, vertex_normals=nrm, process=False)
    scene = trimesh.Scene()
    scene.add_geometry(mesh, node_name="a", geom_name="box", transform=xf)
    if second is not None:
        scene.graph.update(frame_to="b", frame_from=scene.graph.base_frame, geometry="box", matrix=second)
    path.write_bytes(trimesh.exchange.gltf.export_glb(scene))
    return box.vertices, nrm


@pytest.mark.parametrize("case", ["one-node", "two-nodes", "instanced"])
def test_gltf_normal_goes_through_the_node_transform_as_its_inverse_transpose(tmp_path, case):
    rot = trimesh.transformations.rotation_matrix(0.7, [1, 2, 3])
    xf = rot @ np.diag([1.0, 2.5, 0.5, 1.0])  # non-uniform scale: the inverse transpose differs from the matrix
    xf[:3, 3] = (10, 0, 0)
    second = xf.copy()
    second[:3, 3] = (20, 0, 0)
    v, nrm = _gltf_with_normals(tmp_path / "b.glb", xf, None if case == "one-node" else second)
    a = prepare_scene([tmp_path / "b.glb"], tmp_path / "s", IngestParams(instance=case == "instanced"))
    assert a["warnings"] == [] and a["objects"] == (1 if case == "one-node" else 2)
    st = SceneStore(tmp_path / "s")
    xf, second = Y_TO_Z @ xf, Y_TO_Z @ second  # glTF is y-up: massview turns it to z-up before the node transforms
    expect = nrm @ np.linalg.inv(xf[:3, :3])
    expect /= np.linalg.norm(expect, axis=1, keepdims=True)
    for o in range(st.skeleton.count):
        m = st.get_mesh(int(st.skeleton.geometry[o]), 0)
        t = st.skeleton.transform[o]
        world = m.positions.astype(np.float64) @ t[:3, :3].T + t[:3, 3]
        n = m.normals.astype(np.float64) @ np.linalg.inv(t[:3, :3])  # as the renderers turn them
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        placed = v @ xf[:3, :3].T + (xf if world[:, 0].mean() < 15 else second)[:3, 3]
        k = np.argmin(np.linalg.norm(world[:, None] - placed[None], axis=2), axis=1)
        assert m.vertex_count == 8 and np.linalg.norm(world - placed[k], axis=1).max() < 1e-5
        np.testing.assert_allclose(n, expect[k], atol=1e-4)  # (stored octahedral int16)


def test_crease_angle_option_smooths_a_cube_at_180_and_is_checked(tmp_path):
    _cube_obj(tmp_path / "box.obj", "none")
    counts = {}
    for name, extra in (("default", ()), ("smooth", ("--crease-angle", 180))):
        run_cli("prepare", "scene", tmp_path / "box.obj", "-o", tmp_path / f"{name}.scene", "-q", *extra)
        run_cli("render", tmp_path / f"{name}.scene", "--path", "orbit", "--frames", 1, "--size", "200x150", "--out", tmp_path / f"r_{name}", "-q")
        counts[name] = _colours(tmp_path / f"r_{name}" / "frames" / "00000.png")
    assert counts["default"] == 2 and counts["smooth"] > 50, counts  # the two flat faces seen; a rounded gradient
    m = _level0(tmp_path / "smooth.scene")
    assert m.vertex_count == 8  # one normal per corner, between its three faces (area-weighted)
    assert (np.abs(m.normals) > 0.3).all()
    assert SceneStore(tmp_path / "smooth.scene").attrs["params"]["crease_angle"] == 180
    assert SceneStore(tmp_path / "default.scene").attrs["params"]["crease_angle"] == 50
    for bad in ("0", "181", "nan"):
        proc = run_cli("prepare", "scene", tmp_path / "box.obj", "-o", tmp_path / "bad.scene", "--crease-angle", bad, check=False)
        assert proc.returncode != 0 and "--crease-angle must be more than 0 and at most 180" in proc.stderr
        assert len(proc.stderr.strip().splitlines()) == 1 and not (tmp_path / "bad.scene").exists()
