"""The stage-breakdown plot of ``massview bench frame``: per rank count, a stacked bar of the
measured stage times (slowest rank, mean over frames) beside a thin stacked bar of their floors,
and the frame periods (1 / throughput) of the synchronous and the pipelined loop as markers."""

from __future__ import annotations

from pathlib import Path

__all__ = ["plot_stages"]

_COLORS = {"lod": "#8c6bb1", "draw": "#2b8cbe", "readback": "#7bccc4", "encode": "#fdae6b", "transfer": "#e6550d", "composite": "#a63603",
           "finish": "#74c476", "other": "#bdbdbd"}


def plot_stages(results: list[dict], path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .frame import STAGES

    fig, ax = plt.subplots(figsize=(9, 4.2), dpi=100)
    labels = []
    for i, r in enumerate(results):
        s = r["sync"]
        base = fbase = 0.0
        for k, stage in enumerate(STAGES):
            ax.bar(i - 0.12, s["stage_ms"][k], 0.5, bottom=base, color=_COLORS[stage], label=stage if i == 0 else None)
            ax.bar(i + 0.27, s["floor_ms"][k], 0.14, bottom=fbase, color=_COLORS[stage], hatch="//", edgecolor="white")
            base += s["stage_ms"][k]
            fbase += s["floor_ms"][k]
        ax.plot([i - 0.37, i + 0.13], [1e3 / s["throughput_fps"]] * 2, color="black", lw=1.5, label="frame period, sync" if i == 0 else None)
        period = 1e3 / r["pipelined"]["throughput_fps"]
        ax.plot([i - 0.37, i + 0.13], [period] * 2, color="black", ls="--", lw=1.5, label="frame period, pipelined" if i == 0 else None)
        labels.append(f"{r['ranks']} rank{'s' if r['ranks'] > 1 else ''}\nLP {r['lp_threads']}")
    ax.set_xticks(range(len(results)), labels)
    ax.set_ylabel("ms per frame (each stage: its slowest rank)")
    ax.set_title(title + "\nwide bars: each stage of its slowest rank (so their stack may exceed the frame period); "
                 "narrow hatched bars: floors", fontsize=9)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
