"""Finding the checkerboard's inner corners in an image.

Recorded images defeat any single detector setting, so several are tried in turn: the sector-based
detector (``findChessboardCornersSB``) on an image pyramid, the reduced copies of a large image first and the
full image last, with the fast flags (corners refined at full resolution); then at full resolution with its
accuracy and normalisation flags; then the classic detector with sub-pixel refinement.
"""
from __future__ import annotations

import multiprocessing

import cv2
import numpy as np

from geometry.board import BoardModel

from ..errors import MeasurementError
from .detection import CornerDetection, subpixel_refine

_SB_ATTEMPTS = (
    ("SB exhaustive+accuracy", cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY),
    ("SB normalize+exhaustive+accuracy",
     cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY),
    ("SB normalize+exhaustive", cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_EXHAUSTIVE),
    ("SB default", 0),
)


def square_gray(gray: np.ndarray, corners: np.ndarray, pattern: tuple[int, int]) -> np.ndarray:
    """The mean grey level of a 3 x 3 pixel patch at the centre of each square between the inner corners
    (the mean of its four corners), (rows - 1, cols - 1)."""
    cols, rows = pattern
    g = corners.reshape(rows, cols, 2)
    centres = 0.25 * (g[:-1, :-1] + g[1:, :-1] + g[:-1, 1:] + g[1:, 1:])
    blurred = cv2.blur(gray, (3, 3))
    x = np.clip(np.rint(centres[..., 0]).astype(int), 0, gray.shape[1] - 1)
    y = np.clip(np.rint(centres[..., 1]).astype(int), 0, gray.shape[0] - 1)
    return blurred[y, x].astype(float)


def _subpixel(gray: np.ndarray, corners: np.ndarray, pattern: tuple[int, int], max_half: int = 5
              ) -> tuple[np.ndarray, int]:
    """``subpixel_refine`` of a whole grid of corners, the window's half-size 40% of the smallest square side
    read from the grid."""
    grid = corners.reshape(pattern[1], pattern[0], 2)
    sides = np.concatenate([np.linalg.norm(np.diff(grid, axis=0), axis=2).ravel(),
                            np.linalg.norm(np.diff(grid, axis=1), axis=2).ravel()])
    return subpixel_refine(gray, corners, 0.4 * float(sides.min()), max_half)


# Seconds the classic detector (the last resort) may run on one image.
CLASSIC_BUDGET_S = 20.0
# Reduced copies are searched first: the detector's cost grows with the pixel count, while the pattern is
# found as well once its squares are this many pixels wide or more.
MIN_SQUARE_PX_REDUCED = 12.0
# Images of this many pixels or more try both settings on their reduced copies. Below it, the second does not
# pay: where the pattern is not found in a reduced copy (a small board, a fisheye's edge), each failed search
# there costs more than the whole image's (1024 x 800 fisheye images: 130 and 210 ms failing at half size, 65 ms
# found at full size), while the first, where it finds the pattern, saves some 45 ms.
MIN_PIXELS_BOTH_REDUCED = 1.2e6
# Flag sets for each level of the pyramid, most often successful first. Without the accuracy flag (which
# makes the detector 4x slower) and with the two ``cornerSubPix`` passes that follow, the corners are as
# accurate: 0.053 px RMS against the truth either way on 30 rendered 1024x768 boards, 0.057 px at 1920x1208.
# A finer copy's search around the pattern a coarser one saw: this many of that copy's squares beyond its outer
# inner corners (the board's outer squares and border must be in view).
CROP_MARGIN_SQUARES = 4.0
_PYRAMID_ATTEMPTS = (
    ("SB exhaustive", cv2.CALIB_CB_EXHAUSTIVE),
    ("SB normalize+exhaustive", cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_EXHAUSTIVE),
)


def detect_chessboard(gray: np.ndarray, board: BoardModel, budget_s: float | None = CLASSIC_BUDGET_S
                      ) -> CornerDetection | None:
    """Inner corners of the checkerboard ``board`` in an 8-bit greyscale image, or None when no setting finds
    them all.

    First on a pyramid with the fast flags: reduced copies (halved while the image is 1000 px or larger),
    then the full image, the corners refined at full resolution; then at full resolution with every
    setting. The sector-based detector's
    corners carry a systematic, board-wide error (in simulation a scale error of about 4e-4 that moves each
    board's depth by millimetres, the same way on every board); the final ``cornerSubPix`` step on the full
    image's gradient removes most of it, whichever copy the pattern was found in. The classic detector, last,
    runs within ``budget_s`` seconds; past it, :class:`MeasurementError` (the frame is skipped with that
    reason).
    """
    pattern = board.inner_corners_shape
    found = _detect_pyramid(gray, pattern)
    if found is None:
        found = _detect_full(gray, pattern, budget_s)
    if found is None:
        return None
    return CornerDetection(found.corners_px, found.method, square_gray=square_gray(gray, found.corners_px, pattern))


# The most a corner may leave the line of its neighbours along a row or column, as a share of their distance:
# a board seen at any angle through any lens bends its grid smoothly (a square 1.7 times the next, the most
# perspective gives, is 0.5); a grid that jumps is the detector's mistake.
MAX_GRID_BEND = 0.5


def grid_is_smooth(corners: np.ndarray, pattern: tuple[int, int]) -> bool:
    """Whether each inner corner lies near the middle of its two neighbours along every row and column (within
    ``MAX_GRID_BEND`` of their half-distance)."""
    grid = corners.reshape(pattern[1], pattern[0], 2)
    for g in (grid, grid.transpose(1, 0, 2)):
        if g.shape[1] < 3:
            continue
        bend = np.linalg.norm(g[:, 2:] - 2 * g[:, 1:-1] + g[:, :-2], axis=2)
        half = 0.5 * np.linalg.norm(g[:, 2:] - g[:, :-2], axis=2)
        if np.any(bend > MAX_GRID_BEND * half):
            return False
    return True


def _sector(image: np.ndarray, pattern: tuple[int, int], flags: int) -> np.ndarray | None:
    """``findChessboardCornersSB``'s whole grid, or None. Its search draws from OpenCV's random generator, whose
    state every call moves on: seeded here, each image gets the same answer whatever was detected before it (in
    its thread), so a dataset's measurements do not depend on its frames' order or the workers' count (without
    it, one image of a 4-board set gave a true grid on its thread's first call and a broken one after)."""
    cv2.setRNGSeed(0)
    ok, corners = cv2.findChessboardCornersSB(image, pattern, flags=flags)
    if not ok or corners is None or len(corners) != pattern[0] * pattern[1]:
        return None
    corners = corners.reshape(-1, 2).astype(float)
    return corners if grid_is_smooth(corners, pattern) else None


def _found(level: np.ndarray, pattern: tuple[int, int], flags: int, box: tuple | None) -> np.ndarray | None:
    """The sector detector's corners in ``level`` (in its pixels), searched first within ``box`` (x0, y0, x1,
    y1) when given, then in the whole copy; None when not found."""
    for x0, y0, x1, y1 in ([box] if box is not None else []) + [(0, 0, level.shape[1], level.shape[0])]:
        corners = _sector(level[y0:y1, x0:x1], pattern, flags)
        if corners is not None:
            return corners + (x0, y0)
    return None


def _detect_pyramid(gray: np.ndarray, pattern: tuple[int, int]) -> CornerDetection | None:
    copies, level = [gray], gray
    while max(level.shape) >= 1000:
        level = cv2.pyrDown(level)
        copies.append(level)
    box = None  # where a coarser copy saw the pattern too small to trust: the finer copy searches there first
    for level in reversed(copies):  # coarsest first, the full image last
        scale = gray.shape[1] / level.shape[1]
        # A small image's reduced copy gets the first setting alone: a failed search there costs more than the
        # whole image's (below).
        attempts = _PYRAMID_ATTEMPTS if level is gray or gray.size >= MIN_PIXELS_BOTH_REDUCED else \
            _PYRAMID_ATTEMPTS[:1]
        for name, flags in attempts:
            c = _found(level, pattern, flags, box)
            if c is None:
                continue
            grid = c.reshape(pattern[1], pattern[0], 2)
            side = min(np.linalg.norm(np.diff(grid, axis=0), axis=2).min(),
                       np.linalg.norm(np.diff(grid, axis=1), axis=2).min())
            if side < MIN_SQUARE_PX_REDUCED and level is not gray:
                # Too small here to trust: the next finer copy (twice the size) searches the pattern's box with a
                # margin of CROP_MARGIN_SQUARES squares first, a fraction of the whole image's cost.
                m = CROP_MARGIN_SQUARES * side
                lo, hi = 2 * (c.min(axis=0) - m), 2 * (c.max(axis=0) + m)
                box = (max(int(lo[0]), 0), max(int(lo[1]), 0), int(hi[0]) + 1, int(hi[1]) + 1)
                break
            # Pixel centres: x_full = (x_reduced + 0.5) * scale - 0.5.
            full = (c + 0.5) * scale - 0.5
            # Two refinements at full resolution: a wide window pulls the corners in from the reduced copy's
            # sampling, then the usual window settles them on the saddle point.
            full, _ = _subpixel(gray, full, pattern, max_half=int(np.clip(0.4 * side * scale, 2, 12)))
            refined, half = _subpixel(gray, full, pattern)
            at = f" at 1/{scale:.0f}" if level is not gray else ""
            return CornerDetection(refined, f"{name}{at}+subpix{half}")
    return None


def _detect_full(gray: np.ndarray, pattern: tuple[int, int], budget_s: float | None = None
                 ) -> CornerDetection | None:
    for name, flags in _SB_ATTEMPTS:
        corners = _sector(gray, pattern, flags)
        if corners is not None:
            refined, half = _subpixel(gray, corners, pattern)
            return CornerDetection(refined, f"{name}+subpix{half}")
    corners = _classic_bounded(gray, pattern, budget_s) if budget_s is not None else _classic(gray, pattern)
    if corners is not None:
        return CornerDetection(corners, "classic+subpix")
    return None


def _classic(gray: np.ndarray, pattern: tuple[int, int]) -> np.ndarray | None:
    found, corners = cv2.findChessboardCorners(
        gray, pattern, flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
    if not found or corners is None:
        return None
    crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-3)
    corners = cv2.cornerSubPix(gray, corners.astype(np.float32), (5, 5), (-1, -1), crit).reshape(-1, 2)
    return corners.astype(float) if grid_is_smooth(corners, pattern) else None


def _classic_child(gray, pattern, conn) -> None:
    cv2.setNumThreads(1)
    conn.send(_classic(gray, pattern))
    conn.close()


def _classic_bounded(gray: np.ndarray, pattern: tuple[int, int], budget_s: float) -> np.ndarray | None:
    """The classic detector in a child process that is stopped after ``budget_s`` seconds (it can run for
    minutes on some dark or noisy images, and a native call cannot be interrupted otherwise)."""
    # A fork server: a clean process (forked children of a process whose OpenCV thread pool is running can
    # deadlock), started once and forked from for each image that needs it.
    try:
        ctx = multiprocessing.get_context("forkserver")
        ctx.set_forkserver_preload(["cv2", "estimators.camera.chessboard"])
    except ValueError:  # no fork server on this platform: spawn (slower to start)
        ctx = multiprocessing.get_context("spawn")
    receive, send = ctx.Pipe(duplex=False)
    child = ctx.Process(target=_classic_child, args=(gray, pattern, send), daemon=True)
    child.start()
    send.close()
    try:
        if not receive.poll(budget_s):
            raise MeasurementError(f"corner detection ran past its time budget of {budget_s:g} s (the classic "
                                   "detector on an image where the sector detector found no board)",
                                   hint="check the image's exposure, or that the board is in it")
        try:
            return receive.recv()
        except EOFError:  # the child died
            return None
    finally:
        if child.is_alive():
            child.kill()
        child.join()
        receive.close()
