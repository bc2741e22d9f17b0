"""What the benches report when something goes wrong, and what they leave behind (walk12: a
failed flight reported as a pass, a one-rank flight's peak RSS as 0, an older checkout's store
error as a traceback with the wrong advice, a copy of that checkout left in /tmp by every run)."""

import json
import shutil
from pathlib import Path

from conftest import run_cli


def test_bench_memory_reports_a_failed_flight_as_failed(tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"keyframes": []}))
    proc = run_cli("bench", "memory", "--ranks", "1", "--paths", f"{bad},zoom", "--sections", "fly", "--frames", "1",
                   "--size", "96x64", check=False, timeout=600)
    out = " ".join(proc.stdout.split())
    assert proc.returncode == 1
    assert f"--path {bad}` failed (exit 2): no peak RSS to report" in out and f"the flights of {bad} failed" in out
    zoom = out.split("--path zoom`", 1)[1].split(";", 1)[0]  # one rank: render runs in the launcher, whose peak is the rank's
    per_rank = int(zoom.split("per rank ", 1)[1].split(" MiB")[0])
    assert per_rank > 50, zoom


def test_bench_lod_against_a_checkout_that_cannot_read_the_store(terrain_store, tmp_path):
    """A checkout of an older store format: one line naming --against, the store and what to do,
    before anything is compiled or timed; its temporary copy is removed at exit."""
    import tempfile

    import massview

    old = tmp_path / "old" / "src"
    shutil.copytree(Path(massview.__file__).parent, old / "massview", ignore=shutil.ignore_patterns("__pycache__"))
    store_py = old / "massview" / "data" / "terrain" / "store.py"
    store_py.write_text(store_py.read_text().replace("\nFORMAT_VERSION = 3\n", "\nFORMAT_VERSION = 2\n"))
    before = set(Path(tempfile.gettempdir()).glob("massview_against_*"))
    proc = run_cli("bench", "lod", "--store", terrain_store, "--against", old, check=False, timeout=300)
    assert proc.returncode != 0 and "Traceback" not in proc.stderr, proc.stderr[-2000:]
    msg = " ".join(proc.stderr.split())
    assert f"--against {old}: that checkout cannot read {terrain_store}" in msg and "pass it with --store" in msg
    assert "loading (compiling)" not in proc.stdout
    assert set(Path(tempfile.gettempdir()).glob("massview_against_*")) <= before
