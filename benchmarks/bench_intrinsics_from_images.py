"""Coverage of the engine's covariance where the camera's intrinsics are calibrated from the dataset's own images
(make bench; `python benchmarks/bench_intrinsics_from_images.py [--trials 16] [--seed 300]`).

Simulated 8-frame datasets (VLP-16 and HDL-64 in turn) with the camera block taken out of dataset.yaml, so that
the intrinsics are calibrated from the same images (Zhang, OpenCV's standard deviations), calibrated by the engine
(``calibrate_rig``, no posterior: its Laplace covariance). The truth's squared Mahalanobis distance (NEES, 6 dof)
under the joint covariance with the held intrinsics' share (``rig_graph.held_intrinsics_share``), under the same
covariance without it (the engine before it had the share), and under the camera-LiDAR pair's own solve's covariance
(its refinement's first-order intrinsics term). An honest covariance has NEES mean 6 and 95% of the trials below
12.59.
"""
from __future__ import annotations

import argparse
import json
import multiprocessing
import sys
import tempfile
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

LIMIT_95 = 12.59  # chi-square, 6 dof


def trial(seed: int) -> dict:
    from estimators.io.rig_dataset import load_rig
    from estimators.rig_calibration import calibrate_rig
    from estimators.simulation.simulator import simulate_dataset
    from estimators.solvers.refinement_options import RefinementOptions
    from estimators.solvers.rig_graph import held_intrinsics_share
    from geometry.rotations import T_log

    lidar = ("vlp16", "hdl64e")[seed % 2]
    with tempfile.TemporaryDirectory() as tmp:
        path = simulate_dataset(Path(tmp) / "ds", n_poses=8, seed=seed, lidar=lidar)
        text = (path / "dataset.yaml").read_text()
        (path / "dataset.yaml").write_text(text[:text.index("camera:")])
        truth = np.array(json.loads((path / "ground_truth.json").read_text())["T_camera_lidar"])
        r = calibrate_rig(load_rig(path), np.random.default_rng(seed), samples=0, advise=False)
    sol = r.solution
    T, C = sol.transform("cam0", "lidar0")
    share = held_intrinsics_share(sol.names, sol.reference, list(r.camera_views), list(r.lidar_views), sol,
                                  RefinementOptions())
    without = replace(sol, covariance_joint=sol.covariance_joint - share)
    _, C0 = without.transform("cam0", "lidar0")
    xi = T_log(np.linalg.inv(T) @ truth)
    pair = r.pair_results[("cam0", "lidar0")]
    xp = T_log(np.linalg.inv(pair.T_camera_lidar) @ truth)
    return {"seed": seed, "lidar": lidar, "frames": len(r.pair_frames[("cam0", "lidar0")]),
            "rot_err_deg": float(np.degrees(np.linalg.norm(xi[:3]))),
            "trans_err_mm": float(1000 * np.linalg.norm(xi[3:])),
            "sd_rot_deg": float(np.degrees(np.sqrt(np.trace(C[:3, :3])))),
            "sd_rot_deg_without": float(np.degrees(np.sqrt(np.trace(C0[:3, :3])))),
            "nees": float(xi @ np.linalg.solve(C, xi)), "nees_without": float(xi @ np.linalg.solve(C0, xi)),
            "nees_pair": float(xp @ np.linalg.solve(pair.covariance, xp))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--trials", type=int, default=16)
    ap.add_argument("--seed", type=int, default=300)
    args = ap.parse_args()
    seeds = list(range(args.seed, args.seed + args.trials))
    with ProcessPoolExecutor(2, mp_context=multiprocessing.get_context("forkserver")) as pool:
        rows = list(pool.map(trial, seeds))
    print(f"{args.trials} simulated 8-frame datasets (VLP-16 and HDL-64 in turn, seeds {seeds[0]}..{seeds[-1]}), the "
          "camera's intrinsics calibrated from the same images; the engine's estimate, no posterior")
    print()
    print("| seed | LiDAR | frames | error deg, mm | rotation sd (root of trace) deg: with the share, without | NEES "
          "with the share | without | the pair's own |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['seed']} | {r['lidar']} | {r['frames']} | {r['rot_err_deg']:.3f}, {r['trans_err_mm']:.1f} | "
              f"{r['sd_rot_deg']:.3f}, {r['sd_rot_deg_without']:.3f} | {r['nees']:.1f} | {r['nees_without']:.1f} | "
              f"{r['nees_pair']:.1f} |")
    print()
    for key, what in (("nees", "with the held intrinsics' share (the engine now)"),
                      ("nees_without", "without it (the engine before)"),
                      ("nees_pair", "the pair's own solve")):
        v = np.array([r[key] for r in rows])
        print(f"NEES {what}: mean {v.mean():.1f}, median {np.median(v):.1f}, below {LIMIT_95} in "
              f"{np.sum(v < LIMIT_95)} of {len(v)} (an honest covariance: mean 6, 95% below)")


if __name__ == "__main__":
    main()
