"""The scene's check of the recorded sets' board calibrations, and of the same calibrations turned and moved
(make bench; `python benchmarks/bench_check_recorded.py [--data ../shared/realdata] [--deg 1] [--cm 5]`).

Per recorded 3D set: the engine's board calibration (``estimators.calibrate``, no posterior: its Laplace
covariance) checked by the scene (``check_scene`` with that covariance, as `lidarcam check --calibration
calibration.json` does), then the same calibration turned by ``--deg`` about each of the camera's axes, either
way, and moved by ``--cm`` along each, either way (about and along the camera's axes, through its centre: the
given covariance kept), each checked the same way. A check passes at p >= 0.01 (``scene_check.ALPHA``); the
perturbed ones should all be flagged. Sets absent from ``--data`` are skipped. A second table says, per axis, where
the scene's own estimate lies from the calibration and the smallest change along that axis the calibration's check
flags (``SceneCheck.smallest_flagged``): what the scene can tell there, the bound on the perturbations' flags.
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

AXES = "xyz"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", default=str(ROOT.parent / "shared" / "realdata"))
    ap.add_argument("--deg", type=float, default=1.0, help="the turn about each camera axis (default 1)")
    ap.add_argument("--cm", type=float, default=5.0, help="the move along each camera axis (default 5)")
    args = ap.parse_args()

    from estimators.pipeline.scene_check import ALPHA, VOUCHES_WITHIN, check_scene
    from geometry.rotations import R_from_rotvec, T_from_Rt

    from bench_targetless_recorded import recorded_boards

    print(f"each set's board calibration (no posterior: its Laplace covariance) checked by its scene, then turned by "
          f"{args.deg:g} deg about and moved by {args.cm:g} cm along each camera axis (x right, y down, z forward), "
          f"either way; flagged: p < {ALPHA}; verdict: the check's first line (OK only where it agrees and would flag "
          f"a turn of {VOUCHES_WITHIN[0]:g} deg and a move of {VOUCHES_WITHIN[1]:g} mm along every axis)")
    print()
    print("| set | calibration | p | flagged | verdict | the scene's estimate from it: deg, mm |")
    print("|---|---|---|---|---|---|")
    bounds = []
    for name, folder, boards in recorded_boards(args.data, "| {name} | absent from {data}: skipped | | | | |"):
        T_b, C_b, camera = boards.T_camera_lidar, np.asarray(boards.covariance), boards.camera_model("cam0")
        cases = [("as calibrated", np.eye(4))]
        for k, axis in enumerate(AXES):
            for sign in (1, -1):
                w = np.zeros(3)
                w[k] = sign * np.radians(args.deg)
                turn = T_from_Rt(R_from_rotvec(w), np.zeros(3))
                cases.append((f"turned {sign * args.deg:+g} deg about {axis}", turn))
        for k, axis in enumerate(AXES):
            for sign in (1, -1):
                t = np.zeros(3)
                t[k] = sign * args.cm / 100
                cases.append((f"moved {sign * args.cm:+g} cm along {axis}", T_from_Rt(np.eye(3), t)))
        flagged, said_ok, flags = 0, 0, {}
        for label, D in cases:
            c = check_scene(folder, D @ T_b, camera=camera, given_covariance=C_b)
            xi = c.test["difference_tangent"]
            p = c.test["p_value"]
            flag = p is not None and p < ALPHA
            flagged += flag and label != "as calibrated"
            said_ok += c.verdict.level == "OK" and label != "as calibrated"
            flags[label] = flag
            if label == "as calibrated":
                calibrated = c
            print(f"| {name} | {label} | {p:.3g} | {'yes' if flag else 'no'} | {c.verdict.level} | "
                  f"{np.degrees(np.linalg.norm(xi[:3])):.2f}, {1000 * np.linalg.norm(xi[3:]):.0f} |", flush=True)
        print(f"| {name} | perturbed: {flagged} of {len(cases) - 1} flagged, {said_ok} said OK | | | | |", flush=True)
        bounds.append((name, calibrated, T_b, flags))
    _bounds(bounds, args)


def _bounds(bounds: list, args) -> None:
    """Per set and camera axis: where the scene's own estimate lies from the board calibration (as a turn about, a
    move along the axis: ``Log(T_scene T_boards^-1)``, the perturbations' form), the smallest change along that axis
    the calibration's check flags (``SceneCheck.smallest_flagged``: at the test's level were the scene's estimate
    at the calibration), and which of the perturbations were flagged. A perturbation towards the scene's estimate
    lands that much nearer it: flagged only where the two together exceed the smallest flagged."""
    from geometry.rotations import T_inverse, T_log

    if not bounds:
        return
    print()
    print("what the scene can flag along each camera axis, from the calibration's check:")
    print()
    print("| set | about / along | the scene's estimate as a change of the calibration | the smallest change flagged "
          "| perturbed either way: flagged (+, -) |")
    print("|---|---|---|---|---|")
    for name, c, T_b, flags in bounds:
        d = T_log(c.fit.T_camera_lidar @ T_inverse(T_b))
        smallest = c.smallest_flagged()
        for k in range(6):
            axis, turn = AXES[k % 3], k < 3
            unit, scale, size = ("deg", np.degrees(1.0), args.deg) if turn else ("mm", 1000.0, args.cm * 10)
            label = (lambda sign: f"turned {sign * args.deg:+g} deg about {axis}") if turn else \
                (lambda sign: f"moved {sign * args.cm:+g} cm along {axis}")
            least = "undetermined" if smallest is None else (
                "free" if not np.isfinite(smallest[0 if turn else 1][k % 3]) else
                f"{smallest[0 if turn else 1][k % 3]:.{2 if turn else 0}f} {unit}")
            marks = ", ".join("yes" if flags[label(sign)] else "no" for sign in (1, -1))
            print(f"| {name} | {'about' if turn else 'along'} {axis} | {scale * d[k]:+.{2 if turn else 0}f} {unit} | "
                  f"{least} | {marks} ({size:g} {unit}) |", flush=True)


if __name__ == "__main__":
    main()
