"""A board waved before the rig, from the bag to calibration.json: the moving board read and solved with the clocks'
offset, beside the offset held at 0 and beside still-pose extraction of the same bags (make bench;
`python benchmarks/bench_moving_bag.py [--bags N] [--workers W] [--speed]`).

Each bag (``tests/rosbag_writer.write_waved_bag``, ROS 2 MCAP): the default rig (its 1024 x 768 camera at 20 Hz,
images drawn as polygons, blurred over a 4 ms exposure) with, in turn, a VLP-16-, an OS1-64-, an HDL-64E-like
LiDAR at 10 Hz (whole sweeps in a room, 20 mm range noise) whose returns carry Ouster's ``t`` field, Velodyne's
``time`` field or no time field (then timed by their azimuth), or a Livox-like rosette (Livox's ``offset_time``
field; its 38-degree cone sees the board part of the time); 30-90 s of a board waved at 0.2-1.0 m/s and
20-90 deg/s with three pauses of 2 s; the camera's clock ahead of the LiDAR's by an offset drawn in +-100 ms.
Read by ``extract_bag`` and solved by ``pipeline.moving_board`` (offset free, and held at 0); the same bag read
for still poses only (``ExtractOptions(follow_motion=False)``: what extraction kept before) and calibrated by the
engine where it keeps 3 frames or more. Printed: the errors against the truth, the NEES of the extrinsic and the
offset together (7 dof), and the extrinsic's RMS error against the continuous model's bound (the joint solve's
inverse information at its estimate: 1 for an efficient estimate).

``--memory``: the same configuration at 15 and 60 s: each command's peak memory against the bag's length.

``--speed``: a 60 s bag of an OS1-64-like LiDAR (131 072 returns a sweep, 10 Hz) and a 1280 x 720 camera at
20 Hz, through ``lidarcam extract`` and ``lidarcam calibrate`` as commands: wall time and peak memory of each.
"""
from __future__ import annotations

import argparse
import dataclasses
import os
import shutil
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

LIDARS = ("vlp16", "os64", "hdl64e", "rosette")
FIELDS = ("t", "time", None)
BOARD = "9x7:0.1:1.0x1.0"
# The camera's pointing term's sizes (px) the NEES is also given at (``_nees_at_pointing``).
POINTING_PX = (0.0, 0.02, 0.03, 0.05)


def _rig(rng, lidar: str, width: int, height: int, focal: float):
    from estimators.lidar.lidar_models import Rosette
    from estimators.simulation.simulator import default_rig
    from geometry.camera import CameraModel

    rig = default_rig(rng, "vlp16" if lidar == "rosette" else lidar)
    if lidar == "rosette":
        rig = dataclasses.replace(rig, beams=Rosette(sigma_range_m=0.02))
    K = np.array([[focal, 0.0, width / 2], [0.0, focal, height / 2], [0.0, 0.0, 1.0]])
    return dataclasses.replace(rig, camera=CameraModel(K, np.zeros(5), width, height, source="simulator"))


def _nees_at_pointing(result, truth, offset_true) -> dict:
    """The NEES (7 dof) were the camera's pointing term another size: the solve's covariance less the term it
    carries (``POINTING_SD_PX``), plus the term at each of ``POINTING_PX`` (px -> NEES)."""
    from estimators.solvers.clock_offset import POINTING_SD_PX, pointing_covariance
    from geometry.rotations import T_inverse, T_log

    K = result.camera.K
    e = np.r_[T_log(T_inverse(result.T_camera_lidar) @ truth), offset_true - result.time_offset_s]
    base = result.covariance_with_offset.copy()
    base[:6, :6] -= pointing_covariance(result.T_camera_lidar, POINTING_SD_PX / K[1, 1], POINTING_SD_PX / K[0, 0])
    out = {}
    for px in POINTING_PX:
        C = base.copy()
        C[:6, :6] += pointing_covariance(result.T_camera_lidar, px / K[1, 1], px / K[0, 0])
        out[px] = float(e @ np.linalg.solve(C, e))
    return out


def _errors(T, covariance, truth, offset_hat, offset_true, cov7=None) -> dict:
    from geometry.rotations import T_inverse, T_log

    xi = T_log(T_inverse(T) @ truth)
    out = {"rot_deg": float(np.degrees(np.linalg.norm(xi[:3]))), "trans_mm": float(1000 * np.linalg.norm(xi[3:])),
           "offset_err_ms": 1000 * (offset_hat - offset_true)}
    if covariance is not None:
        out["bound_rot_deg2"] = float(np.degrees(1) ** 2 * np.trace(covariance[:3, :3]))
        out["bound_trans_mm2"] = float(1e6 * np.trace(covariance[3:, 3:]))
    if cov7 is not None:
        e = np.r_[xi, offset_true - offset_hat]
        out["nees"] = float(e @ np.linalg.solve(cov7, e))
    return out


def _trial(seed: int) -> dict:
    from estimators.errors import LidarcamError
    from estimators.io.bag_extract import ExtractOptions, extract_bag
    from estimators.io.dataset import load_dataset
    from estimators.pipeline.moving_board import calibrate_moving
    from estimators.rig_calibration import calibrate
    from estimators.cli.parser import board_argument
    from tests.rosbag_writer import write_waved_bag

    rng = np.random.default_rng(seed)
    lidar = LIDARS[seed % len(LIDARS)]
    field = "offset_time" if lidar == "rosette" else FIELDS[(seed // len(LIDARS)) % len(FIELDS)]
    rig = _rig(rng, lidar, 1024, 768, 940.0)
    duration, offset = rng.uniform(30.0, 90.0), rng.uniform(-0.1, 0.1)
    speed, turn = rng.uniform(0.2, 1.0), rng.uniform(20.0, 90.0)
    starts = np.sort(rng.choice(np.arange(3.0, duration - 5.0, 5.0), 3, replace=False))
    pauses = tuple((float(a), float(a + 2.0)) for a in starts)
    board = board_argument(BOARD)
    row = {"seed": seed, "lidar": lidar, "field": str(field), "duration_s": duration, "offset_s": offset,
           "speed": speed, "turn": turn}
    with tempfile.TemporaryDirectory(prefix="lidarcam-bench-") as tmp:
        tmp = Path(tmp)
        write_waved_bag(tmp / "bag", "mcap", rig, duration, rng, time_offset_s=offset, speed_mps=speed,
                        turn_dps=turn, time_field=field, pauses=pauses)
        t0 = time.perf_counter()
        try:
            summary = extract_bag(tmp / "bag", tmp / "ds", board, "/camera/image_raw", cloud_topic="/points")
        except LidarcamError as exc:  # refused by extract: counted and listed with its reason too
            row["refused"] = f"extract: {exc}"
            return row
        row["recording"] = summary.recording
        try:
            free = calibrate_moving(tmp / "ds", np.random.default_rng(seed))
        except LidarcamError as exc:  # refused with its reason: counted and listed, not in the error rows
            row["refused"] = str(exc)
            return row
        row["seconds"] = time.perf_counter() - t0
        held = calibrate_moving(tmp / "ds", np.random.default_rng(seed), time_offset_s=0.0)
        row["sweeps"], row["images"] = free.sweeps, free.views
        row["free"] = _errors(free.T_camera_lidar, free.covariance, rig.T_camera_lidar, free.time_offset_s, offset,
                              free.covariance_with_offset)
        row["free"]["nees_at_pointing"] = _nees_at_pointing(free, rig.T_camera_lidar, offset)
        row["held"] = _errors(held.T_camera_lidar, None, rig.T_camera_lidar, 0.0, offset)
        row["verdict"] = free.verdict.level
        row["still"] = None
        try:
            still = extract_bag(tmp / "bag", tmp / "still", board, "/camera/image_raw", cloud_topic="/points",
                                options=ExtractOptions(follow_motion=False))
            row["still_frames"] = still.frames
        except LidarcamError as exc:  # no still pose at all: none kept, and why
            row["still_frames"], row["still_refused"] = 0, str(exc)
        if row["still_frames"] >= 3:
            try:
                result = calibrate(load_dataset(tmp / "still"), rng=np.random.default_rng(seed), samples=0)
                p = result.pair("cam0", "lidar0")
                row["still"] = _errors(p.T, None, rig.T_camera_lidar, 0.0, offset)
            except LidarcamError as exc:
                row["still_refused"] = str(exc)
        shutil.rmtree(tmp / "bag", ignore_errors=True)
    return row


def _tree_rss_gb(pid: int) -> float:
    """The resident memory (GB) of a process and every process below it, read from /proc (0 where gone)."""
    total, todo = 0, [pid]
    while todo:
        p = todo.pop()
        try:
            status = Path(f"/proc/{p}/status").read_text()
            total += int(next(line.split()[1] for line in status.splitlines() if line.startswith("VmRSS:")))
            for task in Path(f"/proc/{p}/task").iterdir():
                todo += [int(c) for c in (task / "children").read_text().split()]
        except (OSError, StopIteration, ValueError):
            continue
    return total / 1024 ** 2


def _timed(cmd: list[str]) -> tuple[float, float, str, float]:
    """Wall seconds, peak resident memory (GB) of the command's own process, its output, and the peak of its whole
    process tree (its worker processes too; sampled every 0.1 s)."""
    import threading

    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    peak, done = [0.0], threading.Event()

    def sample():
        while not done.is_set():
            peak[0] = max(peak[0], _tree_rss_gb(proc.pid))
            done.wait(0.1)

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    out = proc.stdout.read()
    _, status, usage = os.wait4(proc.pid, 0)
    done.set()
    sampler.join()
    if os.waitstatus_to_exitcode(status) != 0:
        raise SystemExit(f"{' '.join(cmd)} failed:\n{out}")
    return time.perf_counter() - t0, usage.ru_maxrss / 1024 ** 2, out, max(peak[0], usage.ru_maxrss / 1024 ** 2)


def _through_commands(seed: int, length_s: float) -> tuple[float, tuple, tuple]:
    """The speed bag's configuration (an OS1-64-like LiDAR, a 1280 x 720 camera at 20 Hz, the camera's clock 35 ms
    ahead) of ``length_s`` through ``lidarcam extract`` and ``lidarcam calibrate``: the bag's size (GB) and each
    command's :func:`_timed`."""
    from tests.rosbag_writer import write_waved_bag

    rng = np.random.default_rng(seed)
    rig = _rig(rng, "os64", 1280, 720, 1000.0)
    with tempfile.TemporaryDirectory(prefix="lidarcam-bench-") as tmp:
        tmp = Path(tmp)
        write_waved_bag(tmp / "bag", "mcap", rig, length_s, rng, time_offset_s=0.035)
        size = sum(f.stat().st_size for f in (tmp / "bag").rglob("*") if f.is_file()) / 1024 ** 3
        exe = [sys.executable, "-m", "estimators"]
        ex = _timed(exe + ["extract", str(tmp / "bag"), "--image-topic", "/camera/image_raw", "--cloud-topic",
                           "/points", "--board", BOARD, "--out", str(tmp / "ds")])
        ca = _timed(exe + ["calibrate", str(tmp / "ds"), "--out", str(tmp / "cal")])
    return size, ex, ca


def speed(seed: int) -> None:
    size, ex, ca = _through_commands(seed, 60.0)
    print(f"A 60 s bag ({size:.1f} GB): an OS1-64-like LiDAR (64 x 2048 returns a sweep, 10 Hz, Ouster's t field) and "
          "a 1280 x 720 camera at 20 Hz, the camera's clock 35 ms ahead:\n")
    print("| command | wall time | peak memory |")
    print("|---|---|---|")
    print(f"| lidarcam extract | {ex[0]:.1f} s | {ex[1]:.2f} GB |")
    print(f"| lidarcam calibrate | {ca[0]:.1f} s | {ca[1]:.2f} GB |")
    print(f"| both | {ex[0] + ca[0]:.1f} s | {max(ex[1], ca[1]):.2f} GB |")
    print("\nThe calibration's printout:\n")
    print("\n".join("    " + line for line in ca[2].splitlines()[:13]))
    print()


def memory(seed: int, lengths: tuple[float, ...] = (15.0, 60.0)) -> None:
    """The speed bag's configuration at several lengths through ``lidarcam extract`` and ``lidarcam calibrate``:
    the peak memory of each (the measurement stage streams the bag, so its memory should not grow with the
    length; the calibration holds every image's corners and the sweeps' board returns, which do)."""
    print("The speed bag's configuration (an OS1-64-like LiDAR, a 1280 x 720 camera at 20 Hz) at several lengths:\n")
    print("| length | bag | extract: peak memory (its process / with its worker) | wall time | calibrate: peak memory "
          "(its process / with its workers) | wall time |")
    print("|---|---|---|---|---|---|")
    for length in lengths:
        size, ex, ca = _through_commands(seed, length)
        print(f"| {length:.0f} s | {size:.1f} GB | {ex[1]:.2f} / {ex[3]:.2f} GB | {ex[0]:.1f} s | "
              f"{ca[1]:.2f} / {ca[3]:.2f} GB | {ca[0]:.1f} s |")
    print("\n(with its workers: the resident sizes of the process tree summed, sampled every 0.1 s; pages a forked "
          "worker shares with its parent count twice. Wall times of this run: the speed page's run, alone on the "
          "machine, is the timing)\n")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bags", type=int, default=12)
    ap.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--speed", action="store_true", help="also time a 60 s 64-beam bag through the commands")
    ap.add_argument("--memory", action="store_true", help="also the commands' peak memory on 15 and 60 s bags")
    a = ap.parse_args()
    if a.speed:
        speed(a.seed)
    if a.memory:
        memory(a.seed)
    if a.bags <= 0:
        return
    t0 = time.time()
    with ProcessPoolExecutor(a.workers) as pool:
        every = list(pool.map(_trial, range(a.seed, a.seed + a.bags)))
    rows = [r for r in every if "refused" not in r]
    refused = [r for r in every if "refused" in r]

    def col(name, key):
        return np.array([r[name][key] for r in rows if r.get(name) is not None])

    def rms(x):
        return float(np.sqrt(np.mean(np.square(x)))) if len(x) else float("nan")

    still_rows = [r for r in rows if r.get("still") is not None]
    print(f"{a.bags} simulated bags, 30-90 s (mean {np.mean([r['duration_s'] for r in every]):.0f} s), board at "
          "0.2-1.0 m/s with three 2-s pauses, clock offsets in +-100 ms; read as: "
          + ", ".join(f"{k} {sum(r.get('recording') == k for r in every)}"
                      for k in sorted({r['recording'] for r in every if 'recording' in r}))
          + (f"; {len(refused)} refused (listed at the end)" if refused else "") + ":\n")
    print("| | moving board, offset free (prior +-0.2 s) | moving board, offset held at 0 | still poses only |")
    print("|---|---|---|---|")
    print(f"| used (mean) | {np.mean([r['images'] for r in rows]):.0f} images, "
          f"{np.mean([r['sweeps'] for r in rows]):.0f} sweeps | the same | "
          f"{np.mean([r['still_frames'] for r in rows]):.1f} frames; calibrated {len(still_rows)} of {len(rows)} "
          "(3 frames or more) |")
    print(f"| offset error, RMS | {rms(col('free', 'offset_err_ms')):.2f} ms | "
          f"{rms(col('held', 'offset_err_ms')):.1f} ms | - |")
    print(f"| offset error, largest | {np.abs(col('free', 'offset_err_ms')).max():.2f} ms | - | - |")
    print(f"| rotation error, RMS | {rms(col('free', 'rot_deg')):.3f} deg | {rms(col('held', 'rot_deg')):.3f} deg | "
          f"{rms(col('still', 'rot_deg')):.3f} deg |")
    print(f"| translation error, RMS | {rms(col('free', 'trans_mm')):.1f} mm | {rms(col('held', 'trans_mm')):.1f} mm | "
          f"{rms(col('still', 'trans_mm')):.1f} mm |")
    nees = col("free", "nees")
    print(f"| NEES, extrinsic and offset (7 dof: 7 if honest), mean | {nees.mean():.1f} "
          f"(sd of the mean {nees.std(ddof=1) / np.sqrt(len(nees)):.1f}) | - | - |")
    at = [r["free"]["nees_at_pointing"] for r in rows if r.get("free")]
    print("| NEES were the camera's pointing term (px) another size, mean | " + ", ".join(
        f"{px}: {np.mean([a[px] for a in at]):.1f}" for px in POINTING_PX) + " | - | - |")
    ratio_r = rms(col("free", "rot_deg")) / np.sqrt(np.mean(col("free", "bound_rot_deg2")))
    ratio_t = rms(col("free", "trans_mm")) / np.sqrt(np.mean(col("free", "bound_trans_mm2")))
    print(f"| RMS error / the continuous model's bound | rotation {ratio_r:.2f}, translation {ratio_t:.2f} | - | - |")
    print("| verdicts | " + ", ".join(f"{k} {sum(r['verdict'] == k for r in rows)}"
                                      for k in ("OK", "CHECK", "UNTRUSTED")) + " | - | - |")
    print(f"| seconds, extract and calibrate (in process), median | {np.median([r['seconds'] for r in rows]):.1f} "
          "| - | - |")
    by = {lid: [r for r in rows if r["lidar"] == lid] for lid in LIDARS}
    print("\nBy LiDAR (offset free): " + "; ".join(
        f"{lid}: offset RMS {rms([r['free']['offset_err_ms'] for r in rs]):.2f} ms, "
        f"{rms([r['free']['trans_mm'] for r in rs]):.1f} mm" for lid, rs in by.items() if rs))
    print("\nEach bag (offset free): seed, LiDAR, time field, length, board speed and turn rate, offset, its error, "
          "the extrinsic's errors, NEES (7 dof), the verdict:\n")
    print("| seed | LiDAR | field | s | m/s | deg/s | offset ms | error ms | deg | mm | NEES | verdict |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        f = r["free"]
        print(f"| {r['seed']} | {r['lidar']} | {r['field']} | {r['duration_s']:.0f} | {r['speed']:.2f} | "
              f"{r['turn']:.0f} | {1000 * r['offset_s']:+.1f} | {f['offset_err_ms']:+.2f} | {f['rot_deg']:.3f} | "
              f"{f['trans_mm']:.1f} | {f['nees']:.1f} | {r['verdict']} |")
    if refused:
        print(f"\nRefused by extract or calibrate ({len(refused)} of {a.bags}; not in the rows above): " + "; ".join(
            f"seed {r['seed']} ({r['lidar']}, offset {1000 * r['offset_s']:+.1f} ms): {r['refused']}"
            for r in refused))
    print(f"\n({a.bags} bags in {time.time() - t0:.0f} s on {a.workers} processes; "
          f"seeds {a.seed}..{a.seed + a.bags - 1})")


if __name__ == "__main__":
    main()
