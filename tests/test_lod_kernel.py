"""The compiled split test (massview.data.lodkernel) gives the numpy View's bits: flags, pixel
errors and culling codes per sphere, and so the same LOD stage output (the recorded digests)."""

import numpy as np
import pytest

from massview.core.paths import load_path
from massview.lod.kpatch_cut import View, load_split_kernel, split_kernel
from massview.core.errors import ConfigError


@pytest.fixture(scope="module")
def hier(terrain_store):
    from test_lod_stage import _hierarchies

    assert load_split_kernel(wait=True) is not None
    return _hierarchies(terrain_store)[2]


def _bits(a):
    return a.view(np.uint8) if a.dtype != bool else a


@pytest.mark.parametrize("path", ["flyover", "zoom", "turn", "forward"])
def test_kernel_test_is_numpys(hier, path):
    rng = np.random.default_rng(3)
    p = load_path(path, *hier.bounds())
    for at in (0.1, 0.5, 0.9):
        cam = p.camera(at, 640, 360)
        n = 4000  # the top batch's spheres and random ones around the eye (some behind it, some containing it)
        xyz = np.stack([rng.normal(cam.position[i], 400.0, n) for i in range(3)])
        r, err = rng.uniform(0, 300, n), rng.uniform(0, 5, n)
        err[::7] = 0.0
        for tau in (0.05, 1.0):
            a, b = View(cam, tau, kernel="numpy"), View(cam, tau, kernel="numba")
            for x, rr, e in ((hier.top.xyz, hier.top.r, hier.top.err), (xyz, r, err)):
                want, got = a.test(x, rr, e), b.test(x, rr, e)
                for w, g in zip(want, got):
                    assert w.dtype == g.dtype and np.array_equal(_bits(w), _bits(g))
                assert np.array_equal(a.planes_code(x, rr), b.planes_code(x, rr))
            assert np.isinf(b.test(xyz, r, err)[1]).any()  # the spheres behind the eye were tested


@pytest.mark.parametrize("kernel", ["numpy", "numba"])
def test_stage_output_with_each_kernel(terrain_store, monkeypatch, kernel):
    from test_lod_stage import STAGE_DIGESTS, _stage_digests

    monkeypatch.setenv("MASSVIEW_SPLIT_KERNEL", kernel)
    got = _stage_digests(terrain_store)
    assert [k for k in got if got[k] != STAGE_DIGESTS[k]] == []


def test_unknown_kernel_says_what_to_use(monkeypatch):
    monkeypatch.setenv("MASSVIEW_SPLIT_KERNEL", "fortran")
    with pytest.raises(ConfigError, match="numpy"):
        split_kernel()
