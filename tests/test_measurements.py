"""Camera and LiDAR board measurements against simulated ground truth."""
from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from estimators.camera.board_pose import estimate_board_pose, plane_jacobian
from estimators.camera.corners import detect_corners
from estimators.camera.detection import CornerDetection
from estimators.errors import MeasurementError
from estimators.io.dataset import load_dataset
from estimators.io.image_io import read_gray
from estimators.io.pointcloud_io import read_scan
from estimators.lidar.board_segmentation import SegmentationParams, find_board
from estimators.simulation.rendering import render_image
from estimators.simulation.simulator import default_rig, sample_board_poses, scene_patches
from geometry.camera import CameraModel
from geometry.planes import Plane
from geometry.rotations import T_inverse, T_retract, transform_points


def _truth(ds):
    gt = json.loads((ds.root / "ground_truth.json").read_text())
    return np.array(gt["T_camera_lidar"]), {k: np.array(v) for k, v in gt["T_camera_board"].items()}


def _plane_of(T_camera_board):
    n = T_camera_board[:3, 2]
    return Plane(n, n @ T_camera_board[:3, 3])


def test_camera_planes_match_truth_within_reported_uncertainty(sim_hdl64e, sim_vlp16):
    """Rendered images of 16 boards: each camera plane's error (normal and distance, 3 dof) against the truth is
    judged under the covariance the solver gives it (the pose's, from the corner residuals, times
    ``CORNER_ERROR_CORRELATION`` squared: rendered-corner errors correlate, issue 3). Each board within the 99.9%
    point of chi-square with 3 dof (16.27); the 16 together within the 0.1-99.9% points of chi-square with 48 dof
    (23.3-84.0), so that a covariance 2x too small in variance (a mean of 96) fails 69% of the time and one 2x too
    large (a mean of 24) 44%, a right one 0.2%."""
    from estimators.solvers.refinement_options import CORNER_ERROR_CORRELATION

    total = 0.0
    for path in (sim_hdl64e, sim_vlp16):
        ds = load_dataset(path)
        _, boards = _truth(ds)
        for f in ds.frames:
            det = detect_corners(read_gray(f.image), ds.board)
            assert det is not None, f.name
            obs = estimate_board_pose(det, ds.board, ds.camera)
            true = _plane_of(boards[f.name])
            e = np.append(obs.plane.normal - true.normal, obs.plane.distance - true.distance)
            d2 = float(e @ np.linalg.pinv(CORNER_ERROR_CORRELATION**2 * obs.plane_covariance, rcond=1e-10) @ e)
            assert d2 < 16.27, (path.name, f.name, d2)
            total += d2
            assert obs.reprojection_rms_px < 0.3
    assert 23.3 < total < 84.0, total


def test_plane_jacobian_matches_finite_differences():
    rng = np.random.default_rng(3)
    T = T_retract(np.eye(4), rng.normal(0, 0.5, 6))
    J = plane_jacobian(T)
    eps = 1e-6
    for k in range(6):
        d = np.zeros(6)
        d[k] = eps
        a, b = T_retract(T, d), T_retract(T, -d)
        num = (np.append(a[:3, 2], a[:3, 2] @ a[:3, 3]) - np.append(b[:3, 2], b[:3, 2] @ b[:3, 3])) / (2 * eps)
        np.testing.assert_allclose(J[:, k], num, atol=1e-7)


def test_fisheye_pose_from_rendered_image():
    """The fisheye (Kannala-Brandt) path: render through a fisheye camera, recover the board plane."""
    rng = np.random.default_rng(21)
    rig = default_rig(rng)
    fisheye = CameraModel(K=np.array([[600.0, 0, 640], [0, 600.0, 400], [0, 0, 1]]),
                          dist=[-0.05, -0.07, 0.09, -0.05], width=1280, height=800, model="fisheye")
    from dataclasses import replace
    rig = replace(rig, camera=fisheye, max_distance_m=3.0)
    T_cb = sample_board_poses(rig, 1, rng)[0]
    T_lc = T_inverse(rig.T_camera_lidar)
    patches, bi = scene_patches(rig, T_lc @ T_cb)
    img = render_image(fisheye, T_lc, patches, bi, transform_points(T_lc @ T_cb, rig.board.outline()), rng)
    det = detect_corners(img, rig.board)
    assert det is not None
    obs = estimate_board_pose(det, rig.board, fisheye)
    true = _plane_of(T_cb)
    assert np.degrees(np.arccos(min(1.0, obs.plane.normal @ true.normal))) < 0.5
    assert abs(obs.plane.distance - true.distance) < 0.01


def test_lidar_board_found_and_plane_accurate(sim_vlp16):
    """Every simulated sweep: the board is found, its normal within 0.6 deg and its offset at the board's centre
    within 1 cm of the truth."""
    ds = load_dataset(sim_vlp16)
    T_cl, boards = _truth(ds)
    T_lc = T_inverse(T_cl)
    rng = np.random.default_rng(0)
    for f in ds.frames:
        obs = estimate_board_pose(detect_corners(read_gray(f.image), ds.board), ds.board, ds.camera)
        lid = find_board(read_scan(f.scan), ds.board, obs, rng)
        true = _plane_of(boards[f.name]).transformed(T_lc)
        assert np.degrees(np.arccos(min(1.0, lid.plane.normal @ true.normal))) < 0.6, f.name
        centre = transform_points(T_lc @ boards[f.name], ds.board.centre[None])  # offset where the points are
        assert abs(lid.plane.signed_distances(centre)[0]) < 0.01, f.name
        assert 0.01 < lid.plane_rms_m < 0.03  # 2 cm range noise, seen at an angle
        np.testing.assert_allclose(lid.moment[3, 3], lid.n_points)


def test_board_not_found_is_a_reason_not_a_guess(sim_vlp16):
    ds = load_dataset(sim_vlp16)
    f = ds.frames[0]
    obs = estimate_board_pose(detect_corners(read_gray(f.image), ds.board), ds.board, ds.camera)
    pts = read_scan(f.scan)
    T_cl, boards = _truth(ds)
    board_plane = _plane_of(boards[f.name]).transformed(T_inverse(T_cl))
    without_board = pts[np.abs(board_plane.signed_distances(pts)) > 0.15]
    with pytest.raises(MeasurementError, match="no planar segment of the board's size|only"):
        find_board(without_board, ds.board, obs, np.random.default_rng(0))
    with pytest.raises(MeasurementError):
        find_board(pts, ds.board, obs, np.random.default_rng(0), SegmentationParams(max_sensor_separation_m=-3.0))


def test_classic_detector_runs_within_its_time_budget():
    """Where the sector detector finds no board, the classic detector runs last, in a child process stopped
    after the budget: a slow image costs the budget, not minutes, and the frame gets that reason."""
    board = default_rig(np.random.default_rng(0)).board
    noise = np.random.default_rng(1).integers(0, 256, (768, 1024), dtype=np.uint8)
    with pytest.raises(MeasurementError, match="time budget of 0.001 s"):
        detect_corners(noise, board, budget_s=0.001)
    # Within a budget it can keep, a blank image is simply "not found".
    assert detect_corners(np.full((480, 640), 128, np.uint8), board, budget_s=10.0) is None


def test_corners_do_not_depend_on_what_was_detected_before(tmp_path, monkeypatch):
    """The sector detector draws from OpenCV's random generator, which each call moves on. On this varied 2D
    layout (the end-to-end study's 4-board trial 27) the second board's image gave a true grid on its thread's
    first call and, on every later one, a grid whose last row lay on the board's border: the pair's solve then
    landed 13 degrees off without a word, or right, by the workers' count. Seeded per call, every call finds the
    true grid (each corner within 1 px of the truth's projection), and a grid that jumps is refused. (The
    detector itself: ``detect_corners`` keeps each search by the image, below.)"""
    from estimators.camera.chessboard import detect_chessboard, grid_is_smooth
    from estimators.simulation.simulator import rig_2d, sample_layout, simulate_frames, write_dataset

    rng = np.random.default_rng(1953701558)
    rig = rig_2d("varied", rng, 0.01)
    poses = sample_layout(rig, "spread", 4, rng)
    ds = load_dataset(write_dataset(tmp_path / "ds", rig, simulate_frames(rig, 4, rng, poses=poses)))
    _, boards = _truth(ds)
    gray = read_gray(ds.frames[1].image)
    truth_px = ds.camera.project(transform_points(boards[ds.frames[1].name], ds.board.inner_corners()))
    pattern = ds.board.inner_corners_shape
    for _ in range(3):
        det = detect_chessboard(gray, ds.board)
        # the pattern's two corner families read alike: the grid may start at either end
        err = min(np.abs(det.corners_px - truth_px).max(), np.abs(det.corners_px[::-1] - truth_px).max())
        assert err < 1.0
        assert grid_is_smooth(det.corners_px, pattern)
    broken = det.corners_px.copy()
    broken[-1] += 3 * (broken[-1] - broken[-2])  # the last corner thrown along its row
    assert not grid_is_smooth(broken, pattern)
    # detect_corners searches an image once: the same pixels again (another array) give that search's record,
    # read-only; other pixels, or another board, are searched
    from estimators.camera import corners

    first = detect_corners(gray, ds.board)
    assert detect_corners(gray.copy(), ds.board) is first and not first.corners_px.flags.writeable
    np.testing.assert_allclose(first.corners_px, det.corners_px)
    searched = []
    real = corners.detect_chessboard
    monkeypatch.setattr(corners, "detect_chessboard", lambda *a: searched.append(1) or real(*a))
    assert detect_corners(np.roll(gray, 1, axis=1), ds.board) is not first and len(searched) == 1
    assert detect_corners(gray, ds.board) is first and len(searched) == 1
    detect_corners(gray, replace(ds.board, square_size=0.9 * ds.board.square_size))
    assert len(searched) == 2


def test_ambiguous_board_orientation_is_refused_not_guessed():
    """A small board far away is foreshortened alike by two tilts (IPPE's two poses): its corners cannot say
    which, and a plane from the wrong one is tens of degrees off under a covariance of a fraction of a degree.
    Such a board is refused with the reason and both tilts (for a 2D solver to decide by the laser); the same
    board near the camera is measured as usual."""
    from geometry.board import BoardModel
    from geometry.rotations import R_from_rotvec, T_from_Rt

    board = BoardModel((4, 4), 0.1)  # 3 x 3 inner corners
    camera = default_rig(np.random.default_rng(0)).camera
    centre = np.array([0.15, 0.15, 0.0])

    def observe(distance, seed):
        R = R_from_rotvec([0.0, np.radians(35.0), 0.0])
        T = T_from_Rt(R, np.array([0.0, 0.0, distance]) - R @ centre)
        uv = camera.project(transform_points(T, board.inner_corners()))
        uv = uv + np.random.default_rng(seed).normal(0.0, 0.2, uv.shape)
        return T, CornerDetection(uv, "simulated")

    refused = 0
    for seed in range(20):
        T, det = observe(8.0, seed)
        try:
            obs = estimate_board_pose(det, board, camera)
        except MeasurementError as exc:
            assert "orientation is ambiguous" in exc.message
            # both tilts come with it (for the 2D solver to try), one of them the true one, best first
            tilts = [np.degrees(np.arccos(min(1.0, o.plane.normal @ T[:3, 2]))) for o in exc.observations]
            excess = [o.orientation_excess_chi2 for o in exc.observations]
            assert len(tilts) == 2 and min(tilts) < 10.0 and max(tilts) > 20.0
            assert excess[0] == 0.0 and 0.0 <= excess[1] < 9.0
            refused += 1
            continue
        # Kept only when the other tilt fits clearly worse: then the kept plane is the true one.
        assert np.degrees(np.arccos(min(1.0, obs.plane.normal @ T[:3, 2]))) < 10.0
    assert refused >= 10  # at 8 m, 0.2 px noise: the two tilts are usually indistinguishable
    for seed in range(5):
        T, det = observe(1.5, seed)
        obs = estimate_board_pose(det, board, camera)
        assert np.degrees(np.arccos(min(1.0, obs.plane.normal @ T[:3, 2]))) < 2.0


def test_a_board_of_unknown_size_is_trimmed_by_its_pattern_and_margin():
    """A board whose size dataset.yaml leaves out, on a post in its own plane reaching 0.8 m below it (returns as
    dense as the board's): the piece is cut to a window of the pattern's extent and 15 cm on each side (before,
    with no size, it was kept whole), so the post's lower part is gone while the board's returns stay."""
    from geometry.board import BoardModel

    rng = np.random.default_rng(3)
    board = BoardModel((8, 6), 0.1)  # pattern 0.8 x 0.6 m, size unknown
    u, v = rng.uniform(-0.05, 0.85, 3000), rng.uniform(-0.05, 0.65, 3000)
    post_u, post_v = 0.4 + rng.uniform(-0.03, 0.03, 250), rng.uniform(-0.8, 0.0, 250)
    local = np.column_stack([np.r_[u, post_u], np.r_[v, post_v], rng.normal(0.0, 0.003, 3250)])
    A = np.array([[0.0, 0.2, -0.98], [1.0, 0.0, 0.0], [0.0, 0.98, 0.2]])
    Q, R = np.linalg.qr(A)
    T_lidar_board = np.eye(4)
    T_lidar_board[:3, :3], T_lidar_board[:3, 3] = Q * np.sign(np.diag(R)), [3.0, -0.4, -0.3]
    obs = find_board(transform_points(T_lidar_board, local), board, None, rng)
    q = transform_points(T_inverse(T_lidar_board), obs.points)
    on_board = (q[:, 1] > -0.05) & (q[:, 0] > -0.05) & (q[:, 0] < 0.85)
    assert on_board.sum() > 2800
    assert np.all(q[:, 1] > -0.5)  # the pattern's 0.6 m and the margins: 0.9 m of window at most


def test_a_dataset_whose_ring_field_holds_one_value_is_measured_as_one_without(tmp_path):
    # A ring field of zeros (a converter's) read as beams made the board one ring: 13 of a bag's 579 ring ends were
    # left, and the estimate moved 0.03 -> 0.19 degree with an OK verdict. It is set aside, and the warning says so.
    from pypcd4 import PointCloud

    from estimators.io.pointcloud_io import write_scan
    from estimators.pipeline.measurement import measure
    from estimators.simulation.simulator import simulate_dataset

    without = simulate_dataset(tmp_path / "without", n_poses=4, seed=3, lidar="vlp16", ring_field=False)
    zeros = simulate_dataset(tmp_path / "zeros", n_poses=4, seed=3, lidar="vlp16")
    for path in sorted(zeros.glob("*.pcd")):
        a = PointCloud.from_path(path).numpy(("x", "y", "z", "intensity"))
        write_scan(path, a[:, :3], a[:, 3], ring=np.zeros(len(a), np.uint16))
    a, b = measure(without), measure(zeros)
    extra = [w for w in b.warnings if w not in a.warnings]
    assert len(extra) == 1 and extra[0].startswith("4 of 4 sweeps (the first 0000): its beam index (ring field or "
                                                   "organised rows) is not one: 100% of the returns beyond 2 m")
    for fa, fb in zip(a.frames, b.frames, strict=True):  # beams found from the elevations, alike
        assert fa.usable and fb.usable and fb.lidar.rings is not None
        np.testing.assert_array_equal(fa.lidar.points, fb.lidar.points)
        np.testing.assert_array_equal(fa.lidar.rings, fb.lidar.rings)


def test_a_board_resting_about_one_place_keeps_the_returns_of_its_edges(tmp_path):
    # Six of eight boards about one place (turned up to ~10 degrees, moved ~2 cm): the static scene takes the board
    # for background there, and the camera's outline restores its returns. Drawn under the consensus extrinsic, that
    # outline fell inside one edge: its returns were cut there and not at the others (a frame kept 2016 of its
    # 2052), which shifted the ring ends. The scene's background just beyond the outline is restored too.
    from estimators.pipeline.measurement import measure
    from estimators.simulation.simulator import simulate_frames, write_dataset

    rng = np.random.default_rng(0)
    rig = default_rig(rng, "os64")
    poses = sample_board_poses(rig, 8, rng)
    for k in range(1, 7):
        poses[k] = T_retract(poses[0], np.r_[rng.normal(0, 0.15, 3), rng.normal(0, 0.02, 3)])
    frames = simulate_frames(rig, len(poses), rng, poses=poses)
    m = measure(write_dataset(tmp_path / "ds", rig, frames, "pcd"))
    for f, truth in zip(m.frames, frames, strict=True):
        hit = int(truth.board_mask.sum())  # the returns whose beams hit the board
        assert f.usable and 0.99 * hit <= len(f.lidar.points) <= 1.01 * hit, (f.name, len(f.lidar.points), hit)
