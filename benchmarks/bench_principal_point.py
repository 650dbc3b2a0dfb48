"""Which side is biased when the planes and the board's edges disagree: the recorded sets calibrated with
`--edges` under the dataset's intrinsics and with the principal point moved (make bench; each set skipped when
absent from ../shared/realdata; `python benchmarks/bench_principal_point.py [--shift PX]`).

A principal point that is off moves every board sideways in the camera (its outline), while its plane barely
moves: the edges and the planes then call for different extrinsics. Printed per shift: the planes-against-edges
test (d2 on 6 dof and its p-value), the boards' plane-consistency variance factor (chi-square per dof: how far
the camera's and the LiDAR's planes disagree, 1 ideal) and the estimate's translation (camera frame, mm) against
the source tool's reference.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
from dataclasses import replace
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # as the CLI does (see bench_refinement.py)

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from estimators import calibrate  # noqa: E402
from estimators.io.dataset import load_dataset  # noqa: E402
from estimators.solvers.refinement_options import RefinementOptions  # noqa: E402

REALDATA = Path(__file__).resolve().parents[2] / "shared" / "realdata"
SETS = ("acfr_ouster64_b", "acfr_vlp16_a")


def reference_T(path: Path) -> np.ndarray | None:
    """The source tool's reference ``T_camera_lidar`` of a recorded set, or None when the set has none."""
    ref = path / "reference.json"
    if not ref.is_file():
        return None
    T = json.loads(ref.read_text()).get("T_camera_lidar")
    return None if T is None else np.array(T, dtype=float)


def _reference(path: Path) -> np.ndarray | None:
    """The reference's translation (mm, camera frame), or None."""
    T = reference_T(path)
    return None if T is None else 1000 * T[:3, 3]


def recorded_sets():
    """``(name, path, dataset)`` of each recorded set present in ../shared/realdata (an absent one is said)."""
    for name in SETS:
        path = REALDATA / name
        if not path.is_dir():
            print(f"{name}: not in {REALDATA}; skipped")
            continue
        yield name, path, load_dataset(path)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--shift", type=float, default=20.0, help="principal point shift (px; default 20)")
    args = ap.parse_args()
    s = args.shift
    shifts = [(0.0, 0.0), (s, 0.0), (-s, 0.0), (0.0, s), (0.0, -s), (1.5 * s, 0.5 * s)]
    for name, path, ds in recorded_sets():
        ref = _reference(path)
        print(f"{name}: --edges with the principal point moved (dataset's cx, cy = {ds.camera.K[0, 2]:.1f}, "
              f"{ds.camera.K[1, 2]:.1f} px)" + ("" if ref is None else
                                               f"; reference t = ({ref[0]:.1f}, {ref[1]:.1f}, {ref[2]:.1f}) mm"))
        print(f"  {'dcx px':>7s}{'dcy px':>7s}{'planes vs edges d2':>20s}{'p':>8s}{'vf':>7s}   t (mm, camera)")
        for dx, dy in shifts:
            p = ds.camera.params.copy()
            p[2] += dx
            p[3] += dy
            res = calibrate(replace(ds, camera=ds.camera.with_params(p)), options=RefinementOptions(edges=True),
                            posterior=None, rng=np.random.default_rng(0))
            edges = res.edges.get("lidar0") or {}
            test = edges.get("planes_against_edges")
            vf = res.pair_results[("cam0", "lidar0")].refinement.variance_factor  # the pair's own planes
            t = 1000 * res.T_camera_lidar[:3, 3]
            d2 = f"{test['d2']:20.1f}{test['p_value']:8.3f}" if test else f"{'-':>20s}{'-':>8s}"
            print(f"  {dx:7.0f}{dy:7.0f}{d2}{vf:7.2f}   "
                  f"({t[0]:.1f}, {t[1]:.1f}, {t[2]:.1f})")


if __name__ == "__main__":
    main()
