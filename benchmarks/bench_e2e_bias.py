"""End-to-end bias: the truth's offsets from the estimate over independent sets of simulated datasets.

In standard deviations, over datasets rendered and ray cast end to end (the pipeline's defaults), and where a
shift would come from: each frame's camera board-plane distance and LiDAR plane distance (mapped by the true
extrinsic) against the true board.

Trials draw their seeds as ``lidarcam study coverage`` does (``SeedSequence(seed)``), so ``--seed 0`` holds the
posterior page's end-to-end datasets (its first N) and other seeds independent ones.

Usage: python benchmarks/bench_e2e_bias.py [--trials 100] [--seeds 0 1 2] [--workers 2]
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

AXES = ("rot_x", "rot_y", "rot_z", "trans_x", "trans_y", "trans_z")


def trial(seed: int) -> tuple[np.ndarray, list[float], list[float]]:
    """One dataset: the truth's tangent offset from the estimate over the Laplace standard deviations, and its
    frames' camera and LiDAR plane distance errors (m)."""
    from estimators import calibrate
    from estimators.io.dataset import load_dataset
    from estimators.simulation.simulator import default_rig, sample_board_poses, simulate_frames, write_dataset
    from geometry.rotations import T_inverse, T_log

    rng = np.random.default_rng(seed)
    rig = default_rig(rng, "hdl64e", 0.02)  # as the coverage study's end-to-end trials
    poses = sample_board_poses(rig, 8, rng)
    with tempfile.TemporaryDirectory() as tmp:
        sim = simulate_frames(rig, 8, rng, poses=poses, workers=1)
        result = calibrate(load_dataset(write_dataset(Path(tmp) / "ds", rig, sim)), rng=rng, samples=0)
    truth = {f.name: f.T_camera_board for f in sim}
    cam, lid = [], []
    for f in result.frames:
        if f.usable and f.name in truth:
            n, p = truth[f.name][:3, 2], truth[f.name][:3, 3]
            for plane, out in ((f.camera.plane, cam), (f.lidar.plane.transformed(rig.T_camera_lidar), lid)):
                out.append(float(np.sign(plane.normal @ n) * plane.distance - n @ p))
    xi = T_log(T_inverse(result.T_camera_lidar) @ rig.T_camera_lidar)
    return xi / np.sqrt(np.diag(result.covariance)), cam, lid


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=100)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args()
    print(f"{args.trials} end-to-end datasets per seed (8 poses, HDL-64E-like, the pipeline's defaults); "
          "z: the truth's "
          "offset from the estimate over its Laplace standard deviation (mean 0 without bias; its standard error "
          "about 1/sqrt(trials))")
    print(f"{'seed':>4s} " + " ".join(f"{a:>14s}" for a in AXES) + "   camera plane mm   LiDAR plane mm")
    pooled = []
    with ProcessPoolExecutor(max_workers=args.workers) as pool:
        for seed in args.seeds:
            seeds = [int(s) for s in np.random.SeedSequence(seed).generate_state(args.trials)]
            rows = list(pool.map(trial, seeds))
            z = np.array([r[0] for r in rows])
            cam = 1000 * np.concatenate([r[1] for r in rows])
            lid = 1000 * np.concatenate([r[2] for r in rows])
            pooled.append(z)
            se = z.std(axis=0, ddof=1) / np.sqrt(len(z))
            print(f"{seed:4d} " + " ".join(f"{m:+6.2f} +- {s:4.2f}" for m, s in zip(z.mean(axis=0), se))
                  + f"   {cam.mean():+.3f} +- {cam.std(ddof=1) / np.sqrt(len(cam)):.3f}"
                  + f"   {lid.mean():+.3f} +- {lid.std(ddof=1) / np.sqrt(len(lid)):.3f}")
    z = np.concatenate(pooled)
    se = z.std(axis=0, ddof=1) / np.sqrt(len(z))
    print(f"{'all':>4s} " + " ".join(f"{m:+6.2f} +- {s:4.2f}" for m, s in zip(z.mean(axis=0), se)))
    print("(+- one standard error over the trials; plane distances: each frame's error against the true board, the "
          "LiDAR's plane mapped by the true extrinsic, mean over the frames)")


if __name__ == "__main__":
    main()
