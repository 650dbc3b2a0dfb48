"""Corner detection: time and accuracy of the pyramid search (make bench; `python benchmarks/bench_corners.py`).

(a) The shared recorded images (1920x1208): median seconds per image on one core for the detection as it runs
    (reduced copies first, corners refined at full resolution) and for the full-resolution chain alone, the
    images detected by each, and the RMS difference of their corners.
(b) Rendered boards at 1024x768, 1920x1208 and 3840x2160 (the simulator's camera, its focal length scaled with
    the image): per-corner RMS error against the true projections, both ways, and the median time.
"""
from __future__ import annotations

import os
import sys
import time
from dataclasses import replace
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import cv2  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from estimators.camera import chessboard  # noqa: E402
from estimators.io.dataset import load_dataset  # noqa: E402
from estimators.simulation.rendering import render_image  # noqa: E402
from estimators.simulation.simulator import default_rig, sample_board_poses, scene_patches  # noqa: E402
from geometry.camera import CameraModel  # noqa: E402
from geometry.rotations import T_inverse, transform_points  # noqa: E402

REALDATA = Path(__file__).resolve().parents[2] / "shared" / "realdata"


def _timed(fn, *args):
    t0 = time.perf_counter()
    out = fn(*args)
    return out, time.perf_counter() - t0


def recorded() -> None:
    sets = [d for d in sorted(REALDATA.glob("*")) if (d / "dataset.yaml").is_file()]
    print("(a) recorded images, one core")
    print(f"{'set':18s}{'images':>7s}{'found now':>10s}{'found full-res':>15s}{'s/image now':>12s}"
          f"{'s/image full-res':>17s}{'max RMS diff px':>16s}")
    for d in sets:
        ds = load_dataset(d)
        pattern = ds.board.inner_corners_shape
        t_new, t_old, found_new, found_old, diff = [], [], 0, 0, []
        for f in ds.frames:
            gray = cv2.imread(str(f.image), cv2.IMREAD_GRAYSCALE)
            if gray is None:
                continue
            new, tn = _timed(chessboard.detect_chessboard, gray, ds.board)
            old, to = _timed(chessboard._detect_full, gray, pattern)
            t_new.append(tn)
            t_old.append(to)
            found_new += new is not None
            found_old += old is not None
            if new is not None and old is not None:
                diff.append(float(np.sqrt(np.mean(np.sum((new.corners_px - old.corners_px) ** 2, axis=1)))))
        print(f"{d.name:18s}{len(ds.frames):7d}{found_new:10d}{found_old:15d}{np.median(t_new):12.3f}"
              f"{np.median(t_old):17.3f}{max(diff) if diff else float('nan'):16.4f}")


def rendered(trials: int = 8) -> None:
    print("(b) rendered boards (per-corner RMS error against the truth, px; median s/image)")
    print(f"{'resolution':12s}{'found now':>10s}{'found full-res':>15s}{'err now':>9s}{'err full-res':>13s}"
          f"{'s now':>8s}{'s full-res':>11s}")
    base = default_rig(np.random.default_rng(0))
    for w, h in ((1024, 768), (1920, 1208), (3840, 2160)):
        k = w / 1024.0
        K = base.camera.K.copy()
        K[0, 0] *= k
        K[1, 1] *= k
        K[0, 2], K[1, 2] = w / 2.0, h / 2.0
        cam = CameraModel(K, base.camera.dist, w, h, base.camera.model, "bench")
        rig = replace(base, camera=cam)
        rng = np.random.default_rng(7)
        poses = sample_board_poses(rig, trials, rng)
        pattern = rig.board.inner_corners_shape
        errs_new, errs_old, t_new, t_old, fn, fo = [], [], [], [], 0, 0
        T_lc = T_inverse(rig.T_camera_lidar)
        for T_cb in poses:
            T_lb = T_lc @ T_cb
            patches, bi = scene_patches(rig, T_lb)
            gray = render_image(cam, T_lc, patches, bi, transform_points(T_lb, rig.board.outline()), rng)
            truth = cam.project(transform_points(T_cb, rig.board.inner_corners()))
            new, tn = _timed(chessboard.detect_chessboard, gray, rig.board)
            old, to = _timed(chessboard._detect_full, gray, pattern)
            t_new.append(tn)
            t_old.append(to)
            for det, errs in ((new, errs_new), (old, errs_old)):
                if det is not None:  # the pattern's 180-degree symmetry: the detector may list it reversed
                    errs.append(min((np.sum((c - truth) ** 2, axis=1) for c in (det.corners_px, det.corners_px[::-1])),
                                    key=np.sum))
            fn += new is not None
            fo += old is not None

        def rms(e):
            return float(np.sqrt(np.mean(np.concatenate(e)))) if e else float("nan")

        print(f"{f'{w}x{h}':12s}{fn:10d}{fo:15d}{rms(errs_new):9.3f}{rms(errs_old):13.3f}{np.median(t_new):8.3f}"
              f"{np.median(t_old):11.3f}")


def main() -> None:
    cv2.setNumThreads(1)
    if REALDATA.is_dir():
        recorded()
    else:
        print(f"(a) {REALDATA} is absent; skipped")
    rendered()


if __name__ == "__main__":
    main()
