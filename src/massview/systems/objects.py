"""The built-in object scene as a parallel rendering system.

Plan (rank 0): sort-first tiles — for ``kd``, the screen rectangles of the visible objects'
boxes weighted by triangle count — or sort-last ranges R_i. Render (every rank): cull the
objects against the task's sub-frustum, keep the task's database range, draw with one
multi-draw-indirect call, read back the task's viewport.
"""

from __future__ import annotations

from urllib.parse import parse_qsl

import numpy as np

from ..core.camera import Camera
from ..core.config import RenderConfig
from ..core.errors import ConfigError
from ..core.image import Image
from ..core.stats import FrameStats
from ..core.task import Task
from ..data.generators import generate_objects
from ..lod.cull import screen_rects, spheres_in_frustum
from ..parallel.decompose import parse_decomposition, sort_first_tiles, sort_last_ranges
from ..render.context import create_context, release_gl
from ..render.meshes import MeshRenderer
from ..render.view import ViewRenderer

__all__ = ["ObjectsSystem"]


class ObjectsSystem:
    """``builtin:objects[?n=COUNT&seed=S]`` — a deterministic field of shaded meshes."""

    sort_last_modes: tuple[str, ...] = ()

    def __init__(self, spec: str = "builtin:objects", egl_device: int | None = None):
        params = dict(parse_qsl(spec.partition("?")[2]))
        unknown = set(params) - {"n", "seed"}
        if unknown:
            raise ConfigError(f"scene {spec!r}: unknown parameter(s) {', '.join(sorted(unknown))}; builtin:objects takes n and seed")
        try:
            n, seed = int(params.get("n", 3000)), int(params.get("seed", 7))
        except ValueError:
            raise ConfigError(f"scene {spec!r}: n and seed must be integers") from None
        self.spec = spec
        self.scene = generate_objects(n, seed)
        self._egl_device = egl_device
        self._gl = None

    # -- plan (pure numpy) ---------------------------------------------------------------
    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return self.scene.bounds

    @property
    def obstacles(self) -> tuple[np.ndarray, np.ndarray]:
        """The objects' boxes (about their bounding spheres), which ``walkthrough`` walks round."""
        c, r = self.scene.centers, self.scene.radii[:, None]
        return c - r, c + r

    def visible(self, camera: Camera, vp=None) -> np.ndarray:
        return np.nonzero(spheres_in_frustum(self.scene.centers, self.scene.radii, camera.frustum_planes(vp)))[0]

    def plan(self, camera: Camera, cfg: RenderConfig, nranks: int) -> list[Task]:
        kind, layout = parse_decomposition(cfg.decomposition, self.sort_last_modes)
        full = camera.viewport
        if kind == "sort-last":
            return [Task(i, full, data_range=r) for i, r in enumerate(sort_last_ranges(nranks))]
        rects = weights = None
        if layout in ("kd", "balanced"):
            vis = self.visible(camera)
            rects = screen_rects(camera, self.scene.box_lo[vis], self.scene.box_hi[vis])
            weights = self.scene.triangles[vis]
        tiles = sort_first_tiles(layout, nranks, camera.width, camera.height, cfg.grid, rects, weights)
        return [Task(i, vp) for i, vp in enumerate(tiles)]

    # -- render (GL) ---------------------------------------------------------------------
    def close(self) -> None:
        release_gl(self)

    def _renderers(self):
        if self._gl is None:
            ctx = create_context(self._egl_device)
            s = self.scene
            self._gl = (ctx, MeshRenderer(ctx, s.positions, s.normals, s.colors, s.indices, s.index_offset), ViewRenderer(ctx))
        return self._gl

    def render(self, task: Task, camera: Camera, cfg: RenderConfig, stats: FrameStats, tint=(0, 0, 0, 0)) -> Image:
        _, meshes, view = self._renderers()
        with stats.stage("lod"):
            items = self.visible(camera, None if task.viewport == camera.viewport else task.viewport)
            if task.data_range is not None:
                items = np.intersect1d(items, self.scene.range_items(*task.data_range), assume_unique=True)
            if task.items is not None:
                items = np.intersect1d(items, np.asarray(task.items), assume_unique=True)
        stats.count("objects", len(items))
        return view.render(camera, task.viewport, lambda mvp: meshes.draw(items, mvp, tint), stats, cfg.tile_targets)

    def render_reference(self, camera: Camera, cfg: RenderConfig) -> Image:
        """Everything, full frame, one rank: the serial image parallel results must equal."""
        full = Task(0, camera.viewport)
        return self.render(full, camera, RenderConfig(width=cfg.width, height=cfg.height), FrameStats(-1, 0))

    @property
    def renderer(self) -> str:
        from ..render.context import renderer_string

        return renderer_string(self._renderers()[0])
