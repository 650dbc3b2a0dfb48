"""Solver-comparison studies: spec validation, a tidy CSV scored against the truth and the bound, and the
same rows from local processes and from a Dask LocalCluster."""
from __future__ import annotations

import csv
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from estimators.analysis.study import COLUMNS, parse_spec, run_study
from estimators.errors import DatasetError

SPEC = {"name": "tiny", "lidar": "3d", "solvers": ["closed-form", "factor-graph"], "frames": [4, 6],
        "range_noise_m": [0.02], "trials": 2, "seed": 3}


def _read(path: Path) -> list[dict]:
    with open(path) as fh:
        return list(csv.DictReader(fh))


def test_spec_errors_name_the_key():
    with pytest.raises(DatasetError, match="unknown solver"):
        parse_spec({"solvers": ["magic"]})
    with pytest.raises(DatasetError, match="from 3 to"):
        parse_spec({"frames": [2]})
    with pytest.raises(DatasetError, match="range_noise_m"):
        parse_spec({"range_noise_m": ["loud"]})
    # values a simulation cannot be drawn at, or that would run the defaults in silence: refused, naming the key
    # (negative, zero, NaN or infinite noise raised numpy's errors from inside a trial; a typo'd key or 3.7 frames
    # ran something else than was asked, a trial count of 1e8 filled the memory before the first trial)
    for bad, key in (({"range_noise_m": -0.01}, "range_noise_m"), ({"range_noise_m": float("nan")}, "range_noise_m"),
                     ({"corner_noise_px": 0}, "corner_noise_px"), ({"corner_noise_px": 50}, "corner_noise_px"),
                     ({"seed": -5}, "seed"), ({"frames": [3.7]}, "frames"), ({"trials": 100_000_000}, "trials"),
                     ({"trails": 5}, "unknown key"), ({"frames": list(range(3, 1000)), "trials": 2000}, "more than")):
        with pytest.raises(DatasetError, match=key):
            parse_spec(bad)
    assert parse_spec({"seed": 2 ** 53 + 1, "frames": 4.0}).seed == 2 ** 53 + 1
    spec = parse_spec({"lidar": "2d", "frames": 5})
    assert spec.solvers == ("minimal-min-residual", "minimal-lower-bound", "minimal-lower-bound-no-extent")
    assert spec.range_noise_m == (0.01,) and spec.frames == (5,)


def test_local_and_dask_runs_give_identical_rows(tmp_path):
    """2 cells x 2 trials x 2 solvers: every row scored, errors against the truth consistent with the bound,
    the factor graph at least as accurate as the closed form on average, and a Dask LocalCluster returns
    exactly the local rows (times aside)."""
    distributed = pytest.importorskip("distributed")
    spec = parse_spec(SPEC)
    local = run_study(spec, tmp_path / "local", workers=1, progress=False)
    assert len(local) == spec.n_trials * 2 == 8
    rows = _read(tmp_path / "local" / "study.csv")
    assert list(rows[0]) == list(COLUMNS) and len(rows) == 8
    assert all(r["ok"] == "1" for r in rows)
    for name in ("summary.json", "errors_vs_frames.png", "errors_vs_noise.png", "time.png"):
        assert (tmp_path / "local" / name).stat().st_size > 0
    fg = [r for r in local if r["solver"] == "factor-graph"]
    cf = [r for r in local if r["solver"] == "closed-form"]
    # Errors over the bound: a few sigma at most; the refinement's d2 is finite and not absurd.
    assert max(r[f"err_over_bound_{a}"] for r in fg for a in ("rot_x", "trans_z")) < 5.0
    assert all(0.0 <= r["d2"] < 40.0 for r in fg) and all(np.isnan(r["d2"]) for r in cf)
    assert np.mean([r["trans_err_mm"] for r in fg]) <= np.mean([r["trans_err_mm"] for r in cf]) * 1.2

    # one worker process: the rows travel through the scheduler all the same (a second costs its interpreter)
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster, \
            distributed.Client(cluster) as client:
        remote = run_study(spec, tmp_path / "dask", scheduler=client, progress=False)
    def strip(rows):  # repr: NaN (no covariance) must compare equal to NaN
        return [{k: repr(v) for k, v in r.items() if k != "seconds"} for r in rows]

    assert strip(local) == strip(remote)


def test_cli_study_runs_a_spec_and_refuses_a_bad_one(tmp_path):
    spec = tmp_path / "spec.yaml"
    spec.write_text("lidar: 2d\nframes: [4]\ntrials: 1\n")
    r = subprocess.run([sys.executable, "-m", "estimators", "study", str(spec), "--out", str(tmp_path / "o"),
                        "--workers", "1"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    rows = _read(tmp_path / "o" / "study.csv")
    assert {row["solver"] for row in rows} == {"minimal-min-residual", "minimal-lower-bound",
                                               "minimal-lower-bound-no-extent"}
    # The one seeded 4-board layout: every solver reaches the true basin, the same minimum (the truth within the
    # reported 99.9% region, chi-square 6 dof), and the lower bound's two variants agree to the bit.
    assert all(row["ok"] == "1" and row["hit"] == "1" and float(row["d2"]) < 22.46 for row in rows), rows
    d2 = {row["solver"]: float(row["d2"]) for row in rows}
    assert d2["minimal-lower-bound"] == d2["minimal-lower-bound-no-extent"]
    assert abs(d2["minimal-min-residual"] - d2["minimal-lower-bound"]) < 1e-6
    bad = tmp_path / "bad.yaml"
    bad.write_text("lidar: 4d\n")
    r = subprocess.run([sys.executable, "-m", "estimators", "study", str(bad), "--out", str(tmp_path / "b")],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "bad.yaml" in r.stderr and "lidar must be 3d or 2d" in r.stderr
    assert not (tmp_path / "b").exists()


def test_layout_families_are_an_axis_and_their_bounds_rank_as_expected(tmp_path):
    """Measurement level, 8 frames, 3 trials per family: the one-way and frontal families' bounds of the planes
    are far above the spread family's (the planar method's point; the board's edges, which the factor graph adds,
    narrow the gap, and its errors are read against their bound), errors stay within a few bounds, and the layout
    figure is written."""
    spec = parse_spec({"lidar": "3d", "solvers": ["closed-form", "factor-graph"],
                       "layouts": ["spread", "upward", "frontal"], "frames": [8], "trials": 3, "seed": 1})
    assert [c[0] for c in spec.cells] == ["spread", "upward", "frontal"]
    rows = run_study(spec, tmp_path, workers=1, progress=False)
    planes = [r for r in rows if r["solver"] == "closed-form"]
    assert {r["bound"] for r in planes} == {"planes"}
    assert {r["bound"] for r in rows if r["solver"] == "factor-graph"} == {"edges"}
    bound = {f: np.mean([r["bound_trans_mm"] for r in planes if r["layout"] == f]) for f in spec.layouts}
    rot = {f: np.mean([r["bound_rot_deg"] for r in planes if r["layout"] == f]) for f in spec.layouts}
    assert bound["upward"] > 2 * bound["spread"] and bound["frontal"] > 2 * bound["spread"], bound
    assert rot["frontal"] > 3 * rot["spread"], rot
    assert all(r["ok"] and max(r[f"err_over_bound_{a}"] for a in ("rot_x", "rot_y", "rot_z", "trans_x", "trans_y",
                                                                   "trans_z")) < 5.0
               for r in rows if r["solver"] == "factor-graph")
    assert (tmp_path / "errors_vs_layout.png").stat().st_size > 0
    with pytest.raises(DatasetError, match="unknown layout"):
        parse_spec({"layouts": ["zigzag"]})


def test_end_to_end_mode_renders_scans_and_images(tmp_path):
    """One end-to-end trial (4 rendered images and VLP-16 sweeps): both solvers calibrate from the files, within
    1 deg / 5 cm of the truth and a few bounds (the bound is the measurement model's)."""
    spec = parse_spec({"lidar": "3d", "model": "vlp16", "solvers": ["closed-form", "factor-graph"], "frames": [4],
                       "trials": 1, "seed": 2, "mode": "end-to-end"})
    rows = run_study(spec, tmp_path, workers=1, progress=False)
    assert [r["solver"] for r in rows] == ["closed-form", "factor-graph"]
    for r in rows:
        assert r["ok"] == 1 and r["mode"] == "end-to-end" and r["frames_used"] == 4, r
        assert r["rot_err_deg"] < 1.0 and r["trans_err_mm"] < 50.0, r
    assert max(rows[1][f"err_over_bound_{a}"] for a in ("rot_x", "rot_y", "rot_z", "trans_x", "trans_y",
                                                        "trans_z")) < 6.0
    assert 0.0 <= rows[1]["d2"] < 30.0
