"""M1 end to end (`massview render SCENE --system dmmr`): real mpiexec, real GL, the one-rank
reference (every object in the frustum, no occlusion culling) as the oracle."""

from __future__ import annotations

import json

import numpy as np
import pytest

from massview.core.config import RenderConfig
from massview.core.errors import ConfigError
from massview.core.paths import load_path
from massview.systems.dmmr import DmmrSystem

from conftest import RenderBatches, run_cli, summary

SCENE = "builtin:objects?n=400&seed=3"
SIZE = "320x240"


def _args(*extra, frames=3, scene=SCENE):
    return [scene, "--system", "dmmr", "--frames", frames, "--size", SIZE, "--reference", *extra]


def _read(out):
    recs = [json.loads(line) for line in (out / "stats.jsonl").read_text().splitlines()]
    return summary(out), recs


def dmmr(out, ranks, *extra, frames=3, scene=SCENE):
    run_cli("render", *_args(*extra, frames=frames, scene=scene), "--ranks", ranks, "--out", out, "-q")
    return _read(out)


PARALLEL = [(3, None), (4, None), (5, None), (4, "sort-first:grid")]


@pytest.fixture(scope="module")
def plant(tmp_path_factory):
    """A small generated power plant (≈3.5 k objects, 8 levels of groups, occluder walls)."""
    from massview.data.generators.scenes import generate_scene

    out = tmp_path_factory.mktemp("plant") / "plant.zarr"
    generate_scene("plant", out, copies=1, size=0.15, seed=1)
    return out


@pytest.fixture(scope="module")
def cases(tmp_path_factory, plant):
    """The module's M1 renders on a warm store: one job per rank count (conftest.RenderBatches)."""
    return RenderBatches(tmp_path_factory, {
        **{f"parallel-{n}-{d}": (n, _args("--occlusion", "off", *(("--decomposition", d) if d else ()))) for n, d in PARALLEL},
        "occlusion": (3, _args("--path", "walkthrough", "--id-check", scene=plant, frames=4)),
        "id-check": (3, _args("--id-check", "--query-threshold", "100", frames=2)),
    }, label="dmmr")


@pytest.mark.mpi
@pytest.mark.parametrize("ranks,decomposition", PARALLEL)
def test_parallel_equals_serial_without_occlusion_culling(cases, ranks, decomposition):
    # grid: the equal-tile baseline
    s, recs = _read(cases.out(f"parallel-{ranks}-{decomposition}"))
    assert s["ranks"] == ranks and s["frames"] == 3
    if decomposition:
        assert s["decomposition"] == decomposition
    assert s["max_abs_diff"] == 0 and s["diff_fraction"] == 0.0
    clients = [r for r in recs if r["rank"] > 0]
    assert {r["rank"] for r in clients} == set(range(1, ranks))
    assert all(r["counters"].get("queries_issued", 0) == 0 for r in clients)
    gl = s["renderer"].partition("clients' GL: ")[2]  # walk5 L8: the clients' GL renderer, not only the system's name
    assert " / " in gl and ("llvmpipe" in gl.lower() or "nvidia" in gl.lower()), s["renderer"]


@pytest.mark.mpi
def test_occlusion_culling_keeps_the_image_and_draws_fewer_triangles(cases, plant):
    on, recs = _read(cases.out("occlusion"))
    clients = [r for r in recs if r["rank"] > 0]
    assert sorted((r["frame"], r["rank"]) for r in clients) == [(f, c) for f in range(4) for c in (1, 2)]
    for r in clients:  # inside the MPI job, every frame, every client: ID-buffer visible ⊆ drawn
        missed = set(r["idbuffer_ids"]) - set(r["drawn_ids"])
        assert not missed and r["counters"]["idbuffer_missed"] == 0, (r["frame"], r["rank"], sorted(missed))
        assert len(r["idbuffer_ids"]) == r["counters"]["idbuffer_visible"]
    drew = [f for f in range(4) if sum(len(r["drawn_ids"]) for r in clients if r["frame"] == f) > 0]
    assert len(drew) >= 3  # (the walk's last view may look out of the plant along its middle alley)
    assert all(sum(len(r["idbuffer_ids"]) for r in clients if r["frame"] == f) > 0 for f in drew)
    assert on["max_abs_diff"] == 0 and on["diff_fraction"] == 0.0  # equal to the reference: no culling, one rank
    server = [r for r in recs if r["rank"] == 0]
    reference_triangles = np.mean([r["counters"]["triangles_in_frustum"] for r in server])  # what the reference draws
    assert on["triangles_per_frame"] < 0.5 * reference_triangles
    clients = [r for r in recs if r["rank"] > 0]
    assert sum(r["counters"].get("culled_by_occlusion", 0) for r in clients) > 0
    assert max(r["counters"].get("queries_issued", 0) for r in clients) > 1
    from massview.data.scene import SceneStore

    levels = int(SceneStore(plant).groups.depth.max()) + 1
    for r in clients:  # batched: one wait per round of the group-tree walk (≤ levels + 1), never one per query
        c = r["counters"]
        assert (c.get("query_waits", 0) > 0) == (c.get("queries_issued", 0) > 0) and c.get("query_waits", 0) <= levels + 1
        assert c.get("queries_issued", 0) == c.get("group_queries", 0) + c.get("object_queries", 0)
    assert sum(r["counters"].get("culled_by_group", 0) for r in clients) > 0  # hidden groups culled objects unqueried


def _on_tmpfs(path) -> bool:
    """Whether ``path`` lies on a RAM file system (no block device reads to count)."""
    best, fs = "", ""
    from pathlib import Path

    for line in Path("/proc/mounts").read_text().splitlines():
        mnt, kind = line.split()[1], line.split()[2]
        if str(path).startswith(mnt) and len(mnt) > len(best):
            best, fs = mnt, kind
    return fs in ("tmpfs", "ramfs")


def test_process_meter_counts_file_and_device_reads_of_a_cold_file(tmp_path):
    from massview.systems.dmmr_meter import ProcessMeter, drop_page_cache

    f = tmp_path / "blob.bin"
    f.write_bytes(np.random.default_rng(1).integers(0, 255, 4 << 20, dtype=np.uint8).tobytes())
    assert drop_page_cache(f) == 4 << 20
    m = ProcessMeter()
    f.read_bytes()
    cold = m.step()
    f.read_bytes()
    warm = m.step()
    assert cold["file_read_bytes"] >= 4 << 20 and warm["file_read_bytes"] >= 4 << 20
    if not _on_tmpfs(tmp_path):  # the cold read reached the device, the warm one the page cache
        assert cold["device_read_bytes"] >= 4 << 20 > warm["device_read_bytes"]
    assert cold["cpu_ms"] >= 0 and warm["cpu_ms"] >= 0


@pytest.mark.mpi
def test_cold_store_reads_from_the_device_and_the_speedup_digest_sums_per_level_and_per_process(tmp_path, plant):
    from massview.app.bench.dmmr_speedup import speedup_digest
    from massview.systems.dmmr_meter import drop_page_cache

    drop_page_cache(plant)
    s, recs = dmmr(tmp_path, 3, "--path", "walkthrough", "--client-cache-mb", "8", scene=plant, frames=4)
    assert s["max_abs_diff"] == 0  # the images are the reference's
    d = speedup_digest(recs, one_process=False)
    assert d["clients"] == 2 and len(d["cpu_ms_per_process"]) == 3 and all(v > 0 for v in d["cpu_ms_per_process"])
    first = [r["counters"] for r in recs if r["rank"] > 0 and r["frame"] == 0]
    assert sum(c["vis_disk_loads"] + c["disk_loads"] for c in first) > 0 and sum(c["file_read_bytes"] for c in first) > 0
    if not _on_tmpfs(plant):  # a cold store: the clients' first frames really read the block device
        assert sum(c["device_read_bytes"] for c in first) > 0
    assert d["frame_mesh_bytes"] > 0 and d["depth_mesh_bytes"] > 0


@pytest.mark.mpi
def test_id_check_reports_objects_a_lossy_query_threshold_culls(cases):
    """The check can fail: with --query-threshold 100 boxes showing fewer pixels are culled,
    and the clients' ID buffers find some of those objects visible."""
    _, recs = _read(cases.out("id-check"))
    clients = [r for r in recs if r["rank"] > 0]
    missed = [len(set(r["idbuffer_ids"]) - set(r["drawn_ids"])) for r in clients]
    assert [r["counters"]["idbuffer_missed"] for r in clients] == missed
    assert min(missed) > 0


@pytest.mark.mpi
@pytest.mark.slow
def test_stage_pipeline_period_is_the_slowest_stage_and_latency_three_frames(tmp_path):
    delay = "divide:150,visibility:450,render:150"
    args = ("--stage-delay", delay, "--occlusion", "off")
    _, piped = dmmr(tmp_path / "on", 2, *args, frames=8, scene="builtin:objects?n=60")
    _, sync = dmmr(tmp_path / "off", 2, *args, "--stage-pipeline", "off", frames=5, scene="builtin:objects?n=60")

    def server(recs):
        rs = sorted((r for r in recs if r["rank"] == 0), key=lambda r: r["frame"])
        return [r["times_ms"]["total"] for r in rs[2:]], [r["counters"]["frames_in_flight"] for r in rs]

    period_p, flight_p = server(piped)
    period_s, flight_s = server(sync)
    assert max(flight_p) == 3 and max(flight_s) == 1
    slowest, total = 450, 750
    assert np.median(period_s) >= 0.95 * total
    assert 0.95 * slowest <= np.median(period_p) < np.median(period_s) * 0.85


def test_one_rank_in_process_matches_the_reference_and_reports_per_stage():
    cfg = RenderConfig(width=240, height=180, frames=3, system="dmmr", reference=True, gpu_mb=64, client_cache_mb=32)
    sys_ = DmmrSystem("builtin:objects?n=200&seed=1", cfg)
    try:
        cams = load_path("orbit", *sys_.bounds).cameras(3, 240, 180)
        frames = {}
        class _Self:
            def Get_rank(self):
                return 0

            def Get_size(self):
                return 1

            def bcast(self, v, root=0):
                return v

        records, diffs = sys_.run_path(_Self(), cams, cfg, lambda f, img: frames.__setitem__(f, img))
        assert sorted(frames) == [0, 1, 2]
        assert "clients' GL: " in sys_.renderer  # the in-process client's GL renderer string (walk5 L8)
        assert all(d[0] == 0 for _, d in diffs) and len(diffs) == 3
        client = [r for r in records if r["rank"] == 1]
        assert len(client) == 3
        for key in ("visibility", "load", "draw", "readback", "encode", "send"):
            assert key in client[0]["times_ms"]
        for key in ("queries_issued", "culled_by_occlusion", "gpu_hits", "ram_hits", "disk_loads", "bytes_uploaded"):
            assert key in client[0]["counters"]
        c0 = client[0]["counters"]
        assert c0["vis_disk_loads"] > 0 and c0["disk_loads"] + c0["ram_hits"] > 0  # GPU 1 read the store first
        assert client[-1]["counters"]["bytes_uploaded"] < c0["bytes_uploaded"]  # GPU buffers reused along the path
        lb = np.asarray(sys_.store.skeleton.level_bytes, np.int64)
        for r in records:  # per-frame process counters on the server and the client
            # (device reads are not bounded by read() bytes: the kernel's readahead and pages faulted in through
            # memory maps count as the process's device reads — 499712 against 455622 in a run with a cold cache)
            assert r["counters"]["cpu_ms"] > 0 and r["counters"]["file_read_bytes"] >= 0 and r["counters"]["device_read_bytes"] >= 0
        assert all(0 < r["counters"]["frame_mesh_bytes"] <= lb.max(1).sum() for r in client)
        assert all(0 < r["counters"]["depth_mesh_bytes"] <= lb.max(1).sum() for r in client)
        records, _ = sys_.run_path(_Self(), [cams[0]] * 3, cfg)  # a static camera
        c = {r["frame"]: r["counters"] for r in records if r["rank"] == 1}
        assert c[1]["bytes_uploaded"] == 0 and c[1]["gpu_hits"] == c[1]["objects_drawn"] > 0  # GPU 2: nothing new
        assert c[1]["frame_mesh_bytes"] == c[2]["frame_mesh_bytes"] > 0  # the same meshes drawn
        assert c[1]["vis_bytes_uploaded"] > 0 and c[2]["vis_bytes_uploaded"] == 0  # GPU 1: frame 0's visible set joins the depth pass once
    finally:
        sys_.close()


def test_bad_dmmr_options_are_clear_errors():
    with pytest.raises(ConfigError, match="--visible-frames"):
        RenderConfig(visible_frames=0)
    with pytest.raises(ConfigError, match="--occluder-lod"):
        RenderConfig(occluder_lod="fine")
    with pytest.raises(ConfigError, match="--query-hierarchy"):
        RenderConfig(query_hierarchy="maybe")
    p = run_cli("render", SCENE, "--system", "dmmr", "--occlusion", "maybe", check=False)
    assert p.returncode != 0 and "--occlusion" in p.stderr


def test_frame_at_a_time_path_for_the_viewer_matches_the_reference():
    from massview.parallel.runtime import self_comm

    cfg = RenderConfig(width=240, height=180, system="dmmr", reference=True, gpu_mb=64, client_cache_mb=32, color_by_rank=False)
    sys_ = DmmrSystem("builtin:objects?n=200&seed=2", cfg)
    try:
        comm = self_comm()
        for f, cam in enumerate(load_path("turn", *sys_.bounds).cameras(3, 240, 180)):
            res = sys_.render_frame(comm, cfg, cam, f)
            assert res.tile is not None and res.diff[0] == 0
            assert res.stats.counters["objects_in_frustum"] > 0
    finally:
        sys_.close()


def test_async_loading_draws_what_is_resident_then_converges_and_fills_the_viewer_panel():
    """--loading async (the viewer's default): the first frame defers every mesh to the
    background loaders and draws nothing missing; a static camera then fills in until
    nothing is deferred and the image equals the reference. The panel rows carry M1's figures."""
    import time

    from massview.parallel.runtime import self_comm

    cfg = RenderConfig(width=240, height=180, system="dmmr", reference=True, gpu_mb=64, client_cache_mb=32, loading="async")
    sys_ = DmmrSystem("builtin:objects?n=200&seed=2", cfg)
    try:
        comm = self_comm()
        cam = load_path("turn", *sys_.bounds).cameras(1, 240, 180)[0]
        res = sys_.render_frame(comm, cfg, cam, 0)
        c0 = sys_._panel_clients[0]["counters"]
        assert c0["deferred"] > 0 and c0["objects_drawn"] < res.stats.counters["objects_sent"]
        assert res.diff[0] > 0  # something is still loading
        for f in range(1, 400):  # bounded by frames, not time: the loaders finish long before
            res = sys_.render_frame(comm, cfg, cam, f)
            if sys_._panel_clients[0]["counters"]["deferred"] == 0:
                break
            time.sleep(0.01)
        assert sys_._panel_clients[0]["counters"]["deferred"] == 0 and res.diff[0] == 0
        rows = dict(sys_.panel([{**res.stats.to_json(), "rank": 0}])["rows"])
        assert rows["M1 objects in frustum / sent"] == f"{res.stats.counters['objects_in_frustum']} / {res.stats.counters['objects_sent']}"
        for label in ("occlusion queries / culled", "cache GPU hits/RAM hits/disk loads", "deferred (loading) / drawn coarser",
                      "bytes uploaded / sent", "ms divide · visibility · render · assemble"):
            assert label in rows
    finally:
        sys_.close()


def test_generator_detail_scales_triangles_and_keeps_the_nodes():
    """bench dmmr scales a copy's triangles to the machine with --detail; the nodes (the
    paper's 20 000 a plant, 8 levels of hierarchy) do not depend on it."""
    from massview.data.generators.scenes import _shape_parts, generate_scene

    for key in (("pipe", 0.2, 3.0), ("tank", 4.0, 1.1), ("elbow", 0.2, 0.6), ("dome", 3.0)):
        tris = [sum(len(part[0][1]) for part in _shape_parts(key, d)) for d in (1.0, 0.5)]
        assert tris[1] <= 0.5 * tris[0], key
    with pytest.raises(ConfigError, match="--detail"):
        generate_scene("plant", "/nonexistent/never-written.zarr", detail=0)


def test_bad_speedup_options_are_clear_errors(tmp_path):
    import argparse

    from massview.app.bench import dmmr as bench

    ap = argparse.ArgumentParser()
    bench.add_arguments(ap)
    from massview.app.bench.dmmr_speedup import run_speedup

    for argv, msg in ((["--speedup-clients", "2,x"], "--speedup-clients"), (["--speedup-clients", "0"], "--speedup-clients"),
                      (["--speedup-plants", "0"], "--speedup-plants"), (["--speedup-gpu-mb", "0"], "--speedup-gpu-mb")):
        with pytest.raises(ConfigError, match=msg):
            run_speedup(ap.parse_args(["--workdir", str(tmp_path), *argv]))
    assert not any(tmp_path.iterdir())  # refused before generating anything


def test_dmmr_wait_mode_is_checked(monkeypatch):
    """MASSVIEW_DMMR_WAIT: sleep (default) or spin; anything else is named in the error."""
    from massview.core.errors import ConfigError
    from massview.systems.dmmr_links import _sleeping

    monkeypatch.delenv("MASSVIEW_DMMR_WAIT", raising=False)
    assert _sleeping() is True
    monkeypatch.setenv("MASSVIEW_DMMR_WAIT", "spin")
    assert _sleeping() is False
    monkeypatch.setenv("MASSVIEW_DMMR_WAIT", "yield")
    with pytest.raises(ConfigError, match="MASSVIEW_DMMR_WAIT='yield'"):
        _sleeping()
