"""Generated massive scenes of the massive-model papers' character: plant, city, forest.

The source papers replicate real models: the Coal Power Plant (12 M triangles, ~20 000
geometry nodes, 8 levels of hierarchy) 4–8 times, Fatehpur Sikri (4.8 M triangles, 1113
nodes) up to 36 times, a forest of 250 bunnies and trees (25 M triangles). ``generate_scene``
builds one *copy* procedurally as a list of nodes (a shape, a rigid placement with uniform
scale, a colour, a hierarchy path), and places ``copies`` copies on a grid. Replicas are
stored as separate geometry, as in the papers: the data must not fit in memory.

* **plant** — 2×2 halls of 4 storeys; each storey has walls and a floor slab (large, closed:
  heavy occlusion) and a grid of bays of girders (columns, beams), pipe runs (straight
  segments, elbows, flanges) and a vessel. Path: hall, storey, bay row, bay, system,
  assembly, item (+ copy = 8 levels). ~21 600 nodes, ~8.4 M triangles per copy at size 1 (12 copies: 101 M).
* **city** — blocks of red-sandstone buildings: facade bodies with window frames, onion
  domes, columned pavilions (chhatris) and minarets. ~1100 nodes, ~4.1 M triangles per copy.
* **forest** — conifers, broad-leaved trees (lumpy crowns) and a real-world mesh from a
  registry package (pyvista's ``ant.ply``; or, with ``real="bunny"``, the scanned Stanford
  bunny shipped in pymeshlab's wheel, as in M2's paper) scattered on a ground plate. ~250 objects, ~13.7 M
  triangles per copy.

Memory stays bounded however many copies: nodes are generated one at a time, the LOD levels
of each distinct shape are computed once (in its own frame) and cached, and every placed copy
goes straight to the :class:`SceneWriter`, which writes shard by shard and checkpoints.
Everything is a function of (scene, size, copies, seed): deterministic.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Callable

import numpy as np

from ...core.errors import ConfigError
from ..rebuild import is_complete_store, one_writer, rebuild_beside
from ..scene.mesh import Mesh
from ..scene.store import FORMAT
from ..scene.simplify import build_levels, is_closed
from ..scene.writer import SceneWriter
from . import shapes

__all__ = ["SCENE_KINDS", "REAL_MESHES", "Node", "scene_nodes", "generate_scene", "real_mesh", "real_mesh_path"]

SCENE_KINDS = ("plant", "city", "forest")
PATH_DEPTH = {"plant": 8, "city": 6, "forest": 3}


@dataclass(frozen=True)
class Node:
    """One geometry node of a copy: ``shape`` key (kind, params...), placement (3x4 rigid
    rotation+translation, ``scale`` uniform), RGB colour 0..255, hierarchy ``path``."""

    shape: tuple
    placement: tuple  # 12 floats, row-major 3x4
    scale: float
    color: tuple
    path: tuple


def _place(R: np.ndarray, t, scale: float = 1.0) -> tuple:
    return tuple(np.concatenate([R, np.asarray(t, float)[:, None]], 1).ravel().tolist()), float(scale)


def _rot(direction, spin: float = 0.0) -> np.ndarray:
    p = (np.eye(3), np.zeros((0, 3), np.int64), np.eye(3))
    return shapes.orient(p, direction, spin=spin)[0]  # rows: images of the unit axes -> columns of R transposed


def _R(direction, spin: float = 0.0) -> np.ndarray:
    return _rot(direction, spin).T


# -- plant ------------------------------------------------------------------------------
_PIPE_COL = [(230, 190, 40), (60, 150, 70), (50, 100, 190), (190, 50, 40), (200, 200, 200)]


def _plant(size: float, seed: int) -> tuple[list[Node], tuple[float, float]]:
    rng = np.random.default_rng(seed)
    bays = max(1, round(59 * size))
    rows = max(1, round(math.sqrt(bays)))
    cols = max(1, round(bays / rows))
    bay, storey = 6.0, 7.0
    hall_w, hall_d = cols * bay, rows * bay
    nodes: list[Node] = []
    for hall in range(4):
        hx, hy = (hall % 2) * (hall_w + 8), (hall // 2) * (hall_d + 8)
        for fl in range(4):
            z = fl * storey
            nodes += _plant_shell(hall, fl, hx, hy, z, hall_w, hall_d, storey)
            for r in range(rows):
                for c in range(cols):
                    nodes += _plant_bay(rng, (hall, fl, r, c), hx + c * bay, hy + r * bay, z, bay, storey)
    return nodes, (2 * hall_w + 8, 2 * hall_d + 8)


def _plant_shell(hall, fl, hx, hy, z, w, d, h) -> list[Node]:
    t = 0.3
    walls = [((w, t, h), (hx, hy - t, z)), ((w, t, h), (hx, hy + d, z)), ((t, d, h), (hx - t, hy, z)),
             ((t, d, h), (hx + w, hy, z)), ((w, d, t), (hx, hy, z - t))]
    out = []
    for k, (dims, o) in enumerate(walls):
        pl, s = _place(np.eye(3), o)
        col = (200, 190, 170) if k < 4 else (150, 150, 150)
        out.append(Node(("box", *[round(v, 3) for v in dims]), pl, s, col, (hall, fl, 0, 0, 0, 0, k)))
    return out


def _plant_bay(rng, key, x, y, z, bay, h) -> list[Node]:
    hall, fl, r, c = key
    out = []
    steel = (120, 60, 50) if (r + c) % 3 else (110, 115, 125)
    for k, (dx, dy) in enumerate(((0.3, 0.3), (bay - 0.3, 0.3), (0.3, bay - 0.3), (bay - 0.3, bay - 0.3))):
        pl, s = _place(np.eye(3), (x + dx, y + dy, z))
        out.append(Node(("ibeam", h - 0.4), pl, s, steel, (hall, fl, r, c, 0, 0, k)))
    for k, (d, o) in enumerate((((1, 0, 0), (x + 0.3, y + 0.3, z + h - 0.4)), ((1, 0, 0), (x + 0.3, y + bay - 0.3, z + h - 0.4)),
                                ((0, 1, 0), (x + 0.3, y + 0.3, z + h - 0.4)), ((0, 1, 0), (x + bay - 0.3, y + 0.3, z + h - 0.4)))):
        pl, s = _place(_R(d, math.pi / 2), o)
        out.append(Node(("ibeam", bay - 0.6), pl, s, steel, (hall, fl, r, c, 0, 1, k)))
    for run in range(3):
        rad = float(rng.choice([0.12, 0.2, 0.3]))
        col = _PIPE_COL[int(rng.integers(len(_PIPE_COL)))]
        zz = z + 1.2 + run * 1.6
        yy = y + 1.2 + run * 1.5
        seg = bay / 2
        for k in range(2):
            pl, s = _place(_R((1, 0, 0)), (x + k * seg, yy, zz))
            out.append(Node(("pipe", rad, seg), pl, s, col, (hall, fl, r, c, 1, run, k)))
        pl, s = _place(_R((0, 0, 1), math.pi * 0.5 * int(rng.integers(4))), (x + bay - 0.6, yy, zz))
        out.append(Node(("elbow", rad, 0.6), pl, s, col, (hall, fl, r, c, 1, run, 2)))
        for k in range(2):
            pl, s = _place(_R((1, 0, 0)), (x + k * seg - 0.04, yy, zz))
            out.append(Node(("flange", rad), pl, s, (90, 90, 95), (hall, fl, r, c, 1, run, 3 + k)))
    th = float(rng.choice([2.5, 4.0, 5.5]))
    rad = float(rng.choice([0.8, 1.1]))
    pl, s = _place(np.eye(3), (x + bay / 2 + 0.8, y + bay / 2 + 0.6, z + 0.05))
    out.append(Node(("tank", th, rad), pl, s, (235, 235, 228), (hall, fl, r, c, 2, 0, 0)))
    return out


# -- city -------------------------------------------------------------------------------
def _city(size: float, seed: int) -> tuple[list[Node], tuple[float, float]]:
    rng = np.random.default_rng(seed)
    nblock = max(1, round(25 * size))
    side = max(1, math.ceil(math.sqrt(nblock)))
    cell = 40.0
    nodes: list[Node] = []
    for b in range(nblock):
        bx, by = (b % side) * cell, (b // side) * cell
        for k in range(4):
            ox, oy = bx + (k % 2) * 18 + 2, by + (k // 2) * 18 + 2
            nodes += _building(rng, (b // side, b % side, k), ox, oy)
    return nodes, (side * cell, side * cell)


_STONE = [(170, 80, 55), (185, 95, 65), (160, 72, 50)]


def _building(rng, key, x, y) -> list[Node]:
    w = float(rng.choice([10.0, 12.0, 14.0]))
    h = float(rng.choice([6.0, 9.0, 12.0]))
    stone = _STONE[int(rng.integers(3))]
    out = []
    pl, s = _place(np.eye(3), (x, y, 0))
    out.append(Node(("facade", w, h), pl, s, stone, (*key, 0, 0)))
    pl, s = _place(np.eye(3), (x + w / 2, y + w / 2, h))
    out.append(Node(("dome", w * 0.3), pl, s, (235, 228, 215), (*key, 1, 0)))
    for k, (dx, dy) in enumerate(((0.8, 0.8), (w - 0.8, 0.8), (0.8, w - 0.8), (w - 0.8, w - 0.8))):
        kind = ("minaret", h + 4.0) if k % 2 == 0 else ("chhatri", 1.2)
        pl, s = _place(np.eye(3), (x + dx, y + dy, 0 if kind[0] == "minaret" else h))
        out.append(Node(kind, pl, s, stone if kind[0] == "minaret" else (225, 215, 200), (*key, 2, k)))
    for k in range(5):
        pl, s = _place(np.eye(3), (x + 1.5 + k * (w - 3) / 4, y - 1.0, 0))
        out.append(Node(("column", 3.5), pl, s, (200, 180, 160), (*key, 3, k)))
    return out


# -- forest -----------------------------------------------------------------------------
def _forest(size: float, seed: int, real: str = "ant") -> tuple[list[Node], tuple[float, float]]:
    rng = np.random.default_rng(seed)
    n = max(1, round(250 * size))
    side = math.ceil(math.sqrt(n))
    cell = 8.0
    nodes = []
    pl, s = _place(np.eye(3), (0, 0, -0.2))
    nodes.append(Node(("box", side * cell, side * cell, 0.2), pl, s, (95, 120, 60), (0, 0)))
    for i in range(n):
        gx, gy = (i % side + 0.5) * cell, (i // side + 0.5) * cell
        jx, jy = rng.uniform(-1.5, 1.5, 2)
        spin = float(rng.uniform(0, 2 * math.pi))
        kind = int(rng.integers(3))
        variant = int(rng.integers(4))
        if kind == 2:
            shape, col, sc = ("real", real), (150, 90, 45), float(rng.uniform(0.08, 0.12)) * REAL_SCALE[real]
        else:
            shape, col, sc = (("conifer", variant), (40, 100, 45), 1.0) if kind == 0 else (("broadleaf", variant), (70, 130, 40), 1.0)
            sc = float(rng.uniform(0.8, 1.2))
        pl, s = _place(_R((0, 0, 1), spin), (gx + jx, gy + jy, 0), sc)
        nodes.append(Node(shape, pl, s, col, (1 + i // side, i % side)))
    return nodes, (side * cell, side * cell)


_LAYOUTS: dict[str, Callable] = {"plant": _plant, "city": _city, "forest": _forest}


def scene_nodes(kind: str, size: float = 1.0, seed: int = 1, real: str = "ant") -> tuple[list[Node], tuple[float, float]]:
    """The nodes of one copy and the copy's footprint (x, y extent). ``real``: the packaged
    real-world mesh the forest scatters among its trees (``ant``, the default, or ``bunny``:
    the scanned Stanford bunny, as in the paper's forest); the layout is the same either way."""
    if kind not in _LAYOUTS:
        raise ConfigError(f"unknown scene {kind!r}; choose one of {', '.join(SCENE_KINDS)}")
    if not (math.isfinite(size) and size > 0):
        raise ConfigError(f"--size must be a positive number, got {size}")
    if real not in REAL_MESHES:
        raise ConfigError(f"unknown real-world mesh {real!r}; choose one of {', '.join(REAL_MESHES)}")
    return _forest(size, seed, real) if kind == "forest" else _LAYOUTS[kind](size, seed)


# name -> (package, file inside it, scanned?): real-world meshes shipped inside registry packages
REAL_MESHES = {"ant": ("pyvista", "examples/ant.ply", False),
               "bunny": ("pymeshlab", "tests/sample_meshes/bunny.obj", True)}  # the Stanford bunny, 3-D scanned (28 088 v, 56 172 t)
REAL_SCALE = {"ant": 1.0, "bunny": 50.0}  # node scale factor: both about 3 m across in the forest


def real_mesh(name: str = "ant") -> tuple[np.ndarray, np.ndarray]:
    """(vertices f8 (v,3), triangles i8 (t,3)) of a packaged real-world mesh. The ant as in its
    file; the scanned bunny through the scene store's own OBJ ingest (:func:`open_input`, then
    :func:`clean_soup`: redundant vertices merged, degenerate faces dropped — §4's first step),
    turned from its file's y-up to the scenes' z-up."""
    if name == "ant":
        import trimesh

        m = trimesh.load(real_mesh_path(name), process=False, force="mesh")
        return np.asarray(m.vertices, float), np.asarray(m.faces, np.int64)
    from ..scene.soup import clean_soup
    from ..scene.sources import open_input

    soup = open_input(real_mesh_path(name), stream_bytes=1 << 62)
    p, _, _, f = clean_soup(soup.corners(np.arange(len(soup.faces))))
    p = np.asarray(p, np.float64)
    return np.stack([p[:, 0], -p[:, 2], p[:, 1]], axis=1), np.asarray(f, np.int64)


def real_mesh_path(name: str = "ant") -> Path:
    """A real-world mesh shipped inside a registry package (``REAL_MESHES``), found without
    importing the package; ConfigError when it is not installed."""
    import importlib.util

    if name not in REAL_MESHES:
        raise ConfigError(f"unknown real-world mesh {name!r}; choose one of {', '.join(REAL_MESHES)}")
    pkg, rel, _ = REAL_MESHES[name]
    spec = importlib.util.find_spec(pkg)
    if spec is None or not spec.submodule_search_locations:
        raise ConfigError(f"the forest's {name} mesh ships with {pkg}; install it (`pip install {pkg}`)")
    path = Path(list(spec.submodule_search_locations)[0]) / rel
    if not path.exists():
        raise ConfigError(f"{path} is missing from the installed {pkg}; reinstall {pkg}")
    return path


# -- shapes in their own frame ----------------------------------------------------------
_TRUNK = (100, 70, 45)


def _elbow(rad: float, bend: float, seg: int = 24, sweep: int = 12) -> shapes.Part:
    """A quarter torus: tube of radius ``rad`` bent with radius ``bend`` about +z."""
    u = np.linspace(0, math.pi / 2, sweep + 1)[:, None]
    v = np.linspace(0, 2 * math.pi, seg + 1)[None, :]
    n = np.stack([np.cos(v) * np.cos(u), np.cos(v) * np.sin(u), np.sin(v) + 0 * u], -1)
    c = np.stack([bend * np.cos(u), bend * np.sin(u), 0 * u], -1)
    p = c + rad * n
    return p.reshape(-1, 3) - [bend, 0, 0], shapes._grid(sweep, seg), n.reshape(-1, 3)


def _facade(w: float, h: float) -> list:
    parts = [(shapes.box((0, 0, 0), (w, w, h)), None)]
    floors, per = max(1, int(h // 3)), max(1, int(w // 2))
    for f in range(floors):
        z0 = f * 3 + 0.8
        for k in range(per):
            a = (k + 0.5) * w / per
            for side in range(4):
                frame = [shapes.box((a - 0.5, -0.12, z0), (a - 0.4, 0, z0 + 1.6)), shapes.box((a + 0.4, -0.12, z0), (a + 0.5, 0, z0 + 1.6)),
                         shapes.box((a - 0.5, -0.12, z0 - 0.1), (a + 0.5, 0, z0)), shapes.box((a - 0.5, -0.12, z0 + 1.6), (a + 0.5, 0, z0 + 1.75))]
                part = shapes.merge(frame)
                ang = side * math.pi / 2
                R = _R((0, 0, 1), ang)
                centre = np.array([w / 2, w / 2, 0])
                p = (part[0] - centre) @ R.T + centre
                parts.append(((p, part[1], part[2] @ R.T), (225, 200, 170)))
    return parts


def _shape_parts(key: tuple, detail: float = 1.0) -> list:
    """[(Part, colour or None (= the node's))] of a shape key, in the shape's own frame;
    ``detail`` scales the tessellation counts of curved shapes (triangles ≈ detail² × at 1)."""
    def n(c: int, least: int = 3) -> int:
        return max(least, round(c * detail))

    k = key[0]
    if k == "box":
        return [(shapes.box((0, 0, 0), key[1:4]), None)]
    if k == "ibeam":
        return [(shapes.ibeam(key[1], 0.3, 0.2, 0.03, 0.02), None)]
    if k == "pipe":
        return [(shapes.tube(key[2], key[1], n(24), n(8, 1)), None)]
    if k == "elbow":
        return [(_elbow(key[1], key[2], seg=n(24), sweep=n(12, 2)), None)]
    if k == "flange":
        return [(shapes.tube(0.08, key[1] * 1.5, n(24), 1), None)]
    if k == "tank":
        return [(shapes.tank(key[1], key[2], n(64), n(32, 2)), None)]
    if k == "facade":
        return _facade(key[1], key[2])
    if k == "dome":
        r = key[1]
        return [(shapes.tube(r * 0.3, r, n(96), n(8, 1)), None), (shapes.orient(shapes.dome(r, n(96), n(48, 2)), (0, 0, 1), (0, 0, r * 0.3)), None)]
    if k == "minaret":
        h = key[1]
        return [(shapes.tube(h, 0.6, n(48), n(32, 1)), None), (shapes.orient(shapes.tube(0.15, 0.9, n(48), 2), (0, 0, 1), (0, 0, h * 0.7)), None),
                (shapes.orient(shapes.dome(0.7, n(48), n(24, 2)), (0, 0, 1), (0, 0, h)), (235, 228, 215))]
    if k == "chhatri":
        r = key[1]
        cols = [(shapes.orient(shapes.tube(1.5, 0.08, n(12), 2), (0, 0, 1), (x * r * 0.8, y * r * 0.8, 0)), None) for x in (-1, 1) for y in (-1, 1)]
        return cols + [(shapes.box((-r, -r, 1.5), (r, r, 1.7)), None), (shapes.orient(shapes.dome(r * 0.8, n(64), n(32, 2)), (0, 0, 1), (0, 0, 1.7)), None)]
    if k == "column":
        h = key[1]
        return [(shapes.box((-0.3, -0.3, 0), (0.3, 0.3, 0.3)), None), (shapes.orient(shapes.tube(h - 0.6, 0.2, n(32), n(16, 1)), (0, 0, 1), (0, 0, 0.3)), None),
                (shapes.box((-0.3, -0.3, h - 0.3), (0.3, 0.3, h)), None)]
    if k == "conifer":
        v = key[1]
        trunk = (shapes.tube(1.5, 0.25, 24, 4), _TRUNK)
        cones = [(shapes.orient(shapes.cone(3.0 - 0.4 * i, 2.4 - 0.4 * i - 0.1 * v, 128, 48), (0, 0, 1), (0, 0, 1.2 + 1.5 * i)), None) for i in range(5)]
        return [trunk, *cones]
    if k == "broadleaf":
        v = key[1]
        trunk = (shapes.tube(3.0, 0.3, 24, 6), _TRUNK)
        crowns = [(shapes.orient(shapes.blob(2.0, 1.8, 1.6, 96, 192, seed=10 * v + i), (0, 0, 1), (dx, dy, 3.8 + dz)), None)
                  for i, (dx, dy, dz) in enumerate(((0, 0, 0.8), (0.9, 0.4, 0), (-0.7, -0.6, 0.2)))]
        return [trunk, *crowns]
    if k == "real":
        from ..scene.mesh import vertex_normals

        p, t = real_mesh(key[1])
        p = (p - [(p[:, 0].min() + p[:, 0].max()) / 2, (p[:, 1].min() + p[:, 1].max()) / 2, p[:, 2].min()])

        return [((p, t, vertex_normals(p, t).astype(float)), None)]
    raise ValueError(f"unknown shape {key!r}")


@lru_cache(maxsize=4096)
def shape_levels(key: tuple, backend: str = "fast-simplification", detail: float = 1.0) -> tuple[tuple[Mesh, ...], tuple[float, ...], tuple[np.ndarray, ...], bool]:
    """LOD levels of a shape in its own frame (colours are placeholders), their errors, per
    level a boolean mask (v,) of vertices keeping the node's colour, and whether it is closed.
    Cached: a copy has a few hundred distinct shapes."""
    parts = _shape_parts(key, detail)
    p, t, n = shapes.merge([pt for pt, _ in parts])
    fixed = np.concatenate([np.tile(np.array(c if c else (0, 0, 0), np.uint8), (len(pt[0]), 1)) for pt, c in parts])
    own = np.concatenate([np.full(len(pt[0]), c is None) for pt, c in parts])
    col = np.concatenate([fixed, np.where(own, 0, 255).astype(np.uint8)[:, None]], 1)  # alpha marks fixed colours
    mesh = Mesh(p.astype(np.float32), n.astype(np.float32), col, t.astype(np.uint32))
    levels, errors = build_levels(mesh, backend=backend)
    return tuple(levels), tuple(errors), tuple(lv.colors[:, 3] == 0 for lv in levels), is_closed(mesh.indices, mesh.positions)


def place_levels(node: Node, offset: np.ndarray, backend: str = "fast-simplification", detail: float = 1.0) -> tuple[list[Mesh], list[float], bool]:
    """The node's LOD levels in world coordinates (copy ``offset`` added), coloured."""
    levels, errors, own, closed = shape_levels(node.shape, backend, detail)
    m = np.asarray(node.placement, float).reshape(3, 4)
    R, t = m[:, :3], m[:, 3] + offset
    color = np.array([*node.color, 255], np.uint8)
    out = []
    for lv, mask in zip(levels, own):
        c = lv.colors.copy()
        c[mask] = color
        c[:, 3] = 255
        out.append(Mesh((node.scale * (lv.positions.astype(np.float64) @ R.T) + t).astype(np.float32),
                        (lv.normals @ R.T.astype(np.float32)).astype(np.float32), c, lv.indices))
    return out, [e * node.scale for e in errors], closed


def copy_offsets(copies: int, extent: tuple[float, float]) -> np.ndarray:
    """(copies, 3) offsets of the copies on a near-square grid with a 5 % gap."""
    side = math.ceil(math.sqrt(copies))
    i = np.arange(copies)
    return np.stack([(i % side) * extent[0] * 1.05, (i // side) * extent[1] * 1.05, np.zeros(copies)], 1)


@one_writer
def generate_scene(kind: str, out, copies: int = 1, size: float = 1.0, seed: int = 1, overwrite: bool = False,
                   progress=None, backend: str = "fast-simplification", detail: float = 1.0) -> dict:
    """Write scene ``kind`` with ``copies`` replicas to the store ``out``; resumes an
    interrupted run with the same arguments. ``detail`` scales the tessellation of curved
    shapes (node count and hierarchy unchanged). Returns the store attributes."""
    if copies < 1:
        raise ConfigError(f"--copies must be at least 1, got {copies}")
    if not (math.isfinite(detail) and detail > 0):
        raise ConfigError(f"--detail must be a positive number, got {detail}")
    if overwrite and is_complete_store(out, FORMAT):  # built beside it and swapped in: a stopped rebuild loses nothing
        return rebuild_beside(out, FORMAT, lambda p: generate_scene(kind, p, copies, size, seed, False, progress, backend, detail))
    nodes, extent = scene_nodes(kind, size, seed)
    params = {"generator": kind, "copies": int(copies), "size": float(size), "seed": int(seed), "simplifier": backend}
    if detail != 1.0:
        params["detail"] = float(detail)
    w = SceneWriter(out, params, {"source": f"generate scene {kind}", "units": "m"}, path_depth=PATH_DEPTH[kind], overwrite=overwrite)
    offsets = copy_offsets(copies, extent)
    prog = progress or (lambda *a: None)
    skip = w.geometries_done
    prog("objects", min(skip, len(nodes) * copies), len(nodes) * copies)
    for j, node in enumerate(nodes):  # object-major: each distinct node once, all its copies
        if (j + 1) * copies <= skip:
            continue
        for c in range(copies):
            if j * copies + c < skip:
                continue
            levels, errors, closed = place_levels(node, offsets[c], backend, detail)
            gid = w.add_geometry(levels, errors, closed)
            w.add_object(gid, (c, *node.path))
            w.step()
            prog("objects", 1, len(nodes) * copies)
    return w.finish({"copies": int(copies), "extent_per_copy": list(extent)})
