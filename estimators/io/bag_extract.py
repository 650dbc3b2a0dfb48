"""A dataset folder from a ROS 1 bag or a ROS 2 bag (sqlite3 or MCAP), read with ``rosbags`` (no ROS install).

One pass over the bag, streaming: images are examined on a fixed time grid of ``1/check_hz`` (the first image in
each cell, so stamp jitter never skips a cell); each examined image is paired with the scan nearest in header
time (within ``max_dt_s``); the board's inner corners are found in a reduced copy of the image, and consecutive
examinations whose corners moved less than ``still_px`` form a *still segment*. A segment that lasts
``still_s`` or longer (from its first to its last examined image, plus one grid cell and one camera period,
which those images stand for) gives one frame: its steadiest interior image (the one
whose corners moved least towards both neighbours) with its scan, so a hand-held or tripod board yields one
frame per pose. A pose already kept is not kept again. Every image not kept is counted under its reason.

Memory stays bounded: at most a few scans (those within the pairing window), the images awaiting their scan,
and two candidate frames are held; kept frames go to disk as they are found.

A bag whose board moved between most examined images (``MOVING_SHARE``) is a moving board's recording: it is read
again, every image and sweep (``bag_motion``), into ``motion.npz``, which ``calibrate`` solves with the clocks'
offset. extract.json's ``recording`` says which kind the bag was read as. A still-pose recording whose board was
seen moving between its poses (``MOVED_TO_TIME`` examined images or more; a 3D LiDAR, the camera's intrinsics
known) is read that second time too: its frames give the extrinsic as before, its motion the clocks' offset.
"""
from __future__ import annotations

import hashlib
import json
import os
import re
from collections import Counter, deque
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from geometry.board import BoardModel
from geometry.camera import CameraModel

from ..camera.charuco import MIN_CHARUCO_CORNERS, detect_charuco
from ..errors import BagError
from .dataset import dataset_spec, write_dataset_yaml
from .bag_motion import REASONS as MOVING_REASONS
from .bag_motion import MovingBoardReader
from .image_io import to_gray8
from .motion_track import EXAMPLES, MOVING_BOARD, STILL_POSES, save_motion_track
from .output import atomic_directory
from .pointcloud_io import write_scan, write_scan_2d
from .ros_messages import (camera_from_info, decode_image, decode_laser_scan, decode_point_cloud, decode_point_times,
                           stamp_ns)

IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
CLOUD_TYPE = "sensor_msgs/msg/PointCloud2"
SCAN_TYPE = "sensor_msgs/msg/LaserScan"
INFO_TYPE = "sensor_msgs/msg/CameraInfo"
# Board detection for the stillness test runs on a copy whose longer side is at most this (pixels).
DETECT_MAX_SIDE = 960
MAX_PENDING_IMAGES = 64
# The recording's kind: still poses (one frame each), or a board that moves (every image and sweep used). A bag is
# read as moving when the board moved between at least this share of the examined images that show it.
STILL, MOVING = STILL_POSES, MOVING_BOARD
MOVING_SHARE = 0.6
# The still reading stops early when, before any still pose, the board moved between this share of the first
# EARLY_IMAGES examined images that show it (5 s at --check-hz 5): the bag is then read as a moving board.
EARLY_IMAGES, EARLY_SHARE = 25, 0.9
# A still-pose recording is also followed between its poses (to time the clocks) when the board moved between at
# least this many of its examined images (2 s of motion at --check-hz 5).
MOVED_TO_TIME = 10

REASONS = {
    "kept": "kept (one per still pose)",
    "between_checks": "not examined (between checks at --check-hz)",
    "no_board": "no board found in the image",
    "moving": "board moving (still for less than --still-s)",
    "same_pose": "same still pose as the kept frame",
    "repeat_pose": "repeats a pose already kept",
    "no_scan": "no scan within --max-dt",
}


@dataclass(frozen=True)
class ExtractOptions:
    """Pairing and stillness settings for :func:`extract_bag`.

    Attributes
    ----------
    max_dt_s : float
        Pair an image with the nearest scan within this many seconds (header stamps).
    still_s : float
        The board must stay still this long (s) to give a frame.
    still_px : float
        Largest corner motion (px of the full image) between examined images that still counts as still.
    check_hz : float
        Examine at most this many images per second.
    scan_format : str or None
        ``pcd``, ``ply``, ``npy`` or ``csv``; default ``pcd`` for a 3D LiDAR, ``csv`` (angle,range) for a 2D one.
    follow_motion : bool
        Read a bag whose board moves as a moving board (every image and sweep); False: still poses only, whatever
        the board does (what extraction did before moving boards were read; the benchmark's comparison).
    """

    max_dt_s: float = 0.05
    still_s: float = 1.0
    still_px: float = 2.0
    check_hz: float = 5.0
    scan_format: str | None = None  # default: pcd for a 3D LiDAR, csv (angle,range) for a 2D one
    follow_motion: bool = True

    def __post_init__(self):
        for name in ("max_dt_s", "still_s", "still_px", "check_hz"):
            if not getattr(self, name) > 0:
                raise ValueError(f"Expected {name} > 0, got {getattr(self, name)}")


@dataclass(frozen=True)
class ExtractSummary:
    """What an extraction kept and why it dropped the rest (counts of image messages)."""

    out: Path
    lidar: str
    frames: int
    images: int
    counts: dict = field(default_factory=dict)
    camera_source: str | None = None
    point_times: str | None = None
    recording: str = STILL
    # A still-pose recording's motion between its poses, in words: followed into motion.npz (to time the clocks),
    # or why not; None when the board never moved in view.
    motion: str | None = None

    def lines(self) -> list[str]:
        if self.recording == MOVING:
            out = [f"recording: {MOVING} ({self.images} images; every image and sweep that shows the board is used; "
                   "calibrate solves the clocks' offset with the extrinsic)"]
            out += [f"  {n:6d}  {MOVING_REASONS[k]}" for k, n in self.counts.items() if n]
        else:
            out = [f"recording: {STILL} ({self.images} images: {self.frames} frames kept, one per still board pose)"]
            out += [f"  {n:6d}  {REASONS[k]}" for k, n in self.counts.items() if k != "kept" and n]
            if self.motion:
                out.append(f"between the poses: {self.motion}")
        out.append(f"intrinsics: {self.camera_source}" if self.camera_source else
                   "intrinsics: none in the bag (calibrate estimates them from the board views)")
        if self.point_times:
            out.append(f"per-return LiDAR time: {self.point_times}")
        return out


@dataclass
class _Check:
    stamp: int
    image: np.ndarray
    corners: np.ndarray | None
    scan: object = None  # the scan message paired with this image, or None
    scan_stamp: int | None = None


def _detect(gray: np.ndarray, board: BoardModel, max_side: int = DETECT_MAX_SIDE) -> np.ndarray | None:
    """Inner corners (N, 2) in full-image pixels, found on a copy reduced to ``max_side``, or None. A ChArUco board:
    every inner corner's row, NaN for the ones not seen (None when too few are seen to fix the board)."""
    scale = min(1.0, max_side / max(gray.shape))
    small = cv2.resize(gray, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA) if scale < 1 else gray
    if board.is_charuco:
        det = detect_charuco(small, board)
        if det is None:
            return None
        out = np.full((len(board.inner_corners()), 2), np.nan)
        out[det.corner_ids] = det.corners_px / scale
        return out
    pattern = board.inner_corners_shape
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_FAST_CHECK
    found, corners = cv2.findChessboardCorners(small, pattern, flags=flags)
    if not found:
        return None
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.01)
    corners = cv2.cornerSubPix(small, corners, (4, 4), (-1, -1), criteria)
    return corners.reshape(-1, 2).astype(float) / scale


class Detections:
    """:func:`_detect`, each image searched once: a camera's images are read by the still poses' pass and again
    by the board's following for each LiDAR (``_follow``); the detections are kept by the image's content (a
    16-byte digest, the shape and the size searched at) and given back as copies."""

    def __init__(self, board: BoardModel):
        self.board, self.found = board, {}

    def __call__(self, gray: np.ndarray, board: BoardModel | None = None, max_side: int = DETECT_MAX_SIDE
                 ) -> np.ndarray | None:
        if board is not None and board is not self.board:
            return _detect(gray, board, max_side)
        key = (hashlib.blake2b(np.ascontiguousarray(gray).data, digest_size=16).digest(), gray.shape, max_side)
        if key not in self.found:
            self.found[key] = _detect(gray, self.board, max_side)
        found = self.found[key]
        return None if found is None else found.copy()


def corner_motion(a: np.ndarray | None, b: np.ndarray | None) -> float:
    """Largest corner displacement (px) between two detections, allowing the detector's reversed order; over
    the corners seen in both (ChArUco: NaN rows are corners not seen), at least ``MIN_CHARUCO_CORNERS``."""
    if a is None or b is None or a.shape != b.shape:
        return float("inf")
    out = float("inf")
    for other in (b, b[::-1]):
        d = np.linalg.norm(a - other, axis=1)
        d = d[np.isfinite(d)]
        if len(d) >= min(MIN_CHARUCO_CORNERS, len(a)):
            out = min(out, float(d.max()))
    return out


class _StillSegments:
    """Groups examined images into still segments and emits one frame per segment that lasts long enough."""

    def __init__(self, options: ExtractOptions, emit):
        self.o, self.emit = options, emit
        # Each examined image stands for its grid cell and its camera period: a segment's duration is the time
        # from its first to its last examined image plus this (so that a board held for still_s plus one
        # camera period is kept whatever the grid's phase).
        self.credit_s = 1.0 / options.check_hz
        self.counts: Counter = Counter()
        # Examined images with the board, and those whose corners moved beyond still_px since the one before.
        self.with_board = self.moved = 0
        self.kept_corners: list[np.ndarray] = []
        self._reset()

    def _reset(self):
        self.first: _Check | None = None
        self.prev: _Check | None = None
        self.prev_motion = float("inf")  # motion from the check before prev to prev
        self.best: _Check | None = None
        self.best_score = float("inf")
        self.n = 0

    def add(self, c: _Check) -> None:
        if c.corners is None:
            self.close()
            self.counts["no_board"] += 1
            return
        motion = corner_motion(self.prev.corners, c.corners) if self.prev is not None else float("inf")
        self.with_board += 1
        self.moved += bool(np.isfinite(motion) and motion > self.o.still_px)
        if motion > self.o.still_px:
            self.close()
            self.first, self.n = c, 0
        elif self.prev is not None and self.prev is not self.first and self.prev.scan is not None:
            # prev is interior: score it by its motion towards both neighbours.
            score = max(self.prev_motion, motion)
            if score < self.best_score:
                self.best, self.best_score = self.prev, score
        self.prev, self.prev_motion = c, motion
        self.n += 1

    def close(self) -> None:
        if self.first is None:
            return
        duration = (self.prev.stamp - self.first.stamp) * 1e-9 + self.credit_s
        n, best = self.n, self.best
        if duration < self.o.still_s or n < 3:
            self.counts["moving"] += n
        elif best is None:
            self.counts["no_scan"] += n
        elif any(corner_motion(k, best.corners) <= self.o.still_px for k in self.kept_corners):
            self.counts["repeat_pose"] += n
        else:
            self.kept_corners.append(best.corners)
            self.emit(best)
            self.counts["kept"] += 1
            self.counts["same_pose"] += n - 1
        self._reset()


class _ImageGrid:
    """One image topic's fixed time grid of ``1/check_hz`` (the first image in each cell is examined, so examined
    images are one cell apart whatever the stamps' jitter), its images' count and time span, and its camera
    period, which credits its still segments (``segments.credit_s``)."""

    def __init__(self, options: ExtractOptions, segments: _StillSegments):
        self.hz, self.segments = options.check_hz, segments
        self.origin = self.last_cell = self.last_stamp = None
        self.intervals: deque = deque(maxlen=16)  # recent image intervals (ns), for the camera's period
        self.n = 0
        self.span: list = [None, None]

    def examine(self, stamp: int) -> bool:
        """Count an image stamped ``stamp`` and say whether it is examined."""
        self.n += 1
        self.span = [stamp if self.span[0] is None else min(self.span[0], stamp),
                     stamp if self.span[1] is None else max(self.span[1], stamp)]
        if self.last_stamp is not None and stamp > self.last_stamp:
            self.intervals.append(stamp - self.last_stamp)
            self.segments.credit_s = 1.0 / self.hz + float(np.median(self.intervals)) * 1e-9
        self.last_stamp = stamp
        self.origin = stamp if self.origin is None else self.origin
        cell = (stamp - self.origin) * self.hz // 1_000_000_000
        if cell == self.last_cell:
            self.segments.counts["between_checks"] += 1
            return False
        self.last_cell = cell
        return True


def _open_reader(bag: Path):
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    if not bag.exists():
        raise BagError("bag not found", path=bag, hint="give a ROS 1 .bag file or a ROS 2 bag folder")
    try:
        reader = AnyReader([bag], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
        reader.open()
    except Exception as exc:  # rosbags raises several kinds for files that are not bags
        raise _unreadable_bag(bag, exc) from exc
    return reader


def _messages(reader, bag: Path, conns):
    """``(connection, bag time, message)`` in bag order; a damaged chunk or message is one :class:`BagError`."""
    stream = reader.messages(connections=conns)
    while True:
        try:
            conn, t_bag, raw = next(stream)
            msg = reader.deserialize(raw, conn.msgtype)
        except StopIteration:
            return
        except Exception as exc:  # rosbags raises several kinds on damaged chunks and messages
            raise _unreadable_bag(bag, exc) from exc
        yield conn, t_bag, msg


def _plain(exc: BaseException) -> str:
    """An exception's message as plain words: rosbags nests messages as tuples (``"index damaged: ('x',)"``)."""
    text = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
    text = re.sub(r"[(\[]?'([^']*)',?[)\]]?", r"\1", text)
    return text.strip(" .")[:160]


def _unreadable_bag(bag: Path, exc: BaseException) -> BagError:
    """One plain sentence for a bag that rosbags cannot open, with what to try."""
    detail = _plain(exc)
    if "index" in detail.lower() or "header" in detail.lower() or "could not read" in detail.lower():
        return BagError(f"the bag is damaged or cut short ({detail.lower()})", path=bag,
                        hint="reindex it (ROS 1: rosbag reindex; ROS 2: ros2 bag reindex) or copy it again")
    return BagError(f"not a readable ROS 1 or ROS 2 bag ({detail})", path=bag,
                    hint="give a .bag file (ROS 1) or the folder holding metadata.yaml (ROS 2)")


def _topic(reader, bag: Path, topic: str, types: tuple[str, ...], flag: str):
    conns = [c for c in reader.connections if c.topic == topic]
    if not conns:
        present = sorted({c.topic for c in reader.connections if c.msgtype in types})
        listing = ", ".join(present) if present else "none"
        raise BagError(f"no topic {topic!r} ({' or '.join(t.split('/')[-1] for t in types)} topics in the bag: "
                       f"{listing})", path=bag, hint=f"set {flag} to one of them")
    wrong = [c.msgtype for c in conns if c.msgtype not in types]
    if wrong:
        raise BagError(f"topic {topic!r} holds {wrong[0]}, not {' or '.join(types)}", path=bag,
                       hint=f"set {flag} to a topic of that type")
    return conns


def _camera_info_topic(reader, image_topic: str) -> str | None:
    """The CameraInfo topic nearest the image topic: in its namespace or a parent one (``/cam/image_raw/compressed``
    finds ``/cam/image_raw/camera_info``, then ``/cam/camera_info``); else the bag's only one, if any."""
    infos = sorted({c.topic for c in reader.connections if c.msgtype == INFO_TYPE})
    namespace = image_topic.rsplit("/", 1)[0]
    while True:
        same = [t for t in infos if t.rsplit("/", 1)[0] == namespace]
        if same:
            return same[0]
        if not namespace:
            break
        namespace = namespace.rsplit("/", 1)[0]
    return infos[0] if len(infos) == 1 else None


def extract_bag(bag: str | os.PathLike, out: str | os.PathLike, board: BoardModel, image_topic: str,
                cloud_topic: str | None = None, scan_topic: str | None = None,
                camera_info_topic: str | None = None, use_camera_info: bool = True,
                options: ExtractOptions = ExtractOptions(), progress: bool = False,
                overwrite: bool = False, intrinsics: CameraModel | None = None) -> ExtractSummary:
    """Write a dataset folder from a ROS 1 or ROS 2 bag: one frame per still board pose, or a moving board's
    record (see the module).

    The folder (``dataset.yaml``, ``NNNN.png`` and ``NNNN.pcd|csv`` or ``motion.npz``, ``extract.json``) appears
    complete or not at all.

    Parameters
    ----------
    bag : str or os.PathLike
        A ROS 1 ``.bag`` file, a ROS 2 bag folder, or its ``.db3`` or ``.mcap`` file.
    out : str or os.PathLike
        The dataset folder to write.
    board : BoardModel
        The board (``lidarcam extract --board`` parses the short form).
    image_topic : str
        A ``sensor_msgs/Image`` or ``CompressedImage`` topic.
    cloud_topic : str, optional
        A ``PointCloud2`` topic (a 3D LiDAR).
    scan_topic : str, optional
        A ``LaserScan`` topic (a 2D LiDAR); give exactly one of the two.
    camera_info_topic : str, optional
        The ``CameraInfo`` topic (default: the one beside the image topic, if any).
    use_camera_info : bool
        False: write no intrinsics; ``calibrate`` then estimates them from the board views.
    intrinsics : CameraModel, optional
        The camera's intrinsics (``io.intrinsics_file``, ``lidarcam extract --intrinsics``): used and written
        instead of any ``CameraInfo`` (a bag recorded without it can then be followed as a moving board).
    options : ExtractOptions
        Pairing and stillness settings.
    progress : bool
        Show a progress bar.
    overwrite : bool
        Replace an existing folder.

    Returns
    -------
    ExtractSummary
        The frames kept and, per reason, the images dropped.

    Raises
    ------
    BagError
        A missing topic, an unknown encoding, or no image paired with a scan.
    """
    from tqdm.auto import tqdm

    bag = Path(bag)
    if (cloud_topic is None) == (scan_topic is None):
        raise BagError("give exactly one of a cloud topic (3D LiDAR) and a scan topic (2D LiDAR)", path=bag,
                       hint="pass --cloud-topic T or --scan-topic T")
    lidar = "3d" if cloud_topic else "2d"
    scan_format = options.scan_format or ("pcd" if lidar == "3d" else "csv")
    detect = Detections(board)  # each image searched once, by the still poses' pass and the following
    reader = _open_reader(bag)
    try:
        img_conns = _topic(reader, bag, image_topic, IMAGE_TYPES, "--image-topic")
        lidar_conns = (_topic(reader, bag, cloud_topic, (CLOUD_TYPE,), "--cloud-topic") if cloud_topic else
                       _topic(reader, bag, scan_topic, (SCAN_TYPE,), "--scan-topic"))
        use_camera_info = use_camera_info and intrinsics is None
        info_topic = camera_info_topic
        if info_topic is None and use_camera_info:
            info_topic = _camera_info_topic(reader, image_topic)
        info_conns = _topic(reader, bag, info_topic, (INFO_TYPE,), "--camera-info-topic") \
            if info_topic and use_camera_info else []
        lidar_topic = cloud_topic or scan_topic
        conns = img_conns + lidar_conns + info_conns
        total = sum(c.msgcount for c in conns)
        with atomic_directory(out, overwrite=overwrite) as tmp:
            records: list[dict] = []
            scan_gaps: deque = deque(maxlen=64)  # consecutive sweeps' stamp spacing: a sweep's period
            point_times: list[str] = []  # how the first kept sweep's returns are timed, in words

            def emit(c: _Check) -> None:
                name = f"{len(records):04d}"
                cv2.imwrite(str(tmp / f"{name}.png"), c.image)
                if lidar == "3d":
                    xyz, inten, ring = decode_point_cloud(c.scan, lidar_topic, rings=True)
                    write_scan(tmp / f"{name}.{scan_format}", xyz, inten, ring)
                    if not point_times:
                        point_times.append(_timing_words(c.scan, lidar_topic, scan_gaps))
                else:
                    write_scan_2d(tmp / f"{name}.{scan_format}", *decode_laser_scan(c.scan))
                records.append({"name": name, "image_stamp_ns": c.stamp, "scan_stamp_ns": c.scan_stamp,
                                "dt_ms": round((c.scan_stamp - c.stamp) * 1e-6, 3)})

            segments = _StillSegments(options, emit)
            grid = _ImageGrid(options, segments)
            scans: deque = deque()  # (stamp, msg) in arrival order
            pending: deque = deque()  # examined images awaiting a later scan
            camera: CameraModel | None = intrinsics
            scan_span = [None, None]
            peak = {"scans": 0, "images_awaiting_a_scan": 0}
            max_dt = int(options.max_dt_s * 1e9)

            def resolve(c: _Check) -> None:
                if scans:
                    stamp, msg = min(scans, key=lambda s: abs(s[0] - c.stamp))
                    if abs(stamp - c.stamp) <= max_dt:
                        c.scan, c.scan_stamp = msg, stamp
                segments.add(c)

            def span(s, t):
                s[0] = t if s[0] is None else min(s[0], t)
                s[1] = t if s[1] is None else max(s[1], t)

            bar = tqdm(total=total, desc=f"reading {bag.name}", unit="msg", disable=not progress)
            for conn, t_bag, msg in _messages(reader, bag, conns):
                bar.update(1)
                stamp = stamp_ns(msg, t_bag)
                if conn.topic == info_topic:
                    if camera is None:
                        camera = camera_from_info(msg, info_topic)
                    continue
                if conn.topic == lidar_topic:
                    if scan_span[1] is not None and stamp > scan_span[1]:
                        scan_gaps.append(stamp - scan_span[1])
                    span(scan_span, stamp)
                    scans.append((stamp, msg))
                    while pending and stamp > pending[0].stamp + max_dt:
                        resolve(pending.popleft())
                else:
                    if not grid.examine(stamp):
                        continue
                    image = decode_image(msg, image_topic)
                    if intrinsics is not None and image.shape[:2] != (intrinsics.height, intrinsics.width):
                        raise BagError(f"the intrinsics given ({intrinsics.source}) are for {intrinsics.width} x "
                                       f"{intrinsics.height} images and {image_topic}'s are {image.shape[1]} x "
                                       f"{image.shape[0]}", path=bag, hint="give the intrinsics of this camera "
                                                                           "at this resolution")
                    pending.append(_Check(stamp, image, detect(to_gray8(image))))
                    if len(pending) > MAX_PENDING_IMAGES:
                        resolve(pending.popleft())
                    if options.follow_motion and not records and segments.with_board >= EARLY_IMAGES and \
                            segments.moved >= EARLY_SHARE * segments.with_board:
                        break  # a moving board from the start: read as one (below), not examined to the end
                # A scan followed by one no later than every image still to come can never be the nearest
                # again (images still to come: the pending ones, or ones stamped after now less a second's lag).
                horizon = pending[0].stamp if pending else stamp - 1_000_000_000
                while len(scans) > 1 and scans[1][0] <= horizon:
                    scans.popleft()
                peak["scans"] = max(peak["scans"], len(scans))
                peak["images_awaiting_a_scan"] = max(peak["images_awaiting_a_scan"], len(pending))
            bar.close()
            while pending:
                resolve(pending.popleft())
            segments.close()
            n_images = grid.n
            moving = options.follow_motion and segments.with_board >= 10 and \
                segments.moved >= MOVING_SHARE * segments.with_board
            if moving:  # read again, every image and sweep (this reading may have stopped early: no overlap check)
                return _extract_moving(reader, bag, tmp, Path(out), board, camera, img_conns + lidar_conns,
                                       image_topic, lidar_topic, lidar, segments, info_topic, progress, detect)
            _check_overlap(bag, image_topic, lidar_topic, grid.span, scan_span, n_images, options)
            if not records:
                counts = ", ".join(f"{n} {REASONS[k]}" for k, n in segments.counts.items() if n)
                raise BagError(f"no still board poses found among {n_images} images ({counts})", path=bag,
                               hint="hold the board still for --still-s seconds per pose, or raise --still-px "
                                    "for a hand-held board")
            write_dataset_yaml(tmp, dataset_spec(lidar, board, camera),
                               f"extracted by lidarcam from {bag.name}: {image_topic} + {lidar_topic}")
            motion = _between_poses(reader, bag, tmp, board, camera, img_conns + lidar_conns, image_topic,
                                    lidar_topic, lidar, segments, options, progress, detect=detect)
            counts = {k: int(segments.counts.get(k, 0)) for k in REASONS}
            (tmp / "extract.json").write_text(json.dumps({
                "bag": str(bag), "recording": STILL, "image_topic": image_topic, "lidar_topic": lidar_topic,
                "camera_info_topic": info_topic if camera is not None and intrinsics is None else None,
                "options": {"max_dt_s": options.max_dt_s, "still_s": options.still_s,
                            "still_px": options.still_px, "check_hz": options.check_hz},
                "images": n_images, "counts": counts, "peak_buffered_messages": peak,
                "point_times": point_times[0] if point_times else None, "motion_between_poses": motion,
                "frames": records}, indent=1) + "\n")
    finally:
        reader.close()
    return ExtractSummary(Path(out), lidar, len(records), n_images, counts,
                          camera.source if camera is not None else None, point_times[0] if point_times else None,
                          motion=motion)


def _between_poses(reader, bag: Path, tmp: Path, board: BoardModel, camera: CameraModel | None, conns,
                   image_topic: str, lidar_topic: str, lidar: str, segments: "_StillSegments",
                   options: ExtractOptions, progress: bool, remedy: str = "give them with --intrinsics FILE",
                   detect: Detections | None = None) -> str | None:
    """A still-pose recording's board followed between its poses into ``motion.npz`` (``calibrate`` times the
    clocks with it) when it was seen moving (``MOVED_TO_TIME``); what was done, or why not, in words (None: the
    board never moved in view; ``remedy``: what gives the camera's intrinsics where the bag has none; ``detect``:
    the detections of the camera's images so far)."""
    if segments.moved < MOVED_TO_TIME or not options.follow_motion:
        return None
    if lidar != "3d":
        return "not followed (a 2D scanner's line does not time the clocks)"
    if camera is None:
        return f"not followed (following the board needs the camera's intrinsics: the bag has no CameraInfo; {remedy})"
    try:
        track, _, _ = _follow(reader, bag, tmp, board, camera, conns, image_topic, lidar_topic, progress, detect)
    except BagError as exc:
        return f"not followed ({exc.problem})"
    save_motion_track(tmp, track)
    return (f"followed: {len(track.view_stamps_s)} images and {len(track.sweep_stamps_s)} sweeps that show the board "
            "kept (motion.npz), to time the clocks")


def _extract_moving(reader, bag: Path, tmp: Path, out: Path, board: BoardModel, camera: CameraModel | None, conns,
                    image_topic: str, lidar_topic: str, lidar: str, segments: _StillSegments,
                    info_topic: str | None, progress: bool, detect: Detections | None = None) -> ExtractSummary:
    """A second pass over a bag whose board moves: every image and sweep read into ``motion.npz``
    (``bag_motion``), with ``dataset.yaml`` and ``extract.json``."""
    share = f"its corners moved beyond --still-px between {segments.moved} of the {segments.with_board} examined " \
            "images that show it"
    if lidar != "3d":
        raise BagError(f"the board moves ({share}), and a moving board needs a 3D LiDAR's sweeps", path=bag,
                       hint="with a 2D scanner hold the board still for --still-s seconds per pose")
    if camera is None:
        raise BagError(f"the board moves ({share}), and following it needs the camera's intrinsics: the bag has "
                       "no CameraInfo", path=bag, hint="give them with --intrinsics FILE, record the camera's "
                                                       "CameraInfo topic (or name it with --camera-info-topic), or "
                                                       "hold the board still per pose")
    track, counts, images = _follow(reader, bag, tmp, board, camera, conns, image_topic, lidar_topic, progress,
                                    detect)
    save_motion_track(tmp, track)
    write_dataset_yaml(tmp, dataset_spec(lidar, board, camera),
                       f"extracted by lidarcam from {bag.name} (a moving board): {image_topic} + {lidar_topic}")
    (tmp / "extract.json").write_text(json.dumps({
        "bag": str(bag), "recording": MOVING, "image_topic": image_topic, "lidar_topic": lidar_topic,
        "camera_info_topic": info_topic, "images": images, "counts": counts, "moved_share":
        round(segments.moved / segments.with_board, 3), "point_times": track.point_times,
        "origin_ns": track.origin_ns}, indent=1) + "\n")
    return ExtractSummary(out, lidar, 0, images, counts, camera.source, track.point_times, MOVING)


def _follow(reader, bag: Path, tmp: Path, board: BoardModel, camera: CameraModel, conns, image_topic: str,
            lidar_topic: str, progress: bool, detect: Detections | None = None):
    """Every image and sweep of the bag read (``bag_motion.MovingBoardReader``): the record, the images' counts
    per reason and the images read; a :class:`BagError` when too little of the board was seen. ``detect``: the
    camera's images searched before (:class:`Detections`)."""
    from tqdm.auto import tqdm

    follow = MovingBoardReader(board, camera, detect or Detections(board), image_topic, np.random.default_rng(0),
                               tmp / EXAMPLES)
    bar = tqdm(total=sum(c.msgcount for c in conns), desc=f"following the board in {bag.name}", unit="msg",
               disable=not progress)
    try:
        for conn, t_bag, msg in _messages(reader, bag, conns):
            bar.update(1)
            (follow.sweep if conn.topic == lidar_topic else follow.image)(stamp_ns(msg, t_bag), msg)
        track = follow.track(bag)
    finally:
        follow.close()
        bar.close()
    return track, {k: int(follow.counts.get(k, 0)) for k in MOVING_REASONS}, follow.images


def _timing_words(msg, topic: str, gaps) -> str:
    """How a sweep's returns are timed (``ros_messages.decode_point_times``; the sweep's period from the
    stamps' median spacing ``gaps``, ns), in words: said by ``extract`` (still poses do not use them)."""
    period_s = float(np.median(gaps)) * 1e-9 if gaps else None
    try:
        times = decode_point_times(msg, topic, period_s)
    except BagError as exc:
        return f"unusable ({exc.problem})"
    return times.source if times is not None else \
        "unknown (no time field, and the stored order is not the firing order)"


def _check_overlap(bag, image_topic, lidar_topic, img_span, scan_span, n_images, options) -> None:
    if n_images == 0:
        raise BagError(f"topic {image_topic!r} has no messages", path=bag, hint="check the recording")
    if scan_span[0] is None:
        raise BagError(f"topic {lidar_topic!r} has no messages", path=bag, hint="check the recording")
    slack = options.max_dt_s * 1e9
    if img_span[0] > scan_span[1] + slack or scan_span[0] > img_span[1] + slack:
        raise BagError(f"{image_topic} ({img_span[0] * 1e-9:.3f}-{img_span[1] * 1e-9:.3f} s) and {lidar_topic} "
                       f"({scan_span[0] * 1e-9:.3f}-{scan_span[1] * 1e-9:.3f} s) do not overlap in time",
                       path=bag, hint="check that both sensors stamp with the same clock")
