"""ChArUco boards against the checkerboard (make bench; issue 18).

(a) Detection on rendered images at three resolutions, the same poses for both patterns: boards found,
    per-corner RMS error against the truth (the corners the board pose keeps), median seconds per image on
    one core. Target: ChArUco within 1.5x the checkerboard's time at 1920x1208.
(b) End to end (render, detect, segment, solve, factor graph; no posterior) on layouts that both patterns see
    whole: RMS error over trials against the Cramer-Rao bound of the layout. Target: ChArUco's ratio within
    10% of the checkerboard's.
(c) ChArUco datasets with about 30% of the poses cut by the image's edge: frames with at least 6 corners in
    the image, and how many of them calibrate uses. Target: all.

`python benchmarks/bench_charuco.py [--trials N]` (default 12 per row of (b)).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import cv2  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from estimators import calibrate  # noqa: E402
from estimators.camera.board_pose import estimate_board_pose  # noqa: E402
from estimators.camera.corners import detect_corners  # noqa: E402
from estimators.io.dataset import load_dataset  # noqa: E402
from estimators.simulation.rendering import render_image  # noqa: E402
from estimators.simulation.simulator import (as_charuco, default_rig, sample_board_poses, scene_patches,  # noqa: E402
                                             simulate_dataset, simulate_frames, write_dataset)
from estimators.solvers.observation_model import Layout, cramer_rao_bound  # noqa: E402
from geometry.camera import CameraModel  # noqa: E402
from geometry.rotations import T_inverse, T_log, transform_points  # noqa: E402


def _scaled_rig(rig, w: int, h: int):
    k = w / 1024.0
    K = rig.camera.K.copy()
    K[0, 0] *= k
    K[1, 1] *= k
    K[0, 2], K[1, 2] = w / 2.0, h / 2.0
    return replace(rig, camera=CameraModel(K, rig.camera.dist, w, h, rig.camera.model, "bench"))


def _corner_errors(obs, rig, T_cb) -> np.ndarray:
    """Detected minus true corners (M, 2); a checkerboard's detector may list its grid reversed (the
    pattern's half-turn symmetry), so the better of the two orders."""
    truth = rig.camera.project(transform_points(T_cb, obs.corners_board(rig.board)))
    if obs.corner_ids is not None:
        return obs.corners_px - truth
    return min((obs.corners_px - truth, obs.corners_px[::-1] - truth), key=lambda d: float(np.sum(d**2)))


def detection(images: int = 8) -> None:
    print("(a) detection on rendered images (same poses; corner RMS error against the truth, px; median s/image, "
          "one core)")
    print(f"{'resolution':12s}{'pattern':>14s}{'found':>7s}{'corners':>9s}{'err px':>8s}{'s/image':>9s}"
          f"{'time ratio':>12s}")
    base = default_rig(np.random.default_rng(0))
    for w, h in ((1024, 768), (1920, 1208), (3840, 2160)):
        rig0 = _scaled_rig(base, w, h)
        poses = sample_board_poses(rig0, images, np.random.default_rng(7))
        times = {}
        for pattern in ("checkerboard", "charuco"):
            rig = rig0 if pattern == "checkerboard" else replace(rig0, board=as_charuco(rig0.board))
            rng = np.random.default_rng(8)
            T_lc = T_inverse(rig.T_camera_lidar)
            found, n_corners, errs, t = 0, 0, [], []
            for T_cb in poses:
                T_lb = T_lc @ T_cb
                patches, bi = scene_patches(rig, T_lb)
                gray = render_image(rig.camera, T_lc, patches, bi, transform_points(T_lb, rig.board.outline()), rng)
                t0 = time.perf_counter()
                det = detect_corners(gray, rig.board)
                t.append(time.perf_counter() - t0)
                if det is None:
                    continue
                e = np.sum(_corner_errors(estimate_board_pose(det, rig.board, rig.camera), rig, T_cb) ** 2, axis=1)
                errs.append(e)
                found += 1
                n_corners += len(e)
            times[pattern] = float(np.median(t))
            ratio = times[pattern] / times["checkerboard"]
            print(f"{f'{w}x{h}':12s}{pattern:>14s}{found:7d}{n_corners:9d}"
                  f"{float(np.sqrt(np.mean(np.concatenate(errs)))) if errs else float('nan'):8.3f}"
                  f"{times[pattern]:9.3f}{ratio:12.2f}")
    print("  target: ChArUco at most 1.5x the checkerboard's time at 1920x1208")


def accuracy(trials: int, tmp: Path) -> None:
    print(f"\n(b) end to end on layouts both patterns see whole (8 poses, VLP-16, 2 cm range noise; {trials} trials)")
    errs = {"checkerboard": [], "charuco": []}
    scaled = {"checkerboard": [], "charuco": []}
    used = {"checkerboard": 0, "charuco": 0}
    for t in range(trials):
        rng = np.random.default_rng([18, t])
        rig0 = default_rig(rng, "vlp16", 0.02)
        poses = sample_board_poses(rig0, 8, rng)
        for pattern in errs:
            rig = rig0 if pattern == "checkerboard" else replace(rig0, board=as_charuco(rig0.board))
            frames = simulate_frames(rig, 8, np.random.default_rng([18, t, 1]), poses=poses)
            path = write_dataset(tmp / f"{pattern}_{t}", rig, frames)
            res = calibrate(load_dataset(path), rng=np.random.default_rng(t), posterior=None)
            xi = T_log(T_inverse(res.T_camera_lidar) @ rig.T_camera_lidar)
            # The bound of this layout at the corner noise this pattern's detections actually have (their
            # per-axis RMS error against the true corners) and the simulated 2 cm range noise.
            e = np.concatenate([_corner_errors(f.camera, rig, T_cb) for f, T_cb in zip(res.frames, poses) if f.usable])
            layout = Layout(rig.camera, rig.board, rig.beams, rig.T_camera_lidar, tuple(poses),
                            float(np.sqrt(np.mean(e**2))), 0.02)
            crb = cramer_rao_bound(layout)
            bound = np.array([np.trace(crb[:3, :3]), np.trace(crb[3:, 3:])])
            errs[pattern].append(xi)
            scaled[pattern].append(np.array([xi[:3] @ xi[:3], xi[3:] @ xi[3:]]) / bound)
            used[pattern] += len(res.frames_used["lidar0"])
    print("  ratio: RMS over trials of each trial's error against its layout's Cramer-Rao bound at the corner noise")
    print("  of the pattern's own detections (against the true corners) and 2 cm range noise; the 3 axes together")
    print(f"  {'pattern':14s}{'frames used':>12s}{'rot RMS deg':>13s}{'trans RMS mm':>14s}{'rot/CRB':>9s}"
          f"{'trans/CRB':>11s}")
    ratio = {}
    for pattern, xis in errs.items():
        x = np.array(xis)
        ratio[pattern] = np.sqrt(np.mean(scaled[pattern], axis=0))
        print(f"  {pattern:14s}{f'{used[pattern]}/{8 * trials}':>12s}"
              f"{np.degrees(np.sqrt(np.mean(np.sum(x[:, :3] ** 2, axis=1)))):13.4f}"
              f"{1000 * np.sqrt(np.mean(np.sum(x[:, 3:] ** 2, axis=1))):14.2f}"
              f"{ratio[pattern][0]:9.2f}{ratio[pattern][1]:11.2f}")
    q = ratio["charuco"] / ratio["checkerboard"]
    print(f"  ChArUco / checkerboard: rotation {q[0]:.2f}, translation {q[1]:.2f} (target at most 1.10)")


def partial(datasets: int, tmp: Path) -> None:
    print(f"\n(c) ChArUco datasets with about 30% of the poses cut by the image's edge ({datasets} x 8 poses)")
    cut = with6 = used = 0
    for k in range(datasets):
        path = simulate_dataset(tmp / f"cut_{k}", 8, seed=100 + k, lidar="vlp16", pattern="charuco")
        ds = load_dataset(path)
        truth = json.loads((path / "ground_truth.json").read_text())["T_camera_board"]
        res = calibrate(ds, rng=np.random.default_rng(k), posterior=None)
        used_names = set(res.frames_used["lidar0"])
        for f in ds.frames:
            uv = ds.camera.project(transform_points(np.array(truth[f.name]), ds.board.inner_corners()))
            n_in = int(ds.camera.in_image(uv).sum())
            cut += n_in < len(uv)
            if n_in >= 6:
                with6 += 1
                used += f.name in used_names
    print(f"  poses cut by the image's edge: {cut} of {8 * datasets}; frames with at least 6 corners in the image: "
          f"{with6}; used: {used} (target: all)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=12)
    args = ap.parse_args()
    cv2.setNumThreads(1)
    detection()
    with tempfile.TemporaryDirectory() as tmp:
        accuracy(args.trials, Path(tmp))
        partial(max(2, args.trials // 3), Path(tmp))


if __name__ == "__main__":
    main()
