"""Systems: per-frame plan → render → composite wiring of T1, T2, M1, M2 and the built-in scene."""

from __future__ import annotations

from ..core.errors import ConfigError, SceneNotFoundError
from .frameloop import FrameResult, display_tiles, render_frame

__all__ = ["open_system", "scene_kind", "FrameResult", "display_tiles", "render_frame"]


def scene_kind(spec: str) -> str:
    """"objects", "scene" or "terrain" for a scene name, or SceneNotFoundError saying what to give."""
    if spec.startswith("builtin:objects"):
        return "objects"
    from pathlib import Path

    p = Path(spec)
    from ..data.scene import is_scene_store

    if p.is_dir() and is_scene_store(p):
        return "scene"
    if p.is_dir() and (p / "zarr.json").exists():
        from ..data.terrain import TerrainStore

        TerrainStore(p)  # raises a StoreError naming what is wrong with it
        return "terrain"
    if p.exists():
        what = "a folder without a store's zarr.json" if p.is_dir() else "a file (a store is a folder)"
        raise SceneNotFoundError(f"{spec}: is {what}, not a massview terrain or scene store; give a store made by "
                                 "`massview prepare terrain INPUT -o STORE` or `massview prepare scene MESH... -o SCENE` "
                                 "(an elevation or mesh file goes to prepare first)")
    raise SceneNotFoundError(
        f"scene {spec!r} not found: give builtin:objects[?n=COUNT&seed=S] or a terrain store "
        "or a scene store (make one with `massview prepare terrain INPUT -o STORE`, `massview generate terrain STORE --size N`, "
        "`massview prepare scene MESH... -o SCENE` or `massview generate scene plant -o SCENE`)"
    )


def open_system(spec: str, cfg=None):
    """The rendering system for a scene: ``builtin:objects[?n=..&seed=..]``, a terrain store
    or a scene store."""
    egl = getattr(cfg, "egl_device", None)
    if getattr(cfg, "system", "auto") == "roettger":
        from .roettger import RoettgerSystem

        return RoettgerSystem((spec, *cfg.layers), cfg)
    if getattr(cfg, "system", "auto") == "reliefboards":  # M2 runs its own role loop (systems/reliefboards_job.py)
        raise ConfigError("system 'reliefboards' (M2) has no in-process system object: use massview.render(scene, cameras, "
                          f"ranks=N, system='reliefboards') or `massview render {spec} --system reliefboards --ranks N`")
    kind = scene_kind(spec)
    if getattr(cfg, "system", "auto") == "dmmr":  # M1: server + clients over a scene (or builtin:objects)
        from .dmmr import DmmrSystem

        return DmmrSystem(spec, cfg)
    if kind == "objects":
        from .objects import ObjectsSystem

        return ObjectsSystem(spec, egl)
    kw = {} if cfg is None else {"cache_bytes": cfg.cache_mb << 20, "gpu_bytes": cfg.gpu_mb << 20, "loading": cfg.loading}
    if kind == "scene":
        from .scene import SceneSystem

        return SceneSystem(spec, egl_device=egl, **kw)
    from .terrain import TerrainSystem

    return TerrainSystem(spec, egl_device=egl, **kw)
