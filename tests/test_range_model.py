"""The LiDAR range model (issue 16): the augmented sufficient statistics, recovery of an injected range offset
against simulated truth, the model test, and validation (held-out scores, two halves)."""
from __future__ import annotations

import json
from dataclasses import replace

import numpy as np

from estimators.analysis.validation import cross_validate, score_frames, split_halves
from estimators.calibration import solve
from estimators.cli import main
from estimators.measurements import observe_lidar_board
from estimators.simulation.simulator import default_rig, sample_board_poses
from estimators.solvers.closed_form import solve_closed_form
from estimators.solvers.observation_model import Layout, simulate_measurements
from estimators.solvers.range_model import RangeTerms, frame_whitener, terms_for
from estimators.solvers.refinement import measurement_model_options, refine
from geometry.rotations import T_inverse, T_log


def _frames(seed: int, offset_m: float, n: int = 10):
    """Measurement-level frames whose ranges are all lengthened by ``offset_m`` (measured = true + offset)."""
    rng = np.random.default_rng(seed)
    rig = default_rig(rng)
    layout = Layout(rig.camera, rig.board, rig.beams, rig.T_camera_lidar, tuple(sample_board_poses(rig, n, rng)),
                    0.2, 0.02)
    frames = simulate_measurements(layout, np.random.default_rng(seed + 1))
    out = []
    for f in frames:
        P = f.lidar.points
        r = np.linalg.norm(P, axis=1, keepdims=True)
        out.append(replace(f, lidar=observe_lidar_board(P * (r + offset_m) / r)))
    return layout, out


def _refine(layout, frames, model: str):
    T0 = solve_closed_form([f.camera.plane for f in frames], [f.lidar.plane for f in frames]).T_camera_lidar
    return refine(frames, layout.board, layout.camera, T0, measurement_model_options(range_model=model))


def test_augmented_moment_square_root_is_exact_for_any_plane_and_offset():
    rng = np.random.default_rng(3)
    P = rng.normal(size=(200, 3)) * [0.4, 0.3, 0.01] + [3.0, 0.5, 0.2]
    obs = observe_lidar_board(P)
    terms = RangeTerms(("offset",), (0.05,))
    fw = frame_whitener(obs, 0.0, terms)
    beams = P / np.linalg.norm(P, axis=1, keepdims=True)
    c = np.maximum(np.abs(beams @ obs.plane.normal), 0.1)
    for _ in range(5):
        n = obs.plane.normal + rng.normal(0, 0.05, 3)
        n /= np.linalg.norm(n)
        pi = np.append(n, -(obs.plane.distance + rng.normal(0, 0.05)))
        beta = rng.normal(0, 0.03, 1)
        # Cost straight from the points: range-weighted residual less the offset's plane shift.
        direct = np.sum(((P @ pi[:3] + pi[3]) / c - beta[0] * np.mean(c) / c) ** 2)
        theta = np.concatenate([pi, beta])
        assert abs(np.sum((fw.W @ theta) ** 2) + fw.floor - direct) < 1e-9 * max(direct, 1.0)


def test_injected_range_offset_is_recovered_within_its_interval_and_the_extrinsic_stays_unbiased():
    hits, d2s = 0, []
    for seed in range(6):
        layout, frames = _frames(100 + seed, 0.03)
        ref = _refine(layout, frames, "offset")
        fit = ref.range_model
        assert fit.chosen == "offset" and fit.names == ("offset",)
        hits += abs(fit.values_m[0] - 0.03) <= 1.96 * fit.std_m[0]
        xi = T_log(T_inverse(ref.T_camera_lidar) @ layout.T_camera_lidar)
        d2s.append(float(xi @ np.linalg.solve(ref.covariance, xi)))
    # 95% intervals: at least 5 of 6 (a 97% binomial bound); the truth's distance under the marginal
    # covariance stays chi-square(6)-like (mean 6; a limit of 3 x 6 catches an unmodelled bias).
    assert hits >= 5
    assert np.mean(d2s) < 18


def test_without_the_offset_model_an_injected_offset_biases_the_extrinsic():
    layout, frames = _frames(200, 0.03)
    ref = _refine(layout, frames, "none")
    xi = T_log(T_inverse(ref.T_camera_lidar) @ layout.T_camera_lidar)
    assert float(xi @ np.linalg.solve(ref.covariance, xi)) > 30


def test_auto_keeps_the_model_without_terms_on_unbiased_data():
    fits = [_refine(*_frames(300 + s, 0.0), "auto").range_model for s in range(5)]
    assert [f.chosen for f in fits].count("none") >= 4  # 1% test: a false inclusion in 5 trials is unlikely
    assert all(f.tests and f.tests[0]["model"] == "offset" for f in fits)


def test_per_ring_terms_need_rings_and_fall_back_to_the_offset():
    from estimators.solvers.range_model import FrameLabels

    labels = FrameLabels((None, None), (None, None))
    assert terms_for("per-ring", labels).names == ("offset",)
    labels = FrameLabels((np.array([0, 0, 3]), np.array([3, 5])), (None, None))
    terms = terms_for("per-ring", labels)
    assert terms.names == ("offset", "ring 0", "ring 3", "ring 5") and terms.rings == (0, 3, 5)


def test_split_halves_and_cross_validation_agree_on_a_consistent_simulation():
    layout, frames = _frames(500, 0.0, n=12)

    def solve_subset(fs):
        return solve(fs, layout.board, layout.camera, options=measurement_model_options())

    sh = split_halves(frames, solve_subset)
    assert sh["mahalanobis_d2"] <= sh["limit_99"], sh
    cv = cross_validate(frames, layout.board, layout.camera, 3, solve_subset)
    assert cv["p_value"] > 0.01 and cv["dof"] == 36


def test_held_out_frames_of_a_biased_sensor_are_flagged():
    layout, frames = _frames(600, 0.0, n=12)
    res = solve(frames[:8], layout.board, layout.camera, options=measurement_model_options())
    ref = res.refinement
    good = score_frames(frames[8:], layout.board, layout.camera, res.T_camera_lidar, ref.covariance,
                        ref.corner_noise_px, ref.range_noise_m)
    moved = res.T_camera_lidar.copy()
    moved[:3, 3] += [0.03, 0.0, 0.0]  # a calibration 3 cm off along the camera's x
    bad = score_frames(frames[8:], layout.board, layout.camera, moved, ref.covariance, ref.corner_noise_px,
                       ref.range_noise_m)
    assert sum(s.chi2 for s in good) < sum(s.chi2 for s in bad)
    assert sum(s.flagged for s in bad) >= 2 and sum(s.flagged for s in good) <= 1


def test_cli_validate_and_split_write_validation_json(sim_hdl64e, tmp_path):
    out = tmp_path / "cal"
    assert main(["calibrate", str(sim_hdl64e), "--out", str(out), "--samples", "0", "--no-report",
                 "--split", "halves", "--range-model", "auto"]) == 0
    data = json.loads((out / "validation.json").read_text())
    assert data["split_halves"]["mahalanobis_d2"] >= 0 and "verdict" in data["split_halves"]
    cal = json.loads((out / "calibration.json").read_text())
    assert cal["lidar_range_model"]["requested"] == "auto"
    assert main(["validate", str(sim_hdl64e), "--calibration", str(out), "--out", str(tmp_path / "v")]) == 0
    v = json.loads((tmp_path / "v" / "validation.json").read_text())
    assert v["frames"] and "NOT held out" in v["held_out"]


def test_cli_validate_names_a_broken_calibration(sim_hdl64e, tmp_path, capsys):
    bad = tmp_path / "calibration.json"
    bad.write_text("{}")
    assert main(["validate", str(sim_hdl64e), "--calibration", str(bad)]) == 2
    assert "calibration.json" in capsys.readouterr().err
