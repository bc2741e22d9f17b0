"""Systems: per-frame plan → render → composite wiring of T1, T2, M1, M2 and the built-in scene."""

from __future__ import annotations

from ..core.errors import SceneNotFoundError
from .frameloop import FrameResult, display_tiles, render_frame

__all__ = ["open_system", "FrameResult", "display_tiles", "render_frame"]


def open_system(spec: str, egl_device: int | None = None):
    """The rendering system for a scene name: ``builtin:objects[?n=..&seed=..]``."""
    if spec.startswith("builtin:objects"):
        from .objects import ObjectsSystem

        return ObjectsSystem(spec, egl_device)
    raise SceneNotFoundError(
        f"scene {spec!r} not found: give builtin:objects[?n=COUNT&seed=S] (terrain stores come with `massview prepare terrain`)"
    )
