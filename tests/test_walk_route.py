"""``walkthrough`` walks round a scene's objects (lod/walk.py): on street grids, a maze that is
open only south–north, a closed scene (the old straight line), and a generated city store, where
the old straight line went through building walls. Checked on the cameras themselves: every
eye stays clear of every box that stands in a walker's way."""

from __future__ import annotations

import numpy as np
import pytest

from massview.core.paths import load_path
from massview.lod.walk import plan_walk, walk_route


def _blocks(n: int, size: float, street: float, height: float = 20.0):
    """An n × n grid of buildings ``size`` wide with ``street``-wide streets between them
    (and half a street round the edge)."""
    step = size + street
    c = np.array([(street / 2 + i * step, street / 2 + j * step) for i in range(n) for j in range(n)])
    lo = np.column_stack([c, np.zeros(len(c))])
    hi = np.column_stack([c + size, np.full(len(c), height)])
    return lo, hi


def _clearance(eyes: np.ndarray, blo: np.ndarray, bhi: np.ndarray) -> float:
    """The least xy distance from any eye to any box footprint."""
    d = np.maximum(np.maximum(blo[None, :, :2] - eyes[:, None, :2], eyes[:, None, :2] - bhi[None, :, :2]), 0)
    return float(np.min(np.linalg.norm(d, axis=2)))


def _eyes(blo, bhi, obstacles, frames=40):
    lo, hi = blo.min(0), bhi.max(0)
    cams = load_path("walkthrough", lo, hi, route=plan_walk("walkthrough", lo, hi, obstacles)).cameras(frames, 64, 48)
    return lo, hi, np.array([c.position for c in cams]), np.array([c.forward for c in cams])


@pytest.mark.parametrize("n,size,street", [(6, 12.0, 4.0), (9, 20.0, 3.0), (4, 30.0, 8.0)])
def test_the_walk_keeps_to_the_streets(n, size, street):
    blo, bhi = _blocks(n, size, street)
    lo, hi, eyes, fwd = _eyes(blo, bhi, (blo, bhi))
    assert _clearance(eyes, blo, bhi) >= 0.5  # never inside (or brushing) a building
    assert np.allclose(eyes[:, 2], 1.7)
    assert eyes[-1, 0] - eyes[0, 0] > 0.7 * (hi[0] - lo[0])  # it crosses the scene, west to east
    assert abs(np.mean(eyes[:, 1]) - (lo[1] + hi[1]) / 2) < (size + street)  # on a street near the middle
    assert np.all(fwd[:, 0] > 0.5)  # looking the way it walks
    _, _, straight, _ = _eyes(blo, bhi, None)
    assert _clearance(straight, blo, bhi) == 0.0  # (the old straight line did walk through walls here)


def test_a_scene_open_only_south_north_is_walked_south_north():
    x = 2.0 + 16.0 * np.arange(6)  # long slabs from the south edge to the north one: streets run south-north only
    wl = np.column_stack([x, np.zeros(6), np.zeros(6)])
    wh = np.column_stack([x + 12.0, np.full(6, 100.0), np.full(6, 20.0)])
    lo, hi, eyes, fwd = _eyes(wl, wh, (wl, wh))
    assert _clearance(eyes, wl, wh) >= 0.5
    assert eyes[-1, 1] - eyes[0, 1] > 0.7 * (hi[1] - lo[1])
    assert np.all(fwd[:, 1] > 0.5)


def test_low_and_floor_sized_boxes_are_not_in_the_way():
    """A kerb (below the knee), a ground slab under everything and a box over the whole scene
    (an enclosure one walks inside) do not stop the walk."""
    blo, bhi = _blocks(5, 12.0, 4.0)
    slab = np.array([[0.0, 0.0, -0.3, 80.0, 80.0, 0.0], [0.0, 0.0, 0.0, 80.0, 80.0, 20.0]])
    kerbs = np.array([[0.0, 14.0, 0.0, 80.0, 14.3, 0.2]])
    wl, wh = np.vstack([blo, slab[:, :3], kerbs[:, :3]]), np.vstack([bhi, slab[:, 3:], kerbs[:, 3:]])
    way = walk_route(wl.min(0), wh.max(0), wl, wh, wl.min(0)[2] + 1.7)
    assert way is not None and way[-1, 0] - way[0, 0] > 50


def test_a_closed_scene_falls_back_to_the_straight_walk():
    box = (np.array([[0.0, 28, 0], [48, 0, 0]]), np.array([[100.0, 32, 10], [52, 60, 10]]))  # a wall across each way
    assert walk_route([0, 0, 0], [100, 60, 10], *box, 1.7) is None
    assert plan_walk("walkthrough", [0, 0, 0], [100, 60, 10], box) is None
    planned = load_path("walkthrough", [0, 0, 0], [100, 60, 10], route=None).cameras(5, 64, 48)
    straight = load_path("walkthrough", [0, 0, 0], [100, 60, 10]).cameras(5, 64, 48)
    assert [c.position for c in planned] == [c.position for c in straight]


def test_the_walk_is_deterministic_and_only_walkthrough_is_planned():
    blo, bhi = _blocks(6, 12.0, 4.0)
    a = _eyes(blo, bhi, (blo, bhi))[2]
    b = _eyes(blo, bhi, (blo.copy(), bhi.copy()))[2]
    assert np.array_equal(a, b)
    lo, hi = blo.min(0), bhi.max(0)
    for name in ("orbit", "flyover", "zoom"):
        assert plan_walk(name, lo, hi, (blo, bhi)) is None
        way = plan_walk("walkthrough", lo, hi, (blo, bhi))
        assert [c.position for c in load_path(name, lo, hi, route=way).cameras(4, 64, 48)] == \
            [c.position for c in load_path(name, lo, hi).cameras(4, 64, 48)]


def test_a_generated_city_is_walked_through_its_streets(tmp_path):
    """The generated city (where the old walk went through walls): the CLI's system and the
    Python API give the same planned cameras, and no eye is inside a building's box."""
    import massview as mv
    from massview.data.generators.scenes import generate_scene
    from massview.data.scene import SceneStore
    from massview.systems import open_system
    from massview.core.config import RenderConfig

    store = tmp_path / "city.zarr"
    generate_scene("city", store, copies=1, size=0.15)
    st = SceneStore(store)
    blo, bhi = st.object_boxes
    lo, hi = st.bounds
    cams = mv.path("walkthrough", str(store), frames=12, size=(64, 48))
    system = open_system(str(store), RenderConfig())
    try:
        cli = load_path("walkthrough", *system.bounds, route=plan_walk("walkthrough", *system.bounds, system.obstacles)).cameras(12, 64, 48)
    finally:
        if hasattr(system, "close"):
            system.close()
    assert [c.position for c in cams] == [c.position for c in cli]
    eyes = np.array([c.position for c in cams])
    z = eyes[0, 2]
    stands = (bhi[:, 2] > lo[2] + 0.3 * (z - lo[2])) & (blo[:, 2] < z)
    assert _clearance(eyes, blo[stands], bhi[stands]) > 0.3
    straight = np.array([c.position for c in load_path("walkthrough", lo, hi).cameras(12, 64, 48)])
    assert _clearance(straight, blo[stands], bhi[stands]) == 0.0  # (what the issue was)


def test_walkthrough_on_a_terrain_walks_on_its_ground(terrain_store, tmp_path):
    """On a terrain store ``walkthrough`` keeps the eye 1.7 units above the ground under it (it
    stood 1.7 above the lowest sample of the whole DEM, under the surface almost everywhere, and
    its frames showed the terrain from below), with a near plane inside that height; with
    --exaggeration the ground is the exaggerated one. The frames show ground below, sky above."""
    import massview as mv
    from massview.data.terrain import TerrainStore
    from tests.conftest import load_png, not_sky, run_cli

    st = TerrainStore(terrain_store)
    lay, (dx, dy), vs = st.layout, st.spacing, st.vertical_scale
    cams = mv.path("walkthrough", str(terrain_store), frames=6, size=(160, 100))
    for c in cams:
        col, row = c.position[0] / dx, -c.position[1] / dy
        r0, c0 = int(np.floor(row)), int(np.floor(col))
        blk = st.get_block(0, r0 // (lay.M - 1), c0 // (lay.M - 1))
        lr, lc = r0 % (lay.M - 1), c0 % (lay.M - 1)
        ground = float(blk[lr:lr + 2, lc:lc + 2].max()) * vs
        assert c.position[2] == pytest.approx(ground + 1.7, abs=1e-6)
        assert c.near < 1.7
    out = tmp_path / "w"
    run_cli("render", terrain_store, "--path", "walkthrough", "--frames", 3, "--size", "160x100", "--exaggeration", 3,
            "--out", out, "-q")
    for k in range(3):
        f = load_png(out / "frames" / f"{k:05d}.png")
        assert not_sky(f[-10:]) == 10 * 160, f"frame {k}: sky below the eye (the eye is under the ground)"
        assert not_sky(f[:10]) < 0.75 * 10 * 160, f"frame {k}: no sky in the top rows"


# a 20 x 20 town of six towers 2-5 units high (glTF: y up, x-z ground), scattered round the middle
_TOWN = [(7.2, -5.7, 3.5), (-3.0, -1.2, 4.8), (-1.5, 0.8, 4.5), (4.1, 0.6, 2.1), (4.6, -3.1, 3.0), (-5.9, -1.6, 3.4)]


def _tiny_town(path) -> None:
    import trimesh

    ground = trimesh.Trimesh([[-10, 0, -10], [10, 0, -10], [10, 0, 10], [-10, 0, 10]], [[0, 2, 1], [0, 3, 2]], process=False)
    ground.visual.face_colors = [120, 120, 120, 255]
    scene = trimesh.Scene()
    scene.add_geometry(ground, node_name="ground", geom_name="ground")
    for i, (x, z, h) in enumerate(_TOWN):
        tower = trimesh.creation.box(extents=(1.5, h, 1.5))
        tower.apply_translation((x, h / 2, z))
        tower.visual.face_colors = [220, 40, 40, 255]
        scene.add_geometry(tower, node_name=f"t{i}", geom_name=f"t{i}")
    scene.export(path)


@pytest.mark.parametrize("system", ["auto", "reliefboards"])
def test_a_walk_through_a_tiny_town_shows_its_towers(tmp_path, system):
    """A 20-unit glTF town, 4 frames of walkthrough: every frame shows towers. The walker looked
    along the way's first or last few cells and 10 units ahead, half the town: the first frame
    faced the corner the way bends to, and the last stood 1.6 units from the edge looking out of
    the town (towers in 1 of 4 frames); reliefboards walked the straight line through the towers."""
    from conftest import load_png, run_cli

    _tiny_town(tmp_path / "town.glb")
    run_cli("prepare", "scene", tmp_path / "town.glb", "-o", tmp_path / "town.zarr", "-q")
    out = tmp_path / "walk"
    run_cli("render", tmp_path / "town.zarr", "--path", "walkthrough", "--frames", 4, "--size", "160x128", "--system", system,
            *(("--ranks", 2) if system == "reliefboards" else ()), "--out", out, "-q")
    red = []
    for i in range(4):
        img = load_png(out / "frames" / f"{i:05d}.png").astype(int)
        red.append(int(((img[..., 0] > img[..., 1] + 50) & (img[..., 0] > img[..., 2] + 50)).sum()))
    assert min(red) > 0.02 * 160 * 128, red
