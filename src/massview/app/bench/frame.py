"""The whole terrain frame per stage, against each stage's floor, for 1–4 ranks.

``massview bench frame [STORE]`` renders the demo flyover (the 4097² synthetic terrain with
heights ×2.5 that ``massview demo`` caches in ``~/.cache/massview``, generated into
``--workdir`` when missing) at ``--size`` on each rank count, twice: with the synchronous frame
loop (per-stage times) and with the pipelined one (throughput). Each job first measures, on all
its ranks at once — the conditions the frames run under —

* the draw rate of one plain mesh (a coarse level of the same store as one VBO and one draw
  call, the way VTK draws a surface) with the same camera: triangles/s;
* the memory bandwidth (every rank copying at once; the higher of a frame-sized and a 64 MiB copy,
  as in ``bench composite``) and the point-to-point bandwidth.

Per stage, the floor of a rank (the slowest rank's floor is the stage's floor) is:

* ``lod``: the front's arrays (13 int64 per patch) read and written once ÷ memory bandwidth
  (a loose bound: the LOD has no bandwidth-bound core);
* ``draw``: the triangles it drew ÷ the plain-mesh rate;
* ``readback``: its pixels (8 B each) ÷ memory bandwidth;
* ``encode``/``composite``: the bytes those kernels must touch (``touched_*`` counters) ÷
  memory bandwidth; ``transfer``: the bytes it received ÷ point-to-point bandwidth;
* ``finish``: the system's display-side touch of the final tile (terrain: the sky painted on its
  background pixels), its pixels read and written once (8 B each) ÷ memory bandwidth;
* ``other``: the rest of the frame (the camera and plan broadcasts, the LOD's bookkeeping
  outside its ``lod`` stage); no floor.

Printed: per rank count, each stage's mean (over frames, slowest rank) and its ratio to the
floor, the frame time, the share of the frame that is not drawing, pipelined vs synchronous
throughput and latency, and how busy the cores were in each loop (CPU time of all threads of
all ranks ÷ wall time × cores: overlapping frames can only fill cores the synchronous loop
leaves idle); the first job also probes how fast a compositing thread runs while the main
thread draws (the GIL during GL calls, see :func:`_gil_probe`). ``--png`` draws the stage breakdown. Ranks share the
cores with llvmpipe's raster threads: ``--lp-threads`` sets ``LP_NUM_THREADS`` per case
(``auto``: :func:`massview.parallel.runtime.raster_threads`, the launcher's default; ``default``:
Mesa's own choice, one thread per CPU in every rank). Nothing here asserts a time.
"""

from __future__ import annotations

import json
import os
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from ...core.config import RenderConfig, parse_size
from ...core.paths import load_path
from ...core.stats import FrameStats
from ...parallel.exchange import max_over_ranks, measure_bandwidth, measure_memory_bandwidth
from ...parallel.runtime import local_cores, raster_threads, relaunch, world
from .args import int_list, positive, size, terrain_store

__all__ = ["add_arguments", "run", "worker", "STAGES"]

STAGES = ("lod", "draw", "readback", "encode", "transfer", "composite", "finish", "other")
_TIMED = STAGES[:-1]  # "other": the rest of the frame (broadcasts, LOD bookkeeping outside "lod")
_FRONT_BYTES = 13 * 8  # the front's per-patch arrays (lod/kpatch.py Front), int64 each


def add_arguments(p) -> None:
    import argparse

    p.add_argument("store", nargs="?", default=None, help="terrain store (default: the demo's 4097² terrain)")
    p.add_argument("--ranks", type=int_list(1), default="1,2,3,4", help="rank counts, comma-separated (default 1,2,3,4)")
    p.add_argument("--size", type=size, default="1280x1024")
    p.add_argument("--frames", type=positive, default=8, help="timed frames per loop (default 8)")
    p.add_argument("--decomposition", default="sort-last:kpatch")
    p.add_argument("--compositor", default="binary-swap")
    p.add_argument("--codec", default="auto", help="sub-image codec, as render's --codec (default auto)")
    p.add_argument("--lp-threads", type=int_list(0, extra=("auto", "default"), example="auto,2"), default="auto", help="LP_NUM_THREADS per case, comma-separated: auto, default or a number")
    p.add_argument("--workdir", default="out/bench", help="where the demo terrain is generated when it is not cached")
    p.add_argument("--png", type=Path, default=None, help="write the stage breakdown plot here")
    p.add_argument("--worker", type=Path, default=None, help=argparse.SUPPRESS)
    p.add_argument("--gil-probe", action="store_true", help=argparse.SUPPRESS)


def demo_store(workdir: str) -> Path:
    """The demo's cached 4097² terrain if complete, else one generated (once) into ``workdir``."""
    cached = Path(os.path.expanduser("~/.cache/massview/demo_terrain_4097.zarr"))
    if (cached / "zarr.json").exists() and _complete(cached):
        return cached
    store = Path(workdir) / "demo_terrain_4097.zarr"
    if not ((store / "zarr.json").exists() and _complete(store)):
        from ...data.terrain import prepare_terrain
        from ...data.terrain.synthetic import SyntheticSource

        store.parent.mkdir(parents=True, exist_ok=True)
        prepare_terrain(SyntheticSource(4097, 1), store, vertical_scale=2.5, overwrite=True)
    return store


def _complete(store: Path) -> bool:
    try:
        from ...data.terrain import TerrainStore

        TerrainStore(store)
        return True
    except Exception:  # noqa: BLE001 - an unfinished or foreign store: regenerate ours
        return False


def _plain_rate(system, camera, max_side: int = 1025) -> float:
    """Triangles/s of one plain mesh (the coarsest level with ≤ ``max_side`` samples a side,
    one VBO, one draw) in this rank's GL context with ``camera``; best of 3."""
    from ...render.terrain import PlainMeshRenderer

    st, lay = system.store, system.lay
    lv = next(lv for lv in range(lay.levels) if lay.blocks(lv) * (lay.M - 1) + 1 <= max_side)
    nb, m = lay.blocks(lv), lay.M - 1
    heights = np.empty((nb * m + 1, nb * m + 1), np.float32)
    for i in range(nb):
        for j in range(nb):
            heights[i * m: i * m + m + 1, j * m: j * m + m + 1] = st.get_block(lv, i, j)
    dx, dy = st.spacing
    ctx, _, _, view = system.renderers()
    plain = PlainMeshRenderer(ctx, heights, None, (dx * 2**lv, dy * 2**lv), st.vertical_scale)
    best = 0.0
    for _ in range(3):
        s = FrameStats(-1, 0)
        view.render(camera, camera.viewport, plain.draw, s)
        best = max(best, plain.triangles / (s.times_ms["draw"] / 1e3))
    plain.release()
    return best


def _floors(st: FrameStats, pixels: int, bw: float, mem: float, rate: float) -> dict:
    c = st.counters
    return {"lod": 2 * c.get("front_patches", 0) * _FRONT_BYTES / mem, "draw": st.triangles / rate,
            "readback": 8 * pixels / mem, "encode": c.get("touched_encode", 0) / mem,
            "transfer": st.bytes_recv / bw if bw else 0.0, "composite": c.get("touched_composite", 0) / mem,
            "finish": 8 * c.get("finished_pixels", 0) / mem, "other": 0.0}


def _loop(comm, system, cfg, cams, pixels, bw, mem, rate) -> dict:
    from ...systems.frameloop import render_frames

    stages, floors, totals, tris = [], [], [], []
    comm.Barrier()
    t0, cpu0 = time.perf_counter(), time.process_time()
    for res in render_frames(comm, system, cfg, cams):
        st = res.stats
        mine = [st.times_ms.get(s, 0.0) / 1e3 for s in _TIMED]
        mine.append(max(0.0, st.times_ms["total"] / 1e3 - sum(mine)))
        stages.append([max_over_ranks(comm, v) for v in mine])
        floors.append([max_over_ranks(comm, v) for v in _floors(st, pixels, bw, mem, rate).values()])
        totals.append(max_over_ranks(comm, st.times_ms["total"] / 1e3))
        tris.append(comm.allreduce(st.triangles))
    wall = max_over_ranks(comm, time.perf_counter() - t0)
    cpu = comm.allreduce(time.process_time() - cpu0)  # every thread of every rank, llvmpipe's raster threads included
    return {"stage_ms": (np.mean(stages, 0) * 1e3).tolist(), "floor_ms": (np.mean(floors, 0) * 1e3).tolist(),
            "latency_ms": float(np.mean(totals) * 1e3), "throughput_fps": cfg.frames / wall, "triangles": float(np.mean(tris)),
            "busy": cpu / (wall * local_cores())}


def _gil_probe(system, cams, cfg, seconds: float = 0.6) -> float:
    """How fast a second thread runs Python + numpy compositing work (encode the top band of a
    rendered frame and merge it into a copy of itself) while this thread draws frames, relative
    to while this thread sleeps: what the pipelined loop's communication thread gets during a
    draw. A GL call that keeps the GIL (moderngl's draw calls) stops that thread for its
    whole duration; the wait for llvmpipe's raster threads (``render.context.finish``) does not. Best of three
    alternating windows each (a shared machine's load comes and goes)."""
    from ...core.image import Image
    from ...core.task import Task
    from ...parallel.composite import split_rows

    img = system.render(Task(0, cams[0].viewport), cams[0], cfg, FrameStats(-1, 0))
    top = split_rows(img.viewport, 2)[0]
    acc = Image(img.color[: top.h].copy(), img.depth[: top.h].copy(), top)
    alone = drawing = 0.0
    for _ in range(3):
        alone = max(alone, _probe_rate(system, cams, cfg, img, acc, False, seconds))
        drawing = max(drawing, _probe_rate(system, cams, cfg, img, acc, True, seconds))
    return drawing / alone if alone else float("nan")


def _probe_rate(system, cams, cfg, img, acc, draw: bool, seconds: float) -> float:
    """Work items/s of the probe's thread while this thread draws (``draw``) or sleeps."""
    import threading

    from ...core.task import Task
    from ...parallel.codec import encode_region, merge_into

    stop, done = threading.Event(), [0]

    def work():
        while not stop.is_set():
            merge_into(acc, encode_region(img, acc.viewport, "blosc2"), front=False)
            done[0] += 1

    thread = threading.Thread(target=work, daemon=True)
    t0 = time.perf_counter()
    thread.start()
    f = 0
    while time.perf_counter() - t0 < seconds:
        if draw:
            cam = cams[f % len(cams)]
            system.render(Task(0, cam.viewport), cam, cfg, FrameStats(-1, 0))
            f += 1
        else:
            time.sleep(0.01)
    stop.set()
    thread.join()
    return done[0] / (time.perf_counter() - t0)


def worker(args) -> int:
    from ...systems import open_system
    from ...systems.frameloop import render_frame

    comm = world()
    rank, n = comm.Get_rank(), comm.Get_size()
    w, h = parse_size(args.size)
    cfg = RenderConfig(width=w, height=h, frames=args.frames, path="flyover", decomposition=args.decomposition,
                       compositor=args.compositor, codec=args.codec, loading="complete")
    system = open_system(args.store, cfg)
    cams = load_path("flyover", *system.bounds).cameras(args.frames, w, h)
    for f in range(args.frames):  # warm up along the whole path: loads, GL buffers, caches
        render_frame(comm, system, cfg, cams[f] if rank == 0 else None, -1)
    rate = _plain_rate(system, cams[0])
    bw = measure_bandwidth(comm)
    mem = max(measure_memory_bandwidth(comm, 8 * w * h), measure_memory_bandwidth(comm))  # as bench composite
    comm.Barrier()
    gil = _gil_probe(system, cams, cfg) if args.gil_probe and rank == 0 else None
    comm.Barrier()
    pixels = w * h  # sort-last: every rank reads back the full frame; sort-first: its tile
    if not args.decomposition.startswith("sort-last"):
        pixels = -(-w * h // n)
    out = {"ranks": n, "lp_threads": os.environ.get("LP_NUM_THREADS", "Mesa default"), "plain_Mtri_s": rate / 1e6,
           "p2p_MBps": bw / 1e6, "mem_MBps": mem / 1e6, "gil_probe": gil}
    out["sync"] = _loop(comm, system, replace(cfg, pipeline="off"), cams if rank == 0 else None, pixels, bw, mem, rate)
    out["pipelined"] = _loop(comm, system, replace(cfg, pipeline="on"), cams if rank == 0 else None, pixels, bw, mem, rate)
    system.close()
    if rank == 0:
        Path(args.worker).write_text(json.dumps(out))
    return 0


def _cases(args) -> list[tuple[int, str]]:
    counts = [int(v) for v in args.ranks.split(",") if v.strip()]
    return [(n, lp.strip()) for n in counts for lp in args.lp_threads.split(",") if lp.strip()]


def _launch(args, store: Path, n: int, lp: str, tmp: str, probe: bool = False) -> dict | None:
    out = Path(tmp) / f"frame{n}_{lp}.json"
    argv = ["bench", "frame", str(store), "--worker", str(out), "--size", args.size, "--frames", str(args.frames),
            "--decomposition", args.decomposition, "--compositor", args.compositor, "--codec", args.codec,
            *(["--gil-probe"] if probe else [])]
    saved = os.environ.get("LP_NUM_THREADS")
    # "default": Mesa's own choice, one raster thread per CPU in every rank (set explicitly,
    # since the launcher would otherwise put its own default in)
    threads = raster_threads(n) if lp == "auto" else (os.cpu_count() or 1 if lp == "default" else int(lp))
    os.environ["LP_NUM_THREADS"] = str(os.cpu_count() or 1 if threads is None else threads)
    try:
        rc = relaunch(argv, n)
    finally:
        if saved is None:
            os.environ.pop("LP_NUM_THREADS", None)
        else:
            os.environ["LP_NUM_THREADS"] = saved
    return json.loads(out.read_text()) if rc == 0 else None


def run(args) -> int:
    if args.worker is not None:
        return worker(args)
    from rich.console import Console

    console = Console(width=None if Console().is_terminal else 400)  # (a log or file: no column cut; walk7 L5)
    store = terrain_store(args.store) if args.store else demo_store(args.workdir)
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        for i, (n, lp) in enumerate(_cases(args)):
            console.print(f"[dim]{n} rank(s), LP_NUM_THREADS {lp} ...[/]")
            r = _launch(args, store, n, lp, tmp, probe=i == 0)
            if r is None:
                console.print(f"[red]the {n}-rank job failed[/]")
                return 1
            results.append(r)
    _print(console, results, args, store)
    if args.png:
        from .frame_plot import plot_stages

        plot_stages(results, args.png, f"{store.name}, {args.size}, {args.decomposition}, {args.compositor}")
        console.print(f"stage breakdown: {args.png}")
    return 0


def _print(console, results, args, store) -> None:
    from rich.table import Table

    t = Table(title=f"frame per stage vs floor (ms, slowest rank, mean of {args.frames} frames): {store.name}, {args.size}, "
                    f"{args.decomposition}, {args.compositor}, codec {args.codec}")
    for c in ("ranks", "LP thr", "Mtri/s plain", *STAGES, "frame ms", "floor ms", "not drawing", "pipelined fps", "sync fps", "latency ms on/off",
              "cores busy sync/pipe"):
        t.add_column(c, justify="right", overflow="fold")
    for r in results:
        s, p = r["sync"], r["pipelined"]
        cells = [f"{m:.1f} ({m / f:.1f}×)" if f > 0 else f"{m:.1f}" for m, f in zip(s["stage_ms"], s["floor_ms"])]
        not_drawing = 1 - s["stage_ms"][1] / s["latency_ms"]
        t.add_row(str(r["ranks"]), r["lp_threads"], f"{r['plain_Mtri_s']:.1f}", *cells, f"{s['latency_ms']:.0f}",
                  f"{sum(s['floor_ms']):.1f}", f"{not_drawing:.0%}", f"{p['throughput_fps']:.2f} ({p['throughput_fps'] / s['throughput_fps']:.2f}×)",
                  f"{s['throughput_fps']:.2f}", f"{p['latency_ms']:.0f} / {s['latency_ms']:.0f}", f"{s['busy']:.0%} / {p['busy']:.0%}")
    console.print(t)
    console.print("each stage: its mean ms (slowest rank) and, in brackets, its ratio to its floor — lod: the front's arrays read and "
                  "written once ÷ memory bandwidth (a loose bound: the LOD is not bandwidth-bound, so its ratio is large); draw: its "
                  "triangles ÷ the plain-mesh rate (Mtri/s plain); readback, encode, composite, finish: the bytes they must touch ÷ "
                  "memory bandwidth; transfer: the bytes received ÷ point-to-point bandwidth (it includes waiting for a peer's draw). "
                  "not drawing: 1 − draw ÷ frame (issue 20: at most 30 % at 2 ranks).")
    console.print("cores busy: CPU time of every thread of every rank (llvmpipe's raster threads included) ÷ (wall time × cores); "
                  "a pipelined loop can raise throughput by at most 1 ÷ the synchronous loop's share.")
    probe = next((r["gil_probe"] for r in results if r.get("gil_probe") is not None), None)
    if probe is not None:
        console.print(f"GIL probe: a compositing thread runs at {probe:.2f}× its own speed while the main thread draws "
                      "(moderngl keeps the GIL through its draw calls; the wait for llvmpipe's raster threads goes through "
                      "render.context.finish, a glFinish that releases it; the rest is the cores the raster threads take).")
