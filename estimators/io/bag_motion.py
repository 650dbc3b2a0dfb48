"""A bag whose board moves, read into a :class:`~estimators.io.motion_track.MotionTrack`: every image's board corners
and every sweep's board returns with their own times, streaming (memory bounded by a second of messages).

Each image: the board's corners followed from the two images before (their motion carried on, each refined to its
saddle: a millisecond) or, where they cannot be, found by ``bag_extract``'s detector (five times a second while
the board is lost) and refined at full resolution; kept in an order that does not flip the board's pose between
images, and checked against the board's grid seen in perspective. Each sweep: its returns' times
(``point_times``), then the board among its returns (``lidar.board_segmentation``, gated by the camera's board in
the image nearest its stamp; the board moves centimetres within the clocks' offset, far less than the gate), found
in a worker process while the bag is read on and taken back in order. A sweep or image that gives nothing is
counted under its reason.
"""
from __future__ import annotations

from collections import Counter, deque
from pathlib import Path

import numpy as np

from geometry.board import BoardModel
from geometry.camera import CameraModel

from ..camera.board_pose import pose_of_corners
from ..camera.chessboard import MIN_SQUARE_PX_REDUCED
from ..camera.detection import subpixel_refine
from ..errors import AmbiguousBoardError, BagError, MeasurementError
from ..lidar.board_segmentation import SegmentationParams, find_board, range_gate
from .image_io import to_gray8
from .motion_track import MotionTrack
from .ros_messages import decode_image, decode_timed_cloud

# A sweep is segmented once the camera's stream has passed its stamp by this (ns): its nearest image is then seen.
LOOK_AHEAD_NS = 150_000_000
# Recent images kept for gating sweeps (ns).
KEEP_VIEWS_NS = 1_000_000_000
# An image this near (s) the one before is ordered like it; after a longer gap, by the image's own axes.
CONTINUOUS_S = 0.5
# Corners are followed from image to image across gaps up to this (ns): two periods of a 20 Hz camera, one of 10 Hz.
TRACK_GAP_NS = 120_000_000
# Corners farther than this (px RMS) from the board's grid seen in perspective are not the board's (a tracked
# corner on a wrong saddle, a detection gone astray); 0.2 px corners fit to about that.
MAX_GRID_RMS_PX = 1.0
# Images kept whole for the report: one every this (ns) of the board in view, at most this many.
EXAMPLE_EVERY_NS, MAX_EXAMPLES = 5_000_000_000, 8
# While the board is lost the detector looks at most once in this (ns); it is found again within that.
LOOK_EVERY_NS = 200_000_000
# The detector looks at a copy at most this wide (px), and where it finds no board there and the board is small,
# at the whole image (a board far away: reduced to 640 px, a 1024 x 768 image lost it on 2 of 12 simulated bags
# whose still poses were found at 960 px; ``MovingBoardReader._find``); the corners are then refined at full
# resolution.
DETECT_MAX_SIDE = 640
# The whole image is searched too where the board's squares were last seen under this many times the detector's
# smallest (``MIN_SQUARE_PX_REDUCED``) in the reduced copy: at 12 px there it missed a blurred board in every image
# of a simulated bag (19 px squares in a 1024 px image reduced to 640; the bag was refused), found whole.
REDUCED_MARGIN = 1.5
# Sweeps handed to the worker and not yet taken back, at most (memory: a few sweeps).
MAX_WAITING = 4

REASONS = {
    "views": "images with the board (all used)",
    "tracked": "  of them followed from the images before (the rest found by the detector)",
    "no_board": "images without the board found (out of view, or too blurred to find)",
    "off_grid": "images whose corners fit no board seen in perspective (left out)",
    "not_looked": "images not looked at while the board was lost (the detector looks 5 times a second)",
    "sweeps": "sweeps with the board (all used)",
    "no_board_in_sweep": "sweeps without the board's returns (no board-sized plane where the camera puts it)",
    "ambiguous": "sweeps where two board-sized planes agree with the camera's board",
    "no_view": "sweeps with no image of the board within 0.5 s",
    "no_times": "sweeps whose returns' times are unknown",
}


class MovingBoardReader:
    """Feed it a bag's messages in order (:meth:`image`, :meth:`sweep`), then :meth:`track`."""

    def __init__(self, board: BoardModel, camera: CameraModel, detect, topic: str, rng: np.random.Generator,
                 examples: Path | None = None):
        self.board, self.camera, self.detect, self.topic = board, camera, detect, topic
        self.seed = int(rng.integers(2 ** 31))  # sweep k's segmentation is seeded seed + k
        self.examples, self.example_stamps = examples, []  # the folder for the report's images, their stamps
        self.counts: Counter = Counter()
        self.images = 0
        self.origin: int | None = None
        self.stamps: list[int] = []
        self.corners: list[np.ndarray] = []
        self.recent: deque = deque()  # (stamp ns, index in corners) of the last second's images
        self.poses: dict = {}  # index in corners -> its board pose (or None), solved when a sweep asks
        self.last_pose: tuple | None = None  # (stamp ns, pose) last solved
        self.pool = None  # the worker that finds the board's returns in each sweep
        self.waiting: deque = deque()  # (stamp, returns, their times, camera's board, seed, future) in order
        self.inline = False  # True: no worker; each sweep's board found in this process
        self.segmented = 0
        self.lost_since: int | None = None  # the stamp since which the board is not found, or None
        self.last_look = -1  # the stamp the detector last looked at
        self.pending: deque = deque()  # (stamp ns, cloud message) awaiting the camera's stream
        self.gaps: deque = deque(maxlen=64)
        self.last_sweep: int | None = None
        self.camera_now = -1
        self.sweep_stamps: list[int] = []
        self.points: list[np.ndarray] = []
        self.offsets: list[np.ndarray] = []
        self.sources: Counter = Counter()
        self.against = 0  # sweeps whose time field ran against their stored order

    def image(self, stamp: int, msg) -> None:
        self.origin = stamp if self.origin is None else min(self.origin, stamp)
        self.camera_now = max(self.camera_now, stamp)
        self.images += 1
        gray = to_gray8(decode_image(msg, self.topic))
        corners = self._tracked(gray, stamp)
        if corners is not None and self._grid_rms_px(corners) > MAX_GRID_RMS_PX:
            corners = None  # followed onto a wrong saddle (a corner at the board's edge, blur): the detector looks
        if corners is not None:
            self.counts["tracked"] += 1
        elif self.lost_since is not None and stamp - self.last_look < LOOK_EVERY_NS:
            self.counts["not_looked"] += 1  # the board lost: the detector looks a few times a second
            return self._after_image(stamp)
        else:
            self.last_look = stamp
            found = self._find(gray)
            corners = None if found is None else self._ordered(self._refined(gray, found), stamp)
            off_grid = corners is not None and self._grid_rms_px(corners) > MAX_GRID_RMS_PX
            corners = None if off_grid else corners
            self.counts["off_grid" if off_grid else "no_board"] += corners is None
        if corners is None:
            self.lost_since = stamp if self.lost_since is None else self.lost_since
        else:
            self.counts["views"] += 1
            self.stamps.append(stamp)
            self.corners.append(corners.astype(np.float32))
            self.recent.append((stamp, len(self.corners) - 1))
            self.lost_since = None
            self._keep_example(stamp, msg)
        self._after_image(stamp)

    def _find(self, gray: np.ndarray) -> np.ndarray | None:
        """The board's corners found by the detector on a copy reduced to ``DETECT_MAX_SIDE``, or None; where that
        finds none and the board was last seen too small for the copy (its squares under the detector's
        ``MIN_SQUARE_PX_REDUCED`` there, with the margin ``REDUCED_MARGIN``), or not yet seen, on the whole image. A
        board lost while large is lost to blur or the image's edge: looked for at full size, the blurred ones were
        found, and their corners cost the moving-board bench's accuracy (errors 0.95 / 0.87 of the bound -> 1.24 /
        1.23)."""
        found = self.detect(gray, self.board, DETECT_MAX_SIDE)
        scale = DETECT_MAX_SIDE / max(gray.shape)
        if found is None and scale < 1 and (
                not self.corners or
                _square_px(self.corners[-1].astype(float)) * scale < REDUCED_MARGIN * MIN_SQUARE_PX_REDUCED):
            found = self.detect(gray, self.board, max(gray.shape))
        return found

    def _keep_example(self, stamp: int, msg) -> None:
        """The image kept whole for the report: one every ``EXAMPLE_EVERY_NS`` of the board in view, at most
        ``MAX_EXAMPLES``."""
        if self.examples is None or len(self.example_stamps) >= MAX_EXAMPLES or \
                (self.example_stamps and stamp - self.example_stamps[-1] < EXAMPLE_EVERY_NS):
            return
        import cv2

        self.examples.mkdir(exist_ok=True)
        cv2.imwrite(str(self.examples / f"{len(self.example_stamps):04d}.png"), decode_image(msg, self.topic))
        self.example_stamps.append(stamp)

    def _after_image(self, stamp: int) -> None:
        while self.recent and self.recent[0][0] < stamp - KEEP_VIEWS_NS:
            self.recent.popleft()
        self._flush(self.camera_now - LOOK_AHEAD_NS)

    def _tracked(self, gray: np.ndarray, stamp: int) -> np.ndarray | None:
        """A checkerboard's corners followed from the two images before (their motion in the image carried on, then
        each corner refined to its saddle): a detection costs tens of milliseconds, this one. None where they
        cannot be followed: not two images within ``TRACK_GAP_NS`` before, a corner predicted near the image's
        edge, or one the refinement moved by a quarter of a square or more (a wrong saddle; the detector then
        looks)."""
        if self.board.is_charuco or len(self.stamps) < 2:
            return None
        t0, t1 = self.stamps[-2], self.stamps[-1]
        if stamp - t1 > TRACK_GAP_NS or t1 - t0 > TRACK_GAP_NS or t1 <= t0:
            return None
        c0, c1 = self.corners[-2].astype(float), self.corners[-1].astype(float)
        predicted = c1 + (c1 - c0) * ((stamp - t1) / (t1 - t0))
        side = _square_px(predicted)
        h, w = gray.shape
        if not np.all((predicted >= side) & (predicted <= np.array([w - 1, h - 1]) - side)):
            return None
        refined = subpixel_refine(gray, predicted, side / 3.0)[0]
        if np.max(np.linalg.norm(refined - predicted, axis=1)) >= side / 4.0:
            return None
        return refined

    def _grid_rms_px(self, corners: np.ndarray) -> float:
        """How far the corners lie from the board's grid seen in perspective (px): the RMS residual of the plane's
        homography onto their undistorted image points, least squares, in pixels of the focal length."""
        import cv2

        seen = np.all(np.isfinite(corners), axis=1)
        if seen.sum() < 6:
            return np.inf
        X = self.board.inner_corners()[seen, :2]
        xy = self.camera.normalized_from_pixels(corners[seen])
        H, _ = cv2.findHomography(X, xy, 0)
        if H is None:
            return np.inf
        p = np.column_stack([X, np.ones(len(X))]) @ H.T
        r = p[:, :2] / p[:, 2:] - xy
        return float(np.sqrt(np.mean(np.sum(r ** 2, axis=1))) * self.camera.K[0, 0])

    def _pose(self, index: int):
        """The board's pose in image ``index`` (solved when a sweep asks for it, from the last pose solved where
        that is within half a second), or None."""
        if index not in self.poses:
            before = self.last_pose
            near = before is not None and abs(self.stamps[index] - before[0]) <= KEEP_VIEWS_NS // 2
            try:
                obs = pose_of_corners(self.corners[index], self.board, self.camera,
                                      before[1].T_camera_board if near else None)
                self.last_pose = (self.stamps[index], obs)
            except MeasurementError:
                obs = None
            self.poses[index] = obs
        return self.poses[index]

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
        out = corners.copy()
        out[seen] = subpixel_refine(gray, corners[seen], _square_px(corners[seen]) / 3.0)[0]
        return out

    def _ordered(self, corners: np.ndarray, stamp: int) -> np.ndarray:
        """A checkerboard's corners in the order nearest the previous image's; after a gap, the order whose grid
        points the way the last one seen did (its rows' and columns' directions in the image: a board is not
        turned half round while out of view), or with none seen, whose first corner is the upper-left one. A
        board's pose must not flip between its images. A ChArUco board's as found (its markers fix the order)."""
        if self.board.is_charuco:
            return corners
        if self.stamps and (stamp - self.stamps[-1]) * 1e-9 <= CONTINUOUS_S:
            prev = self.corners[-1]
            if np.linalg.norm(corners[::-1] - prev, axis=1).max() < np.linalg.norm(corners - prev, axis=1).max():
                return corners[::-1].copy()
            return corners
        if self.stamps:
            cols = self.board.inner_corners_shape[0]
            prev = self.corners[-1].astype(float)
            axes = np.array([prev[cols - 1] - prev[0], prev[-cols] - prev[0]])
            now = np.array([corners[cols - 1] - corners[0], corners[-cols] - corners[0]])
            return corners if np.sum(axes * now) >= 0 else corners[::-1].copy()
        return corners if corners[0].sum() <= corners[-1].sum() else corners[::-1].copy()

    def _flush(self, until: int) -> None:
        while self.pending and self.pending[0][0] <= until:
            self._segment(*self.pending.popleft())

    def _segment(self, stamp: int, msg) -> None:
        near = sorted((abs(s - stamp), i) for s, i in self.recent)
        obs = next((self._pose(i) for d, i in near if d <= KEEP_VIEWS_NS // 2 and self._pose(i) is not None), None)
        if obs is None:
            self.counts["no_view"] += 1
            return
        period = float(np.median(self.gaps)) * 1e-9 if self.gaps else None
        xyz, times = decode_timed_cloud(msg, self.topic, period)
        if times is None:
            self.counts["no_times"] += 1
            return
        self.sources[times.source] += 1
        self.against += times.against_order
        # The board's returns are found in a worker process while this one reads on (a 64-beam sweep takes tens of
        # milliseconds); results are taken in order, each sweep with its own seed, so the record does not depend on
        # the timing.
        seed = self.seed + len(self.waiting) + self.segmented
        self.waiting.append((stamp, xyz, times.offset_s, obs, seed, self._submit(xyz, obs, seed)))
        while len(self.waiting) > MAX_WAITING:
            self._take()

    def _submit(self, xyz: np.ndarray, obs, seed: int):
        """The sweep handed to the worker (started at the first: forked where the system forks, so that a script
        without a ``__main__`` guard works), or None where there is none (its board then found when taken)."""
        from concurrent.futures.process import BrokenProcessPool

        if self.pool is None and not self.inline:
            import multiprocessing
            from concurrent.futures import ProcessPoolExecutor

            kind = "fork" if "fork" in multiprocessing.get_all_start_methods() else "spawn"
            self.pool = ProcessPoolExecutor(1, mp_context=multiprocessing.get_context(kind))
        try:
            return None if self.inline else self.pool.submit(board_returns, xyz, self.board, obs, seed)
        except (BrokenProcessPool, RuntimeError, OSError):
            self.inline = True  # no worker to be had: this process finds the boards itself
            return None

    def _take(self) -> None:
        """The oldest sweep's board returns from the worker, kept or counted under the reason they were not."""
        from concurrent.futures.process import BrokenProcessPool

        stamp, xyz, offsets, obs, seed, future = self.waiting.popleft()
        self.segmented += 1
        try:
            index, why = future.result() if future is not None else board_returns(xyz, self.board, obs, seed)
        except BrokenProcessPool:  # the worker died (killed, or could not start): the same work here
            self.inline = True
            index, why = board_returns(xyz, self.board, obs, seed)
        if index is None:
            self.counts[why] += 1
            return
        self.counts["sweeps"] += 1
        self.sweep_stamps.append(stamp)
        self.points.append(xyz[index].astype(np.float32))
        self.offsets.append(offsets[index].astype(np.float32))

    def close(self) -> None:
        """Stop the worker."""
        if self.pool is not None:
            self.pool.shutdown(cancel_futures=True)
            self.pool = None

    def track(self, bag) -> MotionTrack:
        """The record, or a :class:`BagError` saying why the recording gives none."""
        self._flush(np.iinfo(np.int64).max)
        while self.waiting:
            self._take()
        self.close()
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
                           np.concatenate(self.offsets), source,
                           (np.array(self.example_stamps, dtype=np.int64) - o) * 1e-9,
                           2 * self.against > sum(self.sources.values()))


def _square_px(corners: np.ndarray) -> float:
    """The smallest distance between consecutive corners (a square's side in the image, px; at least 6)."""
    return max(float(np.min(np.linalg.norm(np.diff(corners, axis=0), axis=1))) if len(corners) > 1 else 6.0, 6.0)


def board_returns(xyz: np.ndarray, board: BoardModel, camera_board, seed: int) -> tuple[np.ndarray | None, str]:
    """The indices of the board's returns in a sweep (``find_board``, gated by the camera's board
    ``camera_board``; RANSAC seeded by ``seed``), or None and the reason (a key of ``REASONS``)."""
    from scipy.spatial import cKDTree  # here: scipy.spatial takes 0.3 s to import

    lo, hi = range_gate(board, camera_board, SegmentationParams().max_sensor_separation_m)
    ranges = np.linalg.norm(xyz, axis=1)
    gated = np.flatnonzero((ranges >= lo) & (ranges <= hi))
    try:
        found = find_board(xyz[gated], board, camera_board, np.random.default_rng(seed))
    except AmbiguousBoardError:
        return None, "ambiguous"
    except MeasurementError:
        return None, "no_board_in_sweep"
    dist, k = cKDTree(xyz[gated]).query(found.points)
    return gated[k[dist < 1e-9]], "sweeps"
