"""Rendering one task's viewport with either target strategy, with stage timing.

``ViewRenderer.render(camera, vp, draw, stats, tile_target)`` calls ``draw(mvp)`` (which issues
the GL draws and returns triangles submitted) and reads back the pixels of ``vp``:

* default: a full-size target, full-frame matrix, scissor = ``vp`` → bit-identical to the
  same pixels of a serial full-frame render;
* ``tile_target=True``: a ``vp``-sized target with the off-axis sub-frustum (what a display
  wall larger than one framebuffer needs), equal up to rasterization rounding (~1e-4 of pixels
  on llvmpipe).

Framebuffers are cached per size. Stages recorded: ``draw`` (including ``glFinish``) and
``readback``.
"""

from __future__ import annotations

from typing import Callable

import moderngl
import numpy as np

from ..core.camera import Camera, Viewport
from ..core.image import Image, blank_image
from ..core.stats import FrameStats
from .context import finish
from .framebuffer import Framebuffer

__all__ = ["ViewRenderer"]


class ViewRenderer:
    def __init__(self, ctx: moderngl.Context):
        self.ctx = ctx
        self._fbs: dict[tuple[int, int], Framebuffer] = {}

    def _fb(self, w: int, h: int) -> Framebuffer:
        fb = self._fbs.get((w, h))
        if fb is None:
            if len(self._fbs) > 4:  # sizes change (kd tiles): keep only a few
                for old in self._fbs.values():
                    old.release()
                self._fbs.clear()
            fb = self._fbs[(w, h)] = Framebuffer(self.ctx, w, h)
        return fb

    def render(self, camera: Camera, vp: Viewport, draw: Callable[[np.ndarray], int], stats: FrameStats,
               tile_target: bool = False) -> Image:
        if vp.empty:
            return blank_image(vp)
        with stats.stage("draw"):
            if tile_target:
                fb = self._fb(vp.w, vp.h)
                fb.begin()
                stats.triangles += draw(camera.view_projection(vp))
            else:
                fb = self._fb(camera.width, camera.height)
                full = vp == camera.viewport
                fb.begin(scissor=None if full else vp)
                stats.triangles += draw(camera.view_projection())
            finish(self.ctx)  # releases the GIL while the raster threads draw
        with stats.stage("readback"):
            return fb.read(vp, origin=vp if tile_target else None)

    def release(self) -> None:
        for fb in self._fbs.values():
            fb.release()
        self._fbs.clear()
