"""Board layouts: predicted against Monte Carlo uncertainty, the planar method's layout experiment, the
equal-angle claim, and the suggested next pose against a random one (make bench; measurement level).

Layouts follow the planar method's setup (1024 x 768 camera, 1 m board, 2-5 m): 16 and 8 spread poses,
4 poses over the image's quadrants with normals in four quadrants, 8 poses all tilted one way (upwards,
or to the right). Each row: the predicted std (Cramer-Rao bound) and the Monte Carlo RMS error per
axis over repeated noise draws (each calibrated by the engine, ``calibrate``, from the frames as measured), their
largest ratio, and the re-projection offset (RMS, px) of the boards' centres mapped through the estimate, horizontal
and vertical. Calibrated with the planes alone
(`--no-edges`), the model of the bound: the default adds the board's edges (bench_board_edges compares those with
their own bound).

Usage: python benchmarks/bench_layout.py [--trials 150] [--workers 2]
"""
from __future__ import annotations

import argparse
import os
import sys
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # as the CLI does (see bench_refinement.py)

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from estimators.analysis.layout_analysis import analyse, suggest_poses  # noqa: E402
from estimators.io.measurement_store import Measurements  # noqa: E402
from estimators.rig_calibration import calibrate  # noqa: E402
from estimators.errors import DegenerateLayoutError  # noqa: E402
from estimators.simulation.simulator import (  # noqa: E402
    _pose_fits, board_pose, default_rig, one_way_poses, sample_board_poses)
from estimators.solvers.observation_model import Layout, board_hits, simulate_measurements  # noqa: E402
from estimators.solvers.refinement_options import measurement_model_options  # noqa: E402
from geometry.rotations import T_inverse, T_log, transform_points  # noqa: E402

CORNER_NOISE_PX, RANGE_NOISE_M = 0.2, 0.02


def _pose(rig, centre, tilt_deg, azimuth_deg, spin_deg=0.0):
    return board_pose(rig.board, centre, np.deg2rad(tilt_deg), np.deg2rad(azimuth_deg), np.deg2rad(spin_deg))


def layouts(seed: int = 7):
    rng = np.random.default_rng(seed)
    rig = default_rig(rng, "hdl64e", RANGE_NOISE_M)
    out = {"16 spread": sample_board_poses(rig, 16, rng), "8 spread": sample_board_poses(rig, 8, rng)}
    # Four boards spread left and right over the part of the image the LiDAR also sees (its field of view
    # ends 2 degrees above the horizon), their normals tilted 30 degrees into the four quadrants.
    quads = []
    for k in range(4):
        while True:
            z = rng.uniform(2.5, 4.5)
            side = -1.0 if k in (0, 3) else 1.0
            T = _pose(rig, [side * rng.uniform(0.1, 0.35) * z, rng.uniform(0.0, 0.25) * z, z], 30.0, 45.0 + 90.0 * k)
            if _pose_fits(rig, T):
                quads.append(T)
                break
    out["4 quadrants"] = quads
    out["8 upward"] = one_way_poses(rig, 8, rng, "up", depth_m=(2.5, 4.5))
    out["8 right"] = one_way_poses(rig, 8, rng, "right", depth_m=(2.5, 4.5))
    return rig, out


def _layout(rig, poses):
    return Layout(rig.camera, rig.board, rig.beams, rig.T_camera_lidar, tuple(poses), CORNER_NOISE_PX, RANGE_NOISE_M)


def _trial(args):
    seed, layout = args
    rng = np.random.default_rng(seed)
    frames = simulate_measurements(layout, rng)
    try:
        # the planes alone, the model of the bound each row is compared with (the default adds the board's edges,
        # whose bound `lidarcam layout` prints beside it, bench_board_edges's rows)
        res = calibrate(Measurements(layout.camera, layout.board, "3d", tuple(frames)), samples=0,
                        options=measurement_model_options(edges=False))
    except DegenerateLayoutError:
        return None
    T = res.T_camera_lidar
    xi = T_log(T_inverse(T) @ layout.T_camera_lidar)
    # Re-projection offset: each board's centre as the LiDAR sees it, mapped by the estimate into the image.
    offs = []
    for T_cb in layout.T_camera_board:
        c_cam = T_cb[:3, :3] @ layout.board.centre + T_cb[:3, 3]
        c_lidar = transform_points(T_inverse(layout.T_camera_lidar), c_cam[None])
        uv = layout.camera.project(np.vstack([c_cam, transform_points(T, c_lidar)]))
        offs.append(uv[1] - uv[0])
    return xi, np.sqrt(np.mean(np.square(offs), axis=0))


def monte_carlo(layout, trials, workers, seed=0):
    # The beams that hit each board do not change between noise draws: cast them once.
    layout = replace(layout, hits=tuple(board_hits(layout, i) for i in range(layout.n_frames)))
    seeds = [int(s) for s in np.random.SeedSequence(seed).generate_state(trials)]
    if workers == 1:  # in this process (a notebook's quick run)
        out = [o for o in map(_trial, [(s, layout) for s in seeds]) if o is not None]
    else:
        with ProcessPoolExecutor(workers) as pool:
            out = [o for o in pool.map(_trial, [(s, layout) for s in seeds]) if o is not None]
    if not out:
        return None, None, trials
    xi = np.array([o[0] for o in out])
    off = np.sqrt(np.mean(np.square([o[1] for o in out]), axis=0))
    return np.sqrt(np.mean(xi**2, axis=0)), off, trials - len(out)


def _row(name, layout, trials, workers):
    a = analyse(layout)
    pred = np.sqrt(np.diag(a.covariance))
    rms, off, failed = monte_carlo(layout, trials, workers)
    units = np.array([np.degrees(1.0)] * 3 + [1000.0] * 3)
    if rms is None:
        print(f"  {name:14s}" + "".join(f"{v:8.3f}" for v in pred[:3] * units[:3])
              + "".join(f"{v:7.2f}" for v in pred[3:] * units[3:])
              + f" | refused in every draw (normal spread below the closed form's limit): {a.weakest_words}")
        return
    ratio = np.max(np.abs(rms / pred - 1.0))
    print(f"  {name:14s}" + "".join(f"{v:8.3f}" for v in pred[:3] * units[:3])
          + "".join(f"{v:7.2f}" for v in pred[3:] * units[3:])
          + " |" + "".join(f"{v:8.3f}" for v in rms[:3] * units[:3]) + "".join(f"{v:7.2f}" for v in rms[3:] * units[3:])
          + f" |{100 * ratio:6.1f}%{off[0]:7.2f}{off[1]:7.2f}{a.condition_number:7.1f}"
          + (f"  ({failed} degenerate draws)" if failed else ""))


def _header(title):
    print(title)
    print(f"  {'layout':14s}{'predicted std: rot x y z deg, trans x y z mm':^45s} |"
          f"{'Monte Carlo RMS error: same axes':^45s} |{'max dev':>7s}{'du px':>7s}{'dv px':>7s}{'cond':>7s}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=150)
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args()
    rig, sets = layouts()
    _header(f"(f) the planar method's layouts: predicted vs Monte Carlo ({args.trials} draws each; "
            f"corners {CORNER_NOISE_PX} px, ranges {100 * RANGE_NOISE_M:.0f} cm)")
    for name, poses in sets.items():
        _row(name, _layout(rig, poses), args.trials, args.workers)
    print()
    _header("(g) three boards at equal azimuths (0/120/240 deg) tilted by alpha (the optimum is 54.7 deg)")
    for alpha in (15.0, 25.0, 35.0, 45.0, 54.7, 65.0):
        poses = [_pose(rig, [0.0, 0.0, 3.5], alpha, az) for az in (0.0, 120.0, 240.0)]
        _row(f"alpha {alpha:4.1f}", _layout(rig, poses), args.trials, args.workers)
    print()
    print("(h) the suggested fourth pose against random feasible ones (3 spread boards to start)")
    rng = np.random.default_rng(11)
    base = _layout(rig, sample_board_poses(rig, 3, rng))
    (T_best, _), = suggest_poses(base, rig, 1, np.random.default_rng(12))
    rms_best, _, _ = monte_carlo(_layout(rig, list(base.T_camera_board) + [T_best]), args.trials, args.workers)
    randoms = []
    for k in range(5):
        T_rand = sample_board_poses(rig, 1, np.random.default_rng(100 + k))[0]
        randoms.append(monte_carlo(_layout(rig, list(base.T_camera_board) + [T_rand]), args.trials, args.workers)[0])
    def norms(r):
        return np.degrees(np.linalg.norm(r[:3])), 1000 * np.linalg.norm(r[3:])
    print(f"  suggested pose: RMS rotation {norms(rms_best)[0]:.3f} deg, translation {norms(rms_best)[1]:.2f} mm")
    for k, r in enumerate(randoms):
        print(f"  random pose {k}: RMS rotation {norms(r)[0]:.3f} deg, translation {norms(r)[1]:.2f} mm")


if __name__ == "__main__":
    main()
