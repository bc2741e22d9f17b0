"""M2 keeps the scene store's precision: a scene at UTM-like coordinates (500000, 4000000, 250)
gives the same Reliefboards (maps and frames) and the same frames as the copy at the origin.
The store keeps each object in float32 about its own centre with a float64 transform; M2 used to
build float32 *world* positions from it (0.25-0.5 m steps at 4e6: unit spheres turned into
stair-stepped lumps). Now every float32 coordinate is relative to a nearby point — an M2 object's
box centre (backends), the scene's centre (the visualization rank's buffer), a board's centre —
and the large translations cancel in float64 matrices, as M1 draws camera-relative."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh
from PIL import Image

from conftest import load_png, run_cli, save_diff
from massview.core.camera import Camera
from massview.data.scene import SceneStore
from massview.data.scene.ingest import IngestParams, prepare_scene
from massview.lod.clusters import FEASIBLE, ClusterParams
from massview.systems.boardscene import objects_from_store
from test_scene_precision import OFFSET, write_ply64

gl = pytest.importorskip("massview.render.boards")
from massview.render.context import create_context  # noqa: E402
from massview.render.framebuffer import Framebuffer  # noqa: E402
from massview.render.meshes import MeshRenderer  # noqa: E402

W, H = 240, 180


def _balls() -> tuple[np.ndarray, np.ndarray]:
    """Six unit icospheres (1280 triangles each) on a 3 x 2 grid, 4 apart."""
    ball = trimesh.creation.icosphere(3)
    v, f = [], []
    for k in range(6):
        v.append(np.asarray(ball.vertices) + [4.0 * (k % 3), 4.0 * (k // 3), 0.3 * k])
        f.append(np.asarray(ball.faces) + k * len(ball.vertices))
    return np.concatenate(v), np.concatenate(f)


@pytest.fixture(scope="module")
def stores(tmp_path_factory):
    root = tmp_path_factory.mktemp("m2prec")
    v, f = _balls()
    out = {}
    for name, off in (("origin", np.zeros(3)), ("far", OFFSET)):
        write_ply64(root / f"{name}.ply", v + off, f)
        a = prepare_scene([root / f"{name}.ply"], root / f"{name}.scene", IngestParams(object_triangles=1500))
        assert a["objects"] == 6 and a["triangles"] == len(f)
        out[name] = root / f"{name}.scene"
    return out


def _objects(path):
    obj = objects_from_store(SceneStore(path), ClusterParams(t_nz=100, p=64, r_y=H, min_triangles=100))
    order = np.lexsort(np.round(obj.centers - obj.centers.min(0), 3).T[::-1])  # the same objects in the same order
    return obj, order


def test_boards_and_originals_at_utm_coordinates_equal_those_at_the_origin(stores, tmp_path):
    ctx = create_context()
    builder = gl.BoardBuilder(ctx)
    fb = Framebuffer(ctx, W, H)
    direction = np.array([0.6, -0.7, -0.35])
    got = {}
    for name, off in (("origin", np.zeros(3)), ("far", OFFSET)):
        obj, order = _objects(stores[name])
        assert obj.count == 6 and (obj.status == FEASIBLE).all()
        boards = [builder.build(int(i), *obj.mesh(i), direction=direction, size=64, box_lo=obj.box_lo[i], box_hi=obj.box_hi[i],
                                origin=obj.origins[i]) for i in order]
        lo, hi = obj.bounds
        c = (lo + hi) / 2
        cam = Camera.look_at(c - direction * 9, c, fovy=50.0, near=1.0, far=60.0, width=W, height=H)
        meshes = MeshRenderer(ctx, *obj.concatenated())
        relief = gl.BoardRenderer(ctx)
        for b in boards:
            relief.put(b)
        frames = []
        for draw in (lambda mvp: meshes.draw(np.arange(obj.count), mvp), lambda mvp: relief.draw(order, mvp)):
            fb.begin()
            draw(cam.view_projection())
            ctx.finish()
            frames.append(fb.read(cam.viewport).color[..., :3].copy())
        meshes.release()
        relief.release()
        got[name] = (boards, frames, np.asarray(c) - off)
    builder.release()
    fb.release()
    np.testing.assert_allclose(got["far"][2], got["origin"][2], atol=1e-6)
    for a, b in zip(got["origin"][0], got["far"][0]):
        assert np.allclose(np.asarray(b.frame.center) - OFFSET, a.frame.center, atol=1e-6) and b.frame.radius == pytest.approx(a.frame.radius)
        same = np.count_nonzero(a.stencil != b.stencil)
        assert a.stencil.sum() > 800 and same <= 2, f"{same} stencil pixels differ"  # (a pixel on an edge may flip)
        both = a.stencil & b.stencil
        da = np.zeros(a.stencil.shape, np.float32)
        db = da.copy()
        da[a.stencil], db[b.stencil] = a.distance, b.distance
        assert np.abs(da[both] - db[both]).max() < 2e-3 * a.frame.radius  # (0.25 m steps would be 0.25 here)
    for k, (a, b) in enumerate(zip(got["origin"][1], got["far"][1])):
        Image.fromarray(np.concatenate([a, b], 1)).save(tmp_path / f"{('originals', 'boards')[k]}.png")
        assert np.count_nonzero(np.any(a != a[0, 0], axis=2)) > 0.15 * W * H  # the balls fill part of the frame
        equal = np.all(np.abs(a.astype(int) - b.astype(int)) <= 1, axis=2).mean()
        if equal < 0.998:
            save_diff(a, b, tmp_path / f"diff{k}.png")
        assert equal >= 0.998, f"{('originals', 'boards')[k]}: only {equal:.2%} of the pixels equal (diff: {tmp_path / f'diff{k}.png'})"


@pytest.mark.mpi
def test_m2_frames_at_utm_coordinates_equal_those_at_the_origin(stores, tmp_path):
    """The whole system (a visualization rank and a backend under mpiexec, boards waited for so
    the frames are deterministic): far objects drawn from boards, near ones as originals."""
    frames = {}
    for name in ("origin", "far"):
        run_cli("render", stores[name], "--system", "reliefboards", "--ranks", 2, "--frames", 4, "--path", "forward",
                "--size", f"{W}x{H}", "--tnz", 1500, "--board-px", 64, "--min-triangles", 100, "--wait-boards", "-q",
                "--out", tmp_path / name)
        frames[name] = [load_png(p) for p in sorted((tmp_path / name / "frames").glob("*.png"))]
        s = json.loads((tmp_path / name / "summary.json").read_text())
        assert s["tris_board_mean"] > 0 and s["tris_near_mean"] > 0  # frames of boards and originals
    assert len(frames["origin"]) == len(frames["far"]) == 4
    for k, (a, b) in enumerate(zip(frames["origin"], frames["far"])):
        equal = np.all(np.abs(a.astype(int) - b.astype(int)) <= 1, axis=2).mean()
        if equal < 0.995:
            save_diff(a, b, tmp_path / f"diff{k}.png")
        assert equal >= 0.995, f"frame {k}: only {equal:.2%} of the pixels equal (diff: {tmp_path / f'diff{k}.png'})"
