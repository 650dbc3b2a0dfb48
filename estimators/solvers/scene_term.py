"""A measurement of one pair's transform joined to a solved graph at its linearisation (``calibrate --scene``).

The graph's estimate is every sensor's pose ``T_ref`` with the joint covariance ``P`` of their right tangents
(``RigSolution``). A second witness measures the pair's transform ``T_a_b`` as ``T_meas`` with covariance ``C``
(its right tangent). To first order ``T_a_b`` moves by ``H x`` when the poses move by ``x``, with
``H = [-Ad(T_a_b^-1) | I]`` on the blocks of ``a`` and ``b`` (``rig_graph.pair_transform``), and the measurement
reads ``z = Log(T_a_b^-1 T_meas)``. Where the witness leaves a direction free (its standard deviation beyond
``limits``), that direction is not measured: ``z``, ``H`` and ``C`` are projected on the constrained ones
(``scene_alignment.constrained_directions``). The joint estimate is the Kalman step ``x = K z``,
``K = P H^T (H P H^T + C)^-1``, with covariance ``(I - K H) P``: the graph's Gauss-Newton step with the witness's
Gaussian factor added, exact where the graph's factors are linear over the step. A sample ``x_i`` of the graph's
posterior becomes ``(I - K H) x_i + K e_i`` (``e_i`` drawn from ``C``) about the joint estimate: samples of the
joint posterior to the same order.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from geometry.rotations import T_inverse, T_log

from . import chi_square
from .factor_graph import adjoint
from .scene_alignment import CONSTRAINED, constrained_directions


@dataclass(frozen=True, eq=False)
class JoinedTerm:
    """A witness's measurement joined to the graph: the step ``dx`` of every pose's tangent (6N), the joint
    covariance, the gain (6N x k) and the projected Jacobian (k x 6N) that move the posterior's samples, and the
    test of the witness against the graph (``d2`` on ``dof`` = k directions, ``p_value``)."""

    dx: np.ndarray
    covariance: np.ndarray
    gain: np.ndarray
    H: np.ndarray
    noise: np.ndarray  # k x k: the witness's covariance on the measured directions
    innovation: np.ndarray  # k x k: the difference's covariance, graph's and witness's (``H P H^T + noise``)
    difference: np.ndarray  # k: the witness less the graph on the measured directions
    d2: float
    dof: int
    p_value: float

    def moved_samples(self, xi: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """The graph's posterior samples (M, 6N, tangents at the graph's estimate) as samples of the joint
        posterior (tangents at the joint estimate; module docstring)."""
        e = rng.multivariate_normal(np.zeros(self.noise.shape[0]), self.noise, len(xi), method="eigh")
        return xi - xi @ (self.gain @ self.H).T + e @ self.gain.T


def pair_jacobian(names: tuple, T_ref: dict, a: str, b: str) -> np.ndarray:
    """``H`` (6 x 6N): how ``T_a_b``'s right tangent moves with every sensor's pose tangent (``names`` order)."""
    H = np.zeros((6, 6 * len(names)))
    ka, kb = names.index(a), names.index(b)
    H[:, 6 * ka:6 * ka + 6] = -adjoint(T_inverse(T_inverse(T_ref[a]) @ T_ref[b]))
    H[:, 6 * kb:6 * kb + 6] = np.eye(6)
    return H


def join_pair_measurement(names: tuple, T_ref: dict, P: np.ndarray, a: str, b: str, T_meas: np.ndarray,
                          C_meas: np.ndarray, blocks: int | None = None,
                          limits: tuple[float, float] = CONSTRAINED) -> JoinedTerm | None:
    """The witness ``T_meas`` (``T_a_b``, covariance ``C_meas``) joined to the graph's estimate ``T_ref`` with
    joint covariance ``P`` (module docstring) over every direction it constrains; None when it constrains none.
    The test: chi-square on the measured directions, or, where the witness's covariance was estimated from
    ``blocks`` independent blocks, Hotelling's F on ``(k, blocks - k)`` as the scene's own test
    (``scene_alignment.consistency``)."""
    T_ab = T_inverse(T_ref[a]) @ T_ref[b]
    z = T_log(T_inverse(T_ab) @ T_meas)
    V, lam = constrained_directions(C_meas, limits)
    if V.shape[1] == 0:
        return None
    s = np.r_[np.full(3, 1.0 / limits[0]), np.full(3, 1.0 / limits[1])]
    W = V.T * s[None, :]  # k x 6: the constrained directions' coordinates, in units of ``limits``
    return _kalman(P, W @ pair_jacobian(names, T_ref, a, b), W @ z, np.diag(lam), blocks)


def join_pair_translation(names: tuple, T_ref: dict, P: np.ndarray, a: str, b: str, T_meas: np.ndarray,
                          C_meas: np.ndarray, u: np.ndarray, blocks: int | None = None) -> JoinedTerm:
    """The witness joined along one direction only: ``u . t`` (``u`` a unit vector in a's frame, ``t`` the
    translation of ``T_a_b``), as ``T_meas`` gives it with the variance its covariance ``C_meas`` gives that
    number (its rotation's share included). The test as :func:`join_pair_measurement`'s, on one direction."""
    T_ab = T_inverse(T_ref[a]) @ T_ref[b]
    Rm = T_meas[:3, :3]
    h = np.r_[np.zeros(3), u @ T_ab[:3, :3]][None, :]  # u . t moves by u . R v for a right step (w, v)
    y = np.array([u @ (T_meas[:3, 3] - T_ab[:3, 3])])
    r = np.array([[float(u @ Rm @ C_meas[3:, 3:] @ Rm.T @ u)]])
    return _kalman(P, h @ pair_jacobian(names, T_ref, a, b), y, r, blocks)


def _kalman(P: np.ndarray, H: np.ndarray, y: np.ndarray, R: np.ndarray, blocks: int | None) -> JoinedTerm:
    """The step, joint covariance and gain of the measurement ``y = H x + e``, ``e ~ N(0, R)``, and its test."""
    S = H @ P @ H.T + R
    S_inv = np.linalg.inv(0.5 * (S + S.T))
    K = P @ H.T @ S_inv
    A = np.eye(len(P)) - K @ H
    cov = A @ P @ A.T + K @ R @ K.T  # Joseph's form of (I - K H) P: symmetric and positive to rounding
    d2 = float(y @ S_inv @ y)
    k = int(len(y))
    if blocks is not None and blocks > k:
        p = float(chi_square.fdtrc(k, blocks - k, d2 * (blocks - k) / (k * (blocks - 1))))
    else:
        p = float(chi_square.sf(d2, k))
    return JoinedTerm(K @ y, 0.5 * (cov + cov.T), K, H, R, S, y, d2, k, p)
