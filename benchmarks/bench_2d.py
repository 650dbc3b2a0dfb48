"""2D LiDAR: true-solution hit rate, accuracy against the Cramer-Rao bound, and selection time of the
three ways to choose among the minimal solutions (measurement-level simulation of the default 2D rig:
a 270-degree scanner, boards 1.5-4 m away, corners 0.2 px).

A trial is a hit when the final estimate is the local minimum that the factor graph reaches when
started from the ground truth. Selections:
- min-residual: the baseline (Vasconcelos et al.): the least laser cost over every solution, refined;
- lower-bound: the lower-bound method (Peng et al.): clusters, effective lower bound, every kept
  candidate refined, least refined cost;
- lower-bound+extent (the default): the same after dropping solutions whose laser segments leave the
  boards' outlines.

Run: ``python benchmarks/bench_2d.py [--trials N] [--workers W]`` (``make bench`` runs it).
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from estimators.calibration import refine_candidates  # noqa: E402
from estimators.errors import DegenerateLayoutError  # noqa: E402
from estimators.simulation.simulator import default_rig_2d, sample_board_poses  # noqa: E402
from estimators.solvers.observation_model import Layout, cramer_rao_bound, simulate_measurements  # noqa: E402
from estimators.solvers.refinement import refine  # noqa: E402
from estimators.solvers.solution_selection import select_minimal, solution_distances  # noqa: E402
from geometry.rotations import T_inverse, T_log  # noqa: E402

SELECTIONS = (("min-residual", "minimal-min-residual", False), ("lower-bound", "minimal-lower-bound", False),
              ("lower-bound+extent", "minimal-lower-bound", True))


def trial(args) -> dict:
    seed, n_boards, noise_m = args
    rng = np.random.default_rng(seed)
    rig = default_rig_2d(rng, noise_m)
    poses = sample_board_poses(rig, n_boards, rng)
    layout = Layout(rig.camera, rig.board, rig.beams, rig.T_camera_lidar, tuple(poses), 0.2, noise_m)
    frames = simulate_measurements(layout, rng)
    out = {"boards": n_boards, "noise_m": noise_m, "crb": np.sqrt(np.diag(cramer_rao_bound(layout)))}
    try:
        truth_basin = refine(frames, rig.board, rig.camera, rig.T_camera_lidar).T_camera_lidar
    except DegenerateLayoutError:
        out["skipped"] = True
        return out
    for label, method, extent in SELECTIONS:
        try:
            t0 = time.perf_counter()
            sel = select_minimal(frames, rig.board, method, use_extent=extent)
            seconds = time.perf_counter() - t0
            ref, alternatives = refine_candidates(frames, rig.board, rig.camera, sel)
        except DegenerateLayoutError:
            out[label] = None
            continue
        T = ref.T_camera_lidar
        hit = solution_distances(np.array([T, truth_basin]))[0] < 0.05
        out[label] = {"hit": bool(hit), "xi": T_log(T_inverse(T) @ rig.T_camera_lidar), "seconds": seconds,
                      "ambiguous": bool(alternatives)}
    return out


def run(cells, trials, workers, seed=0):
    args = []
    for k, (n, noise) in enumerate(cells):
        seeds = np.random.SeedSequence([seed, k]).generate_state(trials)
        args += [(int(s), n, noise) for s in seeds]
    with ProcessPoolExecutor(workers) as pool:
        rows = list(pool.map(trial, args, chunksize=4))
    return rows


def summarise(rows, key_fn):
    groups: dict = {}
    for r in rows:
        if r.get("skipped"):
            continue
        groups.setdefault(key_fn(r), []).append(r)
    return groups


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--trials", type=int, default=200)
    ap.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    a = ap.parse_args()
    t0 = time.perf_counter()
    by_boards = [(n, 0.01) for n in range(3, 9)]
    by_noise = [(4, s) for s in (0.005, 0.01, 0.02, 0.03)]
    rows = run(by_boards + by_noise, a.trials, a.workers)
    nb = len(by_boards) * a.trials
    labels = [s[0] for s in SELECTIONS]

    def table(title, groups, name):
        print(f"\n{title}")
        print(f"  {name:>8s}" + "".join(f"{lab:>20s}" for lab in labels) + "   ambiguous(+extent)  trials")
        for key in sorted(groups):
            g = groups[key]
            cells = []
            for lab in labels:
                ok = [r[lab] for r in g if r.get(lab) is not None]
                cells.append(f"{100 * np.mean([o['hit'] for o in ok]):19.1f}%" if ok else f"{'-':>20s}")
            amb = [r[labels[-1]]["ambiguous"] for r in g if r.get(labels[-1])]
            print(f"  {key:>8}" + "".join(cells) + f"{100 * np.mean(amb):19.1f}%  {len(g):6d}")

    table("(i) true-solution hit rate vs number of boards (1 cm range noise)",
          summarise(rows[:nb], lambda r: r["boards"]), "boards")
    table("(ii) true-solution hit rate vs range noise (4 boards)",
          summarise(rows[nb:], lambda r: f"{100 * r['noise_m']:.1f}cm"), "noise")

    print("\n(iii) accuracy of the default selection's hits against the Cramer-Rao bound (RMS error / mean bound)")
    print(f"  {'boards':>8s}{'rot x':>8s}{'rot y':>8s}{'rot z':>8s}{'tr x':>8s}{'tr y':>8s}{'tr z':>8s}"
          f"   RMS rot deg  RMS trans mm")
    for n, g in sorted(summarise(rows[:nb], lambda r: r["boards"]).items()):
        hits = [r for r in g if r.get(labels[-1]) and r[labels[-1]]["hit"]]
        if len(hits) < 5:
            continue
        xi = np.array([r[labels[-1]]["xi"] for r in hits])
        crb = np.mean([r["crb"] for r in hits], axis=0)
        rms = np.sqrt(np.mean(xi**2, axis=0))
        print(f"  {n:>8}" + "".join(f"{v:8.2f}" for v in rms / crb)
              + f"{np.degrees(np.linalg.norm(rms[:3])):13.3f}{1000 * np.linalg.norm(rms[3:]):14.1f}")

    print("\n(iv) selection time (the minimal solver over all triples, scoring, clustering; s, mean / max)")
    print(f"  {'boards':>8s}" + "".join(f"{lab:>22s}" for lab in labels))
    for n, g in sorted(summarise(rows[:nb], lambda r: r["boards"]).items()):
        cells = []
        for lab in labels:
            t = [r[lab]["seconds"] for r in g if r.get(lab)]
            cells.append(f"{np.mean(t):13.3f} / {np.max(t):5.3f}" if t else f"{'-':>22s}")
        print(f"  {n:>8}" + "".join(cells))
    print(f"\n({len(rows)} trials in {time.perf_counter() - t0:.0f} s on {a.workers} processes)")


if __name__ == "__main__":
    main()
