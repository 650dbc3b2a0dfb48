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


def _subpixel(gray: np.ndarray, corners: np.ndarray, pattern: tuple[int, int]) -> tuple[np.ndarray, int]:
    """Corners moved to the saddle point of the image gradient (``cornerSubPix``) in a window that stays
    inside the neighbouring squares (half-size 40% of the smallest square side seen, 2-5 px)."""
    grid = corners.reshape(pattern[1], pattern[0], 2)
    sides = np.concatenate([np.linalg.norm(np.diff(grid, axis=0), axis=2).ravel(),
                            np.linalg.norm(np.diff(grid, axis=1), axis=2).ravel()])
    half = int(np.clip(np.floor(0.4 * sides.min()), 2, 5))
    crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_MAX_ITER, 100, 1e-4)
    out = cv2.cornerSubPix(gray, corners.astype(np.float32).reshape(-1, 1, 2).copy(), (half, half), (-1, -1), crit)
    return out.reshape(-1, 2).astype(float), half


def detect_corners(gray: np.ndarray, board: BoardModel) -> CornerDetection | None:
    """Inner corners of ``board`` in an 8-bit greyscale image, or None when no setting finds them all.

    The sector-based detector's corners carry a systematic, board-wide error (in simulation a scale
    error of about 4e-4 that moves each board's depth by millimetres, the same way on every board);
    a final ``cornerSubPix`` step on the image gradient removes most of it.
    """
    pattern = board.inner_corners_shape
    for name, flags in _SB_ATTEMPTS:
        found, corners = cv2.findChessboardCornersSB(gray, pattern, flags=flags)
        if found and corners is not None and len(corners) == pattern[0] * pattern[1]:
            refined, half = _subpixel(gray, corners.reshape(-1, 2), pattern)
            return CornerDetection(refined, f"{name}+subpix{half}")
    found, corners = cv2.findChessboardCorners(
        gray, pattern, flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
    if found and corners is not None:
        crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-3)
        corners = cv2.cornerSubPix(gray, corners.astype(np.float32), (5, 5), (-1, -1), crit)
        return CornerDetection(corners.reshape(-1, 2).astype(float), "classic+subpix")
    return None
