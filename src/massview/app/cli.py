"""The ``massview`` command line: a thin shell over :mod:`massview.api`.

Commands: ``render`` (a camera path on N ranks, :func:`massview.render`), ``view`` (live, in
the browser), ``report`` (table and plot of a run), ``demo``, ``generate``/``prepare``/
``info``/``verify`` (terrain data) and ``bench NAME`` (built from the registry
:data:`massview.app.bench.BENCHES`).

``render --ranks N`` starts a real MPI job through the API (``mpiexec -n N python -m massview
__job DIR``, see :mod:`massview.api`); ``view --ranks N`` relaunches itself under ``mpiexec``.
Under an external ``mpiexec -n N massview ...`` both use all the ranks they were given. Errors
print as one message, no traceback, and exit non-zero.
"""

from __future__ import annotations

import argparse
import atexit
import json
import os
import re
import sys
import textwrap
from pathlib import Path

from ..core.config import COMPOSITOR_NAMES, RenderConfig, parse_size, parse_sun
from ..core.errors import ConfigError, MassviewError, StoreError, disk_full, full_disk_line
from ..core.paths import BUILTIN_PATHS
from ..parallel.codec import CODEC_CHOICES
from ..parallel.runtime import ignore_late_sigterm, in_mpi_job, interrupt_on_sigterm, reuse_freed_memory
from . import upgrade_cmds
from .dmmr_cmds import add_dmmr_args

__all__ = ["main", "build_parser"]

DECOMPOSITIONS = ("sort-first:horizontal", "sort-first:vertical", "sort-first:grid", "sort-first:kd", "sort-first:balanced", "sort-last",
                  "sort-last:kpatch", "sort-last:linear", "sort-last:quadtree", "sort-last:visible", "sort-last:static")


def _grid(spec: str) -> tuple[int, int]:
    try:
        r, c = (int(v) for v in spec.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{spec!r}: expected ROWSxCOLS, e.g. 2x3") from None
    if r < 1 or c < 1:
        raise argparse.ArgumentTypeError(f"{spec!r}: rows and cols must be positive")
    return r, c


def _positive(v: str) -> int:
    try:
        i = int(v)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{v!r} is not an integer") from None
    if i < 1:
        raise argparse.ArgumentTypeError(f"{v} must be at least 1")
    return i


def _add_render_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("scene", help="a terrain store, a scene store, or builtin:objects[?n=COUNT&seed=S]")
    p.add_argument("--ranks", type=_positive, default=None, help="local ranks to launch (default 1; ignored under an external mpiexec)")
    p.add_argument("--decomposition", default="sort-last", metavar="MODE",
                   help=f"one of {', '.join(DECOMPOSITIONS)} (default sort-last; terrain: sort-last = sort-last:kpatch; scene: sort-last = sort-last:visible; sort-first = sort-first:horizontal); "
                        "'horizontal' = side-by-side columns, 'vertical' = stacked rows")
    p.add_argument("--compositor", default="binary-swap", choices=COMPOSITOR_NAMES, help="sort-last depth compositing (default binary-swap)")
    p.add_argument("--radix-k", type=int, default=None, help="k for radix-k (default 4)")
    p.add_argument("--codec", default=None, choices=CODEC_CHOICES,
                   help="sub-image codec (default auto: on one node runs without byte compression and final regions as raw rows; "
                        "across nodes blosc2)")
    p.add_argument("--path", default="orbit", help=f"camera path: {', '.join(BUILTIN_PATHS)} or a keyframe FILE.json (default orbit)")
    p.add_argument("--frames", type=_positive, default=10, help="frames to render (default 10)")
    p.add_argument("--size", default="1280x1024", help="image WIDTHxHEIGHT (default 1280x1024)")
    p.add_argument("--grid", type=_grid, default=None, help="ROWSxCOLS for sort-first:grid (default: chosen for the rank count)")
    p.add_argument("--wall", default=None, metavar="CxR", help="display wall: C×R display ranks each write their own tile")
    p.add_argument("--tile-targets", action="store_true", help="sort-first into tile-sized targets (off-axis frusta; equal to ~1e-4 of pixels)")
    p.add_argument("--color-by-rank", action="store_true", help="tint each rank's contribution")
    p.add_argument("--tau", type=float, default=1.0, help="terrain and scenes: pixel tolerance of the LOD (default 1)")
    p.add_argument("--cache-mb", type=int, default=256, help="terrain and scenes: RAM block cache per rank, MiB (default 256)")
    p.add_argument("--gpu-mb", type=int, default=256, help="terrain and scenes: GL block pool per rank, MiB (default 256)")
    p.add_argument("--loading", choices=("async", "complete"), default="complete",
                   help="terrain and scenes: complete = wait until every block the view needs is loaded (default for render: final-quality frames); "
                        "async = never wait for data, draw coarser meanwhile (default for view)")
    p.add_argument("--exaggeration", type=float, default=1.0, help="terrain: vertical exaggeration at view time, about the lowest sample (default 1; applied after the "
                        "store's --vertical-scale, which prepare set)")
    p.add_argument("--sun", default="315,45", help="terrain: sun AZIMUTH,ALTITUDE in degrees, as gdaldem (default 315,45)")
    p.add_argument("--colormap", default="auto", help="terrain: a matplotlib colormap, hypsometric, ortho, none (grey) or auto (default)")
    p.add_argument("--haze", type=float, default=1.0, help="terrain: aerial perspective strength, 0 = off (default 1)")
    p.add_argument("--pipeline", choices=("on", "off"), default=None,
                   help="render: on = composite and deliver frame i on a thread while frame i+1 is drawn (same images); off = one frame after the other (default)")
    p.add_argument("--reference", action="store_true", help="also render each frame on one rank and report max_abs_diff and diff_fraction")
    p.add_argument("--video", action="store_true", help="render: also write OUT/video.mp4 of the frames (H.264, 30 fps)")
    p.add_argument("--out", "-o", type=Path, default=Path("out/render"), help="output folder (default out/render)")
    p.add_argument("--quiet", "-q", action="store_true", help="no progress bar or summary table")
    p.add_argument("--fault", default=None, help=argparse.SUPPRESS)
    _add_roettger_args(p)
    from .reliefboards_cmds import add_render_args as _add_reliefboard_args

    _add_reliefboard_args(p)
    add_dmmr_args(p)


def _add_roettger_args(p: argparse.ArgumentParser) -> None:
    """T2 flags (``--system roettger``: computation + visualization ranks)."""
    p.add_argument("layers", nargs="*", default=[], help="T2: further terrain stores drawn as stacked layers")
    p.add_argument("--system", choices=("auto", "roettger", "dmmr", "reliefboards"), default="auto",
                   help="auto (by scene: T1 for terrain, the scene renderer for scene stores), roettger (T2), dmmr (M1: rank 0 server, other ranks clients) or reliefboards (M2)")
    p.add_argument("--compute-ranks", type=_positive, default=1, help="T2: computation ranks; the other ranks visualize (default 1)")
    p.add_argument("--paper-partition", action="store_true", help="T2: the paper's overlapping (2^m+1)² portions instead of the exact partition")
    p.add_argument("--triangle-budget", type=_positive, default=None, help="T2: at most N triangles per frame (≥ 0.9 N when the view has more)")
    p.add_argument("--roettger-C", type=float, default=None, help="T2: minimum global resolution C in [2, 64] (default: the store table's, 4)")
    p.add_argument("--roettger-c", type=float, default=None, help="T2: desired global resolution c (default √3/(tau · pixel angle))")
    p.add_argument("--no-fan-delta", dest="fan_delta", action="store_false", help="T2: resend every visible fan each frame (no change-only messages)")


def _add_view_args(v: argparse.ArgumentParser) -> None:
    """``view``'s own flags and defaults (after render's)."""
    v.add_argument("--port", type=int, default=8080, help="HTTP port (default 8080; 0 picks a free one)")
    v.add_argument("--host", default="127.0.0.1", help="address to bind (default 127.0.0.1: this machine only)")
    v.set_defaults(size="960x540", out=None, loading="async")


def build_parser(argv: list[str] | None = None) -> argparse.ArgumentParser:
    """The whole command line; given ``argv``, the ``bench`` subcommands (whose modules import
    the renderer, MPI and the scene systems: ~0.1 s) only when ``argv`` starts with ``bench``."""
    from .. import __version__

    ap = argparse.ArgumentParser(prog="massview", description="Parallel out-of-core rendering of massive terrains and models.")
    ap.add_argument("--version", action="version", version=f"massview {__version__}")
    sub = ap.add_subparsers(dest="command", required=True, metavar="COMMAND")
    r = sub.add_parser("render", help="render a camera path on N ranks")
    _add_render_args(r)
    v = sub.add_parser("view", help="live parallel rendering in the browser")
    _add_render_args(v)
    _add_view_args(v)
    rep = sub.add_parser("report", help="summary table and report.png of a render folder")
    rep.add_argument("dir", type=Path, help="the --out folder of a `massview render` run (its stats.jsonl and summary.json); "
                                            "report.png is written there. A folder of M2 runs gets the figures across backend counts")
    dm = sub.add_parser("demo", help="the main job on built-in data: terrain flyover on local ranks, video and report")
    dm.add_argument("--ranks", type=_positive, default=2, help="local ranks (default 2)")
    dm.add_argument("--frames", type=_positive, default=90, help="frames of the flyover (default 90: 3 s of video)")
    dm.add_argument("--terrain-size", type=_positive, default=4097, help="samples per side of the synthetic terrain (default 4097)")
    dm.add_argument("--cache-dir", default=os.environ.get("MASSVIEW_CACHE", "~/.cache/massview"), help="where the demo terrain is kept (default ~/.cache/massview, or $MASSVIEW_CACHE; made once, reused by later demos)")
    dm.add_argument("--out", default="out/demo", help="output folder (default out/demo)")
    gen = sub.add_parser("generate", help="generate synthetic data")
    gsub = gen.add_subparsers(dest="what", required=True, metavar="WHAT")
    gt = gsub.add_parser("terrain", help="a synthetic DEM (ridged multifractal), generated tile by tile")
    gt.add_argument("out", nargs="?", help="output: a store folder, FILE.tif or FILE.npy (or give it with -o, as other commands take it)")
    gt.add_argument("-o", "--output", default=None, help="the same output, as an option")
    gt.add_argument("--size", type=_positive, required=True, help="samples per side")
    gt.add_argument("--seed", type=int, default=1)
    gt.add_argument("--format", choices=("store", "tif", "npy"), default=None, help="default: from the extension (store otherwise)")
    gt.add_argument("--block", type=int, default=257, help="M-block size for --format store (129, 257, 513)")
    gt.add_argument("--overwrite", action="store_true")
    gt.add_argument("--quiet", "-q", action="store_true")
    from .scene_cmds import add_generate_parser, add_prepare_parser

    add_generate_parser(gsub)
    prep = sub.add_parser("prepare", help="build a store from real data")
    psub = prep.add_subparsers(dest="what", required=True, metavar="WHAT")
    pt = psub.add_parser("terrain", help="elevation (GeoTIFF/COG, .npy, .npz, SRTM .hgt, raw) -> terrain store")
    pt.add_argument("input")
    pt.add_argument("-o", "--output", required=True, help="store folder to write")
    pt.add_argument("--block", type=int, default=257, help="M-block size: 129, 257 (default) or 513")
    pt.add_argument("--vertical-scale", type=float, default=1.0, help="factor taking the stored heights to world units, kept in the store (default 1; e.g. 0.3048 for heights in feet). "
                         "To exaggerate relief for viewing use `render --exaggeration`, which needs no new prepare")
    pt.add_argument("--nodata", type=float, default=None, help="nodata value (default: the file's own)")
    pt.add_argument("--array", default=None, help="array name inside an .npz")
    pt.add_argument("--shape", default=None, help="ROWSxCOLS of a raw binary input")
    pt.add_argument("--dtype", default=None, help="dtype of a raw binary input, e.g. float32, <i2, >u2")
    pt.add_argument("--spacing", default=None, metavar="DX[,DY]",
                    help="sample spacing for inputs without a georeference (.npy, .npz, raw, plain TIFF), in the CRS's units "
                         "(metres without --crs); default: FILE.json beside the input, else 1 m (with a warning)")
    pt.add_argument("--crs", default=None, help="CRS of an input without one, e.g. EPSG:32632 (anything rasterio understands)")
    pt.add_argument("--color", default=None, help="orthophoto (RGB GeoTIFF) for the colour pyramid: placed by georeference when it and the DEM both have one (same CRS; an image of another place is an error), otherwise stretched over the DEM")
    pt.add_argument("--no-color", action="store_true", help="no colour pyramid")
    pt.add_argument("--overwrite", action="store_true", help="rebuild a complete store")
    pt.add_argument("--workers", type=int, default=0, help="worker threads (default 0: every core); the output does not depend on it")
    pt.add_argument("--quiet", "-q", action="store_true")
    add_prepare_parser(psub)
    from .roettger_cmds import add_parsers as _roettger_parsers

    _roettger_parsers(psub)
    from .reliefboards_cmds import add_parsers as _reliefboard_parsers

    _reliefboard_parsers(psub)
    inf = sub.add_parser("info", help="levels, blocks, size on disk, compression, georeference of a store")
    inf.add_argument("store", help="a terrain store or a scene store folder")
    inf.add_argument("--json", action="store_true", help="print the figures as JSON instead of a table")
    ver = sub.add_parser("verify", help="check that every block decodes and the metadata is consistent")
    ver.add_argument("store", help="a terrain store or a scene store folder")
    ver.add_argument("--quiet", "-q", action="store_true", help="no progress bar")
    b = sub.add_parser("bench", help="benchmarks (figures as ratios against a baseline measured in the same run)")
    bsub = b.add_subparsers(dest="bench", required=True, metavar="WHAT")
    if argv is None or argv[:1] == ["bench"]:
        from .bench import BENCHES

        for name, mod in BENCHES.items():
            mod.add_arguments(bsub.add_parser(name, help=_doc_summary(mod.__doc__, name), description=_doc_text(mod.__doc__, name),
                                              formatter_class=DefaultsHelpFormatter))
    upgrade_cmds.add_parsers(sub)
    return ap


class DefaultsHelpFormatter(argparse.HelpFormatter):
    """Help in which each option with a default states it where its own text does not: "(default
    X)" is added (a bench's --size, --frames, --tau... showed none). Options whose default is
    None or False, and hidden ones, are left as they are (their help says what "not given" means)."""

    def _fill_text(self, text, width, indent):  # a description's paragraphs stay paragraphs
        return "\n\n".join(textwrap.fill(" ".join(p.split()), width, initial_indent=indent, subsequent_indent=indent)
                           for p in text.split("\n\n"))

    def add_argument(self, action) -> None:
        if action.option_strings and action.help != argparse.SUPPRESS and action.default not in (None, False, argparse.SUPPRESS) \
                and "default" not in (action.help or ""):
            action.help = f"{action.help} (default %(default)s)" if action.help else "default %(default)s"
        super().add_argument(action)


def _doc_text(doc: str | None, name: str, paragraphs: int = 2) -> str:
    """A bench module's ``--help`` description: the first ``paragraphs`` paragraphs of its
    docstring without reST markup (what it runs, what it prints, what the figures mean)."""
    parts = [re.sub(r":[a-z]+:`~?", "`", " ".join(p.split())).replace("``", "").replace("`", "")  # (roles: :func:`~a.b` → a.b)
             for p in (doc or name).strip().split("\n\n")]
    parts = [p for p in parts if p and not re.fullmatch(r"massview bench [^.]*:", p)]  # (a bare usage line heading the text)
    return "\n\n".join(parts[:paragraphs])


def _doc_summary(doc: str | None, name: str) -> str:
    """A bench module's help: its docstring's first paragraph, without reST markup, up to its
    first full stop (the first line alone stopped mid-sentence)."""
    text = _doc_text(doc, name, 1)
    m = re.search(r"(?<! al)(?<! e\.g)\.(\s|$)", text)
    return text[: m.start() + 1] if m else text


def render_config(args) -> RenderConfig:
    """The RenderConfig of a render/view command line: every flag whose dest is a RenderConfig
    field (``--cache-mb`` -> ``cache_mb``) is passed by name, so a new field needs only its flag."""
    from dataclasses import fields

    w, h = parse_size(args.size)
    flags = {f.name: getattr(args, f.name) for f in fields(RenderConfig) if hasattr(args, f.name)}
    return RenderConfig.from_env(**{**flags, "width": w, "height": h, "sun": parse_sun(args.sun) if hasattr(args, "sun") else None})


def typed_options(argv: list[str]) -> set[str]:
    """The RenderConfig fields whose flags ``argv`` (a ``render``/``view`` command line) gives
    (:func:`typed_flags`)."""
    from dataclasses import fields

    return typed_flags(argv) & {f.name for f in fields(RenderConfig)}


def m2_option_warning(argv: list[str]) -> str | None:
    """The warning line for M2's options typed on a render without ``--system reliefboards``
    (walk8 M2: they were ignored silently), or None. (They are no RenderConfig fields, so
    :func:`massview.app.options.option_warnings` never sees them.)"""
    from .options import M2_OPTIONS, no_effect_line

    return no_effect_line(M2_OPTIONS, typed_flags(argv), "without --system reliefboards (M2 options)")


def typed_flags(argv: list[str]) -> set[str]:
    """The option names (argparse dests) ``argv`` (a ``render``/``view`` command line) gives,
    as argparse resolves them (abbreviations, ``--opt=value``): the line is parsed by the
    command's own arguments once for every name, then again into a namespace that holds a
    marker under each name — argparse fills in a default only where a name is missing, so the
    names still marked were not typed."""

    def parser() -> argparse.ArgumentParser:
        p = argparse.ArgumentParser(prog=f"massview {argv[0]}")
        _add_render_args(p)
        if argv[0] == "view":
            _add_view_args(p)
        return p

    rest = _negative_values(argv[1:])
    unset = object()
    marked = argparse.Namespace(**{name: unset for name in vars(parser().parse_args(rest))})
    got = vars(parser().parse_args(rest, namespace=marked))
    typed = {name for name, v in got.items() if v is not unset and v != []}  # ([]: no further T2 layer given)
    if "size" in typed:
        typed |= {"width", "height"}
    return typed


def cmd_render(args, argv: list[str]) -> int:
    from .. import api
    from ..parallel.runtime import in_mpi_job, world

    cfg = render_config(args)
    if in_mpi_job() and world().Get_rank() == 0 and args.ranks and args.ranks != world().Get_size() and not _launched_by_us():
        print(f"massview: note: running on the {world().Get_size()} ranks mpiexec gave, not --ranks {args.ranks}", file=sys.stderr)
    typed = {name: getattr(cfg, name) for name in typed_options(argv)}  # (judged by massview.app.options)
    m2 = None if in_mpi_job() else m2_option_warning(argv)
    if m2:
        print(f"massview: warning: {m2}", file=sys.stderr)
    try:
        res = api.render(args.scene, cfg.path, ranks=args.ranks, out=args.out, images=False, progress=not args.quiet, config=cfg,
                         **typed)
    except api.RankJobError as e:  # the failing rank printed its message already; an interrupted one left it to us
        if e.returncode == 130:
            _say_interrupted(args.out)
        return e.returncode
    except KeyboardInterrupt:  # Ctrl-C (the ranks of a --ranks N job stopped quietly)
        _say_interrupted(args.out)
        return 130
    except SystemExit as e:  # SIGTERM or SIGHUP to the launcher: its status stays 128 + signal
        if e.code in (129, 143):
            _say_interrupted(args.out)
        raise
    video = None
    if res is not None and getattr(args, "video", False):
        from .demo import write_video

        try:
            video = write_video(Path(args.out) / "frames", Path(args.out) / "video.mp4")
        except FileNotFoundError:
            print(f"massview: warning: --video: {args.out}/frames holds no frames (a --wall run writes its tiles under wall/); "
                  "no video written", file=sys.stderr)
    if res is not None and not args.quiet:
        from .report import print_summary

        print_summary(res.summary)
        print(f"wrote {args.out}/summary.json, {args.out}/stats.jsonl and the frames" + (f", and {video}" if video else ""))
    return 0


def _say_interrupted(out: Path) -> None:
    """One line for a render stopped part-way: how many frames it recorded, and where."""
    from ..parallel.runtime import in_mpi_job, world

    if in_mpi_job() and world().Get_rank() != 0:
        return
    frames = set()
    try:
        with open(out / "stats.jsonl") as f:
            for line in f:
                try:
                    frames.add(int(json.loads(line)["frame"]))
                except (ValueError, KeyError, TypeError):
                    pass  # (a last line cut short)
    except OSError:
        pass
    pngs = len(list((out / "frames").glob("[0-9]*.png"))) if (out / "frames").is_dir() else 0
    where = f"; frames so far in {out}" if frames or pngs else ""
    if pngs > len(frames):  # (the last frame's image is written before its stats record: walk7 L2)
        where += f" ({pngs} images in frames/, the last without its stats record)"
    print(f"massview: interrupted after {len(frames)} frame{'' if len(frames) == 1 else 's'}{where}", file=sys.stderr, flush=True)


_VIEW_IGNORES = ("--out", "-o", "--frames", "--path", "--reference", "--pipeline", "--video")  # render's options that view accepts and does not use


def cmd_view(args, argv) -> int:
    from ..parallel.runtime import guarded, in_mpi_job, relaunch, world

    cfg = render_config(args)
    if cfg.system == "reliefboards":
        from .reliefboards_cmds import cmd_view as _reliefboards_view

        return _reliefboards_view(args, argv, cfg)
    if not (0 <= args.port <= 65535):
        raise ConfigError(f"--port must be in 0..65535, got {args.port}")
    if not in_mpi_job():
        from ..api import validate
        from .viewer.server import check_port

        ignored = [f for f in _VIEW_IGNORES if any(a == f or a.startswith(f + "=") for a in argv)]
        if ignored:
            print(f"massview: note: view ignores {', '.join(ignored)} (render's options: the browser steers the camera, "
                  "and nothing is written)", file=sys.stderr)

        check_port(args.host, args.port)  # before the scene is loaded or any rank starts
        from ..api import warn_options
        from ..core.paths import load_path
        from ..systems import scene_kind

        validate(args.scene, cfg, args.ranks or 1)
        warn_options(args.scene, scene_kind(args.scene), cfg, typed_options(argv))
        load_path(cfg.path, [0, 0, 0], [1, 1, 1])
        if (args.ranks or 1) > 1:
            return relaunch(argv, args.ranks)
    comm = world()
    from .view_cmd import run_view

    return guarded(comm, run_view, comm, args, cfg)


def _warn_m2_options(scene: str, cfg: RenderConfig, argv: list[str]) -> None:
    """M2's parent process: a warning line per typed option it does not use (a terrain store
    is refused by M2's own check)."""
    from ..api import warn_options
    from ..systems import scene_kind

    kind = scene_kind(scene)
    if kind != "terrain":
        warn_options(scene, kind, cfg, typed_options(argv))


def _launched_by_us() -> bool:
    import os

    return os.environ.get("MASSVIEW_UNDER_MPI") == "1"


def cmd_report(args) -> int:
    from .report import load_run, print_summary, write_report

    if not (args.dir / "stats.jsonl").exists() and args.dir.is_dir():
        from .reliefboards_report import m2_runs, write_collection_report

        if m2_runs(args.dir):  # a folder of reliefboards runs: Figures 9 and 11 across backend counts
            for path in write_collection_report(args.dir):
                print(f"wrote {path}")
            return 0
    notes: list = []
    summary, records = load_run(args.dir, notes)
    for n in notes:
        print(f"massview: note: {n}", file=sys.stderr)
    print_summary(summary)
    path = write_report(args.dir, records, summary)
    print(f"wrote {path}")
    return 0


def cmd_bench(args) -> int:
    from .bench import BENCHES

    return BENCHES[args.bench].run(args)


def _report_peak_rss() -> None:
    """With MASSVIEW_PEAK_RSS_FILE set, write this process's peak RSS (bytes) there at exit."""
    import os

    path = os.environ.get("MASSVIEW_PEAK_RSS_FILE")
    if not path:
        return

    path = path.replace("{rank}", os.environ.get("PMI_RANK", "launcher"))  # one file per MPI rank (bench ingest)

    def write():
        with open("/proc/self/status") as f:
            kb = next(int(line.split()[1]) for line in f if line.startswith("VmHWM:"))
        Path(path).write_text(str(kb * 1024))

    atexit.register(write)


def _no_final_collection() -> None:
    """At exit, after every other exit handler (registered first, so it runs last): collect the
    young generations, then move every object still alive out of the collector's reach
    (``gc.freeze``). The interpreter's own collections at shutdown then skip the ~10⁶ objects
    numba, zarr and the modules leave (0.4–0.6 s of every command's exit measured here, against
    0.1 s); cyclic garbage of the old generation is left to the process's end, unfinalized, as
    objects alive at exit are. Files are closed by their own ``with`` blocks, not by that."""
    import gc

    gc.collect(1)
    gc.freeze()


_DASH_VALUE = re.compile(r"^-\d")


def _negative_values(argv: list[str]) -> list[str]:
    """``--opt -5x10`` → ``--opt=-5x10``: argparse takes a value that starts with a dash and is
    not a plain number (``-5x10``, ``-1e3``) for an option and says only "expected one
    argument"; joined, the value reaches the option's own check, which names what is wrong.
    (No option of massview is a dash and a digit.)"""
    out: list[str] = []
    for tok in argv:
        if out and _DASH_VALUE.match(tok) and out[-1].startswith("--") and "=" not in out[-1] and out[-1] != "--":
            out[-1] = f"{out[-1]}={tok}"
        else:
            out.append(tok)
    return out


_EXIT_HANDLER: list = []  # (registered once per process, by the first main)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not _EXIT_HANDLER:
        _EXIT_HANDLER.append(atexit.register(_no_final_collection))
    _report_peak_rss()
    reuse_freed_memory()  # per-frame images reuse freed pages (issue 20)
    if not in_mpi_job():
        return _main(argv)
    interrupt_on_sigterm()  # a rank stopped by SIGTERM says so and aborts the job like Ctrl-C
    try:
        return _main(argv)
    finally:
        ignore_late_sigterm()  # its work is done: a stop arriving now is not an interruption


def _main(argv: list[str]) -> int:
    if argv[:1] == ["__job"] and len(argv) == 2:  # a rank of a job started by massview.api.render
        from .render_job import run_job

        return run_job(argv[1])
    if argv[:1] == ["__m2job"] and len(argv) == 2:  # a rank of an M2 job started by massview.api.render
        from ..systems.reliefboards_job import run_job as run_m2_job

        return run_m2_job(argv[1])
    args = build_parser(argv).parse_args(_negative_values(argv))
    from ..api import flag_names

    try:
        with flag_names():  # the API's messages name --flags here, and its warnings are lines
            return _dispatch(args, argv)
    except MassviewError as e:
        print(f"massview: error: {e}", file=sys.stderr)
        return 2 if isinstance(e, ConfigError) else 1
    except KeyboardInterrupt:
        print("massview: interrupted", file=sys.stderr)
        return 130
    except Exception as e:  # a full disk, wherever it struck: one line, not a traceback (walk9 M1)
        if disk_full(e) is None:
            raise
        where = getattr(args, "out", None) or getattr(args, "output", None) or "the output"
        print(f"massview: error: {full_disk_line(e, where)}; free space (or choose another output) and run the "
              "command again", file=sys.stderr)
        return 1


def _check_store_spec(store: str, command: str) -> None:
    """``info``/``verify`` of a built-in scene or of a render's output folder: a StoreError
    saying what it is and what to run instead (walk8 L5: "no such store", "not a readable zarr
    group")."""
    if store.startswith("builtin:"):
        raise StoreError(f"{store}: a built-in scene, generated when it is rendered, not a store on disk: nothing to {'inspect' if command == 'info' else command} "
                         "(`massview render builtin:objects` draws it; `massview generate scene plant -o SCENE` makes a scene store)")
    p = Path(store)
    if p.is_dir() and not (p / "zarr.json").exists() and ((p / "summary.json").exists() or (p / "stats.jsonl").exists()):
        raise StoreError(f"{store}: the output folder of a `massview render` run, not a store: `massview report {store}` "
                         f"summarises it (report.png); `massview {command}` takes the store that run drew")


def _dispatch(args, argv: list[str]) -> int:
    """Run the parsed command; its status."""
    if args.command == "render" and args.system == "reliefboards":
        from .reliefboards_cmds import cmd_render as _reliefboards

        cfg = render_config(args)
        if not in_mpi_job():
            _warn_m2_options(args.scene, cfg, argv)
        return _reliefboards(args, argv, cfg)
    if args.command == "render":
        return cmd_render(args, argv)
    if args.command == "view":
        return cmd_view(args, argv)
    if args.command == "report":
        return cmd_report(args)
    if args.command == "bench":
        return cmd_bench(args)
    if args.command == "demo":
        from .demo import run_demo

        return run_demo(args)
    if args.command == "upgrade":
        return upgrade_cmds.cmd_upgrade(args)
    if args.command == "prepare" and args.what == "reliefboards":
        from .reliefboards_cmds import cmd_prepare

        return cmd_prepare(args)
    if args.command == "prepare" and args.what == "roettger":
        from .roettger_cmds import cmd_prepare_roettger

        return cmd_prepare_roettger(args)
    if args.command in ("generate", "prepare", "info", "verify"):
        from . import scene_cmds, terrain_cmds

        if args.command in ("info", "verify"):
            _check_store_spec(args.store, args.command)
        if args.command in ("info", "verify") and not Path(args.store).exists():
            raise StoreError(f"{args.store}: no such store; make a terrain store with `massview prepare terrain INPUT -o STORE` "
                             "or a scene store with `massview prepare scene MESH... -o SCENE`")
        scene = getattr(args, "what", None) == "scene" or (args.command in ("info", "verify") and scene_cmds.is_scene(args.store))
        return getattr(scene_cmds if scene else terrain_cmds, f"cmd_{args.command}")(args)
    return 0
