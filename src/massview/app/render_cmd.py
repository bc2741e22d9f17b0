"""``massview render``: run a camera path on every rank and write frames, stats and summary.

Outputs in ``DIR``: ``frames/NNNNN.png`` (or ``wall/rROWcCOL/NNNNN.png``, one folder per display
rank, with ``--wall``), ``stats.jsonl`` (one record per frame per rank) and ``summary.json``.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

from PIL import Image as PILImage

from ..core.config import RenderConfig
from ..core.image import Image
from ..core.paths import load_path
from ..core.stats import summarize
from ..parallel.decompose import parse_decomposition
from ..systems import display_tiles, open_system
from ..systems.frameloop import render_frames

__all__ = ["run_render", "write_png"]


def write_png(path: Path, img: Image) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    PILImage.fromarray(img.color[..., :3]).save(path, compress_level=1)


def _tile_dir(out: Path, cfg: RenderConfig, rank: int, nranks: int) -> Path:
    if not cfg.wall:
        return out / "frames"
    cols = int(cfg.wall.lower().split("x")[0])
    return out / "wall" / f"r{rank // cols}c{rank % cols}"


def run_render(comm, scene: str, cfg: RenderConfig, out: Path, quiet: bool = False) -> dict | None:
    """Render ``cfg.frames`` frames of ``cfg.path``; returns the summary on rank 0."""
    rank, n = comm.Get_rank(), comm.Get_size()
    system = open_system(scene, cfg)
    kind, mode = parse_decomposition(cfg.decomposition, system.sort_last_modes)
    cameras = load_path(cfg.path, *system.bounds).cameras(cfg.frames, cfg.width, cfg.height) if rank == 0 else None
    is_display = any(r == rank for r, _ in display_tiles(cfg, n))
    tile_dir = _tile_dir(out, cfg, rank, n)
    if rank == 0:
        out.mkdir(parents=True, exist_ok=True)
    comm.Barrier()

    def sink(frame: int, tile: Image) -> None:
        write_png(tile_dir / f"{frame:05d}.png", tile)

    progress = None
    if rank == 0 and not quiet:
        from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

        progress = Progress(TextColumn("[bold]render[/] {task.fields[what]}"), BarColumn(), TextColumn("{task.completed}/{task.total} frames"),
                            TimeRemainingColumn(), transient=False, console=_stderr_console())
        what = f"{scene} · {n} rank{'s' if n > 1 else ''} · {cfg.decomposition}" + (f" · {cfg.compositor}" if kind == "sort-last" else "")
        bar = progress.add_task("render", total=cfg.frames, what=what)
        progress.start()
    records, diffs = [], []
    stats_file = open(out / "stats.jsonl", "w") if rank == 0 else None
    t_start = time.perf_counter()
    try:
        for res in render_frames(comm, system, cfg, cameras, sink if is_display else None):
            f = res.stats.frame
            gathered = comm.gather((res.stats.to_json(), res.diff), root=0)
            if rank == 0:
                for rec, diff in gathered:
                    records.append(rec)
                    stats_file.write(json.dumps(rec) + "\n")
                    if diff is not None:
                        diffs.append((f, diff))
                stats_file.flush()
                if progress:
                    progress.advance(bar)
    finally:
        if progress:
            progress.stop()
        if stats_file:
            stats_file.close()
    wall_s = time.perf_counter() - t_start
    if hasattr(system, "close"):
        system.close()
    rss = comm.gather(_peak_rss(), root=0)
    if rank != 0:
        return None
    summary = summarize(
        records,
        scene=scene,
        decomposition=f"{kind}:{mode}" if mode else kind,
        compositor=cfg.compositor if kind == "sort-last" else "tile-assembly",
        size=[cfg.width, cfg.height],
        path=cfg.path,
        wall=cfg.wall,
        tile_targets=cfg.tile_targets,
        codec=cfg.codec,
        renderer=system.renderer,
        peak_rss_mib_per_rank=[round(v / 2**20, 1) for v in rss],
        pipeline=cfg.pipeline,
        wall_s=round(wall_s, 3),
        throughput_fps=round(cfg.frames / wall_s, 3) if wall_s > 0 else None,  # frames delivered per second
    )
    summary["latency_ms"] = summary.get("mean_frame_ms")  # a frame's draw start to delivery (max over ranks)
    if cfg.reference:
        per_frame = {}
        for f, (mx, nd, npx) in diffs:
            a = per_frame.setdefault(f, [0, 0, 0])
            a[0], a[1], a[2] = max(a[0], mx), a[1] + nd, a[2] + npx
        summary["max_abs_diff"] = max((v[0] for v in per_frame.values()), default=0)
        summary["diff_fraction"] = max((v[1] / v[2] for v in per_frame.values() if v[2]), default=0.0)
    (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    return summary


def _peak_rss() -> int:
    """This process's peak resident memory in bytes (VmHWM), 0 where /proc is missing."""
    try:
        with open("/proc/self/status") as f:
            return next(int(line.split()[1]) * 1024 for line in f if line.startswith("VmHWM:"))
    except (OSError, StopIteration):
        return 0


def _stderr_console():
    from rich.console import Console

    return Console(file=sys.stderr)
