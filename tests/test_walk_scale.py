"""``walkthrough`` and ``flyover`` scale with the scene (lod/walk.py ``scene_footing``).

Before, a scene's walker always stood 1.7 units above the bottom of its box:

* in a model in millimetres whose ground slab spans z −350..−250, that is inside the slab:
  every frame a grey smear (8 of 8 frames fully drawn, no background, no part in view);
* round a single object with no ground (a sphere of radius 50), under it: of 8 frames,
  walkthrough showed the object's inside or nothing, flyover passed over it looking away
  (half the frames blank).

Now the walker stands on the slab's top with its eye scaled to the parts standing there, and
round a lone object walkthrough and flyover go round it looking at it. Generated metric
scenes (city, plant) keep their walk exactly. Inputs are made here and prepared with the CLI;
frames are rendered with the CLI and their pixels read."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from conftest import load_png, run_cli

BG = np.array([22, 26, 34])  # massview.core.image.BACKGROUND_RGBA: a scene's empty pixels
W, H = 160, 120
FRAMES = 8
SLAB_TOP = -250.0
PARTS = [(-300, -200, 150, 120, 300), (100, 150, 200, 100, 200), (300, -150, 120, 160, 400), (-150, 220, 100, 100, 150),
         (0, -50, 80, 80, 250)]  # (x, y, width, depth, height) in mm, standing on the slab


def _slab():
    slab = trimesh.creation.box([1000, 800, 100])
    slab.apply_translation([0, 0, SLAB_TOP - 50])
    slab.visual.face_colors = [120, 120, 120, 255]
    return slab


def _parts():
    out = []
    for x, y, sx, sy, h in PARTS:
        b = trimesh.creation.box([sx, sy, h])
        b.apply_translation([x, y, SLAB_TOP + h / 2])
        b.visual.face_colors = [200, 40, 40, 255]
        out.append(b)
    return out


def _prepare(tmp_path, meshes, name) -> str:
    files = []
    for i, m in enumerate(meshes):
        files.append(tmp_path / f"{name}{i}.ply")
        m.export(files[-1])
    store = tmp_path / f"{name}.scene"
    run_cli("prepare", "scene", *files, "-o", store, "-q")
    return str(store)


def _frames(store, path, out) -> list[np.ndarray]:
    run_cli("render", store, "--path", path, "--frames", FRAMES, "--size", f"{W}x{H}", "--out", out, "-q")
    return [load_png(out / "frames" / f"{k:05d}.png").astype(int) for k in range(FRAMES)]


def _drawn(img) -> np.ndarray:
    return np.abs(img - BG).sum(axis=2) > 6


def _red(img) -> np.ndarray:
    return (img[..., 0] > img[..., 1] + 50) & (img[..., 0] > img[..., 2] + 50)


def test_a_walk_through_a_millimetre_assembly_stands_on_its_slab(tmp_path):
    """A 1000 × 800 mm ground slab (z −350..−250, its own object) with five parts 150–400 mm
    tall: the walker stands on the slab's top, its eye a quarter of the parts' median height
    above it (62.5 mm). Every frame: background above (not inside the slab), the slab under
    the eye (the bottom rows drawn), a part in view."""
    import massview as mv

    store = _prepare(tmp_path, [_slab(), *_parts()], "mm")
    eyes = np.array([c.position for c in mv.path("walkthrough", store, frames=FRAMES, size=(W, H))])
    assert np.allclose(eyes[:, 2], SLAB_TOP + 0.25 * 250.0)
    frames = _frames(store, "walkthrough", tmp_path / "walk")
    for k, f in enumerate(frames):
        d = _drawn(f)
        assert d[:H // 4].mean() < 0.9, f"frame {k}: its top quarter is {d[:H // 4].mean():.2f} drawn (the eye is inside the slab)"
        assert d[-4:].mean() > 0.99, f"frame {k}: the slab is not under the eye"
        assert _red(f).mean() > 0.02, f"frame {k}: no part in view ({_red(f).mean():.3f} red)"


@pytest.mark.parametrize("what", ["sphere", "one-object assembly"])
def test_walkthrough_and_flyover_round_an_object_with_no_ground_show_it_in_every_frame(tmp_path, what):
    """A sphere of radius 50, and the assembly as one PLY (one object: its box is the scene's):
    nothing to walk on or among, so walkthrough walks and flyover flies round it looking at
    it: every frame shows it whole (more than 8 % drawn, nothing at the frame's border, the
    drawn pixels' extent centred in the frame's middle third) and never only it (not the inside
    of it)."""
    if what == "sphere":
        sphere = trimesh.creation.icosphere(subdivisions=4, radius=50)
        sphere.visual.face_colors = [200, 40, 40, 255]
        store = _prepare(tmp_path, [sphere], "sphere")
    else:
        store = _prepare(tmp_path, [trimesh.util.concatenate([_slab(), *_parts()])], "one")
    for path in ("walkthrough", "flyover"):
        for k, f in enumerate(_frames(store, path, tmp_path / path)):
            d = _drawn(f)
            ys, xs = np.nonzero(d)
            assert 0.08 < d.mean() < 0.9, f"{path} frame {k}: {d.mean():.3f} of it drawn"
            assert not (d[0].any() or d[-1].any() or d[:, 0].any() or d[:, -1].any()), f"{path} frame {k}: cut at the border"
            cx, cy = (xs.min() + xs.max()) / 2 / W, (ys.min() + ys.max()) / 2 / H
            assert abs(cx - 0.5) < 1 / 6 and abs(cy - 0.5) < 1 / 6, f"{path} frame {k}: drawn extent centred at ({cx:.2f}, {cy:.2f})"


@pytest.mark.parametrize("kind", ["city", "plant"])
def test_generated_metric_scenes_keep_their_walk(tmp_path, kind):
    """The generated city and plant: the walker's eye stays 1.7 m above the box's bottom (the
    plant's ground-floor slab top is 0.3 above it: 1.4 m there), with the same route as the
    boxes alone give, and a walkable footing."""
    import massview as mv
    from massview.core.paths import Footing, load_path
    from massview.data.generators.scenes import generate_scene
    from massview.data.scene import SceneStore
    from massview.lod.walk import plan_walk, scene_footing

    store = tmp_path / f"{kind}.scene"
    generate_scene(kind, store, copies=1, size=0.05, seed=1)
    st = SceneStore(store)
    lo, hi = st.bounds
    foot = scene_footing(lo, hi, *st.object_boxes)
    assert foot == Footing(float(lo[2]), 1.7, True)
    cams = mv.path("walkthrough", str(store), frames=6, size=(64, 48))
    old = load_path("walkthrough", lo, hi, route=plan_walk("walkthrough", lo, hi, st.object_boxes)).cameras(6, 64, 48)
    assert [c.position for c in cams] == [c.position for c in old]
    assert np.allclose([c.position[2] - lo[2] for c in cams], 1.7)


def test_footing_from_boxes():
    """Boxes alone: a street grid stands on the box's bottom at 1.7; a ground slab is stood on;
    a floor wider than a quarter of the scene but tall (a hall) is not a floor; one object
    alone, or only enclosures, is nothing to walk on."""
    from massview.core.paths import Footing
    from massview.lod.walk import scene_footing

    c = np.array([(2.0 + 16 * i, 2.0 + 16 * j) for i in range(5) for j in range(5)])
    blo = np.column_stack([c, np.zeros(len(c))])
    bhi = np.column_stack([c + 12, np.full(len(c), 20.0)])
    assert scene_footing(blo.min(0), bhi.max(0), blo, bhi) == Footing(0.0, 1.7, True)
    slab_lo, slab_hi = np.array([[-500.0, -400, -350]]), np.array([[500.0, 400, -250]])
    plo = np.array([[x - sx / 2, y - sy / 2, SLAB_TOP] for x, y, sx, sy, h in PARTS])
    phi = np.array([[x + sx / 2, y + sy / 2, SLAB_TOP + h] for x, y, sx, sy, h in PARTS])
    wl, wh = np.vstack([slab_lo, plo]), np.vstack([slab_hi, phi])
    assert scene_footing(wl.min(0), wh.max(0), wl, wh) == Footing(SLAB_TOP, 62.5, True)
    one = scene_footing([-50, -50, -50], [50, 50, 50], [[-50, -50, -50]], [[50, 50, 50]])
    assert not one.walkable
    hall = np.array([[0.0, 0, 0]]), np.array([[40.0, 40, 20]])
    assert not scene_footing(hall[0][0], hall[1][0], *hall).walkable
    flat = np.array([[0.0, 0, 0]]), np.array([[40.0, 40, 0]])  # a ground mesh alone: stood on, eye 1.7 above it
    assert scene_footing(flat[0][0], flat[1][0], *flat) == Footing(0.0, 1.7, True)
    assert Footing.of_box([0, 0, 0], [40, 40, 0]).eye == 0.0  # (a flat box still makes every path)


def test_scenes_too_small_or_too_full_to_walk_in_are_gone_round():
    """walk6 #1–#3: a table with a vase (2 m × 1 m), a scan that ``prepare scene`` cut into 32
    pieces (2 × 1.44 × 3.3) and a ring with a box (5 m across) counted as walkable: the walker
    crawled under the table top, walked inside the scan and inside the ring's tube. A footprint
    under 10 eye heights is not walked in, and a scene whose objects leave no way between them
    is gone round (it walked the straight line through them); a street grid still walks."""
    from massview.lod.walk import fit_path, scene_footing

    legs = [((x, y, 0.0), (x + 0.06, y + 0.06, 0.72)) for x in (0.0, 1.94) for y in (0.0, 0.94)]
    table = legs + [((0.0, 0.0, 0.72), (2.0, 1.0, 0.75)), ((0.9, 0.4, 0.75), (1.1, 0.6, 0.95))]
    blo, bhi = (np.array([b[k] for b in table]) for k in (0, 1))
    assert not scene_footing(blo.min(0), bhi.max(0), blo, bhi).walkable
    xs, ys, zs = np.meshgrid(np.linspace(-1, 0.5, 4), np.linspace(-0.72, 0.36, 2), np.linspace(-1.66, 0.83, 4), indexing="ij")
    plo = np.column_stack([xs.ravel(), ys.ravel(), zs.ravel()])
    phi = plo + [0.5, 0.72, 0.83]
    assert not scene_footing(plo.min(0), phi.max(0), plo, phi).walkable
    for spec in ("walkthrough", "flyover"):  # framed round it: every eye outside the scene's box, looking at it
        cams = fit_path(spec, blo.min(0), bhi.max(0), (blo, bhi)).cameras(4, 64, 48)
        assert all(np.any((c.position < blo.min(0)) | (c.position > bhi.max(0))) for c in cams)
    # a 100 m square packed with 10 m blocks, no street between them: no way, so round it
    c = np.array([(10.0 * i, 10.0 * j) for i in range(10) for j in range(10)])
    klo, khi = np.column_stack([c, np.zeros(len(c))]), np.column_stack([c + 10, np.full(len(c), 20.0)])
    assert scene_footing(klo.min(0), khi.max(0), klo, khi).walkable  # (roomy, and things stand on the ground)
    cams = fit_path("walkthrough", klo.min(0), khi.max(0), (klo, khi)).cameras(4, 64, 48)
    assert all(np.any((cm.position < klo.min(0)) | (cm.position > khi.max(0))) for cm in cams)
