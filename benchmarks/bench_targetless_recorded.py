"""Targetless calibration on the recorded sets, from guesses 2 degrees and 10 cm off their board calibration
(make bench; `python benchmarks/bench_targetless_recorded.py [--data ../shared/realdata] [--guesses 3]
[--refine-intrinsics]`).

Per recorded 3D set: the engine's board calibration (``estimators.calibrate``, no posterior) and the scene's check
of it (``check_scene`` with its covariance: the scene's own estimate). Then ``calibrate_targetless`` from guesses
made by turning the board calibration by 2 degrees about a random axis and moving it by 10 cm along a random
direction (generator seeded by ``[guess, 65]``), under the board calibration's intrinsics as ``calibrate
--targetless`` takes a calibration.json's (with ``--refine-intrinsics``, those refined with the boards). Each row
says whether it was refused (and why), its verdict and time, and where it landed: how far from the boards'
estimate and its d2 under the boards' covariance (their 99% region: d2 at most 16.81, chi-square with 6 degrees of
freedom), and how far from the scene's estimate in the check and its d2 under that estimate's covariance. Sets
absent from ``--data`` are skipped.
"""
from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

SETS = ("acfr_vlp16_a", "acfr_ouster64_b")
OFF_DEG, OFF_M = 2.0, 0.10
REGION_99 = 16.81  # chi-square, 6 degrees of freedom


def apart(T: np.ndarray, T_ref: np.ndarray, C_ref: np.ndarray) -> tuple[str, float]:
    """``T`` from ``T_ref`` in degrees and millimetres, and its d2 under ``C_ref`` (``T_ref``'s right tangent)."""
    from geometry.rotations import T_inverse, T_log

    xi = T_log(T_inverse(T_ref) @ T)
    d2 = float(xi @ np.linalg.solve(C_ref, xi))
    return f"{np.degrees(np.linalg.norm(xi[:3])):.2f} deg, {1000 * np.linalg.norm(xi[3:]):.0f} mm, d2 {d2:.3g}", d2


def recorded_boards(data: str, absent_row: str, refine_intrinsics: bool = False):
    """Each recorded 3D set (``SETS``) under ``data``: its name, folder and board calibration by the engine (no
    posterior: its Laplace covariance; the intrinsics refined with the boards where ``refine_intrinsics``); for a
    set absent there, ``absent_row`` (formatted with ``name`` and ``data``) is printed instead."""
    from estimators import calibrate
    from estimators.solvers.refinement_options import RefinementOptions

    for name in SETS:
        folder = Path(data) / name
        if not (folder / "dataset.yaml").is_file():
            print(absent_row.format(name=name, data=data))
            continue
        yield name, folder, calibrate(folder, samples=0, options=RefinementOptions(refine_intrinsics=refine_intrinsics))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", default=str(ROOT.parent / "shared" / "realdata"))
    ap.add_argument("--guesses", type=int, default=3)
    ap.add_argument("--refine-intrinsics", action="store_true",
                    help="the board calibrations with their intrinsics refined, the scene's under those")
    args = ap.parse_args()

    from estimators.errors import LidarcamError
    from estimators.pipeline.scene_check import check_scene
    from estimators.pipeline.targetless import calibrate_targetless

    from bench_targetless import off_by

    if args.refine_intrinsics:
        print("the board calibrations' intrinsics refined with the boards; the check and the targetless refinement "
              "under them")
    print(f"guesses: the board calibration turned by {OFF_DEG:g} deg about a random axis and moved by "
          f"{100 * OFF_M:g} cm along a random direction; d2 under the boards' covariance (their 99% region: d2 at "
          f"most {REGION_99}) and under the scene's in the check of the board calibration")
    print()
    print("| set | guess | outcome | seconds | from the boards | within their 99% | from the scene's estimate |")
    print("|---|---|---|---|---|---|---|")
    for name, folder, boards in recorded_boards(args.data, "| {name} | | absent from {data}: skipped | | | | |",
                                                args.refine_intrinsics):
        T_b, C_b, camera = boards.T_camera_lidar, boards.covariance, boards.camera_model("cam0")
        check = check_scene(folder, T_b, camera=camera, given_covariance=C_b)
        T_s, C_s = check.fit.T_camera_lidar, check.believed_covariance
        for k in range(args.guesses):
            guess = off_by(T_b, OFF_DEG, OFF_M, np.random.default_rng([k, 65]))
            try:
                r = calibrate_targetless(folder, guess, camera=camera)
            except LidarcamError as exc:
                print(f"| {name} | {k} | refused: {exc.problem} | | | | |", flush=True)
                continue
            (from_boards, d2), (from_scene, _) = apart(r.T_camera_lidar, T_b, C_b), apart(r.T_camera_lidar, T_s, C_s)
            print(f"| {name} | {k} | {r.verdict.level} | {r.seconds:.1f} | {from_boards} | "
                  f"{'yes' if d2 <= REGION_99 else 'no'} | {from_scene} |", flush=True)
        print(f"| {name} | check | the scene's estimate, p = {check.test['p_value']:.2g} | | "
              f"{apart(T_s, T_b, C_b)[0]} | | |", flush=True)


if __name__ == "__main__":
    main()
