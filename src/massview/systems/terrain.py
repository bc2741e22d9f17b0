"""T1: parallel out-of-core terrain rendering (Goswami, Makhinya, Bösch, Pajarola 2010).

Every rank runs the same K-patch LOD on the same camera. Per frame:

1. blocks that finished loading (RAM cache, worker threads) are uploaded to the GL pool;
2. the ranks agree on the blocks resident everywhere (one Allreduce of a bit per block), so
   the cut — a pure function of (camera, data, agreed residency) — is identical on every rank
   and in the serial reference; missing blocks are requested by priority and their coarser
   ancestors drawn meanwhile (the frame never waits, unless ``loading="complete"``; async
   waits only for the one top block when it is not resident: the first frame);
3. the cut: sort-first ranks with a layout fixed before the frame (horizontal, vertical,
   grid) restrict it to their own tile's sub-frustum, as the paper's §4.2 does ("the meta
   bintree traversal is then restricted to the particular view frustum"), so the LOD cost
   divides among ranks. The split test is per diamond; a tile's walk decides every diamond
   whose sphere touches its sub-frustum as the whole frame's does, so the patches it can see
   are the whole frame's, in the same order, and the tiles assemble bit-exactly. The same
   Allreduce ORs each rank's front blocks and wanted blocks, so every rank keeps and loads
   what any tile needs and the agreed residency stays global. Other decompositions cut the
   whole frame (sort-last shares it; kd and balanced tiles are planned from it);
4. the front is filtered by the task: sort-first culls it against the tile's sub-frustum;
   sort-last keeps the rank's range R_i by one of the paper's three enumerations (§4.1):
   ``linear`` (origin x of the finest M-block under the patch), ``quadtree`` (Morton interval of
   that block),
   ``kpatch`` (an equal share of the enumerated visible front).

Block sets (residency, front blocks, shading and wanted blocks) are flat boolean arrays over
:class:`~massview.lod.blockindex.BlockIndex` ids, not sets of tuples.
"""

from __future__ import annotations

import numpy as np

from ..core.camera import Camera, Viewport
from ..core.config import RenderConfig
from ..core.errors import ConfigError
from ..core.image import Image
from ..core.stats import FrameStats
from ..core.task import Task
from ..data.cache import BlockCache
from ..data.terrain import TerrainStore
from ..lod.cull import screen_rects
from ..lod.blockindex import BlockIndex, KeepSet
from ..lod.kpatch import Front, PatchHierarchy, lookup_blocks, patch_boxes, select_front, visible_patches
from ..lod.texlod import ShadingPyramid
from ..parallel.decompose import parse_decomposition, sort_first_tiles, sort_last_ranges
from ..parallel.exchange import agree_all, any_rank
from ..parallel.runtime import return_free_heap
from ..render.context import create_context, release_gl, renderer_string
from ..render.colormaps import Shading, paint_sky
from ..render.terrain import BlockPool, TerrainRenderer, payload_bytes, payload_parts
from ..render.view import ViewRenderer

__all__ = ["TerrainSystem", "SORT_LAST_MODES"]

SORT_LAST_MODES = ("kpatch", "linear", "quadtree")


def _morton(i: np.ndarray, j: np.ndarray) -> np.ndarray:
    out = np.zeros_like(i)
    for b in range(32):
        out |= ((j >> b) & 1) << (2 * b) | ((i >> b) & 1) << (2 * b + 1)
    return out


def _mapping(nbytes: int) -> np.ndarray:
    """A uint8 array of ``nbytes`` in its own anonymous mapping, unmapped when the last reference
    goes. A staged block's bytes then leave the process when the GL pool takes it, instead of
    staying in a loader thread's malloc arena (glibc keeps freed blocks below 32 MiB there:
    :func:`massview.parallel.runtime.reuse_freed_memory`), so the RAM budget bounds resident
    bytes. Its pages are mapped at once (``MAP_POPULATE``, where the platform has it): one
    call instead of a page fault per 4 KiB as the block is decoded into it."""
    import mmap

    flags = getattr(mmap, "MAP_PRIVATE", 0) | getattr(mmap, "MAP_ANONYMOUS", 0) | getattr(mmap, "MAP_POPULATE", 0)
    try:
        m = mmap.mmap(-1, max(nbytes, 1), flags=flags) if flags else mmap.mmap(-1, max(nbytes, 1))
    except (OSError, ValueError):
        m = mmap.mmap(-1, max(nbytes, 1))
    return np.frombuffer(m, np.uint8, nbytes)


class TerrainSystem:
    sort_last_modes = SORT_LAST_MODES

    def __init__(self, path, cache_bytes: int = 256 << 20, gpu_bytes: int = 256 << 20, egl_device: int | None = None,
                 loading: str = "async"):
        if loading not in ("async", "complete"):
            raise ConfigError(f"--loading must be async or complete, got {loading!r}")
        self.store = TerrainStore(path)
        self.spec = str(path)
        lay = self.lay = self.store.layout
        self._lod = self.store.lod_arrays()
        self._minmax = [self.store.block_minmax(lv) for lv in range(lay.levels)]
        self.h = self._hierarchy(1.0)
        self._blocks = BlockIndex(lay.levels, lay.L)
        self._tex_ids = np.zeros(0, np.int64)  # shading blocks the current view wants
        self._shading_pyramid = (None, None)  # (hierarchy, ShadingPyramid) for _want_shading
        self._front_mask = np.zeros(self._blocks.size, bool)  # blocks this rank's last front drew from
        self._keep_mask = self._union = self._front_mask  # ... and, cutting tiles, every rank's (not evicted on upload)
        self._want_mask = np.zeros(self._blocks.size, bool)  # blocks this rank's cut requested
        self._morton_codes = None  # the data blocks' sorted Morton codes (sort-last:quadtree, _morton_cut)
        self._tex_have, self._grids = -1, None
        self.cache = BlockCache(self._load, cache_bytes, workers=2)
        self.gpu_bytes, self.loading, self._egl_device = gpu_bytes, loading, egl_device
        self._gl = None
        self.front: Front | None = None
        self._wanted: set = set()
        self._counted = dict(self.cache.counters)  # cache counters at the last frame's report
        return_free_heap()  # the hierarchy's construction temporaries (~130 MiB at 32769²)

    # -- data ---------------------------------------------------------------------------
    def _hierarchy(self, exaggeration: float) -> PatchHierarchy:
        h = getattr(self, "h", None)
        if h is None or h.exaggeration != exaggeration:
            h = PatchHierarchy(self.lay, *self._lod, spacing=self.store.spacing, vscale=self.store.vertical_scale,
                               exaggeration=exaggeration)
        return h

    def _load(self, key):
        """Block ``key``'s payload (:func:`pack_payload`'s layout), decoded straight into its
        own mapping (:func:`_mapping`)."""
        lv, i, j = key
        out = _mapping(payload_bytes(self.lay.M, self.store.has_color))
        h, shade, color = payload_parts(out, self.lay.M, self.store.has_color)
        self.store.get_block(lv, i, j, out=h)
        self.store.get_shade(lv, i, j, out=shade, heights=h)
        if color is not None:
            self.store.get_color(lv, i, j, out=color)
        return out

    def shading(self, cfg: RenderConfig) -> Shading:
        cmap = cfg.colormap
        if cmap == "auto":
            cmap = "ortho" if self.store.has_color else "hypsometric"
        return Shading(cfg.exaggeration, tuple(cfg.sun), cmap, cfg.haze)

    @property
    def bounds(self):
        """The terrain's world box at the exaggeration of the current hierarchy (the last
        frame's; 1 until a frame is drawn at another)."""
        return self.h.bounds()

    def bounds_at(self, cfg: RenderConfig):
        """The world box as drawn at ``cfg.exaggeration`` (what paths and clip planes are fitted
        to), whatever exaggeration the current hierarchy has: :meth:`PatchHierarchy.bounds`'s
        own formula."""
        from ..lod.kpatch import world_box

        h = self.h
        return world_box(self.lay, h.zmin[0].src[0], h.zmax[0].src[0], (h.dx, h.dy), h.vs, cfg.exaggeration)

    def ground(self, cfg: RenderConfig | None = None):
        """The surface the ``walkthrough`` path walks on, at ``cfg``'s exaggeration
        (:func:`massview.lod.walk.kpatch_ground`: the hierarchy's world heights)."""
        from ..lod.walk import kpatch_ground

        return kpatch_ground(self.store, 1.0 if cfg is None else cfg.exaggeration)

    def _renderers(self):
        if self._gl is None:
            ctx = create_context(self._egl_device)
            pool = BlockPool(ctx, self.lay.M, self.lay.levels, self.lay.L, self.gpu_bytes, ortho=self.store.has_color)
            lo, hi = self.h.bounds()
            terrain = TerrainRenderer(ctx, pool, self.lay.k, self.store.spacing, self.store.vertical_scale,
                                      (self.lay.rows, self.lay.cols), base=self.h.base, world_size=float(np.hypot(*(hi - lo)[:2])),
                                      peak=float(np.max(self._lod[3][0])) * self.store.vertical_scale)  # back-face culling above it
            self._gl = (ctx, pool, terrain, ViewRenderer(ctx))
        return self._gl

    def renderers(self):
        """This rank's GL objects, created on first use: (context, block pool, terrain renderer,
        view renderer) — for tools drawing beside the system (``bench terrain``'s plain mesh)."""
        return self._renderers()

    @property
    def renderer(self) -> str:
        return renderer_string(self._renderers()[0])

    def _upload_ready(self, keep) -> int:
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
                    self.cache.discard(key)  # the pool holds it now: RAM keeps only blocks not yet uploaded
                    n += 1
        return n

    def _request(self, lv, bi, bj, prio) -> None:
        ids = self._blocks.ids(lv, bi, bj)
        self._want_mask[ids] = True
        _, pool, _, _ = self._renderers()
        miss = ~lookup_blocks(pool.resident, np.asarray(lv), np.asarray(bi), np.asarray(bj))  # not agreed, but here
        ids, prio = ids[miss], np.asarray(prio)[miss]
        for key, p in zip(self._blocks.keys(ids), prio.tolist()):
            self._wanted.add(key)
            self.cache.request(key, p)

    # -- per frame ----------------------------------------------------------------------
    def lod_viewport(self, comm, camera: Camera, cfg: RenderConfig) -> Viewport | None:
        """The sub-frustum this rank's cut is restricted to: its own tile for sort-first layouts
        fixed before the frame (horizontal, vertical, grid) on several ranks, else None (the
        whole frame: sort-last needs it to share the visible front; kd and balanced tiles are
        planned from it)."""
        n = comm.Get_size()
        kind, mode = parse_decomposition(cfg.decomposition, self.sort_last_modes)
        if n == 1 or kind != "sort-first" or mode not in ("horizontal", "vertical", "grid"):
            return None
        return sort_first_tiles(mode, n, camera.width, camera.height, cfg.grid)[comm.Get_rank()]

    def prepare_frame(self, comm, camera: Camera, cfg: RenderConfig, stats: FrameStats) -> None:
        """Uploads, residency agreement and the LOD front (same on every rank, or each rank's
        tile of it for fixed sort-first layouts)."""
        _, pool, terrain, _ = self._renderers()
        self.h = self._hierarchy(cfg.exaggeration)
        terrain.set_shading(self.shading(cfg))
        self.cache.begin_frame()
        vp = self.lod_viewport(comm, camera, cfg)
        with stats.stage("lod"):
            self._want_shading(camera)
            front, grids = self._lod_loop(comm, camera, cfg, stats, vp)
        self._grids, self._tau = grids, cfg.tau
        self.front = front if front is not None else Front.empty()
        terrain.set_pages(pool.page_table(grids))
        self._tex_have = -1
        self._front_mask = self._blocks.mask(self.front.block_ids(self._blocks.offset, self._blocks.nb))
        self._keep_mask = self._front_mask | self._union if vp is not None else self._front_mask
        used = self._front_mask.copy()
        used[self._tex_ids] = True
        pool.touch(self._blocks.keys(np.flatnonzero(used)))
        now = dict(self.cache.counters)  # loads finish between frames: count since the last report
        stats.count("blocks_loaded", now["loads"] - self._counted["loads"])
        stats.count("cache_hits", now["hits"] - self._counted["hits"])
        stats.count("bytes_loaded", now["bytes_loaded"] - self._counted["bytes_loaded"])
        self._counted = now
        stats.count("deferred_splits", self.front.deferred)
        stats.count("front_patches", len(self.front))

    def _lod_loop(self, comm, camera: Camera, cfg: RenderConfig, stats: FrameStats, vp):
        """Upload, agree, select; with ``loading="complete"`` repeat until no rank defers a split."""
        _, pool, _, _ = self._renderers()
        top = (self.lay.L, 0, 0)
        stalled, best, waited = 0, -1, False
        while True:
            if not pool.resident[top[0]][0, 0]:
                self._wanted.add(top)
                self.cache.request(top, float("inf"))
            keep = KeepSet(self._blocks, self._keep_mask, self._tex_ids)
            stats.count("blocks_uploaded", self._upload_ready(keep))
            grids = self._agree(comm, pool, vp is not None)
            self._want_mask[:] = False
            if not grids[top[0]][0, 0] and not waited:  # (agreed: the same on every rank) the one top block, which every
                waited = True                           # view can draw: a first async frame waits for it (walk7 L6: empty sky)
                stats.count("blocks_uploaded", self._wait_for_loads(keep))
                continue
            front = select_front(self.h, camera, cfg.tau, grids, self._request, vp) if grids[top[0]][0, 0] else None
            missing = front is None or front.deferred > 0
            if self.loading != "complete" or not any_rank(comm, missing or self._shading_missing(grids)):
                return front, grids
            if not any_rank(comm, missing):  # only shading blocks missing: wait while they keep arriving
                have = self._shading_count(grids)
                if have <= self._tex_have:
                    return front, grids
                self._tex_have = have
                stats.count("blocks_uploaded", self._wait_for_loads(keep))
                continue
            # complete loading: wait for the requested blocks; give up when the fronts stop
            # growing (blocks only cycle through budgets too small for this view)
            size = len(front) if front is not None else 0
            size = comm.allreduce(size) if vp is not None else size
            stalled, best = (0, size) if size > best else (stalled + 1, best)
            if stalled > 5:
                raise ConfigError("--loading complete: the blocks this view needs do not fit the budgets "
                                  f"(--cache-mb {self.cache.budget >> 20}, --gpu-mb {self.gpu_bytes >> 20}); raise them or --tau")
            stats.count("blocks_uploaded", self._wait_for_loads(keep))

    def _agree(self, comm, pool, tiles: bool) -> list[np.ndarray]:
        """Blocks resident on every rank, as per-level grids. With per-tile cuts the same
        Allreduce also ORs the blocks each rank's cut drew from and wanted (last pass), so every
        rank keeps and loads what any tile needs and the agreement stays the same everywhere."""
        flat = self._blocks.flat(pool.resident)
        if not tiles:
            agreed = agree_all(comm, flat)
        else:
            both = agree_all(comm, np.concatenate([flat, ~self._front_mask, ~self._want_mask]))
            k = len(flat)
            agreed = both[:k]
            self._union = ~both[k:2 * k]  # every rank's last front blocks
            self._keep_mask = self._keep_mask | self._union
            for key in self._blocks.keys(np.flatnonzero(~both[2 * k:] & ~flat)):
                self._wanted.add(key)
                self.cache.request(key, 1e-3)  # another tile's: after this rank's own
        return self._blocks.grids(agreed)

    def _want_shading(self, camera: Camera) -> None:
        """Request the shading-pyramid blocks this view samples (after the geometry's)."""
        h = self.h
        if self._shading_pyramid[0] is not h:  # the blocks' world boxes, once per hierarchy (exaggeration)
            self._shading_pyramid = (h, ShadingPyramid(self._minmax, self.lay.M, self.store.spacing,
                                                       lambda z: h.base + h.exaggeration * (z * h.vs - h.base)))
        lv, bi, bj, prio = self._shading_pyramid[1].blocks(camera)
        self._tex_ids = self._blocks.ids(lv, bi, bj)
        _, pool, _, _ = self._renderers()
        flat = self._blocks.flat(pool.resident)
        miss = np.flatnonzero(~flat[self._tex_ids])
        for key, p in zip(self._blocks.keys(self._tex_ids[miss]), prio[miss].tolist()):
            self._wanted.add(key)
            self.cache.request(key, 1e-6 * p)

    def _shading_count(self, grids) -> int:
        return int(np.count_nonzero(self._blocks.flat(grids)[self._tex_ids]))

    def _shading_missing(self, grids) -> bool:
        return self._shading_count(grids) < len(self._tex_ids)

    def _wait_for_loads(self, keep) -> int:
        """Wait until the cache has loaded what was requested (at most 60 s), uploading blocks
        to the pool as they arrive: the RAM cache then stages a few blocks at a time instead of
        all a view needs (which was 160-190 MiB per rank on the 32769² flyover). Returns the
        blocks uploaded."""
        import time

        t0, n = time.monotonic(), 0
        while not self.cache.idle() and time.monotonic() - t0 < 60:
            time.sleep(0.002)
            n += self._upload_ready(keep)
        return n

    # -- plan and render ----------------------------------------------------------------
    def _visible(self, camera: Camera, vp=None) -> np.ndarray:
        return visible_patches(self.h, self.front, camera, vp)

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
        span0 = self.lay.M - 1  # both: the finest M-block under the patch centroid
        cx, cy = (f.ax[vis] + f.lx[vis] + f.rx[vis]) // 3, (f.ay[vis] + f.ly[vis] + f.ry[vis]) // 3
        if mode == "linear":  # that block's origin x (the paper's O_M(x) of the block the patch drew from put
            nx = self._data_blocks()[1]
            x = np.minimum(cx // span0, nx - 1) / float(nx)  # every patch of a coarse block on rank 0: they all start at x = 0),
            return vis[(x >= a) & (x < b)]  # as a share of the blocks that hold data (not of the padded square)
        # quadtree: Morton order of that block, cut into runs of equal counts of the blocks that hold data
        z = _morton(cy // span0, cx // span0)
        return vis[(z >= self._morton_cut(a)) & (z < self._morton_cut(b))]

    def _data_blocks(self) -> tuple[int, int]:
        """(rows, columns) of the level-0 blocks that hold data: a non-square DEM's padded square
        has whole rows or columns of padding blocks, which the sort-last database splits skip."""
        M = self.lay.M
        return max(-(-(self.lay.rows - 1) // (M - 1)), 1), max(-(-(self.lay.cols - 1) // (M - 1)), 1)

    def _morton_cut(self, a: float) -> int:
        """The Morton code where the share ``a`` (0..1) of the data blocks, in Morton order,
        begins (0 at 0, 4^L at 1): ``sort-last:quadtree`` gives each rank a run of equal counts
        of them. For a square DEM filling its blocks this is ceil(a·4^L), the plain split."""
        codes = self._morton_codes
        if codes is None:
            ny, nx = self._data_blocks()
            i, j = np.meshgrid(np.arange(ny, dtype=np.int64), np.arange(nx, dtype=np.int64), indexing="ij")
            codes = self._morton_codes = np.sort(_morton(i.ravel(), j.ravel()))
        k = int(np.ceil(a * len(codes) - 1e-9))
        return 0 if k <= 0 else int(4**self.lay.L) if k >= len(codes) else int(codes[k])

    def render(self, task: Task, camera: Camera, cfg: RenderConfig, stats: FrameStats, tint=(0, 0, 0, 0)) -> Image:
        _, _, terrain, view = self._renderers()
        with stats.stage("lod"):
            idx = self.select(task, camera, cfg)  # increasing indices: all of them is the front itself
            part = self.front if len(idx) == len(self.front) else self.front.take(idx)
        stats.count("patches", len(part))
        stats.count("blocks_drawn", int(np.count_nonzero(self._blocks.mask(part.block_ids(self._blocks.offset, self._blocks.nb)))))
        return view.render(camera, task.viewport, lambda mvp: terrain.draw(part, mvp, tint, camera.position), stats, cfg.tile_targets)

    def finish(self, camera: Camera, cfg: RenderConfig, img: Image) -> Image:
        """The final pixels (after compositing and delivery): the sky behind the terrain."""
        return paint_sky(camera, img)

    def render_reference(self, camera: Camera, cfg: RenderConfig) -> Image:
        """The serial image: the whole frame's cut (with the residency every rank agreed on
        this frame, so a rank whose own cut covers only its tile recomputes it) drawn alone."""
        ref_cfg = RenderConfig(width=cfg.width, height=cfg.height, tau=cfg.tau, exaggeration=cfg.exaggeration, sun=cfg.sun,
                               colormap=cfg.colormap, haze=cfg.haze)
        own = self.front
        if own is not None and own.code_vp is not None:
            self.front = select_front(self.h, camera, cfg.tau, self._grids)
        try:
            return self.finish(camera, cfg, self.render(Task(0, camera.viewport), camera, ref_cfg, FrameStats(-1, 0)))
        finally:
            self.front = own

    def close(self) -> None:
        self.cache.close()
        release_gl(self)
