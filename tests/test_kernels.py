"""The in-place compositing kernels (issue 20) against the old numpy ones, bit for bit."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import reference_kernels as ref
from massview.core.camera import Viewport
from massview.core.errors import ParallelError
from massview.core.image import BACKGROUND_RGBA, Image, blank_image
from massview.parallel import kernels
from massview.parallel.codec import CODECS, decode_image, decode_runs, encode_image, encode_region, merge_into, paste_into
from massview.parallel.composite import _TILES, _merge_round, _tile_buffer


def contract_image(rng, vp, fill, levels=None):
    """A random image under the Image contract: background = depth 1.0 + background color;
    active depths in [0, 1) — drawn from few ``levels`` to force exact ties between images."""
    img = blank_image(vp)
    mask = rng.random((vp.h, vp.w)) < fill
    n = int(mask.sum())
    img.color[mask] = rng.integers(0, 256, (n, 4), dtype=np.uint8)
    d = rng.integers(0, levels, n) / np.float32(levels) if levels else rng.random(n) * 0.999
    img.depth[mask] = d.astype(np.float32)
    return img


def same(a: Image, b: Image) -> bool:
    return a.viewport == b.viewport and np.array_equal(a.color, b.color) and np.array_equal(a.depth.view(np.uint32), b.depth.view(np.uint32))


@given(st.integers(0, 60), st.integers(0, 60), st.sampled_from([0.0, 0.05, 0.5, 0.97, 1.0]),
       st.sampled_from(sorted(CODECS)), st.integers(0, 2**31))
@settings(max_examples=80, deadline=None)
def test_encode_decode_match_the_reference_bytes_and_pixels(w, h, fill, codec, seed):
    img = contract_image(np.random.default_rng(seed), Viewport(7, 3, w, h), fill)
    new, old = encode_image(img, codec), ref.encode_image(img, codec)
    assert new == old  # same wire bytes, so every reader agrees
    assert same(decode_image(old), ref.decode_image(old))


@given(st.integers(0, 2**31), st.integers(1, 50), st.integers(1, 40), st.integers(0, 20), st.integers(0, 20))
@settings(max_examples=60, deadline=None)
def test_encode_region_equals_encoding_the_crop(seed, w, h, cx, cy):
    rng = np.random.default_rng(seed)
    img = contract_image(rng, Viewport(2, 5, w, h), 0.6)
    vp = Viewport(2 + cx, 5 + cy, int(rng.integers(0, w + 1)), int(rng.integers(0, h + 1)))
    assert encode_region(img, vp, "lz4") == ref.encode_image(img.crop(vp), "lz4")


@pytest.mark.parametrize("k", [2, 3, 4, 5])
@pytest.mark.parametrize("fill", [0.1, 0.7, 1.0])
def test_merge_round_equals_decode_and_combine_in_rank_order(k, fill):
    for seed in range(12):
        rng = np.random.default_rng(seed * 31 + k)
        vp = Viewport(0, int(rng.integers(0, 9)), int(rng.integers(1, 70)), int(rng.integers(1, 50)))
        parts = [contract_image(rng, vp, fill, levels=int(rng.choice([3, 50, 0])) or None) for _ in range(k)]
        digit = int(rng.integers(0, k))
        msgs = [encode_image(p, "lz4") if j != digit else None for j, p in enumerate(parts)]
        old = ref.composite_round([parts[j] if j == digit else ref.decode_image(m) for j, m in enumerate(msgs)])
        own = Image(parts[digit].color.copy(), parts[digit].depth.copy(), vp)
        assert same(_merge_round(own, msgs, digit), old)


@given(st.integers(0, 2**31))
@settings(max_examples=40, deadline=None)
def test_paste_into_a_tile_equals_paste_of_the_decoded_part(seed):
    rng = np.random.default_rng(seed)
    tile = Viewport(10, 20, 37, 29)
    part = Viewport(10 + int(rng.integers(0, 30)), 20 + int(rng.integers(0, 20)), int(rng.integers(0, 8)), int(rng.integers(0, 10)))
    img = contract_image(rng, part, 0.5)
    msg = ref.encode_image(img, "blosc2")
    old, new = blank_image(tile), blank_image(tile)
    old.paste(ref.decode_image(msg))
    paste_into(new, msg)
    assert same(new, old)


@pytest.mark.parametrize("codec", sorted(CODECS))
def test_paste_with_fill_writes_every_pixel_like_a_decoded_paste(codec):
    rng = np.random.default_rng(5)
    tile = Viewport(4, 9, 53, 31)
    img = contract_image(rng, tile, 0.4)
    out = Image(rng.integers(0, 256, (31, 53, 4), dtype=np.uint8), rng.random((31, 53)).astype(np.float32), tile)
    paste_into(out, ref.encode_image(img, codec), fill=True)
    assert same(out, ref.decode_image(ref.encode_image(img, codec)))


def test_corrupt_runs_are_refused_not_written_out_of_bounds():
    img = contract_image(np.random.default_rng(3), Viewport(0, 0, 16, 8), 0.5)
    msg = bytearray(encode_image(img, "none"))
    msg[32:36] = (10_000).to_bytes(4, "little")  # first run far past the viewport
    with pytest.raises(ParallelError, match="runs do not cover"):
        merge_into(blank_image(img.viewport), bytes(msg), front=False)
    with pytest.raises(ParallelError, match="inside the tile"):
        paste_into(blank_image(Viewport(0, 0, 4, 4)), encode_image(img, "none"))


@given(st.integers(0, 2**31), st.booleans(), st.sampled_from([0.0, 0.3, 0.9, 1.0]))
@settings(max_examples=60, deadline=None)
def test_index_kernels_equal_the_mask_kernels_on_contiguous_and_strided_views(seed, front, fill):
    """merge/paste by active-pixel index (contiguous accumulators) and by mask (strided crops)
    give the old kernels' pixels; the index list is the mask's nonzero positions."""
    rng = np.random.default_rng(seed)
    w, h = int(rng.integers(1, 40)), int(rng.integers(1, 30))
    part = contract_image(rng, Viewport(0, 0, w, h), fill, levels=4)
    acc = contract_image(rng, Viewport(0, 0, w, h), 0.6, levels=4)
    _, runs, c, d = decode_runs(encode_image(part, "none"))
    assert np.array_equal(kernels.active_index(runs, d.size), np.flatnonzero(kernels.active_mask(runs, (h, w))))
    old = ref.combine(part, acc) if front else ref.combine(acc, part)
    wide = contract_image(rng, Viewport(0, 0, w + 5, h), 0.5)  # acc as a strided crop of a wider image
    wide.color[:, 2:2 + w], wide.depth[:, 2:2 + w] = acc.color, acc.depth
    for color, depth in ((acc.color.copy(), acc.depth.copy()), (wide.color[:, 2:2 + w], wide.depth[:, 2:2 + w])):
        kernels.merge_runs(runs, c, d, color.view(np.uint32)[..., 0], depth, front)
        assert same(Image(np.ascontiguousarray(color), np.ascontiguousarray(depth), acc.viewport), old)
    pasted = blank_image(Viewport(0, 0, w + 5, h))
    kernels.paste_runs(runs, c, d, pasted.color[:, 2:2 + w].view(np.uint32)[..., 0], pasted.depth[:, 2:2 + w])
    assert same(pasted.crop(Viewport(2, 0, w, h)), Image(part.color, part.depth, Viewport(2, 0, w, h)))


def test_a_pooled_tile_is_reused_only_when_nothing_holds_it():
    vp = Viewport(0, 0, 31, 17)
    _TILES.clear()
    first = _tile_buffer(vp, blank=True)
    second = _tile_buffer(vp, blank=False)
    assert not np.shares_memory(first.color, second.color)  # the first is still held
    kept = first.color[..., :3]  # a view of a part keeps the whole buffer
    del first
    third = _tile_buffer(vp, blank=True)
    assert not np.shares_memory(third.color, kept)
    assert np.all(third.depth == 1) and np.all(third.color == np.array(BACKGROUND_RGBA, np.uint8))
    del kept, third
    again = _tile_buffer(vp, blank=False)
    assert len(_TILES) == 3 and any(np.shares_memory(again.color, c) for c, _ in _TILES)  # a released buffer comes back
    del again
    other = _tile_buffer(Viewport(0, 0, 8, 8), blank=False)  # a new size replaces a free buffer
    assert len(_TILES) == 3 and any(np.shares_memory(other.color, c) for c, _ in _TILES)


@given(st.integers(0, 2**31), st.booleans(), st.sampled_from([0.0, 0.3, 0.9, 1.0]), st.sampled_from(sorted(CODECS)))
@settings(max_examples=60, deadline=None)
def test_a_part_sent_with_every_pixel_active_combines_and_pastes_to_the_same_pixels(seed, front, fill, codec):
    """codec.encode_message(dense_above=...) sends full parts with every pixel active
    (kernels.pack_dense: background pixels as active ones with depth 1.0 and the background
    color): merged in front of or behind an accumulator (contiguous or a strided crop) and
    pasted, it gives the run-coded part's pixels, bit for bit; below the threshold the message
    is the run-coded one."""
    from massview.parallel.codec import encode_message

    rng = np.random.default_rng(seed)
    w, h = int(rng.integers(1, 40)), int(rng.integers(1, 30))
    vp = Viewport(0, 0, w, h)
    part = contract_image(rng, vp, fill, levels=4)
    acc = contract_image(rng, vp, 0.6, levels=4)
    sparse, dense = encode_message(part, vp, codec), encode_message(part, vp, codec, dense_above=-1.0)
    assert bytes(encode_message(part, vp, codec, dense_above=1.0)) == bytes(sparse) == encode_image(part, codec)
    _, runs, _, d = decode_runs(dense)
    assert list(runs) == [0, w * h] and d.size == w * h
    wide = contract_image(rng, Viewport(0, 0, w + 5, h), 0.5)
    wide.color[:, 2:2 + w], wide.depth[:, 2:2 + w] = acc.color, acc.depth
    def crop():  # a strided crop of a fresh copy of the wider image
        c = Image(wide.color.copy(), wide.depth.copy(), wide.viewport)
        return Image(c.color[:, 2:2 + w], c.depth[:, 2:2 + w], vp)

    for target in (lambda: Image(acc.color.copy(), acc.depth.copy(), vp), crop):
        a, b = target(), target()
        merge_into(a, sparse, front)
        merge_into(b, dense, front)
        assert same(a, b)
    for fill_bg in (False, True):
        a, b = blank_image(vp), blank_image(vp)
        paste_into(a, sparse, fill=True)
        paste_into(b, dense, fill=fill_bg)  # a dense part writes every pixel either way
        assert same(a, b)
