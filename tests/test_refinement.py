"""Factor-graph refinement, its covariance, and the Cramer-Rao bound (measurement-level simulation).

Layouts are the default rig's (1024x768 camera, 1 m board, HDL-64E beams) with fixed seeds.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from estimators.errors import DegenerateLayoutError
from estimators.measurements import FrameMeasurement, observe_lidar_board
from estimators.simulation.simulator import default_camera, default_rig, sample_board_poses
from estimators.solvers.closed_form import solve_closed_form
from estimators.solvers.factors import corner_residuals, lidar_plane
from estimators.solvers.observation_model import (
    Layout,
    board_hits,
    corner_pixels,
    cramer_rao_bound,
    fisher_information,
    simulate_measurements,
)
from estimators.solvers.noise_levels import pooled_range_noise_m
from estimators.solvers.refinement import refine
from estimators.solvers.refinement_options import RefinementOptions
from geometry.camera import CameraModel
from geometry.planes import Plane, moment_matrix, sqrt_excess_moment
from geometry.rotations import R_from_rotvec, T_from_Rt, T_inverse, T_log, T_retract, random_rotation


def _layout(seed: int, n: int = 8, corner_noise_px: float = 0.15, range_noise_m: float = 0.02) -> Layout:
    rng = np.random.default_rng(seed)
    rig = default_rig(rng)
    poses = sample_board_poses(rig, n, rng)
    return Layout(rig.camera, rig.board, rig.beams, rig.T_camera_lidar, tuple(poses), corner_noise_px, range_noise_m)


def _xi(T_hat, T_true):
    return T_log(T_inverse(T_hat) @ T_true)


def _numeric_jacobian(f, T, eps=1e-6):
    return np.column_stack([(f(T_retract(T, e)) - f(T_retract(T, -e))) / (2 * eps) for e in np.eye(6) * eps])


@pytest.mark.parametrize("model", ["pinhole", "fisheye"])
def test_corner_factor_jacobian_matches_numeric(model):
    cam = default_camera()
    if model == "fisheye":
        cam = CameraModel(cam.K, np.array([0.05, -0.01, 0.002, -0.0005]), cam.width, cam.height, "fisheye")
    layout = _layout(1, n=1)
    T = layout.T_camera_board[0]
    X = layout.board.inner_corners()
    px = cam.project(X @ T[:3, :3].T + T[:3, 3]) + 0.2
    _, H = corner_residuals(T, X, px, cam)
    num = _numeric_jacobian(lambda Tb: corner_residuals(Tb, X, px, cam)[0], T)
    np.testing.assert_allclose(H, num, atol=1e-4 * np.abs(num).max())


def test_plane_factor_jacobians_match_numeric():
    rng = np.random.default_rng(2)
    Tx = T_from_Rt(random_rotation(rng), rng.normal(size=3))
    Tb = T_from_Rt(random_rotation(rng), rng.normal(size=3) + [0, 0, 3])
    _, H_x, H_b = lidar_plane(Tx, Tb)
    np.testing.assert_allclose(H_x, _numeric_jacobian(lambda T: lidar_plane(T, Tb)[0], Tx), atol=1e-8)
    np.testing.assert_allclose(H_b, _numeric_jacobian(lambda T: lidar_plane(Tx, T)[0], Tb), atol=1e-8)


def test_sqrt_excess_moment_reproduces_every_plane_cost():
    rng = np.random.default_rng(3)
    P = rng.uniform(-0.5, 0.5, (400, 3)) * [1, 1, 0] + [0.2, 0.1, 3.0] + rng.normal(0, 0.01, (400, 3))
    M = moment_matrix(P, rng.uniform(0.5, 2.0, 400))
    W, floor = sqrt_excess_moment(M)
    assert W.shape == (3, 4)
    for _ in range(20):
        plane = Plane(rng.normal(size=3), rng.normal())
        pi = plane.coefficients
        assert pi @ M @ pi == pytest.approx(float(np.sum((W @ pi) ** 2)) + floor, rel=1e-9)
    # Points on one line (a 2D scan without noise) leave a rank-2 factor.
    line = np.outer(np.linspace(-0.5, 0.5, 50), [1.0, 0.3, 0.0]) + [3.0, 0.0, 0.0]
    assert sqrt_excess_moment(moment_matrix(line))[0].shape[0] == 2


def test_fisher_information_matches_finite_differences_of_the_measurement_model():
    """The bound's information equals J^T J of the noise-free measurements (corner pixels / sigma_px and
    beam ranges / sigma_r) differentiated numerically in every parameter."""
    layout = _layout(4, n=3)
    hits = [board_hits(layout, i) for i in range(3)]

    def measurements(theta):
        T = T_retract(layout.T_camera_lidar, theta[:6])
        out = []
        for i in range(3):
            Tb = T_retract(layout.T_camera_board[i], theta[6 + 6 * i:12 + 6 * i])
            shifted = replace(layout, T_camera_board=layout.T_camera_board[:i] + (Tb,) + layout.T_camera_board[i + 1:])
            out.append(corner_pixels(shifted, i).ravel() / layout.corner_noise_px)
            n = Tb[:3, 2]
            d = n @ Tb[:3, 3]
            dirs = hits[i][0]
            out.append((d - n @ T[:3, 3]) / (dirs @ (T[:3, :3].T @ n)) / layout.range_noise_m)
        return np.concatenate(out)

    eps = 1e-6
    J = np.column_stack([(measurements(e) - measurements(-e)) / (2 * eps) for e in np.eye(24) * eps])
    F = fisher_information(layout)
    np.testing.assert_allclose(F, J.T @ J, rtol=1e-4, atol=1e-6 * np.abs(F).max())


def test_noise_free_refinement_converges_to_truth_from_a_perturbed_start():
    layout = _layout(5, n=6, corner_noise_px=0.0, range_noise_m=0.0)
    frames = simulate_measurements(layout, np.random.default_rng(0))
    start = T_retract(layout.T_camera_lidar, np.r_[np.deg2rad([3.0, -2.0, 2.5]), 0.10, -0.08, 0.05])
    ref = refine(frames, layout.board, layout.camera, start,
                 RefinementOptions(corner_noise_px=0.1, range_noise_m=0.01, edges=False))
    xi = _xi(ref.T_camera_lidar, layout.T_camera_lidar)
    assert np.abs(xi[:3]).max() < 1e-7 and np.abs(xi[3:]).max() < 1e-6, xi


def test_covariance_is_the_inverse_hessian_of_the_cost_and_matches_the_bound():
    """Marginals of the extrinsic equal the extrinsic block of the inverse numerical Hessian of the same
    cost (sum of squared whitened residuals, by finite differences in every variable), and the bound."""
    layout = _layout(6, n=4)
    frames = simulate_measurements(layout, np.random.default_rng(1))
    opts = RefinementOptions(corner_noise_px=layout.corner_noise_px, range_noise_m=layout.range_noise_m,
                             robust="none", corner_scale_sd=0.0, edges=False)
    T0 = solve_closed_form([f.camera.plane for f in frames], [f.lidar.plane for f in frames]).T_camera_lidar
    ref = refine(frames, layout.board, layout.camera, T0, opts)
    boards = [ref.T_camera_board[f.name] for f in frames]
    measured = pooled_range_noise_m([f.lidar for f in frames])
    whiteners = [sqrt_excess_moment(f.lidar.unbiased_range_moment(measured))[0] for f in frames]

    def cost(theta):
        T = T_retract(ref.T_camera_lidar, theta[:6])
        c = 0.0
        for i, f in enumerate(frames):
            Tb = T_retract(boards[i], theta[6 + 6 * i:12 + 6 * i])
            r, _ = corner_residuals(Tb, layout.board.inner_corners(), f.camera.corners_px, layout.camera)
            c += r @ r / layout.corner_noise_px**2
            e = whiteners[i] @ lidar_plane(T, Tb)[0]
            c += e @ e / layout.range_noise_m**2
        return 0.5 * c

    n = 6 + 6 * len(frames)
    h = np.r_[np.full(3, 2e-5), np.full(3, 2e-5), np.tile(np.r_[np.full(3, 2e-5), np.full(3, 2e-5)], len(frames))]
    H = np.empty((n, n))
    E = np.diag(h)
    for a in range(n):
        for b in range(a, n):
            H[a, b] = H[b, a] = (cost(E[a] + E[b]) - cost(E[a] - E[b]) - cost(-E[a] + E[b]) + cost(-E[a] - E[b])) / (
                4 * h[a] * h[b])
    cov_numeric = np.linalg.inv(H)[:6, :6]
    np.testing.assert_allclose(ref.covariance, cov_numeric, rtol=0.03, atol=0.03 * np.abs(np.diag(cov_numeric)).max())
    crb = cramer_rao_bound(layout)
    # At the same layout and noise the reported covariance is the bound (linearised at the estimate
    # instead of the truth, and with the fitted instead of the true plane weights): within 5% in std.
    np.testing.assert_allclose(np.sqrt(np.diag(ref.covariance)), np.sqrt(np.diag(crb)), rtol=0.05)


def test_robust_loss_survives_a_moved_board_where_least_squares_does_not():
    """One frame's LiDAR board is 15 cm off its camera plane (the board moved between image and scan)."""
    layout = _layout(7, n=8)
    frames = simulate_measurements(layout, np.random.default_rng(2))
    bad = frames[3]
    moved = bad.lidar.points + 0.15 * bad.lidar.plane.normal
    frames[3] = FrameMeasurement(bad.name, bad.camera, observe_lidar_board(moved))
    T0 = solve_closed_form([f.camera.plane for f in frames], [f.lidar.plane for f in frames]).T_camera_lidar
    std = np.sqrt(np.diag(cramer_rao_bound(layout)))

    noise = dict(corner_noise_px=layout.corner_noise_px, edges=False)  # the planes' robust loss alone
    plain = refine(frames, layout.board, layout.camera, T0,
                   RefinementOptions(robust="none", outliers="downweight", **noise))
    robust = refine(frames, layout.board, layout.camera, T0, RefinementOptions(robust="huber", **noise))
    err_plain = np.abs(_xi(plain.T_camera_lidar, layout.T_camera_lidar)) / std
    err_robust = np.abs(_xi(robust.T_camera_lidar, layout.T_camera_lidar)) / std
    assert err_plain.max() > 10, err_plain  # least squares is pulled far off by the one bad frame
    assert err_robust.max() < 4, err_robust  # the robust fit stays within its statistical error
    fit = {f.name: f for f in robust.frames}[bad.name]
    assert fit.dropped and "moved" in fit.outlier
    assert sum(f.dropped for f in robust.frames) == 1
    # Cauchy, kept and down-weighted rather than dropped.
    other = refine(frames, layout.board, layout.camera, T0,
                   RefinementOptions(robust="cauchy", outliers="downweight", **noise))
    assert (np.abs(_xi(other.T_camera_lidar, layout.T_camera_lidar)) / std).max() < 4
    fit = {f.name: f for f in other.frames}[bad.name]
    assert fit.weight < 0.01 and not fit.dropped and fit.outlier
    # With the default (image-calibrated, weaker) corner noise the board can follow the bad plane; the
    # frame's consistency statistic still catches it and the frame is dropped.
    default = refine(frames, layout.board, layout.camera, T0)
    assert [f.name for f in default.frames if f.dropped] == [bad.name]
    assert (np.abs(_xi(default.T_camera_lidar, layout.T_camera_lidar)) / std).max() < 8


def test_degenerate_layout_is_an_error_naming_the_unobservable_direction():
    """Boards turned only about the camera's vertical axis: normals in the x-z plane, so translation
    along camera y (LiDAR z) is unobservable."""
    layout = _layout(8, n=1)
    poses = []
    for k, yaw in enumerate(np.deg2rad([-35.0, -12.0, 12.0, 35.0])):
        R = R_from_rotvec([0.0, yaw, 0.0])
        poses.append(T_from_Rt(R, np.array([0.0, 0.0, 3.0 + 0.2 * k]) - R @ layout.board.centre))
    layout = replace(layout, T_camera_board=tuple(poses))
    frames = simulate_measurements(layout, np.random.default_rng(3))
    assert all(f.lidar.n_points > 100 for f in frames)
    with pytest.raises(DegenerateLayoutError) as exc:
        refine(frames, layout.board, layout.camera, layout.T_camera_lidar, RefinementOptions())
    assert "translation" in exc.value.problem


def test_options_are_validated():
    with pytest.raises(ValueError, match="robust"):
        RefinementOptions(robust="l1")
    with pytest.raises(ValueError, match="corner_noise_px"):
        RefinementOptions(corner_noise_px=-1.0)
