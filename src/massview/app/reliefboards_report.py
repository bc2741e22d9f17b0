"""Plots of M2 runs as the paper's figures (Süß et al. 2010, §7).

* :func:`write_run_report` — one run (``massview report DIR``): frame time along the path with
  boards against all-original geometry when the run had ``--reference`` (Figure 10), triangles
  drawn by kind, requests issued/answered/pending, and the angle-error distribution.
* :func:`write_backend_figures` — runs with 1, 2, 4, 8 … backends (``massview bench
  reliefboards``): mean and maximum response time against the number of backends (Figure 9) and
  the angle-error distribution per backend count with min, max, quartiles and mean (Figure 11).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["write_run_report", "write_backend_figures"]


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def write_run_report(out: Path, records: list[dict], summary: dict) -> Path:
    """``DIR/report.png`` of one M2 run."""
    plt = _plt()
    recs = sorted(records, key=lambda r: r["frame"])
    f = np.array([r["frame"] for r in recs])
    c = [r["counters"] for r in recs]
    fig, ax = plt.subplots(2, 2, figsize=(11, 7))
    a = ax[0, 0]
    a.plot(f, [r["times_ms"]["total"] for r in recs], "k-", lw=1.5, label="with Reliefboards")
    ref = [(fr, k["ref_frame_ms"]) for fr, k in zip(f, c) if "ref_frame_ms" in k]
    if ref:  # every frame, or every k-th with --reference-every
        a.plot(*zip(*ref), "r.-", lw=1, label="all original geometry")
    a.set_ylabel("frame time (ms)")
    a.set_title("frame time along the path (paper Fig. 10)")
    a.legend(fontsize=8)
    b = ax[0, 1]
    kinds = [("tris_near", "near zone + infeasible"), ("tris_far_original", "far originals"), ("tris_board", "Reliefboards")]
    b.stackplot(f, *[np.array([k[key] for k in c]) / 1e3 for key, _ in kinds], labels=[lbl for _, lbl in kinds], alpha=0.8)
    b.set_ylabel("triangles drawn (k)")
    b.legend(fontsize=8, loc="upper right")
    r = ax[1, 0]
    r.plot(f, np.cumsum([k.get("requests", 0) for k in c]), label="requests issued")
    r.plot(f, np.cumsum([k.get("answered", 0) for k in c]), label="answered")
    r.plot(f, [k["pending"] for k in c], label="pending")
    r.set_xlabel("frame")
    r.set_ylabel("requests")
    r.legend(fontsize=8)
    h = ax[1, 1]
    angles = [x for k in c for x in k.get("angle_error", [])]
    h.hist(angles, bins=np.arange(0, 46, 1.5), color="tab:blue")
    h.set_xlabel("angle error of the boards drawn (deg)")
    h.set_ylabel("board draws")
    rt = summary.get("response_ms", {})
    h.set_title(f"response mean {rt.get('mean', '-')} ms, max {rt.get('max', '-')} ms", fontsize=9)
    fig.suptitle(f"{summary.get('scene', '')} · reliefboards · {summary.get('backends', '?')} backends", fontsize=10)
    fig.tight_layout()
    path = out / "report.png"
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def write_backend_figures(path: Path, runs: dict[int, dict], title: str = "") -> Path:
    """Figures 9 and 11 from ``runs[backends] = {"response_ms": [...], "angle_error": [...]}``."""
    plt = _plt()
    nb = sorted(runs)
    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4))
    mean = [np.mean(runs[n]["response_ms"]) if runs[n]["response_ms"] else np.nan for n in nb]
    mx = [np.max(runs[n]["response_ms"]) if runs[n]["response_ms"] else np.nan for n in nb]
    a.plot(nb, mean, "o-", label="mean")
    a.plot(nb, mx, "s--", label="max")
    a.set_xscale("log", base=2)
    a.set_xticks(nb, [str(n) for n in nb])
    a.set_xlabel("backends")
    a.set_ylabel("response time (ms)")
    a.set_title("response time (paper Fig. 9)")
    a.legend(fontsize=8)
    data = [runs[n]["angle_error"] or [0.0] for n in nb]
    b.boxplot(data, whis=(0, 100), showmeans=True)
    b.set_xticks(range(1, len(nb) + 1), [str(n) for n in nb])
    b.set_xlabel("backends")
    b.set_ylabel("angle error (deg)")
    b.set_title("angle error: min, quartiles, max, mean (paper Fig. 11)")
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def m2_runs(folder: Path) -> dict[str, dict[int, Path]]:
    """Sub-folders of ``folder`` holding M2 runs, as ``{scene: {backends: run folder}}``."""
    import json

    found: dict[str, dict[int, Path]] = {}
    for sub in sorted(p for p in Path(folder).iterdir() if (p / "summary.json").exists() and (p / "stats.jsonl").exists()):
        s = json.loads((sub / "summary.json").read_text())
        if s.get("system") == "reliefboards":
            found.setdefault(Path(str(s["scene"])).name, {})[int(s["backends"])] = sub
    return found


def write_collection_report(folder: Path) -> list[Path]:
    """Figures 9 and 11 for every scene among the M2 runs under ``folder`` (``massview report
    DIR`` on a folder of runs, e.g. a ``bench reliefboards`` workdir)."""
    from ..core.stats import read_stats

    out = []
    for scene, runs in m2_runs(folder).items():
        data = {}
        for nb, sub in runs.items():
            recs = read_stats(sub / "stats.jsonl")
            data[nb] = {"response_ms": [x for r in recs for x in r["counters"].get("response_ms", [])],
                        "angle_error": [x for r in recs for x in r["counters"].get("angle_error", [])]}
        out.append(write_backend_figures(Path(folder) / f"report-{scene}.png", data, f"{scene} · reliefboards"))
    return out
