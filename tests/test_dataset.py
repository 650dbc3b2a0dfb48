"""The dataset folder contract: parsing, pairing and one-line errors."""
from __future__ import annotations

import numpy as np
import pytest

from estimators.errors import DatasetError
from estimators.io.dataset import load_dataset

YAML = """lidar: 3d
board: {squares: [9, 7], square_size: 0.1, size: [1.0, 1.0]}
camera: {model: fisheye, width: 640, height: 480, K: [[400, 0, 320], [0, 400, 240], [0, 0, 1]],
         dist: [0.01, 0.0, 0.0, 0.0]}
"""


def _make(tmp_path, yaml_text=YAML, stems=("0000", "0001"), scan=".npy"):
    (tmp_path / "dataset.yaml").write_text(yaml_text)
    for s in stems:
        (tmp_path / f"{s}.png").write_bytes(b"")
        np.save(tmp_path / f"{s}{scan}", np.ones((4, 3)))
    return tmp_path


def test_parses_board_camera_and_pairs_frames(tmp_path):
    ds = load_dataset(_make(tmp_path))
    assert ds.lidar == "3d" and ds.board.squares == (9, 7) and ds.board.size == (1.0, 1.0)
    assert ds.camera.model == "fisheye" and ds.camera.dist.shape == (4,)
    assert [f.name for f in ds.frames] == ["0000", "0001"]
    assert ds.ground_truth() is None


@pytest.mark.parametrize("lidar, family, accuracy", [
    ("3d", None, 0.05),
    ("{type: 3d, family: Ouster}", "ouster", 0.03),
    ("{type: 3d, family: hesai, range_accuracy_m: 0.015}", "hesai", 0.015),
    ("{family: some-new-lidar}", "some-new-lidar", 0.05),
])
def test_the_lidar_entry_gives_the_range_accuracy_of_the_range_terms_priors(tmp_path, lidar, family, accuracy):
    """``lidar: 3d`` or a mapping with the sensor family and its range accuracy: the range model's priors come
    from the accuracy given, else the family's default, else the conservative 5 cm."""
    from estimators.calibration import dataset_range_accuracy
    from estimators.solvers.range_model import FrameLabels, terms_for

    ds = load_dataset(_make(tmp_path, YAML.replace("lidar: 3d", f"lidar: {lidar}")))
    assert ds.lidar == "3d" and ds.lidar_family == family
    assert dataset_range_accuracy(ds) == pytest.approx(accuracy)
    terms = terms_for("per-ring", FrameLabels((np.array([0, 1]),), (None,)), dataset_range_accuracy(ds))
    assert terms.prior_sd == pytest.approx((accuracy, 0.2 * accuracy, 0.2 * accuracy))


def test_camera_is_optional(tmp_path):
    ds = load_dataset(_make(tmp_path, "lidar: 3d\nboard: {squares: [6, 8], square_size: 0.095}\n"))
    assert ds.camera is None and not ds.board.size_known


@pytest.mark.parametrize("text,match", [
    ("lidar: 4d\nboard: {squares: [9, 7], square_size: 0.1}\n", "lidar must be"),
    ("lidar: 3d\n", "board needs squares"),
    ("lidar: 3d\nboard: {squares: [9, 7], square_size: -1}\n", "invalid board"),
    ("lidar: [3d\n", "invalid YAML"),
    ("- a\n- b\n", "expected a mapping"),
    (YAML.replace("fisheye", "orthographic"), "pinhole or fisheye"),
    (YAML.replace("lidar: 3d", "lidar: {type: 3d, range_accuracy_m: -0.03}"), "range_accuracy_m must be"),
    (YAML.replace("lidar: 3d", "lidar: {type: 3d, accuracy: 0.03}"), "unknown lidar key"),
    (YAML.replace("lidar: 3d", "lidar: {type: 4d}"), "lidar must be"),
    (YAML + "range_accuracy_m: 0.03\n", r"unknown key\(s\) \['range_accuracy_m'\].*under lidar:"),
    (YAML.replace("board:", "borad:"), r"unknown key\(s\) \['borad'\]"),
    (YAML.replace("dist: [0.01, 0.0, 0.0, 0.0]", "dist: [0.01]"), "invalid camera"),
    (YAML.replace("[[400, 0, 320], [0, 400, 240], [0, 0, 1]]", "[[400, 0, 0], [0, 400, 0], [320, 240, 1]]"),
     r"invalid camera .*\(transposed\?\)"),
    (YAML.replace("square_size: 0.1, size: [1.0, 1.0]", "square_size: 100"), r"square_size in metres.*millimetres"),
    (YAML.replace("size: [1.0, 1.0]", "size: [1000, 1000]"), r"board size in metres.*millimetres"),
    ("lidar: 3d\nboard: {squares: [9, 7], square_size: 0.1}\ncamera: {width: 10}\n", "camera lacks K, height"),
    ("!!python/object/apply:os.system ['echo hacked']\n", "invalid YAML"),
])
def test_bad_yaml_is_one_line_naming_the_file(tmp_path, text, match):
    _make(tmp_path, text)
    with pytest.raises(DatasetError, match=match) as info:
        load_dataset(tmp_path)
    assert "dataset.yaml" in info.value.message and "\n" not in info.value.message


def test_unpaired_and_missing(tmp_path):
    _make(tmp_path)
    (tmp_path / "0002.png").write_bytes(b"")
    with pytest.raises(DatasetError, match="0002.png: image has no scan"):
        load_dataset(tmp_path)
    (tmp_path / "0002.csv").write_text("angle,range\n0.0,1.0\n")  # a 2D scanner's scan in a 3D dataset: named
    with pytest.raises(DatasetError, match="0002.csv is a 2D LiDAR's scan: set lidar in dataset.yaml"):
        load_dataset(tmp_path)
    (tmp_path / "0002.csv").unlink()
    (tmp_path / "0002.png").unlink()
    np.save(tmp_path / "0003.npy", np.ones((4, 3)))
    with pytest.raises(DatasetError, match="0003.npy: scan has no image"):
        load_dataset(tmp_path)
    with pytest.raises(DatasetError, match="dataset folder not found"):
        load_dataset(tmp_path / "nope")
    (tmp_path / "0003.npy").unlink()
    (tmp_path / "dataset.yaml").unlink()
    with pytest.raises(DatasetError, match="no dataset.yaml"):
        load_dataset(tmp_path)


def test_two_scans_for_one_frame(tmp_path):
    _make(tmp_path)
    np.ones((4, 4), np.float32).tofile(tmp_path / "0000.bin")
    with pytest.raises(DatasetError, match="two files for frame '0000'"):
        load_dataset(tmp_path)


ROS_YAML = """image_width: 640
image_height: 480
camera_name: cam
camera_matrix:
  rows: 3
  cols: 3
  data: [600.0, 0.0, 321.5, 0.0, 601.0, 239.5, 0.0, 0.0, 1.0]
distortion_model: {model}
distortion_coefficients:
  rows: 1
  cols: {n}
  data: {dist}
"""


@pytest.mark.parametrize("model,dist,expect", [("plumb_bob", [-0.1, 0.02, 0.001, -0.002, 0.0], "pinhole"),
                                               ("equidistant", [0.01, -0.02, 0.003, -0.001], "fisheye")])
def test_intrinsics_files_of_ros_opencv_and_lidarcam_give_one_camera(tmp_path, model, dist, expect):
    """ROS camera_calibration's YAML, OpenCV's FileStorage (as lidarcam's opencv-yaml export writes it) and a
    dataset.yaml's camera block give the same model; a file without intrinsics is one line naming it."""
    import cv2

    from estimators.io.intrinsics_file import load_intrinsics

    (tmp_path / "ost.yaml").write_text(ROS_YAML.format(model=model, n=len(dist), dist=dist))
    ros = load_intrinsics(tmp_path / "ost.yaml")
    assert ros.model == expect and (ros.width, ros.height) == (640, 480) and ros.source == "file ost.yaml"
    np.testing.assert_array_equal(ros.K, [[600.0, 0, 321.5], [0, 601.0, 239.5], [0, 0, 1]])
    np.testing.assert_array_equal(ros.dist, dist)
    fs = cv2.FileStorage(str(tmp_path / "cv.yaml"), cv2.FILE_STORAGE_WRITE)
    fs.write("camera_model", expect)
    fs.write("image_width", 640)
    fs.write("image_height", 480)
    fs.write("camera_matrix", ros.K)
    fs.write("distortion_coefficients", np.asarray(dist, dtype=float).reshape(1, -1))
    fs.release()
    (tmp_path / "dataset.yaml").write_text(f"camera:\n  model: {expect}\n  K: {ros.K.tolist()}\n  dist: {dist}\n"
                                           "  width: 640\n  height: 480\n")
    for name in ("cv.yaml", "dataset.yaml"):
        other = load_intrinsics(tmp_path / name)
        assert other.model == expect and (other.width, other.height) == (640, 480)
        np.testing.assert_allclose(other.K, ros.K)
        np.testing.assert_allclose(other.dist, dist)
    (tmp_path / "none.yaml").write_text("board: {squares: [9, 7]}\n")
    with pytest.raises(DatasetError, match=r"none\.yaml: holds no intrinsics"):
        load_intrinsics(tmp_path / "none.yaml")
