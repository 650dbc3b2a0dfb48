"""What the posterior's samples say, in GTSAM's tangent about the estimate (a pair's right tangent: ``T_true =
T_hat Exp(xi)``): equal-tailed intervals, squared Mahalanobis distances, the credible regions (the samples'
covariance's ellipsoid about the estimate holding a level's share of them; with several minima, the union of each
one's own ellipsoid about it) and a heavy-tail note; the sampler's settings (:class:`PosteriorOptions`); and the
cells of several refined minima (:class:`ModeCells`), within which each is sampled. The posterior itself is the
engine's (``rig_posterior.sample_rig_posterior``: every sensor's pose from the joint graph's likelihood, a pair's
as a rig of two).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from geometry.rotations import T_exp

from . import chi_square as chi2
from .refinement import Refinement

LIKELIHOODS = ("gaussian", "student-t")
SAMPLERS = ("proposal", "ensemble")


@dataclass(frozen=True)
class PosteriorOptions:
    """Settings of the posterior sampler (emcee).

    Attributes
    ----------
    min_ess : int
        Effective samples wanted, of the slowest-mixing parameter.
    walkers : int
        Ensemble walkers (at least 24: twice the up to 11 parameters).
    likelihood : str
        ``gaussian`` or ``student-t``.
    nu : float
        The Student-t likelihood's degrees of freedom.
    max_steps : int
        Steps at most.
    chunk : int
        Steps between convergence checks.
    progress : bool
        Show a progress bar.
    sampler : str
        ``proposal`` (:func:`run_with_proposal`: most moves from a pilot-tuned independence proposal) or
        ``ensemble`` (differential evolution and the stretch move alone; slower to mix, for comparison).
    """

    min_ess: int = 2000  # effective samples wanted (of the slowest-mixing parameter)
    walkers: int = 48
    likelihood: str = "gaussian"
    nu: float = 4.0  # Student-t degrees of freedom
    max_steps: int = 40000
    chunk: int = 500
    progress: bool = False
    sampler: str = "proposal"

    def __post_init__(self):
        if self.likelihood not in LIKELIHOODS:
            raise ValueError(f"Expected likelihood in {LIKELIHOODS}, got {self.likelihood!r}")
        if self.sampler not in SAMPLERS:
            raise ValueError(f"Expected sampler in {SAMPLERS}, got {self.sampler!r}")
        if self.min_ess < 1 or self.walkers < 24:
            raise ValueError(f"Expected min_ess >= 1 and walkers >= 24 (at least twice the up to 11 parameters), got "
                             f"{self.min_ess} and {self.walkers}")


# A posterior whose 99.9% region (:func:`region_d2`) reaches this many times a Gaussian's squared distance
# is reported as heavy-tailed (:func:`heavy_tails`). The sampled noise scale alone makes every posterior a
# scale mixture, its 99.9% region 1.4-1.6 times a Gaussian's (the simulated default, ``lidarcam demo``): the
# warning is kept for the posteriors the covariance misdescribes (a 2D layout's curved valley, a minor mode).
HEAVY_TAIL_FACTOR = 2.0


# The equal-tailed intervals every posterior summary gives (calibration.json, printout, reports).
INTERVAL_LEVELS = (0.68, 0.95)


def equal_tailed(samples: np.ndarray, level: float) -> np.ndarray:
    """The equal-tailed intervals (K, 2) of each column of ``samples`` (M, K) at ``level`` (e.g. 0.95)."""
    q = 100 * (1 - level) / 2
    return np.percentile(samples, [q, 100 - q], axis=0).T


def mahalanobis_d2(samples: np.ndarray, xi: np.ndarray) -> np.ndarray:
    """Squared Mahalanobis distance of tangent offsets ``xi`` (rows; from the estimate the samples' tangent is
    taken at) under the covariance of ``samples`` (M, 6)."""
    xi = np.atleast_2d(xi)
    return np.einsum("ni,ni->n", xi, np.linalg.solve(np.cov(samples, rowvar=False), xi.T).T)


def region_d2(samples: np.ndarray, level: float, index: np.ndarray | None = None,
              centers: np.ndarray | None = None) -> float:
    """The credible region at ``level`` of posterior ``samples`` (M, 6; tangent offsets from the estimate): the
    ellipsoid of their covariance, about the estimate, that holds ``level`` of them, never smaller than a
    Gaussian's (the chi-square point, 6 dof). A posterior with heavy tails (a 2D layout's curved valley, the
    sampled range noise, a minor mode) needs a larger distance than the Gaussian's: the covariance's chi-square
    ellipsoid would leave the truth outside more often than ``1 - level``. With several modes (each sample's mode
    ``index``, the modes' minima at tangent offsets ``centers``), the region is the union of one ellipsoid per mode
    (:func:`mode_distance`), at the one distance that holds ``level`` of all samples."""
    d2 = (mahalanobis_d2(samples, samples) if index is None
          else mode_distance(samples, index, centers, samples, own=True))
    return float(max(chi2.ppf(level, 6), np.quantile(d2, level, method="higher")))


# A mode with fewer samples than this has its covariance taken from all samples (its own would be noise).
MIN_MODE_SAMPLES = 60


def mode_covariances(samples: np.ndarray, index: np.ndarray, modes: int) -> list[np.ndarray]:
    """Each mode's covariance: that of its samples (``index == k``), or of all samples for a mode with fewer than
    ``MIN_MODE_SAMPLES``."""
    out = []
    for k in range(modes):
        mine = samples[index == k]
        out.append(np.cov(mine if len(mine) >= MIN_MODE_SAMPLES else samples, rowvar=False))
    return out


def mode_distance(samples: np.ndarray, index: np.ndarray, centers: np.ndarray, xi: np.ndarray,
                  own: bool = False) -> np.ndarray:
    """The squared Mahalanobis distance of tangent offsets ``xi`` (rows) from the nearest mode of a mixture:
    mode ``k``'s minimum at ``centers[k]``, its covariance that of its samples (``index == k``). Each mode is
    described by its own ellipsoid, not the mixture's one: a minor mode far along a curved valley lies beyond
    the mixture's ellipsoid that holds 99.9% of the samples, yet well inside its own. ``own``: ``xi`` are the
    samples themselves, each measured from its own mode."""
    xi = np.atleast_2d(xi)
    info = [np.linalg.pinv(C) for C in mode_covariances(samples, index, len(centers))]
    d2 = np.stack([np.einsum("ni,ij,nj->n", xi - c, P, xi - c) for c, P in zip(centers, info)], axis=1)
    return d2[np.arange(len(xi)), index] if own else d2.min(axis=1)


def heavy_tails(samples: np.ndarray, level: float = 0.999, what: str = "posterior") -> str | None:
    """A note when the region of ``samples`` at ``level`` reaches beyond ``HEAVY_TAIL_FACTOR`` times a Gaussian's
    distance (the covariance alone then understates how far the truth may lie), else None."""
    q, g = region_d2(samples, level), chi2.ppf(level, 6)
    if q < HEAVY_TAIL_FACTOR * g:
        return None
    return (f"the {what}'s tails are heavier than a Gaussian's: its {100 * level:g}% region reaches a squared "
            f"Mahalanobis distance of {q:.1f} under the covariance (a Gaussian's {g:.1f}); judge tail "
            "probabilities by that region or the samples (posterior.npz), not by the covariance alone")


def regions(samples: np.ndarray, index: np.ndarray | None = None, centers: np.ndarray | None = None,
            T: np.ndarray | None = None, weights: tuple = ()) -> dict:
    """The credible regions (:func:`region_d2`) of ``samples`` at 99% and 99.9%, beside a Gaussian's, for
    calibration.json; with several modes (each sample's mode ``index``, the modes' minima at tangent offsets
    ``centers`` of the estimate ``T``, their masses ``weights``), each mode's minimum and covariance: the region is
    the union of their ellipsoids."""
    levels = {f"{100 * level:g}%": {"d2": region_d2(samples, level, index, centers),
                                    "gaussian_d2": float(chi2.ppf(level, 6))} for level in (0.99, 0.999)}
    if index is None:
        return {"definition": "T = T_hat * Exp(xi) with xi^T covariance^-1 xi at most d2: the covariance's "
                              "ellipsoid about the estimate holding the level's share of the samples, never below a "
                              "Gaussian's chi-square point", **levels}
    covs = mode_covariances(samples, index, len(centers))
    modes = [{"T": (T @ T_exp(c)).tolist(), "posterior_mass": float(w), "covariance": C.tolist()}
             for c, w, C in zip(centers, weights, covs)]
    return {"definition": "T = T_mode * Exp(xi) with xi^T covariance^-1 xi at most d2 for one of the modes (each its "
                          "minimum and the covariance of its samples): the union of the modes' ellipsoids holding the "
                          "level's share of the samples, never below a Gaussian's chi-square point",
            **levels, "modes": modes}


class ModeCells:
    """The cells of several refined minima: each point belongs to the minimum nearest to it, by the squared
    Mahalanobis distance of ``[rotation vector; translation]`` (the point relative to the minimum, in the
    minimum's axes) under the minimum's covariance. Sampled within its cell, each minimum's samples stay its own,
    and mixing them by the minima's masses counts none twice (a wide, shallow minimum's walkers would otherwise
    reach a deeper one)."""

    def __init__(self, refs: list[Refinement]):
        self.R = np.array([r.T_camera_lidar[:3, :3] for r in refs])
        self.t = np.array([r.T_camera_lidar[:3, 3] for r in refs])
        self.info = np.array([np.linalg.pinv(r.covariance) for r in refs])

    def nearest(self, R: np.ndarray, t: np.ndarray) -> np.ndarray:
        """The index of the nearest minimum for (w, 3, 3) rotations and (w, 3) translations of ``T_camera_lidar``."""
        from scipy.spatial.transform import Rotation

        d = np.empty((len(R), len(self.R)))
        for j, (Rj, tj, Ij) in enumerate(zip(self.R, self.t, self.info)):
            rel = np.einsum("ji,wjk->wik", Rj, R)
            x = np.hstack([Rotation.from_matrix(rel).as_rotvec(), (t - tj) @ Rj])
            d[:, j] = np.einsum("wi,ij,wj->w", x, Ij, x)
        return np.argmin(d, axis=1)
