"""The collective render loop under ``massview render`` and :func:`massview.render`.

:func:`run_render` runs on every rank of ``comm`` at once: it renders a list of cameras (or
``cfg.frames`` frames of ``cfg.path``) through :func:`massview.systems.render_frame` and, on
rank 0, returns a :class:`JobOutput` — the summary, the per-frame per-rank stats records and
(with ``keep``) the display tiles as numpy arrays. With an ``out`` folder it writes:

* ``frames/NNNNN.png`` (or ``wall/rROWcCOL/NNNNN.png``, one folder per display rank, with
  ``--wall``), lossless, so images read back are the rendered pixels bit for bit;
* ``depth/NNNNN.npy`` (``wall_depth/rROWcCOL/`` with a wall): float32 window depth in [0, 1],
  1 = background, with ``depth``;
* ``stats.jsonl`` (one record per frame per rank) and ``summary.json``.
"""

from __future__ import annotations

import json
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from PIL import Image as PILImage

from ..core.camera import Camera, Viewport
from ..core.config import RenderConfig
from ..core.image import Image
from ..core.stats import clear_run_outputs, summarize
from ..lod.walk import fit_path
from ..parallel.decompose import parse_decomposition
from ..systems import display_tiles, open_system
from ..systems.frameloop import render_frames

__all__ = ["run_render", "write_png", "tile_dir", "JobOutput"]


@dataclass
class JobOutput:
    """What rank 0 holds after :func:`run_render`."""

    summary: dict
    records: list[dict]
    tiles: dict[int, list[tuple[Viewport, np.ndarray, np.ndarray | None]]] = field(default_factory=dict)
    # frame -> [(tile viewport, RGB uint8 (h, w, 3), depth float32 (h, w) or None)], from every display rank


def write_png(path: Path, img: Image) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    PILImage.fromarray(img.color[..., :3]).save(path, compress_level=1)


def tile_dir(out: Path, cfg: RenderConfig, rank: int, what: str = "frames") -> Path:
    """Where display rank ``rank`` writes its frames (``what="depth"``: its depth arrays)."""
    if not cfg.wall:
        return out / what
    cols = int(cfg.wall.lower().split("x")[0])
    return out / ("wall" if what == "frames" else f"wall_{what}") / f"r{rank // cols}c{rank % cols}"


def _sink(out: Path | None, cfg: RenderConfig, rank: int, keep: bool, depth: bool, kept: list):
    tdir = tile_dir(out, cfg, rank) if out is not None else None
    ddir = tile_dir(out, cfg, rank, "depth") if out is not None else None

    def sink(frame: int, tile: Image) -> None:
        if tdir is not None:
            write_png(tdir / f"{frame:05d}.png", tile)
            if depth:
                ddir.mkdir(parents=True, exist_ok=True)
                np.save(ddir / f"{frame:05d}.npy", tile.depth)
        if keep:
            kept.append((frame, tile.viewport.to_json(), np.ascontiguousarray(tile.color[..., :3]), tile.depth.copy() if depth else None))

    return sink


def run_render(comm, scene, cfg: RenderConfig, out: Path | None = None, quiet: bool = False, cameras: list[Camera] | None = None,
               keep: bool = False, depth: bool = False, path_label: str | None = None) -> JobOutput | None:
    """Render on every rank of ``comm``; returns the :class:`JobOutput` on rank 0, None elsewhere.

    ``scene``: a scene spec (opened here, closed at the end) or an open system (left open).
    ``cameras``: rank 0's list (others may pass None); default: ``cfg.frames`` cameras of ``cfg.path``.
    ``keep``: gather every display tile to rank 0 (RGB and, with ``depth``, depth) into the result.
    ``path_label``: what the summary names as the path (default ``cfg.path``).
    """
    rank, n = comm.Get_rank(), comm.Get_size()
    system = open_system(scene, cfg) if isinstance(scene, str) else scene
    name = scene if isinstance(scene, str) else getattr(system, "spec", "scene")
    kind, mode = parse_decomposition(cfg.decomposition, system.sort_last_modes)
    decomposition, compositor = f"{kind}:{mode}" if mode else kind, cfg.compositor if kind == "sort-last" else "tile-assembly"
    if hasattr(system, "split_label"):  # a system that splits the frame its own way (M1, T2)
        decomposition, compositor = system.split_label(cfg)
    if rank == 0 and cameras is None:
        ground = system.ground(cfg) if cfg.path == "walkthrough" and hasattr(system, "ground") else None
        box = system.bounds_at(cfg) if hasattr(system, "bounds_at") else system.bounds  # (T2's bounds are drawn ones already)
        cameras = fit_path(cfg.path, *box, getattr(system, "obstacles", None), ground).cameras(cfg.frames, cfg.width, cfg.height)
    nframes = comm.bcast(len(cameras) if rank == 0 else None, root=0)
    is_display = any(r == rank for r, _ in display_tiles(cfg, n))
    if rank == 0 and out is not None:
        out.mkdir(parents=True, exist_ok=True)
        clear_run_outputs(out)  # an earlier run's frames, stats and summary (before any rank writes)
    comm.Barrier()
    kept: list = []
    sink = _sink(out, cfg, rank, keep, depth, kept) if is_display else None
    progress = _progress(f"{name} · {n} rank{'s' if n > 1 else ''} · {decomposition}"
                         + (f" · {compositor}" if compositor != "tile-assembly" else ""), nframes) if rank == 0 and not quiet else None
    records, diffs = [], []
    stats_file = open(out / "stats.jsonl", "w") if rank == 0 and out is not None else None
    t_start = time.perf_counter()
    try:
        if hasattr(system, "run_path"):  # a system with its own pipelined frame loop (M1)
            early: set = set()

            def on_record(rec: dict) -> None:  # the server's record of each frame as it is finished: an
                early.add(id(rec))             # interrupted run keeps its frames' statistics (walk6 #7)
                if stats_file:
                    stats_file.write(json.dumps(rec) + "\n")
                    stats_file.flush()
                if progress:
                    progress[0].advance(progress[1])

            got = system.run_path(comm, cameras, cfg, sink, on_record=on_record)
            for rec in (got[0] if got else []):
                records.append(rec)
                if stats_file and id(rec) not in early:
                    stats_file.write(json.dumps(rec) + "\n")
            diffs = got[1] if got else []
        for res in render_frames(comm, system, cfg, cameras, sink, 0 if hasattr(system, "run_path") else nframes):
            f = res.stats.frame
            gathered = comm.gather((res.stats.to_json(), res.diff), root=0)
            if rank == 0:
                for rec, diff in gathered:
                    records.append(rec)
                    if stats_file:
                        stats_file.write(json.dumps(rec) + "\n")
                    if diff is not None:
                        diffs.append((f, diff))
                if stats_file:
                    stats_file.flush()
                if progress:
                    progress[0].advance(progress[1])
    finally:
        if progress:
            progress[0].stop()
        if stats_file:
            stats_file.close()
    wall_s = time.perf_counter() - t_start
    if isinstance(scene, str) and hasattr(system, "close"):
        system.close()
    rss = comm.gather(_peak_rss(), root=0)
    all_kept = comm.gather(kept, root=0) if keep else None
    if rank != 0:
        return None
    roles = system.rank_roles(n) if hasattr(system, "rank_roles") else None  # (T2, M1: ranks with a role each)
    extra = {"system": cfg.system, "roles": roles} if roles else {}
    summary = summarize(
        records, work_ranks=[r for r, role in enumerate(roles) if role in system.work_roles] if roles else None, **extra,
        scene=name, decomposition=decomposition, compositor=compositor, size=[cfg.width, cfg.height],
        path=path_label or cfg.path, wall=cfg.wall,
        tile_targets=cfg.tile_targets, codec=cfg.codec, renderer=system.renderer,
        peak_rss_mib_per_rank=[round(v / 2**20, 1) for v in rss], pipeline=cfg.pipeline, wall_s=round(wall_s, 3),
        throughput_fps=round(nframes / wall_s, 3) if wall_s > 0 else None,  # frames delivered per second
    )
    summary["latency_ms"] = summary.get("mean_frame_ms")  # a frame's draw start to delivery (max over ranks)
    if cfg.reference:
        summary.update(_reference_figures(diffs))
    if out is not None:
        (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    tiles: dict = {}
    for per_rank in all_kept or []:
        for frame, vp, rgb, dep in per_rank:
            tiles.setdefault(frame, []).append((Viewport.from_json(vp), rgb, dep))
    return JobOutput(summary, records, tiles)


def _reference_figures(diffs) -> dict:
    per_frame: dict = {}
    for f, (mx, nd, npx) in diffs:
        a = per_frame.setdefault(f, [0, 0, 0])
        a[0], a[1], a[2] = max(a[0], mx), a[1] + nd, a[2] + npx
    return {"max_abs_diff": max((v[0] for v in per_frame.values()), default=0),
            "diff_fraction": max((v[1] / v[2] for v in per_frame.values() if v[2]), default=0.0)}


def _progress(what: str, total: int):
    from rich.console import Console
    from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

    p = Progress(TextColumn("[bold]render[/] {task.fields[what]}"), BarColumn(), TextColumn("{task.completed}/{task.total} frames"),
                 TimeRemainingColumn(), transient=False, console=Console(file=sys.stderr))
    bar = p.add_task("render", total=total, what=what)
    p.start()
    return p, bar


def _peak_rss() -> int:
    """This process's peak resident memory in bytes (VmHWM), 0 where /proc is missing."""
    try:
        with open("/proc/self/status") as f:
            return next(int(line.split()[1]) * 1024 for line in f if line.startswith("VmHWM:"))
    except (OSError, StopIteration):
        return 0
