"""T2 (Röttger): the paper's experiments at this machine's scale — §4.1 speed-up, Figures 6 and 7,
T1 vs T2, peak RSS per computation rank (Gouranton et al. §4).

The paper's set-up: one 1000 × 760 layer (about 1.52 M triangles at full resolution), 1–6
layers stacked as copies, 1280 × 1024 pixels per visualization node. Here the layer is cut
from real data: the USGS Jacksboro-fault DEM shipped with matplotlib (344 × 403 samples, SRTM
3″, about 80 m) tiled with alternate copies mirrored (so the terrain is continuous across the
seams and keeps the real DEM's roughness at its own sample spacing, where resampling it up
would smooth it), cut to 1000 × 760 and given 80 m spacing. Layers are copies of it drawn below each other.
Sections (``--sections``):

* ``speedup`` (§4.1): sequential LOD time ÷ parallel LOD time (per frame the maximum over the
  computation ranks; median over frames) for C = 1, 2, 4 over the layer counts, with the exact
  and the paper's partition (the paper: about 2.75 at 4–1, constant in the layer count). The
  sequential LOD is ``--reference``'s: the visualization rank runs the whole-DEM LOD alone
  after each frame while the computation ranks sleep, so both are measured in the same job,
  frame by frame (and the parallel image is checked against the serial one). The runs draw
  1/16 of the pixels with the desired resolution c of the full 1280 × 1024 image (same field
  of view and aspect: the same LOD and the same culling).
* ``fig6``: frame rate of sequential (``--reference``'s frame: whole-DEM LOD and every fan
  drawn, no culling, as the paper's sequential version), 1–1 and 4–1 over the layer counts
  (the paper: +80 % sequential → 1–1, +25 % 1–1 → 4–1), each gain a ratio to the sequential
  frame of the same job; ``fig7``: 4–1 against 4–4 (a 2 × 2 wall, 1280 × 1024 per
  visualization rank as in the paper's tiled display).
* ``t1t2``: T1 and T2 on the same store, path, image size and rank count: frame time,
  triangles, bytes per frame, peak RSS per rank.
* ``rss``: peak RSS per computation rank (each rank's own VmHWM, gathered by the run) on a
  16385² store with C = 4, against 1.5 × (the DEM's bytes ÷ C) + the peak of the same run on a
  257² store.

Timings are wall-clock; on a shared machine compare the ratios (each against a baseline
measured in the same run). Results go to ``WORKDIR/results.json``; a table puts the paper's
figures beside ours at the end.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

__all__ = ["add_arguments", "run", "layer_store", "parse_counts"]

SECTIONS = ("speedup", "fig6", "fig7", "t1t2", "rss")


def add_arguments(p) -> None:
    p.add_argument("--workdir", default="out/bench/roettger", help="stores and runs are kept here (default out/bench/roettger)")
    p.add_argument("--sections", default=",".join(SECTIONS), help=f"comma-separated subset of {', '.join(SECTIONS)}")
    p.add_argument("--layers", default="1,3,6", help="layer counts for speedup/fig6/fig7, e.g. 1-6 or 1,2,4,6 (default 1,3,6)")
    p.add_argument("--frames", type=int, default=3, help="frames of the orbit path per run (default 3)")
    p.add_argument("--size-per-vis", default="1280x1024", help="pixels per visualization rank (the paper's 1280x1024)")
    p.add_argument("--big-size", type=int, default=16385, help="samples per side of the RSS store (default 16385)")
    p.add_argument("--big-store", default=None, help="an existing large store for the rss section (default: generated in WORKDIR)")


def parse_counts(spec: str) -> list[int]:
    """'1-6' or '1,2,4,6' (or a mix) → sorted unique positive ints."""
    from ...core.errors import ConfigError

    out: set[int] = set()
    try:
        for part in spec.split(","):
            a, _, b = part.strip().partition("-")
            out.update(range(int(a), int(b or a) + 1))
    except ValueError:
        raise ConfigError(f"--layers {spec!r}: use counts like 1-6 or 1,2,4,6") from None
    if not out or min(out) < 1:
        raise ConfigError(f"--layers {spec!r}: counts must be >= 1")
    return sorted(out)


def _cli(*args) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PMI_", "MPI_", "HYDRA_", "MASSVIEW_UNDER"))}
    proc = subprocess.run([sys.executable, "-m", "massview", *map(str, args)], capture_output=True, text=True, env=env)
    if proc.returncode != 0:
        raise RuntimeError(f"massview {' '.join(map(str, args))} failed:\n{proc.stderr[-3000:]}")
    return proc


def layer_store(workdir: Path) -> Path:
    """The 1000 × 760 real-DEM layer (Jacksboro DEM tiled with mirrored copies, 80 m), prepared once."""
    from matplotlib import cbook

    from ...data.terrain import ArraySource, TerrainStore, prepare_terrain

    path = workdir / "layer1000x760.zarr"
    try:
        TerrainStore(path)
        return path
    except Exception:  # noqa: BLE001 - missing or incomplete: (re)build
        pass
    e = cbook.get_sample_data("jacksboro_fault_dem.npz")["elevation"].astype(np.float32)
    pair = np.block([[e, e[:, ::-1]], [e[::-1], e[::-1, ::-1]]])  # mirrored: continuous across the seams
    big = np.tile(pair, (2, 2))[:760, :1000]
    prepare_terrain(ArraySource(np.ascontiguousarray(big), "jacksboro-mirrored-1000x760", transform=(0, 80.0, 0, 0, 0, -80.0)),
                    path, block=129, color=None, overwrite=True)
    return path


class Runs:
    """``massview render`` jobs of T2 and T1 under real mpiexec, each run once per bench
    invocation (a later section asking for the same job reuses it)."""

    def __init__(self, workdir: Path, store: Path, frames: int):
        self.workdir, self.store, self.frames = workdir, store, frames
        self._done: dict = {}
        self.wall_s: dict = {}

    def t2(self, layers: int, C: int, V: int, size: str, *extra) -> tuple[dict, list]:
        """(summary, records) of an orbit with C computation and V visualization ranks; V = 4
        is a 2 × 2 wall of ``size`` tiles, V = 1 one ``size`` image."""
        from ...core.stats import read_stats

        tag = f"t2_{layers}L_{C}-{V}_{size}" + "".join(str(e).strip("-") for e in extra).replace(".", "p")
        if tag not in self._done:
            out = self.workdir / "runs" / tag
            w, h = (int(v) for v in size.split("x"))
            wall = ["--wall", "2x2", "--size", f"{2 * w}x{2 * h}"] if V == 4 else ["--size", size]
            t0 = time.perf_counter()
            _cli("render", self.store, *([self.store] * (layers - 1)), "--system", "roettger", "--ranks", C + V, "--compute-ranks",
                 C, "--frames", self.frames, "--path", "orbit", "--out", out, "-q", *wall, *extra)
            self.wall_s[tag] = round(time.perf_counter() - t0, 1)
            self._done[tag] = (json.loads((out / "summary.json").read_text()), read_stats(out / "stats.jsonl"))
        return self._done[tag]

    def t1(self, ranks: int, size: str) -> dict:
        out = self.workdir / "runs" / f"t1_{ranks}_{size}"
        t0 = time.perf_counter()
        _cli("render", self.store, "--ranks", ranks, "--frames", self.frames, "--size", size, "--path", "orbit", "--out", out, "-q")
        self.wall_s[f"t1_{ranks}_{size}"] = round(time.perf_counter() - t0, 1)
        return json.loads((out / "summary.json").read_text())


def per_frame(recs: list, V: int) -> dict:
    """Per frame: the sequential baseline the visualization leader measured in the same job
    (``seq_lod`` ms, ``seq`` ms = LOD + draw of every fan), the parallel LOD (``par_lod``: the
    maximum over computation ranks, ranks >= V) and the frame time (``frame``: max total)."""
    out: dict = {}
    for r in recs:
        f = out.setdefault(r["frame"], {"par_lod": 0.0, "frame": 0.0})
        f["frame"] = max(f["frame"], r["times_ms"].get("total", 0.0))
        if r["rank"] >= V:
            f["par_lod"] = max(f["par_lod"], r["times_ms"]["lod"])
        elif r["rank"] == 0 and "reference_lod_ms" in r["counters"]:
            f["seq_lod"], f["seq"] = r["counters"]["reference_lod_ms"], r["counters"]["reference_ms"]
    return out


def _median(frames: dict, f, skip_first: bool = False) -> float:
    keys = sorted(frames)[1:] if skip_first and len(frames) > 1 else sorted(frames)
    return float(np.median([f(frames[k]) for k in keys]))


def _speedup(args, runs: Runs, layer_counts, res) -> None:
    from ...core.paths import load_path
    from ...lod.roettger import default_c

    w, h = (int(v) for v in args.size_per_vis.split("x"))
    small = f"{w // 4}x{h // 4}"
    c = default_c(1.0, load_path("orbit", np.zeros(3), np.ones(3)).fovy, h)
    print(f"§4.1  sequential LOD ÷ parallel LOD (max over computation ranks), per frame, median; LOD of {args.size_per_vis}"
          f" (c = {c:.0f}); the paper: ≈2.75 at 4-1")
    print(f"{'layers':>6} {'C':>2} {'exact':>7} {'paper':>7}   seq ms / par ms (exact)")
    for L in layer_counts:
        for C in (1, 2, 4):
            row = {"layers": L, "C": C}
            for part, extra in (("exact", ()), ("paper", ("--paper-partition",))):
                summ, recs = runs.t2(L, C, 1, small, "--reference", "--roettger-c", f"{c:.6g}", *extra)
                fr = per_frame(recs, 1)
                row[f"{part}_ratio"] = round(_median(fr, lambda x: x["seq_lod"] / x["par_lod"]), 3)
                row[f"{part}_sequential_lod_ms"] = round(_median(fr, lambda x: x["seq_lod"]), 1)
                row[f"{part}_lod_ms"] = round(_median(fr, lambda x: x["par_lod"]), 1)
                if part == "exact":
                    row["max_abs_diff"] = summ.get("max_abs_diff")
            res.setdefault("speedup", []).append(row)
            print(f"{L:>6} {C:>2} {row['exact_ratio']:>7.2f} {row['paper_ratio']:>7.2f}   {row['exact_sequential_lod_ms']:6.1f} / "
                  f"{row['exact_lod_ms']:.1f}   (parallel image == serial: max_abs_diff {row['max_abs_diff']})")


def _fig6(args, runs: Runs, layer_counts, res) -> None:
    size = args.size_per_vis
    print(f"Figure 6  frame rate at {size}: sequential (the visualization rank alone: whole-DEM LOD, every fan drawn, as the "
          f"paper's), 1-1, 4-1; gains are ratios to the sequential frame measured in the same job, frame 0 left out; "
          f"the paper: +80 % seq→1-1, +25 % 1-1→4-1")
    for L in layer_counts:
        s11, r11 = runs.t2(L, 1, 1, size, "--reference")
        s41, r41 = runs.t2(L, 4, 1, size, "--reference")
        f11, f41 = per_frame(r11, 1), per_frame(r41, 1)
        g11 = _median(f11, lambda x: x["seq"] / x["frame"], True)
        g41 = _median(f41, lambda x: x["seq"] / x["frame"], True)
        row = {"layers": L, "sequential_fps": round(1e3 / _median(f11, lambda x: x["seq"], True), 3),
               "sequential_fps_4_1_job": round(1e3 / _median(f41, lambda x: x["seq"], True), 3),
               "frames_in_medians": max(min(len(f11), len(f41)) - 1, 1),
               "fps_1_1": round(1e3 / _median(f11, lambda x: x["frame"], True), 3),
               "fps_4_1": round(1e3 / _median(f41, lambda x: x["frame"], True), 3),
               "gain_seq_to_1_1": round(g11 - 1, 3), "gain_1_1_to_4_1": round(g41 / g11 - 1, 3),
               "triangles_per_frame": s41["triangles_per_frame"], "max_abs_diff": max(s11.get("max_abs_diff", 0), s41.get("max_abs_diff", 0))}
        res.setdefault("fig6", []).append(row)
        print(f"  layers {L}: seq {row['sequential_fps']:.2f} (in the 4-1 job {row['sequential_fps_4_1_job']:.2f})  "
              f"1-1 {row['fps_1_1']:.2f}  4-1 {row['fps_4_1']:.2f} fps  (gain over each job's own sequential frame: "
              f"{row['gain_seq_to_1_1']:+.0%}, 1-1 → 4-1 {row['gain_1_1_to_4_1']:+.0%}: the ratio of the two normalised gains; "
              f"{row['triangles_per_frame'] / 1e6:.2f} M triangles; max_abs_diff {row['max_abs_diff']})")
        if row["frames_in_medians"] < 3:  # (walk8 M3: a median of one frame, said nowhere)
            print(f"  note: each median is of {row['frames_in_medians']} frame(s) (frame 0 left out); give --frames 6 or more "
                  "for figures that do not move between runs")


def _fig7(args, runs: Runs, layer_counts, res) -> None:
    size = args.size_per_vis
    print(f"Figure 7  4-1 against 4-4 ({size} per visualization rank; 4-4 = a 2x2 wall, 4x the pixels)")
    for L in layer_counts:
        s41, _ = runs.t2(L, 4, 1, size)
        s44, _ = runs.t2(L, 4, 4, size)
        row = {"layers": L, "fps_4_1": s41["fps"], "fps_4_4": s44["fps"], "ratio_4_4_over_4_1": round(s44["fps"] / s41["fps"], 3)}
        res.setdefault("fig7", []).append(row)
        print(f"  layers {L}: 4-1 {s41['fps']:.2f}  4-4 {s44['fps']:.2f} fps (x{row['ratio_4_4_over_4_1']:.2f})")


def _t1t2(args, runs: Runs, res) -> None:
    ranks, size = 5, args.size_per_vis
    print(f"T1 vs T2  same store, orbit path, {size}, {ranks} ranks (T1: its default decomposition; T2: 4 computation + 1 visualization)")
    s1 = runs.t1(ranks, size)
    s2, recs = runs.t2(1, 4, 1, size)
    full = sum(r["counters"].get("bytes_full", 0) for r in recs)
    xyz = sum(r["counters"].get("bytes_xyz", 0) for r in recs)
    sent = sum(r["bytes_sent"] for r in recs if r["rank"] >= 1)
    for name, s in (("T1", s1), ("T2", s2)):
        row = {k: s.get(k) for k in ("mean_frame_ms", "fps", "triangles_per_frame", "bytes_per_frame", "peak_rss_mib_per_rank")}
        res.setdefault("t1t2", {})[name] = row
        print(f"  {name}: {row['mean_frame_ms']:.0f} ms/frame, {row['triangles_per_frame'] / 1e6:.2f} M triangles, "
              f"{row['bytes_per_frame'] / 1e6:.2f} MB/frame, peak RSS {row['peak_rss_mib_per_rank']} MiB")
    res["t1t2"]["T2_bytes"] = {"sent": sent, "full_index_height": full, "xyz": xyz}
    print(f"  T2 fans: sent {sent / 1e6:.2f} MB in {args.frames} frames; all visible fans each frame would be "
          f"{full / 1e6:.2f} MB as (index, height) and {xyz / 1e6:.2f} MB as (x, y, z) "
          f"(saved {1 - sent / max(full, 1):.0%} by sending only changes, {1 - full / max(xyz, 1):.0%} by the encoding)")


def _rss(args, workdir: Path, res) -> None:
    from ...data.terrain import TerrainStore
    from ...data.terrain.roettger import has_table

    big = Path(args.big_store) if args.big_store else workdir / f"big{args.big_size}.zarr"
    if not args.big_store and not big.exists():
        print(f"  generating a {args.big_size}² store in {big} (once; ~3 min at 16385²) ...", flush=True)
        _cli("generate", "terrain", big, "--size", args.big_size, "--seed", 3, "-q")
    if not has_table(TerrainStore(big)):
        _cli("prepare", "roettger", big, "-q")
    small = workdir / "small257.zarr"
    if not small.exists():
        _cli("generate", "terrain", small, "--size", 257, "--seed", 3, "-q")
    peaks = {}
    for name, path in (("big", big), ("small", small)):
        s, _ = Runs(workdir / f"rss_{name}", path, 2).t2(1, 4, 1, args.size_per_vis)
        peaks[name] = s["peak_rss_mib_per_rank"][1:]
    st = TerrainStore(big)
    dem_mib = st.layout.rows * st.layout.cols * 4 / 2**20
    bound = 1.5 * dem_mib / 4 + max(peaks["small"])
    res["rss"] = {"dem_mib": round(dem_mib, 1), "compute_peak_mib": peaks["big"], "small_peak_mib": peaks["small"],
                  "bound_mib": round(bound, 1), "within": max(peaks["big"]) < bound}
    print(f"RSS  {st.layout.rows}² store, C = 4: computation ranks peak {peaks['big']} MiB; bound 1.5 × {dem_mib:.0f}/4 + "
          f"{max(peaks['small']):.0f} (257² run) = {bound:.0f} MiB → {'within' if res['rss']['within'] else 'OVER'}")


def _paper_table(res: dict) -> None:
    """The paper's figures beside ours (one column per layer count)."""
    rows = []
    sp = res.get("speedup", [])
    for C, part in ((4, "exact"), (4, "paper"), (2, "exact"), (1, "exact")):
        vals = [r for r in sp if r["C"] == C]
        if vals:
            paper = "≈2.75, constant" if C == 4 else "–"
            rows.append((f"§4.1 seq÷par LOD, {C}-1 ({part})", paper, " / ".join(f"{r[f'{part}_ratio']:.2f}" for r in vals),
                         "/".join(str(r["layers"]) for r in vals)))
    f6 = res.get("fig6", [])
    if f6:
        ls = "/".join(str(r["layers"]) for r in f6)
        rows.append(("Fig 6 gain seq → 1-1", "+80 %", " / ".join(f"{r['gain_seq_to_1_1']:+.0%}" for r in f6), ls))
        rows.append(("Fig 6 gain 1-1 → 4-1 (normalised)", "+25 %",
                     " / ".join(f"{r['gain_1_1_to_4_1']:+.0%}" for r in f6), ls))
        rows.append(("Fig 6 fps 4-1", "> 10 up to 4 layers", " / ".join(f"{r['fps_4_1']:.2f}" for r in f6), ls))
    f7 = res.get("fig7", [])
    if f7:
        rows.append(("Fig 7 fps 4-4 ÷ 4-1", "> 1 at every size", " / ".join(f"{r['ratio_4_4_over_4_1']:.2f}" for r in f7),
                     "/".join(str(r["layers"]) for r in f7)))
    if "rss" in res:
        r = res["rss"]
        rows.append(("RSS per computation rank, 16385², C=4", "(issue) < bound", f"{max(r['compute_peak_mib']):.0f} MiB < "
                     f"{r['bound_mib']:.0f} MiB" if r["within"] else f"{max(r['compute_peak_mib']):.0f} MiB OVER {r['bound_mib']:.0f}", "1"))
    if not rows:
        return
    print("\nThe paper (Gouranton et al. §4; 4+1 nodes, GeForce-class boards) beside this run (2 shared cores, llvmpipe):")
    print(f"  {'figure':<40} {'paper':<20} {'ours':<34} layers")
    for name, paper, ours, ls in rows:
        print(f"  {name:<40} {paper:<20} {ours:<34} {ls}")
    res["paper_table"] = [dict(zip(("figure", "paper", "ours", "layers"), r)) for r in rows]


def run(args) -> int:
    from ...core.errors import ConfigError

    workdir = Path(args.workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    sections = [s.strip() for s in args.sections.split(",") if s.strip()]
    bad = [s for s in sections if s not in SECTIONS]
    if bad:
        raise ConfigError(f"--sections: unknown {bad}; use a subset of {', '.join(SECTIONS)}")
    layer_counts = parse_counts(args.layers)
    store = layer_store(workdir)
    runs = Runs(workdir, store, args.frames)
    res: dict = {"store": str(store), "note": "wall-clock on a shared 2-core machine; compare ratios", "section_s": {}}
    steps = {"speedup": lambda: _speedup(args, runs, layer_counts, res), "fig6": lambda: _fig6(args, runs, layer_counts, res),
             "fig7": lambda: _fig7(args, runs, layer_counts, res), "t1t2": lambda: _t1t2(args, runs, res),
             "rss": lambda: _rss(args, workdir, res)}
    for name in SECTIONS:
        if name in sections:
            t0 = time.perf_counter()
            steps[name]()
            res["section_s"][name] = round(time.perf_counter() - t0, 1)
            print(f"  ({name}: {res['section_s'][name]:.0f} s)", flush=True)
            (workdir / "results.json").write_text(json.dumps({**res, "run_wall_s": runs.wall_s}, indent=2) + "\n")
    _paper_table(res)
    res["run_wall_s"] = runs.wall_s
    (workdir / "results.json").write_text(json.dumps(res, indent=2) + "\n")
    print(f"wrote {workdir / 'results.json'}")
    return 0
