"""Systems: per-frame plan → render → composite wiring of T1, T2, M1, M2 and the built-in scene."""

from __future__ import annotations

from ..core.errors import SceneNotFoundError
from .frameloop import FrameResult, display_tiles, render_frame

__all__ = ["open_system", "scene_kind", "FrameResult", "display_tiles", "render_frame"]


def scene_kind(spec: str) -> str:
    """"objects" or "terrain" for a scene name, or SceneNotFoundError saying what to give."""
    if spec.startswith("builtin:objects"):
        return "objects"
    from pathlib import Path

    p = Path(spec)
    if p.is_dir() and (p / "zarr.json").exists():
        from ..data.terrain import TerrainStore

        TerrainStore(p)  # raises a StoreError naming what is wrong with it
        return "terrain"
    raise SceneNotFoundError(
        f"scene {spec!r} not found: give builtin:objects[?n=COUNT&seed=S] or a terrain store "
        "(make one with `massview prepare terrain INPUT -o STORE` or `massview generate terrain STORE --size N`)"
    )


def open_system(spec: str, cfg=None):
    """The rendering system for a scene: ``builtin:objects[?n=..&seed=..]`` or a terrain store."""
    egl = getattr(cfg, "egl_device", None)
    if getattr(cfg, "system", "auto") == "roettger":
        from .roettger import RoettgerSystem

        return RoettgerSystem((spec, *cfg.layers), cfg)
    if scene_kind(spec) == "objects":
        from .objects import ObjectsSystem

        return ObjectsSystem(spec, egl)
    from .terrain import TerrainSystem

    kw = {} if cfg is None else {"cache_bytes": cfg.cache_mb << 20, "gpu_bytes": cfg.gpu_mb << 20, "loading": cfg.loading}
    return TerrainSystem(spec, egl_device=egl, **kw)
