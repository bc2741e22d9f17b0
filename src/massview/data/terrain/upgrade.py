"""``upgrade``: bring an older terrain store to the current format version in place.

Version 1 → 2: the K-patch errors are recomputed as exact bounds (:mod:`deviation`), the
shading pyramid ``shade/`` is added (:mod:`colors`), and the baked computed colour of
version 1 (tint × a fixed hillshade) is dropped — colour and lighting are now applied at view
time. Heights are untouched. The version attribute is written last, so an interrupted upgrade
leaves a version-1 store that the same command finishes.

On a current store ``upgrade`` writes again the ``halo/0`` rows the heights do not give (a
missing, truncated or damaged file: what ``verify`` and ``render`` name) and removes a ``shade/0``
an interrupted upgrade left.

Version 2 → 3: ``halo/0`` (the samples around each level-0 block) is written from the heights,
the version attribute set, and then ``shade/0`` deleted (level 0's shading is computed on
reading, bit for bit what was stored: :meth:`TerrainStore.get_shade`); nothing else changes.
Stopped before the version is set, the store is still a readable version-2 one and the same
command starts again; stopped after it, before ``shade/0`` is gone, the command deletes it.
A version-2 store reads as it is, so this only saves its space (about half of it).
"""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Callable

from ...core.errors import StoreError
from ..rebuild import writing
from .colors import write_shading
from .ingest import compute_metadata, write_metadata
from .store import FORMAT_VERSION, HaloWriter, TerrainStore, create_halo_array, create_shade_arrays

__all__ = ["upgrade_store"]


def upgrade_store(path, progress: Callable[[str, int, int], None] | None = None) -> str | None:
    """Upgrade the store at ``path``, or repair a current one's halos; what was done (a
    sentence) or None when it is current and sound already. Holds the store's writer lock
    (:func:`rebuild.writing`) meanwhile."""
    with writing(path):
        return _upgrade(path, progress)


def _upgrade(path, progress) -> str | None:
    import zarr

    prog = progress or (lambda phase, adv, total: None)
    store = TerrainStore(path, require_complete=False, upgrading=True)
    version = int(store.attrs.get("format_version", 0))
    if version > FORMAT_VERSION:
        return None  # (TerrainStore refused it: a newer massview's)
    if not store.attrs.get("complete"):
        raise StoreError(f"{path}: the store is incomplete; finish it with the same `massview prepare terrain` command first")
    g = zarr.open_group(str(Path(path)), mode="r+")
    if version == FORMAT_VERSION:  # current: halos the heights do not give are written again, a leftover shade/0 removed
        done = []
        n = _halos_from_heights(store, g, prog, only_wrong=True)
        if n:
            done.append(f"wrote the halos of {n} level-0 block row(s) again from the heights")
        if _remove_old_shade0(path):
            done.append("removed shade/0, left by an interrupted upgrade")
        return "; ".join(done) or None
    if version == 2:
        _halos_from_heights(store, g, prog)
        g.attrs.update({"format_version": FORMAT_VERSION})
        _remove_old_shade0(path)
        return f"upgraded from format version 2 to {FORMAT_VERSION}"
    meta = compute_metadata(store, prog)
    write_metadata(g, store.layout, meta)
    create_shade_arrays(g, store.layout)
    write_shading(store, g, meta.zlo, meta.zhi, prog)
    if store.attrs.get("color") == "computed" and "color" in g:
        del g["color"]
    g.attrs.update({"height_range": [meta.zlo, meta.zhi], "format_version": FORMAT_VERSION})
    return f"upgraded from format version {version} to {FORMAT_VERSION}"


def _remove_old_shade0(path) -> bool:
    """Delete a version-2 ``shade/0`` folder (whole, or what an interrupted deletion left:
    chunk files without their ``zarr.json``); True when there was one."""
    old = Path(path) / "shade" / "0"
    if not old.exists():
        return False
    shutil.rmtree(old)
    return True


def _halos_from_heights(store: TerrainStore, g, prog, only_wrong: bool = False) -> int:
    """``halo/0`` of every level-0 block row, from the heights (each block row read once);
    ``only_wrong``: only the rows whose file is missing or holds other bytes (the array is
    made anew where its ``zarr.json`` is missing or not the layout's). The rows written."""
    from .colors import block_halos, grid_row

    lay = store.layout
    nb, M = lay.blocks(0), lay.M
    try:
        ok = only_wrong and store.check_array("halo/0", g["halo/0"]) is None
    except Exception:  # noqa: BLE001 - missing or unreadable zarr.json
        ok = False
    if not ok:
        create_halo_array(g, lay)
        only_wrong = False
    out = HaloWriter(g)
    written = 0
    prev, cur = None, store.get_block_row(0, 0).copy()
    for i in range(nb):
        nxt = store.get_block_row(0, i + 1).copy() if i + 1 < nb else None
        halos = block_halos(grid_row(prev, M - 2) if prev is not None else None, cur, grid_row(nxt, 1) if nxt is not None else None)
        if not (only_wrong and _same_file(store.chunk_path(0, i, 0, "halo"), halos)):
            out.write(i, halos)
            written += 1
        prev, cur = cur, nxt
        prog("halos", 1, nb)
    return written


def _same_file(f: Path, halos) -> bool:
    try:
        return f.read_bytes() == halos.astype("<f4").tobytes()
    except OSError:
        return False
