"""The sampler every posterior runs (a pair's and a rig's): emcee's ensemble, with most moves independent draws from
a Laplace approximation (Metropolis-Hastings corrected), run until the chain is long against its autocorrelation
and holds the effective samples asked for.
"""
from __future__ import annotations

import sys
import threading
import time
from dataclasses import dataclass, replace

import numpy as np

_EMCEE_IMPORT = threading.Lock()


def _emcee():
    """emcee, imported without scipy.stats where nothing has loaded it yet. emcee's KDE move, which no posterior
    here uses, imports scipy.stats when emcee is imported (about 0.45 s of scipy's start-up on this project's
    machine, a tenth of the demo); emcee leaves that move without it when scipy.stats cannot be imported, which a
    ``None`` in ``sys.modules`` makes so for the length of emcee's own import."""
    with _EMCEE_IMPORT:
        if "emcee" in sys.modules or "scipy.stats" in sys.modules:
            import emcee

            return emcee
        sys.modules["scipy.stats"] = None  # type: ignore[assignment]
        try:
            import emcee
        finally:
            if sys.modules.get("scipy.stats", False) is None:
                del sys.modules["scipy.stats"]
        return emcee


@dataclass(frozen=True, eq=False)
class ChainResult:
    """An ensemble run: samples after burn-in (flattened), the full chain for traces, and diagnostics."""

    samples: np.ndarray  # (M, ndim)
    chain: np.ndarray  # (steps, walkers, ndim)
    tau: np.ndarray  # integrated autocorrelation time per parameter (steps)
    acceptance: float
    ess: float
    burn: int
    converged: bool
    seconds: float

    def diagnostics(self) -> dict:
        """The run's diagnostics as every posterior's record gives them (calibration.json's ``posterior``, a single
        pair's and a rig's alike)."""
        return {"walkers": int(self.chain.shape[1]), "steps": int(self.chain.shape[0]),
                "parameters": int(self.chain.shape[2]), "burn_in": self.burn, "tau_steps": self.tau.tolist(),
                "tau_steps_max": float(np.max(self.tau)), "acceptance_fraction": self.acceptance,
                "effective_samples": self.ess, "converged": self.converged, "seconds": self.seconds}

    def words(self, likelihood: str) -> str:
        """The run in a line, as the printout and the reports say it."""
        return (f"emcee, {self.chain.shape[2]} parameters, {likelihood} likelihood: {self.ess:.0f} effective samples, "
                f"tau {float(np.max(self.tau)):.1f} steps, acceptance {self.acceptance:.2f}, {self.seconds:.1f} s"
                + ("" if self.converged else ", NOT converged"))


class _NoBar:
    """What :func:`run_ensemble` asks of a progress bar, doing nothing."""

    def __enter__(self) -> "_NoBar":
        return self

    def __exit__(self, *exc) -> None:
        return None

    def update(self, n: int) -> None:
        pass

    def set_postfix(self, **values) -> None:
        pass


def _progress_bar(progress: bool, total: int, label: str):
    """A tqdm bar when ``progress``; else nothing (tqdm.auto loads asyncio: 25 ms of every run's start)."""
    if not progress:
        return _NoBar()
    from tqdm.auto import tqdm

    return tqdm(total=total, desc=label, unit="step", leave=False)


def walkers_inside(log_prob, initial: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """``initial`` with every walker that starts where the target is zero (its log-probability not finite) moved to
    one that starts inside, plus a thousandth of the walkers' spread. Left there, such a walker never moves (emcee
    compares a move's log-probability with its own, -inf: nan, never accepted) and stays in the samples at a point
    the posterior excludes. :class:`~estimators.errors.PosteriorSkippedError` when no walker starts inside."""
    lp = np.asarray(log_prob(initial), dtype=float)
    out = ~np.isfinite(lp)
    if not out.any():
        return initial
    inside = np.flatnonzero(~out)
    if inside.size == 0:
        from ..errors import PosteriorSkippedError

        raise PosteriorSkippedError("every walker of the sampler starts where the posterior is zero",
                                    hint="the covariance is the Laplace one")
    moved = initial.copy()
    spread = 1e-3 * initial[inside].std(axis=0)
    moved[out] = initial[rng.choice(inside, out.sum())] + spread * rng.standard_normal((out.sum(), initial.shape[1]))
    still = ~np.isfinite(np.asarray(log_prob(moved[out]), dtype=float))  # beside a wall: the walker itself
    moved[np.flatnonzero(out)[still]] = initial[rng.choice(inside, still.sum())]
    return moved


def run_ensemble(log_prob, initial: np.ndarray, rng: np.random.Generator, min_ess: int = 2000,
                 max_steps: int = 40000, chunk: int = 500, progress: bool = False, label: str = "posterior",
                 moves=None) -> ChainResult:
    """Run emcee (vectorised log-probability over walkers) until the chain is longer than 50
    integrated autocorrelation times and holds ``min_ess`` effective samples, or ``max_steps``.

    The sampler's random state is seeded from ``rng``; results repeat for the same generator state. ``moves``:
    emcee's ``(move, weight)`` list (default: differential evolution and the stretch move, below).
    """
    t0 = time.perf_counter()
    nwalkers, ndim = initial.shape
    # Differential-evolution moves mix about three times faster than the stretch move alone on these
    # near-Gaussian targets. (emcee's DE snooker move is left out: with it, the samples of the calibration
    # posterior came out 10% too narrow against the analytic Gaussian.)
    emcee = _emcee()

    moves = moves if moves is not None else [(emcee.moves.DEMove(), 0.8), (emcee.moves.StretchMove(), 0.2)]
    sampler = emcee.EnsembleSampler(nwalkers, ndim, log_prob, vectorize=True, moves=moves)
    initial = walkers_inside(log_prob, initial, rng)
    state = emcee.State(initial, random_state=np.random.RandomState(int(rng.integers(2**32))).get_state())
    steps, converged, n = 0, False, chunk
    with _progress_bar(progress, max_steps, label) as bar:
        while steps < max_steps:
            n = min(n, max_steps - steps)
            state = sampler.run_mcmc(state, n, progress=False)
            steps += n
            bar.update(n)
            tau = sampler.get_autocorr_time(tol=0)
            t_max = float(np.max(tau))
            burn = int(np.ceil(2 * t_max))
            ess = nwalkers * (steps - burn) / t_max
            bar.set_postfix(tau=f"{t_max:.0f}", ess=f"{ess:.0f}")
            if steps > 50 * t_max and ess >= min_ess:
                converged = True
                break
            # The next check where the current autocorrelation time says both could hold (10% more, at
            # least 50 steps, at most ``chunk``): the same rule, checked without overshooting by a chunk.
            short = max(50 * t_max - steps, min_ess * t_max / nwalkers + 2 * t_max - steps)
            n = int(np.clip(np.ceil(1.1 * short), 50, chunk))
    chain = sampler.get_chain()
    return ChainResult(samples=chain[burn:].reshape(-1, ndim), chain=chain, tau=np.asarray(tau, dtype=float),
                       acceptance=float(np.mean(sampler.acceptance_fraction)), ess=float(ess), burn=burn,
                       converged=converged, seconds=time.perf_counter() - t0)


class LaplaceProposal:
    """An independence proposal for emcee's ``MHMove``: a multivariate Student-t about ``centre`` (default the
    origin: the MAP in tangent parameters) with a covariance near the posterior's (scaled by ``scale``), whatever
    the walker's position. Where the posterior is near Gaussian, nearly every proposal is an independent draw
    accepted with high probability, so the chain's autocorrelation stays a few steps in any dimension (an
    ensemble move's grows with it); the t's tails keep the sampler exact where the posterior's are heavier."""

    def __init__(self, covariance: np.ndarray, nu: float = 30.0, scale: float = 1.05,
                 centre: np.ndarray | None = None):
        self.L = np.linalg.cholesky(covariance) * scale
        self.nu = nu
        self.centre = np.zeros(len(covariance)) if centre is None else np.asarray(centre, dtype=float)

    def log_density(self, x: np.ndarray) -> np.ndarray:
        u = np.linalg.solve(self.L, (x - self.centre).T)
        return -0.5 * (self.nu + x.shape[1]) * np.log1p(np.sum(u * u, axis=0) / self.nu)

    def __call__(self, coords: np.ndarray, random) -> tuple[np.ndarray, np.ndarray]:
        n, d = coords.shape
        w = random.chisquare(self.nu, n) / self.nu
        new = self.centre + (random.randn(n, d) / np.sqrt(w)[:, None]) @ self.L.T
        return new, self.log_density(coords) - self.log_density(new)


# Steps of the pilot that tunes :func:`run_with_proposal`'s proposal when no covariance is given, and the tails and
# scale of a proposal whose target has a sampled noise scale (every pair's and rig's: a scale mixture, and a 2D
# layout's has a curved valley; an independence proposal lighter-tailed than its target visits the tails too
# rarely). On six simulated 8-board mounted 2D sets: autocorrelation 6-8 steps (4-5 with a t(30) x 1.05), the
# samples' standard deviations and 99.9% regions as the ensemble moves alone give them, within their noise.
PILOT_STEPS = 300
SCALED_TAILS = {"nu": 5.0, "scale": 1.2}


def run_with_proposal(log_prob, initial: np.ndarray, rng: np.random.Generator, covariance: np.ndarray | None = None,
                      min_ess: int = 2000, max_steps: int = 40000, chunk: int = 500, progress: bool = False,
                      label: str = "posterior", centre: np.ndarray | None = None,
                      tails: dict | None = None) -> ChainResult:
    """:func:`run_ensemble` with most moves drawn from a :class:`LaplaceProposal` of ``covariance`` (about the
    origin) and the rest by differential evolution (for what the proposal misses). Without ``covariance``
    (parameters beyond the Laplace approximation's: a noise scale, a board outline), a pilot of ``PILOT_STEPS``
    ensemble steps gives the proposal its centre and covariance (the second half of its samples' mean and
    covariance) and the chain starts where the pilot ends; its time is counted in ``seconds``. The target is the
    same: only how fast the chain mixes changes (autocorrelation 25 -> 6 steps on the simulated default pair,
    40 -> 10-40 on 2D layouts). ``centre`` and ``tails`` (a :class:`LaplaceProposal`'s ``nu`` and ``scale``) set the
    proposal's centre and tails with a given ``covariance``."""
    emcee = _emcee()

    pilot = None
    if covariance is None:
        pilot = run_ensemble(log_prob, initial, rng, min_ess=1, max_steps=PILOT_STEPS, chunk=PILOT_STEPS)
        tail = pilot.chain[len(pilot.chain) // 2:].reshape(-1, initial.shape[1])
        covariance, centre = np.cov(tail, rowvar=False), tail.mean(axis=0)
        initial = pilot.chain[-1]
    try:
        proposal = LaplaceProposal(0.5 * (covariance + covariance.T), centre=centre,
                                   **(tails or ({} if pilot is None else SCALED_TAILS)))
    except np.linalg.LinAlgError:  # a direction the pilot did not move in: the ensemble moves alone
        return run_ensemble(log_prob, initial, rng, min_ess, max_steps, chunk, progress, label)
    moves = [(emcee.moves.MHMove(proposal), 0.7), (emcee.moves.DEMove(), 0.3)]
    run = run_ensemble(log_prob, initial, rng, min_ess, max_steps, chunk, progress, label, moves=moves)
    return run if pilot is None else replace(run, seconds=run.seconds + pilot.seconds)


def mixture_picks(sizes: list[int], weights, n: int, rng: np.random.Generator) -> list[np.ndarray]:
    """Which samples of each of several modes' runs (``sizes`` samples each) make ``n`` samples of their mixture by
    ``weights`` (normalised here): each mode's count drawn from the multinomial, its samples drawn from its run
    (with replacement only when it has fewer than its count). Every multimodal posterior mixes its modes so."""
    w = np.asarray(weights, dtype=float)
    counts = rng.multinomial(n, w / w.sum())
    return [rng.choice(size, size=c, replace=c > size) for size, c in zip(sizes, counts)]
