"""Writing a scene store object by object with bounded memory, resumable.

A producer (generator, ingest) hands the writer *units* in a fixed order — one geometry with
its LOD levels and the objects that place it — and calls :meth:`SceneWriter.step` after each.
Records go to a per-level buffer that is written a shard (16 MiB) at a time; every
``checkpoint_bytes`` the buffers are flushed and the tables and counters are saved, so a build
that is interrupted re-runs from its last checkpoint: the producer skips the first
``geometries_done`` units. Memory: one shard per level plus the tables (~200 B per object).
:meth:`finish` derives the skeleton and the culling groups, then sets ``complete`` last.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

from ...core.errors import StoreError
from .groups import build_groups, kd_paths
from .mesh import Mesh, crc32, decoded_bytes, encode_record
from .store import FORMAT, FORMAT_VERSION, GEOMETRY_TABLES, GROUP_FIELDS, SKELETON_FIELDS

__all__ = ["SceneWriter", "CHUNK_BYTES", "CHECKPOINT_BYTES", "occluder_flags", "enclosing_store"]

CHUNK_BYTES = 32 * 1024
CHECKPOINT_BYTES = 64 << 20  # records written between two checkpoints (what an interrupted build keeps)
SHARD_CHUNKS = 512
_ROWS = 16384


def _codec():
    from zarr.codecs import BloscCodec

    return BloscCodec(cname="zstd", clevel=1, shuffle="shuffle", typesize=4)


def occluder_flags(radius: np.ndarray, triangles0: np.ndarray, closed: np.ndarray) -> np.ndarray:
    """Occluder heuristic (Distributed massive model rendering §4: large, closed, simple
    objects): a closed surface, at most 4096 triangles at level 0 (cheap to draw in the depth
    pass), and a bounding radius at least the scene's 75th percentile. Shapes (n,) each."""
    if len(radius) == 0:
        return np.zeros(0, bool)
    big = radius >= np.percentile(radius, 75)
    return big & closed & (triangles0 <= 4096)


def enclosing_store(path) -> Path | None:
    """The zarr store (a folder with a ``zarr.json``) that ``path`` would lie inside, or None."""
    p = Path(path).resolve()
    return next((d for d in p.parents if (d / "zarr.json").is_file()), None)


class SceneWriter:
    """Create (or resume) a scene store at ``path``. ``params`` identify the build: an
    incomplete store with equal params is resumed, anything else needs ``overwrite``."""

    def __init__(self, path, params: dict, attrs: dict | None = None, levels_max: int = 8, path_depth: int = 0,
                 overwrite: bool = False, checkpoint_bytes: int = CHECKPOINT_BYTES):
        import zarr

        self.path = Path(path)
        outer = enclosing_store(self.path)
        if outer is not None:
            raise StoreError(f"{self.path} is inside the store {outer}; choose an output outside every store")
        self.L, self.D = int(levels_max), int(path_depth)
        self.checkpoint_bytes = checkpoint_bytes
        self.resumed = self._open_existing(params, overwrite)
        if not self.resumed:
            self.g = zarr.open_group(str(self.path), mode="w", zarr_format=3)
            self.g.attrs.update({"format": FORMAT, "format_version": FORMAT_VERSION, "complete": False, "units": "1",
                                 "source": None, **(attrs or {}), "params": params, "levels_max": self.L,
                                 "chunk_bytes": CHUNK_BYTES, "path_depth": self.D,
                                 "checkpoint": {"geometries": 0, "objects": 0, "cursor": [0] * self.L}})
            self._create_arrays()
        ck = self.g.attrs["checkpoint"]
        self.geometries_done, self.objects_done = int(ck["geometries"]), int(ck["objects"])
        self.cursor = [int(c) for c in ck["cursor"]]
        self.base = list(self.cursor)
        self.buf = [bytearray() for _ in range(self.L)]
        self._data = [self.g[f"geometry/data/{lv}"] for lv in range(self.L)]
        self.rows: dict[str, list] = {k: [] for k in (*GEOMETRY_TABLES, "o_geometry", "o_transform", "o_path")}
        self.n_geom, self.n_obj = self.geometries_done, self.objects_done
        self._since = 0

    def _open_existing(self, params: dict, overwrite: bool) -> bool:
        import zarr

        if not self.path.exists():
            return False
        try:
            g = zarr.open_group(str(self.path), mode="r+")
            old = dict(g.attrs)
        except Exception:  # noqa: BLE001 - not a zarr group
            old = None
        if old is None or old.get("format") != FORMAT:  # never removed, --overwrite or not: it may be the input, or a user's folder
            if not self.path.is_dir() or any(self.path.iterdir()):
                raise StoreError(f"{self.path} exists and is not a massview scene store (--overwrite replaces only scene "
                                 f"stores); choose another -o or remove it")
        elif old.get("complete") and not overwrite:
            raise StoreError(f"{self.path} is already a complete scene store; pass --overwrite to rebuild it")
        elif old.get("params") == params and not overwrite and old.get("levels_max") == self.L:
            self.g = g
            return True
        shutil.rmtree(self.path) if self.path.is_dir() else self.path.unlink()
        return False

    def _create_arrays(self) -> None:
        g, L = self.g, self.L
        for lv in range(L):
            g.create_array(f"geometry/data/{lv}", shape=(0,), chunks=(CHUNK_BYTES,), shards=(CHUNK_BYTES * SHARD_CHUNKS,),
                           dtype="uint8", compressors=_codec(), fill_value=0)
        spec = {"offset": ((L,), "int64"), "nbytes": ((L,), "int64"), "vertices": ((L,), "int64"), "triangles": ((L,), "int64"),
                "error": ((L,), "float32"), "crc": ((L,), "uint32"), "qlo": ((3,), "float64"), "qhi": ((3,), "float64"),
                "closed": ((), "bool"), "levels": ((), "int8"), "radius": ((), "float64")}
        for k, (tail, dt) in spec.items():
            g.create_array(f"geometry/{k}", shape=(0, *tail), chunks=(_ROWS, *tail), dtype=dt, fill_value=0)
        for k, (tail, dt) in {"geometry": ((), "int32"), "transform": ((4, 4), "float64"), "path": ((max(self.D, 1),), "int32")}.items():
            g.create_array(f"objects/{k}", shape=(0, *tail), chunks=(_ROWS, *tail), dtype=dt, fill_value=0)

    # -- producing ------------------------------------------------------------------------
    def add_geometry(self, levels: list[Mesh], errors: list[float], closed: bool | None = None) -> int:
        """Append one geometry (level meshes, level 0 first, local coordinates) and its level
        errors; returns its id. ``closed`` defaults to a test on level 0 (welded by position)."""
        from .simplify import is_closed

        if not 1 <= len(levels) <= self.L:
            raise ValueError(f"a geometry needs 1..{self.L} levels, got {len(levels)}")
        p0 = levels[0].positions.astype(np.float64)
        qlo, qhi = p0.min(axis=0), p0.max(axis=0)
        row = {k: np.zeros(self.L, np.int64) for k in ("offset", "nbytes", "vertices", "triangles")}
        row["error"], row["crc"] = np.zeros(self.L, np.float32), np.zeros(self.L, np.uint32)
        for lv, m in enumerate(levels):
            rec = encode_record(m, lv, qlo, qhi)
            row["offset"][lv], row["nbytes"][lv] = self._append(lv, rec), len(rec)
            row["vertices"][lv], row["triangles"][lv] = m.vertex_count, m.triangle_count
            row["error"][lv], row["crc"][lv] = errors[lv], crc32(rec)
            self._since += len(rec)
        row.update(qlo=qlo, qhi=qhi, levels=len(levels), radius=float(np.linalg.norm(p0 - (qlo + qhi) / 2, axis=1).max()),
                   closed=is_closed(levels[0].indices, levels[0].positions) if closed is None else bool(closed))
        for k, v in row.items():
            self.rows[k].append(v)
        self.n_geom += 1
        return self.n_geom - 1

    def add_object(self, geometry: int, path=(), transform: np.ndarray | None = None) -> int:
        """Place ``geometry`` (local -> world ``transform`` 4x4, identity by default; kept in
        float64, so a translation to georeferenced coordinates is exact) as a new object at
        hierarchy ``path`` (``path_depth`` ints); returns the object id."""
        self.rows["o_geometry"].append(int(geometry))
        self.rows["o_transform"].append(np.eye(4) if transform is None else np.asarray(transform, np.float64))
        p = np.zeros(max(self.D, 1), np.int32)
        p[: len(path)] = path
        self.rows["o_path"].append(p)
        self.n_obj += 1
        return self.n_obj - 1

    def step(self) -> None:
        """Call after each unit; saves a checkpoint when enough bytes were added since the last."""
        if self._since >= self.checkpoint_bytes:
            self.checkpoint()

    def _append(self, lv: int, rec: bytes) -> int:
        pad = (-self.cursor[lv]) % CHUNK_BYTES
        self.buf[lv] += bytes(pad)
        off = self.cursor[lv] + pad
        self.buf[lv] += rec
        self.cursor[lv] = off + len(rec)
        shard = CHUNK_BYTES * SHARD_CHUNKS
        boundary = self.cursor[lv] // shard * shard
        if boundary > self.base[lv]:
            self._flush(lv, boundary)
        return off

    def _flush(self, lv: int, upto: int) -> None:
        n = upto - self.base[lv]
        if n <= 0:
            return
        data = np.frombuffer(bytes(self.buf[lv][:n]), np.uint8)
        arr = self._data[lv]
        if arr.shape[0] < upto:  # grows with the data (shrinking a zarr array walks its chunk grid)
            arr.resize((upto,))
        arr[self.base[lv]: upto] = data
        del self.buf[lv][:n]
        self.base[lv] = upto

    def checkpoint(self) -> None:
        """Flush every level's buffer (to a chunk boundary) and save the tables and counters."""
        for lv in range(self.L):
            end = -(-self.cursor[lv] // CHUNK_BYTES) * CHUNK_BYTES
            self.buf[lv] += bytes(end - self.cursor[lv])
            self.cursor[lv] = end
            self._flush(lv, end)
        names = {k: f"geometry/{k}" for k in GEOMETRY_TABLES}
        names.update(o_geometry="objects/geometry", o_transform="objects/transform", o_path="objects/path")
        for k, name in names.items():
            if self.rows[k]:
                a = self.g[name]
                old = a.shape[0]
                a.resize((old + len(self.rows[k]), *a.shape[1:]))
                a[old:] = np.stack(self.rows[k]).astype(a.dtype)
                self.rows[k] = []
        self.g.attrs["checkpoint"] = {"geometries": self.n_geom, "objects": self.n_obj, "cursor": self.cursor}
        self.geometries_done, self.objects_done = self.n_geom, self.n_obj
        self._since = 0

    # -- finishing ------------------------------------------------------------------------
    def finish(self, attrs: dict | None = None) -> dict:
        """Derive skeleton and groups, record totals, set ``complete``. Returns the attributes."""
        self.checkpoint()
        g = self.g
        tab = {k: np.asarray(g[f"geometry/{k}"][...]) for k in GEOMETRY_TABLES}
        geom = np.asarray(g["objects/geometry"][...])
        xf = np.asarray(g["objects/transform"][...])
        paths = np.asarray(g["objects/path"][...])
        if len(geom) == 0:
            raise StoreError(f"{self.path}: the scene has no objects; nothing to write")
        sk = _skeleton(tab, geom, xf)
        if self.D == 0:
            paths = kd_paths(sk["center"])
        tree, leaf = build_groups(paths, sk["box_lo"], sk["box_hi"])
        sk["group"] = leaf
        for k in SKELETON_FIELDS:
            _write(g, f"skeleton/{k}", sk[k])
        for k in GROUP_FIELDS:
            _write(g, f"groups/{k}", getattr(tree, k))
        summary = {"objects": int(len(geom)), "geometries": int(len(tab["levels"])), "groups": int(tree.count),
                   "triangles": int(sk["triangles"][:, 0].sum()), "instanced": bool(len(tab["levels"]) < len(geom)),
                   "occluders": int(sk["occluder"].sum()), **(attrs or {})}
        g.attrs.update(summary)
        g.attrs["complete"] = True
        return dict(g.attrs)


def _write(g, name: str, arr: np.ndarray) -> None:
    chunks = (min(max(len(arr), 1), 1 << 16), *arr.shape[1:])
    g.create_array(name, shape=arr.shape, chunks=chunks, dtype=arr.dtype, overwrite=True, fill_value=0)[...] = arr


def _skeleton(tab: dict, geom: np.ndarray, xf: np.ndarray) -> dict:
    """Per-object world-space skeleton arrays from the geometry tables and transforms."""
    qlo, qhi = tab["qlo"][geom], tab["qhi"][geom]
    corners = np.stack([np.where(np.array([(i >> k) & 1 for k in range(3)], bool), qhi, qlo) for i in range(8)], 1)
    m = xf.astype(np.float64)
    world = np.einsum("nij,nkj->nki", m[:, :3, :3], corners) + m[:, None, :3, 3]
    scale = np.linalg.norm(m[:, :3, :3], axis=1).max(axis=1)
    center = np.einsum("nij,nj->ni", m[:, :3, :3], (qlo + qhi) / 2) + m[:, :3, 3]
    tri = tab["triangles"][geom]
    return {
        "center": center, "radius": tab["radius"][geom] * scale,
        "box_lo": world.min(axis=1), "box_hi": world.max(axis=1),
        "levels": tab["levels"][geom].astype(np.int8), "triangles": tri.astype(np.int64),
        "level_error": (tab["error"][geom] * scale[:, None]).astype(np.float32),
        "level_bytes": decoded_bytes(tab["vertices"][geom], tri).astype(np.int64),
        "occluder": occluder_flags(tab["radius"][geom] * scale, tri[:, 0], tab["closed"][geom]),
        "geometry": geom.astype(np.int32), "transform": xf.astype(np.float64),
    }
