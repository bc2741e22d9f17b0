"""``verify``: every array has the shape its layout gives, every chunk of the heights, the
shading (and colour) pyramid and the Röttger table decodes, metadata agrees with the data, errors
are saturated and the table is the one the heights give. Chunks are read one at a time, so
memory stays bounded (the table is recomputed a depth at a time, as ``prepare`` makes it)."""

from __future__ import annotations

import numpy as np

from ...core.errors import StoreError, describe
from .ingest import compute_metadata
from .meta import reduce_max
from .roettger import has_table, iter_table
from .store import TerrainStore, shade_arrays

__all__ = ["verify_store"]


def verify_store(path, progress=None) -> list[str]:
    """Problems found (empty when the store is sound). Unreadable blocks raise
    :class:`StoreError` naming the block."""
    store = TerrainStore(path, require_complete=False)
    problems = []
    if not store.attrs.get("complete"):
        from ..rebuild import being_written

        if being_written(path):  # (its unfinished rows are no problem: nothing else to say yet, walk10 L5)
            return ["store is not marked complete: a prepare is writing it now; wait for it to finish, then verify"]
        problems.append("store is not marked complete (prepare was interrupted); re-run the same prepare command")
    lay = store.layout
    for lv in range(lay.levels):
        done = np.asarray(store.array(f"blocks/{lv}/done")[...])  # (StoreError naming it when missing or damaged)
        if not done.all():
            i, j = np.argwhere(done == 0)[0]
            problems.append(f"level {lv}: block ({i}, {j}) and {int((done == 0).sum()) - 1} more never finished writing")
    if problems and not store.attrs.get("complete"):  # blocks are missing because the prepare stopped: resumable, say so
        return problems                                 # (reading them would name each as "missing, re-run with --overwrite")
    prog = progress or (lambda *a: None)
    problems += _check_shapes(store)
    if problems:  # arrays of the wrong shape: decoding them would only repeat it
        return problems
    meta = compute_metadata(store, prog)
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
    problems += _check_shading(store, prog)
    if store.has_color:
        problems += _check_pyramid_chunks(store, "color", prog)
    problems += _check_roettger(store, prog)
    return problems


def _names(store: TerrainStore) -> list[str]:
    """Every array the store should hold."""
    lay = store.layout
    out = [f"{a}/{lv}" for lv in range(lay.levels) for a in ("heights", *(("color",) if store.has_color else ()))]
    out += shade_arrays(lay) if store.shade0_computed else [f"shade/{lv}" for lv in range(lay.levels)]
    out += [f"blocks/{lv}/{k}" for lv in range(lay.levels) for k in ("minmax", "error", "done")]
    out += [f"lod/{k}/{j}" for j in range(lay.J) for k in ("square_error", "edge_error")]
    out += [f"lod/{k}/{j}" for j in range(lay.J + 1) for k in ("zmin", "zmax")]
    if has_table(store):
        out += [f"roettger/d2/{t}" for t in range(int(store.attrs["roettger"]["depths"]))]
    return out


def _check_shapes(store: TerrainStore) -> list[str]:
    """Each array's shape, chunk shape and dtype against what the layout gives (one problem
    per array, naming its zarr.json)."""
    out = []
    for name in _names(store):
        try:
            arr = store.array(name)
        except StoreError as e:
            out.append(str(e))
            continue
        p = store.check_array(name, arr)
        if p:
            out.append(p)
    return out


MAX_PER_ARRAY = 5  # problems named per array (then a count)


def _halo_row_problem(store: TerrainStore, i: int) -> str | None:
    """The problem of level-0 block row i's halo file (missing, not the row's size, or holding
    unset samples), naming the file once for its whole row; None when it reads."""
    lay = store.layout
    f, size = store.chunk_path(0, i, 0, "halo"), lay.blocks(0) * 4 * (lay.M + 2) * 4
    try:
        data = f.read_bytes()
    except OSError:
        return f"the halo file of level-0 block row {i} is missing ({f}); {store.halo_fix}"
    if len(data) != size:
        return f"the halo file of level-0 block row {i} ({f}) has {len(data)} bytes, not {size}; {store.halo_fix}"
    if np.isnan(np.frombuffer(data, "<f4")).any():
        return f"the halo file of level-0 block row {i} ({f}) holds unset (NaN) samples; {store.halo_fix}"
    return None


def _check_pyramid_chunks(store: TerrainStore, what: str, prog) -> list[str]:
    """Every chunk (one block each) of ``shade/<l>`` or ``color/<l>`` is there and decodes to
    a block, read one at a time (a missing chunk file would render as the fill value)."""
    lay, out = store.layout, []
    total = sum(lay.blocks(lv) ** 2 for lv in range(lay.levels))
    for lv in range(lay.levels):
        nb, bad = lay.blocks(lv), []
        if what == "shade" and lv == 0 and store.shade0_computed:  # its halo files, one a block row
            for i in range(nb):
                problem = _halo_row_problem(store, i)
                if problem:
                    bad.append(problem)
                prog(f"verify {what}", nb, total)
            out += _capped(bad, "halo/0")
            continue
        arr = store.array(f"{what}/{lv}")
        for i in range(nb):
            for j in range(nb):
                _, problem = _stored_block(store, what, lv, i, j, lambda: np.asarray(arr[i, j]))
                if problem:
                    bad.append(problem)
            prog(f"verify {what}", nb, total)
        out += _capped(bad, f"{what}/{lv}")
    return out


class _ShadingCheck:
    """A level's shading writer for :func:`colors.write_shading` that compares each block it is
    given with the stored one instead (missing, undecodable or different: a problem each)."""

    def __init__(self, store: TerrainStore, level: int):
        self.store, self.level, self.bad = store, level, []
        self.halos = level == 0 and store.shade0_computed  # level 0 computed from the heights and halo/0

    def write(self, i: int, j0: int, blocks: np.ndarray) -> None:
        lv = self.level
        if self.halos:  # a halo file that does not read: named once for its row
            problem = _halo_row_problem(self.store, i)
            if problem:
                self.bad.append(problem)
                return
        for k in range(blocks.shape[0]):
            j = j0 + k
            got, problem = _stored_block(self.store, "shade", lv, i, j, lambda: self.store.get_shade(lv, i, j))
            if problem:
                self.bad.append(problem)
            elif got.tobytes() != np.ascontiguousarray(blocks[k]).tobytes():
                held, fix = (("samples around the block (its halo)", self.store.halo_fix) if self.halos
                             else ("shading", "re-run prepare with --overwrite"))
                self.bad.append(f"shading block (level {lv}, {i}, {j}) is not what its heights give (the file "
                                f"{self.store.shade_file(lv, i, j)} holds other or damaged {held}) — {fix}")


def _stored_block(store: TerrainStore, what: str, lv: int, i: int, j: int, read):
    """(the block ``read()`` decodes, None), or (None, the problem) where the chunk file of
    ``<what>/<lv>`` block (i, j) is missing or does not decode."""
    label = {"shade": "shading", "color": "colour"}[what]
    f = store.shade_file(lv, i, j) if what == "shade" else store.chunk_path(lv, i, j, what)
    if not f.is_file():
        return None, f"{label} block (level {lv}, {i}, {j}) is missing ({f}); re-run prepare with --overwrite"
    try:
        return read(), None
    except Exception as e:  # noqa: BLE001 - codec errors come in many types
        return None, (f"{label} block (level {lv}, {i}, {j}) does not decode ({describe(e)}); the file {f} is damaged — "
                      "re-run prepare with --overwrite")


def _check_shading(store: TerrainStore, prog) -> list[str]:
    """Every block of ``shade/<l>`` is there, decodes, and is bit for bit the shading its
    heights give (computed again, as prepare does; walk9 M4: a chunk replaced by another
    block's decoded fine and rendered as a wrongly lit square)."""
    from .colors import write_shading

    lay = store.layout
    if not store.attrs.get("complete") or not store.attrs.get("height_range"):  # (a prepare stopped before its shading pass)
        return _check_pyramid_chunks(store, "shade", prog)
    zlo, zhi = (float(v) for v in store.attrs["height_range"])
    checks = [_ShadingCheck(store, lv) for lv in range(lay.levels)]
    write_shading(store, None, zlo, zhi, lambda phase, adv, total: prog("verify shade", adv, total), writers=checks)
    out = [p for c in checks for p in _capped(sorted(c.bad), "halo/0" if c.halos else f"shade/{c.level}")]
    old = store.path / "shade" / "0"
    if store.shade0_computed and old.exists():
        out.append(f"{old} is left from an interrupted `massview upgrade` (format 3 computes level 0's shading and never "
                   f"reads it); run `massview upgrade {store.path}` to remove it")
    return out


def _check_roettger(store: TerrainStore, prog) -> list[str]:
    """T2's table: every chunk of ``roettger/d2/<t>`` decodes and holds what the heights give
    (recomputed a depth at a time; a chunk file may be absent only where the table is 0 there,
    as zarr leaves such chunks unwritten)."""
    meta = store.attrs.get("roettger")
    if not meta:
        return []
    if not has_table(store):
        return [f"its Röttger table attribute {meta} does not match the layout ({store.layout.n - 1} depths); "
                f"re-run `massview prepare roettger {store.path}`"]
    fix = f"re-run `massview prepare roettger {store.path}` (or prepare with --overwrite)"
    out = []
    for t, want in iter_table(store, float(meta["C_min"]), lambda *a: prog("verify roettger", *a[1:])):
        name = f"roettger/d2/{t}"
        arr, bad = store.array(name), []
        ch = tuple(arr.chunks)
        root = store.path / "roettger" / "d2" / str(t)
        for ci in range(-(-want.shape[0] // ch[0])):
            for cj in range(-(-want.shape[1] // ch[1])):
                sl = (slice(ci * ch[0], (ci + 1) * ch[0]), slice(cj * ch[1], (cj + 1) * ch[1]))
                f = root / arr.metadata.encode_chunk_key((ci, cj))
                if not f.is_file():
                    if np.any(want[sl] != 0):
                        bad.append(f"{name}: chunk ({ci}, {cj}) is missing ({f}); {fix}")
                    continue
                try:
                    have = np.asarray(arr[sl])
                except Exception as e:  # noqa: BLE001
                    bad.append(f"{name}: chunk ({ci}, {cj}) does not decode ({describe(e)}); the file {f} is damaged — {fix}")
                    continue
                if not np.allclose(have, want[sl], rtol=1e-6, atol=0):
                    bad.append(f"{name}: chunk ({ci}, {cj}) ({f}) differs from the roughness the heights give; {fix}")
        out += _capped(bad, name)
    return out


def _capped(bad: list[str], name: str) -> list[str]:
    if len(bad) > MAX_PER_ARRAY:
        return bad[:MAX_PER_ARRAY] + [f"{name}: {len(bad) - MAX_PER_ARRAY} more problems like these"]
    return bad
