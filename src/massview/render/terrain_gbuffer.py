"""Deferred terrain shading: G-buffers that share the target's depth, and the two passes.

Why: on llvmpipe a triangle that covers any pixel centre runs the fragment shader on a whole
4×4 stamp. At full resolution (33.5 M triangles on 1.3 M pixels) nearly every triangle is
sub-pixel, so the forward path ran the per-pixel shading (page table, two pyramid fetches,
haze, sky) ~16× per triangle instead of once per pixel. Here pass 1 draws the geometry with
a trivial shader writing the shading's inputs (terrain_gbuffer.frag.glsl); pass 2 shades each
written pixel once (terrain_shade.frag.glsl). Both passes call the same ``terrain_color()``
(terrain_shading.glsl) on the same float32 values the forward shader interpolates and
differentiates, so images are the forward path's bit for bit (tests/test_terrain_draw.py).

G-buffer per target (``W×H``): ``g0`` RGBA32F (grid.xy, dFdx grid.xy), ``g1`` RGBA32F (dFdy
grid.xy, world.xy), ``g2`` RG32F (world.z, draw serial): 40 bytes per pixel.
"""

from __future__ import annotations

import moderngl
import numpy as np

__all__ = ["GBuffers", "SERIAL_LIMIT"]

SERIAL_LIMIT = 1 << 24  # serials stay exact in float32


def _alive(obj) -> bool:
    return type(obj.mglo).__name__ != "InvalidObject"


class GBuffers:
    """G-buffer framebuffers keyed by the target framebuffer they pair with (its depth
    attachment is shared, so the depth test of pass 1 is the forward path's)."""

    def __init__(self, ctx: moderngl.Context, keep: int = 4):
        self.ctx, self.keep = ctx, keep
        self._entries: list[tuple] = []  # (target, depth, fbo, textures)
        self.serial = 0

    def next_serial(self) -> float:
        """A serial for the next draw; at the float32 limit every G-buffer is zeroed first, so
        no stale pixel can carry a reused serial."""
        self.serial += 1
        if self.serial >= SERIAL_LIMIT:
            for *_, texs in self._entries:
                for t in texs:
                    t.write(np.zeros(t.width * t.height * t.components, np.float32).tobytes())
            self.serial = 1
        return float(self.serial)

    def for_target(self, target: moderngl.Framebuffer) -> moderngl.Framebuffer:
        """The G-buffer framebuffer of ``target`` (created on first use), with ``target``'s
        viewport and scissor."""
        depth = target.depth_attachment
        if depth is None:
            raise RuntimeError("deferred terrain shading needs a target with a depth attachment")
        self._entries = [e for e in self._entries if _alive(e[0]) and _alive(e[1]) or self._drop(e)]
        entry = next((e for e in self._entries if e[0] is target and e[1] is depth), None)
        if entry is None:
            if len(self._entries) >= self.keep:
                self._drop(self._entries.pop(0))
            w, h = target.size
            texs = [self.ctx.texture((w, h), c, np.zeros(w * h * c, np.float32).tobytes(), dtype="f4") for c in (4, 4, 2)]
            for t in texs:
                t.filter = (moderngl.NEAREST, moderngl.NEAREST)
            entry = (target, depth, self.ctx.framebuffer(color_attachments=texs, depth_attachment=depth), texs)
            self._entries.append(entry)
        fbo = entry[2]
        fbo.viewport, fbo.scissor = target.viewport, target.scissor
        return fbo

    def textures(self, fbo: moderngl.Framebuffer) -> list[moderngl.Texture]:
        return next(e[3] for e in self._entries if e[2] is fbo)

    @staticmethod
    def _drop(entry) -> bool:
        entry[2].release()
        for t in entry[3]:
            t.release()
        return False

    def release(self) -> None:
        for e in self._entries:
            self._drop(e)
        self._entries.clear()
