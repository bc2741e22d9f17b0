"""Depth compositing and image delivery.

Everything reuses one associative ``combine(front, back)``: per pixel, the nearer depth wins
and on equal depth the front operand (the lower rank) wins, so any grouping of ranks in order
gives the same image as compositing serially in rank order.

Sort-last compositors are instances of one radix-k exchange (Peterka et al., "A configurable
algorithm for parallel image-compositing applications", SC 2009): the ranks are arranged as a
mixed-radix number with digits k_1 × k_2 × ... = N; in round i each group of k_i ranks that
differ only in digit i splits its current region into k_i row bands and each member gathers
and combines one band from all members, in rank order.

* ``direct-send``: one round with k = N.
* ``binary-swap``: log2(P) rounds of k = 2 over P ranks, P the largest power of two ≤ N. The
  N − P ranks above P are folded in: odd rank 2i+1 (i < N − P) joins the first round of its
  partner 2i as a sender only, sending each of that round's two bands straight to the rank that
  gathers it (the classic fold sent its whole image to 2i, which had to combine all of it before
  the first round could start: at 3 ranks rank 0 took 1.5 images on its critical path, now 1).
* ``radix-k``: N factored into digits ≤ k (a prime factor larger than k is one digit).

Kernels work in place (issue 20): bands are encoded from views of the image, received
messages are combined into this rank's own band by their active pixels without being decoded
to images (lower ranks' parts in front, nearest first, then higher ranks' — the same pixels as
combining in rank order), and the band lives in a per-thread scratch buffer reused frame
after frame. ``combine`` itself stays the reference the tests compare with. A rank never
waits where it has work of its own: each band is sent the moment it is encoded
(:class:`~.exchange.Outbox`), the own band is copied while those fly, each part is received
just before it is combined, and sends are completed only at the end of :func:`deliver`.

Each rank ends with the final pixels of one region (maybe empty). ``deliver`` then moves
regions to display tiles: the destination rank (one tile covering the frame) or the ranks of
a display wall, each receiving only the pixels of its own tile, in row chunks so that a
display rank pastes one while its sender encodes the next, into a pooled tile buffer.
"""

from __future__ import annotations

import sys
import threading
import time
from contextlib import contextmanager

import numpy as np

from ..core.camera import Viewport
from ..core.config import COMPOSITOR_NAMES
from ..core.errors import ConfigError
from ..core.image import BACKGROUND_RGBA, Image
from ..core.stats import FrameStats
from .codec import decode_runs, encode_message, merge_decoded, merge_into, message_counts, paste_decoded, resolve_codec
from .exchange import Outbox, receive, receive_into, wait_all

__all__ = ["COMPOSITORS", "PIECES", "combine", "split_rows", "radix_factors", "composite", "final_regions", "deliver"]

COMPOSITORS = COMPOSITOR_NAMES  # (defined in core.config, which the CLI's parser imports without MPI)

# Where a rank's compositing time goes, recorded as ``piece.<name>`` in FrameStats.times_ms on
# top of the stages encode / transfer / composite (``bench composite`` prints them): encode
# (pack + compress), wait (for a peer's message or for peers to take this rank's), decode
# (decompress + check), combine (depth-merge, or paste into the tile), copy (the own band into
# the accumulator, the own part into the tile, a tile's background fill).
PIECES = ("encode", "wait", "decode", "combine", "copy")
_STAGE_OF = {"encode": "encode", "wait": "transfer", "decode": "composite", "combine": "composite", "copy": "composite"}


@contextmanager
def _timed(stats: FrameStats, piece: str):
    """Add the body's wall time to the piece and to the stage it belongs to; for a wait also
    this thread's CPU time in it as ``cpu.wait`` (MPI busy-polling; near 0 when the wait
    sleeps: :func:`~.exchange.wait_mode`)."""
    t0, c0 = time.perf_counter(), (time.thread_time() if piece == "wait" else 0.0)
    try:
        yield
    finally:
        dt, times = (time.perf_counter() - t0) * 1e3, stats.times_ms
        stage, key = _STAGE_OF[piece], "piece." + piece
        times[stage] = times.get(stage, 0.0) + dt
        times[key] = times.get(key, 0.0) + dt
        if piece == "wait":
            times["cpu.wait"] = times.get("cpu.wait", 0.0) + (time.thread_time() - c0) * 1e3


def combine(front: Image, back: Image) -> Image:
    """Depth-composite two images of the same viewport; ``front`` wins ties. Associative."""
    if front.viewport != back.viewport:
        raise ConfigError(f"combine needs equal viewports, got {front.viewport} and {back.viewport}")
    take = back.depth < front.depth
    color = np.where(take[..., None], back.color, front.color)
    depth = np.where(take, back.depth, front.depth)
    return Image(color, depth, front.viewport)


def split_rows(vp: Viewport, k: int) -> list[Viewport]:
    """``k`` row bands covering ``vp`` in order (some empty when vp has fewer than k rows)."""
    cuts = [vp.y + (vp.h * i) // k for i in range(k + 1)]
    return [Viewport(vp.x, cuts[i], vp.w, cuts[i + 1] - cuts[i]) for i in range(k)]


def radix_factors(n: int, k: int) -> list[int]:
    """Digits for radix-k over n ranks: each the largest divisor ≤ k of what remains, or the
    remaining prime itself when it has none."""
    if k < 2:
        raise ConfigError(f"radix-k needs k >= 2, got {k}")
    out, rest = [], n
    while rest > 1:
        d = next((d for d in range(min(k, rest), 1, -1) if rest % d == 0), None)
        if d is None:
            d = next(p for p in range(2, rest + 1) if rest % p == 0)
        out.append(d)
        rest //= d
    return out


def _band(img: Image, vp: Viewport) -> Image:
    """The row band ``vp`` of ``img`` as a view (bands span the full width: contiguous)."""
    rows = slice(vp.y - img.viewport.y, vp.y - img.viewport.y + vp.h)
    return Image(img.color[rows], img.depth[rows], vp)


_POOL = threading.local()


def _scratch(vp: Viewport) -> Image:
    """This thread's reusable accumulator buffer shaped to ``vp``: compositing writes into the
    same pages frame after frame (a fresh 1280×1024 image costs more in page faults than the
    whole combine). Valid until the next :func:`composite` call on this thread."""
    need = vp.w * vp.h
    buf = getattr(_POOL, "buf", None)
    if buf is None or buf[1].size < need:
        buf = _POOL.buf = (np.empty(4 * need, np.uint8), np.empty(need, np.float32))
    return Image(buf[0][: 4 * need].reshape(vp.h, vp.w, 4), buf[1][:need].reshape(vp.h, vp.w), vp)


def _owned(img: Image, owned: bool, stats: FrameStats) -> Image:
    """``img`` itself when this rank owns its pixels, else a copy in the scratch buffer."""
    if owned:
        return img
    with _timed(stats, "copy"):
        out = _scratch(img.viewport)
        np.copyto(out.color, img.color)
        np.copyto(out.depth, img.depth)
    _count_touched(stats, "composite", 2 * img.nbytes)
    return out


def _encode_to(box: Outbox, dest: int, img: Image, vp: Viewport, codec: str, tag: int, stats: FrameStats,
               dense: float | None = None) -> None:
    """Encode the pixels of ``vp`` and start sending them to ``dest`` at once (``dense``: see
    :func:`~.codec.encode_message`)."""
    with _timed(stats, "encode"):
        msg = encode_message(img, vp, codec, dense)
        box.send(dest, msg, tag)
    pixels, nact = message_counts(msg)
    _count_touched(stats, "encode", 4 * pixels + 4 * nact + len(msg))


def _merge_order(k: int, digit: int) -> list[int]:
    """The order parts are combined in: lower ranks nearest first (each in front of all so far),
    then higher ranks (each behind all so far) — the same pixels as combining in rank order."""
    return [*range(digit - 1, -1, -1), *range(digit + 1, k)]


def _receive(comm, source: int, tag: int, stats: FrameStats) -> tuple:
    """The next message from ``source``, taken apart (:func:`decode_runs`), and its size."""
    with _timed(stats, "wait"):
        msg = receive(comm, source, tag, stats)
    with _timed(stats, "decode"):
        return decode_runs(msg), msg.size


def _merge_part(own: Image, comm, source: int, tag: int, front: bool, stats: FrameStats) -> None:
    part, size = _receive(comm, source, tag, stats)
    with _timed(stats, "combine"):
        merge_decoded(own, part, front)
    nact = part[3].size
    _count_touched(stats, "composite", size + 4 * nact)


def _merge_round(own: Image, parts: list, digit: int) -> Image:
    """Combine received messages ``parts`` (rank order, ``parts[digit]`` unused) into ``own``
    in place (see :func:`_merge_order`)."""
    for j in _merge_order(len(parts), digit):
        merge_into(own, parts[j], front=j < digit)
    return own


def _round_group(members: list[int], idx: int, stride: int, k: int) -> list[int]:
    """The ``k`` members (rank order) that swap bands with ``members[idx]`` in the round of
    ``stride``; member j of the group gathers band j."""
    digit = (idx // stride) % k
    return [members[idx + (j - digit) * stride] for j in range(k)]


def _radix_rounds(comm, img: Image, members: list[int], factors: list[int], stats, codec, box: Outbox, owned: bool = False,
                  dense: float | None = None, extra: int = 0) -> Image:
    """The rounds of radix-k over ``members``. Per round: encode each outgoing band and send it
    at once (nearest peers first: they combine this rank's part first), copy the own band while
    those fly, then receive each part just before combining it, in merge order. In the first
    round, members below ``2 * extra`` also receive from their folded partner (binary-swap)."""
    me = comm.Get_rank()
    idx = members.index(me)
    current = img
    stride = 1
    for rnd, k in enumerate(factors):
        digit = (idx // stride) % k
        group = _round_group(members, idx, stride, k)
        bands = split_rows(current.viewport, k)
        for j in sorted((j for j in range(k) if j != digit), key=lambda j: abs(j - digit)):
            _encode_to(box, group[j], current, bands[j], codec, rnd, stats, dense)
        current = _owned(_band(current, bands[digit]), owned or rnd > 0, stats)
        senders = sorted(group + [g + 1 for g in group if g < 2 * extra]) if rnd == 0 else group
        pos = senders.index(me)
        for j in _merge_order(len(senders), pos):
            _merge_part(current, comm, senders[j], rnd, j < pos, stats)
        stride *= k
    return current


_TILES: list[tuple[np.ndarray, np.ndarray]] = []
_TILES_LOCK = threading.Lock()
_TILES_KEPT = 3


def _refcounts(pool: list) -> list[int]:
    """The larger reference count of each pooled pair's two arrays, as this code sees it."""
    return [max(sys.getrefcount(c), sys.getrefcount(d)) for c, d in pool]


_FREE_REFS = _refcounts([(np.empty(1), np.empty(1))])[0]  # what a pair only the pool holds shows here


def _tile_buffer(vp: Viewport, blank: bool) -> Image:
    """A display tile's buffer: a pooled one nobody holds any more (its arrays referenced only
    by the pool: every view numpy hands out keeps a reference to the array it came from, so a
    tile, or any part of one, still held by a caller is never reused), else a new one. Reusing
    pages saves the page faults of a fresh tile every frame (~1 ms at 1280×1024)."""
    with _TILES_LOCK:
        free = [i for i, refs in enumerate(_refcounts(_TILES)) if refs == _FREE_REFS]
        same = [i for i in free if _TILES[i][0].shape == (vp.h, vp.w, 4)]
        if same:
            color, depth = _TILES[same[0]]
        else:
            color, depth = np.empty((vp.h, vp.w, 4), np.uint8), np.empty((vp.h, vp.w), np.float32)
            if free and len(_TILES) >= _TILES_KEPT:  # the tile size changed: forget a free one of another size
                del _TILES[free[0]]
            if len(_TILES) < _TILES_KEPT:
                _TILES.append((color, depth))
        out = Image(color, depth, vp)
    if blank:
        out.color[...] = BACKGROUND_RGBA
        out.depth.fill(np.float32(1.0))
    return out


def _copy_region(out: Image, src: Image, vp: Viewport) -> None:
    """Copy the pixels of ``vp`` from ``src`` into ``out`` (both must contain ``vp``)."""
    def sl(img):
        return (slice(vp.y - img.viewport.y, vp.y - img.viewport.y + vp.h), slice(vp.x - img.viewport.x, vp.x - img.viewport.x + vp.w))
    np.copyto(out.color[sl(out)], src.color[sl(src)])
    np.copyto(out.depth[sl(out)], src.depth[sl(src)])


def _count_touched(stats, stage: str, nbytes: int) -> None:
    """Count the bytes a stage must read and write at the least into ``touched_<stage>``: the
    memory term of the floors of ``massview bench composite`` and ``bench frame``. Pixels are
    8 B (color 4 + depth 4). Encoding a region: its depths read (4 B a pixel), the colors of
    its active pixels read (4 B each), the message written. Combining a message into the own
    band: the message read and the band's depths at its active pixels (4 B each); copying the
    own band into the accumulator (first round only): 8 B a pixel read and 8 written. A
    display tile: every pixel written once (8 B), the own region's pixels read (8 B), the
    messages read. Temporaries (masks, indices, decompressed bodies) are not counted: they are
    above the floor."""
    stats.count(f"touched_{stage}", nbytes)


def composite(comm, img: Image, method: str = "binary-swap", k: int = 4, stats: FrameStats | None = None, codec: str = "auto",
              outbox: Outbox | None = None, owned: bool = False) -> Image:
    """Sort-last depth compositing of every rank's full-frame ``img``. Returns the final pixels
    of the region this rank ends up owning (an empty viewport for ranks that own none) as a view
    of this thread's scratch buffer: valid until the next call on this thread (hand it to
    :func:`deliver` or copy it). ``img`` is left unchanged unless ``owned`` (the caller gives
    it up, as the frame loop does with each frame's read-back): then the rounds combine into
    ``img``'s own rows — no copy of the own band — and the piece is a view of ``img`` (pass it
    to :func:`deliver` as ``frame``: a display rank assembles its tile in it). With ``outbox``
    this rank's sends may still be in flight on return (pass the same outbox to
    :func:`deliver`, which waits for all of them at its end: a rank need not wait for its peers
    to take its parts before it starts encoding its final region); without, they are
    completed here."""
    stats = stats if stats is not None else FrameStats(frame=-1, rank=comm.Get_rank())
    n, me = comm.Get_size(), comm.Get_rank()
    codec, raw = resolve_codec(comm, codec)
    dense = DENSE_ABOVE if raw else None
    if n == 1:
        return img
    members, factors, extra = _plan(n, method, k)
    box = outbox if outbox is not None else Outbox(comm, stats)
    if me < 2 * extra and me % 2:  # folded: a sender only, in its partner's first round
        group = _round_group(members, members.index(me - 1), 1, factors[0])
        bands = split_rows(img.viewport, factors[0])
        for j in sorted(range(len(group)), key=lambda j: abs(group[j] - me)):  # nearest first
            _encode_to(box, group[j], img, bands[j], codec, 0, stats, dense)
        piece = Image(img.color[:0, :0], img.depth[:0, :0], Viewport(0, 0, 0, 0))
    else:
        piece = _radix_rounds(comm, img, members, factors, stats, codec, box, owned=owned, dense=dense, extra=extra)
    if outbox is None:
        with _timed(stats, "wait"):
            box.wait()
    return piece


_DELIVER_TAG, _ROWS_TAG = 200, 300
# With codec "auto" on one node, a part more than this share active travels with every pixel
# active (codec.encode_message): copying it costs less than finding its runs. Measured on
# 1280×256 bands of real partial images (encode + bytes at 6–10 GB/s + merge): 6 % active, runs
# 0.22 ms against 0.54; 23 %, 0.56 against 0.54; 46 %, 0.87 against 0.54.
DENSE_ABOVE = 0.25


def _plan(n: int, method: str, k: int) -> tuple[list[int], list[int], int]:
    """(members of the radix rounds, their digits, ranks folded away first) of ``method``."""
    if method == "direct-send":
        return list(range(n)), [n], 0
    if method == "radix-k":
        return list(range(n)), radix_factors(n, k), 0
    if method != "binary-swap":
        raise ConfigError(f"unknown compositor {method!r}; use one of {', '.join(COMPOSITORS)}")
    p = 1 << (n.bit_length() - 1)
    extra = n - p
    return [r for r in range(n) if r >= 2 * extra or r % 2 == 0], [2] * (p.bit_length() - 1), extra


def final_regions(n: int, method: str, k: int, vp: Viewport) -> list[Viewport]:
    """The region each of ``n`` ranks holds after :func:`composite` of full-frame images of
    ``vp`` (what :func:`deliver` would otherwise learn with an allgather): computed the way the
    rounds split it, so every rank knows all regions without a message."""
    if n == 1:
        return [vp]
    members, factors, _ = _plan(n, method, k)
    regions = [Viewport(0, 0, 0, 0)] * n
    for idx, rank in enumerate(members):
        current, stride = vp, 1
        for f in factors:
            current = split_rows(current, f)[(idx // stride) % f]
            stride *= f
        regions[rank] = current
    return regions


def deliver(comm, piece: Image, tiles: list[tuple[int, Viewport]], stats: FrameStats | None = None, codec: str = "auto",
            regions: list[Viewport] | None = None, outbox: Outbox | None = None, frame: Image | None = None) -> Image | None:
    """Move final pixels to display tiles. ``piece`` is the region this rank holds (regions of
    all ranks partition the frame); ``tiles`` lists (display rank, tile viewport); ``regions``
    every rank's region when the caller knows them (:func:`final_regions`), else they are
    allgathered. Returns the assembled tile on display ranks, None elsewhere (on one rank whose
    one tile is the piece's viewport: the piece itself). ``frame``: the image the piece is a
    view of, given up by the caller (:func:`composite` with ``owned``); a display rank whose
    tile is that image's viewport assembles the tile in it — its own region is already in
    place, the other ranks' parts are received or pasted around it — and returns it.

    Each part for another rank travels in row chunks (:func:`_chunks`), each sent the moment
    it is encoded; a display rank prepares its tile (a pooled buffer) and copies its own part
    while those messages fly, and pastes each chunk as it takes it. At the end it waits for every send of ``outbox`` (the
    one :func:`composite` left in flight) and its own."""
    stats = stats if stats is not None else FrameStats(frame=-1, rank=comm.Get_rank())
    me = comm.Get_rank()
    if comm.Get_size() == 1 and tiles == [(0, piece.viewport)]:
        return piece  # one rank, one tile: the image is the tile (no copy)
    if regions is None:
        regions = [Viewport.from_json(v) for v in comm.allgather(piece.viewport.to_json())]
    codec, raw = resolve_codec(comm, codec)
    box, local = outbox if outbox is not None else Outbox(comm, stats), None
    for rank, tile in tiles:
        part = piece.viewport.intersect(tile)
        if part.empty:
            continue
        if rank == me:
            local = part
            continue
        if raw and _whole_rows(part, piece.viewport, tile):
            _send_rows(box, rank, piece, part, stats)
            continue
        for chunk in _chunks(part):
            _encode_to(box, rank, piece, chunk, codec, _DELIVER_TAG, stats, DENSE_ABOVE if raw else None)
    my_tile = next((t for r, t in tiles if r == me), None)
    out = None if my_tile is None else _assemble(comm, my_tile, piece, local, regions, stats, raw, frame)
    with _timed(stats, "wait"):
        box.wait()
    return out


def _assemble(comm, tile: Viewport, piece: Image, local: Viewport | None, regions: list[Viewport], stats: FrameStats,
              raw: bool = False, frame: Image | None = None) -> Image:
    """The display tile: raw rows received straight into it (started first, completed last),
    the own part copied (or already in place in ``frame``), every other rank's run-coded part
    received and pasted."""
    me = comm.Get_rank()
    sources = [r for r, reg in enumerate(regions) if r != me and not reg.intersect(tile).empty]
    covered = sum(regions[r].intersect(tile).area for r in [*sources, me]) == tile.area
    in_place = covered and local is not None and frame is not None and frame.viewport == tile and _is_view(piece, frame)
    with _timed(stats, "copy"):
        out = frame if in_place else _tile_buffer(tile, blank=not covered)  # regions partition the frame: each pixel written once
    rows = [s for s in sources if raw and _whole_rows(regions[s].intersect(tile), regions[s], tile)]
    requests = [req for s in rows for req in _receive_rows(comm, out, regions[s].intersect(tile), s, stats)]
    if local is not None and not in_place:
        with _timed(stats, "copy"):
            _copy_region(out, piece, local)
        _count_touched(stats, "composite", 16 * local.area)
    _count_touched(stats, "composite", 0 if covered else out.nbytes)
    for s in sources:
        if s in rows:
            continue
        for _ in _chunks(regions[s].intersect(tile)):
            part, size = _receive(comm, s, _DELIVER_TAG, stats)
            with _timed(stats, "combine"):
                paste_decoded(out, part, fill=covered)
            _count_touched(stats, "composite", size + (8 * part[0].area if covered else 0))
    with _timed(stats, "wait"):
        wait_all(requests)
    return out


def _is_view(piece: Image, frame: Image) -> bool:
    """Whether ``piece``'s arrays are exactly ``frame``'s pixels of ``piece.viewport``."""
    v = piece.viewport
    if v.empty or v.intersect(frame.viewport) != v:
        return False
    rows = slice(v.y - frame.viewport.y, v.y - frame.viewport.y + v.h)
    cols = slice(v.x - frame.viewport.x, v.x - frame.viewport.x + v.w)

    def same(a, b):
        return a.shape == b.shape and a.strides == b.strides and a.__array_interface__["data"][0] == b.__array_interface__["data"][0]

    return same(piece.color, frame.color[rows, cols]) and same(piece.depth, frame.depth[rows, cols])


def _whole_rows(part: Viewport, region: Viewport, tile: Viewport) -> bool:
    """Whether ``part`` (= region ∩ tile) is whole rows of both the sender's region and the
    tile: contiguous memory on both sides, so it travels as raw rows without packing (sender
    and receiver decide alike from the viewports)."""
    return not part.empty and part.w == region.w == tile.w


def _send_rows(box: Outbox, dest: int, piece: Image, part: Viewport, stats: FrameStats) -> None:
    """Send the rows ``part`` of ``piece`` as they are: color, then depth (no packing, no copy
    when the piece is contiguous; its buffer stays untouched until :func:`deliver` ends)."""
    rows = slice(part.y - piece.viewport.y, part.y - piece.viewport.y + part.h)
    with _timed(stats, "encode"):
        for arr in (piece.color[rows], piece.depth[rows]):
            box.send(dest, np.ascontiguousarray(arr).reshape(-1).view(np.uint8), _ROWS_TAG)


def _receive_rows(comm, out: Image, part: Viewport, source: int, stats: FrameStats) -> list:
    """Start receiving ``source``'s raw rows ``part`` straight into the tile ``out``."""
    rows = slice(part.y - out.viewport.y, part.y - out.viewport.y + part.h)
    return [receive_into(comm, arr, source, _ROWS_TAG, stats) for arr in (out.color[rows], out.depth[rows])]


_CHUNK_PIXELS = 1 << 18


def _chunks(part: Viewport) -> list[Viewport]:
    """The row bands a large part travels in (each ≤ ~256 k pixels; both sides compute the
    same): a whole image folded onto a partner, a final region delivered to a display rank.
    The receiver combines or pastes one while the sender encodes the next."""
    return split_rows(part, max(1, -(-part.area // _CHUNK_PIXELS)))
