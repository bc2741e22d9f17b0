"""Shared helpers: run the real CLI (under real mpiexec for --ranks > 1) and read its outputs."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

SMALL_SCENE = "builtin:objects?n=400"
SMALL_SIZE = "320x240"


def run_cli(*args, timeout=300, check=True) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PMI_", "MPI_", "HYDRA_", "MASSVIEW_"))}
    proc = subprocess.run([sys.executable, "-m", "massview", *map(str, args)], capture_output=True, text=True,
                          timeout=timeout, env=env)
    if check and proc.returncode != 0:
        raise AssertionError(f"massview {' '.join(map(str, args))} exited {proc.returncode}\nstderr:\n{proc.stderr[-4000:]}")
    return proc


def summary(out: Path) -> dict:
    return json.loads((out / "summary.json").read_text())


def load_png(path: Path) -> np.ndarray:
    with Image.open(path) as im:
        return np.asarray(im.convert("RGB"))


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
