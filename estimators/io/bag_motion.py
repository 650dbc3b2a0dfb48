"""A bag whose board moves, read into a :class:`~estimators.io.motion_track.MotionTrack`: every image's board corners
and every sweep's board returns with their own times, streaming (memory bounded by a second of messages).

Each image: the board's corners found (``bag_extract``'s detector, then refined at full resolution), listed in the
order nearest the previous image's (a checkerboard's grid is found from either end; the board's pose must not flip
between images) and the board's pose solved. Each sweep: its returns' times (``point_times``), then the board
among its returns (``lidar.board_segmentation``, gated by the camera's board in the image nearest its stamp; the
board moves centimetres within the clocks' offset, far less than the gate), its returns kept with their times. A
sweep or image that gives nothing is counted under its reason.
"""
from __future__ import annotations

from collections import Counter, deque

import numpy as np

from geometry.board import BoardModel
from geometry.camera import CameraModel

from ..camera.board_pose import estimate_board_pose
from ..camera.detection import CornerDetection, subpixel_refine
from ..errors import AmbiguousBoardError, BagError, MeasurementError
from ..lidar.board_segmentation import find_board
from .image_io import to_gray8
from .motion_track import MotionTrack
from .ros_messages import decode_image, decode_point_cloud, decode_point_times

# A sweep is segmented once the camera's stream has passed its stamp by this (ns): its nearest image is then seen.
LOOK_AHEAD_NS = 150_000_000
# Recent images kept for gating sweeps (ns).
KEEP_VIEWS_NS = 1_000_000_000
# An image this near (s) the one before is ordered like it; after a longer gap, by the image's own axes.
CONTINUOUS_S = 0.5

REASONS = {
    "views": "images with the board (all used)",
    "no_board": "images without the board found (out of view, or too blurred to find)",
    "bad_pose": "images whose corners give no board pose",
    "sweeps": "sweeps with the board (all used)",
    "no_board_in_sweep": "sweeps without the board's returns (no board-sized plane where the camera puts it)",
    "ambiguous": "sweeps where two board-sized planes agree with the camera's board",
    "no_view": "sweeps with no image of the board within 0.5 s",
    "no_times": "sweeps whose returns' times are unknown",
}


class MovingBoardReader:
    """Feed it a bag's messages in order (:meth:`image`, :meth:`sweep`), then :meth:`track`."""

    def __init__(self, board: BoardModel, camera: CameraModel, detect, topic: str, rng: np.random.Generator):
        self.board, self.camera, self.detect, self.topic, self.rng = board, camera, detect, topic, rng
        self.counts: Counter = Counter()
        self.origin: int | None = None
        self.stamps: list[int] = []
        self.corners: list[np.ndarray] = []
        self.recent: deque = deque()  # (stamp ns, CameraBoardObservation) of the last second's images
        self.pending: deque = deque()  # (stamp ns, cloud message) awaiting the camera's stream
        self.gaps: deque = deque(maxlen=64)
        self.last_sweep: int | None = None
        self.camera_now = -1
        self.sweep_stamps: list[int] = []
        self.points: list[np.ndarray] = []
        self.offsets: list[np.ndarray] = []
        self.sources: Counter = Counter()

    def image(self, stamp: int, msg) -> None:
        self.origin = stamp if self.origin is None else min(self.origin, stamp)
        self.camera_now = max(self.camera_now, stamp)
        gray = to_gray8(decode_image(msg, self.topic))
        found = self.detect(gray, self.board)
        if found is None:
            self.counts["no_board"] += 1
        else:
            corners = self._ordered(self._refined(gray, found), stamp)
            seen = np.flatnonzero(np.all(np.isfinite(corners), axis=1))
            ids = None if len(seen) == len(corners) else seen
            try:
                obs = estimate_board_pose(CornerDetection(corners[seen], "moving", ids), self.board, self.camera)
            except MeasurementError:
                self.counts["bad_pose"] += 1
            else:
                self.counts["views"] += 1
                self.stamps.append(stamp)
                self.corners.append(corners.astype(np.float32))
                self.recent.append((stamp, obs))
        while self.recent and self.recent[0][0] < stamp - KEEP_VIEWS_NS:
            self.recent.popleft()
        self._flush(self.camera_now - LOOK_AHEAD_NS)

    def sweep(self, stamp: int, msg) -> None:
        self.origin = stamp if self.origin is None else min(self.origin, stamp)
        if self.last_sweep is not None and stamp > self.last_sweep:
            self.gaps.append(stamp - self.last_sweep)
        self.last_sweep = stamp
        self.pending.append((stamp, msg))
        self._flush(self.camera_now - LOOK_AHEAD_NS)

    def _refined(self, gray: np.ndarray, corners: np.ndarray) -> np.ndarray:
        """Corners refined at full resolution within a third of the smallest square's side in the image."""
        seen = np.all(np.isfinite(corners), axis=1)
        if seen.sum() < 2:
            return corners
        pts = corners[seen]
        side = np.min(np.linalg.norm(np.diff(pts, axis=0), axis=1)) if len(pts) > 1 else 6.0
        out = corners.copy()
        out[seen] = subpixel_refine(gray, pts, max(side, 6.0) / 3.0)[0]
        return out

    def _ordered(self, corners: np.ndarray, stamp: int) -> np.ndarray:
        """A checkerboard's corners in the order nearest the previous image's (or, after a gap, the one whose first
        corner is the upper-left one); a ChArUco board's as found (its markers fix the order)."""
        if self.board.is_charuco:
            return corners
        if self.stamps and (stamp - self.stamps[-1]) * 1e-9 <= CONTINUOUS_S:
            prev = self.corners[-1]
            if np.linalg.norm(corners[::-1] - prev, axis=1).max() < np.linalg.norm(corners - prev, axis=1).max():
                return corners[::-1].copy()
            return corners
        return corners if corners[0].sum() <= corners[-1].sum() else corners[::-1].copy()

    def _flush(self, until: int) -> None:
        while self.pending and self.pending[0][0] <= until:
            self._segment(*self.pending.popleft())

    def _segment(self, stamp: int, msg) -> None:
        near = [(abs(s - stamp), obs) for s, obs in self.recent]
        if not near or min(near, key=lambda x: x[0])[0] > KEEP_VIEWS_NS // 2:
            self.counts["no_view"] += 1
            return
        obs = min(near, key=lambda x: x[0])[1]
        period = float(np.median(self.gaps)) * 1e-9 if self.gaps else None
        xyz, _ = decode_point_cloud(msg, self.topic)
        times = decode_point_times(msg, self.topic, period)
        if times is None:
            self.counts["no_times"] += 1
            return
        self.sources[times.source] += 1
        try:
            found = find_board(xyz, self.board, obs, self.rng)
        except AmbiguousBoardError:
            self.counts["ambiguous"] += 1
            return
        except MeasurementError:
            self.counts["no_board_in_sweep"] += 1
            return
        from scipy.spatial import cKDTree  # here: scipy.spatial takes 0.3 s to import
        dist, index = cKDTree(xyz).query(found.points)
        index = index[dist < 1e-9]
        self.counts["sweeps"] += 1
        self.sweep_stamps.append(stamp)
        self.points.append(xyz[index].astype(np.float32))
        self.offsets.append(times.offset_s[index].astype(np.float32))

    def track(self, bag) -> MotionTrack:
        """The record, or a :class:`BagError` saying why the recording gives none."""
        self._flush(np.iinfo(np.int64).max)
        if self.counts["no_times"] and not self.sweep_stamps:
            raise BagError("the board moves, and the sweeps' returns carry no time (no time field, and their stored "
                           "order is not the firing order): a moving board needs each return's time", path=bag,
                           hint="record the LiDAR driver's per-point time field, or hold the board still per pose")
        if len(self.stamps) < 10 or len(self.sweep_stamps) < 6:
            counts = ", ".join(f"{n} {REASONS[k]}" for k, n in self.counts.items() if n)
            raise BagError(f"the board moves, and too little of it was seen to follow it ({counts})", path=bag,
                           hint="keep the whole board in the camera's view and before the LiDAR while waving it")
        o = self.origin
        source = self.sources.most_common(1)[0][0] if self.sources else ""
        return MotionTrack(int(o), (np.array(self.stamps, dtype=np.int64) - o) * 1e-9, np.stack(self.corners),
                           (np.array(self.sweep_stamps, dtype=np.int64) - o) * 1e-9,
                           np.array([len(p) for p in self.points]), np.concatenate(self.points),
                           np.concatenate(self.offsets), source)
