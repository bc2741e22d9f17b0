"""Bad input gets a clear message naming the parameter, no traceback, a non-zero exit."""

import pytest

from conftest import run_cli


@pytest.mark.parametrize("args,needle", [
    (["render", "builtin:objects", "--decomposition", "sort-middle"], "--decomposition 'sort-middle'"),
    (["render", "nosuch.zarr"], "scene 'nosuch.zarr' not found"),
    (["render", "builtin:objects", "--size", "big"], "--size 'big'"),
    (["render", "builtin:objects", "--path", "spiral"], "--path 'spiral'"),
    (["render", "builtin:objects", "--ranks", "2", "--wall", "3x3"], "--wall 3x3"),
    (["render", "builtin:objects", "--ranks", "3", "--decomposition", "sort-first:grid", "--grid", "2x2"], "--grid 2x2"),
    (["render", "builtin:objects?n=abc"], "n and seed must be integers"),
    (["report", "/nonexistent/run"], "no stats.jsonl"),
])
def test_bad_input_is_reported_plainly(args, needle, tmp_path):
    proc = run_cli(*args, "--out", tmp_path, check=False) if args[0] == "render" else run_cli(*args, check=False)
    assert proc.returncode != 0
    assert needle in proc.stderr
    assert "Traceback" not in proc.stderr
