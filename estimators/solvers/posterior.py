"""The posterior of ``T_camera_lidar`` by MCMC (emcee), in GTSAM's tangent space around the MAP.

A pair's likelihood is the rig's (``rig_posterior.pair_likelihood``: the rig of its camera and its LiDAR, over
the views its graph was built from), 3D or 2D. The model, in a pair's terms:

Parameters: ``xi`` (6), ``T = T_hat Exp(xi)``; for a 2D scan with its segment ends, the dataset's outline (4);
for a 2D scan, ``log r``; last ``log s``, the scale of the camera-side noise (the effective corner noise and any
per-board plane error) relative to what the refinement assumed: that level is the least certain part of the noise
model (corner errors correlate within a board), so it is estimated with the extrinsic, under a log-normal prior
(sd 0.5 on ``log s``). A 3D LiDAR's range noise is not sampled: thousands of board points pin it down. A 2D
scan's rests on a few dozen: its scale ``r`` is sampled as well (flat prior on ``log r``), the lines' residuals
about their own best fits carrying their share of its likelihood, so the intervals hold the range noise's
uncertainty (a Student-t-like widening of the tails).

Likelihood, per used frame ``i`` (MATH.md section 3), with the board pose integrated out: the corners fix the
board pose ``b_i`` with covariance ``Sigma_b = sigma_px^2 (J^T J)^-1`` at the board's own corner noise;
linearising the board plane in the board pose,

    e_i(T) = W_i pi(T, b_i),   C_i = sigma_r^2 I + W_i H_b Sigma_b H_b^T W_i^T (+ the per-board plane error),

``W_i`` the square root of the board points' excess range moment, so ``e_i`` carries all of the frame's
LiDAR points in O(1), and ``C_i(s) = A_i + s^2 B_i`` (LiDAR part, camera part). Gaussian:
``-e^T C^-1 e / 2 - log det C / 2``; Student-t with ``nu`` degrees of freedom:
``-(nu + k)/2 log(1 + e^T C^-1 e / nu) - log det C / 2`` (heavy tails for frames that the Gaussian would let
dominate). A frame the robust loss down-weighted keeps that weight. When the intrinsics were calibrated
from the same images, their first-order effect (from the refinement) is convolved into the samples. With a
LiDAR range model (``solvers.range_model``) its terms are held at the MAP in the likelihood and their share of
the extrinsic's covariance is convolved in the same way, so the intervals are marginal over them. With the
board's edges (``--edges``), their share of the log-posterior enters as a quadratic about the MAP (their
nuisances and the board poses profiled out), second order like a Laplace approximation of that share alone:
the ends' Huber weights are those of the refinement. A 2D scan's segment ends enter by their own likelihood
(``board_edges.EndSet``) with the dataset's outline under its prior: with a few boards, an end hidden before its
edge moves the posterior beyond what a quadratic holds. Several refined minima are each sampled within their
cell (:class:`ModeCells`) and mixed by mass (:func:`sample_posterior`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from geometry.board import BoardModel
from geometry.camera import CameraModel
from geometry.rotations import T_exp, T_log, retangent_batch

from ..errors import DegenerateLayoutError, LidarcamError, PosteriorSkippedError
from ..measurements import FrameMeasurement
from . import chi_square as chi2
from .refinement import Refinement
from .refusal import POSTERIOR_REFUSAL_FACTOR, scan_refusal
from .rig_posterior import pair_likelihood, run_chain
from .sampler import ChainResult, mixture_picks

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


# A posterior whose 99.9% region (``Posterior.region_d2``) reaches this many times a Gaussian's squared distance
# is reported as heavy-tailed (``Posterior.heavy_tails``). The sampled noise scale alone makes every posterior a
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


@dataclass(frozen=True, eq=False)
class Posterior:
    """Posterior samples of ``xi`` (tangent at ``T_map``) and of the noise scale, with diagnostics."""

    T_map: np.ndarray
    xi: np.ndarray  # (M, 6)
    scale: np.ndarray  # (M,)
    run: ChainResult
    likelihood: str
    warnings: tuple[str, ...] = ()
    # With several modes (2D): each mode's share of the samples, the MAP's first (empty: one mode), and each
    # sample's mode (index into the weights; None: one mode).
    mode_weights: tuple[float, ...] = ()
    mode_index: np.ndarray | None = None
    mode_centers: np.ndarray | None = None  # (K, 6): each mode's minimum, a tangent offset from T_map

    @property
    def covariance(self) -> np.ndarray:
        return np.cov(self.xi, rowvar=False)

    def intervals(self, level: float) -> np.ndarray:
        """Equal-tailed intervals (6, 2) of each tangent axis at ``level`` (e.g. 0.95)."""
        return equal_tailed(self.xi, level)

    def d2(self, xi: np.ndarray) -> np.ndarray:
        """Squared Mahalanobis distance of tangent offsets ``xi`` (from the MAP, ``T = T_map Exp(xi)``) under
        :attr:`covariance`."""
        return mahalanobis_d2(self.xi, xi)

    def region_d2(self, level: float) -> float:
        """The credible region at ``level`` (:func:`region_d2`): ``T = T_map Exp(xi)`` with
        ``region_distance(xi)`` at most this."""
        return region_d2(self.xi, level, self.mode_index, self.mode_centers)

    def region_distance(self, xi: np.ndarray) -> np.ndarray:
        """The distance the credible region bounds, of tangent offsets ``xi`` (rows): :meth:`d2` for one mode,
        the distance from the nearest mode under that mode's covariance for several (:func:`mode_distance`)."""
        if self.mode_index is None:
            return self.d2(xi)
        return mode_distance(self.xi, self.mode_index, self.mode_centers, xi)

    def contains(self, T: np.ndarray, level: float) -> bool:
        """Whether the pose ``T`` (``T_camera_lidar``) lies in the credible region at ``level``."""
        xi = T_log(np.linalg.inv(self.T_map) @ T)
        return bool(self.region_distance(xi)[0] <= self.region_d2(level))

    def heavy_tails(self, level: float = 0.999) -> str | None:
        """A note when the region at ``level`` reaches beyond ``HEAVY_TAIL_FACTOR`` times a Gaussian's distance
        (:func:`heavy_tails`), else None."""
        return heavy_tails(self.xi, level)

    def summary(self) -> dict:
        """Intervals in degrees (rotation about the LiDAR's axes) and millimetres (translation along them)."""
        out = {}
        for level in INTERVAL_LEVELS:
            iv = self.intervals(level)
            out[f"{round(100 * level)}%"] = {"rotation_deg_about_lidar_xyz": np.degrees(iv[:3]).tolist(),
                                            "translation_mm_along_lidar_xyz": (1000 * iv[3:]).tolist()}
        return out

    def regions(self) -> dict:
        """The credible regions (:func:`regions`) at 99% and 99.9%, beside a Gaussian's; with several modes, each
        mode's minimum and covariance (the region is the union of their ellipsoids)."""
        if self.mode_index is None:
            return regions(self.xi)
        covs = mode_covariances(self.xi, self.mode_index, len(self.mode_centers))
        modes = [{"T_camera_lidar": (self.T_map @ T_exp(c)).tolist(), "posterior_mass": w, "covariance": C.tolist()}
                 for c, w, C in zip(self.mode_centers, self.mode_weights, covs)]
        return {"definition": "T = T_mode * Exp(xi) with xi^T covariance^-1 xi at most d2 for one of the modes "
                              "(each its minimum and the covariance of its samples): the union of the modes' "
                              "ellipsoids holding the level's share of the samples, never below a Gaussian's "
                              "chi-square point",
                **{f"{100 * level:g}%": {"d2": self.region_d2(level), "gaussian_d2": float(chi2.ppf(level, 6))}
                   for level in (0.99, 0.999)},
                "modes": modes}

    def diagnostics(self) -> dict:
        return {"likelihood": self.likelihood, **self.run.diagnostics(),
                "noise_scale_median": float(np.median(self.scale)),
                "mode_weights": list(self.mode_weights)}  # the diagnostics of the chain are the MAP mode's


def rig_likelihood(ref: Refinement, likelihood: str = "gaussian", nu: float = 4.0, cells: "ModeCells | None" = None,
                   cell: int = 0):
    """A pair's likelihood, as its posterior samples it: the rig's over the views its graph was built from
    (``rig_posterior.pair_likelihood``), its range terms held at their estimate, its edges' share as a quadratic, a
    2D scan's segment ends by their own likelihood; within mode ``cell`` of ``cells`` when given."""
    rm = ref.range_model
    lidar = ref.views[1]
    least = 2 if ref.end_terms is not None and lidar.scan_line else 3  # scan lines with their segment ends: 2
    if len(lidar.W) < least:
        raise LidarcamError(f"only {len(lidar.W)} frame(s) left for the posterior; it needs at least {least}")
    return pair_likelihood(ref.T_camera_lidar, ref.covariance, ref.T_camera_board, ref.views,
                           np.asarray(rm.values_m) if rm is not None and rm.terms is not None else None,
                           ref.edge_share, likelihood, nu, ref.end_terms, cells, cell)


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


# A Laplace covariance beyond these limits does not describe a posterior worth sampling: some direction is
# not determined by the data (an ensemble started there is degenerate, and emcee refuses it).
MAX_SAMPLED_ROTATION_SD_RAD = float(np.deg2rad(10.0))
MAX_SAMPLED_TRANSLATION_SD_M = 0.5
MAX_SAMPLED_CONDITION = 1e12


def unsampled_reason(covariance: np.ndarray) -> str | None:
    """Why a posterior with this Laplace covariance (GTSAM tangent) should not be sampled, or None."""
    C = np.asarray(covariance, dtype=float)
    if C.shape != (6, 6) or not np.all(np.isfinite(C)):
        return "the Laplace covariance is not finite"
    sd = np.sqrt(np.maximum(np.diag(C), 0.0))
    w = np.linalg.eigvalsh(0.5 * (C + C.T))
    if sd[:3].max() > MAX_SAMPLED_ROTATION_SD_RAD or sd[3:].max() > MAX_SAMPLED_TRANSLATION_SD_M:
        return (f"the problem is nearly degenerate (Laplace standard deviations up to {np.degrees(sd[:3].max()):.1f} "
                f"deg and {1000 * sd[3:].max():.0f} mm): the data do not determine every direction")
    if w[0] <= 0 or w[-1] / w[0] > MAX_SAMPLED_CONDITION:
        return (f"the Laplace covariance is nearly singular (condition number {w[-1] / max(w[0], 1e-300):.1e}): "
                "some direction is determined far better than the others can be sampled together")
    return None


def sample_posterior(frames: list[FrameMeasurement], board: BoardModel, camera: CameraModel, ref: Refinement,
                     rng: np.random.Generator, options: PosteriorOptions = PosteriorOptions(),
                     other_modes: tuple = (), mass: float = 1.0) -> Posterior:
    """Sample the posterior of ``T_camera_lidar`` around the refinement's MAP. ``other_modes``: other refined
    minima that hold posterior mass, as ``(Refinement, mass)`` pairs, ``mass`` the MAP's own. Walkers do not
    cross between separated minima, so each is sampled from its own start, and the samples are mixed in
    proportion to the masses, in the MAP's tangent: the intervals cover every mode. A mode that cannot be
    sampled contributes its Laplace approximation (with a warning). A nearly degenerate problem at the MAP raises
    :class:`PosteriorSkippedError` with the reason (``unsampled_reason``) instead of sampling; a 2D MAP mode
    whose samples spread ``POSTERIOR_REFUSAL_FACTOR`` times as far as the refinement refuses
    (:func:`refusal.scan_refusal`) raises :class:`DegenerateLayoutError`."""
    cells = ModeCells([ref] + [r for r, _ in other_modes]) if other_modes else None
    main = _sample_mode(frames, board, camera, ref, rng, options, cells, 0)
    usable = [f for f in frames if f.usable]
    if usable and all(f.lidar.is_scan_line for f in usable):
        # 2D: the MAP's own mode, sampled, spread well beyond what the refinement refuses (its curved valley
        # reaches further than its Laplace approximation): unobservable in all but name, not an answer.
        weak = scan_refusal(main.covariance, ref.T_camera_lidar, len(usable), ref.end_terms is not None,
                            POSTERIOR_REFUSAL_FACTOR)
        if weak is not None:
            raise DegenerateLayoutError(f"sampled, {weak.problem}", hint=weak.hint)
    if not other_modes:
        return main
    parts, warnings, centers = [(main.xi, main.scale, mass)], list(main.warnings), [np.zeros(6)]
    for k, (r, m) in enumerate(other_modes, start=2):
        try:
            p = _sample_mode(frames, board, camera, r, rng, options, cells, k - 1)
            xi_k, scale_k = p.xi, p.scale
            warnings += [f"mode {k}: {w}" for w in p.warnings]
        except PosteriorSkippedError as exc:
            warnings.append(f"mode {k} (mass {m:.0%}) not sampled ({exc.message}): its Laplace approximation is "
                            "mixed in")
            xi_k = rng.multivariate_normal(np.zeros(6), r.covariance, len(main.xi))
            scale_k = np.ones(len(xi_k))
        # Each sample T_k Exp(xi) in the MAP's tangent.
        parts.append((retangent_batch(r.T_camera_lidar, xi_k, ref.T_camera_lidar), scale_k, m))
        centers.append(T_log(np.linalg.inv(ref.T_camera_lidar) @ r.T_camera_lidar))
    w = np.array([m for _, _, m in parts], dtype=float)
    w = w / w.sum()
    xi, scale, index = [], [], []
    for m, ((x, sc, _), pick) in enumerate(zip(parts, mixture_picks([len(x) for x, _, _ in parts], w,
                                                                     len(main.xi), rng))):
        xi.append(x[pick])
        scale.append(sc[pick])
        index.append(np.full(len(pick), m))
    return Posterior(ref.T_camera_lidar, np.concatenate(xi), np.concatenate(scale), main.run, options.likelihood,
                     tuple(warnings), tuple(float(v) for v in w), np.concatenate(index), np.array(centers))


def _sample_mode(frames: list[FrameMeasurement], board: BoardModel, camera: CameraModel, ref: Refinement,
                 rng: np.random.Generator, options: PosteriorOptions, cells: "ModeCells | None" = None,
                 index: int = 0) -> Posterior:
    """The posterior about one refined minimum (:func:`sample_posterior`), within its cell of ``cells`` (mode
    ``index``) when given."""
    reason = unsampled_reason(ref.covariance)
    if reason is not None:
        raise PosteriorSkippedError(reason, hint="the covariance is the Laplace one; add board poses that "
                                                 "constrain the weak direction")
    scan = any(f.lidar.is_scan_line for f in frames if f.usable)
    try:
        # The rig's likelihood over the pair's camera and LiDAR views (one likelihood for both). A 2D pair's
        # posterior is not near its Laplace approximation (a curved valley, its segment ends): its proposal is
        # tuned by a pilot run.
        like = rig_likelihood(ref, options.likelihood, options.nu, cells, index)
        keep, run = run_chain(like, ref.covariance, rng, options.min_ess, options.max_steps, options.walkers,
                              options.sampler != "proposal", options.chunk, options.progress,
                              pilot=scan or cells is not None)
        samples, scale = keep[:, :6], np.exp(keep[:, -1])
    except ValueError as exc:  # emcee refuses a degenerate ensemble or a NaN log-probability
        raise PosteriorSkippedError(f"the sampler refused the problem ({exc})",
                                    hint="the covariance is the Laplace one") from exc
    warnings = []
    if not run.converged:
        warnings.append(f"the posterior chain stopped at {run.chain.shape[0]} steps, before 50 autocorrelation times "
                        f"(tau {np.max(run.tau):.0f}) and {options.min_ess} effective samples ({run.ess:.0f}): "
                        "intervals are rough; raise the step limit")
    xi = samples
    if ref.intrinsics_covariance is not None:
        # Intrinsics calibrated from the same images: their (first-order, Gaussian) effect is convolved in.
        xi = xi + rng.multivariate_normal(np.zeros(6), ref.intrinsics_covariance, len(xi))
    if ref.conflict_covariance is not None:
        # The planes and the edges conflict: the samples hold both answers, as the covariance does.
        xi = xi + rng.multivariate_normal(np.zeros(6), ref.conflict_covariance, len(xi), method="eigh")
    if ref.range_model is not None and ref.range_model.terms is not None:
        # The range terms were held at the MAP: their uncertainty's share is convolved in (marginal intervals).
        xi = xi + rng.multivariate_normal(np.zeros(6), ref.range_model.extrinsic_share, len(xi))
    return Posterior(ref.T_camera_lidar, xi, scale, run, options.likelihood, tuple(warnings))
