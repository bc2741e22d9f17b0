"""Direct chunk writes (store.ArrayChunkWriter) make exactly the files zarr's own
``arr[...] = a`` makes: the same chunk keys and bytes, chunks equal to the fill value skipped
(and old files of them removed) as zarr skips them, partial edge chunks padded with the fill
value; and the Röttger table and metadata arrays written with it equal those written through
zarr, file for file (zarr.json included)."""

import hashlib
import os

import numpy as np
import pytest
import zarr
from zarr.codecs import BloscCodec

from massview.data.terrain import ArraySource, TerrainStore, prepare_terrain
from massview.data.terrain.metadata import compute_metadata, write_metadata
from massview.data.terrain.roettger import TABLE_CODEC, VERSION, k_factor, write_table
from massview.data.terrain.store import CHUNK_KEYS, array_chunk_writer


def tree(root) -> dict:
    """{relative path: sha256} of every file under ``root``."""
    out = {}
    for dp, _, fn in os.walk(root):
        for f in fn:
            p = os.path.join(dp, f)
            with open(p, "rb") as fh:
                out[os.path.relpath(p, root)] = hashlib.sha256(fh.read()).hexdigest()
    return out


def awkward(shape, dtype, chunks, fill) -> np.ndarray:
    """Data whose chunks include all-fill ones, one of −0.0 (data at a 0.0 fill: bits differ),
    NaN, a chunk equal to the fill but for its last element, and ordinary values."""
    rng = np.random.default_rng(7)
    a = (rng.standard_normal(shape) * 100).astype(dtype) if np.dtype(dtype).kind == "f" else rng.integers(1, 200, shape).astype(dtype)
    c0 = tuple(slice(0, c) for c in chunks)
    a[c0 if chunks != shape else slice(0, shape[0] // 2)] = fill  # the first chunk: the fill value (half the array if one chunk)
    if a.ndim == 2 and shape[1] > 2 * chunks[1]:
        c1 = (slice(0, chunks[0]), slice(chunks[1], 2 * chunks[1]))
        a[c1] = fill
        a[chunks[0] - 1, 2 * chunks[1] - 1] = 1  # fill but for its last element
    if np.dtype(dtype).kind == "f" and a.ndim == 2 and shape[0] > 2 * chunks[0]:
        a[chunks[0]: 2 * chunks[0], : chunks[1]] = -0.0
        a[2 * chunks[0]:, : chunks[1]] = np.nan  # the edge chunks of the first column: NaN
        a[chunks[0]: 2 * chunks[0], chunks[1]: 2 * chunks[1]] = np.float32(np.nan) if np.isnan(fill) else fill
    return a


CASES = [  # shape, chunks, dtype, compressors, fill value
    ((37, 53), (16, 16), "float32", BloscCodec(cname="zstd", clevel=3, shuffle="shuffle", typesize=4), 0.0),
    ((37, 53), (16, 16), "float32", "auto", 0.0),  # zarr's default zstd (the metadata arrays)
    ((37, 53), (16, 16), "float32", None, 0.0),
    ((37, 53), (16, 16), "float32", BloscCodec(cname="lz4", clevel=9, shuffle="shuffle", typesize=4), float("nan")),
    ((37, 53), (16, 16), "float32", "auto", 5.0),
    ((64, 64), (64, 64), "float32", "auto", 0.0),  # one whole chunk (the metadata arrays)
    ((2, 9, 9), (2, 9, 9), "float32", "auto", 0.0),
    ((3, 20, 21), (2, 8, 8), "float32", "auto", 0.0),
    ((37, 53), (16, 16), "uint8", "auto", 0),
]


@pytest.mark.parametrize("shape, chunks, dtype, compressors, fill", CASES)
@pytest.mark.parametrize("write_empty", [False, True])
@pytest.mark.parametrize("sep", ["/", "."])  # the chunk keys prepare writes (CHUNK_KEYS), and flat ones'
def test_direct_chunks_are_the_files_zarr_writes(tmp_path, shape, chunks, dtype, compressors, fill, write_empty, sep):
    a = awkward(shape, dtype, chunks, fill)
    trees = []
    for way in ("zarr", "direct"):
        g = zarr.open_group(str(tmp_path / way), mode="w", zarr_format=3)
        arr = g.create_array("x/y", shape=shape, chunks=chunks, dtype=dtype, compressors=compressors, fill_value=fill,
                             config={"write_empty_chunks": write_empty}, chunk_key_encoding={"name": "default", "separator": sep})
        w = array_chunk_writer(arr)
        assert w is not None
        for data in ((a + 1).astype(dtype), a):  # written twice: the second write's fill chunks remove the first's files
            if way == "zarr":
                arr[...] = data
            else:
                w.write(data, np.ndindex(*w.grid))
        trees.append(tree(tmp_path / way))
        np.testing.assert_array_equal(arr[...], a)
    assert trees[0] == trees[1]
    assert any(k.endswith("zarr.json") for k in trees[0]) and sum(f"/c{sep}" in k for k in trees[0]) >= 1


def test_writer_is_refused_where_it_does_not_apply(tmp_path):
    mem = zarr.open_group(zarr.storage.MemoryStore(), mode="w", zarr_format=3)
    assert array_chunk_writer(mem.create_array("a", shape=(4,), dtype="float32")) is None  # not a local store
    g = zarr.open_group(str(tmp_path / "s"), mode="w", zarr_format=3)
    assert array_chunk_writer(g.create_array("b", shape=(4,), dtype="float32", shards=(4,), chunks=(2,))) is None
    assert array_chunk_writer(g.create_array("c", shape=(4,), dtype="float32", compressors=zarr.codecs.GzipCodec())) is None
    assert array_chunk_writer(g.create_array("d", shape=(4,), dtype="float32", chunk_key_encoding={"name": "v2"})) is None


def write_table_through_zarr(g, d2, C_min):
    """The table as write_table wrote it before the direct writes (arr[...] = a)."""
    g.attrs["roettger"] = None
    for t, a in enumerate(d2):
        ch = (min(a.shape[0], 256), min(a.shape[1], 256))
        g.create_array(f"roettger/d2/{t}", shape=a.shape, chunks=ch, dtype="float32", overwrite=True,
                       compressors=BloscCodec(**TABLE_CODEC), chunk_key_encoding=CHUNK_KEYS)[...] = a
    g.attrs["roettger"] = {"version": VERSION, "C_min": float(C_min), "K": k_factor(C_min), "depths": len(d2)}


@pytest.mark.parametrize("workers", [1, 2])
def test_table_is_the_one_zarr_writes(tmp_path, workers):
    rng = np.random.default_rng(3)
    d2 = [(rng.random((2**t, 2**t)) * 3).astype(np.float32) for t in range(10)]
    d2[9][:300, :] = 0  # a padded DEM's flat padding: whole chunks (and part of one row of them) are 0 → not written
    d2[9][300:310, :40] = -0.0
    d2[8][:, 200:] = np.nan
    d2[3][:] = 0
    trees = []
    for way in ("zarr", "direct"):
        g = zarr.open_group(str(tmp_path / way), mode="w", zarr_format=3)
        g.attrs["format"] = "x"
        for _ in range(2):  # rewritten over itself, as a resumed prepare does
            if way == "zarr":
                write_table_through_zarr(g, d2, 4.0)
            else:
                write_table(g, iter(list(enumerate(d2))), 4.0, workers=workers)
        trees.append(tree(tmp_path / way))
    assert trees[0] == trees[1]
    assert "roettger/d2/9/c/0/0" not in trees[1] and "roettger/d2/9/c/1/0" in trees[1]


def write_metadata_through_zarr(g, lay, meta):
    """The metadata arrays as write_metadata wrote them before the direct writes."""
    for lv in range(lay.levels):
        for name, arr in ((f"blocks/{lv}/minmax", meta.minmax[lv]), (f"blocks/{lv}/error", meta.block_error[lv])):
            g.create_array(name, shape=arr.shape, dtype="float32", chunks=arr.shape, overwrite=True, chunk_key_encoding=CHUNK_KEYS)[...] = arr
    for j in range(lay.J):
        for name, arr in ((f"lod/square_error/{j}", meta.sq[j]), (f"lod/edge_error/{j}", meta.dg[j])):
            g.create_array(name, shape=arr.shape, dtype="float32", chunks=arr.shape, overwrite=True, chunk_key_encoding=CHUNK_KEYS)[...] = arr
    for j in range(lay.J + 1):
        for name, arr in ((f"lod/zmin/{j}", meta.zmin[j]), (f"lod/zmax/{j}", meta.zmax[j])):
            g.create_array(name, shape=arr.shape, dtype="float32", chunks=arr.shape, overwrite=True, chunk_key_encoding=CHUNK_KEYS)[...] = arr


@pytest.mark.parametrize("flat", [False, True])
def test_metadata_arrays_are_the_ones_zarr_writes(tmp_path, flat):
    h = np.zeros((300, 200), np.float32)  # flat: zero heights and errors (chunks equal to the fill value, not written)
    if not flat:
        h[100:, 50:] = np.random.default_rng(2).standard_normal((200, 150)).astype(np.float32) * 30
    prepare_terrain(ArraySource(h, "dem"), tmp_path / "s.zarr", block=129, color=None)
    store = TerrainStore(tmp_path / "s.zarr")
    meta = compute_metadata(store, lambda *a: None)
    trees = []
    for way in ("zarr", "direct"):
        g = zarr.open_group(str(tmp_path / way), mode="w", zarr_format=3)
        for lv in range(store.layout.levels):  # (as create_store makes the blocks/<l> groups)
            g.create_array(f"blocks/{lv}/done", shape=(1, 1), dtype="uint8")
        (write_metadata_through_zarr if way == "zarr" else write_metadata)(g, store.layout, meta)
        trees.append(tree(tmp_path / way))
    assert trees[0] == trees[1]
    assert {k: v for k, v in tree(tmp_path / "s.zarr").items() if k.startswith("lod/")} == {k: v for k, v in trees[1].items() if k.startswith("lod/")}
    n_arrays = sum(k.endswith("zarr.json") and k.count("/") == 3 and "done" not in k for k in trees[1])
    n_chunks = sum("/c/" in k and "done" not in k for k in trees[1])
    assert n_arrays == 2 * store.layout.levels + 2 * store.layout.J + 2 * (store.layout.J + 1)
    assert (n_chunks == 0) if flat else (n_arrays // 2 < n_chunks <= n_arrays)


@pytest.mark.parametrize("color", [False, True])
def test_store_arrays_are_the_ones_zarr_creates(tmp_path, monkeypatch, color):
    """create_store's arrays (the first of each family through zarr, the rest from its zarr.json)
    and create_shade_arrays over a store's old shading (``massview upgrade``): the files zarr's
    own create_array calls leave, old chunks removed."""
    from massview.data.terrain import store as st
    from massview.data.terrain.layout import TerrainLayout

    lay = TerrainLayout(700, 600, 129, 17)
    trees = []
    for way in ("zarr", "direct"):
        if way == "zarr":
            monkeypatch.setattr(st._ArraysLike, "create", lambda self, name, family, **kw: self.g.create_array(name, **kw))
        else:
            monkeypatch.undo()
        g, resumed = st.create_store(tmp_path / way, lay, {"source": "x", "spacing": [1.0, 1.0]}, color)
        assert not resumed
        old = tmp_path / way / "shade" / "1" / "c" / "0" / "0" / "0" / "0"
        old.parent.mkdir(parents=True)
        old.write_bytes(b"old chunk")
        (tmp_path / way / "shade" / "1" / "c.0.1.0.0.0").write_bytes(b"old chunk")
        st.create_shade_arrays(g, lay)
        trees.append(tree(tmp_path / way))
    assert trees[0] == trees[1]
    assert sum(k.endswith("zarr.json") for k in trees[1]) == 1 + 4 + color + lay.levels * (4 + color)  # groups: root, heights, shade, halo, blocks (color); per level: heights, shade (halo at level 0), blocks/<l>, its done (color)
    assert not any("/c/" in k or "/c." in k for k in trees[1])


@pytest.mark.parametrize("order", ["data, then flat", "flat, then data"])
def test_metadata_rewritten_over_old_arrays_is_what_zarr_leaves(tmp_path, order):
    """write_metadata over arrays already there (``massview upgrade``, a resumed prepare): the
    files zarr's create_array(overwrite=True) + arr[...] = a leave, old chunks gone where the
    new array is all fill value; and a parent group written by write_metadata itself."""
    import dataclasses

    h = np.random.default_rng(5).standard_normal((300, 200)).astype(np.float32).cumsum(axis=0)
    prepare_terrain(ArraySource(h, "dem"), tmp_path / "s.zarr", block=129, color=None)
    store = TerrainStore(tmp_path / "s.zarr")
    data = compute_metadata(store, lambda *a: None)
    flat = dataclasses.replace(data, **{f: [np.zeros_like(a) for a in getattr(data, f)]
                                        for f in ("minmax", "block_error", "sq", "dg", "zmin", "zmax")})
    metas = (data, flat) if order.startswith("data") else (flat, data)
    trees = []
    for way in ("zarr", "direct"):
        g = zarr.open_group(str(tmp_path / way), mode="w", zarr_format=3)
        for lv in range(store.layout.levels):
            g.create_array(f"blocks/{lv}/done", shape=(1, 1), dtype="uint8")
        for meta in metas:
            (write_metadata_through_zarr if way == "zarr" else write_metadata)(g, store.layout, meta)
        trees.append(tree(tmp_path / way))
    assert trees[0] == trees[1]
    assert ("lod/zarr.json" in trees[1]) and any(k.startswith("lod/zmin/0/c/") for k in trees[1]) == (metas[1] is data)


def test_table_beside_the_shading_pass_or_alone_gives_the_same_store(tmp_path, monkeypatch):
    from massview.data.terrain import ingest

    h = np.random.default_rng(4).standard_normal((700, 650)).astype(np.float32).cumsum(axis=0)
    trees = []
    for limit in (ingest._TABLE_BESIDE_SHADING, 0):  # beside (the tests' small tables), then alone
        monkeypatch.setattr(ingest, "_TABLE_BESIDE_SHADING", limit)
        res = prepare_terrain(ArraySource(h, "dem"), tmp_path / f"s{limit}.zarr", block=129, color=None, workers=2)
        assert ("Röttger table" in res.stages) == (limit == 0)
        trees.append(tree(tmp_path / f"s{limit}.zarr"))
    assert trees[0] == trees[1]
    assert sum(k.startswith("roettger/d2/") and "/c/" in k for k in trees[0]) > 0


def test_table_writer_raises_its_error_on_join(tmp_path):
    from massview.data.terrain.roettger import TableWriter

    g = zarr.open_group(str(tmp_path / "s"), mode="w", zarr_format=3)

    def failing():
        yield 0, np.zeros((1, 1), np.float32)
        raise RuntimeError("propagation failed")

    w = TableWriter(g, failing(), 4.0, workers=2)
    with pytest.raises(RuntimeError, match="propagation failed"):
        w.join()
    assert zarr.open_group(str(tmp_path / "s"), mode="r").attrs["roettger"] is None  # "no table"
