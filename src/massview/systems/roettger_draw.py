"""T2's visualization side: gather the fans held from every computation rank and draw them.

Fans are drawn in one canonical order, per layer by the Morton code of their centre sample:
the order the serial reference emits, whatever the partition or the order messages arrived
in, so the parallel image equals the serial one bit for bit.
"""

from __future__ import annotations

import numpy as np

from ..core.camera import Camera, Viewport
from ..core.image import Image
from ..core.stats import FrameStats
from ..lod.roettger import morton2
from ..render.colormaps import Shading, haze_start
from ..render.context import create_context, renderer_string
from ..render.roettger import FanRenderer, LayerGeometry
from ..render.view import ViewRenderer
from .roettger_portion import LayerInfo

__all__ = ["FanDrawer", "gather_layers", "canonical_order"]

Layer = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]  # lengths, index, height, rank per fan


def canonical_order(lengths: np.ndarray, index: np.ndarray, S: int) -> np.ndarray:
    """Fan permutation sorting by the Morton code of each fan's centre (its first vertex)."""
    starts = np.concatenate([[0], np.cumsum(lengths.astype(np.int64))[:-1]])
    centre = index[starts].astype(np.int64) if len(lengths) else np.zeros(0, np.int64)
    return np.argsort(morton2(centre // S, centre % S), kind="stable")


def _permute(lengths, arrays, order):
    lens = lengths.astype(np.int64)
    starts = np.concatenate([[0], np.cumsum(lens)[:-1]])
    nl = lens[order]
    newstart = np.concatenate([[0], np.cumsum(nl)[:-1]])
    gather = np.repeat(starts[order] - newstart, nl) + np.arange(nl.sum())
    return lengths[order], [a[gather] for a in arrays]


def gather_layers(held_by_rank: list, infos: list[LayerInfo]) -> list[Layer]:
    """``held_by_rank[k][layer]`` (HeldFans from computation rank k) → one canonical layer list."""
    out = []
    for li, info in enumerate(infos):
        parts = [h[li] for h in held_by_rank]
        lengths = np.concatenate([p.lengths for p in parts]).astype(np.uint32)
        index = np.concatenate([p.index for p in parts]).astype(np.uint32)
        height = np.concatenate([p.height for p in parts]).astype(np.float32)
        rank = np.concatenate([np.full(len(p.lengths), k, np.int64) for k, p in enumerate(parts)])
        order = canonical_order(lengths, index, info.index_dim)
        lengths, (index, height) = _permute(lengths, [index, height], order)
        out.append((lengths, index, height, rank[order]))
    return out


class FanDrawer:
    """GL context, fan renderer and framebuffers of a visualization rank."""

    def __init__(self, infos: list[LayerInfo], egl_device: int | None = None, shading: Shading | None = None):
        self.ctx = create_context(egl_device)
        los, his = zip(*(i.bounds() for i in infos))
        self._lo, self._hi = np.min(los, axis=0), np.max(his, axis=0)
        self._size = float(np.hypot(*(self._hi - self._lo)[:2]))  # the haze scale: the horizontal diagonal, as T1's
        self.fans = FanRenderer(self.ctx, shading, self._size)
        self.view = ViewRenderer(self.ctx)
        self.geoms = [LayerGeometry(i.index_dim, i.spacing, i.vscale, (i.rows, i.cols), i.zrange, i.zoffset) for i in infos]


    @property
    def renderer(self) -> str:
        return renderer_string(self.ctx)

    def draw(self, camera: Camera, vp: Viewport, layers: list[Layer], tint: bool, stats: FrameStats) -> Image:
        def draw(mvp):
            return sum(self.fans.draw(g, *layer, mvp, tint, li) for li, (g, layer) in enumerate(zip(self.geoms, layers)))

        self.fans.set_eye(camera.position, haze_start(camera.position, self._lo, self._hi, self._size))

        try:
            return self.view.render(camera, vp, draw, stats)
        finally:
            self.fans.end_frame()

    def release(self) -> None:
        self.fans.release()
        self.view.release()
