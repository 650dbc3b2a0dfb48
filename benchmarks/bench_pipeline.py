"""Per-stage times and accuracy of the pipeline on simulated datasets (make bench): each pair folder calibrated by
the engine `lidarcam calibrate` runs (``estimators.calibrate``), with its default posterior.

The measurement's stage times are summed over frames (it runs frames on 2 threads, so its wall time is lower); the
solve's (the camera-LiDAR pair's own solve, the joint graph, the next pose, the posterior) are wall times.
"""
from __future__ import annotations

import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # as the CLI does (see bench_refinement.py)

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from estimators import calibrate  # noqa: E402
from estimators.calibration import solve  # noqa: E402
from estimators.io.dataset import load_dataset  # noqa: E402
from estimators.simulation.simulator import simulate_dataset  # noqa: E402
from geometry.rotations import T_inverse, T_log, rotation_error  # noqa: E402

CASES = [("HDL-64E", "hdl64e", 16, 0), ("HDL-64E", "hdl64e", 8, 1), ("VLP-16", "vlp16", 8, 2)]
STAGES = ["load_images", "corners", "load_scans", "segmentation", "pairs", "joint", "posterior"]


def main() -> None:
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for label, model, poses, seed in CASES:
            path = Path(tmp) / f"{model}_{poses}"
            t0 = time.perf_counter()
            simulate_dataset(path, poses, seed, model, sigma_range_m=0.02)
            t_sim = time.perf_counter() - t0
            ds = load_dataset(path)
            t0 = time.perf_counter()
            res = calibrate(ds, rng=np.random.default_rng(seed))
            wall = time.perf_counter() - t0
            G = ds.ground_truth()
            own = res.pair_results[("cam0", "lidar0")]  # the pair's own solve, which starts the joint graph
            cf = solve(list(own.frames), ds.board, res.camera_model("cam0"), refine="none").T_camera_lidar
            errs = []
            for T in (cf, res.T_camera_lidar):
                errs += [np.degrees(rotation_error(T[:3, :3], G[:3, :3])), 1000 * np.linalg.norm(T[:3, 3] - G[:3, 3])]
            xi = T_log(T_inverse(res.T_camera_lidar) @ G)
            d2 = float(xi @ np.linalg.solve(res.covariance, xi))
            rows.append((f"{label} x{poses} (seed {seed})", [res.timings_s.get(s, 0.0) for s in STAGES], wall,
                         t_sim, len(res.frames_used["lidar0"]), poses, errs, d2, own.condition_number))
    head = f"{'dataset':24s}" + "".join(f"{s:>13s}" for s in STAGES) + f"{'calib wall':>12s}{'simulate':>10s}"
    print("Per-stage seconds: the measurement's CPU summed over frames (2 worker threads), the solve's wall (pairs: "
          "the pair's own solve; joint: the one graph, with its edges); wall = whole calibrate call")
    print(head)
    for name, st, wall, tsim, *_ in rows:
        print(f"{name:24s}" + "".join(f"{v:13.2f}" for v in st) + f"{wall:12.2f}{tsim:10.2f}")
    print()
    print("Accuracy against ground truth (2 cm range noise, 2 grey-level pixel noise): closed form, then the")
    print("factor graph; d2 = squared Mahalanobis distance of the truth under the reported covariance (6 dof)")
    print(f"{'dataset':24s}{'frames':>8s}{'cf rot deg':>12s}{'cf trans mm':>13s}{'fg rot deg':>12s}"
          f"{'fg trans mm':>13s}{'d2':>7s}{'normal cond':>13s}")
    for name, _, _, _, used, poses, errs, d2, cond in rows:
        print(f"{name:24s}{f'{used}/{poses}':>8s}{errs[0]:12.3f}{errs[1]:13.1f}{errs[2]:12.3f}{errs[3]:13.1f}"
              f"{d2:7.1f}{cond:13.2f}")

if __name__ == "__main__":
    main()
