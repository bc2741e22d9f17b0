"""A prepared polygon scene (scene store) rendered with the runtime's decompositions.

Every rank holds the skeleton and computes the same cut from the same camera. Per frame:

1. **cull** the skeleton hierarchically (group boxes level by level, then the objects of
   straddling groups — :class:`~massview.lod.scene.SkeletonCuller`) against the full frustum;
2. **choose levels** from ``--tau`` (projected ``level_error`` at the nearest point of each
   bounding sphere — a pure function of the camera);
3. **plan** (the same on every rank): sort-first tiles (``kd`` weighted by the chosen levels'
   triangles) or sort-last ranges; each rank *claims* the objects its task draws (all visible
   objects on a display rank rendering ``--reference``);
4. **upload** meshes that finished loading (RAM cache, worker threads) into the GL pool, and
   **agree on residency**: an Allreduce (AND) of the (object × level) residency bits, where a
   rank that does not claim an object votes "resident". Every rank that draws an object then
   draws the same level: the desired one when resident everywhere it is claimed, else the
   finest coarser resident level (or a finer one) — so parallel == serial whatever finished
   loading where. Missing meshes are requested by screen size (the coarsest level first, so
   something shows soon); with ``loading="complete"`` the frame waits until the desired
   levels are in, otherwise it waits only once: the first frame, for the coarsest levels of
   the objects it draws that have nothing resident (their smallest meshes), so it is not
   empty.

Sort-last modes: ``visible`` (default) — the visible objects, in id order, split into ranges
of equal chosen-level triangles; ``static`` — object id ranges of equal level-0 triangles over
the whole scene. Ranges are contiguous in id order, and lower ranks win depth ties when
compositing, as the lower id wins in the serial draw order, so sort-last is exact too.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from ..core.camera import Camera
from ..core.config import RenderConfig
from ..core.errors import ConfigError
from ..core.image import Image
from ..core.stats import FrameStats
from ..core.task import Task
from ..data.cache import BlockCache
from ..lod.cull import boxes_in_frustum, screen_rects
from ..lod.scene import SkeletonCuller, choose_levels, lod_scale, resolve_levels
from ..parallel.decompose import parse_decomposition, sort_first_tiles, sort_last_ranges
from ..parallel.exchange import agree_all, any_rank
from ..render.context import create_context, release_gl, renderer_string
from ..render.scene import MeshPool, SceneRenderer, pack_mesh
from ..render.view import ViewRenderer
from .frameloop import display_tiles

__all__ = ["SceneSystem", "SORT_LAST_MODES"]

SORT_LAST_MODES = ("visible", "static")


@dataclass
class Cut:
    """The frame's visible objects ``vis`` (k,) sorted ids, their desired levels, weights
    (desired-level triangles) and the level drawn now (-1: none resident yet)."""

    camera: Camera
    vis: np.ndarray
    desired: np.ndarray
    weights: np.ndarray
    drawn: np.ndarray
    tasks: list | None = None


def _normal_matrices(model: np.ndarray) -> np.ndarray:
    """(n, 3, 3) inverse-transpose of each model matrix's linear part (normals stay normal
    under non-uniform scales)."""
    lin = model[:, :3, :3]
    det = np.linalg.det(lin)
    out = np.tile(np.eye(3), (len(model), 1, 1))
    ok = np.abs(det) > 1e-300
    out[ok] = np.linalg.inv(lin[ok]).transpose(0, 2, 1)
    return out


class SceneSystem:
    sort_last_modes = SORT_LAST_MODES
    max_requests = 384  # load requests issued per frame (most important first)

    def __init__(self, store, cache_bytes: int = 256 << 20, gpu_bytes: int = 256 << 20, egl_device: int | None = None,
                 loading: str = "async", workers: int = 2):
        if loading not in ("async", "complete"):
            raise ConfigError(f"--loading must be async or complete, got {loading!r}")
        if isinstance(store, (str, bytes)) or hasattr(store, "__fspath__"):
            from ..data.scene import SceneStore

            store = SceneStore(store)
        self.store, self.spec = store, str(getattr(store, "path", "scene"))
        sk = self.sk = store.skeleton
        self.culler = SkeletonCuller(store.groups, sk.group, sk.box_lo, sk.box_hi)
        self.levels = np.asarray(sk.levels, np.int64)
        self.geometry = np.asarray(sk.geometry, np.int64)
        self.tris = np.asarray(sk.triangles, np.int64)
        self.model = np.asarray(sk.transform, np.float64)
        self.normal = _normal_matrices(self.model)
        t0 = self.tris[:, 0].astype(np.float64)
        self.static_start = np.concatenate([[0.0], np.cumsum(t0)[:-1]]) / max(t0.sum(), 1.0)
        self.n_geom = int(self.geometry.max(initial=-1)) + 1
        self.cache = BlockCache(self._load, cache_bytes, workers=workers)
        self.gpu_bytes, self.loading, self._egl_device = gpu_bytes, loading, egl_device
        self._gl = None
        self._wanted: dict[tuple[int, int], int] = {}
        self._frame = 0
        self.cut: Cut | None = None
        self._counted = dict(self.cache.counters)

    # -- data ---------------------------------------------------------------------------
    def _load(self, key):
        m = self.store.get_mesh(int(key[0]), int(key[1]))
        return pack_mesh(m.positions, m.normals, m.colors, m.indices)

    @property
    def bounds(self):
        lo, hi = self.store.bounds
        return np.asarray(lo, np.float64), np.asarray(hi, np.float64)

    @property
    def obstacles(self):
        """The objects' boxes, which the ``walkthrough`` path walks round."""
        return self.store.object_boxes

    def _renderers(self):
        if self._gl is None:
            ctx = create_context(self._egl_device)
            pool = MeshPool(ctx, self.n_geom, self.tris.shape[1], self.gpu_bytes)
            self._gl = (ctx, pool, SceneRenderer(ctx, pool), ViewRenderer(ctx))
        return self._gl

    @property
    def pool(self) -> MeshPool:
        return self._renderers()[1]

    @property
    def renderer(self) -> str:
        return renderer_string(self._renderers()[0])

    # -- per frame ----------------------------------------------------------------------
    def cull(self, camera: Camera, cfg: RenderConfig) -> Cut:
        """Visible objects and their desired levels (pure function of camera and skeleton)."""
        vis = np.flatnonzero(self.culler.visible(camera.frustum_planes()))
        sk = self.sk
        desired = choose_levels(camera, sk.center[vis], sk.radius[vis], self.levels[vis], sk.level_error[vis], cfg.tau)
        weights = self.tris[vis, desired]
        return Cut(camera, vis, desired, weights, np.full(len(vis), -1, np.int64))

    def prepare_frame(self, comm, camera: Camera, cfg: RenderConfig, stats: FrameStats) -> None:
        """Cull, choose levels, plan, upload, agree on residency (same cut on every rank)."""
        _, pool, _, _ = self._renderers()
        self._frame += 1
        self.cache.begin_frame()
        rank, n = comm.Get_rank(), comm.Get_size()
        with stats.stage("lod"):
            t0 = time.perf_counter()
            cut = self.cull(camera, cfg)
            stats.count("cull_ms", (time.perf_counter() - t0) * 1e3)
            cut.tasks = self._plan(cut, cfg, n)
            claim = np.zeros(len(cut.vis), bool)
            claim[self.select(cut.tasks[rank], cut, cfg)] = True
            if cfg.reference and any(r == rank for r, _ in display_tiles(cfg, n)):
                claim[:] = True
            self._agree_levels(comm, cut, claim, cfg, stats)
        self.cut = cut
        self._report(stats, cut, claim)

    def _agree_levels(self, comm, cut: Cut, claim: np.ndarray, cfg: RenderConfig, stats: FrameStats) -> None:
        pool = self.pool
        g = self.geometry[cut.vis]
        keep = set(zip(g[claim].tolist(), cut.desired[claim].tolist()))
        if self.cut is not None:
            ok = self.cut.drawn >= 0
            keep |= set(zip(self.geometry[self.cut.vis[ok]].tolist(), self.cut.drawn[ok].tolist()))
        if self.loading == "complete":
            self._check_fits(cut, claim)
        stalled, best = 0, -1
        first = self.loading != "complete" and self._frame == 1  # (the same on every rank)
        while True:
            stats.count("meshes_uploaded", self._upload_ready(keep))
            mask = pool.resident[g]
            mask[~claim] = True
            cut.drawn = resolve_levels(cut.desired, agree_all(comm, mask))
            missing = claim & (cut.drawn != cut.desired)
            self._request(cut, claim)
            if first:  # async's first frame waits once for the coarsest levels of what it claims (walk8 L2: an empty frame 0)
                first = False
                empty = claim & (cut.drawn < 0)
                if any_rank(comm, empty.any()):
                    obj = cut.vis[empty]
                    keys = list(zip(self.geometry[obj].tolist(), (self.levels[obj] - 1).tolist()))
                    for key in keys:  # (all of them: _request issues at most max_requests a frame)
                        self._want(key, 2e12)
                    self._wait_for_loads(keys, limit_s=10.0)
                    continue
            if self.loading != "complete" or not any_rank(comm, missing.any()):
                return
            done = int(np.count_nonzero(claim & (cut.drawn == cut.desired)))
            stalled, best = (0, done) if done > best else (stalled + 1, best)
            if stalled > 50:
                raise ConfigError("--loading complete: the meshes this view needs do not fit the budgets "
                                  f"(--cache-mb {self.cache.budget >> 20}, --gpu-mb {self.gpu_bytes >> 20}); raise them or --tau")
            self._wait_for_loads()

    def _check_fits(self, cut: Cut, claim: np.ndarray) -> None:
        """Complete loading: fail at once, naming the budgets, when the wanted meshes cannot
        fit (a lower bound: 24 of the store's 28 decoded bytes per vertex reach the pool)."""
        obj, lv = cut.vis[claim], cut.desired[claim]
        keys, first = np.unique(self.geometry[obj] * self.tris.shape[1] + lv, return_index=True)
        need = int(np.asarray(self.sk.level_bytes)[obj[first], lv[first]].sum() * 24 // 28)
        budget = min(self.pool.budget, self.cache.budget)
        if need > budget:
            raise ConfigError(f"--loading complete: the meshes this view needs do not fit the budgets (at least {need >> 20} MiB "
                              f"for --cache-mb {self.cache.budget >> 20}, --gpu-mb {self.gpu_bytes >> 20}); raise them or --tau")

    def _request(self, cut: Cut, claim: np.ndarray) -> None:
        """Queue loads for claimed objects not drawn at their desired level: the coarsest level
        first for objects with nothing resident (async), then the desired level, by screen
        size; only the ``max_requests`` most important per frame (the loaders cannot do more,
        and the cache drops requests not renewed)."""
        need = np.flatnonzero(claim & (cut.drawn != cut.desired))
        if len(need) == 0:
            return
        obj = cut.vis[need]
        cam = cut.camera
        diff = self.sk.center[obj] - np.asarray(cam.position)
        d = np.maximum(np.sqrt(np.einsum("ij,ij->i", diff, diff)) - self.sk.radius[obj], cam.near)
        prio = self.sk.radius[obj] * lod_scale(cam) / d
        g, lv = self.geometry[obj], cut.desired[need]
        coarse = (self.levels[obj] - 1)
        first = (cut.drawn[need] < 0) & (self.loading != "complete")  # nothing resident: its coarsest level before any finer one
        rest = ~(first & (coarse == lv))  # (an object whose desired level is its coarsest: requested once, as a first)
        keys_g = np.concatenate([g[first], g[rest]])
        keys_l = np.concatenate([coarse[first], lv[rest]])
        keys_p = np.concatenate([prio[first] + 1e12, prio[rest]])
        top = np.argsort(-keys_p, kind="stable")[: self.max_requests]
        for gi, li, p in zip(keys_g[top].tolist(), keys_l[top].tolist(), keys_p[top].tolist()):
            self._want((gi, li), p)

    def _want(self, key, priority: float) -> None:
        self._wanted[key] = self._frame
        self.cache.request(key, priority)

    def _upload_ready(self, keep: set) -> int:
        pool, n = self.pool, 0
        for key, frame in list(self._wanted.items()):
            if pool.resident[key] or self._frame - frame > self.cache.max_age:
                del self._wanted[key]
                continue
            packed = self.cache.get(key)
            if packed is not None and pool.upload(key, packed, keep):
                del self._wanted[key]
                n += 1
        return n

    def _wait_for_loads(self, keys: list = (), limit_s: float = 60.0) -> None:
        """Wait until nothing is loading any more, every mesh of ``keys`` (requested already) is
        in the cache if any are given, or ``limit_s`` passed."""
        t0 = time.monotonic()
        while time.monotonic() - t0 < limit_s:
            if self.cache.idle() or (keys and all(self.cache.contains(k) for k in keys)):
                return
            time.sleep(0.002)

    def _report(self, stats: FrameStats, cut: Cut, claim: np.ndarray) -> None:
        drawn = cut.drawn[claim]
        stats.count("objects_visible", len(cut.vis))
        stats.count("objects_claimed", int(claim.sum()))
        stats.count("objects_coarser", int(np.count_nonzero(drawn > cut.desired[claim])))
        stats.count("objects_missing", int(np.count_nonzero(drawn < 0)))
        now = dict(self.cache.counters)
        for name, key in (("meshes_loaded", "loads"), ("cache_hits", "hits"), ("bytes_loaded", "bytes_loaded")):
            stats.count(name, now[key] - self._counted[key])
        self._counted = now
        stats.count("cache_resident_bytes", self.cache.resident_bytes)
        stats.count("gpu_used_bytes", self.pool.used_bytes)
        ok = cut.drawn >= 0
        self.pool.touch(zip(self.geometry[cut.vis[ok]].tolist(), cut.drawn[ok].tolist()))

    # -- plan and render ----------------------------------------------------------------
    def _plan(self, cut: Cut, cfg: RenderConfig, nranks: int) -> list[Task]:
        camera = cut.camera
        kind, mode = parse_decomposition(cfg.decomposition, self.sort_last_modes)
        if kind == "sort-last":
            return [Task(i, camera.viewport, data_range=r) for i, r in enumerate(sort_last_ranges(nranks))]
        rects = weights = None
        if mode == "kd":
            rects = screen_rects(camera, self.sk.box_lo[cut.vis], self.sk.box_hi[cut.vis])
            weights = cut.weights.astype(np.float64)
        tiles = sort_first_tiles(mode, nranks, camera.width, camera.height, cfg.grid, rects, weights)
        return [Task(i, vp) for i, vp in enumerate(tiles)]

    def plan(self, camera: Camera, cfg: RenderConfig, nranks: int) -> list[Task]:
        cut = self.cut if self.cut is not None and self.cut.camera == camera else self.cull(camera, cfg)
        if cut.tasks is None or len(cut.tasks) != nranks:
            cut.tasks = self._plan(cut, cfg, nranks)
        return cut.tasks

    def select(self, task: Task, cut: Cut, cfg: RenderConfig) -> np.ndarray:
        """Indices into ``cut.vis`` that ``task`` draws (ascending: the serial draw order)."""
        camera = cut.camera
        idx = np.arange(len(cut.vis))
        if task.viewport != camera.viewport:
            planes = camera.frustum_planes(task.viewport)
            idx = np.flatnonzero(boxes_in_frustum(self.sk.box_lo[cut.vis], self.sk.box_hi[cut.vis], planes))
        if task.data_range is not None:
            a, b = task.data_range
            _, mode = parse_decomposition(cfg.decomposition, self.sort_last_modes)
            if mode == "static":
                start = self.static_start[cut.vis]
            else:
                w = cut.weights.astype(np.float64)
                start = np.concatenate([[0.0], np.cumsum(w)[:-1]]) / max(w.sum(), 1.0)
            idx = idx[(start[idx] >= a) & (start[idx] < b)]
        if task.items is not None:
            idx = idx[np.isin(cut.vis[idx], np.asarray(task.items))]
        return idx

    def render(self, task: Task, camera: Camera, cfg: RenderConfig, stats: FrameStats, tint=(0, 0, 0, 0)) -> Image:
        _, _, scene, view = self._renderers()
        cut = self.cut
        with stats.stage("lod"):
            idx = self.select(task, cut, cfg)
            idx = idx[cut.drawn[idx] >= 0]
            obj, lv = cut.vis[idx], cut.drawn[idx]
        stats.count("objects_drawn", len(obj))
        eye = np.asarray(camera.position)
        shift = np.eye(4)
        shift[:3, 3] = eye

        def draw(mvp):
            return scene.draw(self.geometry[obj], lv, self.model[obj], self.normal[obj], eye, mvp @ shift, tint)

        return view.render(camera, task.viewport, draw, stats, cfg.tile_targets)

    def render_reference(self, camera: Camera, cfg: RenderConfig) -> Image:
        """Every visible object at the agreed levels, full frame, one rank."""
        ref_cfg = RenderConfig(width=cfg.width, height=cfg.height, tau=cfg.tau)
        return self.render(Task(0, camera.viewport), camera, ref_cfg, FrameStats(-1, 0))

    def close(self) -> None:
        self.cache.close()
        release_gl(self)
