"""Every export format parsed back to the transform it was written from, the ROS tf order against a
hand-computed case, and bad calibration files through the CLI."""
from __future__ import annotations

import json
import shlex
import xml.etree.ElementTree as ET

import cv2
import numpy as np
import pytest

from estimators.cli import main
from estimators.errors import LidarcamError
from estimators.io.export import FORMATS, export_calibration, write_export
from geometry.rotations import R_from_quat_xyzw, R_from_rpy, T_from_Rt, T_inverse, random_rotation


def parse_ros_tf(text: str, variant: str, parent: str, child: str) -> np.ndarray:
    """``T_parent_child`` from one of the three static_transform_publisher lines."""
    lines = [shlex.split(ln) for ln in text.splitlines() if ln and not ln.startswith("#")]
    if variant == "ros2":
        args = next(a for a in lines if a[0] == "ros2")[4:]
        kv = dict(zip(args[::2], args[1::2]))
        assert kv["--frame-id"] == parent and kv["--child-frame-id"] == child
        t = [float(kv[f"--{k}"]) for k in "xyz"]
        return T_from_Rt(R_from_quat_xyzw([float(kv[f"--q{k}"]) for k in "xyzw"]), t)
    args = [a for a in lines if a[0] == "rosrun"][0 if variant == "ros1-quat" else 1][3:]
    assert args[-2:] == [parent, child]
    v = [float(x) for x in args[:-2]]
    if variant == "ros1-quat":
        assert len(v) == 7
        return T_from_Rt(R_from_quat_xyzw(v[3:]), v[:3])
    yaw, pitch, roll = v[3:]
    return T_from_Rt(R_from_rpy([roll, pitch, yaw]), v[:3])


def parse_urdf(text: str) -> tuple[np.ndarray, str, str]:
    joint = ET.fromstring(text.split("?>", 1)[1]).find("joint")
    o = joint.find("origin")
    T = T_from_Rt(R_from_rpy([float(x) for x in o.get("rpy").split()]), [float(x) for x in o.get("xyz").split()])
    return T, joint.find("parent").get("link"), joint.find("child").get("link")


def parse_kitti(text: str) -> dict:
    """As KITTI's development kit and pykitti read calibration files: ``key: floats``, other lines skipped."""
    out = {}
    for line in text.splitlines():
        key, value = line.split(":", 1)
        try:
            out[key] = np.array([float(x) for x in value.split()])
        except ValueError:
            pass
    return out


def _T(seed=3):
    rng = np.random.default_rng(seed)
    return T_from_Rt(random_rotation(rng), rng.normal(0, 0.3, 3))


def test_ros_tf_order_matches_a_hand_computed_case():
    # T_camera_lidar: a 90 deg turn about z and t = (1, 2, 3). Its inverse: Rz(-90 deg) and -R^T t = (-2, 1, -3).
    T = T_from_Rt(R_from_rpy([0.0, 0.0, np.pi / 2]), [1.0, 2.0, 3.0])
    text = export_calibration(T, "ros-tf", camera_frame="cam", lidar_frame="velo")
    assert "static_transform_publisher 1 2 3 0 0 0.707106781 0.707106781 cam velo" in text
    assert "static_transform_publisher 1 2 3 1.57079633 0 0 cam velo" in text  # yaw pitch roll
    assert "--x 1 --y 2 --z 3 --qx 0 --qy 0 --qz 0.707106781 --qw 0.707106781 --frame-id cam " \
           "--child-frame-id velo" in text
    text = export_calibration(T, "ros-tf", camera_frame="cam", lidar_frame="velo", parent="lidar")
    assert "static_transform_publisher -2 1 -3 0 0 -0.707106781 0.707106781 velo cam" in text
    assert "(T_lidar_camera): p_velo = R p_cam + t" in text


@pytest.mark.parametrize("parent", ["camera", "lidar"])
def test_every_format_parses_back_to_the_transform(parent):
    T = _T()
    frames = {"camera_frame": "camera_optical", "lidar_frame": "os_sensor", "parent": parent}
    T_tree = T if parent == "camera" else T_inverse(T)
    names = ("camera_optical", "os_sensor")[:: 1 if parent == "camera" else -1]
    tf = export_calibration(T, "ros-tf", **frames)
    for variant in ("ros1-quat", "ros1-ypr", "ros2"):
        np.testing.assert_allclose(parse_ros_tf(tf, variant, *names), T_tree, atol=5e-9)
    T_urdf, par, child = parse_urdf(export_calibration(T, "urdf", **frames))
    assert (par, child) == names
    np.testing.assert_allclose(T_urdf, T_tree, atol=5e-9)
    # KITTI, YAML and JSON always hold T_camera_lidar (velo to cam), whatever the tree's parent.
    k = parse_kitti(export_calibration(T, "kitti", **frames))
    np.testing.assert_allclose(k["R"].reshape(3, 3), T[:3, :3], atol=5e-9)
    np.testing.assert_allclose(k["T"], T[:3, 3], atol=5e-9)
    np.testing.assert_allclose(k["Tr_velo_to_cam"].reshape(3, 4), T[:3], atol=5e-9)
    fs = cv2.FileStorage(export_calibration(T, "opencv-yaml", **frames),
                         cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_MEMORY)
    np.testing.assert_allclose(fs.getNode("T_camera_lidar").mat(), T, atol=1e-15)
    np.testing.assert_allclose(fs.getNode("T_lidar_camera").mat() @ T, np.eye(4), atol=1e-12)
    assert fs.getNode("lidar_frame").string() == "os_sensor"
    assert "p_camera_optical = R p_os_sensor + t" in fs.getNode("direction").string()
    j = json.loads(export_calibration(T, "json", **frames))
    np.testing.assert_allclose(j["T_camera_lidar"], T)
    assert j["frame_names"] == {"camera": "camera_optical", "lidar": "os_sensor"}


def test_the_usual_mounting_exports_to_urdf_exactly_and_without_a_warning(recwarn):
    """A camera looking along the LiDAR's x axis is at pitch -90 degrees, where roll and yaw turn about one axis
    (gimbal lock): the rpy written still gives the rotation back, and scipy's warning of it is not passed on."""
    R = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
    T = T_from_Rt(R, [0.1, -0.2, 0.05])
    T_urdf, _, _ = parse_urdf(export_calibration(T, "urdf", camera_frame="cam", lidar_frame="velo"))
    np.testing.assert_allclose(T_urdf, T, atol=1e-8)  # the file's 9 significant digits
    assert not [w for w in recwarn if "Gimbal" in str(w.message)]


def test_yaml_and_json_carry_covariance_and_intrinsics(tmp_path):
    cov = np.diag([1e-6, 2e-6, 3e-6, 1e-4, 2e-4, 3e-4])
    cal = {"version": "x", "dataset": "rig", "T_camera_lidar": _T(4).tolist(), "covariance": cov.tolist(),
           "covariance_convention": "xi = [rot; trans]",
           "intrinsics": {"model": "pinhole", "width": 640, "height": 480,
                          "K": [[500.0, 0, 320], [0, 500, 240], [0, 0, 1]], "dist": [0.1, -0.05, 0, 0, 0]}}
    (tmp_path / "calibration.json").write_text(json.dumps(cal))
    path = write_export(tmp_path / "calibration.json", "opencv-yaml", tmp_path / "cal.yaml")
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    np.testing.assert_allclose(fs.getNode("covariance").mat(), cov)
    np.testing.assert_allclose(fs.getNode("camera_matrix").mat(), cal["intrinsics"]["K"])
    assert fs.getNode("distortion_coefficients").mat().shape == (1, 5)
    assert fs.getNode("image_width").real() == 640
    j = json.loads(export_calibration(tmp_path, "json"))  # a folder holding calibration.json works too
    assert j["covariance"] == cal["covariance"] and j["dataset"] == "rig"


def test_a_moving_boards_clock_offset_goes_where_a_format_has_room_for_it(tmp_path):
    """OpenCV YAML carries ``time_offset_s`` and its deviation, JSON the whole file, ROS tf a comment (a transform has
    no place for it) that leaves the commands as they were; a non-finite offset is a malformed file."""
    cal = {"T_camera_lidar": _T(5).tolist(), "time_offset_s": -0.0312, "time_offset_std_s": 0.0002}
    (tmp_path / "calibration.json").write_text(json.dumps(cal))
    fs = cv2.FileStorage(str(write_export(tmp_path, "opencv-yaml", tmp_path / "cal.yaml")), cv2.FILE_STORAGE_READ)
    assert fs.getNode("time_offset_s").real() == -0.0312 and fs.getNode("time_offset_std_s").real() == 0.0002
    assert json.loads(export_calibration(tmp_path, "json"))["time_offset_s"] == -0.0312
    tf = export_calibration(tmp_path, "ros-tf")
    assert "t_lidar_stamp: -0.0312 s +- 0.0002 s" in tf
    (tmp_path / "plain").mkdir()
    (tmp_path / "plain" / "calibration.json").write_text(json.dumps({"T_camera_lidar": cal["T_camera_lidar"]}))
    assert [ln for ln in tf.splitlines() if "t_lidar_stamp" not in ln] == \
        export_calibration(tmp_path / "plain", "ros-tf").splitlines()
    (tmp_path / "calibration.json").write_text(json.dumps(cal | {"time_offset_s": float("nan")}))
    with pytest.raises(LidarcamError, match="time_offset_s must be a finite number"):
        export_calibration(tmp_path, "json")


def test_an_untrusted_calibration_is_exported_only_when_asked_and_every_export_carries_its_verdict(tmp_path, capsys):
    """Copied into a robot's files, an UNTRUSTED transform would read as an answer: ``export`` refuses it (exit 2,
    nothing written) unless ``--allow-untrusted``; a CHECK one is written with a note on stderr; each file's comment
    carries the verdict (one line, no ``--`` inside an XML comment). And --out may be written again."""
    reason = "T_cam0_lidar0: 5 of 5 frames' boards disagree (--no-edges: the planes alone)"
    out = tmp_path / "x.urdf"
    for level, code in (("UNTRUSTED", 2), ("CHECK", 0), ("OK", 0)):
        path = tmp_path / f"{level}.json"
        path.write_text(json.dumps({"T_camera_lidar": _T().tolist(), "verdict": {"level": level, "reasons": [reason]
                                                                                 if level != "OK" else []}}))
        assert main(["export", str(path), "--format", "urdf", "--out", str(out)]) == code
        err = capsys.readouterr().err
        if level == "UNTRUSTED":
            assert "verdict is UNTRUSTED" in err and "--allow-untrusted" in err and not out.exists()
            assert main(["export", str(path), "--format", "urdf", "--out", str(out), "--allow-untrusted"]) == 0
            err = capsys.readouterr().err
        assert ("note: exporting" in err) == (level != "OK")
        text = out.read_text()  # written again over the last one
        comment = text.splitlines()[1]
        assert f"verdict {level}" in comment and "--" not in comment[4:-3]
        np.testing.assert_allclose(parse_urdf(text)[0], _T(), atol=1e-8)


def test_export_cli_writes_atomically_and_refuses_bad_input(tmp_path, capsys):
    (tmp_path / "calibration.json").write_text(json.dumps({"T_camera_lidar": _T().tolist()}))
    out = tmp_path / "velo_to_cam.txt"
    assert main(["export", str(tmp_path / "calibration.json"), "--format", "kitti", "--out", str(out)]) == 0
    np.testing.assert_allclose(parse_kitti(out.read_text())["T"], _T()[:3, 3], atol=5e-9)
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []

    def refused(argv, *needles):
        assert main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and all(n in err for n in needles), err

    bad = tmp_path / "bad.json"
    target = tmp_path / "never.urdf"
    refused(["export", str(tmp_path / "missing.json"), "--format", "urdf", "--out", str(target)],
            "missing.json", "calibration file not found")
    bad.write_text("{not json")
    refused(["export", str(bad), "--format", "urdf", "--out", str(target)], "bad.json", "not valid JSON")
    T = _T()
    T[:3, :3] *= 1.1
    bad.write_text(json.dumps({"T_camera_lidar": T.tolist()}))
    refused(["export", str(bad), "--format", "urdf", "--out", str(target)], "not a rigid transform")
    refused(["export", str(tmp_path / "calibration.json"), "--format", "urdf", "--camera-frame", "lidar"],
            "distinct")
    assert not target.exists()
    for fmt in FORMATS:  # every format also from Python, for a result-like object
        with pytest.raises(LidarcamError):
            export_calibration(T, fmt)
