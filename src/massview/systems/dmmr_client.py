"""A client of the massive-model system (Revanth & Narayanan 2012, §3.5–3.8).

Two modules, each on its own GL context (the paper's two GPUs), run as the last two stages
of the frame pipeline:

* :meth:`DmmrClient.visibility` (GPU 1): the sub-frustum's potential occluders and the
  previous frame's visible objects are drawn to depth, every other object is tested with
  batched hardware occlusion queries (:mod:`massview.render.queries`) — through the scene's
  group tree (:mod:`massview.systems.dmmr_hierarchy`, the same visible set with fewer
  queries) or one per object box (``--query-hierarchy off``, the paper's) — and objects that
  pass are marked visible for ``--visible-frames`` frames
  (:class:`~massview.lod.visibility.VisibilityState`);
* :meth:`DmmrClient.render` (GPU 2): the visible list is made resident through the
  three-level cache (:class:`~massview.render.geometry_cache.GeometryCache`: GPU ← RAM ←
  store; meshes visible in the previous frame are still on the GPU and are reused), drawn
  into the client's viewport with the full-frame matrices and a scissor (bit-exact with a
  serial render), read back and compressed with the runtime's codec.

Both GL pools share one RAM cache. Occluders are drawn at the level the frame renders
(``--occluder-lod exact``: conservative, the images equal the reference) or at the coarsest
level (``coarse``, as the paper: cheaper, but a simplified occluder may poke out in front of
the object and hide something visible — the reference diff reports it).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from ..core.camera import Camera, Viewport
from ..core.config import RenderConfig
from ..core.image import Image
from ..core.stats import FrameStats
from ..data.cache import BlockCache
from ..lod.scene import lod_scale
from ..lod.visibility import VisibilityState, boxes_reach_near
from ..parallel.codec import encode_image, resolve_codec
from ..parallel.runtime import world
from ..render.context import create_context, renderer_string
from ..render.geometry_cache import GeometryCache, packed_loader
from ..render.queries import OcclusionQuerier, SceneIdBuffer
from ..render.scene import MeshPool, SceneRenderer
from ..render.view import ViewRenderer
from .dmmr_hierarchy import GroupQueries, box_screen_area, widen_boxes

__all__ = ["ClientTask", "Visible", "DmmrClient", "SceneDrawer", "normal_matrices"]


@dataclass(frozen=True)
class ClientTask:
    """What the server sends a client for one frame: the camera, the client's viewport, the
    sorted object ids in its sub-frustum and the LOD level chosen for each."""

    frame: int
    camera: Camera
    viewport: Viewport
    items: np.ndarray
    levels: np.ndarray


@dataclass
class Visible:
    """The visibility module's output for the renderer: indices into ``task.items``."""

    task: ClientTask
    keep: np.ndarray
    stats: FrameStats = field(repr=False, default=None)
    ids: dict = field(repr=False, default_factory=dict)  # --record-ids / --id-check: lists for the record


def normal_matrices(model: np.ndarray) -> np.ndarray:
    """(n, 3, 3) inverse-transpose of each model matrix's linear part."""
    lin = model[:, :3, :3]
    out = np.tile(np.eye(3), (len(model), 1, 1))
    ok = np.abs(np.linalg.det(lin)) > 1e-300
    out[ok] = np.linalg.inv(lin[ok]).transpose(0, 2, 1)
    return out


class SceneDrawer:
    """One GL context with its own mesh pool (GPU cache level) over a shared RAM cache."""

    def __init__(self, sk, ram: BlockCache, gpu_bytes: int, egl_device: int | None):
        self.ctx = create_context(egl_device)
        self.geometry = np.asarray(sk.geometry, np.int64)
        self.model = np.asarray(sk.transform, np.float64)
        self.normal = normal_matrices(self.model)
        with self.ctx:
            n_geom = int(self.geometry.max(initial=-1)) + 1
            self.pool = MeshPool(self.ctx, n_geom, int(np.asarray(sk.triangles).shape[1]), gpu_bytes)
            self.cache = GeometryCache(self.pool, ram)
            self.renderer = SceneRenderer(self.ctx, self.pool)
            self.view = ViewRenderer(self.ctx)

    def ensure(self, obj: np.ndarray, lv: np.ndarray):
        return self.cache.ensure(zip(self.geometry[obj].tolist(), np.asarray(lv).tolist()))

    def draw_fn(self, camera: Camera, obj: np.ndarray, lv: np.ndarray, tint=(0.0, 0.0, 0.0, 0.0)):
        """``draw(mvp) -> triangles`` for objects ``obj`` at levels ``lv`` (resident)."""
        eye = np.asarray(camera.position)
        shift = np.eye(4)
        shift[:3, 3] = eye

        def draw(mvp: np.ndarray) -> int:
            return self.renderer.draw(self.geometry[obj], lv, self.model[obj], self.normal[obj], eye, mvp @ shift, tint)

        return draw

    def release(self) -> None:
        with self.ctx:
            self.view.release()
            self.renderer.release()
            self.pool.release()
        self.ctx.release()


class DmmrClient:
    """One client; ``visibility`` and ``render`` may run on two threads (one context each)."""

    def __init__(self, store, cfg: RenderConfig, rank: int, ram_bytes: int):
        self.sk = store.skeleton
        self.cfg, self.rank = cfg, rank
        self.box_lo = np.asarray(self.sk.box_lo, np.float64)
        self.box_hi = np.asarray(self.sk.box_hi, np.float64)
        self.occluder = np.asarray(self.sk.occluder, bool)
        self.coarsest = np.asarray(self.sk.levels, np.int64) - 1
        self.level_bytes = np.asarray(self.sk.level_bytes, np.int64)
        self.ram = BlockCache(packed_loader(store), ram_bytes, workers=2)
        self.state = VisibilityState(len(self.box_lo), cfg.visible_frames)
        groups = store.groups
        leaf = np.asarray(self.sk.group, np.int64)
        self.groups = (GroupQueries(groups.parent, groups.depth, leaf)  # a scene without a tree: one query per box
                       if cfg.query_hierarchy == "on" and len(groups.parent) and (leaf >= 0).all() else None)
        self._vis: tuple[SceneDrawer, OcclusionQuerier] | None = None
        self._ren: SceneDrawer | None = None
        self._gl: str | None = None  # the render context's GL renderer string, once it exists
        self._ids: SceneIdBuffer | None = None

    def _vis_gl(self):
        if self._vis is None:
            d = SceneDrawer(self.sk, self.ram, self.cfg.gpu_mb << 20, self.cfg.egl_device)
            with d.ctx:
                self._vis = (d, OcclusionQuerier(d.ctx))
        return self._vis

    def visibility(self, task: ClientTask, stats: FrameStats) -> Visible:
        """Module 2 of §3.3 for one frame; fills ``stats`` (stage ``visibility``)."""
        items = task.items
        stats.count("objects_received", len(items))
        if self.cfg.occlusion != "on" or len(items) == 0:
            return Visible(task, np.arange(len(items)), stats)
        drawer, querier = self._vis_gl()
        cam = task.camera
        with drawer.ctx, stats.stage("visibility"):
            near = boxes_reach_near(cam, self.box_lo[items], self.box_hi[items])
            plan = self.state.plan(task.frame, items, self.occluder, near)
            pos = np.searchsorted(items, plan.depth_pass)
            lv = task.levels[pos] if self.cfg.occluder_lod == "exact" else self.coarsest[plan.depth_pass]
            with stats.stage("vis_load"):
                occ, lv, c, _ = self._resident(drawer, plan.depth_pass, lv, exact=True)
            passed, counts = self._query(querier, cam, task.viewport, drawer.draw_fn(cam, occ, lv), plan.query, stats)
            visible = self.state.finish(plan, passed)
        stats.count("depth_mesh_bytes", int(self.level_bytes[occ, lv].sum()))
        for k, v in (("depth_pass_objects", len(plan.depth_pass)), ("culled_by_occlusion", int((~passed).sum())),
                     ("marked_visible", len(plan.marked)), ("near_visible", len(plan.near)), *counts.items()):
            stats.count(k, v)
        for k, v in c.to_counters("vis_").items():
            stats.count(k, v)
        return Visible(task, np.searchsorted(items, visible), stats)

    def _query(self, querier: OcclusionQuerier, cam: Camera, vp, draw_depth, query: np.ndarray, stats: FrameStats):
        """Depth pre-pass, then the queries of objects ``query``: through the group tree
        (:class:`~massview.systems.dmmr_hierarchy.GroupQueries`, ``--query-hierarchy on``) or
        one per object box (``off``, the paper's). Returns (passed per object, counters)."""
        t0 = time.perf_counter()
        tris = querier.begin(cam, vp, draw_depth)
        pixel, eye = 1.0 / lod_scale(cam), np.asarray(cam.position)
        lo, hi = widen_boxes(self.box_lo[query], self.box_hi[query], eye, pixel)  # ties go to the visible side
        thr = self.cfg.query_threshold
        if self.groups is None:
            samples = querier.query(lo, hi)
            passed, counts = samples > thr, {"queries_issued": len(query), "object_queries": len(query)}
        else:
            res = self.groups.run(query, lo, hi, querier.query, lambda a, b: boxes_reach_near(cam, a, b), thr,
                                  eye, pixel, lambda a, b: box_screen_area(cam, vp, a, b))
            passed = res.passed
            counts = {"queries_issued": res.issued, "object_queries": res.object_queries, "group_queries": res.group_queries,
                      "culled_by_group": res.culled_by_group}
        querier.end()
        stats.times_ms["vis_issue"] = 1e3 * (time.perf_counter() - t0 - querier.wait_s)
        stats.times_ms["vis_retrieve"] = 1e3 * querier.wait_s
        return passed, {**counts, "query_waits": querier.waits, "depth_pass_triangles": tris}

    def render(self, vis: Visible, stats: FrameStats, tint=(0.0, 0.0, 0.0, 0.0)) -> tuple[Image, bytes]:
        """Module 3: load, draw, read back and compress the sub-frame."""
        if self._ren is None:
            self._ren = SceneDrawer(self.sk, self.ram, self.cfg.gpu_mb << 20, self.cfg.egl_device)
            with self._ren.ctx:
                self._gl = renderer_string(self._ren.ctx)
        d, task = self._ren, vis.task
        obj, lv = task.items[vis.keep], task.levels[vis.keep]
        with d.ctx:
            t0 = time.perf_counter()
            obj, lv, c, coarser = self._resident(d, obj, lv, exact=False)
            stats.times_ms["load"] = (time.perf_counter() - t0) * 1e3
            img = d.view.render(task.camera, task.viewport, d.draw_fn(task.camera, obj, lv, tint), stats)
            if self.cfg.id_check:
                vis.ids["idbuffer_ids"] = self._id_check(d, task, obj, stats)
        stats.count("objects_drawn", len(obj))
        stats.count("frame_mesh_bytes", int(self.level_bytes[obj, lv].sum()))
        stats.count("drawn_coarser", coarser)
        if self.cfg.record_ids or self.cfg.id_check:
            vis.ids["drawn_ids"] = obj.tolist()
        for k, v in c.to_counters().items():
            stats.count(k, v)
        stats.count("ram_resident_bytes", self.ram.resident_bytes)
        stats.count("gpu_used_bytes", d.pool.used_bytes)
        with stats.stage("encode"):
            payload = encode_image(img, resolve_codec(world(), self.cfg.codec)[0])
        return img, payload

    def _resident(self, d: SceneDrawer, obj: np.ndarray, lv: np.ndarray, exact: bool):
        """What to draw of objects ``obj`` at levels ``lv``: (objects, levels, CacheCounts,
        drawn at a coarser level). ``--loading complete``: all of them, the frame waits for its
        loads. ``async``: the resident ones; the others are requested in the background (their
        coarsest level first) and meanwhile drawn at the finest coarser resident level — or,
        with ``exact`` (occluders: a coarser mesh may hide what the exact one shows), left out."""
        if self.cfg.loading == "complete" or len(obj) == 0:
            return obj, lv, d.ensure(obj, lv), 0
        g = d.geometry[obj]
        gone = ~d.pool.resident[g, lv]
        first = np.stack([g[gone], self.coarsest[obj[gone]]], 1).tolist()  # coarsest first: something to show soon
        c = d.cache.ensure([*map(tuple, first), *zip(g.tolist(), np.asarray(lv).tolist())], wait=False)
        res = d.pool.resident[g, lv]
        lv, coarser = np.array(lv, np.int64), 0
        if not exact and not res.all():
            miss = np.flatnonzero(~res)
            rows = d.pool.resident[g[miss]] & (np.arange(d.pool.resident.shape[1])[None] > lv[miss][:, None])
            has = rows.any(1)
            lv[miss[has]] = rows.argmax(1)[has]
            res[miss[has]] = True
            coarser = int(has.sum())
        return obj[res], lv[res], c, coarser

    def _id_check(self, d: SceneDrawer, task: ClientTask, drawn: np.ndarray, stats: FrameStats) -> list[int]:
        """``--id-check``: an ID-buffer render of every object in the sub-frustum at the frame's
        levels (loading them all); counts the objects it shows that were not drawn."""
        with stats.stage("id_check"):
            d.ensure(task.items, task.levels)
            if self._ids is None:
                self._ids = SceneIdBuffer(d.ctx, d.pool)
            truth = self._ids.visible(task.camera, task.viewport, task.items, d.geometry[task.items], task.levels, d.model[task.items])
        stats.count("idbuffer_visible", len(truth))
        stats.count("idbuffer_missed", int(len(np.setdiff1d(truth, drawn))))
        return truth.tolist()

    def release_visibility(self) -> None:
        """Free GPU 1's context (call on the thread that used it)."""
        if self._vis is not None:
            d, q = self._vis
            with d.ctx:
                q.release()
            d.release()
            self._vis = None

    def release_render(self) -> None:
        """Free GPU 2's context (call on the thread that used it)."""
        if self._ren is not None:
            if self._ids is not None:
                with self._ren.ctx:
                    self._ids.release()
                self._ids = None
            self._ren.release()
            self._ren = None

    def gl_renderer(self) -> str | None:
        """The GL renderer string of this client's render context (None before it drew anything;
        kept after the context is released)."""
        return self._gl

    def close(self) -> None:
        self.ram.close()
