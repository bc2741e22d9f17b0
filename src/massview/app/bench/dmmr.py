"""M1 (distributed massive models): Tables 1–3, occlusion on/off, Algorithm 1 vs equal tiles, pipelining, speed-up.

The massive-model system's experiments (Revanth & Narayanan 2012, §4), ``massview bench dmmr``.

Scenes are generated once into ``--workdir`` (non-instanced: every copy is separate geometry,
as in the paper): power plants replicated ``--plants`` times (the paper: 4, 6, 8 copies of
~20 000 nodes, 8 levels of hierarchy) and cities replicated ``--cities`` times (16, 25, 36
copies of 1113 nodes). ``--plant-size``/``--city-size`` scale each copy to this machine; the
printed table states nodes, triangles per copy and hierarchy depth.

Each case is a real ``massview render SCENE --system dmmr --path walkthrough`` job
(server + clients under mpiexec). Printed:

* Tables 1–3: frame time (the server's period between delivered frames) and each module's
  mean time: server frustum division, send to clients, receive & assemble; per client:
  enable occlusion queries (occluder load + depth pass + issue), retrieve query results,
  load geometry to render, render (draw + read back), send to server (compress + send);
* occlusion culling on ÷ off (triangles, frame time);
* Algorithm 1 against equal screen tiles (max ÷ mean client render time, and triangles);
* pipelined against synchronous (throughput and latency in frames and ms);
* speed-up: the paper's §4 experiment (:mod:`.dmmr_speedup`): one rank with one client's RAM
  against nd clients, and the compute-only line with the whole scene in RAM.

Timings on a shared CPU are noisy: read the ratios, which are measured in the same run.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from .dmmr_path import PAPER
from .dmmr_speedup import add_arguments as _speedup_arguments

__all__ = ["add_arguments", "run"]


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--workdir", default="out/bench/dmmr", help="where scenes are generated once and runs kept")
    p.add_argument("--plants", default="4,6,8", help="plant copies for Tables 1-2 (default 4,6,8)")
    p.add_argument("--plant-clients", default="2,4", help="client counts for the plant tables (default 2,4)")
    p.add_argument("--cities", default="16,25,36", help="city copies for Table 3 (default 16,25,36)")
    p.add_argument("--city-clients", default="4")
    p.add_argument("--plant-size", type=float, default=1.0, help="size of one plant copy (generate scene --size; 1: 21 584 nodes)")
    p.add_argument("--city-size", type=float, default=1.0, help="size of one city copy (1: 1100 nodes)")
    p.add_argument("--plant-detail", type=float, default=0.5,
                   help="tessellation of a plant copy (generate scene --detail; 0.5: 2.5 M triangles a copy, the paper's 12 M scaled to llvmpipe)")
    p.add_argument("--city-detail", type=float, default=0.5, help="tessellation of a city copy (0.5: 1.36 M triangles a copy; the paper's 4.8 M)")
    p.add_argument("--frames", type=int, default=300, help="frames of the walkthrough for Tables 1-3 (the paper: 300)")
    p.add_argument("--compare-frames", type=int, default=None, help="frames for the comparisons (default: --frames)")
    p.add_argument("--path", default="serpentine", help="serpentine (a sweep over every copy, default) or any --path of render")
    p.add_argument("--size", default="1280x1024")
    p.add_argument("--gpu-mb", type=int, default=512)
    p.add_argument("--items", "--parts", dest="parts", default="tables,queries,occlusion,split,pipeline,speedup",
                   help="what to run: tables (1-3), queries (group-tree against per-object queries), occlusion, split, pipeline, "
                        "speedup (the paper's §4 experiment, --speedup-*), waits (the links' sleeping polls against MPI's spinning "
                        "calls; comma-separated)")
    _speedup_arguments(p)


def _scene(args, kind: str, copies: int) -> Path:
    from ...data.generators.scenes import generate_scene

    size, detail = (args.plant_size, args.plant_detail) if kind == "plant" else (args.city_size, args.city_detail)
    out = Path(args.workdir) / f"{kind}_x{copies}_s{size:g}_d{detail:g}.zarr"
    if not (out / "zarr.json").exists() or not json.loads((out / "zarr.json").read_text()).get("attributes", {}).get("complete"):
        print(f"generating {out} ...", flush=True)
        generate_scene(kind, out, copies=copies, size=size, seed=1, detail=detail)
    return out


def _path_for(args, scene: Path) -> str:
    """The serpentine sweep over the scene's copies (written beside the runs), or ``--path``."""
    if args.path != "serpentine":
        return args.path
    from ...data.scene import SceneStore
    from .dmmr_path import serpentine_path

    s = SceneStore(scene)
    lo, hi = s.bounds
    out = Path(args.workdir) / "runs" / f"{scene.stem}_path.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    return str(serpentine_path(out, lo, hi, int(s.attrs.get("copies", 1)), s.attrs.get("extent_per_copy", hi[:2] - lo[:2])))


def _copies_seen(scene: Path, recs: list[dict]) -> tuple[int, int, int]:
    """(copies, copies drawn on some frame, fewest frames any copy was drawn on)."""
    from ...data.scene import SceneStore
    from .dmmr_path import copy_of_objects

    s = SceneStore(scene)
    n = int(s.attrs.get("copies", 1))
    cp = copy_of_objects(s.skeleton.center, s.bounds[0], n, s.attrs.get("extent_per_copy", (1e30, 1e30)))
    frames = np.zeros(n, np.int64)
    for f in sorted({r["frame"] for r in recs}):
        ids = [i for r in recs if r["frame"] == f and r["rank"] > 0 for i in r.get("drawn_ids", [])]
        frames[np.unique(cp[np.asarray(ids, np.int64)])] += 1
    return n, int((frames > 0).sum()), int(frames.min())


def _job(args, scene: Path, clients: int, tag: str, *extra: str, frames: int | None = None, ranks: int | None = None,
         gpu_mb: int | None = None) -> dict | None:
    """One ``massview render --system dmmr`` job on ``clients`` clients (+ the server), or on
    ``ranks`` ranks (1: the server and one client in one process); its digest."""
    import time

    from ...core.stats import read_stats
    from ...parallel.runtime import relaunch

    out = Path(args.workdir) / "runs" / f"{scene.stem}_c{clients}_{tag}"
    argv = ["render", str(scene), "--system", "dmmr", "--path", _path_for(args, scene), "--frames", str(frames or args.frames),
            "--size", args.size, "--gpu-mb", str(gpu_mb or args.gpu_mb), "--out", str(out), "-q", *extra]
    t0 = time.perf_counter()
    if relaunch(argv, ranks or clients + 1) != 0:
        print(f"  {tag}: render failed", flush=True)
        return None
    recs = read_stats(out / "stats.jsonl")
    d = _digest(recs)
    d["wall_s"] = time.perf_counter() - t0
    d["stats"] = str(out / "stats.jsonl")
    if "--record-ids" in extra:
        d["copies"], d["copies_seen"], d["min_frames_per_copy"] = _copies_seen(scene, recs)
    print(f"  {scene.name} on {clients} client(s), {tag}: {frames or args.frames} frames in {d['wall_s']:.0f} s"
          + (f"; copies drawn: {d['copies_seen']} of {d['copies']} (each on at least {d['min_frames_per_copy']} frames)"
             if "copies" in d else ""), flush=True)
    return d


def _digest(recs: list[dict]) -> dict:
    """Means over the frames: the server's period and modules, each client's modules."""
    server = [r for r in recs if r["rank"] == 0]
    clients = sorted({r["rank"] for r in recs if r["rank"] > 0})
    steady = server[2:] if len(server) > 4 else server

    def cmean(rank, *keys, counter=False):
        rs = [r for r in recs if r["rank"] == rank]
        return float(np.mean([sum((r["counters"] if counter else r["times_ms"]).get(k, 0.0) for k in keys) for r in rs]))

    per_client = {
        "enable_queries": [cmean(c, "vis_load", "vis_issue") for c in clients],
        "retrieve": [cmean(c, "vis_retrieve") for c in clients],
        "load": [cmean(c, "load") for c in clients],
        "render": [cmean(c, "draw", "readback") for c in clients],
        "to_server": [cmean(c, "encode", "send") for c in clients],
        "queries": [cmean(c, "queries_issued", counter=True) for c in clients],
        "group_queries": [cmean(c, "group_queries", counter=True) for c in clients],
        "query_waits": [cmean(c, "query_waits", counter=True) for c in clients],
        "visibility": [cmean(c, "visibility") for c in clients],
        "culled": [cmean(c, "culled_by_occlusion", counter=True) for c in clients],
        "drawn": [cmean(c, "objects_drawn", counter=True) for c in clients],
        "triangles": [float(np.mean([r["triangles"] for r in recs if r["rank"] == c])) for c in clients],
    }
    return {
        "frame_ms": float(np.mean([r["times_ms"]["total"] for r in steady])),
        "divide": float(np.mean([r["times_ms"].get("divide", 0) for r in server])),
        "send": float(np.mean([r["times_ms"].get("send", 0) for r in server])),
        "assemble": float(np.mean([r["times_ms"].get("assemble", 0) for r in server])),
        "latency_ms": float(np.mean([r["counters"]["latency_ms"] for r in steady])),
        "latency_frames": int(max(r["counters"]["frames_in_flight"] for r in server)),
        "in_frustum": float(np.mean([r["counters"]["objects_in_frustum"] for r in server])),
        "triangles": float(sum(per_client["triangles"])),
        "clients": per_client,
    }


def _fmt(v) -> str:
    return "/".join(f"{x:.1f}" for x in v)


_ROWS = [("frame time (period)", "frame"), ("server: frustum division", "divide"), ("server: send to clients", "send"),
         ("server: receive & assemble (decompress+paste)", "assemble"), ("GPU1: enable occlusion queries", "enable_queries"),
         ("GPU1: retrieve query results", "retrieve"), ("GPU2: load geometry to render", "load"),
         ("GPU2: render (draw + read back)", "render"), ("GPU2: send to server (compress + send)", "to_server")]


def _table(title: str, cases: dict, paper: dict) -> None:
    """Our means (ms) with the paper's figure for the same case in brackets."""
    print(f"\n{title}  — ours [paper], ms")
    print(" | ".join(["module"] + [f"{k} copies" for k in cases]))
    for label, key in _ROWS:
        cells = []
        for k, d in cases.items():
            if d is None:
                cells.append("-")
                continue
            ours = d["frame_ms"] if key == "frame" else d[key] if key in d else d["clients"][key]
            theirs = paper.get(k, {}).get(key)
            text = _fmt(ours) if isinstance(ours, list) else f"{ours:.1f}"
            ref = "" if theirs is None else f" [{_fmt(theirs) if isinstance(theirs, list) else theirs}]"
            cells.append(text + ref)
        print(" | ".join([label] + cells))
    for label, fn in (("latency ms / frames in flight", lambda d: f"{d['latency_ms']:.0f} / {d['latency_frames']}"),
                      ("objects in frustum", lambda d: f"{d['in_frustum']:.0f}"),
                      ("queries / culled / drawn per client", lambda d: " ; ".join(_fmt(d["clients"][k]) for k in ("queries", "culled", "drawn"))),
                      ("triangles drawn / frame", lambda d: f"{d['triangles'] / 1e6:.2f} M"),
                      ("copies drawn (fewest frames a copy)", lambda d: f"{d.get('copies_seen', '?')}/{d.get('copies', '?')} ({d.get('min_frames_per_copy', '?')})")):
        print(" | ".join([label] + [fn(d) if d else "-" for d in cases.values()]))


def _describe(scene: Path) -> str:
    from ...data.scene import SceneStore

    s = SceneStore(scene)
    sk = s.skeleton
    copies = int(s.attrs.get("copies", 1))
    return (f"{scene.name}: {len(sk.radius):,} nodes ({len(sk.radius) // copies:,} a copy), "
            f"{int(sk.triangles[:, 0].sum()) // copies:,} triangles a copy, {int(s.groups.depth.max()) + 1} levels of hierarchy")


def _tables(args, results: dict) -> None:
    pcl = [int(v) for v in args.plant_clients.split(",") if v]
    for kind, counts, clients in (("plant", args.plants, pcl), ("city", args.cities, [int(v) for v in args.city_clients.split(",") if v])):
        for n in clients:
            cases = {}
            for k in (int(v) for v in counts.split(",") if v):
                scene = _scene(args, kind, k)
                print(_describe(scene), flush=True)
                cases[k] = _job(args, scene, n, "table", "--record-ids")
            if not cases:
                continue
            key = f"{'plants' if kind == 'plant' else 'cities'}_{n}"
            name = {"plants_2": "Table 1", "plants_4": "Table 2", "cities_4": "Table 3"}.get(key, "table")
            _table(f"{name}-like: {kind} copies on {n} clients, {args.size}, {args.frames} frames of {args.path}", cases, PAPER.get(key, {}))
            results[key] = cases


def run(args) -> int:
    import time

    t0 = time.perf_counter()
    parts = set(args.parts.split(","))
    plants = [int(v) for v in args.plants.split(",") if v]
    n = [int(v) for v in args.plant_clients.split(",") if v][-1]
    results: dict = {}
    if "tables" in parts:
        _tables(args, results)
    if plants and parts & {"queries", "occlusion", "split", "pipeline", "waits"}:
        scene = _scene(args, "plant", plants[0])
        base = _job(args, scene, n, "compare", "--record-ids", frames=args.compare_frames)
        results["comparisons"] = _comparisons(args, parts, scene, n, base)
    if "speedup" in parts:
        from .dmmr_speedup import run_speedup

        results["speedup"] = run_speedup(args)
    out = Path(args.workdir) / "results.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({str(k): v for k, v in results.items()}, indent=1, default=float))
    print(f"\nwrote {out} in {time.perf_counter() - t0:.0f} s (figures taken on a shared CPU: compare the ratios)")
    return 0


def _comparisons(args, parts: set, scene: Path, n: int, base: dict | None) -> dict:
    out: dict = {}
    if base is None:
        return out
    fr = args.compare_frames
    print(f"\ncomparisons on {scene.name}, {n} clients, {fr or args.frames} frames (ratios against the run with the defaults)")
    if "queries" in parts and (flat := _job(args, scene, n, "flat_queries", "--record-ids", "--query-hierarchy", "off", frames=fr)):
        out["queries"] = _queries_line(base, flat)
    if "occlusion" in parts and (off := _job(args, scene, n, "occl_off", "--occlusion", "off", frames=fr)):
        out["occlusion_off_over_on"] = {"triangles": off["triangles"] / max(base["triangles"], 1), "frame_time": off["frame_ms"] / base["frame_ms"]}
        print(f"  occlusion culling off ÷ on: triangles {off['triangles'] / 1e6:.2f} M ÷ {base['triangles'] / 1e6:.2f} M = "
              f"{out['occlusion_off_over_on']['triangles']:.2f}×, frame time {off['frame_ms']:.0f} ÷ {base['frame_ms']:.0f} ms = "
              f"{out['occlusion_off_over_on']['frame_time']:.2f}×")
    if "split" in parts and (grid := _job(args, scene, n, "grid", "--decomposition", "sort-first:grid", frames=fr)):
        def imb(d, key="render"):
            r = np.asarray(d["clients"][key])
            return float(r.max() / max(r.mean(), 1e-9))
        out["render_imbalance"] = {"algorithm1": imb(base), "equal_tiles": imb(grid),
                                   "triangles_algorithm1": imb(base, "triangles"), "triangles_equal_tiles": imb(grid, "triangles")}
        print(f"  max ÷ mean client render time: Algorithm 1 {imb(base):.2f}, equal screen tiles {imb(grid):.2f} "
              f"(triangles: {imb(base, 'triangles'):.2f} vs {imb(grid, 'triangles'):.2f}); frame time {base['frame_ms']:.0f} vs {grid['frame_ms']:.0f} ms")
    if "pipeline" in parts and (sync := _job(args, scene, n, "sync", "--stage-pipeline", "off", frames=fr)):
        out["pipeline"] = {"throughput_ratio": sync["frame_ms"] / base["frame_ms"], "latency_frames": [base["latency_frames"], sync["latency_frames"]],
                           "latency_ms": [base["latency_ms"], sync["latency_ms"]]}
        print(f"  pipelined ÷ synchronous throughput {out['pipeline']['throughput_ratio']:.2f}× ({base['frame_ms']:.0f} vs {sync['frame_ms']:.0f} ms a frame); "
              f"latency {base['latency_frames']} vs {sync['latency_frames']} frames, {base['latency_ms']:.0f} vs {sync['latency_ms']:.0f} ms")
    if "waits" in parts:
        out["waits"] = _waits_line(args, scene, n, base, fr)
    return out


def _waits_line(args, scene: Path, n: int, base: dict, fr) -> dict:
    """The dmmr links' sleeping polls (the default, ``base``) against MPI's blocking calls,
    which spin (``MASSVIEW_DMMR_WAIT=spin``), then sleeping again: frame time and the CPU all
    processes spent a frame (the sum of their ``cpu_ms``)."""
    import os

    from ...core.stats import read_stats
    from .dmmr_speedup import speedup_digest

    def cpu(d):
        return speedup_digest(read_stats(Path(d["stats"])), False)["cpu_ms"]

    old = os.environ.get("MASSVIEW_DMMR_WAIT")
    os.environ["MASSVIEW_DMMR_WAIT"] = "spin"
    try:
        spin = _job(args, scene, n, "waits_spin", frames=fr)
    finally:
        if old is None:
            os.environ.pop("MASSVIEW_DMMR_WAIT")
        else:
            os.environ["MASSVIEW_DMMR_WAIT"] = old
    again = _job(args, scene, n, "waits_sleep", frames=fr)
    if spin is None or again is None:
        return {}
    sleep_ms = [base["frame_ms"], again["frame_ms"]]
    sleep_cpu = [cpu(base), cpu(again)]
    out = {"frame_ms_sleep": sleep_ms, "frame_ms_spin": spin["frame_ms"], "cpu_ms_sleep": sleep_cpu, "cpu_ms_spin": cpu(spin)}
    print(f"  waits: sleeping polls vs spinning MPI calls (runs: sleep, spin, sleep): frame time {sleep_ms[0]:.0f}/{sleep_ms[1]:.0f} "
          f"vs {spin['frame_ms']:.0f} ms ({spin['frame_ms'] / np.mean(sleep_ms):.2f}× spin ÷ sleep); CPU of all processes a frame "
          f"{sleep_cpu[0]:.0f}/{sleep_cpu[1]:.0f} vs {out['cpu_ms_spin']:.0f} ms")
    return out


def _drawn_sets(a: str, b: str) -> dict:
    """Compare the drawn sets of two runs (stats files with drawn_ids) client-frame by client-frame."""
    from ...core.stats import read_stats

    sets = [{(r["frame"], r["rank"]): set(r.get("drawn_ids", [])) for r in read_stats(Path(f)) if r["rank"] > 0} for f in (a, b)]
    out = {"equal": 0, "flat_more": 0, "tree_more": 0, "other": 0, "client_frames": len(sets[1])}
    for k, flat in sets[1].items():
        tree = sets[0].get(k, set())
        out["equal" if tree == flat else "flat_more" if tree < flat else "tree_more" if flat < tree else "other"] += 1
    return out


def _queries_line(tree: dict, flat: dict) -> dict:
    """Group-tree queries (the default) against one query per object box: per client per frame."""
    q = {k: float(np.mean(d["clients"][key])) for k, d, key in (("tree", tree, "queries"), ("flat", flat, "queries"),
                                                                    ("tree_groups", tree, "group_queries"), ("tree_waits", tree, "query_waits"),
                                                                    ("flat_waits", flat, "query_waits"), ("tree_vis_ms", tree, "visibility"),
                                                                    ("flat_vis_ms", flat, "visibility"))}
    q.update(frame_ms_tree=tree["frame_ms"], frame_ms_flat=flat["frame_ms"], **_drawn_sets(tree["stats"], flat["stats"]))
    print(f"  occlusion queries per client per frame: group tree {q['tree']:.0f} ({q['tree_groups']:.0f} on groups, {q['tree_waits']:.1f} waits) "
          f"vs one per object box {q['flat']:.0f} ({q['flat_waits']:.1f} waits) = {q['flat'] / max(q['tree'], 1e-9):.1f}× fewer; "
          f"visibility stage {q['tree_vis_ms']:.0f} vs {q['flat_vis_ms']:.0f} ms; frame time {q['frame_ms_tree']:.0f} vs {q['frame_ms_flat']:.0f} ms "
          f"({q['frame_ms_flat'] / q['frame_ms_tree']:.2f}×); drawn sets: equal on {q['equal']} of {q['client_frames']} client-frames, "
          f"per-object queries drew more on {q['flat_more']}, the tree more on {q['tree_more']}, other {q['other']}")
    return q


if __name__ == "__main__":  # python -m massview.app.bench.dmmr
    ap = argparse.ArgumentParser(prog="massview bench dmmr")
    add_arguments(ap)
    raise SystemExit(run(ap.parse_args()))
