"""``calibrate --scene``: a witness of one pair's transform joined to the graph (``solvers.scene_term``), and the
command's choice to join or not (``pipeline.scene_witness``)."""
from __future__ import annotations

import json
from pathlib import Path

import gtsam
import numpy as np
import pytest

from estimators.cli import main
from estimators.errors import DegenerateLayoutError
from estimators.solvers.factor_graph import adjoint
from estimators.solvers.scene_term import join_pair_measurement
from geometry.rotations import R_from_rotvec, T_from_Rt, T_inverse, T_log, T_retract

NAMES = ("cam0", "lidar0")
T_TRUE = T_from_Rt(R_from_rotvec(np.radians([91.0, -2.0, 89.0])), np.array([0.05, -0.20, -0.15]))


def _spd(rng: np.random.Generator, rot_sd: float, trans_sd: float) -> np.ndarray:
    A = rng.normal(size=(6, 6))
    C = A @ A.T / 6 + np.eye(6)
    s = np.r_[np.full(3, rot_sd), np.full(3, trans_sd)]
    return s[:, None] * C * s[None, :]


def _gtsam_fuse(T0, P0, T1, P1):
    """One pose under two Gaussian priors, solved and marginalised by GTSAM: the truth the linear step must meet."""
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    graph.add(gtsam.PriorFactorPose3(0, gtsam.Pose3(T0), gtsam.noiseModel.Gaussian.Covariance(P0)))
    graph.add(gtsam.PriorFactorPose3(0, gtsam.Pose3(T1), gtsam.noiseModel.Gaussian.Covariance(P1)))
    values.insert(0, gtsam.Pose3(T0))
    out = gtsam.LevenbergMarquardtOptimizer(graph, values).optimize()
    return out.atPose3(0).matrix(), gtsam.Marginals(graph, out).marginalCovariance(0)


@pytest.mark.parametrize("reference", ["cam0", "lidar0"])
def test_the_joined_term_is_gtsams_fusion_of_the_two_witnesses(reference):
    """A graph of the camera and the LiDAR with either as the reference, its estimate 0.3 deg and 8 mm off the
    witness's: the Kalman step's pose and covariance are GTSAM's solve of the pose under both Gaussians (within
    2e-5 rad, 2e-6 m and 1% of each standard deviation: second-order terms of a step this small)."""
    rng = np.random.default_rng(5)
    Pb, C = _spd(rng, 0.002, 0.004), _spd(rng, 0.004, 0.006)
    T_meas = T_retract(T_TRUE, np.r_[np.radians([0.2, -0.2, 0.1]), [0.005, -0.006, 0.002]])
    P = np.zeros((12, 12))
    if reference == "cam0":  # the LiDAR's pose is the free one: T_ref = T_camera_lidar
        T_ref = {"cam0": np.eye(4), "lidar0": T_TRUE}
        P[6:, 6:] = Pb
        T_want, C_want = _gtsam_fuse(T_TRUE, Pb, T_meas, C)
    else:  # the camera's is: T_ref = T_lidar_camera, whose witness is T_meas^-1 with the covariance carried over
        T_ref = {"cam0": T_inverse(T_TRUE), "lidar0": np.eye(4)}
        P[:6, :6] = Pb
        Ad = adjoint(T_meas)
        T_want, C_want = _gtsam_fuse(T_inverse(T_TRUE), Pb, T_inverse(T_meas), Ad @ C @ Ad.T)
    term = join_pair_measurement(NAMES, T_ref, P, "cam0", "lidar0", T_meas, C)
    k = NAMES.index("lidar0" if reference == "cam0" else "cam0")
    T_got = T_retract(T_ref[NAMES[k]], term.dx[6 * k:6 * k + 6])
    xi = T_log(T_inverse(T_want) @ T_got)
    assert np.linalg.norm(xi[:3]) < 2e-5 and np.linalg.norm(xi[3:]) < 2e-6
    sd_got = np.sqrt(np.diag(term.covariance[6 * k:6 * k + 6, 6 * k:6 * k + 6]))
    np.testing.assert_allclose(sd_got, np.sqrt(np.diag(C_want)), rtol=0.01)
    assert term.dof == 6 and 0.0 < term.p_value < 1.0


def test_samples_moved_by_the_term_have_the_joint_covariance_and_a_free_direction_is_not_measured():
    """20 000 draws of the graph's covariance moved by the gain have the joint covariance (within 5% of each
    standard deviation); a witness whose rotation about one axis is 5 degrees uncertain measures 5 directions."""
    rng = np.random.default_rng(7)
    P = np.zeros((12, 12))
    P[6:, 6:] = _spd(rng, 0.002, 0.004)
    T_ref = {"cam0": np.eye(4), "lidar0": T_TRUE}
    term = join_pair_measurement(NAMES, T_ref, P, "cam0", "lidar0", T_TRUE, _spd(rng, 0.003, 0.005))
    xi = rng.multivariate_normal(np.zeros(12), P, 20000, method="eigh")
    moved = term.moved_samples(xi, rng)
    np.testing.assert_allclose(np.sqrt(np.diag(np.cov(moved, rowvar=False)))[6:],
                               np.sqrt(np.diag(term.covariance))[6:], rtol=0.05)
    C = np.diag(np.r_[np.radians([5.0, 0.1, 0.1]) ** 2, np.full(3, 0.005 ** 2)])
    assert join_pair_measurement(NAMES, T_ref, P, "cam0", "lidar0", T_TRUE, C).dof == 5


def _office_with_scene(path: "Path") -> None:
    """Seed 3's simulated office (64-beam LiDAR, ten board poses) into ``path/ds``, and its ``calibrate --scene``
    (no posterior, no report) into ``path/out`` with its exit code and printout beside (``printed.json``)."""
    import contextlib
    import io

    from estimators.simulation.simulator import simulate_dataset

    simulate_dataset(path / "ds", n_poses=10, seed=3, lidar="os64", scene="office")
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        code = main(["calibrate", str(path / "ds"), "--out", str(path / "out"), "--scene", "--samples", "0",
                     "--no-report"])
    (path / "printed.json").write_text(json.dumps([code, printed.getvalue()]))


@pytest.fixture(scope="module")
def office(tmp_path_factory):
    """The office (``_office_with_scene``: made once for every test process; tests write elsewhere) and its
    truth."""
    from .conftest import shared_folder

    tmp = shared_folder(tmp_path_factory, "scene_joint_office", _office_with_scene)
    return tmp, np.array(json.loads((tmp / "ds" / "ground_truth.json").read_text())["T_camera_lidar"])


@pytest.fixture(scope="module")
def office_scene(office):
    """``calibrate --scene`` of the office into ``out``: its exit code and printout."""
    return tuple(json.loads((office[0] / "printed.json").read_text()))


def test_a_scene_that_agrees_is_joined_and_keeps_the_boards_verdict(office, office_scene):
    """Seed 3's office, the board left out: the scene agrees with the boards (which are within 0.05 deg of the
    truth) along their weak direction and over every direction, and is joined: the verdict stays OK, both tests
    are in the record, the joint estimate is calibration.json's (within 0.05 deg of the truth, its standard
    deviation along the weak direction no larger than the boards'), and the printout shows the boards', the
    scene's and the joint estimates along it. (Before each contour was measured along its ring, the scene's
    estimate lay 0.3 deg off here and disagreed over every direction.)"""
    tmp, truth = office
    code, out = office_scene
    assert code == 0 and out.startswith("OK\n")
    assert "  boards " in out and "  scene " in out and "  joint " in out and "joined: the estimates" in out
    got = json.loads((tmp / "out" / "calibration.json").read_text())
    record = got["scene"]["T_cam0_lidar0"]
    tests = record["boards_against_scene"]
    assert record["joined"] is True and tests["every_direction"]["p_value"] > 0.01
    assert tests["along_weak_direction"]["p_value"] > 0.01 and tests["along_weak_direction"]["dof"] == 1
    T = np.array(got["T_camera_lidar"])
    np.testing.assert_allclose(T, np.array(record["joint"]["T_camera_lidar"]))
    assert np.degrees(np.linalg.norm(T_log(T_inverse(T) @ truth)[:3])) < 0.05
    sds = {w["estimate"]: w["sd_mm"] for w in record["along_weak_direction_mm"]}
    assert sds["joint"] <= sds["boards"] + 1e-9


def test_boards_moved_or_turned_are_contradicted_by_the_scene(office, monkeypatch):
    """The same office's board calibration moved by 10 cm along its weak direction: the scene's check from there
    puts the LiDAR back, the scene and the boards disagree, the verdict is CHECK naming it, and the moved estimate
    is not joined. Turned by 1 degree about the camera's y (its translation kept, so that along the weak direction
    the two may agree): the same, through the test over every direction."""
    from dataclasses import replace

    import estimators as lc

    tmp, _ = office
    result = lc.calibrate(tmp / "ds", rng=np.random.default_rng(3), posterior=None)
    sol = result.solution
    pair = result.pair("cam0", "lidar0")
    u = lc.SceneWitness("cam0", "lidar0", pair.T, pair.covariance).weak_direction()
    moved_T = sol.T_ref["lidar0"].copy()
    moved_T[:3, 3] += 0.10 * u
    turned_T = sol.T_ref["lidar0"].copy()
    turned_T[:3, :3] = R_from_rotvec(np.radians(1.0) * np.array([0.0, 1.0, 0.0])) @ turned_T[:3, :3]
    # the scene's check leaves the board out where the calibration found it, without searching the images again
    # (``detect_corners`` keeps each search by the image's pixels: a search made is a call of the detector)
    from estimators.camera import corners

    searched = []
    detect = corners.detect_chessboard
    monkeypatch.setattr(corners, "detect_chessboard", lambda *a, **k: searched.append(1) or detect(*a, **k))
    for T in (moved_T, turned_T):
        off = replace(result, solution=replace(sol, T_ref={**sol.T_ref, "lidar0": T}))
        checked = lc.with_scene(off, np.random.default_rng(0))
        w = checked.scene[("cam0", "lidar0")]
        assert w.contradicts and not w.joined and min(w.term.p_value, w.overall.p_value) < 0.01
        assert checked.verdict.level == "CHECK" and "the scene puts the LiDAR" in checked.verdict.line
        np.testing.assert_allclose(checked.T_camera_lidar, T)
    assert not searched


def test_scene_is_refused_where_it_has_no_boards_or_no_graph(office, capsys, tmp_path):
    """--scene with --targetless, or with --refine none: exit 2, one line, nothing written."""
    tmp, _ = office
    for extra in (["--targetless", "--initial-guess", "0 0 0 0 0 0"], ["--refine", "none"]):
        assert main(["calibrate", str(tmp / "ds"), "--out", str(tmp_path / "x"), "--scene", *extra]) == 2
        err = capsys.readouterr().err.strip()
        assert err.count("\n") == 0 and "--scene" in err and not (tmp_path / "x").exists()


def _as_rig(pair: "Path", out: "Path") -> "Path":
    """A camera-LiDAR folder written as the rig folder of its ``cam0`` and ``lidar0`` (the same files)."""
    import shutil

    import yaml

    spec = yaml.safe_load((pair / "dataset.yaml").read_text())
    sensors = [{"name": "cam0", "type": "camera", **spec["camera"]}, {"name": "lidar0", "type": "lidar", "lidar": "3d"}]
    (out / "cam0").mkdir(parents=True)
    (out / "lidar0").mkdir()
    for f in pair.iterdir():
        if f.suffix in (".png", ".pcd"):
            shutil.copy(f, out / ("cam0" if f.suffix == ".png" else "lidar0") / f.name)
    (out / "dataset.yaml").write_text(yaml.safe_dump({"board": spec["board"], "sensors": sensors}))
    return out


def test_a_rig_folder_takes_check_and_scene_as_its_pair_folder_does(office, office_scene, capsys, tmp_path,
                                                                    monkeypatch):
    """Seed 3's office as a rig folder of cam0 and lidar0: ``calibrate --scene`` forms the same scene term as on
    the pair folder (the same boards' and scene's estimates and tests, to 1e-9), and ``check`` of the boards'
    transform on the rig folder (cam0 and its LiDAR) gives the pair's p-value; given the rig's calibration.json
    (its transforms found by the sensors' names), a sensor the rig has not is refused in one line (exit 2); and
    ``--targetless`` given that file starts from its first pair's transform."""
    tmp, _ = office
    rig = _as_rig(tmp / "ds", tmp_path / "rig")
    assert office_scene[0] == 0
    assert main(["calibrate", str(rig), "--out", str(tmp_path / "rig_out"), "--scene", "--samples", "0",
                 "--no-report"]) == 0
    capsys.readouterr()
    a = json.loads((tmp / "out" / "calibration.json").read_text())["scene"]["T_cam0_lidar0"]
    b = json.loads((tmp_path / "rig_out" / "calibration.json").read_text())["scene"]["T_cam0_lidar0"]
    np.testing.assert_allclose(a["T_camera_lidar_boards"], b["T_camera_lidar_boards"], atol=1e-9)
    np.testing.assert_allclose(a["scene"]["T_camera_lidar"], b["scene"]["T_camera_lidar"], atol=1e-9)
    for key in ("along_weak_direction", "every_direction"):
        assert a["boards_against_scene"][key]["p_value"] == pytest.approx(b["boards_against_scene"][key]["p_value"])
    assert a["joined"] == b["joined"] and a["scene"]["check_p_value"] == pytest.approx(b["scene"]["check_p_value"])
    given = str(tmp_path / "rig_out" / "calibration.json")
    boards = tmp_path / "boards.json"  # the transform the term's check was made from (the file's is the joint one)
    boards.write_text(json.dumps({"T_camera_lidar": b["T_camera_lidar_boards"]}))
    code = main(["check", str(rig), "--calibration", str(boards), "--camera", "cam0", "--out",
                 str(tmp_path / "rig_check")])
    out = capsys.readouterr().out
    got = json.loads((tmp_path / "rig_check" / "check.json").read_text())
    assert code == (0 if got["consistent"] else 4) and got["camera"] == "cam0" and got["lidar"] == "lidar0"
    assert "cam0 and lidar0: p = " in out
    assert got["p_value"] == pytest.approx(b["scene"]["check_p_value"], rel=1e-9)
    assert main(["check", str(rig), "--calibration", given, "--camera", "cam7", "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "the rig has no camera 'cam7'" in err and not (tmp_path / "x").exists()
    # --targetless on the rig folder starts from its first pair's transform in the rig's calibration.json, under
    # that calibration's intrinsics of its first camera
    import estimators.pipeline.targetless as targetless

    started = []

    def stop(folder, T_guess, keep_board=False, camera=None):
        started.append((T_guess, camera))
        raise DegenerateLayoutError("stopped here")

    monkeypatch.setattr(targetless, "calibrate_targetless", stop)
    assert main(["calibrate", str(rig), "--targetless", "--initial-guess", given, "--out", str(tmp_path / "y")]) == 2
    cal = json.loads(Path(given).read_text())
    assert len(started) == 1 and np.allclose(started[0][0], cal["transforms"]["T_cam0_lidar0"]["T"])
    assert np.allclose(started[0][1].K, cal["cameras"]["cam0"]["K"]) and "calibration.json" in started[0][1].source
    assert "stopped here" in capsys.readouterr().err


def test_a_two_camera_rig_in_a_furnished_room_checks_each_pair_and_forms_each_pairs_term(tmp_path, capsys):
    """A rig of two cameras and a 64-beam LiDAR in a furnished room (seed 3, six frames; the second camera
    renders the same room): ``check`` of the second camera's true transform is consistent and of it turned by 1
    degree about that camera's y contradicted (exit 4); ``calibrate --scene`` forms the term of both pairs, the
    second on the estimate the first left, each with both tests, and writes each pair's page in its folder."""
    from estimators.simulation.rig_simulator import simulate_rig

    rig = simulate_rig(tmp_path / "rig", n_poses=6, seed=3, cameras=2, scene="furnished")
    truth = json.loads((rig / "ground_truth.json").read_text())
    T = T_inverse(np.array(truth["T_cam0_cam1"])) @ np.array(truth["T_cam0_lidar0"])
    turned = T_from_Rt(R_from_rotvec(np.radians([0.0, 1.0, 0.0])), np.zeros(3)) @ T
    for name, T_given, code in (("true", T, 0), ("turned", turned, 4)):
        (tmp_path / f"{name}.json").write_text(json.dumps({"transforms": {"T_cam1_lidar0": {"T": T_given.tolist()}}}))
        assert main(["check", str(rig), "--camera", "cam1", "--calibration", str(tmp_path / f"{name}.json"),
                     "--out", str(tmp_path / name)]) == code
    assert main(["calibrate", str(rig), "--scene", "--samples", "0", "--out", str(tmp_path / "cal")]) == 0
    out = capsys.readouterr().out
    assert "the scene's term for T_cam0_lidar0" in out and "the scene's term for T_cam1_lidar0" in out
    scene = json.loads((tmp_path / "cal" / "calibration.json").read_text())["scene"]
    assert set(scene) == {"T_cam0_lidar0", "T_cam1_lidar0"}
    assert all(set(w["boards_against_scene"]) == {"along_weak_direction", "every_direction"} for w in scene.values())
    assert all((tmp_path / "cal" / f"scene_{c}_lidar0" / "scene_check.html").is_file() for c in ("cam0", "cam1"))
