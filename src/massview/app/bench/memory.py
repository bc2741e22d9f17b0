"""Peak RSS per rank flying a terrain, against its budgets and an empty GL rank (issue 20).

``massview bench memory STORE`` (default: the demo's 4097² terrain; the issue's case is the
32769² store) measures, in one run, on ``--ranks`` local ranks (default 4):

* ``baseline``: an *empty GL rank* — the same imports, MPI, a headless GL context and one
  framebuffer of ``--size`` — each rank's ``VmHWM``: what any rank costs on this machine;
* ``fly``: for each path of ``--paths`` (default ``zoom,flyover``), the real command
  ``massview render STORE --ranks N --path P --frames F`` with default options (or the given
  ``--cache-mb``/``--gpu-mb``), each rank's ``VmHWM`` and the parent's (the process that
  relaunched itself under mpiexec), written at exit (``MASSVIEW_PEAK_RSS_FILE``);
* ``account``: the same flight in a job that opens the system step by step and records each
  rank's ``VmRSS`` after every step (store, LOD arrays and K-patch hierarchy, GL context +
  block pool + renderers, first frame, all frames) and what each budgeted part holds: the GL
  pool's bytes (its budget, counted as GL stores them), the RAM cache's peak bytes (≤ its
  budget), the hierarchy's arrays.

Printed per path: each rank's peak, the empty-rank baseline, the GL pool and the RAM cache
peak (with their budgets), the hierarchy, and the rest no budget covers (peak − baseline −
pool − cache peak); the worst case the budgets allow (baseline + both budgets + the rest);
and the parent's peak. Under ``llvmpipe`` the GL pool lives in the rank's own memory, so it
counts in RSS. Nothing is asserted.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
import tempfile
from pathlib import Path

import numpy as np

from ...core.errors import ConfigError
from ...core.paths import BUILTIN_PATHS
from .args import choices_list, positive, size, terrain_store
from .child import run_measured

__all__ = ["add_arguments", "run", "worker", "status_mib", "held_bytes"]

GIB = 1024


def add_arguments(p) -> None:
    p.add_argument("store", nargs="?", default=None, help="terrain store (default: the demo's 4097² terrain)")
    p.add_argument("--ranks", type=positive, default=4, help="local ranks (default 4)")
    p.add_argument("--paths", default="zoom,flyover", help="camera paths, comma-separated (default zoom,flyover)")
    p.add_argument("--frames", type=positive, default=8, help="frames per path (default 8)")
    p.add_argument("--size", type=size, default="1280x1024")
    p.add_argument("--cache-mb", type=int, default=None, help="RAM cache budget per rank (default: render's default)")
    p.add_argument("--gpu-mb", type=int, default=None, help="GL pool budget per rank (default: render's default)")
    p.add_argument("--sections", type=choices_list(("baseline", "fly", "account")), default="baseline,fly,account", help="baseline, fly, account (comma-separated)")
    p.add_argument("--workdir", default="out/bench", help="where the demo terrain is generated when it is not cached")
    p.add_argument("--worker", type=Path, default=None, help=argparse.SUPPRESS)
    p.add_argument("--probe", default=None, help=argparse.SUPPRESS)


def status_mib(*keys: str) -> dict[str, float]:
    """Fields of /proc/self/status in MiB (``VmRSS``, ``VmHWM``, ...); {} where /proc is missing."""
    out = {}
    try:
        with open("/proc/self/status") as f:
            for line in f:
                k, _, v = line.partition(":")
                if k in keys:
                    out[k] = int(v.split()[0]) / 1024
    except OSError:
        pass
    return out


def held_bytes(obj, seen=None) -> int:
    """Bytes of the numpy arrays reachable from ``obj`` through attributes, lists, tuples, dicts
    and lazy columns (``src``), each base array counted once."""
    seen = set() if seen is None else seen
    if isinstance(obj, np.ndarray):
        base = obj
        while isinstance(base.base, np.ndarray):
            base = base.base
        if id(base) in seen:
            return 0
        seen.add(id(base))
        return base.nbytes
    if isinstance(obj, (list, tuple)):
        return sum(held_bytes(v, seen) for v in obj)
    if isinstance(obj, dict):
        return sum(held_bytes(v, seen) for v in obj.values())
    slots = getattr(type(obj), "__slots__", ())
    fields = {k: getattr(obj, k) for k in slots if hasattr(obj, k)}
    fields.update(getattr(obj, "__dict__", {}))
    if not fields or isinstance(obj, type) or id(obj) in seen:
        return 0
    seen.add(id(obj))
    return sum(held_bytes(v, seen) for v in fields.values())


# -- the rank side (python -m massview bench memory --worker OUT --probe baseline|account) ----------------
def _config(args, path: str):
    from ...core.config import RenderConfig, parse_size

    w, h = parse_size(args.size)
    budgets = {k: v for k, v in (("cache_mb", args.cache_mb), ("gpu_mb", args.gpu_mb)) if v is not None}
    return RenderConfig.from_env(width=w, height=h, frames=args.frames, path=path, **budgets)


def _baseline(comm, args) -> dict:
    """An empty GL rank: a flying rank's imports, MPI, a GL context and one framebuffer."""
    from ...core.config import parse_size
    from ...render.context import create_context
    from ...render.framebuffer import Framebuffer
    from ...systems import terrain  # noqa: F401  (the flying rank's imports)

    ctx = create_context()
    fb = Framebuffer(ctx, *parse_size(args.size))
    comm.Barrier()
    fb.release()
    return {"hwm": status_mib("VmHWM")["VmHWM"]}


def _account(comm, args) -> dict:
    """A flight opened step by step: VmRSS after each step and what the budgeted parts hold."""
    from ...app.render_cmd import run_render
    from ...core.paths import load_path
    from ...systems import open_system

    cfg = _config(args, args.probe.split(":", 1)[1])
    steps = [("imports + MPI", status_mib("VmRSS")["VmRSS"])]
    system = open_system(args.store, cfg)
    steps.append(("store, LOD arrays, hierarchy", status_mib("VmRSS")["VmRSS"]))
    _, pool, _, _ = system.renderers()
    steps.append(("GL context, block pool, renderers", status_mib("VmRSS")["VmRSS"]))
    cams = load_path(cfg.path, *system.bounds).cameras(cfg.frames, cfg.width, cfg.height) if comm.Get_rank() == 0 else None
    run_render(comm, system, cfg.__class__(**{**cfg.to_json(), "frames": 1}), None, True, cams[:1] if cams else None)
    steps.append(("first frame", status_mib("VmRSS")["VmRSS"]))
    run_render(comm, system, cfg, None, True, cams)
    steps.append((f"{cfg.frames} frames", status_mib("VmRSS")["VmRSS"]))
    out = {"steps": steps, "hwm": status_mib("VmHWM")["VmHWM"], "pool_mib": pool.gpu_bytes / 2**20,
           "pool_blocks": [len(pool.slots), pool.capacity], "cache_peak_mib": system.cache.peak_bytes / 2**20,
           "hierarchy_mib": held_bytes(system.h) / 2**20, "cache_budget_mib": cfg.cache_mb, "gpu_budget_mib": cfg.gpu_mb}
    system.close()
    return out


def worker(args) -> int:
    from ...parallel.runtime import world

    comm = world()
    mine = _baseline(comm, args) if args.probe == "baseline" else _account(comm, args)
    got = comm.gather(mine, root=0)
    if comm.Get_rank() == 0:
        Path(args.worker).write_text(json.dumps(got))
    return 0


# -- the launcher side -------------------------------------------------------------------------------------
def _probe(args, store: Path, probe: str, tmp: Path) -> list[dict] | None:
    from ...parallel.runtime import relaunch

    out = tmp / f"{_slug(probe)}.json"
    argv = ["bench", "memory", str(store), "--worker", str(out), "--probe", probe, "--size", args.size,
            "--frames", str(args.frames)]
    for flag, v in (("--cache-mb", args.cache_mb), ("--gpu-mb", args.gpu_mb)):
        if v is not None:
            argv += [flag, str(v)]
    return json.loads(out.read_text()) if relaunch(argv, args.ranks) == 0 else None


def _fly(args, store: Path, path: str, tmp: Path):
    cmd = [sys.executable, "-m", "massview", "render", str(store), "--ranks", str(args.ranks), "--path", path,
           "--frames", str(args.frames), "--size", args.size, "--out", str(tmp / f"fly_{_slug(path)}"), "--quiet"]
    for flag, v in (("--cache-mb", args.cache_mb), ("--gpu-mb", args.gpu_mb)):
        if v is not None:
            cmd += [flag, str(v)]
    return run_measured(cmd, tmp / f"fly_{_slug(path)}.rss", ranks=args.ranks)


def _slug(name: str) -> str:
    """``name`` (a path name, or a keyframe file's path) as one file name."""
    return re.sub(r"[^A-Za-z0-9_.-]", "_", name)


def run(args) -> int:
    if args.worker is not None:
        return worker(args)
    from rich.console import Console

    from .frame import demo_store

    console = Console(width=None if Console().is_terminal else 170)
    sections = {s.strip() for s in args.sections.split(",") if s.strip()}
    paths = [p.strip() for p in args.paths.split(",") if p.strip()]
    bad = [p for p in paths if p not in BUILTIN_PATHS and not (p.endswith(".json") and Path(p).is_file())]
    if bad or not paths:
        raise ConfigError(f"--paths {args.paths}: {', '.join(bad) or 'nothing given'} is neither a built-in path "
                          f"({', '.join(BUILTIN_PATHS)}) nor a keyframe .json file")
    store = terrain_store(args.store) if args.store else demo_store(args.workdir)
    cfg = _config(args, paths[0])
    console.print(f"[bold]bench memory[/] {store}, {args.ranks} ranks, {args.size}, {args.frames} frames, budgets per rank: "
                  f"RAM cache {cfg.cache_mb} MiB + GL pool {cfg.gpu_mb} MiB; figures are each rank's VmHWM (MiB)")
    with tempfile.TemporaryDirectory(prefix="massview-memory-") as tmp:
        tmp = Path(tmp)
        base = _probe(args, store, "baseline", tmp) if "baseline" in sections else None
        if base is not None:
            console.print("empty GL rank (imports, MPI, GL context, one framebuffer): "
                          + ", ".join(f"{r['hwm']:.0f}" for r in base))
        failed = []
        for path in paths:
            fly = _fly(args, store, path, tmp) if "fly" in sections else None
            acc = _probe(args, store, f"account:{path}", tmp) if "account" in sections else None
            if (fly is not None and fly.returncode != 0) or ("account" in sections and acc is None):
                failed.append(path)
            _print(console, path, args, base, fly, acc)
    if failed:
        console.print(f"[red]bench memory: the flights of {', '.join(failed)} failed; no figures for them[/]")
        return 1
    return 0


def _print(console, path: str, args, base, fly, acc) -> None:
    from rich.table import Table

    b = max((r["hwm"] for r in base), default=0.0) if base else 0.0
    if fly is not None and fly.returncode != 0:
        console.print(f"[bold]{path}[/]: `massview render --ranks {args.ranks} --path {path}` [red]failed (exit {fly.returncode})[/]: "
                      "no peak RSS to report")
    elif fly is not None:
        ranks = dict(fly.rank_peak_rss)
        if args.ranks == 1 and not ranks.get(0):  # one rank: render runs in the launcher process itself
            ranks[0] = fly.peak_rss
        peaks = [ranks.get(r, 0) / 2**20 for r in range(args.ranks)]
        verdict = "all under 1 GiB" if peaks and max(peaks) < GIB else "NOT all under 1 GiB"
        console.print(f"[bold]{path}[/]: `massview render --ranks {args.ranks} --path {path}` (exit {fly.returncode}, "
                      f"{fly.wall_s:.0f} s): per rank {', '.join(f'{p:.0f}' for p in peaks)} MiB ({verdict}); "
                      f"the parent (launcher) {fly.peak_rss / 2**20:.0f} MiB")
    if not acc:
        return
    t = Table(title=f"{path}: where each rank's memory goes (MiB; the account job, a second flight of the same path)")
    for c in ("rank", "peak", "empty GL rank", "GL pool", "RAM cache peak", "hierarchy", "rest (no budget)",
              "worst case: baseline + budgets + rest"):
        t.add_column(c, justify="right")
    for r, a in enumerate(acc):
        rest = a["hwm"] - b - a["pool_mib"] - a["cache_peak_mib"]
        worst = b + a["gpu_budget_mib"] + a["cache_budget_mib"] + rest
        t.add_row(str(r), f"{a['hwm']:.0f}", f"{b:.0f}", f"{a['pool_mib']:.0f} of {a['gpu_budget_mib']} ({a['pool_blocks'][0]}/{a['pool_blocks'][1]} blocks)",
                  f"{a['cache_peak_mib']:.0f} of {a['cache_budget_mib']}", f"{a['hierarchy_mib']:.0f}", f"{rest:.0f}", f"{worst:.0f}")
    console.print(t)
    s = Table(title=f"{path}: rank 0's VmRSS after each step (MiB)")
    s.add_column("step")
    s.add_column("VmRSS", justify="right")
    s.add_column("+", justify="right")
    prev = 0.0
    for name, v in acc[0]["steps"]:
        s.add_row(name, f"{v:.0f}", f"{v - prev:+.0f}")
        prev = v
    console.print(s)
