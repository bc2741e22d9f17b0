"""Issue 20, ingest fast paths: each writes exactly the store the general path writes.

* a float32 ``.npy`` read straight into the strips (no nodata, every new sample finite) gives
  the very files of the general read path (an in-memory array source), with the input width
  equal to or narrower than the padded grid, and with non-finite samples in some strips (those
  strips fall back to the general path and are filled);
* the shading pass with the edge rows kept from the pyramid pass (each worker decodes its own
  row) writes the same shading chunks as reading the neighbouring rows back;
* ``bench ingest``'s write floor writes the same names and bytes as the store it copies;
* ``make_top_folder`` is only a hint: it makes the folder and never fails on a file system
  without the flag;
* ``run_ready`` (the shading pass's scheduler) starts a task that a finished one made ready
  before the next first task, and after a failure finishes what runs, then raises.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from massview.data.terrain import ArraySource, open_source, prepare_terrain
from massview.data.terrain.synthetic import SyntheticSource


def _files(root: Path, meta: bool = False) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*"))
            if p.is_file() and (meta or p.name != "zarr.json")}


def _dem(rows: int, cols: int, bad: bool) -> np.ndarray:
    a = SyntheticSource(max(rows, cols), seed=3).read(0, rows, 0, cols).astype(np.float32)
    if bad:
        a[150, 10:40] = np.nan  # in the second strip of 129-sample blocks
        a[5, 7] = np.inf
    return np.ascontiguousarray(a)


@pytest.mark.parametrize("rows,cols,bad", [(257, 257, False), (300, 277, False), (300, 277, True)])
def test_npy_read_straight_into_strips_writes_the_general_paths_store(tmp_path, rows, cols, bad):
    a = _dem(rows, cols, bad)
    npy = tmp_path / "dem.npy"
    np.save(npy, a)
    src = open_source(npy)
    assert hasattr(src, "read_float32_into")
    general = ArraySource(np.load(npy), src.name, transform=src.transform)
    general.spacing = src.spacing  # the same georeference as the file source
    straight, general_reads = [], []
    read_into, read = src.read_float32_into, src.read
    src.read_float32_into = lambda r0, out: straight.append(read_into(r0, out)) or straight[-1]
    src.read = lambda *a: general_reads.append(a) or read(*a)
    fast_res = prepare_terrain(src, tmp_path / "fast.zarr", block=129, K=5, workers=2)
    assert straight and all(straight)  # every strip was read straight into its buffer ...
    # ... and only the 2 strips with non-finite samples again, with the void fill's one pass over the
    # input (at the first void) and its window of rows round each strip's voids
    assert len(general_reads) == (2 + 1 + 2 if bad else 0)
    prepare_terrain(general, tmp_path / "general.zarr", block=129, K=5, workers=2)
    fast, gen = _files(tmp_path / "fast.zarr"), _files(tmp_path / "general.zarr")
    assert sorted(fast) == sorted(gen)
    assert [k for k in fast if fast[k] != gen[k]] == []
    assert fast_res.filled == (31 if bad else 0)


def test_shading_from_kept_edge_rows_equals_reading_neighbours_back(tmp_path):
    import zarr

    from massview.data.terrain.colors import write_shading
    from massview.data.terrain.store import TerrainStore, create_shade_arrays

    prepare_terrain(SyntheticSource(700, seed=5), tmp_path / "a.zarr", block=129, K=5, workers=2)
    shutil.copytree(tmp_path / "a.zarr", tmp_path / "b.zarr")
    shutil.rmtree(tmp_path / "b.zarr" / "shade")
    g = zarr.open_group(str(tmp_path / "b.zarr"), mode="r+")
    store = TerrainStore(tmp_path / "b.zarr")
    create_shade_arrays(g, store.layout)
    zlo, zhi = store.attrs["height_range"]
    write_shading(store, g, zlo, zhi, lambda *a: None, workers=2)  # no edges: neighbours read back
    a, b = _files(tmp_path / "a.zarr" / "shade", meta=True), _files(tmp_path / "b.zarr" / "shade", meta=True)
    assert sorted(a) == sorted(b) and len(a) > 10
    assert [k for k in a if a[k] != b[k]] == []


def test_write_floor_writes_the_same_names_and_bytes(tmp_path):
    from massview.app.bench.ingest import _write_floor

    prepare_terrain(SyntheticSource(300, seed=2), tmp_path / "s.zarr", block=129, K=5, workers=1)
    seconds, system = _write_floor(tmp_path / "s.zarr", tmp_path / "floor", threads=2)
    assert seconds > 0 and system >= 0
    assert _files(tmp_path / "floor", meta=True) == _files(tmp_path / "s.zarr", meta=True)


def test_page_cost_times_new_and_cached_pages_and_leaves_nothing(tmp_path):
    from massview.app.bench.ingest import _free_page_reporting, _page_cost

    new, again = _page_cost(tmp_path, mib=4)
    assert new > 0 and again > 0
    assert list(tmp_path.iterdir()) == []
    assert isinstance(_free_page_reporting(), bool)


def test_make_top_folder_is_only_a_hint(tmp_path):
    from massview.data.terrain.store import make_top_folder

    root = tmp_path / "x" / "c"
    first = make_top_folder(str(root))
    assert root.is_dir() and isinstance(first, bool)
    assert make_top_folder(str(root)) == first  # again: no error, same answer


def test_run_ordered_keeps_workers_busy_behind_a_slow_task_and_delivers_in_order():
    import threading

    from massview.data.terrain.workers import run_ordered

    release, started, lock = threading.Event(), [], threading.Lock()

    def task(k):
        def run():
            with lock:
                started.append(k)
            if k == 0:  # the oldest task is slow: it waits until task 5 has started
                assert release.wait(30), "later tasks were not started while the oldest ran"
            if k == 5:
                release.set()
            return k
        return run

    got = []
    run_ordered(2, (task(k) for k in range(12)), got.append, depth=2)
    assert got == list(range(12))  # results in submission order
    assert started.index(5) < len(started) and release.is_set()


def test_run_ordered_hands_on_the_results_before_a_failure_then_raises():
    from massview.data.terrain.workers import run_ordered

    def task(k):
        def run():
            if k == 4:
                raise ValueError("task 4")
            return k
        return run

    got = []
    with pytest.raises(ValueError, match="task 4"):
        run_ordered(2, (task(k) for k in range(10)), got.append)
    assert got == [0, 1, 2, 3]


def _ready_tasks(started, lock, gate=None):
    """First tasks 0, 1, 2; task 0 makes a follower "f0" ready; task 1 waits (``gate``) until it ran."""
    def task(k):
        def run():
            with lock:
                started.append(k)
            if k == "f0" and gate is not None:
                gate.set()
            if k == 1 and gate is not None:
                assert gate.wait(30), "the follower of task 0 did not run while task 1 waited"
            return k
        return run
    return (task(k) for k in range(3)), (lambda res: [task("f0")] if res == 0 else []), task


@pytest.mark.parametrize("workers", [1, 2])
def test_run_ready_starts_followers_before_the_next_first_task(workers):
    import threading

    from massview.data.terrain.workers import run_ready

    started, lock, got = [], threading.Lock(), []
    first, then, _ = _ready_tasks(started, lock, threading.Event() if workers > 1 else None)
    run_ready(workers, first, then, got.append, depth=1)
    assert sorted(map(str, got)) == ["0", "1", "2", "f0"]
    assert started.index("f0") < started.index(2)
    if workers == 1:
        assert started == [0, "f0", 1, 2]


def test_run_ready_finishes_the_running_tasks_after_a_failure_then_raises():
    import threading

    from massview.data.terrain.workers import run_ready

    started, lock, got = [], threading.Lock(), []
    first, _, task = _ready_tasks(started, lock)

    def then(res):
        if res == 0:
            def fail():
                raise ValueError("follower")
            return [fail]
        return []

    with pytest.raises(ValueError, match="follower"):
        run_ready(2, first, then, got.append, depth=1)
    assert {0, 1} <= set(got)  # the tasks submitted before the failure were finished and handed on


def test_buffer_pool_reuses_given_buffers_and_keeps_no_more_than_its_budget():
    from massview.data.terrain.workers import BufferPool

    pool = BufferPool(keep=2 * 4000)
    a, b, c = (pool.take((10, 100), np.float32) for _ in range(3))
    assert a.shape == (10, 100) and a.dtype == np.float32
    for x in (a, b, c):  # the third is over the budget: freed, not kept
        pool.give(x)
    got = [pool.take((10, 100), np.float32) for _ in range(3)]
    assert sum(any(g is x for x in (a, b)) for g in got) == 2 and not any(g is c for g in got)
    assert pool.take((10, 100), np.float16) is not a  # another dtype: a new buffer


def test_bench_ingest_deletes_at_its_end_and_the_next_run_says_so(tmp_path):
    """``bench ingest`` deletes its store and its floor copy only after measuring, notes when,
    and a run started soon after says that its prepare follows that deletion (ext4's
    recently-deleted inodes cost new files more); a kept store is moved aside, not deleted
    before the prepare."""
    from conftest import run_cli

    np.save(tmp_path / "dem.npy", SyntheticSource(300, seed=2).read(0, 300, 0, 300).astype(np.float32))
    args = ("bench", "ingest", "--dem", tmp_path / "dem.npy", "--workdir", tmp_path / "w", "--fly", "off", "--workers", 1)
    first = run_cli(*args, "--keep")
    assert "files were deleted" not in first.stdout
    assert (tmp_path / "w" / "dem.zarr").is_dir() and not list((tmp_path / "w").glob("floor.tmp*"))
    second = run_cli(*args)
    assert "files were deleted" in " ".join(second.stdout.split())  # (the floor copy of the first run)
    left = sorted(p.name for p in (tmp_path / "w").iterdir())
    assert not [n for n in left if n.endswith(".zarr") or ".old-" in n or n.startswith("floor.tmp")], left


def test_bench_ingest_dem_must_be_an_existing_file(tmp_path):
    """An explicit ``--dem`` that does not exist is an error naming it (exit 2), and nothing is
    generated: it silently generated a 1 GiB synthetic DEM at that path and benchmarked it
    (walk12 finding 2). A folder, or a file prepare does not read, is an error too."""
    from conftest import run_cli

    missing, work = tmp_path / "missing.npy", tmp_path / "w"
    proc = run_cli("bench", "ingest", "--dem", missing, "--workdir", work, "--fly", "off", "--size", 129, check=False)
    assert proc.returncode == 2 and f"--dem {missing}: no such file" in proc.stderr, proc.stderr
    assert "Traceback" not in proc.stderr and "generating" not in proc.stdout
    assert sorted(tmp_path.iterdir()) == []  # (no DEM, no .partial, no work folder)
    proc = run_cli("bench", "ingest", "--dem", tmp_path, "--workdir", work, "--fly", "off", check=False)
    assert proc.returncode == 2 and f"--dem {tmp_path}: is a folder" in proc.stderr and "Traceback" not in proc.stderr
    (tmp_path / "x.npy").write_text("not an array")
    proc = run_cli("bench", "ingest", "--dem", tmp_path / "x.npy", "--workdir", work, "--fly", "off", check=False)
    assert proc.returncode == 2 and "not a DEM prepare reads" in proc.stderr and "Traceback" not in proc.stderr
    assert not work.exists()


def test_compile_clock_counts_what_numba_compiles():
    """``compile_clock`` counts the signatures numba compiles within its block and the seconds
    they take; none for a function already compiled."""
    from massview.data.jit import compile_clock, njit

    @njit
    def twice(x):
        return 2 * x

    with compile_clock() as clock:
        assert twice(3) == 6
    assert clock.kernels >= 1 and clock.seconds > 0
    with compile_clock() as again:
        assert twice(4) == 8
    assert again.kernels == 0 and again.seconds == 0


def _compiling_prepare_file(*a, **kw):
    """prepare_file, after compiling a function no cache holds (what a new checkout's prepare does)."""
    from massview.app import terrain_cmds
    from massview.data.jit import njit

    @njit
    def plus_one(x):
        return x + 1

    assert plus_one(1) == 2
    return terrain_cmds._real_prepare_file(*a, **kw)


def test_prepare_records_a_compile_in_the_stages_file(tmp_path, monkeypatch):
    """``prepare terrain`` writes to ``MASSVIEW_STAGES_FILE`` what numba compiled during the
    ingest (``bench ingest`` runs it with --quiet, which hides the compile note), and that
    nothing compiled when all was loaded or in memory."""
    from massview.app import terrain_cmds
    from massview.app.cli import build_parser

    np.save(tmp_path / "d.npy", SyntheticSource(129, seed=2).read(0, 129, 0, 129).astype(np.float32))
    stages = tmp_path / "stages.json"
    monkeypatch.setenv("MASSVIEW_STAGES_FILE", str(stages))

    def prepare(out):
        argv = ["prepare", "terrain", str(tmp_path / "d.npy"), "--spacing", "10", "-o", str(tmp_path / out), "--quiet"]
        assert terrain_cmds.cmd_prepare(build_parser(argv).parse_args(argv)) == 0
        return json.loads(stages.read_text())

    prepare("a.zarr")  # (the kernels loaded, or compiled, once in this process)
    assert prepare("b.zarr")["compile"] == {"seconds": 0, "kernels": 0}
    monkeypatch.setattr(terrain_cmds, "_real_prepare_file", terrain_cmds.prepare_file, raising=False)
    monkeypatch.setattr(terrain_cmds, "prepare_file", _compiling_prepare_file)
    said = prepare("c.zarr")
    assert said["compile"]["kernels"] >= 1 and said["compile"]["seconds"] > 0 and said["stages"]


def test_bench_ingest_warms_the_kernels_and_warns_of_a_compile_in_its_figure(tmp_path, monkeypatch, capsys):
    """``bench ingest`` prepares a small DEM untimed first (the kernels load, or compile, before
    the clock starts: walk12 finding 1, 14 MB/s for 90 on a new checkout) and says so; when the
    timed prepare's stages file says numba compiled, it warns that the figure includes it."""
    from massview.app.bench import ingest
    from massview.app.cli import build_parser

    real = ingest.run_measured

    def measured(cmd, rss_file, ranks=0):  # the timed prepare, as if it had compiled for 1.5 s
        r = real(cmd, rss_file, ranks)
        f = Path(os.environ["MASSVIEW_STAGES_FILE"])
        f.write_text(json.dumps({**json.loads(f.read_text()), "compile": {"seconds": 1.5, "kernels": 3}}))
        return r

    monkeypatch.setattr(ingest, "run_measured", measured)
    argv = ["bench", "ingest", "--size", "129", "--workdir", str(tmp_path / "w"), "--fly", "off", "--workers", "1"]
    assert ingest.run(build_parser(argv).parse_args(argv)) == 0
    out = " ".join(capsys.readouterr().out.split())
    assert "warming the ingest kernels with an untimed prepare of a 129² synthetic DEM" in out, out
    assert "warning: numba compiled 3 kernel signatures during the timed prepare: the figures above include 1.5 s of " \
           "compiling; run again" in out, out
    left = sorted(p.name for p in (tmp_path / "w").iterdir())
    assert not [n for n in left if n.endswith(".zarr") or n.startswith(("floor.tmp", "warmup.tmp"))], left


def test_bench_ingest_deletes_what_it_wrote_on_ctrl_c(tmp_path, monkeypatch):
    """Ctrl-C during the timed prepare: the partial store and its lock are deleted, not left for
    the next run (walk12 finding 13: 627 MB kept), and the interruption goes on."""
    from massview.app.bench import ingest
    from massview.app.cli import build_parser

    def interrupted(cmd, rss_file, ranks=0):
        store = Path(cmd[cmd.index("-o") + 1])
        (store / "heights").mkdir(parents=True)
        (store / "heights" / "c.0.0").write_bytes(b"x" * 100)
        store.with_name(f".{store.name}.lock").write_text("pid")
        raise KeyboardInterrupt

    monkeypatch.setattr(ingest, "run_measured", interrupted)
    argv = ["bench", "ingest", "--size", "129", "--workdir", str(tmp_path / "w"), "--fly", "off", "--workers", "1"]
    with pytest.raises(KeyboardInterrupt):
        ingest.run(build_parser(argv).parse_args(argv))
    left = sorted(p.name for p in (tmp_path / "w").iterdir())
    assert "synthetic_129_seed1.npy" in left  # (the DEM is kept for later runs)
    assert not [n for n in left if ".zarr" in n or n.endswith(".tmp")], left
