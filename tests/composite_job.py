"""Run under mpiexec by tests/test_composite_mpi.py: every compositor, then delivery to rank 0
and to a 2x2 wall, on random images under the Image contract (few depth levels, so ties
between ranks are frequent), with parts split into many small chunks; rank 0 checks every
result against the serial fold of ``combine`` in rank order, bit for bit. Two frames per
case reuse the pooled tile and the scratch buffers; a tile kept from the first frame must
survive the second."""

import sys

import numpy as np

from massview.core.camera import Viewport
from massview.core.image import Image, blank_image
from massview.core.stats import FrameStats
from massview.parallel import composite as cp
from massview.parallel.codec import resolve_codec
from massview.parallel.decompose import parse_wall
from massview.parallel.exchange import Outbox
from massview.parallel.runtime import guarded, world


def contract_image(rng, vp, fill):
    img = blank_image(vp)
    mask = rng.random((vp.h, vp.w)) < fill
    img.color[mask] = rng.integers(0, 256, (int(mask.sum()), 4), dtype=np.uint8)
    img.depth[mask] = (rng.integers(0, 7, int(mask.sum())) / np.float32(8)).astype(np.float32)
    return img


def same(a, b):
    return a.viewport == b.viewport and np.array_equal(a.color, b.color) and np.array_equal(a.depth.view(np.uint32), b.depth.view(np.uint32))


def main(comm) -> int:
    n, me = comm.Get_size(), comm.Get_rank()
    # one node: "auto" sends runs uncompressed and final regions to rank 0 as raw rows (the wall's
    # half-width tiles still travel as runs), so both delivery paths are checked below
    assert resolve_codec(comm, "auto") == ("none", True), "mpiexec on one node should report all ranks local"
    cp._CHUNK_PIXELS = int(sys.argv[1])  # noqa: SLF001 - many chunks on a small frame
    vp = Viewport(0, 0, 173, 151)
    for frame in range(2):
        images = [contract_image(np.random.default_rng(1000 * frame + r), vp, 0.35 + 0.1 * r) for r in range(n)]
        serial = images[0]
        for img in images[1:]:
            serial = cp.combine(serial, img)
        kept = {}
        for method, codec, owned in [(m, c, o) for m in cp.COMPOSITORS for c, o in (("lz4", False), ("auto", False), ("auto", True))]:
            walls = [[(0, vp)]] + ([list(enumerate(parse_wall("2x2", n, vp.w, vp.h)))] if n == 4 else [])
            for tiles in walls:
                st = FrameStats(frame, me)
                box = Outbox(comm, st)
                mine_img = Image(images[me].color.copy(), images[me].depth.copy(), vp)  # owned: compositing may write into it
                piece = cp.composite(comm, mine_img if owned else images[me], method, 2, st, codec, box, owned=owned)
                tile = cp.deliver(comm, piece, tiles, st, codec, cp.final_regions(n, method, 2, vp), box, mine_img if owned else None)
                if not owned:
                    assert same(mine_img, images[me]), "composite changed an image it does not own"
                mine = next((t for r, t in tiles if r == me), None)
                assert (tile is None) == (mine is None)
                if tile is not None:
                    assert same(tile, serial.crop(mine)), f"{method} {codec} owned={owned} {tiles} frame {frame} rank {me}"
                    if frame == 0 and len(tiles) == 1:
                        kept[method, codec, owned] = (tile, serial)
        for tile, ref in kept.values():
            assert same(tile, ref), "a kept tile was overwritten by a later frame"
    comm.Barrier()
    if me == 0:
        print("composite job ok")
    return 0


if __name__ == "__main__":
    comm = world()
    sys.exit(guarded(comm, main, comm))
