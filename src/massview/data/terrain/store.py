"""The terrain store: a zarr v3 group holding the M-block pyramid and its LOD metadata.

Layout (readable with plain zarr; ``M`` = block size, ``nb_l = 2^(L-l)``)::

    attrs: format "massview-terrain", format_version 3, complete (bool), M, K, levels,
           rows, cols (input samples), padded (S), spacing [dx, dy] (metres), vertical_scale,
           crs (WKT or null), transform (GDAL 6-tuple or null), nodata {value, filled},
           source, height_range [min, max], color ("computed" | "orthophoto" | null)
    heights/<l>     float32 (nb_l, nb_l, M, M), chunk (1, 1, M, M), blosc lz4 5 + shuffle (_compressor):
                    block (i, j) = finest samples rows (i(M-1)+r)2^l, cols (j(M-1)+c)2^l;
                    its file ``heights/<l>/c/<i>/<j>/0/0`` (zarr's default keys, CHUNK_KEYS)
    shade/<l>       float16 (nb_l, nb_l, M, M, 3), chunk (1, 1, M, M, 3): slope ∂h/∂x, ∂h/∂y
                    (per metre, x east, y north) and height fraction, mip-filtered (colors.py);
                    levels l ≥ 1 only since version 3 (level 0 is computed on reading, below)
    halo/0          float32 (nb_0, nb_0, 4, M+2), chunk (1, nb_0, 4, M+2), uncompressed: the finest
                    samples around level-0 block (i, j) (r0 = i(M-1), c0 = j(M-1), indices
                    clamped to the grid): [0] row r0-1 and [1] row r0+M, columns c0-1 .. c0+M;
                    [2] column c0-1 and [3] column c0+M, rows r0-1 .. r0+M. With the block's
                    heights they give its level-0 shading (:meth:`TerrainStore.get_shade`), bit for
                    bit what version 2 stored, in ~1/70 of the bytes
    color/<l>       uint8 (nb_l, nb_l, M, M, 3), chunk (1, 1, M, M, 3)     [orthophoto only]
    blocks/<l>/minmax   float32 (nb_l, nb_l, 2)   min and max height of the block
    blocks/<l>/error    float32 (nb_l, nb_l)      saturated geometric error (height units)
    blocks/<l>/done     uint8 (nb_l, nb_l)        1 once the block is written (resume)
    lod/square_error/<j>  float32 (2^j, 2^j)            saturated K-patch square-diamond error: a
                          bound on |drawn patch − finest samples| under it (deviation.py)
    lod/edge_error/<j>    float32 (2, 2^j+1, 2^j+1)     edge diamonds: [0] horizontal, [1] vertical
    lod/zmin/<j>, lod/zmax/<j>  float32 (2^j, 2^j)      height range of each level-j square

The direct chunk reads and writes take each array's chunk file names from its own
``zarr.json`` (its chunk key encoding): a store whose arrays use flat keys (``c.<i>.<j>…``)
reads and resumes as well as one with zarr's default nested keys, which prepare writes.

Samples beyond ``rows``/``cols`` are padding (edge-replicated) and are not drawn. A store is
only opened when ``complete`` is true, which ``prepare`` sets after everything is written.

Version 2 made the K-patch errors exact bounds and added ``shade/``; a version-1 store is
refused with a message naming ``massview upgrade STORE``, which rewrites both in place.
Version 3 (this one) stores ``halo/0`` instead of ``shade/0`` (issue 20: level 0's shading
was half of a store's bytes and a sixth of prepare's CPU time, and costs ~0.35 ms a block to
compute, what decoding it cost);
version-2 stores are read as they are (their ``shade/0``), and ``massview upgrade`` converts one.
"""

from __future__ import annotations

import copy
import os
import shutil
import threading
from pathlib import Path

import numpy as np

from ...core.errors import BlockNotFoundError, CorruptBlockError, StoreError
from .layout import TerrainLayout

__all__ = ["FORMAT", "FORMAT_VERSION", "TerrainStore", "create_store", "rows_done", "create_shade_arrays", "shade_arrays", "HaloWriter", "create_halo_array", "OLDEST_READABLE", "dir_size", "ChunkWriter", "block_blosc", "make_top_folder", "CHUNK_KEYS", "write_file", "write_chunk_file", "block_view", "wide_row",
           "ArrayChunkWriter", "array_chunk_writer"]

FORMAT = "massview-terrain"
FORMAT_VERSION = 3
OLDEST_READABLE = 2  # a version-2 store reads as it is (its stored shade/0); version 1 needs `massview upgrade`
CHUNK_KEYS = {"name": "default", "separator": "/"}
"""The chunk key encoding of every array a prepare creates: zarr's default ``c/i/j/0/0``, three
or four folders per chunk (27 874 folders for 11 441 files at 16385²). Flat keys (``"."``:
``c.i.j.0.0``, one folder per array) were measured twice and lost where it matters here (issue
20): on a fresh ext4 file system they save the folders' ``mkdir`` (~190 µs a chunk against ~38;
prepare of the 16385² DEM 12.6–13.5 s against 13.8–14.6 s, system CPU −1.1 s), but on ext4
without a journal, as this host's, a store written 35 s after another was deleted took
17.0–21.0 s against 12.6–14.7 s (system CPU 12.6–17.7 s against 6.0–7.6 s): thousands of files
in one folder are all allocated in one block group, and each allocation scans that group's
recently freed inodes (``find_inode_bit`` → ``recently_deleted``), where the row folders spread
them over many groups (:func:`make_top_folder`)."""


def _compressor(typesize: int = 4):
    """Blosc lz4 (level 5) + byte shuffle. Lossless, like the zstd level 3 of the first format-2
    stores and the lz4 level 9 of the stores before issue 20's eleventh round, so the decoded
    arrays are the same. Against zstd 1, lz4 encodes 3.3× (heights) to 2× (shading) and decodes
    4.4× to 2.5× faster per CPU-second (4097² synthetic store). Level 5 against level 9, on
    one core over 21 level-0 blocks of the 16385² synthetic store: encoding heights 1264 vs 942
    MB/s, shading 839 vs 647 MB/s, decoding ~1.1× faster; the whole store ~2.5 % larger
    (heights 808 vs 794 MiB, shading 1562 vs 1517 MiB). Levels 1–4 were no faster than 5."""
    from zarr.codecs import BloscCodec

    return BloscCodec(cname="lz4", clevel=5, shuffle="shuffle" if typesize > 1 else "noshuffle", typesize=typesize)


_RESUME_KEYS = {"source": "input name", "source_stamp": "input file's size or modification time",
               "source_dtype": "input data type", "spacing": "spacing", "vertical_scale": "vertical scale", "crs": "CRS",
               "transform": "georeference"}


def _resume_differences(old: dict, attrs: dict, layout: TerrainLayout) -> list[str]:
    """What differs between an interrupted run's store attributes ``old`` and this run's: the
    layout, the input (name, file size and modification time, data type, nodata value) and
    the options that shape the store (spacing, vertical scale, CRS, georeference)."""
    out = ["layout (size, --block or K)"] if any(old.get(k) != v for k, v in layout.to_json().items()) else []
    if old.get("format_version") != FORMAT_VERSION:
        out.append(f"store format (version {old.get('format_version')}, from another massview; this one writes {FORMAT_VERSION})")
    out += [what for k, what in _RESUME_KEYS.items() if old.get(k) != attrs.get(k)]
    if (old.get("nodata") or {}).get("value") != (attrs.get("nodata") or {}).get("value"):
        out.append("nodata value")
    return out


def create_store(path: Path, layout: TerrainLayout, attrs: dict, color: bool, overwrite: bool = False,
                 restarted: list | None = None):
    """Create (or reopen for resuming, when its layout, its input and the options that shape it
    match) an incomplete store. An incomplete store from a run whose input or options differ is
    made anew; what differed is appended to ``restarted`` when given."""
    import zarr

    path = Path(path)
    if path.is_dir() and not any(path.iterdir()):  # an empty folder (made by hand, or a mount point): a new store goes in it
        pass
    elif path.exists():
        try:
            g = zarr.open_group(str(path), mode="r+")
            old = dict(g.attrs)
        except Exception:  # noqa: BLE001 - not a zarr group
            old = None
        if old is None or old.get("format") != FORMAT:
            raise StoreError(f"{path} exists and is not a massview terrain store; choose another -o or remove it")
        differ = _resume_differences(old, attrs, layout)
        if old.get("complete") and not overwrite:
            raise StoreError(f"{path} is already a complete store; pass --overwrite to rebuild it")
        arrays = [f"{a}/{lv}" for lv in range(layout.levels) for a in ("heights", *(("color",) if color else ()))]
        arrays += [f"blocks/{lv}/done" for lv in range(layout.levels)] + shade_arrays(layout)
        if not differ and not overwrite and all((path / a / "zarr.json").is_file() for a in arrays):
            return g, True  # resume (a run stopped while creating the arrays left nothing to resume: made anew)
        if differ and not overwrite and restarted is not None:  # (a complete store without --overwrite raised above)
            restarted.extend(differ)
        shutil.rmtree(path)
    g = zarr.open_group(str(path), mode="w-", zarr_format=3)  # (nothing there, or an empty folder: kept, as a mount point must be)
    g.attrs.update({"format": FORMAT, "format_version": FORMAT_VERSION, "complete": False, **layout.to_json(),
                    "levels": layout.levels, "padded": layout.S, **attrs})
    M, new = layout.M, _ArraysLike(g)
    for lv in range(layout.levels):
        nb = layout.blocks(lv)
        new.create(f"heights/{lv}", "heights", shape=(nb, nb, M, M), chunks=(1, 1, M, M), dtype="float32",
                   compressors=_compressor(), fill_value=np.nan, chunk_key_encoding=CHUNK_KEYS)
        if color:
            new.create(f"color/{lv}", "color", shape=(nb, nb, M, M, 3), chunks=(1, 1, M, M, 3), dtype="uint8",
                       compressors=_compressor(1), fill_value=0, chunk_key_encoding=CHUNK_KEYS)
        new.create(f"blocks/{lv}/done", "done", shape=(nb, nb), chunks=(nb, nb), dtype="uint8", fill_value=0,
                   chunk_key_encoding=CHUNK_KEYS)
    create_shade_arrays(g, layout, new)
    return g, False


def rows_done(path) -> tuple[int, int] | None:
    """(level-0 block rows flagged done, level-0 block rows) of an incomplete store at ``path``
    (what a resumed prepare does not read or write again), or None where there is no such store."""
    import zarr

    try:
        g = zarr.open_group(str(path), mode="r")
        if g.attrs.get("format") != FORMAT or g.attrs.get("complete"):
            return None
        done = np.asarray(g["blocks/0/done"][...])
    except Exception:  # noqa: BLE001 - no store, or one stopped before its arrays existed
        return None
    return int(done.all(axis=1).sum()), int(done.shape[0])


def shade_arrays(layout: TerrainLayout) -> list[str]:
    """The names of the shading arrays a current-version store holds: ``halo/0``, ``shade/1`` …"""
    return ["halo/0"] + [f"shade/{lv}" for lv in range(1, layout.levels)]


def create_shade_arrays(g, layout: TerrainLayout, new: _ArraysLike | None = None) -> None:
    """Create :func:`shade_arrays` (empty; any old ones of those names replaced)."""
    M, new = layout.M, new or _ArraysLike(g)
    create_halo_array(g, layout)
    for lv in range(1, layout.levels):
        nb = layout.blocks(lv)
        new.create(f"shade/{lv}", "shade", shape=(nb, nb, M, M, 3), chunks=(1, 1, M, M, 3), dtype="float16",
                   compressors=_compressor(2), fill_value=0, overwrite=True,
                   chunk_key_encoding=CHUNK_KEYS)


def create_halo_array(g, layout: TerrainLayout) -> None:
    """Create ``halo/0`` (empty; an old one replaced)."""
    nb0, M = layout.blocks(0), layout.M
    g.create_array("halo/0", shape=(nb0, nb0, 4, M + 2), chunks=(1, nb0, 4, M + 2), dtype="float32", compressors=None,
                   fill_value=np.nan, overwrite=True, chunk_key_encoding=CHUNK_KEYS)


class HaloWriter:
    """Writes ``halo/0`` a block row at a time (one chunk, its raw little-endian bytes: the
    array has no compressor), from any thread."""

    def __init__(self, group):
        arr = group["halo/0"]
        root = Path(str(group.store.root))
        self.files = _ChunkFiles(str(root / group.path / "halo/0" if group.path else root / "halo/0"), arr.metadata.encode_chunk_key)
        self.shape = tuple(arr.shape[1:])

    def write(self, i: int, halos: np.ndarray) -> None:
        """Block row ``i``'s halos (nb, 4, M+2) float32."""
        if halos.shape != self.shape:
            raise StoreError(f"{self.files.root}: a halo row of shape {halos.shape}, not {self.shape}")
        self.files.put((i, 0, 0, 0), np.ascontiguousarray(halos, "<f4").reshape(-1).view(np.uint8))


class _ArraysLike:
    """``group.create_array`` for a family of arrays that differ only in shape and chunk shape
    (a store's ``heights/<l>``, ``shade/<l>``, ``blocks/<l>/done``, its metadata arrays …): the
    first of each family through zarr, the others as copies of its ``zarr.json``
    (:func:`array_like`), without zarr's ~5 ms event-loop round trip per array. All through zarr
    where the group is not in a local folder, and for a family whose first array's parent group
    is not a plain new group (zarr's document for it is what missing parents get). (An existing
    array is replaced, whatever ``overwrite`` says: callers create fresh stores or pass
    ``overwrite=True``.)"""

    def __init__(self, g):
        from zarr.storage import LocalStore

        self.g = g
        self.base = None
        if isinstance(g.store, LocalStore):
            root = str(g.store.root)
            self.base = os.path.join(root, *g.path.split("/")) if g.path else root
        self.first: dict = {}  # family → (its first array's folder, the zarr.json of that array's parent group)

    def folder(self, name: str) -> str:
        """The folder of the array ``name`` (a local group only)."""
        return os.path.join(self.base, *name.split("/"))

    def create(self, name: str, family: str, *, shape: tuple, chunks: tuple, **kw):
        """Create the array; returns it where zarr made it, None where it was copied (its folder
        is :meth:`folder`)."""
        t = self.first.get(family)
        if t is None:
            arr = self.g.create_array(name, shape=shape, chunks=chunks, **kw)
            if self.base is not None:
                group_doc = plain_group_doc(os.path.dirname(self.folder(name)))
                if group_doc is not None:
                    self.first[family] = (self.folder(name), group_doc)
            return arr
        array_like(t[0], self.base, name, shape, chunks, t[1])
        return None


def plain_group_doc(folder: str) -> bytes | None:
    """The ``zarr.json`` of the group at ``folder`` when it is the document zarr writes for a new
    group (no attributes), else None."""
    import json

    try:
        with open(os.path.join(folder, "zarr.json"), "rb") as fh:
            doc = fh.read()
        parsed = json.loads(doc)
    except (OSError, ValueError):
        return None
    return doc if parsed.get("attributes") == {} and parsed.get("node_type") == "group" else None


def array_like(template: str, base: str, name: str, shape: tuple, chunks: tuple, group_doc: bytes) -> str:
    """Create the zarr v3 array ``name`` under the group folder ``base`` as the array at the
    folder ``template`` with ``shape`` and ``chunks`` instead of its own: its ``zarr.json`` is the
    template's with those two changed, encoded as zarr encodes it (``json.dumps``, ``allow_nan``,
    indent 2), so the file is the one ``create_array`` writes (tests/test_direct_chunks.py). Any
    old array there is removed first (as ``overwrite=True`` does); missing parent groups get
    ``group_doc`` (zarr's document for a new group). Returns the new array's folder."""
    import json

    with open(os.path.join(template, "zarr.json"), "rb") as fh:
        doc = json.loads(fh.read())
    doc["shape"] = list(shape)
    doc["chunk_grid"]["configuration"]["chunk_shape"] = list(chunks)
    d, parts = base, name.split("/")
    for p in parts[:-1]:
        d = os.path.join(d, p)
        if not os.path.exists(os.path.join(d, "zarr.json")):
            os.makedirs(d, exist_ok=True)
            with open(os.path.join(d, "zarr.json"), "wb") as fh:
                fh.write(group_doc)
    root = os.path.join(d, parts[-1])
    shutil.rmtree(root, ignore_errors=True)
    os.makedirs(root)
    with open(os.path.join(root, "zarr.json"), "wb") as fh:
        fh.write(json.dumps(doc, allow_nan=True, indent=2).encode())
    return root


def block_blosc(arr):
    """The blosc codec object of a block array (``heights/<l>``, ``shade/<l>``, ``color/<l>``)
    whose chunks are single blocks ``(1, 1, M, M[, 3])`` stored as little-endian bytes + blosc
    (what prepare writes), for direct chunk reads and writes; None for any other layout (read
    and written through zarr)."""
    from zarr.codecs import BloscCodec, BytesCodec

    meta = arr.metadata
    codecs = meta.codecs
    ok = (len(codecs) == 2 and isinstance(codecs[0], BytesCodec) and isinstance(codecs[1], BloscCodec)
          and (codecs[0].endian is None or codecs[0].endian.value == "little")
          and tuple(meta.chunk_grid.chunk_shape) == (1, 1) + tuple(meta.shape[2:]))
    return codecs[1]._blosc_codec if ok else None


def _decode_block(blosc, data: bytes, out: np.ndarray) -> bool:
    """Decode one block's chunk bytes ``data`` into ``out`` (C-contiguous); False, with nothing
    decoded, where ``data`` cannot be a chunk of it (shorter than blosc's 16-byte header, longer
    than the block stored uncompressed, or a header giving another decoded size)."""
    if not 16 <= len(data) <= out.nbytes + 16 or int.from_bytes(data[4:8], "little") != out.nbytes:  # blosc header: nbytes
        return False
    blosc.decode(data, out=out.reshape(-1).view(np.uint8))
    return True


class ChunkWriter:
    """Whole-chunk writes of one array of a store, encoded on the calling thread.

    The bytes are exactly those zarr writes (its blosc codec object encodes the chunk's
    little-endian bytes, stored under the array's chunk key, ``c/i/j/0/…`` or a flat
    ``c.i.j.0…``), but
    without zarr's per-chunk event-loop round trip, so worker threads compress in parallel
    (blosc releases the GIL). Reads go through zarr as before. Only for arrays whose chunks are
    single blocks (``(1, 1, M, M[, 3])``) with codecs ``bytes`` + ``blosc``."""

    def __init__(self, group, name: str):
        arr = group[name]
        self.blosc = block_blosc(arr)
        if self.blosc is None:
            raise StoreError(f"{name}: unexpected codecs {arr.metadata.codecs} or chunks {arr.metadata.chunk_grid} for direct chunk writes")
        self.dtype = np.dtype(arr.dtype).newbyteorder("<")
        root = Path(str(group.store.root))
        self.files = _ChunkFiles(str(root / group.path / name if group.path else root / name), arr.metadata.encode_chunk_key)
        self.tail = (0,) * (arr.ndim - 2)

    def write(self, i: int, j0: int, blocks: np.ndarray) -> None:
        """Blocks (n, M, M[, 3]) into chunks (i, j0 .. j0+n-1), each written by
        :meth:`_ChunkFiles.put`."""
        for k in range(blocks.shape[0]):
            data = self.blosc.encode(np.ascontiguousarray(blocks[k], self.dtype).reshape(-1).view(np.uint8))
            self.files.put((i, j0 + k) + self.tail, data)


class _ChunkFiles:
    """The chunk files of one array at folder ``root`` whose chunk keys ``key`` gives: a
    ``c/i/j/…`` key (:data:`CHUNK_KEYS`) gets its folders made as zarr would, ``c`` once
    (:func:`make_top_folder`), each chunk row's once, the rest by :func:`write_chunk_file`; a
    flat ``c.i.j`` key is one file in that folder. Thread-safe."""

    def __init__(self, root: str, key):
        self.root, self.key = root, key
        self._made: set = set()
        self._lock = threading.Lock()

    def path(self, coords: tuple) -> str:
        return os.path.join(self.root, *self.key(coords).split("/"))

    def put(self, coords: tuple, data) -> None:
        parts = self.key(coords).split("/")
        if len(parts) == 1:
            write_file(os.path.join(self.root, parts[0]), data)
            return
        row = os.path.join(self.root, *parts[:2])
        if row not in self._made:
            with self._lock:
                if parts[0] not in self._made:
                    make_top_folder(os.path.join(self.root, parts[0]))
                    self._made.add(parts[0])
            os.makedirs(row, exist_ok=True)
            self._made.add(row)
        write_chunk_file(os.path.join(row, parts[2]), parts[3:], data)

    def remove(self, coords: tuple) -> None:
        try:
            os.unlink(self.path(coords))
        except FileNotFoundError:
            pass


_FS_IOC_GETFLAGS, _FS_IOC_SETFLAGS, _FS_TOPDIR_FL = 0x80086601, 0x40086602, 0x00020000  # <linux/fs.h>


def make_top_folder(root: str) -> bool:
    """Make an array's chunk folder ``…/c`` and mark it a "top directory" (``chattr +T``):
    ext4's Orlov allocator then places each chunk row's folder, and the ~60–250 inodes under
    it, in a block group with many free inodes instead of next to the parent. Without it, a
    store written where another was just deleted (``--overwrite``, a benchmark loop) lands in
    groups whose free inodes were all deleted in the last 1–5 minutes, which ext4 without a
    journal skips one by one on every ``mkdir`` and ``open`` (``find_inode_bit`` →
    ``recently_deleted``): writing a 16385² store took 12–15 s of calls there, 3.3–3.5 s with
    the flag (issue 20, under load). Only an allocation hint: names and bytes are unchanged.
    Returns whether the flag was set (False on file systems without it)."""
    import fcntl
    import struct

    os.makedirs(root, exist_ok=True)
    try:
        fd = os.open(root, os.O_RDONLY | os.O_DIRECTORY)
    except OSError:
        return False
    try:
        flags = struct.unpack("i", fcntl.ioctl(fd, _FS_IOC_GETFLAGS, b"\0" * 4))[0]
        if not flags & _FS_TOPDIR_FL:
            fcntl.ioctl(fd, _FS_IOC_SETFLAGS, struct.pack("i", flags | _FS_TOPDIR_FL))
        return True
    except OSError:  # not ext2/3/4, or not permitted: only slower
        return False
    finally:
        os.close(fd)


def write_chunk_file(d: str, tail: list, data) -> None:
    """Write one chunk's encoded bytes at ``d/<tail...>``: its own folders (``i/j``, ``i/j/0`` …)
    with one ``mkdir`` each, parents first (``Path.mkdir(parents=True)`` tried the deepest
    first: 3–5 calls, two failing), then the file by :func:`write_file`."""
    for name in tail:
        try:
            os.mkdir(d)
        except FileExistsError:  # (a resumed run, or a rewritten chunk)
            pass
        d = os.path.join(d, name)
    write_file(d, data)


_NEW_FILE = os.O_WRONLY | os.O_CREAT | os.O_TRUNC | getattr(os, "O_CLOEXEC", 0)


def write_file(path: str, data) -> None:
    """``data`` (bytes or a contiguous buffer) as the whole file ``path``, with ``os.open`` /
    ``os.write`` / ``os.close``: a chunk file without Python's file objects, ~15–20 µs of
    interpreter time (and two GIL hand-offs) less per file than ``open(path, "wb")`` (issue 20;
    11 441 files at 16385²)."""
    view = memoryview(data).cast("B")
    fd = os.open(path, _NEW_FILE, 0o666)
    try:
        done = os.write(fd, view)
        while done < len(view):  # (a regular file takes it all at once; a short write only on a full disk or a signal)
            done += os.write(fd, view[done:])
    finally:
        os.close(fd)


def block_view(wide: np.ndarray, nb: int, M: int) -> np.ndarray:
    """(M, nb·(M-1)+1, ...) global rows → (nb, M, M, ...) blocks sharing their borders, as a
    read-only view (no copy; :meth:`ChunkWriter.write` copies one block at a time)."""
    st = wide.strides
    return np.lib.stride_tricks.as_strided(wide, (nb, M, M) + wide.shape[2:], ((M - 1) * st[1],) + st, writeable=False)


def wide_row(blocks: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """(nb, M, M, ...) blocks of one block row → (M, nb·(M-1)+1, ...) global rows (a copy, into
    ``out`` when given)."""
    nb, M = blocks.shape[0], blocks.shape[1]
    out = np.empty((M, nb * (M - 1) + 1) + blocks.shape[3:], blocks.dtype) if out is None else out
    for j in range(nb):
        out[:, j * (M - 1): j * (M - 1) + M] = blocks[j]
    return out


def dir_size(path: Path) -> int:
    return sum(f.stat().st_size for f in Path(path).rglob("*") if f.is_file())


class TerrainStore:
    """Read access to a complete terrain store. ``get_block`` is thread-safe."""

    def __init__(self, path, require_complete: bool = True, upgrading: bool = False):
        import zarr

        self.path = Path(path)
        if not self.path.exists():
            raise StoreError(f"{self.path}: no such terrain store; create one with `massview prepare terrain INPUT -o {self.path}`")
        try:
            self.group = zarr.open_group(str(self.path), mode="r")
            self.attrs = dict(self.group.attrs)
        except Exception as e:  # noqa: BLE001
            raise StoreError(f"{self.path}: not a readable zarr group ({e})") from None
        if self.attrs.get("format") != FORMAT:
            raise StoreError(f"{self.path}: not a massview terrain store (format attribute is {self.attrs.get('format')!r})")
        if self.attrs.get("format_version", 0) > FORMAT_VERSION:
            raise StoreError(f"{self.path}: format version {self.attrs['format_version']} is newer than this massview ({FORMAT_VERSION}); upgrade massview")
        if self.attrs.get("format_version", 0) < OLDEST_READABLE and not upgrading:
            raise StoreError(f"{self.path}: format version {self.attrs.get('format_version', 0)} was written by an older massview "
                             f"(its LOD errors are not true screen-space bounds and it has no shading pyramid); "
                             f"run `massview upgrade {self.path}` to bring it to version {FORMAT_VERSION} in place, "
                             "or re-run `massview prepare terrain` with --overwrite")
        if require_complete and not self.attrs.get("complete"):
            from ..rebuild import being_written

            if being_written(self.path):
                raise StoreError(f"{self.path}: store is being written by a prepare running now; wait for it to finish")
            raise StoreError(f"{self.path}: store is incomplete (prepare was interrupted); re-run the same `massview prepare terrain` command to finish it")
        try:
            self.layout = TerrainLayout(int(self.attrs["rows"]), int(self.attrs["cols"]), int(self.attrs["M"]), int(self.attrs["K"]))
        except (KeyError, TypeError, ValueError) as e:
            raise StoreError(f"{self.path}: its attributes (zarr.json) have no valid layout ({type(e).__name__}: {e}); the store is "
                             "damaged — re-run `massview prepare terrain` with --overwrite") from None
        self._check_attrs_against_arrays()
        self._heights = [self.array(f"heights/{lv}") for lv in range(self.layout.levels)]
        for lv, h in enumerate(self._heights):
            self.check_array(f"heights/{lv}", h, raise_=True)
        self._shade: dict = {}  # level → the open shade/<level> array (_shade_array)
        self._codecs: dict = {}  # (what, level) → block_blosc of that array, or False (_block_codec)
        self._keys: dict = {}  # (what, level) → that array's chunk key function (_chunk_key)
        self.has_color = "color" in self.group and self.attrs.get("color") == "orthophoto"
        self.has_shade = ("shade" in self.group or "halo" in self.group) and not upgrading
        self.shade0_computed = self.attrs.get("format_version", 0) >= 3  # level-0 shading from heights + halo/0
        if self.shade0_computed:  # its kernel's module (numba) imported now, on this thread: two loader threads importing
            from . import rowkernels  # noqa: F401 - numba at once for their first get_shade fail (a partly initialised module)
        self._shade0_params = None  # (dx, dy, zlo, rng) of shading_params, once (_computed_shade0)
        self._color = [self.group[f"color/{lv}"] for lv in range(self.layout.levels)] if self.has_color else None

    def _check_attrs_against_arrays(self) -> None:
        """The root attributes' layout (M, rows, cols, levels, padded) must agree with itself and
        with ``heights/0``'s block size and block count; a StoreError naming both where not (an
        edited or damaged root ``zarr.json`` otherwise surfaced as "heights/3 does not open")."""
        lay, a = self.layout, self.attrs
        said = f"M {lay.M}, levels {a.get('levels', '?')}, padded {a.get('padded', '?')}, rows {lay.rows}, cols {lay.cols}"
        try:
            h0 = self.group["heights/0"]
            shape, chunks = tuple(h0.shape), tuple(h0.chunks)
        except Exception:  # noqa: BLE001 - heights/0 itself damaged: named when it is opened below
            return
        own = (a.get("levels", lay.levels) == lay.levels and a.get("padded", lay.S) == lay.S)
        if own and len(shape) == 4 and chunks[2:] == (lay.M, lay.M):
            return  # the attributes agree with heights/0's blocks (its shape is checked, and named, as an array's)
        have = (f"heights/0 is {'×'.join(map(str, shape[:2]))} blocks in {'×'.join(map(str, chunks[2:]))} chunks"
                if len(shape) == 4 and len(chunks) == 4 else f"heights/0 has shape {list(shape)}")
        raise StoreError(f"{self.path}: its attributes ({said}) do not match its arrays ({have}; the attributes make "
                         f"{lay.blocks(0)}×{lay.blocks(0)} blocks of {lay.M}×{lay.M} in {lay.levels} levels); its "
                         f"{self.path / 'zarr.json'} is damaged — re-run `massview prepare terrain` with --overwrite")

    def expected(self, name: str) -> tuple[tuple, tuple | None, str] | None:
        """(shape, chunk shape or None when not fixed, dtype) that the layout gives the array
        ``name`` (as :func:`create_store`, ``write_metadata`` and the Röttger table make them),
        or None for a name this layout does not know."""
        lay, parts = self.layout, name.split("/")
        M = lay.M
        try:
            if parts[0] in ("heights", "shade", "color") and len(parts) == 2:
                nb = lay.blocks(int(parts[1]))
                tail = () if parts[0] == "heights" else (3,)
                dt = {"heights": "float32", "shade": "float16", "color": "uint8"}[parts[0]]
                return (nb, nb, M, M) + tail, (1, 1, M, M) + tail, dt
            if parts == ["halo", "0"]:
                nb = lay.blocks(0)
                return (nb, nb, 4, M + 2), (1, nb, 4, M + 2), "float32"
            if parts[0] == "blocks" and len(parts) == 3:
                nb = lay.blocks(int(parts[1]))
                return {"minmax": ((nb, nb, 2), None, "float32"), "error": ((nb, nb), None, "float32"),
                        "done": ((nb, nb), None, "uint8")}.get(parts[2])
            if parts[0] == "lod" and len(parts) == 3:
                j = int(parts[2])
                if parts[1] == "edge_error":
                    return (2, 2**j + 1, 2**j + 1), None, "float32"
                return (2**j, 2**j), None, "float32"
            if parts[:2] == ["roettger", "d2"] and len(parts) == 3:
                t = int(parts[2])
                return (2**t, 2**t), None, "float32"
        except (ValueError, IndexError):
            return None
        return None

    def check_array(self, name: str, arr, raise_: bool = False) -> str | None:
        """A problem (naming the array, its ``zarr.json`` and what to do) when the open array
        ``arr`` has another shape, chunk shape or dtype than :meth:`expected` says; None when it
        agrees. ``raise_``: raise it as a StoreError instead."""
        want = self.expected(name)
        if want is None:
            return None
        shape, chunks, dtype = want
        have = (tuple(arr.shape), tuple(arr.chunks), str(np.dtype(arr.dtype)))
        bad = []
        if have[0] != shape:
            bad.append(f"shape {list(have[0])}, not {list(shape)}")
        if chunks is not None and have[1] != chunks:
            bad.append(f"chunks {list(have[1])}, not {list(chunks)}")
        if have[2] != dtype:
            bad.append(f"dtype {have[2]}, not {dtype}")
        if not bad:
            return None
        msg = (f"the array {name} has {' and '.join(bad)} (what the store's attributes, M {self.layout.M} and "
               f"{self.layout.levels} levels, give); its {self.path / name / 'zarr.json'} is damaged — {self._fix(name)}")
        if raise_:
            raise StoreError(f"{self.path}: {msg}")
        return msg

    def array(self, name: str):
        """The store's zarr array ``name`` (e.g. ``blocks/0/minmax``); StoreError naming it where
        it is missing or its ``zarr.json`` does not parse."""
        try:
            return self.group[name]
        except Exception as e:  # noqa: BLE001 - KeyError, JSONDecodeError, zarr's own errors
            raise StoreError(f"{self.path}: the array {name} does not open ({type(e).__name__}: {e}); the store is damaged — "
                             f"{self._fix(name)}") from None

    def _fix(self, name: str) -> str:
        """What to do about the damaged array ``name``: ``halo/0`` is written again from the heights."""
        return self.halo_fix if name == "halo/0" else "re-run `massview prepare terrain` with --overwrite"

    @property
    def spacing(self) -> tuple[float, float]:
        dx, dy = self.attrs.get("spacing", [1.0, 1.0])
        return float(dx), float(dy)

    @property
    def vertical_scale(self) -> float:
        return float(self.attrs.get("vertical_scale", 1.0))

    @property
    def block_bytes(self) -> int:
        return self.layout.M * self.layout.M * 4

    def _check_key(self, level: int, i: int, j: int) -> None:
        nb = self.layout.blocks(level) if 0 <= level < self.layout.levels else 0
        if not (0 <= i < nb and 0 <= j < nb):
            raise BlockNotFoundError(f"{self.path}: block (level {level}, {i}, {j}) is outside the pyramid ({self.layout.levels} levels)")

    def chunk_path(self, level: int, i: int, j: int, what: str = "heights") -> Path:
        """The file of block (level, i, j) of ``what`` (``heights``, ``shade``, ``color`` or
        ``halo``: level 0 only, one file a block row)."""
        if what == "halo":
            return self.path / "halo" / "0" / self._chunk_key("halo", 0)((i, 0, 0, 0))
        return self.path / what / str(level) / self._chunk_key(what, level)((i, j, 0, 0, 0)[:4 + (what != "heights")])

    def shade_file(self, level: int, i: int, j: int) -> Path:
        """The file block (level, i, j)'s shading comes from: its ``shade`` chunk, or at level 0 of
        a version-3 store the ``halo/0`` chunk of its block row."""
        return self.chunk_path(level, i, j, "halo" if level == 0 and self.shade0_computed else "shade")

    def _chunk_key(self, what: str, level: int):
        """The chunk key function of ``<what>/<level>`` (its ``zarr.json``'s encoding), looked up
        once; zarr's default ``c/i/j/…`` where the array does not open (a store being upgraded
        has no ``shade``)."""
        key = (what, level)
        if key not in self._keys:
            try:
                arr = self._block_array(what, level)
                self._keys[key] = arr.metadata.encode_chunk_key
            except Exception:  # noqa: BLE001 - no such array: name where zarr would look
                self._keys[key] = lambda c: "c/" + "/".join(map(str, c))
        return self._keys[key]

    def _block_codec(self, what: str, level: int):
        """:func:`block_blosc` of ``<what>/<level>``, looked up once; False where there is none
        (read through zarr)."""
        key = (what, level)
        if key not in self._codecs:
            arr = self._block_array(what, level)
            self._codecs[key] = block_blosc(arr) or False
        return self._codecs[key]

    def _block_array(self, what: str, level: int):
        """The array ``<what>/<level>`` (``heights``, ``color``, ``shade`` or ``halo``)."""
        if what == "halo":
            return self.group["halo/0"]
        return self._heights[level] if what == "heights" else self._color[level] if what == "color" else self._shade_array(level)

    def _shade_array(self, level: int):
        """``shade/<level>``, opened once."""
        if level not in self._shade:
            self._shade[level] = self.group[f"shade/{level}"]
        return self._shade[level]

    def _direct_block(self, what: str, level: int, i: int, j: int, dtype: str, tail: tuple = (),
                      out: np.ndarray | None = None) -> np.ndarray | None:
        """Block (level, i, j) of ``what`` decoded straight from its chunk file with the array's
        blosc codec into ``out`` (or a new array), the same values as zarr's read, ~10× faster
        (no event-loop round trip); None where the file is missing, is not one block's chunk,
        or does not decode — the caller then reads through zarr, which gives the fill value or
        names the damage."""
        blosc = self._block_codec(what, level)
        if blosc is False:
            return None
        M = self.layout.M
        if out is None or out.shape != (M, M) + tail or out.dtype != np.dtype(dtype) or not out.flags.c_contiguous:
            out = np.empty((M, M) + tail, dtype)
        try:
            fd = os.open(self.chunk_path(level, i, j, what), os.O_RDONLY | getattr(os, "O_CLOEXEC", 0))
            try:
                data = os.read(fd, out.nbytes + 17)
            finally:
                os.close(fd)
            return out if _decode_block(blosc, data, out) else None
        except (OSError, RuntimeError, ValueError, TypeError):
            return None

    def get_block(self, level: int, i: int, j: int, out: np.ndarray | None = None) -> np.ndarray:
        """Heights of block (level, i, j): float32 (M, M), rows = +y; in ``out`` when given (a
        C-contiguous float32 (M, M) array, which is then returned)."""
        self._check_key(level, i, j)
        try:
            b = self._direct_block("heights", level, i, j, "<f4", out=out)
            b = _into(out, np.asarray(self._heights[level][i, j])) if b is None else b
        except Exception as e:  # noqa: BLE001 - codec errors come in many types
            raise CorruptBlockError(f"{self.path}: block (level {level}, {i}, {j}) does not decode ({type(e).__name__}: {e}); "
                                    f"the file {self.chunk_path(level, i, j)} is damaged — re-run prepare with --overwrite") from None
        if np.isnan(b).any():
            raise BlockNotFoundError(f"{self.path}: block (level {level}, {i}, {j}) is missing ({self.chunk_path(level, i, j)}); "
                                     "re-run prepare with --overwrite")
        return b

    def get_block_row(self, level: int, i: int, out: np.ndarray | None = None) -> np.ndarray:
        """All blocks of block row ``i`` at ``level`` (nb, M, M), read in one call (zarr decodes
        the chunks concurrently); failures are re-raised per block with its name. ``out``, a
        C-contiguous float32 (nb, M, M) buffer, receives them where the chunks decode directly
        (the usual case; check the returned array, which is then ``out``)."""
        self._check_key(level, i, 0)
        row = self._direct_row(level, i, out)
        if row is not None:
            return row
        try:
            row = np.asarray(self._heights[level][i])
        except Exception:  # noqa: BLE001 - find and name the bad block
            return np.stack([self.get_block(level, i, j) for j in range(self.layout.blocks(level))])
        if np.isnan(row).any():
            j = int(np.argwhere(np.isnan(row).any(axis=(1, 2)))[0, 0])
            self.get_block(level, i, j)  # raises BlockNotFoundError naming it
        return row

    def _direct_row(self, level: int, i: int, out: np.ndarray | None = None) -> np.ndarray | None:
        """Block row ``i`` decoded straight from its chunk files with the array's blosc codec
        (the inverse of :class:`ChunkWriter`: the same decoded values as zarr's read, without its
        per-chunk event-loop round trip; each file opened relative to the array's folder and
        read with one call), or None when any chunk is missing, longer than a block's chunk can
        be, does not decode to a whole block, or the codecs are not bytes + blosc — the caller
        then reads through zarr, which names the bad block."""
        blosc = self._block_codec("heights", level)
        if blosc is False:
            return None
        M, nb = self.layout.M, self.layout.blocks(level)
        if out is None or out.shape != (nb, M, M) or out.dtype != np.dtype("<f4") or not out.flags.c_contiguous:
            out = np.empty((nb, M, M), "<f4")
        cap = out[0].nbytes + 16  # the largest a chunk of a block can be (blosc's 16-byte header, data stored uncompressed)
        key = self._chunk_key("heights", level)
        try:
            row = os.open(os.path.join(self.path, "heights", str(level)), os.O_RDONLY | os.O_DIRECTORY)
        except OSError:
            return None
        try:
            for j in range(nb):
                fd = os.open(key((i, j, 0, 0)), os.O_RDONLY | getattr(os, "O_CLOEXEC", 0), dir_fd=row)
                try:
                    data = os.read(fd, cap + 1)
                finally:
                    os.close(fd)
                if not _decode_block(blosc, data, out[j]):
                    return None
        except (OSError, RuntimeError, ValueError, TypeError):  # missing, damaged or wrong-sized chunk
            return None
        finally:
            os.close(row)
        return out

    def get_color(self, level: int, i: int, j: int, out: np.ndarray | None = None) -> np.ndarray | None:
        """Orthophoto colour of block (level, i, j): uint8 (M, M, 3), or None without one; in
        ``out`` when given."""
        if not self.has_color:
            return None
        self._check_key(level, i, j)
        b = self._direct_block("color", level, i, j, "u1", (3,), out=out)
        if b is not None:
            return b
        try:
            return _into(out, np.asarray(self._color[level][i, j]))
        except Exception as e:  # noqa: BLE001
            raise CorruptBlockError(f"{self.path}: colour block (level {level}, {i}, {j}) does not decode ({e})") from None

    def get_shade(self, level: int, i: int, j: int, out: np.ndarray | None = None,
                  heights: np.ndarray | None = None) -> np.ndarray:
        """Shading maps of block (level, i, j): float16 (M, M, 3) = slope x, slope y, height
        fraction (see :mod:`colors`); in ``out`` when given. At level 0 of a version-3 store
        they are computed from the block's heights (``heights`` when the caller has read them)
        and its halo (:func:`colors.shade0_block`)."""
        self._check_key(level, i, j)
        if level == 0 and self.shade0_computed:
            return self._computed_shade0(i, j, out, heights)
        b = self._direct_block("shade", level, i, j, "<f2", (3,), out=out)
        if b is not None:
            return b
        try:
            return _into(out, np.asarray(self._shade_array(level)[i, j]))
        except Exception as e:  # noqa: BLE001
            raise CorruptBlockError(f"{self.path}: shading block (level {level}, {i}, {j}) does not decode ({e}); "
                                    "re-run `massview upgrade` or prepare with --overwrite") from None

    def _computed_shade0(self, i: int, j: int, out: np.ndarray | None, heights: np.ndarray | None) -> np.ndarray:
        from .colors import shade0_block

        if self._shade0_params is None:
            try:
                zlo, zhi = (float(v) for v in self.attrs["height_range"])
            except (KeyError, TypeError, ValueError):
                raise StoreError(f"{self.path}: its attributes have no height_range, which its level-0 shading needs; the "
                                 f"store is damaged — re-run `massview prepare terrain` with --overwrite") from None
            self._shade0_params = shading_params(self.spacing, zlo, zhi)
        h = self.get_block(0, i, j) if heights is None else heights
        M = self.layout.M
        if out is None or out.shape != (M, M, 3) or out.dtype != np.float16 or not out.flags.c_contiguous:
            res = shade0_block(self.get_halo(i, j), h, *self._shade0_params)
            return _into(out, res)
        return shade0_block(self.get_halo(i, j), h, *self._shade0_params, out=out)

    def get_halo(self, i: int, j: int) -> np.ndarray:
        """The samples around level-0 block (i, j): float32 (4, M+2) (``halo/0``), read
        straight from its block row's file (one small read) where it has the array's size,
        else through zarr (which names the damage)."""
        self._check_key(0, i, j)
        M, nb = self.layout.M, self.layout.blocks(0)
        out = np.empty((4, M + 2), "<f4")
        f = self.chunk_path(0, i, j, "halo")
        try:
            fd = os.open(f, os.O_RDONLY | getattr(os, "O_CLOEXEC", 0))
            try:
                if os.fstat(fd).st_size == nb * out.nbytes:
                    data = os.pread(fd, out.nbytes, j * out.nbytes)
                    if len(data) == out.nbytes:
                        out.reshape(-1).view(np.uint8)[:] = np.frombuffer(data, np.uint8)
                        if not np.isnan(out).any():
                            return out
            finally:
                os.close(fd)
        except OSError:
            pass
        try:
            got = np.asarray(self.group["halo/0"][i, j], np.float32)
        except Exception as e:  # noqa: BLE001 - codec and shape errors come in many types
            raise CorruptBlockError(f"{self.path}: the halo of block (level 0, {i}, {j}) does not decode ({type(e).__name__}: {e}); "
                                    f"the file {f} is damaged — {self.halo_fix}") from None
        if got.shape != out.shape or np.isnan(got).any():
            raise BlockNotFoundError(f"{self.path}: the halo of block (level 0, {i}, {j}) is missing or damaged ({f}); "
                                     f"{self.halo_fix}")
        return got

    @property
    def halo_fix(self) -> str:
        """What to do about a damaged ``halo/0``: ``massview upgrade`` writes it again from the heights."""
        return f"run `massview upgrade {self.path}` to write it again from the heights (or prepare with --overwrite)"

    def block_minmax(self, level: int) -> np.ndarray:
        return np.asarray(self.array(f"blocks/{level}/minmax")[...])

    def block_error(self, level: int) -> np.ndarray:
        return np.asarray(self.array(f"blocks/{level}/error")[...])

    def height_ranges(self, j: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """(zmin, zmax) float32 (2^j, 2^j) of the level-j squares (``lod/zmin/<j>``,
        ``lod/zmax/<j>``); level 0 is the whole domain's range (what the world box needs)."""
        return np.asarray(self.array(f"lod/zmin/{j}")[...]), np.asarray(self.array(f"lod/zmax/{j}")[...])

    def lod_arrays(self):
        """(square_error[j], edge_error[j], zmin[j], zmax[j]) lists for the patch LOD."""
        J = self.layout.J
        sq = [np.asarray(self.array(f"lod/square_error/{j}")[...]) for j in range(J)]
        dg = [np.asarray(self.array(f"lod/edge_error/{j}")[...]) for j in range(J)]
        zmin = [np.asarray(self.array(f"lod/zmin/{j}")[...]) for j in range(J + 1)]
        zmax = [np.asarray(self.array(f"lod/zmax/{j}")[...]) for j in range(J + 1)]
        return sq, dg, zmin, zmax


def shading_params(spacing: tuple, zlo: float, zhi: float) -> tuple:
    """(dx, dy, zlo, rng) of the shading kernels: what :func:`colors.write_shading` and
    :meth:`TerrainStore.get_shade` both use, so level 0 computed on reading is what prepare made."""
    return (float(spacing[0]), float(spacing[1]), float(zlo), max(float(zhi) - float(zlo), 1e-6))


def _into(out: np.ndarray | None, a: np.ndarray) -> np.ndarray:
    """``a`` copied into ``out`` (returned) when given, else ``a``."""
    if out is None:
        return a
    out[...] = a
    return out


class ArrayChunkWriter:
    """Whole-array writes of one zarr v3 array's chunks, encoded and written on the calling
    thread (any thread: each call writes its own chunk files), for arrays that zarr's async
    pipeline would otherwise write one event-loop round trip and one thread hop per codec
    and chunk at a time (the Röttger table, the metadata arrays).

    The files are exactly those ``arr[...] = a`` writes (tests/test_direct_chunks.py): each
    chunk is copied into a C-ordered buffer of the chunk shape, initialised to the fill value
    where the array ends inside it (zarr's partial edge chunks); a chunk that zarr's own
    ``NDBuffer.all_equal`` finds equal to the fill value (bit for bit at a fill of 0.0, so
    −0.0 is data; NaN equal to a NaN fill) is not written and any old file of it removed,
    unless the array's ``write_empty_chunks`` says otherwise; the rest are encoded with the
    array's own codec object (little-endian bytes, then its blosc or zstd compressor) and
    written under its chunk key. Use :func:`array_chunk_writer`, which returns None where this
    does not apply."""

    def __init__(self, arr, encode):
        from zarr.core.buffer import default_buffer_prototype

        meta = arr.metadata
        self.shape, self.chunks = tuple(meta.shape), tuple(meta.chunk_grid.chunk_shape)
        self.dtype = np.dtype(arr.dtype)
        self.fill = meta.fill_value
        self.skip_fill = not arr._async_array.config.write_empty_chunks
        self.encode = encode
        self.files = _ChunkFiles(os.path.join(str(arr.store.root), *arr.path.split("/")), meta.encode_chunk_key)
        self._nd = default_buffer_prototype().nd_buffer.from_numpy_array

    def like(self, root: str, shape: tuple, chunks: tuple) -> ArrayChunkWriter:
        """The writer of the array at folder ``root`` made from this one's by :func:`array_like`
        (same dtype, fill value, codecs and chunk keys; ``shape`` and ``chunks`` its own)."""
        out = copy.copy(self)
        out.shape, out.chunks, out.files = tuple(shape), tuple(chunks), _ChunkFiles(root, self.files.key)
        return out

    @property
    def grid(self) -> tuple:
        """The number of chunks along each axis."""
        return tuple(-(-n // c) for n, c in zip(self.shape, self.chunks))

    def write(self, a: np.ndarray, coords) -> None:
        """The chunks at ``coords`` (an iterable of chunk index tuples) of the whole array ``a``
        (the array's shape and dtype)."""
        if a.shape != self.shape or a.dtype != self.dtype:
            raise StoreError(f"{self.files.root}: direct chunk write of a {a.dtype} {a.shape} array into a {self.dtype} {self.shape} one")
        for c in coords:
            self._write_chunk(a, tuple(c))

    def _write_chunk(self, a: np.ndarray, c: tuple) -> None:
        part = a[tuple(slice(i * s, min((i + 1) * s, n)) for i, s, n in zip(c, self.chunks, self.shape))]
        if part.shape == self.chunks:
            buf = np.ascontiguousarray(part)
        else:  # an edge chunk: the fill value beyond the array's end, as zarr pads it
            buf = np.full(self.chunks, self.fill, self.dtype)
            buf[tuple(slice(0, k) for k in part.shape)] = part
        if self.skip_fill and self._nd(buf.reshape(-1)[:1]).all_equal(self.fill) and self._nd(buf).all_equal(self.fill):
            self.files.remove(c)  # (the first element decides almost every chunk; the whole chunk only where it is the fill value)
            return
        data = np.ascontiguousarray(buf, self.dtype.newbyteorder("<")).reshape(-1).view(np.uint8)
        self.files.put(c, data if self.encode is None else self.encode(data))


def array_chunk_writer(arr) -> ArrayChunkWriter | None:
    """An :class:`ArrayChunkWriter` for the zarr array ``arr``, or None (write through zarr)
    unless it is a zarr v3 array in a local store with a regular chunk grid, the default
    chunk keys (``c.…`` or ``c/…``), codecs ``bytes`` (little-endian) + at most one blosc or zstd
    compressor, and a fill value."""
    from zarr.codecs import BloscCodec, BytesCodec, ZstdCodec
    from zarr.core.chunk_grids import RegularChunkGrid
    from zarr.core.chunk_key_encodings import DefaultChunkKeyEncoding
    from zarr.storage import LocalStore

    meta = getattr(arr, "metadata", None)
    if getattr(meta, "zarr_format", None) != 3 or not isinstance(arr.store, LocalStore) or meta.fill_value is None:
        return None
    if not isinstance(meta.chunk_grid, RegularChunkGrid) or not isinstance(meta.chunk_key_encoding, DefaultChunkKeyEncoding):
        return None
    codecs = meta.codecs
    if not (1 <= len(codecs) <= 2 and isinstance(codecs[0], BytesCodec)) or np.dtype(arr.dtype).byteorder == ">":
        return None
    if codecs[0].endian is not None and codecs[0].endian.value != "little":
        return None
    if len(codecs) == 1:
        return ArrayChunkWriter(arr, None)
    if isinstance(codecs[1], BloscCodec):
        return ArrayChunkWriter(arr, codecs[1]._blosc_codec.encode)
    if isinstance(codecs[1], ZstdCodec):
        return ArrayChunkWriter(arr, codecs[1]._zstd_codec.encode)
    return None
