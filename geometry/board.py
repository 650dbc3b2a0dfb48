"""The planar target: a checkerboard, or a ChArUco board (a checkerboard with ArUco markers in its white
squares, so that every inner corner carries an id and a partial view still gives the board's pose).

Board frame: origin at one corner of the physical board, x along its width (``squares[0]`` squares),
y along its height (``squares[1]`` squares), z = x cross y, the board's normal, pointing away from
the printed side (into the board, away from a camera that sees the pattern). For a ChArUco board this is
OpenCV's board frame (origin at the pattern's top-left corner as printed, y down the printed page) shifted
by the pattern offset; inner corner ``k`` is ChArUco corner id ``k``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


# A checkerboard has at most this many squares along a side (far more than any printable board).
MAX_SQUARES = 100
# A square or a board larger than these (m) is no calibration board's: its size given in millimetres or centimetres.
MAX_SQUARE_M, MAX_BOARD_M = 0.5, 5.0
CHECKERBOARD, CHARUCO = "checkerboard", "charuco"
PATTERNS = (CHECKERBOARD, CHARUCO)


def aruco_dictionary_size(name: object) -> int:
    """Markers in OpenCV's predefined ArUco dictionary ``name`` (e.g. ``DICT_5X5_100``); ValueError naming
    the known ones when there is no such dictionary."""
    import cv2

    known = sorted(k for k in dir(cv2.aruco) if k.startswith("DICT_") and isinstance(getattr(cv2.aruco, k), int))
    if not isinstance(name, str) or name not in known:
        raise ValueError(f"Expected dictionary as one of OpenCV's ({', '.join(known)}), got {name!r}")
    return int(cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name)).bytesList.shape[0])


# When dataset.yaml gives no board size: the board is taken to reach at most this far (m) beyond the printed
# pattern on each side (white borders are a few centimetres; a stand's posts and feet are beyond).
UNKNOWN_SIZE_MARGIN_M = 0.15


@dataclass(frozen=True)
class BoardModel:
    """A checkerboard of ``squares = (nx, ny)`` squares of ``square_size`` m, printed on a board.

    ``size`` is the physical board ``(width, height)`` in m, or None when unknown (then the pattern's
    extent is only a lower bound). ``pattern_offset`` is the board corner to pattern corner offset;
    when None the pattern is centred.
    """

    squares: tuple[int, int]
    square_size: float
    size: tuple[float, float] | None = None
    pattern_offset: tuple[float, float] | None = None
    # ChArUco only: the pattern, the markers' side (m), OpenCV's dictionary name, and OpenCV's legacy layout
    # (before 4.6, boards with an even number of rows started with a white square)
    pattern: str = CHECKERBOARD
    marker_size: float | None = None
    dictionary: str | None = None
    legacy_pattern: bool = False

    def __post_init__(self):
        nx, ny = (int(s) for s in self.squares)
        if nx < 3 or ny < 3 or nx > MAX_SQUARES or ny > MAX_SQUARES:
            raise ValueError(f"Expected 3 to {MAX_SQUARES} squares along each side, got {nx} x {ny}")
        if not (self.square_size > 0 and np.isfinite(self.square_size)):
            raise ValueError(f"Expected a positive square_size in metres, got {self.square_size}")
        if self.square_size > MAX_SQUARE_M:
            raise ValueError(f"Expected square_size in metres, at most {MAX_SQUARE_M:g}, got {self.square_size:g} "
                             "(millimetres?)")
        object.__setattr__(self, "squares", (nx, ny))
        object.__setattr__(self, "square_size", float(self.square_size))
        if self.size is not None:
            w, h = (float(s) for s in self.size)
            if not (np.isfinite(w) and np.isfinite(h)):
                raise ValueError(f"Expected a finite board size, got {w} x {h}")
            if max(w, h) > MAX_BOARD_M:
                raise ValueError(f"Expected the board size in metres, at most {MAX_BOARD_M:g} a side, got {w:g} x "
                                 f"{h:g} (millimetres?)")
            if w + 1e-9 < nx * self.square_size or h + 1e-9 < ny * self.square_size:
                raise ValueError(
                    f"Expected the board size {w} x {h} m to hold the {nx * self.square_size:.3f} x "
                    f"{ny * self.square_size:.3f} m pattern")
            object.__setattr__(self, "size", (w, h))
        if self.pattern_offset is not None:
            offset = tuple(float(o) for o in self.pattern_offset)
            if len(offset) != 2 or not np.all(np.isfinite(offset)):
                raise ValueError(f"Expected pattern_offset as two finite numbers (m), got {self.pattern_offset}")
            object.__setattr__(self, "pattern_offset", offset)
        if self.pattern not in PATTERNS:
            raise ValueError(f"Expected pattern in {PATTERNS}, got {self.pattern!r}")
        if self.pattern == CHARUCO:
            if self.marker_size is None or self.dictionary is None:
                raise ValueError("Expected marker_size (m) and dictionary for a charuco board")
            m = float(self.marker_size)
            if not (np.isfinite(m) and 0 < m < self.square_size):
                raise ValueError(f"Expected marker_size between 0 and the square size {self.square_size} m, "
                                 f"got {self.marker_size}")
            object.__setattr__(self, "marker_size", m)
            object.__setattr__(self, "legacy_pattern", bool(self.legacy_pattern))
            size = aruco_dictionary_size(self.dictionary)
            if size < self.n_markers:
                raise ValueError(f"Expected a dictionary of at least {self.n_markers} markers for "
                                 f"{nx} x {ny} squares, got {self.dictionary} ({size} markers)")

    @property
    def is_charuco(self) -> bool:
        return self.pattern == CHARUCO

    @property
    def n_markers(self) -> int:
        """ChArUco markers on the board: one in each white square."""
        nx, ny = self.squares
        return nx * ny // 2 if self.is_charuco else 0

    @property
    def first_square_black(self) -> bool:
        """Whether the pattern's square (0, 0) is black (OpenCV's legacy ChArUco layout flips it for an
        even number of rows)."""
        return not (self.is_charuco and self.legacy_pattern and self.squares[1] % 2 == 0)

    @property
    def inner_corners_shape(self) -> tuple[int, int]:
        """OpenCV ``patternSize``: (columns, rows) of inner corners."""
        return self.squares[0] - 1, self.squares[1] - 1

    @property
    def pattern_extent(self) -> tuple[float, float]:
        return self.squares[0] * self.square_size, self.squares[1] * self.square_size

    @property
    def size_known(self) -> bool:
        return self.size is not None

    @property
    def extent(self) -> tuple[float, float]:
        """The board's (width, height): its given size, or the pattern's extent when unknown."""
        return self.size if self.size is not None else self.pattern_extent

    @property
    def unknown_margin(self) -> float:
        """How far (m) the board may reach beyond :attr:`extent` on each side: 0 when its size is given, else
        ``UNKNOWN_SIZE_MARGIN_M`` around the pattern (a board's white border)."""
        return 0.0 if self.size is not None else UNKNOWN_SIZE_MARGIN_M

    @property
    def judged_extent(self) -> tuple[float, float]:
        """The largest (width, height) the board can have: its size, or the pattern's extent grown by
        :attr:`unknown_margin` on each side. LiDAR returns are judged and trimmed by it."""
        w, h = self.extent
        return w + 2 * self.unknown_margin, h + 2 * self.unknown_margin

    @property
    def offset(self) -> np.ndarray:
        """Board corner to pattern corner, in the board frame (m)."""
        if self.pattern_offset is not None:
            return np.array(self.pattern_offset)
        pw, ph = self.pattern_extent
        w, h = self.extent
        return np.array([(w - pw) / 2.0, (h - ph) / 2.0])

    def inner_corners(self) -> np.ndarray:
        """(M, 3) inner corners in the board frame, row by row, as OpenCV's detector orders them."""
        cols, rows = self.inner_corners_shape
        s = self.square_size
        i, j = np.meshgrid(np.arange(1, cols + 1), np.arange(1, rows + 1))
        xy = np.column_stack([i.ravel() * s, j.ravel() * s]) + self.offset
        return np.column_stack([xy, np.zeros(len(xy))])

    def outline(self) -> np.ndarray:
        """(4, 3) corners of the board's extent in the board frame, going round."""
        w, h = self.extent
        return np.array([[0, 0, 0], [w, 0, 0], [w, h, 0], [0, h, 0]], dtype=float)

    @property
    def centre(self) -> np.ndarray:
        w, h = self.extent
        return np.array([w / 2.0, h / 2.0, 0.0])

    def reflectance(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Reflectance in [0, 1] at board coordinates: black squares 0, white paper and margins 1 (a
        ChArUco board's markers are not drawn here: see ``simulation.rendering``'s texture).

        Points outside the board get NaN.
        """
        x = np.asarray(x, dtype=float)
        y = np.asarray(y, dtype=float)
        w, h = self.extent
        out = np.ones(np.broadcast(x, y).shape)
        outside = (x < 0) | (x > w) | (y < 0) | (y > h)
        px = (x - self.offset[0]) / self.square_size
        py = (y - self.offset[1]) / self.square_size
        nx, ny = self.squares
        inside = (px >= 0) & (px < nx) & (py >= 0) & (py < ny)
        black = inside & ((np.floor(px) + np.floor(py)) % 2 == (0 if self.first_square_black else 1))
        out[black] = 0.0
        out[outside] = np.nan
        return out
