"""How well each rig camera's corner noise model describes its board poses, on simulated rig folders (make bench;
`python benchmarks/bench_rig_corners.py [--rigs N] [--cameras C] [--poses P]`).

Each rig (`simulation.rig_simulator`, as in bench_rig.py: C cameras and an HDL-64E-like LiDAR, P board poses in
the first camera's view) is calibrated from its folder (`rig_calibration.calibrate_rig`, no posterior). For every
camera and every board it saw: the error of its board pose (PnP on the detected corners) against the truth, and
its squared Mahalanobis distance under the pose covariance at the noise the graph gives that board's corners
(`CameraViews.sigma`: the board's own residual, shrunk towards the camera's pooled one, times
`refinement_options.CORNER_ERROR_CORRELATION`), and, beside it, at one pooled noise per camera as the single pair had
it (the pooled residual times 1.28, `POOLED_FACTOR`), in all 6 of the pose's
numbers (6 ideal), in the 3 that fix the board's plane (rotation about the board's x and y, translation along
its normal: what a LiDAR sees; 3 ideal) and in the 3 in the plane (3 ideal). For two cameras that saw the same
board: the d2 of the difference of their board-frame errors, what a camera-camera transform rests on (6 ideal if
their errors were independent). The mean corner residual (per axis) and `sigma_px` (pooled, times the rig's factor)
per camera are printed too, and over all boards the fraction beyond chi-square's 99% point (1% ideal).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_rig import numbered_as  # noqa: E402

PLANE, IN_PLANE = [0, 1, 5], [2, 3, 4]
POOLED_FACTOR = 1.28  # the single pair's corner model before each board had its own noise


def _one(args) -> dict:
    from estimators.io.rig_dataset import load_rig
    from estimators.pipeline.rig_measurement import pattern_flip
    from estimators.rig_calibration import calibrate_rig
    from estimators.solvers.refinement_options import CORNER_ERROR_CORRELATION
    from estimators.simulation.rig_simulator import simulate_rig
    from estimators.solvers.factors import corner_residuals
    from geometry.rotations import T_log

    seed, cameras, poses = args
    with tempfile.TemporaryDirectory() as tmp:
        folder = simulate_rig(Path(tmp) / "rig", poses, seed, cameras)
        gt = json.loads((folder / "ground_truth.json").read_text())
        res = calibrate_rig(load_rig(folder), np.random.default_rng(seed), workers=1, samples=0, advise=False)
    flip = pattern_flip(res.rig.board)
    out = {"cameras": {}, "pairs": {}}
    errors = {}
    for cv in res.camera_views:
        T_cam0_cam = np.array(gt[f"T_cam0_{cv.name}"])
        rows = []
        for stem, T_hat in cv.T_camera_board.items():
            T_true = numbered_as(T_hat, np.linalg.inv(T_cam0_cam) @ np.array(gt["T_cam0_board"][stem]), flip)
            xi = T_log(np.linalg.inv(T_hat) @ T_true)
            r, H = corner_residuals(T_hat, cv.corners_board[stem], cv.corners_px[stem], cv.camera)
            info = H.T @ H / cv.sigma(stem)**2
            C = np.linalg.inv(info)
            part = [float(xi[k] @ np.linalg.solve(C[np.ix_(k, k)], xi[k])) for k in (PLANE, IN_PLANE)]
            pooled = cv.sigma_px / CORNER_ERROR_CORRELATION * POOLED_FACTOR
            rows.append((float(xi @ info @ xi), *part, float(np.sqrt(np.mean(r**2))),
                         float(xi @ H.T @ H @ xi) / pooled**2))
            errors[(cv.name, stem)] = (xi, C)
        out["cameras"][cv.name] = (rows, cv.sigma_px)
    names = [cv.name for cv in res.camera_views]
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            shared = sorted({s for n, s in errors if n == a} & {s for n, s in errors if n == b})
            out["pairs"][f"{a}-{b}"] = [float((d := errors[(a, s)][0] - errors[(b, s)][0])
                                              @ np.linalg.solve(errors[(a, s)][1] + errors[(b, s)][1], d))
                                        for s in shared]
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--rigs", type=int, default=10)
    ap.add_argument("--cameras", type=int, default=6)
    ap.add_argument("--poses", type=int, default=16)
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args()
    with ProcessPoolExecutor(args.workers) as pool:
        runs = list(pool.map(_one, [(s, args.cameras, args.poses) for s in range(args.rigs)]))
    print(f"{args.rigs} simulated rigs: {args.cameras} cameras + an HDL-64E-like LiDAR, {args.poses} board poses in "
          "the first camera's view; each camera's board poses against the truth at the graph's corner noise")
    print(f"{'':38s}{'each board its own noise':>34s}{'one pooled noise':>18s}")
    print(f"{'camera':8s}{'boards':>8s}{'residual px':>13s}{'sigma_px':>10s}{'d2 (6)':>9s}{'plane (3)':>11s}"
          f"{'in-plane (3)':>14s}{'d2 (6)':>10s}{'median':>8s}")
    everyone = []
    for name in runs[0]["cameras"]:
        rows = np.array([row for r in runs if name in r["cameras"] for row in r["cameras"][name][0]])
        everyone.append(rows)
        sigma = np.mean([r["cameras"][name][1] for r in runs if name in r["cameras"]])
        print(f"{name:8s}{len(rows):8d}{rows[:, 3].mean():13.3f}{sigma:10.3f}{rows[:, 0].mean():9.2f}"
              f"{rows[:, 1].mean():11.2f}{rows[:, 2].mean():14.2f}{rows[:, 4].mean():10.2f}"
              f"{np.median(rows[:, 4]):8.2f}")
    rows = np.concatenate(everyone)
    q99 = 16.81  # chi-square, 6 dof, 99%
    print(f"all {len(rows)} boards: each its own noise: d2 mean {rows[:, 0].mean():.2f}, "
          f"median {np.median(rows[:, 0]):.2f} "
          f"(chi-square 5.35), beyond the 99% point {100 * np.mean(rows[:, 0] > q99):.1f}%; "
          "one pooled noise per camera "
          f"(x {POOLED_FACTOR}): mean {rows[:, 4].mean():.2f}, median {np.median(rows[:, 4]):.2f}, beyond "
          f"{100 * np.mean(rows[:, 4] > q99):.1f}%")
    print("two cameras' errors on the boards both saw: d2 of their difference (6 if independent)")
    for pair in runs[0]["pairs"]:
        d2 = [x for r in runs for x in r["pairs"].get(pair, [])]
        if d2:
            print(f"{pair:12s}{len(d2):6d} boards  d2 {np.mean(d2):.2f}")


if __name__ == "__main__":
    main()
