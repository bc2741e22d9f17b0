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
