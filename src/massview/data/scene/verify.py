"""``info`` and ``verify`` of a scene store.

``verify`` decodes every level of every geometry (checksums included) and checks that counts
agree with the tables, indices are in range, coordinates are finite and inside the geometry's
box, errors start at 0 and never decrease, the skeleton is what the geometry gives (boxes,
spheres, triangle counts, decoded bytes) and every group box holds its objects and child
groups. Problems name the object (and level and chunks) at fault.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ...core.errors import BlockNotFoundError, StoreError
from .mesh import record_size
from .store import GEOMETRY_TABLES, GROUP_FIELDS, REBUILD, SKELETON_FIELDS, SceneStore
from .writer import _skeleton

__all__ = ["scene_info", "verify_scene"]


def _dir_size(path: Path) -> int:
    return sum(f.stat().st_size for f in Path(path).rglob("*") if f.is_file())


def scene_info(path) -> dict:
    st = SceneStore(path, require_complete=False)
    a = st.attrs
    info = {"path": str(path), "complete": bool(a.get("complete")), "format_version": a.get("format_version"),
            "source": a.get("source"), "units": a.get("units"), "params": a.get("params")}
    if not info["complete"]:
        ck = a.get("checkpoint", {})
        return {**info, "written_geometries": ck.get("geometries"), "written_objects": ck.get("objects"), "disk_bytes": _dir_size(path)}
    sk = st.skeleton
    lo, hi = st.bounds
    raw = int(st.tables["nbytes"].sum())
    disk = _dir_size(Path(path) / "geometry" / "data")
    return {**info, "objects": sk.count, "geometries": st.geometry_count, "instanced": bool(a.get("instanced")),
            "groups": st.groups.count, "group_depth": int(st.groups.depth.max()), "occluders": int(sk.occluder.sum()),
            "triangles_level0": int(sk.triangles[:, 0].sum()),
            "triangles_per_level": [int(x) for x in sk.triangles.sum(axis=0)],
            "objects_by_level_count": {int(k): int(v) for k, v in zip(*np.unique(sk.levels, return_counts=True))},
            "bounds": [lo.round(4).tolist(), hi.round(4).tolist()],
            "decoded_bytes_level0": int(sk.level_bytes[:, 0].sum()), "record_bytes": raw, "geometry_disk_bytes": disk,
            "compression_ratio": round(raw / disk, 3) if disk else None, "disk_bytes": _dir_size(path),
            **{k: a[k] for k in ("textures_baked", "triangles_removed") if k in a},  # (prepare scene; older stores lack them)
            **_reliefboards_info(path)}


def _reliefboards_info(path) -> dict:
    """``{"reliefboards": …}``: the clustering ``prepare reliefboards`` stored (cluster counts by
    status and the parameters it was made with), or nothing where the store has none."""
    from ..board_clusters import read_clusters

    try:
        cl = read_clusters(path)
    except StoreError as e:
        return {"reliefboards": f"unreadable ({e})"}
    if cl is None:
        return {}
    counts = np.bincount(cl.status, minlength=3)
    keep = ("t_nz", "d_nz", "sl_c", "p", "r_y", "fovy", "min_triangles")
    return {"reliefboards": {"clusters": int(len(cl.status)), "feasible": int(counts[0]), "too_large": int(counts[1]),
                             "too_few_triangles": int(counts[2]), **{k: cl.attrs[k] for k in keep if k in cl.attrs}}}


def _who(st: SceneStore, owners: dict, gid: int) -> str:
    objs = owners.get(gid, [])
    return f"object {objs[0]}" if len(objs) == 1 else f"geometry {gid} (objects {objs[:4]})"


def _check_geometry(st: SceneStore, gid: int, who: str, by_file: dict) -> list[str]:
    t, out = st.tables, []
    nlev = int(t["levels"][gid])
    err = t["error"][gid, :nlev]
    if err[0] != 0 or np.any(np.diff(err) < 0):
        out.append(f"{who}: level errors {err.tolist()} do not start at 0 and rise")
    for lv in range(nlev):
        v, n = int(t["vertices"][gid, lv]), int(t["triangles"][gid, lv])
        if int(t["nbytes"][gid, lv]) != record_size(v, n, lv):
            out.append(f"{who}, level {lv}: record is {int(t['nbytes'][gid, lv])} bytes, {v} vertices and {n} triangles need {record_size(v, n, lv)}")
            continue
        try:
            m = st.get_mesh(gid, lv)
        except StoreError as e:
            if e.file is not None:  # a file missing or damaged: reported once, with the records it holds
                by_file.setdefault(str(e.file), []).append((f"{who}, level {lv}", e))
            else:
                out.append(f"{who}, level {lv}: {e}")
            continue
        if n and int(m.indices.max()) >= v:
            out.append(f"{who}, level {lv}: a triangle refers to vertex {int(m.indices.max())} of {v}")
        if not np.isfinite(m.positions).all():
            out.append(f"{who}, level {lv}: non-finite coordinates")
        elif lv == 0 and v and not (np.array_equal(m.positions.min(0).astype(np.float64), t["qlo"][gid])
                                    and np.array_equal(m.positions.max(0).astype(np.float64), t["qhi"][gid])):
            out.append(f"{who}, level 0: vertices span {m.positions.min(0).tolist()}..{m.positions.max(0).tolist()}, "
                       f"the box says {t['qlo'][gid].tolist()}..{t['qhi'][gid].tolist()}")
        elif lv == 0 and v:
            c = (t["qlo"][gid] + t["qhi"][gid]) / 2
            r = float(np.linalg.norm(m.positions - c, axis=1).max())
            if r > t["radius"][gid] * (1 + 1e-9) + 1e-9:
                out.append(f"{who}: vertices reach {r} from the centre, beyond the bounding radius {float(t['radius'][gid])}")
    return out


def verify_scene(path, progress=None) -> list[str]:
    """Problems found (empty when the store is sound)."""
    st = SceneStore(path, require_complete=False)
    if not st.attrs.get("complete"):
        return ["store is not marked complete (its build was interrupted); re-run the same command to finish it"]
    prog = progress or (lambda *a: None)
    sk = st.skeleton
    owners: dict[int, list[int]] = {}
    for o, g in enumerate(sk.geometry.tolist()):
        owners.setdefault(g, []).append(o)
    problems = _check_counts(st)
    if problems:  # tables of the wrong length: what follows would index past them
        return problems
    by_file: dict[str, list] = {}
    for gid in range(st.geometry_count):
        problems += _check_geometry(st, gid, _who(st, owners, gid), by_file)
        prog("verify", 1, st.geometry_count)
    for f, hits in by_file.items():
        first, e = hits[0]
        more = f" (and {len(hits) - 1} more records in that file)" if len(hits) > 1 else ""
        if isinstance(e, BlockNotFoundError):
            problems.append(f"missing file {f}: it held {len(hits)} record(s), the first {first}; the store is damaged — {REBUILD}")
        else:
            problems.append(f"{first}: {e}{more}")
    xf = st.read("objects/transform")
    want = _skeleton(st.tables, sk.geometry, xf)
    for k in ("center", "radius", "box_lo", "box_hi", "triangles", "level_error", "level_bytes", "levels"):
        bad = np.nonzero(~np.isclose(np.asarray(getattr(sk, k), float), np.asarray(want[k], float), rtol=1e-6, atol=1e-9)
                         .reshape(sk.count, -1).all(axis=1))[0]
        if len(bad):
            problems.append(f"object {int(bad[0])}: skeleton {k} disagrees with its geometry ({len(bad)} objects affected)")
    problems += _check_groups(st)
    return problems


def _check_counts(st: SceneStore) -> list[str]:
    """The root attributes' counts (objects, geometries, groups, triangles, levels_max)
    against the arrays' lengths, and every table's length against its family's."""
    a, out = st.attrs, []
    n, G, L = st.skeleton.count, st.geometry_count, st.levels_max
    fam = {"skeleton": (n, SKELETON_FIELDS), "objects": (n, ("geometry", "transform", "path")),
           "groups": (st.groups.count, GROUP_FIELDS), "geometry": (G, GEOMETRY_TABLES)}
    for key, have in (("objects", n), ("geometries", G), ("groups", st.groups.count)):
        if key in a and a[key] != have:
            out.append(f"its attributes say {key} {a[key]} but its arrays hold {have} ({key if key != 'geometries' else 'geometry'}/); "
                       f"its {st.path / 'zarr.json'} is damaged — {REBUILD}")
    for grp, (count, names) in fam.items():
        for k in names:
            try:
                shape = tuple(st.array(f"{grp}/{k}").shape)
            except StoreError as e:
                out.append(str(e))
                continue
            wide = k in {"skeleton": ("triangles", "level_error", "level_bytes"),
                         "geometry": ("offset", "nbytes", "vertices", "triangles", "error", "crc")}.get(grp, ())
            if shape[:1] != (count,) or (wide and shape[1:2] != (L,)):
                want = f"{count}" + (f" × {L} (levels_max)" if wide else "")
                out.append(f"the array {grp}/{k} has shape {list(shape)}, not {want} as the store's other arrays; "
                           f"its {st.path / grp / k / 'zarr.json'} is damaged — {REBUILD}")
    if not out and "triangles" in a and a["triangles"] != int(st.skeleton.triangles[:, 0].sum()):
        out.append(f"its attributes say triangles {a['triangles']} but its objects hold {int(st.skeleton.triangles[:, 0].sum())}; "
                   f"its {st.path / 'zarr.json'} is damaged — {REBUILD}")
    return out


def _check_groups(st: SceneStore) -> list[str]:
    sk, gr, out = st.skeleton, st.groups, []
    g = sk.group
    bad = np.nonzero((sk.box_lo < gr.box_lo[g] - 1e-9).any(1) | (sk.box_hi > gr.box_hi[g] + 1e-9).any(1))[0]
    if len(bad):
        out.append(f"object {int(bad[0])}: its box is not inside its group {int(g[bad[0]])}'s box")
    p = gr.parent[1:]
    if np.any(p >= np.arange(1, gr.count)) or gr.parent[0] != -1:
        out.append("groups: a parent does not precede its child")
    else:
        badg = np.nonzero((gr.box_lo[1:] < gr.box_lo[p] - 1e-9).any(1) | (gr.box_hi[1:] > gr.box_hi[p] + 1e-9).any(1))[0]
        if len(badg):
            out.append(f"group {int(badg[0]) + 1}: its box is not inside its parent's")
    return out
