"""Maximum-likelihood refinement of ``T_camera_lidar`` on a GTSAM factor graph, with its covariance.

The graph (MATH.md sections 2, 3, 6): the extrinsic and one board pose per frame; a corner factor per
frame (reprojection through the dataset's camera model) and a plane factor per frame (the board points'
exact sufficient statistics, in range units). Plane factors may carry a robust loss (Huber or Cauchy on
the whitened norm of the frame's 3-vector); frames whose planes disagree with their board beyond the
noise are flagged, and dropped or down-weighted.

Noise levels:
- ``range_noise_m``: given, or pooled from the board points' residuals about their best planes.
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
factors (a global offset, per-ring offsets, a black-square offset) in one vector variable with a prior; under
``auto`` each is added while a likelihood-ratio test at 1% supports it. Per-ring and black-square terms that
leave the boards inconsistent fall back to the global offset (their within-board structure then differs from
board to board, which a shared term cannot hold).

The covariance is ``gtsam.Marginals`` of the extrinsic, in GTSAM's right tangent: ``T_true = T_hat Exp(xi)``,
``xi = [rot; trans]``.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import gtsam
import numpy as np
from scipy.stats import chi2

from geometry.board import BoardModel
from geometry.camera import CameraModel
from geometry.planes import Plane, plane_difference
from geometry.rotations import T_log

from ..errors import DegenerateLayoutError
from ..measurements import FrameMeasurement
from .closed_form import describe_direction, solve_closed_form
from .factors import (corner_factor, corner_residuals, lidar_plane, lidar_residual, nuisance_plane_factor,
                      nuisance_residual, plane_factor)
from .range_model import (MODEL_TEST_P, RANGE_MODELS, FrameLabels, RangeModelFit, RangeTerms, frame_labels,
                          frame_whiteners, terms_for)

ROBUST_LOSSES = ("none", "huber", "cauchy")
OUTLIER_POLICIES = ("drop", "downweight")
# Effective per-corner noise over the corner residual on rendered images (see the module docstring;
# `make bench` prints the value it measures).
CORNER_ERROR_CORRELATION = 1.4
# Relative scale error of a board's detected corner pattern (per board, independent): it moves the board's
# distance by this fraction, the same way for every corner, which independent corner noise cannot
# represent. Measured on this toolkit's rendered images after cornerSubPix (rms 1.1e-4; `make bench`).
CORNER_SCALE_SD = 1.0e-4
EXTRINSIC = gtsam.symbol("x", 0)
RANGE = gtsam.symbol("r", 0)  # the LiDAR range model's nuisance vector


def board_key(i: int) -> int:
    return gtsam.symbol("b", i)


@dataclass(frozen=True)
class RefinementOptions:
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
    corner_scale_sd: float = CORNER_SCALE_SD
    # The LiDAR range model (``solvers.range_model``): none, offset, per-ring, full, or auto (chosen by test).
    range_model: str = "none"

    def __post_init__(self):
        if self.robust not in ROBUST_LOSSES:
            raise ValueError(f"Expected robust in {ROBUST_LOSSES}, got {self.robust!r}")
        if self.outliers not in OUTLIER_POLICIES:
            raise ValueError(f"Expected outliers in {OUTLIER_POLICIES}, got {self.outliers!r}")
        if self.range_model not in RANGE_MODELS:
            raise ValueError(f"Expected range_model in {RANGE_MODELS}, got {self.range_model!r}")
        for name in ("corner_noise_px", "range_noise_m", "plane_floor_m"):
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
    consistency_dof: int
    consistency_p: float
    iterations: int
    warnings: tuple[str, ...] = ()
    # The part of ``covariance`` due to intrinsics calibrated from the same images (None when given).
    intrinsics_covariance: np.ndarray | None = None
    corner_scale_sd: float = 0.0
    range_model: RangeModelFit | None = None


def corner_residual_px(frames: list[FrameMeasurement], board: BoardModel, camera: CameraModel) -> float:
    """Pooled per-axis corner residual of the per-frame board poses (``2M - 6`` dof per frame)."""
    ss, dof = 0.0, 0
    for f in frames:
        r, _ = corner_residuals(f.camera.T_camera_board, board.inner_corners(), f.camera.corners_px, camera)
        ss += float(r @ r)
        dof += r.size - 6
    return float(np.sqrt(ss / max(dof, 1)))


def pooled_range_noise_m(frames: list[FrameMeasurement]) -> float:
    """Range noise pooled over the frames' best-fit plane residuals (``n - 3`` dof per frame)."""
    fitted = [2 if f.lidar.is_scan_line else 3 for f in frames]
    ss = sum(f.lidar.range_rms_m**2 * max(f.lidar.n_points - k, 1) for f, k in zip(frames, fitted))
    dof = sum(max(f.lidar.n_points - k, 1) for f, k in zip(frames, fitted))
    return float(np.sqrt(ss / dof))


def _robust(noise: gtsam.noiseModel.Base, options: RefinementOptions) -> gtsam.noiseModel.Base:
    if options.robust == "huber":
        return gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(options.robust_threshold), noise)
    if options.robust == "cauchy":
        return gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Cauchy.Create(options.robust_threshold), noise)
    return noise


def _robust_weight(e_norm: float, options: RefinementOptions) -> float:
    k = options.robust_threshold
    if options.robust == "huber":
        return 1.0 if e_norm <= k else k / e_norm
    if options.robust == "cauchy":
        return 1.0 / (1.0 + (e_norm / k) ** 2)
    return 1.0


def _plane_noise(W: np.ndarray, normal: np.ndarray, sigma_r: float, floor_m: float, half_size_m: float,
                 scale_m: float = 0.0) -> np.ndarray:
    """Covariance of a plane factor's residual ``W pi``: the points' range noise, plus a per-board plane
    error (``floor_m`` in distance and at the board's edge) when the data call for one, plus the distance
    error ``scale_m`` of the camera's board from a scale error of its detected pattern."""
    cov = sigma_r**2 * np.eye(W.shape[0])
    if floor_m > 0 or scale_m > 0:
        S = np.zeros((4, 4))
        S[:3, :3] = (np.eye(3) - np.outer(normal, normal)) * (floor_m / half_size_m) ** 2
        S[3, 3] = floor_m**2 + scale_m**2
        cov = cov + W @ S @ W.T
    return cov


class _Problem:
    """The data of one refinement: per frame its plane whitener, the plane noise, the corner noise, and the
    range model's terms (None: none) with their current values ``beta``."""

    def __init__(self, frames: list[FrameMeasurement], board: BoardModel, camera: CameraModel, sigma_px: float,
                 sigma_r: float, options: RefinementOptions, terms: RangeTerms | None = None,
                 labels: FrameLabels | None = None):
        self.frames, self.board, self.camera = frames, board, camera
        self.sigma_px, self.sigma_r, self.options = sigma_px, sigma_r, options
        self.terms, self.labels = terms, labels
        # Noise-corrected at the noise the data show (not at a given sigma_r, which sets the weights only).
        self.fw = frame_whiteners(frames, pooled_range_noise_m(frames), terms, labels)
        self.whiteners = [w.W for w in self.fw]
        self.beta = np.zeros(terms.size if terms else 0)
        self.corners_board = board.inner_corners()
        self.pnp_chi2 = [self.corner_chi2(i, f.camera.T_camera_board) for i, f in enumerate(frames)]

    def whitener(self, i: int) -> np.ndarray:
        return self.whiteners[i]

    def nuisance_rank(self, frames: list[int]) -> int:
        """How many combinations of the nuisance terms the frames' points determine."""
        if self.terms is None:
            return 0
        rows = []
        for i in frames:
            G = np.zeros((self.whiteners[i].shape[0], self.terms.size))
            G[:, self.fw[i].cols] = self.fw[i].W_nuisance
            rows.append(G)
        return _rank(np.vstack(rows))

    def residual(self, i: int, T: np.ndarray, T_board: np.ndarray) -> np.ndarray:
        pi, _, _ = lidar_plane(T, T_board)
        scan = self.frames[i].lidar.is_scan_line
        if self.terms is None:
            return lidar_residual(self.whitener(i), pi, scan)[0]
        fw = self.fw[i]
        return nuisance_residual(fw.W, fw.cols, fw.m_away, pi, self.beta, scan)[0]

    def plane_cov(self, i: int, floor_m: float) -> np.ndarray:
        f = self.frames[i]
        cov = _plane_noise(self.whitener(i)[:, :4], f.lidar.plane.normal, self.sigma_r, floor_m,
                           0.5 * float(np.mean(self.board.extent)),
                           self.options.corner_scale_sd * f.camera.plane.distance)
        return cov

    def graph(self, active: list[int], floor_m: float, robust: bool = True) -> gtsam.NonlinearFactorGraph:
        graph = gtsam.NonlinearFactorGraph()
        corners_board = self.corners_board
        if self.terms is not None:
            graph.add(gtsam.PriorFactorVector(RANGE, np.zeros(self.terms.size),
                                              gtsam.noiseModel.Diagonal.Sigmas(np.array(self.terms.prior_sd))))
        for j, i in enumerate(active):
            f = self.frames[i]
            key = board_key(j)
            graph.add(corner_factor(key, corners_board, f.camera.corners_px, self.camera,
                                    gtsam.noiseModel.Isotropic.Sigma(f.camera.corners_px.size, self.sigma_px)))
            noise = gtsam.noiseModel.Gaussian.Covariance(self.plane_cov(i, floor_m))
            noise = _robust(noise, self.options) if robust else noise
            if self.terms is None:
                graph.add(plane_factor(EXTRINSIC, key, self.whitener(i), noise, f.lidar.is_scan_line))
            else:
                fw = self.fw[i]
                graph.add(nuisance_plane_factor(EXTRINSIC, key, RANGE, fw.W, fw.cols, fw.m_away, noise,
                                                f.lidar.is_scan_line))
        return graph

    def full_chi2(self, i: int, T: np.ndarray, T_board: np.ndarray, floor_m: float) -> float:
        """The frame's whole whitened LiDAR residual (its plane and, with range terms, how far its own best
        range offsets are from the shared ones)."""
        e = self.residual(i, T, T_board)
        return float(e @ np.linalg.solve(self.plane_cov(i, floor_m), e))

    def plane_chi2(self, i: int, T: np.ndarray, T_board: np.ndarray, floor_m: float) -> float:
        """The part of the frame's LiDAR residual that no range offsets of its own could explain: how far its
        camera and LiDAR planes disagree (``plane_dof`` degrees of freedom). Without range terms, all of it."""
        e = self.residual(i, T, T_board)
        L = np.linalg.cholesky(self.plane_cov(i, floor_m))
        z = np.linalg.solve(L, e)
        if self.terms is not None and self.fw[i].W_nuisance.size:
            G = np.linalg.solve(L, self.fw[i].W_nuisance)
            z = z - G @ np.linalg.lstsq(G, z, rcond=None)[0]
        return float(z @ z)

    def plane_dof(self, i: int) -> int:
        Wb = self.fw[i].W_nuisance
        return int(self.whitener(i).shape[0] - (_rank(Wb) if Wb.size else 0))

    def range_consistency(self, frames: list[int], T: np.ndarray, boards: list, floor_m: float) -> tuple[float, int]:
        """How far the frames' own best range offsets disagree with the shared terms (chi-square, dof), or
        (0, 0) without range terms."""
        if self.terms is None:
            return 0.0, 0
        stat = sum(self.full_chi2(i, T, boards[i], floor_m) - self.plane_chi2(i, T, boards[i], floor_m)
                   for i in frames)
        dof = sum(self.whitener(i).shape[0] - self.plane_dof(i) for i in frames) - self.nuisance_rank(frames)
        return float(stat), int(max(dof, 1))

    def total_cost(self, active: list[int], T: np.ndarray, boards: list) -> float:
        """The whole (non-robust, no plane error) cost of the frames at the estimate: corners, every board
        point's squared range error (the best fits' floors included, so that models with other terms
        compare), and the nuisance prior."""
        cost = sum(self.full_chi2(i, T, boards[i], 0.0) + self.corner_chi2(i, boards[i])
                   + self.fw[i].floor / self.sigma_r**2 for i in active)
        if self.terms is not None:
            cost += float(np.sum((self.beta / np.array(self.terms.prior_sd)) ** 2))
        return float(cost)

    def corner_chi2(self, i: int, T_board: np.ndarray) -> float:
        f = self.frames[i]
        r, _ = corner_residuals(T_board, self.corners_board, f.camera.corners_px, self.camera, jacobian=False)
        return float(r @ r) / self.sigma_px**2

    def frame_chi2(self, i: int, T: np.ndarray, T_board: np.ndarray, floor_m: float) -> float:
        """The frame's share of the consistency statistic: its plane residual plus how far its board had
        to move from the camera's own fit (a cheap camera lets a bad LiDAR plane drag the board)."""
        return self.full_chi2(i, T, T_board, floor_m) + self.corner_chi2(i, T_board) - self.pnp_chi2[i]

    def solve(self, active: list[int], T: np.ndarray, boards: list, floor_m: float
              ) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values, int]:
        values = gtsam.Values()
        values.insert(EXTRINSIC, gtsam.Pose3(T))
        for j, i in enumerate(active):
            values.insert(board_key(j), gtsam.Pose3(boards[i]))
        if self.terms is not None:
            values.insert(RANGE, self.beta.copy())
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
        if self.terms is not None:
            self.beta = np.asarray(result.atVector(RANGE), dtype=float)
        return graph, result, int(opt.iterations())

    def consistency(self, frames: list[int], T: np.ndarray, boards: list, floor_m: float) -> tuple[float, int]:
        """The cost the camera alone cannot explain, summed over ``frames`` (chi-square with ``3 N - 6``
        dof under the model)."""
        stat = sum(self.frame_chi2(i, T, boards[i], floor_m) for i in frames)
        return stat, max(sum(self.whitener(i).shape[0] for i in frames) - 6 - self.nuisance_rank(frames), 1)


def _rank(A: np.ndarray) -> int:
    """Numerical rank, relative tolerance 1e-8 (the range regressors' exact collinearities, a global offset
    and the per-ring offsets, survive the square root only to about 1e-10)."""
    sv = np.linalg.svd(A, compute_uv=False)
    return int(np.sum(sv > 1e-8 * sv[0])) if sv.size and sv[0] > 0 else 0


def _degenerate(graph, values, n_frames: int) -> DegenerateLayoutError:
    """Explain a singular system by the extrinsic's least-informed direction."""
    ordering = gtsam.Ordering()
    ordering.push_back(EXTRINSIC)
    for j in range(n_frames):
        ordering.push_back(board_key(j))
    if values.exists(RANGE):
        ordering.push_back(RANGE)
    H, _ = graph.linearize(values).hessian(ordering)
    A, B, C = H[:6, :6], H[:6, 6:], H[6:, 6:]
    info = A - B @ np.linalg.pinv(C) @ B.T
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


def refine(frames: list[FrameMeasurement], board: BoardModel, camera: CameraModel, T_init: np.ndarray,
           options: RefinementOptions = RefinementOptions()) -> Refinement:
    """Refine ``T_camera_lidar`` from the usable frames, starting at ``T_init``."""
    frames = [f for f in frames if f.usable]
    if len(frames) < 3:
        raise DegenerateLayoutError(f"only {len(frames)} usable frame(s); refinement needs at least 3")
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
    prob0, start = prob, (T, list(boards))
    prob, T, boards, model_fit = _choose_range_model(prob, active, inliers, T, boards, floor, options)
    if prob.terms is not None and prob.terms.model != "offset" and options.plane_floor_m is None:
        stat, dof = prob.consistency(inliers, T, boards, floor)
        if chi2.sf(stat, dof) < 0.01:
            # Per-ring and reflectivity terms read structure within each board; when that structure differs
            # from board to board beyond the noise, a shared term cannot hold it (and the plane error cannot
            # absorb it): fall back to the global offset, which only the camera informs.
            why = (f"{model_fit.chosen} terms left the boards inconsistent (chi-square {stat:.0f} on {dof} dof): their "
                   "within-board structure differs from board to board; fell back to the global offset")
            prob, T, boards, model_fit = _choose_range_model(prob0, active, inliers, start[0], start[1], floor,
                                                             replace(options, range_model="offset"))
            model_fit = replace(model_fit, requested=options.range_model, reason=why)
            warnings.append(f"range model: {why}")
    if prob.terms is not None:
        graph, result, its = prob.solve(active, T, boards, floor)
        iterations += its
    stat, dof = prob.consistency(inliers, T, boards, floor)
    variance_factor, p_value = stat / dof, float(chi2.sf(stat, dof))
    if p_value < 0.01 and options.plane_floor_m is None and options.estimate_plane_floor:
        # The planes disagree beyond the point and corner noise (real sensors: range biases per laser,
        # imperfect intrinsics). Model it as a per-board plane error, its size estimated so that the
        # consistency statistic equals its degrees of freedom (method of moments), then solve again.
        lo, hi = 1e-5, 0.5
        start = (T, list(boards), prob.beta.copy())  # every trial starts from the fit without the error
        for _ in range(14):
            floor = float(np.sqrt(lo * hi))
            boards, prob.beta = list(start[1]), start[2].copy()
            graph, result, its = prob.solve(active, start[0], boards, floor)
            iterations += its
            T = result.atPose3(EXTRINSIC).matrix()
            if prob.consistency(inliers, T, boards, floor)[0] > dof:
                lo = floor
            else:
                hi = floor
        floor = hi
        boards, prob.beta = list(start[1]), start[2].copy()
        graph, result, its = prob.solve(active, start[0], boards, floor)
        T = result.atPose3(EXTRINSIC).matrix()
        warnings.append(f"the boards' camera and LiDAR planes disagree more than the point and corner noise explain "
                        f"(chi-square {stat:.0f} on {dof} dof, p = {p_value:.1g}); a per-board plane error of "
                        f"{1000 * floor:.1f} mm, estimated from the data, is included in the covariance")

    try:
        marginals = gtsam.Marginals(graph, result)
        cov = marginals.marginalCovariance(EXTRINSIC)
        if model_fit is not None and prob.terms is not None:
            model_fit = _with_uncertainty(model_fit, prob, marginals)
    except RuntimeError as exc:
        raise _degenerate(graph, result, len(active)) from exc
    ev = np.linalg.eigvalsh(cov) if np.all(np.isfinite(cov)) else np.array([0.0, 1.0])
    if ev[0] <= 0 or ev[0] / ev[-1] < MIN_INFORMATION_RATIO:
        raise _degenerate(graph, result, len(active))

    if model_fit is not None and prob.terms is not None:
        r_stat, r_dof = prob.range_consistency(inliers, T, boards, floor)
        model_fit = replace(model_fit, range_consistency={
            "chi2": r_stat, "dof": r_dof, "p_value": float(chi2.sf(r_stat, r_dof)),
            "meaning": "how far each board's own best range offsets are from the shared terms"})
    cov_intrinsics = None
    if camera.param_std is not None:
        cov_intrinsics = _intrinsics_covariance(prob, active, T, boards, floor, options)
        cov = cov + cov_intrinsics
        warnings.append("intrinsics were calibrated from the same images; their uncertainty is propagated "
                        "into the covariance (first order, parameters taken as independent)")

    fits = []
    for i, f in enumerate(frames):
        c2 = prob.plane_chi2(i, T, boards[i], floor)
        corner = prob.corner_chi2(i, boards[i])
        why = dropped.get(i) or flagged.get(i)
        fits.append(FrameFit(f.name, c2, c2 + corner - prob.pnp_chi2[i], prob.plane_dof(i),
                             float(sigma_px * np.sqrt(corner / f.camera.corners_px.size)),
                             0.0 if i in dropped else _robust_weight(np.sqrt(c2), options), why, i in dropped))
        if why:
            action = "dropped" if i in dropped else "down-weighted"
            warnings.append(f"frame {f.name}: {why}; {action}")
    return Refinement(T, cov, {f.name: boards[i] for i, f in enumerate(frames)}, tuple(fits), float(sigma_px),
                      resid_px, float(sigma_r), float(floor), float(variance_factor), dof, p_value, iterations,
                      tuple(warnings), cov_intrinsics, options.corner_scale_sd, model_fit)


def _choose_range_model(prob: _Problem, active: list[int], inliers: list[int], T: np.ndarray, boards: list,
                        floor: float, options: RefinementOptions) -> tuple:
    """The range model to refine with (``solvers.range_model``): the requested one, or under ``auto`` the
    terms that the data support, added in order while each passes a likelihood-ratio test at 1% on the whole
    cost of the inlier frames. Returns the problem (solved at its estimate), the estimate and the record."""
    if options.range_model == "none":
        return prob, T, boards, None
    labels = frame_labels(prob.frames)
    order = ["none", "offset", "per-ring", "full"]
    wanted = options.range_model
    models = order if wanted == "auto" else ["none", wanted]
    tests, fits, seen = [], {}, set()
    for model in models:
        terms = terms_for(model, labels)
        key = terms.names if terms is not None else ()
        if key in seen:  # per-ring without rings, full without black/white labels: nothing new to test
            continue
        seen.add(key)
        p = prob if model == "none" else _Problem(prob.frames, prob.board, prob.camera, prob.sigma_px, prob.sigma_r,
                                                  options, terms, labels)
        b, T_m = list(boards), T
        if model != "none":
            T_m = p.solve(active, T, b, floor)[1].atPose3(EXTRINSIC).matrix()
        cost = p.total_cost(inliers, T_m, b)
        dof = p.nuisance_rank(inliers)
        fits[model] = (p, T_m, b, cost, dof)
    chosen, why = "none", "no range term tested"
    for model in [m for m in models if m in fits and m != "none"]:
        base = fits[chosen]
        p, T_m, b, cost, dof = fits[model]
        delta, ddof = base[3] - cost, max(dof - base[4], 1)
        p_value = float(chi2.sf(max(delta, 0.0), ddof))
        accept = wanted != "auto" or p_value < MODEL_TEST_P
        tests.append({"model": model, "against": chosen, "cost_decrease": float(delta), "added_dof": int(ddof),
                      "p_value": p_value, "included": bool(accept)})
        if accept:
            chosen = model
            why = (f"requested ({model})" if wanted != "auto" else
                   f"the {model} terms lower the cost by {delta:.1f} on {ddof} dof (p = {p_value:.2g} < {MODEL_TEST_P})")
        elif wanted == "auto":
            break
    if chosen == "none":
        if wanted == "auto":
            why = (f"no range term is supported by the data (likelihood-ratio test at {MODEL_TEST_P}: "
                   f"p = {tests[0]['p_value']:.2g} for a global offset)" if tests else "no range term could be tested")
        return prob, T, boards, RangeModelFit(wanted, "none", why, tests=tuple(tests))
    p, T_m, b, _, _ = fits[chosen]
    return p, T_m, b, RangeModelFit(wanted, chosen, why, p.terms.names, tuple(p.beta.tolist()), tests=tuple(tests),
                                    terms=p.terms)


def _with_uncertainty(fit: RangeModelFit, prob: _Problem, marginals: gtsam.Marginals) -> RangeModelFit:
    """The record with the terms' final values, their marginal standard deviations, the share of the
    extrinsic's covariance due to them, and the global offset's correlation with the translation."""
    keys = gtsam.KeyVector([EXTRINSIC, RANGE])
    J = marginals.jointMarginalCovariance(keys).fullMatrix()
    Cxx, Cxb, Cbb = J[:6, :6], J[:6, 6:], J[6:, 6:]
    share = Cxb @ np.linalg.solve(Cbb, Cxb.T)
    sd_b = np.sqrt(np.maximum(np.diag(Cbb), 0.0))
    corr = Cxb[3:, 0] / np.sqrt(np.maximum(np.diag(Cxx)[3:], 1e-300)) / max(sd_b[0], 1e-300)
    return replace(fit, values_m=tuple(prob.beta.tolist()), std_m=tuple(sd_b.tolist()),
                   extrinsic_share=0.5 * (share + share.T), offset_translation_correlation=tuple(corr.tolist()))


def _intrinsics_covariance(prob: _Problem, active: list[int], T: np.ndarray, boards: list, floor: float,
                           options: RefinementOptions) -> np.ndarray:
    """First-order covariance of the extrinsic due to uncertain intrinsics: re-solve with each parameter
    moved by one standard deviation (OpenCV's, scaled like the corner noise by the correlation factor)
    and sum the outer products of the shifts."""
    cam = prob.camera
    std = cam.param_std * (options.corner_error_correlation if options.corner_noise_px is None else 1.0)
    out = np.zeros((6, 6))
    for k, s in enumerate(std):
        if not (np.isfinite(s) and s > 0):
            continue
        p = cam.params.copy()
        p[k] += s
        moved = _Problem(prob.frames, prob.board, cam.with_params(p), prob.sigma_px, prob.sigma_r, options,
                         prob.terms, prob.labels)
        moved.beta = prob.beta.copy()
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
