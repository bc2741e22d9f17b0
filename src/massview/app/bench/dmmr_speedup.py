"""``massview bench dmmr --items speedup``: the speed-up experiment of Revanth & Narayanan 2012, §4.

The paper's claim: one workstation whose RAM holds only what one client holds (the scene ÷
nd clients) pages geometry from disk every frame, while nd clients together hold the whole
scene; hence ~6× on 3 plants. Here, on ``--speedup-plants`` plant copies (default 3):

* for each nd of ``--speedup-clients`` (default 2,4): one rank alone (server and client in one
  process) with one client's RAM budget, ``--client-cache-mb`` = ⌈scene MB ÷ nd⌉, against nd
  clients each with that same budget; the same ``--gpu-mb`` (``--speedup-gpu-mb``) everywhere;
* a "compute-only" line: the same runs with the whole scene in every client's RAM cache (no
  paging at all), which isolates what the cores buy from what the RAM buys.

Before every run the store's pages are dropped from the OS page cache
(``posix_fadvise(DONTNEED)``) so the run starts cold and its first reads really reach the
block device. Printed per run, per frame (sums over the clients): frame time, the cache
counters per level (GPU hits, RAM hits, disk loads, bytes read from the store, RAM evictions),
bytes read through the file system (``rchar``) and from the block device (``read_bytes``),
the bytes of the meshes drawn and of the depth pre-pass, and process CPU per frame
(``cpu_ms``) of the server and each client. From ``cpu_ms`` a labelled projection: the frame
time "if each client had its own cores" = the busiest process's CPU a frame, and the speed-up
it would give. Caveat: a waiting process that spins counts its spin as CPU, which inflates the
projection's denominator (the dmmr links sleep between polls, so this is small, not nil), and
llvmpipe's raster threads are counted in their process.

Note: the file system's page cache is not part of the budget: after the first (cold) pass a
block evicted from a client's RAM cache is re-read through the file system (``rchar``) but is
often served from the OS page cache rather than the device (``read_bytes``); a workstation
whose whole RAM is the budget would read it from the device. Both figures are printed.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np

from ...core.errors import ConfigError

__all__ = ["add_arguments", "run_speedup", "speedup_digest"]

_LEVEL_KEYS = ("gpu_hits", "ram_hits", "disk_loads", "bytes_from_disk", "ram_evictions", "gpu_evictions")
_PROC_KEYS = ("file_read_bytes", "device_read_bytes", "cpu_ms")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--speedup-plants", type=int, default=3, help="speedup: plant copies of the scene (the paper: 3)")
    p.add_argument("--speedup-clients", default="2,4", help="speedup: client counts nd to compare with one rank alone (default 2,4)")
    p.add_argument("--speedup-gpu-mb", type=int, default=None, help="speedup: --gpu-mb of every run (default: --gpu-mb)")


def _per_frame(recs: list[dict], rank: int, key: str) -> float:
    rs = [r for r in recs if r["rank"] == rank]
    rs = rs[2:] if len(rs) > 4 else rs  # the steady frames, as the frame time
    return float(np.mean([r["counters"].get(key, 0) for r in rs])) if rs else 0.0


def speedup_digest(recs: list[dict], one_process: bool) -> dict:
    """Per frame means from one run's records: sums over the clients of the cache counters per
    level (the render context's GPU pool, plus the visibility context's: ``vis_`` counters) and
    of the mesh bytes; the process counters per process (server = rank 0). ``one_process``: a
    one-rank run, whose server and client records measure the same process (the client's kept)."""
    clients = sorted({r["rank"] for r in recs if r["rank"] > 0})
    out: dict = {"clients": len(clients), "one_process": one_process}
    for k in _LEVEL_KEYS:
        out[k] = sum(_per_frame(recs, c, k) + _per_frame(recs, c, "vis_" + k) for c in clients)
    for k in ("frame_mesh_bytes", "depth_mesh_bytes"):
        out[k] = sum(_per_frame(recs, c, k) for c in clients)
    procs = clients if one_process else [0, *clients]
    for k in _PROC_KEYS:
        out[k + "_per_process"] = [_per_frame(recs, p, k) for p in procs]
        out[k] = float(sum(out[k + "_per_process"]))
    return out


def _scene_mb(scene: Path) -> float:
    from ...data.scene import SceneStore

    return float(np.asarray(SceneStore(scene).skeleton.level_bytes, np.int64).sum()) / (1 << 20)


def _run(args, scene: Path, clients: int, ranks: int, cache_mb: int, gpu_mb: int, tag: str) -> dict | None:
    from ...systems.dmmr_meter import drop_page_cache
    from .dmmr import _job

    drop_page_cache(scene)  # start cold: the first reads reach the block device
    d = _job(args, scene, clients, tag, "--client-cache-mb", str(cache_mb), frames=args.compare_frames or args.frames,
             ranks=ranks, gpu_mb=gpu_mb)
    if d is None:
        return None
    from ...core.stats import read_stats

    d["speedup"] = speedup_digest(read_stats(Path(d["stats"])), ranks == 1)
    return d


def _mb(x: float) -> str:
    return f"{x / 1e6:.1f}"


def _line(label: str, d: dict) -> str:
    s = d["speedup"]
    cpu = "/".join(f"{v:.0f}" for v in s["cpu_ms_per_process"])
    return (f"  {label}: {d['frame_ms']:.0f} ms a frame; per frame: GPU hits {s['gpu_hits']:.0f}, RAM hits {s['ram_hits']:.0f}, "
            f"disk loads {s['disk_loads']:.1f} ({_mb(s['bytes_from_disk'])} MB decoded), RAM evictions {s['ram_evictions']:.1f}; "
            f"read {_mb(s['file_read_bytes'])} MB through the file system, {_mb(s['device_read_bytes'])} MB from the device; "
            f"meshes drawn {_mb(s['frame_mesh_bytes'])} MB + depth pass {_mb(s['depth_mesh_bytes'])} MB; "
            f"CPU ms a frame per process ({'client' if s['one_process'] else 'server/clients'}) {cpu}")


def _projection(one: dict, many: dict) -> tuple[float, float]:
    """(projected frame ms of ``many`` if each process had its own cores, projected speed-up)."""
    busiest = max(many["speedup"]["cpu_ms_per_process"], default=0.0)
    alone = sum(one["speedup"]["cpu_ms_per_process"])
    return busiest, alone / max(busiest, 1e-9)


def _counts(text: str) -> list[int]:
    """``--speedup-clients`` as a list of client counts (each at least 1)."""
    try:
        counts = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise ConfigError(f"--speedup-clients must be comma-separated client counts such as 2,4, got {text!r}") from None
    if not counts or min(counts) < 1:
        raise ConfigError(f"--speedup-clients needs client counts of at least 1, got {text!r}")
    return counts


def run_speedup(args) -> dict:
    """The experiment (see the module doc); prints its lines and returns the figures."""
    from .dmmr import _describe, _scene

    counts = _counts(args.speedup_clients)
    if args.speedup_plants < 1:
        raise ConfigError(f"--speedup-plants must be at least 1, got {args.speedup_plants}")
    if args.speedup_gpu_mb is not None and args.speedup_gpu_mb < 1:
        raise ConfigError(f"--speedup-gpu-mb must be at least 1 MiB, got {args.speedup_gpu_mb}")
    scene = _scene(args, "plant", args.speedup_plants)
    print(_describe(scene), flush=True)
    gpu = args.speedup_gpu_mb or args.gpu_mb
    total = _scene_mb(scene)
    whole = math.ceil(total) + 16  # every object in RAM, with room for the cache's slack
    print(f"\nspeed-up experiment (§4) on {scene.name}: scene {total:.0f} MB of decoded meshes, --gpu-mb {gpu}, "
          f"{args.compare_frames or args.frames} frames; store pages dropped (posix_fadvise DONTNEED) before every run", flush=True)
    if gpu >= total:
        print(f"  note: each GL context's --gpu-mb {gpu} holds the whole scene: once loaded a mesh stays on the GPU, so the RAM "
              "budget only serves first loads (a smaller --speedup-gpu-mb makes the clients re-read from RAM or disk)", flush=True)
    out: dict = {"scene_mb": total, "gpu_mb": gpu, "cases": {}}
    full_one = _run(args, scene, 1, 1, whole, gpu, f"speedup_one_full{whole}_gpu{gpu}")
    for nd in counts:
        budget = math.ceil(total / nd)
        one = _run(args, scene, 1, 1, budget, gpu, f"speedup_one_ram{budget}_gpu{gpu}")
        many = _run(args, scene, nd, nd + 1, budget, gpu, f"speedup_c{nd}_ram{budget}_gpu{gpu}")
        full = _run(args, scene, nd, nd + 1, whole, gpu, f"speedup_c{nd}_full{whole}_gpu{gpu}")
        case: dict = {"client_cache_mb": budget}
        print(f"\n nd = {nd} clients, each with --client-cache-mb {budget} (⌈{total:.0f} MB ÷ {nd}⌉):")
        for label, d, key in (("one rank alone, one client's RAM", one, "one_rank"), (f"{nd} clients, same RAM each", many, "clients"),
                              ("compute-only: one rank alone, whole scene in RAM", full_one, "one_rank_whole"),
                              (f"compute-only: {nd} clients, whole scene in RAM each", full, "clients_whole")):
            if d is not None:
                print(_line(label, d))
                case[key] = {"frame_ms": d["frame_ms"], **d["speedup"]}
        if one and many:
            case["speedup"] = one["frame_ms"] / many["frame_ms"]
            print(f"  speed-up, paging experiment: {case['speedup']:.2f}× ({one['frame_ms']:.0f} ÷ {many['frame_ms']:.0f} ms) "
                  f"[paper: ~6× on 3 plants]")
            ms, sp = _projection(one, many)
            case["projected_frame_ms"], case["projected_speedup"] = ms, sp
            print(f"  projection if each client had its own cores (from cpu_ms; spin-waiting and raster threads inflate CPU): "
                  f"busiest process {ms:.0f} ms a frame → {sp:.2f}×")
        if full_one and full:
            case["speedup_compute_only"] = full_one["frame_ms"] / full["frame_ms"]
            print(f"  speed-up, compute-only (whole scene in RAM everywhere): {case['speedup_compute_only']:.2f}× "
                  f"({full_one['frame_ms']:.0f} ÷ {full['frame_ms']:.0f} ms)")
        out["cases"][nd] = case
    return out
