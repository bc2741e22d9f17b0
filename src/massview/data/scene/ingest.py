"""``prepare scene``: mesh files -> scene store, out of core and resumable.

Each input becomes objects (:mod:`.sources`): structured inputs keep their objects, soups
are cut into cells and split into objects (:mod:`.soup`, Reliefboards §4). A large binary PLY
is streamed: its faces are read a chunk at a time, their corners gathered block by block and
appended to one spill file per cell under ``SCENE/_spill/`` (removed at the end); then the
cells are processed one at a time. A small soup goes through the very same cells in RAM, so
the streamed and the in-memory ingest write the same store.

Positions stay float64 from the file through cleaning (redundant vertices merged and
degenerate faces found at float64 precision) and object cutting. Each object is then stored
in its own frame: float32 coordinates relative to an origin at its box centre, which its
transform (float64) puts back, so georeferenced inputs (UTM-like coordinates in the millions)
keep float32 precision relative to the object instead of ~0.25 m steps at 4e6.

Every object is a *unit* for the :class:`SceneWriter`: its level-0 mesh (redundant vertices
and faces removed, also those that become so only in float32 local coordinates; normals from
the file, made unit, or — when the file has none, or some of the object's corners lack one or
have a zero or NaN one, then for the whole object, with a warning — area-weighted and split
where faces meet at more than ``crease_angle`` degrees),
its LOD levels (:mod:`.simplify`; a soup's objects, which may be pieces of one surface, keep
their open border at every level so pieces meet without cracks), then its placement (the translation to its origin). With
``instance``, structured objects that share a geometry (glTF nodes of one mesh) store it once,
in its own frame, with their transforms composed with that translation. Inputs whose up axis
(``up``, :func:`.sources.up_axis`) is y are turned to massview's z-up as they are read. Re-running an
interrupted prepare with the same arguments skips the units already written; ``complete`` is
set last.
"""

from __future__ import annotations

import json
import shutil
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from ...core.errors import ConfigError, IngestError
from ..rebuild import is_complete_store, one_writer, rebuild_beside
from .mesh import Mesh
from .normals import CREASE_ANGLE
from .plystream import PlyLayout
from .simplify import build_levels
from .soup import Corners, SplitParams, cell_grid, cell_objects, cell_of, clean_mesh, clean_soup, split_dense
from .sources import UP_CHOICES, MemorySoup, StructuredObject, check_input, open_input, stream_bounds, stream_corners, transform_normals, up_axis
from .store import FORMAT
from .writer import CHECKPOINT_BYTES, SceneWriter

__all__ = ["IngestParams", "prepare_scene"]


@dataclass(frozen=True)
class IngestParams:
    object_triangles: int = 16384  # soup objects grow to at most this many triangles
    object_size: float = float("inf")  # ... and at most this longest box side (world units)
    cell_triangles: int = 1 << 18  # soup cell size (bounds the memory of one cell)
    instance: bool = False  # store shared geometry once with transforms
    simplifier: str = "fast-simplification"
    max_levels: int = 8
    stream_bytes: int = 256 << 20  # binary PLY at least this large is streamed
    face_chunk: int = 1 << 18  # faces per streamed read
    vertex_block: int = 1 << 20  # vertices per streamed vertex read (15-40 MB)
    crease_angle: float = CREASE_ANGLE  # meshes without normals: split normals at sharper edges (degrees)
    up: str = "auto"  # the inputs' up axis: auto (y for glTF/GLB, z for the rest), y or z; y-up is turned to z-up

    def __post_init__(self) -> None:
        if self.up not in UP_CHOICES:
            raise ConfigError(f"--up must be one of {', '.join(UP_CHOICES)} (auto: y for glTF/GLB, z for the rest), got {self.up!r}")
        if not self.object_size > 0:  # (inf: no limit; NaN fails too)
            raise ConfigError(f"--object-size must be a positive length in file units (leave it out for no limit), got {self.object_size:g}")
        if self.object_triangles < 1:
            raise ConfigError(f"--object-triangles must be at least 1, got {self.object_triangles}")
        if not 0 < self.crease_angle <= 180:
            raise ConfigError(f"--crease-angle must be more than 0 and at most 180 degrees (180: smooth everything), got {self.crease_angle:g}")

    def split(self) -> SplitParams:
        return SplitParams(self.object_triangles, self.object_size, self.cell_triangles)


def local_frame(p: np.ndarray) -> np.ndarray:
    """The origin (3,) f8 of an object's frame: its box centre, rounded to float32 (so even a
    float32 copy of the translation is exact)."""
    p = np.asarray(p, np.float64)
    return ((p.min(axis=0) + p.max(axis=0)) / 2).astype(np.float32).astype(np.float64)


def _translation(o: np.ndarray) -> np.ndarray:
    t = np.eye(4)
    t[:3, 3] = o
    return t


def usable_normals(nrm: np.ndarray | None) -> np.ndarray | None:
    """Unit normals f32 (v,3) of file normals ``nrm``, or None (compute them) when there are
    none or any is missing (NaN: an OBJ corner without ``vn``), infinite or of zero length."""
    if nrm is None:
        return None
    n = np.asarray(nrm, np.float64)
    ln = np.linalg.norm(n, axis=1, keepdims=True)
    if not (np.isfinite(ln).all() and (ln > 0).all()):
        return None
    return (n / ln).astype(np.float32)


def _mesh(p: np.ndarray, col: np.ndarray, nrm: np.ndarray | None, f: np.ndarray) -> tuple[Mesh, np.ndarray]:
    """(the object's mesh in its own frame, float32 positions relative to the origin; the
    origin (3,) f8). Vertices that become equal in float32 are merged again and faces that
    become degenerate dropped, so the stored mesh has no zero-length edges. File normals
    ``nrm`` must be unit (:func:`usable_normals`) or None: then the mesh's normals are a
    placeholder, split by :func:`build_levels`."""
    o = local_frame(p)
    q = (np.asarray(p, np.float64) - o).astype(np.float32)
    q, col, nrm, f = clean_mesh(q, col, nrm, f)
    n = np.zeros((len(q), 3), np.float32) if nrm is None else nrm.astype(np.float32)
    return Mesh(q, n, col.astype(np.uint8), f.astype(np.uint32)), o


@dataclass
class _Tally:
    """One input's triangles: read from the file, stored at level 0 (each placement counted),
    whether every coordinate read was a float32 value, their largest magnitude and their box."""

    read: int = 0
    kept: int = 0
    float32: bool = True
    largest: float = 0.0
    lo: tuple = (np.inf,) * 3
    hi: tuple = (-np.inf,) * 3

    def add(self, positions: np.ndarray) -> None:
        p = np.asarray(positions, np.float64).reshape(-1, 3)
        self.read += len(p) // 3
        if len(p):
            self.float32 = self.float32 and bool(np.array_equal(p.astype(np.float32), p))
            self.largest = max(self.largest, float(np.abs(p).max()))
            self.lo, self.hi = tuple(np.minimum(self.lo, p.min(axis=0))), tuple(np.maximum(self.hi, p.max(axis=0)))

    def warning(self, name: str) -> str | None:
        """One line when triangles were removed; with the likely cause when more than 1 % were
        and the coordinates are float32 values too coarse for the mesh (fewer than 4096 float32
        steps across it at its largest coordinate)."""
        gone = self.read - self.kept
        if gone <= 0:
            return None
        msg = (f"{name}: {gone:,} of {self.read:,} triangles ({gone / self.read:.1%}) were removed as degenerate (corners at "
               "one point at the file's precision, or within an object's float32 frame) or repeated (the same three vertices twice)")
        step = float(np.spacing(np.float32(self.largest)))
        span = float(np.max(np.subtract(self.hi, self.lo)))
        if gone > 0.01 * self.read and self.float32 and step * 4096 > span:
            msg += (f"; likely cause: the coordinates are float32 values up to {self.largest:.6g}, where float32 steps by "
                    f"{step:g} — coarse for a mesh {span:.4g} across; write the file with float64 (double) coordinates or move "
                    "its origin near the mesh")
        return msg


_UNITS_RATIO = 500.0  # an input this many times larger than another: mixed units? (mm against m is 1000)


_FLAT_RATIO = 1 / 3  # an input thinner along y than this × its x and z extents looks like a y-up model lying flat


def _up_warnings(tally: dict, up: str) -> list[str]:
    """A line per input read as z-up only by ``--up auto`` (PLY, OBJ, STL, OFF: no convention)
    whose box is thinnest along y by far, as a y-up model's would be (walk6 #14: a y-up house
    on a 10 × 0.2 × 10 slab rendered as a wall, with no word at prepare time). Only a hint:
    nothing is turned."""
    if up != "auto":
        return []
    out = []
    for name, t in tally.items():
        if not t.read or up_axis(Path(name), up) != "z" or not np.all(np.isfinite(t.lo)):
            continue
        ex, ey, ez = (float(v) for v in np.asarray(t.hi) - np.asarray(t.lo))
        if ez > 0 and ey < _FLAT_RATIO * min(ex, ez):
            out.append(f"{name}: it is thinnest along y ({ey:.3g} against {ex:.3g} along x and {ez:.3g} along z), as a y-up "
                       "model lying flat would be; massview's world is z-up and this format has no up convention — if it "
                       "renders standing on edge, prepare it again with --up y")
    return out


def _units_warning(tally: dict) -> list[str]:
    """One line when the inputs look like different units (walk6 #12: metre models beside a
    2000 mm part 125 km away rendered as specks in an empty frame): one input ``_UNITS_RATIO``
    times larger than another. (Inputs spread far apart for their size are not warned: the
    tiles of a city are.)"""
    boxes = {k: (np.asarray(t.lo), np.asarray(t.hi)) for k, t in tally.items() if t.read and np.all(np.isfinite(t.lo))}
    if len(boxes) < 2:
        return []
    size = {k: float(np.max(hi - lo)) for k, (lo, hi) in boxes.items()}
    big, small = max(size, key=size.get), min(size, key=size.get)
    if size[big] <= _UNITS_RATIO * max(size[small], 1e-300):
        return []
    lo = np.min([b[0] for b in boxes.values()], axis=0)
    hi = np.max([b[1] for b in boxes.values()], axis=0)
    return [f"the inputs differ in scale: {big} is {size[big]:.4g} units across, {small} {size[small]:.4g} "
            f"({size[big] / max(size[small], 1e-300):.0f}×), together spanning {float(np.max(hi - lo)):.4g}; are they in different "
            "units (millimetres and metres)? They are stored as they are, in one space: scale the files to one unit, or "
            "prepare them into separate stores"]


class _Run:
    """Writes units in order, skipping those a previous run wrote."""

    def __init__(self, w: SceneWriter, prm: IngestParams, progress, fault_after: int | None):
        self.w, self.prm, self.prog, self.fault_after = w, prm, progress, fault_after
        self.unit = 0
        self.triangles = 0
        self.computed: dict[str, list[int]] = {}  # input name -> [objects whose partial normals were replaced, objects]
        self.tally: dict[str, _Tally] = {}  # input name -> its triangles read and stored

    def read(self, source: str, positions: np.ndarray) -> None:
        """Count corner positions (t,3,3) f8 read from ``source``, as the file gives them."""
        self.tally.setdefault(source, _Tally()).add(positions)

    def normals(self, source: str, nrm: np.ndarray | None) -> np.ndarray | None:
        """An object's file normals made unit, or None (computed) when the file has none or some
        are missing or zero: then the whole object gets computed normals (counted for a warning)."""
        n = usable_normals(nrm)
        if nrm is not None:
            c = self.computed.setdefault(source, [0, 0])
            c[0] += n is None
            c[1] += 1
        return n

    def warnings(self) -> list[str]:
        out = [f"{name}: {bad} of {total} objects have faces without a usable normal (no vn, zero or NaN); those objects "
               f"got computed normals (split at {self.prm.crease_angle:g}°) instead of the file's"
               for name, (bad, total) in self.computed.items() if bad]
        return (out + [m for m in (t.warning(name) for name, t in self.tally.items()) if m] + _units_warning(self.tally)
                + _up_warnings(self.tally, self.prm.up))

    def pending(self) -> bool:
        return self.unit >= self.w.geometries_done

    def write(self, source: str, mesh: Mesh, placements: list[np.ndarray | None], crease: bool = False,
              cut: bool = False) -> None:
        """Write one unit of input ``source``: ``mesh`` (local frame) placed by each of
        ``placements`` (4x4 f8); ``crease``: the file brought no normals, split them at the
        crease angle; ``cut``: the mesh may be a piece of a larger surface (a cell or a k-d
        piece), so its open border stays locked at every level (``build_levels``' free_border)."""
        self.tally.setdefault(source, _Tally()).kept += mesh.triangle_count * len(placements)
        if mesh.triangle_count == 0:  # every face collapsed (degenerate at float32 in its own frame)
            return
        if self.pending():
            levels, errors = build_levels(mesh, self.prm.max_levels, backend=self.prm.simplifier,
                                          crease=self.prm.crease_angle if crease else None, free_border=not cut)
            gid = self.w.add_geometry(levels, errors)
            for xf in placements:
                self.w.add_object(gid, (), xf)
            self.w.step()
        self.unit += 1
        self.triangles += mesh.triangle_count
        self.prog("objects", 1, None)
        if self.fault_after is not None and self.unit >= self.fault_after:
            raise KeyboardInterrupt(f"fault injected after {self.unit} units")


def _structured(run: _Run, objs: list[StructuredObject], source: str) -> None:
    if run.prm.instance:
        keys: dict[str, list[StructuredObject]] = {}
        for o in objs:
            keys.setdefault(o.geometry_key, []).append(o)
        for group in keys.values():  # the geometry in its own frame (normals too), each instance's transform composed with it
            for o in group:
                run.read(source, o.corners.positions)
            p, col, nrm, f = clean_soup(group[0].corners)
            nrm = run.normals(source, nrm)
            mesh, origin = _mesh(p, col, nrm, f)
            run.write(source, mesh, [np.asarray(o.transform, np.float64) @ _translation(origin) for o in group], nrm is None)
        return
    for o in objs:
        c = o.corners
        run.read(source, c.positions)
        p = np.einsum("ij,tkj->tki", o.transform[:3, :3], c.positions.astype(np.float64)) + o.transform[:3, 3]
        p, col, nrm, f = clean_soup(Corners(p, c.colors, transform_normals(c.normals, o.transform)))
        nrm = run.normals(source, nrm)
        mesh, origin = _mesh(p, col, nrm, f)
        run.write(source, mesh, [_translation(origin)], nrm is None)


def _cells_of_memory(soup: MemorySoup, prm: IngestParams):
    lo, hi = soup.positions.min(axis=0), soup.positions.max(axis=0)
    dims = cell_grid(lo, hi, len(soup.faces), prm.cell_triangles)
    cent = soup.positions[soup.faces].mean(axis=1)
    cell = cell_of(cent, lo, hi, dims)
    order = np.argsort(cell, kind="stable")
    cuts = np.nonzero(np.diff(cell[order]))[0] + 1
    for sel in np.split(order, cuts):
        yield soup.corners(sel)


def _spill(lay: PlyLayout, spill: Path, prm: IngestParams, progress) -> tuple[int, bool]:
    """Stream the PLY's triangles into per-cell spill files; returns the cell count and
    whether an interrupted run's complete spill was used instead."""
    done = spill / "done.json"
    if done.exists():
        d = json.loads(done.read_text())
        # (spill files of an older massview held float32 positions, or of the other up axis: spill again)
        if d.get("positions") == "f8" and d.get("turn", False) == lay.turn:
            return int(d["cells"]), True
    shutil.rmtree(spill, ignore_errors=True)
    spill.mkdir(parents=True)
    lo, hi = stream_bounds(lay, prm.vertex_block)
    dims = cell_grid(lo, hi, lay.n_faces, prm.cell_triangles)
    for _, c in stream_corners(lay, prm.face_chunk, prm.vertex_block):
        cell = cell_of(c.positions.mean(axis=1), lo, hi, dims)
        order = np.argsort(cell, kind="stable")
        cuts = np.nonzero(np.diff(cell[order]))[0] + 1
        for sel in np.split(order, cuts):
            with open(spill / f"{int(cell[sel[0]])}.bin", "ab") as fh:
                fh.write(_pack(c, sel).tobytes())
        progress("read", c.count, lay.n_faces)
    n = int(np.prod(dims))
    done.write_text(json.dumps({"cells": n, "positions": "f8", "turn": lay.turn}))
    return n, False


def _record_dtype(normals: bool) -> np.dtype:
    fields = [("p", "<f8", (3, 3)), ("c", "u1", (3, 4))]
    return np.dtype(fields + ([("n", "<f4", (3, 3))] if normals else []))


def _pack(c: Corners, sel: np.ndarray) -> np.ndarray:
    rec = np.empty(len(sel), _record_dtype(c.normals is not None))
    rec["p"], rec["c"] = c.positions[sel], c.colors[sel]
    if c.normals is not None:
        rec["n"] = c.normals[sel]
    return rec


def _cells_of_stream(lay: PlyLayout, spill: Path, prm: IngestParams, progress, reused: list):
    cells, again = _spill(lay, spill, prm, progress)
    reused.append(again)
    dt = _record_dtype(lay.has_normals)
    for k in range(cells):
        f = spill / f"{k}.bin"
        if f.exists():
            rec = np.fromfile(f, dt)
            yield Corners(rec["p"], rec["c"], rec["n"] if lay.has_normals else None)


def _params_of(paths: list[Path], prm: IngestParams) -> dict:
    d = {k: (None if v == float("inf") else v) for k, v in asdict(prm).items() if k not in ("face_chunk", "vertex_block")}
    d["inputs"] = [{"name": str(p.resolve()), "bytes": p.stat().st_size, "mtime": int(p.stat().st_mtime)} for p in paths]
    return d


def _distinct(paths: list[Path]) -> None:
    """Refuse an input given twice (by another name, a link, too): each input becomes its own
    objects, so the two copies would lie exactly on top of each other (z-fighting, twice the
    triangles) — there is no option that would place them apart."""
    seen: dict = {}
    for i, p in enumerate(paths):
        st = check_input(p).stat()
        j = seen.setdefault((st.st_dev, st.st_ino), i)
        if j != i:
            raise ConfigError(f"{p} is given twice (inputs {j + 1} and {i + 1}{'' if p == paths[j] else f': {paths[j]}'}); "
                              "each input becomes its own objects, so the copies would lie exactly on top of each other — give it once")


@one_writer
def prepare_scene(inputs, out, prm: IngestParams = IngestParams(), overwrite: bool = False, progress=None,
                  checkpoint_bytes: int = CHECKPOINT_BYTES, fault_after: int | None = None) -> dict:
    """Build the scene store ``out`` from mesh files ``inputs``. Returns the store attributes
    plus ``seconds``, ``input_bytes``, ``resumed`` (an interrupted run's store was continued),
    ``objects_kept`` (of its objects, those this run did not write again: 0 when it had saved
    no checkpoint), ``spill_reused`` (its streamed inputs' spill files were complete and used),
    ``checkpoint_bytes`` and ``warnings`` (messages for the user). The store's attributes
    record ``textures_baked`` (input name -> textured materials or meshes baked to vertex
    colours) and ``triangles_removed`` (input name -> degenerate or repeated triangles dropped).
    ``fault_after`` (tests) interrupts the run after that many units as a KeyboardInterrupt would."""
    if overwrite and is_complete_store(out, FORMAT):  # built beside it and swapped in: a stopped rebuild loses nothing
        return rebuild_beside(out, FORMAT, lambda p: prepare_scene(inputs, p, prm, False, progress, checkpoint_bytes, fault_after))
    t0 = time.perf_counter()
    prog = progress or (lambda *a: None)
    paths = [Path(p) for p in inputs]
    if not paths:
        raise IngestError("no input files given")
    _distinct(paths)
    warn: list[str] = []
    textures: dict[str, int] = {}
    sources = [open_input(p, prm.stream_bytes, warn, prm.up, textures) for p in paths]  # validates before anything is written
    out = Path(out)
    w = SceneWriter(out, _params_of(paths, prm), {"source": ", ".join(p.name for p in paths), "units": "1"},
                    levels_max=prm.max_levels, overwrite=overwrite, checkpoint_bytes=checkpoint_bytes)
    resumed, kept = w.resumed, w.objects_done
    run = _Run(w, prm, prog, fault_after)
    reused: list[bool] = []
    for i, (path, src) in enumerate(zip(paths, sources)):
        if isinstance(src, list):
            _structured(run, src, str(path))
            continue
        cells = (_cells_of_memory(src, prm) if isinstance(src, MemorySoup)
                 else _cells_of_stream(src, out / "_spill" / str(i), prm, prog, reused))
        for cell in cells:
            run.read(str(path), cell.positions)
            for corners in split_dense(cell, prm.cell_triangles):
                for p, col, nrm, f in cell_objects(corners, prm.split()):
                    nrm = run.normals(str(path), nrm)
                    mesh, origin = _mesh(p, col, nrm, f)
                    run.write(str(path), mesh, [_translation(origin)], nrm is None, cut=True)
    attrs = w.finish({"ingest_seconds": round(time.perf_counter() - t0, 3), "textures_baked": textures,
                      "triangles_removed": {k: t.read - t.kept for k, t in run.tally.items()}})
    shutil.rmtree(out / "_spill", ignore_errors=True)
    return {**attrs, "seconds": time.perf_counter() - t0, "input_bytes": sum(p.stat().st_size for p in paths), "resumed": resumed,
            "objects_kept": kept, "spill_reused": any(reused), "checkpoint_bytes": checkpoint_bytes, "warnings": warn + run.warnings()}
