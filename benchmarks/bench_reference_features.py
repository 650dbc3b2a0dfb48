"""The recorded sets: does the source tool's reference agree with the boards it was made from?
(make bench; each set skipped when absent from ../shared/realdata; `python benchmarks/bench_reference_features.py`).

The source tool (github.com/acfr/cam_lidar_calibration) takes its rotation from the boards' normals and its
translation from the boards' centres; it models no range offset. This checks the reference and lidarcam's two
estimates (the engine's, ``calibrate``: planes alone, and with the edges) by those two features, measured here from
the same frames:

- the normals: each frame's LiDAR board normal turned into the camera by the transform, against the camera's
  board normal (their cross product: the turn, in camera axes, that would align them); the mean over frames and
  its standard error (the frames' scatter over the square root of their count);
- the centres: each frame's LiDAR board centre as the source tool defines it (lines through every ring's first
  and last returns on the board, the upper and lower side of each split at the ring that reaches furthest, the
  centre of the four corners where they meet), mapped into the camera, against the camera's board centre;
  the mean over frames and its standard error. The LiDAR's returns are raw (no range offset applied): along
  the boards' normals (about the camera's z) an estimate with a range offset leaves them off by it.
- the outline's offset from the pattern's middle that the estimate with the edges fits (a nuisance), in the
  board's axes and, averaged over the frames, in the camera's: the centres above are the pattern's middle;
- `outside`: returns within 3 cm of a board's plane and up to 25 cm beyond its outline (the camera's outline
  under the estimate with the edges), over all frames: a stand or a holder in the board's plane would show here.
"""
from __future__ import annotations

import os
import sys
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # as the CLI does (see bench_refinement.py)

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench_principal_point import recorded_sets, reference_T  # noqa: E402

from estimators.io.pointcloud_io import read_sweep  # noqa: E402
from estimators.rig_calibration import calibrate  # noqa: E402
from estimators.solvers.range_model import frame_rings  # noqa: E402
from estimators.solvers.refinement_options import RefinementOptions  # noqa: E402
from geometry.rotations import T_inverse, transform_points  # noqa: E402

PLANE_BAND_M = 0.03
BEYOND_M = 0.25


def _side(uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A line ``(point, direction)`` through 2D points by least squares (their principal axis)."""
    c = uv.mean(axis=0)
    return c, np.linalg.svd(uv - c)[2][0]


def _meet(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    (p, u), (q, v) = a, b
    s = np.linalg.solve(np.column_stack([u, -v]), q - p)
    return p + s[0] * u


def source_centre(points: np.ndarray, rings: np.ndarray, normal: np.ndarray, distance: float) -> np.ndarray | None:
    """The board's centre as the source tool defines it, from the board's returns (LiDAR frame), or None when a
    side has fewer than two rings or two sides that should meet are parallel (a board turned as a diamond, as on
    the recorded sets, has four sides the rings cross)."""
    P = points - np.outer(points @ normal - distance, normal)  # on the plane
    u = np.cross([0.0, 0.0, 1.0], normal)
    u /= np.linalg.norm(u)  # horizontal in the plane (towards the LiDAR's left for a board ahead)
    v = np.cross(normal, u)
    uv = np.column_stack([P @ u, P @ v])
    ends = {"left": [], "right": []}
    for r in np.unique(rings):
        q = uv[rings == r]
        ends["left"].append(q[np.argmax(q[:, 0])])
        ends["right"].append(q[np.argmin(q[:, 0])])
    sides = {}
    for key, e in ends.items():
        e = np.array(e)
        e = e[np.argsort(e[:, 1])]  # bottom to top
        k = int(np.argmax(e[:, 0]) if key == "left" else np.argmin(e[:, 0]))
        if k < 1 or k > len(e) - 2:
            return None
        sides[key] = (_side(e[: k + 1]), _side(e[k:]))  # (lower, upper), the furthest ring in both
    (ll, lu), (rl, ru) = sides["left"], sides["right"]
    try:
        corners = np.array([_meet(lu, ru), _meet(ll, rl), _meet(lu, ll), _meet(ru, rl)])
    except np.linalg.LinAlgError:  # parallel sides: an upright board's rings end on two vertical sides
        return None
    c = corners.mean(axis=0)
    return c[0] * u + c[1] * v + distance * normal


def _mean_and_se(rows: list[np.ndarray]) -> str:
    a = np.array(rows)
    m, se = a.mean(axis=0), a.std(axis=0, ddof=1) / np.sqrt(len(a))
    return "(" + ", ".join(f"{x:+.2f}" for x in m) + ") +- (" + ", ".join(f"{x:.2f}" for x in se) + ")"


def main() -> None:
    print("under each transform, the frames' mean in camera axes +- its standard error")
    print(f"{'set':18s}{'transform':16s}{'normals: turn (deg)':>48s}{'centres: shift (mm)':>50s}{'frames':>8s}")
    for name, path, ds in recorded_sets():
        if ds.board.size is None:
            print(f"{name}: no board size; skipped")
            continue
        w, h = ds.board.size
        results = [(label, calibrate(path, rng=np.random.default_rng(0), samples=0,
                                     options=RefinementOptions(edges=edges)))
                   for label, edges in (("planes", False), ("planes + edges", True))]
        frames = [f for f in results[0][1].frames if f.usable]
        rings = frame_rings([f.lidar for f in frames])
        transforms = [(label, res.T_camera_lidar) for label, res in results]
        if (T_ref := reference_T(path)) is not None:
            transforms.append(("reference", T_ref))
        centres = [source_centre(f.lidar.points, r, f.lidar.plane.normal, f.lidar.plane.distance)
                   for f, r in zip(frames, rings)]
        used = [i for i, c in enumerate(centres) if c is not None]
        for label, T in transforms:
            turns = [np.degrees(np.cross(T[:3, :3] @ f.lidar.plane.normal, f.camera.plane.normal)) for f in frames]
            shifts = [1000 * (transform_points(T, centres[i]) - transform_points(frames[i].camera.T_camera_board,
                                                                                  ds.board.centre))
                      for i in used]
            print(f"{name:18s}{label:16s}{_mean_and_se(turns):>48s}{_mean_and_se(shifts):>50s}"
                  f"{f'{len(used)}/{len(frames)}':>8s}")
        offset = np.asarray(results[1][1].edges.get("lidar0", {}).get("outline_offset_m", [0.0, 0.0]))[:2]
        in_camera = np.mean([f.camera.T_camera_board[:3, :2] @ offset for f in frames], axis=0)
        print(f"{name:18s}planes + edges: the outline's offset from the pattern's middle (its nuisance) "
              f"({', '.join(f'{1000 * x:+.1f}' for x in offset)}) mm along the board's x, y; in camera axes, "
              f"mean over frames ({', '.join(f'{1000 * x:+.1f}' for x in in_camera)}) mm")
        T_edges = transforms[1][1]
        outside = total = 0
        scans = {x.name: x.scan for x in ds.frames}
        for f in frames:
            P = read_sweep(scans[f.name]).points
            B = transform_points(T_inverse(f.camera.T_camera_board) @ T_edges, P)
            def within(m: float) -> np.ndarray:
                return (B[:, 0] > -m) & (B[:, 0] < w + m) & (B[:, 1] > -m) & (B[:, 1] < h + m)

            near = (np.abs(P @ f.lidar.plane.normal - f.lidar.plane.distance) < PLANE_BAND_M) & within(BEYOND_M)
            beyond = ~within(0.03)
            outside += int((near & beyond).sum())
            total += int(near.sum())
        print(f"{name:18s}outside: {outside} of {total} returns within {100 * PLANE_BAND_M:.0f} cm of a board's plane "
              f"lie 3-{100 * BEYOND_M:.0f} cm beyond its outline")


if __name__ == "__main__":
    main()
