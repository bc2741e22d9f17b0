"""`prepare scene` keeps georeferenced coordinates: a mesh at UTM-like coordinates (500000,
4000000, 250) is stored as the same mesh at the origin is — every triangle kept, level 0 equal
to the input to float32 precision in each object's own frame — through the in-memory, the
streamed PLY and the instanced ingest, and renders like the copy at the origin. (Casting the
absolute positions to float32 first, as massview did, resolves 0.25-0.5 m at 4e6: a unit sphere
lost a quarter of its triangles and rendered stair-stepped.)"""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from conftest import load_png, run_cli, save_diff
from massview.data.scene import SceneStore
from massview.data.scene.ingest import IngestParams, prepare_scene
from massview.data.scene.verify import verify_scene

OFFSET = np.array([500000.0, 4000000.0, 250.0])


def _sphere() -> trimesh.Trimesh:
    return trimesh.creation.uv_sphere(radius=1.0, count=[48, 28])  # 5152 triangles


def write_ply64(path, v, f) -> None:
    """A binary PLY with double coordinates (trimesh writes float)."""
    head = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(v)}\nproperty double x\nproperty double y\n"
            f"property double z\nelement face {len(f)}\nproperty list uchar int vertex_indices\nend_header\n").encode()
    rec = np.empty(len(f), [("n", "u1"), ("i", "<i4", (3,))])
    rec["n"], rec["i"] = 3, f
    path.write_bytes(head + np.asarray(v, "<f8").tobytes() + rec.tobytes())


def write_obj(path, v, f) -> None:
    path.write_text("".join(f"v {x:.8f} {y:.8f} {z:.8f}\n" for x, y, z in v) + "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in f))


def world_level0(path) -> tuple[np.ndarray, float]:
    """World triangles (t,3,3) f8 of a store's level 0 (local positions through each object's
    transform, in float64) and the largest float32 spacing of any object's local coordinates."""
    st = SceneStore(path)
    tris, ulp = [], 0.0
    for o in range(st.skeleton.count):
        m = st.get_mesh(int(st.skeleton.geometry[o]), 0)
        xf = np.asarray(st.skeleton.transform[o], np.float64)
        tris.append((m.positions.astype(np.float64) @ xf[:3, :3].T + xf[:3, 3])[m.indices])
        ulp = max(ulp, float(np.spacing(np.abs(m.positions).max())))
    return np.concatenate(tris), ulp


def _canonical(idx: np.ndarray, tris: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Triangles as input vertex triples (t,3) and their corners (t,3,3), each rotated to start
    at its smallest index (winding kept) and sorted by the triples."""
    r = idx.argmin(axis=1)
    rows = np.arange(len(idx))
    idx = np.stack([idx[rows, (r + k) % 3] for k in range(3)], 1)
    tris = np.stack([tris[rows, (r + k) % 3] for k in range(3)], 1)
    order = np.lexsort(idx.T[::-1])
    return idx[order], tris[order]


def as_input(tris: np.ndarray, v: np.ndarray, f: np.ndarray, tol: float) -> np.ndarray:
    """Every stored corner lies within ``tol`` (per axis) of an input vertex, and the stored
    triangles are the input's (as vertex triples, winding kept). Returns the corners in the
    input's canonical triangle order."""
    from scipy.spatial import cKDTree

    d, idx = cKDTree(v).query(tris.reshape(-1, 3), p=np.inf)
    assert d.max() <= tol, f"a stored vertex is {d.max():.3g} from the input (float32 rounding: {tol:.3g})"
    got, corners = _canonical(idx.reshape(-1, 3), tris)
    want, _ = _canonical(np.asarray(f), np.zeros((len(f), 3, 3)))
    np.testing.assert_array_equal(got, want)
    return corners


@pytest.mark.parametrize("kind", ["ply", "obj", "ply-streamed"])
def test_georeferenced_mesh_is_stored_as_the_one_at_the_origin(tmp_path, kind):
    m = _sphere()
    v, f = np.asarray(m.vertices, np.float64), np.asarray(m.faces, np.int64)
    prm = IngestParams(object_triangles=700)  # several objects: cut in float64, each in its own frame
    if kind == "ply-streamed":
        prm = IngestParams(object_triangles=700, cell_triangles=1200, stream_bytes=0, face_chunk=500, vertex_block=300)
    got = {}
    for name, off in (("origin", np.zeros(3)), ("far", OFFSET)):
        src = tmp_path / f"{name}.{kind.split('-')[0]}"
        (write_obj if kind == "obj" else write_ply64)(src, v + off, f)
        a = prepare_scene([src], tmp_path / name, prm)
        assert a["triangles"] == len(f), f"{name}: {len(f) - a['triangles']} of {len(f)} triangles lost"
        tris, ulp = world_level0(tmp_path / name)
        got[name] = as_input(tris - off, v, f, ulp)  # the input geometry to float32 rounding of the local coordinates
        assert verify_scene(tmp_path / name) == []
    np.testing.assert_allclose(got["far"], got["origin"], rtol=0, atol=2 * ulp)
    boxes = []  # the same objects (in an order that may differ where box centres tie)
    for name, off in (("origin", np.zeros(3)), ("far", OFFSET)):
        sk = SceneStore(tmp_path / name).skeleton
        b = np.column_stack([sk.box_lo - off, sk.box_hi - off, sk.triangles[:, :1]])
        boxes.append(b[np.lexsort(np.round(b, 5).T[::-1])])
    np.testing.assert_allclose(boxes[1], boxes[0], rtol=0, atol=1e-6)


def test_instanced_geometry_at_georeferenced_placements(tmp_path):
    """glTF nodes of one mesh at UTM-like translations (not whole metres): the instanced store
    (the mesh once, with transforms) and the flat one place every triangle where the file does."""
    m = _sphere()
    offs = [OFFSET + [0.37, 0.71, 0.13], OFFSET + [3.37, 0.71, 0.13]]
    scene = trimesh.Scene()
    scene.add_geometry(m, node_name="n0", geom_name="ball", transform=trimesh.transformations.translation_matrix(offs[0]))
    scene.graph.update(frame_to="n1", frame_from=scene.graph.base_frame, geometry="ball",
                       matrix=trimesh.transformations.translation_matrix(offs[1]))
    glb = tmp_path / "inst.glb"
    scene.export(glb)
    file_v = np.asarray(m.vertices, np.float32).astype(np.float64)  # glTF holds float32 vertices in the mesh's frame
    turn = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])  # glTF is y-up: stored turned to z-up, (x, y, z) -> (x, -z, y)
    file_v, offs = file_v @ turn.T, [o @ turn.T for o in offs]
    for name, inst in (("flat", False), ("inst", True)):
        a = prepare_scene([glb], tmp_path / name, IngestParams(instance=inst))
        assert (a["objects"], a["geometries"]) == (2, 1 if inst else 2)
        tris, ulp = world_level0(tmp_path / name)
        assert len(tris) == 2 * len(m.faces)
        st = SceneStore(tmp_path / name)
        for o in offs:
            mine = tris[(tris[:, 0, 0] > o[0] - 1.5) & (tris[:, 0, 0] < o[0] + 1.5)]
            as_input(mine - o, file_v, np.asarray(m.faces), ulp + np.spacing(1.0))
        assert verify_scene(tmp_path / name) == []
        assert st.skeleton.transform.dtype == np.float64


def test_georeferenced_mesh_renders_like_the_one_at_the_origin(tmp_path):
    m = _sphere()
    frames = {}
    for name, off in (("origin", np.zeros(3)), ("far", OFFSET)):
        write_ply64(tmp_path / f"{name}.ply", np.asarray(m.vertices) + off, m.faces)
        run_cli("prepare", "scene", tmp_path / f"{name}.ply", "-o", tmp_path / f"{name}.scene", "-q")
        run_cli("render", tmp_path / f"{name}.scene", "--path", "orbit", "--frames", 2, "--size", "240x180",
                "--out", tmp_path / f"r_{name}", "-q")
        frames[name] = [load_png(p) for p in sorted((tmp_path / f"r_{name}" / "frames").glob("*.png"))]
    assert len(frames["origin"]) == len(frames["far"]) == 2
    for k, (a, b) in enumerate(zip(frames["origin"], frames["far"])):
        lit = np.any(a != a[0, 0], axis=2).mean()
        assert lit > 0.2  # the sphere fills a good part of the frame
        equal = np.all(np.abs(a.astype(int) - b.astype(int)) <= 1, axis=2).mean()
        if equal < 0.995:
            save_diff(a, b, tmp_path / f"diff{k}.png")
        assert equal >= 0.995, f"frame {k}: only {equal:.1%} of the pixels equal (diff: {tmp_path / f'diff{k}.png'})"
