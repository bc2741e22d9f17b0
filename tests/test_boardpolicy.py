"""§6.1 decisions: near zone front to back until t_nz, boards below E, requests past ε and the size
threshold, never two pending."""

import math

import numpy as np
import pytest

from massview.core.camera import Camera
from massview.core.errors import ConfigError
from massview.lod.boardpolicy import BoardPolicy, plan_frame, projected_size_px

CAM = Camera.look_at((0, 0, 0), (1, 0, 0), fovy=45.0, near=0.1, far=1000, width=1024, height=768)


def _scene():
    # feasible objects at x = 10, 20, 30, 40 (100 triangles each), an infeasible one at 15 (50)
    centers = np.array([[10, 0, 0], [20, 0, 0], [30, 0, 0], [40, 0, 0], [15, 0, 0], [-30, 0, 0]], float)
    radii = np.ones(6)
    tris = np.array([100, 100, 100, 100, 50, 100])
    feasible = np.array([True, True, True, True, False, True])
    return centers, radii, tris, feasible


def _table(n):
    return np.full((n, 3), np.nan), np.zeros(n, np.int64), np.zeros(n, bool)


def test_near_zone_front_to_back_until_tnz_with_infeasible_triangles_counted():
    c, r, t, f = _scene()
    dirs, size, pend = _table(6)
    plan = plan_frame(CAM, c, r, t, f, dirs, size, pend, BoardPolicy(t_nz=260))
    assert plan.infeasible.tolist() == [4]
    assert plan.near.tolist() == [0, 1] and plan.near_triangles == 250
    assert plan.far_original.tolist() == [2, 3] and len(plan.far_board) == 0
    assert plan.requests.tolist() == [2, 3]  # no board yet: requested, front to back; 5 is behind
    assert np.allclose(plan.request_dirs, [[1, 0, 0], [1, 0, 0]])
    assert plan.request_sizes.tolist() == projected_size_px(CAM, c[[2, 3]], r[[2, 3]], BoardPolicy()).tolist()


def _rotated(deg):
    a = math.radians(deg)
    return np.array([math.cos(a), math.sin(a), 0.0])


def _one_far(board_deg=None, board_size=None, pending=False, radius=1.0):
    c, r, t, f = _scene()
    r = r.copy()
    r[2] = radius
    dirs, size, pend = _table(6)
    policy = BoardPolicy(t_nz=260)
    cur = int(projected_size_px(CAM, c[2:3], r[2:3], policy)[0])
    if board_deg is not None:
        dirs[2] = _rotated(board_deg)
        size[2] = cur if board_size is None else board_size(cur)
    pend[2] = pending
    return plan_frame(CAM, c, r, t, f, dirs, size, pend, policy), cur


@pytest.mark.parametrize("deg,board,asked", [(0, True, False), (11.4, True, False), (11.6, True, True),
                                               (44.9, True, True), (45.1, False, True)])
def test_angle_error_renews_past_epsilon_and_draws_originals_past_E(deg, board, asked):
    plan, _ = _one_far(deg)
    assert (2 in plan.far_board) == board and (2 in plan.far_original) == (not board)
    assert (2 in plan.requests) == asked
    if board:
        assert plan.angle_error[plan.far_board.tolist().index(2)] == pytest.approx(deg, abs=1e-6)


@pytest.mark.parametrize("scale,asked", [(1 / 1.29, False), (1 / 1.31, True), (1 / 0.71, False), (1 / 0.69, True)])
def test_projected_size_change_past_thirty_percent_renews(scale, asked):
    plan, cur = _one_far(0.0, board_size=lambda cur: round(cur * scale), radius=3.3)  # ~200 px
    assert cur > 150
    assert 2 in plan.far_board
    assert (2 in plan.requests) == asked


def test_never_two_pending_requests_for_one_object():
    plan, _ = _one_far(50.0, pending=True)
    assert 2 in plan.far_original and 2 not in plan.requests
    plan, _ = _one_far(None, pending=True)
    assert 2 not in plan.requests and 3 in plan.requests


def test_policy_validation():
    with pytest.raises(ConfigError, match="epsilon"):
        BoardPolicy(epsilon_deg=50, max_error_deg=45)


def test_one_source_for_the_policy_defaults():
    from massview.app.cli import build_parser
    from massview.app.reliefboards_cmds import options_from_args
    from massview.lod.boardpolicy import DEFAULT_TNZ, MACHINE_RATE, PAPER_RATE, PAPER_TNZ
    from massview.lod.clusters import ClusterParams
    from massview.systems.reliefboards import ReliefboardOptions

    assert DEFAULT_TNZ == round(PAPER_TNZ * MACHINE_RATE / PAPER_RATE) == 350_000
    assert ReliefboardOptions().policy == BoardPolicy() and ReliefboardOptions().t_nz == DEFAULT_TNZ == ClusterParams().t_nz
    args = build_parser().parse_args(["render", "builtin:objects", "--system", "reliefboards"])
    assert options_from_args(args) == ReliefboardOptions()  # the CLI's defaults are the policy's
    args = build_parser().parse_args(["render", "builtin:objects", "--system", "reliefboards", "--tnz", "7", "--board-px", "16"])
    assert options_from_args(args).policy == BoardPolicy(t_nz=7, p=16) and BoardPolicy(p=16).max_board_px == 32
