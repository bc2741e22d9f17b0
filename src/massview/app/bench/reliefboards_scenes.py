"""Scenes and camera paths of `massview bench reliefboards` (Süß et al. 2010, §7.2): the paper's
forest, plant and 60 M forest generated at a triangle scale, the forest's circle and the plant's
fixed loop. The scaling rules are stated in :mod:`massview.app.bench.reliefboards`."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

__all__ = ["PAPER", "scaled_scene", "measure_rate", "arc_path", "plant_loop_path"]

PAPER = {"forest": 25e6, "plant": 12.4e6, "forest60": 60e6}  # triangles (§7.2, §7.5)
LAYOUT = {"forest": ("forest", 1.0), "plant": ("plant", 0.15), "forest60": ("forest", 2.4)}  # generator kind, size at s = 0.1
GROWS = {"plant"}  # its generator size follows s (the plant's density is fixed); the forests keep their object counts
REAL = {"forest": "bunny", "forest60": "bunny"}  # the scanned Stanford bunny (pymeshlab's wheel) among the trees, as in the paper


def scaled_scene(item: str, scale: float, workdir: Path) -> tuple[Path, dict]:
    """The generated scene of ``item`` with ``scale`` × the paper's triangles: per object the
    generator's simplification level that keeps the running total on target (see the module
    docstring). Written once per (item, scale); returns the store and its figures."""
    from ...data.generators.scenes import PATH_DEPTH, place_levels, scene_nodes, shape_levels
    from ...data.scene.writer import SceneWriter

    kind, size = LAYOUT[item]
    size = size * scale / 0.1 if item in GROWS else size
    path = workdir / (f"{item}-s{scale:g}" + (f"-{REAL[item]}" if item in REAL else "") + ".zarr")
    meta = path.with_suffix(".json")
    if meta.exists() and (path / "zarr.json").exists() and '"complete": true' in (path / "zarr.json").read_text():
        return path, json.loads(meta.read_text())
    t0 = time.perf_counter()
    nodes, _ = scene_nodes(kind, size, 1, real=REAL.get(item, "ant"))
    full = [len(shape_levels(n.shape)[0][0].indices) for n in nodes]  # level-0 triangles (shapes cached)
    ratio = PAPER[item] * scale / sum(full)
    w = SceneWriter(path, {"generator": kind, "size": size, "scale": scale, "item": item},
                    {"source": f"bench reliefboards {item}", "units": "m"}, path_depth=PATH_DEPTH[kind], overwrite=True)
    total = target = 0.0
    for node, n0 in zip(nodes, full):
        levels, errors, closed = place_levels(node, np.zeros(3))
        target += n0 * ratio
        counts = np.array([len(lv.indices) for lv in levels])
        k = int(np.argmin(np.abs(total + counts - target)))
        total += counts[k]
        w.add_object(w.add_geometry(levels[k:], errors[k:], closed), (0, *node.path))
        w.step()
    w.finish({"scale": scale})
    info = {"objects": len(nodes), "triangles": int(total), "unscaled_triangles": int(sum(full)), "write_s": round(time.perf_counter() - t0, 1)}
    meta.write_text(json.dumps(info))
    print(f"wrote {path}: {len(nodes)} objects, {total / 1e6:.2f} M triangles ({sum(full) / 1e6:.2f} M at level 0) in {info['write_s']} s", flush=True)
    return path, info


def measure_rate(scene: Path, width: int, height: int, repeat: int = 2) -> float:
    """Triangles per second drawing every object of ``scene`` as original (this machine, now)."""
    from ...core.camera import Camera
    from ...core.stats import FrameStats
    from ...lod.clusters import ClusterParams
    from ...render.context import create_context
    from ...render.meshes import MeshRenderer
    from ...render.view import ViewRenderer
    from ...systems.boardscene import open_board_objects

    obj = open_board_objects(str(scene), ClusterParams(t_nz=1, r_y=height))
    lo, hi = obj.bounds
    c, ext = (lo + hi) / 2, float(np.linalg.norm(hi - lo))
    cam = Camera.look_at(c + np.array([0.6, -0.7, 0.4]) * ext, c, near=ext * 0.01, far=ext * 4, width=width, height=height)
    ctx = create_context()
    meshes, view = MeshRenderer(ctx, *obj.concatenated()), ViewRenderer(ctx)
    times = []
    for _ in range(repeat + 1):
        st = FrameStats(frame=0, rank=0)
        view.render(cam, cam.viewport, lambda mvp: meshes.draw(np.arange(obj.count), mvp), st)
        times.append(st.times_ms["draw"] + st.times_ms["readback"])
    meshes.release()
    view.release()
    return float(obj.triangles.sum()) / (min(times[1:]) / 1e3)


def arc_path(scene: Path, arc_deg: float, out: Path, radius: float = 0.75, height: float = 0.25) -> Path:
    """A keyframe path circling the scene's centre at ``radius`` × its half diagonal,
    ``height`` × it above the centre, looking at the centre, over ``arc_deg`` degrees
    (keyframes every 2°)."""
    from ...data.scene import SceneStore

    lo, hi = SceneStore(scene).bounds
    c, r = (np.asarray(lo) + np.asarray(hi)) / 2, float(np.linalg.norm(np.asarray(hi) - np.asarray(lo))) / 2
    n = max(2, int(arc_deg / 2) + 1)
    keys = []
    for i, a in enumerate(np.radians(np.linspace(0.0, arc_deg, n))):
        pos = c + np.array([np.cos(a) * radius * r, np.sin(a) * radius * r, height * r])
        keys.append({"time": i / (n - 1), "position": pos.tolist(), "look_at": c.tolist()})
    out.write_text(json.dumps({"keyframes": keys, "fovy": 45.0, "near": r * 0.005, "far": r * 4}))
    return out


def plant_loop_path(bounds, out: Path, steps: int = 600, frames: int | None = None, first: int = 0) -> Path:
    """The plant's fixed path (the paper's Fig. 8 is not in its text, which says only that the
    path is traversed in 6000 steps at a uniform speed and that boards pay where many objects
    are in view): a closed loop that starts outside the plant's west side above its top, crosses
    over its middle looking ahead and down into it, swings round outside its east and north
    sides with the whole plant in view and returns west; the camera looks at a point between the
    plant's centre and 0.4 half-diagonals ahead on the path. The loop is cut into ``steps`` steps
    of equal length (uniform speed) and the file holds steps ``first`` .. ``first + frames - 1``
    as keyframes one time unit apart, so ``--frames frames`` renders exactly those steps.
    ``bounds``: the plant's box (lo, hi), world units."""
    from ...core.paths import KeyframePath

    lo, hi = (np.asarray(v, np.float64) for v in bounds)
    c, ext = (lo + hi) / 2, hi - lo
    r, top = float(np.linalg.norm(ext)) / 2, hi[2]
    way = np.array([[-0.85, -0.3, 0.45], [-0.2, -0.08, 0.3], [0.35, 0.1, 0.3], [0.85, 0.25, 0.45], [0.55, 0.85, 0.55],
                    [-0.3, 0.8, 0.5], [-0.85, -0.3, 0.45]])
    pos = np.column_stack([c[0] + way[:, 0] * ext[0], c[1] + way[:, 1] * ext[1], top + way[:, 2] * r])
    times = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pos, axis=0), axis=1))])
    loop = KeyframePath(times, pos, np.repeat(c[None], len(pos), 0), None, 45.0, r * 0.002, r * 6)  # positions only are used
    dense_t = np.linspace(0.0, 1.0, 3001)  # arc length by 3000 chords
    dense = np.array([loop.pose(t)[0] for t in dense_t])
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(dense, axis=0), axis=1))])
    frames = steps if frames is None else frames
    at = np.interp((np.arange(first, first + frames + 1) % steps) * arc[-1] / steps, arc, dense_t)
    eye = np.array([loop.pose(t)[0] for t in at])
    ahead = np.diff(eye, axis=0)
    ahead /= np.maximum(np.linalg.norm(ahead, axis=1, keepdims=True), 1e-12)
    look = 0.55 * c + 0.45 * (eye[:-1] + ahead * 0.4 * r)
    keys = [{"time": float(i), "position": p.tolist(), "look_at": q.tolist()} for i, (p, q) in enumerate(zip(eye[:-1], look))]
    out.write_text(json.dumps({"keyframes": keys, "fovy": 45.0, "near": r * 0.002, "far": r * 6}))
    return out
