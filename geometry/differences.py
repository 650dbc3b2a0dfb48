"""Derivatives of a vectorised scalar function by central differences."""
from __future__ import annotations

from typing import Callable

import numpy as np


def central_hessian(f: Callable[[np.ndarray], np.ndarray], x0: np.ndarray, h: np.ndarray
                    ) -> tuple[float, np.ndarray, np.ndarray] | None:
    """``f(x0)``, the gradient and the Hessian of ``f`` at ``x0`` (n,) by central differences of steps ``h`` (n,),
    from one call of ``f`` on all ``2 n^2 + 1`` points ((K, n) -> (K,)); None where ``f`` is not finite at one of
    them."""
    n = len(x0)
    e = np.eye(n) * h
    i, j = np.triu_indices(n, 1)
    v = f(np.vstack([x0, x0 + e, x0 - e, x0 + e[i] + e[j], x0 + e[i] - e[j], x0 - e[i] + e[j], x0 - e[i] - e[j]]))
    if not np.all(np.isfinite(v)):
        return None
    f0, fp, fm = v[0], v[1:n + 1], v[n + 1:2 * n + 1]
    q = v[2 * n + 1:].reshape(4, -1)
    H = np.diag((fp - 2 * f0 + fm) / h**2)
    H[i, j] = H[j, i] = (q[0] - q[1] - q[2] + q[3]) / (4 * h[i] * h[j])
    return float(f0), (fp - fm) / (2 * h), H
