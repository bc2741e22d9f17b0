"""Decompositions x ranks (triangles, imbalance, LOD time) and LOD vs a plain mesh.

``massview bench terrain STORE``: decompositions × rank counts, and LOD vs a plain mesh.

Part 1 (parallel): for the ``turn`` and ``zoom`` paths, every decomposition at 1–4 ranks is
rendered as a real MPI job through :func:`massview.render` (``ranks=N``); printed per case: triangles per rank, imbalance
(max/mean), LOD time and front size (patches) per frame.

Part 2: LOD selection time against front size (τ = 1, 0.5, 0.25 on three paths).

``--draw``: only the draw throughput (Mtri/s) of the K-patch path, a plain mesh and
pyvista/VTK on the same triangles, at full resolution and at the demo's LOD (terrain_draw.py).

Part 3 (one rank, one process, same GL context, same cameras and image size): the K-patch
LOD (LOD selection + draw) against drawing the store's finest level as one plain indexed
mesh. Printed: triangles and frame time of each and their ratios. The plain mesh must fit in
memory: it is skipped above ``--max-plain`` triangles.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np

from ...core.config import RenderConfig, parse_size
from ...core.paths import load_path
from ...core.stats import FrameStats
from ...core.task import Task
from ...parallel.runtime import self_comm
from .args import int_list, positive, size, terrain_store

__all__ = ["add_arguments", "run"]


def add_arguments(p) -> None:
    p.add_argument("store")
    p.add_argument("--ranks", type=int_list(1), default="1,2,3,4")
    p.add_argument("--size", type=size, default="1280x1024")
    p.add_argument("--frames", type=positive, default=6)
    p.add_argument("--tau", type=float, default=1.0)
    p.add_argument("--max-plain", type=positive, default=40_000_000, help="largest plain mesh to draw as the baseline (triangles)")
    p.add_argument("--skip-parallel", action="store_true", help="only the one-rank LOD vs plain-mesh comparison")
    p.add_argument("--draw", action="store_true", help="only the draw throughput: K-patch vs plain mesh vs VTK (terrain_draw.py)")
    p.add_argument("--draw-reps", type=positive, default=5, help="draws per path in --draw")
    p.add_argument("--no-vtk", action="store_true", help="--draw without the pyvista/VTK child")


DECOMPS = ["sort-first:horizontal", "sort-first:vertical", "sort-first:grid", "sort-first:kd",
           "sort-last:kpatch", "sort-last:linear", "sort-last:quadtree"]


def _parallel(args, console, table_cls) -> None:
    counts = [int(v) for v in args.ranks.split(",") if v.strip()]
    t = table_cls(title=f"parallel terrain: {args.store}, {args.size}, {args.frames} frames, τ = {args.tau}")
    for c in ("path", "decomposition", "ranks", "triangles per rank (k)", "imbalance", "LOD ms", "front patches", "frame ms"):
        t.add_column(c, justify="right")
    from ... import api
    from ...core.errors import MassviewError

    with tempfile.TemporaryDirectory() as tmp:
        for path in ("turn", "zoom"):
            for n in counts:
                for d in (DECOMPS if n > 1 else DECOMPS[:1]):
                    out = Path(tmp) / f"{path}_{d.replace(':', '_')}_{n}"
                    try:
                        res = api.render(args.store, path, ranks=n, out=out, images=False, frames=args.frames, size=args.size,
                                         decomposition=d, tau=args.tau, loading="complete")
                    except MassviewError as e:
                        console.print(f"[red]{path} {d} {n} ranks failed: {e}[/]")
                        continue
                    s = res.summary
                    front = np.mean([r["counters"].get("front_patches", 0) for r in res.stats])
                    t.add_row(path, d if n > 1 else "(1 rank)", str(n), ", ".join(f"{v / 1e3:.0f}" for v in s["triangles_per_rank"]),
                              f"{s['imbalance']:.3f}", f"{s['stage_ms_mean']['lod']:.1f}", f"{front:.0f}", f"{s['mean_frame_ms']:.0f}")
    console.print(t)
    console.print(PAPER_NOTE)


PAPER_NOTE = (  # (walk8 L4: the T2, M1 and M2 benches say which figure is which; this one did not)
    "Beside the paper (Goswami et al., EGPGV 2010): the sort-last rows are its Figs. 4-6 (linear block and quadtree "
    "enumeration of the M-blocks against active K-patch enumeration, four nodes) and sort-first horizontal against "
    "vertical its Fig. 7, which the paper shows as screenshots; the imbalance column measures what they show. Its Fig. 9 "
    "(frames/s on 1-10 machines, turning and zooming, 16k² Puget Sound and 32k² SRTM, each with its own GPU) has no "
    "counterpart on this host, whose ranks share its cores and one software rasterizer: `massview bench frame` gives the "
    "frame per stage at 1-4 ranks. 'LOD ms' is the whole LOD stage of a frame, with the waits for loads (--loading "
    "complete); the selection alone is the 'LOD selection time' table.")


def _vs_plain(args, console, table_cls) -> None:
    from ...data.terrain import TerrainStore
    from ...render.terrain import PlainMeshRenderer
    from ...systems.terrain import TerrainSystem

    st = TerrainStore(args.store)
    lay = st.layout
    plain_tris = 2 * (lay.rows - 1) * (lay.cols - 1)
    if plain_tris > args.max_plain:
        console.print(f"[yellow]plain-mesh baseline skipped: the finest level is {plain_tris / 1e6:.0f} M triangles "
                      f"(> --max-plain {args.max_plain / 1e6:.0f} M); run this part on a smaller store[/]")
        return
    w, h = parse_size(args.size)
    sysm = TerrainSystem(args.store, loading="complete")
    comm = self_comm()
    ctx, _, _, view = sysm.renderers()
    M = lay.M
    full = np.empty((lay.S, lay.S), np.float32)
    color = np.empty((lay.S, lay.S, 3), np.uint8)
    for i in range(lay.blocks(0)):
        for j in range(lay.blocks(0)):
            full[i * (M - 1): i * (M - 1) + M, j * (M - 1): j * (M - 1) + M] = st.get_block(0, i, j)
            c = st.get_color(0, i, j)
            if c is not None:
                color[i * (M - 1): i * (M - 1) + M, j * (M - 1): j * (M - 1) + M] = c
    plain = PlainMeshRenderer(ctx, full[: lay.rows, : lay.cols], color[: lay.rows, : lay.cols] if st.has_color else None,
                              st.spacing, st.vertical_scale)
    del full, color
    cfg = RenderConfig(width=w, height=h, tau=args.tau, loading="complete")
    t = table_cls(title=f"one rank: K-patch LOD (τ = {args.tau}) vs the finest level as one plain mesh, {w}x{h}")
    for c in ("path", "LOD triangles", "plain triangles", "plain ÷ LOD triangles", "LOD ms (select + draw)", "plain draw ms", "plain ÷ LOD time"):
        t.add_column(c, justify="right")
    for path in ("turn", "zoom"):
        cams = load_path(path, *sysm.bounds).cameras(args.frames, w, h)
        lod_ms, lod_tris, plain_ms = [], [], []
        for cam in cams:
            sysm.prepare_frame(comm, cam, cfg, FrameStats(0, 0))  # loads complete (not timed)
            st_ = FrameStats(0, 0)
            t0 = time.perf_counter()
            sysm.prepare_frame(comm, cam, cfg, st_)
            sysm.render(Task(0, cam.viewport), cam, cfg, st_)
            lod_ms.append((time.perf_counter() - t0) * 1e3)
            lod_tris.append(st_.triangles)
            ps = FrameStats(0, 0)
            t0 = time.perf_counter()
            view.render(cam, cam.viewport, plain.draw, ps)
            plain_ms.append((time.perf_counter() - t0) * 1e3)
        lt, lm, pm = np.mean(lod_tris), np.mean(lod_ms), np.mean(plain_ms)
        t.add_row(path, f"{lt / 1e3:.0f} k", f"{plain_tris / 1e6:.1f} M", f"{plain_tris / max(lt, 1):.1f}×", f"{lm:.0f}", f"{pm:.0f}", f"{pm / lm:.1f}×")
    plain.release()
    sysm.close()
    console.print(t)


def _lod_timing(args, console, table_cls) -> None:
    """LOD selection time against front size (all data resident), over τ and three paths."""
    from ...data.terrain import TerrainStore
    from ...lod.kpatch import PatchHierarchy, select_front

    st = TerrainStore(args.store)
    h = PatchHierarchy(st.layout, *st.lod_arrays(), spacing=st.spacing, vscale=st.vertical_scale)
    w, hh = parse_size(args.size)
    t = table_cls(title=f"LOD selection time vs front size, {w}x{hh} (best of 3, one core)")
    for c in ("path", "τ", "front patches", "select ms", "µs per patch"):
        t.add_column(c, justify="right")
    lo, hi = h.bounds()
    for path, at in (("zoom", 1.0), ("flyover", 0.5), ("forward", 0.5)):
        cam = load_path(path, lo, hi).camera(at, w, hh)
        for tau in (1.0, 0.5, 0.25):
            best, f = float("inf"), None
            for _ in range(3):
                t0 = time.perf_counter()
                f = select_front(h, cam, tau)
                best = min(best, time.perf_counter() - t0)
            t.add_row(path, f"{tau}", f"{len(f)}", f"{best * 1e3:.1f}", f"{best * 1e6 / max(len(f), 1):.2f}")
    console.print(t)


def run(args) -> int:
    from rich.console import Console
    from rich.table import Table

    console = Console(width=None if Console().is_terminal else 150)
    terrain_store(args.store)
    if args.draw:
        from .terrain_draw import run_draw

        run_draw(args, console, Table)
        return 0
    if not args.skip_parallel:
        _parallel(args, console, Table)
    _lod_timing(args, console, Table)
    _vs_plain(args, console, Table)
    return 0
