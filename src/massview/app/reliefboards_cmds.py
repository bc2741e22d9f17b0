"""``massview render SCENE --system reliefboards``: M2 along a camera path, and its §7 metrics.

Outputs in ``DIR`` as for ``massview render``: ``frames/NNNNN.png``, ``stats.jsonl`` (one record
per frame of the visualization rank, with the M2 counters) and ``summary.json`` with the §7
figures: frame time, triangles by kind, requests, mean/max response time, angle-error
distribution (min, quartiles, mean, max), time to a complete view, per-backend loads.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from ..core.config import RenderConfig
from ..core.errors import ConfigError
from ..core.paths import load_path
from ..lod.boardpolicy import DEFAULT_TNZ, BoardPolicy

__all__ = ["add_render_args", "options_from_args", "cmd_render"]


def _stall(spec: str) -> tuple[int, float | None]:
    rank, _, sec = spec.partition(":")
    try:
        return int(rank), (float(sec) if sec else None)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{spec!r}: expected RANK or RANK:SECONDS, e.g. 2 or 2:0.5") from None


def add_render_args(p: argparse.ArgumentParser) -> None:
    """The M2 flags of ``massview render --system reliefboards``."""
    g = p.add_argument_group("reliefboards (--system reliefboards)")
    g.add_argument("--tnz", type=int, default=None, help=f"near-zone triangles t_nz (default {DEFAULT_TNZ}: the paper's 3.5 M scaled to this machine, see lod/boardpolicy.py)")
    g.add_argument("--epsilon", type=float, default=11.5, help="angle error (deg) past which a board is renewed (default 11.5)")
    g.add_argument("--max-error", type=float, default=45.0, help="angle error (deg) past which the original is drawn (default 45)")
    g.add_argument("--size-threshold", type=float, default=0.30, help="relative projected-size change that renews a board (default 0.3)")
    g.add_argument("--board-px", type=int, default=128, help="largest projected board side p in pixels (default 128)")
    g.add_argument("--min-triangles", type=int, default=None, help="objects with fewer triangles are infeasible (default 2·p²)")
    g.add_argument("--replicas", type=int, default=3, help="replicas of each object on the backends (default 3)")
    g.add_argument("--placement-seed", type=int, default=0, help="seed of the random replica placement")
    g.add_argument("--stall-backend", type=_stall, default=None, metavar="RANK[:SEC]",
                   help="simulate a stalled backend (holds every request until the end) or a slow one (SEC more per board)")
    g.add_argument("--tie-rule", choices=("pending", "frame", "run"), default="pending",
                   help="c-collision ties: fewest requests assigned and still pending (default), assigned in this frame only, "
                        "or assigned over the whole run")
    g.add_argument("--reference-every", type=int, default=1, metavar="K",
                   help="with --reference, draw the all-original reference on every K-th frame only (default 1)")
    g.add_argument("--wait-boards", action="store_true",
                   help="deterministic mode for comparisons: each frame waits until every pending board has arrived (not M2's behaviour)")


def options_from_args(args):
    from ..systems.reliefboards import ReliefboardOptions

    stall = args.stall_backend or (None, None)
    policy = BoardPolicy(epsilon_deg=args.epsilon, max_error_deg=args.max_error, size_threshold=args.size_threshold,
                         t_nz=DEFAULT_TNZ if args.tnz is None else args.tnz, p=args.board_px)
    return ReliefboardOptions(policy, replicas=args.replicas, seed=args.placement_seed, min_triangles=args.min_triangles,
                              stall_backend=stall[0], stall_s=stall[1], tie_rule=args.tie_rule, wait_boards=args.wait_boards,
                              reference_every=args.reference_every)


def cmd_render(args, argv, cfg: RenderConfig) -> int:
    """``massview render --system reliefboards``: relaunch under mpiexec, run, print."""
    from ..parallel.runtime import guarded, in_mpi_job, relaunch, world
    from ..systems.reliefboards import check_stall
    from ..systems.reliefboards_job import check_scene, run

    opts = options_from_args(args)
    load_path(cfg.path, [0, 0, 0], [1, 1, 1])
    if not in_mpi_job():
        check_scene(args.scene)
        from ..api import check_render_out

        check_render_out(args.out, args.scene)
        if (args.ranks or 1) < 2:
            raise ConfigError("--system reliefboards needs a visualization rank and at least one backend: give --ranks 2 or more")
        check_stall(opts, args.ranks)  # (walk8 L1: said by every rank, under MPI_Abort lines)
        return relaunch(argv, args.ranks)
    comm = world()
    summary = guarded(comm, run, comm, args.scene, cfg, opts, args.out, args.quiet)
    if summary is not None and not args.quiet:
        print(summary_lines(summary))
        print(f"wrote {args.out}/summary.json, {args.out}/stats.jsonl and the frames")
    return 0


def _dist(d, unit: str) -> str:
    """A {count, min, median, max, ...} summary as one phrase."""
    if not isinstance(d, dict) or not d.get("count"):
        return "none"
    return f"median {d['median']:.4g} {unit} ({d['min']:.4g}–{d['max']:.4g}) over {d['count']}"


def summary_lines(s: dict) -> str:
    """The M2 run's figures for the terminal (summary.json has them all)."""
    done = s.get("ms_to_complete_view")
    rows = [("frame", f"mean {s.get('mean_frame_ms', 0):.1f} ms, 99th percentile {s.get('frame_ms_p99', 0):.1f} ms"),
            ("objects", f"{s.get('objects')} ({s.get('feasible')} feasible for boards)"),
            ("board requests", f"{s.get('requests', 0)}, answered {s.get('answered', 0)}; loads per backend {s.get('loads_per_backend')}"),
            ("response time", _dist(s.get("response_ms"), "ms")),
            ("angle error of boards drawn", _dist(s.get("angle_error_deg"), "°")),
            ("complete view (every far object a board)",
             "no far object was in view in this run (every object within the near zone: nothing for boards)"
             if s.get("frames_with_far_objects") == 0 else "not reached in this run" if done is None else f"after {done:.0f} ms")]
    if s.get("frames_with_far_objects") and not s.get("boards_drawn"):
        rows.append(("boards drawn", f"none: the far objects of {s['frames_with_far_objects']} frames were all drawn as geometry"))
    if "max_abs_diff" in s:
        rows.append(("against the all-original reference", f"max abs diff {s['max_abs_diff']}, {100 * s.get('diff_fraction', 0):.2f} % of pixels"))
    return "\n".join(f"{k}: {v}" for k, v in rows)


def cmd_view(args, argv, cfg: RenderConfig) -> int:
    """``massview view --system reliefboards``: relaunch under mpiexec, serve the viewer."""
    from ..parallel.runtime import guarded, in_mpi_job, relaunch, world
    from ..systems.reliefboards import check_stall
    from .reliefboards_view import run_view_reliefboards

    opts = options_from_args(args)
    if not (0 <= args.port <= 65535):
        raise ConfigError(f"--port must be in 0..65535, got {args.port}")
    if not in_mpi_job():
        from .viewer.server import check_port

        check_port(args.host, args.port)  # before any rank starts
        if (args.ranks or 1) < 2:
            raise ConfigError("--system reliefboards needs a visualization rank and at least one backend: give --ranks 2 or more")
        check_stall(opts, args.ranks)
        return relaunch(argv, args.ranks)
    comm = world()
    return guarded(comm, run_view_reliefboards, comm, args, cfg, opts)


# -- massview prepare reliefboards ----------------------------------------------------------------
def add_parsers(prepare_sub) -> None:
    """``massview prepare reliefboards SCENE``: §4 clustering stored in the scene store."""
    p = prepare_sub.add_parser("reliefboards", help="M2: cluster a scene store into feasible objects (§4), stored in the store")
    p.add_argument("scene", help="a scene store (massview prepare scene / generate scene)")
    p.add_argument("--tnz", type=int, default=DEFAULT_TNZ, help=f"near-zone triangles t_nz (default {DEFAULT_TNZ}: the paper's 3.5 M scaled to this machine, see lod/boardpolicy.py)")
    p.add_argument("--board-px", type=int, default=128, help="largest projected board side p in pixels (default 128)")
    p.add_argument("--size", default="1024x768", help="display WIDTHxHEIGHT; its height is r_y (default 1024x768, the paper's)")
    p.add_argument("--fovy", type=float, default=45.0, help="vertical field of view in degrees (default 45)")
    p.add_argument("--min-triangles", type=int, default=None, help="clusters with fewer triangles are infeasible (default 2·p²)")
    p.add_argument("--candidates", type=int, default=8, help="nearby candidate clusters per cluster (default 8)")
    p.add_argument("--picture", type=Path, default=None, help="also write a PNG of the clusters (as the paper's Figure 5)")
    p.add_argument("--quiet", "-q", action="store_true")


def cmd_prepare(args) -> int:
    from ..core.config import parse_size
    from ..data.board_clusters import write_clusters
    from ..lod.clusters import ClusterParams, cluster_scene
    from ..systems.boardscene import open_scene_store

    _, height = parse_size(args.size)
    params = ClusterParams(t_nz=args.tnz, p=args.board_px, r_y=height, fovy=args.fovy, k=args.candidates,
                           min_triangles=args.min_triangles)
    store = open_scene_store(args.scene)
    sk = store.skeleton
    tris = np.asarray(sk.triangles, np.int64)
    tris = tris[:, 0] if tris.ndim == 2 else tris
    cl = cluster_scene(np.asarray(sk.box_lo, np.float64), np.asarray(sk.box_hi, np.float64), tris, params)
    write_clusters(args.scene, cl.labels, cl.status, {"t_nz": params.t_nz, "p": params.p, "r_y": params.r_y, "fovy": params.fovy,
                                                      "min_triangles": params.board_triangles, "d_nz": cl.d_nz, "sl_c": cl.sl_c})
    counts = np.bincount(cl.status, minlength=3)
    if not args.quiet:
        print(f"{args.scene}: {len(tris)} objects -> {len(cl.status)} clusters: {counts[0]} feasible, {counts[1]} too large "
              f"(> sl_c = {cl.sl_c:.4g}), {counts[2]} with fewer than {params.board_triangles} triangles; d_nz = {cl.d_nz:.4g}")
    if counts[0] == 0:
        print(f"massview: warning: no cluster is feasible, so `render --system reliefboards` will draw every object as geometry "
              f"(no boards): {counts[1]} clusters are longer than sl_c = {cl.sl_c:.4g} (the near zone of t_nz = {params.t_nz:,} "
              f"triangles is only d_nz = {cl.d_nz:.4g} deep) and {counts[2]} have fewer triangles than a board "
              f"({params.board_triangles:,}, --min-triangles). M2 pays off on large scenes (the paper's plant: 12.4 M triangles, "
              f"`generate scene plant --size 1.5`); on this one {_advice(counts, params)}", file=sys.stderr)
    if args.picture is not None:
        write_cluster_picture(args.scene, args.picture, params, parse_size(args.size))
        if not args.quiet:
            print(f"wrote {args.picture}")
    return 0


def _advice(counts, params) -> str:
    """What to change when no cluster is feasible, for each cause there was: clusters too long
    (a larger near zone, ``--tnz``, or smaller objects) and clusters with too few triangles
    (``--min-triangles``)."""
    out = []
    if counts[1]:
        out.append(f"for the {counts[1]} too long, try a larger --tnz (now {params.t_nz:,}: a deeper near zone admits "
                   "longer clusters) or prepare the scene with a smaller --object-triangles")
    if counts[2]:
        out.append(f"for the {counts[2]} with too few triangles, try a lower --min-triangles (now {params.board_triangles:,})")
    return "; ".join(out) or "try a larger --tnz"


def write_cluster_picture(scene: str, path: Path, params, size=(1024, 768)) -> Path:
    """The clusters as in the paper's Figure 5: too large green (as wireframe here, so that
    walls do not hide the rest), feasible clusters in shades of red, clusters with too few
    triangles in other colours."""
    from PIL import Image as PILImage

    from ..core.camera import Camera
    from ..core.stats import FrameStats
    from ..lod.clusters import FEASIBLE, TOO_LARGE
    from ..render.context import create_context
    from ..render.meshes import MeshRenderer
    from ..render.view import ViewRenderer
    from ..systems.boardscene import open_board_objects

    obj = open_board_objects(scene, params)
    lo, hi = obj.bounds
    c, ext = (lo + hi) / 2, float(np.linalg.norm(hi - lo))
    eye = c + np.array([0.55, -0.75, 0.45]) * ext
    cam = Camera.look_at(eye, c, fovy=params.fovy, near=ext * 0.01, far=ext * 4, width=size[0], height=size[1])
    ctx = create_context()
    meshes, view = MeshRenderer(ctx, *obj.concatenated()), ViewRenderer(ctx)
    rng = np.random.default_rng(1)

    def draw(mvp):
        ctx.wireframe = True  # too large: green wireframe, so the clusters inside stay visible
        meshes.draw(np.flatnonzero(obj.status == TOO_LARGE), mvp, (0.2, 0.85, 0.2, 0.9))
        ctx.wireframe = False
        for i in np.flatnonzero(obj.status != TOO_LARGE):
            if obj.status[i] == FEASIBLE:
                tint = (rng.uniform(0.55, 1.0), rng.uniform(0.0, 0.15), rng.uniform(0.0, 0.15), 0.8)
            else:
                tint = (*rng.uniform(0.2, 0.9, 3) * np.array([0.5, 0.7, 1.0]), 0.8)
            meshes.draw(np.array([i]), mvp, tuple(float(v) for v in tint))
        return 0

    img = view.render(cam, cam.viewport, draw, FrameStats(frame=0, rank=0))
    meshes.release()
    view.release()
    path.parent.mkdir(parents=True, exist_ok=True)
    pic = PILImage.fromarray(np.ascontiguousarray(img.color[..., :3]))
    _legend(pic, [((230, 25, 20), f"feasible: gets boards ({int((obj.status == FEASIBLE).sum())})"),
                  ((50, 215, 50), f"too large, longer than sl_c = {obj.sl_c:.3g} ({int((obj.status == TOO_LARGE).sum())}; wireframe)"),
                  ((90, 140, 210), f"too few triangles for a board ({int(((obj.status != FEASIBLE) & (obj.status != TOO_LARGE)).sum())})")])
    pic.save(path, optimize=True)
    return path


def _legend(pic, rows: list[tuple[tuple[int, int, int], str]]) -> None:
    """A box of colour swatches and labels in the picture's top-left corner."""
    from PIL import ImageDraw, ImageFont

    draw = ImageDraw.Draw(pic)
    try:
        font = ImageFont.load_default(size=max(12, pic.height // 48))
    except TypeError:  # Pillow < 10.1: one bitmap size
        font = ImageFont.load_default()
    line = max(16, pic.height // 32)
    width = max(draw.textlength(t, font=font) for _, t in rows) + line * 2
    draw.rectangle([6, 6, 14 + width, 12 + line * len(rows)], fill=(12, 14, 20))
    for k, (rgb, text) in enumerate(rows):
        y = 10 + k * line
        draw.rectangle([12, y + 2, 12 + line - 6, y + line - 4], fill=rgb)
        draw.text((12 + line, y), text, fill=(235, 235, 235), font=font)
