"""2D LiDAR: choosing among the minimal solutions with three boards (the outline cue and the modes' posterior
mass), ill-conditioned triples solved instead of refused, the multi-start fallback, and the second simulator
configuration (simulated ground truth, fixed seeds)."""
from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from estimators.errors import DegenerateLayoutError
from estimators.simulation.simulator import default_rig_2d, rig_2d, sample_board_poses, varied_rig_2d
from estimators.solvers.minimal_solver import MIN_LINE_SIN, solve_three_boards
from estimators.solvers.observation_model import Layout, simulate_measurements
from estimators.solvers.noise_levels import pooled_range_noise_m
from estimators.solvers.refinement import refine
from estimators.solvers.solution_selection import (MIN_MODE_MASS, SHARED_OPTIMUM_RATIO, _merge_by_joint_optimum,
                                                   laser_costs, marginal_laser_costs, multistart_candidates,
                                                   outline_costs, outline_evidence, refine_candidates,
                                                   select_minimal, solution_distances)
from geometry.lines import fit_line_tls
from geometry.planes import Plane
from geometry.rotations import T_exp, T_inverse, T_log, transform_points


def _frames(config: str, n: int, seed: int, noise: float = 0.01):
    rng = np.random.default_rng(seed)
    rig = rig_2d(config, rng, noise)
    poses = sample_board_poses(rig, n, rng)
    layout = Layout(rig.camera, rig.board, rig.beams, rig.T_camera_lidar, tuple(poses), 0.2, noise)
    return rig, simulate_measurements(layout, rng)


def _truth_basin(rig, frames):
    try:  # twice: the second pass estimates the noise terms at the minimum rather than at the truth
        T = refine(frames, rig.board, rig.camera, rig.T_camera_lidar).T_camera_lidar
        return refine(frames, rig.board, rig.camera, T).T_camera_lidar
    except DegenerateLayoutError:
        return None


def test_outline_cost_is_small_at_the_truth_and_grows_when_the_chord_slides():
    """Noise-free segments: their ends are the last returns inside the outline, so at the true extrinsic
    every end scores near the mode; sliding the LiDAR 10 cm along a board's scan line moves the ends off
    the board's edges and costs far more than chi-square noise."""
    rig, frames = _frames("default", 4, 1, noise=1e-4)
    sigma = pooled_range_noise_m([f.lidar for f in frames])
    T = rig.T_camera_lidar
    at_truth = outline_costs(T[None], frames, rig.board, sigma)[0]
    assert at_truth < 4 * len(frames)  # each of 2N ends within about 1.4 sd of its expected depth
    slid = T @ T_exp(np.array([0, 0, 0, 0.0, 0.10, 0.0]))  # 10 cm along the LiDAR's y (along the scan)
    assert outline_costs(slid[None], frames, rig.board, sigma)[0] > at_truth + 50


@pytest.mark.parametrize("n_boards", [3, 4])
def test_laser_cost_with_uncertain_camera_planes_is_chi_square_at_the_truth(n_boards):
    """At the true extrinsic each board's 2 whitened line residuals, scored against the range noise and the
    camera plane's own covariance, are chi-square(2): over 30 layouts the mean is 2N within 20% (the mean's
    statistical sd is under 10%), where treating the camera planes as exact overstates it. With a zero plane
    covariance the two costs are the same."""
    marginal, exact = [], []
    for seed in range(30):
        rig, frames = _frames("default", n_boards, seed)
        T = rig.T_camera_lidar[None]
        marginal.append(marginal_laser_costs(T, frames, 0.01)[0])
        exact.append(laser_costs(T, frames, 0.01)[0])
    assert abs(np.mean(marginal) / (2 * n_boards) - 1) < 0.2
    assert np.mean(exact) > 1.3 * np.mean(marginal)
    rig, frames = _frames("default", n_boards, 0)
    frames = [replace(f, camera=replace(f.camera, plane_covariance=np.zeros((4, 4)))) for f in frames]
    Ts = np.stack([rig.T_camera_lidar, rig.T_camera_lidar @ T_exp(np.array([0.01, 0, 0, 0, 0.02, 0]))])
    np.testing.assert_allclose(marginal_laser_costs(Ts, frames, 0.01), laser_costs(Ts, frames, 0.01), rtol=1e-9)


def test_minima_sharing_one_joint_optimum_are_weighted_by_their_distance_to_it():
    """Two minima whose joint optima coincide share the better evidence; the one nearer the optimum keeps
    weight 1, the other, ``1 / SHARED_OPTIMUM_RATIO`` times as far, gets 1%. A minimum with its own optimum
    is its own mode with its own evidence."""
    def pose(dx):  # a transform dx metres along x: solution distance 20 * dx
        T = np.eye(4)
        T[0, 3] = dx
        return T
    d_near = 0.2
    optimum = pose(d_near)
    refs = [SimpleNamespace(T_camera_lidar=T) for T in (pose(0.0), pose(d_near + d_near / SHARED_OPTIMUM_RATIO),
                                                         pose(5.0))]
    evidence = np.array([2.0, 1.5, 7.0])
    optima = np.stack([optimum, optimum, pose(5.0)])
    shared, log_w = _merge_by_joint_optimum(evidence, optima, refs)
    np.testing.assert_allclose(shared, [1.5, 1.5, 7.0])
    assert log_w[0] == 0.0 and np.exp(log_w[1]) == pytest.approx(0.01, rel=1e-6) and log_w[2] == 0.0


def test_a_minimums_evidence_does_not_depend_on_the_signs_the_eigen_solver_gives(monkeypatch):
    """The evidence search near a minimum draws in its whitened coordinates. An eigendecomposition with some
    eigenvectors' signs flipped is as valid (a last-bit change in the covariance can flip them); the draws must
    not mirror with it, or Powell starts elsewhere and a second mode of the posterior can come or go (varied
    3-board seed 1: a 21% mode). Same least joint cost (1e-9 relative) and same optimum (1e-6) either way."""
    rig, frames = _frames("varied", 3, 1)
    sigma = pooled_range_noise_m([f.lidar for f in frames])
    ref = refine(frames, rig.board, rig.camera, rig.T_camera_lidar)
    best, outline, T_best = outline_evidence(ref, frames, rig.board, sigma)
    eigh = np.linalg.eigh

    def flipped(a):
        w, V = eigh(a)
        return w, V * np.array([-1.0, 1.0, -1.0, -1.0, 1.0, -1.0])

    monkeypatch.setattr(np.linalg, "eigh", flipped)
    best_f, outline_f, T_best_f = outline_evidence(ref, frames, rig.board, sigma)
    assert best_f == pytest.approx(best, rel=1e-9) and outline_f == pytest.approx(outline, rel=1e-6, abs=1e-9)
    np.testing.assert_allclose(T_best_f, T_best, atol=1e-6)


def test_three_boards_choose_the_true_root_and_are_honest_when_they_cannot():
    """Over 6 three-board layouts (default rig, 1 cm), the most probable mode is the true one in at least 5;
    every run reported unambiguous is a hit, and the modes' masses sum to at most 1. (The sweep, 100 layouts
    of each rig with the share answered and the regions' coverage, is ``make bench``'s 2D honesty pages.)"""
    hits = clear_hits = clear = trials = 0
    for seed in range(40):
        rig, frames = _frames("default", 3, seed)
        basin = _truth_basin(rig, frames)
        if basin is None:
            continue
        sel = select_minimal(frames, rig.board)
        ref, modes = refine_candidates(frames, rig.board, rig.camera, sel)
        assert modes[0].refinement is ref and all(m.mass >= MIN_MODE_MASS for m in modes)
        assert sum(m.mass for m in modes) <= 1 + 1e-9
        hit = solution_distances(np.array([ref.T_camera_lidar, basin]))[0] < 0.05
        trials += 1
        hits += hit
        if len(modes) == 1:
            clear += 1
            clear_hits += hit
        if trials == 6:
            break
    assert trials == 6
    assert hits >= 5 and clear_hits == clear and clear >= 4, (hits, clear_hits, clear)


def test_nearly_parallel_laser_lines_are_solved_and_reported_as_weak():
    """Two boards turned alike give laser lines 1.5 degrees apart: the triple used to be refused; it is now
    solved (the true extrinsic among its roots) and flagged weak."""
    rng = np.random.default_rng(0)
    rig = default_rig_2d(rng)
    T = rig.T_camera_lidar
    T_lc = T_inverse(T)
    planes = [Plane([0.0, 0.45, 1.0], 3.0), Plane([0.026, 0.45, 1.0], 3.6), Plane([0.6, -0.3, 1.0], 3.2)]
    lines = []
    for p in planes:
        q = p.transformed(T_lc)  # the board plane in the LiDAR frame; its cut by z = 0
        n2 = q.normal[:2]
        foot = n2 * q.distance / (n2 @ n2)
        d = np.array([-n2[1], n2[0]])
        lines.append(fit_line_tls(foot + np.outer(np.linspace(-0.4, 0.4, 20), d / np.linalg.norm(d))))
    res = solve_three_boards(planes, lines)
    assert res.degenerate is None and res.weak is not None and "nearly parallel" in res.weak
    u, v = lines[0].direction, lines[1].direction
    assert abs(u[0] * v[1] - u[1] * v[0]) < MIN_LINE_SIN
    assert min(solution_distances(np.array([S, T]))[0] for S in res.T_camera_lidar) < 1e-3


def test_multistart_search_finds_the_true_basin_without_the_minimal_solver():
    """The fallback for layouts where no triple solves: from the camera's planes alone, one of its candidates
    refines into the basin that refinement from the truth reaches (4 and 6 boards)."""
    for n, seed in ((4, 2), (6, 3)):
        rig, frames = _frames("default", n, seed)
        basin = _truth_basin(rig, frames)
        assert basin is not None
        starts = multistart_candidates(frames, pooled_range_noise_m([f.lidar for f in frames]))
        refined = []
        for T0 in starts:
            try:  # a start in a wrong basin can refine to a degenerate minimum, which the pipeline skips too
                refined.append(refine(frames, rig.board, rig.camera, T0).T_camera_lidar)
            except DegenerateLayoutError:
                continue
        assert min(solution_distances(np.array([T, basin]))[0] for T in refined) < 0.05


def test_the_polish_leaves_settled_starts_and_ends_where_iterating_every_start_ends(monkeypatch):
    """``_polish`` stops iterating a start whose cost has stopped falling: from 512 rotations spread over SO(3) on
    4 boards, every start ends at the cost (within 1e-7 of it) and the transform (1e-5) that iterating every start
    60 times reaches, with under 70% of the residual evaluations."""
    from estimators.solvers import solution_selection as sel

    rig, frames = _frames("default", 4, 2)
    sigma = pooled_range_noise_m([f.lidar for f in frames])
    starts = np.tile(rig.T_camera_lidar, (512, 1, 1))
    starts[:, :3, :3] = Rotation.from_quat(sel._quasi_uniform_quaternions(512)).as_matrix()
    rows = []

    def residuals(Ts):
        rows.append(len(Ts))
        return sel.laser_residuals(Ts, frames, sigma)

    T_settled, c_settled = sel._polish(starts, residuals)
    settled_rows, rows[:] = sum(rows), []
    monkeypatch.setattr(sel, "POLISH_SETTLED_AFTER", 10**9)
    T_every, c_every = sel._polish(starts, residuals)
    assert sum(rows) == 512 * (1 + 60 * 7) and settled_rows < 0.7 * sum(rows)
    assert np.all(np.abs(c_settled - c_every) <= 1e-7 * c_every)
    assert np.max(np.abs(T_settled - T_every)) < 1e-5


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_second_simulator_configuration_calibrates_with_five_boards(seed):
    """The independent rig family (tilted scan plane, other boards, cameras, steps and ranges): 5 boards at
    1 cm reach the true basin unambiguously (the truth's minimum's basin: within the selection's own distance
    for one minimum, as the segment ends' likelihood, which lets an end far inside the outline be a hidden
    one, can leave two minima under a standard deviation apart there), with the truth in the reported 99.9%
    region."""
    rig, frames = _frames("varied", 5, seed)
    basin = _truth_basin(rig, frames)
    assert basin is not None
    ref, modes = refine_candidates(frames, rig.board, rig.camera, select_minimal(frames, rig.board))
    assert len(modes) == 1
    assert solution_distances(np.array([ref.T_camera_lidar, basin]))[0] < 1.0
    xi = T_log(T_inverse(ref.T_camera_lidar) @ rig.T_camera_lidar)
    assert xi @ np.linalg.solve(ref.covariance, xi) < 22.458  # chi-square, 6 dof, 99.9%


def test_varied_rigs_differ_from_the_default_in_what_they_assume():
    rigs = [varied_rig_2d(np.random.default_rng(s), None) for s in range(30)]
    widths = [r.board.extent[0] for r in rigs]
    steps = {round(float(np.degrees(r.beams.azimuth_step_rad)), 2) for r in rigs}
    # The scan plane's normal (LiDAR z) against the camera's down axis: tilted, not just level.
    tilts = [np.degrees(np.arccos(abs(r.T_camera_lidar[1, 2]))) for r in rigs]
    assert min(widths) < 0.7 and max(widths) > 1.3 and steps == {0.25, 0.5}
    assert max(tilts) > 8.0 and min(r.min_distance_m for r in rigs) == 0.5
    assert {r.camera.width for r in rigs} == {1024, 1280}
    # Points of a board at its pose are where the simulator puts them: the layout is self-consistent.
    rig = rigs[0]
    pose = sample_board_poses(rig, 1, np.random.default_rng(0))[0]
    corners = transform_points(pose, rig.board.outline())
    assert np.all(corners[:, 2] > 0)


def test_a_rendered_dataset_of_the_varied_configuration_calibrates_end_to_end(tmp_path):
    """``simulate --lidar 2d --rig varied`` (rendered images of a board of another size on a rig drawn from the
    second configuration): the pipeline finds the boards and lands within its own 99.9% region of the truth;
    the choice of rig is recorded in ground_truth.json."""
    from scipy.stats import chi2

    from estimators.calibration import calibrate_pair
    from estimators.io.dataset import load_dataset
    from estimators.simulation.simulator import simulate_dataset
    from geometry.rotations import T_log

    path = simulate_dataset(tmp_path / "varied", n_poses=5, seed=3, lidar="2d", rig_config="varied")
    ds = load_dataset(path)
    result = calibrate_pair(ds, posterior=None)
    assert result.frames_used >= 4 and len(result.modes) == 1
    xi = T_log(T_inverse(result.T_camera_lidar) @ ds.ground_truth())
    assert xi @ np.linalg.solve(result.covariance, xi) < chi2.ppf(0.999, 6)
    assert '"rig": "varied"' in (path / "ground_truth.json").read_text()
    out = result.to_dict()
    assert not out["ambiguous"] and len(out["modes"]) == 1 and out["modes"][0]["posterior_mass"] >= 1 - MIN_MODE_MASS


def test_the_varied_rig_is_refused_where_it_does_not_apply(tmp_path):
    from estimators.analysis.study import parse_spec
    from estimators.errors import DatasetError
    from estimators.simulation.simulator import simulate_dataset

    with pytest.raises(DatasetError, match="rig must be default or varied"):
        parse_spec({"lidar": "3d", "rig": "varied"})
    assert parse_spec({"lidar": "2d", "rig": "varied", "solvers": ["minimal-lower-bound"]}).rig == "varied"
    with pytest.raises(ValueError, match="rig_config"):
        simulate_dataset(tmp_path / "x", n_poses=3, lidar="hdl64e", rig_config="varied")


def _tilted(obs, angle_rad: float, board):
    """The observation of the board turned by ``angle_rad`` about its own x axis through its centre: the other
    tilt of an ambiguous board (the same covariances)."""
    from estimators.camera.board_pose import plane_jacobian

    c = board.centre
    T = obs.T_camera_board @ T_exp(np.array([angle_rad, 0, 0, 0, 0, 0]))
    T[:3, 3] += obs.T_camera_board[:3, :3] @ c - T[:3, :3] @ c  # the centre stays where it was
    n = T[:3, 2]
    Jp = plane_jacobian(T)
    return replace(obs, T_camera_board=T, plane=Plane(n, n @ T[:3, 3]),
                   plane_covariance=Jp @ obs.pose_covariance @ Jp.T)


def test_boards_ambiguous_in_their_tilt_are_decided_by_the_laser_when_the_rest_cannot_be_solved():
    """Two usable boards and one whose corners fit two tilts alike (the true tilt listed second, the other 35 degrees
    off and preferred by its corners), calibrated as ``calibrate`` does (the engine, from the measured frames): both
    tilts are solved before the two boards alone, and the one the laser line agrees with is used: the true tilt,
    the camera's board pose in the joint graph, an answer at the truth's basin (the engine had left such boards out
    of its start, and refused two 3-board layouts its bound says are solvable). When the board's two tilts are the
    same plane (nothing to decide by), the two usable boards alone fit two poses, and the calibration is refused
    with why."""
    from estimators.io.measurement_store import Measurements
    from estimators.rig_calibration import calibrate
    from estimators.solvers.solution_selection import select_and_refine

    rig, frames = _frames("default", 3, 5)
    truth = _truth_basin(rig, frames)
    assert truth is not None and all(f.usable for f in frames)
    amb = list(frames)
    alts = (replace(_tilted(frames[2].camera, np.radians(35), rig.board), orientation_excess_chi2=0.0),
            replace(frames[2].camera, orientation_excess_chi2=3.0))
    amb[2] = replace(frames[2], camera=None, reason="board pose: ambiguous", camera_alternatives=alts)
    res = calibrate(Measurements(rig.camera, rig.board, "2d", tuple(amb)), rng=np.random.default_rng(0), samples=0)
    used = res.pair_results[("cam0", "lidar0")].frames
    assert used[2].camera is alts[1]
    assert "0002" in res.frames_used["cam0"] and not res.skipped.get("cam0")
    assert solution_distances(np.array([res.only_pair().T, truth]))[0] < 0.05
    notes = [w for w in res.warnings if "the tilt the laser line agrees with is used" in w]
    assert len(notes) == 1 and res.verdict.level == "OK", res.verdict.line
    same = list(amb)
    same[2] = replace(amb[2], camera_alternatives=(alts[1],) * 2)
    with pytest.raises(DegenerateLayoutError, match="do not decide it either"):
        select_and_refine(same, rig.board, rig.camera)


def test_roots_that_cannot_be_the_rig_are_not_solutions():
    """``physical``: the truth passes; the same rotation with the LiDAR 2 m from the camera fails the default 1 m
    bound (and passes with none); the LiDAR moved through a board's plane to its far side fails; a root that puts
    the segments behind the camera (turned half round about the camera's vertical) fails. ``select_minimal``
    keeps only roots within the bound: all of them, and the truth's, within 0.5 m of the camera for the default
    rig (its LiDAR about 0.11 m away), none within 1 cm, where it refuses naming the bound."""
    from estimators.solvers.solution_selection import physical

    rig, frames = _frames("default", 4, 3)
    T = rig.T_camera_lidar
    far = T.copy()
    far[:3, 3] *= 2.0 / np.linalg.norm(T[:3, 3])
    f0 = frames[0].camera.T_camera_board
    n, d = f0[:3, 2], f0[:3, 2] @ f0[:3, 3]
    through = T.copy()
    through[:3, 3] += (d - n @ T[:3, 3] + 0.5) * n  # 0.5 m beyond the board's plane
    turned = T.copy()
    turned[:3, :3] = np.diag([-1.0, 1.0, -1.0]) @ T[:3, :3]
    Ts = np.array([T, far, through, turned])
    np.testing.assert_array_equal(physical(Ts, frames, 1.0), [True, False, False, False])
    assert physical(far, frames, None)[0]
    sel = select_minimal(frames, rig.board, max_separation_m=0.5)
    assert sel.candidates and sel.max_separation_m == 0.5
    assert all(np.linalg.norm(c.T_camera_lidar[:3, 3]) <= 0.5 for c in sel.candidates + sel.reserve)
    assert sel.n_unphysical > 0  # the minimal solver's other roots
    with pytest.raises(DegenerateLayoutError, match="0.01 m"):
        select_minimal(frames, rig.board, max_separation_m=0.01)


def test_two_boards_of_known_size_are_solved_by_their_segment_ends_when_unambiguous():
    """Two scan segments and their four ends on the edges of a board of known size: 8 constraints on the 6
    unknowns. Default rig, seed 5: answered at the truth's basin, the truth inside the Laplace 99.9% region
    (d2 6.3 when written). Seed 1: two poses fit and the data do not decide between them: refused, saying so.
    A board of unknown size: no segment-end constraint, so two boards are refused as before."""
    from estimators.solvers.solution_selection import select_and_refine

    rig, frames = _frames("default", 2, 5)
    assert all(f.usable for f in frames)
    truth = _truth_basin(rig, frames)
    used, sel, ref, modes, notes = select_and_refine(frames, rig.board, rig.camera)
    assert sel.fallback and sel.n_triples == 0 and len(modes) == 1
    assert solution_distances(np.array([ref.T_camera_lidar, truth]))[0] < 0.05
    xi = T_log(T_inverse(ref.T_camera_lidar) @ rig.T_camera_lidar)
    assert xi @ np.linalg.solve(ref.covariance, xi) < 22.46
    rig1, frames1 = _frames("default", 2, 1)
    with pytest.raises(DegenerateLayoutError, match="with 2 boards, 2 distinct poses fit"):
        select_and_refine(frames1, rig1.board, rig1.camera)
    with pytest.raises(DegenerateLayoutError, match="needs at least 3 boards .2 with the board's size"):
        select_and_refine(frames, replace(rig.board, size=None), rig.camera)


def test_a_folders_board_ambiguous_in_its_tilt_is_measured_for_the_scanners_pair(tmp_path, monkeypatch):
    """A 2D pair folder whose third board's corners fit two tilts alike (the camera's board pose made ambiguous
    here): the engine's measurement skips it for the camera, with its reason, yet gives the scanner's pair that
    frame, its LiDAR segment and both tilts, for the laser to decide (the frame was dropped before it reached the
    pair; with two boards left a 3-board folder was refused)."""
    import estimators.pipeline.measurement as pair_measurement
    import estimators.pipeline.rig_measurement as rig_measurement
    from estimators.errors import AmbiguousOrientationError
    from estimators.io.rig_dataset import load_rig
    from estimators.simulation.simulator import simulate_dataset

    rig = load_rig(simulate_dataset(tmp_path / "ds", n_poses=3, seed=1, lidar="2d"))
    real = rig_measurement.estimate_board_pose
    posed: list = []

    def ambiguous_third(det, board, camera):
        obs = real(det, board, camera)
        posed.append(obs.T_camera_board[:3, 3])
        if len(posed) >= 3 and np.allclose(posed[-1], posed[2]):  # the third board, whenever it is posed
            raise AmbiguousOrientationError("the board's orientation is ambiguous", (
                replace(obs, orientation_excess_chi2=0.0),
                replace(_tilted(obs, np.radians(35), board), orientation_excess_chi2=3.0)))
        return obs

    monkeypatch.setattr(rig_measurement, "estimate_board_pose", ambiguous_third)
    monkeypatch.setattr(pair_measurement, "estimate_board_pose", ambiguous_third)
    measured = rig_measurement.measure_rig(rig, np.random.default_rng(0), workers=1)
    assert list(measured.poses["cam0"]) == ["0000", "0001"] and "ambiguous" in measured.skipped["cam0"]["0002"]
    third = measured.pairs[("cam0", "lidar0")][2]
    assert third.name == "0002" and third.camera is None and third.lidar is not None
    assert len(third.camera_alternatives) == 2
