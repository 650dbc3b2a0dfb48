"""ChArUco boards (issue 18): the board entry, the printed pattern in the simulator, detection of partial
views with ids, and calibration end to end (3D and 2D) through the CLI and the API."""
from __future__ import annotations

import json
from dataclasses import replace

import cv2
import numpy as np
import pytest

from estimators.calibration import calibrate_pair, measure, solve
from estimators.camera.board_pose import estimate_board_pose
from estimators.camera.charuco import MIN_CHARUCO_CORNERS, detect_charuco, opencv_board, spans_plane
from estimators.cli import main
from estimators.errors import DatasetError
from estimators.io.bag_extract import corner_motion, extract_bag
from estimators.io.dataset import load_dataset, parse_board
from estimators.io.measurement_store import load_measurements, save_measurements
from estimators.simulation.simulator import (as_charuco, board_reflectance, default_board, default_rig,
                                             sample_board_poses, simulate_dataset)
from estimators.solvers.observation_model import (Layout, corner_pixels, cramer_rao_bound, seen_corners,
                                                  simulate_measurements)
from geometry.rotations import T_inverse, T_log, transform_points

from .rosbag_writer import write_bag_from_dataset


@pytest.fixture(scope="module")
def charuco_3d(tmp_path_factory):
    """8 poses of the default board printed as ChArUco, VLP-16-like, about 30% of them cut by the image's
    edge."""
    return simulate_dataset(tmp_path_factory.mktemp("charuco") / "vlp16", n_poses=8, seed=21, lidar="vlp16",
                            pattern="charuco")


@pytest.mark.parametrize("entry, match", [
    ({"marker_size": 0.12}, "marker_size between 0 and the square size"),
    ({"marker_size": 0.07, "dictionary": "DICT_9X9_7"}, "dictionary as one of OpenCV's"),
    ({"marker_size": 0.07, "dictionary": "DICT_4X4_50", "squares": [15, 12]}, "at least 90 markers"),
    ({}, "needs marker_size"),
    ({"marker_size": "7 cm"}, "marker_size must be a number"),
    ({"marker_size": 0.07, "legacy_pattern": "yes"}, "legacy_pattern must be true or false"),
    ({"pattern": "circles"}, "pattern must be one of"),
])
def test_bad_charuco_entries_are_one_line_errors_naming_the_key(entry, match, tmp_path):
    b = {"squares": [9, 7], "square_size": 0.1, "pattern": "charuco", **entry}
    with pytest.raises(DatasetError, match=match) as info:
        parse_board(b, tmp_path / "dataset.yaml")
    assert "\n" not in info.value.message and "dataset.yaml" in info.value.message


def test_the_simulated_pattern_is_opencvs_board_in_the_board_frame():
    board = as_charuco(default_board())
    refl = board_reflectance(board)
    s, (ox, oy) = board.square_size, board.offset
    nx, ny = board.squares
    # The checkerboard's squares: black where the plain board model says so (square centres).
    i, j = np.meshgrid(np.arange(nx), np.arange(ny))
    cx, cy = ox + (i.ravel() + 0.5) * s, oy + (j.ravel() + 0.5) * s
    black = board.reflectance(cx, cy) == 0
    assert np.all(refl(cx[black], cy[black]) == 0)
    # Each marker where OpenCV puts it: its black border one bit inside its outline, in a white square whose
    # margin round the marker is white.
    cb = opencv_board(board)
    bit = board.marker_size / 7  # 5x5 bits and a border of one bit
    for quad in cb.getObjPoints():
        q = np.asarray(quad)[:, :2] + [ox, oy]
        lo, hi = q.min(0), q.max(0)
        assert np.allclose(hi - lo, board.marker_size)
        assert refl(lo[0] + bit / 2, (lo[1] + hi[1]) / 2) == 0  # the border
        assert refl(lo[0] - (s - board.marker_size) / 4, (lo[1] + hi[1]) / 2) == 1  # the margin
    assert np.isnan(refl(np.array([-0.01]), np.array([0.5])))[0]


def test_partial_views_give_ids_corners_and_poses_near_the_truth(charuco_3d):
    """Every simulated frame is detected, with 90% of the corners in the image over the set (at the image's
    edge a corner whose markers are cut off cannot be named), and they lie within 0.5 px RMS of the truth
    (pixel noise 2 grey levels), and each pose within 0.5 deg and 2 cm of the truth."""
    ds = load_dataset(charuco_3d)
    truth = json.loads((charuco_3d / "ground_truth.json").read_text())["T_camera_board"]
    partial = seen = in_image = 0
    for f in ds.frames:
        gray = cv2.imread(str(f.image), cv2.IMREAD_GRAYSCALE)
        T = np.array(truth[f.name])
        uv = ds.camera.project(transform_points(T, ds.board.inner_corners()))
        inside = ds.camera.in_image(uv, margin_px=10.0)
        det = detect_charuco(gray, ds.board)
        assert det is not None, f.name
        assert np.all(np.diff(det.corner_ids) > 0) and set(det.corner_ids) <= set(np.nonzero(ds.camera.in_image(uv))[0])
        seen, in_image = seen + len(det.corner_ids), in_image + inside.sum()
        partial += inside.sum() < len(uv)
        # the board pose drops the odd corner a misread marker put pixels away; the rest are accurate
        obs = estimate_board_pose(det, ds.board, ds.camera)
        assert len(obs.corner_ids) >= 0.9 * len(det.corner_ids)
        err = np.linalg.norm(uv[obs.corner_ids] - obs.corners_px, axis=1)
        assert np.sqrt(np.mean(err**2)) < 0.3 and err.max() < 1.0, f.name
        xi = T_log(T_inverse(T) @ obs.T_camera_board)
        assert np.degrees(np.linalg.norm(xi[:3])) < 0.5 and np.linalg.norm(xi[3:]) < 0.02, f.name
    assert partial >= 2  # the set holds partial views
    assert seen >= 0.9 * in_image


def test_a_line_of_corners_does_not_span_the_board():
    board = as_charuco(default_board())
    cols = board.inner_corners_shape[0]
    assert not spans_plane(board, np.arange(cols))  # one row
    assert spans_plane(board, np.r_[np.arange(4), cols + np.arange(4)])  # two rows
    assert not spans_plane(board, np.arange(MIN_CHARUCO_CORNERS - 1) * cols)  # too few


def test_charuco_3d_calibrates_end_to_end_through_the_cli_and_the_measurements_file(charuco_3d, tmp_path):
    out = tmp_path / "out"
    assert main(["calibrate", str(charuco_3d), "--out", str(out), "--samples", "0"]) == 0
    data = json.loads((out / "calibration.json").read_text())
    assert data["frames_used"] == 8  # partial views included
    T, cov = np.array(data["T_camera_lidar"]), np.array(data["covariance"])
    xi = T_log(T_inverse(T) @ load_dataset(charuco_3d).ground_truth())
    assert xi @ np.linalg.solve(cov, xi) < 22.5  # chi-square 6 dof, 99.9%
    assert np.degrees(np.linalg.norm(xi[:3])) < 0.3 and np.linalg.norm(xi[3:]) < 0.02
    # The measurements keep each frame's corner ids; solving them again gives the same extrinsic.
    m = load_measurements(out / "measurements.npz")
    assert m.board.is_charuco and any(f.camera.corner_ids is not None and len(f.camera.corner_ids) < 48
                                      for f in m.frames)
    again = solve(m, rng=np.random.default_rng(0), samples=0)
    np.testing.assert_allclose(again.T_camera_lidar, T, atol=1e-6)


def test_intrinsics_from_partial_charuco_views(tmp_path):
    """No camera entry: Zhang's method from the corners each view saw, partial views included."""
    data = simulate_dataset(tmp_path / "nocam", n_poses=8, seed=22, lidar="vlp16", pattern="charuco",
                            include_camera=False)
    ds = load_dataset(data)
    m = measure(ds, rng=np.random.default_rng(0))
    assert m.camera.K[0, 0] == pytest.approx(940.0, rel=0.02) and m.camera.K[0, 2] == pytest.approx(512.0, abs=15)
    # a measurements file round trip keeps the ids (a partial view's corners are a subset)
    save_measurements(tmp_path / "m", m)
    back = load_measurements(tmp_path / "m" / "measurements.npz")
    for a, b in zip(m.frames, back.frames):
        if a.camera is not None:
            assert np.array_equal(a.camera.corner_ids, b.camera.corner_ids)


def test_charuco_2d_calibrates_through_the_api_and_the_cli(tmp_path):
    data = simulate_dataset(tmp_path / "scan2d", n_poses=6, seed=23, lidar="2d", pattern="charuco")
    ds = load_dataset(data)
    result = calibrate_pair(ds, rng=np.random.default_rng(0), posterior=None)
    xi = T_log(T_inverse(result.T_camera_lidar) @ ds.ground_truth())
    assert result.frames_used == 6
    assert xi @ np.linalg.solve(result.covariance, xi) < 22.46  # chi-square, 6 dof, 99.9%
    # and through the CLI, to the same answer
    out = tmp_path / "out"
    assert main(["calibrate", str(data), "--out", str(out), "--samples", "0", "--no-report", "--no-cache"]) == 0
    cli = json.loads((out / "calibration.json").read_text())
    assert cli["frames_used"] == 6
    np.testing.assert_allclose(np.array(cli["T_camera_lidar"]), result.T_camera_lidar, atol=1e-6)


def test_stillness_compares_the_charuco_corners_both_views_saw():
    a = np.full((48, 2), np.nan)
    a[:10] = np.arange(20).reshape(10, 2)
    b = a.copy()
    b[:3] = np.nan  # three corners lost at the image's edge
    b[3:10] += 0.5
    assert corner_motion(a, b) == pytest.approx(np.hypot(0.5, 0.5))
    b[3:] = np.nan
    assert corner_motion(a, b) == float("inf")  # too few corners in common to judge


def test_the_layout_model_counts_the_corners_in_the_image_of_a_cut_charuco_board():
    rng = np.random.default_rng(24)
    rig = default_rig(rng, "vlp16")
    rig = replace(rig, board=as_charuco(rig.board))
    poses = sample_board_poses(rig, 4, rng, outside_image_share=1.0)  # every pose cut by the image's edge
    layout = Layout(rig.camera, rig.board, rig.beams, rig.T_camera_lidar, tuple(poses), 0.2, 0.02)
    for i in range(4):
        seen = seen_corners(layout, i)
        assert 0.3 * 48 <= len(seen) < 48
        assert np.all(rig.camera.in_image(corner_pixels(layout, i)[seen]))
    crb = cramer_rao_bound(layout)
    assert np.all(np.isfinite(crb)) and np.linalg.eigvalsh(crb)[0] > 0
    # Simulated measurements carry the ids of the corners in the image; their board poses are near the truth.
    frames = simulate_measurements(layout, np.random.default_rng(0))
    for i, f in enumerate(frames):
        assert np.array_equal(f.camera.corner_ids, seen_corners(layout, i))
        assert np.linalg.norm(f.camera.T_camera_board[:3, 3] - poses[i][:3, 3]) < 0.05


def test_a_charuco_bag_extracts_one_frame_per_still_pose(charuco_3d, tmp_path):
    """The bag's stillness check compares the ChArUco corners two images share, cut boards included."""
    bag = write_bag_from_dataset(charuco_3d, tmp_path / "rig.bag", "ros1", image_hz=5)
    board = load_dataset(charuco_3d).board
    summary = extract_bag(bag, tmp_path / "ds", board, "/camera/image_raw", cloud_topic="/velodyne_points")
    assert summary.frames == 8 and summary.counts["kept"] == 8
    assert load_dataset(tmp_path / "ds").board == board  # the board entry, ChArUco keys included
