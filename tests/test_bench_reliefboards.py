"""The plant's fixed path of ``massview bench reliefboards``: a closed loop at uniform speed."""

import json

import numpy as np

from massview.app.bench.reliefboards_scenes import plant_loop_path
from massview.core.paths import load_path


def _positions(path):
    return np.array([k["position"] for k in json.loads(path.read_text())["keyframes"]])


def test_plant_loop_is_closed_uniform_and_cut_into_steps(tmp_path):
    box = (np.array([0.0, 0.0, -0.3]), np.array([120.0, 90.0, 28.0]))
    whole = _positions(plant_loop_path(box, tmp_path / "all.json", steps=60))
    step = np.linalg.norm(np.diff(np.vstack([whole, whole[:1]]), axis=0), axis=1)
    assert len(whole) == 60 and step.max() / step.min() < 1.05  # uniform speed, and the last step closes the loop
    assert np.all(whole[:, 2] > box[1][2])  # above the plant's top
    # the first frames of a finer cut start where the loop starts and go at 1/10 of the step
    part = _positions(plant_loop_path(box, tmp_path / "part.json", steps=600, frames=12))
    assert len(part) == 12 and np.allclose(part[0], whole[0])
    assert np.allclose(np.linalg.norm(np.diff(part, axis=0), axis=1), step.mean() / 10, rtol=0.05)
    # later steps continue the loop; the file renders as a keyframe path with one camera per step
    later = _positions(plant_loop_path(box, tmp_path / "later.json", steps=60, frames=3, first=30))
    assert np.allclose(later, whole[30:33], atol=1e-6 * float(np.linalg.norm(box[1] - box[0])))
    cams = load_path(str(tmp_path / "part.json"), *box).cameras(12, 64, 48)
    assert np.allclose([c.position for c in cams], part, atol=1e-6)
