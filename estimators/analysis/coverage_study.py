"""Coverage of the reported intervals: many simulated calibrations, each scored against its ground truth.

A trial draws a rig (mounting deviation) and board layout, simulates the measurements, calibrates them as
``calibrate`` does (the engine's joint graph and posterior, the pair a rig of two sensors), and records whether the
truth lies inside the 68% and 95% intervals of each tangent axis, and jointly: the 6-D squared Mahalanobis distance
of the truth under the posterior covariance against the same quantile of the posterior samples' own distances
(``joint``), and against the chi-square 6-dof quantile (``joint_chi2``, exact only for a Gaussian posterior).

Modes:
- ``measurement`` (default, fast): corners and ranges drawn from the Gaussian noise model (independent
  corners, so the refinement uses no corner-correlation factor), no rendering, no segmentation.
- ``end-to-end``: rendered images and ray-cast sweeps through the whole pipeline with its defaults (corner
  errors then correlate within a board, which the default noise model must cover).
"""
from __future__ import annotations

import csv
import io
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

from geometry.rotations import T_inverse, T_log, rotation_error

from ..errors import LidarcamError
from ..io.output import write_atomic, write_json_atomic
from ..solvers import chi_square as chi2
from ..solvers.posterior import PosteriorOptions

MODES = ("measurement", "end-to-end")
AXES = ("rot_x", "rot_y", "rot_z", "trans_x", "trans_y", "trans_z")
LEVELS = (0.68, 0.95)


def run_trial(seed: int, mode: str = "measurement", n_frames: int = 8, samples: int = 1000,
              likelihood: str = "gaussian", corner_noise_px: float = 0.2, range_noise_m: float = 0.02) -> dict:
    """One simulated calibration scored against its truth (a flat dict: one CSV row)."""
    from ..io.dataset import load_dataset
    from ..io.measurement_store import Measurements
    from ..rig_calibration import calibrate
    from ..simulation.simulator import default_rig, sample_board_poses, simulate_frames, write_dataset
    from ..solvers.observation_model import Layout, simulate_measurements
    from ..solvers.refinement_options import RefinementOptions, measurement_model_options

    t0 = time.perf_counter()
    rng = np.random.default_rng(seed)
    rig = default_rig(rng, "hdl64e", range_noise_m)
    poses = sample_board_poses(rig, n_frames, rng)
    post_opts = PosteriorOptions(min_ess=samples, likelihood=likelihood)
    if mode == "measurement":
        layout = Layout(rig.camera, rig.board, rig.beams, rig.T_camera_lidar, tuple(poses), corner_noise_px,
                        range_noise_m)
        measured = Measurements(rig.camera, rig.board, "3d", tuple(simulate_measurements(layout, rng)))
        result = calibrate(measured, rng=rng, options=measurement_model_options(), posterior=post_opts)
    elif mode == "end-to-end":
        with tempfile.TemporaryDirectory() as tmp:
            sim = simulate_frames(rig, n_frames, rng, poses=poses)
            ds = load_dataset(write_dataset(Path(tmp) / "ds", rig, sim))
            result = calibrate(ds, rng=rng, posterior=post_opts, options=RefinementOptions())
    else:
        raise ValueError(f"Expected mode in {MODES}, got {mode!r}")
    if result.posterior is None:  # the engine says why in its warnings; a trial without samples scores nothing
        raise LidarcamError(f"coverage trial {seed}: the posterior was not sampled ({'; '.join(result.warnings)})")
    pair = result.only_pair()
    T, G = pair.T, rig.T_camera_lidar
    xi = T_log(T_inverse(T) @ G)
    samples_xi = pair.samples
    mean, P = samples_xi.mean(0), np.linalg.inv(pair.covariance)
    centred = xi - mean
    d2_samples = np.einsum("ni,ij,nj->n", samples_xi - mean, P, samples_xi - mean)
    laplace = result.solution.transform(pair.a, pair.b)[1]
    row = {"seed": seed, "mode": mode, "frames": pair.frames,
           "rot_err_deg": float(np.degrees(rotation_error(T[:3, :3], G[:3, :3]))),
           "trans_err_mm": float(1000 * np.linalg.norm(T[:3, 3] - G[:3, 3])),
           "d2_posterior": float(centred @ P @ centred),
           "d2_laplace": float(xi @ np.linalg.solve(laplace, xi)),
           "effective_samples": result.posterior.run.ess, "seconds": time.perf_counter() - t0}
    # Signed error of the truth from the posterior mean in posterior standard deviations: a mean far
    # from 0 over trials is a bias, a spread above 1 overconfidence.
    for k, axis in enumerate(AXES):
        row[f"z_{axis}"] = float(centred[k] / np.sqrt(pair.covariance[k, k]))
    for level in LEVELS:
        iv = pair.intervals(level)
        inside = (xi >= iv[:, 0]) & (xi <= iv[:, 1])
        for k, axis in enumerate(AXES):
            row[f"in{round(100 * level)}_{axis}"] = int(inside[k])
        # Joint: inside the posterior's own elliptical credible region (the level-quantile of its samples'
        # squared Mahalanobis distances: the sampled noise scale makes the posterior a scale mixture, whose
        # region is wider than the chi-square one), and, for reference, the chi-square 6-dof region.
        row[f"in{round(100 * level)}_joint"] = int(row["d2_posterior"] <= np.quantile(d2_samples, level))
        row[f"in{round(100 * level)}_joint_chi2"] = int(row["d2_posterior"] <= chi2.ppf(level, 6))
    return row


def _trial(args):
    return run_trial(*args)


def run_study(trials: int, out: str | Path, mode: str = "measurement", seed: int = 0, workers: int = 2,
              n_frames: int = 8, samples: int = 1000, progress: bool = False, likelihood: str = "gaussian") -> dict:
    """How often the reported intervals hold the truth, over simulated trials.

    Parameters
    ----------
    trials : int
        Simulated datasets.
    out : str or Path
        Folder for ``coverage.csv`` and ``coverage.json`` (each written atomically).
    mode : str
        ``measurement`` (noise from the model) or ``end-to-end`` (rendered images, full scans).
    seed : int
        Seed of the first trial.
    workers : int
        Local processes (1: the trials run in this process).
    n_frames : int
        Board poses per trial.
    samples : int
        Effective posterior samples per trial.
    progress : bool
        Show a progress bar.
    likelihood : str
        The posterior's likelihood, ``gaussian`` or ``student-t``.

    Returns
    -------
    dict
        The summary: per axis and level, the share of trials whose interval holds the truth.
    """
    if trials < 1:
        raise ValueError(f"Expected at least 1 trial, got {trials}")
    seeds = [int(s) for s in np.random.SeedSequence(seed).generate_state(trials)]
    args = [(s, mode, n_frames, samples, likelihood) for s in seeds]
    rows = []
    if workers == 1:  # in this process: no pool to start (a notebook's quick run, a debugger)
        rows = [_trial(a) for a in tqdm(args, desc=f"coverage ({mode})", disable=not progress)]
    else:
        with ProcessPoolExecutor(max_workers=workers) as pool:
            for row in tqdm(pool.map(_trial, args), total=trials, desc=f"coverage ({mode})", disable=not progress):
                rows.append(row)
    summary = summarize(rows)
    summary.update({"mode": mode, "seed": seed, "frames_per_trial": n_frames, "samples_per_trial": samples,
                    "likelihood": likelihood})
    out = Path(out)
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=list(rows[0]))
    writer.writeheader()
    writer.writerows(rows)
    write_atomic(out / "coverage.csv", lambda fh: fh.write(buf.getvalue()))
    write_json_atomic(out / "coverage.json", summary)
    return summary


def summarize(rows: list[dict]) -> dict:
    """Fractions inside each interval (per axis and joint) with a 95% binomial (Wilson) range."""
    n = len(rows)
    out = {"trials": n, "mean_d2_posterior": float(np.mean([r["d2_posterior"] for r in rows])),
           "mean_d2_laplace": float(np.mean([r["d2_laplace"] for r in rows])), "coverage": {},
           }
    if all(f"z_{a}" in r for r in rows for a in AXES):
        out["z_mean"] = {a: float(np.mean([r[f"z_{a}"] for r in rows])) for a in AXES}
        out["z_std"] = {a: float(np.std([r[f"z_{a}"] for r in rows], ddof=1)) if n > 1 else float("nan")
                        for a in AXES}
    for level in LEVELS:
        key = f"{round(100 * level)}"
        out["coverage"][f"{key}%"] = {
            name: _wilson(sum(r[f"in{key}_{name}"] for r in rows), n) for name in (*AXES, "joint", "joint_chi2")}
    return out


def _wilson(k: int, n: int, z: float = 1.96) -> dict:
    p = k / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * np.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return {"fraction": p, "low": float(centre - half), "high": float(centre + half)}


def format_summary(summary: dict) -> str:
    lines = [f"coverage over {summary['trials']} {summary['mode']} trials "
             f"(mean squared Mahalanobis distance of the truth: posterior {summary['mean_d2_posterior']:.2f}, "
             f"Laplace {summary['mean_d2_laplace']:.2f}; 6 ideal)",
             f"  {'interval':9s}" + "".join(f"{a:>11s}" for a in (*AXES, "joint", "joint_chi2"))]
    for level, cov in summary["coverage"].items():
        lines.append(f"  {level:9s}" + "".join(f"{100 * cov[a]['fraction']:10.1f}%"
                                                for a in (*AXES, "joint", "joint_chi2")))
    if "z_mean" in summary:
        lines.append(f"  {'z mean':9s}" + "".join(f"{summary['z_mean'][a]:11.2f}" for a in AXES))
        lines.append(f"  {'z std':9s}" + "".join(f"{summary['z_std'][a]:11.2f}" for a in AXES))
    return "\n".join(lines)
