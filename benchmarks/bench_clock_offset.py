"""A board waved before the rig, recorded continuously: the clocks' offset and the extrinsic from each LiDAR return
at its own time (make bench; `python benchmarks/bench_clock_offset.py [--recordings N] [--workers W]`).

Per recording (``simulation.waved_board``): the default camera at 20 Hz (0.2 px corners) and a VLP-16-like LiDAR
at 10 Hz (20 mm range noise, each return fired at its azimuth's time), 30-90 s of a board waved at 0.2-1.0 m/s
and 20-90 deg/s about one pose, the camera's clock ahead of the LiDAR's by an offset drawn in +-100 ms, stamps
jittered by 1 ms. Solved by ``solvers.clock_offset`` (offset prior +-0.2 s), and again with the offset held at 0
(what a tool that assumes synchronised clocks gets). Printed: the offset's RMS error and its error's spread
against the reported standard deviation, the extrinsic's RMS rotation and translation errors, and the NEES of the
extrinsic and offset together (7 dof), and the posterior's (``solvers.moving_posterior``): the NEES under its
samples' covariance and how often each equal-tailed 95% interval holds the truth. The camera free-running (its
first image at a random phase of the sweeps).
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def _trial(seed: int) -> dict:
    from estimators.simulation.simulator import default_rig
    from estimators.simulation.waved_board import simulate_waving
    from estimators.solvers.clock_offset import solve_clock_offset
    from estimators.solvers.moving_posterior import sample_moving_posterior
    from geometry.rotations import T_inverse, T_log

    rng = np.random.default_rng(seed)
    rig = default_rig(rng, "vlp16")
    duration, offset = rng.uniform(30.0, 90.0), rng.uniform(-0.1, 0.1)
    speed, turn = rng.uniform(0.2, 1.0), rng.uniform(20.0, 90.0)
    rec = simulate_waving(rig, duration, rng, time_offset_s=offset, speed_mps=speed, turn_dps=turn,
                          stamp_jitter_s=0.001)
    t0 = time.perf_counter()
    sol = solve_clock_offset(list(rec.views), list(rec.sweeps), rng=rng)
    seconds = time.perf_counter() - t0
    post = sample_moving_posterior(sol.fit, np.random.default_rng(seed), min_ess=2000)
    held = solve_clock_offset(list(rec.views), list(rec.sweeps), fixed_offset_s=0.0, rng=rng)
    row = {"seed": seed, "duration_s": duration, "speed": speed, "offset_s": offset, "seconds": seconds,
           "sweeps": sol.sweeps}
    for name, s in (("free", sol), ("held", held)):
        e = T_log(T_inverse(rig.T_camera_lidar) @ s.T_camera_lidar)
        row[f"{name}_rot_deg"] = float(np.degrees(np.linalg.norm(e[:3])))
        row[f"{name}_trans_mm"] = float(1000 * np.linalg.norm(e[3:]))
        row[f"{name}_offset_err_ms"] = 1000 * (s.time_offset_s - offset)
    err = np.r_[T_log(T_inverse(sol.T_camera_lidar) @ rig.T_camera_lidar), offset - sol.time_offset_s]
    row["nees"] = float(err @ np.linalg.solve(sol.covariance, err))
    row["offset_sd_ms"] = 1000 * float(np.sqrt(sol.covariance[6, 6]))
    # the posterior's samples: their covariance's NEES, and whether each interval at 95% holds the truth
    row["posterior_nees"] = float(err @ np.linalg.solve(np.cov(post.xi, rowvar=False), err))
    lo, hi = np.quantile(post.xi, [0.025, 0.975], axis=0)
    row["posterior_in_95"] = ((lo <= err) & (err <= hi)).astype(float)
    row["posterior_seconds"] = post.run.seconds
    row["posterior_ess"] = post.run.ess
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--recordings", type=int, default=30)
    ap.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    t0 = time.time()
    with ProcessPoolExecutor(a.workers) as pool:
        rows = list(pool.map(_trial, range(a.seed, a.seed + a.recordings)))
    r = {k: np.array([row[k] for row in rows]) for k in rows[0]}

    def rms(x):
        return float(np.sqrt(np.mean(np.square(x))))

    print(f"{a.recordings} simulated recordings, 30-90 s (mean {r['duration_s'].mean():.0f} s, "
          f"{r['sweeps'].mean():.0f} sweeps), board at 0.2-1.0 m/s, clock offsets in +-100 ms:\n")
    print("| | offset free (prior +-0.2 s) | offset held at 0 |")
    print("|---|---|---|")
    print(f"| offset error, RMS | {rms(r['free_offset_err_ms']):.2f} ms | {rms(r['held_offset_err_ms']):.1f} ms |")
    print(f"| offset error, largest | {np.abs(r['free_offset_err_ms']).max():.2f} ms | "
          f"{np.abs(r['held_offset_err_ms']).max():.1f} ms |")
    print(f"| rotation error, RMS | {rms(r['free_rot_deg']):.3f} deg | {rms(r['held_rot_deg']):.3f} deg |")
    print(f"| translation error, RMS | {rms(r['free_trans_mm']):.1f} mm | {rms(r['held_trans_mm']):.1f} mm |")
    print(f"| offset error / reported sd, RMS | {rms(r['free_offset_err_ms'] / r['offset_sd_ms']):.2f} | - |")
    print(f"| NEES, extrinsic and offset (7 dof: 7 if honest), mean | {r['nees'].mean():.0f} | - |")
    print(f"| seconds to solve, median | {np.median(r['seconds']):.1f} | - |")
    inside = np.mean(np.stack(r["posterior_in_95"]), axis=0)
    print(f"| posterior (emcee, 2000 effective samples): NEES under its samples' covariance, mean | "
          f"{r['posterior_nees'].mean():.0f} | - |")
    print("| posterior: share of recordings whose truth lies in the 95% interval, rot x y z, trans x y z, offset | "
          + " ".join(f"{v:.2f}" for v in inside) + " | - |")
    print(f"| posterior: seconds, median (effective samples, median) | {np.median(r['posterior_seconds']):.1f} "
          f"({np.median(r['posterior_ess']):.0f}) | - |")
    print(f"\n({a.recordings} recordings in {time.time() - t0:.0f} s on {a.workers} processes; seeds "
          f"{a.seed}..{a.seed + a.recordings - 1})")


if __name__ == "__main__":
    main()
