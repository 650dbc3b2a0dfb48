"""One camera and one LiDAR, calibrated as a rig and as a pair: how far apart the two engines land (make bench;
`python benchmarks/bench_pair_vs_rig.py [--rigs N]`).

Each simulated rig (`simulate_rig`: one camera, one HDL-64E-like LiDAR, 10 poses) is calibrated by the rig's
engine (`calibrate_rig`) and, as the same camera-LiDAR pair over the same frames, by the pair's (`calibrate`),
without posterior. Printed per rig: the rig's estimate against the pair's (degrees, millimetres, and its squared
Mahalanobis distance under the pair's covariance), the ratio of the rig's standard deviations to the pair's (GTSAM
tangent, rotation then translation), and each engine's distance from the truth. Two engines that were one would
print zeros and ratios of 1 (the intrinsics as given: refining them is the engine's alone).

`--scanner --poses N --samples S [--config C]`: a 2D scanner's pair folder of N boards (`simulate_dataset`, lidar
2d, the simulator's configuration C), the rig's engine with its posterior (S effective samples) as `lidarcam
calibrate` runs it (segment ends by default), the pair's own solve with its Laplace covariance (it draws no
posterior): per folder each one's verdict, the masses of the minima it found, and the truth's distance against its
99.9% region (the rig's `PairEstimate.region_d2`: the samples' covariance's ellipsoid about the estimate holding
99.9% of them, with several minima the union of each one's own; the pair's, its covariance's chi-square ellipsoid);
then the answers whose truth lies outside the region while the verdict reads OK (confidently wrong), per engine.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from estimators.calibration import calibrate_pair  # noqa: E402
from estimators.errors import LidarcamError  # noqa: E402
from estimators.io.rig_dataset import load_rig  # noqa: E402
from estimators.rig_calibration import calibrate_rig  # noqa: E402
from estimators.simulation.rig_simulator import simulate_rig  # noqa: E402
from geometry.rotations import T_inverse, T_log  # noqa: E402


def d2(T_hat: np.ndarray, cov: np.ndarray, T: np.ndarray) -> float:
    xi = T_log(T_inverse(T_hat) @ T)
    return float(xi @ np.linalg.solve(cov, xi))


def scanner_rows(n: int, poses: int, samples: int, config: str = "default") -> None:
    """``--scanner``: each 2D pair folder calibrated as a pair and as a rig, with the posterior (module docstring)."""
    from estimators.simulation.simulator import simulate_dataset

    print(f"A camera and a 2D scanner ({config} configuration), {poses} boards, as a pair and as a rig, posterior of "
          f"{samples} effective samples: {n} folders (seeds 0-{n - 1})")
    print("seed  verdict rig / pair  masses rig / pair            rig-pair deg  rig-pair mm  "
          "truth d2/99.9% rig      pair")
    wrong = {"rig": [], "pair": []}
    inside = {"rig": 0, "pair": 0}
    with tempfile.TemporaryDirectory() as tmp:
        for seed in range(n):
            folder = simulate_dataset(Path(tmp) / f"pair{seed}", n_poses=poses, seed=seed, lidar="2d",
                                      rig_config=config)
            T_true = np.array(json.loads((folder / "ground_truth.json").read_text())["T_camera_lidar"])
            try:
                pair = calibrate_pair(folder)  # the pair's own solve draws no posterior: its Laplace covariance
                rig = calibrate_rig(load_rig(folder), np.random.default_rng(0), samples=samples, advise=False)
            except LidarcamError as exc:
                print(f"{seed:4d}  refused: {exc.message[:100]}")
                continue
            pe = rig.pair("cam0", "lidar0")
            x_rig = T_log(T_inverse(pe.T) @ T_true)
            got = {"rig": (float(pe.region_distance(x_rig)[0]), pe.region_d2(0.999), rig.verdict.level)}
            got["pair"] = (d2(pair.T_camera_lidar, pair.covariance, T_true), 22.458, pair.verdict.level)
            for k, (dist, limit, level) in got.items():
                inside[k] += dist <= limit
                if dist > limit and level == "OK":
                    wrong[k].append(seed)
            modes = rig.ambiguous_pairs.get(("cam0", "lidar0"), ())
            masses = ("/".join(f"{m.mass:.2f}" for m in modes) or "1") + " / " + "/".join(
                f"{m.mass:.2f}" for m in pair.modes)
            xi = T_log(T_inverse(pair.T_camera_lidar) @ pe.T)
            print(f"{seed:4d}  {got['rig'][2]:>7s} / {got['pair'][2]:<7s}  {masses:27s}  "
                  f"{np.degrees(np.linalg.norm(xi[:3])):12.4f}  {1000 * np.linalg.norm(xi[3:]):11.2f}  "
                  f"{got['rig'][0]:7.1f}/{got['rig'][1]:<7.1f} {got['pair'][0]:7.1f}/{got['pair'][1]:.1f}")
    for k in ("rig", "pair"):
        print(f"{k}: truth inside its 99.9% region in {inside[k]}; confidently wrong (outside, verdict OK): "
              f"{len(wrong[k])} {wrong[k]}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rigs", type=int, default=5, help="simulated rigs (seeds 0..N-1)")
    ap.add_argument("--scanner", action="store_true", help="a 2D scanner's pair folders (see the docstring)")
    ap.add_argument("--poses", type=int, default=3, help="boards per scanner folder (default 3)")
    ap.add_argument("--samples", type=int, default=500, help="effective posterior samples per engine (--scanner)")
    ap.add_argument("--config", default="default", help="the simulator's 2D configuration (--scanner): default, "
                                                         "varied or mounted")
    a = ap.parse_args()
    if a.scanner:
        scanner_rows(a.rigs, a.poses, a.samples, a.config)
        return
    print(f"One camera and one HDL-64E-like LiDAR, 10 poses, as a rig and as a pair: {a.rigs} rigs "
          f"(seeds 0-{a.rigs - 1})")
    print("seed  rig-pair deg  rig-pair mm  d2 (pair cov)  sd rig/pair (rot x y z, trans x y z)  truth d2 rig / pair")
    truth_d2: dict = {"rig": [], "pair": []}
    with tempfile.TemporaryDirectory() as tmp:
        for seed in range(a.rigs):
            folder = simulate_rig(Path(tmp) / f"rig{seed}", n_poses=10, seed=seed, cameras=1, lidars=1)
            truth = json.loads((folder / "ground_truth.json").read_text())
            T_true = np.linalg.inv(np.array(truth["T_cam0_cam0"])) @ np.array(truth["T_cam0_lidar0"])
            rig = load_rig(folder)
            refused = []
            try:
                T_rig, C_rig = calibrate_rig(rig, np.random.default_rng(0), samples=0).solution.transform("cam0",
                                                                                                         "lidar0")
            except LidarcamError as exc:
                refused.append(f"rig refused: {exc.problem[:70]}")
            try:
                pair = calibrate_pair(rig.pair("cam0", "lidar0"), samples=0)
            except LidarcamError as exc:
                refused.append(f"pair refused: {exc.problem[:70]}")
            if refused:
                print(f"{seed:4d}  " + "; ".join(refused))
                continue
            xi = T_log(T_inverse(pair.T_camera_lidar) @ T_rig)
            ratio = np.sqrt(np.diag(C_rig) / np.diag(pair.covariance))
            truth_d2["rig"].append(d2(T_rig, C_rig, T_true))
            truth_d2["pair"].append(d2(pair.T_camera_lidar, pair.covariance, T_true))
            print(f"{seed:4d}  {np.degrees(np.linalg.norm(xi[:3])):12.4f}  {1000 * np.linalg.norm(xi[3:]):11.2f}  "
                  f"{d2(pair.T_camera_lidar, pair.covariance, T_rig):13.3f}  "
                  + " ".join(f"{r:.2f}" for r in ratio) + f"  {truth_d2['rig'][-1]:9.1f} / {truth_d2['pair'][-1]:.1f}")
    for k, v in truth_d2.items():
        if v:
            print(f"{k}: truth's mean d2 {np.mean(v):.2f} over {len(v)} rigs (6 ideal), beyond 16.81 (99%): "
                  f"{sum(x > 16.81 for x in v)}")


if __name__ == "__main__":
    main()
