"""The chi-square distribution's tail, quantiles and median, and the F and Student t distributions' tails, from
scipy.special.

The tests and gates of the solvers need only these functions. Importing `scipy.stats` for them costs about
0.7 s at start-up (it builds every distribution's docstring), more than a cached calibration's whole solve, so
they are computed here from the regularised incomplete gamma function and its inverse.
"""
from __future__ import annotations

import numpy as np
from scipy.special import chdtrc, chdtri, fdtri, stdtr
from scipy.special import fdtrc as _fdtrc


def sf(x, dof):
    """P(X > x) for X ~ chi-square(dof)."""
    return chdtrc(dof, x)


def isf(p, dof):
    """The x with P(X > x) = p."""
    return chdtri(dof, p)


def ppf(q, dof):
    """The x with P(X <= x) = q."""
    return chdtri(dof, 1.0 - q)


def median(dof):
    """The distribution's median."""
    return chdtri(dof, 0.5)


def fdtrc(dfn, dfd, x):
    """P(X > x) for X ~ F(dfn, dfd)."""
    return _fdtrc(dfn, dfd, x)


def f_isf(p, dfn, dfd):
    """The x with P(X > x) = p for X ~ F(dfn, dfd)."""
    return fdtri(dfn, dfd, 1.0 - p)


def t_sf(t, dof):
    """P(T > t) for T ~ Student's t(dof)."""
    return stdtr(dof, -np.asarray(t, dtype=float))


def drop_p(k: int, ss_given: float, ss_freed: float, dof: float) -> float:
    """The F test of a chi-square's drop from ``ss_given`` to ``ss_freed`` when ``k`` parameters are freed, ``dof``
    the freed fit's degrees of freedom: the chance that freed parameters fitting noise alone drop it this far (NaN
    where the test is not defined)."""
    if not (np.isfinite(ss_given) and np.isfinite(ss_freed)) or k <= 0 or dof <= 0 or ss_freed <= 0:
        return float("nan")
    return float(fdtrc(k, dof, max(ss_given - ss_freed, 0.0) / k / (ss_freed / dof)))


def mahalanobis(x, C, max_var: float = np.inf) -> tuple[float, int]:
    """``x^T C^+ x`` over the directions ``C`` holds (eigenvalues above 1e-9 of its largest, and at most
    ``max_var``: wider ones carry no test) and their count (the chi-square's degrees of freedom)."""
    ev, V = np.linalg.eigh(0.5 * (C + C.T))
    keep = (ev > 1e-9 * max(float(ev[-1]), 1e-300)) & (ev <= max_var)
    y = V[:, keep].T @ np.asarray(x)
    return float(np.sum(y**2 / ev[keep])), int(keep.sum())
