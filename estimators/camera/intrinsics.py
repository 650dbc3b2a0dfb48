"""Intrinsics from the dataset's own images (Zhang's method via ``cv2.calibrateCamera``)."""
from __future__ import annotations

import cv2
import numpy as np

from geometry.board import BoardModel
from geometry.camera import PINHOLE, CameraModel


def calibrate_intrinsics(corner_sets: list[np.ndarray], board: BoardModel, width: int, height: int,
                         corner_ids: list[np.ndarray | None] | None = None) -> tuple[CameraModel, float]:
    """Pinhole (radial-tangential, k1 k2 p1 p2 k3) intrinsics and the RMS reprojection error (px).

    Needs at least 3 views of the board at different orientations. ``param_std`` holds OpenCV's standard
    deviations of ``[fx, fy, cx, cy, k1, k2, p1, p2, k3]`` (from the corner residuals, so as optimistic as
    they are; the refinement scales them with its corner-noise model). ``corner_ids``: per view, which
    inner corners it holds (ChArUco), None for all.
    """
    obj = board.inner_corners().astype(np.float32)
    ids = corner_ids if corner_ids is not None else [None] * len(corner_sets)
    objs = [obj if i is None else obj[i] for i in ids]  # a ChArUco view: the corners it saw
    imgs = [c.reshape(-1, 1, 2).astype(np.float32) for c in corner_sets]
    rms, K, dist, _, _, std, _, _ = cv2.calibrateCameraExtended(objs, imgs, (width, height), None, None)
    cam = CameraModel(K=K, dist=dist.ravel()[:5], width=width, height=height, model=PINHOLE,
                      source=f"calibrated from {len(corner_sets)} images (Zhang), RMS {rms:.3f} px",
                      param_std=np.asarray(std, dtype=float).ravel()[:9])
    return cam, float(rms)
