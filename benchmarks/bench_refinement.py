"""Refinement against the Cramer-Rao bound (make bench).

(a) Measurement level: one fixed 8-frame layout, corner pixels and beam ranges drawn from exactly the
    Gaussian model the bound assumes; both noise levels are estimated from the data, as in use. The engine
    (``calibrate`` on the frames as measured, its joint graph's covariance) on the planes alone against the
    planes' bound, and as it runs by default (the board's edges in, where the board's size is known) against the
    bound with the edges.
(b) End to end: the same layout rendered and ray-cast anew for every draw, then the whole pipeline as
    ``calibrate`` runs it (corner detection, board segmentation, closed form, the engine's joint graph with its
    default noise model, its posterior's covariance).
    The bound uses the detector's effective pixel noise, estimated from the spread of the PnP board
    poses against the truth (larger than the per-corner scatter: corner errors correlate in a board).
(c) Time of the engine's solve alone (``calibrate`` from measured frames, no posterior): 16 frames with 20k board
    points each.
(d) The effective corner noise over varied layouts (8 boards sampled anew for every draw, rendered and
    calibrated end to end): over the board's plane, against the corner residual, which is the pipeline's
    CORNER_ERROR_CORRELATION, with a bootstrap interval over the draws, and the truth's mean d2. The ratio in (b)
    comes from one layout's 8 poses, whose rendering errors repeat from draw to draw.

Ratios are RMS error over the bound's RMS (sqrt of the trace of its rotation or translation block);
d2 is the mean squared Mahalanobis distance of the truth under the reported covariance (6 is ideal).

Usage: python benchmarks/bench_refinement.py [--draws-a 400] [--draws-b 30] [--draws-d 80] [--workers 2]
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

# As the CLI does: single-threaded OpenBLAS (the pipeline parallelises itself; OpenBLAS's threads keep
# spinning after large products and slow the small-matrix work that follows).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from estimators.calibration import solve  # noqa: E402
from estimators.io.dataset import load_dataset  # noqa: E402
from estimators.io.measurement_store import Measurements  # noqa: E402
from estimators.measurements import FrameMeasurement, observe_lidar_board  # noqa: E402
from estimators.simulation.simulator import (  # noqa: E402
    default_rig,
    sample_board_poses,
    sample_layout,
    simulate_frames,
    write_dataset,
)
from estimators.solvers.board_edges import BEAM_SD_RAD  # noqa: E402
from estimators.solvers.closed_form import solve_closed_form  # noqa: E402
from estimators.solvers.factors import corner_residuals  # noqa: E402
from estimators.solvers.observation_model import Layout, cramer_rao_bound, simulate_measurements  # noqa: E402
from estimators.solvers.noise_levels import corner_residual_px  # noqa: E402
from estimators.solvers.refinement_options import CORNER_ERROR_CORRELATION, measurement_model_options  # noqa: E402
from estimators.rig_calibration import calibrate  # noqa: E402
from geometry.rotations import T_from_Rt, T_inverse, T_log, transform_points  # noqa: E402

LAYOUT_SEED = 3
CORNER_NOISE_PX = 0.2
RANGE_NOISE_M = 0.02


def fixed_layout(n: int = 8, seed: int = LAYOUT_SEED, corner_noise_px: float = CORNER_NOISE_PX):
    rng = np.random.default_rng(seed)
    rig = default_rig(rng, "hdl64e", RANGE_NOISE_M)
    poses = sample_board_poses(rig, n, rng)
    return rig, Layout(rig.camera, rig.board, rig.beams, rig.T_camera_lidar, tuple(poses), corner_noise_px,
                       RANGE_NOISE_M)


def _xi(T_hat, T_true):
    return T_log(T_inverse(T_hat) @ T_true)


def _trial_a(args):
    """One draw: the closed form, the factor graph on the planes alone, and the default (the board's edges in)."""
    seed, layout = args
    rng = np.random.default_rng(seed)
    # each beam off its nominal direction by the edge model's footprint, each sweep fired at a random azimuth phase,
    # as real beams are (exact beams would leave the edges' model, which assumes the footprint, conservative)
    frames = simulate_measurements(layout, rng, azimuth_phase=True, beam_sd_rad=BEAM_SD_RAD)
    cf = solve_closed_form([f.camera.plane for f in frames], [f.lidar.plane for f in frames]).T_camera_lidar
    out = [_xi(cf, layout.T_camera_lidar)]
    measured = Measurements(layout.camera, layout.board, "3d", tuple(frames))
    for edges in (False, None):  # the engine from the frames as measured (calibrate), its graph's covariance
        res = calibrate(measured, options=measurement_model_options(edges=edges), samples=0)
        xi = _xi(res.T_camera_lidar, layout.T_camera_lidar)
        out += [xi, float(xi @ np.linalg.solve(res.covariance, xi))]
    return tuple(out)


def _board_flip(board) -> np.ndarray:
    """The board's symmetry: a half turn about its normal through its centre (a plain checkerboard)."""
    c = board.centre
    return T_from_Rt(np.diag([-1.0, -1.0, 1.0]), np.array([2 * c[0], 2 * c[1], 0.0]))


def _trial_b(args):
    seed, rig, poses = args
    rng = np.random.default_rng(seed)
    with tempfile.TemporaryDirectory() as tmp:
        frames = simulate_frames(rig, len(poses), rng, poses=poses)
        ds = load_dataset(write_dataset(Path(tmp) / "ds", rig, frames))
        res = calibrate(ds, rng=np.random.default_rng(seed))  # the engine, with its posterior, as users run it
    used = [f for f in res.frames if f.usable]
    camera = res.cameras["cam0"]
    cf = solve(list(res.frames), rig.board, camera, refine="none").T_camera_lidar
    # PnP board-pose errors against the truth, in units of the unit-noise covariance (J^T J)^-1: over the
    # whole pose (6 dof) and over its plane (rotation about the board's x and y, translation along its
    # normal: 3 dof, the part the LiDAR planes see).
    pose_terms, plane_terms, flip = [], [], _board_flip(rig.board)
    truth = {f.name: f.T_camera_board for f in frames}
    plane = [0, 1, 5]
    for f in used:
        T_true = truth[f.name]
        xi = min((_xi(f.camera.T_camera_board, T) for T in (T_true, T_true @ flip)), key=np.linalg.norm)
        _, J = corner_residuals(T_true, rig.board.inner_corners(), f.camera.corners_px, rig.camera)
        pose_terms.append(float(xi @ (J.T @ J) @ xi))
        C = np.linalg.inv(J.T @ J)[np.ix_(plane, plane)]
        plane_terms.append(float(xi[plane] @ np.linalg.solve(C, xi[plane])))
    xi = _xi(res.T_camera_lidar, rig.T_camera_lidar)
    model = res.range_models.get("lidar0", {}).get("model", "none")
    return (_xi(cf, rig.T_camera_lidar), xi, float(xi @ np.linalg.solve(res.covariance, xi)), pose_terms,
            corner_residual_px(used, rig.board, rig.camera), len(used), plane_terms, res.covariance, model)


def _row(method, errors, d2, bound_name, bounds):
    """A method's RMS errors over its bound's (``bounds[bound_name]``) and its mean d2 (None: no covariance)."""
    crb = bounds[bound_name]
    rms = lambda e: np.sqrt(np.mean(np.sum(e**2, axis=1)))  # noqa: E731
    return (method, bound_name, rms(errors[:, :3]) / np.sqrt(np.trace(crb[:3, :3])),
            rms(errors[:, 3:]) / np.sqrt(np.trace(crb[3:, 3:])), None if d2 is None else float(np.mean(d2)))


def _print_table(title, rows, target, bounds, draws):
    """Each method against the bound of the information it uses: the planes' (corners and board planes), or the
    planes' with the board's edges (every ring end on the board's outline: ``cramer_rao_bound(edges=True)``), which
    the default refinement takes where the board's size is known."""
    print(title)
    for name, crb in bounds.items():
        print(f"  bound, {name}: rotation {np.degrees(np.sqrt(np.trace(crb[:3, :3]))):.4f} deg, translation "
              f"{1000 * np.sqrt(np.trace(crb[3:, 3:])):.2f} mm (RMS over the 3 axes)")
    print(f"  {draws} draws")
    print(f"  {'method':24s}{'against':>9s}{'rot RMS/CRB':>13s}{'trans RMS/CRB':>15s}{'mean d2':>10s}   target")
    for method, against, r, t, d2 in rows:
        d2s = f"{d2:10.2f}" if d2 is not None else f"{'-':>10s}"
        if d2 is None:
            verdict = ""
        else:
            ok = max(r, t) <= target and 5.0 <= d2 <= 7.0
            verdict = f"ratios <= {target}, 5 <= d2 <= 7: {'met' if ok else 'NOT met'}"
        print(f"  {method:24s}{against:>9s}{r:13.3f}{t:15.3f}{d2s}   {verdict}")
    print()


def table_a(draws: int, workers: int) -> None:
    _, layout = fixed_layout()
    seeds = np.random.SeedSequence(1000).generate_state(draws)
    with ProcessPoolExecutor(workers) as pool:
        out = list(pool.map(_trial_a, [(int(s), layout) for s in seeds]))
    cf, planes, d2_planes, edged, d2_edged = (np.array([o[k] for o in out]) for k in range(5))
    bounds = {"planes": cramer_rao_bound(layout), "edges": cramer_rao_bound(layout, edges=True)}
    _print_table(f"(a) measurement level: 8 frames, corners {CORNER_NOISE_PX} px, ranges {100 * RANGE_NOISE_M:.0f} cm",
                 [_row("closed form", cf, None, "planes", bounds),
                  _row("factor graph, planes", planes, d2_planes, "planes", bounds),
                  _row("factor graph (default)", edged, d2_edged, "edges", bounds)], 1.05, bounds, draws)


def table_b(draws: int, workers: int) -> None:
    rig, layout = fixed_layout()
    seeds = np.random.SeedSequence(2000).generate_state(draws)
    with ProcessPoolExecutor(workers) as pool:
        out = list(pool.map(_trial_b, [(int(s), rig, list(layout.T_camera_board)) for s in seeds]))
    cf, ref, d2 = (np.array([o[k] for o in out]) for k in range(3))
    terms = np.concatenate([o[3] for o in out])
    sigma_eff = float(np.sqrt(np.mean(terms) / 6))
    resid = float(np.mean([o[4] for o in out]))
    used = sum(o[5] for o in out)
    effective = Layout(layout.camera, layout.board, layout.beams, layout.T_camera_lidar, layout.T_camera_board,
                       sigma_eff, RANGE_NOISE_M)
    # the ray-cast beams blur the board's edges by the edge model's footprint (as bench_board_edges bounds them)
    bounds = {"planes": cramer_rao_bound(effective), "edges": cramer_rao_bound(effective, edges=True)}
    sigma_plane = float(np.sqrt(np.mean(np.concatenate([o[6] for o in out])) / 3))
    print(f"effective corner noise from {len(terms)} PnP board poses against the truth: whole pose {sigma_eff:.3f} px, "
          f"board plane {sigma_plane:.3f} px; corner residual {resid:.3f} px; ratios {sigma_eff / resid:.2f} (pose), "
          f"{sigma_plane / resid:.2f} (plane; this layout's 8 poses, see (d)); boards used {used} of "
          f"{8 * draws}")
    _print_table("(b) end to end from rendered images and ray-cast sweeps (8 frames, HDL-64E, 2 cm)",
                 [_row("closed form", cf, None, "planes", bounds),
                  _row("factor graph (default)", ref, d2, "edges", bounds)], 1.1, bounds, draws)
    # One layout drawn again and again: what its errors share (a bias fixed by the layout) against what varies.
    C = np.mean([o[7] for o in out], axis=0)
    m = ref.mean(axis=0)
    models = [o[8] for o in out]
    print("  the draws' mean error over the mean reported sd (rot x y z, trans x y z): "
          + " ".join(f"{v:+.2f}" for v in m / np.sqrt(np.diag(C))) + f" (d2 {float(m @ np.linalg.solve(C, m)):.2f}); "
          "range models chosen: " + ", ".join(f"{k} {models.count(k)}" for k in sorted(set(models))))
    plain = [k for k, o in enumerate(out) if o[8] == "none"]
    if 0 < len(plain) < len(out):
        print(f"  the {len(plain)} draws without range terms: mean d2 {np.mean(d2[plain]):.2f}")


def _trial_d(seed: int):
    rng = np.random.default_rng(seed)
    rig = default_rig(rng, "hdl64e", RANGE_NOISE_M)
    return _trial_b((seed, rig, sample_layout(rig, "spread", 8, rng)))


def table_d(draws: int, workers: int) -> None:
    seeds = [int(s) for s in np.random.SeedSequence(5000).generate_state(draws)]
    with ProcessPoolExecutor(workers) as pool:
        out = list(pool.map(_trial_d, seeds))

    def ratio(idx):
        plane = np.concatenate([out[i][6] for i in idx])
        return float(np.sqrt(np.mean(plane) / 3) / np.mean([out[i][4] for i in idx]))

    every = np.arange(len(out))
    rng = np.random.default_rng(0)
    boot = [ratio(rng.integers(0, len(out), len(out))) for _ in range(1000)]
    pose = np.sqrt(np.mean(np.concatenate([o[3] for o in out])) / 6) / np.mean([o[4] for o in out])
    print(f"(d) effective corner noise over {draws} varied layouts (8 boards each, rendered, calibrated end to end)")
    print(f"  boards {sum(len(o[6]) for o in out)}; over the board plane / corner residual {ratio(every):.2f} (90% "
          f"bootstrap {np.percentile(boot, 5):.2f}-{np.percentile(boot, 95):.2f}; the pipeline's "
          f"CORNER_ERROR_CORRELATION {CORNER_ERROR_CORRELATION}); whole pose {pose:.2f}; truth's mean d2 "
          f"{np.mean([o[2] for o in out]):.2f} (6 ideal)")
    print()


def table_c(repeats: int = 20) -> None:
    rig, layout = fixed_layout(16, seed=4)
    rng = np.random.default_rng(5)
    frames = simulate_measurements(layout, rng)
    T_lc = T_inverse(layout.T_camera_lidar)
    dense = []
    for f, T_cb in zip(frames, layout.T_camera_board):
        uv = rng.uniform(0, 1, (20000, 2)) * rig.board.extent
        P = transform_points(T_lc @ T_cb, np.column_stack([uv, np.zeros(len(uv))]))
        beams = P / np.linalg.norm(P, axis=1, keepdims=True)
        dense.append(FrameMeasurement(f.name, f.camera,
                                      observe_lidar_board(P + beams * rng.normal(0, RANGE_NOISE_M, (len(P), 1)))))
    measured = Measurements(rig.camera, rig.board, "3d", tuple(dense))
    times = []
    for _ in range(repeats):  # the engine's whole solve from the measurements (closed form to covariance)
        t0 = time.perf_counter()
        calibrate(measured, samples=0)
        times.append(time.perf_counter() - t0)
    print("(c) the engine's solve, measurements already made, no posterior (target < 1 s)")
    print(f"  {'frames':>8s}{'points/board':>14s}{'median ms':>11s}{'min ms':>9s}")
    print(f"  {16:8d}{20000:14d}{1000 * np.median(times):11.1f}{1000 * np.min(times):9.1f}")
    print()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--draws-a", type=int, default=400)
    ap.add_argument("--draws-b", type=int, default=30)
    ap.add_argument("--draws-d", type=int, default=80)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--only", choices=["a", "b", "c", "d"], default=None, help="run one table")
    args = ap.parse_args()
    if args.only in (None, "c"):
        table_c()
    if args.only in (None, "a"):
        table_a(args.draws_a, args.workers)
    if args.only in (None, "b"):
        table_b(args.draws_b, args.workers)
    if args.only in (None, "d"):
        table_d(args.draws_d, args.workers)


if __name__ == "__main__":
    main()
