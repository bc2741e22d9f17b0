"""``verify``: every block decodes, metadata agrees with the data, errors are saturated."""

from __future__ import annotations

import numpy as np

from ...core.errors import StoreError
from .ingest import compute_metadata
from .meta import reduce_max
from .store import TerrainStore

__all__ = ["verify_store"]


def verify_store(path, progress=None) -> list[str]:
    """Problems found (empty when the store is sound). Unreadable blocks raise
    :class:`StoreError` naming the block."""
    store = TerrainStore(path, require_complete=False)
    problems = []
    if not store.attrs.get("complete"):
        problems.append("store is not marked complete (prepare was interrupted); re-run the same prepare command")
    lay = store.layout
    for lv in range(lay.levels):
        done = np.asarray(store.array(f"blocks/{lv}/done")[...])  # (StoreError naming it when missing or damaged)
        if not done.all():
            i, j = np.argwhere(done == 0)[0]
            problems.append(f"level {lv}: block ({i}, {j}) and {int((done == 0).sum()) - 1} more never finished writing")
    if problems and not store.attrs.get("complete"):  # blocks are missing because the prepare stopped: resumable, say so
        return problems                                 # (reading them would name each as "missing, re-run with --overwrite")
    meta = compute_metadata(store, progress or (lambda *a: None))
    try:
        stored_sq, stored_dg, stored_zmin, stored_zmax = store.lod_arrays()
        stored_mm = [store.block_minmax(lv) for lv in range(lay.levels)]
        stored_err = [store.block_error(lv) for lv in range(lay.levels)]
    except StoreError as e:  # a metadata array missing or damaged
        return problems + [str(e)]
    for lv in range(lay.levels):
        bad = np.argwhere(np.any(stored_mm[lv] != meta.minmax[lv], axis=-1))
        if len(bad):
            i, j = bad[0]
            problems.append(f"level {lv}: block ({i}, {j}) min/max {stored_mm[lv][i, j].tolist()} but its samples give {meta.minmax[lv][i, j].tolist()}")
        if lv > 0:
            kids = reduce_max(stored_err[lv - 1], 2)
            bad = np.argwhere(stored_err[lv] < kids)
            if len(bad):
                i, j = bad[0]
                problems.append(f"level {lv}: block ({i}, {j}) error {stored_err[lv][i, j]} is below a child's ({kids[i, j]}): not saturated")
        if not np.allclose(stored_err[lv], meta.block_error[lv]):
            problems.append(f"level {lv}: block errors differ from the ones the data gives")
    for j in range(lay.J):
        if not (np.array_equal(stored_sq[j], meta.sq[j]) and np.array_equal(stored_dg[j], meta.dg[j])):
            problems.append(f"patch level {j}: stored K-patch errors differ from the ones the data gives")
    for j in range(lay.J + 1):
        if not (np.array_equal(stored_zmin[j], meta.zmin[j]) and np.array_equal(stored_zmax[j], meta.zmax[j])):
            problems.append(f"patch level {j}: stored height ranges differ from the data")
    return problems
