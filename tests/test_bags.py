"""Datasets from ROS 1, ROS 2 sqlite3 and MCAP bags (written here with rosbags from simulated datasets), the
message decoders, and bad bags through the CLI."""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from estimators.calibration import calibrate_pair
from estimators.cli import main
from estimators.errors import BagError
from estimators.io.bag_extract import ExtractOptions, _Check, _StillSegments, extract_bag
from estimators.io.dataset import load_dataset
from estimators.io.pointcloud_io import read_sweep
from estimators.io.ros_messages import camera_from_info, decode_image, decode_point_cloud
from estimators.simulation.simulator import simulate_dataset
from geometry.rotations import rotation_error

from .rosbag_writer import _Bag, bayer_mosaic_rggb, image_message, write_bag_from_dataset

# The folder form's tolerance for 5 VLP-16 frames (tests/test_end_to_end.py: twice the 8-frame target).
MAX_ROT_DEG, MAX_TRANS_M = 1.0, 0.06
BAG_NAMES = {"ros1": "rig.bag", "sqlite3": "rig_sqlite3", "mcap": "rig_mcap"}


@pytest.fixture(scope="module")
def sim5(tmp_path_factory) -> Path:
    return simulate_dataset(tmp_path_factory.mktemp("bags") / "sim", n_poses=5, seed=30, lidar="vlp16")


@pytest.fixture(scope="module")
def folder_result(sim5):
    return calibrate_pair(load_dataset(sim5), posterior=None, rng=np.random.default_rng(0))


def _errors(T, T_ref):
    return np.degrees(rotation_error(T[:3, :3], T_ref[:3, :3])), np.linalg.norm(T[:3, 3] - T_ref[:3, 3])


@pytest.mark.parametrize("kind", ["ros1", "sqlite3", "mcap"])
def test_bag_extracts_one_frame_per_still_pose_and_calibrates_like_the_folder(sim5, folder_result, tmp_path,
                                                                               kind):
    """5 poses held still 1.5 s each (images 5 Hz, scans 10 Hz stamped 13 ms later), moves in between: 5 frames,
    the intrinsics from CameraInfo, and a calibration within the folder form's tolerance of the truth and
    within 0.05 deg / 1 mm of the folder form's own estimate (the images differ by 1 grey level of noise)."""
    bag = write_bag_from_dataset(sim5, tmp_path / BAG_NAMES[kind], kind, image_hz=5)
    summary = extract_bag(bag, tmp_path / "ds", load_dataset(sim5).board, "/camera/image_raw",
                          cloud_topic="/velodyne_points")
    assert summary.frames == 5 and summary.counts["kept"] == 5
    assert sum(summary.counts.values()) == summary.images
    assert summary.counts["no_board"] >= 4 and summary.counts["moving"] > 0
    ds, truth = load_dataset(tmp_path / "ds"), load_dataset(sim5)
    np.testing.assert_allclose(ds.camera.K, truth.camera.K)
    np.testing.assert_allclose(ds.camera.dist, truth.camera.dist)
    record = json.loads((tmp_path / "ds" / "extract.json").read_text())
    assert all(abs(f["dt_ms"] - 13.0) < 1e-6 for f in record["frames"])
    # these clouds carry no time field: how their returns would be timed is said and recorded
    assert record["point_times"] == summary.point_times and "no time field" in summary.point_times
    assert f"per-return LiDAR time: {summary.point_times}" in summary.lines()
    # each return's beam kept from the clouds' ring field, as the folder's sweeps have it
    for f, g in zip(ds.frames, truth.frames, strict=True):
        got, want = read_sweep(f.scan), read_sweep(g.scan)
        np.testing.assert_allclose(got.points, want.points, atol=1e-5)
        np.testing.assert_array_equal(got.ring, want.ring)
    # Streaming: of the bag's 75 scans, never more than the pairing window's few were held at once, and no
    # more images than the 0.6 s gaps between poses (when this recording has no scans) hold: 3 or 4 images,
    # and the first of the next pose's, examined before its scan arrives 13 ms later.
    peak = record["peak_buffered_messages"]
    assert peak["scans"] <= 12 and peak["images_awaiting_a_scan"] <= 5, peak
    result = calibrate_pair(ds, posterior=None, rng=np.random.default_rng(0))
    assert result.frames_used == 5
    rot, trans = _errors(result.T_camera_lidar, truth.ground_truth())
    assert rot < MAX_ROT_DEG and trans < MAX_TRANS_M, (rot, trans)
    rot, trans = _errors(result.T_camera_lidar, folder_result.T_camera_lidar)
    assert rot < 0.05 and trans < 1e-3, (rot, trans)


def test_laser_scan_bag_gives_the_2d_dataset_back(sim_2d, tmp_path):
    """LaserScan messages (invalid returns as inf) become angle,range CSVs equal to the originals to float32
    precision, ROS 1's CameraInfo (upper-case K, D) gives the intrinsics, and the extracted 2D dataset
    calibrates within 1 deg / 5 cm."""
    bag = write_bag_from_dataset(sim_2d, tmp_path / "scan.bag", "ros1", image_hz=5)
    truth = load_dataset(sim_2d)
    summary = extract_bag(bag, tmp_path / "ds", truth.board, "/camera/image_raw", scan_topic="/scan")
    assert summary.frames == 6 and summary.lidar == "2d" and summary.camera_source is not None
    for name in ("0000", "0005"):
        a = np.loadtxt(sim_2d / f"{name}.csv", delimiter=",", skiprows=1)
        b = np.loadtxt(tmp_path / "ds" / f"{name}.csv", delimiter=",", skiprows=1)
        np.testing.assert_allclose(b, a, atol=1e-5)
    ds = load_dataset(tmp_path / "ds")
    assert ds.lidar == "2d"
    np.testing.assert_allclose(ds.camera.K, truth.camera.K)
    np.testing.assert_allclose(ds.camera.dist, truth.camera.dist)
    result = calibrate_pair(ds, posterior=None)
    rot, trans = _errors(result.T_camera_lidar, truth.ground_truth())
    assert rot < 1.0 and trans < 0.05, (rot, trans)


def _checks(segments):
    """(duration s, corner offset px) still segments at 5 Hz, separated by a frame without a board."""
    base = np.random.default_rng(0).uniform(0, 500, (20, 2))
    t, out = 0, []
    for duration, offset in segments:
        for k in range(int(round(duration * 5)) + 1):
            out.append(_Check(t, np.zeros((2, 2), np.uint8), base + offset + 0.1 * (k % 2), scan=object(),
                              scan_stamp=t))
            t += 200_000_000
        out.append(_Check(t, np.zeros((2, 2), np.uint8), None))
        t += 200_000_000
    return out


def test_still_segments_keep_one_frame_per_pose_and_say_why_for_the_rest():
    kept = []
    seg = _StillSegments(ExtractOptions(still_s=1.0, still_px=2.0), kept.append)
    # pose A 1.6 s, a 0.4 s pause (too short), pose B 1.2 s, pose A again 2 s (a repeat).
    for c in _checks([(1.6, 0.0), (0.4, 40.0), (1.2, 80.0), (2.0, 0.0)]):
        seg.add(c)
    seg.close()
    assert len(kept) == 2
    assert np.allclose(kept[0].corners.mean(0) - kept[1].corners.mean(0), -80, atol=0.2)
    assert kept[0].stamp not in (0, 1_600_000_000)  # an interior image, not the segment's first or last
    c = seg.counts
    assert c["kept"] == 2 and c["moving"] == 3 and c["repeat_pose"] == 11 and c["no_board"] == 4
    assert c["same_pose"] == (9 - 1) + (7 - 1)


def test_image_decoders_match_the_original_pixels():
    from rosbags.typesys import Stores, get_typestore

    rng = np.random.default_rng(1)
    bag = _Bag.__new__(_Bag)
    bag.kind, bag.ts = "sqlite3", get_typestore(Stores.ROS2_HUMBLE)
    gray = cv2.GaussianBlur(rng.uniform(0, 255, (48, 64)), (0, 0), 3).astype(np.uint8)
    assert np.array_equal(decode_image(image_message(bag, gray, 0, "mono8")), gray)
    assert np.array_equal(cv2.cvtColor(decode_image(image_message(bag, gray, 0, "rgb8")), cv2.COLOR_BGR2GRAY), gray)
    jpeg = decode_image(image_message(bag, gray, 0, "jpeg"))
    assert np.abs(jpeg.astype(int) - gray).max() <= 3
    # A colour scene through an RGGB sensor: the demosaiced image matches it away from the border, and the
    # red and blue planes are not swapped (which the wrong Bayer code would do).
    bgr = np.stack([np.full((48, 64), 30), np.full((48, 64), 120), np.full((48, 64), 220)], -1).astype(np.uint8)
    mosaic = bayer_mosaic_rggb(bgr[..., ::-1])
    T = bag.ts.types
    msg = T["sensor_msgs/msg/Image"](header=bag.header(0, "c"), height=48, width=64, encoding="bayer_rggb8",
                                     is_bigendian=0, step=64, data=mosaic.ravel())
    out = decode_image(msg)
    assert np.abs(out[4:-4, 4:-4].astype(int) - bgr[4:-4, 4:-4]).max() <= 2
    # 16-bit big-endian mono in rows padded to 136 bytes.
    img16 = rng.integers(0, 65535, (10, 64)).astype(">u2")
    padded = np.zeros((10, 136), np.uint8)
    padded[:, :128] = img16.view(np.uint8).reshape(10, 128)
    msg = T["sensor_msgs/msg/Image"](header=bag.header(0, "c"), height=10, width=64, encoding="mono16",
                                     is_bigendian=1, step=136, data=padded.ravel())
    assert np.array_equal(decode_image(msg), img16.astype(np.uint16))
    msg = T["sensor_msgs/msg/Image"](header=bag.header(0, "c"), height=10, width=64, encoding="yuv422",
                                     is_bigendian=0, step=128, data=np.zeros(1280, np.uint8))
    with pytest.raises(BagError, match="unknown image encoding 'yuv422'"):
        decode_image(msg, "/cam")


def _cloud(fields, points, point_step, height=1, row_pad=0, big=False):
    """A PointCloud2-like message from named numpy columns placed at the given offsets."""
    from types import SimpleNamespace

    names = [f[0] for f in fields]
    order = ">" if big else "<"
    dtype = np.dtype({"names": names, "formats": [order + f[2] for f in fields], "offsets": [f[1] for f in fields],
                      "itemsize": point_step})
    arr = np.zeros(len(points[names[0]]), dtype)
    for n in names:
        arr[n] = points[n]
    width = len(arr) // height
    rows = arr.view(np.uint8).reshape(height, width * point_step)
    data = np.concatenate([rows, np.zeros((height, row_pad), np.uint8)], axis=1).ravel()
    codes = {"f4": 7, "f8": 8, "u2": 4, "u1": 2}
    return SimpleNamespace(
        fields=[SimpleNamespace(name=n, offset=o, datatype=codes[t], count=1) for n, o, t in fields],
        is_bigendian=big, point_step=point_step, row_step=width * point_step + row_pad, height=height,
        width=width, data=data)


def test_point_cloud_layouts_decode_to_the_same_points():
    rng = np.random.default_rng(2)
    xyz = rng.normal(0, 5, (24, 3))
    cols = {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2], "intensity": np.arange(24.0), "ring": np.arange(24) % 8}
    # float64 coordinates after a ring field, organised 4 x 6 with row padding, big-endian.
    msg = _cloud([("ring", 0, "u2"), ("x", 8, "f8"), ("y", 16, "f8"), ("z", 24, "f8"), ("intensity", 32, "f4")],
                 cols, 40, height=4, row_pad=12, big=True)
    pts, inten = decode_point_cloud(msg)
    np.testing.assert_allclose(pts, xyz)
    np.testing.assert_allclose(inten, np.arange(24.0))
    _, _, ring = decode_point_cloud(msg, rings=True)
    np.testing.assert_array_equal(ring, np.arange(24) % 8)
    # a float ring field holding NaN is no beam index: read as a cloud without one
    bad = dict(cols, ring=np.where(np.arange(24) == 3, np.nan, np.arange(24) % 8))
    msg = _cloud([("x", 0, "f4"), ("y", 4, "f4"), ("z", 8, "f4"), ("ring", 12, "f4")], bad, 16)
    assert decode_point_cloud(msg, rings=True)[2] is None
    # float32, no intensity and no ring; NaN and (0,0,0) no-returns dropped.
    xyz2 = xyz.copy()
    xyz2[3] = np.nan
    xyz2[5] = 0.0
    msg = _cloud([("x", 0, "f4"), ("y", 4, "f4"), ("z", 8, "f4")], {"x": xyz2[:, 0], "y": xyz2[:, 1],
                                                                     "z": xyz2[:, 2]}, 16)
    pts, inten = decode_point_cloud(msg)
    assert inten is None and len(pts) == 22
    assert decode_point_cloud(msg, rings=True)[2] is None
    np.testing.assert_allclose(pts, np.delete(xyz, [3, 5], axis=0), rtol=1e-6, atol=1e-5)
    msg = _cloud([("x", 0, "f4"), ("y", 4, "f4")], {"x": xyz[:, 0], "y": xyz[:, 1]}, 8)
    with pytest.raises(BagError, match="no z field"):
        decode_point_cloud(msg, "/points")


def test_camera_info_models():
    from types import SimpleNamespace

    K = [600.0, 0, 320, 0, 610, 240, 0, 0, 1]
    cam = camera_from_info(SimpleNamespace(K=K, D=[0.1, -0.2, 0.001, 0.002, 0.03, 0.01, 0.0, 0.005],
                                           distortion_model="rational_polynomial", width=640, height=480))
    assert cam.model == "pinhole" and cam.dist.size == 8 and cam.K[1, 1] == 610
    cam = camera_from_info(SimpleNamespace(k=K, d=[0.1, 0.01, -0.002, 0.0003], distortion_model="equidistant",
                                           width=640, height=480))
    assert cam.model == "fisheye" and np.allclose(cam.dist, [0.1, 0.01, -0.002, 0.0003])
    with pytest.raises(BagError, match="unknown distortion model 'double_sphere'"):
        camera_from_info(SimpleNamespace(k=K, d=[0.1], distortion_model="double_sphere", width=640, height=480))
    with pytest.raises(BagError, match="all-zero K"):
        camera_from_info(SimpleNamespace(k=[0.0] * 9, d=[], distortion_model="plumb_bob", width=640, height=480))


def _one_line_error(capsys, argv, *needles):
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("lidarcam: error:"), err
    for n in needles:
        assert n in err, err
    return err


def test_a_board_held_still_s_plus_one_camera_period_is_kept_whatever_the_stamp_jitter(sim5, tmp_path):
    """Issue 20's regression: 10 Hz images with 0.3 ms stamp jitter, each pose held 1.1 s (--still-s 1 plus one
    camera period), examined at 5 Hz. Examining only when ``stamp - last_checked >= 0.2 s`` skipped about half
    the cells (the next image lands 0.2 s +- jitter later) and lost poses; the fixed grid keeps all 5 (one seed of
    the jitter: three had taken 20 s of make test)."""
    seed = 0
    bag = write_bag_from_dataset(sim5, tmp_path / "jitter.bag", "ros1", image_hz=10, still_s=1.1, move_s=0.6,
                                 stamp_jitter_s=3e-4, seed=seed)
    summary = extract_bag(bag, tmp_path / "ds", load_dataset(sim5).board, "/camera/image_raw",
                          cloud_topic="/velodyne_points")
    assert summary.frames == 5, summary.lines()
    # and a pose held for clearly less than --still-s is not kept
    short = write_bag_from_dataset(sim5, tmp_path / "short.bag", "ros1", image_hz=10, still_s=0.7, move_s=0.6,
                                   stamp_jitter_s=3e-4, seed=seed)
    with pytest.raises(BagError, match="no still board poses"):
        extract_bag(short, tmp_path / "ds2", load_dataset(sim5).board, "/camera/image_raw",
                    cloud_topic="/velodyne_points")


def test_a_board_that_never_stops_is_followed_and_untimed_returns_are_refused_saying_so(sim5, tmp_path):
    """Each pose's image sliding 40 px/s (8 px between the 5 Hz images) for 1.4 s: read as a moving board (every
    image and sweep), and since these sweeps' returns carry no time field and are not stored in firing order, the
    error says a moving board needs each return's time (not that no pose was held long enough); no folder. Without
    CameraInfo the error says the board cannot be followed without intrinsics."""
    bag = write_bag_from_dataset(sim5, tmp_path / "moving.bag", "ros1", image_hz=5, still_s=1.4,
                                 drift_px_per_s=40.0)
    board = load_dataset(sim5).board
    with pytest.raises(BagError, match=r"the board moves, and the sweeps' returns carry no time"):
        extract_bag(bag, tmp_path / "ds", board, "/camera/image_raw", cloud_topic="/velodyne_points")
    with pytest.raises(BagError, match=r"the board moves \(its corners moved beyond --still-px between \d+ of the "
                                       r"\d+ examined images that show it\), and following it needs the camera's "
                                       r"intrinsics"):
        extract_bag(bag, tmp_path / "ds", board, "/camera/image_raw", cloud_topic="/velodyne_points",
                    use_camera_info=False)
    assert not (tmp_path / "ds").exists()


def test_bad_bags_are_one_line_errors_with_no_output(sim5, tmp_path, capsys):
    bag = write_bag_from_dataset(sim5, tmp_path / "b.bag", "ros1", image_hz=5, still_s=0.6, move_s=0.4)
    out = tmp_path / "out"
    common = ["extract", str(bag), "--board", "9x7:0.1:1.0x1.0", "--out", str(out)]
    _one_line_error(capsys, common + ["--image-topic", "/cam/image", "--cloud-topic", "/velodyne_points"],
                    "no topic '/cam/image'", "/camera/image_raw", "--image-topic")
    _one_line_error(capsys, common + ["--image-topic", "/camera/image_raw", "--cloud-topic", "/points"],
                    "no topic '/points'", "/velodyne_points")
    # Held still only 0.6 s per pose: nothing passes --still-s 1.
    _one_line_error(capsys, common + ["--image-topic", "/camera/image_raw", "--cloud-topic", "/velodyne_points"],
                    "no still board poses", "--still-s")
    _one_line_error(capsys, ["extract", str(tmp_path / "nope.bag"), "--board", "9x7:0.1", "--out", str(out),
                             "--image-topic", "/a", "--cloud-topic", "/b"], "bag not found")
    assert not out.exists()
    # An encoding lidarcam does not decode, and scans an hour away from every image.
    enc = write_bag_from_dataset(sim5, tmp_path / "enc", "mcap", image_hz=2, encoding="yuv422")
    _one_line_error(capsys, ["extract", str(enc), "--board", "9x7:0.1", "--out", str(out), "--image-topic",
                             "/camera/image_raw", "--cloud-topic", "/velodyne_points"], "yuv422", "/camera/image_raw")
    late = write_bag_from_dataset(sim5, tmp_path / "late", "sqlite3", image_hz=2, scan_offset_s=3600.0)
    _one_line_error(capsys, ["extract", str(late), "--board", "9x7:0.1", "--out", str(out), "--image-topic",
                             "/camera/image_raw", "--cloud-topic", "/velodyne_points"], "do not overlap in time")
    assert not out.exists() and not any(p.name.startswith(".out") for p in tmp_path.iterdir())


def test_bag_to_tf_line_from_the_command_line(sim5, tmp_path, capsys):
    """The whole user path: extract, calibrate, export; the pasted ROS 2 tf line encodes the calibration."""
    bag = write_bag_from_dataset(sim5, tmp_path / "rig_mcap", "mcap", image_hz=5)
    assert main(["extract", str(bag), "--image-topic", "/camera/image_raw", "--cloud-topic", "/velodyne_points",
                 "--board", "9x7:0.1:1.0x1.0", "--out", str(tmp_path / "ds")]) == 0
    assert "5 frames kept" in capsys.readouterr().out
    assert main(["calibrate", str(tmp_path / "ds"), "--out", str(tmp_path / "cal"), "--samples", "0",
                 "--no-report"]) == 0
    capsys.readouterr()
    assert main(["export", str(tmp_path / "cal" / "calibration.json"), "--format", "ros-tf", "--parent", "lidar",
                 "--camera-frame", "cam_optical", "--lidar-frame", "velodyne"]) == 0
    text = capsys.readouterr().out
    from .test_export import parse_ros_tf

    T_lidar_cam = parse_ros_tf(text, "ros2", parent="velodyne", child="cam_optical")
    T = np.asarray(json.loads((tmp_path / "cal" / "calibration.json").read_text())["T_camera_lidar"])
    np.testing.assert_allclose(T_lidar_cam @ T, np.eye(4), atol=1e-7)


def test_camera_info_topic_is_found_beside_or_above_the_image_topic():
    from types import SimpleNamespace

    from estimators.io.bag_extract import _camera_info_topic

    def reader(*topics):
        return SimpleNamespace(connections=[SimpleNamespace(topic=t, msgtype="sensor_msgs/msg/CameraInfo")
                                            for t in topics])

    two = reader("/cam/camera_info", "/other/camera_info")
    assert _camera_info_topic(two, "/cam/image_raw/compressed") == "/cam/camera_info"
    assert _camera_info_topic(two, "/cam/image_raw") == "/cam/camera_info"
    assert _camera_info_topic(two, "/x/image") is None  # two candidates, neither beside it: none is guessed
    assert _camera_info_topic(reader("/only/camera_info"), "/x/image") == "/only/camera_info"


def test_each_image_is_searched_for_the_board_once_per_extract(monkeypatch):
    """``bag_extract.Detections``: an image already searched (the same content, at the same size) is not searched
    again, and what it gives back is a copy (a caller's change does not reach the next); another image is."""
    from estimators.io import bag_extract
    from estimators.simulation.board_drawing import draw_board
    from estimators.simulation.simulator import default_rig, sample_board_poses

    rng = np.random.default_rng(4)
    rig = default_rig(rng)
    pose = sample_board_poses(rig, 1, rng)[0]
    image = draw_board(rig.camera, rig.board, pose[None], rng)
    other = draw_board(rig.camera, rig.board, pose[None], rng)  # its own pixel noise
    calls = []
    detect = bag_extract._detect
    monkeypatch.setattr(bag_extract, "_detect", lambda *a: calls.append(1) or detect(*a))
    search = bag_extract.Detections(rig.board)
    first = search(image)
    assert first is not None and len(calls) == 1
    first[:] = 0.0
    again = search(image.copy(), rig.board)
    assert len(calls) == 1 and np.array_equal(again, detect(image, rig.board))
    search(other)
    assert len(calls) == 2
