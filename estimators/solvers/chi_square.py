"""The chi-square distribution's tail, quantiles and median, and the F distribution's tail, from scipy.special.

The tests and gates of the solvers need only these functions. Importing `scipy.stats` for them costs about
0.7 s at start-up (it builds every distribution's docstring), more than a cached calibration's whole solve, so
they are computed here from the regularised incomplete gamma function and its inverse.
"""
from __future__ import annotations

from scipy.special import chdtrc, chdtri
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
