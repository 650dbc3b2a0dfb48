"""Bag extraction: throughput and memory against bag size (make bench).

A simulated HDL-64E dataset is recorded as ROS 1, ROS 2 sqlite3 and ROS 2 MCAP bags (images 1024 x 768 mono8 at
10 Hz, sweeps at 10 Hz, each pose held 2 s and moved for 0.6 s), then `extract_bag` runs on each in a fresh
process; the table gives the bag size, the time, messages per second, the frames kept and the process's peak
resident memory (the reader streams: memory should not grow with the bag).

Usage: python benchmarks/bench_bag.py [--poses 8 16]
"""
from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

BAG_NAMES = {"ros1": "rig.bag", "sqlite3": "rig_sqlite3", "mcap": "rig_mcap"}


def _size(path: Path) -> int:
    return path.stat().st_size if path.is_file() else sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def _extract_in_child(bag: Path, out: Path) -> dict:
    """Run one extraction in a fresh interpreter and report its time and peak memory."""
    code = f"""
import json, time
from pathlib import Path
from estimators.io.bag_extract import _open_reader, extract_bag
from estimators.simulation.simulator import default_board
def peak_mb():  # VmHWM: this process's own peak (ru_maxrss would include the parent's pages before exec)
    line = next(l for l in open("/proc/self/status") if l.startswith("VmHWM"))
    return int(line.split()[1]) / 1024
reader = _open_reader(Path({str(bag)!r}))
messages = reader.message_count
reader.close()
t = time.perf_counter()
s = extract_bag({str(bag)!r}, {str(out)!r}, default_board(), "/camera/image_raw", cloud_topic="/velodyne_points")
print(json.dumps({{"seconds": time.perf_counter() - t, "frames": s.frames, "messages": messages,
                  "rss_mb": peak_mb()}}))
"""
    r = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True)
    return json.loads(r.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--poses", type=int, nargs="+", default=[8, 16])
    args = ap.parse_args()

    from estimators.simulation.simulator import simulate_dataset
    from tests.rosbag_writer import write_bag_from_dataset

    print("bag extraction (HDL-64E sweeps, 1024 x 768 mono8 images at 10 Hz, 2 s still per pose)")
    print(f"  {'poses':>5s} {'bag':>8s} {'size MB':>8s} {'messages':>9s} {'time s':>7s} {'msg/s':>7s} "
          f"{'frames':>7s} {'peak RSS MB':>12s}")
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for n in args.poses:
            ds = simulate_dataset(tmp / f"sim{n}", n_poses=n, seed=40 + n, lidar="hdl64e")
            for kind, name in BAG_NAMES.items():
                bag = write_bag_from_dataset(ds, tmp / f"{n}_{name}", kind, image_hz=10, still_s=2.0)
                stats = _extract_in_child(bag, tmp / f"out_{n}_{kind}")
                messages = stats["messages"]
                print(f"  {n:5d} {kind:>8s} {_size(bag) / 1e6:8.0f} {messages:9d} {stats['seconds']:7.1f} "
                      f"{messages / stats['seconds']:7.0f} {stats['frames']:7d} {stats['rss_mb']:12.0f}")
                shutil.rmtree(bag, ignore_errors=True) if bag.is_dir() else bag.unlink()
                shutil.rmtree(tmp / f"out_{n}_{kind}", ignore_errors=True)
    base = subprocess.run([sys.executable, "-c", "import estimators.io.bag_extract, rosbags.highlevel; "
                           "print(next(int(l.split()[1]) for l in open('/proc/self/status') "
                           "if l.startswith('VmHWM')) / 1024)"],
                          cwd=ROOT, capture_output=True, text=True, check=True).stdout.strip()
    print(f"  (a fresh interpreter that only imports the extractor peaks at {float(base):.0f} MB)")


if __name__ == "__main__":
    main()
