"""The scene store: a zarr v3 group holding a polygon scene as objects with LOD levels.

Layout (readable with plain zarr; n objects, G geometries, L = ``levels_max``)::

    attrs: format "massview-scene", format_version 1, complete (bool, set last), units,
           source, objects n, geometries G, triangles (level-0 total over objects),
           levels_max L, chunk_bytes, instanced (bool), params (what built it, for resume),
           checkpoint {geometries, objects, cursor[L]} (ingest progress)
    skeleton/center (n,3) f8, radius (n,) f8, box_lo, box_hi (n,3) f8   world space
    skeleton/levels (n,) i1; triangles, level_bytes (n,L) i8; level_error (n,L) f4
    skeleton/occluder (n,) bool; group (n,) i4; geometry (n,) i4; transform (n,4,4) f8
    groups/parent (g,) i4 (-1: root), box_lo, box_hi (g,3) f8, depth (g,) i2
    objects/geometry (n,) i4, objects/transform (n,4,4) f8 (f4 in older stores, read
                 alike), objects/path (n,D) i4
    geometry/offset, nbytes, vertices, triangles (G,L) i8; error (G,L) f4; crc (G,L) u4
    geometry/qlo, qhi (G,3) f8 (level-0 box = quantization box, local); closed (G,) bool;
    geometry/levels (G,) i1; radius (G,) f8 (bounding sphere about the box centre, local)
    geometry/data/<l>  uint8 (bytes,), chunks of ``chunk_bytes`` (32 KiB) in shards of
                       512 chunks, blosc zstd: the records of level l (:mod:`.mesh`), each
                       starting at a chunk boundary, so one object's level is one chunk or a
                       few and reading it touches nothing else

``skeleton/`` and ``groups/`` are derived from ``objects/`` and ``geometry/`` when the ingest
finishes; ``complete`` is set after them. Level 0 is the input geometry to float32 precision
in the geometry's local frame: ``prepare scene`` puts each object's origin at its box centre
and its transform translates it back (in float64), so positions far from the world origin
(georeferenced data) keep float32 precision relative to the object;
``level_error`` is a geometric distance in world units (0 at level 0), non-decreasing with the
level. Groups are the culling hierarchy: every object's ``group`` is a leaf, every group's box
holds its children's.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ...core.errors import BlockNotFoundError, CorruptBlockError, StoreError, describe
from .mesh import Mesh, crc32, decode_record

__all__ = ["FORMAT", "FORMAT_VERSION", "SceneStore", "Skeleton", "GroupTree", "Mesh", "is_scene_store"]

FORMAT = "massview-scene"
FORMAT_VERSION = 1


@dataclass(frozen=True)
class Skeleton:
    """Per-object arrays (n objects, Lmax levels); world space unless stated."""

    center: np.ndarray  # (n,3) f8 bounding-sphere centre
    radius: np.ndarray  # (n,) f8
    box_lo: np.ndarray  # (n,3) f8
    box_hi: np.ndarray  # (n,3) f8
    levels: np.ndarray  # (n,) i1, >= 1
    triangles: np.ndarray  # (n,Lmax) i8, 0 past the last level; level 0 = original
    level_error: np.ndarray  # (n,Lmax) f4 geometric error, world units (0 at level 0)
    level_bytes: np.ndarray  # (n,Lmax) i8 decoded bytes of the level
    occluder: np.ndarray  # (n,) bool
    group: np.ndarray  # (n,) i4 leaf group
    geometry: np.ndarray  # (n,) i4 geometry id (== object id unless instanced)
    transform: np.ndarray  # (n,4,4) f8 local -> world (f4 in older stores)

    @property
    def count(self) -> int:
        return len(self.radius)


@dataclass(frozen=True)
class GroupTree:
    """Culling hierarchy: parent (g,) i4 (-1 root), box_lo/box_hi (g,3) f8 world, depth (g,) i2.
    Parents precede their children."""

    parent: np.ndarray
    box_lo: np.ndarray
    box_hi: np.ndarray
    depth: np.ndarray

    @property
    def count(self) -> int:
        return len(self.parent)


SKELETON_FIELDS = ("center", "radius", "box_lo", "box_hi", "levels", "triangles", "level_error", "level_bytes",
                   "occluder", "group", "geometry", "transform")
GROUP_FIELDS = ("parent", "box_lo", "box_hi", "depth")
GEOMETRY_TABLES = ("offset", "nbytes", "vertices", "triangles", "error", "crc", "qlo", "qhi", "closed", "levels", "radius")


class ShardReader:
    """Reads byte ranges of one ``geometry/data/<l>`` array straight from its shard files
    (zarr's sharding layout: inner chunks then an index of (offset, nbytes) u64 pairs and a
    crc32c at the end; inner chunks blosc-compressed). One call costs a pread and a blosc
    decode per chunk instead of zarr's event-loop round trip (~3 ms). Thread-safe."""

    def __init__(self, root: Path, meta: dict):
        sh = meta["codecs"][0]["configuration"]
        self.root = root
        self.cb = int(sh["chunk_shape"][0])
        self.per = int(meta["chunk_grid"]["configuration"]["chunk_shape"][0]) // self.cb
        self._index: dict[int, np.ndarray | None] = {}

    @staticmethod
    def supports(meta: dict) -> bool:
        try:
            sh = meta["codecs"][0]
            inner = [c["name"] for c in sh["configuration"]["codecs"]]
            return (sh["name"] == "sharding_indexed" and sh["configuration"]["index_location"] == "end" and inner == ["bytes", "blosc"]
                    and [c["name"] for c in sh["configuration"]["index_codecs"]] == ["bytes", "crc32c"]
                    and meta["chunk_key_encoding"]["name"] == "default")
        except (KeyError, IndexError, TypeError):
            return False

    def shard_file(self, s: int) -> Path:
        return self.root / "c" / str(s)

    def _shard_index(self, s: int) -> np.ndarray | None:
        """Shard ``s``'s index of (offset, nbytes) pairs; None where its file is absent; a
        :class:`CorruptBlockError` naming the file where the index is cut short, fails its
        crc32c or points past the file's end (a truncated shard)."""
        if s not in self._index:
            f = self.shard_file(s)
            try:
                self._index[s] = self._read_index(f)
            except FileNotFoundError:
                self._index[s] = None
            except CorruptBlockError as e:
                self._index[s] = e
        idx = self._index[s]
        if isinstance(idx, CorruptBlockError):
            raise CorruptBlockError(str(idx), file=idx.file)
        return idx

    def _read_index(self, f: Path) -> np.ndarray:
        n = self.per * 16 + 4
        with open(f, "rb") as fh:
            size = os.fstat(fh.fileno()).st_size
            if size < n:
                raise CorruptBlockError(f"the shard file {f} is {size} bytes, shorter than its {n}-byte index: it is truncated", file=f)
            fh.seek(-n, 2)
            raw = fh.read(n)
        idx = np.frombuffer(raw[:-4], "<u8").reshape(self.per, 2)
        try:
            import google_crc32c  # (zarr's own crc32c; absent: the bounds below still catch a cut file)

            ok = google_crc32c.value(raw[:-4]) == int.from_bytes(raw[-4:], "little")
        except ImportError:
            ok = True
        used = idx[:, 0] != 2**64 - 1
        if not ok or np.any(idx[used, 0] + idx[used, 1] > size - n):
            raise CorruptBlockError(f"the shard file {f} ({size} bytes) is truncated or damaged: its chunk index "
                                    f"{'fails its checksum' if not ok else 'points past its end'}", file=f)
        return idx

    def missing(self, off: int, nb: int) -> list[Path]:
        """The shard files that bytes [off, off+nb) lie in and that do not exist."""
        c0, c1 = off // self.cb, -(-(off + nb) // self.cb)
        shards = range(c0 // self.per, (c1 - 1) // self.per + 1) if c1 > c0 else ()
        return [self.shard_file(s) for s in shards if not self.shard_file(s).is_file()]

    def read(self, off: int, nb: int) -> np.ndarray:
        from numcodecs import blosc

        c0, c1 = off // self.cb, -(-(off + nb) // self.cb)
        out = np.zeros((c1 - c0) * self.cb, np.uint8)
        for c in range(c0, c1):
            s, i = divmod(c, self.per)
            idx = self._shard_index(s)
            if idx is None or idx[i, 0] == 2**64 - 1:
                continue  # never written: fill value
            with open(self.root / "c" / str(s), "rb") as fh:
                raw = os.pread(fh.fileno(), int(idx[i, 1]), int(idx[i, 0]))
            chunk = np.frombuffer(blosc.decompress(raw), np.uint8)
            if len(chunk) != self.cb:
                raise ValueError(f"chunk {c} decodes to {len(chunk)} bytes, not {self.cb}")
            out[(c - c0) * self.cb:(c - c0 + 1) * self.cb] = chunk
        a = off - c0 * self.cb
        return out[a:a + nb]


REBUILD = "re-run `massview prepare scene` / `massview generate scene` with --overwrite"


def is_scene_store(path) -> bool:
    """True when ``path`` is a zarr group whose format attribute names a scene store."""
    import json

    meta = Path(path) / "zarr.json"
    try:
        return json.loads(meta.read_text()).get("attributes", {}).get("format") == FORMAT
    except (OSError, ValueError):
        return False


class SceneStore:
    """Read access to a scene store; ``get_mesh`` is thread-safe. The skeleton, groups and
    geometry tables are read into RAM at open (about 200 bytes per object at Lmax = 8)."""

    def __init__(self, path, require_complete: bool = True):
        import zarr

        self.path = Path(path)
        if not self.path.exists():
            raise StoreError(f"{self.path}: no such scene store; create one with `massview prepare scene INPUT -o {self.path}` "
                             f"or `massview generate scene plant -o {self.path}`")
        try:
            self.group_ = zarr.open_group(str(self.path), mode="r")
            self.attrs = dict(self.group_.attrs)
        except Exception as e:  # noqa: BLE001 - zarr raises many kinds
            raise StoreError(f"{self.path}: not a readable zarr group ({e})") from None
        if self.attrs.get("format") != FORMAT:
            raise StoreError(f"{self.path}: not a massview scene store (format attribute is {self.attrs.get('format')!r})")
        if self.attrs.get("format_version", 0) > FORMAT_VERSION:
            raise StoreError(f"{self.path}: format version {self.attrs['format_version']} is newer than this massview "
                             f"({FORMAT_VERSION}); upgrade massview")
        if require_complete and not self.attrs.get("complete"):
            from ..rebuild import being_written

            if being_written(self.path):
                raise StoreError(f"{self.path}: scene store is being written by a prepare or generate running now; wait for it to finish")
            raise StoreError(f"{self.path}: scene store is incomplete (its build was interrupted); re-run the same "
                             "`massview prepare scene` / `generate scene` command to finish it")
        try:
            self.levels_max = int(self.attrs["levels_max"])
        except (KeyError, TypeError, ValueError) as e:
            raise StoreError(f"{self.path}: its attributes (zarr.json) have no valid levels_max ({type(e).__name__}: {e}); "
                             f"the store is damaged — {REBUILD}") from None
        self.tables = {k: self.read(f"geometry/{k}") for k in GEOMETRY_TABLES}
        self._data = [self.array(f"geometry/data/{lv}") for lv in range(self.levels_max)]
        self._direct = [self._shard_reader(lv) for lv in range(self.levels_max)]
        if self.attrs.get("complete"):
            self.skeleton = Skeleton(**{k: self.read(f"skeleton/{k}") for k in SKELETON_FIELDS})
            self.groups = GroupTree(**{k: self.read(f"groups/{k}") for k in GROUP_FIELDS})

    def array(self, name: str):
        """The store's zarr array ``name``; a StoreError naming it where it is missing or its
        ``zarr.json`` does not parse."""
        try:
            return self.group_[name]
        except Exception as e:  # noqa: BLE001 - KeyError, JSONDecodeError, zarr's own errors
            raise StoreError(f"{self.path}: the array {name} does not open ({describe(e)}); the store is damaged — {REBUILD}") from None

    def read(self, name: str) -> np.ndarray:
        """The whole array ``name`` (a table: small), a StoreError naming it where it does not
        open or decode."""
        arr = self.array(name)
        try:
            return np.asarray(arr[...])
        except Exception as e:  # noqa: BLE001 - codec errors come in many types
            raise StoreError(f"{self.path}: the array {name} does not decode ({describe(e)}); the store is damaged — {REBUILD}") from None

    def _shard_reader(self, lv: int) -> ShardReader | None:
        import json

        root = self.path / "geometry" / "data" / str(lv)
        try:
            meta = json.loads((root / "zarr.json").read_text())
        except (OSError, ValueError):
            return None
        return ShardReader(root, meta) if ShardReader.supports(meta) else None

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """World-space box (lo (3,), hi (3,)) of all objects."""
        return self.skeleton.box_lo.min(axis=0), self.skeleton.box_hi.max(axis=0)

    @property
    def object_boxes(self) -> tuple[np.ndarray, np.ndarray]:
        """World-space boxes (box_lo (n, 3), box_hi (n, 3)) of the objects: what ``walkthrough``
        walks round."""
        return self.skeleton.box_lo, self.skeleton.box_hi

    @property
    def geometry_count(self) -> int:
        return len(self.tables["levels"])

    def chunk_range(self, geometry_id: int, level: int) -> tuple[int, int]:
        """First and one-past-last chunk index of a record in ``geometry/data/<level>``."""
        cb = int(self.attrs["chunk_bytes"])
        off, nb = int(self.tables["offset"][geometry_id, level]), int(self.tables["nbytes"][geometry_id, level])
        return off // cb, (off + max(nb, 1) + cb - 1) // cb

    def _where(self, gid: int, level: int) -> str:
        objs = np.nonzero(self.skeleton.geometry == gid)[0] if hasattr(self, "skeleton") else np.array([gid])
        who = f"object {int(objs[0])}" if len(objs) == 1 else f"geometry {gid} (objects {objs[:4].tolist()}...)"
        c0, c1 = self.chunk_range(gid, level)
        return f"{self.path}: {who}, level {level} (chunks {c0}..{c1 - 1} of geometry/data/{level})"

    def read_record(self, geometry_id: int, level: int) -> np.ndarray:
        """The raw record bytes (uint8) of a geometry's level, checksum verified."""
        gid, lv = int(geometry_id), int(level)
        if not (0 <= gid < self.geometry_count):
            raise BlockNotFoundError(f"{self.path}: geometry {gid} does not exist ({self.geometry_count} geometries)")
        if not (0 <= lv < int(self.tables["levels"][gid])):
            raise BlockNotFoundError(f"{self.path}: geometry {gid} has {int(self.tables['levels'][gid])} levels, not {lv + 1}")
        off, nb = int(self.tables["offset"][gid, lv]), int(self.tables["nbytes"][gid, lv])
        d = self._direct[lv]
        try:
            buf = d.read(off, nb) if d is not None else np.asarray(self._data[lv][off:off + nb])
        except CorruptBlockError as e:  # the shard reader named the file
            raise CorruptBlockError(f"{self._where(gid, lv)} does not decode: {e}; the store is damaged — {REBUILD}",
                                    file=e.file) from None
        except Exception as e:  # noqa: BLE001 - codec errors come in many types
            raise CorruptBlockError(f"{self._where(gid, lv)} does not decode ({describe(e)}); "
                                    f"the store is damaged — {REBUILD}") from None
        if crc32(buf) != int(self.tables["crc"][gid, lv]):
            miss = d.missing(off, nb) if d is not None else []
            if miss:  # (read as the fill value: a record that is not there)
                raise BlockNotFoundError(f"{self._where(gid, lv)}: missing file {miss[0]}; the store is damaged — {REBUILD}",
                                         file=miss[0])
            raise CorruptBlockError(f"{self._where(gid, lv)}: checksum mismatch; the store is damaged — {REBUILD}")
        return buf

    def get_mesh(self, geometry_id: int, level: int) -> Mesh:
        """The mesh of ``geometry_id`` at ``level`` (0 = original), in local coordinates."""
        buf = self.read_record(geometry_id, level)
        t = self.tables
        gid, lv = int(geometry_id), int(level)
        return decode_record(buf, int(t["vertices"][gid, lv]), int(t["triangles"][gid, lv]), lv, t["qlo"][gid], t["qhi"][gid])
