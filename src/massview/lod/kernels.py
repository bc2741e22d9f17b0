"""Which split test and walk the K-patch cut runs: numpy, or the compiled kernels of
:mod:`massview.data.lodkernel` (numba lives in ``data/``, DESIGN.md's layer rule), which give
the same bits (tests/test_lod_kernel.py).

The kernels are loaded on a thread at first use (importing numba and loading the kernels
cached on disk: ~1.5 s; compiling them where no cache exists yet: ~15 s), so no frame waits:
until they are ready the numpy walk cuts the same front. ``MASSVIEW_LOD_KERNEL`` chooses:
``auto`` (default: compiled once loaded), ``numpy`` or ``numba`` (wait for the kernels).
"""

from __future__ import annotations

import atexit
import os
import threading

import numpy as np

from ..core.errors import ConfigError

__all__ = ["LOD_KERNELS", "LOD_KERNEL_ENV", "load_lod_kernels", "lod_kernels"]

LOD_KERNELS = ("auto", "numpy", "numba")
LOD_KERNEL_ENV = "MASSVIEW_LOD_KERNEL"
_LOADER: dict = {"thread": None, "mod": None, "error": None}
_LOADER_LOCK = threading.Lock()


def load_lod_kernels(wait: bool = False):
    """The compiled kernels (the module :mod:`massview.data.lodkernel`) once they are loaded,
    else None. The first call starts loading them on a thread; ``wait`` blocks until the load
    ends. Where numba cannot load, None for good (numpy walks)."""
    with _LOADER_LOCK:
        if _LOADER["thread"] is None:
            thread = threading.Thread(target=_load, name="massview-lod-kernels", daemon=True)
            _LOADER["thread"] = thread
            thread.start()
            atexit.register(thread.join)  # numba must not be torn down mid-compile
    if wait:
        _LOADER["thread"].join()
    return _LOADER["mod"]


def _load() -> None:
    try:
        from ..data import lodkernel

        _warm(lodkernel)
        _LOADER["mod"] = lodkernel
    except Exception as exc:  # noqa: BLE001 - numba missing or broken: the numpy path stays
        _LOADER["error"] = exc


def _warm(k) -> None:
    """Call every kernel once with the argument types the walk passes (compiles or loads them)."""
    z, i, c, b = np.zeros(1), np.zeros(1, np.int64), np.zeros(1, np.int8), np.zeros(1, bool)
    vc = (np.zeros((3, 3)), z.repeat(3), z.repeat(4), z.repeat(4), 0.0, 0.0)  # View's camera constants
    tc = (*vc, z.repeat(2), 0.0, 0.0, 0.0)  # ... and the split test's
    k.split_test(z, z, z, z, z, *tc, b.copy(), z.copy(), c.copy())
    S, mark = np.zeros(3, bool), np.zeros(4, np.uint8)
    k.top_rule(b, b, i, i, b, b, S, b.copy(), b.copy())
    k.top_kept_seeds(b, b, b, 0, i)
    cols, zs = np.zeros((11, 1), np.int64), np.zeros((2, 1))
    for rec in (np.zeros((1, 11), np.int32), np.zeros((1, 11), np.int64)):  # the top's records: int32, or int64 past 2^31 samples
        k.head_records(rec, zs, i, c, i, cols, zs.copy(), c.copy(), i.copy())
    for dt in (np.float32, np.float64):  # stored heights and errors: float32, or float64 (hierarchies built in memory)
        h = np.zeros(4, dt)
        for edge in (False, True):
            k.diamond_test(i[:0], edge, 0, 1, 1.0, -1.0, h, h, z.repeat(4), h, 0.0, 1.0, 1.0, *tc, i.copy(), b.copy(), z.copy(),
                           c.copy(), b.copy(), zs.copy())
        k.leaves(i[:0], 0, 1, 1.0, -1.0, h, h, 0.0, 1.0, 1.0, 1.0, *vc)
    k.kept(i, i, c, b, b, zs)
    box = np.zeros((1, 3))
    k.shading_blocks(box, box, i, i + 1, np.zeros((6, 4)), z.repeat(3), 1.0, 1.0, 1)
    planes = np.zeros((6, 4))
    planes.flags.writeable = False  # cull.frustum_planes' are read-only
    k.shading_blocks(box, box, i, i + 1, planes, z.repeat(3), 1.0, 1.0, 1)
    for edge in (False, True):
        k.resident(i, edge, 0, 1, b, 0, b, b.copy(), np.zeros((2, 1), bool))
    k.square_children(i, b, 1, mark)
    k.edge_children(i, 1, mark)
    k.patch_records(i[:0], np.zeros((0, 9), np.int64), np.zeros((7, 1), np.int64), np.zeros((6, 1), np.int64), 0, cols, i.copy())


def lod_kernels(kernel: str | None = None):
    """The kernel module a :class:`~massview.lod.kpatch_cut.View` uses: ``kernel`` (default
    ``MASSVIEW_LOD_KERNEL``, else ``auto``) ``numpy`` → None, ``numba`` → the compiled one
    (loaded first if need be), ``auto`` → the compiled one once loaded, None until then."""
    choice = kernel or os.environ.get(LOD_KERNEL_ENV) or "auto"
    if choice not in LOD_KERNELS:
        where = "kernel" if kernel else LOD_KERNEL_ENV
        raise ConfigError(f"{where}={choice!r} is not a LOD kernel choice; use one of {', '.join(LOD_KERNELS)}")
    if choice == "numpy":
        return None
    mod = load_lod_kernels(wait=choice == "numba")
    if choice == "numba" and mod is None:
        raise ConfigError(f"LOD kernels 'numba' could not be loaded ({_LOADER['error']}); use {LOD_KERNEL_ENV}=numpy")
    return mod
