"""Per-frame, per-rank statistics: the source of every report, plot and benchmark.

A :class:`FrameStats` records stage times in milliseconds (``lod`` = LOD/cull, ``draw``,
``readback``, ``encode``, ``transfer``, ``composite``, ``total``), triangles drawn, bytes sent
and received, and free-form counters (patches, blocks, cache hits ...). One JSON line per frame
per rank goes to ``stats.jsonl``.
"""

from __future__ import annotations

import json
import os
import re
import time
from contextlib import contextmanager
from dataclasses import dataclass, field

import numpy as np

__all__ = ["STAGES", "PARTS", "FrameStats", "summarize", "read_stats", "clear_run_outputs"]

STAGES = ("lod", "draw", "readback", "encode", "transfer", "composite", "total")
PARTS = ("vis_load", "vis_issue", "vis_retrieve")  # parts of M1's ``visibility`` stage (timed inside it)


@dataclass
class FrameStats:
    frame: int
    rank: int
    times_ms: dict[str, float] = field(default_factory=lambda: {s: 0.0 for s in STAGES})
    triangles: int = 0
    bytes_sent: int = 0
    bytes_recv: int = 0
    counters: dict[str, float] = field(default_factory=dict)

    @contextmanager
    def stage(self, name: str):
        """Add the wall time of the ``with`` body to stage ``name``."""
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.times_ms[name] = self.times_ms.get(name, 0.0) + (time.perf_counter() - t0) * 1e3

    def count(self, name: str, value: float = 1) -> None:
        self.counters[name] = self.counters.get(name, 0) + value

    def to_json(self) -> dict:
        return {
            "frame": self.frame,
            "rank": self.rank,
            "times_ms": {k: round(v, 4) for k, v in self.times_ms.items()},
            "triangles": int(self.triangles),
            "bytes_sent": int(self.bytes_sent),
            "bytes_recv": int(self.bytes_recv),
            "counters": self.counters,
        }


_FRAME_FILE = re.compile(r"^\d{5,}\.(png|npy)$")  # a run's numbered frames (NNNNN.png) and depth arrays (NNNNN.npy)
_FRAME_DIRS = ("frames", "depth")  # and wall/rRcC/, wall_depth/rRcC/ (one folder per display tile)


def clear_run_outputs(out) -> int:
    """Remove what an earlier run left in the output folder ``out`` before a new run writes
    there: first its ``summary.json`` (so a new run that is interrupted never leaves a folder
    that looks finished), then ``stats.jsonl``, ``report.png`` and ``video.mp4`` (made from the
    old frames), and the numbered frames and depth arrays in
    ``frames/``, ``depth/``, ``wall/…/`` and ``wall_depth/…/`` (a 2-frame run after a 5-frame
    one left frames 2–4 of the old run beside the new ones), and those folders where that
    leaves them empty. Nothing else is touched: files of other names, other folders. Returns
    how many files were removed."""
    out = os.fspath(out)
    removed = 0
    for name in ("summary.json", "stats.jsonl", "report.png", "video.mp4"):
        try:
            os.unlink(os.path.join(out, name))
            removed += 1
        except FileNotFoundError:
            pass
    folders = [os.path.join(out, d) for d in _FRAME_DIRS]
    for wall in ("wall", "wall_depth"):
        w = os.path.join(out, wall)
        if os.path.isdir(w):
            folders += [os.path.join(w, t) for t in sorted(os.listdir(w)) if re.fullmatch(r"r\d+c\d+", t)]
    for d in folders:
        if not os.path.isdir(d):
            continue
        for name in os.listdir(d):
            if _FRAME_FILE.match(name) and os.path.isfile(os.path.join(d, name)):
                os.unlink(os.path.join(d, name))
                removed += 1
    for d in folders + [os.path.join(out, w) for w in ("wall", "wall_depth")]:  # (tiles first, then their parents)
        try:
            os.rmdir(d)  # only where it is empty now: a run without depth left an old empty depth/ beside its frames
        except OSError:
            pass
    return removed


def read_stats(path) -> list[dict]:
    with open(path) as f:
        return [json.loads(line) for line in f if line.strip()]


def _busy_summary(records: list[dict], frames: list, work_ranks, fi: dict) -> tuple[dict, float | None, dict] | None:
    """Where ranks time only their own stages and no ``total`` (M1's clients; the server's
    period is the frame time): (the mean of each stage those ranks time, over their records,
    with ``busy``, a frame's sum of them; the max ÷ mean busy time a frame over them; the
    summary's ``stage_ms_over`` and ``time_imbalance_of`` keys), or None where there are none.
    The ranks are the work ranks without a ``total`` (all ranks without one where no work
    ranks are given)."""
    bare = {r["rank"] for r in records} - {r["rank"] for r in records if r["times_ms"].get("total", 0.0) > 0}
    own = sorted(bare & set(work_ranks)) if work_ranks else sorted(bare)
    mine = [r for r in records if r["rank"] in own]
    keys = [k for k in STAGES if k != "total"]
    keys += sorted({k for r in mine for k in r["times_ms"]} - set(STAGES) - set(PARTS))
    keys = [k for k in keys if "." not in k and any(r["times_ms"].get(k, 0.0) for r in mine)]
    if not mine or not keys:
        return None
    busy = np.zeros((len(frames), len(own)))
    col = {r: j for j, r in enumerate(own)}
    for r in mine:
        busy[fi[r["frame"]], col[r["rank"]]] = sum(r["times_ms"].get(k, 0.0) for k in keys)
    means = {k: float(np.mean([r["times_ms"].get(k, 0.0) for r in mine])) for k in keys}
    means["busy"] = float(busy.mean())
    m = busy.mean(axis=1)
    ok = m > 0
    timb = round(float((busy[ok].max(axis=1) / m[ok]).mean()), 4) if ok.any() else None
    return means, timb, {"stage_ms_over": f"ranks {', '.join(map(str, own))}", "time_imbalance_of": "busy"}


def summarize(records: list[dict], work_ranks=None, **extra) -> dict:
    """Summary of per-frame per-rank records: frame time is the max ``total`` over ranks.
    ``imbalance`` (max ÷ mean triangles a frame) and ``time_imbalance`` (max ÷ mean ``total``
    a frame) are over ``work_ranks`` where given: the ranks that share the drawing (T2's
    computation ranks, M1's clients), not those that never draw by their role.
    ``stage_ms_mean`` has each stage's mean over the records (:data:`STAGES`, then any other
    stage the records time, e.g. the frame loop's ``finish``) and ``other``: the part of
    ``total`` in none of them (waiting for the slowest rank; in the first frame, setting up).
    Where work ranks record no ``total`` (M1's clients time only their stages: the server's
    period is the frame time), ``stage_ms_mean`` is over those ranks' records, their own stages
    and ``busy`` (a frame's sum of them), and ``time_imbalance`` is the max ÷ mean busy time a
    frame over them (``stage_ms_over`` names the ranks, ``time_imbalance_of`` is "busy")."""
    frames = sorted({r["frame"] for r in records})
    ranks = sorted({r["rank"] for r in records})
    if not frames:
        return {"frames": 0, "ranks": 0, **extra}
    tri = np.zeros((len(frames), len(ranks)))
    total = np.zeros_like(tri)
    sent = np.zeros_like(tri)
    fi = {f: i for i, f in enumerate(frames)}
    ri = {r: i for i, r in enumerate(ranks)}
    for r in records:
        i, j = fi[r["frame"]], ri[r["rank"]]
        tri[i, j] = r["triangles"]
        total[i, j] = r["times_ms"].get("total", 0.0)
        sent[i, j] = r["bytes_sent"]
    frame_ms = total.max(axis=1)
    work = [ri[r] for r in (work_ranks or ()) if r in ri] or list(range(len(ranks)))
    mean_tri = tri[:, work].mean(axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        imb = np.where(mean_tri > 0, tri[:, work].max(axis=1) / np.where(mean_tri > 0, mean_tri, 1), 1.0)
    stage_means = {}
    for s in STAGES:
        vals = [r["times_ms"].get(s, 0.0) for r in records]
        stage_means[s] = float(np.mean(vals))
    timb = None
    if all(r["times_ms"].get("total", 0.0) > 0 for r in records):  # (walk7 L4: 44 % of a frame was in no listed stage)
        more = sorted(k for k in {k for r in records for k in r["times_ms"]} - set(STAGES) - set(PARTS)
                      if "." not in k)  # (dotted keys, piece.decode, cpu.wait …, are parts of the compositing stages)
        for s in more:
            stage_means[s] = float(np.mean([r["times_ms"].get(s, 0.0) for r in records]))
        listed = [k for k in stage_means if k != "total"]
        stage_means["other"] = float(np.mean([max(r["times_ms"]["total"] - sum(r["times_ms"].get(k, 0.0) for k in listed), 0.0)
                                              for r in records]))
        mean_total = total[:, work].mean(axis=1)
        timb = round(float((total[:, work].max(axis=1) / mean_total).mean()), 4)
    busy = _busy_summary(records, frames, work_ranks, fi) if timb is None else None  # M1: its clients time only their
    stage_means, timb, busy_of = busy or (stage_means, timb, {})                       # own stages (walk8 M1)
    mean_frame_ms = float(frame_ms.mean())
    return {
        "frames": len(frames),
        "ranks": len(ranks),
        **extra,
        **busy_of,
        "mean_frame_ms": round(mean_frame_ms, 3),
        "fps": round(1000.0 / mean_frame_ms, 3) if mean_frame_ms > 0 else None,
        "triangles_per_rank": [float(v) for v in tri.mean(axis=0)],
        "triangles_per_frame": float(tri.sum(axis=1).mean()),
        "imbalance": round(float(imb.mean()), 4),
        "time_imbalance": timb,
        "bytes_per_frame": float(sent.sum(axis=1).mean()),
        "stage_ms_mean": {k: round(v, 3) for k, v in stage_means.items()},
    }
