"""A checkerboard drawn into an image as polygons (OpenCV's anti-aliased fill), fast enough for every image of a
continuous recording; the exposure's motion blur as the mean of the board drawn at instants across it.

A second image generator beside ``rendering`` (which casts rays through a whole scene): a grey background, the
board's white outline and its black squares, each square's sides cut into pieces so that the lens' distortion
bends them. Checkerboards only (a ChArUco board's markers are ``rendering``'s).

OpenCV's anti-aliased fill smooths an edge only along the image's rows: drawn at the image's own size, every edge's
height is rounded to a whole row, which moves each corner's ``v`` by up to half a pixel (sd 0.29 px, the same for
every corner of one row of a level board). The board is therefore drawn on ``ROWS_PER_PIXEL`` rows per pixel and
the rows averaged (sd 0.07 px left; 0.05 along the rows).
"""
from __future__ import annotations

import cv2
import numpy as np

from geometry.board import BoardModel
from geometry.camera import CameraModel
from geometry.rotations import transform_points

# Drawing subpixel precision: coordinates in 1/16 px (cv2's ``shift``).
_SHIFT = 4
BACKGROUND, WHITE, BLACK = 110.0, 215.0, 25.0
ROWS_PER_PIXEL = 4


def _outline(x0: float, y0: float, x1: float, y1: float, pieces: int) -> np.ndarray:
    """A rectangle's boundary in the board frame, each side cut into ``pieces``: (4 pieces, 3)."""
    s = np.linspace(0.0, 1.0, pieces, endpoint=False)
    xs = np.concatenate([x0 + (x1 - x0) * s, np.full(pieces, x1), x1 - (x1 - x0) * s, np.full(pieces, x0)])
    ys = np.concatenate([np.full(pieces, y0), y0 + (y1 - y0) * s, np.full(pieces, y1), y1 - (y1 - y0) * s])
    return np.column_stack([xs, ys, np.zeros_like(xs)])


def _board_polygons(board: BoardModel, pieces: int) -> tuple[np.ndarray, list[np.ndarray]]:
    """The board's outline and its black squares, in the board frame."""
    w, h = board.extent
    squares = []
    nx, ny = board.squares
    for i in range(nx):
        for j in range(ny):
            if (i + j) % 2 == (0 if board.first_square_black else 1):
                x0, y0 = board.offset + board.square_size * np.array([i, j])
                squares.append(_outline(x0, y0, x0 + board.square_size, y0 + board.square_size, pieces))
    return _outline(0.0, 0.0, w, h, 4 * pieces), squares


def draw_board(camera: CameraModel, board: BoardModel, poses: np.ndarray, rng: np.random.Generator,
               pixel_noise: float = 2.0, pieces: int = 3) -> np.ndarray:
    """An 8-bit greyscale image of the board at ``poses`` (``T_camera_board``, (k, 4, 4)): the mean of the board
    drawn at each (k instants across the exposure: its motion blur), with Gaussian pixel noise."""
    outline, squares = _board_polygons(board, pieces)
    S = ROWS_PER_PIXEL
    acc = np.zeros((camera.height * S, camera.width), np.float32)
    for T in np.asarray(poses).reshape(-1, 4, 4):
        img = np.full(acc.shape, BACKGROUND, np.uint8)
        polys = [outline] + squares
        pts = [camera.project(transform_points(T, p)) for p in polys]
        if all(np.all(np.isfinite(p)) for p in pts):
            # Pixel v spans [v - 1/2, v + 1/2): on the fine rows its centre row is (v + 1/2) S - 1/2.
            pts = [np.column_stack([p[:, 0], (p[:, 1] + 0.5) * S - 0.5]) for p in pts]
            fixed = [np.round(np.clip(p, -1e5, 1e5) * (1 << _SHIFT)).astype(np.int32) for p in pts]
            cv2.fillPoly(img, fixed[:1], WHITE, cv2.LINE_AA, _SHIFT)
            cv2.fillPoly(img, fixed[1:], BLACK, cv2.LINE_AA, _SHIFT)
        acc += img
    acc = acc.reshape(camera.height, S, camera.width).mean(axis=1)
    acc /= max(len(np.asarray(poses).reshape(-1, 4, 4)), 1)
    acc = cv2.GaussianBlur(acc, (0, 0), 0.5) + rng.normal(0.0, pixel_noise, acc.shape).astype(np.float32)
    return np.clip(np.rint(acc), 0, 255).astype(np.uint8)
