"""The clustering stored beside a scene store (real zarr files) and M2 objects built from a
store's skeleton and meshes (an in-memory store of the SceneStore shape)."""

from types import SimpleNamespace

import numpy as np
import pytest
import zarr

from massview.core.errors import StoreError
from massview.data.board_clusters import read_clusters, write_clusters
from massview.lod.clusters import FEASIBLE, TOO_FEW_TRIANGLES, ClusterParams
from massview.systems.boardscene import objects_from_store


def test_clusters_round_trip_additively_and_complete_last(tmp_path):
    path = tmp_path / "scene.zarr"
    root = zarr.open_group(str(path), mode="w", zarr_format=3)
    root.attrs["format"] = "massview-scene"
    root.create_array("skeleton/center", shape=(3, 3), dtype="float64")
    assert read_clusters(path) is None
    write_clusters(path, np.array([0, 0, 1]), np.array([FEASIBLE, TOO_FEW_TRIANGLES]), {"d_nz": 2.5, "sl_c": 0.4, "t_nz": 10})
    got = read_clusters(path)
    assert got.labels.tolist() == [0, 0, 1] and got.status.tolist() == [0, 2]
    assert got.attrs["d_nz"] == 2.5 and got.attrs["clusters"] == 2
    again = zarr.open_group(str(path), mode="r")
    assert again.attrs["format"] == "massview-scene" and "skeleton/center" in again  # the store's own data untouched
    zarr.open_group(str(path), mode="r+")["reliefboards"].attrs["complete"] = False  # as if interrupted
    assert read_clusters(path) is None
    with pytest.raises(StoreError, match="not a scene store"):
        write_clusters(tmp_path / "nothing", np.zeros(1), np.zeros(1), {})


def _cube():
    p = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], np.float32)
    t = np.array([0, 1, 3, 0, 3, 2, 4, 6, 7, 4, 7, 5, 0, 4, 5, 0, 5, 1, 2, 3, 7, 2, 7, 6, 0, 2, 6, 0, 6, 4, 1, 5, 7, 1, 7, 3], np.uint32)
    n = (p - 0.5) / np.linalg.norm(p - 0.5, axis=1, keepdims=True)
    return SimpleNamespace(positions=p, normals=n.astype(np.float32), colors=np.full((8, 4), 200, np.uint8), indices=t)


def test_objects_from_a_store_apply_transforms_and_merge_clusters():
    tf = np.tile(np.eye(4), (3, 1, 1))
    tf[1, :3, 3] = (2, 0, 0)
    tf[2, :3, :3] *= 3.0  # scaled copy
    tf[2, :3, 3] = (10, 0, 0)
    lo = np.array([[0, 0, 0], [2, 0, 0], [10, 0, 0]], float)
    hi = lo + np.array([[1], [1], [3]])
    sk = SimpleNamespace(box_lo=lo, box_hi=hi, triangles=np.array([[12, 4], [12, 4], [12, 4]]), geometry=np.zeros(3, int), transform=tf)
    store = SimpleNamespace(skeleton=sk, get_mesh=lambda g, lv: _cube(), path="mem")
    params = ClusterParams(t_nz=20, p=4, r_y=100, fovy=90.0, min_triangles=20)
    obj = objects_from_store(store, params, labels=np.array([0, 0, 1]))
    assert obj.count == 2 and obj.triangles.tolist() == [24, 12]
    assert obj.status[1] != FEASIBLE  # 12 < 20 triangles
    pos, nrm, col, idx = obj.mesh(0)
    assert len(pos) == 16 and len(idx) == 72 and idx.max() == 15
    np.testing.assert_array_equal(obj.origins, [[1.5, 0.5, 0.5], [11.5, 1.5, 1.5]])  # meshes about their box centres
    assert np.allclose(pos.min(0) + obj.origins[0], [0, 0, 0]) and np.allclose(pos.max(0) + obj.origins[0], [3, 1, 1])
    p2 = obj.mesh(1)[0] + obj.origins[1]
    assert np.allclose(p2.min(0), [10, 0, 0]) and np.allclose(p2.max(0), [13, 3, 3])
    assert np.allclose(np.linalg.norm(obj.mesh(1)[1], axis=1), 1, atol=1e-6)
    allp, _, _, allidx, offs, origin = obj.concatenated()
    assert len(allp) == 24 and offs.tolist() == [0, 72, 108] and allidx[72:].min() == 16
    np.testing.assert_array_equal(origin, [6.5, 1.5, 1.5])  # the scene's box centre
    assert np.allclose(allp.min(0) + origin, [0, 0, 0]) and np.allclose(allp.max(0) + origin, [13, 3, 3])
