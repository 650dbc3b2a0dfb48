"""The emcee posterior: the sampler on a known Gaussian, the engine's posterior against the Laplace approximation on
a linear-Gaussian-like layout (measurement level, fixed seeds), and the credible regions read from samples."""
from __future__ import annotations

import numpy as np
import pytest

from estimators.simulation.simulator import default_rig, sample_board_poses
from geometry.rotations import T_exp, T_log
from estimators.solvers.closed_form import solve_closed_form
from estimators.solvers.observation_model import Layout, simulate_measurements
from estimators.io.measurement_store import Measurements
from estimators.pipeline.pair_estimate import PairEstimate
from estimators.rig_calibration import calibrate
from estimators.solvers.posterior import PosteriorOptions, heavy_tails
from estimators.solvers.sampler import run_ensemble
from estimators.solvers.refinement import refine
from estimators.solvers.refinement_options import measurement_model_options

from .numeric import likelihood_gradient, likelihood_hessian, rig_likelihood


def _known_gaussian(seed=0, dim=7):
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(dim, dim))
    cov = A @ A.T + 0.5 * np.eye(dim)
    mean = rng.normal(size=dim)
    P = np.linalg.inv(cov)

    def log_prob(x):
        d = np.atleast_2d(x) - mean
        return -0.5 * np.einsum("ni,ij,nj->n", d, P, d)

    return mean, cov, log_prob


def test_sampler_recovers_a_known_gaussian_and_repeats_with_its_seed():
    mean, cov, log_prob = _known_gaussian()
    rng = np.random.default_rng(1)
    start = rng.multivariate_normal(mean, cov, 48)
    run = run_ensemble(log_prob, start, np.random.default_rng(2), min_ess=4000)
    assert run.converged and run.chain.shape[0] > 50 * np.max(run.tau) and run.ess >= 4000
    sd = np.sqrt(np.diag(cov))
    # ESS >= 4000: the mean's standard error is under 0.02 sd, the sd's under 2%.
    np.testing.assert_allclose(run.samples.mean(0), mean, atol=0.1 * sd.max())
    np.testing.assert_allclose(np.sqrt(np.diag(np.cov(run.samples, rowvar=False))), sd, rtol=0.08)
    again = run_ensemble(log_prob, start, np.random.default_rng(2), min_ess=4000)
    np.testing.assert_array_equal(again.samples, run.samples)


def test_sampler_stops_with_a_warning_state_when_the_step_limit_is_reached():
    mean, cov, log_prob = _known_gaussian(3)
    start = np.random.default_rng(0).multivariate_normal(mean, cov, 32)
    run = run_ensemble(log_prob, start, np.random.default_rng(0), min_ess=10**6, max_steps=600, chunk=300)
    assert not run.converged and run.chain.shape[0] == 600


def test_the_sampler_leaves_scipy_stats_unloaded_and_loadable():
    # emcee's import would load scipy.stats for a move no posterior uses (0.45 s of every sampled calibration);
    # in a fresh interpreter the sampler runs without it, and scipy.stats still imports afterwards.
    import subprocess
    import sys

    code = ("import sys, numpy as np\n"
            "from estimators.solvers.sampler import run_ensemble\n"
            "r = run_ensemble(lambda x: -0.5 * np.sum(x * x, axis=1), np.random.default_rng(0).normal(size=(16, 2)),"
            " np.random.default_rng(1), min_ess=50, max_steps=200, chunk=100)\n"
            "print(len(r.samples) > 0, 'scipy.stats' in sys.modules)\n"
            "import scipy.stats\n"
            "print(scipy.stats.chi2.sf(2.0, 2) > 0)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert out == ["True", "False", "True"]


def test_walkers_that_start_where_the_target_is_zero_are_moved_inside():
    # A half-Gaussian (x >= 0), half of the walkers drawn outside it: emcee never moves a walker from -inf (its
    # acceptance is nan), which stayed in the samples at x < 0 and warned of invalid values. Moved inside, every
    # sample has x >= 0, their mean is the half-Gaussian's sqrt(2/pi) within 0.05, and no warning is raised.
    import warnings

    def log_prob(x):
        out = -0.5 * np.sum(x**2, axis=1)
        out[x[:, 0] < 0] = -np.inf
        return out

    rng = np.random.default_rng(3)
    initial = rng.standard_normal((32, 2))
    assert (initial[:, 0] < 0).sum() > 8
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        run = run_ensemble(log_prob, initial, rng, min_ess=500, max_steps=4000)
    assert run.samples[:, 0].min() >= 0 and abs(run.samples[:, 0].mean() - np.sqrt(2 / np.pi)) < 0.05
    from estimators.errors import PosteriorSkippedError

    with pytest.raises(PosteriorSkippedError, match="every walker"):
        run_ensemble(log_prob, -np.abs(initial), rng, min_ess=10, max_steps=100)


def test_the_laplace_independence_proposal_samples_a_target_it_does_not_match():
    # The proposal's covariance half the target's along one axis and twice along another: with its Metropolis-
    # Hastings correction the chain still has the target's covariance (within 10%, 3 parameters, 40000 draws).
    import emcee

    from estimators.solvers.sampler import LaplaceProposal

    target = np.diag([1.0, 4.0, 0.25])
    P = np.linalg.inv(target)

    def log_prob(x):
        return -0.5 * np.einsum("wi,ij,wj->w", x, P, x)

    moves = [(emcee.moves.MHMove(LaplaceProposal(np.diag([1.0, 2.0, 0.5]))), 0.7), (emcee.moves.DEMove(), 0.3)]
    rng = np.random.default_rng(5)
    run = run_ensemble(log_prob, rng.normal(0, 0.3, (32, 3)), rng, min_ess=4000, moves=moves)
    assert run.converged
    np.testing.assert_allclose(np.cov(run.samples, rowvar=False), target, atol=0.1 * np.sqrt(np.outer(
        np.diag(target), np.diag(target))).max(), rtol=0.1)


def test_the_pilot_tuned_proposal_samples_a_known_gaussian_away_from_the_origin_in_fewer_steps():
    # Without a covariance, a 300-step ensemble pilot gives the proposal its centre and covariance: the chain
    # still has the target's mean and covariance (a 7-dimensional Gaussian whose mean is off the origin, as a
    # board outline's is), and mixes faster than the ensemble moves alone (a shorter autocorrelation time).
    from estimators.solvers.sampler import run_with_proposal

    mean, cov, log_prob = _known_gaussian(4)
    start = np.random.default_rng(1).multivariate_normal(mean, cov, 48)
    run = run_with_proposal(log_prob, start, np.random.default_rng(2), min_ess=4000)
    plain = run_ensemble(log_prob, start, np.random.default_rng(2), min_ess=4000)
    assert run.converged and run.ess >= 4000 and np.max(run.tau) < 0.5 * np.max(plain.tau)
    sd = np.sqrt(np.diag(cov))
    np.testing.assert_allclose(run.samples.mean(0), mean, atol=0.1 * sd.max())
    np.testing.assert_allclose(np.sqrt(np.diag(np.cov(run.samples, rowvar=False))), sd, rtol=0.08)


@pytest.fixture(scope="module")
def measured():
    rng = np.random.default_rng(21)
    rig = default_rig(rng)
    layout = Layout(rig.camera, rig.board, rig.beams, rig.T_camera_lidar, tuple(sample_board_poses(rig, 8, rng)),
                    0.2, 0.02)
    frames = simulate_measurements(layout, np.random.default_rng(22))
    T0 = solve_closed_form([f.camera.plane for f in frames], [f.lidar.plane for f in frames]).T_camera_lidar
    # Corners drawn independently: no correlation factor, so the Laplace covariance is the right one.
    ref = refine(frames, layout.board, layout.camera, T0, measurement_model_options())
    return layout, frames, ref


def test_posterior_log_density_peaks_at_the_map_with_the_laplace_curvature(measured):
    # The likelihood a pair samples (the rig's over its views).
    layout, frames, ref = measured
    model = rig_likelihood(ref)
    H = likelihood_hessian(model)
    np.testing.assert_allclose(np.linalg.inv(H), ref.covariance, rtol=0.02, atol=0.02 * np.abs(ref.covariance).max())
    grad = likelihood_gradient(model)
    # The mode is the MAP to within a few hundredths of a standard deviation on every axis.
    assert np.abs(np.linalg.solve(H, grad) / np.sqrt(np.diag(ref.covariance))).max() < 0.05


@pytest.mark.parametrize("likelihood", ["gaussian", "student-t"])
def test_calibration_posterior_matches_the_laplace_approximation(measured, likelihood):
    """The engine's posterior (``calibrate`` on the frames as measured), near-linear and Gaussian: centred on the
    MAP, with the joint graph's Laplace covariance up to the sampled camera-noise scale s (which scales part of each
    frame's noise, so the standard deviations lie between the Laplace ones and s times them), within the sampling
    error."""
    layout, frames, _ = measured
    res = calibrate(Measurements(layout.camera, layout.board, "3d", tuple(frames)), rng=np.random.default_rng(3),
                    options=measurement_model_options(), posterior=PosteriorOptions(likelihood=likelihood))
    pair = res.only_pair()
    assert pair.samples.shape[1] == 6 and res.posterior.run.converged
    sd = np.sqrt(np.diag(res.solution.transform("cam0", "lidar0")[1]))
    ratio = np.sqrt(np.diag(pair.covariance)) / sd
    s = float(np.median(res.posterior.camera_scale))
    assert 0.6 < s < 1.6, s  # the independent-corner model is the true one here
    # Student-t (nu = 4) frames have variance nu / (nu - 2) times their scale: wider by up to sqrt(2).
    widen = 1.0 if likelihood == "gaussian" else np.sqrt(4.0 / 2.0)
    assert np.all((ratio > min(1.0, s) - 0.12) & (ratio < widen * max(1.0, s) + 0.12)), (ratio, s)
    # The Gaussian posterior is centred on the (Gaussian) MAP; the Student-t one weighs frames differently,
    # so its centre may move by a fraction of a standard deviation.
    assert np.abs(pair.samples.mean(0) / sd).max() < (0.2 if likelihood == "gaussian" else 0.6)
    iv = pair.intervals(0.95)
    assert np.all(iv[:, 0] < 0) and np.all(iv[:, 1] > 0)
    assert {"68%", "95%", "credible_regions"} <= set(pair.summary())


def _posterior_of(xi: np.ndarray, **modes) -> PairEstimate:
    return PairEstimate("cam0", "lidar0", np.eye(4), np.cov(xi, rowvar=False), xi, 8, **modes)


def test_credible_region_is_the_gaussian_one_for_gaussian_samples_and_holds_heavy_tails():
    rng = np.random.default_rng(5)
    n = 400_000
    A = rng.normal(size=(6, 6)) * 0.01
    z = rng.normal(size=(n, 6))
    gauss = _posterior_of(z @ A.T)
    # 400k independent draws: the 99.9% quantile of chi-square(6) (22.46) within 3%; never below it.
    assert 22.458 <= gauss.region_d2(0.999) < 1.03 * 22.458
    assert abs(gauss.region_d2(0.99) - 16.81) < 0.03 * 16.81 + 1e-9 and heavy_tails(gauss.samples) is None
    # Multivariate Student-t, 4 dof: xi = z / sqrt(w / 4), w ~ chi-square(4), covariance 2 A A^T. Under the
    # covariance, d2 = (6 / 2) F(6, 4): its 99.9% point is 3 x 53.44 = 160.3 (F table), far beyond 22.46.
    w = rng.chisquare(4, n)
    heavy = _posterior_of((z / np.sqrt(w / 4)[:, None]) @ A.T)
    assert 0.85 * 160.3 < heavy.region_d2(0.999) < 1.15 * 160.3
    assert "heavier than a Gaussian" in heavy_tails(heavy.samples)
    # The region holds its share of fresh draws from the same distribution (coverage, 0.1% +- 0.03%).
    w2 = rng.chisquare(4, n)
    fresh = (rng.normal(size=(n, 6)) / np.sqrt(w2 / 4)[:, None]) @ A.T
    outside = np.mean(heavy.region_distance(fresh) > heavy.region_d2(0.999))
    assert 0.0005 < outside < 0.0016
    # contains() on a pose: the MAP itself is in, a pose far along the tail is not.
    assert heavy.contains(np.eye(4), 0.999)
    far = np.eye(4)
    far[:3, 3] = 30 * np.sqrt(2) * A[3:, :] @ np.ones(6)
    assert not heavy.contains(far, 0.999)


def test_credible_region_of_a_two_mode_mixture_holds_the_minor_mode():
    """A minor mode with 3% of the mass, far from the main one: the covariance's chi-square ellipsoid leaves it
    out, the region (99.9% of the samples) holds it; with 0.05% of the mass it is left out."""
    rng = np.random.default_rng(8)
    n = 200_000
    for share, inside in ((0.03, True), (0.0005, False)):
        xi = rng.normal(size=(n, 6)) * 0.01
        m = int(share * n)
        xi[:m] += np.array([0.0, 0.0, 0.0, 0.25, 0.0, 0.0])
        post = _posterior_of(xi)
        minor = np.array([0.0, 0.0, 0.0, 0.25, 0.0, 0.0])
        assert post.region_distance(minor)[0] > 22.458
        assert bool(post.region_distance(minor)[0] <= post.region_d2(0.999)) is inside


def test_credible_region_of_modes_is_each_modes_own_ellipsoid():
    """The 2D ChArUco trial that was confidently wrong (bench_2d_honesty varied --pattern charuco, seed
    4138047809): a minor mode with 3% of the mass 0.3 m away, the truth in it (d2 4.8 under its own covariance)
    but beyond the mixture's ellipsoid that holds 99.9% of the samples (d2 90 against 76). Drawn here as two
    Gaussians, the minor one wide about one axis and the truth 3 of its sd out along it: the mixture's ellipsoid
    leaves the truth out, the union of each mode's own ellipsoid (nearer a highest-density region) holds it at
    d2 9. Both hold 99.9% of fresh draws (+- 0.04%, 200k draws): the union gives up the empty space between the
    modes instead of the minor mode's lobes."""
    rng = np.random.default_rng(11)
    sd_main = np.full(6, 0.01)
    sd_minor = np.array([0.05, 0.01, 0.01, 0.01, 0.01, 0.02])
    centre = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.30])

    def draw(n):
        index = (rng.random(n) < 0.03).astype(int)
        xi = rng.normal(size=(n, 6)) * np.where(index[:, None] == 1, sd_minor, sd_main)
        return xi + np.where(index[:, None] == 1, centre, 0.0), index

    xi, index = draw(200_000)
    post = _posterior_of(xi, mode_index=index, mode_centers=np.array([np.zeros(6), centre]),
                         mode_weights=(0.97, 0.03))
    truth = centre + np.array([3 * sd_minor[0], 0.0, 0.0, 0.0, 0.0, 0.0])
    mixture = _posterior_of(xi)
    assert mixture.region_distance(truth)[0] > mixture.region_d2(0.999)  # the mixture's ellipsoid: outside
    assert abs(post.region_distance(truth)[0] - 9.0) < 0.5 and post.region_d2(0.999) < 25.0
    assert post.contains(T_exp(truth), 0.999)
    fresh, _ = draw(200_000)
    outside = np.mean(post.region_distance(fresh) > post.region_d2(0.999))
    assert 0.0006 < outside < 0.0014
    region = post.summary()["credible_regions"]
    assert len(region["modes"]) == 2 and region["99.9%"]["d2"] >= 22.458
    np.testing.assert_allclose(T_log(np.array(region["modes"][1]["T"])), centre, atol=1e-12)
