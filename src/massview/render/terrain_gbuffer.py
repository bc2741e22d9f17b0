"""Deferred terrain shading: a G-buffer that shares the target's depth, and the two passes.

Why: on llvmpipe a triangle that covers any pixel centre runs the fragment shader on a whole
4×4 stamp. With small triangles (a LOD front at one pixel of error: ~1 pixel each; full
resolution: sub-pixel) the forward path ran the per-pixel shading (page table, two pyramid
fetches, haze, sky) many times per pixel. Here pass 1 draws the geometry with a trivial shader
writing the shading's inputs (terrain_gbuffer.frag.glsl); pass 2 shades each written pixel once
(terrain_shade.frag.glsl). Both passes use the same ``terrain_lod()`` and ``terrain_color()``
(terrain_lod.glsl, terrain_shading.glsl) on the same float32 values as the forward shader, so
images are the forward path's bit for bit (tests/test_terrain_draw.py).

G-buffer per target (``W×H``): one RGBA32F texture (grid.xy, world z, pyramid level): 16 bytes
a pixel, one render target (the geometry pass's cost per 4×4 stamp grows with the targets it
writes). It is cleared to level −1 before each draw (colour only; the depth is the target's),
so pass 2 shades exactly the pixels pass 1 wrote in this draw.
"""

from __future__ import annotations

import moderngl

__all__ = ["GBuffers"]


def _alive(obj) -> bool:
    return type(obj.mglo).__name__ != "InvalidObject"


class GBuffers:
    """G-buffer framebuffers keyed by the target framebuffer they pair with (its depth
    attachment is shared, so the depth test of pass 1 is the forward path's)."""

    def __init__(self, ctx: moderngl.Context, keep: int = 4):
        self.ctx, self.keep = ctx, keep
        self._entries: list[tuple] = []  # (target, depth, fbo, textures)

    def begin(self, target: moderngl.Framebuffer) -> moderngl.Framebuffer:
        """The G-buffer framebuffer of ``target`` (created on first use), with ``target``'s
        viewport and scissor, cleared to level −1 inside the scissor (colour only) and bound."""
        depth = target.depth_attachment
        if depth is None:
            raise RuntimeError("deferred terrain shading needs a target with a depth attachment")
        self._entries = [e for e in self._entries if _alive(e[0]) and _alive(e[1]) or self._drop(e)]
        entry = next((e for e in self._entries if e[0] is target and e[1] is depth), None)
        if entry is None:
            if len(self._entries) >= self.keep:
                self._drop(self._entries.pop(0))
            w, h = target.size
            texs = [self.ctx.texture((w, h), 4, dtype="f4")]
            for t in texs:
                t.filter = (moderngl.NEAREST, moderngl.NEAREST)
            entry = (target, depth, self.ctx.framebuffer(color_attachments=texs, depth_attachment=depth), texs)
            self._entries.append(entry)
        fbo = entry[2]
        fbo.viewport, fbo.scissor = target.viewport, target.scissor
        fbo.depth_mask = False  # clear the colour only: the depth is the target's
        fbo.use()
        fbo.clear(0.0, 0.0, 0.0, -1.0)
        fbo.depth_mask = True
        fbo.use()
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
