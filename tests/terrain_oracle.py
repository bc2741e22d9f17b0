"""Rasterisation-free oracles for the terrain LOD and its shading (shared by the fidelity tests).

``drawn_surface`` evaluates the surface the K-patch front draws at every finest sample it
covers (barycentric interpolation on the uniform refinement of every patch), so a test can
project the data point and the drawn point at the same (x, y) and measure the exact pixel
distance between them.
"""

from __future__ import annotations

import numpy as np

from massview.data.terrain import ArraySource, TerrainStore, prepare_terrain
from massview.lod.kpatch import PatchHierarchy, refine_uniform


def real_dem() -> tuple[np.ndarray, tuple[float, float]]:
    """A real DEM shipped with matplotlib: USGS 3 arc-second elevation of the Jacksboro fault
    (Tennessee), 344 × 403 int16 metres; spacing in metres (about 74 × 93 m)."""
    import matplotlib.cbook as cbook

    d = cbook.get_sample_data("jacksboro_fault_dem.npz")
    lat = float((d["ymin"] + d["ymax"]) / 2)
    dx = float(d["dx"]) * 111_320.0 * np.cos(np.radians(lat))
    dy = float(d["dy"]) * 110_574.0
    return np.asarray(d["elevation"], np.float32), (dx, dy)


def make_store(arr: np.ndarray, path, spacing=(30.0, 30.0), block=129, K=17, **kw) -> TerrainStore:
    class Spaced(ArraySource):
        def spacing(self):
            return spacing

    prepare_terrain(Spaced(arr, "test"), path, block=block, K=K, **kw)
    return TerrainStore(path)


def finest(store: TerrainStore) -> np.ndarray:
    lay, M = store.layout, store.layout.M
    out = np.empty((lay.S, lay.S), np.float32)
    for i in range(lay.blocks(0)):
        for j in range(lay.blocks(0)):
            out[i * (M - 1): i * (M - 1) + M, j * (M - 1): j * (M - 1) + M] = store.get_block(0, i, j)
    return out


def hierarchy(store: TerrainStore, exaggeration: float = 1.0) -> PatchHierarchy:
    return PatchHierarchy(store.layout, *store.lod_arrays(), spacing=store.spacing, vscale=store.vertical_scale,
                          exaggeration=exaggeration)


def drawn_surface(front, k: int, heights: np.ndarray, rows: int, cols: int):
    """(x, y, drawn height) for every valid finest sample under every drawn triangle of the
    front (a sample on a shared edge appears once per triangle touching it)."""
    tri = refine_uniform(front.ax, front.ay, front.lx, front.ly, front.rx, front.ry, 2 * k).astype(np.int64)
    lo, hi = tri.min(axis=1), tri.max(axis=1)
    size = hi - lo
    xs, ys, zs = [], [], []
    for w in np.unique(size[:, 0]):
        for h in np.unique(size[:, 1][size[:, 0] == w]):
            sel = (size[:, 0] == w) & (size[:, 1] == h)
            t, o = tri[sel], lo[sel]
            gx, gy = np.meshgrid(np.arange(w + 1), np.arange(h + 1))
            px = o[:, 0:1] + gx.ravel()[None, :]  # (n, P)
            py = o[:, 1:2] + gy.ravel()[None, :]
            a, b, c = t[:, 0], t[:, 1], t[:, 2]
            den = (b[:, 1] - c[:, 1]) * (a[:, 0] - c[:, 0]) + (c[:, 0] - b[:, 0]) * (a[:, 1] - c[:, 1])
            l1 = ((b[:, 1] - c[:, 1])[:, None] * (px - c[:, 0:1]) + (c[:, 0] - b[:, 0])[:, None] * (py - c[:, 1:2])) / den[:, None]
            l2 = ((c[:, 1] - a[:, 1])[:, None] * (px - c[:, 0:1]) + (a[:, 0] - c[:, 0])[:, None] * (py - c[:, 1:2])) / den[:, None]
            l3 = 1 - l1 - l2
            inside = (l1 >= -1e-12) & (l2 >= -1e-12) & (l3 >= -1e-12) & (px < cols) & (py < rows)
            ha, hb, hc = (heights[v[:, 1], v[:, 0]].astype(np.float64)[:, None] for v in (a, b, c))
            z = l1 * ha + l2 * hb + l3 * hc
            xs.append(px[inside])
            ys.append(py[inside])
            zs.append(z[inside])
    return np.concatenate(xs), np.concatenate(ys), np.concatenate(zs)


def screen_errors(h: PatchHierarchy, camera, front, heights: np.ndarray) -> np.ndarray:
    """Exact pixel distance between each visible finest sample and the drawn surface point
    at the same (x, y) (both through the camera's projection, float64)."""
    lay = h.lay
    x, y, s = drawn_surface(front, lay.k, heights, lay.rows, lay.cols)
    data = heights[y, x].astype(np.float64)
    Z, vs, base = h.exaggeration, h.vs, h.base

    def world(z):
        return np.stack([x * h.dx, -y * h.dy, base + Z * (z * vs - base)], axis=1)

    p, dp = camera.project(world(data))
    q, dq = camera.project(world(s))
    vis = (dp > camera.near) & (dq > camera.near) & (p[:, 0] >= 0) & (p[:, 0] <= camera.width) & (p[:, 1] >= 0) & (p[:, 1] <= camera.height)
    return np.linalg.norm(p - q, axis=1)[vis]


class Solo:
    """The one-rank communicator the systems' collectives accept."""

    def Get_size(self):
        return 1

    def Get_rank(self):
        return 0

    def allreduce(self, v, op=None):
        return v


def render_view(system, camera, **cfg):
    """One frame of ``system`` (a TerrainSystem) through its real GL path: an Image."""
    from massview.core.config import RenderConfig
    from massview.core.stats import FrameStats
    from massview.core.task import Task

    cfg = RenderConfig(width=camera.width, height=camera.height, loading="complete", **cfg)
    system.prepare_frame(Solo(), camera, cfg, FrameStats(0, 0))
    return system.render(Task(0, camera.viewport), camera, cfg, FrameStats(0, 0))


def unproject(camera, depth: np.ndarray) -> np.ndarray:
    """World (h, w, 3) points of every pixel centre at its depth-buffer value (GL [0, 1])."""
    h, w = depth.shape
    px, py = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    ndc = np.stack([px / w * 2 - 1, 1 - py / h * 2, depth.astype(np.float64) * 2 - 1, np.ones_like(px)], axis=-1)
    p = ndc @ np.linalg.inv(camera.view_projection()).T
    return p[..., :3] / p[..., 3:]


def luminance(color: np.ndarray) -> np.ndarray:
    c = color[..., :3].astype(np.float64)
    return 0.299 * c[..., 0] + 0.587 * c[..., 1] + 0.114 * c[..., 2]


def isolated_bright(lum: np.ndarray, threshold: float = 60.0) -> int:
    """Pixels brighter than the median of their 3 × 3 neighbourhood by more than ``threshold``."""
    p = np.pad(lum, 1, mode="edge")
    h, w = lum.shape
    stack = np.stack([p[dy:dy + h, dx:dx + w] for dy in range(3) for dx in range(3)])
    return int(np.count_nonzero(lum - np.median(stack, axis=0) > threshold))
