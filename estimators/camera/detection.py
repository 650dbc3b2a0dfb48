"""A board's corners as found in one image: the record both detectors return (``CornerDetection``) and the
saddle-point refinement they share (``subpixel_refine``).
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True, eq=False)
class CornerDetection:
    corners_px: np.ndarray  # (M, 2), ordered as BoardModel.inner_corners() (or as corner_ids)
    method: str
    corner_ids: np.ndarray | None = None  # ChArUco: which inner corners were seen (ascending); None: all
    # Checkerboard: the image's grey level at the centre of each square between the inner corners, (rows - 1,
    # cols - 1) in the corners' order. The detector cannot tell which corner family it started from, so which
    # squares are black is read here (``board_pose`` turns it into ``pattern_inverted``).
    square_gray: np.ndarray | None = None


def subpixel_refine(gray: np.ndarray, corners: np.ndarray, half_px: float, max_half: int = 5
                    ) -> tuple[np.ndarray, int]:
    """Corners moved to the saddle point of the image gradient (``cornerSubPix``) in a window of half-size
    ``half_px`` (rounded down, 2 to ``max_half`` px), which the caller keeps inside the neighbouring squares."""
    half = int(np.clip(np.floor(half_px), 2, max_half))
    crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_MAX_ITER, 100, 1e-4)
    out = cv2.cornerSubPix(gray, corners.astype(np.float32).reshape(-1, 1, 2).copy(), (half, half), (-1, -1), crit)
    return out.reshape(-1, 2).astype(float), half
