"""Prepare a synthetic DEM: MB/s, wall and CPU time, peak RSS, on-disk size; then fly it.

``massview bench ingest [--size 16385|32769]``: prepare a synthetic DEM and report throughput,
compression and peak RSS (issue 20: ≥ 100 MB/s of float32 input at ≤ 1 GiB RSS).

The DEM (default 16385², 1 GiB of float32; ``--size 32769``: 4.3 GB) is generated once into
``--workdir`` as ``synthetic_SIZE_seedSEED.npy``, or given with ``--dem`` (an existing file: a
missing one is an error, exit 2). Then, in the same run:

* baseline: a plain copy of the same bytes (read in 64 MiB pieces, write to a file) — the
  disk floor for touching the data once;
* floor: reading the DEM once (``readinto`` one reused buffer) plus writing the store's own
  files again (same names and bytes, with the chunk writer's calls, on as many threads as
  prepare's workers) — what no ingest can beat on this disk, whatever it computes;
* page cost: seconds per GiB to write page-cache pages the kernel hands out new, and the same
  pages again in place — on a VM whose balloon reports freed pages to its host, the first is
  several times the second, and the store's bytes pay it;
* ``massview prepare terrain --workers N`` in a child process, which reports its own peak
  resident memory (``VmHWM`` of /proc/self/status) at exit. (``wait4``'s ``ru_maxrss`` would
  not do: Linux carries the parent's high-water mark over fork and exec.) CPU time is the
  child's user + system time: CPU ÷ wall is how many cores it kept busy;
* with ``--fly`` (default for sizes ≥ 32769): ``massview render STORE --path zoom`` and
  ``--path flyover`` on ``--ranks`` ranks (default 4) with default budgets, each rank
  reporting its own peak RSS, against the 1 GiB target.

Before the timed prepare, an untimed one of a small synthetic DEM (1025², generated once into
``--workdir``) loads the ingest's numba kernels, or compiles them on a new checkout (~60 s on 2
cores), so that the timed one finds them in the cache; its line says which. The timed prepare
records in its stages file (``MASSVIEW_STAGES_FILE``) what numba still compiled (kernels the
warm-up did not need: the window-level kernels of a DEM of 7 levels, 16385², 29 signatures,
~8 s): then a warning says how many seconds of the figures are compiling, and to run again.

Printed: input MB/s of prepare, its ratio to the copy baseline and to the floor, wall, CPU, the height
compression ratio, the store size, peak RSS and the per-rank peaks. Nothing is asserted.

The run deletes what it wrote (the store, unless ``--keep``, and the floor's copy: ~11 000 files
each at 16385²) only at its end, after every measurement, and notes when (``.bench_deleted`` in
the work folder): ext4 without a journal skips inodes deleted in the last 1–6 minutes one by
one while allocating new ones (``recently_deleted``), so a prepare started soon after such a
deletion pays for it (creating 11 520 small files in 64 folders: 0.41 s of system time on a
quiet file system, 1.40 s right after deleting 23 000; without the store's allocation hint
0.75 s against 3.93 s). A run that starts within 6 minutes of the last one's deletion says so
beside its figures.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

from .child import run_measured

__all__ = ["add_arguments", "run"]


def add_arguments(p) -> None:
    p.add_argument("--size", type=int, default=16385, help="samples per side (default 16385: 1 GiB float32)")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--block", type=int, default=257)
    p.add_argument("--workdir", default="out/bench", help="where the DEM is generated once and the store written")
    p.add_argument("--no-color", action="store_true")
    p.add_argument("--keep", action="store_true", help="keep the store afterwards")
    p.add_argument("--dem", default=None,
                   help="an existing DEM file prepare reads (e.g. .npy with its .json spacing sidecar) instead of the synthetic "
                        "one; it must exist (an error otherwise). Without --dem: WORKDIR/synthetic_SIZE_seedSEED.npy, "
                        "generated on the first run and reused")
    p.add_argument("--workers", type=int, default=0, help="prepare's worker threads (default 0: every core)")
    p.add_argument("--fly", choices=("auto", "on", "off"), default="auto",
                   help="after prepare, render --path zoom and flyover on --ranks ranks and report each rank's peak RSS "
                        "(auto: for sizes ≥ 32769)")
    p.add_argument("--ranks", type=int, default=4, help="ranks of the flights (default 4)")
    p.add_argument("--frames", type=int, default=10, help="frames per flight (default 10)")


def _copy_baseline(src: Path, dst: Path) -> float:
    t0 = time.perf_counter()
    with open(src, "rb") as f, open(dst, "wb") as g:
        while True:
            buf = f.read(64 << 20)
            if not buf:
                break
            g.write(buf)
        g.flush()
        os.fsync(g.fileno())
    dt = time.perf_counter() - t0
    dst.unlink()
    return dt


def _read_floor(src: Path) -> float:
    """Seconds to read ``src`` once into one reused 64 MiB buffer (``readinto``; the page cache
    is warm after the copy baseline): the input side of the floor."""
    buf = bytearray(64 << 20)
    t0 = time.perf_counter()
    with open(src, "rb", buffering=0) as f:
        while f.readinto(buf):
            pass
    return time.perf_counter() - t0


def _page_cost(work: Path, mib: int = 256) -> tuple[float, float]:
    """Seconds per GiB to write into page-cache pages the kernel must newly hand out (a new
    file), and into pages already cached (the same file again, in place): the part of the write
    floor that is the host's memory, not the file system. On a VM that returns freed memory to
    its host (virtio-balloon free page reporting), every new page costs a host fault."""
    piece = b"\x5a" * (1 << 20)
    f = work / "pages.tmp"
    f.unlink(missing_ok=True)
    out = []
    for flags in (os.O_WRONLY | os.O_CREAT | os.O_TRUNC, os.O_WRONLY):
        fd = os.open(f, flags)
        try:
            t = time.perf_counter()
            for k in range(mib):
                os.pwrite(fd, piece, k << 20)
            out.append((time.perf_counter() - t) * 1024 / mib)
        finally:
            os.close(fd)
    f.unlink(missing_ok=True)
    return out[0], out[1]


def _free_page_reporting() -> bool:
    """Whether this machine is a VM whose balloon device reports freed pages to the host
    (virtio device 5, feature bit 5, VIRTIO_BALLOON_F_REPORTING)."""
    for d in Path("/sys/bus/virtio/devices").glob("*"):
        try:
            if int((d / "device").read_text(), 16) == 5 and (d / "features").read_text()[5:6] == "1":
                return True
        except (OSError, ValueError):
            continue
    return False


def _write_floor(store: Path, dst: Path, threads: int = 2) -> tuple[float, float]:
    """Write every file of ``store`` again under ``dst``: the same names and bytes, with the
    chunk writer's own calls (each folder once, :func:`store.make_top_folder` for an array's
    ``c``; the nested chunk folders and the file by :func:`store.write_chunk_file`, a flat
    key's file by :func:`store.write_file`), block rows shared out over ``threads`` threads
    as prepare's workers share them. Each file's bytes are read first, outside the timed part.
    Returns (the slowest thread's seconds in those calls, the system CPU seconds of all threads
    in them): what writing this store costs on this file system, whatever computes it."""
    import resource
    import threading

    from ...data.terrain.store import make_top_folder, write_chunk_file, write_file

    files = sorted(p.relative_to(store) for p in store.rglob("*") if p.is_file())
    rows: dict = {}
    for rel in files:  # a chunk's block row: "c.<i>.…", or the folder under "c"; metadata files go with row 0
        parts = rel.parts
        row = parts[parts.index("c") + 1] if "c" in parts[:-1] else parts[-1].split(".")[1] if parts[-1].startswith("c.") else "0"
        rows.setdefault(row, []).append(rel)
    shares: list = [[] for _ in range(threads)]
    for k, key in enumerate(sorted(rows, key=lambda r: (len(r), r))):
        shares[k % threads].extend(rows[key])
    made, lock = set(), threading.Lock()
    spent, system = [0.0] * threads, [0.0] * threads

    def folder(d: Path) -> None:  # each folder once, parents first, under the lock
        if d in made:
            return
        with lock:
            for f in [*reversed(d.relative_to(dst).parents), d.relative_to(dst)]:
                f = dst / f
                if f not in made:
                    if f.name == "c":
                        make_top_folder(str(f))
                    else:
                        f.mkdir(exist_ok=True)
                    made.add(f)

    def put(rel: Path, data: bytes) -> None:
        parts = rel.parts
        if "c" not in parts[:-1]:
            folder((dst / rel).parent)
            write_file(str(dst / rel), data)
            return
        c = parts.index("c")
        folder(dst.joinpath(*parts[:c + 1]))
        row = dst.joinpath(*parts[:c + 2])
        if row not in made:  # this thread's own row
            os.makedirs(row, exist_ok=True)
            made.add(row)
        write_chunk_file(str(row / parts[c + 2]), list(parts[c + 3:]), data)

    def work(n: int) -> None:
        for rel in shares[n]:
            data = (store / rel).read_bytes()
            r, t = resource.getrusage(resource.RUSAGE_THREAD), time.perf_counter()
            put(rel, data)
            spent[n] += time.perf_counter() - t
            system[n] += resource.getrusage(resource.RUSAGE_THREAD).ru_stime - r.ru_stime

    dst.mkdir(parents=True)
    ts = [threading.Thread(target=work, args=(n,)) for n in range(threads)]
    for t in ts:
        t.start()
    for t in ts:
        t.join()
    return max(spent), sum(system)


def _fly(store: Path, work: Path, args, console) -> list[tuple[str, object]]:
    """Render the zoom and flyover paths on ``args.ranks`` ranks; per-path ChildRun."""
    import sys as _sys

    out = []
    for path in ("zoom", "flyover"):
        cmd = [_sys.executable, "-m", "massview", "render", str(store), "--path", path, "--ranks", str(args.ranks),
               "--frames", str(args.frames), "--out", str(work / f"fly_{path}"), "--quiet"]
        console.print("running: " + " ".join(cmd[2:]))
        out.append((path, run_measured(cmd, work / f"fly_{path}.peak_rss", ranks=args.ranks)))
    return out


_DELETED = ".bench_deleted"  # {"time": epoch s, "files": n}: the last run's deletion (see the module docstring)
_RECENT_S = 360  # ext4's window: 60 s for a clean inode-table block, 360 s for a dirty one


def _files(path: Path) -> int:
    return sum(len(fs) for _, _, fs in os.walk(path)) if path.exists() else 0


def _delete(work: Path, paths: list[Path]) -> None:
    """Delete ``paths`` and note when, and how many files, for the next run's note."""
    n = sum(_files(p) for p in paths)
    for p in paths:
        shutil.rmtree(p, ignore_errors=True)
    if n:
        (work / _DELETED).write_text(json.dumps({"time": time.time(), "files": n}))


def _recent_deletion(work: Path) -> str | None:
    """A note when the last run deleted its files less than ``_RECENT_S`` seconds ago."""
    try:
        d = json.loads((work / _DELETED).read_text())
        ago = time.time() - float(d["time"])
    except (OSError, ValueError, KeyError, TypeError):
        return None
    if not 0 <= ago < _RECENT_S:
        return None
    return (f"{int(d.get('files', 0)):,} files were deleted {ago:.0f} s before this prepare (the last run's): on ext4 without a "
            f"journal new files cost more for up to {_RECENT_S // 60} minutes after (recently deleted inodes are skipped one by one); "
            f"for the figure of a quiet file system, start the next run {_RECENT_S // 60} minutes after the last one ends")


def _check_dem(given: str) -> tuple[Path, int, str]:
    """The ``--dem`` file, checked as prepare will open it, its smaller side and its sample type
    (the table's title: it said float32 for any DEM): a ConfigError (exit 2) naming ``--dem``
    and the path when it does not exist, is a folder or is no DEM prepare reads. (A missing one
    was generated as a 1 GiB synthetic DEM and benchmarked, walk12 finding 2.)"""
    import warnings

    from ...core.errors import ConfigError, MassviewError

    dem = Path(given)
    if not dem.exists():
        raise ConfigError(f"--dem {dem}: no such file; give an existing DEM, or omit --dem to generate (once) and use "
                          "WORKDIR/synthetic_SIZE_seedSEED.npy")
    if dem.is_dir():
        raise ConfigError(f"--dem {dem}: is a folder; give a DEM file prepare reads (.npy, .tif, ...)")
    try:
        from ...data.terrain import open_source

        with warnings.catch_warnings():  # (the child prepare says them)
            warnings.simplefilter("ignore")
            src = open_source(dem)
        ds = getattr(src, "ds", None)
        if ds is not None:
            ds.close()
    except MassviewError as e:
        why = str(e).removeprefix(f"{dem}: ")
        raise ConfigError(f"--dem {dem}: not a DEM prepare reads ({why})") from None
    except OSError as e:
        raise ConfigError(f"--dem {dem}: cannot be read ({e.strerror or e})") from None
    return dem, min(src.rows, src.cols), str(getattr(src, "dtype", "float32"))


def _generate_cmd(dem: Path, size: int, seed: int) -> list[str]:
    """The child command that writes the synthetic DEM ``dem`` (``size``², ``seed``)."""
    return [sys.executable, "-m", "massview", "generate", "terrain", str(dem), "--size", str(size), "--seed", str(seed), "--quiet"]


def _prepare_cmd(dem: Path, store: Path, args) -> list[str]:
    """The child ``prepare terrain`` of ``dem`` into ``store`` with the bench's ``--block``,
    ``--workers`` and colour: the timed one and the warm-up's (the same, so that it loads the
    kernels the timed one takes)."""
    return [sys.executable, "-m", "massview", "prepare", "terrain", str(dem), "-o", str(store), "--block", str(args.block),
            "--workers", str(args.workers), "--quiet"] + (["--no-color"] if args.no_color else [])


def _warm_up(work: Path, side: int, args, console, made: list[Path]) -> Path:
    """Load (or, the first time, compile) the ingest's numba kernels before the clock starts: an
    untimed child ``prepare terrain`` of a small synthetic DEM (generated once into the work
    folder, kept) with the same ``--block``, ``--workers`` and colour: 1025² (4 blocks of 257 a
    side), or the DEM's own smaller ``side`` when that is less (a one-block store takes
    kernels a larger one does not). About 2 s when numba's
    cache holds them; the ~60 s compile of a new checkout otherwise (walk12 finding 1: it was
    timed as the ingest, 14 MB/s instead of 90). Returns its store, for the run to delete at
    its end with the rest (not now: see the module docstring on recent deletions)."""
    n = min(max(1025, 4 * (args.block - 1) + 1), side)
    dem = work / f"warmup_{n}_seed1.npy"
    store = work / f"warmup.tmp-{os.getpid()}.zarr"
    stages = work / "warmup.stages.json"
    made += [dem.with_name(dem.name + ".partial"), store, store.with_name(f".{store.name}.lock"), stages]
    console.print(f"warming the ingest kernels with an untimed prepare of a {n}² synthetic DEM ... ", end="")
    t0 = time.perf_counter()
    if not dem.exists():
        gen = subprocess.run(_generate_cmd(dem, n, 1), stdout=subprocess.DEVNULL)
        if gen.returncode != 0:
            console.print(f"[yellow]generating it failed (exit {gen.returncode}); the timed prepare may include compiling[/]")
            return store
    stages.unlink(missing_ok=True)
    proc = subprocess.run(_prepare_cmd(dem, store, args), env=dict(os.environ, MASSVIEW_STAGES_FILE=str(stages)), stdout=subprocess.DEVNULL)
    dt = time.perf_counter() - t0
    try:
        c = json.loads(stages.read_text()).get("compile") or {}
    except (OSError, ValueError):
        c = {}
    stages.unlink(missing_ok=True)
    if proc.returncode != 0:
        console.print(f"[yellow]failed (exit {proc.returncode}); the timed prepare may include compiling[/]")
    elif c.get("kernels"):
        console.print(f"compiled {c['kernels']} kernel signatures in {c['seconds']:.0f} s ({dt:.1f} s in all; cached for "
                      "later runs)")
    else:
        console.print(f"loaded from numba's cache ({dt:.1f} s)")
    return store


def run(args) -> int:
    """The bench; on Ctrl-C (walk12 finding 13), what this run wrote is deleted before the
    interruption goes on: the partial store and its lock, the floor's and baseline's copies,
    the warm-up's store, a half-generated DEM."""
    made: list[Path] = []
    try:
        return _run(args, made)
    except KeyboardInterrupt:
        work = Path(args.workdir)
        _delete(work, [p for p in made if p.is_dir()])
        for p in made:
            if not p.is_dir():
                p.unlink(missing_ok=True)
        print("bench ingest: interrupted; deleted what this run had written in " + str(work), file=sys.stderr)
        raise


def _run(args, made: list[Path]) -> int:
    from rich.console import Console
    from rich.table import Table

    from ..outputs import check_output_dir
    from ..terrain_cmds import store_info

    console = Console()
    given, side, dtype = _check_dem(args.dem) if args.dem else (None, args.size, "float32")  # (before anything is made)
    work = check_output_dir(Path(args.workdir), "--workdir")
    dem = given or work / f"synthetic_{args.size}_seed{args.seed}.npy"
    if not dem.exists():  # in a child process: this one must stay small (see _peak_rss)
        console.print(f"generating {dem} (once; kept for later runs) ...")
        made.append(dem.with_name(dem.name + ".partial"))
        t0 = time.perf_counter()
        subprocess.run(_generate_cmd(dem, args.size, args.seed), check=True)
        console.print(f"generated in {time.perf_counter() - t0:.1f} s")
    nbytes = dem.stat().st_size
    store = work / f"{dem.stem}.zarr"
    # an interrupted run's leftovers, deleted at the end
    stale = sorted(work.glob("floor.tmp*")) + sorted(work.glob("*.zarr.old-*")) + sorted(work.glob("warmup.tmp-*.zarr"))
    stale.append(_warm_up(work, side, args, console, made))
    made.append(work / "copy.tmp")
    copy_s = _copy_baseline(dem, work / "copy.tmp")
    # a kept store of an earlier run is moved aside (a rename frees no inode) and deleted at the end too
    if store.exists():
        stale.append(store.with_name(f"{store.name}.old-{os.getpid()}"))
        store.rename(stale[-1])
    made += stale + [store, store.with_name(f".{store.name}.lock")]
    recent = _recent_deletion(work)
    if recent:
        console.print(f"[yellow]note:[/] {recent}")
    cmd = _prepare_cmd(dem, store, args)
    console.print("running: " + " ".join(cmd[2:]))
    stages_file = work / "prepare.stages.json"
    stages_file.unlink(missing_ok=True)
    os.environ["MASSVIEW_STAGES_FILE"] = str(stages_file)
    try:
        run = run_measured(cmd, work / "prepare.peak_rss")
    finally:
        del os.environ["MASSVIEW_STAGES_FILE"]
    if run.returncode == 130:  # (interrupted: the child had the Ctrl-C)
        raise KeyboardInterrupt
    if run.returncode != 0:
        console.print(f"[red]prepare failed (exit {run.returncode})[/]")
        _delete(work, stale)
        return run.returncode
    prep_s, rss = run.wall_s, run.peak_rss
    info = store_info(store)
    t = Table(title=f"ingest of {dem.name} ({nbytes / 2**30:.2f} GiB {dtype}), block {args.block}, workers {args.workers or 'all'}")
    t.add_column("figure")
    t.add_column("value", justify="right")
    t.add_row("prepare wall time", f"{prep_s:.1f} s")
    t.add_row("prepare CPU time (user + system)", f"{run.cpu_s:.1f} s ({run.cpu_s / prep_s:.2f} cores busy)")
    t.add_row("prepare throughput", f"{nbytes / 1e6 / prep_s:.1f} MB/s (target 100)")
    said = json.loads(stages_file.read_text()) if stages_file.exists() else {}
    if said.get("seconds"):  # the ingest itself: from prepare_terrain's start to the store marked complete
        own = float(said["seconds"])
        t.add_row("  of it, the ingest itself (without the interpreter's start-up and imports, "
                  f"{max(prep_s - own, 0):.1f} s)", f"{own:.1f} s, {nbytes / 1e6 / own:.1f} MB/s")
    compiled = said.get("compile") or {}
    compile_warning = None
    if compiled.get("kernels"):  # kernels the warm-up did not need (other dtypes, voids, ...): timed with the ingest
        cs = float(compiled.get("seconds", 0))
        compile_warning = (f"numba compiled {compiled['kernels']} kernel signatures during the timed prepare: the figures above "
                           f"include {cs:.1f} s of compiling; run again for the ingest's own rate (they are cached now)")
        t.add_row("[yellow]  of it, numba compiling kernels (not the ingest)[/]",
                  f"[yellow]{cs:.1f} s, {compiled['kernels']} signatures: run again[/]")
    t.add_row("throughput per CPU-second", f"{nbytes / 1e6 / max(run.cpu_s, 1e-9):.1f} MB/s")
    for name, (w, c, sy, flt) in said.get("stages", {}).items():
        t.add_row(f"  stage: {name}", f"{w:.1f} s wall, {c:.1f} CPU-s ({c / max(w, 1e-9):.2f} cores), "
                                      f"{sy:.1f} s system, {flt / 1e3:.0f} k faults")
    t.add_row("copy baseline (same bytes)", f"{copy_s:.1f} s, {nbytes / 1e6 / copy_s:.1f} MB/s")
    t.add_row("prepare ÷ copy time", f"{prep_s / copy_s:.1f}×")
    floor_dir = work / f"floor.tmp-{os.getpid()}"  # (fresh: not a deleted one's name)
    made += [floor_dir, work / "pages.tmp"]
    read_s = _read_floor(dem)
    write_s, write_sys = _write_floor(store, floor_dir, max(args.workers or len(os.sched_getaffinity(0)), 1))
    stale.append(floor_dir)
    floor_s = read_s + write_s
    new_s, again_s = _page_cost(work)
    t.add_row("read floor (the DEM once, page cache, one reused buffer)", f"{read_s:.2f} s, {nbytes / 1e6 / read_s:.0f} MB/s")
    t.add_row("write floor (the same store bytes, the chunk writer's calls)", f"{write_s:.1f} s ({write_sys:.1f} s system CPU)")
    t.add_row("page-cache writes: new pages, the same pages again",
              f"{new_s:.2f}, {again_s:.2f} s per GiB ({info['disk_bytes'] / 2**30 * (new_s - again_s):.1f} s of the write floor is "
              f"new pages{'; this VM reports freed pages to its host' if _free_page_reporting() else ''})")
    t.add_row("prepare ÷ floor (read + write)", f"{prep_s / floor_s:.1f}× ({nbytes / 1e6 / floor_s:.0f} MB/s at the floor)")
    t.add_row("height compression ratio", f"{info['compression_ratio']:.3f}")
    t.add_row("store on disk (heights + shading + metadata)", f"{info['disk_bytes'] / 2**20:.0f} MiB")
    t.add_row("peak RSS of prepare", f"{rss / 2**20:.0f} MiB ({'under' if rss < 2**30 else 'OVER'} the 1 GiB target)")
    fly = args.fly == "on" or (args.fly == "auto" and args.size >= 32769 and not args.dem) or (args.fly == "auto" and args.dem and nbytes >= 4 << 30)
    status = 0
    if fly:
        for path, r in _fly(store, work, args, console):
            if r.returncode != 0:
                t.add_row(f"render --path {path} --ranks {args.ranks}", f"[red]failed (exit {r.returncode})[/]")
                status = r.returncode
                continue
            worst = max(r.rank_peak_rss.values(), default=0)
            ranks = ", ".join(f"{v / 2**20:.0f}" for _, v in sorted(r.rank_peak_rss.items()))
            t.add_row(f"render --path {path} --ranks {args.ranks}: wall, CPU", f"{r.wall_s:.1f} s, {r.cpu_s:.1f} s")
            t.add_row("  peak RSS per rank (MiB)", f"{ranks} ({'all under' if 0 < worst < 2**30 else 'NOT all under'} 1 GiB)")
    if recent:
        t.add_row("file system", recent)
    console.print(t)
    if compile_warning:
        console.print(f"[yellow]warning:[/] {compile_warning}")
    _delete(work, stale + ([] if args.keep else [store]))
    return status
