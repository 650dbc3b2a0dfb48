"""Which LiDAR cue lines up with the image's edges on the recorded sets: depth contours or intensity steps (make
bench; `python benchmarks/bench_scene_cues.py [--data ../shared/realdata]`).

Per recorded 3D set, under its board calibration (``estimators.calibrate``, no posterior), two kinds of LiDAR
points are projected into every frame's image (the board left out, the camera's own view as in the check):

- depth contours (``lidar.depth_edges``: the check's cue);
- intensity steps: along each ring, neighbouring returns at about one range (within 0.1 m) whose intensity differs
  by more than ``STEP_MADS`` times the ring's median absolute step and by 10% of the ring's intensity range,
  placed half way between them.

For each: how many there are, the share that lands within 1.5 px of an image edge (Canny, as the check finds
them), the same share with the extrinsic turned by 0.5 degrees about the camera's x and y (four turns, their
mean): the chance level of that cue in that image, and the share under the scene's own estimate
(``check_scene`` from the board calibration). The lift (share under the calibration over the chance share) says
how well the calibration lays the cue on the edges.
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
STEP_MADS, NEAR_PX, TURN_DEG = 6.0, 1.5, 0.5


def intensity_steps(points: np.ndarray, intensity: np.ndarray, ring: np.ndarray) -> np.ndarray:
    """Half-way points between neighbouring returns of a ring at about one range whose intensity steps."""
    out = []
    r_all = np.linalg.norm(points, axis=1)
    for beam in np.unique(ring):
        idx = np.flatnonzero((ring == beam) & (r_all > 1.0))
        if len(idx) < 10:
            continue
        idx = idx[np.argsort(np.arctan2(points[idx, 1], points[idx, 0]))]
        dI = np.abs(np.diff(intensity[idx].astype(float)))
        same = np.abs(np.diff(r_all[idx])) < 0.1
        mad = np.median(dI[same]) if same.any() else 0.0
        span = np.percentile(intensity[idx], 95) - np.percentile(intensity[idx], 5)
        k = np.flatnonzero(same & (dI > max(STEP_MADS * mad, 0.1 * span, 1e-6)))
        out.append(0.5 * (points[idx[k]] + points[idx[k + 1]]))
    return np.vstack(out) if out else np.zeros((0, 3))


def main() -> None:
    from estimators import calibrate
    from estimators.camera.edge_map import edge_distance
    from estimators.io.pointcloud_io import read_sweep
    from estimators.lidar.depth_edges import depth_edges
    from estimators.pipeline.scene_check import check_scene, read_scene_frames
    from estimators.solvers.scene_alignment import beam_spacing_px, visible_from_camera
    from geometry.rotations import R_from_rotvec, T_from_Rt, transform_points

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(ROOT.parent / "shared" / "realdata"))
    a = ap.parse_args()
    print("| set | cue | points | within 1.5 px of an edge | by chance (turned 0.5 deg) | lift | under the scene's "
          "estimate |")
    print("|---|---|---|---|---|---|---|")
    for name in SETS:
        folder = Path(a.data) / name
        if not folder.is_dir():
            print(f"| {name} | not found under {a.data} | | | | |")
            continue
        T = calibrate(folder, samples=0).T_camera_lidar
        T_scene = check_scene(folder, T).fit.T_camera_lidar
        root, cam, _, frames, _ = read_scene_frames(folder)
        turns = [T_from_Rt(R_from_rotvec(np.radians(TURN_DEG) * np.array(e, float)), np.zeros(3)) @ T
                 for e in ((1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0))]
        counts = {"depth contours": [0, 0, 0.0, 0], "intensity steps": [0, 0, 0.0, 0]}
        for f in frames:
            field = edge_distance(f.gray, 20.0, ignore=f.board_mask)
            sweep = read_sweep(Path(root) / f"{f.name}.pcd") if f.sweep.intensity is None else f.sweep
            spacing = beam_spacing_px(sweep.points, sweep.ring, cam)
            cues = {"depth contours": depth_edges(sweep.points, sweep.ring).points,
                    "intensity steps": intensity_steps(sweep.points, sweep.intensity, sweep.ring)}
            for cue, P in cues.items():
                P = P[visible_from_camera(P, sweep.points, T, cam, spacing_px=spacing)]

                def near(Tx: np.ndarray) -> tuple[int, int]:
                    uv = cam.project(transform_points(Tx, P))
                    ok = np.all(np.isfinite(uv), axis=1) & cam.in_image(np.nan_to_num(uv, nan=-1e9))
                    u = np.clip(np.round(uv[ok, 0]).astype(int), 0, field.shape[1] - 1)
                    v = np.clip(np.round(uv[ok, 1]).astype(int), 0, field.shape[0] - 1)
                    if f.board_mask is not None:
                        keep = ~f.board_mask[v, u]
                        u, v = u[keep], v[keep]
                    return len(u), int(np.sum(field[v, u] <= NEAR_PX))

                n, hit = near(T)
                chance = np.mean([near(Tt)[1] / max(near(Tt)[0], 1) for Tt in turns])
                c = counts[cue]
                c[0] += n
                c[1] += hit
                c[2] += chance * n
                c[3] += near(T_scene)[1]
        for cue, (n, hit, chance_hits, scene_hits) in counts.items():
            share, chance = hit / max(n, 1), chance_hits / max(n, 1)
            print(f"| {name} | {cue} | {n} | {100 * share:.0f}% | {100 * chance:.0f}% | "
                  f"{share / chance if chance > 0 else float('nan'):.2f} | {100 * scene_hits / max(n, 1):.0f}% |")


if __name__ == "__main__":
    main()
