"""CLI commands for terrain data: ``generate terrain``, ``prepare terrain``, ``info``, ``verify``."""

from __future__ import annotations

import json
import os
import shutil
import sys
from contextlib import contextmanager
from pathlib import Path

from ..core.errors import ConfigError, OutputError, StoreError, disk_full, full_disk_line

__all__ = ["cmd_generate", "cmd_prepare", "cmd_info", "cmd_verify", "compile_note", "progress_bar"]


@contextmanager
def progress_bar(quiet: bool = False):
    """Yields ``update(phase, advance, total)``: a rich bar per phase with rate and ETA."""
    if quiet:
        yield lambda *a: None
        return
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, ProgressColumn, TextColumn, TimeRemainingColumn
    from rich.text import Text

    class RateColumn(ProgressColumn):
        def render(self, task):
            return Text(f"{task.speed:8.1f}/s" if task.speed else "        ", style="cyan")

    with Progress(TextColumn("[bold]{task.description:<10}"), BarColumn(), MofNCompleteColumn(), RateColumn(),
                  TimeRemainingColumn(), console=Console(file=sys.stderr)) as p:
        tasks = {}

        def update(phase: str, advance: int, total: int) -> None:
            if phase not in tasks:
                tasks[phase] = p.add_task(phase, total=total)
            p.advance(tasks[phase], advance)

        yield update


def _warn(messages) -> None:
    for m in messages:
        print(f"massview: warning: {m}", file=sys.stderr)


def cmd_generate(args) -> int:
    from ..data.generators.terrain import SYNTHETIC_SPACING
    from ..data.terrain import prepare_terrain
    from ..data.terrain.sources import write_sidecar
    from ..data.terrain.synthetic import SyntheticSource, write_synthetic
    from .outputs import check_output_file, one_output

    out = one_output(args.out, args.output, "`massview generate terrain -o OUT --size N` (OUT: a store folder, FILE.tif or FILE.npy)")
    fmt = args.format or {".npy": "npy", ".tif": "tif", ".tiff": "tif"}.get(out.suffix.lower(), "store")
    if fmt == "store" and not args.format and out.suffix.lower() not in ("", ".zarr") and not out.is_dir():
        raise ConfigError(f"output {out}: {out.suffix} is not a format generate writes; give STORE.zarr (a terrain store folder), "
                          "FILE.tif or FILE.npy (or --format store|tif|npy)")
    check_output_file(out, "output")
    if fmt != "store" and out.is_dir():
        raise OutputError(f"output {out}: is a folder; give a file name for --format {fmt}")
    from ..data.terrain.workers import return_freed_memory

    return_freed_memory()
    with compile_note(args.quiet), progress_bar(args.quiet) as prog:
        if fmt == "store":
            res = prepare_terrain(SyntheticSource(args.size, args.seed), out, block=args.block, overwrite=args.overwrite, progress=prog)
            msg = f"wrote terrain store {out} ({res.layout.levels} levels, {res.seconds:.1f} s)"
        else:
            if out.exists() and not args.overwrite:
                raise ConfigError(f"{out} exists; pass --overwrite to replace it")
            try:
                write_synthetic(out, args.size, args.seed, fmt, lambda a, t: prog("generate", a, t))
            except Exception as e:  # GDAL's write error names no cause (its "No space left" went to its log)
                if disk_full(e) is None and shutil.disk_usage(out.parent).free >= 1 << 20:
                    raise
                raise OutputError(f"{out}: no space left on the device; free space (or choose another output) and run the "
                                  "command again") from None
            msg = f"wrote {out} ({args.size}x{args.size} float32, {SYNTHETIC_SPACING:g} m sample spacing)"
            if fmt == "npy":  # .npy has no georeference: record it beside the file, and say what to pass
                side = write_sidecar(out, (SYNTHETIC_SPACING, SYNTHETIC_SPACING))
                msg += (f"\n.npy holds no georeference: the spacing is recorded in {side}, which `massview prepare terrain` "
                        f"reads; elsewhere pass --spacing {SYNTHETIC_SPACING:g}")
    print(msg)
    return 0


def _shape(spec: str | None):
    if spec is None:
        return None
    try:
        r, c = (int(v) for v in spec.lower().split("x"))
        return r, c
    except ValueError:
        raise ConfigError(f"--shape {spec!r}: expected ROWSxCOLS") from None


@contextmanager
def compile_note(quiet: bool):
    """Within the block, a note on stderr when the ingest's kernels start compiling (numba: the
    first prepare after installing, or one whose input needs kernels the cache lacks, waits
    about a minute on 2 cores for them); nothing when they all load from the cache."""
    if quiet:
        yield
        return
    from ..data.jit import on_first_compile

    def note() -> None:
        print("massview: note: compiling the ingest kernels (about a minute on 2 cores, once: later runs load them "
              "from the cache)", file=sys.stderr, flush=True)

    with on_first_compile(note):
        yield


def prepare_file(input, output, *, option: str, quiet: bool, color=None, no_color: bool = False, nodata=None, array=None,
                 shape=None, dtype=None, spacing=None, crs=None, block: int = 257, vertical_scale: float = 1.0,
                 overwrite: bool = False, workers: int = 0):
    """Open the DEM file ``input`` (and the orthophoto ``color``) and prepare the store
    ``output`` from it: what ``massview prepare terrain`` and :func:`massview.prepare_terrain`
    both run. ``option`` names ``output`` in messages (``-o`` or ``out=``); ``quiet``: no compile
    note, no progress bars. Returns the ingest's PrepareResult (its warnings not yet said)."""
    from ..data.terrain import open_source, prepare_terrain
    from ..data.terrain.workers import return_freed_memory
    from .outputs import check_output_file

    return_freed_memory()  # threads' freed rows go back to the system (≤ 1 GiB RSS, issue 20)
    check_output_file(Path(output), option)
    src = open_source(input, nodata=nodata, array=array, shape=shape, dtype=dtype, spacing=spacing, crs=crs)
    ortho = open_source(color) if color else None
    with compile_note(quiet), progress_bar(quiet) as prog:
        return prepare_terrain(src, Path(output), block=block, vertical_scale=vertical_scale,
                               color=None if no_color else "computed", ortho=ortho, overwrite=overwrite, progress=prog, workers=workers)


@contextmanager
def _compile_record():
    """Yields a function giving what numba compiled within the block, for the stages file of
    ``MASSVIEW_STAGES_FILE`` (``bench ingest``'s child: ``--quiet`` hides :func:`compile_note`,
    and the bench must say when its timed figure includes compiling). Without a stages file
    it gives None, and numba is not loaded here for it."""
    if not os.environ.get("MASSVIEW_STAGES_FILE"):
        yield lambda: None
        return
    from ..data.jit import compile_clock

    with compile_clock() as clock:
        yield lambda: {"seconds": round(clock.seconds, 3), "kernels": clock.kernels}


def cmd_prepare(args) -> int:
    try:
        with _compile_record() as compiled:
            res = prepare_file(args.input, args.output, option="-o", quiet=args.quiet, color=args.color, no_color=args.no_color,
                               nodata=args.nodata, array=args.array, shape=_shape(args.shape), dtype=args.dtype,
                               spacing=args.spacing, crs=args.crs, block=args.block, vertical_scale=args.vertical_scale,
                               overwrite=args.overwrite, workers=getattr(args, "workers", 0))
    except KeyboardInterrupt:
        print(f"massview: interrupted; {_interrupted_note(Path(args.output))}", file=sys.stderr)
        return 130
    except Exception as e:  # a full disk: what is kept and how to go on, in one line (walk9 M1)
        if disk_full(e) is None:
            raise
        print(f"massview: error: {full_disk_line(e, args.output)}; free space, then: {_interrupted_note(Path(args.output))}",
              file=sys.stderr)
        return 1
    mb = res.input_bytes / 1e6
    if not res.resumed:
        how = f"wrote {res.path}"
    elif res.rows_kept:
        how = f"resumed {res.path} ({res.rows_kept} of {res.layout.blocks(0)} block rows of level 0 were already written)"
    else:
        how = f"started {res.path} over (the interrupted run had finished no block row)"
    _warn(res.warnings)  # (first: they describe the run the lines below report)
    lv = res.layout.levels
    print(f"{how}: {res.layout.rows}x{res.layout.cols} samples, "
          f"{lv} level{'' if lv == 1 else 's'} of {res.layout.M}² blocks, {res.filled} nodata sample{'' if res.filled == 1 else 's'} filled, "
          f"{res.seconds:.1f} s ({mb / max(res.seconds, 1e-9):.1f} MB/s)")
    print("stages (wall, CPU of all threads, of it system): " + "; ".join(f"{k} {v[0]:.1f} s, {v[1]:.1f} s, {v[2]:.1f} s" for k, v in res.stages.items()))
    if os.environ.get("MASSVIEW_STAGES_FILE"):  # for `massview bench ingest` (compile: what numba compiled meanwhile)
        Path(os.environ["MASSVIEW_STAGES_FILE"]).write_text(json.dumps({"stages": res.stages, "seconds": res.seconds,
                                                                         "compile": compiled()}))
    return 0


def _interrupted_note(out: Path) -> str:
    """What an interrupted ``prepare terrain`` leaves at ``out`` and how to go on."""
    from ..data.rebuild import is_complete_store
    from ..data.terrain.store import FORMAT, rows_done

    if is_complete_store(out, FORMAT):  # (--overwrite: the rebuild beside it was removed)
        return f"{out} is unchanged; re-run the same command to rebuild it"
    done = rows_done(out)
    if done is None:
        return "no unfinished store to continue; re-run the same command to start"
    if done[0]:
        return (f"{out} keeps the {done[0]} of {done[1]} block rows it finished: re-run the same command to continue "
                "from there")
    return f"{out} has no finished block row yet, so re-running the same command starts it over"


def store_info(path: Path) -> dict:
    from ..data.terrain import TerrainStore, dir_size

    st = TerrainStore(path, require_complete=False)
    lay = st.layout
    disk = dir_size(path)
    hdisk = dir_size(Path(path) / "heights")
    raw = sum(lay.blocks(lv) ** 2 for lv in range(lay.levels)) * lay.M * lay.M * 4
    a = st.attrs
    return {
        "path": str(path), "complete": bool(a.get("complete")), "format_version": a.get("format_version"),
        "samples": [lay.rows, lay.cols], "padded": lay.S,
        "block": lay.M, "K": lay.K, "levels": lay.levels,
        "blocks_per_level": [lay.blocks(lv) ** 2 for lv in range(lay.levels)],
        "spacing_m": a.get("spacing"), "vertical_scale": a.get("vertical_scale"), "height_range": a.get("height_range"),
        "crs": a.get("crs"), "transform": a.get("transform"), "nodata": a.get("nodata"),
        "filled_fraction": round(int((a.get("nodata") or {}).get("filled", 0)) / max(lay.rows * lay.cols, 1), 6),
        "source": a.get("source"),
        "color": a.get("color"), "disk_bytes": disk, "height_disk_bytes": hdisk, "raw_height_bytes": raw,
        "compression_ratio": round(raw / hdisk, 3) if hdisk and a.get("complete") else None,  # (of a whole store only)
        "world_box": _world_box(st) if a.get("complete") else None,
    }


def _world_box(st) -> list[list[float]] | None:
    """[[x, y, z] lo, [x, y, z] hi] in world metres (what keyframe files and ``mv.camera`` use:
    x east = column × dx, y north = −row × dy, z = height × vertical scale)."""
    from ..lod.kpatch import world_box

    try:
        lo, hi = world_box(st.layout, *st.height_ranges(0), st.spacing, st.vertical_scale)
    except Exception:  # noqa: BLE001 - a damaged metadata array: info still prints the rest
        return None
    return [[round(float(v), 3) for v in lo], [round(float(v), 3) for v in hi]]


_COLOR_TEXT = {None: "none (grey, or a colour map at render time)", "computed": "computed: a colour map at render time (no colour arrays)",
               "orthophoto": "orthophoto (color/ arrays)"}


def cmd_info(args) -> int:
    import json

    info = store_info(Path(args.store))
    if args.json:
        print(json.dumps(info, indent=2))
    else:
        from rich.console import Console
        from rich.table import Table

        t = Table(title=f"terrain store {info['path']}", show_header=False)
        for k, v in info.items():
            if k == "crs" and v:
                from ..data.terrain.sources import crs_name

                v = crs_name(v)
            if k in ("disk_bytes", "height_disk_bytes", "raw_height_bytes"):
                v = f"{v / 2**20:.1f} MiB"
            elif k == "color":
                v = _COLOR_TEXT.get(v, v)
            elif k == "world_box" and v:
                v = (", ".join(f"{a} {lo:.6g}..{hi:.6g}" for a, lo, hi in zip("xyz", *v))
                     + " (world metres: keyframe files and mv.camera use these)")
            elif k in ("compression_ratio", "world_box") and v is None:
                v = "— (the store is incomplete)" if not info["complete"] else "—"
            elif k == "format_version" and v == 2:
                v = "2 (stores level 0's shading; `massview upgrade` converts it to 3, about half the size)"
            t.add_row(k, str(v))
        Console().print(t)
    if not info["complete"]:
        from ..data.rebuild import being_written

        why = ("is being written by a prepare running now; wait for it to finish" if being_written(args.store)
               else "is incomplete; re-run the prepare command to finish it")
        print(f"massview: error: {args.store} {why}", file=sys.stderr)
        return 1
    return 0


def cmd_verify(args) -> int:
    from ..data.terrain.verify import verify_store

    with progress_bar(args.quiet) as prog:
        problems = verify_store(Path(args.store), prog)
    if problems:
        for p in problems:
            print(f"massview: verify: {p}", file=sys.stderr)
        raise StoreError(f"{args.store}: {len(problems)} problem(s) found")
    from ..data.terrain import TerrainStore

    what = "heights, shading, colour" if TerrainStore(Path(args.store)).has_color else "heights, shading"
    print(f"{args.store}: OK — every array has its layout's shape, every block ({what}) and the Röttger table "
          "decode, metadata, the shading and the table match the data, errors are saturated")
    return 0
