"""Sort-last compositing cost per algorithm and rank count vs its network + memory floor.

``massview bench composite``:

For each rank count, a job under ``mpiexec`` renders one sort-last partial image per rank of
``--scene`` (default ``builtin:objects``; range R_i, full frame), then composites and delivers
the final image to rank 0 with each algorithm, ``--repeat`` times, as the frame loop does: on a
fresh copy of the image that compositing may write into (``composite(owned=True)``; the copy
is made before the clock starts, as the read-back is before compositing), rank 0 assembling
the frame in its own copy. ``--codec auto,blosc2`` compares codecs in the same job (``auto``,
the default, is what ``render`` uses: on one node, runs without byte compression and final
regions as raw rows). Printed per case: time per
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
in the same job, the modes (and codecs) alternating repeat by repeat so all see the same load. The
per-rank table splits each rank's time (its main thread, from ``/proc/thread-self/schedstat``
and ``getrusage``) into work (on a core, not in a wait), polling (on a core inside a wait:
``cpu.wait``), run queue (runnable, waiting for a core) and asleep (the rest), with its
voluntary / involuntary context switches. Nothing here asserts a time.
"""

from __future__ import annotations

import json
import os
import resource
import tempfile
import time
from pathlib import Path

from ...core.config import RenderConfig, parse_size
from ...core.errors import ConfigError
from ...core.image import Image
from ...core.paths import load_path
from ...core.stats import FrameStats
from ...core.task import Task
from ...parallel.codec import resolve_codec
from ...parallel.composite import COMPOSITORS, PIECES, composite, deliver, final_regions
from ...parallel.decompose import sort_last_ranges
from ...parallel.exchange import (WAIT_ENV_VAR, WAIT_MODES, Outbox, barrier, max_over_ranks, measure_bandwidth, measure_memory_bandwidth,
                                  set_wait_mode)
from ...parallel.runtime import launch_env, local_cores, relaunch, world
from .args import int_list, positive, size

__all__ = ["add_arguments", "run", "worker"]


def add_arguments(p) -> None:
    import argparse

    from ...parallel.codec import CODEC_CHOICES

    p.add_argument("--ranks", type=int_list(2), default="2,3,4", help="rank counts, comma-separated, each at least 2 (default 2,3,4)")
    p.add_argument("--size", type=size, default="1280x1024", help="image WIDTHxHEIGHT composited (default 1280x1024)")
    p.add_argument("--repeat", type=positive, default=5, help="timed repetitions per case (default 5)")
    p.add_argument("--codec", default="auto", help=f"sub-image codecs compared in each job, comma-separated: {', '.join(CODEC_CHOICES)} "
                   "(default auto, as render uses)")
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
    codecs = parse_codecs(args.codec)
    rows = []
    for method in COMPOSITORS:
        for (codec, mode), best in _best_repeats(comm, image, method, cam.viewport, args, codecs, modes).items():
            byte_codec, raw_rows = resolve_codec(comm, codec)
            per_rank = comm.gather(_rank_record(best, bw, mem_bw), root=0)
            sent = comm.allreduce(best["stats"].bytes_sent)
            if rank == 0:
                floor = max(r["floor_net"] + r["floor_mem"] for r in per_rank)
                shared = max(floor, sum(r["floor_net"] + r["floor_mem"] for r in per_rank) / cores)
                rows.append({"algorithm": method, "ranks": n, "codec": codec, "wait": mode, "ms": best["ms"], "bytes": sent, "floor_ms": floor,
                             "ratio": best["ms"] / floor, "shared_floor_ms": shared, "shared_ratio": best["ms"] / shared, "cores": cores,
                             "cpu_ms": max(r["cpu"] for r in per_rank), "bandwidth_MBps": bw / 1e6,
                             "bandwidth_by_wait_MBps": {m: v / 1e6 for m, v in bws.items()}, "mem_MBps": mem_bw / 1e6,
                             "mem_frame_MBps": mem_frame / 1e6, "mem_64MiB_MBps": mem_big / 1e6,
                             "codec_used": byte_codec + (" runs, raw rows to rank 0" if raw_rows else " runs"), "per_rank": per_rank})
    if rank == 0:
        Path(args.worker).write_text(json.dumps(rows))
    return 0


def _parse_list(text: str, option: str, what: str, choices) -> list[str]:
    """A comma-separated ``option`` value: each item one of ``choices``, at least one."""
    items = [v.strip() for v in text.split(",") if v.strip()]
    if not items or any(v not in choices for v in items):
        raise ConfigError(f"{option} {text!r}: use {what} from {', '.join(choices)}, comma-separated")
    return items


def parse_codecs(text: str) -> list[str]:
    from ...parallel.codec import CODEC_CHOICES

    return _parse_list(text, "--codec", "codecs", CODEC_CHOICES)


def parse_modes(text: str) -> list[str]:
    return _parse_list(text, "--wait", "wait modes", WAIT_MODES)


def _sched() -> tuple[float, float, int, int]:
    """This thread's (ms on a core, ms runnable in the run queue, voluntary and involuntary
    context switches); zeros where /proc/thread-self/schedstat is missing."""
    try:
        on, queued, _ = (int(v) for v in Path("/proc/thread-self/schedstat").read_text().split()[:3])
    except (OSError, ValueError):
        on = queued = 0
    ru = resource.getrusage(getattr(resource, "RUSAGE_THREAD", resource.RUSAGE_SELF))
    return on / 1e6, queued / 1e6, ru.ru_nvcsw, ru.ru_nivcsw


def _best_repeats(comm, image, method: str, vp, args, codecs: list[str], modes: list[str]) -> dict[tuple[str, str], dict]:
    """Per (codec, wait mode), the repeat with the smallest time (max over ranks) of composite +
    deliver to rank 0; the cases alternate repeat by repeat, so all see the same load."""
    best: dict[tuple[str, str], dict] = {}
    for _ in range(args.repeat):
        for case in [(c, m) for c in codecs for m in modes]:
            set_wait_mode(case[1])
            rec = _one_repeat(comm, image, method, vp, case[0])
            if case not in best or rec["ms"] < best[case]["ms"]:
                best[case] = rec
    return best


def _one_repeat(comm, image, method: str, vp, codec: str) -> dict:
    """One composite + deliver as the frame loop runs them: on a fresh copy of the rank's
    image that compositing may write into (the frame loop's read-back; the copy is made
    before the clock starts, as the read-back is before compositing)."""
    n, st = comm.Get_size(), FrameStats(0, comm.Get_rank())
    own = Image(image.color.copy(), image.depth.copy(), image.viewport)
    barrier(comm)
    s0, t0, c0 = _sched(), time.perf_counter(), time.thread_time()
    box = Outbox(comm, st)
    piece = composite(comm, own, method, 4, st, codec, box, owned=True)
    t1 = time.perf_counter()
    deliver(comm, piece, [(0, vp)], st, codec, final_regions(n, method, 4, vp), box, own)
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

    from ...systems import scene_kind
    from ..outputs import check_output_file

    counts = [int(v) for v in args.ranks.split(",") if v.strip()]
    modes, codecs = parse_modes(args.wait), parse_codecs(args.codec)
    if args.json is not None:  # before the jobs run, not after (walk12)
        check_output_file(args.json, "--json")
    scene_kind(args.scene)  # a missing or wrong scene: one message here, not one per rank inside the job
    console = Console(width=None if Console().is_terminal else 400)  # (a log or file: no column cut; walk7 L5)
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        for n in counts:
            out = Path(tmp) / f"bench{n}.json"
            argv = ["bench", "composite", "--worker", str(out), "--size", args.size, "--repeat", str(args.repeat), "--codec", ",".join(codecs),
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
    used = sorted({f"{r['codec']}: {r['codec_used']}" for r in results})
    table = Table(title=f"sort-last compositing + delivery to rank 0, {w}x{h}, {args.scene}, best of {args.repeat}; codecs {'; '.join(used)}")
    for col in ("algorithm", "ranks", "codec", "wait", "ms/frame", "MB moved", "p2p MB/s", "mem MB/s (frame / 64 MiB)", "floor ms", "ratio to floor",
                "shared-core floor ms", "ratio to it", "CPU ms"):
        table.add_column(col, justify="right", overflow="fold")
    for r in results:
        wait = f"{r['wait']} *" if r["wait"] == default_wait(r["ranks"]) else r["wait"]
        table.add_row(r["algorithm"], str(r["ranks"]), r["codec"], wait, f"{r['ms']:.2f}", f"{r['bytes'] / 1e6:.2f}", f"{r['bandwidth_MBps']:.0f}",
                      f"{r['mem_frame_MBps']:.0f} / {r['mem_64MiB_MBps']:.0f}", f"{r['floor_ms']:.2f}", f"{r['ratio']:.2f}",
                      f"{r['shared_floor_ms']:.2f}", f"{r['shared_ratio']:.2f}", f"{r['cpu_ms']:.1f}")
    console.print(table)
    console.print("floor = the bytes a rank receives ÷ the point-to-point bandwidth + the bytes it must read and write ÷ the memory "
                  "bandwidth, both measured in this job with every rank working; a case's floor is its slowest rank's. ratio to floor = "
                  "ms/frame ÷ floor (issue 20's target: within 3×). shared-core floor: at least the sum of the ranks' floors ÷ the "
                  f"cores ({local_cores()}). * = the wait mode render uses at that rank count here (sleep when ranks outnumber the "
                  f"cores, else poll; {WAIT_ENV_VAR} overrides).")
    _print_ranks(console, results)


def default_wait(ranks: int) -> str:
    """The wait mode a ``render --ranks N`` job on this machine uses: what the launcher's
    :func:`~massview.parallel.runtime.launch_env` gives its ranks (the environment's own
    setting first), and the ranks' default where it gives none."""
    return launch_env(ranks, dict(os.environ)).get(WAIT_ENV_VAR) or "poll"


def _print_ranks(console, results: list[dict]) -> None:
    from rich.table import Table

    pieces = Table(title="per rank, best repeat: where the time goes (ms) against the floor's two terms (ms); work / polling / run queue / "
                         "asleep from the main thread's schedstat; context switches voluntary / involuntary")
    for col in ("algorithm", "ranks", "codec", "wait", "rank", "ms", "compositing", "delivery", *PIECES, "other", "work", "polling", "run queue",
                "asleep", "csw v/i", "MB in", "MB touched", "floor net", "floor mem"):
        pieces.add_column(col, justify="right", overflow="fold")
    for r in results:
        for p in r["per_rank"]:
            pieces.add_row(r["algorithm"], str(r["ranks"]), r["codec"], r["wait"], str(p["rank"]), f"{p['ms']:.2f}", f"{p['composite']:.2f}",
                           f"{p['deliver']:.2f}", *(f"{p[k]:.2f}" for k in PIECES), f"{p['other']:.2f}",
                           *(f"{p[k]:.2f}" for k in ("work", "polling", "runqueue", "asleep")), f"{p['vcsw']}/{p['ivcsw']}",
                           f"{p['recv_bytes'] / 1e6:.2f}", f"{p['touched_bytes'] / 1e6:.1f}", f"{p['floor_net']:.2f}", f"{p['floor_mem']:.2f}")
    console.print(pieces)
