"""Posterior sampling speed and interval coverage (make bench).

Every table samples the engine's posterior (``calibrate``: the pair a rig of two sensors).
(d) emcee on a 16-frame layout (measurement level): time to >= 2000 effective samples (target < 5 s),
    tau, effective samples per second.
(e) Coverage of the 68% and 95% intervals over 200 measurement-level trials and 100 end-to-end trials
    (target: 95% intervals cover 93-97% on average over the axes, each axis within a true 95%'s binomial 99% band
    for the trials run), as `lidarcam study coverage` prints it.
(f) The two samplers on the same posteriors (simulated 3D and 2D datasets, end to end): the pilot-tuned
    independence proposal (the default) against the ensemble moves alone, their autocorrelation and time, and
    the proposal's samples' standard deviations and 99.9% region over the ensemble's (1 when they sample the same
    posterior; each ratio's noise about 2%).

Usage: python benchmarks/bench_posterior.py [--trials 200] [--trials-e2e 100] [--workers 2] [--samplers 4]
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
from estimators.io.measurement_store import Measurements  # noqa: E402
from estimators.rig_calibration import calibrate  # noqa: E402
from estimators.solvers.observation_model import simulate_measurements  # noqa: E402
from estimators.solvers.posterior import PosteriorOptions, region_d2  # noqa: E402
from estimators.solvers.refinement_options import measurement_model_options  # noqa: E402


def table_d(repeats: int = 3) -> None:
    rig, layout = fixed_layout(16, seed=4)
    measured = Measurements(rig.camera, rig.board, "3d", tuple(simulate_measurements(layout, np.random.default_rng(5))))
    print("(d) posterior sampling, 16 frames, >= 2000 effective samples (target < 5 s)")
    print(f"  {'run':>4s}{'seconds':>9s}{'steps':>7s}{'walkers':>9s}{'tau max':>9s}{'ESS':>7s}{'ESS/s':>8s}"
          f"{'accept':>8s}")
    for k in range(repeats):
        r = calibrate(measured, rng=np.random.default_rng(k), options=measurement_model_options(),
                      posterior=PosteriorOptions()).posterior.run
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
                pooled = float(np.mean([c95[a]["fraction"] for a in axes]))
                # Each share is a binomial over the trials: with n of them an axis's share of a true 95% lies
                # within +-2.58 sqrt(0.95 0.05 / n) of it 99% of the time (4.7 points at n = 100), so the target
                # reads the mean over the axes and the joint region, and each share against that band.
                band = 2.58 * np.sqrt(0.95 * 0.05 / n)
                met = 0.93 <= pooled <= 0.97 and 0.95 - band <= worst and best <= 0.95 + band
                verdict = "met" if met else "NOT met"
                print(f"  95% coverage: mean over the axes and the joint region {100 * pooled:.1f}% (target 93-97%), "
                      f"each {100 * worst:.1f}-{100 * best:.1f}% (a true 95%'s 99% band over {n} trials: "
                      f"{100 * (0.95 - band):.1f}-{100 * min(0.95 + band, 1.0):.1f}%): {verdict}")
                print()


def table_f(per_kind: int) -> None:
    """The samplers compared (module docstring, (f)) on ``per_kind`` datasets of each kind."""
    from dataclasses import replace

    from estimators.io.dataset import load_dataset
    from estimators.pipeline.measurement import measure
    from estimators.simulation.simulator import simulate_dataset

    kinds = (("3D default, 8 poses", dict(n_poses=8)), ("2D default, 5 boards", dict(n_poses=5, lidar="2d")),
             ("2D mounted, 8 boards", dict(n_poses=8, lidar="2d", rig_config="mounted")))
    print("(f) the samplers on the same posteriors: proposal (default) against ensemble moves alone, 2000 effective "
          "samples")
    print(f"  {'dataset':24s}{'seed':>5s}{'tau ens':>8s}{'tau prop':>9s}{'s ens':>7s}{'s prop':>7s}"
          f"{'sd ratio (rot x y z, trans x y z)':>40s}{'r99.9 ratio':>12s}")
    ratios = []
    with tempfile.TemporaryDirectory() as tmp:
        for label, kw in kinds:
            for seed in range(1, per_kind + 1):
                folder = simulate_dataset(Path(tmp) / f"{label.split(',')[0].replace(' ', '_')}{seed}", seed=seed,
                                          **kw)
                m = measure(load_dataset(folder), np.random.default_rng(0))
                runs = {}
                for sampler in ("ensemble", "proposal"):
                    res = calibrate(m, posterior=replace(PosteriorOptions(), sampler=sampler),
                                    rng=np.random.default_rng(seed))
                    runs[sampler] = (res.posterior, res.samples)
                (e, e_xi), (p, p_xi) = runs["ensemble"], runs["proposal"]
                if e is None or p is None:
                    print(f"  {label:24s}{seed:5d}  not sampled")
                    continue
                sd = np.std(p_xi, axis=0) / np.std(e_xi, axis=0)
                r = region_d2(p_xi, 0.999) / region_d2(e_xi, 0.999)
                ratios.append(np.append(sd, r))
                print(f"  {label:24s}{seed:5d}{np.max(e.run.tau):8.1f}{np.max(p.run.tau):9.1f}{e.run.seconds:7.2f}"
                      f"{p.run.seconds:7.2f}{' '.join(f'{v:4.2f}' for v in sd):>40s}{r:12.2f}")
    if ratios:
        a = np.array(ratios)
        print(f"  mean ratios over {len(a)} datasets: sd " + " ".join(f"{v:.3f}" for v in a[:, :6].mean(0))
              + f", 99.9% region {a[:, 6].mean():.3f}")
    print()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=200)
    ap.add_argument("--trials-e2e", type=int, default=100)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--samplers", type=int, default=4, help="datasets of each kind in table (f)")
    args = ap.parse_args()
    table_d()
    table_f(args.samplers)
    table_e(args.trials, args.trials_e2e, args.workers)


if __name__ == "__main__":
    main()
