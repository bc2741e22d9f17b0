"""The plain-mesh baseline of terrain drawing: the finest grid as one VBO and one index
buffer, drawn with one ``glDrawElements`` and per-vertex lighting (what a user would draw
without a terrain system; ``bench terrain`` and ``bench frame`` compare the K-patch path with
it). Vertices are interleaved (height float32, normal xy float16, colour RGBA8)."""

from __future__ import annotations

import moderngl
import numpy as np

from .context import load_shader

__all__ = ["VERTEX_BYTES", "pack_block", "PlainMeshRenderer"]

VERTEX_DTYPE = np.dtype([("h", "<f4"), ("n", "<f2", 2), ("c", "u1", 4)])
VERTEX_BYTES = VERTEX_DTYPE.itemsize
_LIGHT = np.array([-0.45, 0.35, 0.82])
_LIGHT = (_LIGHT / np.linalg.norm(_LIGHT)).astype("f4")


def pack_block(h: np.ndarray, color: np.ndarray | None, dx: float, dy: float, vscale: float,
               slopes: np.ndarray | None = None) -> np.ndarray:
    """(M·M,) interleaved vertices of a block; ``dx, dy`` are world metres between its samples.
    Normals from ``slopes`` (M, M, 2: ∂h/∂x east, ∂h/∂y north, the store's seamless shading
    maps) when given, else from central differences of the block (world frame: y = −row)."""
    if slopes is not None:
        gx, gy = (np.asarray(slopes[..., c], np.float32) * vscale for c in (0, 1))
        nx, ny = -gx, -gy
    else:
        gy, gx = np.gradient(h.astype(np.float32) * vscale, dy, dx)
        nx, ny = -gx, gy  # d/dy_world = −d/drow
    inv = 1.0 / np.sqrt(nx * nx + ny * ny + 1.0)
    out = np.empty(h.size, VERTEX_DTYPE)
    out["h"] = h.ravel()
    out["n"][:, 0] = (nx * inv).ravel()
    out["n"][:, 1] = (ny * inv).ravel()
    if color is None:
        out["c"] = (180, 170, 150, 255)
    else:
        out["c"][:, :3] = color.reshape(-1, 3)
        out["c"][:, 3] = 255
    return out


class PlainMeshRenderer:
    """The baseline without LOD: the finest level as one static indexed mesh (what a user
    would draw without a terrain system), with per-vertex lighting; shares the block packing.
    ``triangles``: (T, 3) uint32 indices into the row-major grid of ``heights`` (e.g. a LOD
    front's triangles, for equal-triangle throughput); default: the whole grid, row by row."""

    def __init__(self, ctx: moderngl.Context, heights: np.ndarray, color: np.ndarray | None, spacing, vscale: float,
                 triangles: np.ndarray | None = None):
        rows, cols = heights.shape
        self.ctx = ctx
        verts = pack_block(heights, color, spacing[0], spacing[1], vscale)
        self.vbo = ctx.buffer(verts.tobytes())
        self.inst = ctx.buffer(np.array([0, 0, 1, 0], np.int32).tobytes())
        if triangles is None:
            r, c = np.meshgrid(np.arange(rows - 1, dtype=np.uint32), np.arange(cols - 1, dtype=np.uint32), indexing="ij")
            a = (r * cols + c).ravel()
            idx = np.stack([a, a + cols, a + 1, a + 1, a + cols, a + cols + 1], 1).ravel()
        else:
            idx = np.ascontiguousarray(triangles, np.uint32).ravel()
        self.triangles = len(idx) // 3
        self.ibo = ctx.buffer(idx.tobytes())
        prog = self.prog = ctx.program(vertex_shader=load_shader("terrain_plain.vert.glsl"), fragment_shader=load_shader("terrain_plain.frag.glsl"))
        prog["u_M"].value = cols  # one grid row = one "block" row
        prog["u_scale"].value = (float(spacing[0]), float(spacing[1]), float(vscale))
        prog["u_light"].value = tuple(_LIGHT)
        self.vao = ctx.vertex_array(self.prog, [(self.vbo, "f 2f2 4f1", "in_h", "in_n", "in_color"), (self.inst, "4i/i", "in_slot")],
                                    index_buffer=self.ibo, index_element_size=4)

    def draw(self, mvp: np.ndarray) -> int:
        self.prog["u_mvp"].write(np.ascontiguousarray(mvp.T, dtype="f4").tobytes())
        self.prog["u_tint"].value = (0.0, 0.0, 0.0, 0.0)
        self.vao.render(moderngl.TRIANGLES)
        return self.triangles

    def release(self) -> None:
        for o in (self.vao, self.ibo, self.vbo, self.inst, self.prog):
            o.release()
