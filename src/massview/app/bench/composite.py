"""Sort-last compositing cost per algorithm and rank count vs its network + memory floor.

``massview bench composite``:

For each rank count, a job under ``mpiexec`` renders one sort-last partial image per rank of
``--scene`` (default ``builtin:objects``; range R_i, full frame), then composites and delivers
the final image to rank 0 with each algorithm, ``--repeat`` times. Printed per case: time per
frame (max over ranks, best of the repeats), bytes moved (all ranks' sends), the ratio to the
floor measured in the same job, and the CPU time of the slowest rank (its thread time: what the
kernels cost apart from waiting for a core or a peer on a shared machine); then, per rank of
the best repeat, where its time went (the compositing pieces of
:data:`massview.parallel.composite.PIECES`: encode, wait, decode, combine, copy; "other" is
the rest: Python and MPI call overhead) beside the two terms of its floor. The floor of a rank is

    bytes it receives ÷ point-to-point bandwidth (every pair of ranks swapping 8 MiB at once)
  + bytes it must read and write (``touched_*`` counters, see
    :func:`massview.parallel.composite._count_touched`) ÷ memory bandwidth (every rank copying
    at once; the higher of a frame-sized copy — the compositor's own working set, which may sit
    in the last-level cache — and a 64 MiB one, so the floor is never set by DRAM for data that
    lives in cache)

and a case's floor is the largest over its ranks (the headline ratio, issue 20's
definition). Beside it, the **shared-core floor** max(floor, sum of the ranks' floors ÷
cores): when ranks outnumber the cores their floors cannot all be paid at once. Both
bandwidths are measured in the job itself, with its rank count, from a common barrier until
the last rank is done: what each rank gets while all of them work, as they do when they
composite (ranks that share a core share it in the measurement too); measured once per wait
mode, the higher figure sets the floor.

``--wait poll,sleep`` runs each case under each of :data:`massview.parallel.exchange.WAIT_MODES`
in the same job, the modes alternating repeat by repeat so both see the same load. The
per-rank table splits each rank's time (its main thread, from ``/proc/thread-self/schedstat``
and ``getrusage``) into work (on a core, not in a wait), polling (on a core inside a wait:
``cpu.wait``), run queue (runnable, waiting for a core) and asleep (the rest), with its
voluntary / involuntary context switches. Nothing here asserts a time.
"""

from __future__ import annotations

import json
import resource
import tempfile
import time
from pathlib import Path

from ...core.config import RenderConfig, parse_size
from ...core.errors import ConfigError
from ...core.paths import load_path
from ...core.stats import FrameStats
from ...core.task import Task
from ...parallel.composite import COMPOSITORS, PIECES, composite, deliver, final_regions
from ...parallel.decompose import sort_last_ranges
from ...parallel.exchange import (WAIT_MODES, Outbox, barrier, max_over_ranks, measure_bandwidth, measure_memory_bandwidth,
                                  set_wait_mode)
from ...parallel.runtime import local_cores, relaunch, world

__all__ = ["add_arguments", "run", "worker"]


def add_arguments(p) -> None:
    import argparse

    from ...parallel.codec import CODECS

    p.add_argument("--ranks", default="2,3,4", help="rank counts, comma-separated (default 2,3,4)")
    p.add_argument("--size", default="1280x1024")
    p.add_argument("--repeat", type=int, default=5, help="timed repetitions per case (default 5)")
    p.add_argument("--codec", default="blosc2", choices=tuple(CODECS))
    p.add_argument("--scene", default="builtin:objects", help="scene or terrain store rendered into the partial images")
    p.add_argument("--wait", default="poll,sleep", help=f"wait modes compared in each job, comma-separated: {', '.join(WAIT_MODES)} "
                   "(default both; see MASSVIEW_MPI_WAIT)")
    p.add_argument("--json", type=Path, default=None, help="also write every row (per-rank records included) to this JSON file")
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
    modes = parse_modes(args.wait)
    bws, frames, bigs = {}, {}, {}
    for mode in modes:  # best of 10: a low figure would inflate the floor
        set_wait_mode(mode)
        bws[mode] = measure_bandwidth(comm, repeat=10)
        frames[mode], bigs[mode] = measure_memory_bandwidth(comm, image.nbytes, repeat=10), measure_memory_bandwidth(comm, repeat=10)
    bw, mem_frame, mem_big = max(bws.values()), max(frames.values()), max(bigs.values())
    mem_bw, cores = max(mem_frame, mem_big), local_cores()
    rows = []
    for method in COMPOSITORS:
        for mode, best in _best_repeats(comm, image, method, cam.viewport, args, modes).items():
            per_rank = comm.gather(_rank_record(best, bw, mem_bw), root=0)
            sent = comm.allreduce(best["stats"].bytes_sent)
            if rank == 0:
                floor = max(r["floor_net"] + r["floor_mem"] for r in per_rank)
                shared = max(floor, sum(r["floor_net"] + r["floor_mem"] for r in per_rank) / cores)
                rows.append({"algorithm": method, "ranks": n, "wait": mode, "ms": best["ms"], "bytes": sent, "floor_ms": floor,
                             "ratio": best["ms"] / floor, "shared_floor_ms": shared, "shared_ratio": best["ms"] / shared, "cores": cores,
                             "cpu_ms": max(r["cpu"] for r in per_rank), "bandwidth_MBps": bw / 1e6,
                             "bandwidth_by_wait_MBps": {m: v / 1e6 for m, v in bws.items()}, "mem_MBps": mem_bw / 1e6,
                             "mem_frame_MBps": mem_frame / 1e6, "mem_64MiB_MBps": mem_big / 1e6, "per_rank": per_rank})
    if rank == 0:
        Path(args.worker).write_text(json.dumps(rows))
    return 0


def parse_modes(text: str) -> list[str]:
    modes = [m.strip() for m in text.split(",") if m.strip()]
    bad = [m for m in modes if m not in WAIT_MODES]
    if bad or not modes:
        raise ConfigError(f"--wait {text!r}: use wait modes from {', '.join(WAIT_MODES)}, comma-separated")
    return modes


def _sched() -> tuple[float, float, int, int]:
    """This thread's (ms on a core, ms runnable in the run queue, voluntary and involuntary
    context switches); zeros where /proc/thread-self/schedstat is missing."""
    try:
        on, queued, _ = (int(v) for v in Path("/proc/thread-self/schedstat").read_text().split()[:3])
    except (OSError, ValueError):
        on = queued = 0
    ru = resource.getrusage(getattr(resource, "RUSAGE_THREAD", resource.RUSAGE_SELF))
    return on / 1e6, queued / 1e6, ru.ru_nvcsw, ru.ru_nivcsw


def _best_repeats(comm, image, method: str, vp, args, modes: list[str]) -> dict[str, dict]:
    """Per wait mode, the repeat with the smallest time (max over ranks) of composite + deliver
    to rank 0; the modes alternate repeat by repeat."""
    best: dict[str, dict] = {}
    for _ in range(args.repeat):
        for mode in modes:
            set_wait_mode(mode)
            rec = _one_repeat(comm, image, method, vp, args)
            if mode not in best or rec["ms"] < best[mode]["ms"]:
                best[mode] = rec
    return best


def _one_repeat(comm, image, method: str, vp, args) -> dict:
    n, st = comm.Get_size(), FrameStats(0, comm.Get_rank())
    barrier(comm)
    s0, t0, c0 = _sched(), time.perf_counter(), time.thread_time()
    box = Outbox(comm, st)
    piece = composite(comm, image, method, 4, st, args.codec, box)
    t1 = time.perf_counter()
    deliver(comm, piece, [(0, vp)], st, args.codec, final_regions(n, method, 4, vp), box)
    t2, cpu, s1 = time.perf_counter(), time.thread_time() - c0, _sched()
    dt = max_over_ranks(comm, t2 - t0)
    return {"ms": dt * 1e3, "own": (t2 - t0) * 1e3, "composite": (t1 - t0) * 1e3, "deliver": (t2 - t1) * 1e3, "cpu": cpu * 1e3, "stats": st,
            "sched": [b - a for a, b in zip(s0, s1)]}


def _rank_record(best: dict, bw: float, mem_bw: float) -> dict:
    """One rank's time split into pieces (ms) and into work / polling / run queue / asleep,
    beside the two terms of its floor (ms)."""
    st = best["stats"]
    pieces = {p: st.times_ms.get("piece." + p, 0.0) for p in PIECES}
    touched = st.counters.get("touched_encode", 0) + st.counters.get("touched_composite", 0)
    on, queued, vcs, ics = best["sched"]
    polling = min(st.times_ms.get("cpu.wait", 0.0), on)
    return {"rank": st.rank, "ms": best["own"], "composite": best["composite"], "deliver": best["deliver"], "cpu": best["cpu"],
            **pieces, "other": best["own"] - sum(pieces.values()), "recv_bytes": st.bytes_recv, "touched_bytes": touched,
            "floor_net": st.bytes_recv / bw * 1e3, "floor_mem": touched / mem_bw * 1e3,
            "work": on - polling, "polling": polling, "runqueue": queued, "asleep": max(0.0, best["own"] - on - queued),
            "vcsw": vcs, "ivcsw": ics, "mean_stage": {k: st.times_ms.get(k, 0.0) for k in ("encode", "transfer", "composite")}}


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

    counts = [int(v) for v in args.ranks.split(",") if v.strip()]
    modes = parse_modes(args.wait)
    console = Console(width=None if Console().is_terminal else 170)
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        for n in counts:
            out = Path(tmp) / f"bench{n}.json"
            argv = ["bench", "composite", "--worker", str(out), "--size", args.size, "--repeat", str(args.repeat), "--codec", args.codec,
                    "--scene", args.scene, "--wait", ",".join(modes)]
            console.print(f"[dim]running {n} ranks ...[/]")
            rc = relaunch(argv, n)
            if rc != 0:
                console.print(f"[red]the {n}-rank job failed (exit {rc})[/]")
                return rc
            results += json.loads(out.read_text())
    _print(console, results, args)
    if args.json is not None:
        args.json.write_text(json.dumps(results, indent=1))
    return 0


def _print(console, results: list[dict], args) -> None:
    from rich.table import Table

    w, h = parse_size(args.size)
    table = Table(title=f"sort-last compositing + delivery to rank 0, {w}x{h}, {args.scene}, codec {args.codec}, best of {args.repeat}")
    for col in ("algorithm", "ranks", "wait", "ms/frame", "MB moved", "p2p MB/s", "mem MB/s (frame / 64 MiB)", "floor ms", "ratio to floor",
                "shared-core floor ms", "ratio to it", "CPU ms"):
        table.add_column(col, justify="right")
    for r in results:
        table.add_row(r["algorithm"], str(r["ranks"]), r["wait"], f"{r['ms']:.2f}", f"{r['bytes'] / 1e6:.2f}", f"{r['bandwidth_MBps']:.0f}",
                      f"{r['mem_frame_MBps']:.0f} / {r['mem_64MiB_MBps']:.0f}", f"{r['floor_ms']:.2f}", f"{r['ratio']:.2f}",
                      f"{r['shared_floor_ms']:.2f}", f"{r['shared_ratio']:.2f}", f"{r['cpu_ms']:.1f}")
    console.print(table)
    _print_ranks(console, results)


def _print_ranks(console, results: list[dict]) -> None:
    from rich.table import Table

    pieces = Table(title="per rank, best repeat: where the time goes (ms) against the floor's two terms (ms); work / polling / run queue / "
                         "asleep from the main thread's schedstat; context switches voluntary / involuntary")
    for col in ("algorithm", "ranks", "wait", "rank", "ms", "compositing", "delivery", *PIECES, "other", "work", "polling", "run queue",
                "asleep", "csw v/i", "MB in", "MB touched", "floor net", "floor mem"):
        pieces.add_column(col, justify="right")
    for r in results:
        for p in r["per_rank"]:
            pieces.add_row(r["algorithm"], str(r["ranks"]), r["wait"], str(p["rank"]), f"{p['ms']:.2f}", f"{p['composite']:.2f}",
                           f"{p['deliver']:.2f}", *(f"{p[k]:.2f}" for k in PIECES), f"{p['other']:.2f}",
                           *(f"{p[k]:.2f}" for k in ("work", "polling", "runqueue", "asleep")), f"{p['vcsw']}/{p['ivcsw']}",
                           f"{p['recv_bytes'] / 1e6:.2f}", f"{p['touched_bytes'] / 1e6:.1f}", f"{p['floor_net']:.2f}", f"{p['floor_mem']:.2f}")
    console.print(pieces)
