"""Finding a board's inner corners in an image, by the detector its kind needs: a checkerboard's whole grid
(``chessboard``) or a ChArUco board's corners with their ids, whole or partly seen (``charuco``). What a search
of an image found is kept by the image's content (``FOUND_KEPT`` searches, the latest): the same pixels searched
again, as a session calibrating one folder several ways does, are not searched twice.
"""
from __future__ import annotations

import hashlib
import threading
from collections import OrderedDict

import numpy as np

from geometry.board import BoardModel

from .charuco import detect_charuco
from .chessboard import CLASSIC_BUDGET_S, detect_chessboard
from .detection import CornerDetection

# Searches kept: a few KB each (the corners and the squares' grey levels).
FOUND_KEPT = 4096
_FOUND: OrderedDict = OrderedDict()
_FOUND_LOCK = threading.Lock()  # images are measured on several threads


def detect_corners(gray: np.ndarray, board: BoardModel, budget_s: float | None = CLASSIC_BUDGET_S
                   ) -> CornerDetection | None:
    """The inner corners of ``board`` in an 8-bit greyscale image, or None where none are found: a checkerboard's
    whole grid (``chessboard.detect_chessboard``, its classic detector within ``budget_s`` seconds), a ChArUco
    board's corners seen, with their ids (``charuco.detect_charuco``). The same image (its pixels, shape and
    type) searched for the same board before gives what that search found (its arrays read-only)."""
    gray = np.ascontiguousarray(gray)
    key = (hashlib.blake2b(gray.data, digest_size=16).digest(), gray.shape, gray.dtype.str, board, budget_s)
    with _FOUND_LOCK:
        if key in _FOUND:
            _FOUND.move_to_end(key)
            return _FOUND[key]
    found = detect_charuco(gray, board) if board.is_charuco else detect_chessboard(gray, board, budget_s)
    if found is not None:
        for a in (found.corners_px, found.corner_ids, found.square_gray):
            if a is not None:
                a.setflags(write=False)
    with _FOUND_LOCK:
        _FOUND[key] = found
        while len(_FOUND) > FOUND_KEPT:
            _FOUND.popitem(last=False)
    return found
