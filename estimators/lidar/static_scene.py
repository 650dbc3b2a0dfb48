"""The static scene behind the board: what every frame of a dataset sees while only the board (and whoever
holds it) moves.

The rig stands still during a calibration, so walls, doors, furniture and the ground return at the same place
in most frames, while the board is somewhere else in each. A board candidate must be mostly in front of that
background (foreground). Three forms, by what the recording tells:

- **Range image** (3D sweeps whose points carry a beam index, from a ``ring`` field or an organised cloud's row, or
  found from the returns' elevations, ``lidar.beam_rings``):
  per beam and azimuth column, the background range is the farthest range that a quarter of the frames (at
  least two) return within half the margin of each other (each frame's farthest return within one column
  either side, as returns wander by a column between sweeps). A point nearer than that was seen through by
  those frames: something that moves (the board, the person holding it), even when the boards of most frames
  cover that cell; boards held at one place in a few frames do not make a surface. Over a window of neighbouring
  cells (rig vibration of a few centimetres, column jitter, depth edges), a point is foreground when it
  matches no background range within ``margin_m`` and lies nearer than some of them (or the window has none).
- **Direction bins** (3D clouds with no beam index whose elevations do not fall into beams: a non-repetitive
  pattern's): the same
  range image over bins of elevation and azimuth, their size chosen so that a sweep returns a few points in each
  (:func:`direction_bin`), so that a board standing on a table or held by a wall is still in front of the
  surface behind it.
- **Per-beam ranges** (2D scans): the range image with one beam row.

A background range counts only where it is *settled*: returned by more than half the frames that do not see
something nearer there. Boards held at one place in a few frames of a cloud cropped to a box around the boards
(nothing behind them but air) do not make a surface, so the next frame's board there stays foreground.

The rig moved between frames when a frame contradicts the static scene. It is judged on the background alone:
the returns on settled cells that match the background, lie beyond it (the frame sees through a surface the
others return), or lie in front of it on a surface that other frames return too (a rig that moved half-way: two
groups of frames, each consistent with itself). A frame whose matching share is under ``moved_fraction``, or
``moved_drop`` under the typical frame's, was taken from elsewhere. Returns in front of the background that no
other frame repeats (the board, its holder) do not count, so a board that fills most of a cropped cloud does
not make the rig look moved, nor do objects left standing at one place in front of it for several frames
(surfaces that lie together within a box of ``max_object_m``: a board on its stand, its holder); a frame with fewer
than ``min_judged`` judged returns is not judged. A frame that contradicts the scene keeps the model, with every
return it does not explain in its foreground (:func:`_checked`), and the note says so, as it says when the stillness
could not be judged or the background would not show a turn of the rig.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from geometry.vectors import row_norms


@dataclass(frozen=True)
class StaticSceneParams:
    margin_m: float = 0.12          # nearer than the background by this much: foreground
    ring_window: int = 1            # neighbouring beams compared (each side)
    column_window: int = 2          # neighbouring azimuth columns compared (each side)
    seen_through: int = 2           # range image: a background surface is returned by this many frames at least
    support_share: float = 0.25     # ... and by this share of the frames
    min_frames: int = 3             # fewer frames: no model
    moved_fraction: float = 0.9     # a frame matching less than this of its judged background: the rig moved
    moved_drop: float = 0.05        # ... or matching it this much less than the typical frame does
    min_judged: int = 100           # a frame with fewer returns on settled background is not judged
    max_object_m: float = 2.5       # surfaces repeated in front of the scene, all within a box this large: an
    min_object_returns: int = 20    # object left there (surfaces of fewer returns are not weighed)
    checked_turn_deg: float = 3.0   # the turn of the rig about its vertical axis the judgement must be able to see


@dataclass(frozen=True, eq=False)
class StaticScene:
    """Background model of a dataset's sweeps. ``kind``: ``range-image`` (beam indices or a 2D scan's beams),
    ``direction-bins`` (an unorganised cloud) or ``none`` (too few frames); ``match`` is each frame's share of its
    judged returns (on settled background) that match it rather than contradict it (nan: too few such returns to
    judge); ``moved`` the frames that contradict it, ``unchecked`` those not judged."""

    kind: str
    params: StaticSceneParams
    match: np.ndarray = field(default_factory=lambda: np.zeros(0))
    note: str = ""
    _background: np.ndarray | None = None  # range image: background range per beam and column (nan: none)
    _column_rad: float = 0.0
    _rows: np.ndarray | None = None      # range image: the beam ids, in row order
    _bin_rad: float | None = None        # direction bins: their side (rad), elevation rows in place of beams
    _frames: tuple = ()                  # the foreground mask of each frame the model was built from
    moved: tuple = ()                    # the frames that contradict the scene (by index)
    unchecked: tuple = ()                # the frames whose stillness could not be judged (by index)

    @property
    def usable(self) -> bool:
        return self.kind != "none"

    def foreground(self, points: np.ndarray, ring: np.ndarray | None = None) -> np.ndarray:
        """Mask of the points in front of the static scene (all True when there is no model)."""
        if not self.usable or len(points) == 0:
            return np.ones(len(points), dtype=bool)
        return self._classify(points, ring)[0]

    def cell_keys(self, points: np.ndarray, ring: np.ndarray | None = None) -> np.ndarray:
        """Each point's cell of the range image (beam or elevation bin, and column) as one key; -1 for a beam
        the model does not hold (and for every point when there is no model)."""
        if not self.usable or len(points) == 0:
            return np.full(len(points), -1, dtype=np.int64)
        row, col = self._cells(points, ring)
        return np.where(row >= 0, row * self._background.shape[1] + col, -1)

    def _cells(self, points: np.ndarray, ring: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """The points' (row, column) in the range image: rows by beam, or by elevation bin."""
        ring = _elevation_rows(points, self._bin_rad) if self._bin_rad is not None else ring
        return _cells(points, ring, self._rows, self._column_rad)

    def frame_foreground(self, k: int) -> np.ndarray | None:
        """The foreground mask of the k-th frame the model was built from (computed once, at the build), or
        None when the model is not usable."""
        return self._frames[k] if self.usable and k < len(self._frames) else None

    def to_dict(self) -> dict:
        return {"kind": self.kind, "note": self.note,
                "frames_matching_static_scene": [None if np.isnan(m) else round(float(m), 3) for m in self.match],
                "frames_contradicting_it": [int(k) for k in self.moved],
                "frames_not_judged": [int(k) for k in self.unchecked]}

    # -- range image -------------------------------------------------------------------------------------
    def _classify(self, points: np.ndarray, ring: np.ndarray | None, cells: tuple | None = None
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(foreground, static, beyond) masks: ``static`` when the range matches a background range of the
        window; ``beyond`` when it lies farther than every one of them (the frame sees through a surface the
        other frames return). ``cells``: the points' ``(row, column, range)`` when known already."""
        row, col, r = cells if cells is not None else (*self._cells(points, ring), _ranges(points))
        # Direction bins are a few azimuth steps wide already: one either side.
        dr, dc = self.params.ring_window, (self.params.column_window if self._bin_rad is None else 1)
        padded = _padded(self._background, dr, dc).ravel()
        width = self._background.shape[1] + 2 * dc
        held = row >= 0  # a beam the model does not hold has no background: foreground
        at = (np.where(held, row, 0) + dr) * width + col + dc  # the cell in the padded image
        margin = self.params.margin_m
        static = np.zeros(len(r), dtype=bool)
        behind = np.zeros(len(r), dtype=bool)
        seen = np.zeros(len(r), dtype=bool)
        with np.errstate(invalid="ignore"):
            for i in range(-dr, dr + 1):
                for j in range(-dc, dc + 1):
                    v = padded[at + i * width + j]
                    static |= np.abs(v - r) <= margin
                    behind |= v > r + margin
                    seen |= ~np.isnan(v)
        static &= held
        return ~static & (behind | ~seen | ~held), static, held & seen & ~static & ~behind


def _elevation_rows(points: np.ndarray, bin_rad: float) -> np.ndarray:
    """Each point's elevation bin (the rows of a range image of an unorganised cloud)."""
    return np.floor(np.arctan2(points[:, 2], np.hypot(points[:, 0], points[:, 1])) / bin_rad).astype(np.int64)


# Candidate sides (degrees) of an unorganised cloud's direction bins, finest first.
# How the note begins where the rig's stillness could not be judged (on every frame or some) or a turn would not show:
# the verdict's CHECK (``pipeline.verdict``).
STILLNESS_NOT_CHECKED = ("the rig's stillness could not be checked", "the rig's stillness is not checked")
BIN_SIDES_DEG = (0.2, 0.3, 0.5, 0.75, 1.0, 1.5, 2.0)


def direction_bin(points: np.ndarray, min_returns: float = 3.0) -> float:
    """The side (rad) of an unorganised cloud's direction bins: the finest of ``BIN_SIDES_DEG`` at which the
    sweep's occupied bins hold ``min_returns`` returns or more (median), so that most bins a surface covers are
    returned in every sweep."""
    az = _azimuth(points)
    for side in np.deg2rad(BIN_SIDES_DEG):
        keys = _elevation_rows(points, side) * 100000 + (az / side).astype(np.int64)
        _, counts = np.unique(keys, return_counts=True)
        if np.median(counts) >= min_returns:
            return float(side)
    return float(np.deg2rad(BIN_SIDES_DEG[-1]))


def _ranges(points: np.ndarray) -> np.ndarray:
    return row_norms(points)


def _azimuth(points: np.ndarray) -> np.ndarray:
    return np.mod(np.arctan2(points[:, 1], points[:, 0]), 2 * np.pi)


def _cells(points: np.ndarray, ring: np.ndarray | None, rows: np.ndarray, column_rad: float
           ) -> tuple[np.ndarray, np.ndarray]:
    """(row, column) of each point in the range image; row -1 for a beam the model does not hold."""
    n_cols = int(np.ceil(2 * np.pi / column_rad))
    col = np.minimum((_azimuth(points) / column_rad).astype(np.int64), n_cols - 1)
    beams = np.zeros(len(points), dtype=np.int64) if ring is None else np.asarray(ring, dtype=np.int64)
    pos = np.clip(np.searchsorted(rows, beams), 0, len(rows) - 1)
    row = np.where(rows[pos] == beams, pos, -1)
    return row, col


def _padded(image: np.ndarray, dr: int, dc: int) -> np.ndarray:
    """The range image with ``dr`` rows of nan above and below (no beam there) and its columns wrapped ``dc``
    either side (azimuth is periodic)."""
    wrapped = np.concatenate([image[:, image.shape[1] - dc:], image, image[:, :dc]], axis=1) if dc else image
    nan = np.full((dr, wrapped.shape[1]), np.nan)
    return np.concatenate([nan, wrapped, nan], axis=0)


def _column_width(points: list[np.ndarray], rings: list[np.ndarray | None]) -> float:
    """The sensor's azimuth step: the median gap between successive returns of one beam (clamped to
    0.05-2 degrees), from the first frame."""
    P, ring = points[0], rings[0]
    beams = np.zeros(len(P), dtype=np.int64) if ring is None else ring
    gaps = []
    for b in np.unique(beams)[:64]:
        az = np.sort(_azimuth(P[beams == b]))
        d = np.diff(az)
        d = d[d > 1e-5]
        if len(d) > 10:
            gaps.append(np.median(d))
    step = float(np.median(gaps)) if gaps else np.deg2rad(0.2)
    return float(np.clip(step, np.deg2rad(0.05), np.deg2rad(2.0)))


def _build_range_image(points: list[np.ndarray], rings: list[np.ndarray | None], params: StaticSceneParams,
                       bin_rad: float | None = None) -> StaticScene:
    """The range image of the sweeps, rows by beam (``rings``) or, given ``bin_rad``, by elevation bin (the
    columns then as wide)."""
    from scipy import ndimage  # here: scipy.ndimage, unused from the cache
    if bin_rad is not None:
        rings = [_elevation_rows(P, bin_rad) for P in points]
    rows = np.unique(np.concatenate([np.zeros(1, np.int64) if r is None else np.unique(r) for r in rings]))
    column = _column_width(points, rings) if bin_rad is None else bin_rad
    n_cols = int(np.ceil(2 * np.pi / column))
    F = len(points)
    stack = np.full((F, len(rows), n_cols), np.nan)
    cells = []  # each frame's (row, column, range), for its classification below
    for k, (P, ring) in enumerate(zip(points, rings)):
        row, col = _cells(P, ring, rows, column)
        r = _ranges(P)
        cells.append((row, col, r))
        ok = row >= 0
        img = np.full(len(rows) * n_cols, np.inf)
        np.minimum.at(img, row[ok] * n_cols + col[ok], r[ok])  # the nearest return of the cell
        img[np.isinf(img)] = -np.inf
        # Each frame's farthest return within one column either side: returns of one surface wander by a
        # column between sweeps, and a board held at one place in several frames must not hide the wall
        # that the other frames see through it.
        far = ndimage.maximum_filter(img.reshape(len(rows), n_cols), size=(1, 3), mode="wrap")
        stack[k] = np.where(np.isfinite(far), far, np.nan)
    m = min(F, max(params.seen_through, int(np.ceil(params.support_share * F))))
    # Farthest first, no return last (sorted in place: the stack is the largest array here, F of the image).
    ordered = np.nan_to_num(stack, nan=-np.inf)
    np.negative(ordered, out=ordered)
    ordered.sort(axis=0)
    np.negative(ordered, out=ordered)
    # The farthest range that m frames return within half the margin of each other: a surface that stays.
    background = np.full(ordered.shape[1:], np.nan)
    for i in range(F - m, -1, -1):  # nearest first, so the farthest qualifying cluster is written last
        with np.errstate(invalid="ignore"):  # -inf - -inf where no frame returns
            ok = (ordered[i] - ordered[i + m - 1] <= 0.5 * params.margin_m) & np.isfinite(ordered[i + m - 1])
        background[ok] = ordered[i][ok]
    del ordered
    # Settled: returned by m frames and by more than half of those that see nothing nearer there. A board held
    # at one place in a few frames of a cloud cropped to the boards is not (the other frames return nothing).
    margin = params.margin_m
    with np.errstate(invalid="ignore"):
        front = stack < background - margin
        near = np.subtract(stack, background)
        np.abs(near, out=near)
        returned = np.sum(near <= margin, axis=0)
        del near
        background[(returned < m) | (returned <= 0.5 * (F - front.sum(axis=0)))] = np.nan
    scene = StaticScene("range-image" if bin_rad is None else "direction-bins", params, _background=background,
                        _column_rad=column, _rows=rows, _bin_rad=bin_rad)
    judged, foreground = [], []
    for k, (P, ring) in enumerate(zip(points, rings)):
        fg, static, beyond = scene._classify(P, ring, cells[k])
        # In front of a settled surface on a surface of its own that m frames (3 at least) return: a second
        # static scene (a board left at one place for two frames is not one), when it is larger than an object
        # that can stand still in front of the scene for a few frames (a board on its stand, its holder).
        # (counted on the cells in front of the scene alone: a few of them, where all frames would cost F^2)
        cells_k = np.flatnonzero(front[k])
        repeated = np.zeros(front[k].shape, dtype=bool)
        with np.errstate(invalid="ignore"):
            near = np.abs(stack.reshape(F, -1)[:, cells_k] - stack[k].ravel()[cells_k]) <= 0.5 * margin
        repeated.ravel()[cells_k] = np.sum(near, axis=0) >= max(m, 3)
        row, col, _ = cells[k]
        on = fg & (row >= 0) & repeated[np.maximum(row, 0), col]
        judged.append((static, beyond | (on & _displaced(P, on, repeated, row, col, params))))
        foreground.append(fg)
    return _checked(scene, judged, tuple(foreground), points, rings)


def _displaced(points: np.ndarray, on: np.ndarray, image: np.ndarray, row: np.ndarray, col: np.ndarray,
               params: StaticSceneParams) -> np.ndarray:
    """Of the returns ``on`` (those on the cells of ``image``: in front of the settled scene, on a surface other
    frames repeat), the ones that show the scene displaced rather than an object left standing in front of it.
    Connected regions of cells (neighbouring beams and columns) larger than ``max_object_m`` (the diagonal of
    their returns' box) count in any case (a wall); the smaller ones count too unless together they lie within
    one such box: a board on its stand and its holder left at one place for a few frames make one place, a rig
    moved half-way shows pieces of its scene all round (regions of fewer than ``min_object_returns`` returns
    are not weighed in that box)."""
    from scipy import ndimage  # here: scipy.ndimage, unused from the cache
    out = np.zeros(len(points), dtype=bool)
    if not on.any():
        return out
    labels, n = ndimage.label(image, structure=np.ones((3, 3), dtype=bool))
    lab = labels[row[on], col[on]]
    idx = np.flatnonzero(on)
    P = points[idx]
    lo = np.full((n + 1, 3), np.inf)
    hi = np.full((n + 1, 3), -np.inf)
    np.minimum.at(lo, lab, P)
    np.maximum.at(hi, lab, P)
    large = np.linalg.norm(hi - lo, axis=1) > params.max_object_m
    objects = ~large & (np.bincount(lab, minlength=n + 1) >= params.min_object_returns)
    if objects.any() and np.linalg.norm(hi[objects].max(axis=0) - lo[objects].min(axis=0)) > params.max_object_m:
        large |= objects
    out[idx] = large[lab]
    return out


def _judged_masks(scene: StaticScene, points: np.ndarray, ring: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """A sweep's returns that match the static scene and those that lie beyond it: a single sweep's judgement,
    without the other frames' repeats."""
    _, static, beyond = scene._classify(points, ring)
    return static, beyond


def _share(static: np.ndarray, against: np.ndarray, min_judged: int) -> float:
    n = static.sum() + against.sum()
    return float(static.sum() / n) if n >= min_judged else np.nan


def _names(frames) -> str:
    return ", ".join(str(int(k)) for k in frames[:8]) + (" ..." if len(frames) > 8 else "")


def _checked(scene: StaticScene, judged: list[tuple[np.ndarray, np.ndarray]], foreground: tuple,
             points: list[np.ndarray], rings: list) -> StaticScene:
    """The scene with its judgement of the rig's stillness: ``judged`` holds each frame's masks of the returns
    that match the static scene and of those that contradict it.

    A frame that contradicts the scene (the rig moved, or the scene changed) keeps the model: every return the
    scene does not explain stays in its foreground, so its board stays a candidate; only the note says so. (A
    board is in front of whatever the scene holds there, so a contradicted model still leaves it in front, while
    dropping the model for every frame leaves each board among all the clutter of its room.) Frames with too few
    returns on settled background are not judged, and a scene that would not show a turn of the rig by
    ``checked_turn_deg`` about its vertical axis (the ground alone, in a cloud cropped to the boards) is said to
    leave the stillness unchecked."""
    p = scene.params
    match = np.array([_share(s, b, p.min_judged) for s, b in judged])
    typical = float(np.nanmedian(match)) if np.isfinite(match).any() else 1.0
    limit = max(p.moved_fraction, typical - p.moved_drop)
    with np.errstate(invalid="ignore"):
        moved = tuple(int(k) for k in np.nonzero(match < limit)[0])
    unjudged = tuple(int(k) for k in np.nonzero(~np.isfinite(match))[0])
    notes = []
    if moved:
        notes.append(f"frame(s) {_names(moved)} contradict the static scene (as little as "
                     f"{100 * np.nanmin(match):.0f}% of their returns on settled background match it, the rest lie "
                     "beyond it or on surfaces that other frames repeat, more than an object left at one place): "
                     "the rig moved, or the "
                     "scene changed; the scene is kept, and every return of theirs that it does not explain stays a "
                     "board candidate")
        foreground = tuple(~judged[k][0] if k in moved else f for k, f in enumerate(foreground))
    if len(unjudged) == len(match):
        notes.append(f"{STILLNESS_NOT_CHECKED[0]}: no frame has {p.min_judged} returns on settled "
                     "background (a cloud cropped to the boards?)")
    elif unjudged:
        notes.append(f"{STILLNESS_NOT_CHECKED[0]} on frame(s) {_names(unjudged)}: fewer than "
                     f"{p.min_judged} of their returns lie on settled background")
    if len(unjudged) < len(match) and not moved:
        # The power of the judgement: the best-judged frame turned by the checked angle either way.
        k = int(np.nanargmax([s.sum() + b.sum() if np.isfinite(m) else -1 for (s, b), m in zip(judged, match)]))
        turns = []
        for sign in (-1.0, 1.0):
            a = sign * np.deg2rad(p.checked_turn_deg)
            Rz = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
            turns.append(_share(*_judged_masks(scene, points[k] @ Rz.T, rings[k]), p.min_judged))
        if not all(t < limit for t in turns):
            notes.append(f"{STILLNESS_NOT_CHECKED[1]}: a {p.checked_turn_deg:g}-degree turn of the rig about "
                         "its vertical axis would not show against the background in view (too little of it changes "
                         "with a turn: the ground alone, a cloud cropped to the boards?)")
    return replace(scene, match=match, note="; ".join(notes), _frames=foreground, moved=moved, unchecked=unjudged)


def build_static_scene(points: list[np.ndarray], rings: list[np.ndarray | None] | None = None,
                       params: StaticSceneParams = StaticSceneParams()) -> StaticScene:
    """The static scene of a dataset's frames: points (N_k, 3) or, for 2D scans, (N_k, 2) in the LiDAR frame,
    and each frame's beam indices when known (None: unorganised). 2D scans use one beam row."""
    if len(points) < params.min_frames:
        return StaticScene("none", params, note=f"{len(points)} frame(s): a static scene needs "
                                                f"{params.min_frames} or more")
    points = [np.column_stack([P[:, :2], np.zeros(len(P))]) if P.shape[1] == 2 else P for P in points]
    rings = rings or [None] * len(points)
    planar = all(np.allclose(P[:, 2], 0.0) for P in points)
    if planar or all(r is not None for r in rings):
        rings = [None] * len(points) if planar else rings
        return _build_range_image(points, rings, params)
    return _build_range_image(points, rings, params, direction_bin(points[0]))
