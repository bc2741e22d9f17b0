"""Compare implementations of the compositing kernels (issue 20): vectorized in-place numpy
(the chosen one, ``massview.parallel.kernels``), the same loops compiled with numba
(``scripts/numba_kernels.py``, needs ``pip install numba``), numexpr (dense combine only), and
the old numpy kernels (``tests/reference_kernels.py``), on two rendered partial images, plus
start-up costs.

    .venv/bin/python scripts/compare_kernels.py A.npz B.npz   # color (h,w,4) uint8 + depth (h,w) float32

Prints per kernel the best of 40 in ms for one band of half the frame (a 2-rank binary-swap
round): encode one band, decode + combine the other rank's band into ours, paste a band into
the tile; and the one-time costs (imports, first call). Measure under the same load for all.
"""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

import reference_kernels as ref  # noqa: E402
from massview.core.camera import Viewport  # noqa: E402
from massview.core.image import Image, blank_image  # noqa: E402
from massview.parallel import codec  # noqa: E402
from massview.parallel.composite import _band, _merge_round, _owned  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
import numba_kernels as nbk  # noqa: E402


def nb_encode(img: Image, vp: Viewport, name: str) -> bytes:
    depth, color, v = codec._views(img, vp)
    nruns, nact = nbk.count_runs(depth)
    raw = np.empty(nruns * 4 + nact * 8, np.uint8)
    a, b = nruns * 4, nruns * 4 + nact * 4
    nbk.fill_runs(depth, color, raw[:a].view(np.uint32), raw[a:b].view(np.uint32), raw[b:].view(np.float32))
    return codec._HEADER.pack(codec._MAGIC, v.x, v.y, v.w, v.h, codec.CODECS[name], nruns, nact) + codec._compress(name, raw)


def nb_merge(acc: Image, msg, front: bool) -> Image:
    _, runs, c, d = codec.decode_runs(msg)
    nbk.merge_runs(runs, c, d, acc.color.view(np.uint32)[..., 0], acc.depth, front)
    return acc


def nb_paste(out: Image, msg) -> None:
    vp, runs, c, d = codec.decode_runs(msg)
    dv, cv, _ = codec._views(out, vp)
    dv.fill(np.float32(1.0))
    cv.fill(codec._BG32)
    nbk.paste_runs(runs, c, d, cv, dv)


def ne_combine(acc: Image, other: Image) -> None:
    import numexpr as ne

    a, b = acc.depth, other.depth
    take = ne.evaluate("b < a")
    ne.evaluate("where(take, b, a)", out=acc.depth)
    np.copyto(acc.color, other.color, where=take[..., None])


_NB_FIRST = (f"import sys; sys.path.insert(0, {str(Path(__file__).resolve().parent)!r}); import numpy as np; import numba_kernels as K; "
             "K.count_runs(np.ones((2, 2), np.float32))")


def best(f, rep=40) -> float:
    t = float("inf")
    for _ in range(rep):
        t0 = time.perf_counter()
        f()
        t = min(t, time.perf_counter() - t0)
    return t * 1e3


def startup(stmt: str) -> float:
    code = f"import time; t=time.perf_counter(); {stmt}; print(time.perf_counter()-t)"
    return min(float(subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout) for _ in range(3)) * 1e3


def main(a_path: str, b_path: str, name: str = "blosc2") -> None:
    from massview.parallel.runtime import reuse_freed_memory

    reuse_freed_memory()  # as the CLI does: per-frame buffers reuse freed pages
    za, zb = np.load(a_path), np.load(b_path)
    h, w = za["depth"].shape
    a, b = (Image(z["color"], z["depth"], Viewport(0, 0, w, h)) for z in (za, zb))
    top, bot = Viewport(0, 0, w, h // 2), Viewport(0, h // 2, w, h - h // 2)
    msg = codec.encode_region(b, top, name)
    out = blank_image(a.viewport)
    rows = {
        "encode band": (best(lambda: ref.encode_image(a.crop(bot), name)), best(lambda: codec.encode_region(a, bot, name)),
                        best(lambda: nb_encode(a, bot, name))),
        "decode + combine band": (best(lambda: ref.combine(a.crop(top), ref.decode_image(msg))),
                                  best(lambda: _merge_round(_owned(_band(a, top), False), [None, msg], 0)),
                                  best(lambda: nb_merge(_owned(_band(a, top), False), msg, False))),
        "paste band into tile": (best(lambda: out.paste(ref.decode_image(msg))), best(lambda: codec.paste_into(out, msg, fill=True)),
                                 best(lambda: nb_paste(out, msg))),
    }
    dense = _owned(_band(a, top), False)
    other = b.crop(top)
    print(f"{Path(a_path).name} + {Path(b_path).name}: {w}x{h}, active {np.mean(a.depth < 1):.0%} / {np.mean(b.depth < 1):.0%}, codec {name}")
    print(f"{'kernel (ms, best of 40)':28s} {'old numpy':>10s} {'np in-place':>12s} {'numba':>8s}")
    nbk.count_runs(a.depth)  # compile or load from cache before timing
    for k, (o, n, j) in rows.items():
        print(f"{k:28s} {o:10.2f} {n:12.2f} {j:8.2f}")
    print(f"dense full-band combine: numpy where {best(lambda: ref.combine(dense, other)):.2f}, numexpr in place {best(lambda: ne_combine(dense, other)):.2f}")
    print(f"start-up (ms, best of 3 fresh processes): import numba {startup('import numba'):.0f}; import numexpr {startup('import numexpr'):.0f}; "
          f"numba kernels loaded from cache + first call "
          f"{startup(_NB_FIRST):.0f}; "
          f"import blosc2 {startup('import blosc2'):.0f}; import lz4.frame {startup('import lz4.frame'):.0f}")


if __name__ == "__main__":
    main(*sys.argv[1:])
