"""The command line's arguments: the parser of every command, and the options the pipeline takes from them."""
from __future__ import annotations

import argparse
import math
import os
from pathlib import Path


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="lidarcam", description="Camera-LiDAR extrinsic calibration from planar boards.")
    sub = p.add_subparsers(dest="command", required=True)

    c = sub.add_parser("calibrate", help="estimate T_camera_lidar from a dataset folder",
                       description="Estimate T_camera_lidar, its covariance and posterior from a dataset folder, and "
                                   "write calibration.json, posterior.npz, measurements.npz and report.html into "
                                   "--out. Example: lidarcam calibrate DS --out CAL")
    c.add_argument("dataset", help="folder with dataset.yaml, NNNN.png and NNNN.pcd|ply|bin|npy (2D: csv|npy|pcd)")
    c.add_argument("--out", required=True, help="output folder (calibration.json is written there)")
    c.add_argument("--init", default="closed-form",
                   choices=["closed-form", "minimal-lower-bound", "minimal-min-residual"],
                   help="initial solution: closed-form (3D LiDAR; for a 2D LiDAR it means minimal-lower-bound), "
                        "or the 2D minimal-solution selections")
    c.add_argument("--no-report", action="store_true", help="skip report.html and its figures")
    c.add_argument("--strict", action="store_true",
                   help="exit with code 3 (after writing the results) when the verdict is UNTRUSTED (docs/method.md, "
                        "the verdict) or the answer is ambiguous (a 2D LiDAR's second solution holds at least 5%% "
                        "of the posterior mass)")
    _solver_arguments(c)
    c.add_argument("--seed", type=_SEED, default=0, help="seed of the segmentation's RANSAC")
    c.add_argument("--max-sensor-separation", type=_positive, default=1.0, metavar="M",
                   help="upper bound on the camera-LiDAR distance, used to gate the board by range (m)")
    c.add_argument("--initial-guess", nargs="+", default=None, metavar="V",
                   help="optional hint for scenes beyond automation: a rough T_camera_lidar as 'x y z roll pitch "
                        "yaw' (m, deg; R = Rz(yaw) Ry(pitch) Rx(roll)) or a file (calibration.json, or a 4x4 "
                        "matrix as .json/.txt/.npy); for a rig folder, a rig's calibration.json (each camera-LiDAR "
                        "pair's transform its guess); LiDAR candidates farther than --guess-tolerance from it are "
                        "rejected (it is never a factor)")
    c.add_argument("--guess-tolerance", nargs=2, type=_positive, default=(10.0, 0.30), metavar=("DEG", "M"),
                   help="plane angle and distance a candidate may differ by under --initial-guess (10 deg 0.30 m)")
    c.add_argument("--roi", nargs=6, type=_finite, default=None,
                   metavar=("XMIN", "YMIN", "ZMIN", "XMAX", "YMAX", "ZMAX"),
                   help="optional hint: only LiDAR points inside this box (LiDAR frame, m) are searched")
    c.add_argument("--measurements", default=None, metavar="FILE",
                   help="solve from a measurements.npz that an earlier calibrate wrote (images and scans are not "
                        "read)")
    c.add_argument("--no-cache", action="store_true",
                   help="measure again even when the measurement cache holds this dataset (docs/reference/cli.md)")
    c.add_argument("--cross-validate", type=_whole(0), default=0, metavar="K",
                   help="also score K folds of frames, each under the calibration of the others (validation.json)")
    c.add_argument("--split", default=None, choices=["halves", "interleaved"],
                   help="also calibrate two halves apart and test their difference against their covariances "
                        "(validation.json): halves, the first and last; interleaved, the even and odd frames")
    c.add_argument("--no-static-scene", action="store_true",
                   help="judge each frame's board alone instead of against the static scene of all frames")
    c.add_argument("--targetless", action="store_true",
                   help="no board: refine --initial-guess (within a few degrees and 10-20 cm) on the scene's depth "
                        "contours and the image's edges (docs/howto/check.md); writes calibration.json and "
                        "report.html, or refuses a start it cannot pull in")
    c.add_argument("--scene", action="store_true",
                   help="a camera and a 3D LiDAR's folder: join the scene's term (its depth contours on the image's "
                        "edges, the board left out) to the boards' graph where the two agree; printed beside the "
                        "boards' along their weak direction (docs/howto/check.md)")
    c.add_argument("--keep-board", action="store_true",
                   help="--targetless: keep a board's edges and contours (by default left out where the camera "
                        "finds it)")
    c.add_argument("--time-offset", type=_finite, default=None, metavar="S",
                   help="a moving board's recording: hold the sensors' clock offset (t_camera_stamp - t_lidar_stamp, "
                        "s) at S instead of solving it with the extrinsic (0: the clocks taken as synchronised)")

    v = sub.add_parser("validate", help="score a dataset's frames under a calibration: plane residuals and outline "
                                        "offsets against what its covariance and the noise predict",
                       description="Score the frames a calibration did not use: each frame's plane residual and "
                                   "outline offset against what the calibration's covariance and the noise "
                                   "predict, with one verdict (validation.json). Example: lidarcam validate DS "
                                   "--calibration CAL")
    v.add_argument("dataset", help="a dataset folder (frames the calibration did not use are held out)")
    v.add_argument("--calibration", required=True, help="calibration.json (or the folder holding it)")
    v.add_argument("--out", default=None, help="folder for validation.json (default: the calibration's folder)")
    v.add_argument("--seed", type=_SEED, default=0, help="seed of the board segmentation's RANSAC")
    v.add_argument("--measurements", default=None, metavar="PATH",
                   help="score the measurements an earlier calibrate wrote (OUT/measurements.npz for a pair folder, "
                        "OUT/measurements/ for a rig) instead of measuring the images and scans again")

    k = sub.add_parser("check", help="whether the scene agrees with an extrinsic: the LiDAR's depth contours on the "
                                     "image's edges (exit 0 consistent, 4 contradicted)",
                       description="Check any T_camera_lidar against the scene: each frame's LiDAR depth contours "
                                   "laid on the image's edges, the scene's own estimate near the given one and a "
                                   "test of their difference (check.json, check.html). Exit 0 when consistent, 4 "
                                   "when the scene contradicts it, 2 on bad input. Example: lidarcam check DS "
                                   "--calibration CAL/calibration.json --out CHECK")
    k.add_argument("dataset", help="a camera-LiDAR folder of synchronised frames (dataset.yaml with camera:; "
                                   "board: optional), or a rig folder (--camera, --lidar)")
    k.add_argument("--calibration", required=True, metavar="FILE",
                   help="calibration.json (a rig's: the pair's transform), any JSON with a 4x4 T_camera_lidar, a "
                        "4x4 matrix (text or .npy)")
    k.add_argument("--camera", metavar="NAME", help="a rig folder's camera to check (default its first)")
    k.add_argument("--lidar", metavar="NAME", help="a rig folder's 3D LiDAR to check (default its first)")
    k.add_argument("--out", required=True, help="folder for check.json and check.html")
    k.add_argument("--keep-board", action="store_true",
                   help="keep the board's edges and contours (by default left out where the camera finds it)")

    s = sub.add_parser("simulate", help="write a simulated dataset with ground_truth.json",
                       description="Write a simulated dataset folder (rendered images, ray-cast scans) with its "
                                   "ground truth, for trying lidarcam without data and for studies. Example: "
                                   "lidarcam simulate --poses 8 --seed 1 --out /tmp/sim")
    s.add_argument("--lidar", default="3d", choices=["3d", "2d"],
                   help="3d: a spinning LiDAR (--model); 2d: a 270-degree single-line scanner, 0.25-degree steps")
    s.add_argument("--model", default="hdl64e", choices=["hdl64e", "vlp16", "os64"],
                   help="3D LiDAR beam model (os64: Ouster OS1-64-like)")
    s.add_argument("--poses", type=_whole(1), default=8, help="board poses (frames)")
    s.add_argument("--seed", type=_SEED, default=0, help="seed of the rig, the poses and the noise")
    s.add_argument("--range-noise", type=_within(0.0, 1.0, " m"), default=None, metavar="M",
                   help="LiDAR range sigma (m; default 0.02 for 3d, 0.01 for 2d)")
    s.add_argument("--pixel-noise", type=_within(0.0, 255.0), default=2.0, metavar="GREY",
                   help="image noise sigma (grey levels)")
    s.add_argument("--scan-format", default=None, choices=["pcd", "ply", "bin", "npy", "csv"],
                   help="default pcd (3d) or csv (2d: angle,range)")
    s.add_argument("--no-camera", action="store_true", help="omit intrinsics (to test self-calibration)")
    s.add_argument("--out", required=True, help="the dataset folder to write")
    s.add_argument("--overwrite", action="store_true", help="replace an existing folder")
    s.add_argument("--range-bias", nargs=3, type=_within(-1.0, 1.0, " m"), default=None,
                   metavar=("OFFSET", "RING_SD", "DARK"),
                   help="inject LiDAR range errors (metres): a global offset, per-ring offsets drawn with this sd, "
                        "an offset on the board's black squares (a rig's: into lidar0)")
    s.add_argument("--range-bias-from-priors", default=None, metavar="FAMILY",
                   help="inject LiDAR range errors drawn from a sensor family's priors (velodyne, ouster, hesai, "
                        "livox, or any name for the conservative default): offset and black-square term 0 +- its "
                        "range accuracy, each ring 0 +- a fifth of it")
    s.add_argument("--intensity", default="contrast", choices=["contrast", "flat", "saturated"],
                   help="the returns' intensity: contrast (black squares dark), flat (no black/white contrast, as an "
                        "uncalibrated LiDAR's) or saturated (255 everywhere)")
    s.add_argument("--no-ring", action="store_true", help="write clouds without a ring field")
    s.add_argument("--cameras", type=int, default=1, metavar="N",
                   help="2 or more: a rig folder (sensors cam0..camN-1 and lidar0, docs/howto/rig.md) whose cameras "
                        "sit beside each other (the fourth and later look backwards, right, left), each seeing the "
                        "frames whose board lies wholly in its image")
    s.add_argument("--lidars", type=int, default=1, metavar="N",
                   help="with --cameras: 2 adds a second LiDAR (lidar1, VLP-16-like, to the first's left)")
    s.add_argument("--scanners", type=int, default=0, metavar="N",
                   help="with --cameras: 1 adds a 2D scanner (scan0, level, below and right of the first camera)")
    s.add_argument("--rig", default="default", choices=["default", "varied", "mounted"],
                   help="2d only. default: the scanner 60 cm up, 1 m boards 1.5-4 m away; varied: a rig drawn from "
                        "a second configuration (tilted scan plane, 0.5-1.5 m boards of other shapes 0.5-8 m away, "
                        "another camera, 0.25 or 0.5 degree steps); mounted: a third (the scanner upside down on "
                        "half the rigs, tilted 10-30 degrees or 0.5 m from the camera, 0.4-1.2 m boards 0.8-6 m "
                        "away, 0.25-1 degree steps, boards at one height on half the rigs)")
    s.add_argument("--pattern", default="checkerboard", choices=["checkerboard", "charuco"],
                   help="the board's pattern: charuco prints the same board with DICT_5X5_100 markers in its "
                        "white squares (then some poses are cut by the image's edge)")
    s.add_argument("--outside-image-share", type=_within(0.0, 1.0), default=None, metavar="SHARE",
                   help="charuco only: the share of poses cut by the image's edge (default 0.3)")
    s.add_argument("--scene", default="default", choices=["default", "office", "hall", "furnished"],
                   help="default: the board on a stand in an empty room; office: doors, pictures, cabinets, "
                        "monitors, a table and a pillar, the board held by a person (3D: some boards partly "
                        "outside the vertical field of view); hall: an open hall; furnished: a furnished room "
                        "(the scene check's rooms), its furniture kept off the lines of sight to the boards; a rig "
                        "(--cameras) sees it with every sensor")

    la = sub.add_parser("layout", help="predicted uncertainty and conditioning of a dataset's or a plan's board "
                                       "poses, and the poses to add",
                        description="Predict the extrinsic's uncertainty (the Cramer-Rao bound) of a dataset's "
                                    "measured board poses or a PLAN.yaml's planned ones, name the weakest "
                                    "direction, and suggest the poses that help most. Example: lidarcam layout DS "
                                    "--suggest 3")
    la.add_argument("source", help="a dataset folder (measured frames) or a PLAN.yaml (planned poses)")
    la.add_argument("--json", default=None, metavar="FILE", help="also write the analysis as JSON")
    la.add_argument("--suggest", type=_whole(0, MAX_SUGGESTED), default=0, metavar="K",
                    help=f"suggest K board poses to add, greedily (at most {MAX_SUGGESTED})")
    la.add_argument("--target", nargs=2, type=_positive, default=None, metavar=("DEG", "MM"),
                    help=f"add suggested poses until every axis's predicted std is within DEG and MM (up to "
                         f"{MAX_SUGGESTED})")
    la.add_argument("--lidar-model", default="hdl64e", choices=["hdl64e", "vlp16", "os64"],
                    help="beam model for suggestions on a 3D dataset (a 2D dataset uses the 2D scanner model; a plan "
                         "names its own)")
    la.add_argument("--range-offset", action="store_true",
                    help="suggest poses for the extrinsic with a LiDAR range offset estimated too (they separate the "
                         "offset from the translation)")
    la.add_argument("--seed", type=_SEED, default=0, help="seed of the candidate poses' draws")

    st = sub.add_parser("study", help="simulation studies: `study SPEC.yaml --out DIR [--scheduler tcp://H:P]` "
                                      "(solver comparison) or `study coverage`",
                        description="Simulation studies: `lidarcam study SPEC.yaml --out DIR` compares solvers on "
                                    "a grid of simulated calibrations (its options below), `lidarcam study "
                                    "coverage` measures how often the reported intervals hold the truth.")
    studies = st.add_subparsers(dest="study", required=True)
    cv = studies.add_parser("coverage", help="how often the reported intervals contain the truth",
                            description="Calibrate simulated datasets and count how often the posterior's 68% and "
                                        "95% intervals hold the truth, per axis (coverage.csv, coverage.json). "
                                        "Example: lidarcam study coverage --trials 200 --out /tmp/cov")
    cv.add_argument("--trials", type=_whole(1), default=200, help="simulated datasets")
    cv.add_argument("--out", required=True, help="folder for coverage.csv and coverage.json")
    cv.add_argument("--mode", default="measurement", choices=["measurement", "end-to-end"],
                    help="measurement: noise drawn from the model (fast); end-to-end: rendered images and sweeps")
    cv.add_argument("--frames", type=_whole(3), default=8, help="board poses per trial")
    cv.add_argument("--samples", type=_whole(1), default=1000, help="effective posterior samples per trial")
    cv.add_argument("--workers", type=_whole(1), default=os.cpu_count() or 1, help="local processes")
    cv.add_argument("--seed", type=_SEED, default=0, help="seed of the first trial")
    cv.add_argument("--likelihood", default="gaussian", choices=["gaussian", "student-t"],
                    help="the posterior's likelihood")

    x = sub.add_parser("extract", help="write a dataset folder from a ROS 1 or ROS 2 (sqlite3, MCAP) bag: one frame "
                                       "per still board pose",
                       description="Write a dataset folder from a ROS 1 or ROS 2 bag (no ROS install needed): one "
                                   "frame per still board pose, each image paired with the scan nearest in time. "
                                   "Example: lidarcam extract rig.bag --image-topic /camera/image_raw "
                                   "--cloud-topic /velodyne_points --board 9x7:0.1:1.0x1.0 --out DS. Several image "
                                   "or LiDAR topics write a rig folder (docs/howto/rig.md): the cameras' still poses "
                                   "that overlap in time are one frame, each LiDAR's scan nearest to it.")
    x.add_argument("bag", help="a ROS 1 .bag file or a ROS 2 bag folder (with metadata.yaml)")
    x.add_argument("--image-topic", required=True, action="append",
                   help="sensor_msgs/Image or CompressedImage topic; repeat it for a rig's cameras (cam0, cam1, ...)")
    x.add_argument("--cloud-topic", action="append", default=[],
                   help="sensor_msgs/PointCloud2 topic (3D LiDAR); repeat it for a rig's LiDARs (lidar0, ...)")
    x.add_argument("--scan-topic", action="append", default=[],
                   help="sensor_msgs/LaserScan topic (2D LiDAR); repeat it for a rig's scanners (scan0, ...)")
    x.add_argument("--camera-info-topic", default=None,
                   help="sensor_msgs/CameraInfo topic (default: the one beside the image topic, if any; a rig's "
                        "cameras each take the one beside their image topic)")
    x.add_argument("--no-camera-info", action="store_true",
                   help="ignore CameraInfo; calibrate will estimate the intrinsics from the board views")
    x.add_argument("--intrinsics", default=None, metavar="FILE",
                   help="the camera's intrinsics, used instead of any CameraInfo: ROS camera_calibration's YAML, an "
                        "OpenCV FileStorage YAML, a dataset.yaml or a calibration.json (one camera)")
    x.add_argument("--board", required=True, metavar="NXxNY:SQUARE[:WxH]",
                   help="the board: squares across x down, square size (m), optionally the board's outer size "
                        "(m), e.g. 9x7:0.1:1.0x0.8; or a YAML file with a board: mapping (e.g. a dataset.yaml)")
    x.add_argument("--out", required=True, help="the dataset folder to write")
    x.add_argument("--max-dt", type=_positive, default=0.05, metavar="S",
                   help="pair an image with the nearest scan within this many seconds (header stamps)")
    x.add_argument("--still-s", type=_positive, default=1.0, metavar="S",
                   help="the board must stay still this long to give a frame")
    x.add_argument("--still-px", type=_positive, default=2.0, metavar="PX",
                   help="largest corner motion between examined images that still counts as still")
    x.add_argument("--check-hz", type=_positive, default=5.0, metavar="HZ",
                   help="examine at most this many images per second")
    x.add_argument("--scan-format", default=None, choices=["pcd", "ply", "npy", "csv"],
                   help="default pcd (3D) or csv (2D: angle,range)")
    x.add_argument("--overwrite", action="store_true", help="replace an existing folder")

    e = sub.add_parser("export", help="T_camera_lidar for ROS tf, URDF, KITTI, OpenCV YAML or JSON, with its "
                                      "direction written beside the numbers",
                       description="Write a calibration's T_camera_lidar for ROS tf, URDF, KITTI, OpenCV YAML or "
                                   "JSON, with its direction written beside the numbers. Example: lidarcam export "
                                   "CAL/calibration.json --format ros-tf --parent lidar --lidar-frame velodyne")
    e.add_argument("calibration", help="calibration.json (or the folder holding it)")
    e.add_argument("--format", required=True, choices=["ros-tf", "urdf", "kitti", "opencv-yaml", "json"],
                   help="the output format")
    e.add_argument("--camera-frame", default="camera", help="the camera's frame name (default camera)")
    e.add_argument("--lidar-frame", default="lidar", help="the LiDAR's frame name (default lidar)")
    e.add_argument("--parent", default="camera", choices=["camera", "lidar"],
                   help="ros-tf and urdf: which frame is the parent (default camera: the numbers are "
                        "T_camera_lidar's; lidar: its inverse)")
    e.add_argument("--out", default=None, help="write to this file (atomically) instead of printing")
    e.add_argument("--allow-untrusted", action="store_true",
                   help="export a calibration whose verdict is UNTRUSTED (refused by default: the file would carry "
                        "it as an answer; its verdict is written in the file's comment either way)")

    d = sub.add_parser("demo", help="simulate the default rig, calibrate it, print the result",
                       description="Simulate the default rig, calibrate it and print the result with its error "
                                   "against the truth; what `make demo` runs. Example: lidarcam demo --out /tmp/demo")
    d.add_argument("--out", default="lidarcam-demo",
                   help="folder for the dataset, calibration.json, posterior.npz and report.html (default "
                        "lidarcam-demo)")
    d.add_argument("--model", default="hdl64e", choices=["hdl64e", "vlp16"], help="3D LiDAR beam model")
    d.add_argument("--poses", type=_whole(3), default=8, help="board poses (frames)")
    d.add_argument("--seed", type=_SEED, default=0, help="seed of the simulation and the solve")
    _solver_arguments(d)
    return p


def _number(text: str, kind=float):
    """``text`` as a ``kind`` (float or int), or argparse's one-line error."""
    try:
        return kind(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected {'a whole number' if kind is int else 'a number'}, got "
                                         f"{text!r}") from None


def _whole(least: int, most: int | None = None):
    """An argument type: a whole number of at least ``least`` (and at most ``most``): a seed, a count."""
    def whole(text: str) -> int:
        v = _number(text, int)
        if v < least or (most is not None and v > most):
            bounds = f"of at least {least}" if most is None else f"from {least} to {most}"
            raise argparse.ArgumentTypeError(f"expected a whole number {bounds}, got {v}")
        return v
    return whole


def _within(lo: float, hi: float, unit: str = ""):
    """An argument type: a number from ``lo`` to ``hi`` (a noise level or an accuracy within its physics)."""
    def within(text: str) -> float:
        v = _number(text)
        if not lo <= v <= hi:
            raise argparse.ArgumentTypeError(f"expected a number from {lo:g} to {hi:g}{unit}, got {text}")
        return v
    return within


def _finite(text: str) -> float:
    v = _number(text)
    if not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text}")
    return v


def _positive(text: str) -> float:
    v = _number(text)
    if not v > 0 or v == float("inf"):
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text}")
    return v


# A seed: numpy's generators take whole numbers from 0.
_SEED = _whole(0)
# Noise levels and accuracies within what a camera's corners and a LiDAR's ranges can be (px, m).
_CORNER_PX = _within(1e-3, 20.0, " px")
_RANGE_M = _within(1e-4, 1.0, " m")
# The most poses ``layout`` suggests (each is a greedy search over sampled poses: a few seconds each).
MAX_SUGGESTED = 40


def _solver_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--refine", default="factor-graph", choices=["factor-graph", "none"],
                   help="factor-graph: maximum likelihood with covariance (default); none: the closed form only")
    p.add_argument("--robust", default="huber", choices=["huber", "cauchy", "none"],
                   help="robust loss on each frame's plane residual (default huber)")
    p.add_argument("--outliers", default="drop", choices=["drop", "downweight"],
                   help="what to do with frames whose planes disagree beyond the noise (default drop)")
    p.add_argument("--corner-noise-px", type=_CORNER_PX, default=None, metavar="PX",
                   help="effective per-corner pixel noise (default: corner residual x the detector's "
                        "error-correlation factor)")
    p.add_argument("--range-noise-m", type=_RANGE_M, default=None, metavar="M",
                   help="LiDAR range noise (default: estimated from the board points)")
    p.add_argument("--range-model", default="auto",
                   choices=["none", "offset", "per-ring", "offset+dark", "full", "auto"],
                   help="LiDAR range errors estimated with the extrinsic: a global offset, per-ring offsets, a "
                        "black-square offset (full); auto (default) adds each term the data support (likelihood-"
                        "ratio test at 0.1%%, valid when the boards disagree beyond the noise)")
    p.add_argument("--range-accuracy", type=_RANGE_M, default=None, metavar="M", dest="range_accuracy_m",
                   help="the LiDAR's range accuracy (m, 1 sd of a systematic error): the range terms' prior (default: "
                        "dataset.yaml's lidar.range_accuracy_m, else its lidar.family's: velodyne and ouster 0.03, "
                        "hesai and livox 0.02, else 0.05)")
    edges = p.add_mutually_exclusive_group()
    edges.add_argument("--edges", action="store_true", default=None,
                       help="use the board's edges (where each ring or a 2D scan's line leaves the board; needs "
                            "board.size), and warn where they cannot be: the default where board.size is given. They "
                            "fix the translation along the boards' planes, which planes leave weak; the result tests "
                            "the planes against the edges, and where they conflict the covariance holds both answers "
                            "and the verdict says CHECK (calibration.json 'board_edges'); the posterior holds their "
                            "share to second order about the estimate. By default a 3D LiDAR's edges are left out "
                            "where they carry the answer (the planes alone over 10 times less certain along a "
                            "direction) and a side grew beyond its prior or the planes conflict with them (a hand or "
                            "a holder at the boards' sides): the planes' answer is given, reading CHECK; --edges "
                            "keeps them")
    edges.add_argument("--no-edges", dest="edges", action="store_false",
                       help="use the boards' planes alone; a 3D estimate is then checked by its ring ends (the "
                            "outlines' mean shift, a warning beyond its 99%% limit)")
    p.add_argument("--refine-intrinsics", action="store_true",
                   help="refine the camera's intrinsics with the extrinsic (camera.param_std in dataset.yaml is their "
                        "prior; without it they are estimated from the frames), then measure the LiDAR's boards "
                        "again under them and solve again: the result gives them, propagates their uncertainty, and "
                        "says whether they lower the sensors' disagreement (calibration.json: a pair's "
                        "'intrinsics_refinement', every camera's in 'cameras', the test in 'intrinsics_test')")
    p.add_argument("--samples", type=_whole(0), default=2000, metavar="N",
                   help="effective posterior samples to draw with emcee (default 2000; 0 skips sampling)")
    p.add_argument("--likelihood", default="gaussian", choices=["gaussian", "student-t"],
                   help="posterior likelihood per frame (student-t: heavy tails)")


def refinement_options(args):
    from ..solvers.refinement_options import RefinementOptions

    return RefinementOptions(robust=args.robust, outliers=args.outliers, corner_noise_px=args.corner_noise_px,
                             range_noise_m=args.range_noise_m, range_model=args.range_model,
                             range_accuracy_m=getattr(args, "range_accuracy_m", None),
                             edges=getattr(args, "edges", None),
                             max_sensor_separation_m=getattr(args, "max_sensor_separation", 1.0),
                             refine_intrinsics=getattr(args, "refine_intrinsics", False))


def hints(args, rig: bool = False):
    """The board search's hints from the command line; for a rig (``rig``) its initial guess is a rig's
    calibration.json, each camera-LiDAR pair's transform that pair's guess."""
    import numpy as np

    from ..pipeline.measurement import Hints, parse_initial_guess, parse_rig_guess

    guess = pairs = None
    if args.initial_guess is not None and rig:
        pairs = parse_rig_guess(args.initial_guess)
    elif args.initial_guess is not None:
        guess = parse_initial_guess(args.initial_guess)
    roi = (None, None) if args.roi is None else (np.array(args.roi[:3]), np.array(args.roi[3:]))
    if args.roi is not None and np.any(roi[0] >= roi[1]):
        from ..errors import LidarcamError

        raise LidarcamError(f"--roi box is empty ({args.roi})", hint="give XMIN YMIN ZMIN XMAX YMAX ZMAX with each "
                                                                    "minimum below its maximum")
    return Hints(initial_guess=guess, guess_angle_rad=float(np.deg2rad(args.guess_tolerance[0])),
                 guess_distance_m=float(args.guess_tolerance[1]), roi_min=roi[0], roi_max=roi[1],
                 static_scene=not args.no_static_scene, pair_guesses=pairs)


def study_spec_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="lidarcam study",
                                description="run a solver-comparison study (a grid of simulated calibrations)")
    p.add_argument("spec", help="SPEC.yaml: solvers x frames x noise levels x trials (docs/howto/studies.md)")
    p.add_argument("--out", required=True, help="folder for study.csv, summary.json and the summary plots")
    p.add_argument("--workers", type=_whole(1), default=os.cpu_count() or 1, help="local processes")
    p.add_argument("--scheduler", default=None, metavar="tcp://HOST:PORT",
                   help="run on this Dask distributed scheduler instead of local processes (same results)")
    return p


def board_argument(text: str):
    """``NXxNY:SQUARE[:WxH]`` or a YAML file with a ``board:`` mapping (or the mapping itself)."""
    from ..errors import LidarcamError
    from ..io.dataset import parse_board
    from ..io.input_files import load_yaml

    path = Path(text)
    if path.suffix.lower() in (".yaml", ".yml"):
        spec = load_yaml(path, "board file", "give NXxNY:SQUARE or a YAML file with a board: mapping")
        return parse_board(spec.get("board", spec) if isinstance(spec, dict) else spec, path)
    parts = text.lower().split(":")
    try:
        if len(parts) not in (2, 3):
            raise ValueError(text)
        squares = tuple(int(v) for v in parts[0].split("x"))
        spec = {"squares": squares, "square_size": float(parts[1])}
        if len(parts) == 3:
            spec["size"] = tuple(float(v) for v in parts[2].split("x"))
    except ValueError:
        raise LidarcamError(f"cannot read --board {text!r}", hint="write squares and square size in metres, "
                            "e.g. --board 9x7:0.1 or 9x7:0.1:1.0x0.8 (outer size), or give a YAML file") from None
    return parse_board(spec, Path("--board"))
