"""The camera's intrinsics refined with the extrinsic (``lidarcam calibrate --refine-intrinsics``).

The intrinsics ``[fx, fy, cx, cy, dist...]`` become a variable of the factor graph: every frame's corner factor
then depends on its board pose and on them, the LiDAR planes on the board poses and the extrinsic as always. The
given calibration is the start and, where its standard deviations are stated (``camera.param_std`` in
dataset.yaml), a Gaussian prior; without them the intrinsics are estimated from the frames' corners alone (Zhang's
problem, which the planes join). Intrinsics calibrated from these same images carry no prior: their corners are
already in the graph.

The joint solve uses the planes without range terms or edges. Its intrinsics and their marginal standard deviations
then stand for the camera's: the boards are observed again under them and the whole refinement runs again, which
propagates the intrinsics' uncertainty into the extrinsic's covariance (first order, as for intrinsics calibrated
from the images). The per-board plane error that refinement estimates weights the planes of the next joint solve,
until it settles (a plane error estimated under wrong intrinsics holds their error, and would weaken the planes
that reveal it). The record says whether the boards' overdispersion (the plane-consistency variance factor)
went down.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import gtsam
import numpy as np

from geometry.camera import CameraModel

from ..errors import DegenerateLayoutError
from ..measurements import FrameMeasurement
from .chi_square import drop_p
from .graph_keys import EXTRINSIC, INTRINSICS
from .plane_graph import PlaneProblem
from .refinement import Refinement
from .refinement_options import RefinementOptions


def param_names(n: int) -> list[str]:
    """The names of a camera's ``n`` intrinsics ``[fx, fy, cx, cy, dist...]`` (a single pair's and a rig's)."""
    return ["fx", "fy", "cx", "cy"] + [f"d{k}" for k in range(n - 4)]


@dataclass(frozen=True, eq=False)
class IntrinsicsFit:
    """The intrinsics refined with the extrinsic.

    Attributes
    ----------
    camera : CameraModel
        The refined model; its ``param_std`` are the joint solve's marginal standard deviations (in OpenCV's
        convention, at the pooled corner residual, as the refinement expects of calibrated intrinsics).
    given_params, params, std : numpy.ndarray
        ``[fx, fy, cx, cy, dist...]`` given and refined, and the refined ones' standard deviations (at the
        effective corner noise).
    prior_sd : numpy.ndarray or None
        The prior's standard deviations (None: no prior, estimated from the frames).
    variance_factor_given, variance_factor_refined : float
        The boards' plane-consistency variance factor (1 when the planes agree to their noise) under the given
        and the refined intrinsics (NaN until both refinements have run: ``calibration.solve`` fills them).
    consistency_dof : float
        The plane-consistency statistic's degrees of freedom (under the refined intrinsics).
    corner_residual_given_px, corner_residual_refined_px : float
        The pooled corner residual under each (the same).
    """

    camera: CameraModel
    given_params: np.ndarray
    params: np.ndarray
    std: np.ndarray
    prior_sd: np.ndarray | None
    variance_factor_given: float = float("nan")
    variance_factor_refined: float = float("nan")
    corner_residual_given_px: float = float("nan")
    corner_residual_refined_px: float = float("nan")
    consistency_dof: float = float("nan")

    @property
    def names(self) -> list[str]:
        return param_names(len(self.params))

    @property
    def overdispersion_p(self) -> float:
        """The F test of the drop in the planes' chi-square against the intrinsics' count of parameters: freed
        intrinsics fit part of the planes' noise, so correct ones lower the variance factor too (by 18% on average,
        0.62-0.99 of it, over twelve simulated 12-board VLP-16 sets); only a drop beyond that says the given ones
        were part of the disagreement."""
        k, dof = len(self.params), self.consistency_dof
        return drop_p(k, self.variance_factor_given * dof, self.variance_factor_refined * dof, dof - k)

    @property
    def lowers_overdispersion(self) -> bool:
        return bool(self.overdispersion_p < 0.05)

    def to_dict(self) -> dict:
        shift = (self.params - self.given_params) / np.where(self.std > 0, self.std, np.inf)
        return {"parameters": [{"name": n, "given": float(g), "refined": float(v), "std": float(s),
                                "shift_in_std": float(z),
                                "prior_sd": float(self.prior_sd[k]) if self.prior_sd is not None else None}
                               for k, (n, g, v, s, z) in enumerate(zip(self.names, self.given_params, self.params,
                                                                       self.std, shift))],
                "prior": "given camera.param_std" if self.prior_sd is not None else
                         "none: estimated from the frames' corners and planes",
                "variance_factor_given": self.variance_factor_given,
                "variance_factor_refined": self.variance_factor_refined,
                "corner_residual_given_px": self.corner_residual_given_px,
                "corner_residual_refined_px": self.corner_residual_refined_px,
                "lowers_overdispersion": self.lowers_overdispersion,
                "lowers_overdispersion_p": self.overdispersion_p,
                "meaning": "variance_factor: the boards' camera and LiDAR planes' disagreement per degree of freedom "
                           "(1 when they agree to their noise) before any per-board plane error; refined "
                           "intrinsics lower it when the F test of its drop against their number of parameters "
                           "has p < 0.05 (freed intrinsics fit part of the planes' noise)"}


def _intrinsics_graph(frames: list[FrameMeasurement], board, camera: CameraModel, ref: Refinement,
                      options: RefinementOptions, plane_floor_m: float, prior_sd: np.ndarray | None):
    """The frames ``ref`` kept, the graph of their corners and planes with the intrinsics a variable (under
    ``prior_sd`` where given; the planes at ``plane_floor_m``, no robust loss) and its values at ``ref``'s solution
    and ``camera``'s intrinsics."""
    dropped = {f.name for f in ref.frames if f.dropped}
    used = [f for f in frames if f.usable and f.name not in dropped and f.name in ref.T_camera_board]
    fits = {f.name: f for f in ref.frames}
    prob = PlaneProblem(used, board, camera, ref.corner_noise_px, ref.range_noise_m, options,
                        sigma_board=[fits[f.name].corner_noise_px for f in used] if options.corner_noise_px is None
                        else None)
    prob.camera = replace(camera, param_std=prior_sd)  # the prior, where one
    active = list(range(len(used)))
    graph = prob.graph(active, plane_floor_m, robust=False, intrinsics=True)
    values = prob.values(active, ref.T_camera_lidar, [ref.T_camera_board[f.name] for f in used], plane_floor_m)
    values.insert(INTRINSICS, np.asarray(camera.params, dtype=float).copy())
    return used, graph, values


def refine_intrinsics(frames: list[FrameMeasurement], board, camera: CameraModel, ref: Refinement,
                      options: RefinementOptions = RefinementOptions(), plane_floor_m: float = 0.0) -> IntrinsicsFit:
    """The intrinsics, the extrinsic and the board poses solved together, started at ``ref`` (a refinement under
    ``camera``) and ``camera``'s intrinsics, with their prior when ``camera`` came from dataset.yaml with
    standard deviations. ``plane_floor_m``: the per-board plane error the planes are weighted with (one estimated
    under the given intrinsics holds their error too, and would weaken the planes that reveal it).

    Raises
    ------
    DegenerateLayoutError
        The board views do not determine the intrinsics (too few, or too alike in orientation) and no prior is
        given.
    """
    given = camera.params
    calibrated_here = camera.source.startswith("calibrated")
    prior_sd = None if calibrated_here or camera.param_std is None else np.asarray(camera.param_std, dtype=float)
    used, graph, values = _intrinsics_graph(frames, board, camera, ref, options, plane_floor_m, prior_sd)
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(options.max_iterations)
    params.setRelativeErrorTol(1e-9)
    params.setAbsoluteErrorTol(1e-9)
    result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    refined = np.asarray(result.atVector(INTRINSICS), dtype=float)
    try:
        cov = gtsam.Marginals(graph, result).marginalCovariance(INTRINSICS)
        std = np.sqrt(np.diag(cov))
        ok = bool(np.all(np.isfinite(std)) and np.all(np.isfinite(refined)))
    except RuntimeError:
        ok = False
    if not ok or np.any(std > np.maximum(0.5 * np.abs(given), 1.0)):
        raise DegenerateLayoutError(
            f"the {len(used)} board views do not determine the camera's intrinsics",
            hint="tilt the board more between views (Zhang's method needs varied orientations), or give the "
                 "intrinsics' standard deviations as camera.param_std in dataset.yaml, or drop --refine-intrinsics")
    try:
        camera_refined = camera.with_params(refined)
    except ValueError as exc:
        raise DegenerateLayoutError(f"the refined intrinsics are not a camera ({exc})",
                                    hint="drop --refine-intrinsics, or give camera.param_std as a prior") from exc
    # Stored in OpenCV's convention (at the pooled corner residual): the refinement scales calibrated intrinsics'
    # standard deviations by the corner error correlation, as it does the corner noise.
    scale = options.corner_error_correlation if options.corner_noise_px is None else 1.0
    source = (f"refined with the extrinsic from {len(used)} frames (given: {camera.source}"
              + (", with its param_std as prior)" if prior_sd is not None else ")"))
    camera_refined = replace(camera_refined, source=source, param_std=std / scale,
                             param_covariance=cov / scale**2)
    return IntrinsicsFit(camera_refined, given, refined, std, prior_sd)


# Below this p-value, the intrinsics' drop test (:func:`intrinsics_drop`) makes the verdict a CHECK.
INTRINSICS_CHECK_P = 1e-3


def intrinsics_drop(frames: list[FrameMeasurement], board, camera: CameraModel, ref: Refinement,
                    options: RefinementOptions = RefinementOptions()) -> dict | None:
    """Whether the boards' camera and LiDAR planes disagree in a way the camera's intrinsics explain: the planes'
    chi-square (weighed with the per-board plane error ``ref`` estimated) with the intrinsics held as given and with
    them freed, the extrinsic and board poses solved in both, and the F test of the drop against the intrinsics'
    count over what the freed planes leave per degree of freedom. Two solves of the graph, no re-measurement: a
    quick check of every 3D result (``pipeline.verdict``), where ``--refine-intrinsics`` is the full
    procedure. None where the graph cannot be solved so."""
    given = np.asarray(camera.params, dtype=float)
    try:
        _, graph, values = _intrinsics_graph(frames, board, camera, ref, options, ref.plane_floor_m, None)
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(options.max_iterations)
        held = gtsam.NonlinearFactorGraph(graph)
        held.add(gtsam.PriorFactorVector(INTRINSICS, given, gtsam.noiseModel.Isotropic.Sigma(len(given), 1e-9)))
        at_given = gtsam.LevenbergMarquardtOptimizer(held, values, params).optimize()
        freed = gtsam.LevenbergMarquardtOptimizer(graph, at_given, params).optimize()
    except RuntimeError:
        return None
    planes = [f for f in (graph.at(i) for i in range(graph.size())) if f is not None and EXTRINSIC in f.keys()]
    ss_g, ss_r = (sum(2.0 * f.error(v) for f in planes) for v in (at_given, freed))
    k, dof = len(given), float(ref.consistency_dof) - len(given)
    if dof <= 0:
        return None
    p = drop_p(k, ss_g, ss_r, dof)
    return {"parameters": k, "chi_square_given": float(ss_g), "chi_square_refined": float(ss_r), "dof": dof,
            "p_value": p, "explains": bool(p < INTRINSICS_CHECK_P),
            "meaning": "the planes' chi-square (with the per-board plane error) under the given intrinsics and with "
                       "them freed; the intrinsics explain the planes' disagreement when the F test of the drop "
                       f"has p < {INTRINSICS_CHECK_P:g} (--refine-intrinsics is the full procedure)"}

