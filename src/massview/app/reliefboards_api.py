"""M2 through the Python API: ``massview.render(scene, what, ranks=N, system="reliefboards")``.

M2 runs its own role loop (one visualization rank, N-1 backends) rather than the collective
frame loop of :func:`massview.app.render_cmd.run_render`, so :func:`massview.api.render` hands
it to :func:`render_reliefboards`: the scene name, the frozen :class:`RenderConfig`, the
:class:`~massview.systems.reliefboards.ReliefboardOptions` and the cameras (or the path name,
resolved on the visualization rank exactly as ``massview render --system reliefboards`` does)
are pickled into a temporary job folder; ``mpiexec -n N python -m massview
__m2job DIR`` runs :func:`massview.app.reliefboards_cmds.run` on every rank, which writes lossless PNG
frames, ``stats.jsonl`` and ``summary.json`` — the CLI's outputs — and this process reads them
back: the visualization rank's pixels bit for bit. Inside an MPI job already, the call is
collective and returns on rank 0.

The M2 parameters are given as ``reliefboards=ReliefboardOptions(...)`` or a dict of its fields
and of :class:`~massview.lod.boardpolicy.BoardPolicy`'s (``t_nz``, ``epsilon_deg``, ``p``, ...).
"""

from __future__ import annotations

import json
import pickle
import shutil
import tempfile
from dataclasses import fields
from pathlib import Path

from ..core.config import RenderConfig
from ..core.errors import ConfigError, MassviewError, RankJobError

__all__ = ["board_options", "render_reliefboards", "run_job"]


def board_options(options=None):
    """A :class:`ReliefboardOptions` from one, from None (the defaults), or from a dict of its
    fields and BoardPolicy's; an unknown key is a ConfigError listing the known ones."""
    from ..lod.boardpolicy import BoardPolicy
    from ..systems.reliefboards import ReliefboardOptions

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
    runtime's :func:`relaunch`, like every other local job), writing into ``out``; RankJobError
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
    from .reliefboards_cmds import run

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
    from ..core.paths import load_path

    if isinstance(what, (str, Path)):
        load_path(str(what), [0, 0, 0], [1, 1, 1])  # a bad name or file is reported now
        return None, RenderConfig(**{**cfg.to_json(), "path": str(what)})
    cams = [what] if isinstance(what, Camera) else list(what)
    if not cams or not all(isinstance(c, Camera) for c in cams):
        raise ConfigError("render(): give a path name, a keyframe .json file, a Camera or a list of Cameras")
    if len({(c.width, c.height) for c in cams}) != 1:
        raise ConfigError("render(): every camera of one render must have the same image size")
    return cams, RenderConfig(**{**cfg.to_json(), "width": cams[0].width, "height": cams[0].height, "frames": len(cams)})


def render_reliefboards(spec: str, what, cfg: RenderConfig, ranks: int | None, out=None, images: bool = True,
                        depth: bool = False, options=None):
    """:func:`massview.api.render` for ``system="reliefboards"``; returns a RenderResult
    (``None`` on ranks other than 0 inside an MPI job)."""
    from ..api import RenderResult
    from ..core.stats import read_stats
    from ..parallel.runtime import in_mpi_job, world
    from .outputs import check_output_dir

    if depth:
        raise ConfigError("render(system='reliefboards'): depth=True is not available (the visualization rank reads back colour only)")
    opts = board_options(options)
    nranks = world().Get_size() if in_mpi_job() else int(ranks or 1)
    if nranks < 2:
        raise ConfigError(f"system 'reliefboards' needs a visualization rank and at least one backend: give ranks=2 or more, got {nranks}")
    cams, cfg = _cameras(cfg.path if what is None else what, cfg)
    if out is not None:
        check_output_dir(Path(out), "out")
    tmp = None if out is not None else Path(tempfile.mkdtemp(prefix="massview-m2-out-"))
    folder = Path(out) if out is not None else tmp / "out"
    try:
        if in_mpi_job():
            from ..parallel.runtime import guarded
            from .reliefboards_cmds import run

            comm = world()
            guarded(comm, run, comm, spec, cfg, opts, folder if comm.Get_rank() == 0 else None, cameras=cams)
            if comm.Get_rank() != 0:
                return None
        else:
            _job(spec, cfg, opts, cams, folder, nranks)
        summary = json.loads((folder / "summary.json").read_text())
        records = read_stats(folder / "stats.jsonl")
        imgs = [_png(folder / "frames" / f"{f:05d}.png") for f in range(len(records))] if images else None
        return RenderResult(imgs, None, summary, records, Path(out) if out is not None else None)
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)


def _png(path: Path):
    import numpy as np
    from PIL import Image as PILImage

    with PILImage.open(path) as im:
        return np.asarray(im.convert("RGB"))
