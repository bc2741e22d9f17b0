"""M2 Reliefboards: the paper's §7 experiments at this machine's scale (`massview bench reliefboards`).

**Scale.** Triangle counts are the paper's times ``s = MACHINE_RATE / PAPER_RATE`` (12 M / 120 M
triangles/s = 1/10, :mod:`massview.lod.boardpolicy`, where t_nz = 3.5 M · s = 350 k is defined):
the visualization rank draws ten times fewer triangles per second than the paper's, so the same
scene fractions take the same share of a frame. The scenes keep the paper's object counts and
layouts; each object's triangle count is scaled by picking, object by object, the generator's
own simplification level (halving per level) that keeps the running total on ``s`` × the
paper's count. p stays 128 px (a pixel size on the paper's 1024×768 screen); the rule "too few
triangles for a board" (2·p²) is scaled by ``s`` like every triangle count.

**Why the plant runs unscaled.** A board costs ~2 triangles per covered pixel whatever its
object (§5: one vertex per pixel of the object's projected size), and the pixels are the
paper's (1024×768), so scaling triangles by ``s`` makes every object ``s`` times cheaper against
its board. For §4's clusters this is fatal: a feasible cluster at the near-zone border projects
to ≤ p px and holds about t_nz·(2·tan(fovy/2)·p/r_y)² triangles (surface-like scene), so its
triangles over its board's are t_nz / (2·(r_y/(2·tan(fovy/2)))²) = t_nz / 1.72 M at 1024×768 —
~2 with the paper's 3.5 M, 0.2 with 350 k, where boards cost more than the originals (measured
last stop: ×0.93–1.01). So the plant runs at the paper's 12.4 M triangles with t_nz = 3.5 M and
the too-few rule 2·p² (``--plant-scale 1``, the default): the one scale that keeps the ratio of
a board's triangles to its cluster's the paper's (the §4 clustering of its 34 640 components
takes about a minute). Its frame times are ~10× the paper's; the ratio boards / all-original is
what compares. The 60 M forest is run both ways: triangles scaled by ``s`` at 1024×768
(``forest60``) and with the image's pixel count scaled by ``s`` too (``forest60px``: sides and
p by √s), which again keeps the paper's ratio of board to object triangles.

**Items** (``--items``, all by default), each at 1024×768 with 1, 2, 4, 8 backends:

* ``forest`` — 250 compact objects used directly (conifers, broad-leaved trees and the scanned
  Stanford bunny that pymeshlab's wheel ships, read through the scene store's OBJ ingest),
  25 M · s triangles, circled along an arc: the paper turns 360° in 6000 steps of ~16 ms,
  3.75°/s; here a frame takes ~0.4 s (0.5–2 s under load), so the same turn rate in wall time
  is ``--deg-per-frame`` 1.5° per frame for ``--frames`` frames (default 60: 90° of the circle);
* ``tie`` — the forest at 4 backends on a slow circle (0.3° per frame, where requests trickle
  one or two a frame) with ``--tie-rule frame`` (ties by this frame's assignments only) and
  ``pending`` (assignments persist until their boards arrive) and ``run`` (every assignment of
  the run counts): the backend loads before/after;
* ``plant`` — the generated plant (12.4 M triangles, 34 640 components) clustered by §4 (the
  paper: ~150 objects) along :func:`plant_loop_path` — the paper's Fig. 8 path is not in its
  text — cut into ``--plant-steps`` 600 equal steps (the paper's 6000 at a 10× lower triangle
  rate: the same wall time per step), of which the first ``--plant-frames`` are rendered;
* ``forest60`` / ``forest60px`` — a 600-object forest of 60 M · s triangles at the largest
  backend count, at 1024×768 and pixel-scaled: the paper's 18 fps with boards against ~2 fps
  all-original (9 PCs), as a ratio.

Each run is ``massview render SCENE --system reliefboards --reference --reference-every K``
under real mpiexec; the all-original baseline is drawn in the same run (every K-th frame), so
frame times are compared as ratios measured together. Backends share this machine's CPU with
the visualization rank (the paper's were separate PCs).
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from ...lod.boardpolicy import DEFAULT_TNZ, MACHINE_RATE, PAPER_RATE, machine_scale
from .reliefboards_scenes import arc_path, measure_rate, plant_loop_path, scaled_scene

__all__ = ["add_arguments", "run"]

def add_arguments(p) -> None:
    p.add_argument("--items", default="forest,tie,plant,forest60,forest60px",
                   help="experiments (default forest,tie,plant,forest60,forest60px)")
    p.add_argument("--backends", default="1,2,4,8", help="backend counts, comma-separated (default 1,2,4,8)")
    p.add_argument("--size", default="1024x768", help="image size (default 1024x768, the paper's)")
    p.add_argument("--frames", type=int, default=60, help="frames per forest run (default 60; the paper: 6000 for the whole circle)")
    p.add_argument("--big-frames", type=int, default=24, help="frames of the forest60 runs (default 24)")
    p.add_argument("--deg-per-frame", type=float, default=1.5,
                   help="degrees of the forest circle per frame (default 1.5: the paper's 3.75 deg/s, 360 deg in 6000 steps of ~16 ms, "
                        "at this machine's ~0.4 s frames)")
    p.add_argument("--plant-path", choices=("loop", "arc", "flyover"), default="loop",
                   help="the plant's path: loop (default: a closed loop over and around the plant at uniform speed, see plant_loop_path), "
                        "arc (around it at 1.1 half-diagonals) or flyover")
    p.add_argument("--plant-scale", type=float, default=1.0,
                   help="triangle scale of the plant, its t_nz and its too-few-triangles rule (default 1: the paper's 12.4 M triangles "
                        "and t_nz 3.5 M — the only scale at which a board's triangles against its cluster's are the paper's: "
                        "see the module's docstring, massview/app/bench/reliefboards.py)")
    p.add_argument("--plant-frames", type=int, default=30, help="frames along the plant's path, its first steps (default 30)")
    p.add_argument("--plant-steps", type=int, default=600,
                   help="steps of the plant's whole loop (default 600: the paper's 6000 at this machine's 10x lower triangle rate, "
                        "so a step takes the paper's wall time)")
    p.add_argument("--reference-every", type=int, default=4, help="draw the all-original baseline every K-th frame (default 4)")
    p.add_argument("--scale", type=float, default=machine_scale(),
                   help=f"triangle scale s against the paper's scenes (default {machine_scale():g} = {MACHINE_RATE / 1e6:g} M / {PAPER_RATE / 1e6:g} M triangles/s)")
    p.add_argument("--board-px", type=int, default=128, help="p, the largest board side (default 128)")
    p.add_argument("--min-triangles", type=int, default=None, help="fewer triangles make an object infeasible (default s · 2·p²)")
    p.add_argument("--tnz", type=int, default=None, help="t_nz (default 3.5 M · s)")
    p.add_argument("--workdir", type=Path, default=Path("out/bench-reliefboards"), help="scenes and runs go here")
    p.add_argument("--out", type=Path, default=None, help="write the figures and results.json here (default: workdir)")
    p.add_argument("--reuse", action="store_true", help="reuse finished runs in the workdir (same frames, t_nz and p)")


def _cli(*args, timeout=3600) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PMI_", "MPI_", "HYDRA_", "MASSVIEW_"))}
    proc = subprocess.run([sys.executable, "-m", "massview", *map(str, args)], capture_output=True, text=True, env=env, timeout=timeout)
    if proc.returncode != 0:
        raise SystemExit(f"massview {' '.join(map(str, args))} failed:\n{proc.stderr[-3000:]}")
    return proc


def _settings(args, over=None) -> tuple[int, int, str, int]:
    """(t_nz, min triangles, size, p) of an item: ``over`` (a dict with any of ``tnz``,
    ``min_triangles``, ``size``, ``board_px``) over the forest's, from ``args``."""
    o = over or {}
    return o.get("tnz", args.tnz), o.get("min_triangles", args.min_triangles), o.get("size", args.size), o.get("board_px", args.board_px)


def _run_one(scene: Path, path, nb: int, frames: int, args, out: Path, extra=(), over=None) -> dict:
    """One ``massview render --system reliefboards --reference`` run with :func:`_settings`."""
    tnz, min_tris, size, board_px = _settings(args, over)
    done = out / "summary.json"
    old = json.loads(done.read_text()) if done.exists() else {}
    t0 = time.perf_counter()
    if args.reuse and old.get("frames") == frames and old.get("t_nz") == tnz and old.get("board_px") == board_px \
            and old.get("min_triangles") == min_tris:
        print(f"(reusing {out})", flush=True)
    else:
        _cli("render", scene, "--system", "reliefboards", "--ranks", nb + 1, "--frames", frames, "--path", path, "--size", size,
             "--tnz", tnz, "--board-px", board_px, "--reference", "--reference-every", args.reference_every,
             "--min-triangles", min_tris, "--out", out, "-q", *extra)
    s = json.loads(done.read_text())
    if "wall_s" not in s:  # a fresh run (a reused one keeps its own)
        s["board_px"], s["min_triangles"], s["wall_s"] = board_px, min_tris, round(time.perf_counter() - t0, 1)
        done.write_text(json.dumps(s, indent=2) + "\n")
    recs = [json.loads(line) for line in (out / "stats.jsonl").read_text().splitlines()]
    ref = [r for r in recs if "ref_frame_ms" in r["counters"]]  # the frames with the baseline
    s["ref_ms"] = float(np.mean([r["counters"]["ref_frame_ms"] for r in ref]))
    s["boards_ms"] = float(np.mean([r["times_ms"]["draw"] + r["times_ms"]["readback"] for r in ref]))
    s["speedup"] = s["ref_ms"] / max(s["boards_ms"], 1e-9)
    late = [r for r in ref if r["frame"] >= frames // 2] or ref  # once the first burst of boards has arrived
    s["speedup_second_half"] = float(np.mean([r["counters"]["ref_frame_ms"] for r in late])
                                     / max(np.mean([r["times_ms"]["draw"] + r["times_ms"]["readback"] for r in late]), 1e-9))
    s["transfer_ms_mean"] = float(np.mean([r["times_ms"].get("transfer", 0.0) for r in recs]))  # boards received: decode + upload
    from ..reliefboards_report import write_run_report

    write_run_report(out, recs, s)  # Fig. 10: frame time along the path, boards against all-original
    later = [r["counters"]["loads"] for r in recs if r["frame"] > 0 and r["counters"].get("loads")]
    s["loads_after_frame0"] = np.sum(later, axis=0).tolist() if later else []  # the trickle after the first burst
    s["_response"] = [x for r in recs for x in r["counters"].get("response_ms", [])]
    s["_angles"] = [x for r in recs for x in r["counters"].get("angle_error", [])]
    return s


def _complete(s) -> str:
    """When every far object first had its board (or that it never did in the run)."""
    comp = s.get("ms_to_complete_view")
    return "complete view not reached" if comp is None else f"complete view after {comp:.0f} ms"


def _row(item, nb, s) -> None:
    rt, ae = s["response_ms"], s["angle_error_deg"]
    print(f"{item:8s} {nb:2d} | draw+read boards {s['boards_ms']:7.0f} ms vs all-original {s['ref_ms']:7.0f} ms (x{s['speedup']:.2f}; "
          f"second half x{s['speedup_second_half']:.2f}; board transfer {s['transfer_ms_mean']:.0f} ms a frame) | "
          f"response mean {rt.get('mean', float('nan')):6.0f} max {rt.get('max', float('nan')):6.0f} ms | angle min/q1/med/q3/max/mean "
          f"{ae.get('min', 0):.1f}/{ae.get('q1', 0):.1f}/{ae.get('median', 0):.1f}/{ae.get('q3', 0):.1f}/{ae.get('max', 0):.1f}/"
          f"{ae.get('mean', 0):.1f} | {_complete(s)} | loads {s['loads_per_backend']} | {s['wall_s']} s",
          flush=True)


def _experiment(item, scene, path, counts, frames, args, out, work, results, over=None) -> None:
    from ..reliefboards_report import write_backend_figures

    runs = {}
    tnz, _, size, board_px = _settings(args, over)
    for nb in counts:
        s = _run_one(scene, path, nb, frames, args, work / f"{item}-{nb}", over=over)
        _row(item, nb, s)
        runs[nb] = {"response_ms": s.pop("_response"), "angle_error": s.pop("_angles")}
        results["items"].setdefault(item, {})[nb] = s
    write_backend_figures(out / f"{item}-backends.png", runs, f"{item} · {frames} frames · {size} · t_nz {tnz} · p {board_px}")


def run(args) -> int:
    from ...core.config import parse_size

    t_start = time.perf_counter()
    w, h = parse_size(args.size)
    counts = [int(v) for v in args.backends.split(",")]
    items = args.items.split(",")
    bad = set(items) - {"forest", "tie", "plant", "forest60", "forest60px"}
    if bad:
        raise SystemExit(f"--items: unknown {', '.join(sorted(bad))}; choose from forest, tie, plant, forest60, forest60px")
    args.min_triangles = args.min_triangles or max(1, round(args.scale * 2 * args.board_px ** 2))
    args.tnz = args.tnz or max(1, round(3_500_000 * args.scale))
    work, out = args.workdir, args.out or args.workdir
    work.mkdir(parents=True, exist_ok=True)
    out.mkdir(parents=True, exist_ok=True)
    results = {"scale": args.scale, "t_nz": args.tnz, "board_px": args.board_px, "min_triangles": args.min_triangles,
               "size": [w, h], "frames": args.frames, "items": {}, "scenes": {}}
    print(f"scale s = {args.scale:g}: t_nz = {args.tnz} (default {DEFAULT_TNZ}), p = {args.board_px} px, min triangles "
          f"{args.min_triangles}, {w}x{h}", flush=True)
    if {"forest", "tie"} & set(items):
        _forest_items(args, items, counts, work, out, results)
    if "plant" in items:
        _plant_item(args, counts, work, out, results)
    if {"forest60", "forest60px"} & set(items):
        _forest60_items(args, items, max(counts), work, out, results)
    results["wall_s"] = round(time.perf_counter() - t_start, 1)
    _paper_table(results)
    (out / "results.json").write_text(json.dumps(results, indent=1, default=float) + "\n")
    print(f"wrote {out}/results.json and the figures ({results['wall_s']} s)")
    return 0


def _forest60_items(args, items, nb: int, work: Path, out: Path, results: dict) -> None:
    """The 60 M forest (scaled by s) at ``nb`` backends: at the full image (``forest60``), and
    with the image's pixel count scaled by s too (``forest60px``: each side by √s, p by √s), which
    keeps the paper's ratio of a board's triangles (~2 per covered pixel) to its object's."""
    big, results["scenes"]["forest60"] = scaled_scene("forest60", args.scale, work)
    arc = arc_path(big, args.deg_per_frame * args.big_frames, work / "forest60-arc.json")
    if "forest60" in items:
        _experiment("forest60", big, arc, [nb], args.big_frames, args, out, work, results)
    if "forest60px" in items:
        w, h = results["size"]
        k = math.sqrt(args.scale)
        over = {"size": f"{round(w * k)}x{round(h * k)}", "board_px": max(2, round(args.board_px * k))}
        _experiment("forest60px", big, arc, [nb], args.big_frames, args, out, work, results, over)


def _forest_items(args, items, counts, work: Path, out: Path, results: dict) -> None:
    """The forest along its circle at every backend count, and the two tie rules on a slow circle."""
    w, h = results["size"]
    forest, results["scenes"]["forest"] = scaled_scene("forest", args.scale, work)
    rate = measure_rate(forest, w, h)
    results["rate_tris_per_s"] = rate
    print(f"triangle rate here now: {rate / 1e6:.1f} M/s all-original (nominal {MACHINE_RATE / 1e6:g} M/s; the paper's node "
          f"{PAPER_RATE / 1e6:g} M/s)", flush=True)
    if "forest" in items:
        arc = arc_path(forest, args.deg_per_frame * args.frames, work / "forest-arc.json")
        _experiment("forest", forest, arc, counts, args.frames, args, out, work, results)
    if "tie" in items:  # the tie rule matters where requests trickle: the previous session's slow circle
        nb = 4 if 4 in counts else max(counts)
        slow = arc_path(forest, 0.3 * args.frames, work / "forest-slow-arc.json")
        tie = {"backends": nb, "deg_per_frame": 0.3}
        for rule in ("frame", "pending", "run"):
            s = _run_one(forest, slow, nb, args.frames, args, work / f"forest-{nb}-slow-{rule}", ("--tie-rule", rule))
            _row(f"tie:{rule[:4]}", nb, s)
            tie[rule] = {"loads": s["loads_per_backend"], "after_frame0": s["loads_after_frame0"]}
        results["items"]["tie"] = tie


def _plant_item(args, counts, work: Path, out: Path, results: dict) -> None:
    """The plant at ``--plant-scale`` (default the paper's 12.4 M triangles, t_nz 3.5 M),
    clustered by §4 (``prepare reliefboards``, timed), along its loop (or the arc / flyover)."""
    ps = args.plant_scale
    budget = (max(1, round(3_500_000 * ps)), max(1, round(ps * 2 * args.board_px ** 2)))
    over = {"tnz": budget[0], "min_triangles": budget[1]}
    plant, results["scenes"]["plant"] = scaled_scene("plant", ps, work)
    t0 = time.perf_counter()
    from ...core.config import parse_size
    from ...data.board_clusters import read_clusters

    old = read_clusters(plant)
    same = old is not None and (old.attrs.get("t_nz"), old.attrs.get("p"), old.attrs.get("r_y"), old.attrs.get("min_triangles")) \
        == (budget[0], args.board_px, parse_size(args.size)[1], budget[1])
    if args.reuse and same:
        text = f"(reusing the stored clustering: {old.attrs['clusters']} clusters, {int((old.status == 0).sum())} feasible)"
    else:
        text = _cli("prepare", "reliefboards", plant, "--tnz", budget[0], "--board-px", args.board_px, "--size", args.size,
                    "--min-triangles", budget[1], "--picture", out / "plant-clusters.png").stdout.strip()
    print(text, f"({time.perf_counter() - t0:.0f} s)", flush=True)
    results["scenes"]["plant"].update(clustering=text, clustering_s=round(time.perf_counter() - t0, 1), t_nz=budget[0],
                                      min_triangles=budget[1])
    if args.plant_path == "flyover":
        path = "flyover"
    elif args.plant_path == "arc":
        path = arc_path(plant, args.deg_per_frame * args.plant_frames, work / "plant-arc.json", 1.1, 0.6)
    else:
        from ...data.scene import SceneStore

        path = plant_loop_path(SceneStore(plant).bounds, work / "plant-loop.json", args.plant_steps, args.plant_frames)
    _experiment("plant", plant, path, counts, args.plant_frames, args, out, work, results, over)


def _paper_table(res: dict) -> None:
    """Ours beside the paper's (§7.2–7.5)."""
    it = res["items"]
    print("\n-- beside the paper (ours: ratios measured in the same runs; this machine shared, under load) --")
    if "plant" in it:
        sp = ", ".join(f"{nb}: x{s['speedup']:.2f} (second half x{s['speedup_second_half']:.2f})" for nb, s in it["plant"].items())
        print(f"plant frame time, all-original / boards: paper 43/16 ms = x2.7, nearly independent of backends | ours {sp}")
    for key, how in (("forest60", "full image"), ("forest60px", "image pixels scaled by s")):
        if key in it:
            nb, s = next(iter(it[key].items()))
            print(f"60 M forest, boards fps / all-original fps: paper 18/2 = x9 with 9 PCs | ours x{s['speedup']:.2f} over the run, "
                  f"x{s['speedup_second_half']:.2f} over its second half, with {nb} backends "
                  f"({res['scenes']['forest60']['triangles'] / 1e6:.1f} M triangles, {how}: {s['size'][0]}x{s['size'][1]}, "
                  f"{s['tris_board_mean'] / 1e3:.0f} k board + {s['tris_near_mean'] / 1e3:.0f} k near + {s['tris_far_original_mean'] / 1e3:.0f} k far-original "
                  f"triangles a frame)")
    for item in ("forest", "plant"):
        for nb, s in it.get(item, {}).items():
            mean = s["response_ms"].get("mean")
            comp = s["ms_to_complete_view"]
            ratio = f"{comp / mean:.1f}x mean response" if comp and mean else "n/a"
            print(f"{item} {nb} backends: {_complete(s)} = {ratio} (paper: ~1x on the plant, ~2x on the forest); "
                  f"angle error mean {s['angle_error_deg'].get('mean')}° (paper Fig. 11: mean 16° at 28 nodes)")
    if "tie" in it:
        t = it["tie"]
        print(f"loads at {t['backends']} backends (forest, 0.3 deg/frame), all / after the first frame's burst: ties by this frame's "
              f"assignments {t['frame']['loads']} / {t['frame']['after_frame0']}; counting pending ones {t['pending']['loads']} / "
              f"{t['pending']['after_frame0']}; counting the run's {t['run']['loads']} / {t['run']['after_frame0']}")
