"""The compiled kernels (massview.data.lodkernel) give the numpy walk's bits: the split test's
flags, pixel errors and culling codes per sphere, the cut (every Front column, in order) with
and without missing blocks, and so the same LOD stage output (the recorded digests)."""

import dataclasses

import numpy as np
import pytest

from massview.core.paths import load_path
from massview.core.errors import ConfigError
from massview.lod.kernels import load_lod_kernels, lod_kernels
from massview.lod.kpatch import Front, select_front
from massview.lod.kpatch_cut import View


@pytest.fixture(scope="module")
def hier(terrain_store):
    from test_lod_stage import _hierarchies

    assert load_lod_kernels(wait=True) is not None
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
            assert np.isinf(b.test(xyz, r, err)[1]).any()  # the spheres behind the eye were tested


@pytest.mark.parametrize("path", ["flyover", "zoom", "turn", "forward"])
def test_kernel_cut_is_numpys(hier, monkeypatch, path):
    """Every column, the codes and the deferred count, whole frame and a tile, all blocks
    resident or some missing (requests: the same blocks, priorities and order)."""
    lay = hier.lay
    rng = np.random.default_rng(11)
    grids = [rng.random((2 ** (lay.L - lv),) * 2) < 0.7 for lv in range(lay.levels)]
    grids[lay.L][0, 0] = True
    p = load_path(path, *hier.bounds())
    lo, hi = hier.bounds()
    low = dataclasses.replace(p.camera(0.5, 640, 360), position=(*p.camera(0.5, 640, 360).position[:2], (lo[2] + hi[2]) / 2))
    for cam in (*(p.camera(at, 640, 360) for at in (0.05, 0.5, 0.95)), low):  # low: inside walked diamonds' spheres
        tile = type(cam.viewport)(0, 0, 320, 360)
        for tau, res, vp in ((0.4, None, None), (1.0, grids, None), (0.3, grids, tile)):
            fronts, calls = [], []
            for kernel in ("numpy", "numba"):
                monkeypatch.setenv("MASSVIEW_LOD_KERNEL", kernel)
                got = []
                fronts.append(select_front(hier, cam, tau, res, lambda *a: got.append([np.asarray(x).tolist() for x in a]), vp))
                calls.append(got)
            a, b = fronts
            for k in (*Front.FIELDS, "code", "bid"):
                x, y = getattr(a, k), getattr(b, k)
                assert x.dtype == y.dtype and np.array_equal(_bits(x), _bits(y)), k
            assert a.deferred == b.deferred and calls[0] == calls[1]


@pytest.mark.parametrize("kernel", ["numpy", "numba"])
def test_shading_blocks_with_each_kernel(terrain_store, monkeypatch, kernel):
    """ShadingPyramid.blocks (numpy, or the compiled descent) is shading_blocks' (numpy, einsum
    plane distances), on the paths and on low and random cameras."""
    from test_lod_stage import _hierarchies, test_shading_pyramid_is_shading_blocks
    from massview.lod.texlod import ShadingPyramid, shading_blocks

    monkeypatch.setenv("MASSVIEW_LOD_KERNEL", kernel)
    st, _, hn = hier = _hierarchies(terrain_store)
    test_shading_pyramid_is_shading_blocks(hier)
    mm = [st.block_minmax(lv) for lv in range(st.layout.levels)]
    zmap = lambda z: hn.base + (z * hn.vs - hn.base)  # noqa: E731
    pyr = ShadingPyramid(mm, st.layout.M, st.spacing, zmap)
    lo, hi = hn.bounds()
    rng = np.random.default_rng(5)
    base = load_path("flyover", lo, hi).camera(0.5, 640, 360)
    seen = 0
    for _ in range(60):
        pos = (*rng.uniform(lo[:2] - 2000, hi[:2] + 2000), rng.uniform(lo[2] - 100, hi[2] + 3000))
        q = rng.normal(size=4)
        cam = dataclasses.replace(base, position=pos, orientation=tuple(q / np.linalg.norm(q)))
        for limit in (4096, 20):
            a, b = shading_blocks(mm, st.layout.M, st.spacing, zmap, cam, limit), pyr.blocks(cam, limit)
            for x, y in zip(a, b):
                assert x.dtype == y.dtype and np.array_equal(_bits(x), _bits(y))
            seen += len(a[0]) > 1
    assert seen > 20


@pytest.mark.parametrize("kernel", ["numpy", "numba"])
def test_stage_output_with_each_kernel(terrain_store, monkeypatch, kernel):
    from test_lod_stage import _stage_digests, recorded_stage_digests

    monkeypatch.setenv("MASSVIEW_LOD_KERNEL", kernel)
    key, want = recorded_stage_digests(terrain_store)
    got = _stage_digests(terrain_store)
    assert [k for k in got if got[k] != want[k]] == [], f"input heights/0 {key[:16]}"


def test_unknown_kernel_says_what_to_use(monkeypatch):
    monkeypatch.setenv("MASSVIEW_LOD_KERNEL", "fortran")
    with pytest.raises(ConfigError, match="numpy"):
        lod_kernels()
