"""simulate -> calibrate through the library and the CLI, and bad input through the CLI."""
from __future__ import annotations

import base64
import json
import re
import shutil
import subprocess
import sys
from pathlib import Path
from html.parser import HTMLParser

import cv2
import numpy as np
import pytest

from estimators.calibration import calibrate_pair
from estimators.cli import main
from estimators.io.dataset import load_dataset
from geometry.rotations import T_inverse, T_log, rotation_error

# Acceptance (issue 2): 8 frames, 2 cm range noise: rotation < 0.5 deg, translation < 3 cm, all boards found.
MAX_ROT_DEG, MAX_TRANS_M = 0.5, 0.03
# The truth inside the reported covariance's 99.9% region: chi-square, 6 dof.
CHI2_6_999 = 22.46


def _d2(result, T_true) -> float:
    """The truth's squared Mahalanobis distance under the result's covariance (its tangent at the estimate)."""
    xi = T_log(T_inverse(result.T_camera_lidar) @ T_true)
    return float(xi @ np.linalg.solve(result.covariance, xi))


def _errors(T, T_true):
    return np.degrees(rotation_error(T[:3, :3], T_true[:3, :3])), np.linalg.norm(T[:3, 3] - T_true[:3, 3])


@pytest.mark.parametrize("refine", ["none", "factor-graph"])
@pytest.mark.parametrize("fixture", ["sim_hdl64e", "sim_vlp16"])
def test_calibration_meets_accuracy_targets(request, fixture, refine):
    """Every board found, the closed form within the acceptance targets; refined, the truth inside the reported
    covariance's 99.9% region (the refined error is a few of its standard deviations, not millimetres)."""
    ds = load_dataset(request.getfixturevalue(fixture))
    result = calibrate_pair(ds, refine=refine, rng=np.random.default_rng(0))
    assert result.frames_used == len(ds.frames) == 8
    if refine == "none":
        rot, trans = _errors(result.T_camera_lidar, ds.ground_truth())
        assert result.covariance is None and rot < MAX_ROT_DEG and trans < MAX_TRANS_M, (rot, trans)
    else:
        assert _d2(result, ds.ground_truth()) < CHI2_6_999


def test_cli_calibrate_writes_documented_json(sim_hdl64e, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["calibrate", str(sim_hdl64e), "--out", str(out)]) == 0
    data = json.loads((out / "calibration.json").read_text())
    for key in ("T_camera_lidar", "quaternion_xyzw", "translation_m", "init", "refine", "frames", "intrinsics",
                "version", "layout", "convention"):
        assert key in data
    assert data["init"] == "closed-form" and data["refine"] == "factor-graph"
    T = np.array(data["T_camera_lidar"])
    np.testing.assert_allclose(T[:3, 3], data["translation_m"])
    cov = np.array(data["covariance"])
    assert cov.shape == (6, 6) and np.allclose(cov, cov.T) and np.linalg.eigvalsh(cov)[0] > 0
    np.testing.assert_allclose(data["std"]["rotation_deg_about_lidar_xyz"], np.degrees(np.sqrt(np.diag(cov)[:3])))
    np.testing.assert_allclose(data["std"]["translation_mm_along_lidar_xyz"], 1000 * np.sqrt(np.diag(cov)[3:]))
    # The truth lies within the reported uncertainty (chi-square 6 dof, 99.9%: 22.5).
    G = load_dataset(sim_hdl64e).ground_truth()
    xi = T_log(T_inverse(T) @ G)
    assert xi @ np.linalg.solve(cov, xi) < 22.5
    # The posterior: samples beside the JSON, intervals and the Laplace covariance kept.
    with np.load(out / "posterior.npz", allow_pickle=False) as post:
        assert post["xi"].shape[1] == 6 and len(post["xi"]) >= 2000
        np.testing.assert_allclose(np.cov(post["xi"], rowvar=False), cov, rtol=1e-6, atol=1e-15)
        np.testing.assert_allclose(post["T_map"], T)
        assert post["chain"].shape[1:] == (data["posterior"]["walkers"], data["posterior"]["parameters"])
    assert data["posterior"]["effective_samples"] >= 2000 and data["posterior"]["converged"]
    for level in ("68%", "95%"):
        iv = np.array(data["intervals"][level]["translation_mm_along_lidar_xyz"])
        assert iv.shape == (3, 2) and np.all(iv[:, 0] < iv[:, 1])
    assert np.array(data["covariance_laplace"]).shape == (6, 6)
    # The credible regions: the share of the written samples within each region's distance, as the JSON says.
    with np.load(out / "posterior.npz", allow_pickle=False) as post:
        d2 = np.einsum("ni,ni->n", post["xi"], np.linalg.solve(cov, post["xi"].T).T)
    for level, share in (("99%", 0.99), ("99.9%", 0.999)):
        region = data["credible_regions"][level]
        assert region["d2"] >= region["gaussian_d2"]
        assert np.mean(d2 <= region["d2"]) >= share - 1e-9
    # The report: self-contained (every figure embedded) with the figures beside it: the plots as PNG, the
    # overlays (photographs) as JPEG.
    page = (out / "report.html").read_text()
    pngs = sorted(p.name for p in out.glob("*.png"))
    jpgs = sorted(p.name for p in out.glob("*.jpg"))
    assert {"corner_cam0_lidar0.png", "residuals_cam0_lidar0.png", "traces.png"} <= set(pngs)
    assert len(jpgs) == data["frames_used"] and all(n.startswith("projection_") for n in jpgs)
    assert not any(n.startswith("projection_") for n in pngs)
    magic = {"png": b"\x89PNG\r\n\x1a\n", "jpeg": b"\xff\xd8\xff"}
    embedded = re.findall(r"src='data:image/(png|jpeg);base64,([A-Za-z0-9+/=]+)'", page)
    # every figure once, and the three overlays the page opens with (right after the estimate) a second time
    assert len(embedded) == len(pngs) + len(jpgs) + 3 and len({b for _, b in embedded}) == len(pngs) + len(jpgs)
    assert sum(kind == "jpeg" for kind, _ in embedded) == len(jpgs) + 3
    assert page.index("<h2>Overlays</h2>") < page.index("<h2>Warnings</h2>")
    assert all(base64.b64decode(b).startswith(magic[kind]) for kind, b in embedded)
    HTMLParser().feed(page)  # well-formed enough to parse
    assert all((out / n).read_bytes().startswith(magic["png"]) for n in pngs)
    assert all((out / n).read_bytes().startswith(magic["jpeg"]) for n in jpgs)
    # A projection: the grey image at the report's width under a caption strip, with the LiDAR's points
    # painted in colour (a grey image has equal channels everywhere else; JPEG's chroma noise stays far below).
    cam = data["intrinsics"]
    proj = cv2.imread(str(out / jpgs[0]), cv2.IMREAD_COLOR)
    scale = min(1.0, 1200 / cam["width"])
    assert proj.shape[1] == round(cam["width"] * scale) and proj.shape[0] == 48 + round(cam["height"] * scale)
    body = proj[48:].astype(int)
    coloured = (np.abs(body[..., 0] - body[..., 1]) + np.abs(body[..., 1] - body[..., 2])) > 30
    assert coloured.mean() > 0.01
    assert "Intervals" in page and "Warnings" in page and "Board outline offsets" in page
    frame = data["frames"][0]
    assert {"name", "used", "reason", "board_points", "plane_rms_m", "corner_rms_px"} <= frame.keys()
    # 2 cm range noise over thousands of points: each board's planes agree to a fraction of a degree
    assert all(f["normal_residual_deg"] < 1.0 and abs(f["distance_residual_m"]) < 0.02 for f in data["frames"])
    assert re.search(r"\n  lidar0 +lidar +8 frames used", capsys.readouterr().out)


def test_cli_samples_zero_skips_the_posterior(sim_hdl64e, tmp_path):
    out = tmp_path / "out"
    assert main(["calibrate", str(sim_hdl64e), "--out", str(out), "--samples", "0", "--no-report"]) == 0
    data = json.loads((out / "calibration.json").read_text())
    assert not (out / "posterior.npz").exists() and data.get("posterior") is None
    assert data["covariance"] is not None and "covariance_laplace" not in data


def test_intrinsics_calibrated_when_camera_absent(sim_hdl64e, tmp_path):
    data = tmp_path / "nocam"
    shutil.copytree(sim_hdl64e, data)
    text = (data / "dataset.yaml").read_text()
    (data / "dataset.yaml").write_text(text[:text.index("camera:")])
    ds = load_dataset(data)
    result = calibrate_pair(ds, rng=np.random.default_rng(0))
    assert "calibrated from 8 images" in result.camera.source
    assert any("intrinsics" in w for w in result.warnings)
    rot, trans = _errors(result.T_camera_lidar, ds.ground_truth())
    assert rot < 1.0 and trans < 0.06, (rot, trans)  # intrinsics from 8 views: looser
    # Their uncertainty is in the covariance: wider than with the given intrinsics, and covering the truth.
    assert result.camera.param_std is not None and any("propagated" in w for w in result.warnings)
    given = calibrate_pair(load_dataset(sim_hdl64e), rng=np.random.default_rng(0))
    assert np.all(np.diag(result.covariance) > np.diag(given.covariance))
    xi = T_log(T_inverse(result.T_camera_lidar) @ ds.ground_truth())
    assert xi @ np.linalg.solve(result.covariance, xi) < 22.5
    # and in the engine's joint covariance (calibrate, the command line's): the graph holds the intrinsics at their
    # values, so their share is added (each moved by its sd, the graph stepped once); without it the truth lay at
    # d2 = 1000 or so (benchmarks/bench_intrinsics_from_images.py)
    from estimators.rig_calibration import calibrate

    engine = calibrate(ds, rng=np.random.default_rng(0), samples=0)
    given_engine = calibrate(load_dataset(sim_hdl64e), rng=np.random.default_rng(0), samples=0)
    C = engine.pair("cam0", "lidar0").covariance
    assert np.all(np.diag(C) > 2 * np.diag(given_engine.pair("cam0", "lidar0").covariance))
    xi = T_log(T_inverse(engine.pair("cam0", "lidar0").T) @ ds.ground_truth())
    assert xi @ np.linalg.solve(C, xi) < 22.5


def _run_cli(*args):
    return subprocess.run([sys.executable, "-m", "estimators", *args], capture_output=True, text=True)


def test_the_console_entry_flushes_its_output_before_it_ends_the_process(tmp_path):
    """``run`` ends the process without the interpreter's teardown: what was printed to a pipe still arrives,
    and the exit code is main's."""
    r = _run_cli("simulate", "--lidar", "2d", "--poses", "3", "--out", str(tmp_path / "s"))
    said = f"wrote 3 frames (2D scanner, default scene, checkerboard) to {tmp_path / 's'}\n"
    assert r.returncode == 0 and r.stdout == said
    r = _run_cli("simulate", "--lidar", "2d", "--poses", "3", "--out", str(tmp_path / "s"))  # exists: refused
    assert r.returncode == 2 and r.stderr.startswith("lidarcam: error:") and r.stdout == ""


def test_demo_simulates_calibrates_and_reports_within_the_posterior(tmp_path):
    """``lidarcam demo`` (what ``make demo`` runs): the dataset, calibration.json and a report with its
    figures, and the truth within the printed posterior (squared Mahalanobis distance under the 0.1% tail
    of a chi-square with 6 dof, 22.5; the error itself under 0.5 deg and 1 cm)."""
    r = _run_cli("demo", "--out", str(tmp_path / "demo"))
    assert r.returncode == 0, r.stderr
    for name in ("dataset/dataset.yaml", "calibration.json", "report.html", "corner_cam0_lidar0.png", "traces.png",
                 "residuals_cam0_lidar0.png", "projection_cam0_lidar0_0000.jpg"):
        assert (tmp_path / "demo" / name).is_file(), name
    rot, tr = map(float, re.search(r"rotation ([\d.]+) deg, translation ([\d.]+) mm", r.stdout).groups())
    d2 = float(re.search(r"squared Mahalanobis distance of the truth under the covariance: ([\d.]+)", r.stdout)[1])
    assert rot < 0.5 and tr < 10.0 and d2 < 22.5, r.stdout
    # where the translation is least certain, and the board that constrains it, from the written joint graph's
    # covariance (as a rig prints its weakest pair; calibration.json's ``covariance`` is the posterior's, 1% wider
    # here)
    cal = json.loads((tmp_path / "demo" / "calibration.json").read_text())
    ev, V = np.linalg.eigh(np.array(cal["covariance_laplace"])[3:, 3:])
    weak = np.array(cal["T_camera_lidar"])[:3, :3] @ V[:, -1]
    said = re.search(r"\nweakest pair: T_cam0_lidar0, translation sd up to ([\d.]+) mm along camera ([xyz]) .*; to "
                     r"constrain it, add a board ", r.stdout)
    assert said and float(said[1]) == pytest.approx(1000 * np.sqrt(ev[-1]), abs=0.051)
    assert said[2] == "xyz"[int(np.argmax(np.abs(weak)))]
    # The README shows this printout's first lines (its verdict, then the estimate): the same to the last digit
    # printed (2e-5, for another machine's rounding).
    shown = re.search(r"opens with its verdict, then the estimate:\n\n```text\n(.*?)```",
                      (Path(__file__).resolve().parents[1] / "README.md").read_text(), flags=re.S)[1].splitlines()
    printed = r.stdout.splitlines()[1:1 + len(shown)]
    assert printed[:2] == shown[:2] == ["OK", "T_cam0_lidar0 (T_camera_lidar: p_camera = R p_lidar + t):"], printed
    np.testing.assert_allclose([[float(v) for v in line.strip(" []").split()] for line in printed[2:]],
                               [[float(v) for v in line.strip(" []").split()] for line in shown[2:]], atol=2e-5)


def test_missing_dataset_is_one_line_exit_2(tmp_path):
    r = _run_cli("calibrate", str(tmp_path / "nope"), "--out", str(tmp_path / "out"))
    assert r.returncode == 2
    assert r.stderr.count("\n") == 1 and "nope: dataset folder not found" in r.stderr
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("args, words", [
    (["calibrate", "DS", "--seed", "-1"], "--seed: expected a whole number of at least 0"),
    (["calibrate", "DS", "--range-noise-m", "1e-9"], "--range-noise-m: expected a number from 0.0001 to 1 m"),
    (["calibrate", "DS", "--range-accuracy", "100"], "--range-accuracy: expected a number from 0.0001 to 1 m"),
    (["calibrate", "DS", "--corner-noise-px", "nan"], "--corner-noise-px: expected a number from 0.001 to 20 px"),
    (["calibrate", "DS", "--max-sensor-separation", "0"], "--max-sensor-separation: expected a positive number"),
    (["calibrate", "DS", "--roi", "nan", "0", "0", "1", "1", "1"], "--roi: expected a finite number"),
    (["calibrate", "DS", "--samples", "-5"], "--samples: expected a whole number of at least 0"),
    (["simulate", "--range-noise", "-1"], "--range-noise: expected a number from 0 to 1 m"),
    (["simulate", "--range-bias", "nan", "0", "0"], "--range-bias: expected a number from -1 to 1 m"),
    (["simulate", "--poses", "0"], "--poses: expected a whole number of at least 1"),
])
def test_numbers_outside_their_physics_are_refused_by_the_parser(args, words, tmp_path, capsys):
    """Each of these ended in a traceback (a negative seed, a range noise of 1e-9 m: LinAlgError), a silent
    nonsense (a NaN box, a NaN range bias written into a dataset) or exit 1; now the parser's one line, exit 2."""
    argv = [a.replace("DS", str(tmp_path)) for a in args] + ["--out", str(tmp_path / "out")]
    with pytest.raises(SystemExit) as exit_:
        main(argv)
    assert exit_.value.code == 2 and words in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_an_initial_guess_of_six_numbers_must_be_finite():
    """A NaN angle went on into the board gate's plane normals (a ValueError traceback)."""
    from estimators.errors import DatasetError
    from estimators.pipeline.measurement import parse_initial_guess

    for bad in (["0", "0", "0", "nan", "0", "0"], ["0", "0", "0", "0", "0", "inf"]):
        with pytest.raises(DatasetError, match="is not six finite numbers"):
            parse_initial_guess(bad)


def test_an_out_that_is_a_file_or_the_dataset_itself_is_one_line_exit_2(tmp_path, capsys):
    """``--out`` a file raised FileExistsError; ``--out`` the dataset folder wrote the report's images into it, and
    the next run refused the folder (an image without a scan)."""
    ds = tmp_path / "ds"
    ds.mkdir()
    (ds / "0000.png").write_bytes(b"")
    for out, words in ((ds / "0000.png", "--out is a file"), (ds, "--out is the dataset folder itself")):
        for args in (["calibrate", str(ds)], ["check", str(ds), "--calibration", "c.json"]):
            assert main([*args, "--out", str(out)]) == 2
            err = capsys.readouterr().err
            assert err.count("\n") == 1 and words in err
    assert sorted(p.name for p in ds.iterdir()) == ["0000.png"]


def test_too_few_frames_and_corrupt_scan_leave_no_output(sim_hdl64e, tmp_path):
    few = tmp_path / "few"
    few.mkdir()
    for name in ("dataset.yaml", "0000.png", "0000.pcd", "0001.png", "0001.pcd"):
        shutil.copy(sim_hdl64e / name, few / name)
    out = tmp_path / "out"
    r = _run_cli("calibrate", str(few), "--out", str(out))
    assert r.returncode == 2 and "only 2 usable frame(s)" in r.stderr and r.stderr.count("\n") == 1
    assert not (out / "calibration.json").exists()
    (few / "0001.pcd").write_bytes(b"VERSION 0.7\nFIELDS x y z\nDATA binary\n\x00")
    r = _run_cli("calibrate", str(few), "--out", str(out))
    assert r.returncode == 2 and "0001.pcd" in r.stderr and r.stderr.count("\n") == 1
    assert not (out / "calibration.json").exists()


def test_a_mirrored_lidar_scans_in_millimetres_and_scan_lines_as_sweeps_are_refused_by_their_cause(sim_vlp16, sim_2d,
                                                                                                    tmp_path, capsys):
    # A LiDAR whose points have y negated (a left-handed frame) has boards that only a reflection lays on the
    # camera's: refused as such, where it read UNTRUSTED with its boards' choice blamed. A scanner's ranges in
    # millimetres are refused once for all its scans, where each frame was skipped with the same reason; its lines
    # saved as z = 0 PCDs under lidar: 3d are named as a scanner's, where every frame was skipped.
    from estimators.io.pointcloud_io import read_sweep, write_scan, write_scan_2d

    mirrored = tmp_path / "mirrored"
    shutil.copytree(sim_vlp16, mirrored)
    for f in load_dataset(mirrored).frames:
        s = read_sweep(f.scan)
        write_scan(f.scan, s.points * [1.0, -1.0, 1.0], s.intensity, s.ring)
    mm = tmp_path / "mm"
    shutil.copytree(sim_2d, mm)
    for f in load_dataset(mm).frames:
        rows = [line.split(",") for line in f.scan.read_text().splitlines()[1:]]
        f.scan.write_text("angle,range\n" + "".join(f"{a},{1000 * float(r)}\n" for a, r in rows))
    flat = tmp_path / "flat"  # the scanner's lines as z = 0 PCDs under lidar: 3d
    shutil.copytree(sim_2d, flat)
    for f in load_dataset(flat).frames:
        a, r = np.loadtxt(f.scan, delimiter=",", skiprows=1, unpack=True)
        write_scan_2d(f.scan.with_suffix(".pcd"), a, r)
        f.scan.unlink()
    (flat / "dataset.yaml").write_text((flat / "dataset.yaml").read_text().replace("lidar: 2d", "lidar: 3d"))
    flipped = tmp_path / "flipped"  # the images mirrored (a driver's flip): the boards read alike
    shutil.copytree(sim_vlp16, flipped)
    for f in load_dataset(flipped).frames:
        cv2.imwrite(str(f.image), cv2.flip(cv2.imread(str(f.image), cv2.IMREAD_UNCHANGED), 1))
    for folder, words in ((mirrored, "through a mirror, not a rotation"), (mm, "none of the 6 scans can be read"),
                          (flat, "they are a 2D scanner's scan lines"), (flipped, "or the images are mirrored")):
        out = tmp_path / f"out_{folder.name}"
        assert main(["calibrate", str(folder), "--out", str(out), "--samples", "0", "--no-report"]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and words in err and not out.exists(), err
        assert folder != mm or "millimetres" in err


def test_frame_without_board_is_skipped_with_reason(sim_hdl64e, tmp_path):
    data = tmp_path / "blank"
    shutil.copytree(sim_hdl64e, data)
    cv2.imwrite(str(data / "0003.png"), np.full((768, 1024), 128, np.uint8))
    result = calibrate_pair(load_dataset(data), rng=np.random.default_rng(0))
    skipped = [f for f in result.frames if not f.usable]
    assert [f.name for f in skipped] == ["0003"] and "checkerboard not found" in skipped[0].reason
    assert result.frames_used == 7


def test_simulate_refuses_to_overwrite(tmp_path):
    out = tmp_path / "sim"
    out.mkdir()
    (out / "keep.txt").write_text("x")
    r = _run_cli("simulate", "--poses", "3", "--out", str(out))
    assert r.returncode == 2 and "not empty" in r.stderr
    assert (out / "keep.txt").exists()


@pytest.mark.parametrize("fmt", ["ply", "bin", "npy"])
def test_every_scan_format_calibrates(tmp_path, fmt):
    """The simulator writes each reader's format; 5 VLP-16 frames calibrate with the truth inside the reported
    99.9% region (the Laplace covariance's)."""
    from estimators.simulation.simulator import simulate_dataset

    path = simulate_dataset(tmp_path / fmt, n_poses=5, seed=30, lidar="vlp16", scan_format=fmt)
    assert len(list(path.glob(f"*.{fmt}"))) == 5
    ds = load_dataset(path)
    result = calibrate_pair(ds, rng=np.random.default_rng(0), posterior=None)
    assert result.frames_used == 5
    assert _d2(result, ds.ground_truth()) < CHI2_6_999


def test_3d_scan_in_a_2d_dataset_is_refused_clearly(sim_2d, tmp_path):
    # a frame whose scan is a 3D cloud is skipped, the file and the problem named; a folder of one frame whose
    # board the camera does not find is refused in one line saying why no pair could be formed, the frame named
    data = tmp_path / "d"
    shutil.copytree(sim_2d, data)
    (data / "0000.csv").unlink()
    np.save(data / "0000.npy", np.array([[1.0, 0.0, 0.4], [2.0, 0.5, -0.2], [3.0, 1.0, 0.1]]))
    r = _run_cli("calibrate", str(data), "--out", str(tmp_path / "out"), "--samples", "0", "--no-report")
    assert r.returncode == 0 and re.search(r"0000: skipped: with cam0: scan: .*0000\.npy: not a 2D scan", r.stdout)
    (tmp_path / "e" / "dataset.yaml").parent.mkdir()
    (tmp_path / "e" / "dataset.yaml").write_text("lidar: 2d\nboard: {squares: [9, 12], square_size: 0.019}\n"
                                                 "camera: {width: 64, height: 48, K: [[50, 0, 32], [0, 50, 24], "
                                                 "[0, 0, 1]]}\n")
    cv2.imwrite(str(tmp_path / "e" / "0000.png"), np.zeros((48, 64), np.uint8))
    np.save(tmp_path / "e" / "0000.npy", np.array([[1.0, 0.0, 0.4], [2.0, 0.5, -0.2], [3.0, 1.0, 0.1]]))
    r = _run_cli("calibrate", str(tmp_path / "e"), "--out", str(tmp_path / "out_e"))
    assert r.returncode == 2 and "no frame where cam0 found the board has a lidar0 scan (skipped: 0000: " in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and not (tmp_path / "out_e").exists()

def test_report_figures_from_the_child_match_in_process(monkeypatch):
    """The report's matplotlib figures drawn in the child process are the very PNGs drawn in this one; the
    same figure of the same arrays is drawn once; and where no child can be started, or it was closed before
    a figure was collected, the figures are drawn here."""
    from estimators.analysis import figure_process as fp
    from estimators.analysis import report_figures as rf

    rng = np.random.default_rng(4)
    posterior = {"xi": 1e-3 * rng.normal(size=(3000, 6)), "covariance_laplace": 1e-6 * np.eye(6),
                 "chain": 1e-3 * rng.normal(size=(120, 16, 7)), "burn": np.array(20)}
    residuals = {"names": np.array(["0000", "0001", "0002"]), "chi2": np.array([1.0, np.nan, 7.5]),
                 "outlier": np.array([False, False, True]), "corner_rms_px": np.array([0.1, 0.2, 0.1]),
                 "angle_deg": np.array([0.1, 0.3, 2.0]), "distance_mm": np.array([1.0, -2.0, 30.0])}
    here = {**rf.DRAWERS["posterior"](**posterior), **rf.DRAWERS["residuals"](**residuals)}
    assert sorted(here) == ["corner.png", "residuals.png", "traces.png"]
    assert all(png[:8] == b"\x89PNG\r\n\x1a\n" for png in here.values())
    rf.prepare()  # on axes built ahead (as the child does between jobs): the same figures
    assert rf.DRAWERS["posterior"](**posterior) == {k: here[k] for k in ("corner.png", "traces.png")}
    assert not rf._SPARE  # taken

    def not_here(kind, arrays):
        raise AssertionError("drawn in the parent, not in the child")

    with monkeypatch.context() as m:
        m.setattr(fp, "_draw_here", not_here)
        with fp.FigureProcess() as figures:
            first = figures.draw("posterior", **posterior)
            second = figures.draw("residuals", **residuals)
            assert figures.draw("posterior", **dict(posterior)) is first  # the same job
            assert {**second(), **first()} == here  # collected out of order
            # A posterior after a job: the child may have built its axes ahead meanwhile.
            again = figures.draw("posterior", **{**posterior, "burn": np.array(30)})
            assert again()["corner.png"] == here["corner.png"]
            child = figures.child
        assert child.poll() is not None  # closing ends the child
    with fp.FigureProcess() as figures:
        late = figures.draw("residuals", **residuals)
    assert late() == {"residuals.png": here["residuals.png"]}  # closed first: drawn here
    monkeypatch.setattr(sys, "executable", "/nonexistent/python")
    with fp.FigureProcess() as none_started:
        assert none_started.child is None
        assert none_started.draw("posterior", **posterior)() == {k: here[k] for k in ("corner.png", "traces.png")}


def test_top_view_draws_points_where_they_lie():
    """The report's top view (OpenCV): a candidate's points at its place in the metric grid, in its colour,
    the chosen one ringed in black; the background sweep grey; the rest white."""
    from estimators.analysis.top_view import _LEFT, _TOP, PLOT_PX, top_view_png

    rng = np.random.default_rng(0)
    sweep = np.column_stack([rng.uniform(-20, 20, 5000), rng.uniform(-20, 20, 5000), np.zeros(5000)])
    board = np.column_stack([np.full(50, 3.0), np.linspace(-0.5, 0.5, 50)])
    other = np.column_stack([np.full(50, 5.0), np.linspace(1.5, 2.5, 50)])
    png = top_view_png(sweep, [board, other], 0, "frame 0000: consensus")
    img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    assert img.shape == (_TOP + PLOT_PX + 44, _LEFT + PLOT_PX + 16, 3)
    # the view is centred on the candidates' mean (4, 1) and 8 m wide: 65 px per metre
    scale = PLOT_PX / 8.0

    def px(x, y):
        return int(round(_TOP + (1.0 + 4.0 - y) * scale)), int(round(_LEFT + (x - 0.0) * scale))

    v, u = px(3.0, 0.0)
    assert tuple(img[v, u]) == (180, 119, 31)  # C0 (tab:blue) in BGR, the chosen board
    assert tuple(img[v, u - 2]) == (0, 0, 0) and tuple(img[v, u - 3]) != (0, 0, 0)  # its black ring: 1 px wider
    v, u = px(5.0, 2.0)
    assert tuple(img[v, u]) == (14, 127, 255)  # C1 (tab:orange)
    plot = img[_TOP + 1:_TOP + PLOT_PX, _LEFT + 1:_LEFT + PLOT_PX]
    assert 150 < np.all(plot == 170, axis=2).sum() < 260  # the sweep in view: about 5000 * (8/40)^2 = 200 returns


def test_a_pair_folder_through_the_one_engine_keeps_the_pairs_options(sim_hdl64e, tmp_path, capsys):
    """A pair folder on the command line is calibrated as the rig of cam0 and lidar0, and still takes its pair's
    options: an initial guess of six numbers (its one camera-LiDAR pair's), its measurements.npz or the rig's
    measurements folder back (the same estimate, bit for bit), and --refine none (the closed form alone, without
    covariance, written as a single pair's file)."""
    from geometry.rotations import rpy_from_R

    truth = load_dataset(sim_hdl64e).ground_truth()
    guess = [*truth[:3, 3], *np.degrees(rpy_from_R(truth[:3, :3]))]
    out = tmp_path / "a"
    assert main(["calibrate", str(sim_hdl64e), "--out", str(out), "--samples", "0", "--no-report",
                 "--initial-guess", *[f"{v:.6f}" for v in guess]]) == 0
    cal = json.loads((out / "calibration.json").read_text())
    T = np.array(cal["T_camera_lidar"])
    assert cal["rig"] and cal["frames_used"] == 8 and np.linalg.norm(T[:3, 3] - truth[:3, 3]) < 0.01
    # the guess given the other way round (T_lidar_camera): refused as such, not as boards out of every frame
    (tmp_path / "inverted.json").write_text(json.dumps({"T_camera_lidar": np.linalg.inv(truth).tolist()}))
    assert main(["calibrate", str(sim_hdl64e), "--out", str(tmp_path / "inv"), "--samples", "0", "--no-report",
                 "--initial-guess", str(tmp_path / "inverted.json")]) == 2
    assert "but 8 lie within its inverse's: the guess is T_lidar_camera" in capsys.readouterr().err
    for k, given in enumerate((out / "measurements.npz", out / "measurements")):
        again = tmp_path / f"again{k}"
        assert main(["calibrate", str(sim_hdl64e), "--out", str(again), "--samples", "0", "--no-report",
                     "--measurements", str(given)]) == 0
        np.testing.assert_array_equal(json.loads((again / "calibration.json").read_text())["T_camera_lidar"], T)
    closed = tmp_path / "closed"
    assert main(["calibrate", str(sim_hdl64e), "--out", str(closed), "--refine", "none"]) == 0
    cal = json.loads((closed / "calibration.json").read_text())
    assert cal["refine"] == "none" and cal["covariance"] is None and "rig" not in cal
    assert np.linalg.norm(np.array(cal["T_camera_lidar"])[:3, 3] - truth[:3, 3]) < 0.05


def test_a_reader_that_closes_the_output_ends_the_command_quietly(tmp_path):
    """``lidarcam ... | head``: the reader closes the pipe after a line; the command ends there with a Unix tool's
    exit code (141, SIGPIPE's), its stderr free of a traceback (it printed one)."""
    cal = tmp_path / "calibration.json"
    cal.write_text(json.dumps({"T_camera_lidar": np.eye(4).tolist()}))
    proc = subprocess.Popen([sys.executable, "-m", "estimators", "export", str(cal), "--format", "ros-tf"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    proc.stdout.close()
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=120) == 141 and "Traceback" not in err, err


def test_the_apis_calibrate_names_an_argument_of_the_wrong_type(sim_vlp16):
    """A notebook's slip (a seed for the generator, options as text, no folder) is a TypeError naming the argument,
    not an AttributeError from deep inside (``'int' object has no attribute 'spawn'``)."""
    from estimators import calibrate

    for kwargs, name in (({"rng": 5}, "rng must be Generator"), ({"options": "x"}, "options must be RefinementOptions"),
                         ({"posterior": 100}, "posterior must be PosteriorOptions or None")):
        with pytest.raises(TypeError, match=name):
            calibrate(sim_vlp16, **kwargs)
    with pytest.raises(TypeError, match="dataset must be"):
        calibrate(None)


def test_scans_numbered_frames_off_their_images_are_refused_naming_the_shift(sim_vlp16, sim_2d, tmp_path, capsys):
    # Each scan renamed to the frame before its own (a scanner's), or two before (a 3D LiDAR's; the first ones' to
    # the last): the boards agree on no extrinsic as paired, and the folder read UNTRUSTED with its boards' choice
    # blamed (a 3D LiDAR's) or was refused as a layout that leaves the translation unobservable (a scanner's).
    # Paired with the scan that many frames earlier, every image's board is found: refused as a numbering that
    # many frames off, naming one pair. Two frames off was read UNTRUSTED while one frame off was refused.
    for source, shift, words in ((sim_vlp16, 2, "2 frames"), (sim_2d, 1, "a frame")):
        shifted = tmp_path / f"shifted_{source.name}"
        shutil.copytree(source, shifted)
        scans = [f.scan for f in load_dataset(source).frames]
        for k, scan in enumerate(scans):
            shutil.copy(scans[(k + shift) % len(scans)], shifted / scan.name)
        out = tmp_path / f"out_{source.name}"
        assert main(["calibrate", str(shifted), "--out", str(out), "--samples", "0", "--no-report"]) == 2
        err = capsys.readouterr().err
        n = len(scans) - shift
        assert err.count("\n") == 1 and not out.exists(), err
        assert f"{n} of {n} do with each image paired with the scan {words} earlier" in err, err
        assert f"({scans[shift].with_suffix('.png').name}'s board is in {scans[0].name})" in err, err
        assert f"numbered {words} off their images" in err, err


def test_a_board_declared_by_its_inner_corners_is_refused_naming_the_squares(sim_vlp16, tmp_path, capsys):
    # The simulated 9 x 7-square board declared 8 x 6 (its inner corners, as OpenCV counts them): on its 8 frames it
    # was found in 1 image and the pair refused as "only 1 usable frame(s) ... record more board poses". Here on 3
    # of them (each image searched in vain costs the classic detector's time budget), found in none; a board of a
    # square more along each side is found in each: refused naming board.squares and the count that fits.
    import yaml

    spec = yaml.safe_load((sim_vlp16 / "dataset.yaml").read_text())
    folder = tmp_path / "inner_corners"
    folder.mkdir()
    for f in load_dataset(sim_vlp16).frames[:3]:
        shutil.copy(f.image, folder / f.image.name)
        shutil.copy(f.scan, folder / f.scan.name)
    (folder / "dataset.yaml").write_text(yaml.safe_dump({**spec, "board": {**spec["board"], "squares": [8, 6]}}))
    assert main(["calibrate", str(folder), "--out", str(tmp_path / "out"), "--samples", "0", "--no-report"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and not (tmp_path / "out").exists(), err
    assert "found the 8 x 6-square board in 0 of 3 images, and a 9 x 7-square one in each of" in err, err
    assert "board.squares counts the squares" in err and "set board.squares: [9, 7]" in err, err


def test_a_pinhole_camera_declared_a_fisheye_is_refused_naming_the_model(sim_vlp16, tmp_path, capsys):
    # The simulated pinhole's k1 k2 p1 p2 (its k3 is 0) declared as a fisheye's k1..k4: its boards fit at a median
    # 0.70 px (0.06 as the pinhole it is), and the set read UNTRUSTED with 7 of 8 boards off the estimate. Refused
    # in one line naming the model, by the command line and by the API's measurement (naming dataset.yaml).
    import yaml

    from estimators import measure
    from estimators.errors import DatasetError

    spec = yaml.safe_load((sim_vlp16 / "dataset.yaml").read_text())
    folder = tmp_path / "declared_fisheye"
    shutil.copytree(sim_vlp16, folder)
    camera = {**spec["camera"], "model": "fisheye", "dist": spec["camera"]["dist"][:4]}
    (folder / "dataset.yaml").write_text(yaml.safe_dump({**spec, "camera": camera}))
    assert main(["calibrate", str(folder), "--out", str(tmp_path / "out"), "--samples", "0", "--no-report"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and not (tmp_path / "out").exists(), err
    assert "camera cam0's boards fit the intrinsics as a fisheye camera" in err, err
    assert "camera.model is pinhole, not fisheye" in err, err
    with pytest.raises(DatasetError, match="the camera's boards fit .* camera.model is pinhole") as raised:
        measure(folder, np.random.default_rng(0))
    assert raised.value.path.endswith("dataset.yaml")


def test_intrinsics_for_another_resolution_are_refused_naming_the_principal_point(sim_vlp16, tmp_path, capsys):
    # K for twice the images' size puts every board twice as far as its returns: each frame was skipped with "only
    # 0 points ... where the camera puts the board" and the pair refused for too few frames. With the principal
    # point at the image's corner, the intrinsics are named instead. K for half their size finds 3 boards by chance
    # in this set: calibrated, and UNTRUSTED (its planes 205 mm apart), naming the principal point too.
    import yaml

    spec = yaml.safe_load((sim_vlp16 / "dataset.yaml").read_text())
    for scale in (2.0, 0.5):
        folder = tmp_path / f"K_{scale}"
        shutil.copytree(sim_vlp16, folder)
        K = np.array(spec["camera"]["K"], float)
        K[:2] *= scale
        (folder / "dataset.yaml").write_text(yaml.safe_dump({**spec, "camera": {**spec["camera"], "K": K.tolist()}}))
        out = tmp_path / f"out_{scale}"
        code = main(["calibrate", str(folder), "--out", str(out), "--samples", "0", "--no-report"])
        run = capsys.readouterr()
        if scale == 0.5:
            verdict = run.out.splitlines()[0]
            assert code == 0 and verdict.startswith("UNTRUSTED: "), verdict
            assert "principal point (256, 192) lies 25% of the width" in verdict, verdict
            continue
        assert code == 2 and run.err.count("\n") == 1 and not out.exists(), run.err
        assert "principal point (1024, 768) lies 50% of the width and 50% of the height from the centre of the " \
               "1024 x 768 images: intrinsics for another resolution" in run.err and "dataset.yaml" in run.err, run.err
