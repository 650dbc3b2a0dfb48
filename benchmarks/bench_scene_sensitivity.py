"""How far the scene's estimate on the recorded sets moves with the check's own settings, against the standard
deviations it reports (make bench; `python benchmarks/bench_scene_sensitivity.py [--data ../shared/realdata]`).

Per recorded 3D set, ``check_scene`` is run from the board calibration (``estimators.calibrate``, no posterior) and
from the source tool's reference (``reference.json``, where the set has one), under each of 8 settings of the cues
a reasonable check could have chosen:

- the depth jump that makes a contour (``lidar.depth_edges.MIN_JUMP_M``: 0.3 m, the check's, or 1 m: only strong
  silhouettes);
- Canny's high threshold as a quantile of the image's gradient (``camera.edge_map.HIGH_QUANTILE``: 0.85, the
  check's, or 0.95: only strong edges);
- the residuals' final truncation (``solvers.scene_alignment.STAGES_PX``: 6 px, the check's, or 10 px).

Each row gives the scene's estimate as a turn about, and a move along, the camera's axes from the board calibration,
and the standard deviations the check reports. Where the estimates of one set spread across settings by more than
those standard deviations, the scene's covariance does not hold the error of its own cue model on that recording,
and its test's p-value against the boards is too small by an unknown amount.

The control (``--simulated N``, 8 by default): N simulated scenes of 10 frames (furnished rooms and offices with the
board left out, VLP-16- and 64-beam LiDARs in turn, seeds 100 on) checked from the truth under the same 8 settings:
the same spread over the reported standard deviations, and the NEES of each setting's estimate.
"""
from __future__ import annotations

import argparse
import itertools
import json
import os
import sys
from functools import partial
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

SETS = ("acfr_vlp16_a", "acfr_ouster64_b")
JUMPS_M, QUANTILES, TRUNCATIONS_PX = (0.3, 1.0), (0.85, 0.95), (6.0, 10.0)
MODELS = ("vlp16", "os64")


def settings():
    """The 8 settings, each as ``(jump m, Canny quantile, truncation px)``."""
    return list(itertools.product(JUMPS_M, QUANTILES, TRUNCATIONS_PX))


def check_under(folder: Path, T: np.ndarray, jump: float, quantile: float, px: float):
    """``check_scene`` of ``T`` with the cues so set, the module defaults put back after."""
    import estimators.camera.edge_map as edge_map
    import estimators.lidar.depth_edges as depth_edges
    import estimators.pipeline.scene_check as scene_check
    import estimators.solvers.scene_alignment as scene_alignment

    defaults = (edge_map.HIGH_QUANTILE, scene_alignment.STAGES_PX)
    scene_check.depth_edges = partial(depth_edges.depth_edges, min_jump_m=jump)
    edge_map.HIGH_QUANTILE, scene_alignment.STAGES_PX = quantile, (px,)
    try:
        return scene_check.check_scene(folder, T)
    finally:
        scene_check.depth_edges = depth_edges.depth_edges
        edge_map.HIGH_QUANTILE, scene_alignment.STAGES_PX = defaults


def simulated(n: int) -> None:
    """The control: the spread over the reported standard deviations on simulated scenes, checked from the truth."""
    import tempfile

    from estimators.errors import LidarcamError
    from estimators.simulation.furnished_room import simulate_scene_dataset
    from estimators.simulation.simulator import simulate_dataset
    from geometry.rotations import T_inverse, T_log

    print()
    print("| simulated scene | seed | LiDAR | checks | spread / reported sd about camera x y z | spread / reported sd "
          "along camera x y z | NEES per setting (6 if honest) |")
    print("|---|---|---|---|---|---|---|")
    for i in range(n):
        seed, generator, model = 100 + i // 2, ("room", "office")[i % 2], MODELS[(i // 2) % len(MODELS)]
        with tempfile.TemporaryDirectory(prefix="lidarcam-bench-") as tmp:
            ds = Path(tmp) / "ds"
            if generator == "room":
                simulate_scene_dataset(ds, n_frames=10, seed=seed, lidar=model)
            else:
                simulate_dataset(ds, n_poses=10, seed=seed, lidar=model, scene="office")
            truth = np.array(json.loads((ds / "ground_truth.json").read_text())["T_camera_lidar"])
            R = truth[:3, :3]
            xs, sds, nees = [], [], []
            for jump, quantile, px in settings():
                try:
                    c = check_under(ds, truth, jump, quantile, px)
                except LidarcamError:
                    continue
                xi = T_log(T_inverse(truth) @ c.fit.T_camera_lidar)
                xs.append(np.r_[np.degrees(R @ xi[:3]), 1000 * (c.fit.T_camera_lidar[:3, 3] - truth[:3, 3])])
                sds.append(np.r_[c.camera_axes_sd()])
                nees.append(float(xi @ np.linalg.solve(c.believed_covariance, xi)))
        if len(xs) < 2:
            print(f"| {generator} | {seed} | {model} | {len(xs)} | | | |")
            continue
        ratio = np.ptp(np.array(xs), axis=0) / np.median(np.array(sds), axis=0)
        print(f"| {generator} | {seed} | {model} | {len(xs)} | {' '.join(f'{x:.1f}' for x in ratio[:3])} | "
              f"{' '.join(f'{x:.1f}' for x in ratio[3:])} | {' '.join(f'{x:.1f}' for x in nees)} |", flush=True)


def main() -> None:
    from estimators import calibrate
    from estimators.errors import LidarcamError
    from geometry.rotations import T_inverse, T_log

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(ROOT.parent / "shared" / "realdata"))
    ap.add_argument("--simulated", type=int, default=8, help="simulated scenes as the control (0: none)")
    a = ap.parse_args()
    print("| set | from | jump | Canny quantile | truncation | p | contour returns | turn about camera x y z (deg) | "
          "move along camera x y z (mm) | reported sd about x y z (deg) | reported sd along x y z (mm) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    notes = []
    for name in SETS:
        folder = Path(a.data) / name
        if not folder.is_dir():
            print(f"| {name} | not found under {a.data} | | | | | | | | | |")
            continue
        T_boards = calibrate(folder, samples=0).T_camera_lidar
        starts = {"boards": T_boards}
        if (folder / "reference.json").is_file():
            starts["reference"] = np.array(json.loads((folder / "reference.json").read_text())["T_camera_lidar"])
        R = T_boards[:3, :3]
        got = []
        for (start, T), (jump, quantile, px) in itertools.product(starts.items(), settings()):
            try:
                c = check_under(folder, T, jump, quantile, px)
            except LidarcamError as exc:
                print(f"| {name} | {start} | {jump:g} m | {quantile:g} | {px:g} px | refused: {exc.problem} "
                      "| | | | | |")
                continue
            T_s = c.fit.T_camera_lidar
            turn = np.degrees(R @ T_log(T_inverse(T_boards) @ T_s)[:3])
            move = 1000 * (T_s[:3, 3] - T_boards[:3, 3])
            rot_sd, tr_sd = c.camera_axes_sd()
            got.append((turn, move, rot_sd, tr_sd))
            print(f"| {name} | {start} | {jump:g} m | {quantile:g} | {px:g} px | {c.test['p_value']:.2g} | "
                  f"{c.fit.points} | {' '.join(f'{x:+.2f}' for x in turn)} | {' '.join(f'{x:+.1f}' for x in move)} | "
                  f"{' '.join(f'{x:.2f}' for x in rot_sd)} | {' '.join(f'{x:.1f}' for x in tr_sd)} |", flush=True)
        if len(got) > 1:
            turns, moves = np.array([g[0] for g in got]), np.array([g[1] for g in got])
            rsd, tsd = np.median([g[2] for g in got], axis=0), np.median([g[3] for g in got], axis=0)
            notes.append(f"{name}: over {len(got)} checks the estimate's turn about the camera's x y z spans "
                         f"{' '.join(f'{x:.2f}' for x in np.ptp(turns, axis=0))} deg (reported sd, median: "
                         f"{' '.join(f'{x:.2f}' for x in rsd)}), its move along them "
                         f"{' '.join(f'{x:.0f}' for x in np.ptp(moves, axis=0))} mm (sd "
                         f"{' '.join(f'{x:.1f}' for x in tsd)}); the turn about the camera's y from the boards' "
                         f"lies between {turns[:, 1].min():+.2f} and {turns[:, 1].max():+.2f} deg")
    print()
    for line in notes:
        print(line)
    if a.simulated:
        simulated(a.simulated)


if __name__ == "__main__":
    main()
