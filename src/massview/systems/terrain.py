"""T1: parallel out-of-core terrain rendering (Goswami, Makhinya, Bösch, Pajarola 2010).

Every rank runs the same K-patch LOD on the same camera. Per frame:

1. blocks that finished loading (RAM cache, worker threads) are uploaded to the GL pool;
2. the ranks agree on the blocks resident everywhere (one Allreduce of a bit per block), so
   the cut — a pure function of (camera, data, agreed residency) — is identical on every rank
   and in the serial reference; missing blocks are requested by priority and their coarser
   ancestors drawn meanwhile (the frame never waits, unless ``loading="complete"``);
3. the front is filtered by the task: sort-first culls it against the tile's sub-frustum;
   sort-last keeps the rank's range R_i by one of the paper's three enumerations (§4.1):
   ``linear`` (M-block origin x), ``quadtree`` (Morton interval of the patch's finest block),
   ``kpatch`` (an equal share of the enumerated visible front).
"""

from __future__ import annotations

import numpy as np

from ..core.camera import Camera
from ..core.config import RenderConfig
from ..core.errors import ConfigError
from ..core.image import Image
from ..core.stats import FrameStats
from ..core.task import Task
from ..data.cache import BlockCache
from ..data.terrain import TerrainStore
from ..data.terrain.colors import shade_block
from ..lod.cull import boxes_in_frustum, screen_rects
from ..lod.kpatch import Front, PatchHierarchy, lookup_blocks, patch_boxes, select_front
from ..parallel.decompose import parse_decomposition, sort_first_tiles, sort_last_ranges
from ..parallel.exchange import agree_all, any_rank
from ..render.context import create_context, renderer_string
from ..render.terrain import BlockPool, TerrainRenderer, pack_block
from ..render.view import ViewRenderer

__all__ = ["TerrainSystem", "SORT_LAST_MODES"]

SORT_LAST_MODES = ("kpatch", "linear", "quadtree")


def _morton(i: np.ndarray, j: np.ndarray) -> np.ndarray:
    out = np.zeros_like(i)
    for b in range(32):
        out |= ((j >> b) & 1) << (2 * b) | ((i >> b) & 1) << (2 * b + 1)
    return out


class TerrainSystem:
    sort_last_modes = SORT_LAST_MODES

    def __init__(self, path, cache_bytes: int = 256 << 20, gpu_bytes: int = 256 << 20, egl_device: int | None = None,
                 loading: str = "async"):
        if loading not in ("async", "complete"):
            raise ConfigError(f"--loading must be async or complete, got {loading!r}")
        self.store = TerrainStore(path)
        self.spec = str(path)
        lay = self.lay = self.store.layout
        self.h = PatchHierarchy(lay, *self.store.lod_arrays(), spacing=self.store.spacing, vscale=self.store.vertical_scale)
        self.cache = BlockCache(self._load, cache_bytes, workers=2)
        self.gpu_bytes, self.loading, self._egl_device = gpu_bytes, loading, egl_device
        self._gl = None
        self.front: Front | None = None
        self._wanted: set = set()
        self._zrange = self.store.attrs.get("height_range") or [0.0, 1.0]
        self._counted = dict(self.cache.counters)  # cache counters at the last frame's report

    # -- data ---------------------------------------------------------------------------
    def _load(self, key):
        lv, i, j = key
        h = self.store.get_block(lv, i, j)
        dx, dy = self.store.spacing
        color = self.store.get_color(lv, i, j)
        if color is None:
            color = shade_block(h, dx * 2**lv, dy * 2**lv, *self._zrange, self.store.vertical_scale)
        return pack_block(h, color, dx * 2**lv, dy * 2**lv, self.store.vertical_scale)

    @property
    def bounds(self):
        return self.h.bounds()

    def _renderers(self):
        if self._gl is None:
            ctx = create_context(self._egl_device)
            pool = BlockPool(ctx, self.lay.M, self.lay.levels, self.lay.L, self.gpu_bytes)
            self._gl = (ctx, pool, TerrainRenderer(ctx, pool, self.lay.k, self.store.spacing, self.store.vertical_scale,
                                                   (self.lay.rows, self.lay.cols)), ViewRenderer(ctx))
        return self._gl

    def renderers(self):
        """This rank's GL objects, created on first use: (context, block pool, terrain renderer,
        view renderer) — for tools drawing beside the system (``bench terrain``'s plain mesh)."""
        return self._renderers()

    @property
    def renderer(self) -> str:
        return renderer_string(self._renderers()[0])

    def _upload_ready(self, keep: set) -> int:
        _, pool, _, _ = self._renderers()
        n = 0
        for key in list(self._wanted):
            if pool.resident[key[0]][key[1], key[2]]:
                self._wanted.discard(key)
                continue
            verts = self.cache.get(key)
            if verts is not None:
                span = (self.lay.M - 1) << key[0]
                if pool.upload(key, verts, (key[1] * span, key[2] * span), 2 ** key[0], keep):
                    self._wanted.discard(key)
                    n += 1
        return n

    def _request(self, lv, bi, bj, prio) -> None:
        for key, p in zip(zip(lv.tolist(), bi.tolist(), bj.tolist()), prio.tolist()):
            self._wanted.add(key)
            self.cache.request(key, p)

    # -- per frame ----------------------------------------------------------------------
    def prepare_frame(self, comm, camera: Camera, cfg: RenderConfig, stats: FrameStats) -> None:
        """Uploads, residency agreement and the LOD front (same on every rank)."""
        _, pool, _, _ = self._renderers()
        self.cache.begin_frame()
        top = (self.lay.L, 0, 0)
        with stats.stage("lod"):
            stalled, best = 0, -1
            while True:
                if not pool.resident[top[0]][0, 0]:
                    self._wanted.add(top)
                    self.cache.request(top, float("inf"))
                keep = self._front_keys()
                uploaded = self._upload_ready(keep)
                stats.count("blocks_uploaded", uploaded)
                flat = np.concatenate([g.ravel() for g in pool.resident])
                agreed = agree_all(comm, flat)
                grids, o = [], 0
                for g in pool.resident:
                    grids.append(agreed[o:o + g.size].reshape(g.shape))
                    o += g.size

                def resident(lv, bi, bj, grids=grids):
                    return lookup_blocks(grids, lv, bi, bj)

                front = select_front(self.h, camera, cfg.tau, resident, self._request) if grids[top[0]][0, 0] else None
                missing = front is None or front.deferred > 0
                if self.loading != "complete" or not any_rank(comm, missing):
                    break
                # complete loading: wait for the requested blocks; give up when the front stops
                # growing (blocks only cycle through budgets too small for this view)
                size = len(front) if front is not None else 0
                stalled, best = (0, size) if size > best else (stalled + 1, best)
                if stalled > 5:
                    raise ConfigError("--loading complete: the blocks this view needs do not fit the budgets "
                                      f"(--cache-mb {self.cache.budget >> 20}, --gpu-mb {self.gpu_bytes >> 20}); raise them or --tau")
                self._wait_for_loads()
        self.front = front if front is not None else Front(*(np.zeros(0, np.int64) for _ in range(13)))
        pool.touch(self._front_keys())
        now = dict(self.cache.counters)  # loads finish between frames: count since the last report
        stats.count("blocks_loaded", now["loads"] - self._counted["loads"])
        stats.count("cache_hits", now["hits"] - self._counted["hits"])
        stats.count("bytes_loaded", now["bytes_loaded"] - self._counted["bytes_loaded"])
        self._counted = now
        stats.count("deferred_splits", self.front.deferred)
        stats.count("front_patches", len(self.front))

    def _front_keys(self) -> set:
        f = self.front
        if f is None or len(f) == 0:
            return set()
        return set(zip(f.level.tolist(), f.bi.tolist(), f.bj.tolist()))

    def _wait_for_loads(self) -> None:
        import time

        t0 = time.monotonic()
        while not self.cache.idle() and time.monotonic() - t0 < 60:
            time.sleep(0.002)

    # -- plan and render ----------------------------------------------------------------
    def _visible(self, camera: Camera, vp=None) -> np.ndarray:
        lo, hi = patch_boxes(self.h, self.front)
        return np.flatnonzero(boxes_in_frustum(lo, hi, camera.frustum_planes(vp)))

    def plan(self, camera: Camera, cfg: RenderConfig, nranks: int) -> list[Task]:
        kind, mode = parse_decomposition(cfg.decomposition, self.sort_last_modes)
        if kind == "sort-last":
            return [Task(i, camera.viewport, data_range=r) for i, r in enumerate(sort_last_ranges(nranks))]
        rects = weights = None
        if mode == "kd":
            vis = self._visible(camera)
            lo, hi = patch_boxes(self.h, self.front.take(vis))
            rects, weights = screen_rects(camera, lo, hi), np.ones(len(vis))
        tiles = sort_first_tiles(mode, nranks, camera.width, camera.height, cfg.grid, rects, weights)
        return [Task(i, vp) for i, vp in enumerate(tiles)]

    def select(self, task: Task, camera: Camera, cfg: RenderConfig) -> np.ndarray:
        """Indices into the front that this task draws."""
        full = task.viewport == camera.viewport
        vis = self._visible(camera, None if full else task.viewport)
        if task.data_range is None:
            return vis
        a, b = task.data_range
        _, mode = parse_decomposition(cfg.decomposition, self.sort_last_modes)
        f = self.front
        if mode == "kpatch":
            n = len(vis)
            return vis[int(round(a * n)): int(round(b * n))]
        if mode == "linear":
            span = (self.lay.M - 1) << f.level[vis]
            x = (f.bj[vis] * span) / float(self.lay.S - 1)
            return vis[(x >= a) & (x < b)]
        span0 = self.lay.M - 1  # quadtree: Morton order of the finest block under the patch centroid
        cx, cy = (f.ax[vis] + f.lx[vis] + f.rx[vis]) // 3, (f.ay[vis] + f.ly[vis] + f.ry[vis]) // 3
        z = _morton(cy // span0, cx // span0) / float(4**self.lay.L)
        return vis[(z >= a) & (z < b)]

    def render(self, task: Task, camera: Camera, cfg: RenderConfig, stats: FrameStats, tint=(0, 0, 0, 0)) -> Image:
        _, _, terrain, view = self._renderers()
        with stats.stage("lod"):
            idx = self.select(task, camera, cfg)
            part = self.front.take(idx)
        stats.count("patches", len(part))
        stats.count("blocks_drawn", len(set(zip(part.level.tolist(), part.bi.tolist(), part.bj.tolist()))))
        return view.render(camera, task.viewport, lambda mvp: terrain.draw(part, mvp, tint), stats, cfg.tile_targets)

    def render_reference(self, camera: Camera, cfg: RenderConfig) -> Image:
        ref_cfg = RenderConfig(width=cfg.width, height=cfg.height, tau=cfg.tau)
        return self.render(Task(0, camera.viewport), camera, ref_cfg, FrameStats(-1, 0))

    def close(self) -> None:
        self.cache.close()
