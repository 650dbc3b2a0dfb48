"""Whole rigs in one graph (io.rig_dataset, solvers.rig_graph, rig_calibration): the folder format and its errors,
the rig corner factor's Jacobians, the pair transforms' covariance, a change of reference, an unconnected sensor,
a simulated rig of three cameras, two 3D LiDARs and a 2D scanner against its ground truth, and the rig's
posterior."""
import json
import re
import subprocess
import sys

import gtsam
import numpy as np
import pytest

from estimators.errors import DatasetError, DegenerateLayoutError, LidarcamError
from estimators.io.rig_dataset import is_rig, load_rig
from estimators.pipeline.rig_measurement import pattern_flip
from estimators.solvers.refinement_options import CORNER_ERROR_CORRELATION, RefinementOptions
from estimators.pipeline.rig_result import range_model_words
from estimators.rig_calibration import calibrate_rig
from estimators.simulation.range_bias import RangeBias
from estimators.simulation.rig_simulator import simulate_rig
from estimators.simulation.simulator import default_board, default_camera
from estimators.solvers.factors import corner_residuals
from estimators.solvers.noise_levels import (BOARD_NOISE_PRIOR_DOF, board_corner_residuals_px, corner_residual_px,
                                             pooled_corner_residual_px)
from estimators.solvers.factor_graph import build_graph, graph_values, rig_corner_factor
from estimators.solvers.rig_graph import (change_reference, graph_reference, pair_transform, redundancy, rig_bound,
                                         spanning_tree)
from estimators.solvers.rig_posterior import RigLikelihood, hold_terms, sample_rig_posterior
from geometry.rotations import T_exp, T_log


@pytest.fixture(scope="module")
def rig_folder(tmp_path_factory):
    from .conftest import shared_folder

    return shared_folder(tmp_path_factory, "rig_3_cameras_2_lidars_1_scanner", lambda path: simulate_rig(
        path, n_poses=10, seed=2, cameras=3, lidars=2, scanners=1))


@pytest.fixture(scope="module")
def rig_result(rig_folder):
    # The boards' planes alone (the scanner's segment ends, in by default, are tested with every LiDAR's edges).
    return calibrate_rig(load_rig(rig_folder), np.random.default_rng(0), edges=False)


def _truth(folder, a, b):
    gt = json.loads((folder / "ground_truth.json").read_text())
    return np.linalg.inv(np.array(gt[f"T_cam0_{a}"])) @ np.array(gt[f"T_cam0_{b}"])


def test_the_rig_folder_lists_each_sensors_files_and_a_missing_file_means_not_seen(rig_folder):
    rig = load_rig(rig_folder)
    assert is_rig(rig_folder)
    assert [s.name for s in rig.sensors] == ["cam0", "cam1", "cam2", "lidar0", "lidar1", "scan0"] \
        and rig.reference == "cam0" and rig.sensor("scan0").lidar == "2d"
    seen = json.loads((rig_folder / "ground_truth.json").read_text())["frames_seen"]
    for s in rig.cameras:
        assert list(s.stems) == seen[s.name]
    # cam2 sees fewer frames than cam0: its pair with the LiDAR covers only those
    assert len(rig.sensor("cam2").stems) < 10
    assert len(rig.pair("cam2", "lidar0").frames) == len(rig.sensor("cam2").stems)


@pytest.mark.parametrize("edit, message", [
    (lambda y: y.replace("reference: cam0", "reference: cam9"), "reference 'cam9' is not a sensor"),
    (lambda y: y.replace("name: cam1", "name: cam0"), "two sensors are named 'cam0'"),
    (lambda y: y.replace("name: cam2\n  type: camera", "name: cam2\n  type: radar"), "has type 'radar'"),
    (lambda y: y.replace("name: cam2", "name: cam7"), "sensor folder cam7/ not found"),
])
def test_a_bad_rig_entry_is_a_one_line_error_naming_it(rig_folder, tmp_path, edit, message):
    import shutil

    folder = tmp_path / "rig"
    shutil.copytree(rig_folder, folder)
    ypath = folder / "dataset.yaml"
    ypath.write_text(edit(ypath.read_text()))
    with pytest.raises(DatasetError, match=message.replace("(", r"\(").replace(")", r"\)")):
        load_rig(folder)


def test_a_cameras_images_numbered_a_frame_off_the_others_are_refused_naming_the_shift(rig_folder, tmp_path, capsys):
    # cam1's image of each frame written as the frame before's: its boards and cam0's agree on no relative pose
    # (it read UNTRUSTED, blaming cam1's scale and intrinsics); paired a frame apart, they agree: refused naming one
    # such pair.
    import shutil

    from estimators.cli import main

    folder = tmp_path / "shifted"
    shutil.copytree(rig_folder, folder)
    images = sorted((rig_folder / "cam1").glob("*.png"))
    for p in (folder / "cam1").glob("*.png"):
        p.unlink()
    stems = sorted(p.stem for p in (rig_folder / "cam0").glob("*.png"))
    for k, stem in enumerate(stems[:-1]):
        source = rig_folder / "cam1" / f"{stems[k + 1]}.png"
        if source in images:
            shutil.copy(source, folder / "cam1" / f"{stem}.png")
    assert main(["calibrate", str(folder), "--out", str(tmp_path / "out"), "--samples", "0", "--no-report"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and not (tmp_path / "out").exists(), err
    assert "cam0's and cam1's boards agree on no one relative pose as the images are numbered" in err, err
    assert "with cam1's a frame earlier (cam0/" in err and "one camera's images are numbered a frame off" in err, err


def test_the_rig_corner_factors_jacobians_match_finite_differences():
    cam, board = default_camera(), default_board()
    X = board.inner_corners()
    T_rs = T_exp(np.array([0.05, -0.1, 0.02, 0.2, 0.01, -0.03]))
    T_rb = T_exp(np.array([0.1, 0.2, -0.05, -0.3, 0.1, 3.0]))
    T_sb = np.linalg.inv(T_rs) @ T_rb
    px = cam.project(X @ T_sb[:3, :3].T + T_sb[:3, 3]) + 0.3
    f = rig_corner_factor(1, 2, X, px, cam, gtsam.noiseModel.Unit.Create(px.size))
    values = gtsam.Values()
    values.insert(1, gtsam.Pose3(T_rs))
    values.insert(2, gtsam.Pose3(T_rb))
    A, _ = f.linearize(values).jacobian()
    h, N = 1e-6, np.zeros_like(A)
    for k in range(12):
        d = np.zeros(6)
        d[k % 6] = h
        for sign in (1, -1):
            v = gtsam.Values()
            v.insert(1, gtsam.Pose3(T_rs @ T_exp(sign * d) if k < 6 else T_rs))
            v.insert(2, gtsam.Pose3(T_rb @ T_exp(sign * d) if k >= 6 else T_rb))
            N[:, k] += sign * f.unwhitenedError(v) / (2 * h)
    np.testing.assert_allclose(A, N, atol=1e-6 * np.abs(N).max())


def test_pair_transforms_and_a_change_of_reference_carry_the_covariance_to_first_order():
    # Monte Carlo over the joint tangent of two poses against the first-order covariances (small spread: 1e-3).
    rng = np.random.default_rng(5)
    Ta, Tb = T_exp(np.array([0.3, -0.2, 0.1, 0.5, -0.2, 0.1])), T_exp(np.array([-0.1, 0.4, 0.2, -0.3, 0.8, 0.2]))
    L = rng.normal(size=(12, 12)) * 1e-3
    cov = L @ L.T
    T_ab, C = pair_transform(Ta, Tb, cov)
    xs = rng.multivariate_normal(np.zeros(12), cov, 4000)
    d = np.array([T_log(np.linalg.inv(T_ab) @ np.linalg.inv(Ta @ T_exp(x[:6])) @ Tb @ T_exp(x[6:])) for x in xs])
    np.testing.assert_allclose(np.cov(d.T), C, atol=0.08 * np.abs(C).max())
    T_new, C_new = change_reference(("a", "b"), {"a": Ta, "b": Tb}, cov, "a")
    np.testing.assert_allclose(T_new["b"], T_ab, atol=1e-12)
    np.testing.assert_allclose(C_new[6:, 6:], C, atol=1e-15)
    assert np.all(C_new[:6] == 0) and np.all(C_new[:, :6] == 0)


def test_a_sensor_with_no_path_to_the_reference_is_an_error_that_names_it():
    names = ("cam0", "cam1", "lidar0")
    with pytest.raises(DegenerateLayoutError, match="cam1"):
        spanning_tree(names, "cam0", {("cam0", "lidar0"): 10, ("cam0", "cam1"): 0, ("cam1", "lidar0"): 0})
    parent = spanning_tree(names, "cam0", {("cam0", "lidar0"): 10, ("cam0", "cam1"): 2, ("cam1", "lidar0"): 8})
    assert parent == {"cam0": None, "lidar0": "cam0", "cam1": "lidar0"}  # the links sharing the most frames


def test_a_symmetric_checkerboards_numbering_flip_maps_corners_onto_reversed_corners():
    board = default_board()  # 9 x 7 squares: the pattern looks the same turned by 180 degrees
    flip = pattern_flip(board)
    X = board.inner_corners()
    np.testing.assert_allclose((X @ flip[:3, :3].T + flip[:3, 3])[::-1], X, atol=1e-12)


def test_a_simulated_rig_against_its_ground_truth(rig_folder, rig_result):
    # Three cameras (two see only some frames), an HDL-64E-like and a VLP-16-like LiDAR and a 2D scanner, 10 frames:
    # every pair within 0.2 deg and 10 mm of the truth (the VLP-16's standard deviations are 2-3 mm) and its d2
    # under its covariance below the chi-square's 99.9% point (22.5 on 6 dof); loops close exactly; the joint graph
    # is at least as sure as each camera-LiDAR pair alone.
    sol = rig_result.solution
    for a, b in rig_result.pairs():
        T, C = sol.transform(a, b)
        xi = T_log(np.linalg.inv(T) @ _truth(rig_folder, a, b))
        assert np.degrees(np.linalg.norm(xi[:3])) < 0.2 and 1000 * np.linalg.norm(xi[3:]) < 10.0, (a, b, xi)
        assert xi @ np.linalg.solve(C, xi) < 22.5, (a, b)
    T01, _ = sol.transform("cam0", "cam1")
    T1l, _ = sol.transform("cam1", "lidar0")
    T0l, _ = sol.transform("cam0", "lidar0")
    np.testing.assert_allclose(T01 @ T1l, T0l, atol=1e-12)
    for (c, lidar), (_, C_pair, _) in rig_result.pairwise.items():
        _, C = sol.transform(c, lidar)
        assert np.trace(C[3:, 3:]) <= 1.05 * np.trace(C_pair[3:, 3:]), c


def test_the_pooled_corner_residual_is_the_per_axis_pixel_noise():
    # 40 boards' exact projections with 0.3 px of noise on each axis, at their true poses: the pooled residual
    # (2M - 6 dof per board) is 0.3 * sqrt(2M / (2M - 6)) within 3% (2M ~ 5000 residuals: sd about 1%).
    rng = np.random.default_rng(3)
    camera, board = default_camera(), default_board()
    X = board.inner_corners()
    views = []
    for _ in range(40):
        T = np.eye(4)
        T[:3, :3] = T_exp(np.r_[rng.uniform(-0.3, 0.3, 3), 0, 0, 0])[:3, :3]
        T[:3, 3] = [rng.uniform(-0.8, -0.2), rng.uniform(-0.6, 0.0), rng.uniform(2.5, 4.0)]
        uv = camera.project(X @ T[:3, :3].T + T[:3, 3])
        views.append((T, X, uv + rng.normal(0.0, 0.3, uv.shape)))
    m2 = 2 * len(X)
    assert pooled_corner_residual_px(views, camera) == pytest.approx(0.3 * np.sqrt(m2 / (m2 - 6)), rel=0.03)


def test_each_cameras_corner_noise_is_the_single_pairs_pooled_and_each_boards_own(rig_result):
    # A camera's pooled corner noise is the pooled per-axis residual the pair's refinement computes for the same
    # frames (it once pooled the per-corner 2D norm, sqrt(2) too large), times the rig's factor; each board's is
    # that board's own residual (2M - 6 dof) shrunk towards the pooled one by BOARD_NOISE_PRIOR_DOF. The frames:
    # a camera's with lidar0, every one of which it saw.
    for cv in rig_result.camera_views:
        frames = [f for f in rig_result.pair_frames[(cv.name, "lidar0")] if f.camera is not None]
        if {f.name for f in frames} != set(cv.corners_px):
            continue
        pooled = corner_residual_px(frames, rig_result.rig.board, cv.camera)
        assert cv.sigma_px == pytest.approx(pooled * CORNER_ERROR_CORRELATION, rel=1e-9), cv.name
        for f in frames:
            r, _ = corner_residuals(f.camera.T_camera_board, f.camera.corners_board(rig_result.rig.board),
                                    f.camera.corners_px, cv.camera, jacobian=False)
            own = (r @ r + BOARD_NOISE_PRIOR_DOF * pooled**2) / (r.size - 6 + BOARD_NOISE_PRIOR_DOF)
            assert cv.sigma(f.name) == pytest.approx(np.sqrt(own) * CORNER_ERROR_CORRELATION, rel=1e-9), f.name
        break
    else:
        pytest.fail("no camera with all its frames in its pair with lidar0")


def test_each_boards_corner_noise_follows_its_own_residual():
    # Boards whose corners carry 0.1 and 0.4 px of noise (the default board's corners): each board's estimate
    # within 15% of its own noise shrunk towards the pooled one (as 30 more residuals at the pooled noise), the
    # pooled one between them; a board of 4 corners (2 dof) is pulled most of the way to the pooled one.
    camera, X = default_camera(), default_board().inner_corners()
    m2 = 2 * len(X)  # at the true poses the residual has all 2M of its dof
    rng = np.random.default_rng(5)
    views, truth = [], []
    for k in range(12):
        T = np.eye(4)
        T[:3, :3] = T_exp(np.r_[rng.uniform(-0.3, 0.3, 3), 0, 0, 0])[:3, :3]
        T[:3, 3] = [rng.uniform(-0.4, 0.0), rng.uniform(-0.4, 0.0), rng.uniform(2.5, 3.5)]
        sd = 0.1 if k % 2 else 0.4
        uv = camera.project(X @ T[:3, :3].T + T[:3, 3])
        views.append((T, X, uv + rng.normal(0.0, sd, uv.shape)))
        truth.append(sd)
    pooled, own = board_corner_residuals_px(views, camera)
    assert 0.15 < pooled < 0.35
    for sd, est in zip(truth, own):
        assert est == pytest.approx(np.sqrt((m2 * sd**2 + BOARD_NOISE_PRIOR_DOF * pooled**2)
                                            / (m2 - 6 + BOARD_NOISE_PRIOR_DOF)), rel=0.15)
    few = [(T, Xb[:4], uv[:4]) for T, Xb, uv in views[:1]] + views[1:]
    _, own_few = board_corner_residuals_px(few, camera)
    assert abs(own_few[0] - pooled) < 0.5 * abs(0.4 - pooled) + 0.02


def test_the_rigs_bound_is_its_covariance_at_its_estimate_and_near_it_at_the_truth(rig_folder, rig_result):
    # rig_bound is the graph's information inverted at the poses given: at the estimate (with the graph's noise
    # scales) exactly the reported joint covariance; at the truth, 1 cm and 0.2 deg away, every standard
    # deviation within 5% of it.
    sol = rig_result.solution
    views = (list(rig_result.camera_views), list(rig_result.lidar_views))
    C = rig_bound(sol.names, sol.reference, *views, sol.T_ref, sol.T_ref_board, sol.noise_scale)
    np.testing.assert_allclose(C, sol.covariance_joint, rtol=1e-6, atol=1e-15)
    gt = json.loads((rig_folder / "ground_truth.json").read_text())
    truth = {n: np.array(gt[f"T_cam0_{n}"]) for n in sol.names}
    flip = pattern_flip(load_rig(rig_folder).board)
    boards = {}
    for st, B in sol.T_ref_board.items():
        options = [np.array(gt["T_cam0_board"][st])] + ([np.array(gt["T_cam0_board"][st]) @ flip] if flip is not None
                                                         else [])
        boards[st] = min(options, key=lambda T: np.linalg.norm(T_log(np.linalg.inv(B) @ T)))
    Ct = rig_bound(sol.names, sol.reference, *views, truth, boards, sol.noise_scale)
    np.testing.assert_allclose(np.sqrt(np.diag(Ct))[6:], np.sqrt(np.diag(sol.covariance_joint))[6:], rtol=0.05)


def test_each_sensors_share_of_the_unknowns_adds_up_to_them_all(rig_result):
    # The hat matrix's trace is the number of unknowns: the sensors' shares of them (its trace over each one's
    # rows) add up to every free sensor pose and board pose, 6 numbers each, to rounding. A LiDAR's pose is fixed
    # by its own planes alone, so its share is at least its 6; every share is below its residual count.
    from dataclasses import replace

    sol = rig_result.solution
    cameras = list(rig_result.camera_views)
    lidars = [replace(lv, ranged=None, terms=None, edges=None) for lv in rig_result.lidar_views]
    inner = graph_reference(sol.reference, [c.name for c in cameras])
    stems = sorted(sol.T_ref_board)
    owners: list = []
    graph = build_graph(sol.names, cameras, lidars, stems, sol.noise_scale, inner, False, owners)
    assert len(owners) == graph.size() and None not in owners
    shares = redundancy(graph, graph_values(sol.names, inner, stems, sol.T_ref, sol.T_ref_board), owners)
    assert sum(shares.values()) == pytest.approx(6 * (len(sol.names) - 1) + 6 * len(stems), rel=1e-8)
    for lv in lidars:
        residuals = sum(W.shape[0] for st, W in lv.W.items() if st in stems)
        assert 6.0 - 1e-8 <= shares[lv.name] < residuals
    for c in cameras:
        assert 0.0 < shares[c.name] < sum(px.size for px in c.corners_px.values())


def _with_frame(result, cam, lidar, T_camera_board, beams, rng):
    """The rig's views with one more frame, "new", seen by ``cam`` (its corners exact) and ``lidar`` (the beams of
    the model ``beams`` that hit its board at the estimate, with range noise at its level), and the board poses
    with it."""
    from dataclasses import replace

    from estimators.lidar.lidar_models import BEAM_MODELS
    from estimators.measurements import lidar_whitener, observe_lidar_board, observe_lidar_line
    from estimators.solvers.observation_model import Layout, board_hits

    sol, T = result.solution, T_camera_board
    camera, board = result.cameras[cam], result.rig.board
    X = board.inner_corners()
    cams = [replace(v, corners_board={**v.corners_board, "new": X},
                    corners_px={**v.corners_px, "new": camera.project(X @ T[:3, :3].T + T[:3, 3])})
            if v.name == cam else v for v in result.camera_views]
    lv = next(v for v in result.lidar_views if v.name == lidar)
    layout = Layout(camera, board, BEAM_MODELS[beams](lv.sigma_m),
                    sol.transform(cam, lidar)[0], (T,), 1.0, lv.sigma_m)
    d, r = board_hits(layout, 0)
    pts = d * (r + rng.normal(0.0, lv.sigma_m, r.shape))[:, None]
    obs = observe_lidar_line(pts) if lv.scan_line else observe_lidar_board(pts)
    lids = [replace(v, W={**v.W, "new": lidar_whitener(obs, v.sigma_m)}) if v.name == lidar else v
            for v in result.lidar_views]
    return cams, lids, {**sol.T_ref_board, "new": sol.T_ref[cam] @ T}


def test_no_next_pose_where_no_board_pose_is_seen_by_both_is_none_not_an_error():
    # A 2D varied honesty trial raised RuntimeError ("no feasible board pose") out of calibrate: the advice's
    # candidate search found no pose both sensors see. A scan plane 10 m below the camera: no advice (None).
    from estimators.analysis.rig_layout import next_pose_for_pair

    T = np.eye(4)
    T[:3, :3] = [[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]]  # the LiDAR's x forward, as mounted
    T[1, 3] = 10.0
    assert next_pose_for_pair(default_camera(), default_board(), T, np.eye(6) * 1e-4, 0.2, 0.01, "2d",
                              np.random.default_rng(0), candidates=5) is None


def test_the_next_pose_for_the_weakest_pair_predicts_what_the_graph_gets_with_it(rig_result):
    # The pose advised for the weakest pair (here a camera with the 2D scanner), and one for a 3D pair: the pair's
    # largest translation sd after it, predicted from the pair's covariance and the frame's information alone,
    # is what the whole graph's information gives with the frame's measurements added (within 3%), and it is
    # at least 20% lower than before.
    from estimators.analysis.rig_layout import next_pose_for_pair

    sol = rig_result.solution
    nxt = rig_result.next_pose
    assert nxt["pair"] == rig_result.layout()["weakest_pair"] == f"T_{nxt['camera']}_{nxt['lidar']}"
    lv = {v.name: v for v in rig_result.lidar_views}
    cv = {v.name: v for v in rig_result.camera_views}
    other = next_pose_for_pair(rig_result.cameras["cam1"], rig_result.rig.board, *sol.transform("cam1", "lidar1"),
                               cv["cam1"].sigma_px * np.sqrt(sol.noise_scale["cam1"]),
                               lv["lidar1"].sigma_m * np.sqrt(sol.noise_scale["lidar1"]), "vlp16",
                               np.random.default_rng(3), candidates=30)
    assert nxt["lidar"] == "scan0"
    for cam, lidar, beams, found in ((nxt["camera"], "scan0", "2d", nxt), ("cam1", "lidar1", "vlp16", other)):
        cams, lids, boards = _with_frame(rig_result, cam, lidar, np.array(found["T_camera_board"]), beams,
                                         np.random.default_rng(1))
        C = rig_bound(sol.names, sol.reference, cams, lids, sol.T_ref, boards, sol.noise_scale)
        ka, kb = sol.names.index(cam), sol.names.index(lidar)
        idx = np.r_[6 * ka:6 * ka + 6, 6 * kb:6 * kb + 6]
        _, P = pair_transform(sol.T_ref[cam], sol.T_ref[lidar], C[np.ix_(idx, idx)])
        after = 1000 * np.sqrt(np.linalg.eigvalsh(P[3:, 3:])[-1])
        assert after == pytest.approx(found["max_translation_sd_mm_after"], rel=0.03), (cam, lidar)
        assert found["max_translation_sd_mm_after"] < 0.8 * found["max_translation_sd_mm_before"], (cam, lidar)


def test_the_rig_posteriors_curvature_at_the_map_is_the_graphs_information(rig_result):
    # Each frame's board pose integrated out in closed form: at the MAP the log-posterior of the free sensors' poses
    # is flat (its gradient moves the mode by far less than 0.01 sd) and its Hessian (central differences) inverts
    # to the graph's joint covariance (gtsam.Marginals, in the graph's reference camera) within 1%.
    sol = rig_result.solution
    like = RigLikelihood(sol, list(rig_result.camera_views), list(rig_result.lidar_views))
    assert like.inner == "cam0" and like.free == ["cam1", "cam2", "lidar0", "lidar1", "scan0"]
    _assert_curvature_is(like, sol.covariance_joint[6:, 6:])  # cam0 is both references here


def _assert_curvature_is(like, cov, h=1e-4):
    """The log-posterior ``like`` is flat at 0 (its gradient moves the mode by less than 0.01 sd) and its Hessian
    (central differences) inverts to ``cov`` within 1%, every correlation too."""
    n = like.nx  # the poses and terms at the graph's noise (log s = 0: the camera side's scale last)
    E = np.eye(n, like.ndim) * h
    grad = np.array([(like(E[i])[0] - like(-E[i])[0]) / (2 * h) for i in range(n)])
    H = np.empty((n, n))
    for i in range(n):
        for j in range(i, n):
            H[i, j] = H[j, i] = (like(E[i] + E[j])[0] - like(E[i] - E[j])[0] - like(E[j] - E[i])[0]
                                 + like(-E[i] - E[j])[0]) / (4 * h * h)
    C = np.linalg.inv(-H)
    np.testing.assert_allclose(np.sqrt(np.diag(C)), np.sqrt(np.diag(cov)), rtol=0.01)
    d = np.sqrt(np.diag(cov))
    assert np.max(np.abs(C - cov) / np.outer(d, d)) < 0.01
    shift = C @ grad
    assert np.all(np.abs(shift) < 0.01 * np.sqrt(np.diag(cov)))


def test_lidars_without_range_errors_keep_planes_alone(rig_result):
    # No LiDAR of the simulated rig has a range error: each one's first camera-LiDAR pair, whose tests choose its
    # range terms, keeps it on planes alone (every p above 0.001; two 3D LiDARs and the scanner). The 3D LiDARs'
    # per-ring and black-square blocks are tested too (their rings from the scans, the squares placed by geometry:
    # both colours on the boards); the scanner has neither, so only its offset is.
    assert set(rig_result.range_models) == {"lidar0", "lidar1", "scan0"}
    for name, rec in rig_result.range_models.items():
        tested = [t["model"] for t in rec["tests"]]
        assert tested == (["offset"] if name == "scan0" else ["offset", "per-ring", "offset+dark"]), name
        assert rec["model"] == "none" and min(t["p_value"] for t in rec["tests"]) > 1e-3, name
        assert rec["chosen_by"] == f"{rig_result.rig.cameras[0].name}-{name}" and "no range term" in rec["reason"]


def test_each_3d_pair_is_checked_by_its_board_edges_and_a_wrong_board_size_is_caught(rig_folder, rig_result,
                                                                                      tmp_path):
    # Under the joint estimate every 3D camera-LiDAR pair's ring ends sit on the camera's outline: each pair's
    # mean shift under 3 mm and within its 99% limit, no warning. With the board declared 5 cm wider than it is
    # in dataset.yaml, every 3D pair's check finds each x side 25 mm in (within 3 mm) and warns about the size,
    # and no pair's mean shift is warned about (the fit starts from least squares: from zero, ends that all lie
    # inside their sides pull nothing, and a frame's shift ran off by 2 m).
    import shutil

    import yaml

    assert {k for k in rig_result.outline_checks} == {(c, d) for c in ("cam0", "cam1", "cam2")
                                                     for d in ("lidar0", "lidar1")}
    for e in rig_result.outline_checks.values():
        assert np.linalg.norm(e["mean_shift_camera_m"]) < 0.003 and e["mean_shift_p_value"] > 0.01
    assert not any("board edges" in w for w in rig_result.warnings)
    assert "board_edges" in rig_result.to_json()["transforms"]["T_cam1_lidar0"]
    folder = tmp_path / "rig"
    shutil.copytree(rig_folder, folder)
    ypath = folder / "dataset.yaml"
    spec = yaml.safe_load(ypath.read_text())
    spec["board"]["size"] = [1.05, 1.0]
    ypath.write_text(yaml.safe_dump(spec, sort_keys=False))
    res = calibrate_rig(load_rig(folder), np.random.default_rng(0), advise=False, edges=False)
    assert len(res.outline_checks) == 6
    for (cam, lidar), e in res.outline_checks.items():
        assert abs(e["growth_m"][0] + 0.025) < 0.003 and e["mean_shift_p_value"] > 0.01, (cam, lidar)
        assert any(w.startswith(f"{cam}-{lidar}: board edges: the LiDAR sees the board -") and " mm wider" in w
                   for w in res.warnings)
    assert not any("outlines sit" in w for w in res.warnings)


def test_the_board_edges_in_the_rigs_graph(rig_folder, rig_result):
    # --edges: each LiDAR's ring ends (the scanner's segment ends) in the joint graph. Every LiDAR has them (the
    # outlines' growth within 3 mm of 0: the board's size is right), every camera-LiDAR pair's largest translation
    # sd is at most the planes' and the scanner's at least 2% lower, and the truth stays inside each camera-LiDAR
    # pair's 99.9% region (d2 below 22.5). The posterior holds the edges to second order about the estimate: each
    # camera-LiDAR pair's posterior standard deviations within 15% of the graph's. The pairs whose edges are used
    # are not checked by them.
    res = calibrate_rig(load_rig(rig_folder), np.random.default_rng(0), edges=True, samples=300, advise=False)
    assert set(res.edges) == {"lidar0", "lidar1", "scan0"} and not res.outline_checks
    for cam, lidar in (("cam0", "lidar0"), ("cam2", "scan0"), ("cam1", "lidar1")):
        sd_post = np.std(res.posterior.pair_samples(cam, lidar), axis=0, ddof=1)
        np.testing.assert_allclose(sd_post, np.sqrt(np.diag(res.solution.transform(cam, lidar)[1])), rtol=0.15)
    for n, e in res.edges.items():
        assert e["ends"] > 10 and np.all(np.abs(e["growth_m"]) < 0.003), n
    for cam in ("cam0", "cam1", "cam2"):
        for lidar in ("lidar0", "lidar1", "scan0"):
            T, C = res.solution.transform(cam, lidar)
            _, C0 = rig_result.solution.transform(cam, lidar)
            sd, sd0 = (np.sqrt(np.linalg.eigvalsh(c[3:, 3:])[-1]) for c in (C, C0))
            assert sd <= sd0 * (0.98 if lidar == "scan0" else 1.0) + 1e-9, (cam, lidar)
            xi = T_log(np.linalg.inv(T) @ _truth(rig_folder, cam, lidar))
            assert xi @ np.linalg.solve(C, xi) < 22.5, (cam, lidar)
    assert next(r for r in res.to_json()["sensors"] if r["name"] == "scan0")["board_edges"]["used"]
    # each 3D LiDAR's edges gain, as a single pair's: how many times less certain its planes alone leave its pose
    # (these spread boards: a few times; above 10 the verdict would say the answer rests on the edges)
    for n in ("lidar0", "lidar1"):
        gain = res.edges[n]["planes_against_edges"]["edges_gain"]
        assert 1.0 < gain < 10.0 and not any("rests on the boards' edges" in r for r in res.verdict.reasons), (n, gain)


@pytest.fixture(scope="module")
def offset_rig(tmp_path_factory):
    return simulate_rig(tmp_path_factory.mktemp("offset") / "rig", n_poses=10, seed=1, cameras=2,
                        range_offset_m=0.03)


def test_a_lidars_range_offset_is_found_by_its_test_and_estimated_in_the_rig(offset_rig):
    # lidar0's returns all 3 cm long. Without range terms its planes conflict with its ring ends, whose own answer
    # holds the truth: the covariance that holds both answers puts it within d2 16.8 (99% of chi-square 6), and
    # with the planes' answer alone held far outside (d2 above 100). Under auto the likelihood-ratio test includes
    # the offset (p < 0.001) and no other term, its estimate is within 3 sd of 3 cm, and the camera-LiDAR transform
    # is back: the truth's d2 below 16.8 and within 5 mm. The posterior holds the offset at its estimate: its
    # Hessian at the MAP is the graph's information of the poses given the offset (within 1%), and the offset's
    # draws, convolved in, agree with the graph's.
    rig = load_rig(offset_rig)
    truth = _truth(offset_rig, "cam0", "lidar0")
    plain = calibrate_rig(rig, np.random.default_rng(0), range_model="none", advise=False)
    T, C = plain.solution.transform("cam0", "lidar0")
    xi = T_log(np.linalg.inv(T) @ truth)
    own = np.asarray(plain.edges["lidar0"]["planes_against_edges"]["edges_own_offset_tangent"])
    assert plain.range_models == {} and plain.contradicted.startswith("lidar0: ")
    assert xi @ np.linalg.solve(C, xi) < 16.8 < 100 < xi @ np.linalg.solve(C - np.outer(own, own), xi)
    # The planes alone (the likelihood below is the planes'; the edges enter the posterior as a quadratic).
    res = calibrate_rig(rig, np.random.default_rng(0), advise=False, edges=False)
    rec = res.range_models["lidar0"]
    assert rec["model"] == "offset" and rec["tests"][0]["p_value"] < 1e-3 and list(rec["terms"]) == ["offset"]
    assert abs(rec["value_m"] - 0.03) < 3 * rec["sd_m"] and rec["sd_m"] < 0.005
    T, C = res.solution.transform("cam0", "lidar0")
    xi = T_log(np.linalg.inv(T) @ truth)
    assert xi @ np.linalg.solve(C, xi) < 16.8 and 1000 * np.linalg.norm(xi[3:]) < 5.0
    # The boards are judged (verdict, calibration.json's frames) with the offset taken off their returns.
    from estimators.pipeline.verdict import plane_residuals

    frames = [f for f in res.pair_frames[("cam0", "lidar0")] if f.usable]
    off = res.returns_without_terms("cam0", "lidar0", frames)
    raw, judged = (np.median([d for _, d in plane_residuals(T, frames, t).values()]) for t in (None, off))
    assert set(off) == {f.name for f in frames} and raw > 0.02 and abs(judged) < 0.01
    # Held at its estimate (as every posterior holds the terms), the likelihood's curvature is the graph's
    # information of the poses given the offset; the offset's share is convolved into the samples.
    lv = next(v for v in res.lidar_views if v.name == "lidar0")
    like = RigLikelihood(res.solution, list(res.camera_views),
                         [hold_terms(lv, res.solution.range_terms["lidar0"][0])])
    full = res.solution.covariance_inner
    assert like.nx == 12 and like.ndim == 13 and full.shape == (13, 13)
    _assert_curvature_is(like, full[:12, :12] - np.outer(full[:12, 12], full[12, :12]) / full[12, 12])
    with pytest.raises(ValueError, match="hold_terms"):
        RigLikelihood(res.solution, list(res.camera_views), list(res.lidar_views))
    post = sample_rig_posterior(res.solution, list(res.camera_views), list(res.lidar_views),
                                np.random.default_rng(4), min_ess=400)
    o = post.range_terms["lidar0"][:, 0]
    assert abs(o.mean() - rec["value_m"]) < 0.2 * rec["sd_m"] and o.std() == pytest.approx(rec["sd_m"], rel=0.15)
    rows = res.to_json()["sensors"]
    assert next(r for r in rows if r["name"] == "lidar0")["range_model"]["model"] == "offset"
    # the report lists the terms as a single pair's does
    from estimators.analysis.rig_report import range_terms_parts

    page = "".join(range_terms_parts(res))
    assert "lidar0: LiDAR range terms" in page
    assert f"<td>offset</td><td>{1000 * rec['value_m']:+.1f}</td><td>{1000 * rec['sd_m']:.1f}</td>" in page


@pytest.fixture(scope="module")
def ranged_rig(tmp_path_factory):
    return simulate_rig(tmp_path_factory.mktemp("ranged") / "rig", n_poses=10, seed=11, cameras=2,
                        range_bias=(0.03, 0.005, 0.01))


def test_the_simulate_command_injects_range_errors_into_a_rigs_first_lidar(tmp_path):
    # --range-bias with --cameras: lidar0's terms in ground_truth.json (a ring's offset per beam, drawn); the
    # family's priors are for a single pair, a one-line error.
    out = tmp_path / "rig"
    run = subprocess.run([sys.executable, "-m", "estimators", "simulate", "--cameras", "2", "--poses", "3", "--out",
                          str(out), "--range-bias", "0.02", "0.004", "0.01"], capture_output=True, text=True,
                         timeout=600)
    assert run.returncode == 0, run.stderr
    truth = json.loads((out / "ground_truth.json").read_text())["range_bias"]["lidar0"]
    assert truth["offset_m"] == 0.02 and truth["dark_m"] == 0.01 and len(truth["ring_offsets_m"]) == 64
    assert 0.002 < np.std(truth["ring_offsets_m"]) < 0.006
    run = subprocess.run([sys.executable, "-m", "estimators", "simulate", "--cameras", "2", "--poses", "3", "--out",
                          str(tmp_path / "other"), "--range-bias-from-priors", "velodyne"], capture_output=True,
                         text=True, timeout=600)
    assert run.returncode != 0 and "is for a single pair" in run.stderr and not (tmp_path / "other").exists()


def test_a_lidars_per_ring_and_black_square_range_errors_are_chosen_and_estimated_in_the_rig(ranged_rig):
    # lidar0's returns 3 cm long, each ring a further N(0, 5 mm), the black squares' 1 cm longer still (the single
    # pair's injected errors). Under auto every block passes its test (p < 0.001, at the noise scales of the
    # largest model: under the planes' scale, which the errors inflate 30-fold, the rings' test failed), the
    # model is full, the offset and the black squares' term are within 3 sd of the truth and the rings' terms
    # within it on the whole (RMS z below 1.5: their prior, 10 mm, is wider than the 5 mm they were drawn with),
    # and both camera-LiDAR transforms are back: the truth's d2 below 16.8 (99% of chi-square 6). The posterior
    # samples every term: its black squares' term agrees with the graph's. A requested model is fitted untested.
    rig = load_rig(ranged_rig)
    gt = RangeBias.from_record(json.loads((ranged_rig / "ground_truth.json").read_text())["range_bias"]["lidar0"])
    res = calibrate_rig(rig, np.random.default_rng(0), samples=300, advise=False)
    rec = res.range_models["lidar0"]
    assert rec["model"] == "full" and all(t["p_value"] < 1e-3 for t in rec["tests"])
    terms = rec["terms"]
    z = {n: (v["value_m"] - gt.term(n)) / v["sd_m"] for n, v in terms.items()}
    assert abs(z["offset"]) < 3 and abs(z["dark"]) < 3 and terms["dark"]["sd_m"] < 0.001
    rings = np.array([v for n, v in z.items() if n.startswith("ring ")])
    assert rings.size > 30 and np.sqrt(np.mean(rings**2)) < 1.5
    for cam in ("cam0", "cam1"):
        T, C = res.solution.transform(cam, "lidar0")
        xi = T_log(np.linalg.inv(T) @ _truth(ranged_rig, cam, "lidar0"))
        assert xi @ np.linalg.solve(C, xi) < 16.8, cam
    # its points weighed with the scatter the terms leave, as the pair that chose them estimated it (the scatter
    # about each board's plane, which the rig took before, holds the rings and black squares too)
    from estimators.solvers.noise_levels import pooled_range_noise_m

    lv = next(v for v in res.lidar_views if v.name == "lidar0")
    chooser = res.pair_results[("cam0", "lidar0")].refinement
    assert lv.sigma_m == chooser.range_noise_m < 0.99 * pooled_range_noise_m(
        [f.lidar for f in res.pair_frames[("cam0", "lidar0")]])
    # the squares placed under an uncertain estimate: their placement's share widens the black squares' term
    # (and the covariance) beyond the graph's curvature, as a single pair's consider step does
    at = 6 * (len(res.solution.names) - 1)
    for v in res.lidar_views:
        if v.name == "lidar0":
            break
        at += v.terms.size if v.has_terms else 0
    k = at + list(terms).index("dark")
    graph_sd = np.sqrt(res.solution.covariance_inner[k, k])
    assert 1.001 * graph_sd < terms["dark"]["sd_m"] < 1.5 * graph_sd
    dark = res.posterior.range_terms["lidar0"][:, list(terms).index("dark")]
    assert abs(dark.mean() - terms["dark"]["value_m"]) < 0.25 * terms["dark"]["sd_m"]
    assert dark.std() == pytest.approx(terms["dark"]["sd_m"], rel=0.2)
    row = next(r for r in res.to_json()["sensors"] if r["name"] == "lidar0")["range_model"]
    assert len(row["terms"]["dark"]["posterior_95%_m"]) == 2
    words = range_model_words(row)
    assert words.startswith("range offset +") and f"{rings.size} ring offsets" in words and "black squares +" in words
    asked = calibrate_rig(rig, np.random.default_rng(0), range_model="offset+dark", advise=False)
    rec = asked.range_models["lidar0"]
    assert rec["model"] == "offset+dark" and list(rec["terms"]) == ["offset", "dark"] and "tests" not in rec


def test_a_sensor_the_data_barely_determine_is_not_sampled_and_says_why(rig_result):
    # The pair's own sampler refused a Laplace covariance of a direction the data do not determine (over 10 degrees
    # or 0.5 m: a chain started there is degenerate); the engine's does too, before any chain runs, naming the
    # sensor, so the graph's covariance stands and the verdict says so.
    from dataclasses import replace

    from estimators.errors import PosteriorSkippedError

    sol = rig_result.solution
    wide = replace(sol, covariance_inner=None if sol.covariance_inner is None else sol.covariance_inner * 1e6,
                   covariance_joint=sol.covariance_joint * 1e6)
    with pytest.raises(PosteriorSkippedError, match="nearly degenerate"):
        sample_rig_posterior(wide, list(rig_result.camera_views), list(rig_result.lidar_views),
                             np.random.default_rng(0), min_ess=100)


def test_the_rig_posterior_agrees_with_the_graph_and_composes_each_pair_from_one_joint_sample(rig_folder, rig_result):
    # emcee over the five free sensors' poses (30 parameters): every pair's posterior standard deviations within
    # 15% of the graph's (the problem is near-linear: only the LiDAR planes' rotation enters beyond first order),
    # its mean within 0.2 sd of the MAP, and the truth's d2 under the posterior covariance below 22.5; each pair's
    # sample is composed from the same joint sample, so T_cam1_lidar0 = T_cam0_cam1^-1 T_cam0_lidar0 per sample.
    sol = rig_result.solution
    post = sample_rig_posterior(sol, list(rig_result.camera_views), list(rig_result.lidar_views),
                                np.random.default_rng(3), min_ess=300)
    assert post.run.converged and post.xi.shape[1] == 36 and np.all(post.xi[:, :6] == 0.0)
    from dataclasses import replace

    sampled = replace(rig_result, posterior=post)
    for a, b in rig_result.pairs():
        T, C = sol.transform(a, b)
        s = post.pair_samples(a, b)
        sd, sd_graph = np.std(s, axis=0), np.sqrt(np.diag(C))
        np.testing.assert_allclose(sd, sd_graph, rtol=0.15, err_msg=f"{a}-{b}")
        assert np.all(np.abs(s.mean(axis=0)) < 0.2 * sd_graph), (a, b)
        xi = T_log(np.linalg.inv(T) @ _truth(rig_folder, a, b))
        d2 = xi @ np.linalg.solve(np.cov(s, rowvar=False), xi)
        assert d2 < 22.5, (a, b)
        # the pair's credible region holds its share of the pair's samples, never below a Gaussian's, and the truth
        region = sampled.pair(a, b).summary()["credible_regions"]["99.9%"]
        inside = np.mean(np.einsum("ni,ni->n", s, np.linalg.solve(np.cov(s, rowvar=False), s.T).T) <= region["d2"])
        assert region["d2"] >= region["gaussian_d2"] and inside >= 0.999 and d2 <= region["d2"], (a, b)
    # the result's pair gives it as a single pair's result does: its estimate, the samples' covariance, the frames
    pe = sampled.pair("cam1", "lidar0")
    assert pe.samples is post.pair_samples("cam1", "lidar0") and pe.frames == rig_result.links[("cam1", "lidar0")] > 0
    np.testing.assert_array_equal(pe.T_camera_lidar, sol.transform("cam1", "lidar0")[0])
    np.testing.assert_allclose(pe.covariance, np.cov(pe.samples, rowvar=False))
    np.testing.assert_allclose(pe.std_translation_mm, 1000 * np.sqrt(np.diag(pe.covariance)[3:]))
    # the reverse pair's samples are each joint sample's, composed the other way: -Ad_T of the forward ones
    np.testing.assert_allclose(pe.inverse().samples, sampled.pair("lidar0", "cam1").samples, atol=1e-12)
    with pytest.raises(KeyError, match="cam7"):
        rig_result.pair("cam7", "lidar0")
    s01, s0l, s1l = (post.pair_samples(*p)[:50] for p in (("cam0", "cam1"), ("cam0", "lidar0"), ("cam1", "lidar0")))
    T01, T0l, T1l = (sol.transform(*p)[0] for p in (("cam0", "cam1"), ("cam0", "lidar0"), ("cam1", "lidar0")))
    for k in range(50):
        np.testing.assert_allclose(np.linalg.inv(T01 @ T_exp(s01[k])) @ T0l @ T_exp(s0l[k]), T1l @ T_exp(s1l[k]),
                                   atol=1e-9)


@pytest.mark.parametrize("given, named", [(["--refine", "none"], "--refine is"),
                                          (["--refine", "none", "--likelihood", "student-t"], "--refine is")])
def test_options_a_rig_folder_would_ignore_are_refused_in_one_line(rig_folder, tmp_path, capsys, given, named):
    """The calibrate options a rig's engine has no setting for are refused with a one-line error naming them
    (exit 2, nothing written), not silently ignored; the options a rig takes are not."""
    from estimators.cli import main
    from estimators.cli.commands import RIG_UNSUPPORTED

    out = tmp_path / "cal"
    assert main(["calibrate", str(rig_folder), "--out", str(out), *given]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and f"{named} not taken by a rig folder" in err and str(rig_folder) in err, err
    assert not out.exists()
    assert not {"samples", "range_model", "edges", "robust", "outliers", "corner_noise_px", "range_noise_m",
                "range_accuracy_m", "init", "strict", "measurements", "max_sensor_separation", "roi",
                "no_static_scene", "split", "cross_validate", "initial_guess", "guess_tolerance",
                "likelihood"} & set(RIG_UNSUPPORTED)
    # a rig's initial guess is a rig's calibration.json: six numbers (one pair's guess) are refused in one line
    assert main(["calibrate", str(rig_folder), "--out", str(out), "--initial-guess", *"000000"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "--initial-guess for a rig takes one file, got 6 value(s)" in err, err


def test_what_takes_a_pair_folder_says_so_for_a_rig_folder(rig_folder, tmp_path, capsys):
    """The pair's Python calibrate on a rig folder: an error saying it is a rig folder and what takes one; validate
    with a single pair's calibration.json, and layout's pair-only options: a one-line error saying so, exit 2."""
    from estimators.calibration import calibrate_pair
    from estimators.cli import main
    from estimators.errors import DatasetError

    (tmp_path / "calibration.json").write_text(json.dumps({
        "T_camera_lidar": np.eye(4).tolist(), "covariance": (1e-4 * np.eye(6)).tolist(),
        "noise": {"corner_noise_px": 0.2, "range_noise_m": 0.01}}))
    for argv, said in ((["layout", str(rig_folder), "--range-offset"], "--range-offset is not taken by a rig folder"),
                       (["validate", str(rig_folder), "--calibration", str(tmp_path)],
                        "a rig folder is given with a single pair's calibration")):
        assert main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert "\n" not in err and said in err, err
    with pytest.raises(DatasetError, match="this is a rig folder.*calibrate_rig"):
        calibrate_pair(rig_folder)


def test_a_scanner_the_rig_leaves_unobservable_is_said_first_as_a_single_pairs_answer_would_be_refused(rig_result):
    # The simulated rig's scanner is well fixed: no warning. With its pose's covariance 10^4 times as large (100 x
    # its standard deviations: degrees), each camera-scanner pair is named as not an answer, the LiDARs' are not.
    from dataclasses import replace

    from estimators.rig_calibration import unobservable_scanners

    sol = rig_result.solution
    assert unobservable_scanners(rig_result, {"scan0"}) == []
    k = sol.names.index("scan0")
    C = sol.covariance_joint.copy()
    C[6 * k:6 * k + 6, :] *= 100.0
    C[:, 6 * k:6 * k + 6] *= 100.0
    said = unobservable_scanners(replace(rig_result, solution=replace(sol, covariance_joint=C)), {"scan0"})
    assert [w.split(":")[0] for w in said] == ["T_cam0_scan0", "T_cam1_scan0", "T_cam2_scan0"]
    assert all("nearly unobservable" in w and "not an answer" in w for w in said)


def test_a_rigs_suggested_poses_each_tighten_the_pair_then_weakest(rig_result):
    """``layout RIG --suggest K``'s poses: each for the camera-LiDAR pair whose predicted largest translation sd is
    then the largest (the first: the layout's weakest pair), each lowering it, as the single next pose does."""
    from estimators.analysis.rig_layout import suggest_rig_poses

    found = suggest_rig_poses(rig_result, 3, np.random.default_rng(0), candidates=30)
    assert len(found) == 3 and found[0]["pair"] == rig_result.layout()["weakest_pair"]
    for f in found:
        assert f["max_translation_sd_mm_after"] < f["max_translation_sd_mm_before"], f["pair"]
    # the second pose is for the pair then weakest: none other is predicted above it
    after = {p: v["max_translation_sd_mm"] for p, v in rig_result.layout()["pairs"].items()}
    after[found[0]["pair"]] = found[0]["max_translation_sd_mm_after"]
    assert found[1]["max_translation_sd_mm_before"] == pytest.approx(max(after.values()), rel=1e-6)
    loose = suggest_rig_poses(rig_result, 3, np.random.default_rng(0), target=(90.0, 1e3), candidates=30)
    assert loose == []  # every pair already meets a loose target


def test_validate_scores_each_camera_lidar_pair_of_a_rig_on_the_frames_its_calibration_did_not_use(
        rig_folder, rig_result, tmp_path, capsys):
    """The rig calibrated on its first 6 frames: `validate` scores every camera-LiDAR pair's other frames under
    that calibration.json (each pair consistent at p > 0.001, as the simulation's noise is the model's), and the
    same calibration with T_cam0_lidar0 moved 30 mm is caught for that pair (p < 1e-6) and no other; without
    T_cam2_scan0 it is refused before a line is printed."""
    from estimators.cli import main
    from estimators.io.measurement_store import save_rig_measurements
    from estimators.pipeline.rig_result import write_rig_calibration

    rig = load_rig(rig_folder)
    stems = sorted(rig_result.measurements.stems)[:6]
    part = calibrate_rig(rig, np.random.default_rng(0), samples=0, advise=False, edges=False,
                         measurements=rig_result.measurements.restricted(stems))
    write_rig_calibration(part, tmp_path / "cal")
    meas = save_rig_measurements(tmp_path / "m", rig_result.measurements, rig.board,
                                 {s.name: s.lidar for s in rig.lidars})

    def validate(cal):
        argv = ["validate", str(rig_folder), "--calibration", str(cal), "--measurements", str(meas), "--out",
                str(tmp_path / "v")]
        assert main(argv) == 0
        return json.loads((tmp_path / "v" / "validation.json").read_text())["pairs"]

    pairs = validate(tmp_path / "cal")
    assert {"T_cam0_lidar0", "T_cam0_lidar1", "T_cam0_scan0"} <= set(pairs)
    for name, v in pairs.items():
        assert v["frames"] and all(f["name"] not in stems for f in v["frame_scores"]), name
        assert v["held_out"] == "frames the calibration did not use" and v["p_value"] > 1e-3, (name, v["p_value"])
    cal = json.loads((tmp_path / "cal" / "calibration.json").read_text())
    cal["transforms"]["T_cam0_lidar0"]["T"][0][3] += 0.03
    (tmp_path / "moved").mkdir()
    (tmp_path / "moved" / "calibration.json").write_text(json.dumps(cal))
    moved = validate(tmp_path / "moved")
    assert moved["T_cam0_lidar0"]["p_value"] < 1e-6
    assert all(moved[n]["p_value"] == v["p_value"] for n, v in pairs.items() if n != "T_cam0_lidar0")
    # a calibration without one of the rig's pairs is refused in one line before any pair is scored or printed
    del cal["transforms"]["T_cam2_scan0"]
    (tmp_path / "short").mkdir()
    (tmp_path / "short" / "calibration.json").write_text(json.dumps(cal))
    capsys.readouterr()
    assert main(["validate", str(rig_folder), "--calibration", str(tmp_path / "short"), "--measurements", str(meas),
                 "--out", str(tmp_path / "w")]) == 2
    said = capsys.readouterr()
    assert said.out == "" and said.err.count("\n") == 1 and "T_cam2_scan0" in said.err, said
    assert not (tmp_path / "w").exists()


def test_the_cli_calibrates_a_rig_folder_and_writes_every_pair(rig_folder, tmp_path, capsys):
    from estimators.cli import main

    out = tmp_path / "cal"
    code = main(["calibrate", str(rig_folder), "--out", str(out)])
    run = capsys.readouterr()
    assert code == 0, run.err
    assert "T_cam2_lidar0" in run.out
    cal = json.loads((out / "calibration.json").read_text())
    assert cal["rig"] and cal["reference"] == "cam0" and [s["name"] for s in cal["sensors"]][-1] == "scan0"
    assert set(cal["transforms"]) == {f"T_cam{k}_{s}" for k in range(3) for s in ("lidar0", "lidar1", "scan0")} | {
        "T_cam0_cam1", "T_cam0_cam2", "T_cam1_cam2", "T_lidar0_lidar1", "T_lidar0_scan0", "T_lidar1_scan0"}
    assert np.array(cal["covariance_joint"]).shape == (36, 36)
    # by default every LiDAR's board edges are measurements (as a single pair's): the board's size is given
    assert {s["name"] for s in cal["sensors"] if (s.get("board_edges") or {}).get("used")} == {"lidar0", "lidar1",
                                                                                                  "scan0"}
    # the posterior by default: each pair's intervals, the joint samples in posterior.npz (5 free sensors' poses, the
    # scanner's range noise scale and the camera side's noise scale, whose samples are there too)
    assert cal["posterior"]["converged"] and cal["posterior"]["parameters"] == 32 and "posterior (emcee" in run.out
    with np.load(out / "posterior.npz", allow_pickle=False) as npz:
        assert npz["noise_scale"].shape == (npz["xi"].shape[0],) and 0.3 < np.median(npz["noise_scale"]) < 3
    iv = cal["transforms"]["T_cam2_lidar0"]["posterior"]["95%"]["translation_mm"]
    assert all(lo < 0 < hi for lo, hi in iv)
    # printed under each camera-LiDAR pair as a single pair prints its own (PairEstimate.intervals)
    assert run.out.count("    95% intervals (about/along ") == 9
    assert f"translation [{iv[0][0]:+.2f}, {iv[0][1]:+.2f}]" in run.out
    assert cal["transforms"]["T_cam2_lidar0"]["posterior"]["credible_regions"]["99.9%"]["d2"] >= 22.45
    with np.load(out / "posterior.npz") as npz:
        assert npz["xi"].shape[1] == 36 and list(npz["names"]) == [s["name"] for s in cal["sensors"]]
    # the weakest camera-LiDAR pair: the one whose translation's largest standard deviation is largest
    sd = {k: np.sqrt(np.linalg.eigvalsh(np.array(v["covariance"])[3:, 3:])[-1]) for k, v in cal["transforms"].items()
          if k.split("_")[1].startswith("cam") and not k.split("_")[2].startswith("cam")}
    assert cal["layout"]["weakest_pair"] == max(sd, key=sd.get) and "weakest pair: " + max(sd, key=sd.get) in run.out
    page = (out / "report.html").read_text()
    assert all(f"T_{a}_lidar0" in page for a in ("cam0", "cam1", "cam2"))
    assert "emcee, 32 parameters" in page and "posterior 95%: t [mm]" in page and "99.9% region: d2" in page
    assert all(f"T_cam{k}_{s}: Intervals" in page for k in range(3) for s in ("lidar0", "lidar1", "scan0"))
    assert "T_cam2_lidar0: Board outline offsets" in page  # the single pair's check, under the joint estimate
    # each 3D LiDAR's edges in the joint graph, printed and reported as a single pair's are (with the test of its
    # planes against them)
    # each sensor's noise as calibration.json gives it (at its noise scale), in a single pair's words
    noise = {x["name"]: x["noise"] for x in cal["sensors"]}
    assert f"noise corners {noise['cam2']['corner_noise_px']:.3f} px" in run.out
    assert f"noise range {1000 * noise['lidar1']['range_noise_m']:.1f} mm" in run.out
    assert "lidar0: Board edges" in page and "ring ends on the boards' outlines, used in the estimate" in page
    assert re.search(r"\n  lidar0 board edges \(used\): \d+ ring ends in \d+ frames; the LiDAR's outlines sit "
                     r"\(camera axes\) .* growth .*\n    planes alone against planes \+ edges: d2", run.out)
    shown = sorted(p.name for p in out.glob("projection_cam2_lidar0_*.jpg"))
    assert shown and all(name in page for name in shown)
    # what a single pair's report shows of its boards, each pair's or LiDAR's: the residuals of each pair solved
    # alone, its normals' spread, each LiDAR's board choices (a top view a frame); traces only for a rig of two
    assert "cam2-lidar0 solved alone: per-frame residuals" in page and "cam0-lidar1: Layout" in page
    assert "lidar0 (with cam0): Which LiDAR points are the board" in page
    assert (out / "residuals_cam1_scan0.png").is_file() and sorted(out.glob("board_choice_lidar1_*.png"))
    assert not (out / "traces.png").exists()
    # each camera-LiDAR pair's posterior drawn as a single pair's is (its samples against the graph's covariance)
    assert all((out / f"corner_cam{k}_{s}.png").stat().st_size > 10000 and f"corner_cam{k}_{s}.png" in page
               for k in range(3) for s in ("lidar0", "lidar1", "scan0"))
    # every sensor's measurements are written beside it, and a re-solve from them reads no image or sweep
    from dataclasses import replace

    from estimators.cli import main
    from estimators.io.measurement_store import load_rig_measurements
    from estimators.pipeline.rig_measurement import given_measurements

    assert cal["measurements_source"] in ("measured", "cache")
    again = tmp_path / "again"
    assert main(["calibrate", str(rig_folder), "--out", str(again), "--measurements", str(out / "measurements"),
                 "--samples", "0", "--no-report"]) == 0
    cal2 = json.loads((again / "calibration.json").read_text())
    assert cal2["measurements_source"] == str(out / "measurements")
    assert cal2["warnings"][0].startswith(f"measurements taken from {out / 'measurements'}")
    for k, v in cal["transforms"].items():
        np.testing.assert_allclose(cal2["transforms"][k]["T"], v["T"], atol=1e-9)
    rm = load_rig_measurements(out / "measurements")
    pair_file = tmp_path / "measurements.npz"  # a pair's file where the rig's folder belongs
    pair_file.write_bytes(b"")
    with pytest.raises(DatasetError, match="a file, where a rig's measurements folder is expected"):
        load_rig_measurements(pair_file)
    with pytest.raises(DatasetError, match="sensors this rig does not have"):
        given_measurements(load_rig(rig_folder), replace(rm, cameras={"camX": rm.cameras["cam0"]}),
                           np.random.default_rng(0))


def test_a_lidar_as_the_rigs_reference(rig_folder, rig_result, tmp_path):
    import shutil

    folder = tmp_path / "rig"
    shutil.copytree(rig_folder, folder)
    ypath = folder / "dataset.yaml"
    ypath.write_text(ypath.read_text().replace("reference: cam0", "reference: lidar0"))
    res = calibrate_rig(load_rig(folder), np.random.default_rng(0), samples=300, edges=False)
    sol = res.solution
    assert sol.reference == "lidar0" and np.allclose(sol.T_ref["lidar0"], np.eye(4))
    T, C = sol.transform("cam1", "lidar0")
    T_cam, C_cam = rig_result.solution.transform("cam1", "lidar0")
    np.testing.assert_allclose(T, T_cam, atol=1e-6)
    np.testing.assert_allclose(C, C_cam, rtol=0.02, atol=1e-12)
    # sampled in the graph's camera frame, carried into the LiDAR's: its own block zero, the others as the graph's
    post = res.posterior
    assert np.all(post.xi[:, 18:24] == 0.0)
    np.testing.assert_allclose(np.sqrt(np.diag(post.covariance_joint)), np.sqrt(np.diag(sol.covariance_joint)),
                               rtol=0.15, atol=1e-12)


def test_a_larger_rig_gives_its_pairs_by_name_only(rig_result):
    # A pair folder's record reads its one pair directly (test_a_pair_folder_is_the_rig...); a rig of three cameras
    # and three LiDARs has no single T_camera_lidar, and says which call gives one
    for name in ("T_camera_lidar", "covariance", "samples", "std_rotation_deg", "std_translation_mm"):
        with pytest.raises(AttributeError, match=r"3 camera\(s\) and 3 LiDAR\(s\).*result.pair\(camera, lidar\)"):
            getattr(rig_result, name)
    assert rig_result.pair("cam1", "lidar0").T.shape == (4, 4)


def test_a_rigs_verdict_takes_a_single_pairs_rules_and_names_the_sensor(rig_result):
    """A simulated rig: OK. Its lidar0's boards given a plane error of 200 mm, beyond any LiDAR's range accuracy:
    UNTRUSTED, naming lidar0; that written into calibration.json."""
    from dataclasses import replace

    assert rig_result.verdict.line == "OK" and rig_result.to_json()["verdict"]["level"] == "OK"
    views = tuple(replace(lv, plane_error={k: replace(pe, floor_m=0.2) for k, pe in lv.plane_error.items()})
                  if lv.name == "lidar0" else lv for lv in rig_result.lidar_views)
    bad = replace(rig_result, lidar_views=views)
    assert bad.verdict.level == "UNTRUSTED" and bad.verdict.reasons[0].startswith(
        "lidar0: the boards' camera and LiDAR planes disagree by 200 mm per board"), bad.verdict
    assert bad.to_json()["verdict"]["reasons"][0].startswith("lidar0: ")
    # a range accuracy given on the command line (--range-accuracy, in its range record) bounds the error instead
    loose = replace(bad, range_models={**bad.range_models, "lidar0": {**bad.range_models["lidar0"], "prior_sd_m": 0.3}})
    assert loose.verdict.line == "OK", loose.verdict


def test_a_lidars_planes_and_edges_in_conflict_are_held_by_the_rigs_covariance(rig_result):
    """lidar0's pose with its edges moved 12 mm along x from its planes-only pose, with a covariance a quarter of
    the planes': the test finds the conflict (p < 0.01), the joint covariance with the conflict's share holds the
    planes-only pose within one standard deviation, and the rig's verdict is a CHECK naming lidar0."""
    from dataclasses import replace

    from estimators.pipeline.rig_edges import conflict_share, planes_against_edges
    from geometry.rotations import T_retract

    planes = rig_result.solution
    moved = dict(planes.T_ref)
    moved["lidar0"] = T_retract(planes.T_ref["lidar0"], np.r_[0.0, 0.0, 0.0, 0.012, 0.0, 0.0])
    edged = replace(planes, T_ref=moved, covariance_joint=0.25 * planes.covariance_joint)
    test = planes_against_edges(planes, edged, "lidar0")
    assert test["p_value"] < 0.01 and planes_against_edges(planes, edged, "cam0") is None  # the reference's is fixed
    records = {"lidar0": {"used": True, "planes_against_edges": test}}
    share = conflict_share(planes, edged, records)
    k = planes.names.index("lidar0")
    C = (edged.covariance_joint + share)[6 * k:6 * k + 6, 6 * k:6 * k + 6]
    xi = np.asarray(test["difference_tangent"])
    assert float(xi @ np.linalg.solve(C, xi)) <= 1.0 + 1e-6
    own = np.asarray(test["edges_own_offset_tangent"])  # the edges' own answer, beyond the estimate: held too
    assert np.linalg.norm(own) > 0 and float(own @ np.linalg.solve(C, own)) <= 1.0 + 1e-6
    held = replace(rig_result, solution=replace(edged, covariance_joint=edged.covariance_joint + share), edges=records)
    assert held.verdict.level == "CHECK" and held.verdict.reasons[0].startswith("lidar0: the boards' planes and their "
                                                                                "ring ends"), held.verdict
    assert "the covariance holds both answers" in held.verdict.line and held.contradicted.startswith("lidar0: ")


def test_a_rigs_tree_exports_every_sensor(rig_result, tmp_path):
    import xml.etree.ElementTree as ET

    from estimators.io.export import export_calibration
    from estimators.pipeline.rig_result import write_rig_calibration
    from geometry.rotations import R_from_quat_xyzw

    path = write_rig_calibration(rig_result, tmp_path)
    tf = export_calibration(path, "ros-tf")
    ros1 = [line.split() for line in tf.splitlines() if line.startswith("rosrun")]
    assert [r[-1] for r in ros1] == ["cam1", "cam2", "lidar0", "lidar1", "scan0"] and all(r[-2] == "cam0" for r in ros1)
    x = np.array(ros1[2][3:10], dtype=float)  # lidar0
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R_from_quat_xyzw(x[3:]), x[:3]
    np.testing.assert_allclose(T, rig_result.solution.T_ref["lidar0"], atol=1e-8)
    joints = ET.fromstring(export_calibration(path, "urdf")).findall("joint")
    assert [j.find("child").get("link") for j in joints] == ["cam1", "cam2", "lidar0", "lidar1", "scan0"]
    assert "camera_matrix" in export_calibration(path, "opencv-yaml")
    with pytest.raises(LidarcamError, match="one camera-LiDAR pair"):
        export_calibration(path, "kitti")


def test_a_cameras_wrong_intrinsics_are_refined_back_with_the_rig(rig_folder, tmp_path, capsys):
    # cam1's focal lengths 1% too long and its k1 halved in dataset.yaml: its corners disagree with the rest
    # (a warning says so, and names the remedy); with the intrinsics in the graph its focal length comes back
    # within 3 standard deviations and its LiDAR transform within 6 mm of the truth (its sd along x is 3 mm with
    # the intrinsics free) and inside its 99.9% region (d2 below 22.5).
    import shutil

    from estimators.simulation.rig_simulator import miscalibrate_camera

    folder = tmp_path / "rig"
    shutil.copytree(rig_folder, folder)
    true_f = float(load_rig(rig_folder).sensor("cam1").camera.K[0, 0])
    rig = load_rig(miscalibrate_camera(folder, "cam1"))
    plain = calibrate_rig(rig, np.random.default_rng(0))
    assert any(w.startswith("cam1: ") and "--refine-intrinsics" in w for w in plain.warnings)
    # and the verdict says so: a camera whose corners disagree with the rest is never OK (6 of 30 simulated rigs
    # with cam1's focal lengths 1% long read OK, 62 mm off, before the rule)
    assert plain.verdict.level != "OK" and "cam1: its corners disagree with the rest" in plain.verdict.line
    refined = calibrate_rig(rig, np.random.default_rng(0), refine_intrinsics=True, samples=400)
    # The posterior is sampled with the intrinsics held at their refined values and convolved with their share of
    # the joint covariance, as a single pair's: each pair's posterior sd within 8% of the joint graph's, which
    # carries the intrinsics (400 effective samples: each sd within about 4% by chance; held, the graph's sd were
    # 1.1-61 times narrower)
    for a, b in (("cam1", "lidar0"), ("cam0", "cam1")):
        C = refined.solution.transform(a, b)[1]
        np.testing.assert_allclose(np.sqrt(np.diag(refined.pair(a, b).covariance) / np.diag(C)), 1.0, atol=0.08)
    # Each pair's boards are judged as the refined intrinsics see them: the answer reads OK (it read UNTRUSTED, the
    # camera's boards posed under the wrong intrinsics disagreeing with the refined estimate)
    assert refined.verdict.line == "OK", refined.verdict.line
    # the refined intrinsics lower the rig's disagreement far beyond what freed parameters fit of its noise
    test = refined.to_json()["intrinsics_test"]
    assert test["lowers_disagreement"] and test["p_value"] < 1e-6 and test["parameters"] == 3 * 9
    assert not any(w.startswith("refining the intrinsics did not lower") for w in refined.warnings)
    p, sd = refined.solution.intrinsics["cam1"]
    assert abs(p[0] - true_f) < 3 * sd[0] and abs(p[1] - true_f) < 3 * sd[1]
    # printed as a single pair's refined intrinsics are: each parameter given and refined, its sd and its move
    from estimators.cli.printing import print_rig

    print_rig(refined)
    given = rig.sensor("cam1").camera.params
    assert (f"  cam1 intrinsics refined:\n    fx  {given[0]:12.5g} -> {p[0]:12.5g}  (sd {sd[0]:.3g}, moved "
            f"{(p[0] - given[0]) / sd[0]:+.1f} sd)") in capsys.readouterr().out
    T, C = refined.solution.transform("cam1", "lidar0")
    xi = T_log(np.linalg.inv(T) @ _truth(rig_folder, "cam1", "lidar0"))
    assert 1000 * np.linalg.norm(xi[3:]) < 6.0 and xi @ np.linalg.solve(C, xi) < 22.5


def test_right_intrinsics_refined_with_the_rig_are_not_credited(rig_folder):
    # The simulated rig's own intrinsics freed: their drop in chi-square is what 27 free parameters fit of the
    # noise (F test p > 0.05), so the refined ones are not credited, and the answer says so first.
    res = calibrate_rig(load_rig(rig_folder), np.random.default_rng(0), refine_intrinsics=True, advise=False,
                        edges=False)
    assert res.intrinsics_test["p_value"] > 0.05 and not res.intrinsics_test["lowers_disagreement"]
    assert res.warnings[0].startswith("refining the intrinsics did not lower the rig's disagreement")


def test_a_rig_bag_gives_each_sensors_frames_back(rig_folder, tmp_path, capsys):
    # Five frames of two cameras (cam2 misses one), the VLP-16-like LiDAR and the 2D scanner, recorded as one ROS 1
    # bag (each pose held 1.5 s, images at 4 Hz, scans at 5 Hz 11 ms later): the command writes a rig folder with
    # five frames, each camera's files where it saw the board, every scan the very one recorded, and the cameras'
    # intrinsics from CameraInfo.
    from estimators.cli import main
    from estimators.errors import BagError
    from estimators.io.pointcloud_io import read_scan, read_scan_2d
    from estimators.io.rig_bag_extract import extract_rig_bag
    from tests.rosbag_writer import rig_topics, write_bag_from_rig

    rig = load_rig(rig_folder)
    stems = ["0000", "0001", "0002", "0003", "0004"]
    assert rig.sensor("cam2").file("0004") is None and rig.sensor("cam2").file("0003") is not None
    bag = write_bag_from_rig(rig_folder, tmp_path / "rig.bag", "ros1", stems, ["cam0", "cam2", "lidar1", "scan0"])
    topics = rig_topics(rig)
    out = tmp_path / "extracted"
    args = ["extract", str(bag), "--image-topic", topics["cam0"], "--image-topic", topics["cam2"],
            "--cloud-topic", topics["lidar1"], "--scan-topic", topics["scan0"], "--board", str(rig_folder /
                                                                                              "dataset.yaml"),
            "--out", str(out)]
    assert main(args) == 0
    x = load_rig(out)
    assert [s.name for s in x.sensors] == ["cam0", "cam1", "lidar0", "scan0"] and x.reference == "cam0"
    assert x.sensor("cam0").stems == tuple(stems) and x.sensor("cam1").stems == tuple(stems[:4])
    np.testing.assert_allclose(x.sensor("cam1").camera.K, rig.sensor("cam2").camera.K)
    for st in stems:
        np.testing.assert_allclose(read_scan(x.sensor("lidar0").file(st)), read_scan(rig.sensor("lidar1").file(st)),
                                   atol=1e-5)
        # LaserScan carries float32 ranges and angles as start + k * increment: 0.1 mm over these ranges
        np.testing.assert_allclose(read_scan_2d(x.sensor("scan0").file(st)), read_scan_2d(rig.sensor("scan0").file(st)),
                                   atol=1e-4)
    record = json.loads((out / "extract.json").read_text())
    assert record["topics"]["cam1"] == topics["cam2"] and record["image_counts"]["cam1"]["kept"] == 4
    # a topic given twice, or a topic not in the bag: one line naming it, and nothing written
    with pytest.raises(BagError, match="given twice"):
        extract_rig_bag(bag, tmp_path / "twice", rig.board, [topics["cam0"], topics["cam0"]], [topics["lidar1"]])
    assert main(args[:-1] + [str(tmp_path / "missing")] + ["--image-topic", "/cam9/image_raw"]) == 2
    assert "/cam9/image_raw" in capsys.readouterr().err and not (tmp_path / "missing").exists()
    assert not (tmp_path / "twice").exists()


@pytest.mark.parametrize("data", ["sim_vlp16", "sim_2d"])
def test_a_pair_folder_is_the_rig_of_cam0_and_lidar0_and_calibrates_as_the_pair(data, request, tmp_path,
                                                                                 monkeypatch):
    # A single camera-LiDAR folder loads as the rig of cam0 (the reference) and lidar0, frame by frame, and its
    # rig calibration.json keeps the pair's T_camera_lidar and covariance. The one graph weighs the rig's
    # boards as the pair's refinement does (each board's corner noise, the LiDAR's robust loss, per-board plane
    # error and outlier frames): the rig lands on the pair's estimate within 1e-5 of its standard deviations and
    # on its covariance within 1e-6 of its scale (numerical precision: 2e-7 sd and 3e-10 when written), a 3D
    # LiDAR's and a 2D scanner's
    # (planes alone: the edges enter each engine in its own steps). Measured once: a second call reads the
    # measurements back from the cache and lands on the same estimate and covariance, bit for bit.
    from estimators.calibration import calibrate_pair
    from estimators.io.dataset import load_dataset
    from estimators.solvers.refinement_options import RefinementOptions

    folder = request.getfixturevalue(data)
    rig = load_rig(folder)
    assert [(s.name, s.type) for s in rig.sensors] == [("cam0", "camera"), ("lidar0", "lidar")]
    assert rig.reference == "cam0" and rig.pair("cam0", "lidar0").frames == load_dataset(folder).frames
    monkeypatch.setenv("LIDARCAM_CACHE_DIR", str(tmp_path))
    res = calibrate_rig(rig, np.random.default_rng(0), advise=False, edges=False, cache=True)
    T, C = res.pair("cam0", "lidar0").T_camera_lidar, res.pair("cam0", "lidar0").covariance
    # a 3D LiDAR's range-term choice is kept beside the cached measurements, and replayed: the measurements read
    # back are the same inputs (no second entry); a scanner's is not kept
    kept = list(tmp_path.glob("rig-*/choices.json"))
    assert bool(kept) == (data == "sim_vlp16")
    again = calibrate_rig(rig, np.random.default_rng(0), advise=False, edges=False, cache=True)
    assert all(len(json.loads(k.read_text())) == 1 for k in kept)
    assert not any("cache" in w for w in res.warnings) and again.warnings[0].startswith("measurements taken from")
    for got, want in zip(again.solution.transform("cam0", "lidar0"), (T, C)):
        np.testing.assert_array_equal(got, want)
    cal = res.to_json()
    np.testing.assert_array_equal(np.array(cal["T_camera_lidar"]), T)
    np.testing.assert_array_equal(np.array(cal["covariance"]), C)
    # the Python API's calibrate is this engine: a folder or a loaded Dataset, the pair's transform and covariance
    # read directly off its record; the closed form alone is the pair's own solve's, refused here in one line
    import estimators

    for given in (folder, load_dataset(folder)):
        api = estimators.calibrate(given, samples=0, options=RefinementOptions(edges=False), cache=True)
        np.testing.assert_array_equal(api.T_camera_lidar, T)
        np.testing.assert_array_equal(api.covariance, C)
        assert api.samples is None and api.std_translation_mm.shape == (3,)
    with pytest.raises(ValueError, match="refine='none'"):
        estimators.calibrate(folder, refine="none")
    pair = calibrate_pair(folder, samples=0, options=RefinementOptions(edges=False))
    xi = T_log(np.linalg.inv(pair.T_camera_lidar) @ T)
    sd = np.sqrt(np.diag(pair.covariance))
    assert np.all(np.abs(xi) < 1e-5 * sd), xi / sd
    assert np.max(np.abs(C - pair.covariance) / np.outer(sd, sd)) < 1e-6
    # the rig's calibration.json has every key of the pair's file, of the same type, and the same values: the
    # transform's, the frames' (each one's measurements, planes, residuals and fit), the noise, consistency,
    # start, range model, layout and intrinsics (the rig's own keys beside them)
    mine = pair.to_dict()
    assert set(mine) <= set(cal), set(mine) - set(cal)
    assert all(type(cal[k]) is type(mine[k]) for k in mine if mine[k] is not None), \
        [k for k in mine if type(cal[k]) is not type(mine[k])]
    for key in ("quaternion_xyzw", "translation_m"):
        np.testing.assert_allclose(cal[key], mine[key], atol=1e-9)
    for key, v in mine["std"].items():
        np.testing.assert_allclose(cal["std"][key], v, rtol=1e-5)
    for key in ("init", "refine", "frames_used", "frames_total", "intrinsics", "contradicted", "tool",
                "intrinsics_check", "covariance_convention"):
        assert cal[key] == mine[key], key
    assert [{k: v for k, v in f.items() if not isinstance(v, float)} for f in cal["frames"]] == \
        [{k: v for k, v in f.items() if not isinstance(v, float)} for f in mine["frames"]]
    for got, want in zip(cal["frames"], mine["frames"]):
        for k in ("normal_residual_deg", "distance_residual_m", "plane_chi2", "robust_weight"):
            if k in want:
                assert got[k] == pytest.approx(want[k], rel=1e-4, abs=1e-9), k
    for key in ("noise", "consistency", "layout"):
        for k, v in mine[key].items():
            assert cal[key][k] == (v if isinstance(v, str) else pytest.approx(v, rel=1e-5)), (key, k)
    assert cal["lidar_range_model"]["chosen"] == mine["lidar_range_model"]["chosen"]
    assert cal["minimal_solutions"]["triples"] == mine["minimal_solutions"]["triples"] if data == "sim_2d" else \
        "minimal_solutions" not in cal
    # both records give either order of the pair alike (T_lidar_camera: the tangent carried by -Ad_T, exactly)
    for a, b in (("cam0", "lidar0"), ("lidar0", "cam0")):
        mine, theirs = pair.pair(a, b), res.pair(a, b)
        sd_ab = np.sqrt(np.diag(theirs.covariance))
        assert np.all(np.abs(T_log(np.linalg.inv(mine.T) @ theirs.T)) < 1e-5 * sd_ab)
        assert np.max(np.abs(mine.covariance - theirs.covariance) / np.outer(sd_ab, sd_ab)) < 1e-6
    with pytest.raises(KeyError, match="cam0"):
        pair.pair("cam1", "lidar0")
    # With the board's edges (a 3D LiDAR's ring ends with --edges; a scanner's segment ends, on by default), each
    # engine takes them in its own steps: the same estimate within 1e-3 of its standard deviations and the same
    # standard deviations within 1e-3 (measured: 6e-4 and 2e-5)
    edged = calibrate_pair(folder, samples=0, options=RefinementOptions(edges=True))
    rig_result = calibrate_rig(rig, np.random.default_rng(0), advise=False, edges=True, cache=True)
    rig_edged = rig_result.pair("cam0", "lidar0")
    sd = np.sqrt(np.diag(edged.covariance))
    assert edged.refinement.edges
    assert np.all(np.abs(T_log(np.linalg.inv(edged.T_camera_lidar) @ rig_edged.T)) < 1e-3 * sd)
    np.testing.assert_allclose(np.sqrt(np.diag(rig_edged.covariance)), sd, rtol=1e-3)
    # and its edges record states what the pair's does (the rig's had neither the outline's uncertainty nor the
    # outlines' mean shift, and so could not warn of them): within 2% (measured on the recorded VLP-16 and Ouster
    # folders: 0.5% and 0.8% on the shift's d2, the planes alone's check's p within 1e-5)
    mine, theirs = edged.refinement.edges, rig_result.edges["lidar0"]
    for key in ("growth_sd_m", "outline_offset_sd_m", "mean_shift_camera_m"):
        np.testing.assert_allclose(theirs[key], mine[key], rtol=0.02, atol=1e-5, err_msg=key)
    assert theirs["mean_shift_dof"] == mine["mean_shift_dof"]
    assert theirs["mean_shift_d2"] == pytest.approx(mine["mean_shift_d2"], rel=0.02, abs=0.01)
    if data == "sim_vlp16":  # a 3D LiDAR's planes alone checked by the ends beside them
        assert theirs["planes_only_check"]["mean_shift_p_value"] == pytest.approx(
            mine["planes_only_check"]["mean_shift_p_value"], rel=0.02)


def test_a_pair_folders_posterior_is_the_same_as_a_pair_and_as_a_rig(tmp_path):
    # One likelihood: the rig's posterior samples the camera side's noise scale s as the likelihood of the pair solved
    # alone (its refinement's views, sampled by the same chain: tests/numeric.sampled) does (its corners' covariance
    # and the boards' plane error times s^2, the board poses integrated out). On an 8-pose pair
    # whose planes leave s uncertain, both posteriors are wider than the Laplace covariance (by 2-6% per axis; the
    # rig's, at the graph's scales alone, was 0.98-1.00 of it), and they agree: every standard deviation within 4%
    # (each from about 6,000 effective samples: 1.3% apart by chance; measured within 1.8%) and s's 5%, 50% and 95%
    # points within 5%; with --likelihood student-t, 22-31% wider than Laplace, every sd within 5%.
    from estimators.calibration import calibrate_pair
    from estimators.simulation.simulator import simulate_dataset

    from .numeric import sampled

    folder = simulate_dataset(tmp_path / "pair", n_poses=8, seed=3)
    pair = calibrate_pair(folder, options=RefinementOptions(edges=False)).refinement
    res = calibrate_rig(load_rig(folder), np.random.default_rng(0), advise=False, edges=False, samples=4000)
    laplace = np.sqrt(np.diag(pair.covariance))
    xi_pair, _, _, scale_pair = sampled(pair, np.random.default_rng(1), 4000)
    sd_pair = np.std(xi_pair, axis=0)
    sd_rig = np.std(res.pair("cam0", "lidar0").samples, axis=0)
    assert np.mean(sd_pair / laplace) > 1.02 and np.mean(sd_rig / laplace) > 1.02
    np.testing.assert_allclose(sd_rig, sd_pair, rtol=0.04)
    q = [5, 50, 95]
    np.testing.assert_allclose(np.percentile(res.posterior.camera_scale, q), np.percentile(scale_pair, q), rtol=0.05)
    # --likelihood student-t (4 dof on each frame's planes against its board) alike, as a pair and as a rig
    xi_t, *_ = sampled(pair, np.random.default_rng(2), 4000, likelihood="student-t")
    t_rig = calibrate_rig(load_rig(folder), np.random.default_rng(0), advise=False, edges=False, samples=4000,
                          measurements=res.measurements, likelihood="student-t")
    assert t_rig.posterior.diagnostics()["likelihood"] == "student-t"
    sd_t = np.std(t_rig.pair("cam0", "lidar0").samples, axis=0)
    np.testing.assert_allclose(sd_t, np.std(xi_t, axis=0), rtol=0.05)  # measured: within 3.1%
    assert np.max(np.abs(sd_t / sd_rig - 1)) > 0.02  # not the Gaussian's


def test_a_2d_pair_folders_posterior_is_the_same_as_a_pair_and_as_a_rig(sim_2d, tmp_path):
    # A 2D scanner's range noise rests on a few dozen points a board: both posteriors sample its scale r with the
    # camera side's s (the lines' own residuals in r's likelihood, flat prior on log r): planes alone, 8 parameters
    # for the rig, and every standard deviation within 4% of the pair's (measured within 2% on three sets).
    from estimators.calibration import calibrate_pair

    from .numeric import sampled

    pair = calibrate_pair(sim_2d, options=RefinementOptions(edges=False)).refinement
    res = calibrate_rig(load_rig(sim_2d), np.random.default_rng(0), advise=False, edges=False, samples=4000)
    assert res.posterior.diagnostics()["parameters"] == 8
    xi_pair, *_ = sampled(pair, np.random.default_rng(1), 4000, pilot=True)
    np.testing.assert_allclose(np.std(res.pair("cam0", "lidar0").samples, axis=0), np.std(xi_pair, axis=0), rtol=0.04)
    # Its report, as a single pair's, has the chain's traces: the pose's tangent first and log s last (r between)
    from estimators.analysis.rig_report import write_rig_report

    run = res.posterior.run
    np.testing.assert_allclose(np.percentile(np.exp(run.chain[run.burn:, :, -1]), q := [5, 50, 95]),
                               np.percentile(res.posterior.camera_scale, q), rtol=0.02)  # the kept ones' are a subset
    page = write_rig_report(res, tmp_path).read_text()
    assert (tmp_path / "traces.png").is_file() and "MCMC traces" in page
    assert "cam0-lidar0 solved alone: per-frame residuals" in page and "cam0-lidar0: Layout" in page


def test_a_scanner_pair_whose_boards_leave_two_answers_is_said_and_the_rigs_posterior_covers_both(tmp_path):
    # A 3-board 2D pair folder (seed 35) whose boards leave two minima, 84% and 16% of the mass by their segment ends;
    # the truth is the second's. As a rig its scanner pair is solved as the single pair is (its ends weigh the
    # minima), so the rig reads CHECK naming both (from the planes alone, a rig read OK on such a folder, seed 1
    # before its segments kept their ends, with the truth at d2 199). It lands on the pair's first minimum (the
    # truth at d2 201 under its covariance), and its posterior mixes both by the pair's masses (each sampled within
    # its own cell), so the truth is within its 99.9% region (measured: d2 15 of 33 under the mixture's covariance;
    # the region is the union of each minimum's own ellipsoid).
    from dataclasses import replace

    from estimators.simulation.simulator import simulate_dataset
    from estimators.solvers.posterior import region_d2

    folder = simulate_dataset(tmp_path / "pair", n_poses=3, seed=35, lidar="2d")
    truth = np.array(json.loads((folder / "ground_truth.json").read_text())["T_camera_lidar"])
    res = calibrate_rig(load_rig(folder), np.random.default_rng(0), advise=False, samples=500)
    modes = res.ambiguous_pairs[("cam0", "lidar0")]
    assert len(modes) == 2 and 0.1 < modes[1].mass < 0.25
    assert res.verdict.level == "CHECK", res.verdict
    assert res.verdict.reasons[0].startswith("T_cam0_lidar0: 2 solutions fit its boards") and \
        "the intervals cover them all" in res.verdict.reasons[0]
    # without the posterior the covariance is the first minimum's alone, and the verdict says so
    assert "the covariance and intervals are the most probable one's" in replace(res, posterior=None).verdict.line
    pe = res.pair("cam0", "lidar0")
    T_lap, C_lap = res.solution.transform("cam0", "lidar0")
    sd = np.sqrt(np.diag(C_lap))
    assert np.all(np.abs(T_log(np.linalg.inv(modes[0].T_camera_lidar) @ pe.T)) < 1e-3 * sd)
    x = T_log(np.linalg.inv(pe.T) @ truth)
    assert x @ np.linalg.solve(C_lap, x) > 100  # the first minimum's covariance leaves the truth out
    assert x @ np.linalg.solve(pe.covariance, x) <= region_d2(pe.samples, 0.999)
    post = res.posterior
    np.testing.assert_allclose(post.mode_weights, [m.mass for m in modes], atol=1e-12)
    assert post.mixed == (("cam0", "lidar0"),)
    assert abs(np.mean(post.mode_index == 1) - modes[1].mass) < 0.02
    # the second minimum's samples lie about it (in the first's tangent)
    x2 = T_log(np.linalg.inv(pe.T) @ modes[1].T_camera_lidar)
    d = pe.samples[post.mode_index == 1] - x2
    C2 = modes[1].refinement.covariance
    assert np.median(np.einsum("ij,ij->i", d, np.linalg.solve(C2, d.T).T)) < 20
    # its region is the union of each minimum's own ellipsoid (the second's centre is that minimum, to the joint
    # graph's precision), which holds the truth nearer than the mixture's ellipsoid does
    assert np.all(np.abs(pe.mode_centers[1] - x2) < 0.05 * np.sqrt(np.diag(C2)))
    assert pe.region_distance(x)[0] < x @ np.linalg.solve(pe.covariance, x) and pe.contains(truth, 0.999)
    regions = pe.summary()["credible_regions"]
    assert [m["posterior_mass"] for m in regions["modes"]] == list(post.mode_weights)
    assert regions["99.9%"]["d2"] == pe.region_d2(0.999)
    assert res.pair_keys("cam0", "lidar0")["credible_regions"] == regions  # a pair folder's calibration.json


def test_a_scanners_second_minimum_is_solved_with_its_ends_assigned_under_it(tmp_path):
    # A 3-board varied folder (seed 25) whose boards leave two minima (65%, 35%; the truth the second's). Solved
    # from the second with the ends assigned to the board's sides under the first, the joint graph slid back to the
    # first on such a folder (seed 23, before its segments kept their ends), and the posterior held the first alone
    # (the truth at d2 178 beyond its region of 42). Each joint minimum has the scanner's ends assigned under it, as
    # its pair's refinement had them: both are mixed, and the truth lies within the region (measured: d2 8.6 of 51).
    from estimators.simulation.simulator import simulate_dataset
    from estimators.solvers.posterior import region_d2

    folder = simulate_dataset(tmp_path / "pair", n_poses=3, seed=25, lidar="2d", rig_config="varied")
    truth = np.array(json.loads((folder / "ground_truth.json").read_text())["T_camera_lidar"])
    res = calibrate_rig(load_rig(folder), np.random.default_rng(0), advise=False, samples=200)
    assert res.posterior.mixed == (("cam0", "lidar0"),) and len(res.posterior.mode_weights) == 2
    assert "the intervals cover them all" in res.verdict.line
    pe = res.pair("cam0", "lidar0")
    x = T_log(np.linalg.inv(pe.T) @ truth)
    assert x @ np.linalg.solve(pe.covariance, x) <= region_d2(pe.samples, 0.999)


@pytest.mark.parametrize("seed", [7, 8])
def test_a_scanner_of_three_boards_keeps_the_start_its_segment_ends_gave_it_in_the_joint_graph(tmp_path, seed):
    # 3-board 2D pair folders whose pair, solved with its segment ends, lands near the truth (d2 3.8 and 5.1). The
    # joint graph's planes alone cannot hold a 3-board scanner: seed 7's pose went 12 deg and 1.2 m astray under
    # them, where no end lay on a board, and the rig answered that (d2 3854); seed 8's information was singular and
    # the rig refused. Its ends now enter the first joint solve, assigned under its start, and the rig lands on the
    # pair's answer (within 1e-3 of its standard deviations).
    from estimators.simulation.simulator import simulate_dataset

    folder = simulate_dataset(tmp_path / "pair", n_poses=3, seed=seed, lidar="2d")
    truth = np.array(json.loads((folder / "ground_truth.json").read_text())["T_camera_lidar"])
    res = calibrate_rig(load_rig(folder), np.random.default_rng(0), advise=False)
    T, C = res.solution.transform("cam0", "lidar0")
    T_pair = res.pairwise[("cam0", "lidar0")][0]
    assert res.edges["lidar0"]["used"] and res.edges["lidar0"]["ends"] >= 3
    assert np.all(np.abs(T_log(np.linalg.inv(T_pair) @ T)) < 1e-3 * np.sqrt(np.diag(C)))
    x = T_log(np.linalg.inv(T) @ truth)
    assert x @ np.linalg.solve(C, x) < 22.5


def test_a_scanner_that_found_two_of_its_three_boards_is_linked_as_its_pair_is_solved(tmp_path):
    # A 3-board pair folder whose third scan holds no board segment (varied seed 2): the single pair solves its two
    # boards by their segment ends and reads OK (the truth at d2 0.76). The rig needed 3 frames for every
    # camera-LiDAR link and refused the folder ("share no usable frames with the rest of the rig"). A scanner taking
    # its ends is now linked by two, and the rig lands on the pair's answer (within 1e-3 of its standard
    # deviations), its covariance the pair's within 1%.
    from estimators.calibration import calibrate_pair
    from estimators.simulation.simulator import simulate_dataset

    folder = simulate_dataset(tmp_path / "pair", n_poses=3, seed=2, lidar="2d", rig_config="varied")
    truth = np.array(json.loads((folder / "ground_truth.json").read_text())["T_camera_lidar"])
    pair = calibrate_pair(folder, samples=0)
    assert sum(f.usable for f in pair.frames) == 2 and pair.verdict.line == "OK"
    res = calibrate_rig(load_rig(folder), np.random.default_rng(0), advise=False)
    assert res.links[("cam0", "lidar0")] == 2 and res.verdict.line == "OK", res.verdict.line
    T, C = res.solution.transform("cam0", "lidar0")
    assert np.all(np.abs(T_log(np.linalg.inv(pair.T_camera_lidar) @ T)) < 1e-3 * np.sqrt(np.diag(C)))
    assert np.allclose(np.diag(C), np.diag(pair.covariance), rtol=0.01)
    x = T_log(np.linalg.inv(T) @ truth)
    assert x @ np.linalg.solve(C, x) < 22.5


def test_a_lidar_whose_pairs_cannot_be_solved_raises_its_pairs_reason(sim_vlp16, monkeypatch):
    # A LiDAR left without a link because its pair's boards cannot be solved (the recorded 2D set's upright boards)
    # is refused with that pair's reason and hint, as the single pair's calibration refuses it, not as a sensor
    # that "shares no usable frames" with the rig.
    from estimators import rig_calibration

    def degenerate(*args, **kwargs):
        raise DegenerateLayoutError("the 4 board normals all lie in one plane (a test)", hint="tilt a board")

    monkeypatch.setattr(rig_calibration, "solve", degenerate)
    with pytest.raises(DegenerateLayoutError) as exc:
        calibrate_rig(load_rig(sim_vlp16), np.random.default_rng(0), advise=False)
    assert exc.value.problem == "cam0-lidar0: the 4 board normals all lie in one plane (a test)"
    assert exc.value.hint == "tilt a board" and exc.value.path == str(sim_vlp16)


def test_a_posterior_the_sampler_refuses_is_said_and_the_graphs_covariance_stands(sim_2d, monkeypatch):
    # emcee raised a ValueError (no autocorrelation time: NaN) on a 3-board scanner's second minimum (varied seed
    # 16), and calibrate_rig let it through. A refused chain is a PosteriorSkippedError: a second minimum is left out
    # of the mixture with its reason, and a rig whose only chain is refused keeps the graph's covariance, said.
    import estimators.solvers.rig_posterior as rp

    def refuse(*args, **kwargs):
        raise ValueError("cannot convert float NaN to integer")

    monkeypatch.setattr(rp, "run_chain", refuse)
    res = calibrate_rig(load_rig(sim_2d), np.random.default_rng(0), advise=False, samples=200)
    assert res.posterior is None
    assert any("the rig's posterior was not sampled (the sampler refused the problem" in w for w in res.warnings)
    assert any(r.startswith("the posterior was not sampled") for r in res.verdict.reasons), res.verdict
    T, C = res.solution.transform("cam0", "lidar0")
    np.testing.assert_allclose(res.pair("cam0", "lidar0").covariance, C)


def test_the_rigs_minima_are_one_pair_a_scanner_and_every_combination_of_two_scanners_minima():
    # Which pairs' minima the rig's posterior mixes (rig_modes.mixable_minima): one holding all its scanner's boards,
    # one pair a scanner (a second camera that saw the same boards sees the same minima); and the joint starts
    # (rig_modes.joint_starts): the estimate first, then each combination of two scanners' minima by the product of
    # their masses, each scanner moved to its minimum's transform from its camera.
    from types import SimpleNamespace

    from estimators.pipeline.rig_modes import joint_starts, mixable_minima

    def mode(mass, T):
        return SimpleNamespace(mass=mass, T_camera_lidar=T, refinement=SimpleNamespace(T_camera_lidar=T,
                                                                                       covariance=1e-4 * np.eye(6)))

    T = {n: T_exp(np.r_[0.1 * k, 0.0, 0.0, k, 0.0, 0.0]) for k, n in enumerate(("cam0", "cam1", "scan0", "scan1"))}
    two = (mode(0.7, T_exp(np.r_[0, 0, 0, 0.1, 0, 0])), mode(0.3, T_exp(np.r_[0, 0.2, 0, 0.1, 0.3, 0])))
    other = (mode(0.9, T_exp(np.r_[0, 0, 0, 0, 0.1, 0])), mode(0.1, T_exp(np.r_[0.3, 0, 0, 0, 0.1, 0.2])))
    frames = {st: SimpleNamespace(name=st) for st in "abcd"}
    pair_frames = {("cam0", "scan0"): [frames[x] for x in "abc"], ("cam1", "scan0"): [frames[x] for x in "abc"],
                   ("cam1", "scan1"): [frames[x] for x in "ab"], ("cam0", "scan1"): [frames[x] for x in "abd"]}
    boards = {"scan0": dict.fromkeys("abc"), "scan1": dict.fromkeys("abd")}
    minima = {("cam0", "scan0"): two, ("cam1", "scan0"): two, ("cam1", "scan1"): other, ("cam0", "scan1"): other}
    kept = mixable_minima(minima, boards, pair_frames)
    assert list(kept) == [("cam0", "scan0"), ("cam0", "scan1")]
    starts = joint_starts(kept, T, "cam0")
    assert [round(m, 6) for _, m, _ in starts] == [0.63, 0.27, 0.07, 0.03]
    assert [tuple(k for *_, k in cells) for _, _, cells in starts] == [(0, 0), (1, 0), (0, 1), (1, 1)]
    start = starts[3][0]
    np.testing.assert_allclose(start["scan0"], T["cam0"] @ two[1].T_camera_lidar, atol=1e-12)
    np.testing.assert_allclose(start["scan1"], T["cam0"] @ other[1].T_camera_lidar, atol=1e-12)
    assert start["cam1"] is T["cam1"]
    assert joint_starts({("cam0", "scan0"): two}, T, "scan0") == []  # the reference is not moved


def test_a_range_term_its_pair_holds_at_zero_the_rig_holds_too(tmp_path):
    # Returns 20 cm long on a LiDAR whose range accuracy is 5 cm: the pair's offset estimate (+208 mm) lies beyond
    # 3 prior standard deviations, so the pair holds it at 0 with its prior variance propagated into the covariance
    # (range_terms_choice.consider_pinned). The rig of the same folder holds it too (rig_terms.hold_pinned), says
    # so first in its record and warnings, and lands on the pair's estimate within 1e-4 of its standard deviations
    # and on its covariance within 1e-6 of its scale (before, the rig kept the term free: 2.5 sd off along the
    # LiDAR's x, that sd a third narrower). Its posterior gets the held term's share convolved in, as the pair's.
    from estimators.calibration import calibrate_pair
    from estimators.simulation.simulator import simulate_dataset

    folder = simulate_dataset(tmp_path / "long", n_poses=8, seed=2, range_bias=(0.2, 0.0, 0.0))
    pair = calibrate_pair(folder, samples=0, options=RefinementOptions(edges=False))
    assert pair.refinement.range_model.pinned == ("offset",)
    res = calibrate_rig(load_rig(folder), np.random.default_rng(0), advise=False, edges=False, samples=300)
    rec = res.range_models["lidar0"]
    assert rec["held_at_prior"][0]["term"] == "offset" and rec["held_at_prior"][0]["estimate_mm"] > 150
    assert abs(rec["value_m"]) < 1e-6 and rec["sd_m"] == pytest.approx(rec["prior_sd_m"], rel=1e-3)
    assert any("held at 0" in w for w in res.warnings)
    assert "offset held at 0 (estimated +2" in range_model_words(rec)
    # What the pair says of its boards the rig says too, once each, prefixed with the pair (the rig had dropped
    # them: the plane error, the incidence structure, two frames 1.4-1.9 deg and 51-64 mm off); the held term once,
    # by the rig's record.
    said = [w for w in pair.warnings if not (w.startswith("range model: ") and " lie beyond " in w)]
    assert len(said) == len(pair.warnings) - 1 >= 4
    for w in said:
        assert res.warnings.count(f"cam0-lidar0: {w}") == 1, w
    assert sum("held at 0" in w for w in res.warnings) == 1
    # A LiDAR of the same rig without terms (another's held) is left as it is.
    from dataclasses import replace

    from estimators.pipeline.rig_terms import held_views
    plain = replace(res.lidar_views[0], ranged=None, terms=None, terms_prior_sd=None)
    assert held_views([plain], {"lidar0": ("offset",)}) == [plain]
    T, C = res.solution.transform("cam0", "lidar0")
    sd = np.sqrt(np.diag(pair.covariance))
    assert np.all(np.abs(T_log(np.linalg.inv(pair.T_camera_lidar) @ T)) < 1e-4 * sd)
    assert np.max(np.abs(C - pair.covariance) / np.outer(sd, sd)) < 1e-6
    post = np.std(res.pair("cam0", "lidar0").samples, axis=0)
    np.testing.assert_allclose(post, sd, rtol=0.1)


def test_a_frame_its_pair_drops_as_an_outlier_stays_out_of_the_joint_graph_and_the_pairs_take_the_rigs_options(
        sim_vlp16, monkeypatch, capsys):
    # Each camera-LiDAR pair's refinement decides its outlier frames (a wrong LiDAR segment, a board that moved):
    # the joint graph leaves them out too, and says why beside the LiDAR's skipped frames. The solver options a rig
    # takes (--robust, --outliers, --corner-noise-px, --range-noise-m, --max-sensor-separation) reach each pair's
    # solve and the joint graph, the measurement hints (--roi, --no-static-scene) its board search; --init is for a
    # rig with a 2D scanner, an initial guess for a pair.
    # A pair whose own boards leave two answers makes the rig's answer ambiguous, said first.
    from dataclasses import replace

    from estimators import rig_calibration
    from estimators.cli.commands import exit_code
    from estimators.cli.parser import build_parser
    from estimators.cli.printing import print_rig
    from estimators.lidar.board_segmentation import SegmentationParams
    from estimators.pipeline import rig_measurement
    from estimators.pipeline.measurement import Hints
    from estimators.solvers.solution_selection import Mode

    real, seen = rig_calibration.solve, []

    def dropping(frames, *args, **kwargs):
        seen.append(kwargs["options"])
        res = real(frames, *args, **kwargs)
        fits = list(res.refinement.frames)
        fits[0] = replace(fits[0], dropped=True, outlier="its laser line is off the camera's board (a test)")
        # and, as a 2D scanner's few boards can, a second minimum with 30% of the mass
        second = T_exp(np.array([0.05, 0, 0, 0, 0.1, 0])) @ res.T_camera_lidar
        modes = tuple(Mode(T, 0.0, 0.0, 0.0, mass, res.refinement) for T, mass in ((res.T_camera_lidar, 0.7),
                                                                                    (second, 0.3)))
        return replace(res, refinement=replace(res.refinement, frames=tuple(fits)), modes=modes)

    monkeypatch.setattr(rig_calibration, "solve", dropping)
    given = RefinementOptions(robust="cauchy", outliers="downweight", corner_noise_px=0.3, range_noise_m=0.025)
    with pytest.raises(DatasetError, match="is for 2D LiDARs, and this rig has none"):
        calibrate_rig(load_rig(sim_vlp16), np.random.default_rng(0), init="minimal-lower-bound")
    with pytest.raises(DatasetError, match="an initial guess is one camera-LiDAR pair's"):
        calibrate_rig(load_rig(sim_vlp16), np.random.default_rng(0), hints=Hints(initial_guess=np.eye(4)))
    measuring, hinted = rig_measurement.measure_frames, []

    def measure_frames(*args, **kwargs):
        hinted.append(kwargs["hints"])
        return measuring(*args, **kwargs)

    monkeypatch.setattr(rig_measurement, "measure_frames", measure_frames)
    # a rig's initial guess (an earlier calibration.json's transforms) reaches its camera-LiDAR pair's board search
    guess = np.array(json.loads((sim_vlp16 / "ground_truth.json").read_text())["T_camera_lidar"])
    res = calibrate_rig(load_rig(sim_vlp16), np.random.default_rng(0), samples=0, advise=False, range_model="none",
                        options=given, params=SegmentationParams(max_sensor_separation_m=0.8),
                        hints=Hints(static_scene=False, pair_guesses={"T_cam0_lidar0": guess}))
    assert [h.static_scene for h in hinted] == [False] and hinted[0].initial_guess is guess
    first = sorted(res.skipped["lidar0"])
    assert len(first) == 1 and "with cam0: its laser line is off the camera's board (a test)" in res.skipped["lidar0"][
        first[0]]
    assert first[0] not in res.frames_used["lidar0"] and len(res.frames_used["lidar0"]) >= 3
    assert [(o.robust, o.outliers, o.corner_noise_px, o.range_noise_m, o.edges, o.max_sensor_separation_m)
            for o in seen] == [("cauchy", "downweight", 0.3, 0.025, False, 0.8)]
    (cv,), (lv,) = res.camera_views, res.lidar_views
    assert cv.sigma_px == 0.3 and set(cv.sigma_board.values()) == {0.3}
    assert lv.sigma_m == 0.025 and lv.robust.robust == "cauchy"
    # A pair's ambiguity is said first, each mode is recorded, and --strict exits 3
    assert res.ambiguous and res.warnings[0].startswith("cam0-lidar0: 2 distinct solutions fit its boards")
    assert [m["posterior_mass"] for m in res.to_json()["ambiguous_pairs"]["T_cam0_lidar0"]] == [0.7, 0.3]
    capsys.readouterr()
    print_rig(res)
    out = capsys.readouterr().out
    first = out.splitlines()[0]
    assert first.startswith("CHECK: ")
    assert "T_cam0_lidar0: 2 solutions fit its boards (posterior mass 70%, 30%)" in first
    # the dropped frame printed with its reason under its sensor, as a single pair prints its own
    stem = sorted(res.skipped["lidar0"])[0]
    assert "\n  lidar0 " in out and f"\n      {stem}: skipped: {res.skipped['lidar0'][stem]}\n" in out
    assert res.to_json()["verdict"]["level"] == "CHECK"
    from estimators.analysis.report import verdict_part  # the rig's report opens with it, as a single pair's does

    assert "CHECK</b>: " in verdict_part(res) and "T_cam0_lidar0: 2 solutions fit its boards" in verdict_part(res)
    strict = build_parser().parse_args(["calibrate", str(sim_vlp16), "--out", "out", "--strict"])
    assert exit_code(strict, res) == 3


def test_a_rigs_k_fold_scores_each_camera_lidar_pairs_held_out_frames_under_the_others(rig_result):
    """--cross-validate K on a rig: each fold's frames scored, pair by pair, under the rig calibrated from the other
    folds (here every fold's calibration is the whole rig's, so the scores are consistent); a fold whose lidar0 is
    moved 12 of its standard deviations along its weakest direction makes every lidar0 pair's verdict fail and no
    other's."""
    from dataclasses import replace

    from estimators.analysis.validation import cross_validate_rig

    sol, rm = rig_result.solution, rig_result.measurements
    cv = cross_validate_rig(rm, rig_result.rig.board, 3, lambda stems: rig_result)
    assert [f["held_out"] for f in cv["folds"]] == [sorted(rm.stems)[j::3] for j in range(3)]
    assert {"T_cam0_lidar0", "T_cam1_lidar1", "T_cam0_scan0"} <= set(cv["pairs"])
    assert all(v["p_value"] > 1e-3 for v in cv["pairs"].values()), cv["pairs"]
    for f in cv["folds"]:
        assert all(x["name"] in f["held_out"] for scores in f["pairs"].values() for x in scores)
    ev, V = np.linalg.eigh(sol.covariance("lidar0"))
    moved = replace(rig_result, solution=replace(sol, T_ref={
        **sol.T_ref, "lidar0": sol.T_ref["lidar0"] @ T_exp(12 * np.sqrt(ev[-1]) * V[:, -1])}))
    bad = cross_validate_rig(rm, rig_result.rig.board, 3, lambda stems: moved)
    assert all((v["p_value"] < 1e-6) == k.endswith("_lidar0") for k, v in bad["pairs"].items()), bad["pairs"]
    with pytest.raises(LidarcamError, match="--cross-validate 1"):
        cross_validate_rig(rm, rig_result.rig.board, 1, lambda stems: rig_result)


def test_two_halves_of_a_rig_are_tested_against_their_covariances(rig_result):
    # --split on a rig: every sensor's pose of one half against the other's, under the sum of their joint
    # covariances (6 dof per sensor but the reference), and each camera-LiDAR pair alone. Two identical halves
    # agree; lidar0 moved by 12 of its standard deviations along its weakest direction in one half is caught by
    # the joint test (d2 at least 12^2 / 2: the halves' covariances add) and by lidar0's pairs alone (the joint
    # test on 30 dof misses 6 sd). The halves come from the measurements, restricted to their frames.
    from dataclasses import replace

    from estimators.analysis.validation import split_rig_halves

    sol, rm = rig_result.solution, rig_result.measurements
    stems = rm.stems
    half = rm.restricted(stems[0::2])
    assert half.stems == stems[0::2] and half.spawned == ()
    assert all(f.name in stems[0::2] for frames in half.pairs.values() for f in frames)
    ev, V = np.linalg.eigh(sol.covariance("lidar0"))
    moved = replace(sol, T_ref={**sol.T_ref, "lidar0": sol.T_ref["lidar0"] @ T_exp(12 * np.sqrt(ev[-1]) * V[:, -1])})
    halves = iter([rig_result, rig_result, rig_result, replace(rig_result, solution=moved)])
    same = split_rig_halves(stems, lambda part: next(halves), "interleaved")
    assert same["mahalanobis_d2"] < 1e-9 and same["dof"] == 6 * (len(sol.names) - 1)
    assert same["verdict"].startswith("the halves agree") and same["halves"] == [stems[0::2], stems[1::2]]
    apart = split_rig_halves(stems, lambda part: next(halves), "halves")
    assert apart["verdict"].startswith("the halves disagree") and apart["mahalanobis_d2"] > 72 * (1 - 1e-6)
    assert all((v["p_value"] < 1e-6) == k.endswith("_lidar0") for k, v in apart["pairs"].items())
    assert apart["pairs"]["T_cam0_lidar0"]["mahalanobis_d2"] == pytest.approx(72, rel=1e-6)
