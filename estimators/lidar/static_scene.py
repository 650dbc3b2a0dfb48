"""The static scene behind the board: what every frame of a dataset sees while only the board (and whoever
holds it) moves.

The rig stands still during a calibration, so walls, doors, furniture and the ground return at the same place
in most frames, while the board is somewhere else in each. A board candidate must be mostly in front of that
background (foreground). Three forms, by what the recording tells:

- **Range image** (3D sweeps whose points carry a beam index, from a ``ring`` field or an organised cloud's row):
  per beam and azimuth column, the background range is the farthest range that a quarter of the frames (at
  least two) return within half the margin of each other (each frame's farthest return within one column
  either side, as returns wander by a column between sweeps). A point nearer than that was seen through by
  those frames: something that moves (the board, the person holding it), even when the boards of most frames
  cover that cell; boards held at one place in a few frames do not make a surface. Over a window of neighbouring
  cells (rig vibration of a few centimetres, column jitter, depth edges), a point is foreground when it
  matches no background range within ``margin_m`` and lies nearer than some of them (or the window has none).
- **Voxel occupancy** (unorganised 3D clouds with no beam index): counts of the frames that occupy each voxel;
  a voxel held by half the frames or more is background, and a point is background when its voxel or a
  neighbour is.
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
not make the rig look moved; a frame with fewer than ``min_judged`` judged returns is not judged. With voxels,
the judged returns are those in a background voxel and those off the background that are not in front of it
(in their direction bin, no nearer than its farthest background voxel): a wall seen from elsewhere. The model
then says so and is not used: each frame falls back to the cues it holds alone.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from scipy import ndimage


@dataclass(frozen=True)
class StaticSceneParams:
    margin_m: float = 0.12          # nearer than the background by this much: foreground
    ring_window: int = 1            # neighbouring beams compared (each side)
    column_window: int = 2          # neighbouring azimuth columns compared (each side)
    voxel_m: float = 0.10           # voxel side for unorganised clouds
    seen_through: int = 2           # range image: a background surface is returned by this many frames at least
    support_share: float = 0.25     # ... and by this share of the frames
    min_frames: int = 3             # fewer frames: no model
    moved_fraction: float = 0.9     # a frame matching less than this of its judged background: the rig moved
    moved_drop: float = 0.05        # ... or matching it this much less than the typical frame does
    min_judged: int = 100           # a frame with fewer returns on settled background is not judged
    direction_bin_deg: float = 1.0  # voxels: the direction bins in which a return is judged in front or not


@dataclass(frozen=True, eq=False)
class StaticScene:
    """Background model of a dataset's sweeps. ``kind``: ``range-image``, ``voxels`` or ``none`` (too few
    frames, or the rig moved); ``match`` is each frame's share of its judged returns (on settled background)
    that match it rather than contradict it (nan: too few such returns to judge)."""

    kind: str
    params: StaticSceneParams
    match: np.ndarray = field(default_factory=lambda: np.zeros(0))
    note: str = ""
    _background: np.ndarray | None = None  # range image: background range per beam and column (nan: none)
    _column_rad: float = 0.0
    _rows: np.ndarray | None = None      # range image: the beam ids, in row order
    _voxels: np.ndarray | None = None    # voxels: sorted keys of background voxels
    _bins: tuple = ()                    # voxels: sorted direction-bin keys and the farthest background in each
    _frames: tuple = ()                  # the foreground mask of each frame the model was built from

    @property
    def usable(self) -> bool:
        return self.kind != "none"

    def foreground(self, points: np.ndarray, ring: np.ndarray | None = None) -> np.ndarray:
        """Mask of the points in front of the static scene (all True when there is no model)."""
        if not self.usable or len(points) == 0:
            return np.ones(len(points), dtype=bool)
        if self.kind == "voxels":
            return ~self._in_background_voxel(points)
        return self._classify(points, ring)[0]

    def frame_foreground(self, k: int) -> np.ndarray | None:
        """The foreground mask of the k-th frame the model was built from (computed once, at the build), or
        None when the model is not usable."""
        return self._frames[k] if self.usable and k < len(self._frames) else None

    def to_dict(self) -> dict:
        return {"kind": self.kind, "note": self.note,
                "frames_matching_static_scene": [None if np.isnan(m) else round(float(m), 3) for m in self.match]}

    # -- range image -------------------------------------------------------------------------------------
    def _classify(self, points: np.ndarray, ring: np.ndarray | None, cells: tuple | None = None
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(foreground, static, beyond) masks: ``static`` when the range matches a background range of the
        window; ``beyond`` when it lies farther than every one of them (the frame sees through a surface the
        other frames return). ``cells``: the points' ``(row, column, range)`` when known already."""
        row, col, r = cells if cells is not None else (*_cells(points, ring, self._rows, self._column_rad),
                                                       _ranges(points))
        dr, dc = self.params.ring_window, self.params.column_window
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

    # -- voxels ------------------------------------------------------------------------------------------
    def _in_background_voxel(self, points: np.ndarray) -> np.ndarray:
        keys = _voxel_keys(points, self.params.voxel_m)
        hit = np.zeros(len(points), dtype=bool)
        for off in _NEIGHBOURS:
            k = keys + off
            pos = np.clip(np.searchsorted(self._voxels, k), 0, max(len(self._voxels) - 1, 0))
            hit |= self._voxels[pos] == k if len(self._voxels) else False
        return hit

    def _not_in_front(self, points: np.ndarray) -> np.ndarray:
        """Returns in a direction bin that holds background voxels and no nearer than the farthest of them by
        the margin (and a voxel): off the background, such a return is not something in front of it (a board, a
        person) but the scene seen from elsewhere."""
        keys, far = self._bins
        if len(keys) == 0:
            return np.zeros(len(points), dtype=bool)
        k = _direction_keys(points, self.params.direction_bin_deg)
        pos = np.clip(np.searchsorted(keys, k), 0, len(keys) - 1)
        there = keys[pos] == k
        slack = self.params.margin_m + np.sqrt(3.0) * self.params.voxel_m
        return there & (_ranges(points) >= far[pos] - slack)


_SHIFT = 2 ** 20
_NEIGHBOURS = np.array([(i * _SHIFT + j) * _SHIFT + k for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)],
                       dtype=np.int64)


def _voxel_keys(points: np.ndarray, size: float) -> np.ndarray:
    ijk = np.floor(points / size).astype(np.int64) + _SHIFT // 2
    ijk = np.clip(ijk, 1, _SHIFT - 2)
    return (ijk[:, 0] * _SHIFT + ijk[:, 1]) * _SHIFT + ijk[:, 2]


def _direction_keys(points: np.ndarray, bin_deg: float) -> np.ndarray:
    """Key of each point's (azimuth, elevation) bin."""
    step = np.deg2rad(bin_deg)
    az = np.floor(_azimuth(points) / step).astype(np.int64)
    el = np.floor((np.arctan2(points[:, 2], np.hypot(points[:, 0], points[:, 1])) + np.pi) / step).astype(np.int64)
    return el * 100000 + az


def _ranges(points: np.ndarray) -> np.ndarray:
    return np.linalg.norm(points, axis=1)


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


def _build_range_image(points: list[np.ndarray], rings: list[np.ndarray | None], params: StaticSceneParams
                       ) -> StaticScene:
    rows = np.unique(np.concatenate([np.zeros(1, np.int64) if r is None else np.unique(r) for r in rings]))
    column = _column_width(points, rings)
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
    ordered = -np.sort(-np.nan_to_num(stack, nan=-np.inf), axis=0)  # farthest first; no return last
    # The farthest range that m frames return within half the margin of each other: a surface that stays.
    background = np.full(ordered.shape[1:], np.nan)
    with np.errstate(invalid="ignore"):  # -inf - -inf where no frame returns
        spans = [ordered[i] - ordered[i + m - 1] for i in range(F - m + 1)]
    for i in range(F - m, -1, -1):  # nearest first, so the farthest qualifying cluster is written last
        ok = (spans[i] <= 0.5 * params.margin_m) & np.isfinite(ordered[i + m - 1])
        background[ok] = ordered[i][ok]
    # Settled: returned by m frames and by more than half of those that see nothing nearer there. A board held
    # at one place in a few frames of a cloud cropped to the boards is not (the other frames return nothing).
    margin = params.margin_m
    with np.errstate(invalid="ignore"):
        front = stack < background - margin
        returned = np.sum(np.abs(stack - background) <= margin, axis=0)
        background[(returned < m) | (returned <= 0.5 * (F - front.sum(axis=0)))] = np.nan
    scene = StaticScene("range-image", params, _background=background, _column_rad=column, _rows=rows)
    judged, foreground = [], []
    for k, (P, ring) in enumerate(zip(points, rings)):
        fg, static, beyond = scene._classify(P, ring, cells[k])
        # In front of a settled surface on a surface of its own that m frames (3 at least) return: a second
        # static scene (a board left at one place for two frames is not one).
        with np.errstate(invalid="ignore"):
            repeated = front[k] & (np.sum(np.abs(stack - stack[k]) <= 0.5 * margin, axis=0) >= max(m, 3))
        row, col, _ = cells[k]
        judged.append((static, beyond | (fg & (row >= 0) & repeated[np.maximum(row, 0), col])))
        foreground.append(fg)
    return _checked(scene, judged, tuple(foreground))


def _build_voxels(points: list[np.ndarray], params: StaticSceneParams) -> StaticScene:
    per_frame = [np.unique(_voxel_keys(P, params.voxel_m)) for P in points]
    keys, counts = np.unique(np.concatenate(per_frame), return_counts=True)
    need = max(2, int(np.ceil(0.5 * len(points))))
    voxels = keys[counts >= need]
    # Each direction bin's farthest background voxel centre: a return off the background and not nearer than it
    # is not in front of the scene but the scene seen from elsewhere.
    centres = (np.stack([voxels // _SHIFT ** 2, voxels // _SHIFT % _SHIFT, voxels % _SHIFT], axis=1)
               - _SHIFT // 2 + 0.5) * params.voxel_m
    bins, inverse = np.unique(_direction_keys(centres, params.direction_bin_deg), return_inverse=True)
    far = np.full(len(bins), -np.inf)
    np.maximum.at(far, inverse.ravel(), _ranges(centres))
    scene = StaticScene("voxels", params, _voxels=voxels, _bins=(bins, far))
    background = [scene._in_background_voxel(P) for P in points]
    off = [~b & scene._not_in_front(P) for b, P in zip(background, points)]
    return _checked(scene, list(zip(background, off)), tuple(~b for b in background))


def _checked(scene: StaticScene, judged: list[tuple[np.ndarray, np.ndarray]], foreground: tuple = ()
             ) -> StaticScene:
    """The scene, or none when a frame contradicts it: ``judged`` holds each frame's masks of the returns that
    match the static scene and of those that contradict it."""
    p = scene.params
    match = np.array([s.sum() / (s.sum() + b.sum()) if s.sum() + b.sum() >= p.min_judged else np.nan
                      for s, b in judged])
    typical = float(np.nanmedian(match)) if np.isfinite(match).any() else 1.0
    with np.errstate(invalid="ignore"):
        moved = np.nonzero(match < max(p.moved_fraction, typical - p.moved_drop))[0]
    if len(moved):
        names = ", ".join(str(int(k)) for k in moved[:8])
        return StaticScene("none", p, match,
                           f"the rig seems to have moved: frame(s) {names} match the static scene for only "
                           f"{100 * match[moved].min():.0f}% of their returns on settled background (the rest see "
                           "through it or show it from elsewhere); each frame's board is found from its own cues")
    return replace(scene, match=match, _frames=foreground)


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
    return _build_voxels(points, params)
