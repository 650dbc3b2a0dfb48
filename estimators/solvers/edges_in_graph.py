"""The boards' edges in the plane graph: the ends of each ring or scan segment on the board's outline as factors
(by default where the board's size is given), their share of the information, the outline check, the
edges' record, and the planes' conflict with the edges (the covariance that holds both answers).
"""
from __future__ import annotations

import gtsam
import numpy as np

from geometry.rotations import T_log

from ..measurements import FrameMeasurement
from . import chi_square as chi2
from .board_edges import GROWTH_PRIOR_SD_M, MAX_END_OFFSET_M, crossings, edge_scatter, end_noise, ring_ends
from .outline_check import outline_check, outline_warnings
from .graph_keys import EXTRINSIC, OUTLINE, board_key, shift_key
from .plane_graph import PlaneProblem, extrinsic_information


def edge_crossings(prob: PlaneProblem, frames: list[FrameMeasurement], active: list[int], T: np.ndarray,
                   boards: list, max_offset_m: float = MAX_END_OFFSET_M) -> list | None:
    """Each active frame's ring ends on the board's edges, sides assigned under ``T`` and ``boards``, those
    within ``max_offset_m`` of their side (None when no frame has any)."""
    found = _rings_and_noise(prob, frames, active)
    T_board_lidar = [np.linalg.inv(boards[i]) @ T if i in active else None for i in range(len(frames))]
    edges = lidar_crossings([f.lidar for f in frames], T_board_lidar, prob.board, found, max_offset_m)
    return edges if any(e is not None and e.size for e in edges) else None


# The last observations :func:`rings_and_noise` was given (held, so that their identities stay theirs) and its
# answer: a rig's edges and its planes-alone outline check ask for the same LiDAR's boards in turn.
_LAST_RINGS: list = []


def rings_and_noise(observations: list, noise_from: list[int] | None = None) -> tuple[list, object, list]:
    """Of LiDAR board observations: each one's rings (a 2D scan's board segment is one ring: its two ends are
    where the scan line leaves the board; None where unknown), the ends' noise (``board_edges.end_noise``) of
    those at ``noise_from`` (default all) and each one's ring ends (``board_edges.ring_ends``). The points' own,
    whatever the extrinsic: found once per set of observations (the same objects asked again get the same
    answer)."""
    key = None if noise_from is not None else tuple(observations)
    if key is not None and _LAST_RINGS and len(_LAST_RINGS[0]) == len(key) and all(
            a is b for a, b in zip(_LAST_RINGS[0], key)):
        return _LAST_RINGS[1]
    found = _rings_and_noise_of(observations, noise_from)
    if key is not None:
        _LAST_RINGS[:] = [key, found]
    return found


def _rings_and_noise_of(observations: list, noise_from: list[int] | None) -> tuple[list, object, list]:
    """:func:`rings_and_noise`, found."""
    from .range_model import frame_rings

    rings = [np.zeros(len(o.points), dtype=np.int64) if o.is_scan_line else r
             for o, r in zip(observations, frame_rings(observations))]
    picked = range(len(observations)) if noise_from is None else noise_from
    noise = end_noise([(observations[i].points, rings[i]) for i in picked if rings[i] is not None])
    ends = [None if r is None else ring_ends(o.points, r, o.open_ends) for o, r in zip(observations, rings)]
    return rings, noise, ends


def lidar_crossings(observations: list, T_board_lidar: list, board, found: tuple | None = None,
                    max_offset_m: float = MAX_END_OFFSET_M) -> list:
    """Each observation's ring ends on the board's outline (``board_edges.crossings``, the ends' noise measured
    on the observations, :func:`rings_and_noise`, or ``found`` from it), sides assigned under its
    ``T_board_lidar``; None where its rings are unknown or its ``T_board_lidar`` is None."""
    if not observations:
        return []
    rings, noise, ends = rings_and_noise(observations) if found is None else found
    return [crossings(o.points, r, T, board, noise.beam_sd_rad, max_offset_m, noise.position_sd_m, e)
            if r is not None and T is not None else None
            for o, r, T, e in zip(observations, rings, T_board_lidar, ends)]


def _rings_and_noise(prob: PlaneProblem, frames: list[FrameMeasurement], active: list[int]
                     ) -> tuple[list, object, list]:
    """:func:`rings_and_noise` of the frames, the noise of the ``active`` ones, kept on ``prob`` (and passed on
    by ``PlaneProblem.variant``)."""
    key = (tuple(id(f) for f in frames), tuple(active))
    if prob.ends_cache is not None and prob.ends_cache[0] == key:
        return prob.ends_cache[1:]
    found = rings_and_noise([f.lidar for f in frames], active)
    prob.ends_cache = (key, *found)
    return found


# Of the ring ends within half the board's smaller side of their sides under the planes' estimate, fewer than
# this share within ``MAX_END_OFFSET_M``: the estimate is further off along the boards than the ends' cut (weakly
# spread normals: boards facing the rig), and the ends are first fitted with the wide cut.
MIN_CUT_SHARE = 0.5


def _ends(edges: list | None) -> int:
    return 0 if edges is None else sum(e.size for e in edges if e is not None)


def _cut_ends(prob: PlaneProblem, frames: list[FrameMeasurement], active: list[int], T: np.ndarray, boards: list
              ) -> tuple[list | None, list | None]:
    """The ends under ``T`` within ``MAX_END_OFFSET_M`` of their sides, and those within half the board's smaller
    side when the first are fewer than ``MIN_CUT_SHARE`` of them (else None): ``T`` is then further off along
    the boards than the cut."""
    edges = edge_crossings(prob, frames, active, T, boards)
    wide = edge_crossings(prob, frames, active, T, boards, max_offset_m=0.5 * min(prob.board.extent))
    return edges, (wide if _ends(edges) < MIN_CUT_SHARE * _ends(wide) else None)


def add_edges(prob: PlaneProblem, frames: list[FrameMeasurement], active: list[int], T: np.ndarray, boards: list,
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
        edges = edge_crossings(prob, frames, active, T_wide, b_wide)
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


# At most this many solves with the ends' scale and the boards' in-plane scatter estimated in turn.
EDGE_ROUNDS = 4


def _solve_with_edges(prob: PlaneProblem, active: list[int], T: np.ndarray, b: list, floor: float
                      ) -> tuple[np.ndarray, list]:
    """Solve with ``prob``'s ends, their scale and the boards' in-plane scatter estimated in turn (at most
    ``EDGE_ROUNDS`` solves; the scatter and scale kept are those of the last solve, which its shifts were
    estimated under)."""
    for k in range(EDGE_ROUNDS):
        prob.solved = prob.solve(active, T, b, floor)[:2]
        T = prob.solved[1].atPose3(EXTRINSIC).matrix()
        tau, scale = _edge_scatter(prob, active, T, b)
        settled = abs(np.log(max(tau, 1e-4) / max(prob.edge_tau, 1e-4))) < 0.1 and \
            abs(np.log(scale / prob.edge_scale)) < 0.05
        if settled or k == EDGE_ROUNDS - 1:
            break
        prob.edge_tau, prob.edge_scale = tau, scale
    return T, b


def _edge_scatter(prob: PlaneProblem, active: list[int], T: np.ndarray, boards: list) -> tuple[float, float]:
    """The boards' in-plane scatter (m) and the ends' scale at the solve (``board_edges.edge_scatter``)."""
    return edge_scatter([(T, boards[i], prob.edges[i]) for i in active if prob.has_edges(i)], prob.board,
                        prob.outline, prob.edge_scale, prob.edge_tau)


def edges_summary(prob: PlaneProblem, active: list[int], T: np.ndarray, boards: list, floor: float, cov: np.ndarray,
                  marginals: gtsam.Marginals, quasi_scale: float) -> tuple[dict, list[str]]:
    """What the edges say, for calibration.json: the ends used, their scale and the boards' in-plane scatter,
    the growth of the outline's sides, each frame's outline shift (board axes) and their mean in camera axes
    against its 99% limit, and the planes-only estimate against this one (a Hausman test: their difference
    against the difference of their covariances, which is the edges' share)."""
    warnings = []
    shift_keys = [(j, i) for j, i in enumerate(active) if prob.has_edges(i)]
    keys = gtsam.KeyVector([OUTLINE] + [shift_key(j) for j, _ in shift_keys])
    J = marginals.jointMarginalCovariance(keys).fullMatrix() * quasi_scale
    stats = outline_statistics([(prob.frames[i].name, int(prob.edges[i].size)) for _, i in shift_keys],
                               [boards[i] for _, i in shift_keys],
                               [prob.shifts.get(i, np.zeros(2)) for _, i in shift_keys], J,
                               prob.edge_tau**2 * quasi_scale)
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
        planes_check, _ = check_outline(planes, active, T_p, b, marginals_p, quasi_scale, quasi_scale * cov_p)
        if planes_check is not None:
            warnings.extend(outline_warnings(planes_check, used=False, beside_edges=True))
        test = {"planes_only_T_camera_lidar": T_p.tolist(), **hausman(T_p, T, cov_p, cov)}
        delta, h2, h_dof, h_p = np.array(test["difference_tangent"]), test["d2"], test["dof"], test["p_value"]
        if h_dof and h_p < 0.01:
            warnings.append(f"board edges: the planes alone and the planes with the edges differ by "
                            f"{np.degrees(np.linalg.norm(delta[:3])):.2f} deg and "
                            f"{1000 * np.linalg.norm(delta[3:]):.0f} mm, beyond what the edges' information "
                            f"explains (d2 {h2:.1f} on {h_dof} dof, p = {h_p:.1g}): the boards' planes or their "
                            "outlines carry a bias (range error with incidence, intrinsics, the board's real size); "
                            "the covariance holds both answers (the planes' and the edges' own, each added along its "
                            "offset); both estimates "
                            "are in calibration.json")
    record = {"used": True, "ends": int(sum(prob.edges[i].size for _, i in shift_keys)),
              "end_scale": prob.edge_scale, "board_scatter_in_plane_m": prob.edge_tau, "growth_m": g.tolist(),
              "outline_offset_m": o.tolist(), **stats, "planes_against_edges": test, "planes_only_check": planes_check}
    return record, outline_warnings(record, used=True) + warnings


def hausman(T_planes: np.ndarray, T_edged: np.ndarray, cov_planes: np.ndarray, cov_edged: np.ndarray) -> dict:
    """The planes-only estimate against the one with the edges (a Hausman test): their difference (tangent at
    ``T_planes``) against the difference of their covariances, which is the edges' share; with the edges' gain
    and where the edges' own answer lies (:func:`edges_own_offset`)."""
    delta = T_log(np.linalg.inv(T_planes) @ T_edged)
    d2, dof = chi2.mahalanobis(delta, cov_planes - cov_edged)
    return {"difference_tangent": delta.tolist(), "d2": d2, "dof": dof,
            "p_value": float(chi2.sf(d2, dof)) if dof else 1.0, "edges_gain": edges_gain(cov_planes, cov_edged),
            "edges_own_offset_tangent": edges_own_offset(delta, cov_planes, cov_edged).tolist()}


# Directions where the edges add less than this share of the planes' information hold no answer of their own.
EDGES_OWN_MIN_SHARE = 1e-3


def edges_own_offset(delta: np.ndarray, cov_planes: np.ndarray, cov_edged: np.ndarray) -> np.ndarray:
    """Where the edges' own answer lies from the estimate with them (tangent), its part beyond their noise.

    With information ``I_p`` (the planes alone) and ``I_e`` (what the edges add), the estimate with both lies
    between the two witnesses' answers: ``I_e (x_e - x) = I_p (x - x_p) = I_p delta``. In the basis where
    ``I_p`` is the identity and ``I_e`` diagonal (``lam``), the witnesses differ by ``D = delta (1 + lam) / lam``,
    of noise variance ``1 + 1 / lam``; their difference beyond it (``D^2 - (1 + 1/lam)``, the method of moments of a
    bias) puts the edges' own answer ``D / (1 + lam)`` from the estimate. Where the planes are the biased witness
    (a range offset that the range terms did not take), that is where the truth lies: the conflict's covariance
    holds it beside the planes' answer (:func:`conflict_covariance`). Zero where a covariance is not positive
    definite, and along directions where the edges add less than ``EDGES_OWN_MIN_SHARE`` of the planes'."""
    try:
        I_p = np.linalg.inv(cov_planes)
        L = np.linalg.cholesky(0.5 * (I_p + I_p.T))
        I_e = np.linalg.inv(cov_edged) - I_p
    except np.linalg.LinAlgError:
        return np.zeros(len(delta))
    Li = np.linalg.inv(L)
    lam, U = np.linalg.eigh(Li @ (0.5 * (I_e + I_e.T)) @ Li.T)
    z = U.T @ (L.T @ delta)
    keep = lam >= EDGES_OWN_MIN_SHARE
    lam = np.where(keep, lam, 1.0)
    D = z * (1.0 + lam) / lam
    beyond = np.where(keep, np.sqrt(np.maximum(D**2 - (1.0 + 1.0 / lam), 0.0)), 0.0)
    return Li.T @ (U @ (np.sign(D) * beyond / (1.0 + lam)))


def outline_statistics(frames: list[tuple[str, int]], boards: list, shifts: list, J: np.ndarray, prior_var: float
                       ) -> dict:
    """An edges record's uncertainty and test, a pair's and a rig LiDAR's alike: the outline's standard deviations
    (its growth's and offset's), each frame's outline shift (``frames``: name and ends; ``shifts``, board axes)
    with its own, and their mean in camera axes (each frame's board axes mapped by its board pose, ``boards``)
    against its 99% limit. ``J``: the joint covariance of the outline (4) and the shifts (2 each). The shifts are
    estimated random effects, each 0 +- the boards' in-plane scatter (variance ``prior_var``): under the model their
    estimates vary by that prior's covariance less their posterior's. That difference is small where the ends say
    little of a shift, so ``prior_var`` must be the prior the shifts were estimated under: with the next round's
    scatter instead (a scatter still shrinking when its rounds ran out), the mean shift of right answers lay
    beyond its 99% limit in 4-7% of simulated datasets (``bench_board_edges``), none with the prior solved with."""
    sd = np.sqrt(np.maximum(np.diag(J[:4, :4]), 0.0))
    A = np.zeros((3, 2 * len(frames)))
    per_frame = []
    for k, ((name, ends), B, d) in enumerate(zip(frames, boards, shifts)):
        A[:, 2 * k:2 * k + 2] = B[:3, :2] / len(frames)
        per_frame.append({"frame": name, "ends": ends, "shift_board_xy_m": np.asarray(d).tolist(),
                          "shift_sd_m": np.sqrt(np.maximum(np.diag(J[4 + 2 * k:6 + 2 * k, 4 + 2 * k:6 + 2 * k]),
                                                           0.0)).tolist()})
    mean = A @ np.concatenate(shifts) if frames else np.zeros(3)
    C = A @ (prior_var * np.eye(J.shape[0] - 4) - J[4:, 4:]) @ A.T
    d2, dof = chi2.mahalanobis(mean, C)
    return {"growth_sd_m": sd[:2].tolist(), "outline_offset_sd_m": sd[2:].tolist(), "frames": per_frame,
            "mean_shift_camera_m": mean.tolist(), "mean_shift_covariance": C.tolist(), "mean_shift_d2": d2,
            "mean_shift_dof": dof, "mean_shift_p_value": float(chi2.sf(d2, dof)) if dof else 1.0}


def edges_gain(cov_planes: np.ndarray, cov: np.ndarray) -> float:
    """How many times less certain the planes alone leave the estimate than the planes with the edges, along the
    direction where that is largest (the square root of the largest generalized eigenvalue of the two
    covariances): above ``EDGES_CARRY`` the answer rests on the boards' edges there."""
    try:
        L = np.linalg.cholesky(cov)
    except np.linalg.LinAlgError:
        return float("inf")
    M = np.linalg.solve(L, np.linalg.solve(L, cov_planes).T)
    return float(np.sqrt(max(np.max(np.linalg.eigvalsh(0.5 * (M + M.T))), 0.0)))


# Beyond this gain (:func:`edges_gain`) the answer rests on the boards' edges: the planes alone leave it this many
# times less certain along some direction, so they cannot test the edges there. Clean boards turned or facing the
# rig gain 4-54 and are right with their edges (bench_board_edges); hand-held boards facing a VLP-16 (bench_handheld)
# gain 10-38 where the hands at the boards' sides move the ends. Edges that carry the answer are left out where they
# show what moved them (:func:`edges_left_out`): a side grown beyond GROWTH_SIGMAS of its prior
# (``board_edges.GROWTH_PRIOR_SD_M``), or the planes in conflict with them (``CONFLICT_P``).
EDGES_CARRY = 10.0
GROWTH_SIGMAS = 3.0


def carrying(edges: dict | None) -> tuple[float, float] | None:
    """Where a used edges record carries the answer (its ``edges_gain`` beyond ``EDGES_CARRY``): that gain and the
    largest growth of a side of the outline (m); else None. :func:`edges_left_out` and the verdict read it."""
    edges = edges or {}
    gain = (edges.get("planes_against_edges") or {}).get("edges_gain", 0.0)
    if not edges.get("used") or not gain > EDGES_CARRY:
        return None
    return gain, float(np.max(np.abs(edges.get("growth_m", [0.0]))))


def gain_words(gain: float) -> str:
    """How much less certain the planes alone leave the answer (:func:`edges_gain`), in words."""
    return "unconstrained" if not np.isfinite(gain) else f"{gain:.0f} times less certain"


def edges_left_out(edges: dict | None) -> str | None:
    """Why a 3D LiDAR's edges are left out of the default estimate (``--edges`` not given), or None: they carry the
    answer (:func:`carrying`) and something at the boards' sides moved them: a side of the outline grown beyond
    ``GROWTH_SIGMAS`` of its prior (a hand or a holder: hand-held boards looked 17-105 mm wider by their ends), or
    the planes alone in conflict with them. Where the edges carry the answer its error is theirs, beyond what the
    planes can test: on hand-held boards the edges' answers lay beyond their 99.9% region in 20 of 37 datasets,
    the planes' alone in none (bench_handheld)."""
    carried = carrying(edges)
    if carried is None:
        return None
    gain, growth = carried
    said = f"the ring ends carry the answer, the planes alone leaving it {gain_words(gain)} along one direction,"
    if growth > GROWTH_SIGMAS * GROWTH_PRIOR_SD_M:
        return f"{said} and make a side of the board {1000 * growth:.0f} mm longer than board.size says"
    if conflict_covariance(edges) is not None:
        return (f"{said} and the planes disagree with them beyond their noise "
                f"(p = {edges['planes_against_edges']['p_value']:.1g})")
    return None


def left_out_warning(why: str) -> str:
    """The warning where the default left a LiDAR's edges out (:func:`edges_left_out`: ``why``), a single pair's
    and a rig LiDAR's (prefixed with its name)."""
    return (f"board edges left out: {why}: a hand or a holder at the boards' sides, or a wrong board.size; the "
            "answer rests on the planes alone, with their covariance (the answer with the edges is in "
            "calibration.json, board_edges.with_edges)")


def check_outline(prob: PlaneProblem, active: list[int], T: np.ndarray, boards: list, marginals: gtsam.Marginals,
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


def edges_information(prob: PlaneProblem, active: list[int], T: np.ndarray, boards: list, floor: float,
                      quasi_scale: float) -> tuple[np.ndarray, np.ndarray]:
    """What the edges add to the extrinsic's log-posterior about this estimate, to second order: ``eta^T xi -
    0.5 xi^T H xi`` in the tangent ``xi`` (the posterior's). ``H``: the information with the edges less that of
    the planes alone, every other variable profiled out; ``eta``: minus the planes' pull at the estimate, which
    the edges balance (the whole graph's is zero there). Scaled like the covariance by ``quasi_scale``."""
    H_all, _ = extrinsic_information(prob.graph(active, floor), prob.values(active, T, boards, floor), len(active))
    planes = prob.variant(edges=False)
    H_p, eta_p = extrinsic_information(planes.graph(active, floor), planes.values(active, T, boards, floor),
                                       len(active))
    ev, V = np.linalg.eigh(0.5 * (H_all - H_p + (H_all - H_p).T))
    return (V * np.maximum(ev, 0.0)) @ V.T / quasi_scale, -eta_p / quasi_scale


# The planes alone against the planes with the edges (``planes_against_edges`` of an edges record): below this
# p-value they conflict beyond their noise; the covariance holds both answers (:func:`conflict_covariance`) and the
# verdict says so.
CONFLICT_P = 0.01


def conflict_covariance(edges: dict | None) -> np.ndarray | None:
    """Where the planes alone and the planes with the edges conflict beyond their noise (3D; the Hausman test of
    :func:`edges_summary` below ``CONFLICT_P``), the covariance that holds both answers: the outer products of
    their difference ``delta`` (tangent) and of the edges' own answer's offset (:func:`edges_own_offset`), errors
    of the model along them with one standard deviation each, so that the planes-only answer and the edges' own
    lie within one standard deviation of the estimate. None when they agree. (With ``delta`` alone, the planes'
    answer was held and the edges' not: on a VLP-16 with every range 2 cm long, boards facing it and no range
    term taken, the truth lay at d2 570-1040 in the three of six layouts that conflict, and at 6-46 with both.)"""
    test = (edges or {}).get("planes_against_edges")
    if not test or not test.get("dof") or test["p_value"] >= CONFLICT_P:
        return None
    delta = np.asarray(test["difference_tangent"], dtype=float)
    own = np.asarray(test.get("edges_own_offset_tangent", np.zeros(6)), dtype=float)
    return np.outer(delta, delta) + np.outer(own, own)


def conflict_words(edges: dict | None) -> str | None:
    """What the planes' conflict with the edges is (:func:`conflict_covariance`), or None: the boards' planes and
    their rings' ends disagree beyond their noise, so one of them carries what the model does not hold (a wrong
    board size or pattern offset, a plane error) and the two pull the answer apart. A 2D scan's planes are not
    tested against its ends (:func:`edges_summary`)."""
    if conflict_covariance(edges) is None:
        return None
    test = edges["planes_against_edges"]
    delta = np.asarray(test["difference_tangent"], dtype=float)
    return (f"the boards' planes and their ring ends on the boards' edges disagree beyond their noise "
            f"({np.degrees(np.linalg.norm(delta[:3])):.2f} deg and {1000 * np.linalg.norm(delta[3:]):.0f} mm apart; "
            f"d2 {test['d2']:.1f} on {test['dof']} dof, p = {test['p_value']:.1g})")
