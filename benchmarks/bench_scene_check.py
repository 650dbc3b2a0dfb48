"""The scene's check against simulated truth (make bench; `python benchmarks/bench_scene_check.py [--scenes N]
[--workers W] [--seed S] [--generator room|office|both]`): how often the true extrinsic is flagged (the
false-alarm rate) and how often a perturbed one is (the power), and how far the scene's own estimate lies from
the truth against its covariance.

Two generators, each scene of 10 frames seen by a VLP-16- or a 64-beam LiDAR in turn:

- ``room``: a furnished room without a board (``simulation.furnished_room``: desks, shelves, chairs, sofas,
  pillars, posters, doors, windows), the rig carried to a new spot and heading for every frame;
- ``office``: the board scenes' office (``simulate_dataset(scene="office")``: walls with doors, pictures,
  cabinets, a table with monitors, a pillar, the board on its holder, the space before the camera kept clear
  for the boards), with the board left out (the default) and kept.

Each is checked by ``pipeline.scene_check.check_scene`` under the truth, the truth turned by 0.2 degrees about
a random axis, and moved by 2 cm along a random direction. Printed per configuration: the share flagged at the
test's level (0.01), the median p-value, how often the scene's estimate is the minimum sought from the given
extrinsic (``scene_alignment.nearest_decided``: else another fits the scene significantly better), and the scene
estimate's error and NEES (6 dof) against the truth under the covariance the check reports, by the given extrinsic
it was sought from: from the truth itself the search can stop where it starts, so the turned and moved cases' estimates
are the fairer measure of the covariance. Beside the flagged counts: how many a test would flag on
average were the truth's reported covariance the scene estimate's own and the estimate unbiased (the noncentral
F's power against each difference), which is what the scene's information allows at the test's level; and
beside the truth's: the median over its checks of the smallest change along one camera axis each flags at its
level (``SceneCheck.smallest_flagged``), along the axis it tells best and the one it tells worst: the size from
which a check tells a change.
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

MODELS = ("vlp16", "os64")
TURN_DEG, MOVE_M = 0.2, 0.02


def _power(covariance: np.ndarray, blocks: int, xi: np.ndarray, alpha: float = 0.01) -> float:
    """The test's power against a difference ``xi`` (tangent) were ``covariance`` the scene estimate's own and
    unbiased: Hotelling's F over the constrained directions is then noncentral F(k, n - k) with noncentrality
    ``xi' C^-1 xi`` over them."""
    from scipy.stats import f, ncf

    from estimators.solvers.scene_alignment import constrained_distance

    d2, k = constrained_distance(covariance, xi)
    n = blocks
    if k == 0 or n <= k:
        return float("nan")
    return float(ncf.sf(f.isf(alpha, k, n - k), k, n - k, d2))


def simulated_cases(generator: str, seed: int, folder: Path) -> tuple[str, np.ndarray, dict]:
    """The scene of ``generator`` and ``seed`` simulated into ``folder`` (its LiDAR by the seed, ``MODELS`` in
    turn), and the extrinsics it is checked under: the truth, the truth turned by ``TURN_DEG`` about a random axis
    and moved by ``MOVE_M`` along a random direction. ``(model, truth, cases)``."""
    import json

    from estimators.simulation.furnished_room import simulate_scene_dataset
    from estimators.simulation.simulator import simulate_dataset
    from geometry.rotations import R_from_rotvec, T_from_Rt

    rng = np.random.default_rng(seed)
    model = MODELS[seed % len(MODELS)]
    if generator == "room":
        simulate_scene_dataset(folder, n_frames=10, seed=seed, lidar=model)
    else:
        simulate_dataset(folder, n_poses=10, seed=seed, lidar=model, scene="office")
    truth = np.array(json.loads((folder / "ground_truth.json").read_text())["T_camera_lidar"])
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    move = rng.normal(size=3)
    move /= np.linalg.norm(move)
    return model, truth, {"truth": truth,
                          "turned": T_from_Rt(R_from_rotvec(np.radians(TURN_DEG) * axis), np.zeros(3)) @ truth,
                          "moved": T_from_Rt(np.eye(3), MOVE_M * move) @ truth}


def _trial(job: tuple[str, int]) -> list[dict]:
    from estimators.errors import LidarcamError
    from estimators.pipeline.scene_check import check_scene
    from geometry.rotations import T_inverse, T_log

    generator, seed = job
    rows = []
    with tempfile.TemporaryDirectory(prefix="lidarcam-bench-") as tmp:
        model, truth, cases = simulated_cases(generator, seed, Path(tmp) / "ds")
        for keep in ((False, True) if generator == "office" else (False,)):
            at_truth = None  # the truth's check: its covariance gives the power expected against the others
            for name, T in cases.items():
                board = "none" if generator == "room" else "kept" if keep else "left out"
                row = {"generator": generator, "seed": seed, "model": model, "board": board, "case": name}
                try:
                    c = check_scene(Path(tmp) / "ds", T, keep_board=keep)
                except LidarcamError as exc:
                    row["refused"] = exc.problem
                    rows.append(row)
                    continue
                row.update(p=c.test["p_value"], consistent=c.consistent, rivals=len(c.rivals),
                           seconds=c.seconds, points=c.fit.points, nearest=c.fit.start == 0)
                if name != "truth" and at_truth is not None:
                    row["power"] = _power(at_truth.believed_covariance, at_truth.fit.blocks,
                                          T_log(T_inverse(truth) @ T))
                if name == "truth":
                    at_truth = c
                    flagged_from = c.smallest_flagged()  # over the axes: the best-told one's and the worst's
                    if flagged_from is not None:
                        row["flagged_from"] = tuple(float(f(v)) for v in flagged_from for f in (np.min, np.max))
                # the estimate against the truth from every start: from the truth itself the search can stay where
                # it starts (a local minimum), so the truth's row alone would understate the error
                xi = T_log(T_inverse(c.fit.T_camera_lidar) @ truth)
                row.update(rot_deg=float(np.degrees(np.linalg.norm(xi[:3]))),
                           trans_mm=float(1000 * np.linalg.norm(c.fit.T_camera_lidar[:3, 3] - truth[:3, 3])),
                           nees=float(xi @ np.linalg.solve(c.believed_covariance, xi)))
                rows.append(row)
    return rows


def _flagged_from(rows: list[dict]) -> str:
    """The median over the truth's checks of the smallest one-axis change each flags at its level
    (``SceneCheck.smallest_flagged``), about (deg) and along (mm) the camera's axis it tells best and the one it
    tells worst (beyond the worst, every one-axis change reaches the test's level)."""
    got = np.array([r["flagged_from"] for r in rows if "flagged_from" in r])
    if not len(got):
        return "-"
    m = np.median(got, axis=0)
    return f"{m[0]:.2f}-{m[1]:.2f} deg, {m[2]:.0f}-{m[3]:.0f} mm"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=20)
    ap.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--generator", choices=("room", "office", "both"), default="both")
    a = ap.parse_args()
    t0 = time.time()
    generators = ("room", "office") if a.generator == "both" else (a.generator,)
    jobs = [(g, s) for g in generators for s in range(a.seed, a.seed + a.scenes)]
    with ProcessPoolExecutor(a.workers) as pool:
        rows = [r for rs in pool.map(_trial, jobs) for r in rs]
    print(f"{a.scenes} simulated scenes per generator of 10 frames (VLP-16- and 64-beam LiDARs in turn), each "
          f"checked under the truth, the truth turned by {TURN_DEG} deg about a random axis and moved by "
          f"{100 * MOVE_M:.0f} cm along a random direction; flagged: p < 0.01\n")
    print("| scenes | LiDAR | board | case | checks | flagged | median p | undetermined | refused | seconds (median) | "
          "estimate from the given's start | expected from the scene's covariance | flagged from, best-worst axis "
          "(median) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    configs = [(g, m, b) for g in generators for m in MODELS
               for b in (("none",) if g == "room" else ("left out", "kept"))]
    for g, model, board in configs:
        for case in ("truth", "turned", "moved"):
            sel = [r for r in rows if (r["generator"], r["model"], r["board"], r["case"]) == (g, model, board, case)]
            done = [r for r in sel if "refused" not in r]
            tested = [r for r in done if r["p"] is not None]
            flagged = sum(r["consistent"] is False for r in done)
            print(f"| {g} | {model} | {board} | {case} | {len(sel)} | {flagged} of {len(tested)} | "
                  f"{np.median([r['p'] for r in tested]) if tested else float('nan'):.3g} | "
                  f"{len(done) - len(tested)} | {len(sel) - len(done)} | "
                  f"{np.median([r['seconds'] for r in done]) if done else float('nan'):.1f} | "
                  f"{sum(r['nearest'] for r in done)} of {len(done)} | "
                  + (f"{np.nansum([r['power'] for r in tested if 'power' in r]):.1f} of "
                     f"{sum('power' in r for r in tested)} |" if case != "truth" else "(1% of them) |")
                  + (f" {_flagged_from(tested)} |" if case == "truth" else " |"))
    print("\nThe scene's estimate against the truth, by the given extrinsic it was sought from (the truth, or the "
          "truth turned or moved as above; each with its 12 starts about it):\n")
    print("| scenes | LiDAR | board | sought from | estimates | rotation error RMS | translation error RMS | "
          "NEES mean / median (6 / 5.3 if honest) | share of NEES beyond chi2(6) 99% | contour returns (median) |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for g, model, board in configs:
        for start, cases in (("the truth", ("truth",)), ("turned or moved", ("turned", "moved"))):
            sel = [r for r in rows if (r["generator"], r["model"], r["board"]) == (g, model, board)
                   and r["case"] in cases and "nees" in r]
            if not sel:
                continue
            nees = np.array([r["nees"] for r in sel])
            print(f"| {g} | {model} | {board} | {start} | {len(sel)} | "
                  f"{np.sqrt(np.mean([r['rot_deg'] ** 2 for r in sel])):.3f} deg | "
                  f"{np.sqrt(np.mean([r['trans_mm'] ** 2 for r in sel])):.1f} mm | {nees.mean():.1f} / "
                  f"{np.median(nees):.1f} | {np.mean(nees > 16.81):.0%} | "
                  f"{np.median([r['points'] for r in sel]):.0f} |")
    refused = [r for r in rows if "refused" in r]
    for r in refused[:10]:
        print(f"- refused, {r['generator']} seed {r['seed']} {r['model']} board {r['board']} {r['case']}: "
              f"{r['refused']}")
    print(f"\n({len(jobs)} scenes in {time.time() - t0:.0f} s on {a.workers} processes; seeds "
          f"{a.seed}..{a.seed + a.scenes - 1})")


if __name__ == "__main__":
    main()
