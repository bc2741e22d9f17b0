"""``massview report DIR``: a table of the summary and ``DIR/report.png`` (frame time per frame,
per-rank load per frame), both from ``stats.jsonl``."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..core.errors import ConfigError
from ..core.stats import PARTS, read_stats, summarize

__all__ = ["print_summary", "write_report"]


def load_run(out: Path, notes: list | None = None) -> tuple[dict, list[dict]]:
    """(summary, records) of a render's --out folder. A last line of ``stats.jsonl`` cut short
    (a run killed while writing it) is left out, and a ``summary.json`` that does not parse
    is recomputed from the records, each with a line in ``notes``; a bad line before the last
    is a ConfigError naming the file and line."""
    sfile, jfile = out / "summary.json", out / "stats.jsonl"
    notes = notes if notes is not None else []
    if not jfile.exists():
        raise ConfigError(f"{out}: no stats.jsonl here; give the --out folder of a `massview render` run")
    lines = [(n, line) for n, line in enumerate(jfile.read_text(errors="replace").splitlines(), 1) if line.strip()]
    records = []
    for k, (n, line) in enumerate(lines):
        try:
            rec = json.loads(line)
            if not (isinstance(rec, dict) and {"frame", "rank"} <= set(rec)):
                raise ValueError("not a frame record")
        except ValueError as e:
            if k == len(lines) - 1:
                notes.append(f"{jfile}: line {n} is cut short (the run stopped while writing it); left out")
                break
            raise ConfigError(f"{jfile}: line {n} is not a frame record ({e}); the file is damaged") from None
        records.append(rec)
    if not records:
        raise ConfigError(f"{jfile}: no frame records; the run wrote none (see its output)")
    summary = None
    if sfile.exists():
        try:
            summary = json.loads(sfile.read_text())
        except ValueError:
            notes.append(f"{sfile} does not parse (the run did not finish?); the figures below are recomputed from stats.jsonl")
    if not isinstance(summary, dict):
        summary = summarize(records)
        n = summary["frames"]
        summary["interrupted_after"] = n
        if not sfile.exists():
            notes.append(f"{out}: no summary.json: the run was interrupted after {n} frame{'' if n == 1 else 's'} (or is still "
                         "running); the figures below are of those frames")
    return summary, records


def print_summary(summary: dict, console=None) -> None:
    from rich.console import Console
    from rich.table import Table

    console = console or Console()
    cut = summary.get("interrupted_after")
    t = Table(title="massview run" + (f" (interrupted after {cut} frames)" if cut is not None else ""), show_header=True)
    t.add_column("figure")
    t.add_column("value", justify="right")
    if summary.get("system") == "reliefboards":  # M2: its records are the visualization rank's frames
        from .reliefboards_cmds import summary_lines

        b = summary.get("backends")
        for key in ("scene", "frames", "size", "fps", "renderer"):
            if summary.get(key) is not None:
                t.add_row(key, "x".join(map(str, summary[key])) if key == "size" else str(summary[key]))
        if b is not None:
            t.add_row("ranks", f"{b + 1} (1 visualization + {b} backends)")
        for line in summary_lines(summary).splitlines():
            k, _, v = line.partition(": ")
            t.add_row(k, v)
        for w in summary.get("warnings", []):
            t.add_row("warning", w)
        console.print(t)
        return
    for key in ("scene", "system", "decomposition", "compositor", "ranks", "roles", "wall", "frames", "size", "mean_frame_ms", "fps",
                "triangles_per_frame", "imbalance", "time_imbalance", "bytes_per_frame", "max_abs_diff", "diff_fraction", "renderer"):
        if key in summary and summary[key] is not None:
            v = summary[key]
            if key == "bytes_per_frame":
                v = f"{v / 1e6:.3f} MB"
            elif key == "triangles_per_frame":
                v = f"{v / 1e6:.3f} M"
            elif key == "size":
                v = "x".join(str(a) for a in v)
            elif key == "roles":
                v = ", ".join(f"{r}: {role}" for r, role in enumerate(v))
            over = f", over the {'computation ranks' if summary.get('system') == 'roettger' else 'clients'}" if summary.get("roles") else ""
            if key == "imbalance":  # (walk7 L4: a triangle figure beside the timings, unlabelled)
                key, v = "imbalance (triangles)", f"{v} (max ÷ mean a frame{over})"
            elif key == "time_imbalance":
                busy = summary.get("time_imbalance_of") == "busy"  # (M1: the clients' busy time, the sum of their stages)
                key, v = f"imbalance ({'busy time' if busy else 'frame time'})", f"{v} (max ÷ mean a frame{over})"
            t.add_row(key, str(v))
    if "triangles_per_rank" in summary:
        t.add_row("triangles_per_rank", ", ".join(f"{v / 1e3:.1f}k" for v in summary["triangles_per_rank"]))
    if "stage_ms_mean" in summary:
        over = f", {summary['stage_ms_over']}" if summary.get("stage_ms_over") else ""
        t.add_row(f"stage ms (mean{over})", ", ".join(f"{k} {v:.1f}" for k, v in summary["stage_ms_mean"].items()))
    console.print(t)


NESTED_STAGES = ("total", *PARTS)  # the frame itself; parts of M1's "visibility"


def rank_times(records: list[dict]):
    """(frames, ranks, ms (frames, ranks), busy (ranks,) bool, triangles (frames, ranks)) for the
    report's plots: each record's ``total`` (its frame time); a rank whose records have no
    total (M1's clients: the server's frame period is the frame time) gets the sum of its
    stage times instead, with ``busy`` set, rather than a line at 0 ms."""
    frames = sorted({r["frame"] for r in records})
    ranks = sorted({r["rank"] for r in records})
    fi, ri = {f: i for i, f in enumerate(frames)}, {r: j for j, r in enumerate(ranks)}
    total = np.zeros((len(frames), len(ranks)))
    stages = np.zeros_like(total)
    tri = np.zeros_like(total)
    for r in records:
        i, j = fi[r["frame"]], ri[r["rank"]]
        t = r["times_ms"]
        total[i, j] = t.get("total", 0.0)
        stages[i, j] = sum(v for k, v in t.items() if k not in NESTED_STAGES)
        tri[i, j] = r["triangles"]
    busy = ~total.any(axis=0) & stages.any(axis=0)
    total[:, busy] = stages[:, busy]
    return frames, ranks, total, busy, tri


def write_report(out: Path, records: list[dict], summary: dict) -> Path:
    if summary.get("system") == "reliefboards":
        from .reliefboards_report import write_run_report

        return write_run_report(out, records, summary)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    frames, ranks, total, busy, tri = rank_times(records)
    from matplotlib.ticker import MaxNLocator

    mark = dict(marker="o", ms=4 if len(frames) < 30 else 0)  # (one frame: a line of one point shows nothing)
    fig, (a, b) = plt.subplots(2, 1, figsize=(9, 6.5), sharex=True)
    framed = total[:, ~busy] if (~busy).any() else total
    a.plot(frames, framed.max(axis=1), "-", color="0.75", lw=5, label="frame (max over ranks)", **mark)  # under the ranks' lines
    for j, rk in enumerate(ranks):
        if busy[j]:  # no frame time of its own (M1's clients): the sum of its stages, dashed
            a.plot(frames, total[:, j], "--", lw=1.2, label=f"rank {rk}: busy (sum of its stages)", **mark)
        else:
            a.plot(frames, total[:, j], lw=1.2, label=f"rank {rk}", **mark)
    a.set_ylabel("time (ms)")
    a.legend(fontsize=7, ncol=3)
    cut = summary.get("interrupted_after")
    system = summary.get("system")
    a.set_title(f"{summary.get('scene', '')} · " + (f"--system {system} · " if system not in (None, "auto") else "")
                + f"{summary.get('decomposition', '')} · {summary.get('compositor', '')} · {len(ranks)} ranks"
                + (f" · interrupted after {cut} frames" if cut is not None else ""))
    roles = summary.get("roles") or []
    for j, rk in enumerate(ranks):
        role = f" ({roles[rk]})" if rk < len(roles) and roles[rk] else ""
        b.plot(frames, tri[:, j] / 1e3, lw=1.5, label=f"rank {rk}{role}", **mark)
    b.set_ylabel("triangles per rank (k)")
    b.set_xlabel("frame")
    b.xaxis.set_major_locator(MaxNLocator(integer=True))
    a.set_ylim(bottom=0)  # from 0: a 0.03 % spread between ranks is not drawn as the whole height
    b.set_ylim(bottom=0)
    if len(frames) == 1:
        b.set_xlim(frames[0] - 1, frames[0] + 1)
    b.legend(fontsize=7, ncol=4)
    fig.tight_layout()
    path = out / "report.png"
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
