"""The M2 runner below app/: one rank's run, its §7 summary, and M2 jobs for the Python API.

M2 runs its own role loop (one visualization rank, N-1 backends) rather than the collective
frame loop of ``massview render``. :func:`run` is one rank of it (the CLI's ``massview render
--system reliefboards``, the viewer's and the API's jobs all call it): it writes lossless PNG
frames, ``stats.jsonl`` and ``summary.json`` with the §7 figures — frame time, triangles by
kind, requests, mean/max response time, angle-error distribution (min, quartiles, mean, max),
time to a complete view, per-backend loads (Süß et al. 2010, §7).

:func:`render_reliefboards` is :func:`massview.api.render` for ``system="reliefboards"``: the
scene name, the frozen :class:`RenderConfig`, the :class:`ReliefboardOptions` and the cameras
(or the path name, resolved on the visualization rank exactly as the CLI does) are pickled into
a temporary job folder; ``python -m massview __m2job DIR`` runs :func:`run_job` on every rank
through the runtime's ``relaunch``, and this process reads the outputs back: the visualization
rank's pixels bit for bit. Inside an MPI job already, the call is collective and returns on
rank 0.

The M2 parameters are given as ``ReliefboardOptions(...)`` or a dict of its fields and of
:class:`~massview.lod.boardpolicy.BoardPolicy`'s (``t_nz``, ``epsilon_deg``, ``p``, ...).
"""

from __future__ import annotations

import json
import pickle
import shutil
import sys
import tempfile
from dataclasses import fields
from pathlib import Path

import numpy as np

from ..core.config import RenderConfig
from ..core.errors import ConfigError, MassviewError, OutputError, RankJobError
from ..core.paths import load_path
from ..core.stats import clear_run_outputs, summarize
from ..lod.walk import fit_path

__all__ = ["board_options", "render_reliefboards", "run_job", "run", "m2_summary"]


def _quantiles(values) -> dict:
    v = np.asarray(values, np.float64)
    if v.size == 0:
        return {"count": 0}
    q = [round(float(x), 3) for x in np.percentile(v, [0, 25, 50, 75, 100])]
    return {"count": int(v.size), "min": q[0], "q1": q[1], "median": q[2], "q3": q[3], "max": q[4], "mean": round(float(v.mean()), 3)}


def m2_summary(records: list[dict]) -> dict:
    """The §7 figures of a run from its per-frame records."""
    c = [r["counters"] for r in records]
    frame_ms = np.array([r["times_ms"]["total"] for r in records])
    resp = [x for k in c for x in k.get("response_ms", [])]
    angles = [x for k in c for x in k.get("angle_error", [])]
    complete = [i for i, k in enumerate(c) if k.get("view_complete")]
    t_complete = float(frame_ms[: complete[0] + 1].sum()) if complete else None
    return {
        "frame_ms_p50": round(float(np.percentile(frame_ms, 50)), 3),
        "frame_ms_p99": round(float(np.percentile(frame_ms, 99)), 3),
        "tris_near_mean": float(np.mean([k["tris_near"] for k in c])),
        "tris_far_original_mean": float(np.mean([k["tris_far_original"] for k in c])),
        "tris_board_mean": float(np.mean([k["tris_board"] for k in c])),
        "requests": int(sum(k.get("requests", 0) for k in c)),
        "answered": int(sum(k.get("answered", 0) for k in c)),
        "pending_at_end": int(c[-1]["pending"]) if c else 0,
        "response_ms": _quantiles(resp),
        "angle_error_deg": _quantiles(angles),
        "frames_with_far_objects": int(sum(1 for k in c if k.get("far_objects", 1))),
        "boards_drawn": int(sum(k.get("boards_drawn", 0) for k in c)),
        "first_complete_frame": complete[0] if complete else None,
        "ms_to_complete_view": round(t_complete, 3) if t_complete is not None else None,
        "loads_per_backend": np.sum([k.get("loads", []) for k in c if k.get("loads")], axis=0).tolist() if c else [],
        "board_passes_on_visualization_rank": int(max((k.get("board_passes_here", 0) for k in c), default=0)),
    }


def _write_png(path: Path, image) -> None:
    from PIL import Image as PILImage

    path.parent.mkdir(parents=True, exist_ok=True)
    PILImage.fromarray(image.color[..., :3]).save(path, compress_level=1)


def run(comm, scene: str, cfg: RenderConfig, opts, out: Path | None, quiet: bool = True, write_frames: bool = True,
        cameras=None):
    """Render ``cfg.frames`` frames of ``cfg.path`` (or the given ``cameras``, needed on rank 0
    only) with M2; returns the summary on rank 0."""
    from .boardscene import open_board_objects
    from .reliefboards import run_reliefboards

    rank = comm.Get_rank()
    fovy = 45.0
    objects = open_board_objects(scene, opts.cluster_params(cfg.height, fovy))
    if rank == 0 and cameras is None:
        # (walkthrough: round the objects, on the scene's ground, as the other systems)
        cameras = fit_path(cfg.path, *objects.bounds, objects.obstacles).cameras(cfg.frames, cfg.width, cfg.height)
    if rank == 0 and cameras and abs(cameras[0].fovy - fovy) > 1e-9:
        raise ConfigError(f"--path {cfg.path}: the reliefboards system classifies objects for fovy {fovy}, the path has {cameras[0].fovy}")
    warnings = board_warnings(objects, cameras, opts.policy) if rank == 0 else []
    if rank == 0 and not quiet:
        for w in warnings:
            print(f"massview: warning: {w}", file=sys.stderr, flush=True)
    stats_file = None
    if rank == 0 and out is not None:
        out.mkdir(parents=True, exist_ok=True)
        clear_run_outputs(out)  # an earlier run's frames, stats and summary
        stats_file = open(out / "stats.jsonl", "w")

    def sink(f, image, stats):
        if stats_file is not None:
            if write_frames:
                _write_png(out / "frames" / f"{f:05d}.png", image)
            stats_file.write(json.dumps(stats.to_json()) + "\n")

    try:
        res = run_reliefboards(comm, objects, opts, cameras, sink, cfg.reference, cfg.egl_device, cfg.color_by_rank)
    finally:
        if stats_file is not None:
            stats_file.close()
    if res is None:
        return None
    summary = _summary(res, scene, cfg, opts, objects, comm.Get_size() - 1)
    summary["warnings"] = warnings
    if out is not None:
        (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    return summary


def board_warnings(objects, cameras, policy) -> list[str]:
    """What will keep this run from drawing boards, said before it starts: no feasible object
    (every object drawn as geometry: §4's clusters are too large or too small for this scene
    and t_nz), or a path that turns so fast about the objects that a board, which arrives a
    frame or more after its request, is already past the angle error E when it could be drawn
    (the median over feasible objects of the angle between consecutive eyes ≥ E/2)."""
    out = []
    feasible = np.flatnonzero(objects.feasible)
    if len(feasible) == 0:
        out.append(f"no object of this scene can get a board ({objects.count} objects, 0 feasible at t_nz = {policy.t_nz:,}): "
                   "every object is drawn as geometry. A scene store's clusters (`massview prepare reliefboards`) say why; "
                   "a larger scene, or a lower --tnz (and --min-triangles) for both commands, gives feasible ones")
    elif cameras is not None and len(cameras) > 1:
        eyes = np.array([c.position for c in cameras], np.float64)
        c = objects.centers[feasible]
        d = eyes[None, :, :] - c[:, None, :]
        d /= np.maximum(np.linalg.norm(d, axis=2, keepdims=True), 1e-12)
        step = np.degrees(np.arccos(np.clip(np.sum(d[:, 1:] * d[:, :-1], axis=2), -1.0, 1.0)))
        typical = float(np.median(step))
        if typical >= policy.max_error_deg / 2:
            out.append(f"the path moves {typical:.0f}° per frame about the feasible objects (median); a board is drawn only within "
                       f"E = {policy.max_error_deg:g}° of the view it was made for and arrives a frame or more after its request, "
                       "so few or no boards will be drawn: give more --frames")
    return out


def _summary(res, scene: str, cfg: RenderConfig, opts, objects, backends: int) -> dict:
    records, extra = res
    summary = summarize(records, scene=scene, system="reliefboards", size=[cfg.width, cfg.height], path=cfg.path,
                        renderer=extra["renderer"], backends=backends)
    summary.update(m2_summary(records))
    summary.update(objects=objects.count, feasible=int(objects.feasible.sum()), d_nz=objects.d_nz, sl_c=objects.sl_c,
                   t_nz=opts.t_nz, late_boards=extra["late_boards"], backend_counters=extra["backends"])
    refs = [r["counters"] for r in records if "ref_max_abs_diff" in r["counters"]]
    if cfg.reference and refs:
        summary["max_abs_diff"] = max(k["ref_max_abs_diff"] for k in refs)
        summary["diff_fraction"] = max(k["ref_diff_fraction"] for k in refs)
    return summary


# -- M2 jobs for the Python API ---------------------------------------------------------------
def board_options(options=None):
    """A :class:`ReliefboardOptions` from one, from None (the defaults), or from a dict of its
    fields and BoardPolicy's; an unknown key is a ConfigError listing the known ones."""
    from ..lod.boardpolicy import BoardPolicy
    from .reliefboards import ReliefboardOptions

    if options is None or isinstance(options, ReliefboardOptions):
        return options or ReliefboardOptions()
    if not isinstance(options, dict):
        raise ConfigError(f"reliefboards=: give a ReliefboardOptions or a dict of its fields, got {type(options).__name__}")
    own = {f.name for f in fields(ReliefboardOptions)} - {"policy"}
    pol = {f.name for f in fields(BoardPolicy)}
    bad = sorted(set(options) - own - pol)
    if bad:
        raise ConfigError(f"reliefboards=: unknown option(s) {', '.join(bad)}; known: {', '.join(sorted(own | pol))}")
    policy = BoardPolicy(**{k: v for k, v in options.items() if k in pol})
    return ReliefboardOptions(policy, **{k: v for k, v in options.items() if k in own})


def _job(spec: str, cfg: RenderConfig, opts, cameras, out: Path, nranks: int) -> None:
    """Run the M2 job on ``nranks`` local ranks (``python -m massview __m2job DIR`` through the
    runtime's ``relaunch``, like every other local job), writing into ``out``; RankJobError
    on failure."""
    from ..parallel.runtime import relaunch

    tmp = Path(tempfile.mkdtemp(prefix="massview-m2-"))
    try:
        job = {"spec": spec, "cfg": cfg, "opts": opts, "cameras": cameras, "out": str(out)}
        (tmp / "job.pkl").write_bytes(pickle.dumps(job))
        rc = relaunch(["__m2job", str(tmp)], nranks)
        if rc != 0:
            err = tmp / "error.txt"
            raise RankJobError(err.read_text().strip() if err.exists() else f"the {nranks}-rank reliefboards job exited with status {rc}", rc)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def run_job(job_dir: str) -> int:
    """One rank of a job started by :func:`_job`; the first failing rank writes error.txt."""
    from ..parallel.runtime import guarded, world

    d = Path(job_dir)
    job = pickle.loads((d / "job.pkl").read_bytes())
    comm = world()

    def body():
        try:
            run(comm, job["spec"], job["cfg"], job["opts"], Path(job["out"]), cameras=job["cameras"] if comm.Get_rank() == 0 else None)
        except BaseException as e:
            text = str(e) if isinstance(e, MassviewError) else f"{type(e).__name__}: {e}"
            try:
                with open(d / "error.txt", "x") as f:
                    f.write(f"rank {comm.Get_rank()} of {comm.Get_size()}: {text}\n")
            except OSError:
                pass
            raise

    guarded(comm, body)
    return 0


def _cameras(what, cfg: RenderConfig):
    """(cameras or None, cfg): a path name/file stays a name (resolved on the visualization
    rank, as the CLI does); cameras are checked and fix the size and frame count."""
    from ..core.camera import Camera

    if isinstance(what, (str, Path)):
        load_path(str(what), [0, 0, 0], [1, 1, 1])  # a bad name or file is reported now
        return None, RenderConfig(**{**cfg.to_json(), "path": str(what)})
    cams = [what] if isinstance(what, Camera) else list(what)
    if not cams or not all(isinstance(c, Camera) for c in cams):
        raise ConfigError("render(): give a path name, a keyframe .json file, a Camera or a list of Cameras")
    if len({(c.width, c.height) for c in cams}) != 1:
        raise ConfigError("render(): every camera of one render must have the same image size")
    return cams, RenderConfig(**{**cfg.to_json(), "width": cams[0].width, "height": cams[0].height, "frames": len(cams)})


def _output_folder(out) -> Path:
    """``out`` made (if needed) as a writable folder; OutputError naming it otherwise."""
    path = Path(out)
    if path.exists() and not path.is_dir():
        raise OutputError(f"out {path}: a file is in the way (the output must be a folder); remove it or choose another path")
    try:
        path.mkdir(parents=True, exist_ok=True)
        tempfile.TemporaryFile(dir=path).close()
    except OSError as e:
        raise OutputError(f"out {path}: cannot write there ({e.strerror or e}); choose a writable location") from None
    return path


def check_scene(spec: str) -> None:
    """M2 draws polygon scenes: a ConfigError naming ``spec`` for a terrain store (it failed on
    rank 0 inside the job, with MPI_Abort's noise), and the store's own error for a missing or
    damaged one, before any rank starts."""
    from . import scene_kind

    if scene_kind(str(spec)) == "terrain":
        raise ConfigError(f"--system reliefboards draws polygon scenes (a scene store or builtin:objects), and {spec} is a "
                          "terrain store: leave --system out (T1) or use --system roettger (T2)")


def render_reliefboards(spec: str, what, cfg: RenderConfig, ranks: int | None, out=None, images: bool = True,
                        depth: bool = False, options=None, result=None):
    """:func:`massview.api.render` for ``system="reliefboards"``: ``result(images or None, None
    (no depth), summary, records, out or None)`` — the API passes its RenderResult; without,
    the tuple — and ``None`` on ranks other than 0 inside an MPI job."""
    from ..core.stats import read_stats
    from ..parallel.runtime import guarded, in_mpi_job, world

    if depth:
        raise ConfigError("render(system='reliefboards'): depth=True is not available (the visualization rank reads back colour only)")
    opts = board_options(options)
    check_scene(spec)
    nranks = world().Get_size() if in_mpi_job() else int(ranks or 1)
    if nranks < 2:
        raise ConfigError(f"system 'reliefboards' needs a visualization rank and at least one backend: give ranks=2 or more, got {nranks}")
    cams, cfg = _cameras(cfg.path if what is None else what, cfg)
    if out is not None:
        _output_folder(out)
    tmp = None if out is not None else Path(tempfile.mkdtemp(prefix="massview-m2-out-"))
    folder = Path(out) if out is not None else tmp / "out"
    try:
        if in_mpi_job():
            comm = world()
            guarded(comm, run, comm, spec, cfg, opts, folder if comm.Get_rank() == 0 else None, cameras=cams)
            if comm.Get_rank() != 0:
                return None
        else:
            _job(spec, cfg, opts, cams, folder, nranks)
        summary = json.loads((folder / "summary.json").read_text())
        records = read_stats(folder / "stats.jsonl")
        imgs = [_png(folder / "frames" / f"{f:05d}.png") for f in range(len(records))] if images else None
        parts = (imgs, None, summary, records, Path(out) if out is not None else None)
        return result(*parts) if result is not None else parts
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)


def _png(path: Path):
    from PIL import Image as PILImage

    with PILImage.open(path) as im:
        return np.asarray(im.convert("RGB"))
