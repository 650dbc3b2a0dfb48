"""Real scenes (issue 15): the static scene model, the cross-frame choice of each frame's board, the office and
hall simulations with a person holding the board, hints, and a posterior that is skipped, not crashed, on a
nearly degenerate problem. Tolerances are stated per test; seeds are fixed."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from estimators import calibrate
from estimators.calibration import calibrate_pair
from estimators.pipeline.measurement import Hints, measure_frames, parse_initial_guess
from estimators.errors import DatasetError, DegenerateLayoutError
from estimators.io.dataset import load_dataset
from estimators.io.pointcloud_io import read_scan_2d, read_sweep
from estimators.lidar.static_scene import build_static_scene
from estimators.measurements import observe_lidar_board
from estimators.simulation.simulator import default_rig, default_rig_2d, simulate_dataset, simulate_frames
from estimators.solvers.association import associate
from estimators.solvers.rig_posterior import unsampled_reason
from geometry.planes import Plane
from geometry.rotations import R_from_rotvec, T_from_Rt, T_inverse, T_log, transform_points


def _on_board(frame_points: np.ndarray, used: np.ndarray, mask: np.ndarray) -> float:
    """Share of the used points that are board returns (ground truth), matched exactly to the sweep."""
    from scipy.spatial import cKDTree

    d, idx = cKDTree(frame_points).query(used)
    assert np.all(d < 1e-5)
    return float(mask[idx].mean())


@pytest.fixture(scope="module")
def office_frames():
    """Six office frames (VLP-16, 2 cm range noise): static furniture, the board held or on a stand."""
    rng = np.random.default_rng(11)
    rig = default_rig(rng, "vlp16", 0.02)
    return rig, simulate_frames(rig, 6, rng, scene="office")


def test_static_scene_separates_the_moving_board_from_the_office(office_frames):
    """Range image (beam index known) and direction bins (an unorganised cloud): at least 95% of the board's
    returns are foreground in every frame and at most 3% of the rest of the room is."""
    rig, frames = office_frames
    for rings, kind in (([f.ring for f in frames], "range-image"), (None, "direction-bins")):
        scene = build_static_scene([f.points for f in frames], rings)
        assert scene.kind == kind and scene.usable and scene.moved == () and scene.note == ""
        for f in frames:
            fg = scene.foreground(f.points, None if rings is None else f.ring)
            assert fg[f.board_mask].mean() >= 0.95, (kind, f.name)
            assert fg[~f.board_mask].mean() <= 0.03, (kind, f.name)


def test_static_scene_notices_a_rig_that_moved(office_frames):
    """One sweep turned by 3 degrees about the vertical: exactly that frame contradicts the scene and the note
    names it (with or without beam indices); the scene is kept, and the turned frame's board is still foreground
    (its returns the scene does not explain stay candidates). Two frames are too few for a model."""
    rig, frames = office_frames
    points = [f.points for f in frames]
    points[2] = points[2] @ R_from_rotvec([0.0, 0.0, np.deg2rad(3.0)]).T
    for rings in ([f.ring for f in frames], None):
        scene = build_static_scene(points, rings)
        assert scene.usable and scene.moved == (2,), (rings is None, scene.moved)
        assert scene.note.startswith("frame(s) 2 contradict the static scene")
        assert scene.frame_foreground(2)[frames[2].board_mask].mean() >= 0.95
        assert scene.frame_foreground(0)[~frames[0].board_mask].mean() <= 0.03  # the others' scene unchanged
    assert not build_static_scene(points[:2]).usable


def test_static_scene_notices_a_rig_that_moved_half_way(office_frames):
    """The last three of six sweeps turned by 3 degrees: two groups of frames, each consistent with itself (each
    group's walls are a surface that three frames return); every frame contradicts the scene."""
    rig, frames = office_frames
    turn = R_from_rotvec([0.0, 0.0, np.deg2rad(3.0)])
    points = [f.points @ turn.T if k >= 3 else f.points for k, f in enumerate(frames)]
    scene = build_static_scene(points, [f.ring for f in frames])
    assert scene.moved == tuple(range(6))
    assert np.all(scene.match < scene.params.moved_fraction)


def test_a_board_left_at_one_place_does_not_make_the_rig_look_moved(office_frames):
    """The board (and its holder) of frame 0 left standing in frames 1 and 2 as well: three frames return it in
    front of the settled scene, as a rig moved half-way returns its walls, but it is no larger than an object
    that stands in front of the scene for a few frames: no frame contradicts the scene."""
    rig, frames = office_frames
    points = [f.points for f in frames]
    board = frames[0].points[frames[0].board_mask]
    rings = [f.ring for f in frames]
    for k in (1, 2):
        points[k] = np.vstack([points[k], board])
        rings[k] = np.concatenate([rings[k], frames[0].ring[frames[0].board_mask]])
    scene = build_static_scene(points, rings)
    assert scene.moved == () and scene.usable


@pytest.mark.parametrize("pad_m", [0.5, 0.3])
def test_a_board_filling_a_cropped_cloud_does_not_make_the_rig_look_moved(office_frames, pad_m):
    """The clouds cropped to one box around the boards (widened by 0.5 or 0.3 m): the boards fill up to 61% or
    81% of the returns. No frame is said to contradict the scene, every board is foreground (at least 98% of its
    returns), with and without beam indices. What little background is left cannot show a move, and the note
    says so: at 0.3 m no frame holds enough settled background to be judged; at 0.5 m a 3-degree turn of the
    rig would not show against it. Uncropped, that turn of one sweep is noticed."""
    from estimators.simulation.simulator import cropped_to_boards

    rig, frames = office_frames
    cropped = cropped_to_boards(frames, pad_m)
    assert max(f.board_mask.mean() for f in cropped) > (0.6 if pad_m == 0.5 else 0.8)
    for rings in ([f.ring for f in cropped], None):
        scene = build_static_scene([f.points for f in cropped], rings)
        assert scene.usable and scene.moved == (), scene.note
        for k, f in enumerate(cropped):
            fg = scene.foreground(f.points, None if rings is None else f.ring)
            assert fg[f.board_mask].mean() >= 0.98, (pad_m, rings is None, f.name)
        if rings is not None:
            unchecked = ("could not be checked: no frame" if pad_m == 0.3
                         else "a 3-degree turn of the rig about its vertical axis would not show")
            assert unchecked in scene.note
    turned = [f.points for f in frames]
    turned[1] = turned[1] @ R_from_rotvec([0.0, 0.0, np.deg2rad(3.0)]).T
    assert build_static_scene(turned, [f.ring for f in frames]).moved == (1,)


@pytest.mark.parametrize("pad_m", [0.5, 0.3])
def test_a_rig_that_moved_in_a_cropped_cloud_is_caught_or_said_to_be_unchecked(office_frames, pad_m):
    """One sweep turned by 3 degrees, then every cloud cropped to the boards' box in the LiDAR's frame (as a
    recorder crops): the turn is either among the frames that contradict the scene or the note says that the
    stillness was not checked; never a silent pass."""
    from dataclasses import replace

    rig, frames = office_frames
    turn = R_from_rotvec([0.0, 0.0, np.deg2rad(3.0)])
    boards = np.vstack([f.points[f.board_mask] for f in frames])
    lo, hi = boards.min(axis=0) - pad_m, boards.max(axis=0) + pad_m
    moved = [replace(f, points=f.points @ turn.T) if k == 1 else f for k, f in enumerate(frames)]
    keep = [np.all((f.points >= lo) & (f.points <= hi), axis=1) for f in moved]
    scene = build_static_scene([f.points[m] for f, m in zip(moved, keep)], [f.ring[m] for f, m in zip(moved, keep)])
    assert 1 in scene.moved or "not checked" in scene.note or "could not be checked" in scene.note, scene.note


def test_a_cropped_cloud_calibrates_with_the_static_scene(tmp_path, office_frames):
    """End to end on clouds cropped 0.3 m around the boards: every frame used, no frame said to contradict the
    scene but a warning that the rig's stillness could not be checked, and the truth inside the reported (Laplace)
    covariance's 99.9% region (chi-square, 6 dof; 6 office frames, VLP-16, 2 cm noise)."""
    from estimators.simulation.simulator import cropped_to_boards, write_dataset

    rig, frames = office_frames
    path = write_dataset(tmp_path / "cropped", rig, cropped_to_boards(frames, 0.3))
    result = calibrate_pair(path, samples=0)
    assert result.frames_used == len(frames)
    assert not any("contradict the static scene" in w for w in result.warnings), result.warnings
    assert any("stillness could not be checked" in w for w in result.warnings), result.warnings
    xi = T_log(T_inverse(result.T_camera_lidar) @ rig.T_camera_lidar)
    assert xi @ np.linalg.solve(result.covariance, xi) < 22.46, xi


def test_static_scene_of_2d_scans_uses_per_beam_ranges():
    """2D office scans with the person in the scan: the board's returns are foreground, the walls not."""
    rng = np.random.default_rng(5)
    rig = default_rig_2d(rng)
    frames = simulate_frames(rig, 5, rng, scene="office")
    scene = build_static_scene([f.points[:, :2] for f in frames])
    assert scene.kind == "range-image"
    for f in frames:
        fg = scene.foreground(f.points[:, :2])
        assert fg[f.board_mask].mean() >= 0.95 and fg[~f.board_mask].mean() <= 0.15, f.name


def _synthetic_frames(rng, n_frames: int, n_decoys: int, T_camera_lidar: np.ndarray, board, tilt_deg=(15, 40)):
    """Camera board poses (normals tilted ``tilt_deg`` from the optical axis), and per frame the true board's
    LiDAR points plus ``n_decoys`` board-sized planar pieces elsewhere (random orientations and places),
    shuffled: every frame is ambiguous."""
    poses, cands, truth = [], [], []
    T_lidar_camera = T_inverse(T_camera_lidar)
    grid = np.stack(np.meshgrid(np.linspace(0, 0.6, 12), np.linspace(0, 0.8, 14)), -1).reshape(-1, 2)
    flat = np.column_stack([grid, np.zeros(len(grid))])
    for k in range(n_frames):
        axis = rng.normal(size=3)
        R = R_from_rotvec(axis / np.linalg.norm(axis) * np.deg2rad(rng.uniform(*tilt_deg)))
        T_cb = T_from_Rt(R, np.array([rng.uniform(-1, 1), rng.uniform(-0.6, 0.6), rng.uniform(2.5, 5.0)]))
        poses.append(T_cb)
        board_pts = transform_points(T_lidar_camera @ T_cb, flat) + rng.normal(0, 0.01, (len(flat), 3))
        pieces = [observe_lidar_board(board_pts)]
        for _ in range(n_decoys):
            a = rng.normal(size=3)
            Rd = R_from_rotvec(a / np.linalg.norm(a) * rng.uniform(0, np.pi))
            Td = T_from_Rt(Rd, rng.uniform([-1, -4, -1.5], [6, 4, 1.5]))
            pieces.append(observe_lidar_board(transform_points(Td, flat) + rng.normal(0, 0.01, (len(flat), 3))))
        order = rng.permutation(len(pieces))
        cands.append([pieces[i] for i in order])
        truth.append(int(np.nonzero(order == 0)[0][0]))
    planes = [Plane(T[:3, 2], T[:3, 2] @ T[:3, 3]).facing_away() for T in poses]
    return planes, poses, cands, truth


def test_consensus_chooses_every_board_when_every_frame_is_ambiguous():
    """12 frames, each with its board and 5 decoys: the joint choice finds all 12 boards, and the extrinsic
    within 0.5 degree and 3 cm of the truth (1 cm point noise). A frame with decoys only is skipped, saying
    why."""
    rng = np.random.default_rng(3)
    from estimators.simulation.simulator import default_board

    board = default_board()
    board = type(board)(squares=(6, 8), square_size=0.1, size=(0.6, 0.8))
    T = T_from_Rt(R_from_rotvec([1.2, -1.2, 1.2]), np.array([0.05, -0.2, -0.1]))
    planes, poses, cands, truth = _synthetic_frames(rng, 12, 5, T, board)
    cands[4] = [c for i, c in enumerate(cands[4]) if i != truth[4]]
    result = associate(planes, poses, cands, board, np.random.default_rng(0))
    for k, choice in enumerate(result.choices):
        if k == 4:
            assert choice.chosen is None and "disagree" in choice.reason
        else:
            assert choice.chosen == truth[k], (k, choice.reason)
    xi = T_log(T_inverse(T) @ result.T_camera_lidar)
    assert np.degrees(np.linalg.norm(xi[:3])) < 0.5 and np.linalg.norm(xi[3:]) < 0.03
    assert result.agreeing == 11


def test_consensus_needs_three_frames_that_span_3d():
    rng = np.random.default_rng(4)
    board = type(default_rig(rng).board)(squares=(6, 8), square_size=0.1, size=(0.6, 0.8))
    T = T_from_Rt(R_from_rotvec([1.2, -1.2, 1.2]), np.zeros(3))
    planes, poses, cands, _ = _synthetic_frames(rng, 2, 2, T, board)
    with pytest.raises(DegenerateLayoutError):
        associate(planes, poses, cands, board, rng)


def test_consensus_on_boards_that_all_face_the_rig():
    """10 frames whose normals lie 1-3 degrees from the optical axis (hand-held boards facing the rig: no triple
    spreads 0.05), each with its board and 3 decoys: the joint choice runs on the triples above the factor
    graph's weak limit and finds every board."""
    rng = np.random.default_rng(5)
    board = type(default_rig(rng).board)(squares=(6, 8), square_size=0.1, size=(0.6, 0.8))
    T = T_from_Rt(R_from_rotvec([1.2, -1.2, 1.2]), np.array([0.05, -0.2, -0.1]))
    planes, poses, cands, truth = _synthetic_frames(rng, 10, 3, T, board, tilt_deg=(1, 3))
    normals = np.array([p.normal for p in planes])
    assert np.linalg.svd(normals, compute_uv=False)[-1] / np.sqrt(len(normals)) < 0.05
    result = associate(planes, poses, cands, board, np.random.default_rng(0))
    assert [c.chosen for c in result.choices] == truth
    # The extrinsic is the (weak) closed form of the true pairs: the layout, not the choice, limits it.
    from estimators.solvers.closed_form import solve_closed_form

    best = solve_closed_form(planes, [c[k].plane for c, k in zip(cands, truth)], allow_weak=True).T_camera_lidar
    xi = T_log(T_inverse(best) @ result.T_camera_lidar)
    assert np.degrees(np.linalg.norm(xi[:3])) < 0.05 and np.linalg.norm(xi[3:]) < 0.002


def test_overlapping_pieces_of_one_board_are_one_candidate():
    """Two pieces that hold most of the same returns, and two coplanar halves that touch, are one board each;
    a piece elsewhere stays a candidate of its own."""
    from estimators.lidar.board_segmentation import _one_per_board

    rng = np.random.default_rng(6)
    board = type(default_rig(rng).board)(squares=(6, 8), square_size=0.1, size=(0.6, 0.8))
    grid = np.stack(np.meshgrid(np.linspace(0, 0.6, 12), np.linspace(0, 0.8, 14)), -1).reshape(-1, 2)
    T_lb = T_from_Rt(R_from_rotvec([0.0, -np.pi / 2 + 0.3, 0.0]), np.array([3.0, -0.3, -0.4]))
    P = transform_points(T_lb, np.column_stack([grid, np.zeros(len(grid))])) + rng.normal(0, 0.005, (len(grid), 3))
    far = P + np.array([0.0, 3.0, 0.0])
    sweep = np.vstack([P, far])
    overlapping = [(observe_lidar_board(P[:120]), 0.2), (observe_lidar_board(P[40:]), 0.4),
                   (observe_lidar_board(far), 0.9)]
    merged = _one_per_board(overlapping, sweep, board)
    assert [c for _, c in merged] == [0.2, 0.9] and len(merged[0][0].points) >= 150
    top, bottom = grid[:, 1] > 0.4, grid[:, 1] <= 0.4
    halves = [(observe_lidar_board(P[top]), 0.3), (observe_lidar_board(P[bottom]), 0.5)]
    merged = _one_per_board(halves, sweep, board)
    assert len(merged) == 1 and len(merged[0][0].points) >= 150


def _check_dataset(path, min_hit_share: float = 0.4):
    """Calibrate a simulated dataset; every frame whose board is at least ``min_hit_share`` hit... is used with
    its points at least 80% on the true board; returns the result and the truth."""
    ds = load_dataset(path)
    truth = np.array(json.loads((path / "ground_truth.json").read_text())["T_camera_lidar"])
    masks = np.load(path / "ground_truth_board_points.npz")
    result = calibrate_pair(ds)
    full = max(int(masks[n].sum()) for n in masks.files)
    for f, fr in zip(result.frames, ds.frames):
        if ds.lidar == "2d":
            pts = read_scan_2d(fr.scan)
            pts = np.column_stack([pts, np.zeros(len(pts))])
        else:
            pts = read_sweep(fr.scan).points
        if f.usable:
            assert _on_board(pts, f.lidar.points if ds.lidar == "3d" else
                             np.column_stack([f.lidar.points[:, :2], np.zeros(len(f.lidar.points))]),
                             masks[f.name]) >= 0.8, f.name
        elif ds.lidar == "3d":
            assert masks[f.name].sum() < min_hit_share * full, (f.name, f.reason)
    return result, truth


def test_office_scene_3d_uses_every_board_and_no_wrong_segment(tmp_path):
    """An office (VLP-16, 3 cm noise, boards held by a person or on a stand, some partly outside the vertical
    field of view): every frame with most of its board hit is used, each with at least 80% of its points on the
    board; the simulation has no range error and the range model chooses none (issue 61: clutter made it keep a
    global offset confounded with the translation); the truth inside the reported 99.9% region."""
    path = simulate_dataset(tmp_path / "office", n_poses=8, seed=2, lidar="vlp16", sigma_range_m=0.03,
                            scene="office")
    result, truth = _check_dataset(path)
    assert result.frames_used >= 7
    assert result.refinement.range_model.chosen == "none", result.refinement.range_model.to_dict()
    xi = T_log(T_inverse(result.T_camera_lidar) @ truth)
    assert xi @ np.linalg.solve(result.covariance, xi) < 22.46, xi
    assert all(f.decision is not None and f.decision.method.startswith("consensus") for f in result.frames)
    frame = result.to_dict()["frames"][0]
    assert {"method", "chosen", "reason", "candidates"} <= frame["lidar_board_choice"].keys()
    # the engine's report (a pair folder's, as `lidarcam calibrate` writes it) shows each frame's board choice; its
    # record lists every frame as measured, as the pair's does (those without a board too)
    engine = calibrate(path, samples=0)
    assert [(f.name, f.usable) for f in engine.frames] == [(f.name, f.usable) for f in result.frames]
    report = engine.report(tmp_path / "out")
    assert (tmp_path / "out" / "board_choice_lidar0_0000.png").is_file() and "Which LiDAR points" in report.read_text()


def test_small_hand_held_board_facing_the_rig_on_a_vlp16(tmp_path):
    """A 0.35 x 0.40 m board held up in an office by a person, 8 frames whose normals all face the rig (no triple
    spreads the closed form's 0.05): the joint choice runs on the weak triples, the overlapping pieces the
    segmentation finds of one board count as one, and 7 of the 8 frames are used with their points on the board; the
    layout is weak (the bound is degrees and centimetres) and the covariance says so: the truth lies within 4
    standard deviations in every axis."""
    from estimators.simulation.simulator import handheld_rig, sample_layout, write_dataset

    rng = np.random.default_rng(2)
    rig = handheld_rig(rng)
    poses = sample_layout(rig, "handheld", 8, rng)
    path = write_dataset(tmp_path / "handheld", rig, simulate_frames(rig, 8, rng, poses=poses, scene="office"))
    result, truth = _check_dataset(path)
    assert result.frames_used >= 7
    xi = T_log(T_inverse(result.T_camera_lidar) @ truth)
    assert np.all(np.abs(xi) < 4 * np.sqrt(np.diag(result.covariance))), xi


def test_the_engines_record_lists_every_frame_as_measured(tmp_path, monkeypatch):
    """bench_handheld's dataset 8011, three of whose eight frames leave no board in the sweep: the engine's record
    lists all eight as the pair's does, in name order (it listed the five usable ones, and a benchmark that paired
    them with its poses by order paired them wrong); its measurements given back in memory solve to the same."""
    from estimators.io.measurement_store import rig_as_pair
    from estimators.simulation.simulator import handheld_rig, sample_layout, write_dataset

    rng = np.random.default_rng(8011)
    rig = handheld_rig(rng)
    poses = sample_layout(rig, "handheld", 8, rng)
    path = write_dataset(tmp_path / "handheld", rig, simulate_frames(rig, 8, rng, poses=poses, scene="office"))
    monkeypatch.setenv("LIDARCAM_CACHE_DIR", str(tmp_path / "cache"))
    engine = calibrate(path, samples=0, cache=True)
    pair = calibrate_pair(path, samples=0, cache=True)
    assert [(f.name, f.usable) for f in engine.frames] == [(f.name, f.usable) for f in pair.frames]
    assert len(engine.frames) == 8 and sum(f.usable for f in engine.frames) == 5
    # its frames as measured, in memory (no file read again), solve to the same estimate and covariance
    again = calibrate(rig_as_pair(engine.measurements, engine.rig.board, "3d"), samples=0)
    assert np.allclose(again.T_camera_lidar, engine.T_camera_lidar, rtol=0, atol=1e-9)
    assert np.allclose(again.covariance, engine.covariance, rtol=1e-6, atol=0)
    with pytest.raises(DatasetError, match="no image"):  # no image to draw its report on: said, not a crash
        again.report(tmp_path / "report")


def test_open_hall_with_3cm_noise_uses_every_frame(tmp_path):
    """Ground patches of the board's size at the boards' distances are background: all 6 frames are used; no range
    error simulated, none chosen; the truth inside the reported 99.9% region."""
    path = simulate_dataset(tmp_path / "hall", n_poses=6, seed=4, lidar="vlp16", sigma_range_m=0.03, scene="hall")
    result, truth = _check_dataset(path)
    assert result.frames_used == 6
    assert result.refinement.range_model.chosen == "none", result.refinement.range_model.to_dict()
    xi = T_log(T_inverse(result.T_camera_lidar) @ truth)
    assert xi @ np.linalg.solve(result.covariance, xi) < 22.46, xi


def test_hand_held_2d_scan_with_the_person_in_it_calibrates_with_its_posterior(tmp_path):
    """A 2D office recording with a person holding each board: the whole pipeline, posterior and report
    included, runs; the segments are chosen by the frames' consensus; the estimate is within 4 standard
    deviations of the truth."""
    path = simulate_dataset(tmp_path / "h2d", n_poses=8, seed=1, lidar="2d", scene="office")
    ds = load_dataset(path)
    engine = calibrate(ds, samples=300)
    truth = np.array(json.loads((path / "ground_truth.json").read_text())["T_camera_lidar"])
    assert engine.posterior is not None and engine.only_pair().frames >= 6
    xi = T_log(T_inverse(engine.T_camera_lidar) @ truth)
    assert np.all(np.abs(xi) < 4 * np.sqrt(np.diag(engine.covariance))), xi
    assert all(f.decision.method.startswith("consensus") for f in engine.frames if f.decision is not None)
    report = engine.report(tmp_path / "out")
    assert (tmp_path / "out" / "board_choice_lidar0_0000.png").is_file() and "Which LiDAR points" in report.read_text()


def test_initial_guess_gates_candidates_and_roi_crops(tmp_path):
    """A guess 90 degrees off rejects every candidate (the reason names the guess); the true extrinsic as a
    guess changes nothing; an ROI that excludes the boards, or every return, leaves no board."""
    path = simulate_dataset(tmp_path / "d", n_poses=5, seed=0, lidar="vlp16")
    ds = load_dataset(path)
    truth = np.array(json.loads((path / "ground_truth.json").read_text())["T_camera_lidar"])
    _, plain, _ = measure_frames(ds, np.random.default_rng(0))
    _, guided, _ = measure_frames(ds, np.random.default_rng(0), hints=Hints(initial_guess=truth))
    assert [f.lidar.n_points for f in plain] == [f.lidar.n_points for f in guided]
    wrong = truth @ T_from_Rt(R_from_rotvec([0, 0, np.pi / 2]), np.zeros(3))
    _, off, _ = measure_frames(ds, np.random.default_rng(0), hints=Hints(initial_guess=wrong))
    assert not any(f.usable for f in off) and all("initial guess" in f.reason for f in off)
    _, cropped, _ = measure_frames(ds, np.random.default_rng(0),
                                   hints=Hints(roi_min=np.array([-9, -9, -9]), roi_max=np.array([-1, 9, 9])))
    assert not any(f.usable for f in cropped)
    _, empty, _ = measure_frames(ds, np.random.default_rng(0),  # a box with no return in it: no board, no error
                                 hints=Hints(roi_min=np.array([90, 90, 90]), roi_max=np.array([91, 91, 91])))
    assert not any(f.usable for f in empty)


def test_initial_guess_parsing(tmp_path):
    T = parse_initial_guess(["0.1", "0.2", "0.3", "-90", "0", "-90"])
    np.testing.assert_allclose(T[:3, 3], [0.1, 0.2, 0.3])
    np.testing.assert_allclose(T[:3, :3], [[0, 0, 1], [-1, 0, 0], [0, -1, 0]], atol=1e-12)
    (tmp_path / "cal.json").write_text(json.dumps({"T_camera_lidar": T.tolist()}))
    np.testing.assert_allclose(parse_initial_guess([str(tmp_path / "cal.json")]), T)
    (tmp_path / "bad.txt").write_text("1 2 3\n4 5 6\n")
    for bad in (["1", "2"], ["a", "b", "c", "d", "e", "f"], [str(tmp_path / "missing.json")],
                [str(tmp_path / "bad.txt")]):
        with pytest.raises(DatasetError):
            parse_initial_guess(bad)


def test_cli_hint_errors_are_one_line_and_exit_2(tmp_path):
    path = simulate_dataset(tmp_path / "d", n_poses=3, seed=0, lidar="vlp16")
    for extra in (["--initial-guess", "1", "2"], ["--roi", "1", "1", "1", "0", "0", "0"]):
        r = subprocess.run([sys.executable, "-m", "estimators", "calibrate", str(path), "--out",
                            str(tmp_path / "o"), *extra], capture_output=True, text=True)
        assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1, r.stderr
        assert not (tmp_path / "o").exists()


def test_posterior_is_skipped_with_its_reason_on_a_nearly_degenerate_problem():
    """A Laplace covariance with an undetermined direction (or nearly singular) is not sampled: the reason
    says why; an ordinary one is sampled."""
    ok = np.diag([1e-6] * 3 + [1e-5] * 3)
    assert unsampled_reason(ok) is None
    wide = ok.copy()
    wide[5, 5] = 4.0
    assert "nearly degenerate" in unsampled_reason(wide)
    flat = ok.copy()
    flat[0, 0] = 1e-22
    assert "singular" in unsampled_reason(flat)
    assert "not finite" in unsampled_reason(np.full((6, 6), np.nan))


def test_cast_over_a_cached_static_background_is_the_single_pass_cast():
    """The simulator casts the static scene once per dataset and each frame's own patches over it: on the
    office (bounded furniture) and the default room (unbounded walls), with a held board, the ranges, patch
    indices and reflectances are exactly those of casting the whole scene in one pass."""
    from estimators.simulation.office import office_layout
    from estimators.simulation.scene import cast, cast_background
    from estimators.simulation.simulator import default_room, sample_board_poses, scene_patches

    rng = np.random.default_rng(3)
    rig = default_rig(rng, "vlp16", 0.02)
    dirs = rng.normal(size=(40000, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    origin = np.array([0.1, -0.05, 0.02])
    for static in (office_layout(-rig.lidar_height_m, rng), default_room(-rig.lidar_height_m)):
        bg = cast_background(origin, dirs, static, 30.0)
        for T_cb, held in zip(sample_board_poses(rig, 4, rng), (True, False, True, False)):
            patches, _ = scene_patches(rig, T_inverse(rig.T_camera_lidar) @ T_cb, static, held)
            one_pass = cast(origin, dirs, patches, 30.0)
            over = cast(origin, dirs, patches, 30.0, bg)
            assert (one_pass[1] == 0).sum() > 0  # the board is in the bundle
            for a, b in zip(one_pass, over):
                np.testing.assert_array_equal(a, b)
    with pytest.raises(ValueError, match="other rays"):
        cast(origin, dirs[:10], patches, 30.0, bg)


def test_rendering_over_the_cached_background_is_the_single_pass_rendering():
    """The camera's image of a frame rendered over the static scene's cached cast (the static pieces that
    cannot hide the board skipped when its edges are anti-aliased) is exactly the image of the whole scene
    rendered in one pass: the default room and the office, held boards and boards on stands."""
    from estimators.simulation.office import office_layout
    from estimators.simulation.rendering import pixel_rays, render_clean
    from estimators.simulation.scene import cast_background, rectangle
    from estimators.simulation.simulator import default_room, sample_board_poses, scene_patches

    rng = np.random.default_rng(5)
    rig = default_rig(rng, "vlp16", 0.02)
    T_lc = T_inverse(rig.T_camera_lidar)
    poses = sample_board_poses(rig, 2, rng)
    # A static post between the camera and the first board, over part of it: it must hide that part.
    T_lb = T_lc @ poses[0]
    near = 0.5 * (T_lc[:3, 3] + T_lb[:3, 3])
    post = rectangle(near - [0.0, 0.05, 0.5], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], 0.1, 1.0, 0.2, "post")
    room = default_room(-rig.lidar_height_m)
    for static in (office_layout(-rig.lidar_height_m, rng), room, room + [post]):
        bg = cast_background(T_lc[:3, 3], pixel_rays(rig.camera, T_lc), static)
        for T_cb, held in zip(poses, (True, False)):
            T_lb = T_lc @ T_cb
            patches, bi = scene_patches(rig, T_lb, static, held)
            outline = transform_points(T_lb, rig.board.outline())
            image = render_clean(rig.camera, T_lc, patches, bi, outline, background=bg)
            np.testing.assert_array_equal(image, render_clean(rig.camera, T_lc, patches, bi, outline))
            if static[-1] is post and T_cb is poses[0]:
                clear = render_clean(rig.camera, T_lc, *scene_patches(rig, T_lb, room, held), outline)
                assert np.count_nonzero(image != clear) > 1000  # the post does hide part of the board


def test_simulated_frames_do_not_depend_on_the_number_of_threads():
    """Frames cast ahead in threads, their noise added in order: the same images and sweeps for 1 or 3
    workers."""
    frames = {}
    for workers in (1, 3):
        rng = np.random.default_rng(9)
        frames[workers] = simulate_frames(default_rig(rng, "vlp16", 0.02), 4, rng, workers=workers)
    for a, b in zip(frames[1], frames[3]):
        np.testing.assert_array_equal(a.image, b.image)
        np.testing.assert_array_equal(a.points, b.points)
        np.testing.assert_array_equal(a.board_mask, b.board_mask)


def test_subpixel_interpolation_is_the_per_ray_interpolation_bit_for_bit():
    """The anti-aliasing rays' undistorted coordinates, gathered once per pixel and neighbour, equal the
    per-ray bilinear interpolation exactly: at the grid's first and last rows and columns too, and for
    offsets that are not multiples of 1/1024 (the per-ray path). The pixel rays shared by a pool's threads
    equal those of one thread."""
    from concurrent.futures import ThreadPoolExecutor

    from estimators.simulation import rendering

    rng = np.random.default_rng(3)
    grid = rng.normal(size=(61, 81, 2))
    pu, pv = rng.integers(0, 80, 500), rng.integers(0, 60, 500)
    pu[:20], pv[20:40], pu[40:60], pv[60:80] = 0, 0, 79, 59
    for S in (1, 2, 3, 4, 5):
        offs = (np.arange(S) + 0.5) / S - 0.5
        ou, ov = np.meshgrid(offs, offs)
        u, v = (pu[:, None] + ou.ravel()).ravel(), (pv[:, None] + ov.ravel()).ravel()
        np.testing.assert_array_equal(rendering._interp_subpixels(grid, pu, pv, offs),
                                      rendering._interp(grid, u, v))
    rig = default_rig(np.random.default_rng(4), "vlp16", 0.02)
    T_lc = T_inverse(rig.T_camera_lidar)
    one = rendering.pixel_rays(rig.camera, T_lc)
    rendering._GRID_CACHE.clear()
    with ThreadPoolExecutor(2) as pool:
        np.testing.assert_array_equal(rendering.pixel_rays(rig.camera, T_lc, pool), one)


def test_too_few_frames_after_a_failed_joint_choice_says_why_it_failed():
    from dataclasses import replace

    from estimators.calibration import CONSENSUS_FAILED, solve
    from estimators.simulation.simulator import sample_layout
    from estimators.solvers.observation_model import Layout, simulate_measurements

    rng = np.random.default_rng(7)
    rig = default_rig(rng, "vlp16", 0.02)
    layout = Layout(rig.camera, rig.board, rig.beams, rig.T_camera_lidar,
                    tuple(sample_layout(rig, "spread", 4, rng)), 0.2, 0.02)
    frames = simulate_measurements(layout, rng)
    ambiguous = "LiDAR board: ambiguous: 2 board-sized planes agree"
    frames[2:] = [replace(f, lidar=None, reason=ambiguous) for f in frames[2:]]
    why = f"{CONSENSUS_FAILED} board candidates agree on (no three frames span 3D)"
    with pytest.raises(DegenerateLayoutError, match="joint choice of their boards failed"):
        solve(frames, rig.board, rig.camera, warnings=[why])
    with pytest.raises(DegenerateLayoutError) as plain:
        solve(frames, rig.board, rig.camera)
    assert "joint choice" not in plain.value.message


@pytest.mark.parametrize("lidar, stand, crop_m", [("hdl64e", "uprights", None), ("spin2d", "uprights", 0.3),
                                                  ("vlp16", "tripod", None)])
def test_a_board_of_unknown_size_on_a_stand(tmp_path, lidar, stand, crop_m):
    """A board on an aluminium stand (two uprights 2 cm beside its ends, 6 cm behind it, from the ground to above
    it, on feet) or a tripod, dataset.yaml without the board's size: every frame is used, and each recorded LiDAR
    plane holds the true plane within its 99.9% region (the truth's chi-square under the plane's own information,
    3 dof: 16.27; over the 8 planes within the 99.9% point of 24 dof, 51.2): the stand's returns are trimmed by
    the pattern's extent and margin and the robust fit, without tilting the plane. On an HDL-64E-like LiDAR, a
    spinning 2D laser's dense sweep cropped to a box 0.3 m around the boards, and a VLP-16."""
    import re
    from dataclasses import replace

    from estimators.simulation.simulator import cropped_to_boards, write_dataset

    rng = np.random.default_rng(4)
    rig = replace(default_rig(rng, lidar, 0.02), stand=stand)
    frames = simulate_frames(rig, 8, rng)
    if crop_m is not None:
        frames = cropped_to_boards(frames, crop_m)
    path = write_dataset(tmp_path / "stand", rig, frames)
    yaml = path / "dataset.yaml"
    yaml.write_text(re.sub(r"  size: \[.*\]\n", "", yaml.read_text()))
    result = calibrate_pair(path, samples=0)
    assert result.frames_used == 8
    assert any("board.size is not given" in w for w in result.warnings)
    total = 0.0
    for f, truth in zip(result.frames, frames):
        true = Plane(np.array([0.0, 0.0, 1.0]), 0.0).transformed(T_inverse(rig.T_camera_lidar) @ truth.T_camera_board)
        M = f.lidar.unbiased_range_moment(0.02) / 0.02**2
        pi_true = true.coefficients * np.sign(true.normal @ f.lidar.plane.normal)
        chi2 = float(pi_true @ M @ pi_true - f.lidar.plane.coefficients @ M @ f.lidar.plane.coefficients)
        assert chi2 < 16.27, (f.name, chi2)
        total += chi2
    assert total < 51.2, total


def test_the_border_of_a_board_of_unknown_size_stops_where_its_points_leave_the_plane():
    """A 0.9 x 0.7 m pattern on a board with a 5 cm white border (2 cm range noise, points every 1.5 cm): the
    border is kept on all four sides (at least 97% of the board's points); an upright 4 cm wide, 2 cm beside the
    board's right end and 4 cm behind its plane, is cut (at most a tenth of its points kept)."""
    from estimators.lidar.board_segmentation import border_trim

    rng = np.random.default_rng(3)
    x, y = np.meshgrid(np.arange(-0.05, 0.95 + 1e-9, 0.015), np.arange(-0.05, 0.75 + 1e-9, 0.015))
    board = np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)])
    yy = np.arange(-0.05, 0.75, 0.015)
    upright = np.vstack([np.column_stack([np.full(len(yy), 0.97 + dx), yy, np.full(len(yy), 0.04)])
                         for dx in (0.0, 0.015, 0.03)])
    for pts in (board, np.vstack([board, upright])):  # the upright last
        residual = pts[:, 2] + rng.normal(0.0, 0.02, len(pts))
        keep = border_trim(pts[:, :2], residual, (0.9, 0.7), 0.02)
        assert keep[:len(board)].mean() >= 0.97
    assert keep[len(board):].mean() <= 0.1


def test_the_robust_plane_leaves_a_stands_posts_out():
    """A 1 x 1 m board (2 mm noise, 10000 returns) joined by two posts 4 cm wide beside its ends, 2 cm behind its
    plane at its top and 13 cm at its bottom (4400 returns, as a dense laser sees them): the converged robust
    fit keeps at least 99% of the board's returns and none of the posts', and its plane is within 0.05 degree of
    the board's."""
    from estimators.lidar.board_segmentation import robust_plane_fit

    rng = np.random.default_rng(7)
    x, y = np.meshgrid(np.arange(0, 1.0, 0.01), np.arange(0, 1.0, 0.01))
    board = np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)])
    posts = np.array([[x0 + dx, yy, 0.02 + 0.1 * (1.1 - yy)] for x0 in (-0.06, 1.02)
                      for yy in np.arange(0.0, 1.1, 0.002) for dx in (0.0, 0.01, 0.02, 0.03)])
    P = np.vstack([board, posts])
    P[:, 2] += rng.normal(0.0, 0.002, len(P))
    plane, keep = robust_plane_fit(P)
    assert keep[:len(board)].mean() >= 0.99 and not keep[len(board):].any()
    assert np.degrees(np.arccos(abs(plane.normal[2]))) < 0.05


def test_the_choice_gate_widens_with_the_rotation_uncertainty():
    """The closed form's rotation covariance from the boards' normals: for three orthogonal normals each known to
    sigma it is sigma^2 / 2 per axis (each axis seen by two normals); for normals crowded round the optical axis it
    is large about that axis only."""
    from estimators.solvers.association import AssociationParams, _rotation_covariance

    params = AssociationParams()
    s2 = params.sigma_angle_rad**2
    np.testing.assert_allclose(_rotation_covariance(np.eye(3), params), s2 / 2 * np.eye(3), rtol=1e-9)
    tilt = np.deg2rad(2.0)
    crowded = np.array([[np.sin(tilt) * np.cos(a), np.sin(tilt) * np.sin(a), np.cos(tilt)]
                        for a in np.linspace(0, 2 * np.pi, 8, endpoint=False)])
    C = _rotation_covariance(crowded, params)
    assert C[2, 2] > 100 * max(C[0, 0], C[1, 1])


@pytest.mark.parametrize("crop_m", [None, 0.3])
def test_a_small_board_on_a_table_under_a_dense_laser_without_its_size(tmp_path, crop_m):
    """Issue 61: an 18 x 24 cm board (6 x 8 squares of 30 mm) standing on a small plate on an optical table, seen
    by a dense LiDAR with a non-repetitive pattern and no beam index (25-40 thousand returns a sweep, thousands
    on the board), 15 poses, dataset.yaml without board.size; the whole lab in the cloud, or the clouds cropped
    0.3 m around the boards. The static scene keeps the board in front of the table it stands on (direction
    bins, judged along the beams; voxels called it background), nothing says the rig moved, every frame is
    used, no range term is kept, and the truth lies inside the reported 99.9% region (chi-square 6 dof; the
    estimate within a few standard deviations, not 26 degrees and 821 mm as the recording gave)."""
    from estimators.simulation.simulator import cropped_to_boards, write_dataset
    from estimators.simulation.table import declared, simulate_table_frames, table_rig

    rng = np.random.default_rng(3)
    rig = table_rig(rng)
    frames, _ = simulate_table_frames(rig, 15, rng)
    assert all(f.ring is None for f in frames) and all(1000 < f.board_mask.sum() < len(f.points) / 2 for f in frames)
    if crop_m is not None:
        frames = cropped_to_boards(frames, crop_m)
    path = write_dataset(tmp_path / "table", declared(rig), frames)
    result = calibrate_pair(path, samples=0)
    assert not any("contradict the static scene" in w for w in result.warnings), result.warnings
    assert any("board.size is not given" in w for w in result.warnings)
    assert result.frames_used == 15
    # No range error simulated, none kept: a border judged by the returns' noisy positions tilted the small board's
    # planes by up to a degree, which the range-term test read as an offset (8 mm, d2 33 on this dataset).
    assert result.refinement.range_model.chosen == "none", result.refinement.range_model.reason
    xi = T_log(T_inverse(result.T_camera_lidar) @ rig.T_camera_lidar)
    assert xi @ np.linalg.solve(result.covariance, xi) < 22.46


def test_a_small_board_on_a_table_under_a_spinning_lasers_sector_keeps_its_plate_and_table_out(tmp_path):
    """The same table under a dense spinning laser's sector, with its beam index (the stands page's dataset 14):
    the board's size not given, its outline is its pattern's, and the returns just beyond it are its plate and the
    table. Restored there as a known board's edge returns are, they bought per-ring range terms that none had
    (p = 1e-5; 3.3 mm off the truth); left out, no range term is kept and the estimate lies within 2 mm."""
    from estimators import calibrate
    from estimators.simulation.simulator import write_dataset
    from estimators.simulation.table import declared, simulate_table_frames, table_rig

    rng = np.random.default_rng(9714)
    rig = table_rig(rng, lidar="sector")
    frames, _ = simulate_table_frames(rig, 15, rng)
    assert all(f.ring is not None for f in frames)
    result = calibrate(write_dataset(tmp_path / "table", declared(rig), frames), rng=np.random.default_rng(14),
                       posterior=None)
    assert result.range_models.get("lidar0", {}).get("model", "none") == "none", result.range_models
    xi = T_log(T_inverse(result.T_camera_lidar) @ rig.T_camera_lidar)
    assert 1000 * np.linalg.norm(xi[3:]) < 2.0 and xi @ np.linalg.solve(result.covariance, xi) < 22.46
