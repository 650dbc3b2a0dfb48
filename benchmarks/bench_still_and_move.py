"""Still poses with the board moved between them (make bench; `python benchmarks/bench_still_and_move.py [--bags N]
[--workers W] [--seed S]`): the poses' extrinsic as before, and the clocks' offset from the motion between them.

Each bag (``tests/rosbag_writer.write_waved_bag``, ROS 2 MCAP): the default rig (a 1024 x 768 camera at 20 Hz)
with, in turn, a VLP-16-, an OS1-64-, an HDL-64E-like and a Livox-like LiDAR at 10 Hz, 30-60 s of a board held
still for 4 s at a time and moved for 1.5 s between (at 0.2-1.0 m/s, 20-90 deg/s), the camera's clock ahead of the
LiDAR's by an offset drawn in +-100 ms. Read by ``extract_bag`` (still poses, the motion between them followed)
and calibrated by the engine (``calibrate_rig``, no posterior sampled); the offset read off the motion at the
poses' extrinsic (``pipeline.offset_between_poses``). Printed: the offset's errors against the truth and their
z-scores (the error over its standard deviation: sd 1 if honest), how often it was not determined and why, the
poses' extrinsic's errors and NEES (6 dof), the motion's disagreement with it, and the verdicts.
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_moving_bag import BOARD, LIDARS, _rig  # noqa: E402

HOLD_S, MOVE_S = 4.0, 1.5


def _trial(seed: int) -> dict:
    from estimators.cli.parser import board_argument
    from estimators.errors import LidarcamError
    from estimators.io.bag_extract import extract_bag
    from estimators.io.rig_dataset import load_rig
    from estimators.rig_calibration import calibrate_rig
    from geometry.rotations import T_inverse, T_log
    from tests.rosbag_writer import write_waved_bag

    rng = np.random.default_rng(seed)
    lidar = LIDARS[seed % len(LIDARS)]
    rig = _rig(rng, lidar, 1024, 768, 940.0)
    duration, offset = rng.uniform(30.0, 60.0), rng.uniform(-0.1, 0.1)
    speed, turn = rng.uniform(0.2, 1.0), rng.uniform(20.0, 90.0)
    pauses = tuple((float(a), float(a + HOLD_S)) for a in np.arange(0.5, duration - HOLD_S, HOLD_S + MOVE_S))
    row = {"seed": seed, "lidar": lidar, "duration_s": duration, "offset_s": offset, "speed": speed, "turn": turn}
    with tempfile.TemporaryDirectory(prefix="lidarcam-bench-") as tmp:
        tmp = Path(tmp)
        field = "offset_time" if lidar == "rosette" else "t"
        write_waved_bag(tmp / "bag", "mcap", rig, duration, rng, time_offset_s=offset, speed_mps=speed,
                        turn_dps=turn, time_field=field, pauses=pauses)
        t0 = time.perf_counter()
        try:
            summary = extract_bag(tmp / "bag", tmp / "ds", board_argument(BOARD), "/camera/image_raw",
                                  cloud_topic="/points")
            row.update(recording=summary.recording, frames=summary.frames, motion=summary.motion)
            if summary.recording != "still poses":
                row["refused"] = f"read as a {summary.recording}"
                return row
            result = calibrate_rig(load_rig(tmp / "ds"), np.random.default_rng(seed))
        except LidarcamError as exc:
            row["refused"] = exc.message
            return row
        row["seconds"] = time.perf_counter() - t0
        p = result.pair("cam0", "lidar0")
        xi = T_log(T_inverse(p.T) @ rig.T_camera_lidar)
        row.update(rot_deg=float(np.degrees(np.linalg.norm(xi[:3]))), trans_mm=float(1000 * np.linalg.norm(xi[3:])),
                   nees=float(xi @ np.linalg.solve(p.covariance, xi)), verdict=result.verdict.level)
        off = result.time_offset
        if off is not None:
            row.update(offset_hat=off.time_offset_s, offset_sd=off.time_offset_std_s, words=off.words,
                       disagreement=off.disagreement_chi2, disagrees=off.disagrees,
                       own_hat=off.motion_offset_s, own_sd=off.motion_offset_std_s)
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bags", type=int, default=12)
    ap.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    t0 = time.time()
    with ProcessPoolExecutor(a.workers) as pool:
        rows = list(pool.map(_trial, range(a.seed, a.seed + a.bags)))
    done = [r for r in rows if "refused" not in r]
    found = [r for r in done if r.get("offset_hat") is not None]
    err = np.array([1000 * (r["offset_hat"] - r["offset_s"]) for r in found])
    z = np.array([(r["offset_hat"] - r["offset_s"]) / r["offset_sd"] for r in found])
    print(f"{a.bags} simulated bags, 30-60 s (mean {np.mean([r['duration_s'] for r in rows]):.0f} s), the board held "
          f"still {HOLD_S:.0f} s and moved {MOVE_S} s between, clock offsets in +-100 ms; read as: "
          + ", ".join(f"{k} {sum(r.get('recording') == k for r in rows)}"
                      for k in sorted({r.get('recording') for r in done})) + f"; refused {len(rows) - len(done)}:\n")
    print("| | |")
    print("|---|---|")
    print(f"| still poses kept (mean) | {np.mean([r['frames'] for r in done]):.1f} |")
    print(f"| offset found | {len(found)} of {len(done)} |")
    if len(found):
        print(f"| offset error, RMS, mean | {np.sqrt(np.mean(err ** 2)):.2f} ms, {err.mean():+.2f} ms |")
        print(f"| offset error, largest | {np.abs(err).max():.2f} ms |")
        print(f"| offset standard deviation, median | {1000 * np.median([r['offset_sd'] for r in found]):.2f} ms |")
        print(f"| offset z-score (error / sd), RMS (1 if honest) | {np.sqrt(np.mean(z ** 2)):.2f} |")
    own = [r for r in done if r.get("own_hat") is not None]
    if own:
        e2 = np.array([1000 * (r["own_hat"] - r["offset_s"]) for r in own])
        z2 = np.array([(r["own_hat"] - r["offset_s"]) / r["own_sd"] for r in own])
        print(f"| the motion's own offset (its extrinsic free): error RMS, mean; z-score RMS | "
              f"{np.sqrt(np.mean(e2 ** 2)):.2f} ms, {e2.mean():+.2f} ms; {np.sqrt(np.mean(z2 ** 2)):.2f} |")
    print(f"| the poses' extrinsic: rotation error RMS | "
          f"{np.sqrt(np.mean([r['rot_deg'] ** 2 for r in done])):.3f} deg |")
    print(f"| the poses' extrinsic: translation error RMS | "
          f"{np.sqrt(np.mean([r['trans_mm'] ** 2 for r in done])):.1f} mm |")
    nees = np.array([r["nees"] for r in done])
    print(f"| the poses' extrinsic: NEES (6 dof: 6 if honest), mean / median | {nees.mean():.1f} / "
          f"{np.median(nees):.1f} |")
    print(f"| the motion's extrinsic disagrees with the poses' (0.001 tail) | "
          f"{sum(bool(r.get('disagrees')) for r in done)} of {len(done)} |")
    print("| verdicts | " + ", ".join(f"{k} {sum(r.get('verdict') == k for r in done)}"
                                      for k in ("OK", "CHECK", "UNTRUSTED")) + " |")
    print(f"| seconds, extract and calibrate (in process), median | "
          f"{np.median([r['seconds'] for r in done]):.1f} |")
    print("\nEach bag: seed, LiDAR, length, speed and turn rate while moved, still poses kept, the offset and its "
          "error (ms) and z-score, the poses' extrinsic's errors and NEES, the motion's disagreement (chi-square, "
          "6 dof), the verdict:\n")
    print("| seed | LiDAR | s | m/s | deg/s | poses | offset ms | error ms | z | deg | mm | NEES | chi-square | "
          "verdict |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        if "refused" in r:
            print(f"| {r['seed']} | {r['lidar']} | {r['duration_s']:.0f} | | | | {1000 * r['offset_s']:+.1f} | "
                  f"refused: {r['refused'][-90:]} | | | | | | |")
            continue
        if r.get("offset_hat") is not None:
            e = 1000 * (r["offset_hat"] - r["offset_s"])
            off = f"{e:+.2f} | {e / (1000 * r['offset_sd']):+.1f}"
        else:
            off = "not found (below) | "
        chi = f"{r['disagreement']:.1f}" if r.get("disagreement") is not None else "-"
        print(f"| {r['seed']} | {r['lidar']} | {r['duration_s']:.0f} | {r['speed']:.2f} | {r['turn']:.0f} | "
              f"{r['frames']} | {1000 * r['offset_s']:+.1f} | {off} | {r['rot_deg']:.3f} | {r['trans_mm']:.1f} | "
              f"{r['nees']:.1f} | {chi} | {r['verdict']} |")
    missed = [r for r in done if r.get("offset_hat") is None]
    if missed:
        print("\nOffset not found:\n")
        for r in missed:
            print(f"- seed {r['seed']}: {r.get('words') or r.get('motion') or 'no motion followed'}")
    print(f"\n({a.bags} bags in {time.time() - t0:.0f} s on {a.workers} processes; "
          f"seeds {a.seed}..{a.seed + a.bags - 1})")


if __name__ == "__main__":
    main()
