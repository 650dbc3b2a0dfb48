"""Per-frame measurements: the board seen by the camera and by the LiDAR (frozen records)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from geometry.planes import Plane


@dataclass(frozen=True, eq=False)
class CameraBoardObservation:
    """The board's pose and plane in the camera frame, from its detected corners.

    ``pose_covariance`` is 6x6 in the right tangent of ``T_camera_board`` (``[rot; trans]``);
    ``plane_covariance`` is 4x4 over ``[normal; distance]`` (rank 3).
    """

    corners_px: np.ndarray
    T_camera_board: np.ndarray
    plane: Plane
    pose_covariance: np.ndarray
    plane_covariance: np.ndarray
    reprojection_rms_px: float
    detector: str


@dataclass(frozen=True, eq=False)
class LidarBoardObservation:
    """The board's points and plane in the LiDAR frame.

    ``moment`` is ``sum [p; 1][p; 1]^T`` over the inlier points: the exact sufficient statistics of
    every point-to-plane sum of squares.
    """

    points: np.ndarray
    plane: Plane
    moment: np.ndarray
    plane_rms_m: float
    candidates: int

    @property
    def n_points(self) -> int:
        return int(len(self.points))


@dataclass(frozen=True, eq=False)
class FrameMeasurement:
    name: str
    camera: CameraBoardObservation | None
    lidar: LidarBoardObservation | None
    reason: str | None = None

    @property
    def usable(self) -> bool:
        return self.camera is not None and self.lidar is not None
