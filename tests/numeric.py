"""Finite-difference helpers shared by the tests."""
from __future__ import annotations

import numpy as np


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
