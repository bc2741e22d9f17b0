"""Up axis of scene inputs: glTF/GLB is +y up by its specification and is turned to massview's
+z up ((x, y, z) -> (x, -z, y)); ``--up y`` does the same for any format, ``--up z`` keeps a file
as it is. Also: an OBJ whose material library is missing says it is drawn grey."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from conftest import load_png, run_cli
from massview.data.scene import SceneStore
from massview.data.scene.ingest import IngestParams, prepare_scene

TOWER_H = 6.0
TURN = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])  # y-up -> z-up


def _yup_town(path) -> None:
    """A glTF as Blender/trimesh write a y-up scene: a green 20x20 ground in the x-z plane (its
    NORMAL +y) and three red towers of one mesh standing along +y, placed by node transforms."""
    ground = trimesh.Trimesh([[-10, 0, -10], [-10, 0, 10], [10, 0, 10], [10, 0, -10]], [[0, 1, 2], [0, 2, 3]],
                             vertex_normals=np.tile([0.0, 1.0, 0.0], (4, 1)), process=False)
    ground.visual.vertex_colors = np.tile([60, 160, 60, 255], (4, 1)).astype(np.uint8)
    tower = trimesh.creation.box([1.0, TOWER_H, 1.0])
    tower.apply_translation([0, TOWER_H / 2, 0])
    tower.visual.vertex_colors = np.tile([170, 40, 40, 255], (len(tower.vertices), 1)).astype(np.uint8)
    scene = trimesh.Scene()
    scene.add_geometry(ground, node_name="ground", geom_name="ground")
    scene.add_geometry(tower, node_name="t0", geom_name="tower", transform=trimesh.transformations.translation_matrix([-5.0, 0, -4.0]))
    for k, (x, z) in enumerate([(0.0, 3.0), (5.0, -2.0)], 1):
        scene.graph.update(frame_to=f"t{k}", frame_from=scene.graph.base_frame, geometry="tower",
                           matrix=trimesh.transformations.translation_matrix([x, 0, z]))
    path.write_bytes(trimesh.exchange.gltf.export_glb(scene))


def _world(path) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per object: world level-0 triangles (t,3,3) and unit world normals (v,3) at their corners."""
    st = SceneStore(path)
    out = []
    for o in range(st.skeleton.count):
        m = st.get_mesh(int(st.skeleton.geometry[o]), 0)
        t = st.skeleton.transform[o].astype(np.float64)
        p = m.positions.astype(np.float64) @ t[:3, :3].T + t[:3, 3]
        n = m.normals.astype(np.float64) @ np.linalg.inv(t[:3, :3])  # as the renderers turn them
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        out.append((p[m.indices], n[m.indices]))
    return out


@pytest.mark.parametrize("instance", [False, True])
def test_gltf_towers_along_y_stand_up_along_z(tmp_path, instance):
    _yup_town(tmp_path / "town.glb")
    a = prepare_scene([tmp_path / "town.glb"], tmp_path / "s", IngestParams(instance=instance))
    assert a["params"]["up"] == "auto" and a["objects"] == 4 and a["geometries"] == (2 if instance else 4)
    lo, hi = SceneStore(tmp_path / "s").bounds
    np.testing.assert_allclose(lo, [-10, -10, 0], atol=1e-5)
    np.testing.assert_allclose(hi, [10, 10, TOWER_H], atol=1e-5)  # z extent: the towers' height
    objs = _world(tmp_path / "s")
    grounds = [(t, n) for t, n in objs if np.ptp(t[..., 2]) < 1e-6]
    assert len(grounds) == 1
    t, n = grounds[0]
    np.testing.assert_allclose(n.reshape(-1, 3), np.tile([0, 0, 1.0], (t.size // 3, 1)), atol=1e-4)  # the file's +y NORMAL
    geo = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])  # winding kept: front faces face up
    assert (geo[:, 2] > 0).all()
    towers = [t for t, _ in objs if np.ptp(t[..., 2]) > 1]
    assert len(towers) == 3 and all(abs(np.ptp(t[..., 2]) - TOWER_H) < 1e-5 for t in towers)
    # --up z: the file as written, the towers lying along +y
    b = prepare_scene([tmp_path / "town.glb"], tmp_path / "z", IngestParams(instance=instance, up="z"))
    assert b["params"]["up"] == "z"
    np.testing.assert_allclose(SceneStore(tmp_path / "z").bounds[1], [10, TOWER_H, 10], atol=1e-5)


def test_gltf_town_renders_with_ground_below_and_towers_up(tmp_path):
    _yup_town(tmp_path / "town.glb")
    red_top, green_top = {}, {}
    for up in ("auto", "z"):
        run_cli("prepare", "scene", tmp_path / "town.glb", "-o", tmp_path / f"{up}.scene", "--up", up, "-q")
        run_cli("render", tmp_path / f"{up}.scene", "--path", "orbit", "--frames", 1, "--size", "240x180", "--out", tmp_path / f"r_{up}", "-q")
        img = load_png(tmp_path / f"r_{up}" / "frames" / "00000.png").astype(int)
        r, g, b = img[..., 0], img[..., 1], img[..., 2]
        red, green = (r > g + 40) & (r > b + 40), (g > r + 40) & (g > b + 20)
        assert red.sum() > 50 and green.sum() > 500, (up, red.sum(), green.sum())
        rows = np.arange(img.shape[0])[:, None]
        red_top[up], green_top[up] = int(rows[red.any(axis=1)].min()), int(rows[green.any(axis=1)].min())
        # the lowest drawn rows: the ground in front (auto), or the wall's foot (z)
    assert red_top["auto"] < green_top["auto"] - 5, (red_top, green_top)  # the towers rise above the ground's far edge
    assert green_top["z"] < red_top["z"], (red_top, green_top)  # read as z-up: a wall, towers sideways, below its top


def _write_ply(path, v, n, c, f) -> None:
    """A binary PLY with float positions, normals and colours."""
    head = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(v)}\n"
            + "".join(f"property float {k}\n" for k in ("x", "y", "z", "nx", "ny", "nz"))
            + "property uchar red\nproperty uchar green\nproperty uchar blue\n"
            + f"element face {len(f)}\nproperty list uchar int vertex_indices\nend_header\n").encode()
    rec = np.empty(len(v), [("p", "<f4", 3), ("n", "<f4", 3), ("c", "u1", 3)])
    rec["p"], rec["n"], rec["c"] = v, n, c
    fr = np.empty(len(f), [("k", "u1"), ("i", "<i4", (3,))])
    fr["k"], fr["i"] = 3, f
    path.write_bytes(head + rec.tobytes() + fr.tobytes())


def _yup_ply_parts():
    """Flat-shaded (corners unshared, face normals) y-up soup: a ground and a tower."""
    ground = trimesh.creation.box([20.0, 0.2, 20.0])
    ground.apply_translation([0, -0.1, 0])
    tower = trimesh.creation.box([1.0, TOWER_H, 1.5])
    tower.apply_translation([2.0, TOWER_H / 2, -3.0])
    parts = []
    for m, col in ((ground, (60, 160, 60)), (tower, (170, 40, 40))):
        v = np.asarray(m.vertices)[m.faces].reshape(-1, 3)
        n = np.repeat(np.asarray(m.face_normals), 3, axis=0)
        parts.append((v, n, np.tile(col, (len(v), 1))))
    v, n, c = (np.concatenate(x) for x in zip(*parts))
    return v, n, c, np.arange(len(v)).reshape(-1, 3)


@pytest.mark.parametrize("stream", [False, True])
def test_ply_with_up_y_equals_the_same_ply_turned_beforehand(tmp_path, stream):
    v, n, c, f = _yup_ply_parts()
    _write_ply(tmp_path / "yup.ply", v, n, c, f)
    _write_ply(tmp_path / "zup.ply", v @ TURN.T, n @ TURN.T, c, f)
    extra = ("--stream-mb", 0) if stream else ()
    frames = {}
    for name, up in (("yup", "y"), ("zup", "z")):
        run_cli("prepare", "scene", tmp_path / f"{name}.ply", "-o", tmp_path / f"{name}.scene", "--up", up, "-q", *extra)
        run_cli("render", tmp_path / f"{name}.scene", "--path", "orbit", "--frames", 1, "--size", "200x150", "--out", tmp_path / f"r_{name}", "-q")
        frames[name] = load_png(tmp_path / f"r_{name}" / "frames" / "00000.png").astype(int)
    a, b = SceneStore(tmp_path / "yup.scene"), SceneStore(tmp_path / "zup.scene")
    np.testing.assert_array_equal(np.asarray(a.bounds), np.asarray(b.bounds))
    np.testing.assert_allclose(a.bounds[1][2], TOWER_H, atol=1e-5)
    assert np.abs(frames["yup"] - frames["zup"]).max() <= 1
    wa, wb = _world(tmp_path / "yup.scene"), _world(tmp_path / "zup.scene")
    key = lambda objs: np.concatenate([np.concatenate([t.reshape(-1, 9), nn.reshape(-1, 9)], 1) for t, nn in objs])  # noqa: E731
    ka, kb = key(wa), key(wb)
    np.testing.assert_allclose(ka[np.lexsort(ka.T[::-1])], kb[np.lexsort(kb.T[::-1])], atol=1e-4)


def test_obj_groups_with_up_y_are_turned(tmp_path):
    obj = tmp_path / "g.obj"
    obj.write_text("o a\nv 0 0 0\nv 1 0 0\nv 0 1 0\nvn 0 0 1\nf 1//1 2//1 3//1\ng b\nv 5 0 0\nv 6 0 0\nv 5 0 -1\nf 4 5 6\n")
    prepare_scene([obj], tmp_path / "y", IngestParams(up="y"))
    objs = _world(tmp_path / "y")
    assert len(objs) == 2
    a = next(t for t, _ in objs if t[..., 0].max() < 2)
    np.testing.assert_allclose(a[0], np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]]) @ TURN.T, atol=1e-6)
    np.testing.assert_allclose(next(n for t, n in objs if t[..., 0].max() < 2)[0], np.tile([0, -1.0, 0], (3, 1)), atol=1e-4)
    b = next(t for t, _ in objs if t[..., 0].max() > 2)
    np.testing.assert_allclose(b[0], np.array([[5, 0, 0], [6, 0, 0], [5, 1, 0]]), atol=1e-6)  # (5, 0, -1) -> (5, 1, 0)


def test_bad_up_is_one_line(tmp_path):
    obj = tmp_path / "t.obj"
    obj.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    proc = run_cli("prepare", "scene", obj, "-o", tmp_path / "s", "--up", "x", check=False)
    assert proc.returncode != 0 and "--up must be one of auto, y, z" in proc.stderr and "'x'" in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1 and not (tmp_path / "s").exists()


def test_obj_with_a_missing_material_library_warns_it_is_drawn_grey(tmp_path):
    obj = tmp_path / "nomtl.obj"
    obj.write_text("mtllib missing.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 0 1\nusemtl foo\nf 1/1 2/2 3/3\n")
    proc = run_cli("prepare", "scene", obj, "-o", tmp_path / "s", "-q")
    warns = [ln for ln in proc.stderr.splitlines() if "warning" in ln]
    assert len(warns) == 1 and str(obj) in warns[0] and "missing.mtl" in warns[0] and "drawn grey" in warns[0], proc.stderr
    (tmp_path / "missing.mtl").write_text("newmtl foo\nKd 0.8 0.1 0.1\n")  # with the library beside it: no warning, its colour
    proc = run_cli("prepare", "scene", obj, "-o", tmp_path / "s2", "-q")
    assert "warning" not in proc.stderr, proc.stderr
    st = SceneStore(tmp_path / "s2")
    col = st.get_mesh(int(st.skeleton.geometry[0]), 0).colors
    assert col[:, 0].min() > 150 and col[:, 1].max() < 80


def test_the_side_of_a_surface_away_from_the_light_is_darker(tmp_path):
    """walk6 #4: the key light was |n·L|, so a plate seen from below was lit exactly as from
    above (and a sphere's underside as brightly as its top). Now the normal is turned towards
    the eye and the side away from the light gets the ambient and a fill light only."""
    import massview as mv

    plate = trimesh.creation.box([4.0, 4.0, 0.02])
    v = np.asarray(plate.vertices)[plate.faces].reshape(-1, 3)
    n = np.repeat(np.asarray(plate.face_normals), 3, axis=0)
    _write_ply(tmp_path / "plate.ply", v, n, np.tile((200, 200, 200), (len(v), 1)), np.arange(len(v)).reshape(-1, 3))
    run_cli("prepare", "scene", tmp_path / "plate.ply", "-o", tmp_path / "plate.scene", "-q")
    store = str(tmp_path / "plate.scene")
    mean = {}
    for side, z in (("above", 6.0), ("below", -6.0)):
        cam = mv.camera(store, position=[0.3, 0.2, z], look_at=[0.0, 0.0, 0.0], size=(96, 72))
        img = mv.render_frame(store, cam).astype(float)
        mean[side] = img[30:42, 42:54].mean()  # the middle of the plate
    assert mean["below"] < 0.6 * mean["above"], mean
