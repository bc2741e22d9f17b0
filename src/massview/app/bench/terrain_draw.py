"""Draw throughput (``massview bench terrain STORE --draw``): K-patch path vs a plain mesh vs VTK.

Two cases on one rank, in one GL context:

* **full resolution**: a view of the whole terrain with τ → 0, so every patch is at level 0
  (all 2·(S−1)² triangles);
* **demo LOD**: the demo's view (``flyover`` at mid-path, 1280×720, τ = 1).

For each case the same triangles are drawn (every path draws the front's own triangles, in
the front's order) by

* ``K-patch`` — :class:`~massview.render.terrain.TerrainRenderer` as the system draws
  (forward or deferred shading by triangles per pixel, back faces culled with the eye above
  the terrain, one multi-draw-indirect call: a command per whole block, else per patch);
* ``K-patch, forward`` / ``K-patch, deferred`` — the same with the shading forced;
* ``K-patch, a draw per patch`` — the same without merging whole blocks into one command;
* ``K-patch before`` — forward per-fragment shading and a draw per patch: the path before
  issue 20 (kept selectable as the reference the new one reproduces bit for bit);
* ``plain mesh`` — :class:`~massview.render.terrain.PlainMeshRenderer`: one VBO of the finest
  grid, one index buffer, one ``glDrawElements`` (per-vertex normal and colour);
* ``VTK`` — pyvista/VTK (``vtk_draw.py``) offscreen through EGL, in a child process, same
  cameras and image size, same triangles as one PolyData.

Timing: ``reps`` draws per path, interleaved, each ``clear + draw + glFinish`` (readback
apart); printed are the median wall time, the process CPU time (all llvmpipe threads), the
calling thread's CPU time (llvmpipe runs vertex processing, clipping, triangle setup and
binning there, rasterisation on its LP_NUM_THREADS threads: on an idle machine the wall
time of a draw of sub-pixel triangles is close to this), Mtri/s = triangles ÷ median wall
time and triangles ÷ median main-thread time, and ratios to the plain mesh and to VTK
measured in the same run. On a loaded machine the wall figures mostly measure the wait for
a core; the CPU figures much less so. Readback (colour + depth of the
whole image) is timed separately. On a GPU, "GPU ms" is the median GL timer query around each
draw's commands: what the GPU spent, apart from the CPU's part of the wall time (on an H200
the K-patch draw's GPU time was a fraction of its wall time before its command building was
made cheap; README "On an NVIDIA GPU"). Mesa's software rasterizers show "—" there.
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from ...core.camera import Camera, look_at_quaternion
from ...core.config import RenderConfig, parse_size
from ...core.paths import load_path
from ...core.stats import FrameStats

__all__ = ["run_draw"]


def _cases(sysm, size):
    """(name, camera, τ) of the two cases."""
    lo, hi = sysm.bounds
    c = (lo + hi) / 2
    ext = float(np.hypot(*(hi - lo)[:2]))
    eye = (c[0], c[1] - 0.3 * ext, hi[2] + 1.2 * ext)
    w, h = size
    full = Camera(eye, look_at_quaternion(eye, c), 45.0, ext * 0.05, ext * 4, w, h)
    demo = load_path("flyover", lo, hi).camera(0.5, 1280, 720)
    return [("full resolution", full, 1e-9), ("demo LOD", demo, 1.0)]


def _time(fb, ctx, fn, reps_out: list, tris_out: list, query=None) -> None:
    """One timed draw: (wall, process CPU, calling-thread CPU, GPU) seconds appended to
    ``reps_out``; GPU time is a GL timer query around the draw's commands (None without
    ``query``)."""
    fb.begin()
    ctx.finish()
    t0, c0, m0 = time.perf_counter(), time.process_time(), time.thread_time()
    if query is None:
        tris = fn()
    else:
        with query:
            tris = fn()
    ctx.finish()
    wall, cpu, main = time.perf_counter() - t0, time.process_time() - c0, time.thread_time() - m0
    reps_out.append((wall, cpu, main, query.elapsed / 1e9 if query is not None else None))
    tris_out.append(tris)


def _ms(v: float) -> str:
    return f"{v:.1f}" if v < 100 else f"{v:.0f}"


def _gpu_timer(ctx):
    """A GL timer query where its figures mean something: not on Mesa's software rasterizers,
    whose time-elapsed queries here returned 0 for some draws and 4294.97 ms (2³² ns) for
    others; None there."""
    r = ctx.info.get("GL_RENDERER", "").lower()
    if "llvmpipe" in r or "softpipe" in r or "swrast" in r:
        return None
    return ctx.query(time=True)


def _vtk(mesh: Path, cam: Camera, reps: int, console) -> dict | None:
    cams = mesh.with_suffix(".json")
    cams.write_text(json.dumps([cam.to_json()]))
    proc = subprocess.run([sys.executable, "-m", "massview.app.bench.vtk_draw", str(mesh), str(cams), str(reps)],
                          capture_output=True, text=True)
    mesh.unlink()
    if proc.returncode != 0:
        console.print(f"[yellow]VTK child failed ({proc.returncode}): {proc.stderr.strip()[-600:]}[/]")
        return None
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _grid(st):
    """Finest heights (rows, cols) float32 and colour (or None), assembled from level-0 blocks."""
    lay, M = st.layout, st.layout.M
    full = np.empty((lay.S, lay.S), np.float32)
    color = np.empty((lay.S, lay.S, 3), np.uint8) if st.has_color else None
    for i in range(lay.blocks(0)):
        for j in range(lay.blocks(0)):
            sl = np.s_[i * (M - 1): i * (M - 1) + M, j * (M - 1): j * (M - 1) + M]
            full[sl] = st.get_block(0, i, j)
            if color is not None:
                color[sl] = st.get_color(0, i, j)
    return full, color


def _world(st, heights, tris):
    """(points, normals) float32 (N, 3) of the grid vertices ``tris`` uses, and ``tris``
    renumbered into them (what VTK gets)."""
    from ...render.terrain import pack_block

    used, inv = np.unique(tris.ravel(), return_inverse=True)
    cols = heights.shape[1]
    r, c = used // cols, used % cols
    dx, dy = st.spacing
    pts = np.stack([c * dx, -(r * dy), heights.ravel()[used] * st.vertical_scale], 1).astype(np.float32)
    nrm = pack_block(heights, None, dx, dy, st.vertical_scale)["n"][used].astype(np.float32)
    nz = np.sqrt(np.maximum(1.0 - (nrm ** 2).sum(1), 0.0))
    return pts, np.column_stack([nrm, nz]).astype(np.float32), inv.reshape(-1, 3).astype(np.int64)


def _case(sysm, st, heights, color, name, cam, tau, reps, mesh: Path | None, console) -> list[tuple]:
    """Rows (case, path, triangles, wall ms, CPU ms, main-thread ms) of one case; prints the
    front and readback. ``mesh``: where to save the triangles for the VTK child (run later,
    when this process has freed its GL memory)."""
    from ...parallel.runtime import self_comm
    from ...render.framebuffer import Framebuffer
    from ...render.terrain import PlainMeshRenderer

    comm = self_comm()
    cfg = RenderConfig(width=cam.width, height=cam.height, tau=tau, loading="complete")
    sysm.prepare_frame(comm, cam, cfg, FrameStats(0, 0))
    front = sysm.front
    ctx, _, terrain, _ = sysm.renderers()
    levels = np.bincount(front.level)
    tris = terrain.front_triangles(front, heights.shape[1])
    if mesh is not None:
        pts, nrm, vt = _world(st, heights, tris)
        np.savez(mesh, points=pts, normals=nrm, triangles=vt)
        del pts, nrm, vt
    plain = PlainMeshRenderer(ctx, heights, color, st.spacing, st.vertical_scale, triangles=tris)
    fb = Framebuffer(ctx, cam.width, cam.height)
    mvp = cam.view_projection()
    deferred, merge = terrain.deferred, terrain.merge

    def kpatch(d, m):
        def fn():
            terrain.deferred, terrain.merge = d, m
            return terrain.draw(front, mvp, eye=cam.position)
        return fn

    paths = {"K-patch": kpatch(None, True), "K-patch, forward": kpatch(False, True), "K-patch, deferred": kpatch(True, True),
             "K-patch, a draw per patch": kpatch(None, False), "K-patch before (forward, a draw per patch)": kpatch(False, False),
             "plain mesh": lambda: plain.draw(mvp)}
    times: dict[str, list] = {k: [] for k in paths}
    counts: dict[str, list] = {k: [] for k in paths}
    draws = {}
    query = _gpu_timer(ctx)
    for k, fn in paths.items():  # warm-up (shader variants, buffer residency, merged patterns)
        _time(fb, ctx, fn, [], [], query)
        draws[k] = terrain.draws
        if k == "K-patch":
            auto = "deferred" if terrain.used_deferred else "forward"
    for _ in range(reps):
        for k, fn in paths.items():
            _time(fb, ctx, fn, times[k], counts[k], query)
    terrain.deferred, terrain.merge = deferred, merge
    rb = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fb.read(cam.viewport)
        rb.append(time.perf_counter() - t0)
    rows = [(name, k, counts[k][0], *(np.median([t[i] for t in v]) * 1e3 for i in range(3)),
             np.median([t[3] for t in v]) * 1e3 if query is not None else None) for k, v in times.items()]
    plain.release()
    fb.release()
    console.print(f"{name}: {cam.width}x{cam.height}, τ = {tau:g}, {len(front)} patches (per level {levels.tolist()}), "
                  f"draw commands {draws['K-patch']} merged / {draws['K-patch, a draw per patch']} per patch, "
                  f"K-patch shading {auto} ({counts['K-patch'][0] / (cam.width * cam.height):.2f} triangles a pixel), "
                  f"readback (colour + depth) {np.median(rb) * 1e3:.1f} ms")
    return rows


def run_draw(args, console, table_cls) -> None:
    """The draw-throughput table (module docstring)."""
    from ...data.terrain import TerrainStore
    from ...systems.terrain import TerrainSystem

    st = TerrainStore(args.store)
    lay = st.layout
    if 2 * (lay.rows - 1) * (lay.cols - 1) > args.max_plain:
        console.print(f"[yellow]draw throughput skipped: the finest level exceeds --max-plain {args.max_plain} triangles[/]")
        return
    heights, color = _grid(st)  # the padded S × S grid: patches index it (padding included)
    budget = int(1.1 * sum(lay.blocks(lv) ** 2 for lv in range(lay.levels)) * lay.M * lay.M * 14)
    sysm = TerrainSystem(args.store, loading="complete", gpu_bytes=budget, cache_bytes=budget)
    tmp = tempfile.TemporaryDirectory()
    t = table_cls(title=f"draw throughput, one rank, one GL context ({args.draw_reps} draws per path, median; CPU = all threads)")
    for c in ("case", "path", "triangles", "wall ms", "CPU ms", "main-thread ms", "GPU ms", "Mtri/s", "÷ plain mesh", "÷ VTK",
              "main-thread Mtri/s", "÷ plain", "÷ VTK "):
        t.add_column(c, justify="right")
    results = []
    try:
        for n, (name, cam, tau) in enumerate(_cases(sysm, parse_size(args.size))):
            mesh = None if args.no_vtk else Path(tmp.name) / f"case{n}.npz"
            results.append((_case(sysm, st, heights, color, name, cam, tau, args.draw_reps, mesh, console), mesh, cam))
    finally:
        sysm.close()
        sysm.renderers()[0].release()
    del heights, color
    try:
        for rows, mesh, cam in results:
            res = _vtk(mesh, cam, args.draw_reps, console) if mesh is not None else None
            if res is not None:
                rows.append((rows[0][0], f"VTK ({res['renderer']})", res["triangles"],
                             *(np.median(res[k]) * 1e3 for k in ("wall_s", "cpu_s", "main_s")), None))
            rate = {r[1]: r[2] / r[3] / 1e3 for r in rows}
            mrate = {r[1]: r[2] / r[5] / 1e3 for r in rows}
            vtk = next((k for k in rate if k.startswith("VTK")), None)
            for case, path, tris, wall, cpu, main, gpu in rows:
                r, m = rate[path], mrate[path]
                t.add_row(case, path, f"{tris / 1e6:.2f} M", _ms(wall), _ms(cpu), _ms(main), _ms(gpu) if gpu is not None else "—", f"{r:.2f}",
                          f"{r / rate['plain mesh']:.2f}", f"{r / rate[vtk]:.2f}" if vtk else "—",
                          f"{m:.2f}", f"{m / mrate['plain mesh']:.2f}", f"{m / mrate[vtk]:.2f}" if vtk else "—")
    finally:
        tmp.cleanup()
    console.print(t)
