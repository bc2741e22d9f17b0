"""The terrain draw path's images do not change (issue 20, draw throughput).

* golden: SHA-256 of colour and depth of renders made with the code before the draw changes
  (tests/data/terrain_golden_hashes.json, recorded on the llvmpipe named in the file; checked
  when this machine's renderer is that one; the synthetic DEM differs in the last bit on CPUs
  without AVX-512 — see tests/ingest_golden.py — so ``by_input`` holds the frames per further
  input, keyed by the store's ``heights/0`` digest);
* side by side: the new path (deferred shading, whole blocks in one command; the default)
  equals the path it replaced (forward shading, a command per patch), bit for bit, on full
  frames, scissored sort-first viewports, tile targets, tints and colour modes;
* the bench's plain mesh draws exactly the front's triangles.
"""

from __future__ import annotations

import hashlib
import json
import warnings
from pathlib import Path

import numpy as np
import pytest

import massview as mv
from conftest import run_cli
from ingest_golden import input_digest
from massview.core.camera import Viewport
from massview.core.config import RenderConfig
from massview.core.paths import load_path
from massview.core.stats import FrameStats
from massview.core.task import Task
from massview.lod.kpatch import refine_uniform
from massview.parallel.runtime import self_comm
from massview.render.context import create_context, renderer_string
from massview.systems.terrain import TerrainSystem

GOLDEN = Path(__file__).parent / "data" / "terrain_golden_hashes.json"


@pytest.fixture(scope="module")
def small_store(tmp_path_factory) -> Path:
    """1000² samples (padded to 1025: the extent discard is exercised), 129² blocks, 4 levels."""
    out = tmp_path_factory.mktemp("draw") / "g.zarr"
    run_cli("generate", "terrain", out, "--size", 1000, "--block", 129, "--seed", 3, "-q")
    return out


def _sha(a: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(a).tobytes()).hexdigest()


def test_renders_match_pre_change_golden(small_store):
    golden = json.loads(GOLDEN.read_text())
    here = renderer_string(create_context())
    if here != golden["renderer"]:
        pytest.skip(f"golden hashes were recorded on {golden['renderer']!r}, this is {here!r} (side-by-side tests still run)")
    key = input_digest(small_store)
    frames = golden.get("by_input", {}).get(key, {}).get("frames", golden["frames"])
    bad = []
    for path in ("flyover", "zoom"):
        for cmap in ("auto", "ortho"):
            with warnings.catch_warnings():  # (ortho on a store without one: grey, and warned so; the golden has it)
                warnings.simplefilter("ignore", mv.MassviewWarning)
                res = mv.render(small_store, path, frames=2, size=(320, 240), loading="complete", depth=True, colormap=cmap)
            for i, (c, d) in enumerate(zip(res.images, res.depths)):
                name = f"{path}/{cmap}/{i}"
                if [_sha(c), _sha(d)] != frames[name]:
                    bad.append(name)
    assert not bad, f"frames differ from the pre-change renders: {bad} (input heights/0 {key[:16]})"


def _render(sysm, cam, cfg, new, vp=None, tint=(0, 0, 0, 0)):
    """``new``: deferred shading and whole-block draws; False: the path before (forward, a
    command per patch); None: the default (shading chosen per draw, whole-block draws)."""
    _, _, terrain, _ = sysm.renderers()
    terrain.deferred, terrain.merge, terrain.sort = new, new is not False, new is not False
    img = sysm.render(Task(0, vp or cam.viewport), cam, cfg, FrameStats(0, 0), tint=tint)
    return img.color.copy(), img.depth.copy()


@pytest.mark.parametrize("colormap", ["auto", "none"])
def test_new_draw_path_equals_old(small_store, colormap):
    sysm = TerrainSystem(small_store, loading="complete", gpu_bytes=64 << 20)
    try:
        lo, hi = sysm.bounds
        cams = [load_path("flyover", lo, hi).camera(0.3, 320, 240), load_path("zoom", lo, hi).camera(0.9, 256, 200),
                load_path("orbit", lo, hi).camera(0.6, 300, 220)]
        _, _, terrain, _ = sysm.renderers()
        checked, merged = 0, 0
        for cam in cams:
            for tau in (1.0, 0.05):
                cfg = RenderConfig(width=cam.width, height=cam.height, tau=tau, loading="complete", colormap=colormap)
                sysm.prepare_frame(self_comm(), cam, cfg, FrameStats(0, 0))
                quarter = Viewport(cam.width // 4, cam.height // 3, cam.width // 2, cam.height // 2)
                tiled = RenderConfig(**{**cfg.to_json(), "tile_targets": True})
                for vp, c, tint in ((None, cfg, (0, 0, 0, 0)), (quarter, cfg, (0.8, 0.1, 0.1, 0.4)), (quarter, tiled, (0, 0, 0, 0))):
                    a = _render(sysm, cam, c, False, vp, tint)
                    b = _render(sysm, cam, c, True, vp, tint)
                    merged += terrain.draws < len(sysm.front)
                    assert (a[0] != 255).any() and (a[1] < 1).any(), "the view shows terrain"
                    for x, y, what in ((a[0], b[0], "colour"), (a[1], b[1], "depth")):
                        assert np.array_equal(x, y), f"{what} differs in {np.count_nonzero(x != y)} values ({cam}, τ {tau}, vp {vp})"
                    checked += 1
        assert checked == 18
        assert merged >= 3, "some views draw whole blocks with one command"
    finally:
        sysm.close()


def test_second_draw_shades_only_its_pixels(small_store):
    """Two draws into one target (the second over part of the first, another tint): the
    deferred pass of each shades only the pixels it wrote (the G-buffer is cleared per draw),
    so the target equals the forward path's, after a different view filled the G-buffer."""
    from massview.render.framebuffer import Framebuffer

    sysm = TerrainSystem(small_store, loading="complete")
    try:
        lo, hi = sysm.bounds
        cfg = RenderConfig(width=200, height=150, loading="complete")
        cam, far = (load_path(p, lo, hi).camera(t, 200, 150) for p, t in (("flyover", 0.5), ("zoom", 0.0)))
        ctx, _, terrain, _ = sysm.renderers()
        fb = Framebuffer(ctx, 200, 150)
        out = []
        for deferred in (False, True):
            terrain.deferred = deferred
            for c in (far, cam):
                sysm.prepare_frame(self_comm(), c, cfg, FrameStats(0, 0))
                fb.begin()
                terrain.draw(sysm.front, c.view_projection(), eye=c.position)
            part = sysm.front.take(np.arange(len(sysm.front) // 3))
            terrain.draw(part, cam.view_projection(), (0.9, 0.1, 0.1, 0.5), cam.position)
            ctx.finish()
            out.append(fb.read(cam.viewport))
        tinted = np.abs(out[0].color.astype(int) - out[0].color[..., ::-1].astype(int)).max() > 0
        assert tinted and np.array_equal(out[0].color, out[1].color) and np.array_equal(out[0].depth, out[1].depth)
        fb.release()
    finally:
        sysm.close()


def test_front_triangles_are_the_drawn_patches(small_store):
    sysm = TerrainSystem(small_store, loading="complete")
    try:
        lo, hi = sysm.bounds
        cam = load_path("flyover", lo, hi).camera(0.5, 320, 240)
        sysm.prepare_frame(self_comm(), cam, RenderConfig(width=320, height=240, loading="complete"), FrameStats(0, 0))
        f = sysm.front
        _, _, terrain, _ = sysm.renderers()
        cols = sysm.lay.S
        got = terrain.front_triangles(f, cols)
        tri = refine_uniform(f.ax, f.ay, f.lx, f.ly, f.rx, f.ry, 2 * sysm.lay.k)  # (n·4^k, 3, 2) (x, y)
        want = (tri[..., 1] * cols + tri[..., 0]).astype(np.uint32)
        assert len(f) > 50 and len(np.unique(f.level)) > 1
        assert np.array_equal(got[:, 0], want[:, 0]) and np.array_equal(np.sort(got, 1), np.sort(want, 1))
        r, c = (got // cols).astype(np.int64), (got % cols).astype(np.int64)  # every triangle faces up (culling)
        cross = (c[:, 1] - c[:, 0]) * (r[:, 2] - r[:, 0]) - (r[:, 1] - r[:, 0]) * (c[:, 2] - c[:, 0])
        assert (cross < 0).all()
    finally:
        sysm.close()


def test_shading_path_follows_triangles_per_pixel(small_store):
    """deferred=None (the default) shades deferred above DEFERRED_ABOVE triangles per pixel of
    the target's scissor, forward below; either way the same bytes."""
    from massview.render.terrain import DEFERRED_ABOVE

    sysm = TerrainSystem(small_store, loading="complete")
    try:
        lo, hi = sysm.bounds
        cam = load_path("flyover", lo, hi).camera(0.5, 160, 120)
        cfg = RenderConfig(width=160, height=120, tau=0.3, loading="complete")
        sysm.prepare_frame(self_comm(), cam, cfg, FrameStats(0, 0))
        _, _, terrain, _ = sysm.renderers()
        assert terrain.deferred is None
        tris = len(sysm.front) * terrain.tris_per_patch
        assert tris > DEFERRED_ABOVE * 160 * 120
        for vp, want in ((None, True), (Viewport(0, 0, 160, 120), True)):
            got = _render(sysm, cam, cfg, None, vp)
            assert terrain.used_deferred is want
        full = sysm.front
        sparse = int(DEFERRED_ABOVE * 160 * 120) // terrain.tris_per_patch // 2  # half the triangles the threshold allows
        assert sparse >= 1
        sysm.front = full.take(sysm.select(Task(0, cam.viewport), cam, cfg)[:sparse])  # a sparse share of the frame
        try:
            auto = _render(sysm, cam, cfg, None)
            assert terrain.used_deferred is False
            forced = _render(sysm, cam, cfg, True)
            assert terrain.used_deferred is True
            assert np.array_equal(auto[0], forced[0]) and np.array_equal(auto[1], forced[1])
        finally:
            sysm.front = full
        assert got[0].shape == (120, 160, 4)
    finally:
        sysm.close()


def test_distinct_rows_is_np_unique():
    """terrain._distinct_rows (rows as one int64 of base-radix digits) gives np.unique(axis=0,
    return_inverse=True)'s rows, in its order, and its inverse; radixes whose keys could
    overflow int64 fall back to np.unique."""
    from massview.render.terrain import _distinct_rows

    rng = np.random.default_rng(5)
    for radix, n, c in ((2, 1000, 6), (17, 5000, 6), (129, 20000, 6), (1025, 3000, 6), (2049, 3000, 6), (7, 1, 3), (9, 0, 6)):
        rows = rng.integers(0, min(radix, 4), (n, c)) * (radix - 1) // 3 if n else np.zeros((0, c), np.int64)
        want, winv = np.unique(rows, axis=0, return_inverse=True)
        got, ginv = _distinct_rows(rows, radix)
        assert np.array_equal(got, want) and np.array_equal(ginv, winv.ravel()), radix
        assert np.array_equal(got[ginv], rows)


def test_pattern_and_merged_ids_in_sorted_order(small_store):
    """A fresh renderer numbers the index patterns of its first front, and the whole-block
    patterns new in one draw, in the rows' lexicographic order (what np.unique(axis=0) gave
    before the int64 keys and the dict of row bytes replaced it), so the index buffer's layout
    is the same as before; each whole-block command draws its block's own patches."""
    sysm = TerrainSystem(small_store, loading="complete")
    try:
        lo, hi = sysm.bounds
        cam = load_path("flyover", lo, hi).camera(0.5, 320, 240)
        sysm.prepare_frame(self_comm(), cam, RenderConfig(width=320, height=240, tau=0.05, loading="complete"), FrameStats(0, 0))
        _, _, terrain, _ = sysm.renderers()
        f = sysm.front
        terrain._patterns.clear(), terrain._pattern_data.clear(), terrain._merged.clear(), terrain._merged_data.clear()
        terrain._commands(f, cam.position)
        pats = list(terrain._patterns)  # insertion order = id
        assert len(pats) > 2 and pats == sorted(pats)
        # two whole blocks with different patch sets, the one with the larger key in the lower slot
        M, tpp = terrain.pool.M, terrain.tris_per_patch
        full = 2 * (M - 1) ** 2 // tpp
        pids = np.tile(np.arange(len(pats)), full)[:full].astype(np.int64)
        base = np.arange(full, dtype=np.int64) * 7 % (M * M)
        other = pids.copy()
        other[0] = (other[0] + 1) % len(pats)
        ka, kb = (np.sort(p * M * M + base) for p in (pids, other))
        hi_p, lo_p = (pids, other) if tuple(ka) > tuple(kb) else (other, pids)
        slots = np.repeat(np.array([3, 8], np.int64), full)
        terrain._merged.clear(), terrain._merged_data.clear()
        cmds = terrain._block_commands(slots, np.concatenate([hi_p, lo_p]), np.concatenate([base, base]), full)
        merged = [tuple(np.frombuffer(b, np.int64).tolist()) for b in terrain._merged]
        assert len(merged) == 2 and merged == sorted(merged)
        ibo = np.concatenate(terrain._pattern_data + terrain._merged_data)
        for c, p in zip(cmds, (hi_p, lo_p)):
            key = np.sort(p * M * M + base)
            want = (np.stack([terrain._pattern_data[q] for q in key // (M * M)]).astype(np.int64) + (key % (M * M))[:, None]).ravel()
            assert c[0] == len(want) and np.array_equal(ibo[c[2]:c[2] + c[0]], want)
        assert cmds[:, 4].tolist() == [3, 8]
    finally:
        sysm.close()


def test_draw_bench_runs_with_gpu_column(small_store):
    """`massview bench terrain --draw` on a small store: every path of both cases in the table,
    with the GPU column ("—" on Mesa's software rasterizer, whose timer queries wrap)."""
    proc = run_cli("bench", "terrain", small_store, "--draw", "--draw-reps", 1, "--no-vtk", "--size", "160x120")
    out = proc.stdout
    assert "GPU ms" in out and "plain mesh" in out and "demo LOD" in out and "full" in out
    assert "draw commands" in out and "readback" in out


def test_time_records_gpu_time_with_a_query():
    """bench terrain's _time appends (wall, CPU, thread CPU, GPU) with a timer query, GPU None
    without one; _gpu_timer gives none on llvmpipe."""
    from massview.app.bench.terrain_draw import _gpu_timer, _time
    from massview.render.framebuffer import Framebuffer

    ctx = create_context()
    fb = Framebuffer(ctx, 64, 48)
    try:
        q = ctx.query(time=True)
        reps, tris = [], []
        _time(fb, ctx, lambda: 7, reps, tris, q)
        _time(fb, ctx, lambda: 8, reps, tris)
        assert tris == [7, 8] and len(reps[0]) == 4 and reps[0][3] is not None and reps[0][3] >= 0 and reps[1][3] is None
        assert all(v >= 0 for v in reps[0][:3])
        if "llvmpipe" in renderer_string(ctx):
            assert _gpu_timer(ctx) is None
    finally:
        fb.release()
        ctx.release()
