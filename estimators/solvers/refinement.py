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
made with the boards' disagreement modelled when they disagree beyond the noise
(:func:`range_terms_choice._model_test`). Per-ring and black-square terms that leave the boards inconsistent
where the offset alone does not fall back to smaller combinations. A term beyond 3 prior standard deviations is
held at 0 with its prior variance propagated
(:func:`range_terms_choice.consider_pinned`). What a plane error of physical size and the boards' scatter leave is
a variance factor (quasi-likelihood), taken as a rig takes each sensor's: the terms' priors are weighed against data
worth that much less (the graph solved again under it, before any term is judged against its prior), and the
covariance is scaled by it. Weighed at their nominal noise, overdispersed boards let the terms run far and
the terms held at 0 then drag the extrinsic (a simulated 64-beam set with 15 mm ring offsets: 2.0 deg and 245 mm
off, against 0.04 deg and 8 mm).

The covariance is ``gtsam.Marginals`` of the extrinsic, in GTSAM's right tangent: ``T_true = T_hat Exp(xi)``,
``xi = [rot; trans]``.

This module runs the refinement (``refine``) and holds its record (``Refinement``); the parts are beside it:
``refinement_options`` (the options), ``noise_levels`` (corner and range noise, the plane factors' noise models),
``plane_graph`` (the problem and its graph), ``edges_in_graph`` (the boards' edges), ``range_terms_choice`` (which
range terms the data support), ``board_scatter`` (the boards' scatter along their weak directions) and
``refusal`` (a 2D answer's refusal).
"""
from __future__ import annotations

import functools
from dataclasses import dataclass, replace

import gtsam
import numpy as np

from geometry.board import BoardModel
from geometry.camera import CameraModel
from geometry.planes import Plane, plane_difference
from geometry.rotations import T_log

from ..errors import DegenerateLayoutError
from ..measurements import FrameMeasurement
from . import chi_square as chi2
from .board_edges import EndTerms
from .board_scatter import BOARD_SCATTER_MEANING, estimate_board_scatter, estimate_plane_error
from .choice_memo import Undigestible, decision, inputs_digest
from .closed_form import solve_closed_form
from .edges_in_graph import (add_edges, check_outline, conflict_covariance, edge_crossings, edges_information,
                             edges_left_out, edges_summary, left_out_warning)
from .noise_levels import corner_noise_levels, excess_scale, pooled_range_noise_m, robust_weight
from .graph_keys import EXTRINSIC
from .plane_graph import MIN_INFORMATION_RATIO, PlaneProblem, degenerate, pooled_range_noise_with_terms_m
from .range_model import (DEFAULT_RANGE_ACCURACY_M, MAX_PRIOR_SIGMAS, MIN_INTENSITY_AGREEMENT, RangeModelFit,
                          frame_labels)
from .range_terms_choice import choose_range_model, consider_pinned, consider_placement, with_uncertainty
from .refinement_options import RefinementOptions, intrinsics_step_scale
from .refusal import check_scan_directions, scan_refusal


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
    corner_noise_px: float = float("nan")  # the effective noise its corners were weighed with


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
    consistency_dof: float  # with the edges, their leverage added (``PlaneProblem.edge_leverage``): not whole
    consistency_p: float
    iterations: int
    warnings: tuple[str, ...] = ()
    # The part of ``covariance`` due to intrinsics calibrated from the same images (None when given).
    intrinsics_covariance: np.ndarray | None = None
    corner_scale_sd: float = 0.0
    range_model: RangeModelFit | None = None
    # The board's edges when used (``solvers.board_edges``): ends, growth, per-frame and mean outline shifts and
    # the test of the planes against the edges (:func:`edges_summary`).
    edges: dict | None = None
    # The edges' share of the extrinsic's log-posterior, second order (:func:`edges_information`): ``(H, eta)``.
    edge_share: tuple[np.ndarray, np.ndarray] | None = None
    # A 2D scan's segment ends and their nuisances at the estimate, which the posterior evaluates exactly
    # (``board_edges.EndTerms``; None without ends or for a 3D LiDAR, whose edges enter as ``edge_share``).
    end_terms: EndTerms | None = None
    # The camera's and the LiDAR's views of the used frames, as the final graph was built from them
    # (``PlaneProblem.views``): a 3D pair's posterior is the rig's likelihood over them (``rig_posterior``).
    views: tuple | None = None
    # The LiDAR's range accuracy (m) the range terms' priors took: bounds the per-board plane error a sensor of its
    # family can make (``pipeline.verdict``).
    range_accuracy_m: float = float("nan")
    # The part of ``covariance`` that holds the planes' conflict with the edges (``conflict_covariance``; None
    # when they agree): the posterior's samples are convolved with it too.
    conflict_covariance: np.ndarray | None = None


def _offset_ends(prob: PlaneProblem, frames: list[FrameMeasurement], active: list[int], T: np.ndarray, boards: list,
                 floor: float, options: RefinementOptions, scan_lines: bool) -> tuple | None:
    """Under ``auto``, for a 3D LiDAR whose board's size is known (``options.offset_with_ends``): the planes'
    problem with the ring ends on the board's outline assigned under ``T`` and solved with (their scale and the
    boards' in-plane scatter estimated, ``edges_in_graph.add_edges``), its estimate and board poses, on which
    ``choose_range_model`` tests a global offset the planes alone do not support; None otherwise or without
    ends."""
    wanted = options.offset_with_ends if options.offset_with_ends is not None else options.edges is not False
    if scan_lines or not prob.board.size_known or not wanted:
        return None
    ended = prob.variant(edges=False)
    T_e, b_e = add_edges(ended, frames, active, T, list(boards), floor)
    return (ended, T_e, b_e) if ended.edges is not None else None


def refine(frames: list[FrameMeasurement], board: BoardModel, camera: CameraModel, T_init: np.ndarray,
           options: RefinementOptions = RefinementOptions(), memo: dict | None = None) -> Refinement:
    """Refine ``T_camera_lidar`` from the usable frames, starting at ``T_init``. ``memo``: the range terms' choices
    made before (``choice_memo``), replayed on inputs of the same content and filled with those made here."""
    if options.range_accuracy_m is None:
        options = replace(options, range_accuracy_m=DEFAULT_RANGE_ACCURACY_M)
    frames = [f for f in frames if f.usable]
    key = None
    if memo is not None and options.range_model == "auto":
        try:
            key = inputs_digest(frames, board, camera, T_init, options)
        except Undigestible:
            pass
    recalled, made = iter(memo.get(key, ()) if key is not None else ()), []
    # Scan lines with their segment ends on a board of known size: two boards can determine the extrinsic.
    least = 2 if (frames and all(f.lidar.is_scan_line for f in frames) and board.size_known
                  and options.edges is not False) else 3
    if len(frames) < least:
        raise DegenerateLayoutError(f"only {len(frames)} usable frame(s); refinement needs at least {least}")
    resid_px, sigma_px, sigma_board = corner_noise_levels(
        ((f.camera.T_camera_board, f.camera.corners_board(board), f.camera.corners_px) for f in frames), camera,
        options)
    sigma_r = options.range_noise_m or max(pooled_range_noise_m([f.lidar for f in frames]), 1e-5)
    prob = PlaneProblem(frames, board, camera, sigma_px, sigma_r, options, sigma_board=sigma_board)
    warnings: list[str] = []
    floor = options.plane_floor_m or 0.0

    active = list(range(len(frames)))
    dropped: dict[int, str] = {}
    flagged: dict[int, str] = {}
    T, boards = T_init, [f.camera.T_camera_board for f in frames]
    iterations = 0
    scan_lines = all(f.lidar.is_scan_line for f in frames)
    use_edges = board.size_known if options.edges is None else options.edges
    if use_edges and board.size_known and scan_lines:
        # A few scan lines leave a direction along the boards loose, where the planes alone drift far from the
        # start: the segment ends hold it from the first solve (sides assigned under the start).
        prob.edges = edge_crossings(prob, frames, active, T, boards)
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

    def with_edges(T, boards, graph, result):
        """The ends on the board's outline added and solved with (``edges_in_graph.add_edges``)."""
        if not board.size_known:
            warnings.append("the board's size is not given (board.size in dataset.yaml): its edges are not used, "
                            "so the translation along the boards' planes rests on the planes alone")
            return T, boards, graph, result
        T, boards = add_edges(prob, frames, active, T, boards, floor)
        if prob.solved is not None:
            graph, result = prob.solved
        if prob.edges is None:
            warnings.append("board edges: no ring end of the boards' points could be used as an edge (none "
                            "crosses the board's outline within half its side under the planes' estimate): "
                            "the estimate rests on the planes alone; check board.size in dataset.yaml")
        if scan_lines and prob.edges is not None:
            check_scan_directions(prob, active, boards)
        return T, boards, graph, result

    # A 2D scan's ends are in before its range terms are chosen (a few lines leave the extrinsic loose without
    # them); a 3D LiDAR's terms and plane error are chosen on the planes, as without the edges, and the ends added
    # after (below).
    if use_edges and scan_lines:
        T, boards, graph, result = with_edges(T, boards, graph, result)
    labels = None
    if options.range_model != "none":
        labels = frame_labels(frames, board, T, boards)
        # the ends' problem on the planes' state here, made once and only where the planes pass the offset over
        ends = functools.cache(functools.partial(_offset_ends, prob, frames, active, T, list(boards), floor, options,
                                                 scan_lines))

        prob, T, boards, model_fit = choose_range_model(prob, active, inliers, T, boards, floor, options, labels,
                                                        ends, next(recalled, None))
        made.append(decision(model_fit))
        if labels.source == "geometry" and prob.terms is not None and "dark" in prob.terms.names:
            # The colours were placed under the extrinsic the model was chosen from, as if it were exact. Placed
            # again under the estimate and blurred by its uncertainty (shares placed sharper than they are known
            # shrink the black-square term), the model is chosen again (once: the extrinsic moves by millimetres).
            try:
                placement_cov = gtsam.Marginals(*prob.solved).marginalCovariance(EXTRINSIC) if prob.solved else None
            except RuntimeError:  # a singular graph is refused below, with its reason
                placement_cov = None
            labels = frame_labels(frames, board, T, boards, placement_cov)
            prob, T, boards, model_fit = choose_range_model(prob, active, inliers, T, boards, floor, options, labels,
                                                            ends, next(recalled, None))
            made.append(decision(model_fit))
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
        if key is not None:
            memo[key] = made
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
                T, boards, graph, result, its = estimate_board_scatter(prob, active, inliers, T, boards, floor)
                prob.solved = (graph, result)
                iterations += its
                warnings.append(
                    f"the boards' ranges vary with incidence unlike a range offset (chi-square {t_stat:.0f} on "
                    f"{t_dof} dof): the offset is taken from the camera's board distances across boards, not from the "
                    "incidence across each board (which barely tells a board's offset from its distance: read so, "
                    f"each board's own offset would scatter by {1000 * prob.tau:.0f} mm)")
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
            # With range terms what the terms leave scales the covariance (below).
            floor, (T, boards, graph, result, its) = estimate_plane_error(prob, active, inliers, T, boards, floor, dof)
            prob.solved = (graph, result)
            iterations += its
            if first:
                warnings.append(f"the boards' camera and LiDAR planes disagree more than the point and corner noise "
                                f"explain (chi-square {stat:.0f} on {dof:.4g} dof, p = {p_value:.1g}); a per-board "
                                f"plane error of {1000 * floor:.1f} mm, estimated from the data, is included in the "
                                "covariance")
        if prob.has_beta and options.plane_floor_m is None and options.estimate_plane_floor:
            T, boards, graph, result, its = _settle_dispersion(prob, active, inliers, T, boards, floor)
            iterations += its
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
    if use_edges and not scan_lines:
        # A 3D LiDAR's ends are added to the planes' final noise model (their range terms and per-board plane
        # error), as a rig adds them: their scatter and scale are estimated under that model, and each frame's
        # ends take its plane error as a nuisance from the first solve with them.
        T, boards, graph, result = with_edges(T, boards, graph, result)

    try:
        marginals = gtsam.Marginals(graph, result)
        cov = marginals.marginalCovariance(EXTRINSIC)
        if model_fit is not None and prob.terms is not None:
            model_fit = with_uncertainty(model_fit, prob, marginals)
            if prob.pinned:
                cov, model_fit = consider_pinned(prob, active, result, floor, model_fit)
            if model_fit.confounding:
                c = model_fit.confounding
                warnings.append(f"range model: the {c['term']} is confounded with the extrinsic (correlation "
                                f"{c['correlation']:.2f} with {c['direction']}); it is marginalised with its prior, "
                                f"which widens that direction's standard deviation from {c['sd_if_known']:.1f} to "
                                f"{c['sd']:.1f} {c['unit']}. {c['advice']}")
    except RuntimeError as exc:
        raise degenerate(graph, result, len(active)) from exc
    ev = np.linalg.eigvalsh(cov) if np.all(np.isfinite(cov)) else np.array([0.0, 1.0])
    if ev[0] <= 0 or ev[0] / ev[-1] < MIN_INFORMATION_RATIO:
        raise degenerate(graph, result, len(active))
    if scan_lines and (weak := scan_refusal(cov, T, len(active), prob.edges is not None)) is not None:
        raise weak

    # Structure that neither the range terms (their scatter bounded by the range accuracy) nor a plane error of
    # physical size explains: the covariance is scaled by the variance factor that remains (quasi-likelihood).
    quasi_scale = 1.0
    if prob.has_beta and options.plane_floor_m is None and options.estimate_plane_floor:
        # The graph weighed the terms' priors against the data at ``prob.dispersion``; its covariance is scaled by
        # that, or by what the final estimate leaves if more (the edges' step moves it).
        stat_f, dof_f = prob.consistency(inliers, T, boards, floor, active)
        quasi_scale = max(excess_scale(stat_f, dof_f), prob.dispersion)
        if quasi_scale > 1.0:
            cov = cov * quasi_scale
            warnings.append(f"the boards disagree beyond what the range terms and a per-board plane error of physical "
                            f"size explain (chi-square {stat_f:.0f} on {dof_f:.3g} dof): the range terms' priors are "
                            f"weighed against data worth 1/{quasi_scale:.2f} of their nominal information, and the "
                            f"covariance is scaled by {quasi_scale:.2f}")
            if model_fit is not None:
                model_fit = replace(model_fit, std_m=tuple(np.sqrt(quasi_scale) * np.array(model_fit.std_m)),
                                    extrinsic_share=quasi_scale * model_fit.extrinsic_share)
    if model_fit is not None and labels is not None and labels.source == "geometry" and prob.has_beta \
            and "dark" in prob.terms.names and "dark" not in model_fit.pinned:
        cov, model_fit, T = consider_placement(prob, active, T, boards, floor, cov, model_fit)
    edges_record = edge_share = end_terms = conflict = None
    if prob.edges is not None:
        edges_record, edge_warnings = edges_summary(prob, active, T, boards, floor, cov / quasi_scale, marginals,
                                                    quasi_scale)
        warnings.extend(edge_warnings)
        edge_share = edges_information(prob, active, T, boards, floor, quasi_scale)
        conflict = conflict_covariance(edges_record)
        if conflict is not None:
            cov = cov + conflict
        if all(frames[i].lidar.is_scan_line for i in active):
            end_terms = EndTerms({frames[i].name: prob.edges[i] for i in active if prob.has_edges(i)},
                                 {frames[i].name: prob.shifts.get(i, np.zeros(2)) for i in active},
                                 np.array(prob.outline, dtype=float), prob.edge_scale * np.sqrt(quasi_scale))
    if model_fit is not None and model_fit.weak_offset is not None:
        # an offset its test half supports, not taken: the covariance holds the answer with it too
        d = np.asarray(model_fit.weak_offset["difference_tangent"])
        cov = cov + np.outer(d, d)
    cov_intrinsics = None
    if camera.param_std is not None:
        cov_intrinsics = _intrinsics_covariance(prob, active, T, boards, floor, options)
        cov = cov + cov_intrinsics
        how = ("parameters taken as independent" if camera.param_covariance is None else
               "with the parameters' correlations")
        what = ("the intrinsics' stated uncertainty (camera.param_std)" if camera.source == "dataset.yaml"
                else "the intrinsics were estimated from the same images; their uncertainty")
        warnings.append(f"{what} is propagated into the covariance (first order, {how})")

    if prob.edges is None and board.size_known and not scan_lines and options.checks:
        edges_record, check_warnings = check_outline(prob, active, T, boards, marginals, quasi_scale, cov)
        warnings.extend(check_warnings)

    fits = []
    for i, f in enumerate(frames):
        c2 = prob.plane_chi2(i, T, boards[i], floor)
        corner = prob.corner_chi2(i, boards[i])
        why = dropped.get(i) or flagged.get(i)
        fits.append(FrameFit(f.name, c2, c2 + corner - prob.pnp_chi2[i], int(prob.whitener(i).shape[0]),
                             float(prob.sigma(i) * np.sqrt(corner / f.camera.corners_px.size)),
                             0.0 if i in dropped else robust_weight(np.sqrt(c2), options, prob.whitener(i).shape[0]),
                             why, i in dropped, prob.sigma(i)))
        if why:
            action = "dropped" if i in dropped else "down-weighted"
            warnings.append(f"frame {f.name}: {why}; {action}")
    out = Refinement(T, cov, {f.name: boards[i] for i, f in enumerate(frames)}, tuple(fits), float(sigma_px),
                     resid_px, float(sigma_r), float(floor), float(variance_factor), round(float(dof), 2), p_value,
                     iterations, tuple(warnings), cov_intrinsics, options.corner_scale_sd, model_fit, edges_record,
                     edge_share, end_terms, prob.views(active, floor), float(options.range_accuracy_m), conflict)
    if options.edges is None and (why := edges_left_out(edges_record)) is not None:
        return planes_instead(out, refine(frames, board, camera, T_init, replace(options, edges=False), memo), why)
    return out


def planes_instead(edged: Refinement, planes: Refinement, why: str) -> Refinement:
    """The planes' refinement given where the default's edges were left out (``edges_in_graph.edges_left_out``:
    ``why``), its edges record the planes' outline check with ``left_out`` (why) and ``with_edges`` (the edges'
    estimate and record) added, and a warning saying so."""
    record = dict(planes.edges or {"used": False})
    record.update(left_out=why, with_edges={"T_camera_lidar": edged.T_camera_lidar.tolist(), **edged.edges})
    return replace(planes, edges=record, warnings=(left_out_warning(why),) + tuple(planes.warnings))


def _intrinsics_covariance(prob: PlaneProblem, active: list[int], T: np.ndarray, boards: list, floor: float,
                           options: RefinementOptions) -> np.ndarray:
    """First-order covariance of the extrinsic due to uncertain intrinsics: re-solve with the parameters moved
    by one standard deviation along each principal direction of their covariance (each parameter alone when only
    standard deviations are known) and sum the outer products of the shifts. Intrinsics estimated from the images
    (OpenCV's, or refined here) are in OpenCV's convention, scaled like the corner noise by the correlation
    factor; stated ones (dataset.yaml) are taken as they are."""
    cam = prob.camera
    out = np.zeros((6, 6))
    for step in cam.param_steps(intrinsics_step_scale(options, cam)):
        moved = prob.variant(camera=cam.with_params(cam.params + step))
        _, result, _ = moved.solve(active, T, list(boards), floor)
        xi = T_log(np.linalg.inv(T) @ result.atPose3(EXTRINSIC).matrix())
        out += np.outer(xi, xi)
    return out


def _settle_dispersion(prob: PlaneProblem, active: list[int], inliers: list[int], T: np.ndarray, boards: list,
                       floor: float) -> tuple:
    """The boards' variance factor that the range terms and the per-board plane error leave
    (``PlaneProblem.dispersion``: 1 unless the planes disagree beyond them at p < ``QUASI_LIKELIHOOD_P``), the
    graph solved again under it until it settles, as a rig's per-sensor scale is (``rig_graph.solve_rig``): the
    data then weigh against the terms' priors as much as they inform, not as much as their nominal noise says.
    Returns ``(T, boards, graph, result, iterations)``."""
    graph, result = prob.solved
    iterations = 0
    for _ in range(3):
        stat, dof = prob.consistency(inliers, T, boards, floor, active)
        new = excess_scale(stat, dof)
        if abs(np.log(new / prob.dispersion)) < 0.05:
            break
        prob.dispersion = new
        b = list(boards)
        graph, result, its = prob.solve(active, T, b, floor)
        prob.solved = (graph, result)
        T, boards = result.atPose3(EXTRINSIC).matrix(), b
        iterations += its
    return T, boards, graph, result, iterations


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
