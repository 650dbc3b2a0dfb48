"""Solver-comparison studies: a grid of simulated calibrations, each scored against its ground truth and
the Cramer-Rao bound of its layout, run on local processes or on a Dask cluster with the same results. The solvers
are a single pair's own solve's stages (``calibration.solve``: closed form, 2D minimal solutions, factor graph),
which start each camera-LiDAR pair of the engine.

A study is given as a mapping (``SPEC.yaml``)::

    name: closed form vs factor graph        # optional
    lidar: 3d                                # 3d | 2d
    model: hdl64e                            # 3D beam model (hdl64e | vlp16); ignored for 2d
    solvers: [closed-form, factor-graph]     # 3d: closed-form, factor-graph
                                             # 2d: minimal-min-residual, minimal-lower-bound,
                                             #     minimal-lower-bound-no-extent
    layouts: [spread, quadrants]             # board-pose families: spread, quadrants, upward, rightward,
                                             # frontal, weak, diamond (see simulator.sample_layout)
    frames: [4, 8, 16]                       # board poses per calibration
    range_noise_m: [0.01, 0.02]              # LiDAR range sigma
    corner_noise_px: [0.2]                   # corner sigma (measurement level)
    trials: 20                               # per cell of layouts x frames x range noise x corner noise
    seed: 0
    mode: measurement                        # measurement (noise drawn from the model) | end-to-end
    rig: default                             # default | varied (2d: mountings drawn per trial)

Every solver of a trial sees the same simulated data (a paired comparison). Each row of ``study.csv`` is one (trial,
solver): the cell, the rotation and translation errors, the errors per axis over the bound, the bound itself
(``bound_rot_deg``, ``bound_trans_mm``: the norms of the per-axis Cramer-Rao standard deviations; ``bound``: of
which data, ``planes`` or, where the solver's refinement used the board's edges, ``edges``: the planes with every
ring or segment end on the board's outline, the simulator's beams exact), the squared Mahalanobis distance under the
solver's covariance (when it gives one), for 2D whether the estimate is the minimum that refinement from the truth
reaches (``hit``), the time, and a failure reason.
Trials are seeded from ``(seed, cell, trial)``, so the same spec gives the same rows on any scheduler.
"""
from __future__ import annotations

import csv
import io
import itertools
import os
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

from ..errors import DatasetError
from ..io.output import write_atomic, write_json_atomic
from ..simulation.simulator import LAYOUT_FAMILIES
from .figures import new_figure, png_bytes

SOLVERS_3D = ("closed-form", "factor-graph")
SOLVERS_2D = ("minimal-min-residual", "minimal-lower-bound", "minimal-lower-bound-no-extent")
AXES = ("rot_x", "rot_y", "rot_z", "trans_x", "trans_y", "trans_z")


@dataclass(frozen=True)
class StudySpec:
    name: str
    lidar: str
    model: str
    solvers: tuple[str, ...]
    layouts: tuple[str, ...]
    frames: tuple[int, ...]
    range_noise_m: tuple[float, ...]
    corner_noise_px: tuple[float, ...]
    trials: int
    seed: int
    mode: str
    rig: str = "default"  # 2D: the simulator configuration (simulation.simulator.RIGS_2D)

    @property
    def cells(self) -> list[tuple[str, int, float, float]]:
        return list(itertools.product(self.layouts, self.frames, self.range_noise_m, self.corner_noise_px))

    @property
    def n_trials(self) -> int:
        return len(self.cells) * self.trials


# The spec's keys; any other is a typo that would silently run the defaults.
SPEC_KEYS = ("name", "lidar", "model", "solvers", "layouts", "frames", "range_noise_m", "corner_noise_px", "trials",
             "seed", "mode", "rig")
# The noise levels a simulated calibration may be drawn at: what a camera's corners and a LiDAR's ranges can be
# (px, m; as the CLI's --corner-noise and --range-noise take them), from which its information stays finite.
CORNER_NOISE_PX = (1e-3, 20.0)
RANGE_NOISE_M = (1e-4, 1.0)
# The most board poses per calibration, and the most trials a study holds (each is a simulated calibration: a
# larger count is a typo, and its list of trials alone would fill the memory).
MAX_FRAMES, MAX_TRIALS = 1000, 1_000_000
_FORMAT = "see the SPEC.yaml format in docs/howto/studies.md"


def _number(x, whole: bool, key: str, source: str, lo: float, hi: float):
    """One value of ``key``: a number (a whole one with ``whole``) from ``lo`` to ``hi``."""
    kind = "a whole number" if whole else "a number"
    try:
        if isinstance(x, bool) or not isinstance(x, (int, float, str)):
            raise TypeError
        v = x if isinstance(x, int) else float(x)  # a whole number as it is: a seed beyond 2^53 kept exact
        if whole and not (np.isfinite(v) and v == int(v)):
            raise ValueError
    except (TypeError, ValueError, OverflowError):
        raise DatasetError(f"{key} must be {kind}, got {x!r}", path=source, hint=_FORMAT) from None
    if not lo <= v <= hi:
        bounds = f"of at least {lo:g}" if hi == np.inf else f"from {lo:g} to {hi:g}" if not whole else \
            f"from {int(lo)} to {int(hi)}"
        raise DatasetError(f"{key} must be {kind} {bounds}, got {x!r}", path=source, hint=_FORMAT)
    return int(v) if whole else v


def _list(v, whole: bool, key: str, source: str, lo: float, hi: float) -> tuple:
    values = v if isinstance(v, (list, tuple)) else [v]
    out = tuple(_number(x, whole, key, source, lo, hi) for x in values)
    if not out:
        raise DatasetError(f"{key} is empty", path=source, hint="give at least one value")
    return out


def parse_spec(spec: dict, source: str = "spec") -> StudySpec:
    """Validate a parsed ``SPEC.yaml`` for :func:`run_study`.

    Parameters
    ----------
    spec : dict
        The spec (see the how-to on studies for its keys).
    source : str
        Its name in error messages.

    Returns
    -------
    StudySpec

    Raises
    ------
    DatasetError
        A missing or bad key, named with what to write.
    """
    if not isinstance(spec, dict):
        raise DatasetError("a study spec must be a mapping", path=source, hint=_FORMAT)
    unknown = [str(k) for k in spec if k not in SPEC_KEYS]
    if unknown:
        raise DatasetError(f"unknown key(s) {unknown}", path=source, hint=f"use some of {list(SPEC_KEYS)}")
    lidar = str(spec.get("lidar", "3d")).lower()
    if lidar not in ("3d", "2d"):
        raise DatasetError(f"lidar must be 3d or 2d, got {lidar!r}", path=source, hint="set lidar: 3d or lidar: 2d")
    allowed = SOLVERS_2D if lidar == "2d" else SOLVERS_3D
    raw_solvers = spec.get("solvers", allowed)
    solvers = tuple(str(v) for v in (raw_solvers if isinstance(raw_solvers, (list, tuple)) else [raw_solvers]))
    bad = [s for s in solvers if s not in allowed]
    if bad or not solvers:
        raise DatasetError(f"unknown solver(s) {bad} for lidar {lidar}", path=source,
                           hint=f"use some of {list(allowed)}")
    model = str(spec.get("model", "hdl64e"))
    if lidar == "3d" and model not in ("hdl64e", "vlp16"):
        raise DatasetError(f"unknown model {model!r}", path=source, hint="use hdl64e or vlp16")
    mode = str(spec.get("mode", "measurement"))
    if mode not in ("measurement", "end-to-end"):
        raise DatasetError(f"mode must be measurement or end-to-end, got {mode!r}", path=source,
                           hint="measurement draws noise from the model; end-to-end renders images and scans")
    raw = spec.get("layouts", ["spread"])
    layouts = tuple(str(v) for v in (raw if isinstance(raw, (list, tuple)) else [raw]))
    bad = [v for v in layouts if v not in LAYOUT_FAMILIES]
    if bad or not layouts:
        raise DatasetError(f"unknown layout(s) {bad}", path=source, hint=f"use some of {list(LAYOUT_FAMILIES)}")
    frames = _list(spec.get("frames", [8]), True, "frames", source, 3, MAX_FRAMES)
    trials = _number(spec.get("trials", 10), True, "trials", source, 1, MAX_TRIALS)
    rig = str(spec.get("rig", "default"))
    if rig not in ("default", "varied") or (rig == "varied" and lidar != "2d"):
        raise DatasetError(f"rig must be default or varied (varied: 2d only), got {rig!r}", path=source,
                           hint="set rig: default, or rig: varied with lidar: 2d")
    default_noise = 0.01 if lidar == "2d" else 0.02
    range_noise = _list(spec.get("range_noise_m", [default_noise]), False, "range_noise_m", source, *RANGE_NOISE_M)
    corner_noise = _list(spec.get("corner_noise_px", [0.2]), False, "corner_noise_px", source, *CORNER_NOISE_PX)
    if len(layouts) * len(frames) * len(range_noise) * len(corner_noise) * trials > MAX_TRIALS:
        raise DatasetError(f"the spec holds more than {MAX_TRIALS} trials", path=source,
                           hint="give fewer values or trials, and run the study in parts with different seeds")
    return StudySpec(name=str(spec.get("name", "study")), lidar=lidar, model="2d" if lidar == "2d" else model,
                     solvers=solvers, layouts=layouts, frames=frames, range_noise_m=range_noise,
                     corner_noise_px=corner_noise, trials=trials,
                     seed=_number(spec.get("seed", 0), True, "seed", source, 0, np.inf), mode=mode, rig=rig)


def trial_arguments(spec: StudySpec) -> list[tuple]:
    """One argument tuple per trial, in a fixed order, each with its own seed from (seed, cell, trial)."""
    args = []
    for c, (family, n, noise, corner) in enumerate(spec.cells):
        for k in range(spec.trials):
            seed = int(np.random.SeedSequence([spec.seed, c, k]).generate_state(1)[0])
            args.append((spec, c, k, seed, family, n, noise, corner))
    return args


def run_trial(args: tuple) -> list[dict]:
    """Simulate one calibration and score every solver of the spec on it (rows of ``study.csv``)."""
    from geometry.rotations import T_inverse, T_log

    from ..calibration import solve
    from ..io.dataset import load_dataset
    from ..lidar.board_segmentation import SegmentationParams
    from ..pipeline.measurement import measure_frames
    from ..simulation.simulator import default_rig, rig_2d, sample_layout, simulate_frames, write_dataset
    from ..solvers.observation_model import Layout, cramer_rao_bound, simulate_measurements
    from ..solvers.refinement import refine
    from ..solvers.refinement_options import RefinementOptions, measurement_model_options
    from ..solvers.solution_selection import solution_distances

    spec, cell, k, seed, family, n, noise, corner = args
    rng = np.random.default_rng(seed)
    rig = rig_2d(spec.rig, rng, noise) if spec.lidar == "2d" else default_rig(rng, spec.model, noise)
    poses = sample_layout(rig, family, n, rng)
    layout = Layout(rig.camera, rig.board, rig.beams, rig.T_camera_lidar, tuple(poses), corner, noise)
    bounds = {"planes": np.sqrt(np.diag(cramer_rao_bound(layout)))}

    def bound_of(result) -> str:
        """Which bound a solver's error is read against: the one of the data it used (its refinement's edges)."""
        edges = result.refinement.edges if result.refinement is not None else None
        if not (edges or {}).get("used"):
            return "planes"
        if "edges" not in bounds:
            try:  # the simulator's beams are exact: no footprint beyond the azimuth step
                bounds["edges"] = np.sqrt(np.diag(cramer_rao_bound(layout, edges=True, beam_sd_rad=0.0)))
            except (ValueError, np.linalg.LinAlgError):
                bounds["edges"] = None
        return "planes" if bounds["edges"] is None else "edges"

    base = {"cell": cell, "trial": k, "seed": seed, "lidar": spec.lidar, "layout": family, "frames": n,
            "range_noise_m": noise, "corner_noise_px": corner, "mode": spec.mode, "bound": "planes",
            "bound_rot_deg": float(np.degrees(np.linalg.norm(bounds["planes"][:3]))),
            "bound_trans_mm": float(1000 * np.linalg.norm(bounds["planes"][3:]))}
    options = measurement_model_options() if spec.mode == "measurement" else RefinementOptions()
    camera = rig.camera
    if spec.mode == "measurement":
        frames = simulate_measurements(layout, rng)
    else:
        # Rendered images and full sweeps, measured once: every solver starts from the same measured frames.
        with tempfile.TemporaryDirectory() as tmp:
            ds = load_dataset(write_dataset(Path(tmp) / "ds", rig, simulate_frames(rig, n, rng, poses=poses)))
            try:
                camera, frames, _ = measure_frames(ds, np.random.default_rng(seed), SegmentationParams(), {},
                                                   workers=1)
            except Exception as exc:  # a failed measurement fails every solver of the trial, with its reason
                reason = f"{type(exc).__name__}: {getattr(exc, 'message', str(exc))}"[:200]
                return [dict(base, solver=s, ok=0, reason=reason, seconds=0.0) for s in spec.solvers]
    truth_basin = None
    rows = []
    for solver in spec.solvers:
        row = dict(base, solver=solver)
        t0 = time.perf_counter()
        try:
            if spec.lidar == "2d":
                init = solver.replace("-no-extent", "")
                extent = False if solver.endswith("-no-extent") else None
                result = solve(frames, rig.board, camera, init=init, options=options, use_extent=extent)
            else:
                refine_mode = "none" if solver == "closed-form" else "factor-graph"
                result = solve(frames, rig.board, camera, refine=refine_mode, options=options)
            T = result.T_camera_lidar
            xi = T_log(T_inverse(T) @ rig.T_camera_lidar)
            kind = bound_of(result)
            bound = bounds[kind]
            row.update({"ok": 1, "reason": "", "frames_used": result.frames_used,
                        "rot_err_deg": float(np.degrees(np.linalg.norm(xi[:3]))),
                        "trans_err_mm": float(1000 * np.linalg.norm(xi[3:])), "bound": kind,
                        "bound_rot_deg": float(np.degrees(np.linalg.norm(bound[:3]))),
                        "bound_trans_mm": float(1000 * np.linalg.norm(bound[3:]))})
            for a, v, b in zip(AXES, xi, bound):
                row[f"err_{a}"] = float(v)
                row[f"err_over_bound_{a}"] = float(abs(v) / b)
            cov = result.covariance
            row["d2"] = float(xi @ np.linalg.solve(cov, xi)) if cov is not None else float("nan")
            if spec.lidar == "2d":
                if truth_basin is None:
                    used = [f for f in frames if f.usable]
                    truth_basin = refine(used, rig.board, camera, rig.T_camera_lidar, options).T_camera_lidar
                row["hit"] = int(solution_distances(np.array([T, truth_basin]))[0] < 0.05)
                row["ambiguous"] = int(bool(result.alternatives))
        except Exception as exc:  # a failed calibration is a result of the study, recorded with its reason
            row.update({"ok": 0, "reason": f"{type(exc).__name__}: {getattr(exc, 'message', str(exc))}"[:200]})
        row["seconds"] = time.perf_counter() - t0
        rows.append(row)
    return rows


COLUMNS = ("cell", "trial", "seed", "lidar", "mode", "layout", "frames", "range_noise_m", "corner_noise_px", "solver",
           "ok", "reason", "frames_used", "rot_err_deg", "trans_err_mm", "bound", "bound_rot_deg", "bound_trans_mm",
           *[f"err_{a}" for a in AXES],
           *[f"err_over_bound_{a}" for a in AXES], "d2", "hit", "ambiguous", "seconds")


def run_study(spec: StudySpec, out: str | Path, workers: int | None = None, scheduler: str | None = None,
              progress: bool = True) -> list[dict]:
    """Run every trial of a study spec and write its table and figures.

    Every solver of a trial sees the same simulated data; the rows are the same on local processes and on a
    cluster.

    Parameters
    ----------
    spec : StudySpec
        From :func:`parse_spec`.
    out : str or Path
        Folder for ``study.csv``, ``summary.json`` and the summary plots (each written atomically).
    workers : int, optional
        Local processes (default: every core; 1 runs the trials in this process).
    scheduler : str or distributed.Client, optional
        A Dask scheduler (``tcp://host:port``) to run the trials on instead.
    progress : bool
        Show a progress bar.

    Returns
    -------
    list of dict
        One row per trial and solver, as in ``study.csv``.

    Examples
    --------
    >>> rows = lc.run_study(lc.parse_spec({"lidar": "3d", "solvers": ["closed-form", "factor-graph"],
    ...                                    "frames": [4, 8], "trials": 10}), "/tmp/study")  # doctest: +SKIP
    """
    args = trial_arguments(spec)
    results: list[list[dict]] = []
    bar = tqdm(total=len(args), desc=spec.name, disable=not progress)
    if scheduler is None and workers == 1:  # in this process: no pool to start (a notebook's quick run, a debugger)
        for a in args:
            results.append(run_trial(a))
            bar.update()
    elif scheduler is None:
        with ProcessPoolExecutor(max_workers=workers or os.cpu_count() or 1) as pool:
            for rows in pool.map(run_trial, args, chunksize=max(1, len(args) // (8 * (workers or 2)))):
                results.append(rows)
                bar.update()
    else:
        from distributed import Client, as_completed

        client = scheduler if isinstance(scheduler, Client) else Client(scheduler)
        try:
            futures = client.map(run_trial, args, pure=False)
            index = {f.key: i for i, f in enumerate(futures)}
            slots: list = [None] * len(args)
            for fut in as_completed(futures):
                slots[index[fut.key]] = fut.result()
                bar.update()
            results = slots
        finally:
            if not isinstance(scheduler, Client):
                client.close()
    bar.close()
    rows = [r for rs in results for r in rs]
    write_outputs(spec, rows, Path(out))
    return rows


def summarize(rows: list[dict]) -> list[dict]:
    """Per (solver, layout, frames, range noise, corner noise): trials, failures, RMS errors, the RMS of the
    bound's norms, median error over the bound, mean d2, hit rate (2D), mean time."""
    groups: dict = {}
    for r in rows:
        key = (r["solver"], r.get("layout", "spread"), r["frames"], r["range_noise_m"], r["corner_noise_px"])
        groups.setdefault(key, []).append(r)
    out = []
    for (solver, family, n, noise, corner), g in sorted(groups.items()):
        ok = [r for r in g if r["ok"]]
        s = {"solver": solver, "layout": family, "frames": n, "range_noise_m": noise, "corner_noise_px": corner,
             "trials": len(g), "failed": len(g) - len(ok), "mean_seconds": float(np.mean([r["seconds"] for r in g]))}
        if "bound_rot_deg" in g[0]:
            s["rms_bound_rot_deg"] = float(np.sqrt(np.mean([r["bound_rot_deg"] ** 2 for r in g])))
            s["rms_bound_trans_mm"] = float(np.sqrt(np.mean([r["bound_trans_mm"] ** 2 for r in g])))
        if ok:
            s["rms_rot_err_deg"] = float(np.sqrt(np.mean([r["rot_err_deg"] ** 2 for r in ok])))
            s["rms_trans_err_mm"] = float(np.sqrt(np.mean([r["trans_err_mm"] ** 2 for r in ok])))
            s["median_err_over_bound"] = float(np.median([[r[f"err_over_bound_{a}"] for a in AXES] for r in ok]))
            d2 = [r["d2"] for r in ok if np.isfinite(r.get("d2", np.nan))]
            s["mean_d2"] = float(np.mean(d2)) if d2 else None
            if "hit" in ok[0]:
                s["hit_rate"] = float(np.mean([r["hit"] for r in ok]))
        out.append(s)
    return out


def write_outputs(spec: StudySpec, rows: list[dict], out: Path) -> None:
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=list(COLUMNS), extrasaction="ignore")
    writer.writeheader()
    for r in rows:
        writer.writerow({c: r.get(c, "") for c in COLUMNS})
    write_atomic(out / "study.csv", lambda fh: fh.write(buf.getvalue()))
    summary = summarize(rows)
    write_json_atomic(out / "summary.json", {"spec": spec.__dict__ | {"solvers": list(spec.solvers)},
                                             "rows": len(rows), "summary": summary})
    for name, png in summary_plots(spec, summary):
        write_atomic(out / name, lambda fh, png=png: fh.write(png), mode="wb")


def _layout_figure(spec: StudySpec, summary: list[dict], frames0: int, noise0: float, corner0: float):
    """RMS errors of each solver per layout family, beside the family's bound (RMS of its norms)."""
    fig, ax = new_figure(1, 2, figsize=(10, 3.6))
    x = np.arange(len(spec.layouts))
    width = 0.8 / (len(spec.solvers) + 1)
    pick = {(s["solver"], s["layout"]): s for s in summary
            if s["frames"] == frames0 and s["range_noise_m"] == noise0 and s["corner_noise_px"] == corner0}
    for a, (key, bkey, label) in zip(ax, [("rms_rot_err_deg", "rms_bound_rot_deg", "RMS rotation error [deg]"),
                                          ("rms_trans_err_mm", "rms_bound_trans_mm", "RMS translation error [mm]")]):
        first = [pick.get((spec.solvers[0], f), {}) for f in spec.layouts]
        a.bar(x, [s.get(bkey, np.nan) for s in first], width, color="0.7", label="Cramer-Rao bound")
        for i, solver in enumerate(spec.solvers):
            a.bar(x + (i + 1) * width, [pick.get((solver, f), {}).get(key, np.nan) for f in spec.layouts], width,
                  label=solver)
        a.set_xticks(x + width * len(spec.solvers) / 2, spec.layouts)
        a.set(ylabel=label, yscale="log", title=f"{frames0} frames, range noise {1000 * noise0:.0f} mm")
    ax[0].legend(fontsize=8)
    return fig


def summary_plots(spec: StudySpec, summary: list[dict]) -> list[tuple[str, bytes]]:
    """Errors per layout family (when there are several), error against frames and against range noise (first
    layout), hit rate (2D), time: one PNG each."""
    figures = []
    noise0, corner0, layout0 = spec.range_noise_m[0], spec.corner_noise_px[0], spec.layouts[0]
    frames0 = spec.frames[len(spec.frames) // 2]
    if len(spec.layouts) > 1:
        figures.append(("errors_vs_layout.png", png_bytes(_layout_figure(spec, summary, frames0, noise0, corner0))))
        summary = [s for s in summary if s["layout"] == layout0]
    panels = [("errors_vs_frames.png", "frames",
               lambda s: s["range_noise_m"] == noise0 and s["corner_noise_px"] == corner0,
               f"{layout0}, range noise {1000 * noise0:.0f} mm"),
              ("errors_vs_noise.png", "range_noise_m",
               lambda s: s["frames"] == frames0 and s["corner_noise_px"] == corner0,
               f"{layout0}, {frames0} frames")]
    for name, xkey, sel, title in panels:
        fig, ax = new_figure(1, 2, figsize=(10, 3.6))
        for solver in spec.solvers:
            pts = sorted((s[xkey], s.get("rms_rot_err_deg", np.nan), s.get("rms_trans_err_mm", np.nan))
                         for s in summary if s["solver"] == solver and sel(s))
            if pts:
                x, rot, tr = map(np.array, zip(*pts))
                ax[0].plot(x, rot, "o-", label=solver)
                ax[1].plot(x, tr, "o-", label=solver)
        ax[0].set(xlabel=xkey, ylabel="RMS rotation error [deg]", title=title, yscale="log")
        ax[1].set(xlabel=xkey, ylabel="RMS translation error [mm]", title=title, yscale="log")
        ax[0].legend(fontsize=8)
        figures.append((name, png_bytes(fig)))

    def by_frames(ax, value) -> None:
        """One line per solver of ``value(summary row)`` against frames, at the first noise levels."""
        for solver in spec.solvers:
            pts = sorted((s["frames"], value(s)) for s in summary
                         if s["solver"] == solver and s["range_noise_m"] == noise0 and s["corner_noise_px"] == corner0)
            if pts:
                ax.plot(*zip(*pts), "o-", label=solver)
        ax.legend(fontsize=8)

    if spec.lidar == "2d":
        fig, ax = new_figure(figsize=(5, 3.6))
        by_frames(ax, lambda s: 100 * s.get("hit_rate", np.nan))
        ax.set(xlabel="frames", ylabel="true-solution hit rate [%]")
        figures.append(("hit_rate.png", png_bytes(fig)))
    fig, ax = new_figure(figsize=(5, 3.6))
    by_frames(ax, lambda s: s["mean_seconds"])
    ax.set(xlabel="frames", ylabel="mean time per calibration [s]")
    figures.append(("time.png", png_bytes(fig)))
    return figures


def format_summary(summary: list[dict]) -> str:
    lines = [f"  {'solver':32s}{'layout':>10s}{'frames':>7s}{'noise mm':>9s}{'corner px':>10s}{'trials':>7s}"
             f"{'failed':>7s}{'rot deg':>9s}{'trans mm':>9s}{'err/bound':>10s}{'d2':>9s}{'hit %':>7s}{'s':>7s}"]
    for s in summary:
        hit = f"{100 * s['hit_rate']:7.1f}" if "hit_rate" in s else f"{'':>7s}"
        d2 = f"{s['mean_d2']:9.3g}" if s.get("mean_d2") is not None else f"{'-':>9s}"
        lines.append(f"  {s['solver']:32s}{s.get('layout', 'spread'):>10s}{s['frames']:7d}"
                     f"{1000 * s['range_noise_m']:9.1f}{s['corner_noise_px']:10.2f}"
                     f"{s['trials']:7d}{s['failed']:7d}{s.get('rms_rot_err_deg', np.nan):9.3f}"
                     f"{s.get('rms_trans_err_mm', np.nan):9.2f}{s.get('median_err_over_bound', np.nan):10.2f}{d2}"
                     f"{hit}{s['mean_seconds']:7.3f}")
    return "\n".join(lines)
