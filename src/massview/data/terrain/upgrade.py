"""``upgrade``: bring an older terrain store to the current format version in place.

Version 1 → 2: the K-patch errors are recomputed as exact bounds (:mod:`deviation`), the
shading pyramid ``shade/`` is added (:mod:`colors`), and the baked computed colour of
version 1 (tint × a fixed hillshade) is dropped — colour and lighting are now applied at view
time. Heights are untouched. The version attribute is written last, so an interrupted upgrade
leaves a version-1 store that the same command finishes.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

from ...core.errors import StoreError
from ..rebuild import writing
from .colors import write_shading
from .ingest import compute_metadata, write_metadata
from .store import FORMAT_VERSION, TerrainStore, create_shade_arrays

__all__ = ["upgrade_store"]


def upgrade_store(path, progress: Callable[[str, int, int], None] | None = None) -> bool:
    """Upgrade the store at ``path``; False when it is current already. Holds the store's
    writer lock (:func:`rebuild.writing`) meanwhile."""
    with writing(path):
        return _upgrade(path, progress)


def _upgrade(path, progress) -> bool:
    import zarr

    prog = progress or (lambda phase, adv, total: None)
    store = TerrainStore(path, require_complete=False, upgrading=True)
    version = int(store.attrs.get("format_version", 0))
    if version >= FORMAT_VERSION:
        return False
    if not store.attrs.get("complete"):
        raise StoreError(f"{path}: the store is incomplete; finish it with the same `massview prepare terrain` command first")
    g = zarr.open_group(str(Path(path)), mode="r+")
    meta = compute_metadata(store, prog)
    write_metadata(g, store.layout, meta)
    create_shade_arrays(g, store.layout)
    write_shading(store, g, meta.zlo, meta.zhi, prog)
    if store.attrs.get("color") == "computed" and "color" in g:
        del g["color"]
    g.attrs.update({"height_range": [meta.zlo, meta.zhi], "format_version": FORMAT_VERSION})
    return True
