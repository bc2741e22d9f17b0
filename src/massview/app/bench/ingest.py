"""Prepare a synthetic DEM: MB/s, compression ratio, peak RSS.

``massview bench ingest``: prepare a synthetic DEM and report throughput, compression, peak RSS.

The DEM (default 16385², 1 GiB of float32) is generated once into ``--workdir`` as ``.npy``.
Then, in the same run:

* baseline: a plain copy of the same bytes (read in 64 MiB pieces, write to a file) — the
  disk floor for touching the data once;
* ``massview prepare terrain`` in a child process, which reports its own peak resident
  memory (``VmHWM`` of /proc/self/status) at exit. (``wait4``'s ``ru_maxrss`` would not do:
  Linux carries the parent's high-water mark over fork and exec.)

Printed: input MB/s of prepare, its ratio to the copy baseline, the height compression
ratio, the store size, and peak RSS against the 1 GiB target. Nothing is asserted.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

from .child import run_measured

__all__ = ["add_arguments", "run"]


def add_arguments(p) -> None:
    p.add_argument("--size", type=int, default=16385, help="samples per side (default 16385: 1 GiB float32)")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--block", type=int, default=257)
    p.add_argument("--workdir", default="out/bench", help="where the DEM is generated once and the store written")
    p.add_argument("--no-color", action="store_true")
    p.add_argument("--keep", action="store_true", help="keep the store afterwards")


def _copy_baseline(src: Path, dst: Path) -> float:
    t0 = time.perf_counter()
    with open(src, "rb") as f, open(dst, "wb") as g:
        while True:
            buf = f.read(64 << 20)
            if not buf:
                break
            g.write(buf)
        g.flush()
        os.fsync(g.fileno())
    dt = time.perf_counter() - t0
    dst.unlink()
    return dt


def run(args) -> int:
    from rich.console import Console
    from rich.table import Table

    from ..outputs import check_output_dir
    from ..terrain_cmds import progress_bar, store_info

    console = Console()
    work = check_output_dir(Path(args.workdir), "--workdir")
    dem = work / f"synthetic_{args.size}_seed{args.seed}.npy"
    if not dem.exists():  # in a child process: this one must stay small (see _peak_rss)
        console.print(f"generating {dem} (once; kept for later runs) ...")
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-m", "massview", "generate", "terrain", str(dem), "--size", str(args.size),
                        "--seed", str(args.seed)], check=True)
        console.print(f"generated in {time.perf_counter() - t0:.1f} s")
    nbytes = dem.stat().st_size
    copy_s = _copy_baseline(dem, work / "copy.tmp")
    store = work / f"synthetic_{args.size}.zarr"
    shutil.rmtree(store, ignore_errors=True)
    cmd = [sys.executable, "-m", "massview", "prepare", "terrain", str(dem), "-o", str(store), "--block", str(args.block)]
    if args.no_color:
        cmd.append("--no-color")
    console.print("running: " + " ".join(cmd[2:]))
    run = run_measured(cmd, work / "prepare.peak_rss")
    if run.returncode != 0:
        console.print(f"[red]prepare failed (exit {run.returncode})[/]")
        return run.returncode
    prep_s, rss = run.wall_s, run.peak_rss
    info = store_info(store)
    t = Table(title=f"ingest of a {args.size}² float32 DEM ({nbytes / 2**30:.2f} GiB), block {args.block}")
    t.add_column("figure")
    t.add_column("value", justify="right")
    t.add_row("prepare time", f"{prep_s:.1f} s")
    t.add_row("prepare throughput", f"{nbytes / 1e6 / prep_s:.1f} MB/s")
    t.add_row("copy baseline (same bytes)", f"{copy_s:.1f} s, {nbytes / 1e6 / copy_s:.1f} MB/s")
    t.add_row("prepare ÷ copy time", f"{prep_s / copy_s:.1f}×")
    t.add_row("height compression ratio", f"{info['compression_ratio']:.3f}")
    t.add_row("store on disk (heights + colour + metadata)", f"{info['disk_bytes'] / 2**20:.0f} MiB")
    t.add_row("peak RSS of prepare", f"{rss / 2**20:.0f} MiB ({'under' if rss < 2**30 else 'OVER'} the 1 GiB target)")
    console.print(t)
    if not args.keep:
        shutil.rmtree(store, ignore_errors=True)
    return 0
