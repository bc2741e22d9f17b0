"""Sort-last compositing cost per algorithm and rank count vs its network + memory floor.

``massview bench composite``:

For each rank count, a job under ``mpiexec`` renders one sort-last partial image per rank of
``--scene`` (default ``builtin:objects``; range R_i, full frame), then composites and delivers
the final image to rank 0 with each algorithm, ``--repeat`` times. Printed per case: time per
frame (max over ranks, best of the repeats), bytes moved (all ranks' sends), and the ratio to
the floor measured in the same job, and the CPU time of the slowest rank (its thread time: what the
kernels cost apart from waiting for a core or a peer on a shared machine). The floor of a rank is

    bytes it receives ÷ point-to-point bandwidth (every pair of ranks swapping 8 MiB at once)
  + bytes it must read and write (``touched_*`` counters: pixels 8 B each of the bands it sends and
    keeps and of the result, plus its messages) ÷ memory bandwidth (every rank copying at once)

and a case's floor is the largest over its ranks. Both bandwidths are measured in the job
itself, with its rank count, from a common barrier until the last rank is done: what each
rank gets while all of them work, as they do when they composite (ranks that share a core
share it in the measurement too). Nothing here asserts a time.
"""

from __future__ import annotations

import json
import tempfile
import time
from pathlib import Path

import numpy as np

from ...core.config import RenderConfig, parse_size
from ...core.paths import load_path
from ...core.stats import FrameStats
from ...core.task import Task
from ...parallel.composite import COMPOSITORS, composite, deliver, final_regions
from ...parallel.decompose import sort_last_ranges
from ...parallel.exchange import Outbox, max_over_ranks, measure_bandwidth, measure_memory_bandwidth
from ...parallel.runtime import relaunch, world

__all__ = ["add_arguments", "run", "worker"]


def add_arguments(p) -> None:
    import argparse

    from ...parallel.codec import CODECS

    p.add_argument("--ranks", default="2,3,4", help="rank counts, comma-separated (default 2,3,4)")
    p.add_argument("--size", default="1280x1024")
    p.add_argument("--repeat", type=int, default=5, help="timed repetitions per case (default 5)")
    p.add_argument("--codec", default="blosc2", choices=tuple(CODECS))
    p.add_argument("--scene", default="builtin:objects", help="scene or terrain store rendered into the partial images")
    p.add_argument("--worker", type=Path, default=None, help=argparse.SUPPRESS)


def worker(args) -> int:
    from ...systems import open_system

    comm = world()
    rank, n = comm.Get_rank(), comm.Get_size()
    w, h = parse_size(args.size)
    cfg = RenderConfig(width=w, height=h, loading="complete")
    system = open_system(args.scene, cfg)
    cam = load_path("orbit", *system.bounds).camera(0.15, w, h)
    image = _render_part(comm, system, cam, cfg)
    bw, mem_bw = measure_bandwidth(comm), measure_memory_bandwidth(comm)
    rows = []
    for method in COMPOSITORS:
        best, best_stats = float("inf"), None
        for _ in range(args.repeat):
            st = FrameStats(0, rank)
            comm.Barrier()
            t0, c0 = time.perf_counter(), time.thread_time()
            box = Outbox(comm, st)
            piece = composite(comm, image, method, 4, st, args.codec, box)
            deliver(comm, piece, [(0, cam.viewport)], st, args.codec, final_regions(n, method, 4, cam.viewport), box)
            cpu = max_over_ranks(comm, time.thread_time() - c0)
            dt = max_over_ranks(comm, time.perf_counter() - t0)
            if dt < best:
                best, best_cpu, best_stats = dt, cpu, st
        sent = comm.allreduce(best_stats.bytes_sent)
        floor = max_over_ranks(comm, best_stats.bytes_recv / bw + (best_stats.counters.get("touched_encode", 0) + best_stats.counters.get("touched_composite", 0)) / mem_bw)
        stages = comm.gather(best_stats.times_ms, root=0)
        if rank == 0:
            mean_stage = {k: float(np.mean([s.get(k, 0.0) for s in stages])) for k in ("encode", "transfer", "composite")}
            rows.append({"algorithm": method, "ranks": n, "ms": best * 1e3, "bytes": sent, "floor_ms": floor * 1e3,
                         "ratio": best / floor, "cpu_ms": best_cpu * 1e3, "bandwidth_MBps": bw / 1e6, "mem_MBps": mem_bw / 1e6, **mean_stage})
    if rank == 0:
        Path(args.worker).write_text(json.dumps(rows))
    return 0


def _render_part(comm, system, cam, cfg):
    """This rank's sort-last part (range R_i of the full frame); terrain systems first run
    their per-frame LOD (with loading "complete", every block the view needs is drawn)."""
    rank, n = comm.Get_rank(), comm.Get_size()
    stats = FrameStats(0, rank)
    if hasattr(system, "prepare_frame"):
        system.prepare_frame(comm, cam, cfg, stats)
    return system.render(Task(rank, cam.viewport, data_range=sort_last_ranges(n)[rank]), cam, cfg, stats)


def run(args) -> int:
    if args.worker is not None:  # one MPI job of the benchmark (started by run below)
        return worker(args)
    from rich.console import Console
    from rich.table import Table

    counts = [int(v) for v in args.ranks.split(",") if v.strip()]
    w, h = parse_size(args.size)
    console = Console(width=None if Console().is_terminal else 150)
    table = Table(title=f"sort-last compositing, {w}x{h}, {args.scene}, codec {args.codec}, best of {args.repeat}")
    for col in ("algorithm", "ranks", "ms/frame", "MB moved", "p2p MB/s", "mem MB/s", "floor ms", "ratio to floor", "CPU ms", "encode ms", "transfer ms", "combine ms"):
        table.add_column(col, justify="right")
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        for n in counts:
            out = Path(tmp) / f"bench{n}.json"
            argv = ["bench", "composite", "--worker", str(out), "--size", args.size, "--repeat", str(args.repeat), "--codec", args.codec,
                    "--scene", args.scene]
            console.print(f"[dim]running {n} ranks ...[/]")
            rc = relaunch(argv, n)
            if rc != 0:
                console.print(f"[red]the {n}-rank job failed (exit {rc})[/]")
                return rc
            results += json.loads(out.read_text())
    for r in results:
        table.add_row(r["algorithm"], str(r["ranks"]), f"{r['ms']:.1f}", f"{r['bytes'] / 1e6:.2f}", f"{r['bandwidth_MBps']:.0f}", f"{r['mem_MBps']:.0f}",
                      f"{r['floor_ms']:.2f}", f"{r['ratio']:.1f}", f"{r['cpu_ms']:.1f}", f"{r['encode']:.1f}", f"{r['transfer']:.1f}", f"{r['composite']:.1f}")
    console.print(table)
    return 0
