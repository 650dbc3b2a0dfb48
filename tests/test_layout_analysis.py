"""Layout analysis: predicted uncertainty from the Fisher information, degenerate plans explained, and
suggested poses that help (measurement-level model; fixed seeds)."""
from __future__ import annotations

import json

import numpy as np
import pytest
import yaml

from estimators.analysis.layout_analysis import analyse, layout_from_plan, suggest_poses, turned_boards
from estimators.cli import main
from estimators.errors import DatasetError
from estimators.solvers.observation_model import cramer_rao_bound
from estimators.solvers.refinement_options import RefinementOptions
from geometry.rotations import R_from_rotvec, T_from_Rt

PLAN = {
    "camera": {"model": "pinhole", "width": 1024, "height": 768, "K": [[940, 0, 512], [0, 940, 384], [0, 0, 1]],
               "dist": [-0.1, 0.06, 0, 0, 0]},
    "board": {"squares": [9, 7], "square_size": 0.1, "size": [1.0, 1.0]},
    "lidar": {"model": "hdl64e", "range_noise_m": 0.02},
    "corner_noise_px": 0.2,
    "poses": [{"centre_m": [-0.6, 0.0, 3.0], "tilt_deg": 30, "azimuth_deg": 0},
              {"centre_m": [0.6, 0.0, 3.0], "tilt_deg": 30, "azimuth_deg": 120},
              {"centre_m": [0.0, 0.3, 3.5], "tilt_deg": 30, "azimuth_deg": 240},
              {"centre_m": [0.0, -0.2, 4.0], "tilt_deg": 20, "azimuth_deg": 60}],
}


def test_predicted_covariance_is_the_cramer_rao_bound_and_leverage_sums_sensibly():
    layout, _ = layout_from_plan(PLAN)
    a = analyse(layout)
    np.testing.assert_allclose(a.covariance, cramer_rao_bound(layout), rtol=1e-6, atol=1e-15)
    assert np.all(np.isfinite(a.std_translation_mm)) and a.condition_number < 10
    assert np.all((a.leverage > 0) & (a.leverage <= 1))


def test_degenerate_plan_is_explained_not_crashed_on():
    """Boards turned only about the camera's vertical axis (normals in its x-z plane): translation along
    camera y cannot be observed."""
    poses = []
    for x, yaw in ((-0.6, -30.0), (0.6, 25.0), (0.0, 5.0)):
        R = R_from_rotvec([0.0, np.deg2rad(yaw), 0.0])
        poses.append({"T_camera_board": T_from_Rt(R, np.array([x, 0.0, 3.0]) - R @ [0.5, 0.5, 0.0]).tolist()})
    layout, _ = layout_from_plan(dict(PLAN, poses=poses))
    a = analyse(layout)
    assert "camera y" in a.weakest_words and "unobservable" in a.weakest_words
    assert not np.all(np.isfinite(a.std_translation_mm))
    assert "unobservable" in a.format()


def test_one_pose_planned_three_times_is_unobservable_with_its_edges_too(tmp_path):
    """The edges' bound of a layout that leaves directions free prints them unobservable, as the planes' does (it
    printed standard deviations of 14 km), and the JSON says null, not Infinity."""
    layout, _ = layout_from_plan(dict(PLAN, poses=[PLAN["poses"][0]] * 3))
    a = analyse(layout)
    assert not np.all(np.isfinite(a.edges["translation_std_mm"]))
    assert "unobservable" in a.format().splitlines()[-1] or "unobservable" in a.format().splitlines()[-2]
    text = json.dumps(a.to_dict())
    assert "Infinity" not in text and None in json.loads(text)["predicted_std"]["translation_mm_along_lidar_xyz"]


def test_planned_poses_the_camera_cannot_find_the_board_in_are_refused():
    """A pose's board seen edge-on, too far for its squares to resolve, or partly outside the image predicts
    information no recording holds: the plan is refused naming the pose."""
    for change, words in (({"tilt_deg": 85}, "from face-on"), ({"centre_m": [0.0, 0.0, 400.0]}, "px in the image"),
                          ({"centre_m": [3.0, 0.0, 3.0]}, "outside the image")):
        poses = [dict(PLAN["poses"][0], **change)] + PLAN["poses"][1:]
        with pytest.raises(DatasetError, match=rf"pose 1: .*{words}"):
            layout_from_plan(dict(PLAN, poses=poses))


def test_suggested_pose_lowers_the_predicted_uncertainty():
    layout, rig = layout_from_plan(dict(PLAN, poses=PLAN["poses"][:3]))
    before = analyse(layout)
    (T, after), = suggest_poses(layout, rig, 1, np.random.default_rng(0), candidates=40)
    assert after.d_optimality > before.d_optimality
    assert np.all(after.std_translation_mm <= before.std_translation_mm + 1e-9)
    assert T.shape == (4, 4) and 2.0 <= np.linalg.norm(T[:3, :3] @ rig.board.centre + T[:3, 3]) <= 5.5


def test_upright_boards_are_told_to_turn_about_their_normals_when_their_edges_would_gain(tmp_path, capsys):
    # Upright boards tilted a little, before a VLP-16: the rings leave them by their left and right sides only,
    # so the edges fix the translation along the boards' height poorly. Turned 45 degrees about their normals,
    # every ring leaves by slanted sides.
    poses = [{"centre_m": [x, y, z], "tilt_deg": tilt, "azimuth_deg": az, "spin_deg": 0}
             for x, y, z, tilt, az in ((-0.8, 0.1, 3.0, 8, 0), (0.8, 0.0, 3.5, 10, 90), (0.0, 0.2, 4.0, 6, 180),
                                       (-0.4, -0.1, 4.5, 12, 270), (0.5, 0.1, 3.0, 5, 45), (0.0, 0.0, 5.0, 9, 135))]
    plan = dict(PLAN, lidar={"model": "vlp16", "range_noise_m": 0.02}, poses=poses)
    layout, _ = layout_from_plan(plan)
    turned = turned_boards(layout)
    c = layout.board.centre
    for T, U in zip(layout.T_camera_board, turned.T_camera_board):
        np.testing.assert_allclose(U[:3, :3] @ c + U[:3, 3], T[:3, :3] @ c + T[:3, 3], atol=1e-12)  # same centre
        np.testing.assert_allclose(U[:3, 2], T[:3, 2], atol=1e-12)                               # same normal
        x0 = np.array([1.0, 0.0, 0.0]) - U[0, 2] * U[:3, 2]
        assert abs(np.degrees(np.arccos(U[:3, 0] @ x0 / np.linalg.norm(x0))) - 45.0) < 1e-6
    edges = analyse(layout).edges
    suggestion = edges["turned_45_deg"]
    assert np.linalg.norm(suggestion["translation_std_mm"]) < 0.8 * np.linalg.norm(edges["translation_std_mm"])
    path = tmp_path / "plan.yaml"
    path.write_text(yaml.safe_dump(plan))
    assert main(["layout", str(path)]) == 0
    assert "with every board turned 45 degrees about its normal" in capsys.readouterr().out
    # Boards already turned 45 degrees gain nothing more: no suggestion.
    diamond = dict(plan, poses=[dict(p, spin_deg=45) for p in poses])
    assert "turned_45_deg" not in analyse(layout_from_plan(diamond)[0]).edges


def test_cli_layout_plan_writes_json_and_rejects_bad_plans(tmp_path, capsys):
    plan = tmp_path / "plan.yaml"
    plan.write_text(yaml.safe_dump(PLAN))
    assert main(["layout", str(plan), "--json", str(tmp_path / "a.json")]) == 0
    data = json.loads((tmp_path / "a.json").read_text())
    assert len(data["frames"]) == 4 and len(data["predicted_std"]["translation_mm_along_lidar_xyz"]) == 3
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump({"board": PLAN["board"]}))
    assert main(["layout", str(bad)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "bad.yaml" in err[0] and "invalid plan" in err[0]
    with pytest.raises(SystemExit) as exit_:  # each suggestion is a search of its own: a thousand would not end
        main(["layout", str(plan), "--suggest", "1000"])
    assert exit_.value.code == 2 and "expected a whole number from 0 to 40" in capsys.readouterr().err


def test_cli_layout_on_a_measured_dataset_predicts_its_refined_covariance(sim_hdl64e, tmp_path):
    """For measured frames the analysis uses the refinement's poses, noise levels and board points: its
    prediction is the Laplace covariance of the same data (the same model, linearised alike)."""
    from estimators.calibration import calibrate_pair
    from estimators.io.dataset import load_dataset

    assert main(["layout", str(sim_hdl64e), "--json", str(tmp_path / "m.json")]) == 0
    data = json.loads((tmp_path / "m.json").read_text())
    assert len(data["frames"]) == 8
    # The prediction is the planes' (the edges' is beside it, ``with_edges``): the planes' refinement.
    result = calibrate_pair(load_dataset(sim_hdl64e), rng=np.random.default_rng(0), posterior=None,
                       options=RefinementOptions(edges=False))
    np.testing.assert_allclose(data["predicted_std"]["translation_mm_along_lidar_xyz"], result.std_translation_mm,
                               rtol=0.1)
    np.testing.assert_allclose(data["predicted_std"]["rotation_deg_about_lidar_xyz"], result.std_rotation_deg,
                               rtol=0.1)
