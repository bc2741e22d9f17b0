"""Drawing triangle meshes held in one vertex/index buffer pair.

The scene's objects are concatenated into one VBO and one IBO (absolute uint32 indices);
object i owns ``index_offset[i]:index_offset[i+1]``. ``draw(items)`` draws any subset with a
single ``glMultiDrawElementsIndirect`` call: consecutive object ids are merged into one
command, so a contiguous database range costs one command and a culled list a few thousand
at most — never one Python draw call per object.
"""

from __future__ import annotations

import moderngl
import numpy as np

from .context import load_shader

__all__ = ["MeshRenderer", "rank_tint", "translated"]

_LIGHT = np.array([0.35, -0.45, 0.82])
_LIGHT = (_LIGHT / np.linalg.norm(_LIGHT)).astype("f4")

_TINTS = np.array(
    [[0.90, 0.30, 0.25], [0.25, 0.65, 0.95], [0.35, 0.85, 0.35], [0.95, 0.80, 0.20],
     [0.75, 0.40, 0.90], [0.20, 0.85, 0.80], [0.95, 0.55, 0.20], [0.60, 0.60, 0.60]]
)


def rank_tint(rank: int | None, strength: float = 0.55) -> tuple[float, float, float, float]:
    """RGBA tint for color-by-rank (alpha is the mix strength); no tint when rank is None."""
    if rank is None:
        return (0.0, 0.0, 0.0, 0.0)
    r, g, b = _TINTS[rank % len(_TINTS)]
    return (float(r), float(g), float(b), strength)


def _runs(items: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Start and end (exclusive) of maximal runs of consecutive ids in sorted ``items``."""
    if len(items) == 0:
        return np.empty(0, np.int64), np.empty(0, np.int64)
    brk = np.nonzero(np.diff(items) != 1)[0]
    starts = np.concatenate([[items[0]], items[brk + 1]])
    ends = np.concatenate([items[brk], [items[-1]]]) + 1
    return starts, ends


def translated(mvp: np.ndarray, origin) -> np.ndarray:
    """``mvp`` · translate(``origin``) in float64: the matrix for positions stored relative to
    ``origin`` (their float32 values stay small far from the world origin; the large
    translations cancel here, in float64, not in the shader's float32)."""
    if origin is None:
        return mvp
    t = np.eye(4)
    t[:3, 3] = origin
    return np.asarray(mvp, np.float64) @ t


class MeshRenderer:
    """Objects' meshes in one VBO/IBO; positions are relative to ``origin`` (world, float64;
    None: the world origin)."""

    def __init__(self, ctx: moderngl.Context, positions, normals, colors, indices, index_offset, origin=None):
        self.ctx = ctx
        self.origin = None if origin is None else np.asarray(origin, np.float64)
        self.index_offset = np.asarray(index_offset, np.int64)
        self.prog = ctx.program(vertex_shader=load_shader("mesh.vert.glsl"), fragment_shader=load_shader("mesh.frag.glsl"))
        self.prog["u_light"].value = tuple(_LIGHT)
        self._buffers = [
            ctx.buffer(np.ascontiguousarray(positions, "f4")),
            ctx.buffer(np.ascontiguousarray(normals, "f4")),
            ctx.buffer(np.ascontiguousarray(colors, "u1")),
        ]
        self._ibo = ctx.buffer(np.ascontiguousarray(indices, "u4"))
        self.vao = ctx.vertex_array(
            self.prog,
            [(self._buffers[0], "3f", "in_pos"), (self._buffers[1], "3f", "in_normal"), (self._buffers[2], "4f1", "in_color")],
            index_buffer=self._ibo,
            index_element_size=4,
        )
        self._indirect = None
        self.gpu_bytes = sum(b.size for b in self._buffers) + self._ibo.size

    def draw(self, items: np.ndarray, mvp: np.ndarray, tint=(0.0, 0.0, 0.0, 0.0)) -> int:
        """Draw objects ``items`` (sorted int array) with the float64 4x4 ``mvp``; returns the
        number of triangles submitted."""
        items = np.asarray(items, np.int64)
        if len(items) == 0:
            return 0
        starts, ends = _runs(items)
        first = self.index_offset[starts]
        count = self.index_offset[ends] - first
        cmds = np.zeros((len(starts), 5), np.uint32)
        cmds[:, 0] = count
        cmds[:, 1] = 1
        cmds[:, 2] = first
        data = cmds.tobytes()
        if self._indirect is None or self._indirect.size < len(data):
            if self._indirect is not None:
                self._indirect.release()
            self._indirect = self.ctx.buffer(reserve=max(len(data), 4096))
        self._indirect.write(data)
        self.prog["u_mvp"].write(np.ascontiguousarray(translated(mvp, self.origin).T, dtype="f4").tobytes())
        self.prog["u_tint"].value = tuple(tint)
        self.vao.render_indirect(self._indirect, mode=moderngl.TRIANGLES, count=len(starts))
        return int(count.sum() // 3)

    def release(self) -> None:
        self.vao.release()
        self.prog.release()
        for b in self._buffers:
            b.release()
        self._ibo.release()
        if self._indirect is not None:
            self._indirect.release()
