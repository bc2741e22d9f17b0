"""The web viewer's first view (``massview view STORE``): a scene store is framed whole and
centred; a terrain and builtin:objects start where they did, at the start of ``flyover``. The viewer runs for real
(one rank) and its first streamed JPEG is read over the WebSocket, as a browser gets it.

Before, every scene started at ``flyover(0)``: low over the west end looking along +x. A glTF
assembly stood cut at the right edge (drawn pixels' centre at x ≈ 0.8 of the width) and a
single sphere showed a corner at the bottom right."""

from __future__ import annotations

import io
import json
import re
import socket
import subprocess
import sys
import time

import numpy as np
import pytest
import trimesh
from PIL import Image

from conftest import clean_env, run_cli, stop_job

BG = np.array([22, 26, 34])  # massview.core.image.BACKGROUND_RGBA: a scene's empty pixels
W, H = 192, 144


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def first_frame(store, *extra, stats: list | None = None) -> np.ndarray:
    """RGB (H, W, 3) of the first view ``massview view STORE --ranks 1 [extra]`` streams, once
    its geometry is in (loads are asynchronous: the first frames draw what is resident): the
    first frame equal to the two before it, from the fifth on. ``stats`` receives the frames'
    stats messages."""
    from websockets.sync.client import connect

    port = _free_port()
    proc = subprocess.Popen([sys.executable, "-m", "massview", "view", str(store), "--ranks", "1", "--port", str(port),
                             "--size", f"{W}x{H}", *map(str, extra)], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            env=clean_env(), start_new_session=True)
    try:
        line, t0 = "", time.monotonic()
        while "serving http" not in line:
            line = proc.stdout.readline()
            assert line or proc.poll() is None, "viewer exited early"
            assert time.monotonic() - t0 < 120
        url = re.search(r"http://(\S+?)/", line).group(1)
        frames: list[np.ndarray] = []
        with connect(f"ws://{url}/ws", open_timeout=60) as ws:
            while len(frames) < 5 or not (np.array_equal(frames[-1], frames[-2]) and np.array_equal(frames[-1], frames[-3])):
                assert len(frames) < 200, "the first view never settled"
                msg = ws.recv(timeout=120)
                if isinstance(msg, bytes):
                    frames.append(np.asarray(Image.open(io.BytesIO(msg)).convert("RGB")))
                else:
                    doc = json.loads(msg)
                    assert doc["type"] in ("hello", "stats", "role")
                    if stats is not None and doc["type"] == "stats":
                        stats.append(doc)
        return frames[-1]
    finally:
        stop_job(proc)


def drawn(img: np.ndarray) -> np.ndarray:
    """Pixels that are not the background (JPEG: a tolerance)."""
    return np.abs(img.astype(int) - BG).sum(axis=2) > 24


def _assembly(path) -> None:
    """A glTF (y up) of five plates along x and a shaft through them, ~260 × 60 × 90 units."""
    scene = trimesh.Scene()
    for i in range(5):
        b = trimesh.creation.box([40, 60, 30])
        b.visual.face_colors = [60 + 30 * i, 100, 200, 255]
        scene.add_geometry(b, node_name=f"p{i}", geom_name=f"p{i}",
                           transform=trimesh.transformations.translation_matrix([i * 50.0, 30 * np.sin(i), 10 * i]))
    shaft = trimesh.creation.cylinder(radius=15, height=260)
    shaft.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0]))
    shaft.apply_translation([100, 0, 0])
    shaft.visual.face_colors = [200, 200, 50, 255]
    scene.add_geometry(shaft, node_name="shaft", geom_name="shaft")
    path.write_bytes(trimesh.exchange.gltf.export_glb(scene))


def _sphere(path) -> None:
    s = trimesh.creation.icosphere(subdivisions=4, radius=50)
    s.visual.face_colors = [200, 60, 40, 255]
    s.export(path)


@pytest.mark.parametrize("make,name", [(_assembly, "asm.glb"), (_sphere, "sphere.ply")])
def test_the_viewer_frames_a_polygon_scene_whole_and_centred(tmp_path, make, name):
    make(tmp_path / name)
    run_cli("prepare", "scene", tmp_path / name, "-o", tmp_path / "s.scene", "-q")
    img = first_frame(tmp_path / "s.scene")
    Image.fromarray(img).save(tmp_path / "first.png")
    d = drawn(img)
    ys, xs = np.nonzero(d)
    frac = d.mean()
    cx, cy = (xs.min() + xs.max()) / 2 / W, (ys.min() + ys.max()) / 2 / H
    print(f"{name}: {frac:.3f} drawn, its extent centred at ({cx:.2f}, {cy:.2f})")
    assert frac > 0.08, f"{frac:.3f} of the frame drawn"
    assert abs(cx - 0.5) < 0.1 and abs(cy - 0.5) < 0.1, f"drawn pixels' extent centred at ({cx:.2f}, {cy:.2f})"
    edge = np.concatenate([d[:, :2].ravel(), d[:, -2:].ravel(), d[:2].ravel(), d[-2:].ravel()])
    assert edge.mean() < 0.01, f"the scene is cut at the frame's edge ({edge.mean():.3f} of the border drawn)"


def test_a_terrain_and_builtin_objects_start_where_they_did(terrain_store):
    """A terrain's and builtin:objects' first view is still the start of flyover (the same
    camera, bit for bit): wide flat fields, where it looks along the field."""
    from massview.api import scene_bounds
    from massview.app.view_cmd import start_camera
    from massview.core.paths import load_path

    for spec, kind in ((str(terrain_store), "terrain"), ("builtin:objects?n=300&seed=4", "objects")):
        lo, hi = scene_bounds(spec, kind)
        assert start_camera(kind, lo, hi, W, H) == load_path("flyover", lo, hi).camera(0.0, W, H)


def test_an_exaggerated_terrain_starts_above_its_relief_and_the_eye_follows_the_slider(terrain_store):
    """walk7 H1: ``view STORE --exaggeration 5`` started at flyover's start fitted to the 1× box,
    under the relief drawn at 5× (its underside hanging from the top of the frame); and raising
    the exaggeration in the browser left the eye where it was, underground. Now the start is
    flyover's at the exaggeration drawn (as ``render``'s), and a new exaggeration moves the eye
    with the relief and refits the far plane to it."""
    from massview.api import open_scene
    from massview.app.viewer import ViewerState
    from massview.app.viewer.state import MessageError
    from massview.core.paths import exaggerated_box, load_path

    scene = open_scene(str(terrain_store))
    stats: list = []
    img = first_frame(terrain_store, "--exaggeration", 5, stats=stats)
    x, y, z = stats[-1]["position"]
    assert z > float(scene.ground(5.0)(np.array([[x, y]]))[0]), "the first view is under the relief"
    assert drawn(img)[H // 2:].mean() > 0.5  # the ground below the horizon, not sky
    lo, hi = scene.bounds
    start = load_path("flyover", lo, hi).camera(0.0, W, H)
    state = ViewerState(start, {"exaggeration": 1.0}, {"decomposition": [], "compositor": []}, 1.0, (lo, hi))
    z1 = start.position[2]
    assert z1 > float(scene.ground(1.0)(np.array([start.position[:2]]))[0])
    f1 = np.array(state.camera().forward)
    state.apply('{"type": "settings", "exaggeration": 5}')
    cam = state.camera()
    f5 = np.array(cam.forward)  # walk8 L3: the view turns with the stretch, towards the same point of the relief
    assert np.isclose(f5[2] / np.hypot(*f5[:2]), 5 * f1[2] / np.hypot(*f1[:2]))
    assert np.isclose(cam.position[2], lo[2] + (z1 - lo[2]) * 5)
    assert cam.position[2] > float(scene.ground(5.0)(np.array([cam.position[:2]]))[0])
    far_corner = max(np.linalg.norm(np.array(c) - cam.position) for c in np.array(np.meshgrid(*zip(*exaggerated_box(lo, hi, 5)))).T.reshape(-1, 3))
    assert cam.far > far_corner
    with pytest.raises(MessageError, match="unknown setting"):  # a message with an unknown key changes nothing
        state.apply('{"type": "settings", "exaggeration": 2, "bogus": 1}')
    assert state.camera().position == cam.position
    state.apply('{"type": "settings", "exaggeration": 1}')
    assert np.isclose(state.camera().position[2], z1) and np.allclose(state.camera().forward, f1)
