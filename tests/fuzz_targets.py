"""Fuzzing support shared by tests/test_fuzz_readers.py (a bounded run) and benchmarks/bench_fuzz.py (the long
run): every reader and decoder lidarcam has for files that come from elsewhere, a well-formed seed input for
each, and the mutations applied to it.

A *file target* is ``(name, suffix, seed bytes, read)``: ``read(path)`` reads the mutated file as lidarcam does.
A *message target* builds a ROS message from drawn field values and decodes it. The one rule checked on both:
the reader returns a well-formed result, or raises ``LidarcamError``; any other exception is a bug.
"""
from __future__ import annotations

import io
import re
import json
import struct
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace
from typing import Callable

import cv2
import numpy as np
import yaml
from hypothesis import strategies as st

from estimators.analysis.layout_analysis import analyse, layout_from_plan
from estimators.analysis.study import parse_spec
from estimators.pipeline.measurement import given_camera, given_covariance, parse_initial_guess, parse_rig_guess
from estimators.io.dataset import load_dataset
from estimators.io.export import FORMATS, export_calibration, load_calibration
from estimators.io.image_io import read_gray
from estimators.io.input_files import load_yaml
from estimators.io.intrinsics_file import load_intrinsics
from estimators.io.measurement_store import load_measurements
from estimators.io.pointcloud_io import read_scan_2d, read_sweep, write_scan
from estimators.io.ros_messages import (camera_from_info, decode_image, decode_laser_scan, decode_point_cloud,
                                       decode_point_times)
from estimators.simulation.simulator import default_camera

# Values a lying header puts where a count, a size or a dimension belongs.
LIES = ("0", "1", "-1", "2", "7", "65535", "65536", "2147483647", "2147483648", "4294967295", "4294967296",
        "999999999999", "18446744073709551615", "1e9", "nan", "inf", "-0", "3.5", "x")
LIE_WORDS = (0, 1, 2, 0x7FFF, 0xFFFF, 0x10000, 0x7FFFFFFF, 0x80000000, 0xFFFFFFFF, 100_000, 1_000_000_000)
TOKENS = ("x", "y", "z", "ring", "intensity", "F", "U", "I", "ascii", "binary", "binary_compressed", "float",
          "double", "uchar", "list", "vertex", "face", "NaN", "inf", "-", "", "~", "!!python/object:os.system",
          "&a", "*a", "[", "{", "null", "0x10")
HEADER_BYTES = 700


def mutate(seed: bytes, ops: list[tuple]) -> bytes:
    """Apply drawn operations: byte flips, truncation, insertion, deletion, numbers and words of the header
    replaced by lies, and 32-bit words of a binary header overwritten."""
    data = bytearray(seed)
    for op in ops:
        kind = op[0]
        n = len(data)
        if kind == "flip" and n:
            data[op[1] % n] ^= op[2]
        elif kind == "truncate":
            del data[op[1] % (n + 1):]
        elif kind == "insert":
            k = op[1] % (n + 1)
            data[k:k] = op[2]
        elif kind == "delete" and n:
            k = op[1] % n
            del data[k:k + op[2]]
        elif kind in ("number", "token"):
            head = bytes(data[:HEADER_BYTES])
            spans = ([m.span() for m in re.finditer(rb"-?\d+(\.\d+)?", head)] if kind == "number"
                     else [m.span() for m in re.finditer(rb"[A-Za-z_]+", head)])
            if spans:
                a, b = spans[op[1] % len(spans)]
                data[a:b] = op[2].encode()
        elif kind == "word" and n >= 4:
            k = op[1] % max(1, min(n, HEADER_BYTES) - 3)
            data[k:k + 4] = struct.pack(">I" if op[3] else "<I", op[2])
    return bytes(data)


def mutations() -> st.SearchStrategy:
    """Lists of one to four mutation operations (hypothesis shrinks them to the smallest that fails)."""
    op = st.one_of(
        st.tuples(st.just("flip"), st.integers(0, 1 << 30), st.integers(1, 255)),
        st.tuples(st.just("truncate"), st.integers(0, 1 << 30)),
        st.tuples(st.just("insert"), st.integers(0, 1 << 30), st.binary(min_size=1, max_size=24)),
        st.tuples(st.just("delete"), st.integers(0, 1 << 30), st.integers(1, 64)),
        st.tuples(st.just("number"), st.integers(0, 200), st.sampled_from(LIES)),
        st.tuples(st.just("token"), st.integers(0, 200), st.sampled_from(TOKENS)),
        st.tuples(st.just("word"), st.integers(0, HEADER_BYTES), st.sampled_from(LIE_WORDS), st.booleans()),
    )
    return st.lists(op, min_size=1, max_size=4)


# --- seed inputs ---------------------------------------------------------------------------------------------

def _points(n: int = 60) -> np.ndarray:
    rng = np.random.default_rng(0)
    return rng.normal(0.0, 3.0, (n, 3)).astype(np.float32)


def _scan_bytes(tmp: Path, name: str, **kw) -> bytes:
    path = tmp / name
    write_scan(path, _points(), intensity=np.arange(60, dtype=np.float32), **kw)
    return path.read_bytes()


def _ply_ascii(tmp: Path) -> bytes:
    from plyfile import PlyData, PlyElement

    v = np.array([tuple(p) for p in _points(20)], dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
    path = tmp / "a.ply"
    PlyData([PlyElement.describe(v, "vertex")], text=True).write(str(path))
    return path.read_bytes()


def _pcd_ascii_organised() -> bytes:
    rows = "\n".join(f"{x:.3f} {y:.3f} {z:.3f} {i}" for i, (x, y, z) in enumerate(_points(12)))
    return ("# .PCD v0.7\nVERSION 0.7\nFIELDS x y z intensity\nSIZE 4 4 4 4\nTYPE F F F F\nCOUNT 1 1 1 1\n"
            "WIDTH 4\nHEIGHT 3\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 12\nDATA ascii\n" + rows + "\n").encode()


def _image(kind: str) -> bytes:
    rng = np.random.default_rng(1)
    img = (rng.random((24, 32)) * 255).astype(np.uint8)
    if kind == "png16":
        ok, buf = cv2.imencode(".png", img.astype(np.uint16) * 257)
    elif kind == "jpeg":
        ok, buf = cv2.imencode(".jpg", img)
    elif kind == "palette":
        from PIL import Image

        out = io.BytesIO()
        Image.fromarray(img).convert("P").save(out, format="PNG")
        return out.getvalue()
    else:
        ok, buf = cv2.imencode(".png", img)
    return buf.tobytes()


def _dataset_yaml(charuco: bool = False) -> bytes:
    board = {"squares": [9, 7], "square_size": 0.1, "size": [1.0, 1.0]}
    if charuco:
        board.update(pattern="charuco", marker_size=0.07, dictionary="DICT_5X5_100", legacy_pattern=False)
    spec = {"lidar": "3d", "board": board, "camera": _camera_entry()}
    return yaml.safe_dump(spec, default_flow_style=None).encode()


def _camera_entry() -> dict:
    cam = default_camera()
    return {"model": cam.model, "width": cam.width, "height": cam.height, "K": cam.K.tolist(),
            "dist": cam.dist.tolist()}


def _plan_yaml() -> bytes:
    plan = {"camera": _camera_entry(), "board": {"squares": [9, 7], "square_size": 0.1, "size": [1.0, 1.0]},
            "lidar": {"model": "vlp16", "range_noise_m": 0.02}, "corner_noise_px": 0.2,
            "poses": [{"centre_m": [0.4 * (i - 1.5), 0.1, 3.0], "tilt_deg": 30, "azimuth_deg": a}
                      for i, a in enumerate((0, 90, 180, 270))]}
    return yaml.safe_dump(plan, default_flow_style=None).encode()


def _study_yaml() -> bytes:
    spec = {"name": "fuzz", "lidar": "3d", "model": "vlp16", "solvers": ["closed-form", "factor-graph"],
            "layouts": ["spread"], "frames": [4, 6], "range_noise_m": [0.02], "corner_noise_px": [0.2],
            "trials": 2, "seed": 0, "mode": "measurement"}
    return yaml.safe_dump(spec, default_flow_style=None).encode()


def _calibration_json() -> bytes:
    T = np.eye(4)
    T[:3, :3] = [[0, -1, 0], [0, 0, -1], [1, 0, 0]]
    T[:3, 3] = [0.1, -0.2, 0.05]
    return json.dumps({"T_camera_lidar": T.tolist(), "covariance": (np.eye(6) * 1e-6).tolist(),
                       "noise": {"corner_px": 0.2, "range_m": 0.02}, "frames": [{"name": "0000", "used": True}]},
                      indent=1).encode()


def _rig_calibration_json() -> bytes:
    """A rig's calibration.json as far as its initial guess reads it: every pair's transform."""
    T = json.loads(_calibration_json())["T_camera_lidar"]
    transforms = {"T_cam0_lidar0": {"T": T}, "T_cam0_cam1": {"T": np.eye(4).tolist()}}
    return json.dumps({"rig": True, "transforms": transforms}, indent=1).encode()


# --- readers -------------------------------------------------------------------------------------------------

def _read_dataset(path: Path):
    folder = path.parent / "ds"
    folder.mkdir(exist_ok=True)
    for name in ("0000.png", "0000.pcd"):  # a frame to pair (load_dataset does not read it)
        (folder / name).touch()
    (folder / "dataset.yaml").write_bytes(path.read_bytes())
    return load_dataset(folder)


def _read_plan(path: Path):
    plan = load_yaml(path, "plan")
    if not isinstance(plan, dict):
        return None
    layout, _ = layout_from_plan(plan, str(path))
    return analyse(layout)


def _read_study(path: Path):
    return parse_spec(load_yaml(path, "study spec"), str(path))


def _motion_npz(tmp: Path) -> bytes:
    from estimators.io.motion_track import MotionTrack, save_motion_track

    rng = np.random.default_rng(0)
    track = MotionTrack(1_700_000_000_000_000_000, np.arange(12) * 0.05, rng.uniform(0, 600, (12, 48, 2)),
                        np.arange(6) * 0.1, np.full(6, 20), rng.normal(0, 1, (120, 3)), rng.uniform(0, 0.1, 120),
                        "field 't'")
    folder = tmp / "motion_seed"
    folder.mkdir(exist_ok=True)
    return save_motion_track(folder, track).read_bytes()


def _read_motion(path: Path):
    from estimators.io.motion_track import load_motion_track

    (path.parent / "motion.npz").write_bytes(path.read_bytes())
    return load_motion_track(path.parent).sweeps()


def _checked_calibration_json() -> bytes:
    """A calibration.json as ``lidarcam check`` reads it: the extrinsic, its covariance and the intrinsics."""
    data = json.loads(_calibration_json())
    cam = default_camera()
    data["intrinsics"] = {"model": cam.model, "width": cam.width, "height": cam.height, "K": cam.K.tolist(),
                          "dist": cam.dist.tolist()}
    return json.dumps(data, indent=1).encode()


def _read_checked(path: Path):
    return parse_initial_guess([str(path)]), given_covariance(str(path)), given_camera(str(path))


def _read_calibration(path: Path):
    data = load_calibration(path)
    return [export_calibration(data, fmt) for fmt in FORMATS]


def _ros_intrinsics_yaml() -> bytes:
    return (b"image_width: 640\nimage_height: 480\ncamera_matrix:\n  rows: 3\n  cols: 3\n  data: [600.0, 0.0, 320.0, "
            b"0.0, 600.0, 240.0, 0.0, 0.0, 1.0]\ndistortion_model: plumb_bob\ndistortion_coefficients:\n  rows: 1\n"
            b"  cols: 5\n  data: [-0.1, 0.01, 0.0, 0.0, 0.0]\n")


def _opencv_intrinsics_yaml() -> bytes:
    fs = cv2.FileStorage("i.yaml", cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY)
    fs.write("camera_model", "pinhole")
    fs.write("image_width", 640)
    fs.write("image_height", 480)
    fs.write("camera_matrix", np.array([[600.0, 0, 320], [0, 600, 240], [0, 0, 1]]))
    fs.write("distortion_coefficients", np.array([[-0.1, 0.01, 0.0, 0.0, 0.0]]))
    return fs.releaseAndGetString().encode()


def _check_points(out) -> None:
    pts = out.points if hasattr(out, "points") else out
    assert np.all(np.isfinite(pts)), "non-finite points returned"


@dataclass(frozen=True)
class FileTarget:
    name: str
    suffix: str
    seed: Callable[[Path], bytes]
    read: Callable[[Path], object]
    check: Callable[[object], None] | None = None


FILE_TARGETS = (
    FileTarget("pcd_ascii", ".pcd", lambda t: _pcd_ascii_organised(), read_sweep, _check_points),
    FileTarget("pcd_binary", ".pcd", lambda t: _scan_bytes(t, "b.pcd", ring=np.arange(60) % 16), read_sweep,
               _check_points),
    FileTarget("pcd_binary_compressed", ".pcd",
               lambda t: _scan_bytes(t, "c.pcd", pcd_encoding="binary_compressed"), read_sweep, _check_points),
    FileTarget("ply_binary", ".ply", lambda t: _scan_bytes(t, "b.ply"), read_sweep, _check_points),
    FileTarget("ply_ascii", ".ply", _ply_ascii, read_sweep, _check_points),
    FileTarget("kitti_bin", ".bin", lambda t: _scan_bytes(t, "k.bin"), read_sweep, _check_points),
    FileTarget("npy", ".npy", lambda t: _scan_bytes(t, "n.npy"), read_sweep, _check_points),
    FileTarget("csv_2d", ".csv", lambda t: b"angle,range\n" + b"".join(
        f"{a:.4f},{2.0 + 0.1 * k:.4f}\n".encode() for k, a in enumerate(np.linspace(-1, 1, 30))),
        read_scan_2d, _check_points),
    FileTarget("png8", ".png", lambda t: _image("png8"), read_gray),
    FileTarget("png16", ".png", lambda t: _image("png16"), read_gray),
    FileTarget("png_palette", ".png", lambda t: _image("palette"), read_gray),
    FileTarget("jpeg", ".jpg", lambda t: _image("jpeg"), read_gray),
    FileTarget("dataset_yaml", ".yaml", lambda t: _dataset_yaml(), _read_dataset),
    FileTarget("dataset_yaml_charuco", ".yaml", lambda t: _dataset_yaml(charuco=True), _read_dataset),
    FileTarget("plan_yaml", ".yaml", lambda t: _plan_yaml(), _read_plan),
    FileTarget("study_yaml", ".yaml", lambda t: _study_yaml(), _read_study),
    FileTarget("calibration_json", ".json", lambda t: _calibration_json(), _read_calibration),
    FileTarget("motion_npz", ".npz", _motion_npz, _read_motion),
    FileTarget("check_calibration_json", ".json", lambda t: _checked_calibration_json(), _read_checked),
    FileTarget("initial_guess_json", ".json", lambda t: _calibration_json(),
               lambda p: parse_initial_guess([str(p)])),
    FileTarget("rig_initial_guess_json", ".json", lambda t: _rig_calibration_json(),
               lambda p: parse_rig_guess([str(p)])),
    FileTarget("intrinsics_ros_yaml", ".yaml", lambda t: _ros_intrinsics_yaml(), load_intrinsics),
    FileTarget("intrinsics_opencv_yaml", ".yaml", lambda t: _opencv_intrinsics_yaml(), load_intrinsics),
)


def measurements_target(seed_npz: bytes, seed_json: bytes) -> tuple[FileTarget, FileTarget]:
    """``measurements.npz`` and ``measurements.json`` (each mutated with the other intact)."""
    def read_npz(path: Path):
        (path.parent / (path.stem + ".json")).write_bytes(seed_json)
        return load_measurements(path)

    def read_json(path: Path):
        (path.parent / (path.stem + ".npz")).write_bytes(seed_npz)
        return load_measurements(path.with_suffix(".npz"))

    return (FileTarget("measurements_npz", ".npz", lambda t: seed_npz, read_npz),
            FileTarget("measurements_json", ".json", lambda t: seed_json, read_json))


def bag_target(seed_bag: bytes, board) -> FileTarget:
    """A small ROS 1 bag, extracted as `lidarcam extract` does."""
    from estimators.io.bag_extract import extract_bag

    def read(path: Path):
        out = path.parent / "extracted"
        return extract_bag(path, out, board, "/camera/image_raw", cloud_topic="/velodyne_points", overwrite=True)

    return FileTarget("ros1_bag", ".bag", lambda t: seed_bag, read)


# --- ROS messages --------------------------------------------------------------------------------------------

_INTS = st.one_of(st.integers(-3, 70), st.sampled_from([0, 1, 2**31 - 1, 2**31, 2**32 - 1, 2**32, 2**63 - 1]))
_FLOATS = st.floats(allow_nan=True, allow_infinity=True, width=32)


def _blob(max_size: int = 4096) -> st.SearchStrategy:
    return st.binary(max_size=max_size).map(lambda b: np.frombuffer(b, np.uint8))


def image_messages() -> st.SearchStrategy:
    raw = st.builds(SimpleNamespace, encoding=st.sampled_from(["mono8", "mono16", "rgb8", "bgra8", "16UC1",
                                                                "bayer_rggb8", "bayer_xx8", "yuv422", "", "8UC3"]),
                    height=_INTS, width=_INTS, step=_INTS, is_bigendian=st.booleans(), data=_blob())
    good = _image("png8")
    compressed = st.builds(SimpleNamespace, format=st.sampled_from(["jpeg", "png", "rgb8; jpeg compressed bgr8",
                                                                    "compressedDepth", ""]),
                           data=st.one_of(_blob(), mutations().map(lambda ops: np.frombuffer(
                               mutate(good, ops), np.uint8))))
    return st.one_of(raw, compressed)


def cloud_messages() -> st.SearchStrategy:
    field = st.builds(SimpleNamespace, name=st.sampled_from(["x", "y", "z", "intensity", "ring", "t", "timestamp"]),
                      offset=_INTS, datatype=st.integers(-1, 10), count=st.integers(0, 3))
    return st.builds(SimpleNamespace, fields=st.lists(field, max_size=6), is_bigendian=st.booleans(),
                     point_step=_INTS, row_step=_INTS, width=_INTS, height=_INTS, data=_blob())


def scan_messages() -> st.SearchStrategy:
    return st.builds(SimpleNamespace, ranges=st.lists(_FLOATS, max_size=200), angle_min=_FLOATS,
                     angle_increment=_FLOATS, range_min=_FLOATS, range_max=_FLOATS)


def info_messages() -> st.SearchStrategy:
    return st.builds(SimpleNamespace, k=st.lists(_FLOATS, max_size=12), d=st.lists(_FLOATS, max_size=16),
                     distortion_model=st.sampled_from(["plumb_bob", "rational_polynomial", "equidistant", "", "xyz"]),
                     width=_INTS, height=_INTS)


MESSAGE_TARGETS = (
    ("Image/CompressedImage", image_messages, lambda m: decode_image(m, "/camera/image_raw")),
    ("PointCloud2", cloud_messages, lambda m: decode_point_cloud(m, "/points")),
    ("PointCloud2 with rings", cloud_messages, lambda m: decode_point_cloud(m, "/points", rings=True)),
    ("PointCloud2 per-return times", cloud_messages, lambda m: decode_point_times(m, "/points", 0.1)),
    ("LaserScan", scan_messages, lambda m: decode_laser_scan(m, "/scan")),
    ("CameraInfo", info_messages, lambda m: camera_from_info(m, "/camera_info")),
)
