"""Hardware occlusion queries on bounding boxes (Revanth & Narayanan 2012, §3.5).

:meth:`OcclusionQuerier.test` does one client's visibility pass for one frame:

1. bind a depth-only target of the full image size, scissored to the client's viewport, and
   run the caller's depth pre-pass (``draw_depth(mvp)``: the potential occluders and the
   previous frame's visible objects — the caller picks their geometry and LOD);
2. with depth writes off and the depth test ``<=``, draw each candidate's box (12 triangles)
   inside its own ``GL_SAMPLES_PASSED`` query;
3. collect the sample counts (:meth:`OcclusionQuerier.begin`, then :meth:`~OcclusionQuerier.query`
   any number of times — the M1 client's group-tree walk calls it once per round — then
   :meth:`~OcclusionQuerier.end`; :meth:`~OcclusionQuerier.test` does all three). Queries are **batched**: a batch of up to ``batch`` boxes is
   issued before the results of the previous batch are read, so one frame blocks on results
   ``ceil(n / batch)`` times (once with the default, unbounded batch), never once per object.

An object passes when more than ``threshold`` samples (pixels) of its box survive. The box
contains the object, so a pixel where the object is in front of every occluder is a pixel
where the box is too: with exact occluder geometry the test is conservative. Boxes reaching
in front of the near plane are clipped and must not be queried
(:func:`massview.lod.visibility.boxes_reach_near` sorts them out first).

:class:`IdBuffer` is the test oracle: it draws objects with their ids as colours and returns
the ids that own at least one pixel of a viewport. :class:`SceneIdBuffer` does the same over
a scene's GL mesh pool (the meshes and levels a client renders), so the running M1 system can
check its own culling (``--id-check``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable

import moderngl
import numpy as np

from ..core.camera import Camera, Viewport
from .context import check_frame_size, load_shader

__all__ = ["QueryResult", "OcclusionQuerier", "IdBuffer", "SceneIdBuffer", "box_vertices"]

# 12 triangles over the 8 corners; corner c has x = hi if c & 1, y = hi if c & 2, z = hi if c & 4
_BOX_TRIANGLES = np.array([
    0, 2, 1, 1, 2, 3,  4, 5, 6, 5, 7, 6,  0, 1, 4, 1, 5, 4,
    2, 6, 3, 3, 6, 7,  0, 4, 2, 2, 4, 6,  1, 3, 5, 3, 7, 5], np.int64)
_CORNER_BITS = np.array([[(c >> k) & 1 for k in range(3)] for c in range(8)], bool)


def box_vertices(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(n·36, 3) float32 triangle vertices of the world boxes ``[lo, hi]`` ((n, 3) each)."""
    lo = np.asarray(lo, np.float64).reshape(-1, 3)
    hi = np.asarray(hi, np.float64).reshape(-1, 3)
    corners = np.where(_CORNER_BITS[None], hi[:, None, :], lo[:, None, :])  # (n, 8, 3)
    return corners[:, _BOX_TRIANGLES].reshape(-1, 3).astype(np.float32)


def _scissor(camera: Camera, vp: Viewport) -> tuple[int, int, int, int]:
    return vp.x, camera.height - vp.y - vp.h, vp.w, vp.h


@dataclass(frozen=True)
class QueryResult:
    """samples: (n,) int64 samples passed per box; passed: samples > threshold;
    waits: times the frame blocked on query results; depth_triangles: pre-pass triangles;
    issue_ms: depth pass and issuing the queries; retrieve_ms: collecting the results."""

    samples: np.ndarray
    passed: np.ndarray
    waits: int
    depth_triangles: int
    issue_ms: float = 0.0
    retrieve_ms: float = 0.0

    @property
    def issued(self) -> int:
        return int(len(self.samples))


class OcclusionQuerier:
    """One client's occlusion-query pass on its own GL context (the paper's GPU 1)."""

    def __init__(self, ctx: moderngl.Context, batch: int = 0):
        self.ctx = ctx
        self.batch = int(batch)
        self.prog = ctx.program(vertex_shader=load_shader("box.vert.glsl"), fragment_shader=load_shader("box.frag.glsl"))
        self._queries: list[moderngl.Query] = []
        self._vbo = None
        self._vao = None
        self._fbo = None
        self._size = None
        self._mvp = None
        self.waits, self.wait_s = 0, 0.0  # of the current frame (since begin)

    def _target(self, w: int, h: int) -> moderngl.Framebuffer:
        if self._size != (w, h):
            if self._fbo is not None:
                self._fbo.depth_attachment.release()
                self._fbo.release()
            self._fbo = self.ctx.framebuffer(color_attachments=[], depth_attachment=self.ctx.depth_renderbuffer((w, h)))
            self._size = (w, h)
        return self._fbo

    def _upload_boxes(self, verts: np.ndarray) -> None:
        data = verts.tobytes()
        if self._vbo is None or self._vbo.size < len(data):
            for o in (self._vao, self._vbo):
                if o is not None:
                    o.release()
            self._vbo = self.ctx.buffer(reserve=max(len(data) * 2, 1 << 16))
            self._vao = self.ctx.vertex_array(self.prog, [(self._vbo, "3f", "in_pos")])
        self._vbo.write(data)

    def begin(self, camera: Camera, vp: Viewport, draw_depth: Callable[[np.ndarray], int] | None) -> int:
        """Step 1: bind the depth target (scissored to ``vp``) and run the depth pre-pass;
        returns its triangles. :meth:`query` may then be called any number of times."""
        fbo = self._target(camera.width, camera.height)
        fbo.use()
        self.ctx.scissor = None
        fbo.depth_mask = True
        fbo.clear(depth=1.0)
        self.ctx.enable(moderngl.DEPTH_TEST)
        self.ctx.disable(moderngl.CULL_FACE)
        self.ctx.scissor = _scissor(camera, vp)
        self.ctx.depth_func = "<"
        self._mvp = camera.view_projection()
        self.waits, self.wait_s = 0, 0.0
        return int(draw_depth(self._mvp)) if draw_depth is not None else 0

    def query(self, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        """Step 2: (n,) int64 samples passed by each box ``[lo[i], hi[i]]`` against the depth
        pre-pass (depth writes off, so the boxes do not occlude one another). One call blocks
        ``ceil(n / batch)`` times (once with the default batch); counted in ``waits``."""
        samples = np.zeros(len(lo), np.int64)
        if len(lo):
            w, s = self._query_boxes(self._fbo, self._mvp, lo, hi, samples)
            self.waits += w
            self.wait_s += s
        return samples

    def end(self) -> None:
        self.ctx.scissor = None

    def test(self, camera: Camera, vp: Viewport, draw_depth: Callable[[np.ndarray], int] | None,
             lo: np.ndarray, hi: np.ndarray, threshold: int = 0) -> QueryResult:
        """Depth pre-pass, then one query per box ``[lo[i], hi[i]]``; see the module doc."""
        t0 = time.perf_counter()
        tris = self.begin(camera, vp, draw_depth)
        samples = self.query(lo, hi)
        self.end()
        total = time.perf_counter() - t0
        return QueryResult(samples, samples > int(threshold), self.waits, tris, 1e3 * (total - self.wait_s), 1e3 * self.wait_s)

    def _query_boxes(self, fbo, mvp: np.ndarray, lo: np.ndarray, hi: np.ndarray, samples: np.ndarray) -> tuple[int, float]:
        """Issue the box queries batch by batch, collecting batch b after issuing b+1; fills
        ``samples``; returns (waits, seconds spent waiting)."""
        n = len(lo)
        while len(self._queries) < n:
            self._queries.append(self.ctx.query(samples=True))
        self._upload_boxes(box_vertices(lo, hi))
        self.prog["u_mvp"].write(np.ascontiguousarray(mvp.T, dtype="f4").tobytes())
        fbo.depth_mask = False
        self.ctx.depth_func = "<="
        step = self.batch if self.batch > 0 else n
        waits, wait_s, pending = 0, 0.0, None
        for start in list(range(0, n, step)) + [None]:
            if start is not None:
                for i in range(start, min(start + step, n)):
                    with self._queries[i]:
                        self._vao.render(moderngl.TRIANGLES, vertices=36, first=36 * i)
            if pending is not None:
                t1 = time.perf_counter()
                waits += self._collect(samples, *pending)
                wait_s += time.perf_counter() - t1
            pending = None if start is None else (start, min(start + step, n))
        fbo.depth_mask = True
        self.ctx.depth_func = "<"
        return waits, wait_s

    def _collect(self, out: np.ndarray, start: int, stop: int) -> int:
        """Read the results of queries [start, stop): one blocking wait for the batch."""
        for i in range(start, stop):
            out[i] = self._queries[i].samples
        return 1

    def release(self) -> None:
        self._queries.clear()  # moderngl 5 queries have no release: they go with the context
        for o in (self._vao, self._vbo, self.prog):
            if o is not None:
                o.release()
        if self._fbo is not None:
            self._fbo.depth_attachment.release()
            self._fbo.release()


class IdBuffer:
    """Draws objects with their id as colour (depth test ``<``, in id order, as the renderer
    does) and reports the ids owning pixels: the ground truth of visibility."""

    def __init__(self, ctx: moderngl.Context, positions: np.ndarray, indices: np.ndarray, index_offset: np.ndarray):
        self.ctx = ctx
        self.index_offset = np.asarray(index_offset, np.int64)
        self.prog = ctx.program(vertex_shader=load_shader("box.vert.glsl"), fragment_shader=load_shader("id.frag.glsl"))
        self._vbo = ctx.buffer(np.ascontiguousarray(positions, "f4"))
        self._ibo = ctx.buffer(np.ascontiguousarray(indices, "u4"))
        self._vao = ctx.vertex_array(self.prog, [(self._vbo, "3f", "in_pos")], index_buffer=self._ibo, index_element_size=4)

    def visible(self, camera: Camera, vp: Viewport, items: np.ndarray) -> np.ndarray:
        """Sorted ids among ``items`` that own at least one pixel of ``vp``."""
        check_frame_size(self.ctx, camera.width, camera.height)
        color = self.ctx.renderbuffer((camera.width, camera.height), 4, dtype="f1")
        depth = self.ctx.depth_renderbuffer((camera.width, camera.height))
        fbo = self.ctx.framebuffer(color_attachments=[color], depth_attachment=depth)
        try:
            fbo.use()
            self.ctx.scissor = None
            fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
            self.ctx.enable(moderngl.DEPTH_TEST)
            self.ctx.disable(moderngl.CULL_FACE)
            self.ctx.depth_func = "<"
            self.prog["u_mvp"].write(np.ascontiguousarray(camera.view_projection().T, dtype="f4").tobytes())
            for i in np.sort(np.asarray(items, np.int64)):
                first, stop = self.index_offset[i], self.index_offset[i + 1]
                self.prog["u_id"].value = int(i) + 1
                self._vao.render(moderngl.TRIANGLES, vertices=int(stop - first), first=int(first))
            raw = fbo.read(viewport=_scissor(camera, vp), components=4, dtype="f1")
        finally:
            fbo.release()
            color.release()
            depth.release()
        px = np.frombuffer(raw, np.uint8).reshape(-1, 4).astype(np.int64)
        ids = px[:, 0] | (px[:, 1] << 8) | (px[:, 2] << 16)
        return np.unique(ids[ids > 0]) - 1

    def release(self) -> None:
        for o in (self._vao, self._ibo, self._vbo, self.prog):
            o.release()


_ID_INSTANCE = np.dtype([("m", "<f4", 16), ("id", "<f4")])


class SceneIdBuffer:
    """The ID-buffer oracle over a :class:`~massview.render.scene.MeshPool`: objects drawn
    at the levels a frame renders, with their world matrices, camera-relative as
    :class:`~massview.render.scene.SceneRenderer` draws them, depth test ``<`` in id order."""

    def __init__(self, ctx: moderngl.Context, pool):
        self.ctx, self.pool = ctx, pool
        self.prog = ctx.program(vertex_shader=load_shader("scene_id.vert.glsl"), fragment_shader=load_shader("scene_id.frag.glsl"))

    def visible(self, camera: Camera, vp: Viewport, ids: np.ndarray, geometry: np.ndarray, level: np.ndarray,
                model: np.ndarray) -> np.ndarray:
        """Sorted ``ids`` ((k,) int, < 2^24 − 1) whose mesh ``(geometry, level)`` (resident in the
        pool) with world matrix ``model`` ((k, 4, 4) float64) owns a pixel of ``vp``."""
        order = np.argsort(np.asarray(ids, np.int64), kind="stable")
        ids, geometry, level, model = np.asarray(ids)[order], np.asarray(geometry)[order], np.asarray(level)[order], np.asarray(model)[order]
        k, p = len(ids), self.pool
        if k == 0 or vp.empty:
            return np.zeros(0, np.int64)
        if not p.resident[geometry, level].all():
            raise RuntimeError("SceneIdBuffer: every mesh must be resident in the GL pool")
        eye = np.asarray(camera.position, np.float64)
        rel = np.array(model, np.float64)
        rel[:, :3, 3] -= eye
        inst = np.empty(k, _ID_INSTANCE)
        inst["m"] = rel.transpose(0, 2, 1).reshape(k, 16)
        inst["id"] = ids + 1
        cmds = np.stack([p.index_count[geometry, level], np.ones(k), p.first_index[geometry, level],
                         p.base_vertex[geometry, level], np.arange(k)], 1).astype(np.uint32)
        shift = np.eye(4)
        shift[:3, 3] = eye
        return self._draw_read(camera, vp, inst, cmds, camera.view_projection() @ shift)

    def _draw_read(self, camera, vp, inst, cmds, vp_matrix) -> np.ndarray:
        ctx = self.ctx
        ib, cb = ctx.buffer(inst.tobytes()), ctx.buffer(cmds.tobytes())
        vao = ctx.vertex_array(self.prog, [(self.pool.buffer, "3f 12x", "in_pos"), (ib, "4f 4f 4f 4f 1f/i", "in_m0", "in_m1", "in_m2", "in_m3", "in_id")],
                               index_buffer=self.pool.buffer, index_element_size=4)
        check_frame_size(ctx, camera.width, camera.height)
        color = ctx.renderbuffer((camera.width, camera.height), 4, dtype="f1")
        depth = ctx.depth_renderbuffer((camera.width, camera.height))
        fbo = ctx.framebuffer(color_attachments=[color], depth_attachment=depth)
        try:
            fbo.use()
            ctx.scissor = None
            fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
            ctx.enable(moderngl.DEPTH_TEST)
            ctx.disable(moderngl.CULL_FACE)
            ctx.depth_func = "<"
            self.prog["u_vp"].write(np.ascontiguousarray(vp_matrix.T, dtype="f4").tobytes())
            vao.render_indirect(cb, mode=moderngl.TRIANGLES, count=len(cmds))
            raw = fbo.read(viewport=_scissor(camera, vp), components=4, dtype="f1")
        finally:
            for o in (fbo, color, depth, vao, ib, cb):
                o.release()
        px = np.frombuffer(raw, np.uint8).reshape(-1, 4).astype(np.int64)
        found = px[:, 0] | (px[:, 1] << 8) | (px[:, 2] << 16)
        return np.unique(found[found > 0]) - 1

    def release(self) -> None:
        self.prog.release()
