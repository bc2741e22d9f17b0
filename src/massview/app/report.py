"""``massview report DIR``: a table of the summary and ``DIR/report.png`` (frame time per frame,
per-rank load per frame), both from ``stats.jsonl``."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..core.errors import ConfigError
from ..core.stats import read_stats, summarize

__all__ = ["print_summary", "write_report"]


def load_run(out: Path) -> tuple[dict, list[dict]]:
    sfile, jfile = out / "summary.json", out / "stats.jsonl"
    if not jfile.exists():
        raise ConfigError(f"{out}: no stats.jsonl here; give the --out folder of a `massview render` run")
    records = read_stats(jfile)
    summary = json.loads(sfile.read_text()) if sfile.exists() else summarize(records)
    return summary, records


def print_summary(summary: dict, console=None) -> None:
    from rich.console import Console
    from rich.table import Table

    console = console or Console()
    t = Table(title="massview run", show_header=True)
    t.add_column("figure")
    t.add_column("value", justify="right")
    for key in ("scene", "decomposition", "compositor", "ranks", "frames", "size", "mean_frame_ms", "fps",
                "triangles_per_frame", "imbalance", "bytes_per_frame", "max_abs_diff", "diff_fraction", "renderer"):
        if key in summary and summary[key] is not None:
            v = summary[key]
            if key == "bytes_per_frame":
                v = f"{v / 1e6:.3f} MB"
            elif key == "triangles_per_frame":
                v = f"{v / 1e6:.3f} M"
            elif key == "size":
                v = "x".join(str(a) for a in v)
            t.add_row(key, str(v))
    if "triangles_per_rank" in summary:
        t.add_row("triangles_per_rank", ", ".join(f"{v / 1e3:.1f}k" for v in summary["triangles_per_rank"]))
    if "stage_ms_mean" in summary:
        t.add_row("stage ms (mean)", ", ".join(f"{k} {v:.1f}" for k, v in summary["stage_ms_mean"].items()))
    console.print(t)


def write_report(out: Path, records: list[dict], summary: dict) -> Path:
    if summary.get("system") == "reliefboards":
        from .reliefboards_report import write_run_report

        return write_run_report(out, records, summary)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    frames = sorted({r["frame"] for r in records})
    ranks = sorted({r["rank"] for r in records})
    total = np.zeros((len(frames), len(ranks)))
    tri = np.zeros_like(total)
    for r in records:
        i, j = frames.index(r["frame"]), ranks.index(r["rank"])
        total[i, j] = r["times_ms"].get("total", 0.0)
        tri[i, j] = r["triangles"]
    fig, (a, b) = plt.subplots(2, 1, figsize=(9, 6.5), sharex=True)
    a.plot(frames, total.max(axis=1), "k-", lw=2, label="frame (max over ranks)")
    for j, rk in enumerate(ranks):
        a.plot(frames, total[:, j], lw=1, alpha=0.6, label=f"rank {rk}")
    a.set_ylabel("time (ms)")
    a.legend(fontsize=7, ncol=3)
    a.set_title(f"{summary.get('scene', '')} · {summary.get('decomposition', '')} · {summary.get('compositor', '')} · {len(ranks)} ranks")
    for j, rk in enumerate(ranks):
        b.plot(frames, tri[:, j] / 1e3, lw=1.5, label=f"rank {rk}")
    b.set_ylabel("triangles per rank (k)")
    b.set_xlabel("frame")
    b.legend(fontsize=7, ncol=4)
    fig.tight_layout()
    path = out / "report.png"
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
