"""Geometry: rotations, planes, the closed form on exact data, camera models, board model."""
from __future__ import annotations

import gtsam
import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from estimators.errors import DegenerateLayoutError
from estimators.solvers.closed_form import normal_spread, solve_closed_form
from geometry.board import BoardModel
from geometry.camera import CameraModel
from geometry.planes import Plane, fit_plane_pca, moment_matrix, sum_squared_distances
from geometry.differences import central_hessian
from geometry.rotations import (
    R_from_quat_xyzw,
    R_from_rotvec,
    T_exp,
    T_from_Rt,
    T_inverse,
    T_local,
    T_log,
    T_retract,
    exp_batch,
    local_batch,
    log_batch,
    quat_xyzw_from_R,
    random_rotation,
    retangent_batch,
    retract_batch,
    rotation_error,
    transform_points,
)
from geometry.vectors import row_norms

seeds = st.integers(min_value=0, max_value=2**32 - 1)


@given(seeds)
def test_se3_exp_matches_gtsam_and_log_inverts(seed):
    rng = np.random.default_rng(seed)
    xi = rng.normal(0, 1.0, 6)
    xi[:3] *= rng.uniform(0.0, 3.0) / np.linalg.norm(xi[:3])  # stay inside the principal branch (< pi)
    T = T_exp(xi)
    np.testing.assert_allclose(T, gtsam.Pose3.Expmap(xi).matrix(), atol=1e-10)
    np.testing.assert_allclose(T_log(T), xi, atol=1e-8)
    T0 = T_from_Rt(random_rotation(rng), rng.normal(size=3))
    np.testing.assert_allclose(T_local(T0, T_retract(T0, xi)), xi, atol=1e-8)
    np.testing.assert_allclose(T_retract(T0, xi), gtsam.Pose3(T0).retract(xi).matrix(), atol=1e-9)


@given(seeds)
def test_the_batched_se3_log_matches_gtsam_and_inverts_the_batched_exp(seed):
    rng = np.random.default_rng(seed)
    xi = rng.normal(0, 1.0, (8, 6))
    xi[:, :3] *= rng.uniform(0.0, 3.0, (8, 1)) / np.linalg.norm(xi[:, :3], axis=1, keepdims=True)
    xi[0, :3] = rng.normal(0, 1e-6, 3)  # the small-angle series
    R, t = exp_batch(xi)
    np.testing.assert_allclose(log_batch(R, t), xi, atol=1e-8)
    for k in range(8):
        np.testing.assert_allclose(log_batch(R[k], t[k])[0], gtsam.Pose3.Logmap(gtsam.Pose3(T_from_Rt(R[k], t[k]))),
                                   atol=1e-8)


@given(seeds)
def test_batched_retract_and_local_are_gtsams_and_carry_samples_between_tangents(seed):
    # A sample T_a Exp(xi) read in another pose's tangent (one minimum's samples in another's): the x with
    # T_b Exp(x) = T_a Exp(xi), as gtsam's retract and localCoordinates give it, to 1e-8.
    rng = np.random.default_rng(seed)
    T_a, T_b = (T_from_Rt(random_rotation(rng), rng.normal(size=3)) for _ in range(2))
    T_b = T_a @ T_exp(rng.normal(0, 0.3, 6))  # near, as two minima of one transform are
    xi = rng.normal(0, 0.05, (5, 6))
    R, t = retract_batch(T_a, xi)
    x = retangent_batch(T_a, xi, T_b)
    for k in range(5):
        T_k = gtsam.Pose3(T_a).retract(xi[k])
        np.testing.assert_allclose(T_from_Rt(R[k], t[k]), T_k.matrix(), atol=1e-10)
        np.testing.assert_allclose(x[k], gtsam.Pose3(T_b).localCoordinates(T_k), atol=1e-8)
    np.testing.assert_allclose(local_batch(T_a, R, t), xi, atol=1e-8)


@given(seeds)
def test_quaternion_round_trip_is_scalar_last(seed):
    R = random_rotation(np.random.default_rng(seed))
    q = quat_xyzw_from_R(R)
    assert q[3] >= 0 and abs(np.linalg.norm(q) - 1) < 1e-12
    np.testing.assert_allclose(R_from_quat_xyzw(q), R, atol=1e-12)
    g = gtsam.Rot3(R).toQuaternion()  # gtsam reports w separately
    np.testing.assert_allclose(abs(g.w()), q[3], atol=1e-9)


@given(seeds)
def test_plane_fit_and_moment_statistics(seed):
    rng = np.random.default_rng(seed)
    n = rng.normal(size=3)
    n /= np.linalg.norm(n)
    d = rng.uniform(0.5, 10)
    basis = np.linalg.svd(n[None])[2][1:]
    pts = d * n + rng.uniform(-1, 1, (200, 2)) @ basis
    plane = fit_plane_pca(pts)
    assert plane.distance >= 0
    assert abs(abs(plane.normal @ n) - 1) < 1e-10 and abs(plane.distance - d) < 1e-9
    noisy = pts + rng.normal(0, 0.01, pts.shape)
    other = Plane(n + rng.normal(0, 0.1, 3), d + 0.05)
    direct = np.sum(other.signed_distances(noisy) ** 2)
    assert sum_squared_distances(other.coefficients, moment_matrix(noisy)) == pytest.approx(direct, rel=1e-9)


@settings(deadline=None)
@given(seeds, st.integers(min_value=3, max_value=12))
def test_closed_form_recovers_exact_transform_from_noise_free_planes(seed, m):
    rng = np.random.default_rng(seed)
    T = T_from_Rt(random_rotation(rng), rng.normal(0, 0.5, 3))
    cams, lids = [], []
    T_lidar_camera = T_inverse(T)
    while len(cams) < m:
        n = rng.normal(size=3)
        n[2] = abs(n[2]) + 0.5
        pc = Plane(n, rng.uniform(1.5, 6.0))
        pl = pc.transformed(T_lidar_camera)
        if pl.distance > 0.1:  # both sensors on the board's front side, as in any real view
            cams.append(pc)
            lids.append(pl)
    assume(normal_spread(np.array([p.normal for p in cams]))[0][-1] > 0.1)
    sol = solve_closed_form(cams, lids)
    assert rotation_error(sol.T_camera_lidar[:3, :3], T[:3, :3]) < 1e-8
    np.testing.assert_allclose(sol.T_camera_lidar[:3, 3], T[:3, 3], atol=1e-7)


def test_closed_form_rejects_too_few_and_coplanar_normals():
    p = [Plane([0, 0, 1], 2.0), Plane([0.3, 0, 1], 3.0)]
    with pytest.raises(DegenerateLayoutError, match="only 2 usable"):
        solve_closed_form(p, p)
    # Normals all in the camera's x-z plane: translation along camera y is undetermined.
    flat = [Plane([np.sin(a), 0, np.cos(a)], 3.0) for a in (-0.5, 0.0, 0.4, 0.7)]
    with pytest.raises(DegenerateLayoutError, match="camera y") as info:
        solve_closed_form(flat, flat)
    assert "tilted about the horizontal axis" in info.value.message


@pytest.mark.parametrize("model,dist", [("pinhole", [-0.2, 0.1, 0.001, -0.001, 0.0]),
                                        ("fisheye", [-0.05, -0.08, 0.09, -0.05])])
def test_camera_project_and_unproject_are_inverse(model, dist):
    cam = CameraModel(K=[[900, 0, 640], [0, 905, 400], [0, 0, 1]], dist=dist, width=1280, height=800, model=model)
    rng = np.random.default_rng(4)
    P = np.column_stack([rng.uniform(-1, 1, 500), rng.uniform(-0.6, 0.6, 500), rng.uniform(1, 5, 500)])
    uv = cam.project(P)
    ok = cam.in_image(uv)
    assert ok.sum() > 300
    np.testing.assert_allclose(cam.normalized_from_pixels(uv[ok]), P[ok, :2] / P[ok, 2:], atol=1e-8)
    assert np.all(np.isnan(cam.project(np.array([[0.0, 0.0, -1.0]]))))


@pytest.mark.parametrize("model,dist", [("pinhole", [-0.2, 0.1, 0.001, -0.001, 0.0]),
                                        ("fisheye", [-0.05, -0.08, 0.09, -0.05])])
def test_camera_projects_a_large_sweep_in_blocks_as_in_one_call(model, dist):
    """More points than one OpenCV call takes (blocks bound the Jacobian OpenCV computes alongside), some
    behind the camera: the pixels of one call over the points in front, bit for bit."""
    import cv2

    from geometry import camera as camera_module

    cam = CameraModel(K=[[900, 0, 640], [0, 905, 400], [0, 0, 1]], dist=dist, width=1280, height=800, model=model)
    n = 2 * camera_module._PROJECT_BLOCK + 123
    P = np.random.default_rng(5).normal(size=(n, 3)) + [0.0, 0.0, 0.5]
    front = P[:, 2] > 1e-9
    project = cv2.fisheye.projectPoints if model == "fisheye" else cv2.projectPoints
    whole = project(P[front].reshape(-1, 1, 3), np.zeros(3), np.zeros(3), cam.K, cam.dist)[0].reshape(-1, 2)
    uv = cam.project(P)
    assert np.all(np.isnan(uv[~front])) and 0 < (~front).sum() < n
    np.testing.assert_array_equal(uv[front], whole)


def test_camera_rejects_bad_intrinsics():
    with pytest.raises(ValueError, match="fisheye dist of length 4"):
        CameraModel(K=np.eye(3), dist=[0.1, 0.2, 0.0], width=10, height=10, model="fisheye")
    with pytest.raises(ValueError, match="positive focal"):
        CameraModel(K=np.zeros((3, 3)), dist=[], width=10, height=10)


def test_board_model_corners_and_extent():
    b = BoardModel(squares=(9, 7), square_size=0.1, size=(1.0, 1.0))
    c = b.inner_corners()
    assert c.shape == (48, 3)
    np.testing.assert_allclose(c[0], [0.15, 0.25, 0.0])  # centred 0.9 x 0.7 pattern on a 1 x 1 board
    np.testing.assert_allclose(c[-1], [0.85, 0.75, 0.0])
    assert b.reflectance(0.01, 0.01) == 1.0 and np.isnan(b.reflectance(-0.1, 0.5))
    assert b.reflectance(0.1, 0.2) == 0.0  # first pattern square is black
    unknown = BoardModel(squares=(9, 7), square_size=0.1)
    assert not unknown.size_known and unknown.extent == pytest.approx((0.9, 0.7))
    with pytest.raises(ValueError, match="hold"):
        BoardModel(squares=(9, 7), square_size=0.1, size=(0.5, 1.0))
    offset = BoardModel(squares=(9, 7), square_size=0.1, size=(1.0, 1.0), pattern_offset=(0.02, 0.03))
    np.testing.assert_allclose(offset.inner_corners()[0], [0.12, 0.13, 0.0])


def test_transform_points_and_inverse():
    rng = np.random.default_rng(1)
    T = T_from_Rt(random_rotation(rng), rng.normal(size=3))
    P = rng.normal(size=(10, 3))
    np.testing.assert_allclose(transform_points(T_inverse(T), transform_points(T, P)), P, atol=1e-12)


def test_weak_normal_spread_is_refused_alone_but_starts_a_refinement():
    """Boards all tilted the same way (the planar method's one-way sets): spread about 0.02 along camera y.
    The closed form alone refuses it; as a start for the factor graph it is allowed, with the exact answer
    on noise-free planes."""
    T = T_from_Rt(R_from_rotvec([0.02, -0.03, 0.01]), np.array([0.05, -0.1, 0.08]))
    normals = [np.array([np.sin(a), -0.5, np.cos(a)]) for a in (-0.5, -0.2, 0.1, 0.4)]
    normals = [n / np.linalg.norm(n) for n in normals]
    normals[0] = normals[0] + np.array([0.0, 0.04, 0.0])
    cam = [Plane(n, 3.0 + 0.2 * k) for k, n in enumerate(normals)]
    T_lc = T_inverse(T)
    lid = [Plane(T_lc[:3, :3] @ p.normal, p.distance - p.normal @ T[:3, 3]) for p in cam]
    s = normal_spread(np.array([p.normal for p in cam]))[0][-1]
    assert 0.01 < s < 0.05
    with pytest.raises(DegenerateLayoutError, match="camera y"):
        solve_closed_form(cam, lid)
    sol = solve_closed_form(cam, lid, allow_weak=True)
    np.testing.assert_allclose(sol.T_camera_lidar, T, atol=1e-9)


def test_a_point_far_outside_the_field_that_distortion_folds_into_the_image_is_not_seen():
    # A wide lens (k1 -0.25, k2 0.08, k3 -0.01): its polynomial returns to zero near 69 degrees off axis, so a
    # point there projects near the image's centre. The bench of ChArUco cut poses met it (NaN board poses).
    cam = CameraModel(K=np.array([[640.0, 0, 640], [0, 640, 400], [0, 0, 1]]),
                      dist=np.array([-0.25, 0.08, 0.0, 0.0, -0.01]), width=1280, height=800)
    folded, near, behind = np.array([2.55, 0.0, 1.0]), np.array([0.3, -0.2, 1.0]), np.array([0.0, 0.0, -1.0])
    uv = cam.project(np.array([folded, near]))
    assert np.all(cam.in_image(uv))  # both land in the image...
    assert cam.sees(np.array([folded, near, behind])).tolist() == [False, True, False]  # ...one is really there
    # Its field: the widest ray through the image's border (a corner's, undistorted), which the folded point lies
    # beyond and the near one within; without distortion, the corner's angle exactly.
    field = cam.field_angle()
    assert np.arctan(np.hypot(640, 400) / 640) < field < np.radians(69)
    assert np.arctan(np.hypot(*folded[:2])) > field > np.arctan(np.hypot(*near[:2]))
    plain = CameraModel(K=cam.K, dist=np.zeros(5), width=1280, height=800)
    assert plain.field_angle() == pytest.approx(np.arctan(np.hypot(640, 400) / 640), abs=1e-9)


def test_central_differences_give_a_quadratics_gradient_and_hessian_and_refuse_a_non_finite_value():
    rng = np.random.default_rng(0)
    A = rng.normal(size=(4, 4))
    A = A @ A.T
    b = rng.normal(size=4)
    x0 = rng.normal(size=4)
    f0, grad, H = central_hessian(lambda X: 0.5 * np.einsum("ki,ij,kj->k", X, A, X) + X @ b, x0, np.full(4, 1e-3))
    np.testing.assert_allclose(f0, 0.5 * x0 @ A @ x0 + x0 @ b, rtol=1e-12)
    np.testing.assert_allclose(grad, A @ x0 + b, atol=1e-8)
    np.testing.assert_allclose(H, A, atol=1e-6)
    assert central_hessian(lambda X: np.where(X[:, 0] > x0[0], np.inf, 0.0), x0, np.full(4, 1e-3)) is None


def test_row_norms_are_numpys_to_the_bit():
    """The sweeps' norms, summed as ``np.linalg.norm(axis=1)`` sums them: equal bit for bit over widths 1-4,
    float64 and float32, integers, and no rows."""
    rng = np.random.default_rng(3)
    for n in (0, 1, 7, 1000):
        for d in (1, 2, 3, 4):
            P = rng.normal(size=(n, d)) * rng.uniform(1e-3, 1e3, size=(n, 1))
            for A in (P, P.astype(np.float32), np.rint(P).astype(np.int64)):
                got, want = row_norms(A), np.linalg.norm(A, axis=1)
                assert got.dtype == want.dtype and np.array_equal(got, want), (n, d, A.dtype)
