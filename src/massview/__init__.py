"""massview: parallel out-of-core rendering of massive terrains and polygon models.

The Python API (the CLI, demo, viewer and benchmarks are shells over it; see
:mod:`massview.api` and docs/ARCHITECTURE.md)::

    import massview as mv
    scene = mv.open_scene("dem.zarr")                     # or "builtin:objects"
    res = mv.render(scene, mv.path("flyover", scene, frames=4, size=(640, 480)), ranks=2)
    mv.show(res.images[0])

Layers (imports point down only): app → systems → parallel → render → lod → data → core.
"""

__version__ = "0.1.0"

from .api import (Frame, RankJobError, RenderResult, Scene, camera, open_scene, path, prepare_scene, prepare_terrain, render,
                  render_config, render_frame, scene_info, show, terrain_info, upgrade_terrain, verify_scene, verify_terrain)
from .core.camera import Camera, Viewport
from .core.config import RenderConfig
from .core.errors import MassviewError, MassviewWarning

__all__ = [
    "__version__",
    "open_scene", "camera", "path", "render", "render_frame", "show", "render_config",
    "prepare_terrain", "terrain_info", "verify_terrain", "upgrade_terrain", "prepare_scene", "scene_info", "verify_scene",
    "Scene", "RenderResult", "Frame", "Camera", "Viewport", "RenderConfig",
    "MassviewError", "MassviewWarning", "RankJobError",
]


class _Package(__import__("types").ModuleType):
    """``massview.render`` is the API function although ``massview/render/`` is also a
    subpackage (the GL layer): when that subpackage is imported, the import system binds it as an
    attribute of this package; the setter keeps it aside, so ``mv.render(...)`` stays the
    function. Code reaches the layer by import (``from massview.render.view import ...``), which
    goes through ``sys.modules`` and is unaffected."""

    @property
    def render(self):
        return _render_function

    @render.setter
    def render(self, module) -> None:
        self.__dict__["_render_layer"] = module


_render_function = render
__import__("sys").modules[__name__].__class__ = _Package
