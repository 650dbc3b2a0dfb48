"""A rig camera with wrong intrinsics, refined with the rig (make bench;
`python benchmarks/bench_rig_intrinsics.py [--rigs N] [--cameras C] [--poses P] [--wrong CAMERA]`).

Each rig (`simulation.rig_simulator`, as in bench_rig.py: C cameras and an HDL-64E-like LiDAR) is written with
one camera's focal lengths 1% too long and its k1 halved in dataset.yaml: cam1's by default; `--wrong cam0`, the
camera the LiDAR's boards are found and first solved with, whose pair's per-board plane errors the joint graph
weighs those boards by. Three calibrations of each
(`rig_calibration.calibrate_rig`):

- `true intrinsics`: the dataset.yaml as simulated (the reference);
- `wrong, fixed`: the wrong intrinsics held fixed (what a user gets without `--refine-intrinsics`);
- `wrong, refined`: `--refine-intrinsics` (every camera's intrinsics unknowns of the graph, no prior).

Per pair and variant: the RMS rotation and translation errors, over the RMS Cramer-Rao bound of the variant's
graph (`rig_graph.rig_bound` at the truth, at the noise levels that graph used; with the intrinsics unknowns at
their true values for `wrong, refined`), the mean squared Mahalanobis distance of the truth under the reported
covariance (6 ideal), and how many rigs warned that the wrong camera's corners disagree with the rest.
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

VARIANTS = ("true intrinsics", "wrong, fixed", "wrong, refined")
FOCAL_ERROR = 1.01
K1_FACTOR = 0.5


def _one(args) -> dict:
    import shutil

    from bench_rig import _bound
    from estimators.io.rig_dataset import load_rig
    from estimators.rig_calibration import calibrate_rig
    from estimators.simulation.rig_simulator import miscalibrate_camera, simulate_rig
    from geometry.rotations import T_log
    from estimators.solvers.rig_graph import pair_transform

    seed, cameras, poses, wrong_name = args
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        folder = simulate_rig(Path(tmp) / "rig", poses, seed, cameras)
        gt = json.loads((folder / "ground_truth.json").read_text())
        true_rig = load_rig(folder)
        wrong = Path(tmp) / "wrong"
        shutil.copytree(folder, wrong)
        wrong_rig = load_rig(miscalibrate_camera(wrong, wrong_name, FOCAL_ERROR, K1_FACTOR))
        for variant in VARIANTS:
            rig = true_rig if variant == "true intrinsics" else wrong_rig
            refine = variant == "wrong, refined"
            res = calibrate_rig(rig, np.random.default_rng(seed), workers=1, refine_intrinsics=refine, advise=False)
            truth_intrinsics = {s.name: np.asarray(s.camera.params) for s in true_rig.cameras} if refine else None
            bound = _bound(res, gt, truth_intrinsics)
            rows = {}
            for a, b in res.pairs():
                truth = np.linalg.inv(np.array(gt[f"T_cam0_{a}"])) @ np.array(gt[f"T_cam0_{b}"])
                T, C = res.solution.transform(a, b)
                xi = T_log(np.linalg.inv(T) @ truth)
                names = res.solution.names
                idx = np.r_[6 * names.index(a):6 * names.index(a) + 6, 6 * names.index(b):6 * names.index(b) + 6]
                _, Cb = pair_transform(np.array(gt[f"T_cam0_{a}"]), np.array(gt[f"T_cam0_{b}"]),
                                       bound[np.ix_(idx, idx)])
                rows[f"T_{a}_{b}"] = (float(xi[:3] @ xi[:3]), float(xi[3:] @ xi[3:]),
                                      float(xi @ np.linalg.solve(C, xi)), float(np.trace(Cb[:3, :3])),
                                      float(np.trace(Cb[3:, 3:])))
            warned = any(w.startswith(f"{wrong_name}: ") for w in res.warnings)
            out[variant] = {"rows": rows, "warned": warned, "verdict": res.verdict.line.split(":")[0]}
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--rigs", type=int, default=20)
    ap.add_argument("--cameras", type=int, default=2)
    ap.add_argument("--poses", type=int, default=12)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--wrong", default="cam1", help="the camera given wrong intrinsics")
    args = ap.parse_args()
    with ProcessPoolExecutor(args.workers) as pool:
        runs = list(pool.map(_one, [(s, args.cameras, args.poses, args.wrong) for s in range(args.rigs)]))
    print(f"{args.rigs} simulated rigs: {args.cameras} cameras + an HDL-64E-like LiDAR, {args.poses} board poses; "
          f"{args.wrong} given focal lengths x{FOCAL_ERROR} and k1 x{K1_FACTOR}")
    print(f"{'pair':16s}{'variant':>17s}{'rot deg':>9s}{'trans mm':>10s}{'rot/CRB':>9s}{'tr/CRB':>8s}{'d2':>10s}")
    for name in runs[0]["true intrinsics"]["rows"]:
        for variant in VARIANTS:
            r = np.array([run[variant]["rows"][name] for run in runs])
            rot, tr = np.sqrt(r[:, 0].mean()), np.sqrt(r[:, 1].mean())
            print(f"{name:16s}{variant:>17s}{np.degrees(rot):9.4f}{1000 * tr:10.2f}"
                  f"{rot / np.sqrt(r[:, 3].mean()):9.2f}{tr / np.sqrt(r[:, 4].mean()):8.2f}{r[:, 2].mean():10.2f}")
    for variant in VARIANTS:
        n = sum(run[variant]["warned"] for run in runs)
        verdicts = [run[variant]["verdict"] for run in runs]
        print(f"{variant}: the warning that {args.wrong}'s corners disagree with the rest in {n} of {len(runs)} rigs; "
              "verdicts " + ", ".join(f"{v} {verdicts.count(v)}" for v in ("OK", "CHECK", "UNTRUSTED")))


if __name__ == "__main__":
    main()
