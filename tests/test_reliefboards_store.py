"""`massview prepare reliefboards` on a real generated scene store, and M2 rendering its clusters."""

import json
import re

import numpy as np
import pytest

from conftest import run_cli

pytest.importorskip("fast_simplification")
pytest.importorskip("trimesh")


@pytest.fixture(scope="module")
def plant(tmp_path_factory):
    from massview.data.generators.scenes import generate_scene

    path = tmp_path_factory.mktemp("m2store") / "plant.zarr"
    generate_scene("plant", path, size=0.01)
    return path


@pytest.mark.slow
@pytest.mark.mpi
def test_prepare_stores_clusters_and_m2_renders_them(plant, tmp_path):
    from massview.data.board_clusters import read_clusters
    from massview.data.scene import SceneStore

    pic = tmp_path / "clusters.png"
    proc = run_cli("prepare", "reliefboards", plant, "--tnz", 20000, "--board-px", 32, "--size", "320x240",
                   "--min-triangles", 200, "--picture", pic)
    assert "clusters:" in proc.stdout and pic.exists()
    store = SceneStore(plant)  # the store still opens and reads as before
    sk = store.skeleton
    got = read_clusters(plant)
    assert len(got.labels) == sk.count and got.labels.max() == len(got.status) - 1
    assert got.attrs["t_nz"] == 20000 and got.attrs["sl_c"] > 0
    lo = np.full((len(got.status), 3), np.inf)
    hi = np.full((len(got.status), 3), -np.inf)
    np.minimum.at(lo, got.labels, sk.box_lo)
    np.maximum.at(hi, got.labels, sk.box_hi)
    feasible = got.status == 0
    assert feasible.any() and len(got.status) < sk.count  # components were merged
    assert np.all((hi - lo)[feasible].max(axis=1) <= got.attrs["sl_c"] + 1e-9)
    info = json.loads(run_cli("info", plant, "--json").stdout)["reliefboards"]  # walk6 #13: info shows the clustering
    assert (info["clusters"], info["feasible"], info["t_nz"]) == (len(got.status), int(feasible.sum()), 20000)
    assert info["feasible"] + info["too_large"] + info["too_few_triangles"] == info["clusters"]
    table = re.sub(r"[│\s]+", " ", run_cli("info", plant).stdout)  # (the table wraps long values in their cell)
    assert f"{len(got.status)} clusters: {int(feasible.sum())} feasible" in table and "t_nz = 20000" in table
    out = tmp_path / "run"
    run_cli("render", plant, "--system", "reliefboards", "--ranks", 2, "--frames", 6, "--path", "orbit",
            "--size", "320x240", "--tnz", 5000, "--board-px", 32, "--out", out, "-q")
    s = json.loads((out / "summary.json").read_text())
    assert s["objects"] == len(got.status) and s["feasible"] == int(feasible.sum())
    assert s["requests"] > 0 and s["board_passes_on_visualization_rank"] == 0


def test_prepare_names_a_missing_store(tmp_path):
    proc = run_cli("prepare", "reliefboards", tmp_path / "nope.zarr", check=False)
    assert proc.returncode != 0 and "not found" in proc.stderr and "generate scene" in proc.stderr


def test_prepare_warns_when_no_cluster_is_feasible(plant, tmp_path):
    """0 feasible clusters (the README's old small-plant example) is said, with what to change."""
    import shutil

    store = tmp_path / "p.zarr"
    shutil.copytree(plant, store)
    proc = run_cli("prepare", "reliefboards", store, "--min-triangles", 10**9)
    assert "0 feasible" in proc.stdout
    assert "warning: no cluster is feasible" in proc.stderr and "try a lower --min-triangles" in proc.stderr
    # clusters too long too (a near zone of 10 triangles): --tnz is advised for them (walk6 #9: only --min-triangles was)
    long = run_cli("prepare", "reliefboards", store, "--tnz", 10, "--min-triangles", 10**9)
    assert "warning: no cluster is feasible" in long.stderr and "too long, try a larger --tnz" in long.stderr, long.stderr
    ok = run_cli("prepare", "reliefboards", store, "--tnz", 20000, "--board-px", 32, "--size", "320x240", "--min-triangles", 100)
    assert "warning" not in ok.stderr
