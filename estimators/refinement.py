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
- After the fit, the plane-consistency statistic (how far each board's camera and LiDAR planes
  disagree, in units of their noise; chi-square with ``3 N - 6`` degrees of freedom under the model)
  is tested; when the model is rejected at 1%, the covariance is inflated by the variance factor.

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
from geometry.planes import Plane, plane_difference, sqrt_excess_moment

from .closed_form import describe_direction
from .errors import DegenerateLayoutError
from .factors import corner_factor, corner_residuals, lidar_plane, plane_factor
from .measurements import FrameMeasurement

ROBUST_LOSSES = ("none", "huber", "cauchy")
OUTLIER_POLICIES = ("drop", "downweight")
# Effective per-corner noise over the corner residual on rendered images (see the module docstring;
# `make bench` prints the value it measures).
CORNER_ERROR_CORRELATION = 4.0
EXTRINSIC = gtsam.symbol("x", 0)


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
    outlier_p: float = 1e-3
    inflate_inconsistent: bool = True
    max_iterations: int = 100

    def __post_init__(self):
        if self.robust not in ROBUST_LOSSES:
            raise ValueError(f"Expected robust in {ROBUST_LOSSES}, got {self.robust!r}")
        if self.outliers not in OUTLIER_POLICIES:
            raise ValueError(f"Expected outliers in {OUTLIER_POLICIES}, got {self.outliers!r}")
        for name in ("corner_noise_px", "range_noise_m"):
            v = getattr(self, name)
            if v is not None and not (np.isfinite(v) and v > 0):
                raise ValueError(f"Expected {name} to be positive, got {v}")


@dataclass(frozen=True)
class FrameFit:
    """How one frame fits the estimate. ``plane_chi2`` is the frame's plane residual in units of the
    range noise (chi-square with ``plane_dof`` degrees of freedom when all is well)."""

    name: str
    plane_chi2: float
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
    variance_factor: float
    consistency_dof: int
    consistency_p: float
    iterations: int
    warnings: tuple[str, ...] = ()


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
    ss = sum(f.lidar.range_rms_m**2 * max(f.lidar.n_points - 3, 1) for f in frames)
    dof = sum(max(f.lidar.n_points - 3, 1) for f in frames)
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


def _build(frames, board, camera, T_init, boards_init, sigma_px, sigma_r, options, robust=True):
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    values.insert(EXTRINSIC, gtsam.Pose3(T_init))
    corners_board = board.inner_corners()
    whiteners = []
    for i, f in enumerate(frames):
        key = board_key(i)
        values.insert(key, gtsam.Pose3(boards_init[i]))
        M = f.camera.corners_px.size
        graph.add(corner_factor(key, corners_board, f.camera.corners_px, camera,
                                gtsam.noiseModel.Isotropic.Sigma(M, sigma_px)))
        W, _ = sqrt_excess_moment(f.lidar.unbiased_range_moment(sigma_r))
        whiteners.append(W)
        noise = gtsam.noiseModel.Isotropic.Sigma(W.shape[0], sigma_r)
        graph.add(plane_factor(EXTRINSIC, key, W, _robust(noise, options) if robust else noise))
    return graph, values, whiteners


def _optimize(graph, values, options) -> tuple[gtsam.Values, int]:
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(options.max_iterations)
    params.setRelativeErrorTol(1e-12)
    params.setAbsoluteErrorTol(1e-12)
    opt = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    result = opt.optimize()
    return result, int(opt.iterations())


def _pnp_chi2(frames, board, camera, sigma_px) -> np.ndarray:
    return np.array([float(np.sum(corner_residuals(f.camera.T_camera_board, board.inner_corners(),
                                                   f.camera.corners_px, camera)[0] ** 2)) / sigma_px**2
                     for f in frames])


def _degenerate(graph, values, frames) -> DegenerateLayoutError:
    """Explain a singular system by the extrinsic's least-informed direction."""
    ordering = gtsam.Ordering()
    ordering.push_back(EXTRINSIC)
    for i in range(len(frames)):
        ordering.push_back(board_key(i))
    H, _ = graph.linearize(values).hessian(ordering)
    A, B, C = H[:6, :6], H[:6, 6:], H[6:, 6:]
    info = A - B @ np.linalg.pinv(C) @ B.T
    vals, vecs = np.linalg.eigh(info)
    weak = vecs[:, 0]
    part = "rotation" if np.linalg.norm(weak[:3]) > np.linalg.norm(weak[3:]) else "translation"
    axis, advice = describe_direction(weak[:3] if part == "rotation" else weak[3:])
    return DegenerateLayoutError(
        f"the {len(frames)} frames leave the extrinsic's {part} unobservable (information {vals[0]:.2g} "
        f"against {vals[-1]:.2g}; weakest direction {np.round(weak, 2).tolist()} in the LiDAR tangent)",
        hint=f"record more board poses; {advice}")


def refine(frames: list[FrameMeasurement], board: BoardModel, camera: CameraModel, T_init: np.ndarray,
           options: RefinementOptions = RefinementOptions()) -> Refinement:
    """Refine ``T_camera_lidar`` from the usable frames, starting at ``T_init``."""
    frames = [f for f in frames if f.usable]
    if len(frames) < 3:
        raise DegenerateLayoutError(f"only {len(frames)} usable frame(s); refinement needs at least 3")
    resid_px = corner_residual_px(frames, board, camera)
    sigma_px = options.corner_noise_px or max(resid_px, 1e-3) * options.corner_error_correlation
    sigma_r = options.range_noise_m or max(pooled_range_noise_m(frames), 1e-5)
    warnings: list[str] = []

    active = list(range(len(frames)))
    dropped: dict[int, str] = {}
    flagged: dict[int, str] = {}
    T, boards = T_init, [f.camera.T_camera_board for f in frames]
    iterations = 0
    for _ in range(4):
        sub = [frames[i] for i in active]
        graph, values, whiteners = _build(sub, board, camera, T, [boards[i] for i in active], sigma_px, sigma_r,
                                          options)
        result, its = _optimize(graph, values, options)
        iterations += its
        T = result.atPose3(EXTRINSIC).matrix()
        for j, i in enumerate(active):
            boards[i] = result.atPose3(board_key(j)).matrix()
        chi = {i: _plane_chi2(whiteners[j], T, boards[i], sigma_r) for j, i in enumerate(active)}
        flagged = _flag_outliers(chi, frames, T, boards, options)
        new = {i: why for i, why in flagged.items() if i not in dropped}
        if options.outliers != "drop" or not new:
            break
        if len(active) - len(new) < 3:
            warnings.append(f"{len(new)} frame(s) look like outliers but dropping them would leave fewer than 3 "
                            "frames; they are kept, down-weighted by the robust loss")
            break
        dropped.update(new)
        active = [i for i in active if i not in new]

    sub = [frames[i] for i in active]
    try:
        marginals = gtsam.Marginals(graph, result)
        cov = marginals.marginalCovariance(EXTRINSIC)
    except RuntimeError as exc:
        raise _degenerate(graph, result, sub) from exc
    if not np.all(np.isfinite(cov)) or np.linalg.eigvalsh(cov)[0] <= 0:
        raise _degenerate(graph, result, sub)

    # Plane consistency: the part of the total cost that the camera alone cannot explain.
    graph_plain, _, _ = _build(sub, board, camera, T, [boards[i] for i in active], sigma_px, sigma_r,
                               options, robust=False)
    total = 2.0 * graph_plain.error(result)
    between = total - float(np.sum(_pnp_chi2(sub, board, camera, sigma_px)))
    dof = max(int(sum(w.shape[0] for w in whiteners)) - 6, 1)
    p_value = float(chi2.sf(between, dof))
    variance_factor = between / dof
    if p_value < 0.01:
        msg = (f"the boards' camera and LiDAR planes disagree more than the noise model allows "
               f"(variance factor {variance_factor:.2f} on {dof} dof, p = {p_value:.1g})")
        if options.inflate_inconsistent:
            cov = cov * variance_factor
            msg += "; the covariance is inflated by it"
        warnings.append(msg)

    fits = []
    for i, f in enumerate(frames):
        r, _ = corner_residuals(boards[i], board.inner_corners(), f.camera.corners_px, camera)
        W, _ = sqrt_excess_moment(f.lidar.unbiased_range_moment(sigma_r))
        c2 = _plane_chi2(W, T, boards[i], sigma_r)
        why = dropped.get(i) or flagged.get(i)
        fits.append(FrameFit(f.name, c2, int(W.shape[0]), float(np.sqrt(np.mean(r**2))),
                             0.0 if i in dropped else _robust_weight(np.sqrt(c2), options), why, i in dropped))
        if why:
            action = "dropped" if i in dropped else "down-weighted"
            warnings.append(f"frame {f.name}: {why}; {action}")
    return Refinement(T, cov, {f.name: boards[i] for i, f in enumerate(frames)}, tuple(fits), float(sigma_px),
                      resid_px, float(sigma_r), float(variance_factor), dof, p_value, iterations, tuple(warnings))


def _plane_chi2(W: np.ndarray, T: np.ndarray, T_board: np.ndarray, sigma_r: float) -> float:
    pi, _, _ = lidar_plane(T, T_board)
    e = W @ pi
    return float(e @ e) / sigma_r**2


def _flag_outliers(chi: dict, frames, T, boards, options) -> dict[int, str]:
    """Frames whose plane residual is extreme for chi-square(3), relative to the typical frame (so that
    a rig whose noise is underestimated overall does not flag every frame)."""
    values = np.array(list(chi.values()))
    typical = max(1.0, float(np.median(values)) / chi2.median(3))
    limit = chi2.isf(options.outlier_p, 3) * typical
    out = {}
    for i, c in chi.items():
        if c > limit:
            f = frames[i]
            n = boards[i][:3, 2]
            angle, dist = plane_difference(f.lidar.plane.transformed(T), Plane(n, n @ boards[i][:3, 3]))
            out[i] = (f"its LiDAR plane disagrees with the camera's board by {np.degrees(angle):.2f} deg and "
                      f"{1000 * dist:.0f} mm (chi-square {c:.0f} on 3 dof, limit {limit:.0f}): a wrong LiDAR "
                      "segment, or the board moved between image and scan")
    return out
