"""Which witness is off on the recorded sets: the boards' planes, their edges, the camera's intrinsics or the scene
(make bench; `python benchmarks/bench_recorded_witnesses.py [--data ../shared/realdata]`).

On the VLP-16 set the scene contradicts the board calibration (``lidarcam check``), its estimate turned about the
camera's y from the boards'. Three explanations were open (issue 65): the given fisheye intrinsics, the scene's
own cues, or the boards. Per recorded 3D set this page puts every witness in one frame, as a turn about and a move
along the camera's axes from the engine's estimate (``estimators.calibrate``, no posterior):

- the boards, solved from one measurement (``estimators.measure``; ``estimators.solve``, the pair's own solve) with
  the planes alone, with the planes and the board's edges, and with each board's plane error held at 12, 24 and
  100 mm: the planes (their normals and their distances) then weigh little, and the edges (the ring ends on
  the outline) and the corners lead;
- the engine with the camera's intrinsics refined (``--refine-intrinsics``);
- the source tool's reference (``reference.json``);
- the scene: ``check_scene`` of each board estimate, under the intrinsics it was estimated with and with its
  covariance (p and the scene's estimate); and the scene's estimate from the engine's with only the contour returns
  nearer than 8 m, beyond 8 m, or in one third of the image across, or of one side of their silhouette (the LiDAR's
  scan reaching an object or leaving it).

And a test of one explanation, a tilt common to every board's LiDAR plane (a range error growing across every
board alike): the LiDAR's board points corrected for such a tilt (about the camera's x and y, each board turned
about its centroid, every point moved along its beam) before the solve, with the planes' consistency (the per-board
plane error it needs) and their test against the edges. If the planes carried such a tilt, removing it would make
them more consistent with the camera's boards and with the edges.

Far returns measure the rotation alone (a translation of 40 mm turns a return 10 m away by 0.2 degrees); near ones
the translation too. A turn with a move that cancel at the boards' distance (2-4 m) is what the boards' positions
cannot see and their normals must.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
from dataclasses import replace
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

SETS = ("acfr_vlp16_a", "acfr_ouster64_b")
FLOORS_M = (0.012, 0.024, 0.1)
NEAR_M = 8.0


def relative(T: np.ndarray, T0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``T`` from ``T0``: the turn about the camera's axes (deg) and the move along them (mm)."""
    from geometry.rotations import T_inverse, T_log

    return np.degrees(T0[:3, :3] @ T_log(T_inverse(T0) @ T)[:3]), 1000 * (T[:3, 3] - T0[:3, 3])


def sd_camera(C: np.ndarray, T: np.ndarray) -> np.ndarray:
    """Standard deviations of the turn about the camera's x, y, z (deg) under ``C`` (right tangent of ``T``)."""
    R = T[:3, :3]
    return np.degrees(np.sqrt(np.maximum(np.diag(R @ C[:3, :3] @ R.T), 0.0)))


def row(name: str, T: np.ndarray, T0: np.ndarray, sd: np.ndarray | None = None, note: str = "") -> str:
    turn, move = relative(T, T0)
    sd_s = "" if sd is None else " ".join(f"{x:.2f}" for x in sd)
    return (f"| {name} | {' '.join(f'{x:+.2f}' for x in turn)} | {sd_s} | {' '.join(f'{x:+.1f}' for x in move)} | "
            f"{note} |")


def scene_subsets(folder: Path, T0: np.ndarray) -> list[tuple[str, object]]:
    """The scene's estimate from ``T0`` on subsets of its contour returns (module docstring): ``(name, fit)``."""
    from estimators.errors import LidarcamError
    from estimators.lidar.depth_edges import depth_edges
    from estimators.pipeline.scene_check import read_scene_frames, scene_views
    from estimators.solvers.scene_alignment import nearest_decided, scene_minima
    from geometry.rotations import transform_points

    _, camera, _, frames, skipped = read_scene_frames(folder)
    views = scene_views(frames, T0, camera, skipped)
    side = {}  # each frame's contour points (LiDAR frame, rounded) -> +1 entering an object, -1 leaving it
    for f in frames:
        c = depth_edges(f.sweep.points, f.sweep.ring)
        turn = np.angle(np.exp(1j * (np.arctan2(c.points[:, 1], c.points[:, 0])
                                     - np.arctan2(f.sweep.points[c.index, 1], f.sweep.points[c.index, 0]))))
        side[f.name] = {tuple(np.round(p, 6)): np.sign(t) for p, t in zip(c.points, turn)}
    third = camera.width / 3

    def keep(view, which):
        r = np.linalg.norm(view.points, axis=1)
        u = camera.project(transform_points(T0, view.points))[:, 0]
        s = np.array([side[view.name].get(tuple(np.round(p, 6)), 0.0) for p in view.points])
        return {"nearer than 8 m": r < NEAR_M, "beyond 8 m": r >= NEAR_M, "left third": u < third,
                "middle third": (u >= third) & (u < 2 * third), "right third": u >= 2 * third,
                "entering an object": s > 0, "leaving an object": s < 0}[which]

    out = []
    for which in ("nearer than 8 m", "beyond 8 m", "left third", "middle third", "right third",
                  "entering an object", "leaving an object"):
        sub = [replace(v, points=v.points[keep(v, which)]) for v in views]
        sub = [v for v in sub if len(v.points)]
        try:
            fit = nearest_decided(scene_minima(sub, camera, T0, decided=True), sub, camera, T0)[0]
        except LidarcamError as exc:
            out.append((which, exc.problem))
            continue
        out.append((which, fit))
    return out


def common_tilt(m, tilt_deg: tuple[float, float], T0: np.ndarray) -> list:
    """The frames of ``m`` with every board's LiDAR points corrected for a tilt common to the boards, ``tilt_deg``
    about the camera's x and y (``T0``'s axes): each point moved along its beam by the range the tilt adds at it,
    turning its board's plane about the points' centroid."""
    from estimators.measurements import observe_lidar_board
    from geometry.rotations import R_from_rotvec

    R = R_from_rotvec(T0[:3, :3].T @ np.radians([tilt_deg[0], tilt_deg[1], 0.0]))
    out = []
    for f in m.frames:
        if not f.usable:
            out.append(f)
            continue
        o = f.lidar
        r = np.linalg.norm(o.points, axis=1)
        u = o.points / r[:, None]
        along = (o.points - o.points.mean(axis=0)) @ (R - np.eye(3)).T @ o.plane.normal  # the tilt, along the normal
        cos = u @ o.plane.normal
        cos = np.where(np.abs(cos) < 0.1, np.copysign(0.1, cos), cos)
        seen = replace(observe_lidar_board(u * (r - along / cos)[:, None], o.candidates), rings=o.rings,
                       intensity=o.intensity)
        out.append(replace(f, lidar=seen))
    return out


def tilt_rows(m, T0: np.ndarray) -> None:
    """The boards solved (planes and edges) after a tilt common to every board is removed (:func:`common_tilt`)."""
    from estimators import solve

    print("\n| common tilt removed, about camera x y (deg) | per-board plane error (mm) | "
          "planes against edges: d2, p | turn about camera x y z (deg) | move along camera x y z (mm) |")
    print("|---|---|---|---|---|")
    for tilt in ((0.0, 0.0), (0.0, 0.5), (0.3, 0.5), (0.5, 0.5), (0.0, -0.5)):
        res = solve(common_tilt(m, tilt, T0), m.board, m.camera)
        test = (res.refinement.edges or {}).get("planes_against_edges") or {}
        turn, move = relative(res.T_camera_lidar, T0)
        print(f"| {tilt[0]:+.1f} {tilt[1]:+.1f} | {1000 * res.refinement.plane_floor_m:.2f} | "
              f"{test.get('d2', float('nan')):.1f}, {test.get('p_value', float('nan')):.2g} | "
              f"{' '.join(f'{x:+.2f}' for x in turn)} | {' '.join(f'{x:+.1f}' for x in move)} |", flush=True)


def one_set(folder: Path) -> None:
    from estimators import calibrate, measure, solve
    from estimators.errors import LidarcamError
    from estimators.pipeline.scene_check import check_scene
    from estimators.solvers.refinement_options import RefinementOptions

    engine = calibrate(folder, samples=0)
    T0 = engine.T_camera_lidar
    m = measure(folder)
    print(f"\n{folder.name}: every witness from the engine's estimate\n")
    print("| witness | turn about camera x y z (deg) | its sd about x y z (deg) | move along camera x y z (mm) | "
          "the scene's check of it: p; the scene's estimate's turn (deg) and move (mm) from the engine's |")
    print("|---|---|---|---|---|")
    boards = {"boards: planes alone": (solve(m, options=RefinementOptions(edges=False)), None),
              "boards: planes + edges (the pair's solve)": (solve(m, options=RefinementOptions(edges=True)), None)}
    for floor in FLOORS_M:
        boards[f"boards: planes + edges, plane error {1000 * floor:g} mm"] = (
            solve(m, options=RefinementOptions(edges=True, plane_floor_m=floor)), None)
    refined = calibrate(folder, samples=0, options=RefinementOptions(refine_intrinsics=True))
    cams = {"engine (calibrate)": (engine, engine.camera_model("cam0")),
            "engine, intrinsics refined": (refined, refined.camera_model("cam0"))}
    for name, (res, camera) in {**cams, **boards}.items():
        T, C = res.T_camera_lidar, res.covariance
        try:
            c = check_scene(folder, T, camera=camera, given_covariance=C)
            turn, move = relative(c.fit.T_camera_lidar, T0)
            note = (f"p = {c.test['p_value']:.2g}; {' '.join(f'{x:+.2f}' for x in turn)}; "
                    f"{' '.join(f'{x:+.1f}' for x in move)}")
        except LidarcamError as exc:
            note = f"refused: {exc.problem}"
        print(row(name, T, T0, sd_camera(C, T), note), flush=True)
    if (folder / "reference.json").is_file():
        ref = np.array(json.loads((folder / "reference.json").read_text())["T_camera_lidar"])
        c = check_scene(folder, ref)
        turn, move = relative(c.fit.T_camera_lidar, T0)
        print(row("the source tool's reference", ref, T0, None,
                  f"p = {c.test['p_value']:.2g} (taken as exact); {' '.join(f'{x:+.2f}' for x in turn)}; "
                  f"{' '.join(f'{x:+.1f}' for x in move)}"), flush=True)
    tilt_rows(m, T0)
    print(f"\nthe scene's estimate from the engine's, on part of its contour returns ({folder.name}):\n")
    print("| returns | contour returns | turn about camera x y z (deg) | its sd (deg) | move along camera x y z (mm) "
          "| |")
    print("|---|---|---|---|---|---|")
    for which, fit in scene_subsets(folder, T0):
        if isinstance(fit, str):
            print(f"| {which} | | refused: {fit} | | | |")
            continue
        print(row(f"{which} | {fit.points}", fit.T_camera_lidar, T0, sd_camera(fit.covariance, fit.T_camera_lidar)),
              flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(ROOT.parent / "shared" / "realdata"))
    a = ap.parse_args()
    for name in SETS:
        folder = Path(a.data) / name
        if not folder.is_dir():
            print(f"{name}: not found under {a.data}")
            continue
        one_set(folder)


if __name__ == "__main__":
    main()
