"""Scene ingest: PLY MB/s, triangles/s, peak RSS; fast-simplification against pyfqmr.

``massview bench scene-ingest``:

1. **simplifiers** — each candidate simplifies the same meshes (pyvista's real ant, a
   generated tree crown, a plant vessel, a 327 k-triangle lumpy sphere) to half their
   triangles: seconds and the measured geometric error (:func:`surface_distance` both ways,
   relative to the mesh size). The store uses the one with the better figures.
2. **ingest** — a binary PLY of at least ``--triangles`` triangles (the level-0 geometry of
   generated plant copies, an unstructured soup, written once into ``--workdir``) is copied
   (the disk floor for touching the bytes once) and then prepared by ``massview prepare
   scene --stream-mb 0`` (the streamed path, whatever the file size) in a child process, which reports its own peak RSS (``VmHWM``) at exit. Printed:
   MB/s and triangles/s, the ratio to the copy, peak RSS against the 1 GiB target.

Nothing is asserted; figures are noisy on a shared machine.
"""

from __future__ import annotations

import math
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from .child import run_measured

__all__ = ["add_arguments", "run"]


def add_arguments(p) -> None:
    p.add_argument("--triangles", type=float, default=50e6, help="least triangles in the PLY (default 50e6)")
    p.add_argument("--size", type=float, default=1.0, help="size of each plant copy (default 1: ~8.4 M triangles)")
    p.add_argument("--workdir", default="out/bench", help="where the PLY is written once and the store built")
    p.add_argument("--simplifier", choices=("fast-simplification", "pyfqmr"), default="fast-simplification")
    p.add_argument("--skip-simplifiers", action="store_true", help="only the ingest")
    p.add_argument("--skip-ingest", action="store_true", help="only the simplifier comparison")
    p.add_argument("--keep", action="store_true", help="keep the store afterwards")


def _test_meshes():
    from ...data.generators import shapes
    from ...data.generators.scenes import real_mesh, shape_levels

    v, f = real_mesh("ant")
    out = [("ant (pyvista, real)", v.astype(np.float32), f)]
    for name, key in (("tree crown", ("broadleaf", 0)), ("plant vessel", ("tank", 4.0, 1.1))):
        m = shape_levels(key)[0][0]
        out.append((name, m.positions, m.indices.astype(np.int64)))
    p, t, _ = shapes.blob(1.0, 1.0, 1.0, 256, 640, seed=3)
    out.append(("bumpy sphere", p.astype(np.float32), t))
    return out


def _compare_simplifiers(console) -> None:
    from rich.table import Table

    from ...data.scene.simplify import BACKENDS, simplify_once, surface_distance

    t = Table(title="quadric simplification to 50 % of the triangles (error relative to the mesh diagonal)")
    for c in ("mesh", "triangles", *[f"{b} {k}" for b in BACKENDS for k in ("s", "error")]):
        t.add_column(c, justify="right")
    for name, p, f in _test_meshes():
        row = [name, f"{len(f):,}"]
        diag = float(np.linalg.norm(p.max(0) - p.min(0)))
        for b in BACKENDS:
            simplify_once(p, f[: min(len(f), 64)], 16, b)  # warm up (imports)
            t0 = time.perf_counter()
            q, g = simplify_once(p, f, len(f) // 2, b)
            dt = time.perf_counter() - t0
            err = max(surface_distance(p[:: max(1, len(p) // 4096)], q, g), surface_distance(q[:: max(1, len(q) // 4096)], p, f))
            row += [f"{dt:.3f}", f"{err / diag:.2e}"]
        t.add_row(*row)
    console.print(t)


def _copy_baseline(src: Path, dst: Path) -> float:
    t0 = time.perf_counter()
    with open(src, "rb") as f, open(dst, "wb") as g:
        while buf := f.read(64 << 20):
            g.write(buf)
        g.flush()
        os.fsync(g.fileno())
    dt = time.perf_counter() - t0
    dst.unlink()
    return dt


# Measured here (README, "scene ingest"): 50.6 M triangles -> a 1.14 GB PLY and an 879 MiB store;
# one 8.25 M-triangle plant copy -> 190 MB, prepared at 45.9 k triangles/s on an idle 2-core host.
PLY_BYTES_PER_TRIANGLE = 22.6
STORE_BYTES_PER_TRIANGLE = 18.2
PREPARE_TRIANGLES_PER_S = 45e3
PLANT_TRIANGLES = 8.4e6  # per copy at --size 1 (approximately; the count printed after writing is exact)


def _ply_path(work: Path, triangles: float, size: float) -> tuple[Path, int]:
    copies = max(1, math.ceil(triangles / (PLANT_TRIANGLES * size)))
    return work / f"plant_s{size:g}_x{copies}.ply", copies


def plan(work: Path, triangles: float, size: float, keep: bool) -> tuple[str, int]:
    """What the ingest part will write and roughly how much disk and time it takes, as one
    paragraph, and the bytes it needs free in ``work`` at its peak (the PLY, if not there yet,
    plus the larger of its one-off copy and the store)."""
    ply, copies = _ply_path(work, triangles, size)
    tris = copies * PLANT_TRIANGLES * size
    ply_b, store_b = tris * PLY_BYTES_PER_TRIANGLE, tris * STORE_BYTES_PER_TRIANGLE
    have = ply.exists()
    if have:
        ply_b = ply.stat().st_size
        first = f"reuses {ply} ({_size(ply_b)})"
    else:
        first = (f"writes {ply}: a binary PLY of ~{tris / 1e6:.1f} M triangles ({copies} plant cop{'y' if copies == 1 else 'ies'}, "
                 f"~{_size(ply_b)}; kept for later runs)")
    need = (0 if have else ply_b) + max(ply_b, store_b)
    minutes = tris / PREPARE_TRIANGLES_PER_S / 60
    took = f"roughly {minutes:.0f} min" if minutes >= 1 else "under a minute"
    text = (f"bench scene-ingest {first}, copies it once (the disk baseline; removed) and prepares a scene store of "
            f"~{_size(store_b)} beside it ({'kept' if keep else 'removed afterwards; --keep keeps it'}): "
            f"~{_size(need)} of free disk needed; prepare takes {took} on 2 idle cores "
            f"({PREPARE_TRIANGLES_PER_S / 1e3:.0f} k triangles/s measured). Smaller: --triangles 5e6.")
    return text, int(need)


def _size(nbytes: float) -> str:
    return f"{nbytes / 1e9:.2f} GB" if nbytes >= 1e9 else f"{nbytes / 1e6:.0f} MB"


def _ply(work: Path, triangles: float, size: float, console) -> Path:
    from ...data.generators.scenes import scene_nodes

    ply, copies = _ply_path(work, triangles, size)
    if not ply.exists():
        console.print(f"writing {ply} ({copies} plant copies, {len(scene_nodes('plant', size)[0]) * copies:,} nodes; once, kept) ...")
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-c", "import sys; from massview.data.generators.plyfile import write_scene_ply; "
                        f"print(write_scene_ply(sys.argv[1], 'plant', {copies}, {size}))", str(ply)], check=True)
        console.print(f"written in {time.perf_counter() - t0:.0f} s")
    return ply


def _ingest(args, console) -> int:
    from rich.table import Table

    from ...data.scene.plystream import read_ply_layout

    work = Path(args.workdir)
    ply = _ply(work, args.triangles, args.size, console)
    lay = read_ply_layout(ply)
    nbytes = ply.stat().st_size
    copy_s = _copy_baseline(ply, work / "copy.tmp")
    store = work / f"{ply.stem}.scene"
    shutil.rmtree(store, ignore_errors=True)
    cmd = [sys.executable, "-m", "massview", "prepare", "scene", str(ply), "-o", str(store), "--simplifier", args.simplifier, "--stream-mb", "0", "-q"]
    console.print("running: " + " ".join(cmd[2:]))
    run = run_measured(cmd, work / "prepare_scene.peak_rss")
    if run.returncode != 0:
        console.print(f"[red]prepare scene failed (exit {run.returncode})[/]")
        return run.returncode
    dt, cpu, rss = run.wall_s, run.cpu_s, run.peak_rss
    from ...data.scene.verify import scene_info

    info = scene_info(store)
    t = Table(title=f"prepare scene of a binary PLY: {lay.n_faces:,} triangles, {lay.n_vertices:,} vertices, {nbytes / 2**30:.2f} GiB")
    t.add_column("figure")
    t.add_column("value", justify="right")
    t.add_row("prepare time", f"{dt:.0f} s")
    t.add_row("throughput", f"{nbytes / 1e6 / dt:.2f} MB/s, {lay.n_faces / dt:,.0f} triangles/s")
    t.add_row("CPU time of prepare (user + sys)", f"{cpu:.0f} s: {lay.n_faces / cpu:,.0f} triangles per CPU-second "
              f"({cpu / dt:.2f} cores busy on average)")
    t.add_row("copy baseline (same bytes)", f"{copy_s:.1f} s ({nbytes / 1e6 / copy_s:.0f} MB/s); prepare ÷ copy {dt / copy_s:.0f}×")
    t.add_row("objects found / LOD triangles (all levels)", f"{info['objects']:,} / {sum(info['triangles_per_level']):,}")
    t.add_row("store on disk / compression of records", f"{info['disk_bytes'] / 2**20:.0f} MiB / {info['compression_ratio']}")
    t.add_row("peak RSS of prepare", f"{rss / 2**20:.0f} MiB ({'under' if rss < 2**30 else 'OVER'} the 1 GiB target)")
    console.print(t)
    if not args.keep:
        shutil.rmtree(store, ignore_errors=True)
    return 0


def run(args) -> int:
    from rich.console import Console

    console = Console()
    if not args.skip_ingest:  # what the ingest part will write, before any part starts
        from ...core.errors import ConfigError

        work = Path(args.workdir)
        work.mkdir(parents=True, exist_ok=True)
        text, need = plan(work, args.triangles, args.size, args.keep)
        console.print(text, soft_wrap=True)  # (the paths stay whole, to copy)
        free = shutil.disk_usage(work).free
        if need > free:
            raise ConfigError(f"bench scene-ingest needs ~{need / 1e9:.2f} GB free in {work}, {free / 1e9:.2f} GB are: "
                              "give a smaller --triangles or another --workdir")
    if not args.skip_simplifiers:
        _compare_simplifiers(console)
    return 0 if args.skip_ingest else _ingest(args, console)
