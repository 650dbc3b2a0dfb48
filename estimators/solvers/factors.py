"""The factors of the calibration graph, as numpy residuals with analytic Jacobians and as GTSAM factors.

Variables are ``gtsam.Pose3``: the extrinsic ``T_camera_lidar`` and one ``T_camera_board`` per frame.
Jacobians are taken in GTSAM's right (body) tangent, ``T Exp(xi)`` with ``xi = [rot; trans]``
(MATH.md sections 2, 3 and 6).

- Corner factor (one per frame): projected minus detected board corners through the dataset's camera
  model, ``2M`` residuals in pixels; with the intrinsics as a second (vector) variable when they are refined.
- Plane factor (one per frame): ``W pi`` with ``pi = [R^T n; n . t - d]`` the camera's board plane
  (``n = R_b e3``, ``d = n . t_b``) mapped into the LiDAR frame and ``W`` the square root of the board
  points' excess moment (:func:`geometry.planes.sqrt_excess_moment`), so that ``|W pi|^2`` plus a
  constant is exactly the sum of squared point-to-plane (or range) errors of all the board's points.
  Serves 2D scans unchanged (``W`` then has rank 2 or 3).
- Plane factor with range terms: the same over ``[pi; beta]``, ``beta`` the LiDAR range model's nuisance
  vector (a third variable; ``solvers.range_model``): ``W [s pi; S beta] + e0``.
"""
from __future__ import annotations

from functools import partial

import gtsam
import numpy as np

from geometry.camera import CameraModel


def corner_residuals(T_camera_board: np.ndarray, corners_board: np.ndarray, corners_px: np.ndarray,
                     camera: CameraModel, jacobian: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
    """Projected minus detected corners (2M,) in pixels, and their Jacobian (2M, 6) by the board pose
    (None when ``jacobian`` is False)."""
    r, H, _ = corner_residuals_intrinsics(T_camera_board, corners_board, corners_px, camera, jacobian)
    return r, H


def corner_residuals_intrinsics(T_camera_board: np.ndarray, corners_board: np.ndarray, corners_px: np.ndarray,
                                camera: CameraModel, jacobian: bool = True
                                ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Projected minus detected corners (2M,) in pixels, and their Jacobians by the board pose (2M, 6) and by
    the camera's :attr:`~geometry.camera.CameraModel.params` (2M, P) (None when ``jacobian`` is False)."""
    R, t = T_camera_board[:3, :3], T_camera_board[:3, 3]
    X = np.asarray(corners_board, dtype=float)
    uv, duv_dp, duv_dk = camera.project_jacobians(X @ R.T + t)
    r = (uv - corners_px).ravel()
    if not jacobian:
        return r, None, None
    # d(point)/d xi for R Exp(w) X + t + R v is [-R [X]x, R]; with A = d uv/d point R, each row a of
    # A [X]x is (a x X)^T, so the rotation block is X x a row by row (written out, on the 2M rows as one
    # 2-D array: np.cross and 3-D broadcasting are slow at this size, and the graph calls this per evaluation).
    A = duv_dp.reshape(-1, 3) @ R
    x, y, z = np.repeat(X, 2, axis=0).T
    H = np.empty((len(A), 6))
    H[:, 0] = y * A[:, 2] - z * A[:, 1]
    H[:, 1] = z * A[:, 0] - x * A[:, 2]
    H[:, 2] = x * A[:, 1] - y * A[:, 0]
    H[:, 3:] = A
    return r, H, duv_dk.reshape(len(r), -1)


def lidar_plane(T_camera_lidar: np.ndarray, T_camera_board: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The board plane ``pi = [m; -d_l]`` in the LiDAR frame, and its Jacobians (4, 6) by the extrinsic
    and by the board pose."""
    R, t = T_camera_lidar[:3, :3], T_camera_lidar[:3, 3]
    Rb = T_camera_board[:3, :3]
    n = Rb[:, 2]
    dt = t - T_camera_board[:3, 3]
    m = n @ R
    pi = np.empty(4)
    pi[:3] = m
    pi[3] = n @ dt
    # [m]x and d n / d w_b = -Rb [e3]x (columns -Rb[:, 1], Rb[:, 0], 0) written out element by element: the graph
    # calls this per evaluation, and a skew matrix built and copied in took a third of its time
    mx, my, mz = m
    H_x = np.zeros((4, 6))
    H_x[0, 1], H_x[0, 2], H_x[1, 0], H_x[1, 2], H_x[2, 0], H_x[2, 1] = -mz, my, mz, -mx, -my, mx
    H_x[3, 3:] = m
    H_b = np.zeros((4, 6))
    H_b[:3, 0] = -(Rb[:, 1] @ R)
    H_b[:3, 1] = Rb[:, 0] @ R
    H_b[3, 0] = -(dt @ Rb[:, 1])
    H_b[3, 1] = dt @ Rb[:, 0]
    H_b[3, 5] = -1.0
    return pi, H_x, H_b


def lidar_residual(W: np.ndarray, pi: np.ndarray, scan_line: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """The whitened LiDAR residual of plane ``pi`` and its Jacobian by ``pi``: ``W pi`` for a board's
    points on a plane; ``W pi / |n_xy|`` for a 2D scan line (in-scan-plane residuals; see
    ``geometry.planes.sqrt_excess_moment_scan``)."""
    e = W @ pi
    if not scan_line:
        return e, W
    g = float(np.hypot(pi[0], pi[1]))
    dg = np.array([pi[0], pi[1], 0.0, 0.0]) / g
    return e / g, W / g - np.outer(e, dg) / g**2


def nuisance_residual(W: np.ndarray, S: np.ndarray, m_away: np.ndarray, pi: np.ndarray, beta: np.ndarray,
                      scan_line: bool = False, e0: np.ndarray | None = None
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The whitened LiDAR residual with range nuisance terms (``solvers.range_model``):
    ``W [s pi (/ |n_xy|); S beta] + e0`` with ``s`` orienting the plane like the fitted one and ``S`` the
    frame's own terms from the shared ones, and its Jacobians by ``pi`` (k x 4) and by ``beta`` (k x K)."""
    e, de = lidar_residual(W[:, :4], pi, scan_line)
    s = 1.0 if float(pi[:3] @ m_away) >= 0 else -1.0
    H_beta = W[:, 4:] @ S if S.size else np.zeros((W.shape[0], len(beta)))
    r = s * e + H_beta @ beta
    return (r if e0 is None else r + e0), s * de, H_beta


def _pose(values: gtsam.Values, key: int) -> np.ndarray:
    return values.atPose3(key).matrix()


def _corner_error(corners_board, corners_px, camera, this, values, H):
    r, J = corner_residuals(_pose(values, this.keys()[0]), corners_board, corners_px, camera, H is not None)
    if H is not None:
        H[0] = J
    return r


def _corner_intrinsics_error(corners_board, corners_px, camera, this, values, H):
    keys = this.keys()
    cam = camera.with_params(values.atVector(keys[1]))
    r, J, J_k = corner_residuals_intrinsics(_pose(values, keys[0]), corners_board, corners_px, cam, H is not None)
    if H is not None:
        H[0], H[1] = J, J_k
    return r


def _plane_error(W, scan_line, this, values, H):
    keys = this.keys()
    pi, H_x, H_b = lidar_plane(_pose(values, keys[0]), _pose(values, keys[1]))
    e, de = lidar_residual(W, pi, scan_line)
    if H is not None:
        H[0] = de @ H_x
        H[1] = de @ H_b
    return e


def _nuisance_plane_error(W, S, m_away, e0, scan_line, this, values, H):
    keys = this.keys()
    pi, H_x, H_b = lidar_plane(_pose(values, keys[0]), _pose(values, keys[1]))
    e, de, H_beta = nuisance_residual(W, S, m_away, pi, values.atVector(keys[2]), scan_line, e0)
    if H is not None:
        H[0] = de @ H_x
        H[1] = de @ H_b
        H[2] = H_beta
    return e


def _affine_plane_error(W, m_away, e0, scan_line, this, values, H):
    keys = this.keys()
    pi, H_x, H_b = lidar_plane(_pose(values, keys[0]), _pose(values, keys[1]))
    e, de, _ = nuisance_residual(W, np.zeros((0, 0)), m_away, pi, np.zeros(0), scan_line, e0)
    if H is not None:
        H[0] = de @ H_x
        H[1] = de @ H_b
    return e


def corner_factor(key_board: int, corners_board: np.ndarray, corners_px: np.ndarray, camera: CameraModel,
                  noise: gtsam.noiseModel.Base) -> gtsam.CustomFactor:
    corners_px = np.asarray(corners_px, dtype=float).reshape(-1, 2)
    return gtsam.CustomFactor(noise, [key_board], partial(_corner_error, np.asarray(corners_board, dtype=float),
                                                          corners_px, camera))


def corner_intrinsics_factor(key_board: int, key_intrinsics: int, corners_board: np.ndarray, corners_px: np.ndarray,
                             camera: CameraModel, noise: gtsam.noiseModel.Base) -> gtsam.CustomFactor:
    """The corner factor with the camera's intrinsics (``[fx, fy, cx, cy, dist...]``, a vector variable) free:
    ``camera`` gives the model, the image size and the skew."""
    corners_px = np.asarray(corners_px, dtype=float).reshape(-1, 2)
    return gtsam.CustomFactor(noise, [key_board, key_intrinsics],
                              partial(_corner_intrinsics_error, np.asarray(corners_board, dtype=float), corners_px,
                                      camera))


def plane_factor(key_extrinsic: int, key_board: int, W: np.ndarray, noise: gtsam.noiseModel.Base,
                 scan_line: bool = False) -> gtsam.CustomFactor:
    return gtsam.CustomFactor(noise, [key_extrinsic, key_board],
                              partial(_plane_error, np.asarray(W, dtype=float), scan_line))


def nuisance_plane_factor(key_extrinsic: int, key_board: int, key_range: int, W: np.ndarray, S: np.ndarray,
                          m_away: np.ndarray, e0: np.ndarray, noise: gtsam.noiseModel.Base, scan_line: bool = False
                          ) -> gtsam.CustomFactor:
    """The plane (or scan-line) factor with the range model's nuisance vector as a third variable."""
    return gtsam.CustomFactor(noise, [key_extrinsic, key_board, key_range],
                              partial(_nuisance_plane_error, np.asarray(W, dtype=float), np.asarray(S, dtype=float),
                                      np.asarray(m_away, dtype=float), np.asarray(e0, dtype=float), scan_line))


def affine_plane_factor(key_extrinsic: int, key_board: int, W: np.ndarray, m_away: np.ndarray, e0: np.ndarray,
                        noise: gtsam.noiseModel.Base, scan_line: bool = False) -> gtsam.CustomFactor:
    """The plane (or scan-line) factor in the range model's form without terms: ``W s pi + e0``."""
    return gtsam.CustomFactor(noise, [key_extrinsic, key_board],
                              partial(_affine_plane_error, np.asarray(W, dtype=float), np.asarray(m_away, dtype=float),
                                      np.asarray(e0, dtype=float), scan_line))
