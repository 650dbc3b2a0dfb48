"""Maximum-likelihood refinement of ``T_camera_lidar`` on a GTSAM factor graph, with its covariance.

The graph (MATH.md sections 2, 3, 6): the extrinsic and one board pose per frame; a corner factor per
frame (reprojection through the dataset's camera model) and a plane factor per frame (the board points'
exact sufficient statistics, in range units). Plane factors may carry a robust loss (Huber or Cauchy on
the whitened norm of the frame's 3-vector); frames whose planes disagree with their board beyond the
noise are flagged, and dropped or down-weighted.

Noise levels:
- ``range_noise_m``: given, or pooled from the board points' residuals about their best planes (with range
  terms in the model, about each board's best plane and terms: the structure they explain is not noise).
- ``corner_noise_px``: given, or the pooled corner residual times ``corner_error_correlation``.
  Detected corners err together within a board (blur, perspective and sampling bias the whole
  pattern alike), so the board pose is less certain than the corner scatter suggests; the factor is
  the ratio of the effective per-corner noise (from the spread of board poses against the truth) to
  the corner residual, measured on this toolkit's rendered images by ``make bench``.
- After the fit, the plane-consistency statistic (the part of the cost the camera alone cannot explain:
  how far each board's camera and LiDAR planes disagree, in units of their noise; chi-square with
  ``3 N - 6`` degrees of freedom under the model) is tested. When the model is rejected at 1% (real
  sensors: range biases per laser, imperfect intrinsics), a per-board plane error is added to every
  plane factor, its size estimated so that the statistic equals its degrees of freedom, and the graph
  is solved again: the estimate weighs the boards accordingly and the covariance includes the error.

LiDAR range model (``RefinementOptions.range_model``; ``solvers.range_model``): nuisance terms of the plane
factors (a global offset, per-ring offsets, a black-square offset) in one vector variable with priors from the
LiDAR's range accuracy. Under ``auto`` each block is added while a likelihood-ratio test at 0.1% supports it,
made with the boards' disagreement modelled when they disagree beyond the noise (:func:`_model_test`). Per-ring
and black-square terms that leave the boards inconsistent where the offset alone does not fall back to smaller
combinations. A term beyond 3 prior standard deviations is held at 0 with its prior variance propagated
(:func:`_consider_pinned`); what a plane error of physical size and the boards' scatter leave scales the
covariance (quasi-likelihood).

The covariance is ``gtsam.Marginals`` of the extrinsic, in GTSAM's right tangent: ``T_true = T_hat Exp(xi)``,
``xi = [rot; trans]``.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import gtsam
import numpy as np

from geometry.board import BoardModel
from geometry.camera import CameraModel
from geometry.planes import Plane, plane_difference
from geometry.rotations import T_exp, T_log

from ..errors import DegenerateLayoutError
from ..measurements import FrameMeasurement
from . import chi_square as chi2
from .board_edges import (EDGE_HUBER, MAX_END_OFFSET_M, OUTLINE, SIDE_NORMALS, EndTerms, crossings, edge_factor,
                          edge_residuals, edge_scatter, end_noise, frame_shift, outline_prior, shift_key,
                          shift_prior)
from .chi_square import fdtrc
from .closed_form import MIN_SCAN_NORMAL_SPREAD, describe_direction, normal_spread, solve_closed_form
from .factors import (affine_plane_factor, corner_factor, corner_residuals, lidar_plane, lidar_residual,
                      nuisance_plane_factor, nuisance_residual, plane_factor)
from .outline_check import outline_check, outline_warnings
from .range_model import (CONFOUNDED_CORRELATION, DEFAULT_RANGE_ACCURACY_M, MAX_PRIOR_SIGMAS,
                          MIN_INTENSITY_AGREEMENT, MODEL_TEST_P, RANGE_MODELS, FrameLabels, FrameWhitener,
                          RangeModelFit, RangeTerms, frame_labels, frame_whiteners, terms_for)

ROBUST_LOSSES = ("none", "huber", "cauchy")
OUTLIER_POLICIES = ("drop", "downweight")
# Effective per-corner noise over the corner residual on rendered images, over the board's plane (the part the
# LiDAR planes see): measured by `make bench` (bench_refinement.py (d), 80 varied layouts, 640 boards: 1.28, 90%
# bootstrap 1.21-1.35). It holds every error of the camera's board plane, the corner pattern's scale included.
CORNER_ERROR_CORRELATION = 1.28
# A rig weighs each board's corners by that board's own residual (``board_corner_residuals_px``), shrunk towards the
# camera's pooled residual by this many degrees of freedom (a 7 x 10 board's residuals have 134).
BOARD_NOISE_PRIOR_DOF = 30.0
EXTRINSIC = gtsam.symbol("x", 0)
RANGE = gtsam.symbol("r", 0)  # the LiDAR range model's nuisance vector
# A per-board plane error (m) beyond which the boards' disagreement is not a plane error (a bent or held board,
# intrinsics: millimetres to a centimetre or two): the model test scales by what remains.
MAX_PLANE_ERROR_M = 0.05
# Prior standard deviation (m) that holds a pinned range term at 0 in the graph.
PINNED_SD_M = 1e-7


def board_key(i: int) -> int:
    return gtsam.symbol("b", i)


@dataclass(frozen=True)
class RefinementOptions:
    """Settings of the factor-graph refinement.

    Attributes
    ----------
    robust : str
        The robust loss on each frame's plane residual: ``huber``, ``cauchy`` or ``none``.
    robust_threshold : float
        The loss's threshold on the whitened residual's norm (default: the square root of chi-square(3) at 99%).
    corner_noise_px : float or None
        Effective per-corner pixel noise; None: estimated from the corner residuals.
    corner_error_correlation : float
        The factor by which the pooled corner residual is scaled to the effective noise (detected corners err
        together within a board).
    range_noise_m : float or None
        LiDAR range noise (m); None: estimated from the board points' scatter.
    outliers : str
        ``drop`` or ``downweight`` a frame whose residual is a gross outlier.
    outlier_p : float
        The tail probability below which a frame is a gross outlier.
    plane_floor_m : float or None
        A per-board plane error (m); None: estimated when the planes disagree beyond the noise.
    estimate_plane_floor : bool
        Estimate that plane error from the data.
    max_iterations : int
        The optimiser's iterations at most.
    corner_scale_sd : float
        A per-board relative scale error of the detected pattern, for a camera known to have one.
    range_model : str
        The LiDAR range model: ``none``, ``offset``, ``per-ring``, ``offset+dark``, ``full``, or ``auto`` (chosen by
        test).
    range_accuracy_m : float or None
        The sensor's range accuracy (m, 1 sd of a systematic error) that sets the range terms' priors; None: a
        conservative default.
    edges : bool or None
        Use the board's edges where the rings (a 2D scan's line) leave it; None: a 2D scan's segment ends are used,
        a 3D LiDAR's ring ends only when True.
    max_sensor_separation_m : float or None
        2D: a solution with the sensors farther apart than this (m) is not a solution; None: no bound.
    refine_intrinsics : bool
        Refine the camera's intrinsics with the extrinsic (``solvers.intrinsics_refinement``; :func:`calibrate` and
        :func:`solve` do it, :func:`refine` does not).
    """

    robust: str = "huber"
    # On the whitened norm of a frame's plane residual; sqrt of chi-square(3) at 99%.
    robust_threshold: float = float(np.sqrt(chi2.ppf(0.99, 3)))
    corner_noise_px: float | None = None
    corner_error_correlation: float = CORNER_ERROR_CORRELATION
    range_noise_m: float | None = None
    outliers: str = "drop"
    # Gross outliers only (a wrong segment or a moved board is off by thousands): detected corners have
    # heavy-tailed errors, and dropping a good frame for a 1-in-1000 residual costs more than it saves.
    outlier_p: float = 1e-6
    # Per-board plane error (m): given, or estimated when the planes disagree beyond the noise.
    plane_floor_m: float | None = None
    estimate_plane_floor: bool = True
    max_iterations: int = 100
    # A per-board relative scale error of the detected corner pattern (it moves the board's distance by that
    # fraction), beyond the effective corner noise, for a camera known to have one; the rendered boards' scale
    # error (1e-4) is already part of CORNER_ERROR_CORRELATION.
    corner_scale_sd: float = 0.0
    # The LiDAR range model (``solvers.range_model``): none, offset, per-ring, offset+dark, full, or auto (chosen
    # by test), and the sensor's range accuracy (m, 1 sd of a systematic error) that sets the terms' priors.
    range_model: str = "auto"
    range_accuracy_m: float | None = None  # None: the conservative default (DEFAULT_RANGE_ACCURACY_M)
    # Without the edges, check a 3D estimate by its ring ends (``solvers.outline_check``; off where the estimate
    # only starts another solve, as a rig's pairwise solves).
    outline_check: bool = True
    # The board's edges where the rings (a 2D scan's line) leave it (``solvers.board_edges``), when the board's
    # size is known. None: a 2D scan's segment ends are used (a few scan lines leave directions along the boards
    # that their planes hardly fix), a 3D LiDAR's ring ends only when asked (True).
    edges: bool | None = None
    # 2D: a minimal solution or refined minimum whose sensors are farther apart than this (m) is not a solution
    # (``solution_selection.physical``); None: no bound. ``calibrate`` uses its segmentation parameters' bound.
    max_sensor_separation_m: float | None = 1.0
    refine_intrinsics: bool = False

    def __post_init__(self):
        if self.robust not in ROBUST_LOSSES:
            raise ValueError(f"Expected robust in {ROBUST_LOSSES}, got {self.robust!r}")
        if self.outliers not in OUTLIER_POLICIES:
            raise ValueError(f"Expected outliers in {OUTLIER_POLICIES}, got {self.outliers!r}")
        if self.range_model not in RANGE_MODELS:
            raise ValueError(f"Expected range_model in {RANGE_MODELS}, got {self.range_model!r}")
        for name in ("corner_noise_px", "range_noise_m", "plane_floor_m", "range_accuracy_m",
                     "max_sensor_separation_m"):
            v = getattr(self, name)
            if v is not None and not (np.isfinite(v) and v > 0):
                raise ValueError(f"Expected {name} to be positive, got {v}")


def measurement_model_options(**changes) -> RefinementOptions:
    """Options for frames simulated at the measurement level (``observation_model.simulate_measurements``):
    corners independent at the given noise, no detector scale error."""
    return RefinementOptions(**{"corner_error_correlation": 1.0, "corner_scale_sd": 0.0, **changes})


@dataclass(frozen=True)
class FrameFit:
    """How one frame fits the estimate. ``plane_chi2`` is the frame's plane residual in units of its noise;
    ``consistency_chi2`` adds how far the board moved from the camera's own fit (about chi-square with
    ``plane_dof`` degrees of freedom when all is well; the outlier test uses it)."""

    name: str
    plane_chi2: float
    consistency_chi2: float
    plane_dof: int
    corner_rms_px: float
    weight: float
    outlier: str | None = None
    dropped: bool = False


@dataclass(frozen=True, eq=False)
class Refinement:
    T_camera_lidar: np.ndarray
    covariance: np.ndarray
    T_camera_board: dict
    frames: tuple[FrameFit, ...]
    corner_noise_px: float
    corner_residual_px: float
    range_noise_m: float
    plane_floor_m: float
    variance_factor: float
    consistency_dof: float  # with the edges, their leverage added (``_Problem.edge_leverage``): not whole
    consistency_p: float
    iterations: int
    warnings: tuple[str, ...] = ()
    # The part of ``covariance`` due to intrinsics calibrated from the same images (None when given).
    intrinsics_covariance: np.ndarray | None = None
    corner_scale_sd: float = 0.0
    range_model: RangeModelFit | None = None
    # The board's edges when used (``solvers.board_edges``): ends, growth, per-frame and mean outline shifts and
    # the test of the planes against the edges (:func:`_edges_record`).
    edges: dict | None = None
    # The edges' share of the extrinsic's log-posterior, second order (:func:`_edge_share`): ``(H, eta)``.
    edge_share: tuple[np.ndarray, np.ndarray] | None = None
    # A 2D scan's segment ends and their nuisances at the estimate, which the posterior evaluates exactly
    # (``board_edges.EndTerms``; None without ends or for a 3D LiDAR, whose edges enter as ``edge_share``).
    end_terms: EndTerms | None = None


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


def corner_residual_px(frames: list[FrameMeasurement], board: BoardModel, camera: CameraModel) -> float:
    """Pooled per-axis corner residual of the frames' board poses (:func:`pooled_corner_residual_px`)."""
    return pooled_corner_residual_px(((f.camera.T_camera_board, f.camera.corners_board(board), f.camera.corners_px)
                                      for f in frames), camera)


def own_fit_residuals(f: FrameMeasurement) -> tuple[float, int]:
    """A frame's squared range residuals about its own best-fit plane (a scan line's: its line) (m^2) and their
    degrees of freedom (``n - 3``; ``n - 2`` for a scan line)."""
    dof = max(f.lidar.n_points - (2 if f.lidar.is_scan_line else 3), 1)
    return f.lidar.range_rms_m**2 * dof, dof


def pooled_range_noise_m(frames: list[FrameMeasurement]) -> float:
    """Range noise pooled over the frames' best-fit plane residuals (:func:`own_fit_residuals`)."""
    ss, dof = np.sum([own_fit_residuals(f) for f in frames], axis=0)
    return float(np.sqrt(ss / dof))


def pooled_range_noise_with_terms_m(prob: "_Problem", frames: list[int]) -> float:
    """Range noise pooled over the frames' best fits of their planes and range terms (``prob.fw``): each
    board spends as many degrees of freedom as its plane and terms span (the rank of its fit)."""
    ss = sum(prob.fw[i].floor for i in frames)
    dof = sum(prob.frames[i].lidar.n_points - prob.fw[i].R.shape[0] for i in frames)
    return float(np.sqrt(ss / max(dof, 1)))


def _threshold(options: RefinementOptions, dof: int) -> float:
    """The robust loss's threshold for a residual of ``dof`` dimensions: ``robust_threshold`` is set for a
    plane's 3 (a range model's factors have more, and would be cut at their typical size otherwise)."""
    return options.robust_threshold * float(np.sqrt(chi2.ppf(0.99, max(dof, 3)) / chi2.ppf(0.99, 3)))


def _robust(noise: gtsam.noiseModel.Base, options: RefinementOptions, dof: int = 3) -> gtsam.noiseModel.Base:
    k = _threshold(options, dof)
    if options.robust == "huber":
        return gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(k), noise)
    if options.robust == "cauchy":
        return gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Cauchy.Create(k), noise)
    return noise


def _robust_weight(e_norm: float, options: RefinementOptions, dof: int = 3) -> float:
    k = _threshold(options, dof)
    if options.robust == "huber":
        return 1.0 if e_norm <= k else k / e_norm
    if options.robust == "cauchy":
        return 1.0 / (1.0 + (e_norm / k) ** 2)
    return 1.0


def _plane_noise(W: np.ndarray, normal: np.ndarray, sigma_r: float, floor_m: float, half_size_m: float,
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
    """Covariance of a frame's whitened LiDAR residual (:func:`_plane_noise`). In the range model's form
    (``fw.R`` set) the per-board plane error acts on the board's own plane (its tilt about its centre,
    ``floor_m`` at the board's edge, and its distance), and ``tau_m`` is the scatter of the board's own offset
    along its weak direction (``fw.weak``: its distance and offsets trading, told apart only by incidence
    across the board)."""
    if fw.R is None:
        return _plane_noise(fw.W, normal, sigma_r, floor_m, half_size_m, scale_m, fw.centre)
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


class _Problem:
    """The data of one refinement: per frame its plane whitener, the plane noise, the corner noise, and the
    range model's terms (None: none) with their current values ``beta``."""

    def __init__(self, frames: list[FrameMeasurement], board: BoardModel, camera: CameraModel, sigma_px: float,
                 sigma_r: float, options: RefinementOptions, terms: RangeTerms | None = None,
                 labels: FrameLabels | None = None, edges: list | None = None):
        self.frames, self.board, self.camera = frames, board, camera
        # Per frame, its ring ends used as the board's edges (``solvers.board_edges``; None: planes only), and
        # the edges' shared growth (m) and the scale of their standard deviations.
        self.edges = edges
        self.outline = np.zeros(4)  # the board's outline: sides' growth (x, y) and offset (x, y), m
        self.edge_scale = 1.0
        self.edge_tau = 1e-3  # the boards' in-plane scatter (m), estimated with the edges
        self.solved = None  # the last solve's (graph, values) when a step beyond the first solves again
        self.shifts: dict[int, np.ndarray] = {}
        self.sigma_px, self.sigma_r, self.options = sigma_px, sigma_r, options
        self.terms, self.labels = terms, labels
        # Noise-corrected at the noise the data show (not at a given sigma_r, which sets the weights only).
        self.fw = frame_whiteners(frames, pooled_range_noise_m(frames), terms, labels)
        self.whiteners = [w.W for w in self.fw]
        self.beta = np.zeros(terms.size if terms else 0)
        self.has_beta = bool(terms is not None and terms.size)
        # Scatter (m) of each board's own range terms about the shared ones: estimated when they disagree
        # beyond the noise (biases that vary with range, incidence or temperature, or terms the model lacks).
        self.tau = 0.0
        # Indices of terms held at their prior mean (0): not believed, their prior variance propagated instead.
        self.pinned: tuple[int, ...] = ()
        self.corners_board = [f.camera.corners_board(board) for f in frames]  # the corners each frame saw
        self.pnp_chi2 = [self.corner_chi2(i, f.camera.T_camera_board) for i, f in enumerate(frames)]

    def whitener(self, i: int) -> np.ndarray:
        return self.whiteners[i]

    def nuisance_rank(self, frames: list[int]) -> int:
        """How many combinations of the nuisance terms the frames' points determine."""
        if self.terms is None:
            return 0
        rows = []
        for i in frames:
            rows.append(self.fw[i].W_nuisance if self.fw[i].S.size else np.zeros((self.whiteners[i].shape[0],
                                                                                  self.terms.size)))
        return _rank(np.vstack(rows))

    def residual(self, i: int, T: np.ndarray, T_board: np.ndarray) -> np.ndarray:
        pi, _, _ = lidar_plane(T, T_board)
        scan = self.frames[i].lidar.is_scan_line
        if self.terms is None:
            return lidar_residual(self.whitener(i), pi, scan)[0]
        fw = self.fw[i]
        return nuisance_residual(fw.W, fw.S, fw.m_away, pi, self.beta, scan, fw.e0)[0]

    def plane_cov(self, i: int, floor_m: float) -> np.ndarray:
        f = self.frames[i]
        return frame_noise(self.fw[i], f.lidar.plane.normal, self.sigma_r, floor_m,
                           0.5 * float(np.mean(self.board.extent)),
                           self.options.corner_scale_sd * f.camera.plane.distance, self.tau)

    def term_consistency(self, frames: list[int], T: np.ndarray, boards: list, floor_m: float) -> tuple[float, int]:
        """How far each board's residual lies along its weak direction (its distance against its offsets, told
        apart only by incidence across the board), in units of its noise: chi-square, one dof per board. Real
        sensors' incidence-dependent biases show here first."""
        stat, dof = 0.0, 0
        for i in frames:
            fw = self.fw[i]
            if fw.R is None or fw.weak is None:
                continue
            Rv = fw.R @ fw.weak
            u = Rv / np.linalg.norm(Rv)
            e = self.residual(i, T, boards[i])
            stat += float(u @ e) ** 2 / float(u @ self.plane_cov(i, floor_m) @ u)
            dof += 1
        return stat, max(dof, 1)

    def graph(self, active: list[int], floor_m: float, robust: bool = True, free_pinned: bool = False
              ) -> gtsam.NonlinearFactorGraph:
        graph = gtsam.NonlinearFactorGraph()
        if self.has_beta:
            sd = np.array(self.terms.prior_sd, dtype=float)
            if self.pinned and not free_pinned:
                sd[list(self.pinned)] = PINNED_SD_M
            graph.add(gtsam.PriorFactorVector(RANGE, np.zeros(self.terms.size),
                                              gtsam.noiseModel.Diagonal.Sigmas(sd)))
        if self.edges is not None:
            graph.add(outline_prior())
        for j, i in enumerate(active):
            f = self.frames[i]
            key = board_key(j)
            if self.has_edges(i):
                graph.add(shift_prior(shift_key(j), self.edge_tau))
                graph.add(edge_factor(EXTRINSIC, key, shift_key(j), self.edges[i], self.board, self.edge_scale))
            graph.add(corner_factor(key, self.corners_board[i], f.camera.corners_px, self.camera,
                                    gtsam.noiseModel.Isotropic.Sigma(f.camera.corners_px.size, self.sigma_px)))
            noise = gtsam.noiseModel.Gaussian.Covariance(self.plane_cov(i, floor_m))
            noise = _robust(noise, self.options, self.whitener(i).shape[0]) if robust else noise
            if self.terms is None:
                graph.add(plane_factor(EXTRINSIC, key, self.whitener(i), noise, f.lidar.is_scan_line))
            elif not self.has_beta:
                fw = self.fw[i]
                graph.add(affine_plane_factor(EXTRINSIC, key, fw.W, fw.m_away, fw.e0, noise, f.lidar.is_scan_line))
            else:
                fw = self.fw[i]
                graph.add(nuisance_plane_factor(EXTRINSIC, key, RANGE, fw.W, fw.S, fw.m_away, fw.e0, noise,
                                                f.lidar.is_scan_line))
        return graph

    def plane_chi2(self, i: int, T: np.ndarray, T_board: np.ndarray, floor_m: float) -> float:
        e = self.residual(i, T, T_board)
        return float(e @ np.linalg.solve(self.plane_cov(i, floor_m), e))

    def corner_chi2(self, i: int, T_board: np.ndarray) -> float:
        f = self.frames[i]
        r, _ = corner_residuals(T_board, self.corners_board[i], f.camera.corners_px, self.camera, jacobian=False)
        return float(r @ r) / self.sigma_px**2

    def frame_chi2(self, i: int, T: np.ndarray, T_board: np.ndarray, floor_m: float) -> float:
        """The frame's share of the consistency statistic: its plane residual plus how far its board had
        to move from the camera's own fit (a cheap camera lets a bad LiDAR plane drag the board)."""
        return self.plane_chi2(i, T, T_board, floor_m) + self.corner_chi2(i, T_board) - self.pnp_chi2[i]

    def values(self, active: list[int], T: np.ndarray, boards: list) -> gtsam.Values:
        values = gtsam.Values()
        values.insert(EXTRINSIC, gtsam.Pose3(T))
        for j, i in enumerate(active):
            values.insert(board_key(j), gtsam.Pose3(boards[i]))
        if self.has_beta:
            values.insert(RANGE, self.beta.copy())
        if self.edges is not None:
            values.insert(OUTLINE, np.array(self.outline, dtype=float))
            for j, i in enumerate(active):
                if self.has_edges(i):
                    values.insert(shift_key(j), self.shifts.get(i, np.zeros(2)))
        return values

    def has_edges(self, i: int) -> bool:
        return self.edges is not None and self.edges[i] is not None and self.edges[i].size > 0

    def variant(self, camera: CameraModel | None = None, labels: FrameLabels | None = None, edges: bool = True
                ) -> "_Problem":
        """The same problem and state (terms and their values, scatter, pinned terms, edges) with another camera
        model or labels, or without the edges."""
        p = _Problem(self.frames, self.board, camera or self.camera, self.sigma_px, self.sigma_r, self.options,
                     self.terms, labels or self.labels)
        p.beta, p.tau, p.pinned = self.beta.copy(), self.tau, self.pinned
        if edges:
            p.copy_edges(self)
        return p

    def copy_edges(self, other: "_Problem") -> None:
        self.edges, self.outline, self.edge_scale = other.edges, other.outline.copy(), other.edge_scale
        self.edge_tau, self.shifts = other.edge_tau, dict(other.shifts)

    def solve(self, active: list[int], T: np.ndarray, boards: list, floor_m: float
              ) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values, int]:
        values = self.values(active, T, boards)
        graph = self.graph(active, floor_m)
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(self.options.max_iterations)
        params.setRelativeErrorTol(1e-9)
        params.setAbsoluteErrorTol(1e-9)
        opt = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
        result = opt.optimize()
        T = result.atPose3(EXTRINSIC).matrix()
        for j, i in enumerate(active):
            boards[i] = result.atPose3(board_key(j)).matrix()
        if self.has_beta:
            self.beta = np.asarray(result.atVector(RANGE), dtype=float)
        if self.edges is not None:
            self.outline = np.asarray(result.atVector(OUTLINE), dtype=float)
            self.shifts = {i: np.asarray(result.atVector(shift_key(j)), dtype=float)
                           for j, i in enumerate(active) if self.has_edges(i)}
        return graph, result, int(opt.iterations())

    def plane_cost(self, frames: list[int], T: np.ndarray, boards: list, floor_m: float) -> float:
        """The cost the camera alone cannot explain, summed over ``frames``."""
        return sum(self.frame_chi2(i, T, boards[i], floor_m) for i in frames)

    def consistency(self, frames: list[int], T: np.ndarray, boards: list, floor_m: float,
                    active: list[int]) -> tuple[float, float]:
        """:meth:`plane_cost` and its degrees of freedom under the model: the frames' whitened rows less 6 and
        the range terms' rank; with the edges in the graph of the ``active`` frames, more (:meth:`edge_leverage`)."""
        dof = sum(self.whitener(i).shape[0] for i in frames) - 6 - self.nuisance_rank(frames)
        if self.edges is not None:
            dof += self.edge_leverage(active, T, boards, floor_m)
        return self.plane_cost(frames, T, boards, floor_m), max(dof, 1)

    def edge_leverage(self, active: list[int], T: np.ndarray, boards: list, floor_m: float) -> float:
        """How many of the extrinsic's and board poses' directions the edges fit rather than the corners and
        planes: ``P - tr(H_cp Sigma)``, ``H_cp`` the corners' and planes' information on those ``P`` unknowns
        and ``Sigma`` their covariance in the whole graph. The planes' and corners' cost at the joint estimate
        then has that many more degrees of freedom than ``3 N - 6`` (the expected cost of a linear model's rows
        is their count less their leverage): three 2D scan lines give their planes 6 rows, which alone would
        fit the extrinsic exactly, while the segment ends fix much of it. Kept within 0-6: the corners fix the
        board poses far better than the edges can, so what the edges take is the extrinsic's."""
        n = len(active)
        H_all = _hessian(self.graph(active, floor_m), self.values(active, T, boards), n)[0]
        planes = self.variant(edges=False)
        H_cp = _hessian(planes.graph(active, floor_m), planes.values(active, T, boards), n)[0]
        k = 6 + 6 * n  # extrinsic and board poses, first in both orderings; range terms last in both
        idx = np.r_[0:k, H_all.shape[0] - (H_cp.shape[0] - k):H_all.shape[0]]
        Sigma = np.linalg.pinv(H_all, hermitian=True)[np.ix_(idx, idx)]
        return float(np.clip(H_cp.shape[0] - np.trace(H_cp @ Sigma), 0.0, 6.0))


def _rank(A: np.ndarray) -> int:
    """Numerical rank, relative tolerance 1e-8 (the range regressors' exact collinearities, a global offset
    and the per-ring offsets, survive the square root only to about 1e-10)."""
    sv = np.linalg.svd(A, compute_uv=False)
    return int(np.sum(sv > 1e-8 * sv[0])) if sv.size and sv[0] > 0 else 0


def _edge_crossings(prob: _Problem, frames: list[FrameMeasurement], active: list[int], T: np.ndarray,
                    boards: list, max_offset_m: float = MAX_END_OFFSET_M) -> list | None:
    """Each active frame's ring ends on the board's edges, sides assigned under ``T`` and ``boards``, those
    within ``max_offset_m`` of their side (None when no frame has any)."""
    from .range_model import frame_rings

    # A 2D scan's board segment is one ring: its two ends are where the scan line leaves the board.
    rings = [np.zeros(len(f.lidar.points), dtype=np.int64) if f.lidar.is_scan_line else r
             for f, r in zip(frames, frame_rings(frames))]
    noise = end_noise([(frames[i].lidar.points, rings[i]) for i in active if rings[i] is not None])
    edges = [crossings(f.lidar.points, rings[i], np.linalg.inv(boards[i]) @ T, prob.board, noise.beam_sd_rad,
                       max_offset_m, noise.position_sd_m)
             if i in active and rings[i] is not None else None for i, f in enumerate(frames)]
    return edges if any(e is not None and e.size for e in edges) else None


# Of the ring ends within half the board's smaller side of their sides under the planes' estimate, fewer than
# this share within ``MAX_END_OFFSET_M``: the estimate is further off along the boards than the ends' cut (weakly
# spread normals: boards facing the rig), and the ends are first fitted with the wide cut.
MIN_CUT_SHARE = 0.5


def _ends(edges: list | None) -> int:
    return 0 if edges is None else sum(e.size for e in edges if e is not None)


def _cut_ends(prob: _Problem, frames: list[FrameMeasurement], active: list[int], T: np.ndarray, boards: list
              ) -> tuple[list | None, list | None]:
    """The ends under ``T`` within ``MAX_END_OFFSET_M`` of their sides, and those within half the board's smaller
    side when the first are fewer than ``MIN_CUT_SHARE`` of them (else None): ``T`` is then further off along
    the boards than the cut."""
    edges = _edge_crossings(prob, frames, active, T, boards)
    wide = _edge_crossings(prob, frames, active, T, boards, max_offset_m=0.5 * min(prob.board.extent))
    return edges, (wide if _ends(edges) < MIN_CUT_SHARE * _ends(wide) else None)


def _add_edges(prob: _Problem, frames: list[FrameMeasurement], active: list[int], T: np.ndarray, boards: list,
               floor: float) -> tuple[np.ndarray, list]:
    """Find each frame's ring ends on the board's edges under the planes' estimate and solve again with them;
    their standard deviations are scaled when the ends scatter beyond them (quasi-likelihood, never below the
    model's), and the boards' in-plane scatter estimated (:func:`_edge_scatter`). Where the planes' estimate
    lies further from the outlines than the ends' cut (``MIN_CUT_SHARE``; 3D), the ends within half the board's
    smaller side are fitted first and assigned again under that estimate. Returns ``T`` and ``boards``."""
    edges, wide = _cut_ends(prob, frames, active, T, boards)
    # A 2D scan's ends are in the graph from the first solve (assigned under the start), so its estimate fits
    # them already; the wide cut is for 3D ends found after the planes' solve.
    if wide is not None and not any(f.lidar.is_scan_line for f in frames):
        start = prob.edge_tau, prob.edge_scale
        prob.edges = wide
        T_wide, b_wide = _solve_with_edges(prob, active, T, list(boards), floor)
        edges = _edge_crossings(prob, frames, active, T_wide, b_wide)
        if edges is not None:  # the ends' scale and scatter are estimated again from the ends under the cut
            T, boards = T_wide, b_wide
            prob.edge_tau, prob.edge_scale = start
    if edges is None:
        if prob.edges is not None:  # ends assigned before, none under the estimate: planes alone
            prob.edges = None
            b = list(boards)
            prob.solved = prob.solve(active, T, b, floor)[:2]
            return prob.solved[1].atPose3(EXTRINSIC).matrix(), b
        return T, boards
    prob.edges = edges
    return _solve_with_edges(prob, active, T, list(boards), floor)


def _solve_with_edges(prob: _Problem, active: list[int], T: np.ndarray, b: list, floor: float
                      ) -> tuple[np.ndarray, list]:
    """Solve with ``prob``'s ends, their scale and the boards' in-plane scatter estimated in turn."""
    for _ in range(4):
        prob.solved = prob.solve(active, T, b, floor)[:2]
        T = prob.solved[1].atPose3(EXTRINSIC).matrix()
        tau, scale = _edge_scatter(prob, active, T, b)
        if abs(np.log(max(tau, 1e-4) / max(prob.edge_tau, 1e-4))) < 0.1 and abs(np.log(scale / prob.edge_scale)) < 0.05:
            break
        prob.edge_tau, prob.edge_scale = tau, scale
    return T, b


def _edge_scatter(prob: _Problem, active: list[int], T: np.ndarray, boards: list) -> tuple[float, float]:
    """The boards' in-plane scatter (m) and the ends' scale at the solve (``board_edges.edge_scatter``)."""
    return edge_scatter([(T, boards[i], prob.edges[i]) for i in active if prob.has_edges(i)], prob.board,
                        prob.outline, prob.edge_scale, prob.edge_tau)


def _edges_record(prob: _Problem, active: list[int], T: np.ndarray, boards: list, floor: float, cov: np.ndarray,
                  marginals: gtsam.Marginals, quasi_scale: float) -> tuple[dict, list[str]]:
    """What the edges say, for calibration.json: the ends used, their scale and the boards' in-plane scatter,
    the growth of the outline's sides, each frame's outline shift (board axes) and their mean in camera axes
    against its 99% limit, and the planes-only estimate against this one (a Hausman test: their difference
    against the difference of their covariances, which is the edges' share)."""
    warnings = []
    shift_keys = [(j, i) for j, i in enumerate(active) if prob.has_edges(i)]
    keys = gtsam.KeyVector([OUTLINE] + [shift_key(j) for j, _ in shift_keys])
    J = marginals.jointMarginalCovariance(keys).fullMatrix() * quasi_scale
    outline_sd = np.sqrt(np.diag(J[:4, :4]))
    # The mean shift in camera axes: each frame's board axes mapped by its board pose.
    A = np.zeros((3, 2 * len(shift_keys)))
    shifts, per_frame = [], []
    for k, (j, i) in enumerate(shift_keys):
        A[:, 2 * k:2 * k + 2] = boards[i][:3, :2] / len(shift_keys)
        d = prob.shifts.get(i, np.zeros(2))
        shifts.append(d)
        sd = np.sqrt(np.diag(J[4 + 2 * k:6 + 2 * k, 4 + 2 * k:6 + 2 * k]))
        per_frame.append({"frame": prob.frames[i].name, "ends": int(prob.edges[i].size),
                          "shift_board_xy_m": d.tolist(), "shift_sd_m": sd.tolist()})
    mean = A @ np.concatenate(shifts)
    # The shifts are estimated random effects (each 0 +- the scatter a priori): under the model their estimates
    # vary by the prior's covariance less the posterior's.
    C = A @ (prob.edge_tau**2 * quasi_scale * np.eye(J.shape[0] - 4) - J[4:, 4:]) @ A.T
    d2, dof = chi2.mahalanobis(mean, C)
    mean_p = float(chi2.sf(d2, dof)) if dof else 1.0
    g, o = prob.outline[:2], prob.outline[2:]
    # The planes alone, from this estimate, with the same noise model. Not for a 2D scan: its lines alone have
    # up to 8 exact solutions for three boards (and several minima for a few more), so their refit from this
    # estimate may land in another, and a difference between minima is no test of a bias (simulated 3-board
    # layouts: p < 0.001 on 8 of 97 right answers).
    cov_p = planes_check = None
    if not any(prob.frames[i].lidar.is_scan_line for i in active):
        planes = prob.variant(edges=False)
        b = list(boards)
        graph, result, _ = planes.solve(active, T, b, floor)
        T_p = result.atPose3(EXTRINSIC).matrix()
        try:
            marginals_p = gtsam.Marginals(graph, result)
            cov_p = marginals_p.marginalCovariance(EXTRINSIC)
        except RuntimeError:  # the planes alone leave a direction unobservable: the edges fix it
            cov_p = None
    test = None
    if cov_p is not None:
        # The outline check of the planes alone too: with the edges in the graph, a pattern placed off where
        # dataset.yaml says pulls the estimate along with the outline, and the shifts about it shrink.
        planes_check, _ = _outline_check(planes, active, T_p, b, marginals_p, quasi_scale, quasi_scale * cov_p)
        if planes_check is not None:
            warnings.extend(outline_warnings(planes_check, used=False, beside_edges=True))
        delta = T_log(np.linalg.inv(T_p) @ T)
        h2, h_dof = chi2.mahalanobis(delta, cov_p - cov)
        h_p = float(chi2.sf(h2, h_dof)) if h_dof else 1.0
        test = {"planes_only_T_camera_lidar": T_p.tolist(), "difference_tangent": delta.tolist(),
                "d2": h2, "dof": h_dof, "p_value": h_p}
        if h_dof and h_p < 0.01:
            warnings.append(f"board edges: the planes alone and the planes with the edges differ by "
                            f"{np.degrees(np.linalg.norm(delta[:3])):.2f} deg and "
                            f"{1000 * np.linalg.norm(delta[3:]):.0f} mm, beyond what the edges' information "
                            f"explains (d2 {h2:.1f} on {h_dof} dof, p = {h_p:.1g}): the boards' planes or their "
                            "outlines carry a bias (range error with incidence, intrinsics, the board's real size); "
                            "both estimates are in calibration.json")
    record = {"used": True, "ends": int(sum(prob.edges[i].size for _, i in shift_keys)),
              "end_scale": prob.edge_scale, "board_scatter_in_plane_m": prob.edge_tau, "growth_m": g.tolist(), "growth_sd_m": outline_sd[:2].tolist(),
              "outline_offset_m": o.tolist(), "outline_offset_sd_m": outline_sd[2:].tolist(), "frames": per_frame,
              "mean_shift_camera_m": mean.tolist(), "mean_shift_covariance": C.tolist(),
              "mean_shift_d2": d2, "mean_shift_dof": dof, "mean_shift_p_value": mean_p,
              "planes_against_edges": test, "planes_only_check": planes_check}
    return record, outline_warnings(record, used=True) + warnings


def _outline_check(prob: _Problem, active: list[int], T: np.ndarray, boards: list, marginals: gtsam.Marginals,
                   quasi_scale: float, cov: np.ndarray) -> tuple[dict | None, list[str]]:
    """The board's edges as a check of this planes-only estimate (``solvers.outline_check``): each frame's ring
    ends found under it, and its joint covariance with the board poses from the graph (scaled like ``cov``, the
    extrinsic's block widened to ``cov`` where the range terms' or the intrinsics' propagation widened it). Where
    the estimate lies further from the outlines than the ends' cut, the ends within half the board's side."""
    edges, wide = _cut_ends(prob, prob.frames, active, T, boards)
    edges = edges if wide is None else wide
    if edges is None:
        return None, []
    used = [(j, i) for j, i in enumerate(active) if edges[i] is not None and edges[i].size]
    keys = gtsam.KeyVector([EXTRINSIC] + [board_key(j) for j, _ in used])
    joint = marginals.jointMarginalCovariance(keys).fullMatrix() * quasi_scale
    ev, V = np.linalg.eigh(0.5 * (cov + cov.T) - joint[:6, :6])
    joint[:6, :6] += (V * np.maximum(ev, 0.0)) @ V.T
    return outline_check(T, [boards[i] for _, i in used], [edges[i] for _, i in used], prob.board,
                         [prob.frames[i].name for _, i in used], joint)


def _hessian(graph, values, n_frames: int) -> tuple[np.ndarray, np.ndarray]:
    """The graph's information and information vector at ``values`` (its cost there is ``0.5 d^T H d - eta^T d``
    + const in the tangent ``d``), ordered extrinsic, board poses, the edges' nuisances, range terms last (those
    present)."""
    ordering = gtsam.Ordering()
    ordering.push_back(EXTRINSIC)
    for j in range(n_frames):
        ordering.push_back(board_key(j))
    for key in [shift_key(j) for j in range(n_frames)] + [OUTLINE, RANGE]:
        if values.exists(key):
            ordering.push_back(key)
    return graph.linearize(values).hessian(ordering)


def _extrinsic_information(graph, values, n_frames: int) -> tuple[np.ndarray, np.ndarray]:
    """The graph's information and information vector on the extrinsic alone at ``values``, every other
    variable profiled out (Schur complement)."""
    H, eta = _hessian(graph, values, n_frames)
    K = H[:6, 6:] @ np.linalg.pinv(H[6:, 6:])
    return H[:6, :6] - K @ H[:6, 6:].T, eta[:6] - K @ eta[6:]


def _edge_share(prob: _Problem, active: list[int], T: np.ndarray, boards: list, floor: float, quasi_scale: float
                ) -> tuple[np.ndarray, np.ndarray]:
    """What the edges add to the extrinsic's log-posterior about this estimate, to second order: ``eta^T xi -
    0.5 xi^T H xi`` in the tangent ``xi`` (the posterior's). ``H``: the information with the edges less that of
    the planes alone, every other variable profiled out; ``eta``: minus the planes' pull at the estimate, which
    the edges balance (the whole graph's is zero there). Scaled like the covariance by ``quasi_scale``."""
    H_all, _ = _extrinsic_information(prob.graph(active, floor), prob.values(active, T, boards), len(active))
    planes = prob.variant(edges=False)
    H_p, eta_p = _extrinsic_information(planes.graph(active, floor), planes.values(active, T, boards), len(active))
    ev, V = np.linalg.eigh(0.5 * (H_all - H_p + (H_all - H_p).T))
    return (V * np.maximum(ev, 0.0)) @ V.T / quasi_scale, -eta_p / quasi_scale


def _degenerate(graph, values, n_frames: int) -> DegenerateLayoutError:
    """Explain a singular system by the extrinsic's least-informed direction."""
    info, _ = _extrinsic_information(graph, values, n_frames)
    vals, vecs = np.linalg.eigh(info)
    weak = vecs[:, 0]
    part = "rotation" if np.linalg.norm(weak[:3]) > np.linalg.norm(weak[3:]) else "translation"
    axis, advice = describe_direction(weak[:3] if part == "rotation" else weak[3:])
    return DegenerateLayoutError(
        f"the {n_frames} frames leave the extrinsic's {part} unobservable (information {vals[0]:.2g} "
        f"against {vals[-1]:.2g}; weakest direction {np.round(weak, 2).tolist()} in the LiDAR tangent)",
        hint=f"record more board poses; {advice}")


# Smallest over largest eigenvalue of the extrinsic's covariance (rad and m) below which a direction is
# taken as unobservable: a good layout of metre-scale boards is near 1e-2; one whose normals do not span 3D
# falls below 1e-6 (its weak translation std grows to metres).
MIN_INFORMATION_RATIO = 1e-6
# A 2D LiDAR's extrinsic whose standard deviation (planes and segment ends) reaches this rotation (rad) or
# translation (m) is refused: the layout leaves it unobservable in all but name, and a point estimate there
# would be a confident-looking guess. A layout is degenerate when its bound reaches 5 degrees or 0.5 m; the
# estimate's own standard deviation scatters about the bound (up to 1.5 times it on simulated mounted layouts
# whose bound is 4.4-4.7 degrees), so the limit on the estimate is 1.5 times that: at 5 degrees such layouts were
# refused, and answered inside their regions when let through.
MAX_SCAN_ROTATION_SD_RAD = np.deg2rad(7.5)
MAX_SCAN_TRANSLATION_SD_M = 0.75


def _check_scan_directions(prob: _Problem, active: list[int], boards: list) -> None:
    """2D: the translation is fixed along the boards' normals (their scan lines) and along the outward normals of
    the sides their segments end on (the ends). When all of these lie in one plane (spread, as
    ``closed_form.normal_spread``, below ``MIN_SCAN_NORMAL_SPREAD``: upright boards whose lines end on their
    upright sides), the translation across it is unobservable: raise :class:`DegenerateLayoutError` naming it."""
    dirs = []
    for i in active:
        dirs.append(boards[i][:3, 2])
        if prob.has_edges(i):
            dirs.extend(SIDE_NORMALS[prob.edges[i].sides] @ boards[i][:3, :2].T)
    spread, weak = normal_spread(np.array(dirs))
    if spread[-1] < MIN_SCAN_NORMAL_SPREAD:
        axis, advice = describe_direction(weak)
        raise DegenerateLayoutError(
            f"the {len(active)} board normals and the board sides their scan segments end on all lie in one plane "
            f"(spread {spread[-1]:.3f} along {axis}): translation along {axis} is unobservable", hint=advice)


# The posterior of a 3-board layout reaches further along its curved valley than its Laplace approximation: a
# mode's samples may spread this many times the refusal limits above before the answer is refused (simulated
# mounted layouts: good answers, 1 degree off, sample 6.5-7.1 degrees; a 38-degree miss sampled 15.5).
POSTERIOR_REFUSAL_FACTOR = 2.0


# The planes alone against the planes with the edges (``Refinement.edges['planes_against_edges']``): below this
# p-value the data contradict the model the estimate rests on, and the answer says so first (``contradiction``).
CONTRADICTION_P = 1e-3


def contradiction(ref: Refinement) -> str | None:
    """Why the estimate cannot be trusted as its covariance says, or None: with ``--edges`` (3D), the boards'
    planes and their rings' ends disagree far beyond their noise (p below ``CONTRADICTION_P``), so one of them
    carries what the model does not hold (a wrong board size or pattern offset, a plane error) and the two pull
    the answer apart. A 2D scan's planes are not tested against its ends (:func:`_edges_record`)."""
    test = (ref.edges or {}).get("planes_against_edges")
    if not test or not test.get("dof") or test["p_value"] >= CONTRADICTION_P:
        return None
    delta = np.asarray(test["difference_tangent"], dtype=float)
    return (f"the boards' planes and their ring ends on the boards' edges disagree far beyond their noise "
            f"({np.degrees(np.linalg.norm(delta[:3])):.1f} deg and {1000 * np.linalg.norm(delta[3:]):.0f} mm apart; "
            f"d2 {test['d2']:.1f} on {test['dof']} dof, p = {test['p_value']:.1g}): the answer may be further off "
            "than its intervals say")


def scan_refusal(cov: np.ndarray, T: np.ndarray, n_frames: int, ends: bool,
                 factor: float = 1.0) -> DegenerateLayoutError | None:
    """The refusal of a 2D extrinsic whose covariance reaches ``MAX_SCAN_ROTATION_SD_RAD`` or
    ``MAX_SCAN_TRANSLATION_SD_M`` times ``factor`` (None when it does not), naming the weakest direction in camera
    axes: the refinement's covariance, or (``factor`` ``POSTERIOR_REFUSAL_FACTOR``) the posterior's about the MAP's
    mode."""
    sd = np.sqrt(np.maximum(np.diag(cov), 0.0))
    max_rot, max_trans = factor * MAX_SCAN_ROTATION_SD_RAD, factor * MAX_SCAN_TRANSLATION_SD_M
    if sd[:3].max() < max_rot and sd[3:].max() < max_trans:
        return None
    part = "translation" if sd[3:].max() / max_trans >= sd[:3].max() / max_rot else "rotation"
    block = cov[3:, 3:] if part == "translation" else cov[:3, :3]
    weak = T[:3, :3] @ np.linalg.eigh(block)[1][:, -1]  # LiDAR axes to camera axes
    axis, advice = describe_direction(weak)
    what = "scan lines and their segment ends on the boards' edges" if ends else "scan lines"
    return DegenerateLayoutError(
        f"the {n_frames} {what} leave the "
        f"extrinsic's {part} nearly unobservable (standard deviations up to {np.degrees(sd[:3].max()):.1f} deg and "
        f"{1000 * sd[3:].max():.0f} mm; weakest along {axis})",
        hint=f"record more board poses; {advice}")


def refine(frames: list[FrameMeasurement], board: BoardModel, camera: CameraModel, T_init: np.ndarray,
           options: RefinementOptions = RefinementOptions()) -> Refinement:
    """Refine ``T_camera_lidar`` from the usable frames, starting at ``T_init``."""
    if options.range_accuracy_m is None:
        options = replace(options, range_accuracy_m=DEFAULT_RANGE_ACCURACY_M)
    frames = [f for f in frames if f.usable]
    # Scan lines with their segment ends on a board of known size: two boards can determine the extrinsic.
    least = 2 if (frames and all(f.lidar.is_scan_line for f in frames) and board.size_known
                  and options.edges is not False) else 3
    if len(frames) < least:
        raise DegenerateLayoutError(f"only {len(frames)} usable frame(s); refinement needs at least {least}")
    resid_px = corner_residual_px(frames, board, camera)
    sigma_px = options.corner_noise_px or max(resid_px, 1e-3) * options.corner_error_correlation
    sigma_r = options.range_noise_m or max(pooled_range_noise_m(frames), 1e-5)
    prob = _Problem(frames, board, camera, sigma_px, sigma_r, options)
    warnings: list[str] = []
    floor = options.plane_floor_m or 0.0

    active = list(range(len(frames)))
    dropped: dict[int, str] = {}
    flagged: dict[int, str] = {}
    T, boards = T_init, [f.camera.T_camera_board for f in frames]
    iterations = 0
    scan_lines = all(f.lidar.is_scan_line for f in frames)
    use_edges = scan_lines if options.edges is None else options.edges
    if use_edges and board.size_known and scan_lines:
        # A few scan lines leave a direction along the boards loose, where the planes alone drift far from the
        # start: the segment ends hold it from the first solve (sides assigned under the start).
        prob.edges = _edge_crossings(prob, frames, active, T, boards)
    for _ in range(max(4, len(frames) // 3)):
        graph, result, its = prob.solve(active, T, boards, floor)
        iterations += its
        T = result.atPose3(EXTRINSIC).matrix()
        chi = {i: prob.frame_chi2(i, T, boards[i], floor) for i in active}
        flagged = _flag_outliers(chi, frames, T, boards, options)
        if options.outliers != "drop" or not flagged:
            break
        if len(active) <= 3:
            warnings.append(f"{len(flagged)} frame(s) look like outliers but dropping them would leave fewer than 3 "
                            "frames; they are kept, down-weighted by the robust loss")
            break
        # Drop the worst frame only: a gross outlier drags the solution and can make good frames look bad.
        worst = max(flagged, key=lambda i: chi[i])
        dropped[worst] = flagged[worst]
        active = [i for i in active if i != worst]
        # Start again from the remaining frames' own closed form and board poses: the outliers dragged the
        # previous solution, and from there a robust loss can hold on to a wrong minimum.
        kept = [frames[i] for i in active]
        try:
            T = solve_closed_form([f.camera.plane for f in kept], [f.lidar.plane for f in kept],
                                  allow_weak=True).T_camera_lidar
        except DegenerateLayoutError:
            T = T_init
        boards = [f.camera.T_camera_board for f in frames]

    inliers = [i for i in active if i not in flagged]
    if use_edges:
        if board.size_known:
            T, boards = _add_edges(prob, frames, active, T, boards, floor)
            if prob.solved is not None:
                graph, result = prob.solved
            if prob.edges is None:
                warnings.append("board edges: no ring end of the boards' points could be used as an edge (none "
                                "crosses the board's outline within half its side under the planes' estimate): "
                                "the estimate rests on the planes alone; check board.size in dataset.yaml")
            if scan_lines and prob.edges is not None:
                _check_scan_directions(prob, active, boards)
        else:
            warnings.append("the board's size is not given (board.size in dataset.yaml): its edges are not used, "
                            "so the translation along the boards' planes rests on the planes alone")
    labels = None
    if options.range_model != "none":
        labels = frame_labels(frames, board, T, boards)
        prob, T, boards, model_fit = _choose_range_model(prob, active, inliers, T, boards, floor, options, labels)
        if labels.source == "geometry" and prob.terms is not None and "dark" in prob.terms.names:
            # The colours were placed under the extrinsic the model was chosen from, as if it were exact. Placed
            # again under the estimate and blurred by its uncertainty (shares placed sharper than they are known
            # shrink the black-square term), the model is chosen again (once: the extrinsic moves by millimetres).
            try:
                placement_cov = gtsam.Marginals(*prob.solved).marginalCovariance(EXTRINSIC) if prob.solved else None
            except RuntimeError:  # a singular graph is refused below, with its reason
                placement_cov = None
            labels = frame_labels(frames, board, T, boards, placement_cov)
            prob, T, boards, model_fit = _choose_range_model(prob, active, inliers, T, boards, floor, options, labels)
        agreement = labels.agreement()
        if agreement is not None and agreement < MIN_INTENSITY_AGREEMENT:
            warnings.append(f"range model: the board returns' intensities agree with the black squares the camera's "
                            f"pattern places in only {100 * agreement:.0f}% of clearly black or white returns: the "
                            "intensity field may be uncalibrated or saturated, or the LiDAR board misplaced; the "
                            "squares are placed by geometry")
        if model_fit is not None:
            model_fit = replace(model_fit, labels_from=labels.source, intensity_agreement=agreement, labels=labels)
            if "fell back" in model_fit.reason:
                warnings.append(f"range model: {model_fit.reason}")
    else:
        model_fit = None
    if prob.has_beta and options.range_noise_m is None:
        # With range terms, the range noise is the points' scatter about each board's own plane and terms: the
        # plane-only residuals pooled above also hold the within-board structure the terms explain (rings,
        # black squares), and taken as noise it would widen every variance (by half, for black squares 5 cm
        # off).
        sigma_terms = pooled_range_noise_with_terms_m(prob, inliers)
        if 1e-5 < sigma_terms < 0.99 * prob.sigma_r:
            prob.sigma_r = sigma_r = sigma_terms
            b = list(boards)
            prob.solved = prob.solve(active, T, b, floor)[:2]
            T, boards = prob.solved[1].atPose3(EXTRINSIC).matrix(), b
    if prob.terms is not None:
        graph, result = prob.solved
    for attempt in range(2):
        if prob.terms is not None:
            graph, result = prob.solved
            t_stat, t_dof = prob.term_consistency(inliers, T, boards, floor)
            if chi2.sf(t_stat, t_dof) < 0.01 and options.estimate_plane_floor:
                T, boards, graph, result, its = _estimate_board_scatter(prob, active, inliers, T, boards, floor)
                prob.solved = (graph, result)
                iterations += its
                warnings.append(
                    f"the boards' ranges vary with incidence unlike a range offset (chi-square {t_stat:.0f} on "
                    f"{t_dof} dof; each board's apparent offset scatters by {1000 * prob.tau:.0f} mm): the offset is "
                    "taken from the camera's board distances across boards, not from the incidence across each board")
            model_fit = replace(model_fit, term_consistency={
                "chi2": t_stat, "dof": t_dof, "p_value": float(chi2.sf(t_stat, t_dof)), "board_scatter_m": prob.tau,
                "board_scatter_meaning": BOARD_SCATTER_MEANING})
        stat, dof = prob.consistency(inliers, T, boards, floor, active)
        variance_factor, p_value = stat / dof, float(chi2.sf(stat, dof))
        if (p_value < 0.01 or floor > 0) and options.plane_floor_m is None and options.estimate_plane_floor:
            # The planes disagree beyond the point and corner noise (real sensors: range biases per laser,
            # imperfect intrinsics). Model it as a per-board plane error, its size estimated so that the
            # consistency statistic equals its degrees of freedom (method of moments), then solve again.
            first = floor == 0
            # With range terms the residual also has the terms' directions, which a plane error cannot hold: its
            # size is bounded by what a plane error can physically be, and what it leaves scales the covariance.
            cap = MAX_PLANE_ERROR_M if prob.has_beta else 0.5
            floor, (T, boards, graph, result, its) = _match_moments(
                prob, active, T, boards, (1e-5, cap), lambda v: v,
                lambda v, T_v, b_v: prob.plane_cost(inliers, T_v, b_v, v) / dof)
            prob.solved = (graph, result)
            iterations += its
            if first:
                warnings.append(f"the boards' camera and LiDAR planes disagree more than the point and corner noise "
                                f"explain (chi-square {stat:.0f} on {dof:.4g} dof, p = {p_value:.1g}); a per-board "
                                f"plane error of {1000 * floor:.1f} mm, estimated from the data, is included in the "
                                "covariance")
        if attempt or prob.terms is None or not prob.has_beta:
            break
        # A term beyond its physical prior is not believed: held at 0, its prior variance propagated (below).
        sd = np.array(prob.terms.prior_sd)
        far = tuple(int(k) for k in np.flatnonzero(np.abs(prob.beta) > MAX_PRIOR_SIGMAS * sd))
        if not far:
            break
        names = ", ".join(f"{prob.terms.names[k]} {1000 * prob.beta[k]:+.0f} mm" for k in far)
        warnings.append(f"range model: {names} lie beyond {MAX_PRIOR_SIGMAS:.0f} prior standard deviations of the "
                        f"sensor's range accuracy ({1000 * options.range_accuracy_m:.0f} mm): likely a term confounded "
                        "with the extrinsic, a wrong LiDAR segment or a board that moved; held at 0 with their prior "
                        "variance propagated into the covariance (set lidar.range_accuracy_m if the sensor is known "
                        "to err more)")
        model_fit = replace(model_fit, pinned=tuple(prob.terms.names[k] for k in far),
                            pinned_values_m=tuple(float(prob.beta[k]) for k in far))
        prob.pinned = far
        prob.beta[list(far)] = 0.0
        b = list(boards)
        graph, result, its = prob.solve(active, T, b, floor)
        prob.solved = (graph, result)
        T, boards = result.atPose3(EXTRINSIC).matrix(), b
        iterations += its

    try:
        marginals = gtsam.Marginals(graph, result)
        cov = marginals.marginalCovariance(EXTRINSIC)
        if model_fit is not None and prob.terms is not None:
            model_fit = _with_uncertainty(model_fit, prob, marginals)
            if prob.pinned:
                cov, model_fit = _consider_pinned(prob, active, result, floor, model_fit)
            if model_fit.confounding:
                c = model_fit.confounding
                warnings.append(f"range model: the {c['term']} is confounded with the extrinsic (correlation "
                                f"{c['correlation']:.2f} with {c['direction']}); it is marginalised with its prior, "
                                f"which widens that direction's standard deviation from {c['sd_if_known']:.1f} to "
                                f"{c['sd']:.1f} {c['unit']}. {c['advice']}")
    except RuntimeError as exc:
        raise _degenerate(graph, result, len(active)) from exc
    ev = np.linalg.eigvalsh(cov) if np.all(np.isfinite(cov)) else np.array([0.0, 1.0])
    if ev[0] <= 0 or ev[0] / ev[-1] < MIN_INFORMATION_RATIO:
        raise _degenerate(graph, result, len(active))
    if scan_lines and (weak := scan_refusal(cov, T, len(active), prob.edges is not None)) is not None:
        raise weak

    # Structure that neither the range terms (their scatter bounded by the range accuracy) nor a plane error of
    # physical size explains: the covariance is scaled by the variance factor that remains (quasi-likelihood).
    quasi_scale = 1.0
    if prob.has_beta and options.plane_floor_m is None and options.estimate_plane_floor:
        stat_f, dof_f = prob.consistency(inliers, T, boards, floor, active)
        if chi2.sf(stat_f, dof_f) < 0.01:
            quasi_scale = stat_f / dof_f
            cov = cov * quasi_scale
            warnings.append(f"the boards disagree beyond what the range terms and a per-board plane error of physical "
                            f"size explain (chi-square {stat_f:.0f} on {dof_f:.3g} dof): the covariance is scaled by "
                            f"{quasi_scale:.2f}")
            if model_fit is not None:
                model_fit = replace(model_fit, std_m=tuple(np.sqrt(quasi_scale) * np.array(model_fit.std_m)),
                                    extrinsic_share=quasi_scale * model_fit.extrinsic_share)
    if model_fit is not None and labels is not None and labels.source == "geometry" and prob.has_beta \
            and "dark" in prob.terms.names and "dark" not in model_fit.pinned:
        cov, model_fit, T = _consider_placement(prob, active, T, boards, floor, cov, model_fit)
    edges_record = edge_share = end_terms = None
    if prob.edges is not None:
        edges_record, edge_warnings = _edges_record(prob, active, T, boards, floor, cov / quasi_scale, marginals,
                                                    quasi_scale)
        warnings.extend(edge_warnings)
        edge_share = _edge_share(prob, active, T, boards, floor, quasi_scale)
        if all(frames[i].lidar.is_scan_line for i in active):
            end_terms = EndTerms({frames[i].name: prob.edges[i] for i in active if prob.has_edges(i)},
                                 {frames[i].name: prob.shifts.get(i, np.zeros(2)) for i in active},
                                 np.array(prob.outline, dtype=float), prob.edge_scale * np.sqrt(quasi_scale))
    cov_intrinsics = None
    if camera.param_std is not None:
        cov_intrinsics = _intrinsics_covariance(prob, active, T, boards, floor, options)
        cov = cov + cov_intrinsics
        how = ("parameters taken as independent" if camera.param_covariance is None else
               "with the parameters' correlations")
        what = ("the intrinsics' stated uncertainty (camera.param_std)" if camera.source == "dataset.yaml"
                else "the intrinsics were estimated from the same images; their uncertainty")
        warnings.append(f"{what} is propagated into the covariance (first order, {how})")

    if prob.edges is None and board.size_known and not scan_lines and options.outline_check:
        edges_record, check_warnings = _outline_check(prob, active, T, boards, marginals, quasi_scale, cov)
        warnings.extend(check_warnings)

    fits = []
    for i, f in enumerate(frames):
        c2 = prob.plane_chi2(i, T, boards[i], floor)
        corner = prob.corner_chi2(i, boards[i])
        why = dropped.get(i) or flagged.get(i)
        fits.append(FrameFit(f.name, c2, c2 + corner - prob.pnp_chi2[i], int(prob.whitener(i).shape[0]),
                             float(sigma_px * np.sqrt(corner / f.camera.corners_px.size)),
                             0.0 if i in dropped else _robust_weight(np.sqrt(c2), options, prob.whitener(i).shape[0]),
                             why, i in dropped))
        if why:
            action = "dropped" if i in dropped else "down-weighted"
            warnings.append(f"frame {f.name}: {why}; {action}")
    return Refinement(T, cov, {f.name: boards[i] for i, f in enumerate(frames)}, tuple(fits), float(sigma_px),
                      resid_px, float(sigma_r), float(floor), float(variance_factor), round(float(dof), 2), p_value,
                      iterations, tuple(warnings), cov_intrinsics, options.corner_scale_sd, model_fit, edges_record,
                      edge_share, end_terms)


BOARD_SCATTER_MEANING = (
    "standard deviation (m) of each board's apparent own range offset about the shared terms, along the board's "
    "distance-against-offset direction (told apart only by how incidence varies across the board): 0 when the "
    "boards agree; a range error that grows with incidence shows here as metres, the weak direction amplifying it, "
    "and the offset then rests on the camera's board distances across boards")
# Upper bound of that scatter (m): past it, no board's own offset information is left.
MAX_BOARD_SCATTER_M = 10.0


def _estimate_board_scatter(prob: _Problem, active: list[int], inliers: list[int], T: np.ndarray, boards: list,
                            floor: float) -> tuple:
    """``prob.tau``, the boards' scatter along their weak directions, by the method of moments on the term
    consistency statistic (:meth:`_Problem.term_consistency`); returns the solve ``(T, boards, graph, result,
    iterations)``."""
    t_dof = prob.term_consistency(inliers, T, boards, floor)[1]

    def with_tau(v):
        prob.tau = v
        return floor

    prob.tau, solve = _match_moments(prob, active, T, boards, (1e-4, MAX_BOARD_SCATTER_M), with_tau,
                                     lambda v, T_v, b_v: prob.term_consistency(inliers, T_v, b_v, floor)[0] / t_dof)
    return solve


def _match_moments(prob: _Problem, active: list[int], T: np.ndarray, boards: list, bounds: tuple[float, float],
                   floor_for, excess) -> tuple:
    """A noise parameter by the method of moments: ``floor_for(v)`` sets it (returning the per-board plane error
    to solve with) and ``excess(v, T, boards)`` is the consistency statistic over its degrees of freedom, which
    falls as ``v`` grows. The root of its logarithm is found by Brent's method in ``log v`` within ``bounds``, to
    0.1% in ``v`` (a geometric bisection to the same precision needs twice the solves); each trial starts from
    the fit without it. Returns the value and its solve ``(T, boards, graph, result, iterations)``."""
    start = (T, list(boards), prob.beta.copy())
    solves: dict[float, tuple] = {}

    def solve_at(u):
        if u not in solves:
            b, prob.beta = list(start[1]), start[2].copy()
            graph, result, n = prob.solve(active, start[0], b, floor_for(float(np.exp(u))))
            T_u = result.atPose3(EXTRINSIC).matrix()
            ratio = excess(float(np.exp(u)), T_u, b)
            solves[u] = (T_u, b, graph, result, n, prob.beta.copy(), float(np.log(max(ratio, 1e-300))))
        return solves[u]

    def log_excess(u):
        return solve_at(u)[6]

    lo, hi = float(np.log(bounds[0])), float(np.log(bounds[1]))
    if log_excess(hi) > 0:
        u = hi            # still inconsistent at the largest value allowed: report that bound
    elif log_excess(lo) <= 0:
        u = lo
    else:
        from scipy.optimize import brentq  # here: scipy.optimize takes 0.08 s to import, rarely needed

        u = float(brentq(log_excess, lo, hi, xtol=1e-3))
    T_u, b_u, graph, result, _, beta, _ = solve_at(u)
    floor_for(float(np.exp(u)))
    prob.beta = beta.copy()
    return float(np.exp(u)), (T_u, b_u, graph, result, sum(s[4] for s in solves.values()))


def _objective(p: _Problem, graph, result, active: list[int], floor_m: float) -> float:
    """Minus twice the log-likelihood (up to a constant shared by every model of the same frames) at a solve:
    the objective the solve minimised (robust loss, priors), the boards' best-fit floors (they differ with the
    terms each board holds) and the log-determinants of the plane factors' covariances relative to the point
    noise (they differ with the terms once a per-board plane error is in place)."""
    logdet = 0.0
    for i in active:
        C = p.plane_cov(i, floor_m) / p.sigma_r**2
        logdet += float(np.linalg.slogdet(C)[1])
    return 2.0 * graph.error(result) + sum(p.fw[i].floor for i in active) / p.sigma_r**2 + logdet


@dataclass
class _ModelFit:
    """One range model solved over the same frames: its problem, estimate, objective and nuisance rank."""

    model: str
    prob: _Problem
    T: np.ndarray
    boards: list
    cost: float
    dof: int


def _fit_model(prob: _Problem, model: str, labels: FrameLabels, active: list[int], inliers: list[int],
               T: np.ndarray, boards: list, floor: float, options: RefinementOptions) -> _ModelFit:
    terms = terms_for(model, labels, options.range_accuracy_m)
    # The model without terms in the same (range) form, so that the objectives compare.
    p = _Problem(prob.frames, prob.board, prob.camera, prob.sigma_px, prob.sigma_r, options,
                 terms if terms is not None else RangeTerms((), ()), labels)
    p.copy_edges(prob)
    b = list(boards)
    graph, result, _ = p.solve(active, T, b, floor)
    p.solved = (graph, result)  # the refinement goes on from this solution
    return _ModelFit(model, p, result.atPose3(EXTRINSIC).matrix(), b, _objective(p, graph, result, active, floor),
                     p.nuisance_rank(inliers))


def _model_test(small: _ModelFit, large: _ModelFit, active: list[int], inliers: list[int], floor: float,
                options: RefinementOptions) -> dict:
    """Whether the terms ``large`` adds to ``small`` are supported: a likelihood-ratio test at ``MODEL_TEST_P``.

    When the boards' planes disagree beyond the noise under the larger model (overdispersed data), the structure
    neither model explains would otherwise be read as a term: the per-board plane error is estimated under the
    larger model (method of moments, at most ``MAX_PLANE_ERROR_M``), both models are solved again with it in
    place, and the decrease of the objective, over the variance factor that remains (a quasi-likelihood scale:
    structure in the terms' own directions, which a plane error cannot hold), is referred to an F distribution
    (the error's size is itself estimated from the boards). Else the
    decrease is referred to chi-square with the added terms' degrees of freedom."""
    ddof = max(large.dof - small.dof, 1)
    stat, cdof = large.prob.consistency(inliers, large.T, large.boards, floor, active)
    dispersion = stat / cdof
    delta = small.cost - large.cost
    record = {"model": large.model, "against": small.model, "cost_decrease": float(delta), "added_dof": int(ddof),
              "variance_factor": float(dispersion), "consistency_dof": round(float(cdof), 2)}
    overdispersed = (chi2.sf(stat, cdof) < 0.01 and options.plane_floor_m is None and options.estimate_plane_floor)
    if overdispersed:
        p_l, p_s = large.prob, small.prob
        saved = [(p, p.beta.copy(), p.solved, p.tau) for p in (p_l, p_s)]
        T_l, b_l = large.T, large.boards
        if p_l.has_beta and chi2.sf(*p_l.term_consistency(inliers, T_l, b_l, floor)) < 0.01:
            T_l, b_l = _estimate_board_scatter(p_l, active, inliers, T_l, b_l, floor)[:2]
        if p_s.has_beta:
            p_s.tau = p_l.tau
        fl, (T_l, b_l, graph_l, result_l, _) = _match_moments(
            p_l, active, T_l, b_l, (1e-5, MAX_PLANE_ERROR_M), lambda v: v,
            lambda v, T_v, b_v: p_l.plane_cost(inliers, T_v, b_v, v) / cdof)
        # What the plane error leaves (structure in the terms' own directions, or beyond a plane error's physical
        # size) scales the test as a quasi-likelihood.
        scale = max(p_l.plane_cost(inliers, T_l, b_l, fl) / cdof, 1.0)
        b_s = list(small.boards)
        graph_s, result_s, _ = p_s.solve(active, small.T, b_s, fl)
        delta = (_objective(p_s, graph_s, result_s, active, fl) - _objective(p_l, graph_l, result_l, active, fl))
        scatter = p_l.tau
        for p, beta, solved, tau in saved:
            p.beta, p.solved, p.tau = beta, solved, tau
        p_value = float(fdtrc(ddof, cdof, max(delta, 0.0) / ddof / scale))
        record.update({"reference": f"F({ddof}, {cdof:.4g})", "plane_error_m": float(fl), "board_scatter_m": scatter,
                       "cost_decrease_with_plane_error": float(delta), "quasi_likelihood_scale": float(scale)})
    else:
        p_value = float(chi2.sf(max(delta, 0.0), ddof))
        record["reference"] = f"chi-square({ddof})"
    record.update({"p_value": p_value, "included": bool(p_value < MODEL_TEST_P)})
    return record


def _relative_consistency(fit: _ModelFit, base: _ModelFit, active: list[int], inliers: list[int], floor: float,
                          fit_test: dict, base_test: dict) -> tuple[float, float]:
    """How the boards agree under ``fit`` against under ``base`` (the global offset alone): the ratio of their
    variance factors and its p-value as F. Per-ring and black-square terms read structure within each board;
    when it differs from board to board, shared terms leave the boards worse than the offset alone. On
    overdispersed data the variance factors compared are those the boards' scatter and a per-board plane error
    of physical size leave (the tests' quasi-likelihood scales; when the offset's leaves none, the combination's is
    tested as chi-square on its own degrees of freedom), else the raw ones."""
    if "quasi_likelihood_scale" in fit_test and "quasi_likelihood_scale" in base_test:
        d1, d0 = fit_test["consistency_dof"], base_test["consistency_dof"]
        base_scale = base_test["quasi_likelihood_scale"]
        ratio = fit_test["quasi_likelihood_scale"] / max(base_scale, 1.0)
        if chi2.sf(base_scale * d0, d0) >= 0.01:
            # The offset alone leaves the boards consistent (its scatter and plane error of physical size explain
            # them): the combination must too, tested on its own degrees of freedom.
            return float(ratio), float(chi2.sf(fit_test["quasi_likelihood_scale"] * d1, d1))
    else:
        s1, d1 = fit.prob.consistency(inliers, fit.T, fit.boards, floor, active)
        s0, d0 = base.prob.consistency(inliers, base.T, base.boards, floor, active)
        ratio = (s1 / d1) / max(s0 / d0, 1.0)
    return float(ratio), float(fdtrc(d1, d0, ratio))


def _choose_range_model(prob: _Problem, active: list[int], inliers: list[int], T: np.ndarray, boards: list,
                        floor: float, options: RefinementOptions, labels: FrameLabels) -> tuple:
    """The range model to refine with (``solvers.range_model``): the requested one, or under ``auto`` the
    terms the data support (:func:`_model_test`): a global offset against none, then the per-ring and the
    black-square terms each against the offset (against none, with the offset, when the offset alone is not
    supported); both when both pass. A combination that leaves the boards'
    planes worse than the offset alone (:func:`_relative_consistency`, at 1%) tries the smaller ones before
    the offset alone. Returns the problem (solved at its estimate), the estimate and the record."""
    wanted = options.range_model
    models = ["none", "offset", "per-ring", "offset+dark", "full"] if wanted == "auto" else [wanted]
    fits: dict[str, _ModelFit] = {}
    seen = set()
    for model in models:  # a requested model is fitted, not tested
        terms = terms_for(model, labels, options.range_accuracy_m)
        key = terms.names if terms is not None else ()
        if key in seen:  # per-ring without rings, black squares without both colours: nothing new to test
            continue
        seen.add(key)
        fits[model] = _fit_model(prob, model, labels, active, inliers, T, boards, floor, options)
    record = dict(requested=wanted, range_accuracy_m=float(options.range_accuracy_m))
    if wanted != "auto":
        f = fits[wanted]
        got = f.prob.terms.model
        why = f"requested ({wanted})" + ("" if got == wanted else f"; the data allow only the {got} terms")
        return f.prob, f.T, f.boards, RangeModelFit(chosen=got, reason=why, names=f.prob.terms.names,
                                                    values_m=tuple(f.prob.beta.tolist()), terms=f.prob.terms, **record)
    tests = [_model_test(fits["none"], fits["offset"], active, inliers, floor, options)]
    # The per-ring and black-square blocks are tested against the offset when it is supported, else against none
    # (with the offset in the block): a strong within-board structure can hide a global offset that only its own
    # terms make visible.
    base = "offset" if tests[0]["included"] else "none"
    blocks, by_model = [], {"offset": tests[0]}
    for model in ("per-ring", "offset+dark"):
        if model in fits:
            tests.append(_model_test(fits[base], fits[model], active, inliers, floor, options))
            by_model[model] = tests[-1]
            if tests[-1]["included"]:
                blocks.append(model)
    if not blocks and base == "none":
        why = (f"no range term is supported by the data (p = {tests[0]['p_value']:.2g} for a global offset, test at "
               f"{MODEL_TEST_P}" + (", with the per-board plane error in place" if "plane_error_m" in tests[0] else "")
               + ")")
        return prob, T, boards, RangeModelFit(chosen="none", reason=why, tests=tuple(tests), **record)
    candidates = (["full"] if len(blocks) == 2 and "full" in fits else []) + blocks + [base]
    if candidates[0] == "full":
        by_model["full"] = _model_test(fits[base], fits["full"], active, inliers, floor, options)
    chosen, notes = base, []
    for model in candidates:
        if model == base:
            break
        ratio, p_rel = _relative_consistency(fits[model], fits["offset"], active, inliers, floor, by_model[model],
                                             tests[0])
        if p_rel >= 0.01:
            chosen = model
            break
        notes.append(f"the {model} terms left the boards' planes {ratio:.1f}x as inconsistent as the offset alone "
                     f"(p = {p_rel:.1g}): their within-board structure differs from board to board")
    if chosen == "none":
        why = ("no range term is kept: " + "; ".join(notes) + f" (a global offset alone: p = {tests[0]['p_value']:.2g}"
               f", test at {MODEL_TEST_P})")
        return prob, T, boards, RangeModelFit(chosen="none", reason=why, tests=tuple(tests), **record)
    f = fits[chosen]
    why = f"the {chosen} terms are supported (" + "; ".join(
        f"{t['model']} against {t['against']}: p = {t['p_value']:.2g}" for t in tests if t["included"]) + ")"
    if notes:
        why += "; " + "; ".join(notes) + f"; fell back to {chosen}"
    return f.prob, f.T, f.boards, RangeModelFit(chosen=chosen, reason=why, names=f.prob.terms.names,
                                                values_m=tuple(f.prob.beta.tolist()), tests=tuple(tests),
                                                terms=f.prob.terms, **record)


def _with_uncertainty(fit: RangeModelFit, prob: _Problem, marginals: gtsam.Marginals) -> RangeModelFit:
    """The record with the terms' final values, their marginal standard deviations, the share of the
    extrinsic's covariance due to them, the global offset's correlation with the translation, and the term
    most confounded with a direction of the extrinsic (its multiple correlation with the 6 parameters)."""
    keys = gtsam.KeyVector([EXTRINSIC, RANGE])
    J = marginals.jointMarginalCovariance(keys).fullMatrix()
    Cxx, Cxb, Cbb = J[:6, :6], J[:6, 6:], J[6:, 6:]
    share = Cxb @ np.linalg.solve(Cbb, Cxb.T)
    sd_b = np.sqrt(np.maximum(np.diag(Cbb), 0.0))
    corr = Cxb[3:, 0] / np.sqrt(np.maximum(np.diag(Cxx)[3:], 1e-300)) / max(sd_b[0], 1e-300)
    confounding = None
    best = (0.0, -1)
    for k in range(Cbb.shape[0]):
        if k in prob.pinned or sd_b[k] <= 0:
            continue
        r2 = float(Cxb[:, k] @ np.linalg.solve(Cxx, Cxb[:, k]) / Cbb[k, k])
        best = max(best, (r2, k))
    if best[1] >= 0 and np.sqrt(max(best[0], 0.0)) > CONFOUNDED_CORRELATION:
        k = best[1]
        g = np.linalg.solve(Cxx, Cxb[:, k])  # the extrinsic's combination most correlated with the term
        u = g / np.linalg.norm(g)
        part = "translation" if np.linalg.norm(u[3:]) >= np.linalg.norm(u[:3]) else "rotation"
        v = u[3:] if part == "translation" else u[:3]
        axis = int(np.argmax(np.abs(v)))
        direction = (f"the {part} {'along' if part == 'translation' else 'about'} the LiDAR's "
                     f"{'xyz'[axis]} axis" + ("" if abs(v[axis]) > 0.9 * np.linalg.norm(v) else
                                              f" (direction {np.round(v / np.linalg.norm(v), 2).tolist()})"))
        e = np.zeros(6)
        e[3 + axis if part == "translation" else axis] = 1.0
        unit, scale = ("mm", 1000.0) if part == "translation" else ("deg", float(np.degrees(1.0)))
        confounding = {"term": prob.terms.names[k], "correlation": float(np.sqrt(best[0])), "direction": direction,
                       "tangent_direction": u.tolist(), "unit": unit, "sd": float(scale * np.sqrt(e @ Cxx @ e)),
                       "sd_if_known": float(scale * np.sqrt(max(e @ (Cxx - share) @ e, 0.0))),
                       "advice": "Boards that face the LiDAR at varied incidence and distances separate them: "
                                 "`lidarcam layout DATASET --suggest 2 --range-offset` suggests the poses to add."}
    return replace(fit, values_m=tuple(prob.beta.tolist()), std_m=tuple(sd_b.tolist()), terms_covariance=Cbb,
                   extrinsic_share=0.5 * (share + share.T), offset_translation_correlation=tuple(corr.tolist()),
                   confounding=confounding)


def _consider_pinned(prob: _Problem, active: list[int], result: gtsam.Values, floor: float, fit: RangeModelFit
                     ) -> tuple[np.ndarray, RangeModelFit]:
    """The extrinsic's covariance with the pinned terms held at 0 and their prior variance propagated (a
    "consider" covariance): ``A^-1 + A^-1 B P B^T A^-1`` over the other variables, with ``A`` their information,
    ``B`` its coupling to the pinned terms and ``P`` the pinned terms' prior covariance. Also returns the record
    with that share in ``extrinsic_share`` and the pinned terms' standard deviations set to their priors."""
    H, _ = _hessian(prob.graph(active, floor, free_pinned=True), result, len(active))
    K = prob.terms.size
    n = H.shape[0] - K
    pinned = [n + k for k in prob.pinned]
    rest = [i for i in range(H.shape[0]) if i not in pinned]
    A, B = H[np.ix_(rest, rest)], H[np.ix_(rest, pinned)]
    P = np.diag(np.array(prob.terms.prior_sd)[list(prob.pinned)] ** 2)
    Ainv = np.linalg.pinv(A)  # A is the information of a solve that succeeded; pinv keeps a rank loss finite
    G = Ainv @ B
    cov_rest = Ainv + G @ P @ G.T
    cov = cov_rest[:6, :6]
    cond = np.linalg.pinv(H[:n, :n])[:6, :6]  # every term known
    std = list(fit.std_m)
    for k in prob.pinned:
        std[k] = float(prob.terms.prior_sd[k])
    share = cov - cond
    return 0.5 * (cov + cov.T), replace(fit, std_m=tuple(std), extrinsic_share=0.5 * (share + share.T))


def _consider_placement(prob: _Problem, active: list[int], T: np.ndarray, boards: list, floor: float,
                        cov: np.ndarray, fit: RangeModelFit) -> tuple[np.ndarray, RangeModelFit, np.ndarray]:
    """The black squares' placement propagated: the colours are placed under the estimate, itself uncertain, and
    a pattern placed a few millimetres off gives the returns near the squares' edges the wrong colour, which
    shrinks the black-square term (and, through it, moves the rest). Placed again under the extrinsic moved by
    one standard deviation each way along each principal direction of ``cov`` and solved again (one Gauss-Newton
    step): the shifts' spread is added to the covariance ("consider" covariance, as for pinned terms and
    intrinsics), and their mean, summed over the directions, is the shrinkage that the estimate's own error
    causes on average (second order): it is taken off the terms and the extrinsic, and its square kept in the
    covariance. Returns the covariance, the record and the extrinsic."""
    ev, V = np.linalg.eigh(0.5 * (cov + cov.T))
    values = prob.values(active, T, boards)
    K = prob.terms.size
    extra = np.zeros((6 + K, 6 + K))
    bias = np.zeros(6 + K)
    for lam, v in zip(ev, V.T):
        shifts = []
        for sign in (1.0, -1.0):
            T_moved = T @ T_exp(sign * np.sqrt(max(lam, 0.0)) * v)
            labels = frame_labels(prob.frames, prob.board, T_moved, boards, prob.labels.placement_cov)
            moved = prob.variant(labels=replace(prob.labels, dark=labels.dark))
            # One Gauss-Newton step from the estimate: the shift the new colours call for, to first order.
            delta = moved.graph(active, floor).linearize(values).optimize()
            shifts.append(np.concatenate([delta.at(EXTRINSIC), delta.at(RANGE)]))
        spread, shrink = 0.5 * (shifts[0] - shifts[1]), 0.5 * (shifts[0] + shifts[1])
        extra += np.outer(spread, spread) + np.outer(shrink, shrink)
        bias += shrink
    std = np.sqrt(np.array(fit.std_m) ** 2 + np.diag(extra)[6:])
    Cbb = fit.terms_covariance + extra[6:, 6:] if fit.terms_covariance is not None else None
    if np.any(np.abs(bias[6:]) > std):  # beyond second order (a term the data barely hold): not corrected
        bias[:] = 0.0
    prob.beta = prob.beta - bias[6:]
    return (cov + extra[:6, :6], replace(fit, values_m=tuple(prob.beta.tolist()), std_m=tuple(std.tolist()),
                                         terms_covariance=Cbb), T @ T_exp(-bias[:6]))


def _intrinsics_covariance(prob: _Problem, active: list[int], T: np.ndarray, boards: list, floor: float,
                           options: RefinementOptions) -> np.ndarray:
    """First-order covariance of the extrinsic due to uncertain intrinsics: re-solve with the parameters moved
    by one standard deviation along each principal direction of their covariance (each parameter alone when only
    standard deviations are known) and sum the outer products of the shifts. Intrinsics estimated from the images
    (OpenCV's, or refined here) are in OpenCV's convention, scaled like the corner noise by the correlation
    factor; stated ones (dataset.yaml) are taken as they are."""
    cam = prob.camera
    scale = options.corner_error_correlation if options.corner_noise_px is None and cam.source != "dataset.yaml" \
        else 1.0
    if cam.param_covariance is not None:
        ev, V = np.linalg.eigh(0.5 * (cam.param_covariance + cam.param_covariance.T))
        steps = [scale * np.sqrt(max(lam, 0.0)) * v for lam, v in zip(ev, V.T)]
    else:
        steps = [scale * s * np.eye(len(cam.param_std))[k] for k, s in enumerate(cam.param_std)
                 if np.isfinite(s) and s > 0]
    out = np.zeros((6, 6))
    for step in steps:
        moved = prob.variant(camera=cam.with_params(cam.params + step))
        _, result, _ = moved.solve(active, T, list(boards), floor)
        xi = T_log(np.linalg.inv(T) @ result.atPose3(EXTRINSIC).matrix())
        out += np.outer(xi, xi)
    return out


def _flag_outliers(chi: dict, frames, T, boards, options) -> dict[int, str]:
    """Frames whose plane residual is extreme for chi-square (3 dof for a plane, 2 for a scan line),
    relative to the typical frame (so that a rig whose noise is underestimated overall does not flag
    every frame)."""
    dof = {i: 2 if frames[i].lidar.is_scan_line else 3 for i in chi}
    typical = max(1.0, float(np.median([c / chi2.median(dof[i]) for i, c in chi.items()])))
    out = {}
    for i, c in chi.items():
        limit = chi2.isf(options.outlier_p, dof[i]) * typical
        if c > limit:
            f = frames[i]
            n = boards[i][:3, 2]
            if f.lidar.is_scan_line:
                what = "its laser line is off the camera's board"
            else:
                angle, dist = plane_difference(f.lidar.plane.transformed(T), Plane(n, n @ boards[i][:3, 3]))
                what = (f"its LiDAR plane disagrees with the camera's board by {np.degrees(angle):.2f} deg and "
                        f"{1000 * dist:.0f} mm")
            out[i] = (f"{what} (consistency chi-square {c:.0f} on {dof[i]} dof, limit {limit:.0f}): a wrong LiDAR "
                      "segment, or the board moved between image and scan")
    return out
