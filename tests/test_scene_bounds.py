"""Scene bounds from metadata (issue 20): the parent of a ``ranks=N`` job fits paths and clip
planes with :func:`massview.api.scene_bounds`, which reads store metadata only. Its box must be
exactly (bit for bit) the box the opened system reports, for every kind of scene, and getting
it must open neither a GL context nor the K-patch hierarchy."""

import numpy as np
import pytest

import massview as mv
from massview import api
from massview.core.config import RenderConfig
from massview.data.generators.scenes import generate_scene
from massview.systems import open_system


def _same(a, b):
    for x, y in zip(a, b):
        x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
        assert x.shape == (3,) and np.array_equal(x, y), (x, y)


@pytest.fixture(scope="module")
def plant(tmp_path_factory):
    out = tmp_path_factory.mktemp("plant") / "p.zarr"
    generate_scene("plant", out, copies=2, size=0.01)
    return out


def test_terrain_bounds_from_metadata_equal_the_systems(terrain_store):
    system = open_system(str(terrain_store), RenderConfig())
    try:
        _same(api.scene_bounds(str(terrain_store), "terrain"), system.bounds)
    finally:
        system.close()


def test_roettger_bounds_from_metadata_equal_the_systems(terrain_store):
    system = open_system(str(terrain_store), RenderConfig(system="roettger"))
    system.infos = system.layer_infos()  # what setup broadcasts from the computation leader
    _same(api.scene_bounds(str(terrain_store), "terrain", "roettger"), system.bounds)


def test_scene_store_and_objects_bounds_equal_the_systems(plant):
    for spec, kind in ((str(plant), "scene"), ("builtin:objects?n=50&seed=3", "objects")):
        system = open_system(spec, RenderConfig())
        try:
            _same(api.scene_bounds(spec, kind), system.bounds)
        finally:
            if hasattr(system, "close"):
                system.close()


def test_scene_bounds_open_no_gl_and_no_hierarchy(terrain_store, plant, monkeypatch):
    """``Scene.bounds`` and the paths fitted with it never build the hierarchy or a GL context."""
    from massview.lod import kpatch
    from massview.render import context

    def refuse(*a, **k):
        raise AssertionError("opened while only the bounds were asked for")

    monkeypatch.setattr(kpatch.PatchHierarchy, "__init__", refuse)
    monkeypatch.setattr(context.moderngl, "create_standalone_context", refuse)
    for spec in (str(terrain_store), str(plant), "builtin:objects?n=20"):
        scene = mv.open_scene(spec)
        lo, hi = scene.bounds
        assert np.all(hi >= lo) and scene._system is None
        assert len(mv.path("flyover", scene, frames=2, size=(64, 48))) == 2
