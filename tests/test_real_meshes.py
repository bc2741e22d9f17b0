"""The packaged real-world meshes the generated forest scatters: pyvista's ant and the scanned
Stanford bunny from pymeshlab's wheel (M2's forest, Süß et al. 2010 §7.2), read through the
scene store's own OBJ ingest."""

import numpy as np
import pytest

from massview.core.errors import ConfigError
from massview.data.generators.scenes import REAL_MESHES, real_mesh, real_mesh_path, scene_nodes


def test_the_scanned_bunny_loads_through_the_store_ingest_z_up():
    path = real_mesh_path("bunny")
    assert path.name == "bunny.obj" and REAL_MESHES["bunny"][2]  # marked scanned
    v, t = real_mesh("bunny")
    assert v.shape == (28088, 3) and t.shape == (56172, 3)  # the file's own counts: nothing lost, nothing duplicated
    assert t.min() == 0 and t.max() == len(v) - 1
    import trimesh

    f = np.asarray(trimesh.load(path, process=False, force="mesh").vertices)
    assert np.allclose(v.min(0), [f[:, 0].min(), -f[:, 2].max(), f[:, 1].min()], atol=1e-6)  # the file's y-up turned z-up
    assert np.allclose(v.max(0), [f[:, 0].max(), -f[:, 2].min(), f[:, 1].max()], atol=1e-6)
    # every triangle is a real one: no degenerate faces survive the ingest's cleaning
    assert np.all((t[:, 0] != t[:, 1]) & (t[:, 1] != t[:, 2]) & (t[:, 0] != t[:, 2]))


def test_forest_with_bunnies_keeps_the_layout_and_the_default_stays_the_ant():
    ants, ext_a = scene_nodes("forest", 0.2, 3)
    bunnies, ext_b = scene_nodes("forest", 0.2, 3, real="bunny")
    assert ext_a == ext_b and len(ants) == len(bunnies)
    real = [i for i, n in enumerate(ants) if n.shape[0] == "real"]
    assert real and all(ants[i].shape == ("real", "ant") and bunnies[i].shape == ("real", "bunny") for i in real)
    for a, b in zip(ants, bunnies):
        assert a.placement == b.placement and a.path == b.path
        assert a.scale == b.scale if a.shape[0] != "real" else b.scale == pytest.approx(a.scale * 50)


def test_unknown_real_mesh_is_named():
    with pytest.raises(ConfigError, match="teapot"):
        scene_nodes("forest", 0.1, real="teapot")
    with pytest.raises(ConfigError, match="teapot"):
        real_mesh_path("teapot")
