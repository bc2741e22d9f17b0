"""Drawing T2 triangle fans on a visualization rank (Gouranton et al. §3.2.1).

A layer arrives as fans: ``lengths`` (uint32 vertices per fan: centre, then the closed ring),
``index`` (uint32 global sample index ``row · dim + col``) and ``height`` (float32), plus the
computation rank of each fan (for colour-by-rank). :class:`FanRenderer` uploads them as one
vertex stream (8 bytes + 4 for the rank) and one uint32 triangle list (the fans expanded to
triangles ``(v0, v_i, v_i+1)``), and draws the layer with one call. Positions are computed in
the vertex shader from the index, so every rank draws bit-identical vertices.
"""

from __future__ import annotations

from dataclasses import dataclass

import moderngl
import numpy as np

from .colormaps import DRAPE_COLORMAPS, LIGHT_WEIGHTS, Shading
from .context import load_shader
from .meshes import _TINTS

__all__ = ["LayerGeometry", "FanRenderer", "fan_triangles"]


@dataclass(frozen=True)
class LayerGeometry:
    """What a layer needs to place its vertices: samples per grid row (``dim``), spacing
    (dx, dy) metres, vertical scale, valid extent (rows, cols), height range, z offset."""

    dim: int
    spacing: tuple[float, float]
    vscale: float
    extent: tuple[int, int]
    zrange: tuple[float, float]
    zoffset: float = 0.0


def fan_triangles(lengths: np.ndarray) -> np.ndarray:
    """(T, 3) uint32 vertex numbers of the triangles of fans with ``lengths`` laid out one
    after the other in a vertex stream."""
    lens = np.asarray(lengths, np.int64)
    ntri = np.maximum(lens - 2, 0)
    if ntri.sum() == 0:
        return np.zeros((0, 3), np.uint32)
    starts = np.concatenate([[0], np.cumsum(lens)[:-1]])
    base = np.repeat(starts, ntri)
    first = np.concatenate([[0], np.cumsum(ntri)[:-1]])
    i = np.arange(ntri.sum()) - np.repeat(first, ntri) + 1
    return np.stack([base, base + i, base + i + 1], 1).astype(np.uint32)


class FanRenderer:
    """Draws T2 layers with T1's shading options (:class:`.colormaps.Shading`: ramp, sun, haze;
    exaggeration is the layers' vertical scale, see ``RoettgerSystem.layer_infos``), and a
    layer's orthophoto where :meth:`set_drape` gave it one."""

    def __init__(self, ctx: moderngl.Context, shading: Shading | None = None, world_size: float = 1.0):
        from .colormaps import SKY_HORIZON, SKY_ZENITH

        self.ctx = ctx
        self.prog = ctx.program(vertex_shader=load_shader("roettger.vert.glsl"),
                                fragment_shader=load_shader("roettger.frag.glsl") + load_shader("sky.glsl"))
        self.prog["u_tints"].write(np.ascontiguousarray(_TINTS, "f4").tobytes())
        self.prog["u_sky_horizon"].value = tuple(SKY_HORIZON)
        self.prog["u_sky_zenith"].value = tuple(SKY_ZENITH)
        self.prog["u_light"].value = LIGHT_WEIGHTS
        self._ramp = ctx.texture((256, 1), 3, dtype="f1")
        self._ramp.filter = (moderngl.LINEAR, moderngl.LINEAR)
        self._ramp.repeat_x = self._ramp.repeat_y = False
        self.prog["u_ramp"].value = 0
        self.prog["u_drape"].value = 1
        self._drapes: dict = {}  # layer → (mipmapped texture, level, side)
        self._no_drape = ctx.texture((1, 1), 3, b"\x80\x80\x80")  # (bound to unit 1 when a layer has none)
        self.world_size = float(world_size)
        self.set_shading(shading or Shading())
        self._bufs: list = []

    def set_drape(self, layer: int, image: np.ndarray, level: int) -> None:
        """Drape ``image`` ((side, side, 3) uint8, :func:`massview.data.terrain.drape.color_image`
        of ``level``) over layer ``layer``: its colour replaces the ramp's there."""
        side = int(image.shape[0])
        tex = self.ctx.texture((side, side), 3, np.ascontiguousarray(image, np.uint8).tobytes(), alignment=1)
        tex.build_mipmaps()
        tex.filter = (moderngl.LINEAR_MIPMAP_LINEAR, moderngl.LINEAR)
        tex.repeat_x = tex.repeat_y = False
        old = self._drapes.pop(layer, None)
        if old is not None:
            old[0].release()
        self._drapes[layer] = (tex, int(level), side)

    def set_shading(self, sh: Shading) -> None:
        """Sun, colour ramp and haze of the next draws (``ortho`` and ``none``: uniform grey where
        a layer has no drape, as T1 without an orthophoto; ``auto``: hypsometric there)."""
        from .colormaps import ramp

        name = "hypsometric" if sh.colormap == "auto" else sh.colormap
        self.prog["u_sun"].value = tuple(float(v) for v in sh.sun_vector())
        self._ramp.write(ramp(name).tobytes())
        self.prog["u_haze"].value = sh.extinction(self.world_size)
        self.shading = sh

    def set_eye(self, eye, haze_from: float = 0.0) -> None:
        self.prog["u_eye"].value = tuple(float(v) for v in eye)
        self.prog["u_haze_from"].value = float(haze_from)

    def draw(self, geom: LayerGeometry, lengths: np.ndarray, index: np.ndarray, height: np.ndarray, rank: np.ndarray,
             mvp: np.ndarray, tint: bool = False, layer: int = 0) -> int:
        """Draw one layer's fans (``rank`` per fan; ``layer``: which drape, if any); returns the
        triangles drawn."""
        tris = fan_triangles(lengths)
        if len(tris) == 0:
            return 0
        verts = np.empty(len(index), np.dtype([("i", "<u4"), ("h", "<f4"), ("r", "<f4")]))
        verts["i"], verts["h"] = index, height
        verts["r"] = np.repeat(np.asarray(rank, np.float32), np.asarray(lengths, np.int64))
        vbo, ibo = self.ctx.buffer(verts.tobytes()), self.ctx.buffer(tris.tobytes())
        vao = self.ctx.vertex_array(self.prog, [(vbo, "u4 f4 f4", "in_idx", "in_h", "in_rank")], index_buffer=ibo, index_element_size=4)
        p = self.prog
        p["u_mvp"].write(np.ascontiguousarray(mvp.T, dtype="f4").tobytes())
        p["u_dim"].value = int(geom.dim)
        p["u_scale"].value = (float(geom.spacing[0]), float(geom.spacing[1]), float(geom.vscale))
        p["u_zoffset"].value = float(geom.zoffset)
        p["u_extent"].value = (float(geom.extent[1] - 1), float(geom.extent[0] - 1))
        p["u_zrange"].value = (float(geom.zrange[0]), float(geom.zrange[1]))
        p["u_tint_on"].value = 1 if tint else 0
        self._ramp.use(0)
        drape = self._drapes.get(layer) if self.shading.colormap in DRAPE_COLORMAPS else None  # (a ramp named: the ramp)
        p["u_drape_on"].value = 0 if drape is None else 1
        if drape is None:
            self._no_drape.use(1)
        else:
            drape[0].use(1)
            p["u_drape_map"].value = (1.0 / (1 << drape[1]), float(drape[2]))
        vao.render(moderngl.TRIANGLES)
        self._bufs.append((vao, vbo, ibo))
        return len(tris)

    def end_frame(self) -> None:
        """Release this frame's buffers (call after the pixels are read back)."""
        for vao, vbo, ibo in self._bufs:
            vao.release()
            vbo.release()
            ibo.release()
        self._bufs.clear()

    def release(self) -> None:
        self.end_frame()
        for tex, _, _ in self._drapes.values():
            tex.release()
        self._drapes.clear()
        self._no_drape.release()
        self._ramp.release()
        self.prog.release()
