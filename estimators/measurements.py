"""Per-frame measurements: the board seen by the camera and by the LiDAR (frozen records)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from geometry.planes import Plane, fit_plane_pca, moment_matrix, sqrt_excess_moment


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
    """The board's points and plane in the LiDAR frame (the sensor at the origin).

    ``moment`` is ``sum [p; 1][p; 1]^T`` over the inlier points: the exact sufficient statistics of
    every point-to-plane sum of squares. ``range_moment`` weighs each point by ``1 / cos^2`` of its
    beam's incidence on the fitted plane, so that its plane cost is a sum of squared *range* errors:
    LiDAR noise acts along the beam (MATH.md section 2). ``range_rms_m`` is the range noise that the
    best-fitting plane leaves (``n - 3`` degrees of freedom).

    The points carry their range noise in every coordinate, not only across the plane, so the expected
    moment holds a noise term ``sigma^2 sum w b b^T`` (``b`` the unit beams) that would bias the plane
    (and the extrinsic's rotation) by order ``sigma^2``; ``beam_moment = sum w b b^T`` lets
    :meth:`unbiased_range_moment` remove it (adjusted least squares).
    """

    points: np.ndarray
    plane: Plane
    moment: np.ndarray
    range_moment: np.ndarray
    beam_moment: np.ndarray
    plane_rms_m: float
    range_rms_m: float
    candidates: int

    @property
    def n_points(self) -> int:
        return int(len(self.points))

    def unbiased_range_moment(self, sigma_range_m: float) -> np.ndarray:
        """``range_moment`` less its expected noise term for range noise ``sigma_range_m``."""
        M = self.range_moment.copy()
        M[:3, :3] -= sigma_range_m**2 * self.beam_moment
        return M


# Beams more oblique than this to the board (cos of incidence) are weighed as if at this angle.
MIN_INCIDENCE_COS = 0.1


def observe_lidar_board(points: np.ndarray, candidates: int = 1) -> LidarBoardObservation:
    """The observation record of a board's inlier points (LiDAR frame, the sensor at the origin)."""
    P = np.asarray(points, dtype=float)
    plane = fit_plane_pca(P)
    r = plane.signed_distances(P)
    beams = P / np.linalg.norm(P, axis=1, keepdims=True)
    cos = np.maximum(np.abs(beams @ plane.normal), MIN_INCIDENCE_COS)
    w = 1.0 / cos**2
    range_moment = moment_matrix(P, w)
    _, floor = sqrt_excess_moment(range_moment)
    dof = max(len(P) - 3, 1)
    return LidarBoardObservation(points=P, plane=plane, moment=moment_matrix(P), range_moment=range_moment,
                                 beam_moment=(beams * w[:, None]).T @ beams,
                                 plane_rms_m=float(np.sqrt(np.mean(r**2))), range_rms_m=float(np.sqrt(max(floor, 0.0) / dof)),
                                 candidates=candidates)


@dataclass(frozen=True, eq=False)
class FrameMeasurement:
    name: str
    camera: CameraBoardObservation | None
    lidar: LidarBoardObservation | None
    reason: str | None = None

    @property
    def usable(self) -> bool:
        return self.camera is not None and self.lidar is not None
