"""Measure once, solve many times: measurements.npz/.json round trips, the measurement cache (and a stale
entry after a file changed), and `calibrate --measurements`."""
from __future__ import annotations

import json

import numpy as np
import pytest

from estimators.calibration import calibrate_pair, measure, solve
from estimators.cli import main
from estimators.io.measurement_store import load_measurements, save_measurements


@pytest.fixture()
def cache(tmp_path, monkeypatch):
    folder = tmp_path / "cache"
    monkeypatch.setenv("LIDARCAM_CACHE_DIR", str(folder))
    return folder


def test_the_suite_keeps_its_measurement_cache_out_of_the_users_home(tmp_path_factory):
    # conftest's folder of the run (its test processes share it), which child processes inherit: not
    # ~/.cache/lidarcam or $XDG_CACHE_HOME's
    import os
    from pathlib import Path

    from estimators.io.measurement_store import cache_dir

    base = tmp_path_factory.getbasetemp()
    assert cache_dir().is_relative_to(base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base)
    assert not cache_dir().is_relative_to(Path.home() / ".cache")


@pytest.mark.parametrize("which", ["sim_vlp16", "sim_2d"])
def test_saved_measurements_solve_to_the_same_extrinsic(which, request, tmp_path):
    path = request.getfixturevalue(which)
    m = measure(path, np.random.default_rng(0))
    save_measurements(tmp_path, m)
    back = load_measurements(tmp_path / "measurements.npz")
    assert [f.name for f in back.frames] == [f.name for f in m.frames]
    assert [f.usable for f in back.frames] == [f.usable for f in m.frames]
    assert back.board == m.board and back.lidar == m.lidar
    a = solve(m, rng=np.random.default_rng(1))
    b = solve(back, rng=np.random.default_rng(1))
    np.testing.assert_allclose(b.T_camera_lidar, a.T_camera_lidar, atol=1e-10)
    np.testing.assert_allclose(b.covariance, a.covariance, rtol=1e-8, atol=1e-14)
    assert b.measurements_source.endswith("measurements.npz")
    for f, g in zip(m.frames, back.frames):
        if f.usable:
            for k in ("rings", "open_ends"):
                a_k, b_k = getattr(f.lidar, k), getattr(g.lidar, k)
                assert (a_k is None and b_k is None) or np.array_equal(a_k, b_k)


def test_a_per_point_array_of_another_length_is_a_damaged_measurements_file(sim_vlp16, tmp_path):
    from estimators.errors import DatasetError

    m = measure(sim_vlp16, np.random.default_rng(0))
    save_measurements(tmp_path, m)
    arrays = dict(np.load(tmp_path / "measurements.npz"))
    k = next(k for k in arrays if k.endswith("_lidar_open_ends"))
    arrays[k] = arrays[k][:-1]
    np.savez(tmp_path / "measurements.npz", **arrays)
    with pytest.raises(DatasetError, match="open_ends is not one value per point"):
        load_measurements(tmp_path / "measurements.npz")


def test_cache_is_used_for_the_same_files_and_options_and_not_after_a_file_changed(sim_vlp16, tmp_path, cache):
    import shutil

    ds = tmp_path / "ds"
    shutil.copytree(sim_vlp16, ds)
    first = calibrate_pair(ds, rng=np.random.default_rng(0), posterior=None, cache=True)
    second = calibrate_pair(ds, rng=np.random.default_rng(0), posterior=None, cache=True)
    assert (first.measurements_source, second.measurements_source) == ("measured", "cache")
    np.testing.assert_allclose(second.T_camera_lidar, first.T_camera_lidar, atol=1e-12)
    # Other segmentation seed: another key.
    other = calibrate_pair(ds, rng=np.random.default_rng(5), posterior=None, cache=True)
    assert other.measurements_source == "measured"
    # A scan rewritten (one point moved by 1 mm): the entry is stale and the dataset is measured again.
    from estimators.io.pointcloud_io import read_sweep, write_scan

    scan = sorted(ds.glob("*.pcd"))[0]
    sweep = read_sweep(scan)
    pts = sweep.points.copy()
    pts[0] += 0.001
    write_scan(scan, pts, sweep.intensity, sweep.ring)
    third = calibrate_pair(ds, rng=np.random.default_rng(0), posterior=None, cache=True)
    assert third.measurements_source == "measured"


def test_cli_writes_measurements_and_solves_from_them(sim_vlp16, tmp_path, cache, capsys):
    out1, out2 = tmp_path / "a", tmp_path / "b"
    assert main(["calibrate", str(sim_vlp16), "--out", str(out1), "--samples", "0", "--no-report",
                 "--no-cache"]) == 0
    assert (out1 / "measurements.npz").is_file() and (out1 / "measurements.json").is_file()
    assert main(["calibrate", str(sim_vlp16), "--out", str(out2), "--samples", "0", "--no-report",
                 "--measurements", str(out1 / "measurements.npz")]) == 0
    a, b = (json.loads((o / "calibration.json").read_text()) for o in (out1, out2))
    np.testing.assert_allclose(b["T_camera_lidar"], a["T_camera_lidar"], atol=1e-10)
    assert b["measurements_source"].endswith("measurements.npz")
    capsys.readouterr()
    (out1 / "measurements.json").write_text("{not json")
    assert main(["calibrate", str(sim_vlp16), "--out", str(tmp_path / "c"), "--samples", "0", "--no-report",
                 "--measurements", str(out1 / "measurements.npz")]) == 2
    err = capsys.readouterr().err
    assert "measurements.json: not valid JSON" in err and "lidarcam calibrate" in err
    assert not (tmp_path / "c" / "calibration.json").exists()


def test_a_board_ambiguous_in_its_tilt_keeps_both_tilts_on_disk(sim_2d, tmp_path):
    """A 2D frame whose board's corners fit two tilts alike is stored with both camera observations and their
    corner chi-square excess, so that a re-solve can still try them."""
    from dataclasses import replace

    m = measure(sim_2d, np.random.default_rng(0))
    k = next(i for i, f in enumerate(m.frames) if f.usable)
    cam = m.frames[k].camera
    other = replace(cam, T_camera_board=cam.T_camera_board @ np.diag([1.0, -1.0, -1.0, 1.0]),
                    orientation_excess_chi2=4.5)
    frames = list(m.frames)
    frames[k] = replace(frames[k], camera=None, reason="board pose: ambiguous", camera_alternatives=(cam, other))
    save_measurements(tmp_path, replace(m, frames=tuple(frames)))
    back = load_measurements(tmp_path / "measurements.npz").frames[k]
    assert back.camera is None and len(back.camera_alternatives) == 2
    for a, b in zip(back.camera_alternatives, (cam, other)):
        np.testing.assert_array_equal(a.T_camera_board, b.T_camera_board)
        np.testing.assert_array_equal(a.plane_covariance, b.plane_covariance)
        assert a.orientation_excess_chi2 == b.orientation_excess_chi2


def test_kept_range_term_choices_of_another_form_are_made_again(tmp_path):
    """``choices.json`` beside cached measurements (``solvers.choice_memo``): entries of the expected form are
    recalled, any other (not JSON, not a list of decisions, a model that is not one, a test without its p-value, a
    weak offset without its 6-vector) is left out, to be chosen again."""
    from estimators.io.measurement_store import CHOICES, load_choices, save_choices
    from estimators.solvers.choice_memo import recallable

    good = {"requested": "auto", "chosen": "offset", "reason": "r", "left_out": [], "weak_offset": None,
            "range_accuracy_m": 0.03, "tests": [{"model": "offset", "against": "none", "p_value": 1e-5,
                                                  "included": True}]}
    assert load_choices(tmp_path) == {}
    (tmp_path / CHOICES).write_text("{not json")
    assert load_choices(tmp_path) == {}
    bad = [{**good, "chosen": "rings"}, {**good, "tests": [{"model": "offset", "included": True}]},
           {**good, "weak_offset": {"p_value": 0.01, "offset_mm": 3.0, "with_ring_ends": False,
                                    "difference_tangent": [0.0] * 5}}, "offset"]
    save_choices(tmp_path, {"a": [good], "b": [good, good], "c": [], **{f"bad{k}": [d] for k, d in enumerate(bad)}})
    assert recallable(load_choices(tmp_path)) == {"a": [good], "b": [good, good]}
