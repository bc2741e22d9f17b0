"""Golden checksums of ``prepare terrain`` output, recorded before the parallel ingest (issue 20).

``store_digest`` walks every array of a terrain store and hashes its *decoded* values (dtype,
shape and bytes), plus the attributes that do not depend on the run; two stores with equal
digests hold identical arrays, whatever their compressed bytes. ``CASES`` are small DEMs that
between them take every branch of the ingest: a real DEM (Jacksboro fault, 344 × 403) with the
pyramid below the patch lattice, a synthetic non-2^n+1 one with ``L > k`` (coarse lattice
above the block size: the "whole window" branch of the exact errors) and one with nodata holes
and an orthophoto (part of the Jacksboro DEM). The holes case was recorded again on 2026-11-29
when void filling changed (data/terrain/voidfill.py: a coarse harmonic surface plus the nearby
detail, instead of iterated neighbour averages inside each strip) — a deliberate change of the
filled samples and all that derives from them; its input became host-independent then, so it
has one recording and no variants.

The recordings were made with format-version-2 stores (``"_format_version": 2``); version 3
(issue 20, 2026-11-29) computes level 0's shading on reading from ``halo/0`` instead of storing
it, and its digest (:func:`store_digest`) is the shading it gives, so the same recordings check
that it gives exactly the stored version-2 shading, and the attributes apart from the version.

Run as a script (``python tests/ingest_golden.py``) to (re)record ``tests/data/ingest_golden.json``
— only ever with the reference ingest; the test compares against the recorded file.

The synthetic DEMs are not the same on every CPU: numpy's float64 ``power`` (the generator's
``** 1.35``) runs AVX-512 SIMD code where the CPU has AVX-512 and glibc's ``pow`` elsewhere, and
the two differ in the last bit for some samples, so the float32 heights differ at a few samples.
The file therefore holds, under ``"_variants"``, a digest set per further input (each told apart
by its ``heights/0``, the input itself): the main sets were recorded on AVX-512 hosts, the variant
on an AVX2-only host (2026-11-27) — there the reference ingest (90f16ec, run on that host) and
today's gave identical digests. :func:`input_digest` gives the key the render and LOD-stage
golden tests use the same way.
"""

from __future__ import annotations

import hashlib
import json
import sys
from pathlib import Path

import numpy as np

from massview.data.terrain import ArraySource, prepare_terrain
from massview.data.terrain.synthetic import SyntheticSource

GOLDEN = Path(__file__).parent / "data" / "ingest_golden.json"
_RUN_ATTRS = {"complete", "source", "source_stamp"}  # (source_stamp: the input file's size and mtime)


def _jacksboro():
    sys.path.insert(0, str(Path(__file__).parent))
    from terrain_oracle import real_dem

    arr, (dx, dy) = real_dem()
    return ArraySource(arr, "jacksboro", transform=(0.0, dx, 0.0, 0.0, 0.0, -dy))


def _holes():
    a = _jacksboro().arr[:301, :277].copy()  # (a file's heights: the same on every CPU, as the fill is)
    a[40:90, 100:180] = -9999.0
    a[200, :] = -9999.0
    return ArraySource(a, "holes", nodata=-9999.0, transform=(0.0, 25.0, 0.0, 0.0, 0.0, -25.0))


class _Ortho(ArraySource):
    def read_rgb(self, r0, r1, c0, c1):
        return self.arr[r0:r1, c0:c1]


def _ortho():
    y, x = np.mgrid[0:150, 0:140]
    rgb = np.stack([(x * 7) % 256, (y * 5) % 256, (x * y) % 256], axis=-1).astype(np.uint8)
    o = _Ortho(rgb[..., 0], "ortho")
    o.arr = rgb
    return o


CASES = {  # name: (source factory, prepare keyword arguments)
    "jacksboro_b129": (_jacksboro, dict(block=129)),
    "synthetic_700x700_b129_K5": (lambda: SyntheticSource(700, seed=3), dict(block=129, K=5)),
    "holes_301x277_b129_ortho": (_holes, dict(block=129, K=9, ortho="ortho")),
}


def prepare_case(name: str, path: Path, **extra):
    make, kw = CASES[name]
    kw = dict(kw)
    if kw.pop("ortho", None):
        kw["ortho"] = _ortho()
    return prepare_terrain(make(), path, **kw, **extra)


def store_digest(path: Path, as_version: int | None = None) -> dict[str, str]:
    """{array path: sha256 of dtype, shape and decoded bytes} and {"attrs": sha256 of the
    run-independent attributes} of a store.

    A version-3 store keeps ``halo/0`` instead of ``shade/0``: its ``"shade/0"`` is the digest
    of the level-0 shading it gives (``get_shade`` of every block, assembled as the version-2
    array was), which every halo sample enters, so ``halo/0`` is not listed. ``as_version``:
    hash the attributes with that ``format_version`` (the recordings' own, :func:`recorded_version`),
    so the digest says whether everything else is as recorded."""
    import zarr

    g = zarr.open_group(str(path), mode="r")
    out = {}
    for name, arr in sorted(_walk(g), key=lambda t: t[0]):
        if name != "halo/0":
            out[name] = _array_digest(arr)
    if "halo/0" in g:
        out["shade/0"] = _computed_shade0_digest(path)
    attrs = {k: v for k, v in dict(g.attrs).items() if k not in _RUN_ATTRS}
    if as_version is not None:
        attrs["format_version"] = as_version
    out["attrs"] = hashlib.sha256(json.dumps(attrs, sort_keys=True).encode()).hexdigest()
    return out


def _computed_shade0_digest(path: Path) -> str:
    from massview.data.terrain import TerrainStore

    st = TerrainStore(path)
    nb, M = st.layout.blocks(0), st.layout.M
    a = np.empty((nb, nb, M, M, 3), np.float16)
    for i in range(nb):
        for j in range(nb):
            st.get_shade(0, i, j, out=a[i, j])
    return _array_digest(a)


def recorded_version() -> int:
    """The store format version the recordings were made with (``"_format_version"``)."""
    return int(json.loads(GOLDEN.read_text()).get("_format_version", 2))


def input_digest(path: Path) -> str:
    """The digest :func:`store_digest` gives a store's ``heights/0`` (its input, padded): what the
    golden tests key host-dependent recordings by."""
    import zarr

    return _array_digest(zarr.open_group(str(path), mode="r")["heights/0"])


def _array_digest(arr) -> str:
    """sha256 of a stored array's dtype, shape and decoded bytes."""
    a = np.ascontiguousarray(np.asarray(arr[...]))
    h = hashlib.sha256(f"{a.dtype.str}{a.shape}".encode())
    h.update(a.tobytes())
    return h.hexdigest()


def recorded_for(name: str, got: dict) -> dict:
    """The recorded digest set of case ``name`` for this input: the one whose ``heights/0`` is
    ``got``'s among the main set and its ``_variants``; the main set when none is."""
    rec = json.loads(GOLDEN.read_text())
    sets = [rec[name], *rec.get("_variants", {}).get(name, [])]
    return next((s for s in sets if s.get("heights/0") == got.get("heights/0")), rec[name])


def _walk(g, prefix=""):
    for name, arr in g.arrays():
        yield prefix + name, arr
    for name, sub in g.groups():
        yield from _walk(sub, prefix + name + "/")


if __name__ == "__main__":
    import tempfile

    old = json.loads(GOLDEN.read_text()) if GOLDEN.exists() else {}
    rec = {k: old[k] for k in ("_variants", "_format_version") if k in old}
    with tempfile.TemporaryDirectory() as d:
        for name in CASES:
            p = Path(d) / f"{name}.zarr"
            prepare_case(name, p)
            rec[name] = store_digest(p, rec.get("_format_version"))
            print(name, len(rec[name]), "arrays")
    GOLDEN.write_text(json.dumps(rec, indent=1, sort_keys=True) + "\n")
    print("wrote", GOLDEN)
