"""The generative measurement model of a calibration layout: its Fisher information, its Cramer-Rao
bound, and measurement-level simulation drawn from exactly that model.

A layout is the rig (camera, LiDAR beams, board) with the true extrinsic and the true board poses.
Measurements are the board's corner pixels (independent Gaussian, ``corner_noise_px`` per axis) and
the ranges of the LiDAR beams that hit the board (independent Gaussian along the beam,
``range_noise_m``). The parameters are ``T_camera_lidar`` and every ``T_camera_board``, perturbed in
GTSAM's right tangent; the bound on the extrinsic is the Schur complement of the full information.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from geometry.board import BoardModel
from geometry.camera import CameraModel
from geometry.rotations import T_inverse, transform_points

from ..camera.board_pose import estimate_board_pose
from ..camera.chessboard import CornerDetection
from ..lidar.lidar_models import BeamModel
from ..measurements import FrameMeasurement, observe_lidar_board, observe_lidar_line
from ..simulation.scene import cast, rectangle
from .factors import corner_residuals, lidar_plane


@dataclass(frozen=True, eq=False)
class Layout:
    """A rig and a set of board poses: everything the bound and the measurement simulation need."""

    camera: CameraModel
    board: BoardModel
    beams: BeamModel
    T_camera_lidar: np.ndarray
    T_camera_board: tuple[np.ndarray, ...]
    corner_noise_px: float
    range_noise_m: float
    # Measured beams per frame ((dirs, ranges) in the LiDAR frame) instead of the beam model's cast.
    hits: tuple | None = None

    @property
    def n_frames(self) -> int:
        return len(self.T_camera_board)


def board_hits(layout: Layout, i: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit beam directions (n, 3) of the LiDAR that hit board ``i`` and their true ranges (n,) (LiDAR
    frame). The board is taken as unoccluded. A layout with measured ``hits`` returns those."""
    if layout.hits is not None:
        return layout.hits[i]
    T_lidar_board = T_inverse(layout.T_camera_lidar) @ layout.T_camera_board[i]
    R, o = T_lidar_board[:3, :3], T_lidar_board[:3, 3]
    w, h = layout.board.extent
    dirs, _ = layout.beams.directions()
    # Only beams within the board's angular box can hit it: cheap pre-selection before the exact cast.
    outline = transform_points(T_lidar_board, layout.board.outline())
    centre = outline.mean(0) / np.linalg.norm(outline.mean(0))
    cos_min = float(np.min((outline / np.linalg.norm(outline, axis=1, keepdims=True)) @ centre))
    near = dirs[dirs @ centre >= cos_min - 1e-9]
    ranges, which, _ = cast(np.zeros(3), near, [rectangle(o, R[:, 0], R[:, 1], w, h, 0.5)], layout.beams.max_range_m)
    hit = which == 0
    return near[hit], ranges[hit]


def corner_pixels(layout: Layout, i: int) -> np.ndarray:
    """True pixels of board ``i``'s inner corners (M, 2), in the board model's row-major order."""
    return layout.camera.project(transform_points(layout.T_camera_board[i], layout.board.inner_corners()))


def frame_information(layout: Layout, i: int) -> np.ndarray:
    """Fisher information (12 x 12) of frame ``i`` over ``[xi_extrinsic, xi_board_i]``."""
    T_cb = layout.T_camera_board[i]
    F = np.zeros((12, 12))
    _, Jc = corner_residuals(T_cb, layout.board.inner_corners(), corner_pixels(layout, i), layout.camera)
    F[6:, 6:] += Jc.T @ Jc / layout.corner_noise_px**2
    dirs, ranges = board_hits(layout, i)
    if len(dirs):
        pi, H_x, H_b = lidar_plane(layout.T_camera_lidar, T_cb)
        P1 = np.hstack([dirs * ranges[:, None], np.ones((len(dirs), 1))])
        # A beam's range rho solves pi . [rho b; 1] = 0, so d rho = -[p; 1] . d pi / (m . b).
        scale = -1.0 / (dirs @ pi[:3])
        J = np.hstack([(P1 @ H_x) * scale[:, None], (P1 @ H_b) * scale[:, None]])
        F += J.T @ J / layout.range_noise_m**2
    return F


def frame_contribution(F_frame: np.ndarray) -> np.ndarray:
    """A frame's 6x6 share of the extrinsic's information: its board pose marginalised (Schur complement).
    Frames have their own board poses, so the extrinsic's information is the sum of these shares."""
    return extrinsic_information(F_frame)


def fisher_information(layout: Layout) -> np.ndarray:
    """Fisher information (6 + 6N square) of ``[xi_extrinsic, xi_board_1, ..., xi_board_N]``."""
    N = layout.n_frames
    F = np.zeros((6 + 6 * N, 6 + 6 * N))
    for i in range(N):
        idx = np.r_[0:6, 6 + 6 * i:12 + 6 * i]
        F[np.ix_(idx, idx)] += frame_information(layout, i)
    return F


def extrinsic_information(F: np.ndarray) -> np.ndarray:
    """The 6x6 information on the extrinsic with the board poses marginalised (Schur complement)."""
    A, B, C = F[:6, :6], F[:6, 6:], F[6:, 6:]
    return A - B @ np.linalg.solve(C, B.T)


def cramer_rao_bound(layout: Layout) -> np.ndarray:
    """The Cramer-Rao bound (6x6 covariance, right tangent of ``T_camera_lidar``) of the layout."""
    return np.linalg.inv(extrinsic_information(fisher_information(layout)))


def simulate_measurements(layout: Layout, rng: np.random.Generator) -> list[FrameMeasurement]:
    """Per frame: corners with Gaussian pixel noise (board pose fitted as from a detection) and the
    board's beam returns with Gaussian range noise. No rendering, no segmentation."""
    frames = []
    for i in range(layout.n_frames):
        uv = corner_pixels(layout, i)
        uv = uv + rng.normal(0.0, layout.corner_noise_px, uv.shape)
        cam = estimate_board_pose(CornerDetection(uv, "simulated"), layout.board, layout.camera)
        dirs, ranges = board_hits(layout, i)
        if len(dirs) < 3:
            frames.append(FrameMeasurement(f"{i:04d}", cam, None, f"only {len(dirs)} LiDAR beams hit the board"))
            continue
        points = dirs * (ranges + rng.normal(0.0, layout.range_noise_m, len(ranges)))[:, None]
        observe = observe_lidar_line if layout.beams.is_2d else observe_lidar_board
        frames.append(FrameMeasurement(f"{i:04d}", cam, observe(points)))
    return frames
