"""Solver-comparison study throughput: a 2,000-trial measurement-level study on this machine's cores, and
the speed-up from 1 to all local processes on a 200-trial one (the same rows either way).

Run: ``python benchmarks/bench_study.py`` (``make bench`` runs it).
"""
from __future__ import annotations

import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from estimators.analysis.study import format_summary, parse_spec, run_study, summarize  # noqa: E402


def main() -> None:
    cores = os.cpu_count() or 1
    big = parse_spec({"name": "2000 trials", "lidar": "3d", "solvers": ["closed-form", "factor-graph"],
                      "frames": [4, 8, 16, 24], "range_noise_m": [0.01, 0.02, 0.04, 0.08, 0.16], "trials": 100,
                      "seed": 0})
    small = parse_spec({"name": "200 trials", "lidar": "3d", "solvers": ["closed-form", "factor-graph"],
                        "frames": [8], "range_noise_m": [0.02, 0.04], "trials": 100, "seed": 1})
    with tempfile.TemporaryDirectory() as tmp:
        print(f"scaling on a {small.n_trials}-trial study (2 solvers each):")
        times = {}
        for w in sorted({1, cores}):
            t0 = time.perf_counter()
            rows = run_study(small, Path(tmp) / f"w{w}", workers=w, progress=False)
            times[w] = time.perf_counter() - t0
            print(f"  {w} process(es): {times[w]:6.1f} s  ({len(rows)} rows)")
        if cores > 1:
            print(f"  speed-up {times[1] / times[cores]:.2f}x on {cores} cores")
        t0 = time.perf_counter()
        rows = run_study(big, Path(tmp) / "big", workers=cores, progress=False)
        seconds = time.perf_counter() - t0
        print(f"\n{big.n_trials}-trial study on {cores} processes: {seconds:.0f} s ({len(rows)} rows, "
              f"{sum(1 for r in rows if not r['ok'])} failed calibrations recorded)")
        print(format_summary(summarize(rows)))


if __name__ == "__main__":
    main()
