"""ChArUco boards: OpenCV's board object for a ``BoardModel``, its printed pattern, and the detection of its
inner corners with their ids in an image, whole or partly seen.

Every inner corner of a ChArUco board is identified by the ArUco markers in the two white squares beside it,
so a board cut by the image's edge still gives its pose, and the board frame is never ambiguous (a plain
checkerboard's is up to a half turn). OpenCV's detector interpolates the corners from the markers and refines
them; here they are refined once more at full resolution in a window inside the squares, as the
checkerboard's are (``detection.subpixel_refine``), in a window that keeps clear of the markers.
"""
from __future__ import annotations

import cv2
import numpy as np

from geometry.board import BoardModel

from .detection import CornerDetection, subpixel_refine

# A partial view is used from this many corners on (they must span the board's plane, not a line).
MIN_CHARUCO_CORNERS = 6
# ... and their spread across the shorter direction, in squares: corners along one row fix no plane.
MIN_CORNER_SPREAD_SQUARES = 0.5


def opencv_board(board: BoardModel) -> cv2.aruco.CharucoBoard:
    """OpenCV's ChArUco board for ``board`` (its pattern only: the board's margins are not OpenCV's)."""
    if not board.is_charuco:
        raise ValueError(f"Expected a charuco board, got pattern {board.pattern!r}")
    dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, board.dictionary))
    cb = cv2.aruco.CharucoBoard(board.squares, board.square_size, board.marker_size, dictionary)
    cb.setLegacyPattern(board.legacy_pattern)
    return cb


def pattern_image(board: BoardModel, px_per_square: int = 64) -> np.ndarray:
    """The printed pattern as an 8-bit image, ``px_per_square`` pixels per square, row 0 at the pattern's
    y = 0 edge (OpenCV's board frame and the board model's agree up to the pattern offset)."""
    nx, ny = board.squares
    return opencv_board(board).generateImage((nx * px_per_square, ny * px_per_square), marginSize=0, borderBits=1)


def pattern_reflectance(board: BoardModel):
    """The printed board's reflectance as a function of board coordinates (0 black, 1 white, NaN off the
    board): the checkerboard's own (``BoardModel.reflectance``), or for a ChArUco board OpenCV's printed pattern
    with its markers, sampled at the nearest texel (96 per square: a marker bit spans about 10)."""
    if not board.is_charuco:
        return board.reflectance
    texels = 96
    img = pattern_image(board, texels).astype(float) / 255.0
    ox, oy = board.offset
    w, h = board.extent

    def reflectance(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
        col = np.floor((x - ox) / board.square_size * texels).astype(int)
        row = np.floor((y - oy) / board.square_size * texels).astype(int)
        inside = (col >= 0) & (col < img.shape[1]) & (row >= 0) & (row < img.shape[0])
        out = np.ones(np.broadcast(x, y).shape)
        out[inside] = img[row[inside], col[inside]]
        out[(x < 0) | (x > w) | (y < 0) | (y > h)] = np.nan
        return out

    return reflectance


def detect_charuco(gray: np.ndarray, board: BoardModel) -> CornerDetection | None:
    """The ChArUco corners seen in an 8-bit greyscale image, with their ids (ascending), or None when fewer
    than ``MIN_CHARUCO_CORNERS`` are seen or they lie along a line."""
    # Markers the first pass missed (small or blurred ones, a few pixels per bit) are looked for again where
    # the board's layout puts them: in simulation 96% of the corners in the image are found instead of 81%.
    params = cv2.aruco.CharucoParameters()
    params.tryRefineMarkers = True
    detector = cv2.aruco.CharucoDetector(opencv_board(board), params)
    corners, ids, markers, marker_ids = detector.detectBoard(gray)
    if corners is None or ids is None or len(ids) < MIN_CHARUCO_CORNERS:
        return None
    ids = ids.ravel().astype(int)
    order = np.argsort(ids)
    ids, corners = ids[order], corners.reshape(-1, 2)[order].astype(float)
    if not spans_plane(board, ids):
        return None
    # The window of the full-resolution refinement stays between a corner and the markers beside it: its
    # half-size is the white margin round a marker, from the markers' typical side in the image. (A window
    # of 40% of the square, the checkerboard's, takes in marker edges: in simulation 0.18 px RMS against the
    # truth instead of 0.09 px.)
    sides = [np.linalg.norm(np.diff(np.vstack([m.reshape(4, 2), m.reshape(4, 2)[:1]]), axis=0), axis=1).min()
             for m in (markers or ())]
    margin = (board.square_size - board.marker_size) / (2 * board.marker_size)  # in marker sides
    refined, half = subpixel_refine(gray, corners, float(np.median(sides)) * margin if sides else 2.0)
    seen = f"{len(ids)} of {np.prod(board.inner_corners_shape)} corners"
    return CornerDetection(refined, f"charuco ({seen})+subpix{half}", corner_ids=ids)


def spans_plane(board: BoardModel, ids: np.ndarray) -> bool:
    """Whether the corners ``ids`` span the board's plane: at least ``MIN_CHARUCO_CORNERS`` of them, spread
    by ``MIN_CORNER_SPREAD_SQUARES`` squares across their main direction."""
    if len(ids) < MIN_CHARUCO_CORNERS:
        return False
    xy = board.inner_corners()[ids, :2]
    sv = np.linalg.svd(xy - xy.mean(0), compute_uv=False)
    # the standard deviation across the main direction, against a square
    return bool(sv[-1] / np.sqrt(len(ids)) >= MIN_CORNER_SPREAD_SQUARES * board.square_size / 2)
