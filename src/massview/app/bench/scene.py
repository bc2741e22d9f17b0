"""``massview bench scene [SCENE]``: skeleton culling time, and a massive scene rendered along
``walkthrough`` on 1 and N ranks with LOD on and off.

Part 1 (numpy, one core, no store): culling of synthetic skeletons of 10 k, 100 k and 1 M
objects (boxes scattered like buildings of a city, a median-split group tree of 64-object
leaves) from cameras along ``walkthrough`` and ``orbit``: the hierarchical cull against the
per-object brute-force test measured in the same run (the baseline), and the level choice.

Part 2 (needs a scene store, e.g. ``massview generate scene plant --copies N``): real
``massview render SCENE --path walkthrough`` jobs at ``--size`` with ``--cache-mb`` and
``--gpu-mb`` per rank, for each rank count, with LOD (``--tau``) and without (τ = 1e-6: level 0
everywhere). Printed per case: mean frame time, triangles drawn per frame (sum over ranks),
cache hits and meshes loaded per frame, objects drawn coarser than wanted, peak RSS per rank;
and the ratios LOD off ÷ LOD on. With ``--loading complete`` the frame time includes waiting
for loads (the ``lod`` stage); the draw time is the GL work alone. Frame times on a shared CPU are noisy: compare ratios.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

from ...core.paths import load_path
from ...core.stats import read_stats
from ...lod.cull import boxes_in_frustum
from ...lod.scene import SkeletonCuller, build_group_tree, choose_levels

__all__ = ["add_arguments", "run", "synthetic_skeleton"]


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("scene", nargs="?", default=None, help="scene store for the render part (omit: culling only)")
    p.add_argument("--ranks", default="1,4", help="rank counts for the render part (default 1,4)")
    p.add_argument("--size", default="1280x1024", help="image WIDTHxHEIGHT of the render part (default 1280x1024)")
    p.add_argument("--frames", type=int, default=12, help="frames per render run (default 12)")
    p.add_argument("--tau", type=float, default=1.0, help="pixel tolerance of the LOD (default 1)")
    p.add_argument("--cache-mb", type=int, default=512, help="RAM block cache per rank, MiB (default 512)")
    p.add_argument("--gpu-mb", type=int, default=512, help="GL block pool per rank, MiB (default 512)")
    p.add_argument("--loading", choices=("async", "complete"), default="async",
                   help="async = never wait for data (default, as the viewer); complete = wait for every block")
    p.add_argument("--objects", default="10000,100000,1000000", help="skeleton sizes for the culling part")
    p.add_argument("--no-lod-off", action="store_true", help="skip the LOD-off runs")
    p.add_argument("--out", default=None, help="keep the render folders here (default: a temporary folder)")


def synthetic_skeleton(n: int, seed: int = 1):
    """(lo, hi, groups, leaf, center, radius, levels, level_error) for ``n`` objects: boxes of
    1–12 units on a square site sized for a constant density, a few tall ones."""
    rng = np.random.default_rng(seed)
    side = 30.0 * np.sqrt(n)
    c = np.empty((n, 3))
    c[:, :2] = rng.uniform(0, side, (n, 2))
    half = rng.uniform(0.5, 6.0, (n, 3))
    half[:, 2] *= rng.choice([1.0, 4.0], n, p=[0.9, 0.1])
    c[:, 2] = half[:, 2]
    lo, hi = c - half, c + half
    groups, leaf = build_group_tree(lo, hi, leaf_size=64)
    radius = np.linalg.norm(half, axis=1)
    lmax = 6
    err = (radius[:, None] * 0.004 * 4.0 ** np.arange(lmax)[None, :]).astype(np.float32)
    err[:, 0] = 0
    return lo, hi, groups, leaf, c, radius, np.full(n, lmax, np.int8), err


def _best_ms(fn, repeat: int = 3) -> float:
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best * 1e3


def _culling(args, console, table_cls) -> None:
    t = table_cls(title="skeleton culling (one core, best of 3, mean over 8 cameras per path)")
    for c in ("objects", "groups", "path", "visible", "hierarchical ms", "brute force ms", "brute ÷ hierarchical", "level choice ms"):
        t.add_column(c, justify="right")
    for n in (int(v) for v in args.objects.split(",") if v.strip()):
        t0 = time.perf_counter()
        lo, hi, groups, leaf, c, r, nlev, err = synthetic_skeleton(n)
        build_s = time.perf_counter() - t0
        culler = SkeletonCuller(groups, leaf, lo, hi)
        for path in ("walkthrough", "orbit"):
            cams = load_path(path, lo.min(0), hi.max(0)).cameras(8, 1280, 1024)
            hier, brute, lod, vis = [], [], [], []
            for cam in cams:
                planes = cam.frustum_planes()
                hier.append(_best_ms(lambda: culler.visible(planes)))
                brute.append(_best_ms(lambda: boxes_in_frustum(lo, hi, planes)))
                v = np.flatnonzero(culler.visible(planes))
                lod.append(_best_ms(lambda: choose_levels(cam, c[v], r[v], nlev[v], err[v], 1.0)))
                vis.append(len(v))
            h, b = np.mean(hier), np.mean(brute)
            t.add_row(f"{n:,}", f"{len(groups.parent):,}", path, f"{np.mean(vis):,.0f}", f"{h:.2f}", f"{b:.2f}", f"{b / h:.1f}×",
                      f"{np.mean(lod):.2f}")
        console.print(f"  {n:,} objects: group tree built in {build_s:.1f} s")
    console.print(t)


def _render_case(args, out: Path, nranks: int, tau: float) -> dict | None:
    from ...parallel.runtime import relaunch

    argv = ["render", str(args.scene), "--path", "walkthrough", "--frames", str(args.frames), "--size", args.size,
            "--tau", str(tau), "--cache-mb", str(args.cache_mb), "--gpu-mb", str(args.gpu_mb), "--loading", args.loading,
            "--decomposition", "sort-last", "--out", str(out), "-q"]
    if relaunch(argv, nranks) != 0:
        return None
    s = json.loads((out / "summary.json").read_text())
    recs = read_stats(out / "stats.jsonl")
    per_frame = {}
    for rec in recs:
        f = per_frame.setdefault(rec["frame"], {"tris": 0, "hits": 0, "loads": 0, "coarser": 0, "ms": 0.0, "draw": 0.0, "lod": 0.0})
        f["tris"] += rec["triangles"]
        f["hits"] += rec["counters"].get("cache_hits", 0)
        f["loads"] += rec["counters"].get("meshes_loaded", 0)
        f["coarser"] += rec["counters"].get("objects_coarser", 0)
        f["ms"] = max(f["ms"], rec["times_ms"]["total"])
        f["draw"] = max(f["draw"], rec["times_ms"]["draw"])
        f["lod"] = max(f["lod"], rec["times_ms"]["lod"])
    frames = list(per_frame.values())
    return {"frame_ms": float(np.mean([f["ms"] for f in frames])), "draw_ms": float(np.mean([f["draw"] for f in frames])),
            "lod_ms": float(np.mean([f["lod"] for f in frames])), "tris": float(np.mean([f["tris"] for f in frames])),
            "hits": float(np.mean([f["hits"] for f in frames])), "loads": float(np.mean([f["loads"] for f in frames])),
            "coarser": float(np.mean([f["coarser"] for f in frames])), "rss": s.get("peak_rss_mib_per_rank", [])}


def _render(args, console, table_cls) -> None:
    t = table_cls(title=f"{args.scene} along walkthrough, {args.size}, {args.frames} frames, sort-last, "
                        f"{args.cache_mb} MiB cache + {args.gpu_mb} MiB GL pool per rank, loading {args.loading}")
    for c in ("ranks", "LOD", "frame ms", "draw ms", "cull+LOD+load ms", "triangles / frame", "cache hits / frame", "meshes loaded / frame",
              "objects coarser", "peak RSS MiB per rank"):
        t.add_column(c, justify="right")
    root = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="bench_scene_"))
    ratios = []
    for n in (int(v) for v in args.ranks.split(",") if v.strip()):
        res = {}
        for label, tau in (("on", args.tau), ("off", 1e-6)):
            if label == "off" and args.no_lod_off:
                continue
            r = _render_case(args, root / f"r{n}_lod_{label}", n, tau)
            if r is None:
                console.print(f"[red]{n} ranks, LOD {label}: render failed[/]")
                continue
            res[label] = r
            t.add_row(str(n), f"{label} (τ = {tau:g})", f"{r['frame_ms']:.0f}", f"{r['draw_ms']:.0f}", f"{r['lod_ms']:.0f}", f"{r['tris'] / 1e6:.2f} M", f"{r['hits']:.0f}",
                      f"{r['loads']:.0f}", f"{r['coarser']:.0f}", ", ".join(f"{v:.0f}" for v in r["rss"]))
        if "on" in res and "off" in res:
            ratios.append(f"{n} rank(s): LOD off ÷ on — triangles {res['off']['tris'] / max(res['on']['tris'], 1):.1f}×, "
                          f"frame time {res['off']['frame_ms'] / max(res['on']['frame_ms'], 1e-9):.1f}×, "
                          f"draw time {res['off']['draw_ms'] / max(res['on']['draw_ms'], 1e-9):.1f}×")
    console.print(t)
    for line in ratios:
        console.print("  " + line)


def run(args) -> int:
    from rich.console import Console
    from rich.table import Table

    console = Console(width=None if Console().is_terminal else 160)
    _culling(args, console, Table)
    if args.scene:
        _render(args, console, Table)
    return 0


if __name__ == "__main__":  # also: python -m massview.app.bench.scene
    ap = argparse.ArgumentParser(prog="massview bench scene")
    add_arguments(ap)
    raise SystemExit(run(ap.parse_args()))
