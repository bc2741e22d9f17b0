"""``upgrade``: bring an older terrain store to the current format version in place.

Version 1 → 2: the K-patch errors are recomputed as exact bounds (:mod:`deviation`), the
shading pyramid ``shade/`` is added (:mod:`colors`), and the baked computed colour of
version 1 (tint × a fixed hillshade) is dropped — colour and lighting are now applied at view
time. Heights are untouched. The version attribute is written last, so an interrupted upgrade
leaves a version-1 store that the same command finishes.

Version 2 → 3: ``halo/0`` (the samples around each level-0 block) is written from the heights,
the version attribute set, and then ``shade/0`` deleted (level 0's shading is computed on
reading, bit for bit what was stored: :meth:`TerrainStore.get_shade`); nothing else changes.
Stopped before the version is set, the store is still a readable version-2 one and the same
command starts again; stopped after it, before ``shade/0`` is gone, the command deletes it.
A version-2 store reads as it is, so this only saves its space (about half of it).
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

from ...core.errors import StoreError
from ..rebuild import writing
from .colors import write_shading
from .ingest import compute_metadata, write_metadata
from .store import FORMAT_VERSION, HaloWriter, TerrainStore, create_halo_array, create_shade_arrays

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
        if version == 3 and "shade" in store.group and "0" in store.group["shade"]:  # a 2 → 3 upgrade stopped just before
            del zarr.open_group(str(Path(path)), mode="r+")["shade/0"]  # its last step: the old level 0, no longer read
            return True
        return False
    if not store.attrs.get("complete"):
        raise StoreError(f"{path}: the store is incomplete; finish it with the same `massview prepare terrain` command first")
    g = zarr.open_group(str(Path(path)), mode="r+")
    if version == 2:
        _halos_from_heights(store, g, prog)
        g.attrs.update({"format_version": FORMAT_VERSION})
        if "shade/0" in g:
            del g["shade/0"]
        return True
    meta = compute_metadata(store, prog)
    write_metadata(g, store.layout, meta)
    create_shade_arrays(g, store.layout)
    write_shading(store, g, meta.zlo, meta.zhi, prog)
    if store.attrs.get("color") == "computed" and "color" in g:
        del g["color"]
    g.attrs.update({"height_range": [meta.zlo, meta.zhi], "format_version": FORMAT_VERSION})
    return True


def _halos_from_heights(store: TerrainStore, g, prog) -> None:
    """``halo/0`` of every level-0 block row, from the heights (each block row read once)."""
    import numpy as np

    from .colors import block_halos

    lay = store.layout
    nb, M = lay.blocks(0), lay.M
    create_halo_array(g, lay)
    out = HaloWriter(g)

    def grid_row(blocks, r):
        return np.concatenate([blocks[:, r, :-1].reshape(-1), blocks[-1, r, -1:]])

    prev, cur = None, store.get_block_row(0, 0).copy()
    for i in range(nb):
        nxt = store.get_block_row(0, i + 1).copy() if i + 1 < nb else None
        out.write(i, block_halos(grid_row(prev, M - 2) if prev is not None else None, cur,
                                 grid_row(nxt, 1) if nxt is not None else None))
        prev, cur = cur, nxt
        prog("halos", 1, nb)
