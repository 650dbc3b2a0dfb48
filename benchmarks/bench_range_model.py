"""LiDAR range model: systematic range errors estimated with the extrinsic, at the measurement level
(make bench; `python benchmarks/bench_range_model.py [--trials N] [--workers W]`).

Per trial: a rig (VLP-16, HDL-64E or OS1-64-like, 2 cm range noise, 0.2 px corners), 12 spread board poses, the
boards' returns. Rows, each refined with `auto` (the terms the data support):
- injected: a global offset of 3 cm, per-ring offsets drawn with sd 5 mm and 1 cm on the black squares; with the
  clouds' ring field and black/white intensity contrast, or with neither (rings clustered from the beams'
  elevations, the squares placed by geometry alone). Error against the Cramer-Rao bound of the model with these
  terms as nuisance parameters (their priors included), the mean squared Mahalanobis distance of the truth (6
  ideal), how often each injected term (the global offset, each ring's total offset, the black-square offset) is
  in the chosen model, and how often it lies in its 95% interval when it is.
- not injected: how often auto adds a term, and the RMS error against the solve without a model; with each board
  as the LiDAR sees it moved from the camera's by a 3 mm per-board plane error (a bent or held board: the
  overdispersion of recorded sets), where a test on the raw point noise reads that structure as a range offset.
- VLP-16 drawn from the priors (`velodyne`, 3 cm accuracy): every term drawn from the model's own prior, so that
  the intervals' coverage is their nominal 95% where the priors, not the data, set them.
The planes alone (no board edges, which the calibration adds by default where the board's size is given): the bound
is the planes' and the terms' (``observation_model.cramer_rao_bound`` has no edges with terms); the edges'
accuracy is bench_board_edges.py's.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

POSES = 12
NOISE_M = 0.02
CORNER_PX = 0.2
INJECT = dict(offset_m=0.03, ring_sd_m=0.005, dark_m=0.01)
BOARD_ERROR_M = 0.003


def _trial(args) -> dict:
    from estimators.lidar.lidar_models import RING_PRIOR_SHARE, range_accuracy_for
    from estimators.simulation.range_bias import RangeBias
    from estimators.simulation.simulator import default_rig, sample_board_poses
    from estimators.solvers.closed_form import solve_closed_form
    from estimators.solvers.observation_model import (Layout, cramer_rao_bound, layout_range_terms,
                                                      simulate_measurements)
    from estimators.solvers.refinement import refine
    from estimators.solvers.refinement_options import measurement_model_options
    from geometry.rotations import T_inverse, T_log, rotation_error

    lidar, inject, recorded, board_error, seed = args
    rng = np.random.default_rng(seed)
    rig = default_rig(rng, lidar, NOISE_M)
    layout = Layout(rig.camera, rig.board, rig.beams, rig.T_camera_lidar, tuple(sample_board_poses(rig, POSES, rng)),
                    CORNER_PX, NOISE_M)
    accuracy = None
    if inject == "prior":  # the terms drawn from the model's own priors for the sensor family
        accuracy = range_accuracy_for("velodyne")
        draw = np.random.default_rng([seed, 7])
        bias = RangeBias.drawn(draw, len(rig.beams.elevations_rad), float(draw.normal(0.0, accuracy)),
                               RING_PRIOR_SHARE * accuracy, float(draw.normal(0.0, accuracy)))
    else:
        bias = RangeBias.drawn(rng, len(rig.beams.elevations_rad), **INJECT) if inject else None
    rings, intensity = (True, "contrast") if recorded == "ring+contrast" else (False, "flat")
    frames = simulate_measurements(layout, np.random.default_rng(seed + 10**6), bias, board_error, rings, intensity)
    T0 = solve_closed_form([f.camera.plane for f in frames], [f.lidar.plane for f in frames]).T_camera_lidar
    out = {}
    for m in (["auto", "none"] if not inject else ["auto"]):
        t0 = time.perf_counter()
        ref = refine(frames, layout.board, layout.camera, T0,
                     measurement_model_options(range_model=m, range_accuracy_m=accuracy, edges=False))
        T = ref.T_camera_lidar
        xi = T_log(T_inverse(T) @ rig.T_camera_lidar)
        sd = np.sqrt(np.diag(ref.covariance))
        out[m] = {"rot": np.degrees(rotation_error(T[:3, :3], rig.T_camera_lidar[:3, :3])),
                  "trans": 1000 * np.linalg.norm(T[:3, 3] - rig.T_camera_lidar[:3, 3]),
                  "d2": float(xi @ np.linalg.solve(ref.covariance, xi)),
                  "max_trans_sigmas": float(np.max(np.abs(xi[3:]) / sd[3:])),
                  "chosen": ref.range_model.chosen if ref.range_model else "none",
                  "seconds": time.perf_counter() - t0}
        fit = ref.range_model
        if inject:
            crb = np.sqrt(np.diag(cramer_rao_bound(layout, layout_range_terms(layout, "full"))))
            out[m]["crb"] = (np.degrees(np.linalg.norm(crb[:3])), 1000 * np.linalg.norm(crb[3:]))
            names = fit.names if fit is not None else ()
            v, s = np.array(fit.values_m if fit else []), np.array(fit.std_m if fit else [])
            hits = {"offset": [bool(abs(v[0] - bias.offset_m) <= 1.96 * s[0])] if "offset" in names else [None]}
            hits["dark"] = ([bool(abs(v[names.index("dark")] - bias.dark_m) <= 1.96 * s[names.index("dark")])]
                            if "dark" in names else [None])
            if fit is not None and fit.terms is not None and fit.terms.rings:
                # Each ring's total offset (global + its own): what the data determine. Clustered rings are
                # numbered from the lowest beam up, the simulator's from the highest down.
                cov = fit.terms_covariance
                n_beams = len(rig.beams.elevations_rad)
                ring_hits = []
                for k, r in enumerate(fit.terms.rings):
                    g = np.zeros(len(v))
                    g[0], g[1 + k] = 1.0, 1.0
                    beam = r if recorded == "ring+contrast" else _beam_of(rig, frames, fit.labels, r, n_beams)
                    if beam is None:
                        continue
                    truth = bias.offset_m + bias.ring_offsets_m[beam]
                    ring_hits.append(bool(abs(g @ v - truth) <= 1.96 * np.sqrt(g @ cov @ g)))
                hits["ring totals"] = ring_hits
            else:
                hits["ring totals"] = [None]
            out[m]["hits"] = hits
    return out


def _beam_of(rig, frames, labels, cluster: int, n_beams: int) -> int | None:
    """The simulated beam whose elevation a clustered ring holds (the nearest beam to its points' elevation)."""
    el = []
    for f, r in zip([f for f in frames if f.usable], labels.rings):
        if r is None:
            continue
        P = f.lidar.points[r == cluster]
        el.extend(np.arctan2(P[:, 2], np.hypot(P[:, 0], P[:, 1])).tolist())
    if not el:
        return None
    return int(np.argmin(np.abs(rig.beams.elevations_rad - np.median(el))))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--trials", type=int, default=100)
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args()
    print(f"LiDAR range model, measurement level: {args.trials} trials per row, {POSES} poses, "
          f"{100 * NOISE_M:.0f} cm range noise, {CORNER_PX} px corners; `auto` in every row; the planes alone "
          "(--no-edges: the bound is the planes' and the terms')")
    head = (f"{'row':48s}{'rot/CRB':>8s}{'tr/CRB':>8s}{'d2':>6s}{'>4sd':>6s}{'offset in':>10s}{'rings in':>10s}"
            f"{'dark in':>10s}{'terms':>7s}{'err/none':>9s}")
    print(head)
    with ProcessPoolExecutor(args.workers) as pool:

        def share(rows, key):
            h = [v for x in rows for v in x["hits"].get(key, [])]
            held = [v for v in h if v is not None]
            if not held:
                return "-"
            return f"{100 * np.mean(held):.1f}%" + ("" if len(held) == len(h) else f"/{100 * len(held) / len(h):.0f}")

        def injected_row(lidar: str, inject, recorded: str, label: str) -> None:
            rows = [x["auto"] for x in pool.map(_trial, [(lidar, inject, recorded, 0.0, s)
                                                          for s in range(args.trials)])]
            e = np.array([[x["rot"], x["trans"]] for x in rows])
            c = np.array([x["crb"] for x in rows])
            ratio = np.sqrt(np.mean(e**2, axis=0)) / np.sqrt(np.mean(c**2, axis=0))
            beyond = np.mean([x["max_trans_sigmas"] > 4 for x in rows])
            print(f"{label:48s}{ratio[0]:8.2f}{ratio[1]:8.2f}{np.mean([x['d2'] for x in rows]):6.1f}"
                  f"{100 * beyond:5.0f}%{share(rows, 'offset'):>10s}{share(rows, 'ring totals'):>10s}"
                  f"{share(rows, 'dark'):>10s}{'':>7s}{'':>9s}")

        def clean_row(lidar: str, board_error: float, label: str) -> None:
            rows = list(pool.map(_trial, [(lidar, False, "ring+contrast", board_error, 10**5 + s)
                                          for s in range(args.trials)]))
            added = np.mean([x["auto"]["chosen"] != "none" for x in rows])
            ea = np.sqrt(np.mean([x["auto"]["trans"] ** 2 for x in rows]))
            en = np.sqrt(np.mean([x["none"]["trans"] ** 2 for x in rows]))
            beyond = np.mean([x["auto"]["max_trans_sigmas"] > 4 for x in rows])
            print(f"{label:48s}{'':8s}{'':8s}{np.mean([x['auto']['d2'] for x in rows]):6.1f}{100 * beyond:5.0f}%"
                  f"{'':>10s}{'':>10s}{'':>10s}{100 * added:6.1f}%{ea / en:9.3f}")

        for lidar in ("vlp16", "hdl64e", "os64"):
            injected_row(lidar, True, "ring+contrast", f"{lidar} injected, ring field, contrast")
            injected_row(lidar, True, "none", f"{lidar} injected, no ring field, flat intensity")
            clean_row(lidar, 0.0, f"{lidar} not injected")
            clean_row(lidar, BOARD_ERROR_M, f"{lidar} not injected, {1000 * BOARD_ERROR_M:.0f} mm board errors")
        injected_row("vlp16", "prior", "ring+contrast", "vlp16 drawn from the velodyne priors")
    print("rot/CRB, tr/CRB: RMS error over the RMS Cramer-Rao bound of the model with the injected terms as nuisance "
          "parameters (their priors included); d2: mean squared Mahalanobis distance of the truth (6 ideal); >4sd: "
          "trials with a translation error beyond 4 reported standard deviations on some axis; X in: share of the "
          "injected term's 95% intervals that hold it, over the trials whose chosen model has the term (/N: the "
          "share of trials that have it; ring totals: global + ring); terms: share of trials where auto adds a "
          "term; err/none: RMS translation error of auto over that of the solve without a model")


if __name__ == "__main__":
    main()
