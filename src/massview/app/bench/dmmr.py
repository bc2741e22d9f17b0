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
* speed-up against one client rendering the same frames alone (same culling, LOD, caches).

Timings on a shared CPU are noisy: read the ratios, which are measured in the same run.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

__all__ = ["add_arguments", "run"]


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--workdir", default="out/bench/dmmr", help="where scenes are generated once and runs kept")
    p.add_argument("--plants", default="4,6,8", help="plant copies for Tables 1-2 (default 4,6,8)")
    p.add_argument("--plant-clients", default="2,4", help="client counts for the plant tables (default 2,4)")
    p.add_argument("--cities", default="16,25,36", help="city copies for Table 3 (default 16,25,36)")
    p.add_argument("--city-clients", default="4")
    p.add_argument("--plant-size", type=float, default=1.0, help="size of one plant copy (generate scene --size)")
    p.add_argument("--city-size", type=float, default=1.0, help="size of one city copy")
    p.add_argument("--frames", type=int, default=300)
    p.add_argument("--size", default="1280x1024")
    p.add_argument("--gpu-mb", type=int, default=512)
    p.add_argument("--parts", default="tables,occlusion,split,pipeline,speedup")


def _scene(args, kind: str, copies: int, size: float) -> Path:
    from ...data.generators.scenes import generate_scene

    out = Path(args.workdir) / f"{kind}_x{copies}_s{size:g}.zarr"
    if not (out / "zarr.json").exists() or not json.loads((out / "zarr.json").read_text()).get("attributes", {}).get("complete"):
        print(f"generating {out} ...", flush=True)
        generate_scene(kind, out, copies=copies, size=size, seed=1)
    return out


def _job(args, scene: Path, clients: int, tag: str, *extra: str) -> dict | None:
    from ...core.stats import read_stats
    from ...parallel.runtime import relaunch

    out = Path(args.workdir) / "runs" / f"{scene.stem}_c{clients}_{tag}"
    argv = ["render", str(scene), "--system", "dmmr", "--path", "walkthrough", "--frames", str(args.frames),
            "--size", args.size, "--gpu-mb", str(args.gpu_mb), "--out", str(out), "-q", *extra]
    if relaunch(argv, clients + 1) != 0:
        print(f"  {tag}: render failed", flush=True)
        return None
    return _digest(read_stats(out / "stats.jsonl"))


def _digest(recs: list[dict]) -> dict:
    server = [r for r in recs if r["rank"] == 0]
    clients = sorted({r["rank"] for r in recs if r["rank"] > 0})
    steady = server[2:] if len(server) > 4 else server

    def cmean(rank, *keys):
        return float(np.mean([sum(r["times_ms"].get(k, 0.0) for k in keys) for r in recs if r["rank"] == rank]))

    per_client = {
        "enable_queries": [cmean(c, "vis_load", "vis_issue") for c in clients],
        "retrieve": [cmean(c, "vis_retrieve") for c in clients],
        "load": [cmean(c, "load") for c in clients],
        "render": [cmean(c, "draw", "readback") for c in clients],
        "send": [cmean(c, "encode", "send") for c in clients],
        "triangles": [float(np.mean([r["triangles"] for r in recs if r["rank"] == c])) for c in clients],
    }
    return {
        "frame_ms": float(np.mean([r["times_ms"]["total"] for r in steady])),
        "divide_ms": float(np.mean([r["times_ms"].get("divide", 0) for r in server])),
        "send_ms": float(np.mean([r["times_ms"].get("send", 0) for r in server])),
        "assemble_ms": float(np.mean([r["times_ms"].get("assemble", 0) for r in server])),
        "latency_ms": float(np.mean([r["counters"]["latency_ms"] for r in steady])),
        "latency_frames": int(max(r["counters"]["frames_in_flight"] for r in server)),
        "in_frustum": float(np.mean([r["counters"]["objects_in_frustum"] for r in server])),
        "triangles": float(sum(np.mean([r["triangles"] for r in recs if r["rank"] == c]) for c in clients)),
        "clients": per_client,
    }


def _fmt(v) -> str:
    return "/".join(f"{x:.1f}" for x in v)


def _table(title: str, cases: dict) -> None:
    print(f"\n{title}")
    rows = [("frame time ms (period)", lambda d: f"{d['frame_ms']:.0f}"), ("latency ms / frames", lambda d: f"{d['latency_ms']:.0f} / {d['latency_frames']}"),
            ("server: frustum division ms", lambda d: f"{d['divide_ms']:.2f}"), ("server: send to clients ms", lambda d: f"{d['send_ms']:.2f}"),
            ("server: receive & assemble ms", lambda d: f"{d['assemble_ms']:.2f}"),
            ("GPU1: enable occlusion queries ms", lambda d: _fmt(d["clients"]["enable_queries"])),
            ("GPU1: retrieve query results ms", lambda d: _fmt(d["clients"]["retrieve"])),
            ("GPU2: load geometry to render ms", lambda d: _fmt(d["clients"]["load"])),
            ("GPU2: render (draw + read back) ms", lambda d: _fmt(d["clients"]["render"])),
            ("GPU2: send to server ms", lambda d: _fmt(d["clients"]["send"])),
            ("objects in frustum", lambda d: f"{d['in_frustum']:.0f}"), ("triangles drawn / frame", lambda d: f"{d['triangles'] / 1e6:.2f} M")]
    names = list(cases)
    print(" | ".join(["module"] + names))
    for label, fn in rows:
        print(" | ".join([label] + [fn(cases[n]) if cases[n] else "-" for n in names]))


def _describe(scene: Path) -> str:
    from ...data.scene import SceneStore

    s = SceneStore(scene)
    sk = s.skeleton
    copies = int(s.attrs.get("copies", 1))
    return (f"{scene.name}: {len(sk.radius):,} nodes ({len(sk.radius) // copies:,} a copy), "
            f"{int(sk.triangles[:, 0].sum()) // copies:,} triangles a copy, {int(s.groups.depth.max()) + 1} levels of hierarchy")


def run(args) -> int:
    parts = set(args.parts.split(","))
    plants = [int(v) for v in args.plants.split(",") if v]
    pcl = [int(v) for v in args.plant_clients.split(",") if v]
    results = {}
    if "tables" in parts:
        for n in pcl:
            cases = {}
            for k in plants:
                scene = _scene(args, "plant", k, args.plant_size)
                print(_describe(scene), flush=True)
                cases[f"{k} plants"] = _job(args, scene, n, "table")
            _table(f"Table {1 if n == 2 else 2}-like: plants on {n} clients, {args.size}, {args.frames} frames of walkthrough", cases)
            results[f"plants_{n}_clients"] = cases
        for n in (int(v) for v in args.city_clients.split(",") if v):
            cases = {}
            for k in (int(v) for v in args.cities.split(",") if v):
                scene = _scene(args, "city", k, args.city_size)
                print(_describe(scene), flush=True)
                cases[f"{k} cities"] = _job(args, scene, n, "table")
            _table(f"Table 3-like: cities on {n} clients", cases)
            results[f"cities_{n}_clients"] = cases
    scene, n = _scene(args, "plant", plants[0], args.plant_size), pcl[-1]
    base = _job(args, scene, n, "table")
    results["comparisons"] = _comparisons(args, parts, scene, n, base)
    (Path(args.workdir) / "results.json").write_text(json.dumps(results, indent=1, default=float))
    print(f"\nwrote {Path(args.workdir) / 'results.json'} (figures taken on a shared CPU: compare the ratios)")
    return 0


def _comparisons(args, parts: set, scene: Path, n: int, base: dict | None) -> dict:
    out = {}
    if base is None:
        return out
    print(f"\ncomparisons on {scene.name}, {n} clients")
    if "occlusion" in parts and (off := _job(args, scene, n, "occl_off", "--occlusion", "off")):
        out["occlusion_off_over_on"] = {"triangles": off["triangles"] / max(base["triangles"], 1), "frame_time": off["frame_ms"] / base["frame_ms"]}
        print(f"  occlusion culling off ÷ on: triangles {out['occlusion_off_over_on']['triangles']:.2f}×, frame time {out['occlusion_off_over_on']['frame_time']:.2f}×")
    if "split" in parts and (grid := _job(args, scene, n, "grid", "--decomposition", "sort-first:grid")):
        def imb(d):
            r = np.asarray(d["clients"]["render"])
            return float(r.max() / max(r.mean(), 1e-9))
        out["render_imbalance"] = {"algorithm1": imb(base), "equal_tiles": imb(grid)}
        print(f"  max ÷ mean client render time: Algorithm 1 {imb(base):.2f}, equal screen tiles {imb(grid):.2f}")
    if "pipeline" in parts and (sync := _job(args, scene, n, "sync", "--stage-pipeline", "off")):
        out["pipeline"] = {"throughput_ratio": sync["frame_ms"] / base["frame_ms"], "latency_frames": [base["latency_frames"], sync["latency_frames"]],
                           "latency_ms": [base["latency_ms"], sync["latency_ms"]]}
        print(f"  pipelined ÷ synchronous throughput {out['pipeline']['throughput_ratio']:.2f}×; latency {base['latency_frames']} vs "
              f"{sync['latency_frames']} frames, {base['latency_ms']:.0f} vs {sync['latency_ms']:.0f} ms")
    if "speedup" in parts and (one := _job(args, scene, 1, "one")):
        out["speedup_vs_one_client"] = one["frame_ms"] / base["frame_ms"]
        print(f"  speed-up of {n} clients over one client alone: {out['speedup_vs_one_client']:.2f}× (frame time {one['frame_ms']:.0f} vs {base['frame_ms']:.0f} ms)")
    return out


if __name__ == "__main__":  # until the bench registry wires it: python -m massview.app.bench.dmmr
    ap = argparse.ArgumentParser(prog="massview bench dmmr")
    add_arguments(ap)
    raise SystemExit(run(ap.parse_args()))
