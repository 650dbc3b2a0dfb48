"""Posterior sampling speed and interval coverage (make bench).

(d) emcee on a 16-frame layout (measurement level): time to >= 2000 effective samples (target < 5 s),
    tau, effective samples per second.
(e) Coverage of the 68% and 95% intervals over 200 measurement-level trials and 30 end-to-end trials
    (target: 95% intervals cover 93-97%), as `lidarcam study coverage` prints it.

Usage: python benchmarks/bench_posterior.py [--trials 200] [--trials-e2e 30] [--workers 2]
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # as the CLI does (see bench_refinement.py)

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench_refinement import fixed_layout  # noqa: E402

from estimators.analysis.coverage_study import format_summary, run_study  # noqa: E402
from estimators.solvers.closed_form import solve_closed_form  # noqa: E402
from estimators.solvers.observation_model import simulate_measurements  # noqa: E402
from estimators.solvers.posterior import PosteriorOptions, sample_posterior  # noqa: E402
from estimators.solvers.refinement import refine  # noqa: E402


def table_d(repeats: int = 3) -> None:
    rig, layout = fixed_layout(16, seed=4)
    frames = simulate_measurements(layout, np.random.default_rng(5))
    T0 = solve_closed_form([f.camera.plane for f in frames], [f.lidar.plane for f in frames]).T_camera_lidar
    ref = refine(frames, rig.board, rig.camera, T0)
    print("(d) posterior sampling, 16 frames, >= 2000 effective samples (target < 5 s)")
    print(f"  {'run':>4s}{'seconds':>9s}{'steps':>7s}{'walkers':>9s}{'tau max':>9s}{'ESS':>7s}{'ESS/s':>8s}"
          f"{'accept':>8s}")
    for k in range(repeats):
        post = sample_posterior(frames, rig.board, rig.camera, ref, np.random.default_rng(k), PosteriorOptions())
        r = post.run
        print(f"  {k:4d}{r.seconds:9.2f}{r.chain.shape[0]:7d}{r.chain.shape[1]:9d}{np.max(r.tau):9.1f}"
              f"{r.ess:7.0f}{r.ess / r.seconds:8.0f}{r.acceptance:8.2f}")
    print()


def table_e(trials: int, trials_e2e: int, workers: int) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        for mode, n in (("measurement", trials), ("end-to-end", trials_e2e)):
            if n > 0:
                summary = run_study(n, Path(tmp) / mode, mode, seed=0, workers=workers)
                print("(e) " + format_summary(summary))
                c95 = summary["coverage"]["95%"]
                axes = [a for a in c95 if a != "joint_chi2"]
                worst = min(c95[a]["fraction"] for a in axes)
                best = max(c95[a]["fraction"] for a in axes)
                verdict = "met" if 0.93 <= worst and best <= 0.97 else "NOT met"
                print(f"  95% coverage range over the axes and the joint region: {100 * worst:.1f}-{100 * best:.1f}% "
                      f"(target 93-97%): {verdict}")
                print()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=200)
    ap.add_argument("--trials-e2e", type=int, default=30)
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args()
    table_d()
    table_e(args.trials, args.trials_e2e, args.workers)


if __name__ == "__main__":
    main()
