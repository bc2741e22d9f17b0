"""T1's whole LOD stage per frame, old against new, and sort-first LOD per tile.

``massview bench lod [--store STORE]``: one process, one rank, real GL pool and block cache,
everything resident (warmed with complete loading first, then timed with nothing loading).

Part 1: for each target front size (default 5 k, 20 k and 80 k patches) τ is bisected on the
``orbit`` camera so the cut reaches the target, and the whole LOD stage of each frame along a
stretch of the path — shading wants, uploads, residency agreement, the cut, front bookkeeping,
culling and the task's share — is timed for the stage as it was before issue 20
(:class:`~massview.app.bench.lod_baseline.BaselineStage`) and for today's, alternating frame by
frame so both see the same load. Printed: front patches, ms per frame of each, their ratio.

Part 2: sort-first on ``--tiles`` ranks (``--layout``): each rank's LOD stage restricted to its
tile (what each rank of a real ``--ranks N`` run does) against the whole-frame LOD stage, on
the same cameras in the same process. Printed per target: whole-frame ms, each rank's ms, the
slowest rank's ratio to the whole frame, and the patches each rank's cut holds.

Part 3, with ``--against SRC`` (another checkout's ``src/``, e.g. the commit before a change,
unpacked with ``git archive``): that checkout's whole LOD stage is imported under another
package name and timed beside this one's on the same cameras, alternating, best of ``--repeat``
(its compiled LOD kernels, where it has them, loaded first as this checkout's are);
printed per target: ms and CPU ms of each, their ratio, and whether the two fronts and task
shares are identical.

The default store is the demo terrain (``~/.cache/massview/demo_terrain_4097.zarr``, generated
as ``massview demo`` does when missing). Timings on a shared machine are noisy: compare the
ratios, which are measured in one run.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np

from ...core.config import RenderConfig, parse_size
from ...core.errors import ConfigError
from ...core.paths import load_path
from ...core.stats import FrameStats
from ...core.task import Task
from .args import int_list, positive, size, terrain_store

__all__ = ["add_arguments", "run"]


def add_arguments(p) -> None:
    p.add_argument("--store", default=None, help="terrain store (default: the demo terrain, generated when missing)")
    p.add_argument("--size", type=size, default="1280x720")
    p.add_argument("--frames", type=positive, default=8, help="timed frames per target")
    p.add_argument("--targets", type=int_list(1, example="5000,20000"), default="5000,20000,80000", help="front sizes (patches) to reach")
    p.add_argument("--tiles", type=positive, default=4, help="sort-first ranks for part 2")
    p.add_argument("--layout", default="horizontal", choices=("horizontal", "vertical", "grid"))
    p.add_argument("--repeat", type=positive, default=3, help="timings per frame (the best is kept)")
    p.add_argument("--against", default=None, metavar="SRC",
                   help="another checkout's src/ directory (e.g. `git archive 8e7be8a src | tar -x -C /tmp/b` gives "
                        "/tmp/b/src): its LOD stage is timed beside this one, alternating frame by frame in this process, "
                        "and its output (the front and the task's share) checked equal")


def _store(arg) -> Path:
    if arg:
        return terrain_store(arg, "--store")
    store = Path(os.path.expanduser(os.environ.get("MASSVIEW_CACHE", "~/.cache/massview"))) / "demo_terrain_4097.zarr"
    if not (store / "zarr.json").exists():
        from ...data.terrain import prepare_terrain
        from ...data.terrain.synthetic import SyntheticSource

        print(f"generating the demo terrain into {store} (once) ...", flush=True)
        prepare_terrain(SyntheticSource(4097, 1), store, vertical_scale=2.5, overwrite=True)
    return store


class _Rank:
    """Rank ``r`` of ``n`` for an in-process stage: collectives return this rank's own data
    (every tile is timed in turn on one process)."""

    def __init__(self, r: int, n: int):
        self.r, self.n = r, n

    def Get_rank(self):
        return self.r

    def Get_size(self):
        return self.n

    def Allreduce(self, mine, out, op=None):
        out[...] = mine

    def allreduce(self, v, op=None):
        return v


def _tau_for(h, camera, target: int) -> float:
    """τ (log bisection) whose cut on ``camera`` holds ~``target`` patches."""
    from ...lod.kpatch import select_front

    lo, hi = 1e-3, 64.0
    for _ in range(22):
        mid = (lo * hi) ** 0.5
        n = len(select_front(h, camera, mid))
        if abs(n - target) < 0.02 * target:
            return mid
        lo, hi = (mid, hi) if n > target else (lo, mid)
    return (lo * hi) ** 0.5


def _best(fn, repeat: int) -> tuple[float, float]:
    """Best (wall ms, main-thread CPU ms) of ``repeat`` calls: on a loaded machine the CPU
    time is what the stage would take alone."""
    wall = cpu = float("inf")
    for _ in range(repeat):
        t0, c0 = time.perf_counter(), time.thread_time()
        fn()
        wall, cpu = min(wall, time.perf_counter() - t0), min(cpu, time.thread_time() - c0)
    return wall * 1e3, cpu * 1e3


def _new_stage(sysm, comm, cam, cfg, nranks: int):
    def go():
        sysm.prepare_frame(comm, cam, cfg, FrameStats(0, 0))
        task = sysm.plan(cam, cfg, nranks)[comm.Get_rank()]
        idx = sysm.select(task, cam, cfg)
        if len(idx) != len(sysm.front):  # as TerrainSystem.render: the whole front is drawn as it is
            sysm.front.take(idx)
    return go


def _old_stage(old, comm, cam, cfg):
    def go():
        old.prepare_frame(comm, cam, cfg)
        old.select(Task(0, cam.viewport), cam)
    return go


def _against(src: str, store: Path):
    """``src``'s massview package imported under another name (a copy of it named
    ``massview_against``: its imports are relative), for timing two versions in one process."""
    import atexit
    import importlib
    import shutil
    import sys
    import tempfile

    pkg = Path(src) / "massview"
    if not (pkg / "systems" / "terrain.py").exists():
        raise SystemExit(f"--against {src}: no massview package there (give a checkout's src/ directory)")
    tmp = Path(tempfile.mkdtemp(prefix="massview_against_"))
    atexit.register(shutil.rmtree, tmp, ignore_errors=True)  # (its modules stay imported until the process ends)
    shutil.copytree(pkg, tmp / "massview_against", ignore=shutil.ignore_patterns("__pycache__"))
    sys.path.insert(0, str(tmp))
    mods = (importlib.import_module("massview_against.systems.terrain"), importlib.import_module("massview_against.core.config"),
            importlib.import_module("massview_against.core.stats"))
    try:  # before anything is compiled or timed: a store of a newer format than that checkout reads is a clear error
        importlib.import_module("massview_against.data.terrain").TerrainStore(store)
    except Exception as e:  # that checkout's own StoreError (another class than ours)
        raise ConfigError(f"--against {src}: that checkout cannot read {store} ({e}); prepare a store with it "
                          f"(PYTHONPATH={src} python -m massview prepare terrain DEM -o STORE) and pass it with --store") from None
    try:  # its compiled LOD kernels, where it has them: loaded before any timed frame, as ours are (a copy compiles them afresh)
        kernels = importlib.import_module("massview_against.lod.kernels")
    except ImportError:  # a checkout from before the compiled stage
        kernels = None
    env = getattr(kernels, "LOD_KERNEL_ENV", None)
    if env and hasattr(kernels, "load_lod_kernels") and os.environ.get(env, "auto") == "auto" and kernels.lod_kernels() is None:
        print(f"--against {src}: loading (compiling) its LOD kernels before timing ...", flush=True)
        kernels.load_lod_kernels(wait=True)
    return mods


def _same_stage(a, b, cam, cfg, ocfg) -> bool:
    fa, fb = a.front, b.front
    cols = (*a.front.FIELDS, "code")
    return (all(np.array_equal(getattr(fa, k), getattr(fb, k)) for k in cols) and fa.deferred == fb.deferred
            and np.array_equal(a.select(a.plan(cam, cfg, 1)[0], cam, cfg), b.select(b.plan(cam, ocfg, 1)[0], cam, ocfg)))


def _cameras(path, bounds, at: float, frames: int, w: int, h: int):
    p = load_path(path, *bounds)
    return [p.camera(min(1.0, at + 0.004 * i), w, h) for i in range(frames)]


def run(args) -> int:
    from rich.console import Console
    from rich.table import Table

    from ...lod.kernels import LOD_KERNEL_ENV, load_lod_kernels, lod_kernels
    from ...parallel.runtime import self_comm
    from ...systems.terrain import TerrainSystem
    from .lod_baseline import BaselineStage

    t_start = time.perf_counter()
    if lod_kernels() is None and os.environ.get(LOD_KERNEL_ENV, "auto") == "auto":
        load_lod_kernels(wait=True)  # no timed frame walks with numpy while the compiled kernels load

    console = Console(width=None if Console().is_terminal else 160)
    w, hh = parse_size(args.size)
    store = _store(args.store)
    other = _against(args.against, store) if args.against else None
    sysm = TerrainSystem(store, cache_bytes=1 << 30, gpu_bytes=1 << 30, loading="complete")
    old = BaselineStage(sysm)
    before = other[0].TerrainSystem(store, cache_bytes=1 << 30, gpu_bytes=1 << 30, loading="complete") if other else None
    t3 = Table(title=f"whole LOD stage per frame, --against {args.against} (before) vs this checkout (now), alternating, one rank")
    for c in ("target", "front patches", "before ms", "now ms", "now ÷ before", "before CPU ms", "now CPU ms", "now ÷ before CPU", "output"):
        t3.add_column(c, justify="right")
    comm = self_comm()
    targets = [int(v) for v in args.targets.split(",") if v.strip()]
    t1 = Table(title=f"whole LOD stage per frame, old vs new: {store.name}, {w}x{hh}, orbit, {args.frames} frames, one rank")
    for c in ("target", "τ", "front patches", "old ms", "new ms", "old ÷ new", "old CPU ms", "new CPU ms", "old ÷ new CPU", "visible"):
        t1.add_column(c, justify="right")
    t2 = Table(title=f"sort-first {args.layout} on {args.tiles} ranks: each rank's LOD stage (own tile) vs the whole frame's")
    for c in ("target", "whole-frame ms (CPU)", "per rank ms (CPU)", "slowest ÷ whole", "whole patches", "per rank patches"):
        t2.add_column(c, justify="right")
    try:
        for target in targets:
            cams = _cameras("orbit", sysm.bounds, 0.5, args.frames, w, hh)
            tau = _tau_for(sysm.h, cams[0], target)
            cfg = RenderConfig(width=w, height=hh, tau=tau, loading="complete")
            tcfg = RenderConfig(width=w, height=hh, tau=tau, loading="complete", decomposition=f"sort-first:{args.layout}")
            sysm.loading = "complete"
            for cam in cams:  # warm: every block these views need, for the whole frame and for the tiles
                sysm.prepare_frame(comm, cam, cfg, FrameStats(0, 0))
            sysm.loading = "async"
            if before is not None:
                ocfg = other[1].RenderConfig(width=w, height=hh, tau=tau, loading="complete")
                before.loading = "complete"
                for cam in cams:
                    before.prepare_frame(comm, cam, ocfg, other[2].FrameStats(0, 0))
                before.loading = "async"
                b_ms, n_ms, same = [], [], True
                for cam in cams:
                    fb, fn = _new_stage(before, comm, cam, ocfg, 1), _new_stage(sysm, comm, cam, cfg, 1)
                    for _ in range(3):  # alternating, best of --repeat each time
                        b_ms.append(_best(fb, args.repeat))
                        n_ms.append(_best(fn, args.repeat))
                    same = same and _same_stage(sysm, before, cam, cfg, ocfg)
                (bw, bc), (nw, nc) = np.mean(b_ms, axis=0), np.mean(n_ms, axis=0)
                t3.add_row(f"{target / 1e3:.0f} k", f"{len(sysm.front)}", f"{bw:.2f}", f"{nw:.2f}", f"{nw / bw:.3f}", f"{bc:.2f}",
                           f"{nc:.2f}", f"{nc / bc:.3f}", "identical" if same else "DIFFERENT")
            old_ms, new_ms, sizes, vis, whole, ranks = [], [], [], [], [], [[] for _ in range(args.tiles)]
            rank_sizes = [[] for _ in range(args.tiles)]
            for cam in cams:
                old_ms.append(_best(_old_stage(old, comm, cam, cfg), args.repeat))
                new_ms.append(_best(_new_stage(sysm, comm, cam, cfg, 1), args.repeat))
                sizes.append(len(sysm.front))
                vis.append(len(sysm.select(Task(0, cam.viewport), cam, cfg)))
                whole.append(new_ms[-1])
                for r in range(args.tiles):
                    ranks[r].append(_best(_new_stage(sysm, _Rank(r, args.tiles), cam, tcfg, args.tiles), args.repeat))
                    rank_sizes[r].append(len(sysm.front))
            (o, oc), (n, nc) = np.mean(old_ms, axis=0), np.mean(new_ms, axis=0)
            t1.add_row(f"{target / 1e3:.0f} k", f"{tau:.3g}", f"{np.mean(sizes):.0f}", f"{o:.2f}", f"{n:.2f}", f"{o / n:.1f}×",
                       f"{oc:.2f}", f"{nc:.2f}", f"{oc / nc:.1f}×", f"{np.mean(vis):.0f}")
            per = [np.mean(x, axis=0) for x in ranks]
            wm = np.mean(whole, axis=0)
            t2.add_row(f"{target / 1e3:.0f} k", f"{wm[0]:.2f} ({wm[1]:.2f})", ", ".join(f"{v[0]:.2f} ({v[1]:.2f})" for v in per),
                       f"{max(v[0] for v in per) / wm[0]:.2f} ({max(v[1] for v in per) / wm[1]:.2f})", f"{np.mean(sizes):.0f}",
                       ", ".join(f"{np.mean(x):.0f}" for x in rank_sizes))
            console.print(f"target {target}: τ = {tau:.3g}, old {o:.2f} ms, new {n:.2f} ms per frame (CPU {oc:.2f}, {nc:.2f})",
                          highlight=False)
    finally:
        sysm.close()
        if before is not None:
            before.close()
    console.print(t1)
    console.print(t2)
    if before is not None:
        console.print(t3)
    console.print(f"bench lod: {time.perf_counter() - t_start:.0f} s (timings taken best of {args.repeat} per frame; "
                  "compare ratios, measured in the same run)", highlight=False)
    return 0
