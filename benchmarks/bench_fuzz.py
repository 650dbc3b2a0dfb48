"""The long fuzz run over every reader (make bench; `python benchmarks/bench_fuzz.py [--cases N]`).

For each reader of tests/fuzz_targets.py: N mutated inputs (hypothesis, derandomised), and a table of cases
tried, how they ended (read, LidarcamError, any other exception: a bug), the slowest case and the process's
peak memory. Targets (issue 20): 10,000 cases per reader, zero other exceptions, no case over 10 s, peak memory
under 1 GB. The first failing input of each reader is printed so that it can be made a regression test.
"""
from __future__ import annotations

import argparse
import os
import resource
import sys
import tempfile
import time
import warnings
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402
from hypothesis import HealthCheck, given, settings  # noqa: E402

from estimators.errors import LidarcamError  # noqa: E402
from tests.fuzz_targets import (  # noqa: E402
    FILE_TARGETS, MESSAGE_TARGETS, bag_target, measurements_target, mutate, mutations)


class Tally:
    def __init__(self):
        self.cases = self.read = self.refused = 0
        self.bugs: list[tuple] = []
        self.slowest = 0.0
        self.peak_mb = 0.0

    def run(self, fn, case) -> None:
        t0 = time.perf_counter()
        try:
            fn()
            self.read += 1
        except LidarcamError:
            self.refused += 1
        except Exception as exc:  # noqa: BLE001 - the point: anything else is a bug to report
            self.bugs.append((type(exc).__name__, str(exc).splitlines()[0][:100] if str(exc) else "", case))
        self.slowest = max(self.slowest, time.perf_counter() - t0)
        self.cases += 1


def _settings(n: int):
    return settings(max_examples=n, deadline=None, derandomize=True, database=None,
                    suppress_health_check=list(HealthCheck))


def fuzz_file(target, n: int, folder: Path) -> Tally:
    tally = Tally()
    seed = target.seed(folder)

    @_settings(n)
    @given(ops=mutations())
    def run(ops):
        path = folder / f"case{target.suffix}"
        path.write_bytes(mutate(seed, ops))

        def read():
            out = target.read(path)
            if target.check is not None:
                target.check(out)

        tally.run(read, ops)

    run()
    return tally


def fuzz_message(strategy, decode, n: int) -> Tally:
    tally = Tally()

    @_settings(n)
    @given(msg=strategy())
    def run(msg):
        tally.run(lambda: decode(msg), msg)

    run()
    return tally


def _extra_targets(folder: Path, with_bag: bool) -> list:
    """measurements.npz/.json and a ROS 1 bag, made from a small simulated dataset."""
    from estimators.calibration import measure
    from estimators.io.dataset import load_dataset
    from estimators.io.measurement_store import save_measurements
    from estimators.simulation.simulator import simulate_dataset
    from tests.rosbag_writer import write_bag_from_dataset

    sim = simulate_dataset(folder / "sim", n_poses=4, seed=5, lidar="vlp16")
    save_measurements(folder / "m", measure(load_dataset(sim), rng=np.random.default_rng(0)))
    out = list(measurements_target((folder / "m" / "measurements.npz").read_bytes(),
                                   (folder / "m" / "measurements.json").read_bytes()))
    if with_bag:
        bag = write_bag_from_dataset(sim, folder / "seed.bag", "ros1", image_hz=2, still_s=2.0, move_s=0.5)
        target = bag_target(bag.read_bytes(), load_dataset(sim).board)
        target.read(bag)  # the seed itself extracts
        out.append(target)
    return out


EXTRA_NAMES = {"measurements_npz", "measurements_json", "ros1_bag"}


def _peak(tally: Tally) -> Tally:
    """The process's peak memory once this reader's cases have run (it only grows: a reader that needed
    more than the ones before it shows as a step)."""
    tally.peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return tally


def _print_row(name: str, t: Tally) -> None:
    """One reader's row, printed as soon as it is done (the whole run takes a while)."""
    print(f"{name:26s}{t.cases:7d}{t.read:7d}{t.refused:8d}{len(t.bugs):6d}{t.slowest:10.2f}"
          f"{t.peak_mb:15.0f}", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=10_000, help="cases per reader (bags: a tenth)")
    ap.add_argument("--readers", default=None, metavar="NAME,...", help="only these readers (default: all)")
    args = ap.parse_args()
    only = None if args.readers is None else set(args.readers.split(","))
    warnings.simplefilter("ignore")
    print(f"{'reader':26s}{'cases':>7s}{'read':>7s}{'refused':>8s}{'bugs':>6s}{'slowest s':>10s}"
          f"{'peak MB so far':>15s}")
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        rows = []
        extra = _extra_targets(tmp / "extra", with_bag=True) if only is None or only & EXTRA_NAMES else []
        for target in [*FILE_TARGETS, *extra]:
            if only is not None and target.name not in only:
                continue
            folder = tmp / target.name
            folder.mkdir()
            n = max(1, args.cases // 10) if target.name.endswith("bag") else args.cases
            rows.append((target.name, _peak(fuzz_file(target, n, folder))))
            _print_row(*rows[-1])
        for name, strategy, decode in MESSAGE_TARGETS:
            if only is not None and name not in only:
                continue
            rows.append((name, _peak(fuzz_message(strategy, decode, args.cases))))
            _print_row(*rows[-1])
        total_bugs = sum(len(t.bugs) for _, t in rows)
        for name, t in rows:
            for kind, text, case in t.bugs[:1]:
                print(f"  {name}: {kind}: {text}\n    input: {case!r}"[:600])
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"peak memory {peak_mb:.0f} MB (target < 1024); other exceptions: {total_bugs} (target 0)")


if __name__ == "__main__":
    main()
