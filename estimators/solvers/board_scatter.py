"""The boards' scatter about the shared range terms along each board's weak direction, by the method of moments
on the term-consistency statistic.
"""
from __future__ import annotations

import numpy as np

from .graph_keys import EXTRINSIC
from .plane_graph import PlaneProblem
from .refinement_options import MAX_PLANE_ERROR_M

BOARD_SCATTER_MEANING = (
    "standard deviation (m) of each board's apparent own range offset about the shared terms, along the board's "
    "distance-against-offset direction (told apart only by how incidence varies across the board): 0 when the "
    "boards agree; a range error that grows with incidence shows here as metres, the weak direction amplifying it, "
    "and the offset then rests on the camera's board distances across boards")
# Upper bound of that scatter (m): past it, no board's own offset information is left.
MAX_BOARD_SCATTER_M = 10.0


def estimate_plane_error(prob: PlaneProblem, active: list[int], inliers: list[int], T: np.ndarray, boards: list,
                         floor: float, dof: float) -> tuple:
    """The per-board plane error by the method of moments (:func:`match_moments`), so that the statistic it
    can explain equals its degrees of freedom; ``dof`` those of the whole consistency statistic at ``floor``.
    Planes only: the whole statistic, within 0.5 m. With range terms the residual also has the terms' own
    directions, which no plane error holds (matched on the whole, the error would run to its cap and sink the
    planes): the planes' own directions (:meth:`PlaneProblem.plane_moment`), within ``MAX_PLANE_ERROR_M``, a
    plane error's physical size. Returns the error and its solve ``(T, boards, graph, result, iterations)``."""
    if not prob.has_beta:
        return match_moments(prob, active, T, boards, (1e-5, 0.5), lambda v: v,
                             lambda v, T_v, b_v: prob.plane_cost(inliers, T_v, b_v, v) / dof)
    plane_dof = prob.plane_moment_dof(inliers, T, boards, floor)
    if prob.edges is not None:  # the edges' leverage (:meth:`PlaneProblem.edge_leverage`) is the extrinsic's
        plane_dof += dof - prob.planes_dof(inliers)
    return match_moments(prob, active, T, boards, (1e-5, MAX_PLANE_ERROR_M), lambda v: v,
                         lambda v, T_v, b_v: prob.plane_moment(inliers, T_v, b_v, v) / plane_dof)


def estimate_board_scatter(prob: PlaneProblem, active: list[int], inliers: list[int], T: np.ndarray, boards: list,
                           floor: float) -> tuple:
    """``prob.tau``, the boards' scatter along their weak directions, by the method of moments on the term
    consistency statistic (:meth:`PlaneProblem.term_consistency`); returns the solve ``(T, boards, graph, result,
    iterations)``."""
    t_dof = prob.term_consistency(inliers, T, boards, floor)[1]

    def with_tau(v):
        prob.tau = v
        return floor

    prob.tau, solve = match_moments(prob, active, T, boards, (1e-4, MAX_BOARD_SCATTER_M), with_tau,
                                    lambda v, T_v, b_v: prob.term_consistency(inliers, T_v, b_v, floor)[0] / t_dof)
    return solve


def match_moments(prob: PlaneProblem, active: list[int], T: np.ndarray, boards: list, bounds: tuple[float, float],
                  floor_for, excess) -> tuple:
    """A noise parameter by the method of moments: ``floor_for(v)`` sets it (returning the per-board plane error
    to solve with) and ``excess(v, T, boards)`` is the consistency statistic over its degrees of freedom, which
    falls as ``v`` grows. The root of its logarithm is found by Brent's method in ``log v`` within ``bounds``, to
    0.1% in ``v`` (a geometric bisection to the same precision needs twice the solves); each trial starts from
    the fit at the nearest value tried (the first from the fit without it). Returns the value and its solve
    ``(T, boards, graph, result, iterations)``."""
    start = (T, list(boards), prob.beta.copy())
    solves: dict[float, tuple] = {}

    def solve_at(u):
        if u not in solves:
            # from the nearest value's fit (the fit without it first): a few iterations, not a solve from afar
            near = solves[min(solves, key=lambda w: abs(w - u))] if solves else None
            T0, b, prob.beta = (start[0], list(start[1]), start[2].copy()) if near is None else \
                (near[0], list(near[1]), near[5].copy())
            graph, result, n = prob.solve(active, T0, b, floor_for(float(np.exp(u))))
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
