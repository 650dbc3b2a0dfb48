"""Test support: ROS 1, ROS 2 sqlite3 and ROS 2 MCAP bags recorded from a simulated dataset folder.

Each of the dataset's board poses is held still for ``still_s`` (images at ``image_hz`` with fresh pixel noise,
scans at ``scan_hz`` offset from the images by ``scan_offset_s``), then the board moves for ``move_s`` (the
image slides sideways, and one image shows no board). Written with ``rosbags`` only: no ROS install.
"""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from estimators.io.dataset import load_dataset
from estimators.io.pointcloud_io import read_sweep

T0_NS = 1_700_000_000 * 1_000_000_000


def _stores(kind: str):
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS1_NOETIC if kind == "ros1" else Stores.ROS2_HUMBLE)


class _Bag:
    def __init__(self, path: Path, kind: str):
        from rosbags.rosbag1 import Writer as Writer1
        from rosbags.rosbag2 import StoragePlugin
        from rosbags.rosbag2 import Writer as Writer2

        self.kind, self.ts = kind, _stores(kind)
        if kind == "ros1":
            self.writer = Writer1(path)
        else:
            plugin = StoragePlugin.MCAP if kind == "mcap" else StoragePlugin.SQLITE3
            self.writer = Writer2(path, version=9, storage_plugin=plugin)
        self.conns: dict = {}

    def __enter__(self):
        self.writer.open()
        return self

    def __exit__(self, *exc):
        self.writer.close()

    def header(self, t_ns: int, frame: str):
        T = self.ts.types
        stamp = T["builtin_interfaces/msg/Time"](sec=t_ns // 1_000_000_000, nanosec=t_ns % 1_000_000_000)
        if self.kind == "ros1":
            return T["std_msgs/msg/Header"](seq=0, stamp=stamp, frame_id=frame)
        return T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame)

    def write(self, topic: str, msg, t_ns: int) -> None:
        msgtype = msg.__msgtype__
        if topic not in self.conns:
            self.conns[topic] = self.writer.add_connection(topic, msgtype, typestore=self.ts)
        data = self.ts.serialize_ros1(msg, msgtype) if self.kind == "ros1" else self.ts.serialize_cdr(msg, msgtype)
        self.writer.write(self.conns[topic], t_ns, data)


def image_message(bag: _Bag, img: np.ndarray, t_ns: int, encoding: str = "mono8"):
    T = bag.ts.types
    if encoding == "jpeg":
        ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 97])
        return T["sensor_msgs/msg/CompressedImage"](header=bag.header(t_ns, "camera"), format="jpeg",
                                                     data=np.frombuffer(buf.tobytes(), np.uint8))
    if encoding == "rgb8":
        data = cv2.cvtColor(img, cv2.COLOR_GRAY2RGB)
    elif encoding == "bayer_rggb8":
        rgb = cv2.cvtColor(img, cv2.COLOR_GRAY2RGB)
        data = bayer_mosaic_rggb(rgb)
    else:
        data = img
    channels = 1 if data.ndim == 2 else data.shape[2]
    return T["sensor_msgs/msg/Image"](header=bag.header(t_ns, "camera"), height=data.shape[0],
                                      width=data.shape[1], encoding=encoding, is_bigendian=0,
                                      step=data.shape[1] * channels, data=np.ascontiguousarray(data).ravel())


def bayer_mosaic_rggb(rgb: np.ndarray) -> np.ndarray:
    """The single-channel RGGB mosaic a Bayer sensor records of an RGB image."""
    m = np.empty(rgb.shape[:2], rgb.dtype)
    m[0::2, 0::2] = rgb[0::2, 0::2, 0]
    m[0::2, 1::2] = rgb[0::2, 1::2, 1]
    m[1::2, 0::2] = rgb[1::2, 0::2, 1]
    m[1::2, 1::2] = rgb[1::2, 1::2, 2]
    return m


# Per-return time fields as drivers write them: Ouster's ``t`` and Livox's ``offset_time`` (uint32 ns from the
# stamp) and Velodyne's ``time`` (float32 s from the stamp), by PointField datatype, numpy format and unit.
TIME_FIELDS = {"t": (6, "<u4", 1e9), "time": (7, "<f4", 1.0), "offset_time": (6, "<u4", 1e9)}


def cloud_message(bag: _Bag, xyz: np.ndarray, t_ns: int, times_s: np.ndarray | None = None,
                  time_field: str = "t", ring: np.ndarray | None = None):
    """x, y, z, intensity float32 and ring uint16 in a padded 32-byte point, as Velodyne drivers publish (``ring``:
    each return's beam; None: no ring field, as a rosette's driver); ``times_s``: each return's time after the
    stamp, in ``time_field`` (:data:`TIME_FIELDS`) at offset 24."""
    T = bag.ts.types
    PF = T["sensor_msgs/msg/PointField"]
    names, formats, offsets = ["x", "y", "z", "intensity", "ring"], ["<f4"] * 4 + ["<u2"], [0, 4, 8, 16, 20]
    if times_s is not None:
        names, formats, offsets = names + [time_field], formats + [TIME_FIELDS[time_field][1]], offsets + [24]
    dtype = np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": 32})
    pts = np.zeros(len(xyz), dtype)
    pts["x"], pts["y"], pts["z"] = xyz.T
    pts["intensity"] = 100.0
    fields = [PF(name="x", offset=0, datatype=7, count=1), PF(name="y", offset=4, datatype=7, count=1),
              PF(name="z", offset=8, datatype=7, count=1), PF(name="intensity", offset=16, datatype=7, count=1)]
    if ring is not None:
        pts["ring"] = ring
        fields.append(PF(name="ring", offset=20, datatype=4, count=1))
    if times_s is not None:
        datatype, _, unit = TIME_FIELDS[time_field]
        pts[time_field] = np.round(times_s * unit) if unit != 1.0 else times_s
        fields.append(PF(name=time_field, offset=24, datatype=datatype, count=1))
    return T["sensor_msgs/msg/PointCloud2"](header=bag.header(t_ns, "lidar"), height=1, width=len(pts),
                                            fields=fields, is_bigendian=False, point_step=32,
                                            row_step=32 * len(pts), data=pts.view(np.uint8).ravel(),
                                            is_dense=True)


def scan_message(bag: _Bag, angles: np.ndarray, ranges: np.ndarray, t_ns: int):
    T = bag.ts.types
    r = np.where(ranges > 0, ranges, np.inf).astype(np.float32)
    return T["sensor_msgs/msg/LaserScan"](
        header=bag.header(t_ns, "laser"), angle_min=float(angles[0]), angle_max=float(angles[-1]),
        angle_increment=float((angles[-1] - angles[0]) / (len(angles) - 1)), time_increment=0.0, scan_time=0.025,
        range_min=0.02, range_max=80.0, ranges=r, intensities=np.zeros(0, np.float32))


def info_message(bag: _Bag, camera, t_ns: int):
    T = bag.ts.types
    upper = bag.kind == "ros1"
    K, D = camera.K.ravel().astype(float), camera.dist.astype(float)
    P = np.hstack([camera.K, np.zeros((3, 1))]).ravel()
    kw = {"D" if upper else "d": D, "K" if upper else "k": K, "R" if upper else "r": np.eye(3).ravel(),
          "P" if upper else "p": P}
    roi = T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    return T["sensor_msgs/msg/CameraInfo"](
        header=bag.header(t_ns, "camera"), height=camera.height, width=camera.width,
        distortion_model="equidistant" if camera.model == "fisheye" else "plumb_bob",
        binning_x=0, binning_y=0, roi=roi, **kw)


def _read_scan_2d_raw(path: Path) -> tuple[np.ndarray, np.ndarray]:
    data = np.loadtxt(path, delimiter=",", skiprows=1)
    return data[:, 0], data[:, 1]


def write_bag_from_dataset(dataset: Path, bag_path: Path, kind: str, *, encoding: str = "mono8",
                           image_hz: float = 10.0, scan_hz: float = 10.0, still_s: float = 1.5,
                           move_s: float = 0.6, scan_offset_s: float = 0.013, camera_info: bool = True,
                           seed: int = 0, image_topic: str = "/camera/image_raw",
                           lidar_topic: str | None = None, stamp_jitter_s: float = 0.0,
                           drift_px_per_s: float = 0.0) -> Path:
    """Record the dataset's poses as a bag of ``kind`` ros1 | sqlite3 | mcap; returns the bag's path.
    ``stamp_jitter_s``: the sd of a Gaussian jitter on every image's stamp (as a camera driver's).
    ``drift_px_per_s``: each pose's image slides sideways at that rate while it is recorded (a board that never
    stops moving)."""
    ds = load_dataset(dataset)
    rng = np.random.default_rng(seed)
    is2d = ds.lidar == "2d"
    lidar_topic = lidar_topic or ("/scan" if is2d else "/velodyne_points")
    t = T0_NS
    dt_img, dt_scan = int(1e9 / image_hz), int(1e9 / scan_hz)
    with _Bag(bag_path, kind) as bag:
        for f in ds.frames:
            img = cv2.imread(str(f.image), cv2.IMREAD_GRAYSCALE)
            scan = _read_scan_2d_raw(f.scan) if is2d else read_sweep(f.scan)
            end = t + int(still_s * 1e9)
            events = [(s, "img") for s in range(t, end, dt_img)]
            events += [(s + int(scan_offset_s * 1e9), "scan") for s in range(t, end, dt_scan)]
            if camera_info and ds.camera is not None:
                events.append((t, "info"))
            for s, what in sorted(events):
                if what == "img":
                    shown = img
                    if drift_px_per_s:
                        shift = np.float32([[1, 0, drift_px_per_s * (s - t) * 1e-9], [0, 1, 0]])
                        shown = cv2.warpAffine(img, shift, img.shape[::-1], borderMode=cv2.BORDER_REPLICATE)
                    noisy = np.clip(shown + rng.normal(0, 1.0, img.shape), 0, 255).astype(np.uint8)
                    s = s + int(rng.normal(0.0, stamp_jitter_s) * 1e9) if stamp_jitter_s > 0 else s
                    bag.write(image_topic, image_message(bag, noisy, s, encoding), s)
                elif what == "scan":
                    msg = scan_message(bag, *scan, s) if is2d else cloud_message(bag, scan.points, s, ring=scan.ring)
                    bag.write(lidar_topic, msg, s)
                else:
                    bag.write(image_topic.rsplit("/", 1)[0] + "/camera_info", info_message(bag, ds.camera, s), s)
            # The board moves to the next pose: it slides across the image, and is out of view once.
            moves = list(range(end, end + int(move_s * 1e9), dt_img))
            for k, s in enumerate(moves):
                s = s + int(rng.normal(0.0, stamp_jitter_s) * 1e9) if stamp_jitter_s > 0 else s
                moved = np.zeros_like(img) if k == len(moves) // 2 else np.roll(img, 25 * (k + 1), axis=1)
                bag.write(image_topic, image_message(bag, moved, s, encoding), s)
            t = end + int(move_s * 1e9)
    return bag_path


def rig_topics(rig) -> dict:
    """The topic of each sensor of a rig folder in :func:`write_bag_from_rig`'s bags."""
    return {s.name: f"/{s.name}/image_raw" if s.type == "camera" else
            f"/{s.name}/points" if s.lidar == "3d" else f"/{s.name}/scan" for s in rig.sensors}


def write_bag_from_rig(folder: Path, bag_path: Path, kind: str, stems: list[str], sensors: list[str], *,
                       image_hz: float = 4.0, scan_hz: float = 5.0, still_s: float = 1.5, move_s: float = 0.6,
                       seed: int = 0) -> Path:
    """Record some frames (``stems``) of a rig folder's ``sensors`` as a bag: as :func:`write_bag_from_dataset`,
    every camera publishing all along (a frame it has no file for: an image without the board), its CameraInfo
    beside it, and every LiDAR its frame's scan (topics: :func:`rig_topics`)."""
    from estimators.io.rig_dataset import load_rig

    rig = load_rig(folder)
    chosen = [rig.sensor(n) for n in sensors]
    topics = rig_topics(rig)
    rng = np.random.default_rng(seed)
    t = T0_NS
    dt_img, dt_scan = int(1e9 / image_hz), int(1e9 / scan_hz)
    with _Bag(bag_path, kind) as bag:
        for k, stem in enumerate(stems):
            end = t + int(still_s * 1e9)
            events = []
            for ci, s in enumerate(chosen):
                if s.type == "camera":
                    path = s.file(stem)
                    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE) if path is not None else np.zeros(
                        (s.camera.height, s.camera.width), np.uint8)
                    events += [(u + 7_000_000 * ci, "img", s, img) for u in range(t, end, dt_img)]
                    if k == 0:
                        events.append((t, "info", s, None))
                elif s.file(stem) is not None:
                    data = read_sweep(s.file(stem)) if s.lidar == "3d" else _read_scan_2d_raw(s.file(stem))
                    events += [(u + 11_000_000, "scan", s, data) for u in range(t, end, dt_scan)]
            for u, what, s, data in sorted(events, key=lambda e: e[0]):
                if what == "img":
                    noisy = np.clip(data + rng.normal(0, 1.0, data.shape), 0, 255).astype(np.uint8)
                    bag.write(topics[s.name], image_message(bag, noisy, u), u)
                elif what == "info":
                    bag.write(f"/{s.name}/camera_info", info_message(bag, s.camera, u), u)
                elif s.lidar == "3d":
                    bag.write(topics[s.name], cloud_message(bag, data.points, u, ring=data.ring), u)
                else:
                    bag.write(topics[s.name], scan_message(bag, *data, u), u)
            # The board moves to the next pose: every camera's image slides, and shows no board once.
            moves = list(range(end, end + int(move_s * 1e9), dt_img))
            for j, u in enumerate(moves):
                for s in chosen:
                    if s.type != "camera":
                        continue
                    path = s.file(stem)
                    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE) if path is not None else np.zeros(
                        (s.camera.height, s.camera.width), np.uint8)
                    moved = np.zeros_like(img) if j == len(moves) // 2 else np.roll(img, 25 * (j + 1), axis=1)
                    bag.write(topics[s.name], image_message(bag, moved, u), u)
            t = end + int(move_s * 1e9)
    return bag_path


def write_waved_bag(bag_path: Path, kind: str, rig, duration_s: float, rng: np.random.Generator, *,
                    time_offset_s: float = 0.0, speed_mps: float = 0.5, turn_dps: float = 45.0,
                    camera_hz: float = 20.0, lidar_hz: float = 10.0, exposure_s: float = 0.004,
                    time_field: str | None = "t", pauses: tuple = (), image_topic: str = "/camera/image_raw",
                    lidar_topic: str = "/points", more_lidars: tuple = (), more_image_topics: tuple = (),
                    times_reversed: bool = False):
    """A board waved before ``rig`` for ``duration_s`` (``simulation.waved_board``), recorded as a bag: every
    image (``simulation.board_drawing``, blurred over ``exposure_s``, stamped at mid-exposure in the camera's
    clock, ``time_offset_s`` ahead of the LiDAR's), every whole sweep in a room clear of the board's path
    (``scene_sweep``, ``room_for``) with its returns' times in ``time_field`` (None: no time field, the returns in
    firing order), CameraInfo once. ``more_lidars``: further LiDARs ``(topic, rig, offset_s)``, each its own
    ``rig`` (the same camera and board, its own ``T_camera_lidar`` and beams) and its own clock, the camera's
    ``offset_s`` ahead of it; ``more_image_topics``: the same images on further topics (a second camera's, with
    its CameraInfo); ``times_reversed``: each return's time written as the sweep's period less it (a field that
    counts down through the firing order). Returns the motion (the truth)."""
    from estimators.simulation.board_drawing import draw_board
    from estimators.simulation.waved_board import room_for, scene_sweep, waving

    motion = waving(rig, rng, speed_mps, turn_dps, pauses)
    lidars = [(lidar_topic, rig, time_offset_s)] + list(more_lidars)
    rooms = [room_for(r, motion, duration_s) for _, r, _ in lidars]
    period = 1.0 / lidar_hz
    events = [(t + time_offset_s, "img", t, None) for t in np.arange(rng.uniform(0, 1 / camera_hz), duration_s,
                                                                       1.0 / camera_hz)]
    for k, (_, _, offset) in enumerate(lidars):  # LiDAR k's clock: the camera's less its offset
        events += [(t + time_offset_s - offset, "scan", t, k) for t in np.arange(0.0, duration_s - period, period)]
    events.sort(key=lambda e: e[2])
    with _Bag(bag_path, kind) as bag:
        for topic in (image_topic, *more_image_topics):
            bag.write(topic.rsplit("/", 1)[0] + "/camera_info", info_message(bag, rig.camera, T0_NS), T0_NS)
        for stamp, what, t, k in events:
            s = T0_NS + int(round(stamp * 1e9))
            if what == "img":
                poses = motion(t + np.linspace(-0.5, 0.5, 5) * exposure_s)
                msg = image_message(bag, draw_board(rig.camera, rig.board, poses, rng), s)
                for topic in (image_topic, *more_image_topics):
                    bag.write(topic, msg, s)
            else:
                topic, r, _ = lidars[k]
                xyz, times, ring = scene_sweep(r, motion, t, period, rng, rooms[k])
                times = period - times if times_reversed else times
                msg = cloud_message(bag, xyz, s, times if time_field else None, time_field or "t", ring)
                bag.write(topic, msg, s + int(period * 1e9))
    return motion
