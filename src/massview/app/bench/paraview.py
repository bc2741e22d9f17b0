"""massview beside ParaView's pvbatch + IceT on the same DEM, cameras, image size and ranks.

``massview bench paraview [STORE]`` (default: the demo's 4097² terrain, as ``bench frame``):

1. exports the store's finest level as one float32 grid and the ``--frames`` cameras of the
   flyover path (position, focal point, up, field of view) — the cameras massview renders;
2. runs ``pvbatch`` (on one Xvfb server started for the whole run when there is no display,
   :func:`x_display`; llvmpipe through GLX) on 1 and 2 ranks (``mpiexec`` of the MPI ParaView
   was built with, found on PATH as ``mpiexec.openmpi``/``mpiexec``), drawing a surface of
   every STEP-th sample (``--steps``; 1: the full surface, 2·(n−1)² triangles; ``auto``: the
   two adjacent steps whose surfaces bracket the triangles massview drew,
   :func:`bracket_steps`), and reads IceT's own timers on every rank (``ICET_COMPOSITE_TIME``
   …) to isolate its compositing per frame;
3. runs massview first, on the same cameras (``bench frame``'s job: warm caches, synchronous
   loop) for sort-last and sort-first on 1 and 2 ranks;
4. prints frame times, triangles, the 1→2-rank speed-ups and the ratios, and compositing per
   frame at 2 ranks: IceT's against massview's encode + transfer + composite;
5. at equal triangles: per mode and rank count, ParaView's frame time interpolated linearly in
   triangles between the two measured surfaces that bracket massview's exact count
   (:func:`interpolate_ms`; never extrapolated: without a bracket it says so), and massview ÷
   ParaView.

When ``pvbatch`` is not installed it says so and exits 0 (Debian/Ubuntu: ``apt-get install
paraview xvfb``). ParaView is never a dependency of massview or of its tests. Nothing here
asserts a time.
"""

from __future__ import annotations

import json
import os
import select
import shutil
import subprocess
import tempfile
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from ...core.paths import load_path
from ...core.config import parse_size
from ...core.errors import ConfigError
from .args import int_list, positive, size, terrain_store
from .frame import STAGES as _STAGE_NAMES

__all__ = ["add_arguments", "run", "surface_triangles", "bracket_steps", "auto_steps", "interpolate_ms", "x_display"]

_SCRIPT = Path(__file__).with_name("pvbatch_script.py")


def add_arguments(p) -> None:
    p.add_argument("store", nargs="?", default=None, help="terrain store (default: the demo's 4097² terrain)")
    p.add_argument("--size", type=size, default="1280x1024")
    p.add_argument("--frames", type=positive, default=8, help="cameras along the flyover path (default 8)")
    p.add_argument("--ranks", type=int_list(1, example="1,2"), default="1,2", help="rank counts (default 1,2)")
    p.add_argument("--workdir", default="out/bench", help="where the exported grid and the demo terrain go")
    p.add_argument("--steps", type=int_list(1, extra=("auto",), example="auto or 9,10"), default="auto", help="ParaView surfaces: every STEP-th sample, comma-separated; auto: as many triangles as massview drew "
                        "(default auto; 1 is the full surface)")
    p.add_argument("--skip-massview", action="store_true", help="only run pvbatch")
    p.add_argument("--reuse", action="store_true", help="reuse pvbatch results already in --workdir (pv_RANKS_STEP.json)")


def export_grid(store_path: Path, workdir: Path) -> dict:
    """The finest level as ``*.heights.raw`` (float32, rows × cols, rows flipped: the last row
    first, so that ParaView's +y grid is massview's y = −row·dy); returns its shape, spacing
    and vertical scale."""
    from ...data.terrain import TerrainStore

    st = TerrainStore(store_path)
    lay = st.layout
    raw = Path(workdir) / f"{Path(store_path).name}.heights.raw"
    if not raw.exists():
        m, nb = lay.M - 1, lay.blocks(0)
        full = np.empty((nb * m + 1, nb * m + 1), np.float32)
        for i in range(nb):
            for j in range(nb):
                full[i * m: i * m + m + 1, j * m: j * m + m + 1] = st.get_block(0, i, j)
        Path(workdir).mkdir(parents=True, exist_ok=True)
        full[: lay.rows, : lay.cols][::-1].tofile(raw)
    dx, dy = st.spacing
    return {"raw": str(raw), "rows": lay.rows, "cols": lay.cols, "dx": dx, "dy": dy, "vscale": st.vertical_scale}


def export_cameras(store_path: Path, frames: int, size: str, path: Path) -> None:
    """The flyover cameras as ParaView wants them (camera looks along −z, up is +y)."""
    from ...systems import open_system

    w, h = parse_size(size)
    system = open_system(str(store_path))
    cams = []
    for c in load_path("flyover", *system.bounds).cameras(frames, w, h):
        pos = np.asarray(c.position)
        cams.append({"position": pos.tolist(), "focal": (pos + c.forward * 100.0).tolist(), "up": c.up.tolist(), "fovy": c.fovy})
    system.close()
    path.write_text(json.dumps({"size": [w, h], "cameras": cams}))


@contextmanager
def x_display(screen: str = "1920x1200x24", timeout: float = 30.0):
    """The X display pvbatch draws on: the caller's ``DISPLAY`` when set, else one Xvfb server
    for the whole ``with`` block, on a free display number that Xvfb picks and reports itself
    once it accepts connections (``-displayfd``), stopped on exit. (This replaced an
    ``xvfb-run -a`` per pvbatch run: after massview's own MPI jobs, the 2-rank pvbatch's server
    refused its connection ("bad X server connection", with its retry, in both runs of the
    whole benchmark on 2026-11-27), while a run without massview's jobs and a run on one server
    started beforehand passed. The cause was not found.)"""
    if os.environ.get("DISPLAY"):
        yield os.environ["DISPLAY"]
        return
    xvfb = shutil.which("Xvfb")
    if xvfb is None:
        raise RuntimeError("pvbatch needs an X display: there is no DISPLAY and Xvfb is not installed "
                           "(Debian/Ubuntu: `apt-get install xvfb`), or set DISPLAY to a running X server")
    with tempfile.TemporaryFile() as log:
        r, w = os.pipe()
        try:
            proc = subprocess.Popen([xvfb, "-displayfd", str(w), "-screen", "0", screen, "-nolisten", "tcp"], pass_fds=(w,),
                                    stdin=subprocess.DEVNULL, stdout=log, stderr=log)
        except BaseException:
            os.close(r)
            raise
        finally:
            os.close(w)
        try:
            number = b""
            while not number.endswith(b"\n"):
                ready, _, _ = select.select([r], [], [], timeout)
                chunk = os.read(r, 32) if ready else b""
                if not chunk:  # timed out, or Xvfb exited without a display
                    break
                number += chunk
        finally:
            os.close(r)
        try:
            if not number.strip().isdigit():
                proc.kill()
                proc.wait()
                log.seek(0)
                raise RuntimeError(f"Xvfb did not start a display within {timeout:g} s (exit {proc.returncode}): "
                                   f"{log.read().decode(errors='replace')[-800:]}")
            yield f":{int(number)}"
        finally:
            if proc.poll() is None:
                proc.terminate()
                try:
                    proc.wait(timeout=10)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()


def run_pvbatch(grid: dict, cams: Path, step: int, ranks: int, workdir: Path, display: str | None = None) -> dict:
    """pvbatch on ``ranks`` ranks drawing every ``step``-th sample; its JSON result. On the X
    ``display`` given, else on :func:`x_display`'s."""
    if display is None:
        with x_display() as d:
            return run_pvbatch(grid, cams, step, ranks, workdir, d)
    out = workdir / f"pv_{ranks}_{step}.json"
    script = workdir / "pvbatch_script.py"  # run from a copy: beside this module, "import paraview" would find it
    shutil.copyfile(_SCRIPT, script)
    args = [script, grid["raw"], grid["rows"], grid["cols"], grid["dx"], grid["dy"], grid["vscale"], step, cams, out]
    cmd = [shutil.which("pvbatch"), "--force-offscreen-rendering", *map(str, args)]
    if ranks > 1:
        mpi = shutil.which("mpiexec.openmpi") or shutil.which("mpiexec")
        cmd = [mpi, "--allow-run-as-root", "--oversubscribe", "-n", str(ranks), *cmd]
    env = dict(os.environ, OMPI_MCA_btl_vader_single_copy_mechanism="none", DISPLAY=display)
    for stale in workdir.glob(f"{out.name}.icet.*.json"):
        stale.unlink()
    for attempt in range(2):  # (a second try where a busy machine made the first fail)
        proc = subprocess.run(cmd, capture_output=True, text=True, env=env)
        if proc.returncode == 0 and out.exists():
            return {**json.loads(out.read_text()), "icet": icet_composite_ms(workdir, out.name)}
    raise RuntimeError(f"pvbatch failed (exit {proc.returncode}, DISPLAY={display}): {' '.join(map(str, cmd))}\n"
                       f"{(proc.stdout + proc.stderr)[-3000:]}")


def surface_triangles(rows: int, cols: int, step: int) -> int:
    """Triangles of ParaView's surface of every ``step``-th sample of a ``rows`` × ``cols`` grid
    (pvbatch_script.py: ``ExtractSubset`` keeps samples 0, s, 2s, … up to the last index on each
    axis — VTK's vtkExtractGrid without IncludeBoundary — and ``Triangulate`` splits every quad
    in two)."""
    if step < 1:
        raise ConfigError(f"--steps: a sample step must be ≥ 1, got {step}")
    return 2 * ((rows - 1) // step) * ((cols - 1) // step)


def bracket_steps(rows: int, cols: int, triangles: float) -> list[int]:
    """The sample steps whose surfaces bracket ``triangles``: [s, s + 1] with s the largest step
    of at least that many triangles (s + 1 has fewer); [s] when s's surface has exactly that
    many; [1] when even the full surface has fewer (no bracket: ParaView is never extrapolated,
    :func:`interpolate_ms` then answers None)."""
    if not triangles > 0:
        raise ConfigError(f"massview drew {triangles} triangles: nothing to match ParaView's surface to")
    if triangles >= surface_triangles(rows, cols, 1):
        return [1]
    s = 1
    while surface_triangles(rows, cols, s + 1) >= triangles:
        s += 1
    return [s] if surface_triangles(rows, cols, s) == triangles else [s, s + 1]


def auto_steps(grid: dict, counts: list[float]) -> list[int]:
    """Every step :func:`bracket_steps` names for any of massview's triangle ``counts``."""
    if not counts:
        raise ConfigError("--steps auto needs massview's own run (leave out --skip-massview)")
    return sorted({s for t in counts for s in bracket_steps(grid["rows"], grid["cols"], t)})


def interpolate_ms(points: list[tuple[float, float]], triangles: float) -> float | None:
    """ParaView's frame time (ms) at ``triangles``, linear in triangles between the nearest
    measured (triangles, ms) points at or below and at or above it; None when ``points`` do not
    bracket it (never extrapolated)."""
    below = [p for p in points if p[0] <= triangles]
    above = [p for p in points if p[0] >= triangles]
    if not below or not above:
        return None
    (t0, m0), (t1, m1) = max(below), min(above)
    if t1 == t0:
        return float(m0)
    return float(m0 + (m1 - m0) * (triangles - t0) / (t1 - t0))


def icet_composite_ms(workdir: Path, name: str) -> dict | None:
    """IceT's own compositing time per frame from the pvbatch ranks' timer files
    (``NAME.icet.RANK.json``, see ``pvbatch_script.py``: rank 0's, the only rank that runs the
    script, its wait for the others included): per frame the slowest rank's
    ``ICET_COMPOSITE_TIME`` (and ``ICET_COLLECT_TIME``, ``ICET_TOTAL_DRAW_TIME``), mean over
    frames, in ms, over the ranks that could read them; None when none could (one rank: IceT does
not composite)."""
    ranks = [json.loads(f.read_text())["frames"] for f in sorted(Path(workdir).glob(f"{name}.icet.*.json"))]
    ranks = [frames for frames in ranks if frames and all(f is not None for f in frames)]
    if not ranks:
        return None
    out = {}
    for key in ("composite", "collect", "total_draw", "render"):
        per_frame = np.max([[f[key] for f in frames] for frames in ranks], axis=0)
        out[key] = 1e3 * float(np.mean(per_frame))
    out["bytes_sent"] = float(np.mean(np.sum([[f["bytes_sent"] for f in frames] for frames in ranks], axis=0)))
    return out


def _massview(args, store: Path, ranks: list[int]) -> dict:
    """massview's frame on the same cameras (``bench frame``'s job): {(mode, ranks): result}."""
    from types import SimpleNamespace

    from .frame import _launch

    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        for mode, dec in (("sort-last", "sort-last:kpatch"), ("sort-first", "sort-first:kd")):
            for n in ranks:
                a = SimpleNamespace(size=args.size, frames=args.frames, decomposition=dec, compositor="binary-swap", codec="auto")
                out[(mode, n)] = _launch(a, store, n, "auto", tmp)
    return out


def run(args) -> int:
    from rich.console import Console

    console = Console(width=None if Console().is_terminal else 150)
    if shutil.which("pvbatch") is None:
        console.print("pvbatch is not installed: the ParaView comparison is skipped (Debian/Ubuntu: "
                      "`apt-get install paraview xvfb`; any ParaView ≥ 5.10 with MPI works)")
        return 0
    from .frame import demo_store

    workdir = Path(args.workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    store = terrain_store(args.store) if args.store else demo_store(args.workdir)
    grid = export_grid(store, workdir)
    cams = workdir / "pv_cameras.json"
    export_cameras(store, args.frames, args.size, cams)
    ranks = [int(v) for v in args.ranks.split(",") if v.strip()]
    mv = {} if args.skip_massview else _massview(args, store, ranks)
    pv = {}
    steps = sorted({s for v in args.steps.split(",") if v.strip()
                    for s in (auto_steps(grid, [r["sync"]["triangles"] for r in mv.values() if r]) if v.strip() == "auto" else [int(v)])})
    for s in steps:
        surface_triangles(grid["rows"], grid["cols"], s)  # a clear error for a step < 1
    todo = [(step, n) for step in steps for n in ranks]
    for step, n in todo:
        done = workdir / f"pv_{n}_{step}.json"
        if args.reuse and done.exists():
            pv[(step, n)] = json.loads(done.read_text())
    if any(key not in pv for key in todo):
        with x_display() as display:  # one X server for every pvbatch run
            for step, n in todo:
                if (step, n) not in pv:
                    console.print(f"[dim]pvbatch, {n} rank(s), every {step} sample(s) (DISPLAY {display}) ...[/]")
                    pv[(step, n)] = run_pvbatch(grid, cams, step, n, workdir, display)
    _print(console, pv, mv, ranks, steps, args, store)
    return 0


def _print(console, pv: dict, mv: dict, ranks: list[int], steps: list[int], args, store: Path) -> None:
    from rich.table import Table

    t = Table(title=f"massview vs ParaView pvbatch + IceT: {store.name}, {args.size}, {args.frames} flyover cameras (mean ms/frame)")
    for c in ("system", "surface / mode", *(f"{n} rank ms" for n in ranks), "M triangles", f"speed-up {ranks[0]}→{ranks[-1]}"):
        t.add_column(c, justify="right")
    rows = []
    for step in steps:
        label = "full" if step == 1 else f"every {step} samples"
        ms = [1e3 * float(np.mean(pv[(step, n)]["seconds"])) for n in ranks]
        rows.append(("ParaView", label, ms, pv[(step, ranks[0])]["triangles"] / 1e6))
    for mode in ("sort-last", "sort-first"):
        if all(mv.get((mode, n)) for n in ranks):
            ms = [mv[(mode, n)]["sync"]["latency_ms"] for n in ranks]
            rows.append(("massview", f"LOD, {mode}", ms, mv[(mode, ranks[0])]["sync"]["triangles"] / 1e6))
    for system, label, ms, mtri in rows:
        t.add_row(system, label, *(f"{v:.0f}" for v in ms), f"{mtri:.3f}", f"{ms[0] / ms[-1]:.2f}×")
    console.print(t)
    _print_compositing(console, pv, mv, ranks, steps)
    _print_equal(console, pv, mv, ranks, steps)
    console.print("ParaView times: Render() + reading the composited image back on rank 0, after one untimed render; "
                  "massview: the synchronous frame (LOD, draw, readback, compositing, delivery to rank 0) with warm caches.")


def _print_compositing(console, pv: dict, mv: dict, ranks: list[int], steps: list[int]) -> None:
    """Compositing per frame at the largest rank count: IceT's own timer (rank 0, the display
    rank) against massview's encode + transfer + composite (the slowest rank's stage means,
    synchronous loop: at least rank 0's); both include waiting for the slower rank's draw."""
    n = ranks[-1]
    if n < 2:
        return
    for step in steps:
        icet = pv[(step, n)].get("icet")
        if not icet:
            console.print(f"IceT timers not read at {n} ranks, every {step} samples (libvtkIceTCore not found)")
            continue
        line = (f"compositing per frame at {n} ranks: IceT (every {step} samples) {icet['composite']:.1f} ms "
                f"(collect {icet['collect']:.1f}, IceT total draw {icet['total_draw']:.1f}, {icet['bytes_sent'] / 1e6:.2f} MB sent)")
        for mode in ("sort-last", "sort-first"):
            r = mv.get((mode, n))
            if r:
                st = dict(zip(_STAGE_NAMES, r["sync"]["stage_ms"]))
                ours = st["encode"] + st["transfer"] + st["composite"]
                line += f"; massview {mode} {ours:.1f} ms ({ours / icet['composite']:.2f}× IceT's)" if icet["composite"] > 0 else ""
        console.print(line)


def _print_equal(console, pv: dict, mv: dict, ranks: list[int], steps: list[int]) -> None:
    """Per mode and rank count: ParaView interpolated to massview's exact triangle count
    (:func:`interpolate_ms` over the surfaces measured at that rank count), and the ratio."""
    from rich.table import Table

    t = Table(title="at equal triangles: ParaView's frame interpolated linearly in triangles to massview's count (never extrapolated)")
    for c in ("mode", "ranks", "massview ms", "M triangles", "ParaView surfaces (M triangles)", "ParaView ms (interpolated)", "massview ÷ ParaView"):
        t.add_column(c, justify="right")
    for mode in ("sort-last", "sort-first"):
        for n in ranks:
            r = mv.get((mode, n))
            if not r:
                continue
            tri = r["sync"]["triangles"]
            points = [(float(pv[(s, n)]["triangles"]), 1e3 * float(np.mean(pv[(s, n)]["seconds"]))) for s in steps if (s, n) in pv]
            ms = interpolate_ms(points, tri)
            used = ", ".join(f"{p[0] / 1e6:.3f}" for p in sorted(points))
            mine = r["sync"]["latency_ms"]
            t.add_row(mode, str(n), f"{mine:.0f}", f"{tri / 1e6:.3f}", used, "no bracket" if ms is None else f"{ms:.0f}",
                      "—" if ms is None else f"{mine / ms:.2f}×")
    console.print(t)
