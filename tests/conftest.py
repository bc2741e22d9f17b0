"""Shared helpers: run the real CLI (under real mpiexec for --ranks > 1) and read its outputs."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from massview.data.terrain import ArraySource

# A shell without job control (a script's `make test &`) starts background commands with SIGINT
# ignored, and an ignored signal stays ignored in every child: the jobs the tests stop with
# Ctrl-C (viewers, launchers) would then not stop. Give this process the default handler back,
# so its children start with SIGINT at its default.
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)

SMALL_SCENE = "builtin:objects?n=400"
SMALL_SIZE = "320x240"


class FlakySource(ArraySource):
    """An in-memory source whose read number ``fail_after + 1`` raises KeyboardInterrupt (an
    interrupted ``prepare``); ``reads`` counts the reads (a resumed run's re-reads)."""

    def __init__(self, arr, fail_after, name="flaky", **kw):
        super().__init__(arr, name, **kw)
        self.reads, self.fail_after = 0, fail_after

    def _raw(self, *a):
        self.reads += 1
        if self.reads > self.fail_after:
            raise KeyboardInterrupt
        return super()._raw(*a)


def clean_env(**extra) -> dict:
    """This process's environment without an enclosing MPI job's or massview's variables (so a
    child starts its own job with its defaults), plus ``extra``."""
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PMI_", "MPI_", "HYDRA_", "MASSVIEW_"))}
    return {**env, **extra}


def descendants(pid: int) -> dict[int, int]:
    """Every process below ``pid`` now (children, their children, ...), from /proc: pid -> its
    start time (so a pid the system has since reused is told apart)."""
    children: dict[int, list[tuple[int, int]]] = {}
    for d in os.listdir("/proc"):
        if d.isdigit():
            st = _stat(int(d))
            if st is not None:
                children.setdefault(st[0], []).append((int(d), st[1]))
    out: dict[int, int] = {}
    todo = [pid]
    while todo:
        for c, start in children.get(todo.pop(), []):
            out[c] = start
            todo.append(c)
    return out


def _stat(pid: int) -> tuple[int, int] | None:
    """(parent pid, start time) of ``pid``, or None when it is gone."""
    try:
        with open(f"/proc/{pid}/stat") as fh:
            f = fh.read().rsplit(")", 1)[1].split()
        return int(f[1]), int(f[19])
    except (OSError, ValueError, IndexError):
        return None


def stop_job(proc: subprocess.Popen, sig=signal.SIGINT, timeout: float = 60) -> str:
    """Stop a ``--ranks`` job (a viewer, a render) started with ``start_new_session=True``:
    ``sig`` to its process group, as a terminal's Ctrl-C, then wait up to ``timeout`` s. Whatever
    of it is still running then — the launcher, and ``mpiexec`` and its ranks, which run in a
    session of their own — is killed (SIGKILL) and the test fails: a job left running would
    slow every later test. Returns the job's output (stdout, with stderr if merged)."""
    tree = descendants(proc.pid)
    if proc.poll() is None:
        try:
            os.killpg(proc.pid, sig)
        except ProcessLookupError:
            pass
    late = out = None
    try:
        out, _ = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        late = f"the job still ran {timeout:g} s after {signal.Signals(sig).name}; killed it and every process below it"
        tree.update(descendants(proc.pid))
        proc.kill()
    for pid, start in tree.items():  # (after a clean stop these are gone already)
        st = _stat(pid)
        if st is not None and st[1] == start:
            try:
                os.kill(pid, signal.SIGKILL)
            except (ProcessLookupError, PermissionError):
                pass
    if late:
        out, _ = proc.communicate()  # (only now: the job's processes held its output pipe open)
        raise AssertionError(f"{late}\n{(out or '')[-2000:]}")
    return out or ""


def run_cli(*args, timeout=300, check=True) -> subprocess.CompletedProcess:
    env = clean_env()
    proc = subprocess.run([sys.executable, "-m", "massview", *map(str, args)], capture_output=True, text=True,
                          timeout=timeout, env=env)
    if check and proc.returncode != 0:
        raise AssertionError(f"massview {' '.join(map(str, args))} exited {proc.returncode}\nstderr:\n{proc.stderr[-4000:]}")
    return proc


def render_cases(root: Path, ranks: int, cases: dict, env: dict | None = None, timeout=900) -> dict:
    """Run ``massview render`` once per case (name -> its arguments, without --ranks/--out/-q),
    all in one job (tests/render_cases_job.py): under real ``mpiexec -n ranks`` with the
    launcher's environment (``launch_env``, as ``--ranks`` sets it), or for one rank in one plain
    process. Returns name -> the case's --out folder (frames, stats.jsonl, summary.json).
    A failing case fails the job; the error names the case."""
    from massview.parallel.runtime import find_mpiexec, launch_env

    root.mkdir(parents=True, exist_ok=True)
    outs = {name: root / name for name in cases}
    spec = [[name, [*map(str, args), "--ranks", str(ranks), "--out", str(outs[name]), "-q"]] for name, args in cases.items()]
    (root / "cases.json").write_text(json.dumps(spec))
    job = [sys.executable, str(Path(__file__).parent / "render_cases_job.py"), str(root / "cases.json")]
    full_env = clean_env(**(env or {}))
    if ranks > 1:
        job = [find_mpiexec(), "-n", str(ranks), *job]
        full_env = launch_env(ranks, {**full_env, "MASSVIEW_UNDER_MPI": "1"})
    proc = subprocess.run(job, capture_output=True, text=True, env=full_env, timeout=timeout)
    if proc.returncode != 0 or "cases ok" not in proc.stdout:
        started = [line[5:] for line in proc.stdout.splitlines() if line.startswith("case ")]
        raise AssertionError(f"the {ranks}-rank job of {len(cases)} render cases failed in case "
                             f"{started[-1] if started else '(none started)'} (status {proc.returncode})\n"
                             f"stderr:\n{proc.stderr[-4000:]}")
    return outs


class RenderBatches:
    """Render cases (name -> (ranks, args)) grouped by rank count: the first test that asks for
    a case renders every case of its rank count in one job (:func:`render_cases`); a failed job
    fails every test that asks for one of its cases, with the same message."""

    def __init__(self, tmp_path_factory, cases: dict, env: dict | None = None, label: str = "cases"):
        self.factory, self.cases, self.env, self.label = tmp_path_factory, cases, env, label
        self.done: dict = {}

    def out(self, name: str) -> Path:
        ranks = self.cases[name][0]
        if ranks not in self.done:
            group = {n: args for n, (r, args) in self.cases.items() if r == ranks}
            try:
                self.done[ranks] = render_cases(self.factory.mktemp(f"{self.label}{ranks}"), ranks, group, self.env)
            except AssertionError as e:
                self.done[ranks] = e
        got = self.done[ranks]
        if isinstance(got, AssertionError):
            raise got
        return got[name]


def summary(out: Path) -> dict:
    return json.loads((out / "summary.json").read_text())


def load_png(path: Path) -> np.ndarray:
    with Image.open(path) as im:
        return np.asarray(im.convert("RGB"))


def not_sky(frame: np.ndarray) -> int:
    """Pixels of an RGB frame that are not the painted sky: every sky colour lies between
    SKY_HORIZON and SKY_ZENITH, so red < green < blue with blue − red ≥ 30; the terrain's
    colours (and white snow) are not like that. A frame with nothing drawn counts ~0."""
    r, g, b = (frame[..., k].astype(np.int16) for k in range(3))
    return int(np.count_nonzero(~((r < g) & (g < b) & (b - r >= 25))))


def save_diff(a: np.ndarray, b: np.ndarray, path: Path) -> Path:
    """Write a diff image (red where pixels differ) next to a failing comparison."""
    d = np.any(a != b, axis=2)
    img = (a // 3).copy()
    img[d] = [255, 0, 0]
    Image.fromarray(img).save(path)
    return path


@pytest.fixture(scope="session")
def serial_small(tmp_path_factory) -> Path:
    """One-rank render of the small scene along `orbit`: the oracle for wall tests."""
    out = tmp_path_factory.mktemp("serial")
    run_cli("render", SMALL_SCENE, "--frames", 2, "--size", SMALL_SIZE, "--out", out, "-q")
    return out


@pytest.fixture(scope="session")
def terrain_store(tmp_path_factory) -> Path:
    """A 2049² synthetic terrain store (4 levels of 257² blocks), built once per session."""
    out = tmp_path_factory.mktemp("terrain") / "t.zarr"
    run_cli("generate", "terrain", out, "--size", 2049, "--seed", 4, "-q")
    return out


@pytest.fixture(scope="module")
def ctx():
    """One headless GL context per test module (Mesa llvmpipe through EGL here)."""
    from massview.render.context import create_context

    c = create_context()
    yield c
    c.release()
