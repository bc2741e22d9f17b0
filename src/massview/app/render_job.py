"""``render(ranks=N > 1)``: the MPI job under :func:`massview.render` and its results.

The caller pickles the scene name, the frozen :class:`RenderConfig` and the cameras into a
temporary job folder and starts ``mpiexec -n N python -m massview __job DIR``
(:func:`massview.parallel.runtime.relaunch`). Every rank runs :func:`run_job`: the collective
:func:`~massview.app.render_cmd.run_render` writes lossless PNG frames (``depth/*.npy`` with
depth), ``stats.jsonl`` and ``summary.json``; the caller reads them back with
:func:`load_frames` — the job's pixels bit for bit. A rank that fails writes its message to
``DIR/error.txt`` before the job aborts; the caller raises it as :class:`RankJobError`.
"""

from __future__ import annotations

import pickle
import shutil
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

import numpy as np

from ..core.config import RenderConfig
from ..core.errors import MassviewError, RankJobError
from .render_cmd import run_render, tile_dir

__all__ = ["RankJobError", "mpi_job", "load_frames", "assemble_tiles", "run_job"]


@contextmanager
def mpi_job(spec: str, cfg: RenderConfig, cameras: list, label: str, out: Path | None, depth: bool, quiet: bool,
            nranks: int) -> Iterator[Path]:
    """Run the job on ``nranks`` ranks; yields the folder holding its outputs (``out``, or a
    temporary one removed on exit)."""
    from ..parallel.runtime import relaunch

    tmp = Path(tempfile.mkdtemp(prefix="massview-job-"))
    try:
        target = out if out is not None else tmp / "out"
        job = {"spec": spec, "cfg": cfg, "cameras": cameras, "label": label, "out": str(target), "depth": depth, "quiet": quiet}
        (tmp / "job.pkl").write_bytes(pickle.dumps(job))
        rc = relaunch(["__job", str(tmp)], nranks)
        if rc != 0:
            err = tmp / "error.txt"
            raise RankJobError(err.read_text().strip() if err.exists() else f"the {nranks}-rank job exited with status {rc}", rc)
        yield target
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def assemble_tiles(tiles, width: int, height: int) -> tuple[np.ndarray, np.ndarray | None]:
    """The full (height, width, 3) uint8 frame (and float32 depth, if the tiles carry it) from
    ``[(viewport, rgb, depth | None)]`` display tiles; one full-size tile is returned as is."""
    if len(tiles) == 1 and tiles[0][0] is not None and (tiles[0][0].w, tiles[0][0].h) == (width, height):
        return tiles[0][1], tiles[0][2]
    rgb = np.zeros((height, width, 3), np.uint8)
    dep = np.ones((height, width), np.float32) if tiles and tiles[0][2] is not None else None
    for vp, c, d in tiles:
        rgb[vp.slices()] = c
        if dep is not None:
            dep[vp.slices()] = d
    return rgb, dep


def load_frames(out: Path, cfg: RenderConfig, nframes: int, depth: bool, nranks: int):
    """(images, depths or None) of a finished run in ``out`` (wall tiles assembled)."""
    from PIL import Image as PILImage

    from ..core.camera import Viewport
    from ..parallel.decompose import parse_wall

    tiles = list(enumerate(parse_wall(cfg.wall, nranks, cfg.width, cfg.height))) if cfg.wall else [(0, Viewport(0, 0, cfg.width, cfg.height))]
    imgs, deps = [], [] if depth else None

    def png(p: Path) -> np.ndarray:
        with PILImage.open(p) as im:
            return np.asarray(im.convert("RGB"))

    for f in range(nframes):
        parts = [(vp, png(tile_dir(out, cfg, r) / f"{f:05d}.png"),
                  np.load(tile_dir(out, cfg, r, "depth") / f"{f:05d}.npy") if depth else None) for r, vp in tiles]
        rgb, dep = assemble_tiles(parts, cfg.width, cfg.height)
        imgs.append(rgb)
        if depth:
            deps.append(dep)
    return imgs, deps


def run_job(job_dir: str) -> int:
    """Every rank of a job (``python -m massview __job DIR``) renders collectively; a failure
    is written to ``DIR/error.txt`` (the first failing rank's) before the job aborts."""
    from ..parallel.runtime import guarded, world

    d = Path(job_dir)
    job = pickle.loads((d / "job.pkl").read_bytes())
    comm = world()
    rank, size = comm.Get_rank(), comm.Get_size()

    def body():
        try:
            run_render(comm, job["spec"], job["cfg"], Path(job["out"]), job["quiet"], job["cameras"] if rank == 0 else None,
                       False, job["depth"], job["label"])
        except BaseException as e:
            text = str(e) if isinstance(e, MassviewError) else f"{type(e).__name__}: {e}"
            try:
                with open(d / "error.txt", "x") as f:
                    f.write((f"rank {rank} of {size}: " if size > 1 else "") + text + "\n")
            except OSError:
                pass
            raise

    guarded(comm, body)
    return 0
