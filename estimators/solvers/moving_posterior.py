"""The posterior of a moving board's extrinsic and clock offset by MCMC (emcee), beside the joint solve's Laplace
covariance (``clock_offset``).

Parameters: the extrinsic's right tangent about the estimate and the offset's departure from it (s): 7, or 6 with
the offset held. The likelihood: every return the joint solve used, Gaussian along its beam at the noise that
solve weighed it by, against the board where the solve left its trajectory (the knots, each sweep's time
nuisance); the offset under its uniform prior (``+-offset_prior_s``), the extrinsic's prior flat. The board's pose
at a return's time plus the offset is expanded to second order in the offset's departure (the board moves a
fraction of a millimetre over the posterior's reach of a few milliseconds; the third order is below a
micrometre), so a walker's likelihood is a few matrix products over the returns, exact in the extrinsic.

Conditional on the trajectory, the chain misses what the camera's board poses, the sweeps' time nuisances and the
camera's pointing add. That share, the joint covariance less the conditional one's Laplace (the likelihood's
Gauss-Newton information, inverted), plus the pointing, is added to every sample as a Gaussian draw (and a sample
it carries past the offset's prior dropped): where the likelihood is Gaussian the samples' covariance is the joint
Laplace one; where it is not (a likelihood curved over its reach, the offset against its prior's edge) the
samples say how.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from geometry.rotations import retract_batch

from ..errors import PosteriorSkippedError
from .clock_offset import MovingFit
from .moving_board_graph import Knots
from .sampler import ChainResult, run_with_proposal

# The offset's step (s) for the board's time derivatives along each return.
H_S = 1e-3
# Walkers of the ensemble (at least twice the parameters), and the samples kept (thinned evenly).
WALKERS = 32
MAX_KEPT = 20000
# Fewer samples than this left inside the offset's prior give no intervals worth the name.
MIN_KEPT = 200
# Steps between the chain's checks of its length: the proposal's autocorrelation is 2-3 steps, so 2000 effective
# samples take about 150 (the default chunk of 500 ran three times that on every recording).
CHUNK = 150
# A beam this close to the board's plane (the cosine) gives no residual, as in the solve.
GRAZING = 1e-3


@dataclass(frozen=True, eq=False)
class MovingPosterior:
    """Samples ``xi`` (M, 7): the extrinsic's right tangent about the estimate and the offset's departure from it
    (s; zero when held), with the chain's diagnostics (``run``), the conditional Laplace covariance the chain's
    proposal used and the covariance added to its samples (the camera's share and pointing)."""

    xi: np.ndarray
    run: ChainResult
    conditional: np.ndarray
    added: np.ndarray


class MovingLikelihood:
    """The log-posterior of :class:`MovingFit`'s problem over walkers' rows ``x`` (W, 6 or 7): see the module."""

    def __init__(self, fit: MovingFit):
        self.fit = fit
        self.free = fit.free_offset
        self.ndim = 7 if self.free else 6
        knots = Knots(fit.tau, fit.K)
        ranges = np.linalg.norm(fit.points, axis=1)
        u = fit.points / ranges[:, None]

        def board(t):
            R, o = knots.poses(t, knots.interval(t))
            return R[:, :, 2], o

        t = fit.times_s + fit.time_offset_s
        (n0, o0), (nm, om), (npl, opl) = board(t), board(t - H_S), board(t + H_S)
        n1, o1 = (npl - nm) / (2 * H_S), (opl - om) / (2 * H_S)
        n2, o2 = (npl - 2 * n0 + nm) / H_S ** 2, (opl - 2 * o0 + om) / H_S ** 2
        m = len(ranges)
        dot = np.einsum
        # along(d) = n(d)^T R u = <R, n(d) u^T>: each order's n u^T as 9 rows (R flattened row by row), so that
        # one matrix product of [R, d R, d^2/2 R] gives every walker's; likewise n(d)^T (o(d) - t), whose
        # n(d)^T o(d) is taken to second order in d, from [1, d, d^2, t, d t, d^2/2 t]
        self.along_rows = np.vstack([(n[:, :, None] * u[:, None, :]).reshape(m, 9).T for n in (n0, n1, n2)])
        c2 = 0.5 * (dot("ni,ni->n", n0, o2) + dot("ni,ni->n", n2, o0)) + dot("ni,ni->n", n1, o1)
        self.num_rows = np.vstack([dot("ni,ni->n", n0, o0), dot("ni,ni->n", n0, o1) + dot("ni,ni->n", n1, o0), c2,
                                   -n0.T, -n1.T, -n2.T])
        self.ranges = ranges
        self.lo = -fit.offset_prior_s - fit.time_offset_s
        self.hi = fit.offset_prior_s - fit.time_offset_s

    def residuals(self, x: np.ndarray) -> np.ndarray:
        """Each walker's residuals (W, m) over the returns (m)."""
        x = np.atleast_2d(x)
        R, t = retract_batch(self.fit.T_camera_lidar, x[:, :6])
        d = x[:, 6:7] if self.free else np.zeros((len(x), 1))
        Rf = R.reshape(len(x), 9)
        along = np.hstack([Rf, d * Rf, 0.5 * d ** 2 * Rf]) @ self.along_rows
        num = np.hstack([np.ones_like(d), d, d ** 2, t, d * t, 0.5 * d ** 2 * t]) @ self.num_rows
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(np.abs(along) > GRAZING, self.ranges - num / along, 0.0)

    def __call__(self, x: np.ndarray) -> np.ndarray:
        x = np.atleast_2d(x)
        out = np.full(len(x), -np.inf)
        ok = np.all(np.isfinite(x), axis=1)
        if self.free:
            ok &= (x[:, 6] >= self.lo) & (x[:, 6] <= self.hi)
        if ok.any():
            r = self.residuals(x[ok]) / self.fit.sigma_r
            out[ok] = -0.5 * np.sum(r * r, axis=1)
        return out

    def conditional_covariance(self, step: float = 1e-7) -> np.ndarray:
        """The Laplace covariance of the likelihood alone (the trajectory held): ``sigma^2 (J^T J)^-1`` of the
        residuals' Jacobian at the estimate, by central differences."""
        E = step * np.eye(self.ndim)
        J = (self.residuals(E) - self.residuals(-E)).T / (2 * step)
        info = J.T @ J / self.fit.sigma_r ** 2
        return np.linalg.inv(0.5 * (info + info.T))


def _psd(C: np.ndarray) -> np.ndarray:
    """The nearest positive semi-definite matrix (negative eigenvalues, round-off, set to zero)."""
    w, V = np.linalg.eigh(0.5 * (C + C.T))
    return (V * np.maximum(w, 0.0)) @ V.T


def sample_moving_posterior(fit: MovingFit, rng: np.random.Generator, min_ess: int = 2000, max_steps: int = 20000,
                            progress: bool = False) -> MovingPosterior:
    """Sample the posterior of ``fit``'s extrinsic and offset (see the module) until ``min_ess`` effective samples
    or ``max_steps``. Raises :class:`~estimators.errors.PosteriorSkippedError` where the conditional information
    is singular (the covariance is then the Laplace one)."""
    joint = fit.covariance.copy()
    joint[:6, :6] += fit.pointing
    return sample_moving_posteriors([fit], joint, rng, min_ess, max_steps, progress)[0]


def sample_moving_posteriors(fits: list[MovingFit], joint: np.ndarray, rng: np.random.Generator, min_ess: int = 2000,
                             max_steps: int = 20000, progress: bool = False) -> list[MovingPosterior]:
    """:func:`sample_moving_posterior` of several LiDARs solved on one board trajectory, whose joint covariance
    (7 per LiDAR, with the camera's pointing) is ``joint``: given the trajectory their likelihoods are independent,
    so each LiDAR's chain runs alone; the camera's share, common to them, is one joint draw per sample (row ``k`` of
    every LiDAR's samples is one joint sample: a transform between two LiDARs is composed row by row)."""
    likes = [MovingLikelihood(f) for f in fits]
    Cs = []
    for like in likes:
        try:
            C = like.conditional_covariance()
            np.linalg.cholesky(C)
        except np.linalg.LinAlgError:
            raise PosteriorSkippedError("the returns leave a direction of the extrinsic or the offset free given "
                                        "the board's trajectory", hint="the covariance is the Laplace one") from None
        Cs.append(C)
    n = likes[0].ndim
    runs = []
    for like, C in zip(likes, Cs):
        start = rng.multivariate_normal(np.zeros(n), 0.25 * C, WALKERS)
        runs.append(run_with_proposal(like, start, rng, C, min_ess=min_ess, max_steps=max_steps, chunk=CHUNK,
                                      progress=progress, label="posterior (moving board)", centre=np.zeros(n)))
    M = min(MAX_KEPT, *(len(r.samples) for r in runs))
    kept = np.hstack([r.samples[np.linspace(0, len(r.samples) - 1, M).astype(int)] for r in runs])
    at = np.concatenate([7 * j + np.arange(n) for j in range(len(fits))])
    conditional = np.zeros((len(at), len(at)))
    for j, C in enumerate(Cs):
        conditional[n * j:n * j + n, n * j:n * j + n] = C
    added = _psd(joint[np.ix_(at, at)] - conditional)
    kept = kept + rng.multivariate_normal(np.zeros(len(at)), added, M, method="eigh")
    inside = np.ones(M, bool)
    for j, like in enumerate(likes):  # the prior holds each offset after the draw too (the share is a factor)
        if like.free:
            inside &= (kept[:, n * j + 6] >= like.lo) & (kept[:, n * j + 6] <= like.hi)
    if inside.sum() < MIN_KEPT:
        raise PosteriorSkippedError(f"only {int(inside.sum())} of {M} samples keep the offset within its prior",
                                    hint="the covariance is the Laplace one; the offset lies at its prior's edge")
    out = []
    for j, (run, C) in enumerate(zip(runs, Cs)):
        xi = np.zeros((int(inside.sum()), 7))
        xi[:, :n] = kept[inside, n * j:n * j + n]
        out.append(MovingPosterior(xi, run, C, added[n * j:n * j + n, n * j:n * j + n]))
    return out
