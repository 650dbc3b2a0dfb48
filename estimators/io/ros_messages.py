"""Decoding ROS sensor messages into arrays, without ROS: images, point clouds, laser scans, camera info.

The functions take the message objects ``rosbags`` deserialises (ROS 1 and ROS 2 alike: they read fields by
name, so ROS 1's upper-case ``K``/``D`` and ROS 2's ``k``/``d`` both work) and raise ``BagError`` with a
one-line reason for anything they cannot decode.
"""
from __future__ import annotations

import functools

import cv2
import numpy as np

from geometry.camera import FISHEYE, PINHOLE, CameraModel

from ..errors import BagError
from .image_io import decode_image_bytes
from .point_times import PointTimes, against_stored_order, azimuth_times, field_times, time_field

# sensor_msgs/PointField datatypes.
_POINT_FIELD_TYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
_INTENSITY_FIELDS = ("intensity", "intensities", "i", "reflectivity")

# ROS's Bayer names give the colour of the first two pixels of the first row; OpenCV names its conversion
# codes after the second row's second and third pixels, so ROS rggb is OpenCV's "BG" (as cv_bridge maps them).
_BAYER = {"rggb": cv2.COLOR_BayerBG2BGR, "bggr": cv2.COLOR_BayerRG2BGR,
          "gbrg": cv2.COLOR_BayerGR2BGR, "grbg": cv2.COLOR_BayerGB2BGR}
_CHANNELS = {"mono": 1, "rgb": 3, "bgr": 3, "rgba": 4, "bgra": 4}
IMAGE_ENCODINGS = ("mono8", "mono16", "rgb8", "bgr8", "rgba8", "bgra8", "rgb16", "bgr16", "8UC1", "8UC3",
                   "16UC1", *(f"bayer_{p}{b}" for p in _BAYER for b in (8, 16)))


def _guarded(kind: str):
    """A decoder whose failures on malformed fields (wrong types, sizes or shapes, absurd values) are one
    :class:`BagError` naming the topic, never a traceback."""
    def wrap(fn):
        @functools.wraps(fn)
        def decoder(msg, topic: str = "", *args, **kwargs):
            try:
                return fn(msg, topic, *args, **kwargs)
            except BagError:
                raise
            except (ValueError, TypeError, AttributeError, OverflowError, IndexError, KeyError, MemoryError,
                    cv2.error) as exc:
                text = (str(exc).strip().splitlines() or [type(exc).__name__])[0][:120]
                raise BagError(f"malformed {kind} message ({type(exc).__name__}: {text})", path=topic or None,
                               hint="the recording is damaged, or the topic holds another message type") from None
        return decoder
    return wrap


def stamp_ns(msg, fallback_ns: int) -> int:
    """The message's header stamp in ns, or the bag's receive time when the stamp is zero or absent."""
    header = getattr(msg, "header", None)
    stamp = getattr(header, "stamp", None)
    if stamp is None:
        return int(fallback_ns)
    sec = getattr(stamp, "sec", getattr(stamp, "secs", 0))
    nsec = getattr(stamp, "nanosec", getattr(stamp, "nsecs", 0))
    ns = int(sec) * 1_000_000_000 + int(nsec)
    return ns if ns > 0 else int(fallback_ns)


@_guarded("image")
def decode_image(msg, topic: str = "") -> np.ndarray:
    """A ``sensor_msgs/Image`` or ``CompressedImage`` as an 8- or 16-bit array, colour in OpenCV's BGR order."""
    if hasattr(msg, "format") and not hasattr(msg, "encoding"):
        return _decode_compressed(msg, topic)
    enc = str(msg.encoding)
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    data = np.asarray(msg.data, dtype=np.uint8)
    kind = enc.lower()
    depth = 16 if kind.endswith("16") or kind == "16uc1" else 8
    if kind.startswith("bayer_"):
        pattern = kind[len("bayer_"):-len(str(depth))]
        if pattern not in _BAYER or kind[-len(str(depth)):] != str(depth):
            raise BagError(f"unknown Bayer encoding {enc!r}", path=topic,
                           hint=f"supported: {', '.join(e for e in IMAGE_ENCODINGS if e.startswith('bayer'))}")
        channels, code = 1, _BAYER[pattern]
    elif kind in ("8uc1", "16uc1"):
        channels, code = 1, None
    elif kind == "8uc3":
        channels, code = 3, None
    else:
        base = kind.rstrip("0123456789")
        if base not in _CHANNELS or kind[len(base):] not in ("8", "16"):
            raise BagError(f"unknown image encoding {enc!r}", path=topic,
                           hint=f"supported: {', '.join(IMAGE_ENCODINGS)}")
        channels, code = _CHANNELS[base], {"rgb": cv2.COLOR_RGB2BGR, "rgba": cv2.COLOR_RGBA2BGR,
                                           "bgra": cv2.COLOR_BGRA2BGR}.get(base)
    itemsize = depth // 8
    row = w * channels * itemsize
    if h <= 0 or w <= 0 or step < row or data.size < step * (h - 1) + row:
        raise BagError(f"image message of {data.size} bytes does not hold {w}x{h} {enc} (step {step})",
                       path=topic, hint="the recording is truncated or its header is wrong")
    rows = np.lib.stride_tricks.as_strided(data, shape=(h, row), strides=(step, 1))
    dtype = np.dtype(np.uint16 if depth == 16 else np.uint8).newbyteorder(">" if msg.is_bigendian else "<")
    img = np.ascontiguousarray(rows).view(dtype).astype(dtype.newbyteorder("="))
    img = img.reshape(h, w, channels) if channels > 1 else img.reshape(h, w)
    if code is not None:
        img = cv2.cvtColor(img, code)
    return img


def _decode_compressed(msg, topic: str) -> np.ndarray:
    fmt = str(msg.format).lower()
    if "compresseddepth" in fmt:
        raise BagError(f"compressed depth image ({msg.format!r}) is not a camera image", path=topic,
                       hint="give the colour or mono image topic")
    img = decode_image_bytes(np.asarray(msg.data, dtype=np.uint8).tobytes(), topic, BagError)
    # "rgb8; jpeg compressed bgr8": the codec returns BGR, which is what the rest of lidarcam expects.
    return img


@_guarded("PointCloud2")
def decode_point_cloud(msg, topic: str = "", rings: bool = False) -> tuple:
    """``sensor_msgs/PointCloud2`` as (N, 3) float64 points and an (N,) intensity (or None); with ``rings``, each
    return's beam too, from a ``ring`` field (Velodyne's, Ouster's, Hesai's drivers), or None.

    Any field layout (offsets, padding, float32 or float64 coordinates, extra fields such as ``ring`` or
    ``t``), organised or not; NaN/inf and (0, 0, 0) no-returns are dropped.
    """
    fields = {f.name for f in msg.fields}
    inten_name = [n for n in _INTENSITY_FIELDS if n in fields][:1]
    ring_name = ["ring"] if rings and "ring" in fields else []
    pts, xyz, keep = _cloud_fields(msg, topic, inten_name + ring_name)
    if not keep.size:
        return (np.zeros((0, 3)), None) + ((None,) if rings else ())
    inten = pts[inten_name[0]][keep].astype(float) if inten_name else None
    if not rings:
        return xyz[keep], inten
    ring = pts["ring"][keep].astype(float) if ring_name else None
    if ring is not None and not (np.all(np.isfinite(ring)) and np.all(ring >= 0) and np.all(ring < 65536)):
        ring = None  # not beam numbers: the cloud is read as one without a ring field
    return xyz[keep], inten, None if ring is None else ring.astype(np.int64)


@_guarded("PointCloud2")
def decode_point_times(msg, topic: str = "", period_s: float | None = None) -> PointTimes | None:
    """The per-return times of the points :func:`decode_point_cloud` returns (in its order), as offsets from the
    message's header stamp (``point_times.field_times``): from the cloud's time field, else from each return's
    azimuth where the sweep's ``period_s`` is given (``point_times.azimuth_times``); None where neither tells."""
    return decode_timed_cloud(msg, topic, period_s)[1]


@_guarded("PointCloud2")
def decode_timed_cloud(msg, topic: str = "", period_s: float | None = None
                       ) -> tuple[np.ndarray, PointTimes | None]:
    """A cloud's returns (N, 3), as :func:`decode_point_cloud` gives them, with their times
    (:func:`decode_point_times`), from one reading of the message."""
    name = time_field(f.name for f in msg.fields)
    pts, xyz, keep = _cloud_fields(msg, topic, [name] if name else [])
    return xyz[keep], _times(msg, topic, period_s, name, pts, xyz, keep)


def _times(msg, topic, period_s, name, pts, xyz, keep) -> PointTimes | None:
    """The returns' times from the field ``name`` (or None), else from their azimuth (``period_s``)."""
    times = field_times(pts[name][keep], name, stamp_ns(msg, 0), topic) if name is not None else None
    rows = (np.arange(keep.size) // max(int(msg.width), 1))[keep] if int(msg.height) > 1 else None
    if times is not None:
        return against_stored_order(times, xyz[keep], rows)
    why = "the cloud has no time field" if name is None else f"its time field {name!r} holds one value throughout"
    return azimuth_times(xyz[keep], period_s, why, rows) if period_s else None


def _cloud_fields(msg, topic: str, extra: list[str]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A PointCloud2's x, y, z and ``extra`` fields as a structured array, its points as (N, 3) float64, and
    which of them are returns (finite, not (0, 0, 0))."""
    fields = {f.name: f for f in msg.fields}
    missing = [c for c in "xyz" if c not in fields]
    if missing:
        raise BagError(f"point cloud has no {', '.join(missing)} field (fields: {', '.join(fields) or 'none'})",
                       path=topic, hint="give a PointCloud2 topic with x, y, z")
    order = ">" if msg.is_bigendian else "<"
    names, formats, offsets = [], [], []
    for name in ("x", "y", "z", *extra):
        f = fields[name]
        if int(f.datatype) not in _POINT_FIELD_TYPES:
            raise BagError(f"field {name!r} has unknown PointField datatype {f.datatype}", path=topic,
                           hint="expected datatypes 1-8 (INT8 ... FLOAT64)")
        names.append(name)
        formats.append(order + _POINT_FIELD_TYPES[int(f.datatype)])
        offsets.append(int(f.offset))
    step, width, height, row_step = int(msg.point_step), int(msg.width), int(msg.height), int(msg.row_step)
    dtype = np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": step})
    data = np.asarray(msg.data, dtype=np.uint8)
    if width * height == 0:
        return np.zeros(0, dtype), np.zeros((0, 3)), np.zeros(0, bool)
    if step < dtype.itemsize or row_step < width * step or data.size < row_step * (height - 1) + width * step:
        raise BagError(f"point cloud of {data.size} bytes does not hold {height}x{width} points of "
                       f"{step} bytes (row_step {row_step})", path=topic,
                       hint="the recording is truncated or its header is wrong")
    rows = [data[r * row_step: r * row_step + width * step] for r in range(height)]
    pts = np.frombuffer(np.concatenate(rows).tobytes(), dtype=dtype)
    xyz = np.column_stack([pts["x"], pts["y"], pts["z"]]).astype(float)
    keep = np.all(np.isfinite(xyz), axis=1) & np.any(xyz != 0.0, axis=1)
    return pts, xyz, keep


@_guarded("LaserScan")
def decode_laser_scan(msg, topic: str = "") -> tuple[np.ndarray, np.ndarray]:
    """``sensor_msgs/LaserScan`` as (angles, ranges) in radians and metres; invalid returns as range 0."""
    ranges = np.asarray(msg.ranges, dtype=float)
    angles = float(msg.angle_min) + float(msg.angle_increment) * np.arange(len(ranges))
    valid = np.isfinite(ranges) & (ranges >= float(msg.range_min)) & (ranges <= float(msg.range_max))
    return angles, np.where(valid, ranges, 0.0)


def _field(msg, *names):
    for n in names:
        if hasattr(msg, n):
            return getattr(msg, n)
    raise AttributeError(names[0])


@_guarded("CameraInfo")
def camera_from_info(msg, topic: str = "") -> CameraModel:
    """``sensor_msgs/CameraInfo`` as the dataset's camera model.

    plumb_bob (5 coefficients) and rational_polynomial (8) become OpenCV's pinhole model; equidistant
    (k1..k4) becomes the fisheye model. ``K`` and ``D`` describe the raw (unrectified) image.
    """
    K = np.asarray(_field(msg, "k", "K"), dtype=float).reshape(3, 3)
    D = np.asarray(_field(msg, "d", "D"), dtype=float).ravel()
    model_name = str(msg.distortion_model).lower()
    if model_name in ("plumb_bob", "rational_polynomial", ""):
        model = PINHOLE
        if D.size not in (0, 4, 5, 8, 12, 14):
            raise BagError(f"{model_name} camera info has {D.size} distortion coefficients", path=topic,
                           hint="expected 5 (plumb_bob) or 8 (rational_polynomial)")
    elif model_name in ("equidistant", "fisheye"):
        model = FISHEYE
        D = D[:4] if D.size >= 4 else D
    else:
        raise BagError(f"unknown distortion model {msg.distortion_model!r}", path=topic,
                       hint="supported: plumb_bob, rational_polynomial, equidistant; or put the camera in "
                            "dataset.yaml yourself")
    if not np.any(K):
        raise BagError("camera info has an all-zero K (the camera is uncalibrated)", path=topic,
                       hint="drop --camera-info-topic to estimate intrinsics from the board views")
    try:
        return CameraModel(K=K, dist=D, width=int(msg.width), height=int(msg.height), model=model,
                           source=f"CameraInfo {topic}".strip())
    except ValueError as exc:
        raise BagError(f"invalid camera info ({exc})", path=topic, hint="check the recording's calibration") \
            from exc
