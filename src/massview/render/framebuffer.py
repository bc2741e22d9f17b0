"""Offscreen RGBA8 + depth framebuffers and readback to numpy, top-left origin.

A :class:`Framebuffer` of size W×H renders either

* the **full-frame** way: full-size target, full-frame matrices, a scissor rectangle limiting
  writes to the task's viewport — bit-identical to the same pixels of a serial render; or
* the **tile** way: a target the size of the viewport, with the camera's off-axis sub-frustum.

``read(vp)`` returns an :class:`Image` of the pixels of ``vp`` with rows flipped from GL's
bottom-left origin to the project's top-left origin. Depth is window depth in [0, 1], float32.
Readback goes into a staging array preallocated per framebuffer (``glReadPixels`` straight into
numpy memory, no intermediate ``bytes``), then one flipping copy per plane into the Image's own
arrays. (Pixel-pack buffers would make the read asynchronous on a GPU; on llvmpipe the read is
a memcpy from the tiles either way, and the frame waits for it at ``glFinish`` already.)
"""

from __future__ import annotations

import moderngl
import numpy as np

from ..core.camera import Viewport
from ..core.image import BACKGROUND_RGBA, Image
from .context import check_frame_size

__all__ = ["Framebuffer"]


class Framebuffer:
    def __init__(self, ctx: moderngl.Context, width: int, height: int):
        self.ctx = ctx
        self.width, self.height = int(width), int(height)
        check_frame_size(ctx, self.width, self.height)
        self._color = ctx.renderbuffer((self.width, self.height), 4, dtype="f1")
        self._depth = ctx.depth_texture((self.width, self.height))
        self.fbo = ctx.framebuffer(color_attachments=[self._color], depth_attachment=self._depth)
        self._stage = np.empty(self.width * self.height * 8, np.uint8)  # readback staging: colour then depth

    @property
    def nbytes(self) -> int:
        return self.width * self.height * 8

    def gl_rect(self, vp: Viewport, origin: Viewport | None = None) -> tuple[int, int, int, int]:
        """GL (x, y, w, h) with bottom-left origin of ``vp`` inside a target whose pixel (0, 0)
        is ``origin``'s top-left corner (default: the full image)."""
        ox, oy = (origin.x, origin.y) if origin else (0, 0)
        return vp.x - ox, self.height - (vp.y - oy) - vp.h, vp.w, vp.h

    def begin(self, scissor: Viewport | None = None) -> None:
        """Bind, clear to the background (whole target) and set viewport and scissor."""
        self.fbo.use()
        self.ctx.scissor = None
        self.fbo.viewport = (0, 0, self.width, self.height)
        r, g, b, a = (c / 255.0 for c in BACKGROUND_RGBA)
        self.fbo.clear(r, g, b, a, depth=1.0)
        self.ctx.enable(moderngl.DEPTH_TEST)
        self.ctx.depth_func = "<"
        self.ctx.disable(moderngl.CULL_FACE)
        if scissor is not None:
            self.ctx.scissor = self.gl_rect(scissor)

    def read(self, vp: Viewport, origin: Viewport | None = None) -> Image:
        """Read the pixels of ``vp`` (destination coordinates); ``origin`` is the viewport the
        target covers when it is a tile-sized target."""
        self.ctx.scissor = None
        rect = self.gl_rect(vp, origin)
        n = vp.w * vp.h
        color, depth = self._stage[:4 * n], self._stage[4 * n:8 * n]
        self.fbo.read_into(color, viewport=rect, components=4, dtype="f1")
        self.fbo.read_into(depth, viewport=rect, components=1, attachment=-1, dtype="f4")
        color = color.reshape(vp.h, vp.w, 4)[::-1].copy()  # the one copy: flip into the Image's own arrays
        depth = depth.view(np.float32).reshape(vp.h, vp.w)[::-1].copy()
        return Image(color, depth, vp)

    def release(self) -> None:
        self.fbo.release()
        self._color.release()
        self._depth.release()
