"""The board's pose in the camera frame from its corners, with a covariance from the residuals.

IPPE on undistorted corners gives the start; Gauss-Newton on the pixel reprojection error through the
full camera model (pinhole or fisheye) refines it. The pose covariance is ``s^2 (J^T J)^-1`` with
``s^2`` the residual variance (2M - 6 degrees of freedom), in the right tangent of ``T_camera_board``.
"""
from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np

from geometry.board import BoardModel
from geometry.camera import CameraModel
from geometry.planes import Plane
from geometry.rotations import R_from_rotvec, T_from_Rt, T_retract, skew, skew_batch, transform_points

from ..errors import AmbiguousOrientationError, MeasurementError
from ..measurements import CameraBoardObservation
from .charuco import spans_plane
from .detection import CornerDetection


def reprojection_residuals(T_camera_board: np.ndarray, corners_board: np.ndarray, camera: CameraModel,
                           corners_px: np.ndarray) -> np.ndarray:
    """Projected minus detected corners, flattened (2M,) pixels."""
    uv = camera.project(transform_points(T_camera_board, corners_board))
    return (uv - corners_px).ravel()


def _pose_jacobian(T: np.ndarray, corners_board: np.ndarray, camera: CameraModel) -> np.ndarray:
    """d residuals / d xi (2M x 6) under ``T Exp(xi)``: the camera model's own projection derivative (OpenCV's)
    times d point / d xi = [-R [X]x, R]."""
    R = T[:3, :3]
    _, d_uv = camera.project_jacobian(transform_points(T, corners_board))  # (M, 2, 3)
    d_point = np.empty((len(corners_board), 3, 6))
    d_point[:, :, :3] = -R @ skew_batch(corners_board)
    d_point[:, :, 3:] = R
    return (d_uv @ d_point).reshape(-1, 6)


def _ippe_starts(corners_board: np.ndarray, camera: CameraModel, corners: np.ndarray) -> list[np.ndarray]:
    """IPPE's poses of a planar target, best first: two where the target's orientation is ambiguous in the
    image (the two tilts that foreshorten it alike), else one."""
    xy = camera.normalized_from_pixels(corners)
    try:
        n, rvecs, tvecs, _ = cv2.solvePnPGeneric(corners_board, xy.reshape(-1, 1, 2), np.eye(3), None,
                                                 flags=cv2.SOLVEPNP_IPPE)
    except cv2.error:
        n = 0
    if not n:
        raise MeasurementError("PnP failed on the detected corners")
    return [T_from_Rt(R_from_rotvec(np.asarray(r).ravel()), np.asarray(t).ravel()) for r, t in zip(rvecs, tvecs)]


# The board's other IPPE pose, refined, is a second explanation of its corners. When its chi-square exceeds the
# best pose's by less than this (its likelihood more than 1% of the best's), the corners do not say which way
# the board is tilted: a board small or far in the image. Measured on simulated 2D layouts (boards of 3x3 to
# 4x6 inner corners up to 8 m away): every wrongly oriented pose (7 of 1400 boards, 30-70 degrees off) had
# a difference under 8, at 0.2 px corner noise; boards 1.5-4 m away never came near.
POSE_AMBIGUITY_CHI2 = 9.0


def plane_jacobian(T_camera_board: np.ndarray) -> np.ndarray:
    """d[n; d] / d xi (4x6) for the board plane ``n = R e3, d = n . t`` under ``T Exp(xi)``."""
    R, t = T_camera_board[:3, :3], T_camera_board[:3, 3]
    e3 = np.array([0.0, 0.0, 1.0])
    dn_dw = -R @ skew(e3)
    J = np.zeros((4, 6))
    J[:3, :3] = dn_dw
    J[3, :3] = t @ dn_dw
    J[3, 3:] = e3
    return J


def _gauss_newton(T: np.ndarray, X: np.ndarray, camera: CameraModel, corners: np.ndarray, iterations: int
                  ) -> np.ndarray:
    for _ in range(iterations):
        r = reprojection_residuals(T, X, camera, corners)
        J = _pose_jacobian(T, X, camera)
        if not (np.all(np.isfinite(r)) and np.all(np.isfinite(J))):
            raise MeasurementError("the board pose does not converge (corners project behind the camera)")
        step = np.linalg.lstsq(J, -r, rcond=None)[0]
        T = T_retract(T, step)
        if np.linalg.norm(step) < 1e-10:
            break
    return T


def estimate_board_pose(detection: CornerDetection, board: BoardModel, camera: CameraModel,
                        iterations: int = 10) -> CameraBoardObservation:
    corners = np.asarray(detection.corners_px, dtype=float)
    ids = detection.corner_ids
    X = board.inner_corners() if ids is None else board.inner_corners()[ids]
    T = _ippe_starts(X, camera, corners)[0]
    squares = detection.square_gray
    if T[:3, 2] @ T[:3, 3] < 0:
        if ids is not None:  # ids fix the board frame: seen from behind is a wrong detection
            raise MeasurementError("the ChArUco corners put the board's printed side away from the camera")
        # The detector ordered the grid mirror-wise (board z towards the camera): reverse its rows so
        # that the board frame is right-handed with z pointing away from the camera, and solve again.
        cols, rows = board.inner_corners_shape
        corners = corners.reshape(rows, cols, 2)[::-1].reshape(-1, 2)
        squares = squares[::-1] if squares is not None else None
        T = _ippe_starts(X, camera, corners)[0]
    T = _gauss_newton(T, X, camera, corners, iterations)
    method = detection.method
    if ids is not None:
        # A ChArUco corner is interpolated from the markers near it, so a wrongly decoded or half-hidden
        # marker can put a corner pixels away from the grid the others agree on: such corners are dropped
        # (beyond 4x the median residual and 1 px) while enough remain to span the board.
        for _ in range(3):
            norms = np.linalg.norm(reprojection_residuals(T, X, camera, corners).reshape(-1, 2), axis=1)
            keep = norms <= max(1.0, 4.0 * float(np.median(norms)))
            if keep.all() or not spans_plane(board, ids[keep]):
                break
            ids, X, corners = ids[keep], X[keep], corners[keep]
            method += f", {int((~keep).sum())} outlying corner(s) dropped"
            T = _gauss_newton(T, X, camera, corners, iterations)
    poses = _orientations(T, X, camera, corners, iterations)
    inverted = pattern_inverted(squares, board) if ids is None else False
    if len(poses) > 1:
        (best, _), (other, excess) = poses[0], poses[1]
        angle = float(np.degrees(np.arccos(np.clip(best[:3, 2] @ other[:3, 2], -1.0, 1.0))))
        raise AmbiguousOrientationError(
            f"the board's orientation is ambiguous: a pose tilted {angle:.0f} degrees from the best fits its "
            f"corners nearly as well (chi-square {excess:.1f} worse; the board is small or far in the image)",
            tuple(replace(_observation(P, X, camera, corners, method, ids, e), pattern_inverted=inverted)
                  for P, e in poses),
            hint="hold the board closer to the camera, or use a board with more squares")
    return replace(_observation(poses[0][0], X, camera, corners, method, ids, 0.0), pattern_inverted=inverted)


def follow_board_pose(corners: np.ndarray, board: BoardModel, camera: CameraModel, T_start: np.ndarray,
                      ids: np.ndarray | None = None, iterations: int = 6) -> CameraBoardObservation:
    """The board's pose from its corners (a checkerboard's in the order of ``inner_corners``, or a ChArUco
    board's ``ids``), solved from ``T_start``: the pose in an image just before, as a moving board's images follow
    it. No IPPE start and no test of the other orientation: the pose nearest the one before is the board's."""
    X = board.inner_corners() if ids is None else board.inner_corners()[ids]
    corners = np.asarray(corners, dtype=float)
    T = _gauss_newton(np.asarray(T_start, dtype=float), X, camera, corners, iterations)
    return _observation(T, X, camera, corners, "followed", ids, 0.0)


def pose_of_corners(corners: np.ndarray, board: BoardModel, camera: CameraModel,
                    T_before: np.ndarray | None = None) -> CameraBoardObservation:
    """The board's pose from one image's stored corners (every inner corner's row, NaN for a ChArUco corner not
    seen): followed from ``T_before`` (the pose in an image just before, :func:`follow_board_pose`) where given,
    else solved from the corners alone (:func:`estimate_board_pose`). Raises MeasurementError."""
    corners = np.asarray(corners, dtype=float)
    seen = np.flatnonzero(np.all(np.isfinite(corners), axis=1))
    if len(seen) < 4:  # a pose needs four points at least; none gave a singular solve
        raise MeasurementError(f"{len(seen)} of the board's corners stored for this image")
    ids = None if len(seen) == len(corners) else seen
    if T_before is not None:
        return follow_board_pose(corners[seen], board, camera, T_before, ids)
    return estimate_board_pose(CornerDetection(corners[seen], "moving", ids), board, camera)


def reobserve(obs: CameraBoardObservation, board: BoardModel, camera: CameraModel, iterations: int = 10
              ) -> CameraBoardObservation:
    """The same detected corners observed under another camera model (refined intrinsics): the pose solved again
    from the old one, its plane and covariances anew; detector, corner ids and pattern colours kept."""
    X = obs.corners_board(board)
    T = _gauss_newton(obs.T_camera_board, X, camera, obs.corners_px, iterations)
    new = _observation(T, X, camera, obs.corners_px, obs.detector, obs.corner_ids, obs.orientation_excess_chi2)
    return replace(new, pattern_inverted=obs.pattern_inverted)


def reobserve_frames(frames: list, board: BoardModel, camera: CameraModel) -> list:
    """The frames (``FrameMeasurement``) with their boards' detected corners observed under ``camera`` (refined
    intrinsics, :func:`reobserve`): the board pose and each ambiguous board's alternatives; the LiDAR side kept."""
    return [replace(f, camera=reobserve(f.camera, board, camera) if f.camera is not None else None,
                    camera_alternatives=tuple(reobserve(a, board, camera) for a in f.camera_alternatives))
            for f in frames]


def pattern_inverted(squares: np.ndarray | None, board: BoardModel) -> bool | None:
    """Whether the image shows white where the board model has black (square (0, 0) of the pattern white):
    the mean grey level of the squares between the inner corners that the model makes black against the others'
    (``squares`` in the final corner order; the square between corners (c, r) and (c + 1, r + 1) is the model's
    square (c + 1, r + 1)). None when unknown (no grey levels, or the two groups differ by less than a tenth
    of the image's range)."""
    if squares is None or squares.size < 2:
        return None
    r, c = np.indices(squares.shape)
    model_black = ((c + r) % 2 == 0) == board.first_square_black
    dark, light = float(squares[model_black].mean()), float(squares[~model_black].mean())
    if abs(dark - light) < 25.5:
        return None
    return dark > light


def _observation(T: np.ndarray, X: np.ndarray, camera: CameraModel, corners: np.ndarray, method: str,
                 ids: np.ndarray | None, excess: float) -> CameraBoardObservation:
    """The observation of pose ``T``: its plane, and their covariances from the corner residuals."""
    r = reprojection_residuals(T, X, camera, corners)
    if not np.all(np.isfinite(r)):
        raise MeasurementError("board pose puts corners behind the camera")
    J = _pose_jacobian(T, X, camera)
    dof = max(r.size - 6, 1)
    var_px = float(r @ r) / dof
    try:
        pose_cov = var_px * np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        raise MeasurementError("the board's corners leave its pose undetermined") from None
    n = T[:3, 2]
    plane = Plane(n, n @ T[:3, 3])
    Jp = plane_jacobian(T)
    return CameraBoardObservation(
        corners_px=corners, T_camera_board=T, plane=plane, pose_covariance=pose_cov,
        plane_covariance=Jp @ pose_cov @ Jp.T, reprojection_rms_px=float(np.sqrt(np.mean(r**2) * 2)),
        detector=method, corner_ids=ids, orientation_excess_chi2=float(excess))


def _orientations(T: np.ndarray, X: np.ndarray, camera: CameraModel, corners: np.ndarray, iterations: int
                  ) -> list[tuple[np.ndarray, float]]:
    """The poses that explain the corners, with their chi-square above the best (in units of the corners'
    residual variance at the best), best first: ``T`` or the board's other IPPE pose (refined), whichever fits
    better, and the other too when it is within ``POSE_AMBIGUITY_CHI2`` and tilted at least a degree away. A
    plane from the wrong one would be tens of degrees off while its covariance claims a fraction of a degree."""
    def rss(pose):
        r = reprojection_residuals(pose, X, camera, corners)
        return float(r @ r) if np.all(np.isfinite(r)) else np.inf

    def tilt_deg(a, b):
        return float(np.degrees(np.arccos(np.clip(a[:3, 2] @ b[:3, 2], -1.0, 1.0))))

    poses = [T]
    for start in _ippe_starts(X, camera, corners):
        try:
            other = _gauss_newton(start, X, camera, corners, iterations)
        except MeasurementError:
            continue
        if tilt_deg(other, T) >= 1.0 and other[:3, 2] @ other[:3, 3] > 0:  # distinct, facing the camera
            poses.append(other)
    costs = np.array([rss(p) for p in poses])
    order = np.argsort(costs, kind="stable")
    best, best_rss = poses[order[0]], float(costs[order[0]])
    var_px = max(best_rss / max(corners.size - 6, 1), 1e-12)
    out = [(best, 0.0)]
    for k in order[1:]:
        excess = (costs[k] - best_rss) / var_px
        if tilt_deg(poses[k], best) >= 1.0 and excess < POSE_AMBIGUITY_CHI2 and len(out) < 2:
            out.append((poses[k], float(excess)))
    return out
