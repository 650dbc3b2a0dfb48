"""Finding the checkerboard's inner corners in an image.

Recorded images defeat any single detector setting, so several are tried in turn: the sector-based
detector (``findChessboardCornersSB``) with and without its accuracy and normalisation flags, then the
classic detector with sub-pixel refinement.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from geometry.board import BoardModel

_SB_ATTEMPTS = (
    ("SB exhaustive+accuracy", cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY),
    ("SB normalize+exhaustive+accuracy",
     cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY),
    ("SB normalize+exhaustive", cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_EXHAUSTIVE),
    ("SB default", 0),
)


@dataclass(frozen=True, eq=False)
class CornerDetection:
    corners_px: np.ndarray  # (M, 2), ordered as BoardModel.inner_corners()
    method: str


def detect_corners(gray: np.ndarray, board: BoardModel) -> CornerDetection | None:
    """Inner corners of ``board`` in an 8-bit greyscale image, or None when no setting finds them all."""
    pattern = board.inner_corners_shape
    for name, flags in _SB_ATTEMPTS:
        found, corners = cv2.findChessboardCornersSB(gray, pattern, flags=flags)
        if found and corners is not None and len(corners) == pattern[0] * pattern[1]:
            return CornerDetection(corners.reshape(-1, 2).astype(float), name)
    found, corners = cv2.findChessboardCorners(
        gray, pattern, flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
    if found and corners is not None:
        crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-3)
        corners = cv2.cornerSubPix(gray, corners.astype(np.float32), (5, 5), (-1, -1), crit)
        return CornerDetection(corners.reshape(-1, 2).astype(float), "classic+subpix")
    return None
