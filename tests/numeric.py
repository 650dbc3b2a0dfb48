"""Finite-difference helpers shared by the tests, and a pair refinement's likelihood and samples of it."""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from estimators.errors import LidarcamError
from estimators.solvers.board_edges import EndTerms
from estimators.solvers.factor_graph import CameraViews, LidarViews
from estimators.solvers.rig_graph import RigSolution
from estimators.solvers.rig_posterior import RigLikelihood, hold_terms


def likelihood_hessian(model, h: float = 1e-5) -> np.ndarray:
    """The Hessian (6x6) of the negative log-posterior ``model`` (a pair's rig likelihood:
    the extrinsic's tangent, then ``log s``) in the extrinsic's tangent at the MAP, the noise scale held at 1
    (central differences)."""

    def f(x):
        return -model(np.append(x, 0.0)[None])[0]

    E = np.eye(6) * h
    return np.array([[(f(E[a] + E[b]) - f(E[a] - E[b]) - f(-E[a] + E[b]) + f(-E[a] - E[b])) / (4 * h * h)
                      for b in range(6)] for a in range(6)])


def likelihood_gradient(model, h: float = 1e-7) -> np.ndarray:
    def f(x):
        return -model(np.append(x, 0.0)[None])[0]

    return np.array([(f(e) - f(-e)) / (2 * h) for e in np.eye(6) * h])


def rig_likelihood(ref, likelihood: str = "gaussian", nu: float = 4.0, cells=None, cell: int = 0):
    """A pair refinement's likelihood (``refinement.Refinement``) as the engine samples a pair's: the rig's over the
    views its graph was built from (:func:`pair_likelihood`), its range terms held at their estimate, its
    edges' share as a quadratic, a 2D scan's segment ends by their own likelihood; within mode ``cell`` of ``cells``
    when given."""
    rm = ref.range_model
    lidar = ref.views[1]
    least = 2 if ref.end_terms is not None and lidar.scan_line else 3  # scan lines with their segment ends: 2
    if len(lidar.W) < least:
        raise LidarcamError(f"only {len(lidar.W)} frame(s) left for the posterior; it needs at least {least}")
    return pair_likelihood(ref.T_camera_lidar, ref.covariance, ref.T_camera_board, ref.views,
                           np.asarray(rm.values_m) if rm is not None and rm.terms is not None else None,
                           ref.edge_share, likelihood, nu, ref.end_terms, cells, cell)


def sampled(ref, rng: np.random.Generator, min_ess: int, pilot: bool = False, likelihood: str = "gaussian"):
    """Samples of a pair refinement's likelihood (:func:`rig_likelihood`) by the engine's chain
    (``rig_posterior.run_chain``; ``pilot`` for a 2D scan's, as the engine runs it): the extrinsic's tangent
    samples (M, 6), the chain, the likelihood and the camera side's noise scale per sample."""
    from estimators.solvers.rig_posterior import run_chain

    model = rig_likelihood(ref, likelihood)
    keep, run = run_chain(model, ref.covariance, rng, min_ess, 40000, pilot=pilot)
    return keep[:, :6], run, model, np.exp(keep[:, -1])


def pair_likelihood(T_camera_lidar: np.ndarray, covariance: np.ndarray, T_camera_board: dict,
                    views: tuple[CameraViews, LidarViews], range_terms: np.ndarray | None = None,
                    quadratic: tuple[np.ndarray, np.ndarray] | None = None, likelihood: str = "gaussian",
                    nu: float = 4.0, ends: EndTerms | None = None, cells=None, cell: int = 0) -> RigLikelihood:
    """A single camera-LiDAR pair's likelihood: the rig of its camera (the reference) and its LiDAR at the
    refinement's estimate, its covariance and board poses (by stem), from the views its graph was built from
    (``PlaneProblem.views``); its range terms, when it has them, held at their estimate ``range_terms`` (the pair
    convolves their share into the samples); ``quadratic``: the board edges' share about the estimate."""
    camera, lidar = views
    if range_terms is not None and lidar.ranged is not None and lidar.terms is not None:
        lidar = hold_terms(lidar, range_terms)
    elif lidar.terms is not None:
        lidar = replace(lidar, terms=None, terms_prior_sd=None)
    joint = np.zeros((12, 12))
    joint[6:, 6:] = covariance
    solution = RigSolution((camera.name, lidar.name), camera.name, {camera.name: np.eye(4),
                                                                     lidar.name: T_camera_lidar},
                           joint, {st: T_camera_board[st] for st in lidar.W}, {}, {}, 0,
                           covariance_inner=covariance)
    # A scan's segment ends enter by their own likelihood, not by the edges' quadratic.
    return RigLikelihood(solution, [camera], [lidar], None if ends is not None else quadratic, likelihood=likelihood,
                         nu=nu, ends=None if ends is None else {lidar.name: ends},
                         cells=() if cells is None else ((cells, camera.name, lidar.name, cell),))
