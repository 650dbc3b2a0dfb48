"""The ``lidarcam`` command line: a thin shell over the library. Arguments are parsed before heavy imports."""
from __future__ import annotations

import argparse
import contextlib
import os
import sys
from pathlib import Path


def _parser() -> argparse.ArgumentParser:
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
                   help="exit with code 3 (after writing the results) when the answer is ambiguous (a 2D LiDAR's "
                        "second solution holds at least 5%% of the posterior mass) or contradicted (with --edges, the "
                        "boards' planes and their ring ends disagree far beyond their noise, p < 0.001)")
    _solver_arguments(c)
    c.add_argument("--seed", type=int, default=0, help="seed of the segmentation's RANSAC")
    c.add_argument("--max-sensor-separation", type=float, default=1.0, metavar="M",
                   help="upper bound on the camera-LiDAR distance, used to gate the board by range (m)")
    c.add_argument("--initial-guess", nargs="+", default=None, metavar="V",
                   help="optional hint for scenes beyond automation: a rough T_camera_lidar as 'x y z roll pitch "
                        "yaw' (m, deg; R = Rz(yaw) Ry(pitch) Rx(roll)) or a file (calibration.json, or a 4x4 "
                        "matrix as .json/.txt/.npy); LiDAR candidates farther than --guess-tolerance from it are "
                        "rejected (it is never a factor)")
    c.add_argument("--guess-tolerance", nargs=2, type=float, default=(10.0, 0.30), metavar=("DEG", "M"),
                   help="plane angle and distance a candidate may differ by under --initial-guess (10 deg 0.30 m)")
    c.add_argument("--roi", nargs=6, type=float, default=None, metavar=("XMIN", "YMIN", "ZMIN", "XMAX", "YMAX", "ZMAX"),
                   help="optional hint: only LiDAR points inside this box (LiDAR frame, m) are searched")
    c.add_argument("--measurements", default=None, metavar="FILE",
                   help="solve from a measurements.npz that an earlier calibrate wrote (images and scans are not "
                        "read)")
    c.add_argument("--no-cache", action="store_true",
                   help="measure again even when the measurement cache holds this dataset (docs/reference/cli.md)")
    c.add_argument("--cross-validate", type=int, default=0, metavar="K",
                   help="also score K folds of frames, each under the calibration of the others (validation.json)")
    c.add_argument("--split", default=None, choices=["halves", "interleaved"],
                   help="also calibrate two halves apart and test their difference against their covariances "
                        "(validation.json): halves, the first and last; interleaved, the even and odd frames")
    c.add_argument("--no-static-scene", action="store_true",
                   help="judge each frame's board alone instead of against the static scene of all frames")

    v = sub.add_parser("validate", help="score a dataset's frames under a calibration: plane residuals and outline "
                                        "offsets against what its covariance and the noise predict",
                       description="Score the frames a calibration did not use: each frame's plane residual and "
                                   "outline offset against what the calibration's covariance and the noise "
                                   "predict, with one verdict (validation.json). Example: lidarcam validate DS "
                                   "--calibration CAL")
    v.add_argument("dataset", help="a dataset folder (frames the calibration did not use are held out)")
    v.add_argument("--calibration", required=True, help="calibration.json (or the folder holding it)")
    v.add_argument("--out", default=None, help="folder for validation.json (default: the calibration's folder)")
    v.add_argument("--seed", type=int, default=0, help="seed of the board segmentation's RANSAC")

    s = sub.add_parser("simulate", help="write a simulated dataset with ground_truth.json",
                       description="Write a simulated dataset folder (rendered images, ray-cast scans) with its "
                                   "ground truth, for trying lidarcam without data and for studies. Example: "
                                   "lidarcam simulate --poses 8 --seed 1 --out /tmp/sim")
    s.add_argument("--lidar", default="3d", choices=["3d", "2d"],
                   help="3d: a spinning LiDAR (--model); 2d: a 270-degree single-line scanner, 0.25-degree steps")
    s.add_argument("--model", default="hdl64e", choices=["hdl64e", "vlp16", "os64"],
                   help="3D LiDAR beam model (os64: Ouster OS1-64-like)")
    s.add_argument("--poses", type=int, default=8, help="board poses (frames)")
    s.add_argument("--seed", type=int, default=0, help="seed of the rig, the poses and the noise")
    s.add_argument("--range-noise", type=float, default=None, metavar="M",
                   help="LiDAR range sigma (m; default 0.02 for 3d, 0.01 for 2d)")
    s.add_argument("--pixel-noise", type=float, default=2.0, metavar="GREY", help="image noise sigma (grey levels)")
    s.add_argument("--scan-format", default=None, choices=["pcd", "ply", "bin", "npy", "csv"],
                   help="default pcd (3d) or csv (2d: angle,range)")
    s.add_argument("--no-camera", action="store_true", help="omit intrinsics (to test self-calibration)")
    s.add_argument("--out", required=True, help="the dataset folder to write")
    s.add_argument("--overwrite", action="store_true", help="replace an existing folder")
    s.add_argument("--range-bias", nargs=3, type=float, default=None, metavar=("OFFSET", "RING_SD", "DARK"),
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
    s.add_argument("--outside-image-share", type=float, default=None, metavar="SHARE",
                   help="charuco only: the share of poses cut by the image's edge (default 0.3)")
    s.add_argument("--scene", default="default", choices=["default", "office", "hall"],
                   help="default: the board on a stand in an empty room; office: doors, pictures, cabinets, "
                        "monitors, a table and a pillar, the board held by a person (3D: some boards partly "
                        "outside the vertical field of view); hall: an open hall")

    la = sub.add_parser("layout", help="predicted uncertainty and conditioning of a dataset's or a plan's board "
                                       "poses, and the poses to add",
                        description="Predict the extrinsic's uncertainty (the Cramer-Rao bound) of a dataset's "
                                    "measured board poses or a PLAN.yaml's planned ones, name the weakest "
                                    "direction, and suggest the poses that help most. Example: lidarcam layout DS "
                                    "--suggest 3")
    la.add_argument("source", help="a dataset folder (measured frames) or a PLAN.yaml (planned poses)")
    la.add_argument("--json", default=None, metavar="FILE", help="also write the analysis as JSON")
    la.add_argument("--suggest", type=int, default=0, metavar="K", help="suggest K board poses to add, greedily")
    la.add_argument("--target", nargs=2, type=_positive, default=None, metavar=("DEG", "MM"),
                    help="add suggested poses until every axis's predicted std is within DEG and MM (up to 40)")
    la.add_argument("--lidar-model", default="hdl64e", choices=["hdl64e", "vlp16", "os64"],
                    help="beam model for suggestions on a 3D dataset (a 2D dataset uses the 2D scanner model; a plan "
                         "names its own)")
    la.add_argument("--range-offset", action="store_true",
                    help="suggest poses for the extrinsic with a LiDAR range offset estimated too (they separate the "
                         "offset from the translation)")
    la.add_argument("--seed", type=int, default=0, help="seed of the candidate poses' draws")

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
    cv.add_argument("--trials", type=int, default=200, help="simulated datasets")
    cv.add_argument("--out", required=True, help="folder for coverage.csv and coverage.json")
    cv.add_argument("--mode", default="measurement", choices=["measurement", "end-to-end"],
                    help="measurement: noise drawn from the model (fast); end-to-end: rendered images and sweeps")
    cv.add_argument("--frames", type=int, default=8, help="board poses per trial")
    cv.add_argument("--samples", type=int, default=1000, help="effective posterior samples per trial")
    cv.add_argument("--workers", type=int, default=os.cpu_count() or 1, help="local processes")
    cv.add_argument("--seed", type=int, default=0, help="seed of the first trial")
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

    d = sub.add_parser("demo", help="simulate the default rig, calibrate it, print the result",
                       description="Simulate the default rig, calibrate it and print the result with its error "
                                   "against the truth; what `make demo` runs. Example: lidarcam demo --out /tmp/demo")
    d.add_argument("--out", default="lidarcam-demo",
                   help="folder for the dataset, calibration.json, posterior.npz and report.html (default "
                        "lidarcam-demo)")
    d.add_argument("--model", default="hdl64e", choices=["hdl64e", "vlp16"], help="3D LiDAR beam model")
    d.add_argument("--poses", type=int, default=8, help="board poses (frames)")
    d.add_argument("--seed", type=int, default=0, help="seed of the simulation and the solve")
    _solver_arguments(d)
    return p


def _positive(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not v > 0 or v == float("inf"):
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text}")
    return v


def _solver_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--refine", default="factor-graph", choices=["factor-graph", "none"],
                   help="factor-graph: maximum likelihood with covariance (default); none: the closed form only")
    p.add_argument("--robust", default="huber", choices=["huber", "cauchy", "none"],
                   help="robust loss on each frame's plane residual (default huber)")
    p.add_argument("--outliers", default="drop", choices=["drop", "downweight"],
                   help="what to do with frames whose planes disagree beyond the noise (default drop)")
    p.add_argument("--corner-noise-px", type=_positive, default=None, metavar="PX",
                   help="effective per-corner pixel noise (default: corner residual x the detector's "
                        "error-correlation factor)")
    p.add_argument("--range-noise-m", type=_positive, default=None, metavar="M",
                   help="LiDAR range noise (default: estimated from the board points)")
    p.add_argument("--range-model", default="auto",
                   choices=["none", "offset", "per-ring", "offset+dark", "full", "auto"],
                   help="LiDAR range errors estimated with the extrinsic: a global offset, per-ring offsets, a "
                        "black-square offset (full); auto (default) adds each term the data support (likelihood-"
                        "ratio test at 0.1%%, valid when the boards disagree beyond the noise)")
    p.add_argument("--range-accuracy", type=_positive, default=None, metavar="M", dest="range_accuracy_m",
                   help="the LiDAR's range accuracy (m, 1 sd of a systematic error): the range terms' prior (default: "
                        "dataset.yaml's lidar.range_accuracy_m, else its lidar.family's: velodyne and ouster 0.03, "
                        "hesai and livox 0.02, else 0.05)")
    edges = p.add_mutually_exclusive_group()
    edges.add_argument("--edges", action="store_true", default=None,
                       help="also use a 3D LiDAR's board edges (where each ring leaves the board; needs board.size): "
                            "they fix the translation along the boards' planes, which planes leave weak. The result "
                            "tests the planes against the edges and checks the outlines' mean shift (calibration.json "
                            "'board_edges'); the posterior holds their share to second order about the estimate. "
                            "Without it they check a 3D estimate (the outlines' mean shift, a warning beyond its 99%% "
                            "limit). A 2D scan's segment ends are used by default")
    edges.add_argument("--no-edges", dest="edges", action="store_false",
                       help="use the boards' planes alone, also for a 2D scan (whose segment ends are otherwise used "
                            "when board.size is given)")
    p.add_argument("--refine-intrinsics", action="store_true",
                   help="refine the camera's intrinsics with the extrinsic (camera.param_std in dataset.yaml is their "
                        "prior; without it they are estimated from the frames): the result gives them, propagates "
                        "their uncertainty, and says whether they lower the boards' overdispersion "
                        "(calibration.json 'intrinsics_refinement')")
    p.add_argument("--samples", type=int, default=2000, metavar="N",
                   help="effective posterior samples to draw with emcee (default 2000; 0 skips sampling)")
    p.add_argument("--likelihood", default="gaussian", choices=["gaussian", "student-t"],
                   help="posterior likelihood per frame (student-t: heavy tails)")


def _options(args):
    from .solvers.refinement import RefinementOptions

    return RefinementOptions(robust=args.robust, outliers=args.outliers, corner_noise_px=args.corner_noise_px,
                             range_noise_m=args.range_noise_m, range_model=args.range_model,
                             range_accuracy_m=getattr(args, "range_accuracy_m", None),
                             edges=getattr(args, "edges", None),
                             max_sensor_separation_m=getattr(args, "max_sensor_separation", 1.0),
                             refine_intrinsics=getattr(args, "refine_intrinsics", False))


def _posterior_options(args):
    from .solvers.posterior import PosteriorOptions

    if args.samples < 0:
        raise SystemExit("lidarcam: error: --samples must be 0 (skip) or positive")
    if args.samples == 0 or args.refine == "none":
        return None
    return PosteriorOptions(min_ess=args.samples, likelihood=args.likelihood, progress=sys.stderr.isatty())


def _print_result(result, truth=None) -> None:
    import numpy as np

    from geometry.rotations import rotation_error

    T = result.T_camera_lidar
    np.set_printoptions(precision=5, suppress=True)
    if result.contradicted:
        print(f"UNTRUSTED: {result.contradicted}. Both estimates are in calibration.json (board_edges, "
              "planes_against_edges); check board.size and the boards' outlines in the report, and add boards.")
    if result.ambiguous:
        masses = ", ".join(f"{m.mass:.0%}" for m in result.modes)
        print(f"AMBIGUOUS: {len(result.modes)} distinct solutions fit the boards (posterior mass {masses}); the most "
              "probable is shown, the intervals cover every mode, and calibration.json lists each with its "
              "covariance. Add boards tilted in other directions to decide.")
    print(f"T_camera_lidar (p_camera = R p_lidar + t), {result.init}, refine {result.refine}:")
    for row in T:
        print("  [" + "  ".join(f"{v:+.5f}" for v in row) + "]")
    print(f"frames used: {result.frames_used} of {len(result.frames)}; normal condition number "
          f"{result.condition_number:.2f}")
    for f in result.frames:
        if f.usable:
            print(f"  {f.name}: {f.lidar.n_points:6d} board points, plane RMS {1000 * f.lidar.plane_rms_m:.1f} mm, "
                  f"corner RMS {f.camera.reprojection_rms_px:.3f} px")
        else:
            print(f"  {f.name}: skipped: {f.reason}")
    if result.covariance is not None:
        ref = result.refinement
        kind = "posterior" if result.posterior is not None else "Laplace"
        print(f"standard deviations ({kind}; GTSAM tangent, about/along the LiDAR's x y z):")
        print("  rotation    " + "  ".join(f"{v:7.3f}" for v in result.std_rotation_deg) + "  deg")
        print("  translation " + "  ".join(f"{v:7.2f}" for v in result.std_translation_mm) + "  mm")
        print("  t in camera " + "  ".join(f"{v:7.2f}" for v in result.std_translation_camera_mm) + "  mm")
        print(f"noise: corners {ref.corner_noise_px:.3f} px effective ({ref.corner_residual_px:.3f} px residual), "
              f"range {1000 * ref.range_noise_m:.1f} mm; plane consistency {ref.variance_factor:.2f} "
              f"(chi-square/dof, {ref.consistency_dof:g} dof, p = {ref.consistency_p:.2g})"
              + (f"; per-board plane error {1000 * ref.plane_floor_m:.1f} mm" if ref.plane_floor_m else ""))
        _print_range_model(ref.range_model)
        _print_edges(ref.edges)
        _print_intrinsics(result.intrinsics_refinement)
    if result.posterior is not None:
        post = result.posterior
        d = post.diagnostics()
        print(f"posterior ({d['likelihood']}): {d['effective_samples']:.0f} effective samples, tau "
              f"{max(d['tau_steps']):.0f} steps, acceptance {d['acceptance_fraction']:.2f}, {d['seconds']:.1f} s; "
              f"99.9% region: squared Mahalanobis distance up to {post.region_d2(0.999):.1f} under the covariance "
              "(a Gaussian's 22.5)")
        for level, iv in post.summary().items():
            rot = iv["rotation_deg_about_lidar_xyz"]
            tr = iv["translation_mm_along_lidar_xyz"]
            print(f"  {level} intervals: rotation " + "  ".join(f"[{a:+.3f}, {b:+.3f}]" for a, b in rot) + " deg")
            print(f"  {'':14s}translation " + "  ".join(f"[{a:+.2f}, {b:+.2f}]" for a, b in tr) + " mm")
    if truth is not None:
        rot = np.degrees(rotation_error(T[:3, :3], truth[:3, :3]))
        tr = 1000 * np.linalg.norm(T[:3, 3] - truth[:3, 3])
        print(f"error against ground truth: rotation {rot:.3f} deg, translation {tr:.1f} mm")
        if result.covariance is not None:
            from geometry.rotations import T_inverse, T_log

            xi = T_log(T_inverse(T) @ truth)
            d2 = float(xi @ np.linalg.solve(result.covariance, xi))
            print(f"  squared Mahalanobis distance of the truth under the covariance: {d2:.1f} "
                  f"(chi-square, 6 dof: mean 6, 95% below 12.6)")
    for w in result.warnings:
        print(f"warning: {w}")


def _print_intrinsics(fit) -> None:
    if fit is None:
        return
    verdict = "lowers" if fit.lowers_overdispersion else "does not lower"
    print(f"intrinsics refined ({'with the given param_std as prior' if fit.prior_sd is not None else 'no prior'}): "
          f"plane consistency {fit.variance_factor_given:.2f} under the given intrinsics, "
          f"{fit.variance_factor_refined:.2f} refined ({verdict} the overdispersion); corner residual "
          f"{fit.corner_residual_given_px:.3f} -> {fit.corner_residual_refined_px:.3f} px")
    for n, g, v, sd in zip(fit.names, fit.given_params, fit.params, fit.std):
        print(f"  {n:3s} {g:12.5g} -> {v:12.5g}  (sd {sd:.3g}, moved {(v - g) / sd:+.1f} sd)")


def _print_edges(edges) -> None:
    if not edges or "mean_shift_camera_m" not in edges:
        return
    from .solvers.outline_check import outline_shift_words

    what = "used" if edges["used"] else "a check, not used in the estimate"
    print(f"board edges ({what}): {edges['ends']} ring ends; the LiDAR's outlines sit (camera axes) "
          + outline_shift_words(edges) + "; growth "
          f"{1000 * edges['growth_m'][0]:+.1f} / {1000 * edges['growth_m'][1]:+.1f} mm per side"
          + (f", outline offset {1000 * edges['outline_offset_m'][0]:+.1f} / "
             f"{1000 * edges['outline_offset_m'][1]:+.1f} mm" if edges["used"] else "")
          + f"; in-plane board scatter {1000 * edges['board_scatter_in_plane_m']:.1f} mm")
    test = edges.get("planes_against_edges")
    if test:
        print(f"  planes alone against planes + edges: d2 {test['d2']:.1f} on {test['dof']} dof (p = "
              f"{test['p_value']:.2g})")


def _print_range_model(fit) -> None:
    import numpy as np

    if fit is None:
        return
    print(f"LiDAR range model: {fit.chosen} ({fit.reason})")
    if not fit.names:
        return
    rings = [(n, v, s) for n, v, s in zip(fit.names, fit.values_m, fit.std_m) if n.startswith("ring")]
    for n, v, s in zip(fit.names, fit.values_m, fit.std_m):
        if not n.startswith("ring"):
            print(f"  {n:8s} {1000 * v:+7.1f} +- {1000 * s:.1f} mm")
    if rings:
        vals = np.array([v for _, v, _ in rings])
        print(f"  per-ring offsets: {len(rings)} rings, spread (sd) {1000 * vals.std():.1f} mm, range "
              f"{1000 * vals.min():+.1f} to {1000 * vals.max():+.1f} mm (all in calibration.json)")
    for n, v in zip(fit.pinned, fit.pinned_values_m):
        print(f"  {n}: estimated {1000 * v:+.1f} mm, beyond {1000 * fit.range_accuracy_m:.0f} mm x 3: held at 0 with "
              "its prior variance in the covariance")
    if fit.offset_translation_correlation:
        print("  correlation of the offset with the translation along the LiDAR's x y z: "
              + "  ".join(f"{c:+.2f}" for c in fit.offset_translation_correlation))
    if fit.confounding:
        c = fit.confounding
        print(f"  confounded: the {c['term']} with {c['direction']} (correlation {c['correlation']:.2f})")
        if c.get("separating_pose"):
            sp = c["separating_pose"]
            x, y, z = sp["board_centre_camera_m"]
            nx, ny, nz = sp["board_normal_camera"]
            now, then = (sp["predicted_translation_std_mm_with_offset"][k] for k in ("now", "with_this_pose"))
            print(f"  the pose that best separates them: board centre at camera ({x:+.2f}, {y:+.2f}, {z:.2f}) m, "
                  f"normal ({nx:+.2f}, {ny:+.2f}, {nz:+.2f}); translation sd along the LiDAR's x y z, predicted from "
                  "the point and corner noise alone (as lidarcam layout does), "
                  + " ".join(f"{v:.1f}" for v in now) + " -> " + " ".join(f"{v:.1f}" for v in then) + " mm")


def _calibrate(args) -> int:
    from .io.dataset import load_dataset
    from .io.rig_dataset import is_rig

    if is_rig(args.dataset):
        return _calibrate_rig(args)
    ds = load_dataset(args.dataset)
    with _figure_process(args, not args.no_report) as figures:
        return _calibrate_with(args, ds, figures)


def _calibrate_rig(args) -> int:
    """A rig folder (``sensors:`` in dataset.yaml): one graph for every sensor (``rig_calibration``)."""
    import numpy as np

    from .io.rig_dataset import load_rig
    from .rig_calibration import calibrate_rig, write_rig_calibration

    rig = load_rig(args.dataset)
    result = calibrate_rig(rig, np.random.default_rng(args.seed), refine_intrinsics=args.refine_intrinsics,
                           samples=args.samples, range_model=args.range_model, edges=bool(args.edges))
    path = write_rig_calibration(result, args.out)
    _print_rig(result)
    print(f"wrote {path}")
    if not args.no_report:
        from .analysis.rig_report import write_rig_report

        print(f"wrote {write_rig_report(result, args.out)}")
    print(f"for ROS tf, URDF or OpenCV: lidarcam export {path} --format ros-tf|urdf|opencv-yaml")
    return 0


def _print_rig(result) -> None:
    import numpy as np

    from .rig_calibration import range_model_words
    from .solvers.outline_check import outline_shift_words
    from .solvers.rig_graph import translation_sd_in_first

    sol = result.solution
    for w in result.warnings[:1]:
        print(f"warning: {w}")
    post = result.posterior
    if post is not None:
        d = post.diagnostics()
        print(f"rig: {len(sol.names)} sensors, reference {sol.reference}; one graph; posterior (emcee, "
              f"{d['parameters']} parameters): {d['effective_samples']:.0f} effective samples, tau "
              f"{d['tau_steps_max']:.0f} steps, acceptance {d['acceptance_fraction']:.2f}, {d['seconds']:.1f} s")
    else:
        print(f"rig: {len(sol.names)} sensors, reference {sol.reference}; one graph, Laplace covariance (posterior "
              "not sampled)")
    for s in result.rig.sensors:
        n = len(result.frames_used.get(s.name, ()))
        skipped = len(result.skipped.get(s.name, {}))
        print(f"  {s.name:10s} {s.type:6s} {n:3d} frames used" + (f", {skipped} skipped" if skipped else "")
              + (f"; {range_model_words(result.range_models[s.name])}" if s.name in result.range_models else ""))
    print("every pair (joint graph; t and its standard deviations in the first sensor's frame, mm; rotation's about "
          "the second sensor's axes, deg; " + ("posterior" if post is not None else "Laplace")
          + " standard deviations; pairwise-only estimate in brackets, as far from the joint one):")
    for a, b in result.pairs():
        T, C = sol.transform(a, b)
        C = C if post is None else np.cov(post.pair_samples(a, b), rowvar=False)
        sd = np.sqrt(np.maximum(np.diag(C), 0.0))
        sd_t = translation_sd_in_first(T, C)
        line = (f"  T_{a}_{b}: t = (" + ", ".join(f"{1000 * v:.1f}" for v in T[:3, 3]) + ") +- ("
                + ", ".join(f"{1000 * v:.1f}" for v in sd_t) + ") mm, rotation sd ("
                + ", ".join(f"{np.degrees(v):.3f}" for v in sd[:3]) + ") deg")
        if (a, b) in result.pairwise:
            from geometry.rotations import T_log

            Tp = result.pairwise[(a, b)][0]
            xi = T_log(np.linalg.inv(T) @ Tp)
            line += (f" [pairwise {np.degrees(np.linalg.norm(xi[:3])):.3f} deg, {1000 * np.linalg.norm(xi[3:]):.1f} mm "
                     "away]")
        print(line)
    for n, e in result.edges.items():
        print(f"  {n} board edges (used): {e['ends']} ends in {e['frames']} frames, scale {e['end_scale']:.2f}, "
              f"in-plane board scatter {1000 * e['board_scatter_in_plane_m']:.1f} mm, growth "
              f"{1000 * e['growth_m'][0]:+.1f} / {1000 * e['growth_m'][1]:+.1f} mm per side, outline offset "
              f"{1000 * e['outline_offset_m'][0]:+.1f} / {1000 * e['outline_offset_m'][1]:+.1f} mm")
    if result.outline_checks:
        print("board edges (a check of the joint estimate, not used in it): each 3D pair's LiDAR board outlines, "
              "camera axes:")
        for (a, b), e in result.outline_checks.items():
            print(f"  T_{a}_{b}: {outline_shift_words(e, ends=True)}")
    for n, (p, sd) in (sol.intrinsics or {}).items():
        given = result.cameras[n].params
        print(f"  {n} intrinsics refined: " + ", ".join(f"{g:.5g} -> {v:.5g} (sd {e:.2g})"
                                                       for g, v, e in zip(given[:4], p[:4], sd[:4])) + " (fx fy cx cy)")
    layout = result.layout()
    if layout["weakest_pair"]:
        w = layout["pairs"][layout["weakest_pair"]]
        print(f"weakest pair: {layout['weakest_pair']}, translation sd up to {w['max_translation_sd_mm']:.1f} mm "
              f"along {w['axis']}; to constrain it, {w['advice']}")
        if layout["next_pose"]:
            from .analysis.rig_layout import next_pose_words

            print("  next pose for it: " + next_pose_words(layout["next_pose"]))
    for link, n in layout["links_with_few_frames"].items():
        print(f"  {link} share {n} frame(s) with the board found in both")
    for w in result.warnings[1:]:
        print(f"warning: {w}")


def _figure_process(args, report: bool):
    """A child that loads matplotlib during the calibration and then draws the report's figures
    (``analysis.figure_process.FigureProcess``), when a report will be drawn; else nothing to start."""
    if report and args.refine != "none":
        from .analysis.figure_process import FigureProcess

        return FigureProcess()
    return contextlib.nullcontext()


def _draw_ahead(figures):
    """The pipeline's ``on_refined`` hook: the report's figures that need no posterior are drawn by the
    figure process while the posterior is sampled (None without a figure process)."""
    if figures is None:
        return None
    from .analysis.report import draw_ahead

    return lambda result: draw_ahead(result, figures)


def _draw_posterior_ahead(result, figures) -> None:
    """Start the posterior's figures (and any other not started yet) as soon as the calibration returns,
    before anything is printed or written."""
    hook = _draw_ahead(figures)
    if hook is not None:
        hook(result)


def _calibrate_with(args, ds, figures) -> int:
    import numpy as np

    from .calibration import calibrate, solve, write_calibration
    from .errors import DatasetError
    from .io.measurement_store import Measurements, load_measurements, save_measurements
    from .lidar.board_segmentation import SegmentationParams

    if args.measurements:
        m = load_measurements(args.measurements)
        if m.board != ds.board or m.lidar != ds.lidar:
            raise DatasetError("the measurements were taken with another board or LiDAR than this dataset.yaml",
                               path=args.measurements, hint="give the dataset the measurements came from")
        from dataclasses import replace

        from .calibration import dataset_range_accuracy

        options = _options(args)
        if options.range_accuracy_m is None:  # as calibrate does: the dataset's LiDAR accuracy
            options = replace(options, range_accuracy_m=dataset_range_accuracy(ds))
        result = solve(m, init=args.init, refine=args.refine, options=options,
                       posterior=_posterior_options(args), rng=np.random.default_rng(args.seed),
                       on_refined=_draw_ahead(figures))
    else:
        result = calibrate(ds, args.init, args.refine, np.random.default_rng(args.seed),
                           SegmentationParams(max_sensor_separation_m=args.max_sensor_separation), _options(args),
                           _posterior_options(args), hints=_hints(args), cache=not args.no_cache,
                           on_refined=_draw_ahead(figures))
        m = Measurements(result.camera, ds.board, ds.lidar, result.frames, (), str(ds.root),
                         result.measurements_source)
    _draw_posterior_ahead(result, figures)
    result = _with_separating_pose(result, ds.board)
    path = write_calibration(result, args.out)
    _print_result(result)
    save_measurements(args.out, m)
    print(f"measurements: {_source_words(result.measurements_source)}; wrote "
          f"{Path(args.out) / 'measurements.npz'} (and .json)")
    print(f"wrote {path}")
    if not args.no_report and result.refinement is not None:
        from .analysis.report import write_report

        print(f"wrote {write_report(result, ds, args.out, figures)} (and its figures)")
    if args.cross_validate or args.split:
        _validation_runs(args, ds, result)
    _export_hint(path)
    return _exit_code(args, result)


def _exit_code(args, result) -> int:
    """0, or ``EXIT_AMBIGUOUS`` (said on stderr) for an ambiguous or contradicted answer under ``--strict``."""
    from .calibration import EXIT_AMBIGUOUS

    if getattr(args, "strict", False) and (result.ambiguous or result.contradicted):
        what = "ambiguous" if result.ambiguous else "contradicted by its boards' edges"
        print(f"lidarcam: the answer is {what} (--strict): exit code {EXIT_AMBIGUOUS}", file=sys.stderr)
        return EXIT_AMBIGUOUS
    return 0


def _with_separating_pose(result, board):
    """The result with, where its range offset is confounded with the extrinsic, the board pose that best separates
    them (``analysis.layout_analysis.separating_pose``) in the confounding record."""
    from dataclasses import replace

    ref = result.refinement
    fit = ref.range_model if ref is not None else None
    if fit is None or not fit.confounding:
        return result
    import numpy as np

    from .analysis.layout_analysis import separating_pose
    from .errors import LidarcamError

    try:
        pose = separating_pose(result, board)
    except (LidarcamError, ValueError, np.linalg.LinAlgError):  # advice only: the calibration stands without it
        pose = None
    if pose is None:
        return result
    fit = replace(fit, confounding={**fit.confounding, "separating_pose": pose})
    return replace(result, refinement=replace(ref, range_model=fit))


def _source_words(source: str) -> str:
    if source == "measured":
        return "measured from the images and scans"
    if source == "cache":
        return "read from the measurement cache (same files and options as an earlier run; --no-cache measures again)"
    return f"read from {source}"


def _validation_runs(args, ds, result) -> None:
    """--cross-validate K and --split halves on the frames already measured (validation.json)."""
    from .analysis.validation import cross_validate, split_halves
    from .calibration import solve
    from .io.output import write_json_atomic

    options = _options(args)

    def solve_subset(frames):
        return solve(frames, ds.board, result.camera, args.init, "factor-graph", options)

    out = {}
    if args.cross_validate:
        cv = cross_validate(list(result.frames), ds.board, result.camera, args.cross_validate, solve_subset)
        out["cross_validation"] = cv
        print(f"cross-validation ({cv['k']} folds): {cv['verdict']}"
              + (f" (chi-square {cv['chi2']:.1f} on {cv['dof']} dof, p = {cv['p_value']:.2g}; flagged: "
                 f"{', '.join(cv['flagged']) or 'none'})" if "chi2" in cv else ""))
    if args.split:
        sh = split_halves(list(result.frames), solve_subset, args.split)
        out["split_halves"] = sh
        extra = (f" (squared Mahalanobis distance {sh['mahalanobis_d2']:.1f}, 99% limit {sh['limit_99']:.1f}; "
                 f"{sh['difference_rotation_deg']:.2f} deg, {sh['difference_translation_mm']:.0f} mm apart)"
                 if "mahalanobis_d2" in sh else "")
        print(f"split ({args.split}): {sh['verdict']}{extra}")
    print(f"wrote {write_json_atomic(Path(args.out) / 'validation.json', out)}")


def _validate(args) -> int:
    import numpy as np

    from .analysis.validation import score_frames, terms_from_json, verdict
    from .calibration import measure_frames
    from .errors import DatasetError
    from .io.dataset import load_dataset
    from .io.input_files import load_json
    from .io.output import write_json_atomic

    cal_path = Path(args.calibration)
    if cal_path.is_dir():
        cal_path = cal_path / "calibration.json"
    cal = load_json(cal_path, "calibration file", "give the calibration.json that lidarcam calibrate wrote")
    try:
        T = np.array(cal["T_camera_lidar"], dtype=float).reshape(4, 4)
        cov = np.array(cal["covariance"], dtype=float).reshape(6, 6)
        noise = cal["noise"]
        used = {f["name"] for f in cal.get("frames", []) if f.get("used")}
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
        raise DatasetError(f"not a calibration.json with a covariance ({type(exc).__name__}: {exc})", path=cal_path,
                           hint="give the calibration.json written by `lidarcam calibrate` (refined)") from None
    if not (np.all(np.isfinite(T)) and np.all(np.isfinite(cov))):
        raise DatasetError("the calibration's transform or covariance is not finite", path=cal_path,
                           hint="recalibrate")
    ds = load_dataset(args.dataset)
    camera, frames, _ = measure_frames(ds, np.random.default_rng(args.seed))
    same = Path(str(cal.get("dataset", ""))).resolve() == Path(ds.root).resolve()
    held = [f for f in frames if f.usable and not (same and f.name in used)]
    note = "frames the calibration did not use"
    if not held:
        held = [f for f in frames if f.usable]
        note = "every frame was used by the calibration: these scores are NOT held out (optimistic)"
    scores = score_frames(held, ds.board, camera, T, cov, float(noise["corner_noise_px"]),
                          float(noise["range_noise_m"]), float(noise.get("plane_floor_m") or 0.0),
                          *terms_from_json(cal.get("lidar_range_model")))
    v = verdict(scores)
    print(f"validate: {len(scores)} frame(s) scored ({note})")
    for s_ in scores:
        print(f"  {s_.name}: chi-square {s_.chi2:6.1f} on {s_.dof} dof (p = {s_.p_value:.2g}); plane offset "
              f"{s_.plane_offset_mm:+6.1f} mm (predicted sd {s_.predicted_offset_sd_mm:.1f}); centre offset "
              f"{s_.outline_offset_px:.1f} px{'  FLAGGED' if s_.flagged else ''}")
    print(f"verdict: {v['verdict']}" + (f" (chi-square {v['chi2']:.1f} on {v['dof']} dof, p = {v['p_value']:.2g})"
                                         if "chi2" in v else ""))
    for f in frames:
        if not f.usable:
            print(f"  {f.name}: skipped: {f.reason}")
    out = Path(args.out) if args.out else cal_path.parent
    path = write_json_atomic(out / "validation.json", {"calibration": str(cal_path), "dataset": str(ds.root),
                                                       "held_out": note, "frames": [x.to_dict() for x in scores],
                                                       **v})
    print(f"wrote {path}")
    return 0


def _hints(args):
    import numpy as np

    from .calibration import Hints, parse_initial_guess

    guess = None if args.initial_guess is None else parse_initial_guess(args.initial_guess)
    roi = (None, None) if args.roi is None else (np.array(args.roi[:3]), np.array(args.roi[3:]))
    if args.roi is not None and np.any(roi[0] >= roi[1]):
        from .errors import LidarcamError

        raise LidarcamError(f"--roi box is empty ({args.roi})", hint="give XMIN YMIN ZMIN XMAX YMAX ZMAX with each "
                                                                    "minimum below its maximum")
    return Hints(initial_guess=guess, guess_angle_rad=float(np.deg2rad(args.guess_tolerance[0])),
                 guess_distance_m=float(args.guess_tolerance[1]), roi_min=roi[0], roi_max=roi[1],
                 static_scene=not args.no_static_scene)


def _export_hint(path) -> None:
    print(f"for ROS tf, URDF, KITTI or OpenCV: lidarcam export {path} --format ros-tf|urdf|kitti|opencv-yaml")


def _simulate(args) -> int:
    from .simulation.simulator import simulate_dataset

    if args.poses < 1:
        raise SystemExit("lidarcam: error: --poses must be at least 1")
    if args.cameras == 1 and (args.lidars != 1 or args.scanners != 0):
        raise SystemExit("lidarcam: error: --lidars and --scanners are for a rig folder (add --cameras N, 2 or more)")
    if args.cameras != 1:
        if args.cameras < 2 or args.lidar == "2d":
            raise SystemExit("lidarcam: error: --cameras N (2 or more) writes a rig folder with a 3D LiDAR")
        from .simulation.rig_simulator import simulate_rig

        if args.lidars not in (1, 2):
            raise SystemExit("lidarcam: error: --lidars is 1 or 2")
        if args.scanners not in (0, 1):
            raise SystemExit("lidarcam: error: --scanners is 0 or 1")
        if args.range_bias_from_priors is not None:
            raise SystemExit("lidarcam: error: --range-bias-from-priors is for a single pair (a rig takes "
                             "--range-bias, injected into lidar0)")
        out = simulate_rig(args.out, args.poses, args.seed, args.cameras, args.model, args.overwrite, args.lidars,
                           args.scanners, range_bias=None if args.range_bias is None else tuple(args.range_bias))
        print(f"wrote a rig of {args.cameras} cameras, {args.lidars} 3D LiDAR(s) and {args.scanners} 2D scanner(s) "
              f"({args.poses} frames) to {out}")
        return 0
    two_d = args.lidar == "2d"
    fmt = args.scan_format or ("csv" if two_d else "pcd")
    allowed = ("csv", "npy", "pcd") if two_d else ("pcd", "ply", "bin", "npy")
    if fmt not in allowed:
        raise SystemExit(f"lidarcam: error: --scan-format {fmt} is not a {args.lidar} scan format (use one of "
                         f"{', '.join(allowed)})")
    if args.rig != "default" and not two_d:
        raise SystemExit("lidarcam: error: --rig varied is a 2D rig (add --lidar 2d)")
    if args.outside_image_share is not None and (args.pattern != "charuco" or not 0 <= args.outside_image_share <= 1):
        raise SystemExit("lidarcam: error: --outside-image-share is a share (0 to 1) of the poses of a charuco board "
                         "(a checkerboard must be seen whole)")
    noise = args.range_noise if args.range_noise is not None else (0.01 if two_d else 0.02)
    model = "2d" if two_d else args.model
    out = simulate_dataset(args.out, args.poses, args.seed, model, noise, args.pixel_noise,
                           fmt, include_camera=not args.no_camera, overwrite=args.overwrite, scene=args.scene,
                           range_bias=None if args.range_bias is None else tuple(args.range_bias),
                           rig_config=args.rig, pattern=args.pattern, outside_image_share=args.outside_image_share,
                           range_bias_family=args.range_bias_from_priors, intensity=args.intensity,
                           ring_field=not args.no_ring)
    print(f"wrote {args.poses} frames ({'2D scanner' if two_d else args.model}, {args.scene} scene, {args.pattern}) "
          f"to {out}")
    return 0


def _layout(args) -> int:
    import numpy as np

    from .analysis.layout_analysis import analyse, layout_from_plan, suggest_poses
    from .errors import DatasetError
    from .io.input_files import load_yaml
    from .io.output import write_json_atomic

    src = Path(args.source)
    if src.is_dir():
        from .analysis.layout_analysis import layout_from_result
        from .calibration import calibrate
        from .io.dataset import load_dataset

        ds = load_dataset(src)
        result = calibrate(ds, rng=np.random.default_rng(args.seed), posterior=None)
        model = "2d" if ds.lidar == "2d" else args.lidar_model
        layout, rig, names = layout_from_result(result, ds.board, model)
    elif src.is_file():
        plan = load_yaml(src, "plan", "fix the plan file")
        if not isinstance(plan, dict):
            raise DatasetError("a plan must be a mapping", path=src,
                               hint="see the PLAN.yaml format in docs/howto/layout.md")
        layout, rig = layout_from_plan(plan, str(src))
        names = [f"plan{i:02d}" for i in range(layout.n_frames)]
    else:
        raise DatasetError("no such dataset folder or plan file", path=src, hint="check the path")
    analysis = analyse(layout, names)
    print(analysis.format())
    out = analysis.to_dict()
    if args.suggest > 0 or args.target:
        from .analysis.layout_analysis import meets

        k_max = args.suggest if not args.target else max(args.suggest, 40)
        target = tuple(args.target) if args.target else None
        print(f"suggested poses (greedy, D-optimal among sampled feasible poses, seed {args.seed}):")
        out["suggestions"] = []
        found = suggest_poses(layout, rig, k_max, np.random.default_rng(args.seed), target=target,
                              range_offset=args.range_offset)
        if target is not None:
            final = found[-1][1] if found else analysis
            if meets(final, *target):
                print(f"the target ({target[0]} deg, {target[1]} mm per axis) is met with {len(found)} more pose(s): "
                      f"{layout.n_frames + len(found)} in all")
            else:
                print(f"the target is not met even with {len(found)} more poses; the closest is below")
        for k, (T, after) in enumerate(found):
            c = T[:3, :3] @ layout.board.centre + T[:3, 3]
            n = T[:3, 2]
            print(f"  {k + 1}: board centre at camera ({c[0]:+.2f}, {c[1]:+.2f}, {c[2]:.2f}) m, normal "
                  f"({n[0]:+.2f}, {n[1]:+.2f}, {n[2]:+.2f}); then std rotation "
                  + " ".join(f"{v:.3f}" for v in after.std_rotation_deg) + " deg, translation "
                  + " ".join(f"{v:.2f}" for v in after.std_translation_mm) + " mm")
            out["suggestions"].append({"T_camera_board": T.tolist(), "centre_m": c.tolist(),
                                       "std_after": after.to_dict()["predicted_std"]})
    if args.json:
        print(f"wrote {write_json_atomic(args.json, out)}")
    return 0


def _study(args) -> int:
    from .analysis.coverage_study import format_summary, run_study

    if args.trials < 1 or args.frames < 3 or args.samples < 1 or args.workers < 1:
        raise SystemExit("lidarcam: error: --trials, --samples and --workers must be positive and --frames >= 3")
    summary = run_study(args.trials, args.out, args.mode, args.seed, args.workers, args.frames, args.samples,
                        progress=sys.stderr.isatty(), likelihood=args.likelihood)
    print(format_summary(summary))
    print(f"wrote {Path(args.out) / 'coverage.csv'} and coverage.json")
    return 0


def _study_spec_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="lidarcam study",
                                description="run a solver-comparison study (a grid of simulated calibrations)")
    p.add_argument("spec", help="SPEC.yaml: solvers x frames x noise levels x trials (docs/howto/studies.md)")
    p.add_argument("--out", required=True, help="folder for study.csv, summary.json and the summary plots")
    p.add_argument("--workers", type=int, default=os.cpu_count() or 1, help="local processes")
    p.add_argument("--scheduler", default=None, metavar="tcp://HOST:PORT",
                   help="run on this Dask distributed scheduler instead of local processes (same results)")
    return p


def _study_spec(argv: list[str]) -> int:
    from .analysis.study import format_summary, parse_spec, run_study, summarize
    from .io.input_files import load_yaml

    args = _study_spec_parser().parse_args(argv)
    path = Path(args.spec)
    raw = load_yaml(path, "study spec", "fix the spec (see docs/howto/studies.md)")
    spec = parse_spec(raw, str(path))
    if args.workers < 1:
        raise SystemExit("lidarcam: error: --workers must be positive")
    where = args.scheduler or f"{args.workers} local process(es)"
    print(f"{spec.name}: {spec.n_trials} trials x {len(spec.solvers)} solvers on {where}")
    rows = run_study(spec, args.out, args.workers, args.scheduler, progress=sys.stderr.isatty())
    print(format_summary(summarize(rows)))
    print(f"wrote {Path(args.out) / 'study.csv'}, summary.json and the plots")
    return 0


def _board_argument(text: str):
    """``NXxNY:SQUARE[:WxH]`` or a YAML file with a ``board:`` mapping (or the mapping itself)."""
    from .errors import LidarcamError
    from .io.dataset import parse_board
    from .io.input_files import load_yaml

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


def _extract(args) -> int:
    from .io.bag_extract import ExtractOptions, extract_bag

    options = ExtractOptions(max_dt_s=args.max_dt, still_s=args.still_s, still_px=args.still_px,
                             check_hz=args.check_hz, scan_format=args.scan_format)
    if not args.cloud_topic and not args.scan_topic:
        raise SystemExit("lidarcam: error: give a LiDAR topic: --cloud-topic (3D) or --scan-topic (2D)")
    if len(args.image_topic) + len(args.cloud_topic) + len(args.scan_topic) > 2:  # a rig folder
        from .io.rig_bag_extract import extract_rig_bag

        if args.camera_info_topic is not None:
            raise SystemExit("lidarcam: error: --camera-info-topic is for one camera; a rig's cameras each take "
                             "the CameraInfo beside their image topic")
        rig = extract_rig_bag(args.bag, args.out, _board_argument(args.board), args.image_topic, args.cloud_topic,
                              args.scan_topic, use_camera_info=not args.no_camera_info, options=options,
                              progress=sys.stderr.isatty(), overwrite=args.overwrite)
        print("\n".join(rig.lines()))
        print(f"wrote {rig.out} (next: lidarcam calibrate {rig.out} --out OUT)")
        return 0
    summary = extract_bag(args.bag, args.out, _board_argument(args.board), args.image_topic[0],
                          cloud_topic=(args.cloud_topic or [None])[0], scan_topic=(args.scan_topic or [None])[0],
                          camera_info_topic=args.camera_info_topic, use_camera_info=not args.no_camera_info,
                          options=options, progress=sys.stderr.isatty(), overwrite=args.overwrite)
    print("\n".join(summary.lines()))
    if summary.frames < 4:
        print(f"warning: only {summary.frames} frames; a 3D calibration needs 3 or more spread poses, 4+ "
              "are advised", file=sys.stderr)
    print(f"wrote {summary.out} (next: lidarcam calibrate {summary.out} --out OUT)")
    return 0


def _export(args) -> int:
    from .io.export import export_calibration, write_export

    frames = {"camera_frame": args.camera_frame, "lidar_frame": args.lidar_frame, "parent": args.parent}
    if args.out is None:
        sys.stdout.write(export_calibration(args.calibration, args.format, **frames))
    else:
        print(f"wrote {write_export(args.calibration, args.format, args.out, **frames)}")
    return 0


def _demo(args) -> int:
    # The figure process starts first: it loads matplotlib while this process loads the pipeline.
    with _figure_process(args, True) as figures:
        return _demo_with(args, figures)


def _demo_with(args, figures) -> int:
    import numpy as np

    from .calibration import calibrate, import_sampler_ahead, write_calibration
    from .io.dataset import load_dataset
    from .simulation.simulator import simulate_dataset

    base = Path(args.out)
    data = base / "dataset"
    print(f"simulating {args.poses} poses of the default rig ({args.model}, seed {args.seed}) into {data} ...")
    import_sampler_ahead()  # while the frames are simulated
    simulate_dataset(data, args.poses, args.seed, args.model, overwrite=True)
    ds = load_dataset(data)
    result = calibrate(ds, refine=args.refine, rng=np.random.default_rng(args.seed), options=_options(args),
                       posterior=_posterior_options(args), on_refined=_draw_ahead(figures))
    _draw_posterior_ahead(result, figures)
    _print_result(result, ds.ground_truth())
    print(f"time: {result.timings_s['total_wall']:.1f} s for measurements and solve")
    path = write_calibration(result, base)
    print(f"wrote {path}")
    if result.refinement is not None:
        from .analysis.report import write_report

        print(f"wrote {write_report(result, ds, base, figures)} (open it in a browser)")
    _export_hint(path)
    return 0


def run() -> None:
    """The ``lidarcam`` console script: :func:`main`, then the process ends at once with its exit code. Every
    file is written and closed by then; skipping the interpreter's orderly teardown of GTSAM, OpenCV, scipy
    and the rest saves a quarter of a second per command."""
    code = main()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    spec_study = len(argv) >= 2 and argv[0] == "study" and argv[1] not in ("coverage", "-h", "--help")
    args = None if spec_study else _parser().parse_args(argv)
    # The pipeline parallelises over frames itself; OpenBLAS's own threads would compete with it for the
    # cores (and keep spinning after large products, slowing the small-matrix work that follows).
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    from .errors import LidarcamError

    handlers = {"calibrate": _calibrate, "validate": _validate, "simulate": _simulate, "demo": _demo, "study": _study, "layout": _layout,
                "extract": _extract, "export": _export}
    try:
        if spec_study:
            return _study_spec(argv[1:])
        return handlers[args.command](args)
    except LidarcamError as exc:
        print(f"lidarcam: error: {exc.message}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("lidarcam: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    run()
