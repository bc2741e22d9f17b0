"""CLI commands for scene data: ``generate scene``, ``prepare scene``, and ``info``/``verify``
of a scene store (``terrain_cmds`` hands those over when the path is a scene store)."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

from ..core.errors import StoreError, disk_full, full_disk_line
from ..data.scene.normals import CREASE_ANGLE  # (numpy only: cheap for the parser)
from .terrain_cmds import _warn, progress_bar

__all__ = ["add_generate_parser", "add_prepare_parser", "cmd_generate", "cmd_prepare", "cmd_info", "cmd_verify", "is_scene"]


def add_generate_parser(gsub) -> None:
    g = gsub.add_parser("scene", help="a replicated massive scene (plant, city, forest), streamed to a scene store")
    g.add_argument("kind", choices=("plant", "city", "forest"))
    g.add_argument("out", nargs="?", help="scene store folder to write (or give it with -o)")
    g.add_argument("-o", "--output", default=None, help="the same output, as an option")
    g.add_argument("--copies", type=int, default=1, help="replicas of the scene, each stored as its own geometry (default 1)")
    g.add_argument("--size", type=float, default=1.0,
                   help="scale of one copy (default 1: plant ~21 600 nodes / 8.4 M triangles, city ~1100 nodes / 4.1 M, forest ~250 objects / 13.7 M)")
    g.add_argument("--seed", type=int, default=1)
    g.add_argument("--detail", type=float, default=1.0,
                   help="tessellation of curved shapes (default 1; triangles scale about as detail², nodes and hierarchy unchanged)")
    g.add_argument("--simplifier", choices=("fast-simplification", "pyfqmr"), default="fast-simplification")
    g.add_argument("--overwrite", action="store_true", help="rebuild a complete store")
    g.add_argument("--quiet", "-q", action="store_true")


def add_prepare_parser(psub) -> None:
    p = psub.add_parser("scene", help="PLY/OBJ/STL/OFF/glTF/GLB meshes -> scene store (objects, LOD levels)")
    p.add_argument("inputs", nargs="+", help="mesh files; several become one scene")
    p.add_argument("-o", "--output", required=True, help="scene store folder to write")
    p.add_argument("--object-triangles", type=int, default=16384, help="largest object cut from an unstructured mesh (default 16384)")
    p.add_argument("--object-size", type=float, default=None, help="largest box side of such an object, in file units (default: no limit)")
    p.add_argument("--instance", action="store_true", help="store geometry placed several times (glTF nodes of one mesh) once, with transforms")
    p.add_argument("--simplifier", choices=("fast-simplification", "pyfqmr"), default="fast-simplification")
    p.add_argument("--levels", type=int, default=8, help="most LOD levels per object (default 8)")
    p.add_argument("--stream-mb", type=float, default=256, help="binary PLY this large or larger is streamed in chunks (default 256)")
    p.add_argument("--crease-angle", type=float, default=CREASE_ANGLE, metavar="DEG",
                   help="meshes without normals in the file: faces meeting at more than DEG degrees get separate (flat) normals, "
                        f"gentler edges are smoothed; 0 < DEG <= 180, 180 smooths everything (default {CREASE_ANGLE:g})")
    p.add_argument("--up", default="auto", metavar="{auto,y,z}",
                   help="the inputs' up axis; massview's world is +z up and y-up inputs are turned to it "
                        "((x, y, z) -> (x, -z, y)). auto (default): y for glTF/GLB (their specification), z for "
                        "PLY/OBJ/STL/OFF (no convention: say --up y for a y-up one)")
    p.add_argument("--overwrite", action="store_true", help="rebuild a complete store")
    p.add_argument("--quiet", "-q", action="store_true")


def cmd_generate(args) -> int:
    from ..core.errors import ConfigError
    from ..data.generators.scenes import generate_scene
    from .outputs import check_output_file, one_output

    out = one_output(args.out, args.output, f"`massview generate scene {args.kind} -o OUT` (OUT: a scene store folder, e.g. city.zarr)")
    if out.suffix.lower() not in ("", ".zarr", ".scene") and not out.is_dir():  # (as generate terrain: -o city.glb is no store name)
        raise ConfigError(f"output {out}: {out.suffix} is not a format generate scene writes; give a scene store folder "
                          "(STORE.zarr or STORE.scene)")
    check_output_file(out, "output")
    try:
        with progress_bar(args.quiet) as prog:
            a = generate_scene(args.kind, out, copies=args.copies, size=args.size, seed=args.seed,
                               overwrite=args.overwrite, progress=prog, backend=args.simplifier, detail=args.detail)
    except KeyboardInterrupt:
        print(f"massview: interrupted; {interrupted_note(out)}", file=sys.stderr)
        return 130
    except Exception as e:  # a full disk: what is kept and how to go on, in one line (walk9 M1)
        if disk_full(e) is None:
            raise
        print(f"massview: error: {full_disk_line(e, out)}; free space, then: {interrupted_note(out)}", file=sys.stderr)
        return 1
    print(f"wrote scene store {out}: {a['objects']} objects, {a['triangles']:,} triangles, {a['groups']} groups, "
          f"{a['occluders']} occluders")
    return 0


def prepare_files(inputs, output, *, option: str, quiet: bool, object_triangles: int = 16384, object_size: float | None = None,
                  instance: bool = False, simplifier: str = "fast-simplification", levels: int = 8, stream_mb: float = 256,
                  crease_angle: float = CREASE_ANGLE, up: str = "auto", overwrite: bool = False) -> dict:
    """Prepare the scene store ``output`` from the mesh files ``inputs``: what ``massview prepare
    scene`` and :func:`massview.prepare_scene` both run. ``option`` names ``output`` in messages
    (``-o`` or ``out=``); ``quiet``: no progress bars. Returns prepare_scene's dict (its
    warnings not yet said)."""
    from ..core.errors import ConfigError
    from ..data.scene.ingest import IngestParams, prepare_scene
    from .outputs import check_output_file

    out = Path(output)
    if object_size is not None and not (math.isfinite(object_size) and object_size > 0):
        raise ConfigError(f"--object-size must be a positive length in file units (leave it out for no limit), got {object_size:g}")
    if not (math.isfinite(stream_mb) and stream_mb >= 0):
        raise ConfigError(f"--stream-mb must be a size in MB, 0 or more, got {stream_mb:g}")
    if object_triangles < 1:
        raise ConfigError(f"--object-triangles must be a positive triangle count, got {object_triangles}")
    if not 1 <= levels <= 16:
        raise ConfigError(f"--levels must be between 1 and 16, got {levels}")
    check_output_file(out, option)
    prm = IngestParams(object_triangles=object_triangles, object_size=object_size or float("inf"), instance=instance,
                       simplifier=simplifier, max_levels=levels, stream_bytes=int(stream_mb * 2**20),
                       crease_angle=crease_angle, up=up)
    with progress_bar(quiet) as prog:
        return prepare_scene(list(inputs), out, prm, overwrite=overwrite, progress=prog)


def cmd_prepare(args) -> int:
    out = Path(args.output)
    try:
        a = prepare_files(args.inputs, out, option="-o", quiet=args.quiet, object_triangles=args.object_triangles,
                          object_size=args.object_size, instance=args.instance, simplifier=args.simplifier, levels=args.levels,
                          stream_mb=args.stream_mb, crease_angle=args.crease_angle, up=args.up, overwrite=args.overwrite)
    except KeyboardInterrupt:
        print(f"massview: interrupted; {interrupted_note(out)}", file=sys.stderr)
        return 130
    except Exception as e:  # a full disk: what is kept and how to go on, in one line (walk9 M1)
        if disk_full(e) is None:
            raise
        print(f"massview: error: {full_disk_line(e, out)}; free space, then: {interrupted_note(out)}", file=sys.stderr)
        return 1
    _warn(a["warnings"])
    s = max(a["seconds"], 1e-9)
    print(f"{_how(a, out)}: {a['objects']} objects "
          f"({a['geometries']} geometries), {a['triangles']:,} triangles, {a['occluders']} occluders, {a['seconds']:.1f} s "
          f"({a['input_bytes'] / 1e6 / s:.1f} MB/s, {a['triangles'] / s:,.0f} triangles/s)")
    return 0


def _how(a: dict, out: Path) -> str:
    """How the store came about: written, resumed (saying how much was kept) or started over."""
    if not a["resumed"]:
        return f"wrote {out}"
    if a["objects_kept"]:
        return f"resumed {out} ({a['objects_kept']} of {a['objects']} objects were already written)"
    return (f"started {out} over{' from its spilled cells' if a['spill_reused'] else ''} (the interrupted run had saved no "
            f"checkpoint: one is saved every {a['checkpoint_bytes'] / 2**20:g} MiB of stored geometry)")


def interrupted_note(out: Path) -> str:
    """What an interrupted ``prepare``/``generate scene`` leaves at ``out`` and how to go on."""
    from ..data.scene.writer import CHECKPOINT_BYTES

    try:
        attrs = json.loads((Path(out) / "zarr.json").read_text())["attributes"]
        kept, complete = int(attrs["checkpoint"]["objects"]), bool(attrs.get("complete"))
    except (OSError, ValueError, KeyError, TypeError):  # no store yet
        return "nothing was written yet; re-run the same command to start"
    if complete:  # (--overwrite, stopped before it began rewriting)
        return f"{out} is unchanged; re-run the same command to rebuild it"
    if kept:
        return f"{out} keeps the {kept} objects of its last checkpoint: re-run the same command to continue from there"
    return (f"{out} has no checkpoint yet (one is saved every {CHECKPOINT_BYTES >> 20} MiB of stored geometry), so "
            "re-running the same command starts it over")


def is_scene(path) -> bool:
    from ..data.scene import is_scene_store

    return is_scene_store(path)


def cmd_info(args) -> int:
    from ..data.scene.verify import scene_info

    info = scene_info(Path(args.store))
    if args.json:
        print(json.dumps(info, indent=2))
    else:
        from rich.console import Console
        from rich.table import Table

        t = Table(title=f"scene store {info['path']}", show_header=False)
        for k, v in info.items():
            if k.endswith("bytes") and isinstance(v, int):
                v = f"{v / 2**20:.1f} MiB"
            elif k == "reliefboards" and isinstance(v, dict):
                v = _clusters_line(v)
            t.add_row(k, str(v))
        Console().print(t)
    if not info["complete"]:
        from ..data.rebuild import being_written

        why = ("is being written by a prepare running now; wait for it to finish" if being_written(args.store)
               else "is incomplete; re-run the prepare/generate command to finish it")
        print(f"massview: error: {args.store} {why}", file=sys.stderr)
        return 1
    return 0


def _clusters_line(rb: dict) -> str:
    """The stored Reliefboards clustering in one line, as ``prepare reliefboards`` printed it."""
    g = lambda k: f"{rb[k]:.4g}" if isinstance(rb.get(k), (int, float)) else "?"  # noqa: E731
    return (f"{rb['clusters']} clusters: {rb['feasible']} feasible, {rb['too_large']} too large (> sl_c = {g('sl_c')}), "
            f"{rb['too_few_triangles']} with too few triangles (< {rb.get('min_triangles', '?')}); t_nz = {rb.get('t_nz', '?')}, "
            f"d_nz = {g('d_nz')}, board {rb.get('p', '?')} px, r_y = {rb.get('r_y', '?')} px, fovy = {rb.get('fovy', '?')}")


def cmd_verify(args) -> int:
    from ..data.scene.verify import verify_scene

    with progress_bar(args.quiet) as prog:
        problems = verify_scene(Path(args.store), prog)
    if problems:
        for p in problems[:20]:
            print(f"massview: verify: {p}", file=sys.stderr)
        raise StoreError(f"{args.store}: {len(problems)} problem(s) found")
    print(f"{args.store}: OK — every object's levels decode, bounds contain the geometry, counts and errors agree")
    return 0
