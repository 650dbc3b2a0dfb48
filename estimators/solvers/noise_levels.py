"""The noise levels of the plane graph: the pooled corner residual and each board's, the pooled range noise, and
the plane factors' noise models (whitened by the range terms, with a per-board plane error and the robust loss).
"""
from __future__ import annotations

import gtsam
import numpy as np

from geometry.board import BoardModel
from geometry.camera import CameraModel

from ..measurements import FrameMeasurement
from . import chi_square as chi2
from .factors import corner_residuals
from .range_model import FrameWhitener
from .refinement_options import RefinementOptions

# A rig weighs each board's corners by that board's own residual (``board_corner_residuals_px``), shrunk towards the
# camera's pooled residual by this many degrees of freedom (a 7 x 10 board's residuals have 134).
BOARD_NOISE_PRIOR_DOF = 30.0

# A sensor's noise is scaled by its chi-square per degree of freedom (quasi-likelihood) only when its factors
# disagree beyond their noise at this level: the single pair's plane test, which estimates a per-board plane error
# there instead (each LiDAR's, carried into the graph by its ``PlaneError``). Scaling every excess, significant or
# not, made the covariance too wide (`make bench`, noise_models.md); a LiDAR whose boards carry no plane error
# has every excess scaled, the only account of it it has. A rig's sensors (``rig_graph.solve_rig``) and a pair's
# boards with range terms (``refinement``, the terms' priors weighed against it) take the same level.
QUASI_LIKELIHOOD_P = 0.01


def excess_scale(stat: float, dof: float) -> float:
    """A chi-square statistic's variance factor ``stat / dof`` when it exceeds its degrees of freedom at
    ``QUASI_LIKELIHOOD_P``, else 1: what a sensor's noise (a pair's terms' priors) is scaled by."""
    return stat / dof if stat > dof and chi2.sf(stat, dof) < QUASI_LIKELIHOOD_P else 1.0


def pooled_corner_residual_px(views, camera: CameraModel) -> float:
    """Pooled per-axis corner residual of board poses (``2M - 6`` dof each); ``views``: ``(T_camera_board,
    corners_board, corners_px)`` per board."""
    return board_corner_residuals_px(views, camera)[0]


def board_corner_residuals_px(views, camera: CameraModel, prior_dof: float = BOARD_NOISE_PRIOR_DOF
                              ) -> tuple[float, list[float]]:
    """The pooled per-axis corner residual (:func:`pooled_corner_residual_px`) and each board's own (its ``2M - 6``
    dof), shrunk towards the pooled one as if the pooled one were ``prior_dof`` more residuals of that board: a
    board's corner noise follows its image (its distance, tilt, blur and light), so a rig weighs each board by its
    own; the shrinkage keeps a board of few corners from a lucky small residual."""
    ss, dofs = [], []
    for T, X, px in views:
        r, _ = corner_residuals(T, X, px, camera, jacobian=False)
        ss.append(float(r @ r))
        dofs.append(max(r.size - 6, 1))
    pooled = float(np.sqrt(sum(ss) / max(sum(dofs), 1)))
    return pooled, [float(np.sqrt((s + prior_dof * pooled**2) / (d + prior_dof))) for s, d in zip(ss, dofs)]


def corner_noise_levels(views, camera: CameraModel, options: RefinementOptions) -> tuple[float, float, list[float]]:
    """The corners' effective pixel noise for the graph: the pooled residual (:func:`board_corner_residuals_px`),
    the camera's effective noise (for a board not recorded) and each board's, both the residuals times
    ``options.corner_error_correlation``; or ``options.corner_noise_px`` for every board when given."""
    views = list(views)
    pooled, per_board = board_corner_residuals_px(views, camera)
    if options.corner_noise_px:
        return pooled, options.corner_noise_px, [options.corner_noise_px] * len(views)
    k = options.corner_error_correlation
    return pooled, max(pooled, 1e-3) * k, [max(v, 1e-3) * k for v in per_board]


def corner_residual_px(frames: list[FrameMeasurement], board: BoardModel, camera: CameraModel) -> float:
    """Pooled per-axis corner residual of the frames' board poses (:func:`pooled_corner_residual_px`)."""
    return pooled_corner_residual_px(((f.camera.T_camera_board, f.camera.corners_board(board), f.camera.corners_px)
                                      for f in frames), camera)


def own_fit_residuals(obs) -> tuple[float, int]:
    """A LiDAR board observation's squared range residuals about its own best-fit plane (a scan line's: its line)
    (m^2) and their degrees of freedom (``n - 3``; ``n - 2`` for a scan line)."""
    dof = max(obs.n_points - (2 if obs.is_scan_line else 3), 1)
    return obs.range_rms_m**2 * dof, dof


def pooled_range_noise_m(observations: list) -> float:
    """Range noise pooled over LiDAR board observations' best-fit plane residuals (:func:`own_fit_residuals`)."""
    ss, dof = np.sum([own_fit_residuals(o) for o in observations], axis=0)
    return float(np.sqrt(ss / dof))


def _threshold(options: RefinementOptions, dof: int) -> float:
    """The robust loss's threshold for a residual of ``dof`` dimensions: ``robust_threshold`` is set for a
    plane's 3 (a range model's factors have more, and would be cut at their typical size otherwise)."""
    return options.robust_threshold * float(np.sqrt(chi2.ppf(0.99, max(dof, 3)) / chi2.ppf(0.99, 3)))


def robust_noise(noise: gtsam.noiseModel.Base, options: RefinementOptions, dof: int = 3) -> gtsam.noiseModel.Base:
    k = _threshold(options, dof)
    if options.robust == "huber":
        return gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(k), noise)
    if options.robust == "cauchy":
        return gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Cauchy.Create(k), noise)
    return noise


def robust_weight(e_norm: float, options: RefinementOptions, dof: int = 3) -> float:
    k = _threshold(options, dof)
    if options.robust == "huber":
        return 1.0 if e_norm <= k else k / e_norm
    if options.robust == "cauchy":
        return 1.0 / (1.0 + (e_norm / k) ** 2)
    return 1.0


def plane_noise(W: np.ndarray, normal: np.ndarray, sigma_r: float, floor_m: float, half_size_m: float,
                 scale_m: float = 0.0, centre: np.ndarray | None = None) -> np.ndarray:
    """Covariance of a plane factor's residual ``W pi``: the points' range noise, plus a per-board plane
    error when the data call for one (the board tilted about its centre by ``floor_m`` over its half-size and
    moved along its normal by ``floor_m``: a bent or held board, imperfect intrinsics), plus the distance error
    ``scale_m`` of the camera's board from a scale error of its detected pattern. ``centre``: the board points'
    centroid (LiDAR frame); without it the tilt is about the foot of the perpendicular from the sensor."""
    cov = sigma_r**2 * np.eye(W.shape[0])
    if floor_m > 0 or scale_m > 0:
        S = np.zeros((4, 4))
        S_nn = (np.eye(3) - np.outer(normal, normal)) * (floor_m / half_size_m) ** 2
        S[:3, :3] = S_nn
        S[3, 3] = floor_m**2 + scale_m**2
        if centre is not None:  # pi = [n; -d], d = n . c at the centre: a tilt there moves d by dn . c
            S[:3, 3] = S[3, :3] = -S_nn @ centre
            S[3, 3] += float(centre @ S_nn @ centre)
        cov = cov + W @ S @ W.T
    return cov


def frame_noise(fw: FrameWhitener, normal: np.ndarray, sigma_r: float, floor_m: float, half_size_m: float,
                scale_m: float = 0.0, tau_m: float = 0.0) -> np.ndarray:
    """Covariance of a frame's whitened LiDAR residual (:func:`plane_noise`). In the range model's form
    (``fw.R`` set) the per-board plane error acts on the board's own plane (its tilt about its centre,
    ``floor_m`` at the board's edge, and its distance), and ``tau_m`` is the scatter of the board's own offset
    along its weak direction (``fw.weak``: its distance and offsets trading, told apart only by incidence
    across the board)."""
    if fw.R is None:
        return plane_noise(fw.W, normal, sigma_r, floor_m, half_size_m, scale_m, fw.centre)
    k = fw.R.shape[1]
    V = np.zeros((k, k))
    s2 = (floor_m / half_size_m) ** 2
    V[:fw.nt, :fw.nt] = s2 * np.eye(fw.nt)
    V[fw.nt, fw.nt] = floor_m**2 + scale_m**2
    if fw.centre is not None and fw.tangent is not None:  # a tilt about the centre moves d by (T dt) . c
        g = fw.tangent.T @ fw.centre
        V[:fw.nt, fw.nt] = V[fw.nt, :fw.nt] = s2 * g
        V[fw.nt, fw.nt] += s2 * float(g @ g)
    Rv = fw.R @ fw.weak
    return sigma_r**2 * np.eye(fw.R.shape[0]) + fw.R @ V @ fw.R.T + tau_m**2 * np.outer(Rv, Rv)
