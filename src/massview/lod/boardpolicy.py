"""What the visualization rank draws and requests each frame (Süß et al. 2010, §6.1).

Pure numpy over per-object arrays, so every decision is a function of (camera, skeleton, board
table) and can be tested without GL or MPI:

1. Infeasible objects in the frustum are drawn as originals; their triangles count toward t_nz.
2. Feasible objects in the frustum, front to back by centre distance, are drawn as originals
   while the running triangle count stays within t_nz — the near zone. The first object that
   would exceed it ends the near zone.
3. Every other feasible object in the frustum (the far zone) is drawn from its board if one has
   arrived and its angle error — the angle between the board's creation direction and the
   current direction from the observer to the object's centre — is below E; else as original.
4. A far object gets a request when it has no board, when its angle error exceeds ε, or when its
   projected side length differs from the board's resolution by more than the size threshold
   (relative to the board's) — unless a request for it is already pending (never two). Requests
   are issued front to back and carry (object, direction, projected size in pixels).

The projected size is the projected diameter of the object's bounding sphere,
``2 · radius · r_y / (2 · distance · tan(fovy/2))`` pixels, clamped to
``[min_board_px, max_board_px]`` (a feasible object beyond d_nz projects to about p = 128
pixels a side at most; its bounding sphere to up to √3·p, hence the cap of 2·p).

**t_nz at this machine's scale** (the one place it is defined; the README and
``massview bench reliefboards`` cite it): the paper draws t_nz = 3.5 M triangles in the near
zone (§7.2) on a visualization node that draws about :data:`PAPER_RATE` = 120 M triangles/s (its
60 M-triangle forest at about 2 fps all-original, §7.5). Here the visualization rank draws with
llvmpipe on 2 CPU cores, nominally :data:`MACHINE_RATE` = 12 M triangles/s at 1024×768 (5–15 M
measured idle; the bench measures and prints it). Triangle budgets scale by the rate ratio::

    t_nz = 3.5 M · MACHINE_RATE / PAPER_RATE = 3.5 M / 10 = 350 000        (:data:`DEFAULT_TNZ`)

and the bench scales its forests' triangle counts by the same factor, :func:`machine_scale`. Its
plant runs unscaled (12.4 M triangles, t_nz = 3.5 M): a board's cost is per pixel, so scaling
triangles but not pixels makes §4's clusters cost no more than their boards (the bench's
docstring gives the ratio, t_nz / 1.72 M at 1024×768).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..core.camera import Camera
from ..core.errors import ConfigError
from .cull import spheres_in_frustum
from .reliefboard import angle_error_deg

__all__ = ["BoardPolicy", "FramePlan", "plan_frame", "projected_size_px", "PAPER_TNZ", "PAPER_RATE", "MACHINE_RATE",
           "DEFAULT_TNZ", "machine_scale", "scaled_tnz"]

PAPER_TNZ = 3_500_000  # triangles, §7.2
PAPER_RATE = 120e6  # triangles/s of the paper's visualization node: 60 M triangles at ~2 fps all-original (§7.5)
MACHINE_RATE = 12e6  # triangles/s of llvmpipe on this machine's 2 cores at 1024x768 (nominal; 5-15 M measured idle)


def machine_scale(rate: float = MACHINE_RATE) -> float:
    """The factor that maps the paper's triangle counts to a machine drawing ``rate`` triangles/s."""
    return float(rate) / PAPER_RATE


def scaled_tnz(rate: float = MACHINE_RATE) -> int:
    """t_nz for a machine drawing ``rate`` triangles/s: 3.5 M · rate / 120 M."""
    return max(1, int(round(PAPER_TNZ * machine_scale(rate))))


DEFAULT_TNZ = scaled_tnz()  # 350 000


@dataclass(frozen=True)
class BoardPolicy:
    """§6.1/§7.2 parameters, the single source of M2's defaults: ε and E in degrees, the
    relative size threshold, t_nz triangles (:data:`DEFAULT_TNZ`, the paper's 3.5 M scaled to
    this machine), p the largest projected board side in pixels (the paper gives none: 128);
    requested board sizes are clamped to ``[min_board_px, 2·p]``."""

    epsilon_deg: float = 11.5
    max_error_deg: float = 45.0
    size_threshold: float = 0.30
    t_nz: int = DEFAULT_TNZ
    p: int = 128
    min_board_px: int = 4

    @property
    def max_board_px(self) -> int:
        """The largest board resolution requested: 2·p (a bounding sphere projects to up to √3·p)."""
        return max(self.min_board_px, 2 * self.p)

    def __post_init__(self) -> None:
        if not 0 < self.epsilon_deg <= self.max_error_deg <= 180:
            raise ConfigError(f"need 0 < epsilon <= E <= 180 degrees, got epsilon={self.epsilon_deg} E={self.max_error_deg}")
        if not self.size_threshold > 0:
            raise ConfigError(f"size threshold must be positive, got {self.size_threshold}")
        if self.t_nz < 0:
            raise ConfigError(f"--tnz must be non-negative, got {self.t_nz}")
        if self.p < 1:
            raise ConfigError(f"--board-px must be at least 1 pixel, got {self.p}")
        if self.min_board_px < 2:
            raise ConfigError(f"the smallest board side must be at least 2 pixels, got {self.min_board_px}")


@dataclass(frozen=True)
class FramePlan:
    """One frame's decision; index arrays are int64 object ids.

    infeasible, near, far_original, far_board: what is drawn how; angle_error: (len(far_board),)
    degrees of the boards drawn; requests: ids to request, front to back, with directions
    (k, 3) float64 unit (observer → centre) and sizes (k,) int pixels; near_triangles:
    triangles of infeasible + near objects."""

    infeasible: np.ndarray
    near: np.ndarray
    far_original: np.ndarray
    far_board: np.ndarray
    angle_error: np.ndarray
    requests: np.ndarray
    request_dirs: np.ndarray
    request_sizes: np.ndarray
    near_triangles: int


def projected_size_px(camera: Camera, centers: np.ndarray, radii: np.ndarray, policy: BoardPolicy) -> np.ndarray:
    """(n,) int projected bounding-sphere diameter in pixels, clamped to the policy's bounds."""
    dist = np.maximum(np.linalg.norm(centers - np.asarray(camera.position), axis=1), 1e-9)
    px = radii * camera.height / (dist * math.tan(math.radians(camera.fovy) / 2))
    return np.clip(np.round(px), policy.min_board_px, policy.max_board_px).astype(np.int64)


def plan_frame(camera: Camera, centers, radii, triangles, feasible, board_dir, board_size, pending,
               policy: BoardPolicy) -> FramePlan:
    """The §6.1 decision for one frame.

    centers (n, 3), radii (n,) float64 bounding spheres; triangles (n,) int64; feasible (n,)
    bool; board_dir (n, 3) float64 creation direction of the resident board (NaN rows: none);
    board_size (n,) int resolution of the resident board (0: none); pending (n,) bool."""
    centers, radii = np.asarray(centers, np.float64), np.asarray(radii, np.float64)
    triangles = np.asarray(triangles, np.int64)
    vis = np.nonzero(spheres_in_frustum(centers, radii, camera.frustum_planes()))[0]
    infeasible = vis[~feasible[vis]]
    cand = vis[feasible[vis]]
    to_obj = centers[cand] - np.asarray(camera.position)
    order = np.argsort(np.linalg.norm(to_obj, axis=1), kind="stable")
    cand, to_obj = cand[order], to_obj[order]
    base = int(triangles[infeasible].sum())
    within = base + np.cumsum(triangles[cand]) <= policy.t_nz
    n_near = int(np.argmin(within)) if not within.all() else len(cand)
    near, far, far_dir = cand[:n_near], cand[n_near:], to_obj[n_near:]
    far_dir = far_dir / np.maximum(np.linalg.norm(far_dir, axis=1, keepdims=True), 1e-12)
    has = board_size[far] > 0
    err = np.full(len(far), np.inf)
    if has.any():
        err[has] = angle_error_deg(board_dir[far[has]], far_dir[has])
    size = projected_size_px(camera, centers[far], radii[far], policy)
    with np.errstate(divide="ignore", invalid="ignore"):
        size_change = np.abs(size - board_size[far]) / np.where(has, board_size[far], 1)
    use_board = has & (err < policy.max_error_deg)
    want = ~has | (err > policy.epsilon_deg) | (size_change > policy.size_threshold)
    ask = want & ~pending[far]
    return FramePlan(infeasible, near, far[~use_board], far[use_board], err[use_board], far[ask], far_dir[ask],
                     size[ask], base + int(triangles[near].sum()))
