"""The recorded sets, planes alone against planes and board edges, side by side
(make bench; each set skipped when absent from ../shared/realdata; `python benchmarks/bench_edges_recorded.py`).

With the planes alone the board's edges check the estimate; with `--edges` they are in it. Every estimate is the
engine's (``calibrate``, as ``lidarcam calibrate`` gives it), its halves solved again from its measurements.

Per set and model: the estimate's translation (camera frame, mm) and its distance from the source tool's
reference, and the reference's squared Mahalanobis distance under the estimate's covariance (``T_ref = T_hat
Exp(xi)``; against the same 99% limit): a reference a few centimetres away can lie inside the estimate's
uncertainty, where the boards, all a few metres in front of the rig, trade the rotation for the translation;
the LiDAR's board outlines' mean shift from the camera's (mm) and its p-value against its 99% limit
(with the planes alone the ends check the estimate; with the edges they are in it); the planes-against-edges test
(d2 on 6 dof, p); under the source tool's reference, the outlines' mean shift by the same fit (camera's board
poses); and the first and last halves of the frames calibrated apart: the squared Mahalanobis distance
of their difference against the sum of their covariances and its 99% limit.
"""
from __future__ import annotations

import os
import sys
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # as the CLI does (see bench_refinement.py)

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench_principal_point import recorded_sets, reference_T  # noqa: E402
from bench_realdata import solved_again  # noqa: E402

from estimators.rig_calibration import calibrate  # noqa: E402
from estimators.solvers import chi_square as chi2  # noqa: E402
from estimators.solvers.board_edges import crossings  # noqa: E402
from estimators.solvers.outline_check import outline_check  # noqa: E402
from estimators.solvers.range_model import frame_rings  # noqa: E402
from estimators.solvers.refinement_options import RefinementOptions  # noqa: E402
from geometry.rotations import T_inverse, T_log  # noqa: E402


def main() -> None:
    print(f"{'set':18s}{'model':16s}{'t (mm, camera)':>26s}{'from ref mm':>13s}{'ref d2':>8s}{'outline shift mm':>18s}"
          f"{'p':>8s}{'planes vs edges':>17s}{'halves d2':>11s}{'99% limit':>11s}")
    for name, path, ds in recorded_sets():
        T_ref = reference_T(path)
        ref = None if T_ref is None else 1000 * T_ref[:3, 3]
        frames = None
        for label, edges in (("planes (check)", False), ("planes + edges", True)):
            res = calibrate(path, rng=np.random.default_rng(0), samples=0, options=RefinementOptions(edges=edges))
            frames = [f for f in res.frames if f.usable]
            t = 1000 * res.T_camera_lidar[:3, 3]
            if ref is None:
                far = f"{'-':>13s}{'-':>8s}"
            else:
                xi_ref = T_log(T_inverse(res.T_camera_lidar) @ T_ref)
                far = f"{np.linalg.norm(t - ref):13.1f}{float(xi_ref @ np.linalg.solve(res.covariance, xi_ref)):8.1f}"
            e = (res.edges.get("lidar0") if edges else res.outline_checks.get(("cam0", "lidar0"))) or {}
            shift = (f"{1000 * np.linalg.norm(e['mean_shift_camera_m']):18.1f}{e['mean_shift_p_value']:8.3f}"
                     if "mean_shift_camera_m" in e else f"{'-':>18s}{'-':>8s}")
            test = e.get("planes_against_edges")
            test = f"{test['d2']:9.1f}, p {test['p_value']:.3f}" if test else "-"
            stems = [f.name for f in frames]
            half = len(stems) // 2
            ra, rb = (solved_again(res, stems=s, edges=edges) for s in (stems[:half], stems[half:]))
            xi = T_log(T_inverse(ra.T_camera_lidar) @ rb.T_camera_lidar)
            d2 = float(xi @ np.linalg.solve(ra.covariance + rb.covariance, xi))
            print(f"{name:18s}{label:16s}{'(' + ', '.join(f'{v:.1f}' for v in t) + ')':>26s}{far}{shift}"
                  f"{test:>17s}{d2:11.1f}{chi2.isf(0.01, 6):11.1f}")
        if ref is not None:
            shift = 1000 * np.linalg.norm(_outline_shift(frames, ds.board, T_ref)["mean_shift_camera_m"])
            print(f"{name:18s}{'reference':16s}{'(' + ', '.join(f'{v:.1f}' for v in ref) + ')':>26s}{'':21s}"
                  f"{shift:18.1f}{'-':>8s}")


def _outline_shift(frames, board, T: np.ndarray) -> dict:
    """The outlines' mean shift under ``T`` (the check's fit, with the camera's board poses; no covariance of
    ``T``: only the shift is printed)."""
    rings = frame_rings([f.lidar for f in frames])
    used = [(f, crossings(f.lidar.points, r, T_inverse(f.camera.T_camera_board) @ T, board))
            for f, r in zip(frames, rings) if r is not None]
    used = [(f, e) for f, e in used if e.size]
    record, _ = outline_check(T, [f.camera.T_camera_board for f, _ in used], [e for _, e in used], board,
                              [f.name for f, _ in used], np.zeros((6 + 6 * len(used),) * 2))
    return record


if __name__ == "__main__":
    main()
