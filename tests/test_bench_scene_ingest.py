"""``massview bench scene-ingest`` says what it will write, and roughly how much disk and time,
before it starts (its default wrote a 50 M-triangle, 1.1 GB PLY without a word)."""

import pytest

from conftest import run_cli


def test_the_default_plan_names_the_ply_the_disk_and_the_time(tmp_path):
    from massview.app.bench.scene_ingest import plan

    text, need = plan(tmp_path, 50e6, 1.0, keep=False)
    assert f"writes {tmp_path / 'plant_s1_x6.ply'}: a binary PLY of ~50.4 M triangles (6 plant copies, ~1.14 GB" in text
    assert "~2.28 GB of free disk needed" in text and "roughly 19 min" in text and "--triangles 5e6" in text
    assert 2.2e9 < need < 2.4e9  # the PLY, then its one-off copy (larger than the store)


@pytest.mark.slow  # a 150 k-triangle PLY written and prepared (~20 s on 2 cores)
def test_the_plan_is_printed_before_anything_is_written(tmp_path):
    out = run_cli("bench", "scene-ingest", "--skip-simplifiers", "--triangles", "1e4", "--size", "0.01", "--workdir", tmp_path).stdout
    flat = " ".join(out.split())
    assert flat.startswith(f"bench scene-ingest writes {tmp_path / 'plant_s0.01_x1.ply'}"), flat[:300]
    assert flat.index("of free disk needed") < flat.index("writing ") < flat.index("prepare scene of a binary PLY")
    again = " ".join(run_cli("bench", "scene-ingest", "--skip-simplifiers", "--triangles", "1e4", "--size", "0.01",
                             "--workdir", tmp_path).stdout.split())
    assert again.startswith(f"bench scene-ingest reuses {tmp_path / 'plant_s0.01_x1.ply'} (3 MB)"), again[:300]
