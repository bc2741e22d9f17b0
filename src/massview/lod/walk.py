"""A walking route through a model's free space, for the ``walkthrough`` path.

``walkthrough`` used to walk a straight line along x with a sway, whatever stood there: in a
generated city it went through building walls. :func:`walk_route` plans the walk on the
objects' boxes instead:

1. **obstacles**: the xy footprints of the boxes that reach into the band a walker's body
   occupies (from 30 % of the eye height up to 20 % above the eye), rasterised on a grid of
   about ``cells`` cells along the longer side (a difference array, one ``cumsum`` per axis).
   Boxes lower than the band (kerbs, floors) and boxes whose footprint covers more than a
   quarter of the scene (a ground slab, a hall one walks inside) are not obstacles;
2. **clearance**: each free cell's distance to the nearest obstacle (``distance_transform_edt``);
   cells closer than ``max(1 cell, 30 % of the eye height)`` are not walkable;
3. **route**: the cheapest walkable 8-connected way from the west end (8–15 % of the width; the
   straight walk ran 8–92 %) to the east end (85–92 %), each step costing its length × (1 +
   (4 cells / clearance)²), so the walk keeps to the middle of streets; each end cell costs its
   distance from the scene's middle line (of equal ways the one nearest the middle wins) and
   more per cell of distance from the 8 % (92 %) line than a step can cost (Dijkstra from one source joined to every start
   cell, ``scipy.sparse.csgraph``); where west–east has no way, south–north is tried;
4. **smoothing**: the cell centres resampled every 2 cells along the way and averaged over 5
   neighbours twice, a point kept smoothed only where it is still walkable.

Returns None where no way exists (the caller walks the old straight line then). Planned here
(``lod``, which may use scipy) and handed to :func:`massview.core.paths.load_path` as waypoints.

Before that, :func:`scene_footing` reads from the same boxes what the walker stands on and how
tall it is (a :class:`massview.core.paths.Footing`):

* **ground**: the top of the lowest *floor* — a box covering more than a quarter of the
  scene's footprint, no taller than a quarter of its shorter side, in the lower half of the
  scene (a ground slab, a storey's floor) — else the box's bottom (a city whose buildings
  stand on it). A millimetre model's ground slab at z −350..−250 put the eye 1.7 above −350,
  inside the slab;
* **eye height**: 1.7 units (a person in metres) unless the objects standing on the ground
  are typically more than 50 times that (median box height above 85 units: a model in
  millimetres, not a street); then a quarter of that median height. At most 30 % of the
  scene's height above the ground, as before;
* **walkable**: False where there is no floor and nothing small enough to walk among stands
  on the ground (a single object, a sphere: the walker stood under it, its frames blank), and
  where the scene is too small for a walker: its footprint's shorter side under 10 eye heights
  (a table 2 m long, a scanned statue cut into pieces by ``prepare scene``, a ring 5 m across:
  the walker crawled under the table top, walked inside the scan and inside the ring's tube);
  ``walkthrough`` and ``flyover`` then go round the scene, framed. So they do where
  :func:`walk_route` finds no way between the objects (it walked the straight line through
  them).
"""

from __future__ import annotations

import numpy as np

from ..core.paths import EYE_HEIGHT, Footing, load_path

__all__ = ["fit_path", "scene_footing", "walk_route", "plan_walk", "terrain_ground", "kpatch_ground"]

_BAND = (0.3, 1.2)  # the walker's body, as fractions of the eye height above the ground it stands on
_EDGE = 25.0  # cost per cell an end lies inside the 8 % (92 %) line: above a diagonal step's most, √2 × (1 + 4²)
_MAX_FOOTPRINT = 0.25  # of the scene's footprint: larger boxes are floors or enclosures, not obstacles
_FLOOR_THIN = 0.25  # a floor's height, at most, as a fraction of its shorter side
_TALL = 50.0  # objects standing on the ground typically taller than this many eye heights: not metres
_EYE_OF_TALL = 0.25  # the eye height then, as a fraction of their median height
_WALK_ROOM = 10.0  # a scene's footprint, shorter side, at least this many eye heights to walk in


def fit_path(spec: str, lo, hi, obstacles=None, ground=None):
    """The camera path ``spec`` (a ``--path`` value) fitted to a scene: its box ``lo``..``hi``,
    the objects' boxes ``obstacles`` ((box_lo, box_hi), or None: a terrain) and a terrain's
    ``ground`` (``xy -> z``, ``walkthrough`` only): for a polygon scene, the :func:`scene_footing`
    and, for ``walkthrough``, the way round the objects (:func:`plan_walk`). What the CLI's
    render, M2's job and the Python API each call."""
    footing = None
    if spec in ("walkthrough", "flyover") and obstacles is not None and ground is None:
        footing = scene_footing(lo, hi, *obstacles)
    route = plan_walk(spec, lo, hi, obstacles)
    if spec == "walkthrough" and footing is not None and footing.walkable and route is None:  # no way between the
        footing = Footing(footing.ground, footing.eye, walkable=False)  # objects: round them, not through them
    return load_path(spec, lo, hi, route=route, ground=ground, footing=footing)


def scene_footing(lo, hi, box_lo, box_hi) -> Footing:
    """What a walker in the box ``lo``..``hi`` stands on, how high its eye is and whether there
    is ground to walk on at all, from the objects' boxes ``box_lo``..``box_hi`` ((n, 3) each; see
    the module)."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    blo, bhi = np.asarray(box_lo, np.float64).reshape(-1, 3), np.asarray(box_hi, np.float64).reshape(-1, 3)
    if not len(blo):
        return Footing.of_box(lo, hi)
    side = np.clip(bhi[:, :2] - blo[:, :2], 0, None)
    big = np.prod(side, axis=1) > _MAX_FOOTPRINT * float(np.prod(np.clip(hi[:2] - lo[:2], 0, None)))
    floor = big & (bhi[:, 2] - blo[:, 2] <= _FLOOR_THIN * side.min(axis=1)) & (bhi[:, 2] <= (lo[2] + hi[2]) / 2)
    ground = float(bhi[floor, 2].min()) if floor.any() else float(lo[2])
    room = float(hi[2]) - ground
    stands = ~floor & (blo[:, 2] <= ground + 0.02 * room) & (bhi[:, 2] > ground)
    tall = float(np.median(bhi[stands, 2] - ground)) if stands.any() else 0.0
    eye = _EYE_OF_TALL * tall if tall > _TALL * EYE_HEIGHT else EYE_HEIGHT
    roomy = float(np.min(hi[:2] - lo[:2])) >= _WALK_ROOM * eye  # (before the height cap: a walker's size, not the scene's)
    eye = min(eye, 0.3 * room) if room > 0 else EYE_HEIGHT
    return Footing(ground, eye, walkable=bool(roomy and (floor.any() or (stands & ~big).any())))


def plan_walk(path: str, lo, hi, obstacles) -> np.ndarray | None:
    """The route for the camera path ``path`` (a ``--path`` value) in the box ``lo``..``hi``
    with the objects' boxes ``obstacles`` ((box_lo, box_hi), or None): :func:`walk_route` on
    the :func:`scene_footing`'s ground at its eye height for ``walkthrough`` in a scene with
    objects and ground to walk on, else None (what :func:`massview.core.paths.load_path` takes
    as ``route``)."""
    if path != "walkthrough" or obstacles is None:
        return None
    foot = scene_footing(lo, hi, *obstacles)
    if not foot.walkable:
        return None
    return walk_route(lo, hi, *obstacles, foot.ground + foot.eye, ground_z=foot.ground)


def walk_route(lo, hi, box_lo, box_hi, eye_z: float, cells: int = 256, ground_z: float | None = None) -> np.ndarray | None:
    """xy waypoints (k, 2) of a walk at height ``eye_z`` across the box ``lo``..``hi`` that
    keeps clear of the boxes ``box_lo``..``box_hi`` ((n, 3) each), or None (see the module).
    ``ground_z``: what the walker stands on (default: the box's bottom)."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    box_lo, box_hi = np.asarray(box_lo, np.float64).reshape(-1, 3), np.asarray(box_hi, np.float64).reshape(-1, 3)
    ext = hi[:2] - lo[:2]
    if not (np.all(ext > 0) and np.all(np.isfinite(ext))):
        return None
    h = float(ext.max()) / cells
    n = np.maximum(np.ceil(ext / h).astype(int), 1)
    base = float(lo[2]) if ground_z is None else float(ground_z)
    body = eye_z - base
    band = (base + _BAND[0] * body, base + _BAND[1] * body)
    foot = np.prod(np.clip(box_hi[:, :2] - box_lo[:, :2], 0, None), axis=1)
    hit = (box_hi[:, 2] > band[0]) & (box_lo[:, 2] < band[1]) & (foot <= _MAX_FOOTPRINT * float(np.prod(ext)))
    occ = _footprints(box_lo[hit, :2], box_hi[hit, :2], lo[:2], h, n)
    from scipy.ndimage import distance_transform_edt

    clear = distance_transform_edt(~occ) * h if occ.any() else np.full(occ.shape, np.inf)
    walkable = clear >= max(h, 0.3 * body)
    cost = 1.0 + (4.0 * h / np.maximum(clear, 1e-9)) ** 2
    edges = _edges(walkable, cost)
    for axis in (0, 1):  # west-east, then south-north
        way = _cheapest_way(walkable, edges, axis)
        if way is not None:
            pts = lo[:2] + (np.stack(np.unravel_index(way, walkable.shape), 1) + 0.5) * h
            return _smooth(pts, h, walkable, lo[:2])
    return None


def _footprints(blo: np.ndarray, bhi: np.ndarray, origin: np.ndarray, h: float, n: np.ndarray) -> np.ndarray:
    """(nx, ny) bool: the cells any of the rectangles ``blo``..``bhi`` touches."""
    d = np.zeros((n[0] + 1, n[1] + 1), np.int32)
    if len(blo):
        a = np.clip(np.floor((blo - origin) / h).astype(np.int64), 0, n - 1)
        b = np.clip(np.floor((bhi - origin) / h).astype(np.int64), 0, n - 1) + 1
        for (i, j), s in (((a[:, 0], a[:, 1]), 1), ((b[:, 0], a[:, 1]), -1), ((a[:, 0], b[:, 1]), -1), ((b[:, 0], b[:, 1]), 1)):
            np.add.at(d, (i, j), s)
    return np.cumsum(np.cumsum(d, 0), 1)[:-1, :-1] > 0


def _edges(walkable: np.ndarray, cost: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(from, to, weight) of the 8-connected steps between walkable cells (flat indices; each
    step once), weighted by its length × the mean cost of its two cells."""
    nx, ny = walkable.shape
    idx = np.arange(nx * ny).reshape(nx, ny)
    rows, cols, wts = [], [], []
    for di, dj in ((1, 0), (0, 1), (1, 1), (1, -1)):
        a = (slice(0, nx - di), slice(max(0, -dj), ny - max(0, dj)))
        b = (slice(di, nx), slice(max(0, dj), ny - max(0, -dj)))
        ok = walkable[a] & walkable[b]
        w = np.hypot(di, dj) * (cost[a] + cost[b]) / 2
        rows.append(idx[a][ok])
        cols.append(idx[b][ok])
        wts.append(w[ok])
    return np.concatenate(rows), np.concatenate(cols), np.concatenate(wts)


def _cheapest_way(walkable: np.ndarray, edges: tuple, axis: int) -> np.ndarray | None:
    """Flat cell indices of the cheapest walkable way along :func:`_edges` from the cells at
    8–15 % of ``axis`` to those at 85–92 %, or None."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import dijkstra

    nx, ny = walkable.shape
    size, mid = walkable.shape[axis], (walkable.shape[1 - axis] - 1) / 2
    first, last = int(0.08 * size), int(0.92 * size)
    i, j = np.divmod(np.arange(walkable.size), ny)
    along, across = (i, j) if axis == 0 else (j, i)
    flat = walkable.reshape(-1)
    starts = np.flatnonzero(flat & (along >= first) & (along <= int(0.15 * size)))
    goals = np.flatnonzero(flat & (along >= int(0.85 * size)) & (along <= last))
    if not len(starts) or not len(goals):
        return None
    # Each end cell costs its distance in cells from the middle line (of equal ways the one nearest
    # the middle wins) and _EDGE × its distance from the 8 % (92 %) line (more than walking there
    # can cost, so the walk spans 8–92 % wherever that is open), through one source joined to
    # the start cells and added to the goals' distances.
    src = nx * ny
    r, c, w = edges
    g = coo_matrix((np.concatenate([w, w, np.abs(across[starts] - mid) + _EDGE * (along[starts] - first) + 1.0]),
                    (np.concatenate([r, c, np.full(len(starts), src)]), np.concatenate([c, r, starts]))), shape=(src + 1,) * 2).tocsr()
    dist, pred = dijkstra(g, directed=True, indices=src, return_predecessors=True)
    end = goals[np.argmin(dist[goals] + np.abs(across[goals] - mid) + _EDGE * (last - along[goals]))]
    if not np.isfinite(dist[end]):
        return None
    way = [int(end)]
    while pred[way[-1]] >= 0 and pred[way[-1]] != src:
        way.append(int(pred[way[-1]]))
    return np.array(way[::-1])


def _smooth(pts: np.ndarray, h: float, walkable: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """The way resampled every 2 cells and averaged over 5 neighbours twice, each point kept
    smoothed only where its cell is walkable."""
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    if s[-1] <= 0:
        return pts[:1]
    u = np.linspace(0, s[-1], max(int(s[-1] / (2 * h)), 1) + 1)
    out = np.stack([np.interp(u, s, pts[:, 0]), np.interp(u, s, pts[:, 1])], 1)
    for _ in range(2):
        pad = np.concatenate([out[:1].repeat(2, 0), out, out[-1:].repeat(2, 0)])
        avg = sum(pad[k:k + len(out)] for k in range(5)) / 5
        cell = np.clip(np.floor((avg - origin) / h).astype(int), 0, np.array(walkable.shape) - 1)
        keep = walkable[cell[:, 0], cell[:, 1]]
        out = np.where(keep[:, None], avg, out)
    return out


def terrain_ground(store, z_of_h):
    """``ground(xy (n, 2)) -> z (n,)``: the world height a walker stands on at each xy of a
    terrain store's world (x = col·dx, y = −row·dy; points outside are clamped to the edge):
    ``z_of_h`` (stored height → world z, e.g. the hierarchy's exaggeration) of the highest of
    the four finest samples round the point — never below the full-resolution surface there.
    Blocks are read as needed (one per point at most) and kept for the call."""
    lay = store.layout
    dx, dy = (float(v) for v in store.spacing)
    step = lay.M - 1

    def ground(xy) -> np.ndarray:
        xy = np.asarray(xy, np.float64).reshape(-1, 2)
        col = np.clip(xy[:, 0] / dx, 0, lay.cols - 1)
        row = np.clip(-xy[:, 1] / dy, 0, lay.rows - 1)
        blocks: dict = {}
        out = np.empty(len(xy))
        for k, (r, c) in enumerate(zip(row, col)):
            best = -np.inf
            for rr in {int(np.floor(r)), min(int(np.floor(r)) + 1, lay.rows - 1)}:
                for cc in {int(np.floor(c)), min(int(np.floor(c)) + 1, lay.cols - 1)}:
                    bi, bj = min(rr // step, lay.blocks(0) - 1), min(cc // step, lay.blocks(0) - 1)
                    if (bi, bj) not in blocks:
                        blocks[bi, bj] = store.get_block(0, bi, bj)
                    best = max(best, float(blocks[bi, bj][rr - bi * step, cc - bj * step]))
            out[k] = best
        return np.asarray(z_of_h(out), np.float64)

    return ground


def kpatch_ground(store, exaggeration: float = 1.0):
    """:func:`terrain_ground` in T1's world heights: ``base + Z·(h·vertical_scale − base)``,
    base the lowest scaled height (``lod/zmin/0``, as :func:`.kpatch.world_box` and the
    hierarchy have it), Z the ``exaggeration``; from the store's metadata alone."""
    from functools import partial

    from .columns import heights

    vs = float(store.vertical_scale)
    base = float(np.min(store.height_ranges(0)[0])) * vs
    return terrain_ground(store, partial(heights, base, vs, float(exaggeration)))
