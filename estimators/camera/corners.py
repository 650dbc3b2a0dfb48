"""Finding a board's inner corners in an image, by the detector its kind needs: a checkerboard's whole grid
(``chessboard``) or a ChArUco board's corners with their ids, whole or partly seen (``charuco``).
"""
from __future__ import annotations

import numpy as np

from geometry.board import BoardModel

from .charuco import detect_charuco
from .chessboard import CLASSIC_BUDGET_S, detect_chessboard
from .detection import CornerDetection


def detect_corners(gray: np.ndarray, board: BoardModel, budget_s: float | None = CLASSIC_BUDGET_S
                   ) -> CornerDetection | None:
    """The inner corners of ``board`` in an 8-bit greyscale image, or None where none are found: a checkerboard's
    whole grid (``chessboard.detect_chessboard``, its classic detector within ``budget_s`` seconds), a ChArUco
    board's corners seen, with their ids (``charuco.detect_charuco``)."""
    if board.is_charuco:
        return detect_charuco(gray, board)
    return detect_chessboard(gray, board, budget_s)
