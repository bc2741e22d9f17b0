"""What ``prepare scene`` tells its user (walkthrough 5): textures baked to vertex colours,
triangles dropped as degenerate, resumed or started over, refused options and outputs — and
the terrain prepare's resume wording."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh
from conftest import run_cli
from PIL import Image

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
