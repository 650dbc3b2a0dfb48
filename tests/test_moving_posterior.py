"""The posterior of a moving board's extrinsic and clock offset (``estimators.solvers.moving_posterior``) against
the joint solve it samples about, on the solver-level simulation of a waved board
(``estimators.simulation.waved_board``)."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from estimators.simulation.simulator import default_rig
from estimators.simulation.waved_board import simulate_waving
from estimators.solvers.clock_offset import solve_clock_offset
from estimators.solvers.moving_board_graph import Knots, along_beam_residuals
from estimators.solvers.moving_posterior import MovingLikelihood, sample_moving_posterior


@pytest.fixture(scope="module")
def fit():
    """10 s of a board waved before a VLP-16 and a 20 Hz camera whose clock reads 45 ms ahead (seed 1), solved
    with the board's extent and the camera's pointing: the joint solve's problem at its estimate."""
    rng = np.random.default_rng(1)
    rig = default_rig(rng, "vlp16")
    rec = simulate_waving(rig, 10.0, rng, time_offset_s=0.045)
    sol = solve_clock_offset(list(rec.views), list(rec.sweeps), returns_per_sweep=100, extent=rig.board.extent,
                             pointing_sd_rad=(1e-4, 1e-4))
    return sol.fit


def test_the_likelihood_is_the_solves_residuals_with_the_board_moved_to_second_order_in_the_offset(fit):
    """At the estimate the residuals are the joint solve's exactly (1e-12 m); with the offset moved by 2 and 4 ms
    (3 and 5 of its standard deviations) they stay within 2 um and 20 um of the exact ones (the range noise is
    20 mm); an extrinsic turned by 0.1 deg is taken exactly (no expansion in it)."""
    like = MovingLikelihood(fit)
    knots = Knots(fit.tau, fit.K)
    ranges = np.linalg.norm(fit.points, axis=1)

    def exact(T, d):
        t = fit.times_s + fit.time_offset_s + d
        return along_beam_residuals(T, *knots.poses(t, knots.interval(t)), ranges, fit.points / ranges[:, None])

    for d, tol in ((0.0, 1e-12), (0.002, 2e-6), (-0.004, 2e-5)):
        x = np.zeros((1, 7))
        x[0, 6] = d
        assert np.abs(like.residuals(x)[0] - exact(fit.T_camera_lidar, d)).max() < tol
    x = np.zeros((1, 7))
    x[0, 2] = np.radians(0.1)
    from geometry.rotations import T_retract

    turned = T_retract(fit.T_camera_lidar, x[0, :6])
    assert np.abs(like.residuals(x)[0] - exact(turned, 0.0)).max() < 1e-12


def test_the_samples_have_the_joint_solves_covariance_where_the_posterior_is_gaussian(fit):
    """Far from the offset's prior edges the likelihood is near Gaussian: the samples (the chain's, with the
    camera's share added) have the joint solve's standard deviations within 6% each and their mean within 0.1 of
    them of the estimate; the conditional covariance the proposal used is inside the joint one."""
    post = sample_moving_posterior(fit, np.random.default_rng(0), min_ess=2000)
    assert post.run.converged and post.run.ess >= 2000
    joint = fit.covariance.copy()
    joint[:6, :6] += fit.pointing
    sd = np.sqrt(np.diag(joint))
    np.testing.assert_allclose(np.std(post.xi, axis=0, ddof=1), sd, rtol=0.06)
    assert np.all(np.abs(post.xi.mean(axis=0)) < 0.1 * sd)
    assert np.all(np.linalg.eigvalsh(fit.covariance - post.conditional) > -1e-12)


def test_an_offset_at_its_priors_edge_is_held_inside_it_by_the_samples(fit):
    """The same recording with the offset's prior narrowed to end one standard deviation above the estimate:
    every sample's offset lies within the prior, and the upper 97.5% point is the edge's, not the Laplace one's
    (two standard deviations above)."""
    sd = float(np.sqrt(fit.covariance[6, 6]))
    edge = dataclasses.replace(fit, offset_prior_s=fit.time_offset_s + sd)
    post = sample_moving_posterior(edge, np.random.default_rng(0), min_ess=1000)
    offsets = fit.time_offset_s + post.xi[:, 6]
    assert offsets.max() <= edge.offset_prior_s + 1e-12
    assert np.quantile(offsets, 0.975) < fit.time_offset_s + 1.5 * sd


def test_an_offset_beyond_its_priors_edge_leaves_the_posterior_unsampled_with_the_reason(fit):
    """The prior narrowed to end three standard deviations below the estimate: no sample can stand there, and
    the sampler says so (a ``PosteriorSkippedError``: the caller keeps the Laplace covariance), nothing else."""
    from estimators.errors import PosteriorSkippedError

    sd = float(np.sqrt(fit.covariance[6, 6]))
    beyond = dataclasses.replace(fit, offset_prior_s=fit.time_offset_s - 3 * sd)
    with pytest.raises(PosteriorSkippedError):
        sample_moving_posterior(beyond, np.random.default_rng(0), min_ess=500)
