"""Bad input gets a clear message naming the parameter, no traceback, a non-zero exit (and the
exit itself: cli.main's last exit handler)."""

import argparse
import os
import subprocess
import sys

import numpy as np
import pytest

from conftest import clean_env, run_cli


@pytest.mark.parametrize("args,needle", [
    (["render", "builtin:objects", "--decomposition", "sort-middle"], "--decomposition 'sort-middle'"),
    (["render", "nosuch.zarr"], "scene 'nosuch.zarr' not found"),
    (["render", "builtin:objects", "--size", "big"], "--size 'big'"),
    (["render", "builtin:objects", "--path", "spiral"], "--path 'spiral'"),
    (["render", "builtin:objects", "--ranks", "2", "--wall", "3x3"], "--wall 3x3"),
    (["render", "builtin:objects", "--ranks", "3", "--decomposition", "sort-first:grid", "--grid", "2x2"], "--grid 2x2"),
    (["render", "builtin:objects?n=abc"], "n and seed must be integers"),
    (["report", "/nonexistent/run"], "no stats.jsonl"),
    (["render", os.path.dirname(__file__)], "is a folder without a store's zarr.json"),
    (["render", __file__], "is a file (a store is a folder)"),
    (["info", "/nonexistent/store.zarr"], "no such store; make a terrain store"),
    (["verify", "/nonexistent/store.zarr"], "or a scene store"),
    (["render", "builtin:objects", "--size", "-5x10"], "--size -5x10: width and height must be between 1"),  # (was argparse's "expected one argument")
    (["generate", "terrain", "--size", "65"], "no output given"),
    (["generate", "terrain", "a.npy", "-o", "b.npy", "--size", "65"], "two outputs given"),
    (["generate", "terrain", "-o", "g.txt", "--size", "65"], ".txt is not a format generate writes"),
    (["generate", "scene", "city", "--size", "0.01"], "no output given; `massview generate scene city -o OUT`"),  # (was argparse's usage)
    (["generate", "scene", "city", "a.zarr", "-o", "b.zarr", "--size", "0.01"], "two outputs given"),
    (["generate", "scene", "city", "-o", "c.glb", "--size", "0.01"], ".glb is not a format generate scene writes"),
    # larger than llvmpipe's 16384 (was GL's "framebuffer is not complete" in a 25-line traceback)
    (["render", "builtin:objects", "--size=32768x8", "--frames", "1"], "draws frames of at most"),
    (["render", "builtin:objects", "--size=32768x8", "--frames", "1", "--ranks", "2"], "draws frames of at most"),
    (["render", "/nonexistent/s.zarr", "--system", "reliefboards", "--ranks", "2"], "not found"),
    # walk8 L5: T2 on a polygon scene (was "create one with massview prepare terrain INPUT -o builtin:objects"), info of a built-in
    (["render", "builtin:objects", "--system", "roettger", "--ranks", "2", "--compute-ranks", "1"],
     "--system roettger (T2) draws terrain stores, and builtin:objects is a polygon scene"),
    (["info", "builtin:objects"], "builtin:objects: a built-in scene, generated when it is rendered, not a store on disk"),
])
def test_bad_input_is_reported_plainly(args, needle, tmp_path):
    proc = run_cli(*args, "--out", tmp_path, check=False) if args[0] == "render" else run_cli(*args, check=False)
    assert proc.returncode != 0
    assert needle in proc.stderr
    assert "Traceback" not in proc.stderr


def test_exit_skips_the_final_collection_after_every_other_exit_handler(tmp_path):
    """cli.main registers its gc.freeze first, so it runs after the exit handlers registered
    later (numba's, zarr's, the peak-RSS writer) and before those registered before main; the
    process still exits with the command's status and its files written."""
    import subprocess

    code = ("import atexit, gc, sys\n"
            "atexit.register(lambda: print('frozen at exit:', gc.get_freeze_count() > 0))\n"
            "from massview.app.cli import main\n"
            "rc = main(['generate', 'terrain', '--size', '65', '--format', 'npy', '--quiet', sys.argv[1]])\n"
            "print('frozen before exit:', gc.get_freeze_count() > 0)\n"
            "sys.exit(rc)\n")
    out = subprocess.run([sys.executable, "-c", code, str(tmp_path / "d.npy")], capture_output=True, text=True,
                         env={**os.environ, "MASSVIEW_PEAK_RSS_FILE": str(tmp_path / "rss")})
    assert out.returncode == 0, out.stderr
    assert out.stdout.splitlines()[-2:] == ["frozen before exit: False", "frozen at exit: True"]
    assert (tmp_path / "d.npy").exists() and int((tmp_path / "rss").read_text()) > 0


@pytest.mark.parametrize("args,needle", [
    (["--colormap", "notacmap"], "--colormap 'notacmap' is not a matplotlib colormap"),
    (["--system", "dmmr", "--ranks", "2"], "--system dmmr draws polygon scenes"),
])
def test_terrain_options_are_checked_before_any_rank_or_output(terrain_store, tmp_path, args, needle):
    """A colormap matplotlib does not know, and M1 on a terrain store: one line before the
    ranks start, no output folder (they failed after the progress bar started, or on rank 1
    with MPI_Abort noise, leaving an empty folder)."""
    proc = run_cli("render", terrain_store, *args, "--frames", "1", "--size", "64x48", "--out", tmp_path / "out", check=False)
    assert proc.returncode != 0 and needle in proc.stderr and "Traceback" not in proc.stderr and "MPI_Abort" not in proc.stderr
    assert not (tmp_path / "out").exists()


def test_info_of_a_render_folder_points_to_report(tmp_path):
    """walk8 L5: `massview info RUN` said "not a readable zarr group (No group found …)"."""
    run = tmp_path / "run"
    run.mkdir()
    (run / "summary.json").write_text("{}")
    for cmd in ("info", "verify"):
        proc = run_cli(cmd, run, check=False)
        assert proc.returncode != 0 and f"`massview report {run}` summarises it" in proc.stderr, proc.stderr
        assert "zarr" not in proc.stderr and "Traceback" not in proc.stderr


def test_version():
    import massview

    proc = run_cli("--version")
    assert proc.stdout.strip() == f"massview {massview.__version__}"


@pytest.mark.slow  # compiles the ingest kernels once (about a minute on 2 cores)
def test_compile_note_only_when_kernels_compile(tmp_path):
    """``prepare terrain`` says the kernels are compiling when numba compiles any (here: an empty
    cache), and says nothing when they all load from the cache. (It looked for any .nbi file
    beside the package, and assumed a cache wherever NUMBA_CACHE_DIR was set, so a DEM needing
    kernels the cache lacked compiled for ~37 s without a word.)"""
    np.save(tmp_path / "d.npy", np.random.default_rng(0).normal(size=(65, 65)).astype(np.float32).cumsum(axis=0))
    env = clean_env(NUMBA_CACHE_DIR=str(tmp_path / "numba"))
    runs = [subprocess.run([sys.executable, "-m", "massview", "prepare", "terrain", str(tmp_path / "d.npy"), "--spacing", "10",
                            "-o", str(tmp_path / f"{i}.zarr")], capture_output=True, text=True, env=env, timeout=900)
            for i in range(2)]
    assert [r.returncode for r in runs] == [0, 0], runs[-1].stderr[-2000:]
    assert runs[0].stderr.count("note: compiling the ingest kernels") == 1, runs[0].stderr[-2000:]
    assert "compiling" not in runs[1].stderr, runs[1].stderr[-2000:]


def test_generate_terrain_takes_its_output_as_o_too(tmp_path):
    """``generate terrain -o OUT`` as every other command takes its output, and positionally."""
    run_cli("generate", "terrain", "-o", tmp_path / "a.npy", "--size", 65, "-q")
    run_cli("generate", "terrain", tmp_path / "b.npy", "--size", 65, "-q")
    assert (tmp_path / "a.npy").read_bytes() == (tmp_path / "b.npy").read_bytes()


def test_generate_scene_takes_its_output_positionally_too(tmp_path):
    """``generate scene KIND OUT`` as ``generate terrain OUT`` takes it, and ``-o OUT``: the same store."""
    from massview.data.scene import SceneStore

    run_cli("generate", "scene", "city", "-o", tmp_path / "a.zarr", "--size", 0.01, "-q")
    run_cli("generate", "scene", "city", tmp_path / "b.scene", "--size", 0.01, "-q")  # (the README's name for a scene store)
    a, b = SceneStore(tmp_path / "a.zarr"), SceneStore(tmp_path / "b.scene")
    assert a.skeleton.count == b.skeleton.count > 0 and a.attrs["triangles"] == b.attrs["triangles"]
    assert np.array_equal(a.skeleton.center, b.skeleton.center)


def test_a_dash_value_reaches_its_option():
    from massview.app.cli import _negative_values

    assert _negative_values(["render", "s", "--size", "-5x10", "--frames", "-3", "-q"]) == ["render", "s", "--size=-5x10", "--frames=-3", "-q"]
    assert _negative_values(["render", "s", "--size=1x1", "-3"]) == ["render", "s", "--size=1x1", "-3"]  # (already joined)
    assert _negative_values(["--", "-3"]) == ["--", "-3"]


def test_bench_help_lines_are_whole_sentences():
    """`massview bench --help` gave first docstring lines cut mid-sentence, with reST markup."""
    from massview.app.bench import BENCHES
    from massview.app.cli import _doc_summary

    for name, mod in BENCHES.items():
        h = _doc_summary(mod.__doc__, name)
        assert "``" not in h and h.endswith((".", ")")), (name, h)
    assert _doc_summary("A thing (Smith et al. 2010) does x.\n\nMore.", "x") == "A thing (Smith et al. 2010) does x."


def test_bare_sort_first_is_horizontal(tmp_path):
    """``--decomposition sort-first`` (no layout) renders as sort-first:horizontal, as
    ``sort-last`` alone takes the system's default mode (it was "not available for this scene")."""
    from conftest import summary

    run_cli("render", "builtin:objects", "--ranks", "2", "--decomposition", "sort-first", "--frames", "1", "--size", "64x48",
            "--out", tmp_path, "-q")
    assert summary(tmp_path)["decomposition"] == "sort-first:horizontal"


def test_reliefboards_on_a_terrain_store_is_one_line_before_any_rank(terrain_store, tmp_path):
    """--system reliefboards (M2) on a terrain store: one line naming it before the job starts (it
    failed on rank 0 inside the job, with MPI_Abort's noise), as --system dmmr does; the API too."""
    import massview as mv
    from massview.core.errors import ConfigError

    proc = run_cli("render", terrain_store, "--system", "reliefboards", "--ranks", "2", "--out", tmp_path / "o", check=False)
    assert proc.returncode != 0 and "Traceback" not in proc.stderr and "MPI_Abort" not in proc.stderr
    assert "--system reliefboards draws polygon scenes" in proc.stderr and not (tmp_path / "o").exists()
    with pytest.raises(ConfigError, match="draws polygon scenes"):
        mv.render(str(terrain_store), ranks=2, system="reliefboards", frames=1, size=(64, 48))


def test_render_out_must_not_be_the_input_store(terrain_store, tmp_path):
    """``render STORE -o STORE`` wrote frames/, stats.jsonl and summary.json among the store's arrays."""
    for out in (terrain_store, terrain_store / "frames"):
        proc = run_cli("render", terrain_store, "--frames", "1", "--size", "32x24", "--out", out, check=False)
        assert proc.returncode != 0 and "input store" in proc.stderr and "Traceback" not in proc.stderr
    assert not (terrain_store / "frames").exists() and not (terrain_store / "summary.json").exists()


def test_render_out_in_any_store_is_refused_before_a_rank_starts(terrain_store, tmp_path):
    """--out naming a store (the input, or another one) or a folder inside one is one line for
    every system, the scene untouched (reliefboards wrote frames/ into its input store; the
    others wrote into another store)."""
    run_cli("generate", "scene", "city", "-o", tmp_path / "s.scene", "--size", 0.01, "-q")
    before = sorted(p.name for p in (tmp_path / "s.scene").iterdir())
    for args, needle in (
        (["render", tmp_path / "s.scene", "--system", "reliefboards", "--ranks", "2", "--out", tmp_path / "s.scene"], "is the input store"),
        (["render", "builtin:objects", "--out", tmp_path / "s.scene"], "is the store"),
        (["render", "builtin:objects", "--out", tmp_path / "s.scene" / "frames"], "is inside the store"),
        (["render", tmp_path / "s.scene", "--out", terrain_store], "is the store"),
    ):
        proc = run_cli(*args, "--frames", "1", "--size", "64x48", check=False)
        assert proc.returncode != 0 and needle in proc.stderr and "Traceback" not in proc.stderr, proc.stderr
    assert sorted(p.name for p in (tmp_path / "s.scene").iterdir()) == before


def test_options_without_effect_get_one_warning_line_each(terrain_store, tmp_path):
    """On builtin:objects and a scene store, --exaggeration, --colormap and --compute-ranks were
    accepted without a word; on a terrain store without --system roettger, --compute-ranks. Now
    one warning line per reason, the render goes on; options not typed are never judged."""
    run_cli("generate", "scene", "city", "-o", tmp_path / "s.scene", "--size", 0.01, "-q")
    for scene in ("builtin:objects?n=60", tmp_path / "s.scene"):
        proc = run_cli("render", scene, "--exaggeration", 2, "--colormap", "viridis", "--compute-ranks", 2, "--frames", 1,
                       "--size", "64x48", "--out", tmp_path / "o", "-q")
        assert [line for line in proc.stderr.splitlines() if "warning" in line] == [
            f"massview: warning: --exaggeration, --colormap: no effect on {scene}, a polygon scene (terrain shading and heights "
            "only); leave them out",
            "massview: warning: --compute-ranks: no effect without --system roettger (T2 options); leave it out"], proc.stderr
    proc = run_cli("render", terrain_store, "--compute-ranks=2", "--exaggeration", 2, "--frames", 1, "--size", "64x48",
                   "--out", tmp_path / "t", "-q")
    assert proc.stderr.splitlines() == ["massview: warning: --compute-ranks: no effect without --system roettger "
                                        "(T2 options; add it to use them); leave it out"], proc.stderr
    plain = run_cli("render", "builtin:objects?n=60", "--frames", 1, "--size", "64x48", "--out", tmp_path / "p", "-q")
    assert "warning" not in plain.stderr
    m2 = run_cli("render", "builtin:objects?n=60", "--tnz", 1000, "--stall-backend", 1, "--frames", 1, "--size", "64x48",
                 "--out", tmp_path / "m", "-q")  # walk8 M2: M2's options were ignored without a word
    assert m2.stderr.splitlines() == ["massview: warning: --tnz, --stall-backend: no effect without --system reliefboards "
                                      "(M2 options); leave them out"], m2.stderr
    from massview.app.options import option_warnings
    from massview.core.config import RenderConfig

    said = option_warnings("x.scene", "scene", RenderConfig(system="reliefboards", decomposition="sort-last:kpatch", wall="2x1"),
                           {"decomposition", "wall", "system"})
    assert said == ["--decomposition, --wall: no effect with --system reliefboards (its one visualization rank draws every "
                    "frame whole; the others are board backends); leave them out"]


def test_dmmr_with_a_wall_a_negative_roettger_c_and_a_stalled_non_backend_are_refused_before_any_rank(tmp_path, terrain_store):
    """walk8 L1: these were refused inside the ranks, each under MPICH's MPI_Abort lines."""
    for args, needle in ((["builtin:objects?n=60", "--system", "dmmr", "--wall", "2x1", "--ranks", 3],
                          "--wall and --tile-targets are not available with --system dmmr"),
                         ([terrain_store, "--system", "roettger", "--compute-ranks", 1, "--roettger-c", -2, "--ranks", 2],
                          "--roettger-c must be a finite number >= 0, got -2"),
                         (["builtin:objects?n=60", "--system", "reliefboards", "--stall-backend", 7, "--ranks", 2],
                          "--stall-backend 7 is not a backend rank (with --ranks 2 the backends are rank 1)")):
        proc = run_cli("render", *args, "--frames", 1, "--size", "64x48", "--out", tmp_path / "o", check=False)
        assert proc.returncode == 2 and needle in proc.stderr, proc.stderr
        assert "Abort" not in proc.stderr and "on rank" not in proc.stderr, proc.stderr


def test_dmmr_with_sort_last_is_refused_before_any_rank(tmp_path):
    """--system dmmr --decomposition sort-last ran sort-first:balanced without a word (M1 divides
    the screen); left out, the decomposition is M1's own, as before."""
    proc = run_cli("render", "builtin:objects?n=60", "--system", "dmmr", "--decomposition", "sort-last", "--ranks", 2,
                   "--frames", 1, "--size", "64x48", "--out", tmp_path / "o", check=False)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr and "MPI_Abort" not in proc.stderr
    assert "--system dmmr (M1) divides the screen among its clients, it has no sort-last mode" in proc.stderr
    assert not (tmp_path / "o").exists()


def test_bench_options_show_their_defaults():
    """`massview bench scene --help` showed no default for --size, --frames, --tau, --cache-mb,
    --gpu-mb, --loading (composite: --size); every option with a default now states it."""
    from massview.app.cli import build_parser

    ap = build_parser(["bench"])
    bench = next(a for a in ap._actions if a.dest == "command").choices["bench"]
    for name, sub in next(a for a in bench._actions if a.dest == "bench").choices.items():
        sub.format_help()
        for a in sub._actions:
            if a.option_strings and a.help != argparse.SUPPRESS and a.default not in (None, False, argparse.SUPPRESS):
                assert "default" in sub._get_formatter()._expand_help(a), (name, a.option_strings, a.help)
    out = run_cli("bench", "scene", "--help").stdout.split("options:", 1)[1]
    for flag, says in (("--frames FRAMES", "(default 12)"), ("--cache-mb CACHE_MB", "(default 512)"),
                       ("--loading {async,complete}", "(default, as the viewer)")):
        block = out.split(flag, 1)[1].split("\n  --", 1)[0]
        assert says in " ".join(block.split()), (flag, block)


@pytest.mark.parametrize("args,needle", [
    # walk12: each was a traceback, some after a whole run or after an MPI job started
    (["bench", "composite", "--ranks", "2,x"], "argument --ranks: 'x' is not an integer"),
    (["bench", "composite", "--ranks", "1"], "argument --ranks: 1 is below 2"),
    (["bench", "composite", "--size", "0x0"], "argument --size: 0x0: width and height must be between 1"),
    (["bench", "composite", "--repeat", "0"], "argument --repeat: 0 is below 1"),
    (["bench", "composite", "--scene", os.path.dirname(__file__)], "is a folder without a store's zarr.json"),
    (["bench", "frame", "--ranks", "2,x"], "argument --ranks: 'x' is not an integer"),
    (["bench", "frame", "--lp-threads", "many"], "argument --lp-threads: 'many' is not an integer"),
    (["bench", "lod", "--targets", "5x"], "argument --targets: '5x' is not an integer"),
    (["bench", "lod", "--targets", "-5"], "argument --targets: -5 is below 1"),
    (["bench", "lod", "--tiles", "0"], "argument --tiles: 0 is below 1"),
    (["bench", "lod", "--store", os.path.dirname(__file__)], "is a folder without a store's zarr.json"),
    (["bench", "paraview", "--steps", "nonsense"], "argument --steps: 'nonsense' is not an integer"),
    (["bench", "terrain", "builtin:objects", "--draw"], "is the built-in objects scene, not a terrain store"),
    (["bench", "terrain", "x.zarr", "--draw-reps", "0"], "argument --draw-reps: 0 is below 1"),
    (["bench", "memory", "--ranks", "0"], "argument --ranks: 0 is below 1"),
    (["bench", "memory", "--sections", "everything"], "use comma-separated words out of baseline, fly, account"),
    (["bench", "memory", "--paths", "nowhere"], "--paths nowhere: nowhere is neither a built-in path"),
])
def test_bench_options_are_checked_before_anything_runs(args, needle):
    proc = run_cli(*args, check=False, timeout=120)
    assert proc.returncode != 0 and needle in proc.stderr and "Traceback" not in proc.stderr, proc.stderr[-2000:]


def test_bench_composite_json_folder_is_checked_before_the_jobs(tmp_path):
    """walk12: --json into a file's 'folder' failed with FileNotFoundError after the whole run;
    now before any job, and a missing folder is created."""
    (tmp_path / "f").write_text("x")
    proc = run_cli("bench", "composite", "--ranks", "2", "--json", tmp_path / "f" / "out.json", check=False, timeout=120)
    assert proc.returncode != 0 and "is a file, not a folder" in proc.stderr and "running 2 ranks" not in proc.stdout


def test_bench_help_describes_what_is_measured():
    """walk12: `massview bench NAME --help` said nothing of what the bench runs; it now gives
    the module docstring's first two paragraphs, as paragraphs, without reST markup."""
    out = run_cli("bench", "composite", "--help").stdout
    head = out.split("options:", 1)[0]
    flat = " ".join(head.split())
    assert "network + memory floor" in flat and "For each rank count" in flat and ":data:" not in flat and "``" not in flat
    assert "\n\n" in head.split("[--json JSON]", 1)[1].strip()
    from massview.app.cli import _doc_text

    assert _doc_text("A :func:`~m.f` at ~/.cache in ~2 s.\n\nmassview bench q:\n\nB.", "q") == "A m.f at ~/.cache in ~2 s.\n\nB."
