"""Which noise model the one graph uses for each concept, chosen by coverage (make bench;
`python benchmarks/bench_noise_models.py [--seeds N] [--workers W]`).

One camera and one LiDAR, calibrated by the one graph (`rig_calibration.calibrate_rig`, the pair as the rig of cam0
and lidar0) under each concept's two candidate models, and by the single pair's engine (`calibration.calibrate`)
for reference, without posterior and without the board's edges:

- `one graph`: each board's corners at their own residual (shrunk towards the camera's pooled one) times 1.0, each
  LiDAR board's plane at the range noise plus the per-board plane error its pair's consistency test calls for
  (robust loss, outlier frames dropped), a sensor's noise scaled only when its chi-square exceeds its dof at 1%;
- `pooled corners`: the camera's pooled residual times 1.28 for every board (`POOLED_FACTOR`, the single pair's
  model before the one graph);
- `scaled planes`: each LiDAR board's plane at the range noise alone, every sensor's excess chi-square scaled away
  (no per-board plane error, no robust loss, no test);
- `pair engine`: the single pair's refinement.

Over five generators (the rig simulator with an HDL-64E-like and a VLP-16-like LiDAR; the pair simulator with an
HDL-64E in its default scene, a VLP-16 in its office, and its varied 2D scanner), N seeds each: the squared
Mahalanobis distance of the truth under each answer's covariance (chi-square with 6 dof when the model holds: mean
6, 5% beyond 12.6, 1% beyond 16.8). The mean of N such distances is uncertain by about sqrt(12 / N).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from estimators import rig_calibration  # noqa: E402
from estimators.calibration import calibrate_pair  # noqa: E402
from estimators.io.rig_dataset import load_rig  # noqa: E402
from estimators.solvers import rig_graph  # noqa: E402
from estimators.solvers.chi_square import ppf  # noqa: E402
from estimators.solvers.factor_graph import CameraViews  # noqa: E402
from estimators.solvers.refinement_options import CORNER_ERROR_CORRELATION, RefinementOptions  # noqa: E402

POOLED_FACTOR = 1.28
from estimators.simulation.rig_simulator import simulate_rig  # noqa: E402
from estimators.simulation.simulator import simulate_dataset  # noqa: E402
from geometry.rotations import T_inverse, T_log  # noqa: E402

GENERATORS = {
    "rig simulator, HDL-64E, 10 poses": ("rig", "hdl64e", 10, "default"),
    "rig simulator, VLP-16, 8 poses": ("rig", "vlp16", 8, "default"),
    "pair simulator, HDL-64E, 8 poses": ("pair", "hdl64e", 8, "default"),
    "pair simulator, VLP-16 in the office, 10 poses": ("pair", "vlp16", 10, "office"),
    "pair simulator, varied 2D scanner, 6 poses": ("pair", "2d", 6, "varied"),
}
VARIANTS = ("one graph", "pooled corners", "scaled planes", "pair engine")


def _pooled_views(original):
    def views(name, camera, poses, board, *options):
        v = original(name, camera, poses, board, *options)
        return CameraViews(v.name, v.camera, v.sigma_px / CORNER_ERROR_CORRELATION * POOLED_FACTOR, v.corners_board,
                           v.corners_px, v.T_camera_board, {})
    return views


def _plain_planes(original):
    def views(name, sigma_m, frames, T_ref_board, board, scan_line, options):
        v = original(name, sigma_m, frames, T_ref_board, board, scan_line, options)
        return replace(v, plane_error=None, robust=None)
    return views


def _rig_answer(folder: Path, variant: str) -> tuple[np.ndarray, np.ndarray]:
    saved = (rig_calibration.camera_views_of, rig_calibration.lidar_views_of, rig_graph.excess_scale)
    try:
        if variant == "pooled corners":
            rig_calibration.camera_views_of = _pooled_views(saved[0])
        if variant == "scaled planes":
            rig_calibration.lidar_views_of = _plain_planes(saved[1])
            rig_graph.excess_scale = lambda ss, dof: max(ss / dof, 1.0)  # every excess scaled
        res = rig_calibration.calibrate_rig(load_rig(folder), np.random.default_rng(0), samples=0, advise=False,
                                            edges=False)
        return res.solution.transform("cam0", "lidar0")
    finally:
        rig_calibration.camera_views_of, rig_calibration.lidar_views_of, rig_graph.excess_scale = saved


def _one(task) -> dict:
    label, seed = task
    kind, lidar, poses, scene = GENERATORS[label]
    out = {"generator": label, "seed": seed}
    with tempfile.TemporaryDirectory() as tmp:
        if kind == "rig":
            folder = simulate_rig(Path(tmp) / "rig", n_poses=poses, seed=seed, cameras=1, lidars=1, lidar=lidar)
            gt = json.loads((folder / "ground_truth.json").read_text())
            truth = np.linalg.inv(np.array(gt["T_cam0_cam0"])) @ np.array(gt["T_cam0_lidar0"])
        else:
            folder = Path(simulate_dataset(Path(tmp) / "pair", poses, seed, lidar,
                                           rig_config=scene if lidar == "2d" else "default",
                                           scene=scene if scene == "office" else "default"))
            truth = np.array(json.loads((folder / "ground_truth.json").read_text())["T_camera_lidar"])
        for variant in VARIANTS:
            try:
                if variant == "pair engine":
                    pair = calibrate_pair(folder if kind == "pair" else load_rig(folder).pair("cam0", "lidar0"),
                                          samples=0, options=RefinementOptions(edges=False))
                    T, C = pair.T_camera_lidar, pair.covariance
                else:
                    T, C = _rig_answer(folder, variant)
                xi = T_log(T_inverse(T) @ truth)
                out[variant] = float(xi @ np.linalg.solve(C, xi))
            except Exception as exc:  # a refusal counts as no answer
                out[variant] = None
                out[f"{variant} error"] = str(exc)[:120]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=20, help="datasets per generator")
    ap.add_argument("--workers", type=int, default=2)
    a = ap.parse_args()
    tasks = [(label, 1000 * k + s) for k, label in enumerate(GENERATORS) for s in range(a.seeds)]
    with ProcessPoolExecutor(a.workers) as pool:
        rows = list(pool.map(_one, tasks))
    q95, q99 = ppf(0.95, 6), ppf(0.99, 6)
    print(f"One camera and one LiDAR, {a.seeds} datasets per generator: the truth's d2 under each answer's covariance "
          f"(chi-square 6: mean 6, 5% beyond {q95:.1f}, 1% beyond {q99:.1f})")
    print(f"{'generator / model':<52}{'answers':>8}{'mean d2':>9}{'median':>8}{'>95%':>7}{'>99%':>7}")
    total = {v: [] for v in VARIANTS}
    for label in GENERATORS:
        print(label)
        for v in VARIANTS:
            d2 = np.array([r[v] for r in rows if r["generator"] == label and r[v] is not None])
            total[v].extend(d2.tolist())
            print(f"  {v:<50}{len(d2):>8}{d2.mean():>9.2f}{np.median(d2):>8.2f}{np.mean(d2 > q95):>7.1%}"
                  f"{np.mean(d2 > q99):>7.1%}")
    print("all generators")
    for v in VARIANTS:
        d2 = np.array(total[v])
        print(f"  {v:<50}{len(d2):>8}{d2.mean():>9.2f}{np.median(d2):>8.2f}{np.mean(d2 > q95):>7.1%}"
              f"{np.mean(d2 > q99):>7.1%}")
    errors = [(r["generator"], r["seed"], v, r[f"{v} error"]) for r in rows for v in VARIANTS if f"{v} error" in r]
    for g, s, v, e in errors:
        print(f"no answer: {g}, seed {s}, {v}: {e}")


if __name__ == "__main__":
    main()
