"""The scene's estimate zone by zone of the image, on the recorded sets (make bench; `python
benchmarks/bench_scene_zones.py [--data ../shared/realdata]`): whether the scene's disagreement with the boards
comes from one part of the image (the fisheye's periphery, where the intrinsics are least sure) or from all.

Per recorded 3D set: the board calibration (``estimators.calibrate``, the CLI's engine, no posterior), then the
scene's contours under it split by how far from the principal point they land (as a share of the half-diagonal:
the centre, a middle ring, the periphery, and all), and the scene's estimate (``scene_minima`` from the board
calibration, with the check's covariance) from each zone alone. Printed per zone: the contour returns, the RMS
residual, the board calibration less the scene's (rotation about, translation along the camera's axes) and that
difference's squared Mahalanobis distance under the zone's covariance (6 dof). Zones whose estimates disagree
with each other as much as with the boards say the scene's own contours or edges are biased, not the boards.

Each set twice: under the given intrinsics, then under the intrinsics refined with the boards
(``refine_intrinsics``, the camera model of the solution used for the scene too). If the given intrinsics were
what turns the scene from the boards, the refined ones would bring the zones together and onto the boards.
"""
from __future__ import annotations

import argparse
import os
import sys
from dataclasses import replace
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

ZONES = ((0.0, 0.35, "centre"), (0.35, 0.6, "middle"), (0.6, 2.0, "periphery"), (0.0, 2.0, "all"))
SETS = ("acfr_vlp16_a", "acfr_ouster64_b")
MIN_RETURNS = 100


def main() -> None:
    from estimators import calibrate
    from estimators.pipeline.scene_check import read_scene_frames, scene_views
    from estimators.solvers.refinement_options import RefinementOptions

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(ROOT.parent / "shared" / "realdata"))
    a = ap.parse_args()
    for name in SETS:
        folder = Path(a.data) / name
        if not folder.is_dir():
            print(f"{name}: not found under {a.data}; skipped")
            continue
        _, _, _, frames, skipped = read_scene_frames(folder)
        for refined in (False, True):
            result = calibrate(folder, samples=0, options=RefinementOptions(refine_intrinsics=refined))
            cam = result.camera_model("cam0")
            label = "intrinsics refined with the boards" if refined else "the given intrinsics"
            _zones(name, label, result.T_camera_lidar, cam, scene_views(frames, result.T_camera_lidar, cam, skipped))


def _zones(name: str, label: str, board: np.ndarray, cam, views: list) -> None:
    """One table: the scene's estimate from each zone of the image under ``board`` and ``cam``."""
    from estimators.errors import LidarcamError
    from estimators.solvers.scene_alignment import minima_scatter, scene_minima
    from geometry.rotations import T_inverse, T_log, transform_points

    centre, half = cam.K[:2, 2], 0.5 * np.hypot(cam.width, cam.height)
    print(f"\n{name}, {label} ({cam.model}, {cam.width} x {cam.height}, {len(views)} frames with contours; "
          f"fx {cam.K[0, 0]:.1f}, cx {cam.K[0, 2]:.1f}, cy {cam.K[1, 2]:.1f})\n")
    print("| zone (share of the half-diagonal) | contour returns | RMS px | board - scene: rotation about the "
          "camera's x, y, z (deg) | translation along them (mm) | d2 (6 dof) |")
    print("|---|---|---|---|---|---|")
    for lo, hi, zone_name in ZONES:
        zone = []
        for v in views:
            uv = cam.project(transform_points(board, v.points))
            r = np.linalg.norm(uv - centre, axis=1) / half
            keep = (r >= lo) & (r < hi)
            if keep.any():
                zone.append(replace(v, points=v.points[keep]))
        n = sum(len(v.points) for v in zone)
        if n < MIN_RETURNS:
            print(f"| {zone_name} ({lo:.2f}-{hi:.2f}) | {n} | - | too few contour returns to solve (below "
                  f"{MIN_RETURNS}) | | |")
            continue
        try:
            fits = scene_minima(zone, cam, board)
        except LidarcamError as exc:
            print(f"| {zone_name} ({lo:.2f}-{hi:.2f}) | {n} | - | refused: "
                  f"{exc.problem} | | |")
            continue
        fit = fits[0]
        cov = fit.covariance + minima_scatter(fits, zone, cam, board)
        xi = T_log(T_inverse(fit.T_camera_lidar) @ board)
        rot = np.degrees(fit.T_camera_lidar[:3, :3] @ xi[:3])
        trans = 1000 * (board[:3, 3] - fit.T_camera_lidar[:3, 3])
        try:
            d2 = f"{float(xi @ np.linalg.solve(cov, xi)):.0f}"
        except np.linalg.LinAlgError:
            d2 = "-"
        print(f"| {zone_name} ({lo:.2f}-{hi:.2f}) | {fit.points} | {fit.rms_px:.2f} | "
              f"({', '.join(f'{x:+.2f}' for x in rot)}) | ({', '.join(f'{x:+.0f}' for x in trans)}) | {d2} |")


if __name__ == "__main__":
    main()
