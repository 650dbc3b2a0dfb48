"""``T_camera_lidar`` in the forms robotics stacks load, each with the transform's direction written beside it.

Formats (``FORMATS``):

- ``ros-tf``: ``static_transform_publisher`` command lines for ROS 1 (quaternion and yaw-pitch-roll forms)
  and ROS 2 (named arguments). tf's order: ``x y z qx qy qz qw parent child``, the pose of ``child`` in
  ``parent``;
- ``urdf``: a fixed joint (with its two links) whose ``origin`` is the child's pose in the parent;
- ``kitti``: ``calib_velo_to_cam.txt`` lines ``R:`` (row-major) and ``T:`` with ``x_cam = R x_velo + T``, and
  ``Tr_velo_to_cam:`` (the 3x4 ``[R | T]``, row-major) as the object benchmark writes it;
- ``opencv-yaml``: an OpenCV FileStorage YAML with both directions, the covariance and the intrinsics;
- ``json``: lidarcam's ``calibration.json`` with the frame names and the inverse transform added.

``parent`` picks the tree direction for tf and URDF: ``camera`` (default; the numbers are
``T_camera_lidar``'s, the LiDAR a child of the camera) or ``lidar`` (the inverse, the camera a child of the LiDAR).
KITTI, OpenCV YAML and JSON always hold ``T_camera_lidar`` (YAML and JSON also its inverse).
"""
from __future__ import annotations

import datetime as _dt
import json
import os
from pathlib import Path

import cv2
import numpy as np

from geometry.rotations import T_inverse, quat_xyzw_from_R, rpy_from_R

from ..errors import LidarcamError
from .input_files import load_json
from .output import write_atomic

FORMATS = ("ros-tf", "urdf", "kitti", "opencv-yaml", "json")


def _num(x: float) -> str:
    return f"{float(x):.9g}"


def _nums(a) -> str:
    return " ".join(_num(x) for x in np.ravel(a))


def load_calibration(path: str | os.PathLike) -> dict:
    """Read a ``calibration.json`` and check that it holds a rigid 4x4 ``T_camera_lidar``.

    Parameters
    ----------
    path : str or os.PathLike
        The file, or the folder holding it.

    Returns
    -------
    dict
        The file's content.

    Raises
    ------
    LidarcamError
        A missing or unreadable file, or a ``T_camera_lidar`` that is not a rigid transform.
    """
    path = Path(path)
    if path.is_dir():
        path = path / "calibration.json"
    data = load_json(path, "calibration file", "give the calibration.json written by lidarcam calibrate",
                     LidarcamError)
    if isinstance(data, dict) and data.get("rig") is True:
        try:
            for s in data["sensors"]:
                _check_rigid(np.asarray(s[f"T_{data['reference']}_{s['name']}"], dtype=float))
        except (ValueError, TypeError, KeyError, AttributeError) as exc:
            raise LidarcamError(f"malformed rig calibration ({exc})", path=path,
                                hint="give the calibration.json written by lidarcam calibrate") from None
        return data
    if not isinstance(data, dict) or "T_camera_lidar" not in data:
        raise LidarcamError("no T_camera_lidar in the file", path=path,
                            hint="give the calibration.json written by lidarcam calibrate")
    try:
        _check_rigid(np.asarray(data["T_camera_lidar"], dtype=float))
    except (ValueError, TypeError) as exc:
        raise LidarcamError(f"T_camera_lidar is not a rigid transform ({exc})", path=path,
                            hint="re-run lidarcam calibrate") from exc
    try:
        if data.get("covariance") is not None:
            C = np.asarray(data["covariance"], dtype=float)
            if C.shape != (6, 6) or not np.all(np.isfinite(C)):
                raise ValueError(f"covariance must be a finite 6x6 matrix, got shape {C.shape}")
        for key in ("time_offset_s", "time_offset_std_s"):
            if data.get(key) is not None and not np.isfinite(float(data[key])):
                raise ValueError(f"{key} must be a finite number of seconds")
        intr = data.get("intrinsics")
        if intr:
            from geometry.camera import CameraModel

            CameraModel(K=np.asarray(intr["K"], dtype=float), dist=np.asarray(intr["dist"], dtype=float),
                        width=int(intr["width"]), height=int(intr["height"]), model=str(intr["model"]))
    except (ValueError, TypeError, KeyError, OverflowError, AttributeError) as exc:
        raise LidarcamError(f"malformed calibration file ({exc})", path=path,
                            hint="give the calibration.json written by lidarcam calibrate") from None
    return data


def _check_rigid(T: np.ndarray) -> np.ndarray:
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"expected a finite 4x4 matrix, got shape {T.shape}")
    R = T[:3, :3]
    if np.abs(R @ R.T - np.eye(3)).max() > 1e-6 or np.linalg.det(R) < 0 or \
            np.abs(T[3] - [0, 0, 0, 1]).max() > 1e-12:
        raise ValueError("R is not a rotation or the last row is not 0 0 0 1")
    return T


def _as_calibration(calibration) -> dict:
    if isinstance(calibration, dict):
        return calibration
    if hasattr(calibration, "to_dict"):
        return calibration.to_dict()
    if isinstance(calibration, (str, os.PathLike)):
        return load_calibration(calibration)
    return {"T_camera_lidar": np.asarray(calibration, dtype=float).tolist()}


def verdict_of(cal: dict) -> tuple[str | None, list[str]]:
    """A calibration.json's verdict: its level (None for a file without one) and its reasons."""
    verdict = cal.get("verdict")
    if not isinstance(verdict, dict) or not verdict.get("level"):
        return None, []
    return str(verdict["level"]), [str(r) for r in verdict.get("reasons") or []]


def verdict_words(cal: dict, limit: int = 200) -> str:
    """The calibration's verdict as an export's comment says it (``; verdict OK``, or the level and its first
    reason, cut at ``limit`` characters), so that a transform copied into a robot's files carries it; "" for a file
    without one. Kept to one line, and free of ``--`` (an XML comment may not hold it)."""
    level, reasons = verdict_of(cal)
    if not level:
        return ""
    first = " ".join(reasons[0].split()) if reasons else ""
    if len(first) > limit:
        first = first[:limit].rstrip() + "..."
    text = f"; verdict {level}" + (f": {first}" if first else "")
    while "--" in text:
        text = text.replace("--", "- -")
    return text


def _tree(T_camera_lidar: np.ndarray, camera_frame: str, lidar_frame: str, parent: str):
    if parent == "camera":
        return (T_camera_lidar, camera_frame, lidar_frame, "T_camera_lidar",
                f"p_{camera_frame} = R p_{lidar_frame} + t")
    if parent == "lidar":
        return (T_inverse(T_camera_lidar), lidar_frame, camera_frame, "T_lidar_camera",
                f"p_{lidar_frame} = R p_{camera_frame} + t")
    raise ValueError(f"Expected parent 'camera' or 'lidar', got {parent!r}")


def export_calibration(calibration, fmt: str, camera_frame: str = "camera", lidar_frame: str = "lidar",
                       parent: str = "camera") -> str:
    """The calibration as text for ROS tf, URDF, KITTI, OpenCV YAML or JSON, with its direction written beside it.

    Parameters
    ----------
    calibration : CalibrationResult, str, os.PathLike, dict or numpy.ndarray
        A result, a ``calibration.json`` path or its content, or a 4x4 ``T_camera_lidar``.
    fmt : str
        One of ``ros-tf``, ``urdf``, ``kitti``, ``opencv-yaml``, ``json``.
    camera_frame, lidar_frame : str
        The two frames' names (distinct, without spaces).
    parent : str
        ``camera``: the LiDAR is the child (``T_camera_lidar``'s own numbers); ``lidar``: the inverse.

    Returns
    -------
    str

    Raises
    ------
    LidarcamError
        Bad frame names, or a transform that is not rigid.

    Examples
    --------
    >>> print(lc.export_calibration("/tmp/calib/calibration.json", "ros-tf", lidar_frame="velodyne"))  # doctest: +SKIP
    """
    if fmt not in FORMATS:
        raise ValueError(f"Expected a format in {FORMATS}, got {fmt!r}")
    if camera_frame == lidar_frame or any(not f or any(c.isspace() for c in f) for f in (camera_frame, lidar_frame)):
        raise LidarcamError(f"frame names must be distinct and without spaces, got camera {camera_frame!r} and "
                            f"lidar {lidar_frame!r}", hint="set --camera-frame and --lidar-frame")
    cal = _as_calibration(calibration)
    if cal.get("rig") is True and "T_camera_lidar" not in cal:  # a rig of one camera and one LiDAR: the pair's
        return _rig_export(cal, fmt)
    try:
        T = _check_rigid(np.asarray(cal["T_camera_lidar"], dtype=float))
    except (ValueError, TypeError, KeyError) as exc:
        raise LidarcamError(f"T_camera_lidar is not a rigid transform ({exc})",
                            hint="give a 4x4 [R t; 0 0 0 1] with R a rotation") from exc
    origin = (f"lidarcam {cal.get('version', '?')} calibration of {cal.get('dataset', 'an unnamed dataset')}"
              + verdict_words(cal))
    writers = {"ros-tf": _ros_tf, "urdf": _urdf, "kitti": _kitti, "opencv-yaml": _opencv_yaml, "json": _json}
    return writers[fmt](T, cal, camera_frame, lidar_frame, parent, origin)


def write_export(calibration, fmt: str, path: str | os.PathLike, **frames) -> Path:
    """Write :func:`export_calibration`'s text to a file, atomically.

    Parameters
    ----------
    calibration : CalibrationResult, str, os.PathLike, dict or numpy.ndarray
        As for :func:`export_calibration`.
    fmt : str
        As for :func:`export_calibration`.
    path : str or os.PathLike
        The file to write.
    **frames
        ``camera_frame``, ``lidar_frame`` and ``parent``, as for :func:`export_calibration`.

    Returns
    -------
    Path
    """
    text = export_calibration(calibration, fmt, **frames)
    return write_atomic(path, lambda fh: fh.write(text))


def _rig_export(cal: dict, fmt: str) -> str:
    """A rig's tree: every sensor a child of the reference sensor (frames named as the sensors), for ROS tf
    (one static transform per sensor), URDF (a fixed joint per sensor), OpenCV YAML (per camera its intrinsics
    and its transform to every LiDAR) or JSON; KITTI holds one camera-LiDAR pair and is refused."""
    ref = cal["reference"]
    origin = f"lidarcam {cal.get('version', '?')} rig calibration (reference {ref})" + verdict_words(cal)
    poses = {s["name"]: _check_rigid(np.asarray(s[f"T_{ref}_{s['name']}"], dtype=float))
             for s in cal["sensors"] if s["name"] != ref}
    if fmt == "kitti":
        raise LidarcamError("KITTI's calib file holds one camera-LiDAR pair, not a rig",
                            hint="export ros-tf, urdf, opencv-yaml or json, or take a pair from 'transforms'")
    if fmt == "ros-tf":
        lines = [f"# {origin}", f"# Each sensor's pose in '{ref}': p_{ref} = R p_sensor + t; arguments x y z (m), "
                 "qx qy qz qw, parent, child.", "# ROS 1:"]
        lines += [f"rosrun tf2_ros static_transform_publisher {_nums(T[:3, 3])} {_nums(quat_xyzw_from_R(T[:3, :3]))} "
                  f"{ref} {n}" for n, T in poses.items()]
        lines.append("# ROS 2 (Humble and later, named arguments):")
        for n, T in poses.items():
            t, q = T[:3, 3], quat_xyzw_from_R(T[:3, :3])
            lines.append(f"ros2 run tf2_ros static_transform_publisher --x {_num(t[0])} --y {_num(t[1])} "
                         f"--z {_num(t[2])} --qx {_num(q[0])} --qy {_num(q[1])} --qz {_num(q[2])} --qw {_num(q[3])} "
                         f"--frame-id {ref} --child-frame-id {n}")
        return "\n".join(lines + _rig_offsets_comment(cal)) + "\n"
    if fmt == "urdf":
        lines = ['<?xml version="1.0"?>', f"<!-- {origin}. Each joint origin is the sensor's pose in '{ref}'; rpy "
                 "are fixed-axis roll, pitch, yaw in radians: R = Rz(yaw) Ry(pitch) Rx(roll). -->",
                 '<robot name="lidarcam_rig">', f'  <link name="{ref}"/>']
        for n, T in poses.items():
            lines += [f'  <link name="{n}"/>', f'  <joint name="{ref}_to_{n}" type="fixed">',
                      f'    <parent link="{ref}"/>', f'    <child link="{n}"/>',
                      f'    <origin xyz="{_nums(T[:3, 3])}" rpy="{_nums(rpy_from_R(T[:3, :3]))}"/>', "  </joint>"]
        return "\n".join(lines + ["</robot>", ""])
    if fmt == "opencv-yaml":
        fs = cv2.FileStorage("export.yaml", cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY)
        fs.write("source", origin)
        fs.write("direction", "T_a_b maps b's points into a's frame: p_a = R p_b + t (metres)")
        for name, intr in cal.get("cameras", {}).items():
            fs.startWriteStruct(name, cv2.FileNode_MAP)
            fs.write("camera_model", str(intr["model"]))
            fs.write("image_width", int(intr["width"]))
            fs.write("image_height", int(intr["height"]))
            fs.write("camera_matrix", np.asarray(intr["K"], dtype=float))
            fs.write("distortion_coefficients", np.asarray(intr["dist"], dtype=float).reshape(1, -1))
            for key, tr in cal.get("transforms", {}).items():
                if key.startswith(f"T_{name}_"):
                    fs.write(key, np.asarray(tr["T"], dtype=float))
            fs.endWriteStruct()
        offsets = _rig_offsets(cal)
        if offsets:
            for key, k in (("time_offsets_s", 0), ("time_offsets_std_s", 1)):
                fs.startWriteStruct(key, cv2.FileNode_MAP)
                for n, v in offsets.items():
                    if v[k] is not None:
                        fs.write(n, v[k])
                fs.endWriteStruct()
            fs.write("time_offsets_convention", str(cal.get("time_offsets_convention", "")))
        return fs.releaseAndGetString()
    out = dict(cal)
    out["direction"] = "T_a_b maps b's points into a's frame: p_a = R p_b + t (metres)"
    return json.dumps(out, indent=1) + "\n"


def _rig_offsets(cal: dict) -> dict:
    """A rig's LiDARs' determined clock offsets: ``name -> (offset s, its sd s or None)``; a malformed entry is a
    malformed file."""
    values, sds = cal.get("time_offsets_s") or {}, cal.get("time_offsets_std_s") or {}
    if not isinstance(values, dict) or not isinstance(sds, dict):
        raise LidarcamError("malformed time_offsets_s", hint="write the calibration again with lidarcam calibrate")
    out = {}
    for n, v in values.items():
        if v is None:
            continue
        sd = sds.get(n)
        if not isinstance(v, (int, float)) or not np.isfinite(v) or \
                (sd is not None and (not isinstance(sd, (int, float)) or not np.isfinite(sd))):
            raise LidarcamError(f"malformed time offset of {n}",
                                hint="write the calibration again with lidarcam calibrate")
        out[str(n)] = (float(v), None if sd is None else float(sd))
    return out


def _rig_offsets_comment(cal: dict) -> list[str]:
    """ros-tf's comment lines for a rig's LiDARs' clock offsets (a transform has no place for them)."""
    ref = cal.get("time_offsets_reference", "cam0")
    return [f"# The clocks' offset t_{ref}_stamp - t_{n}_stamp: {_num(v)} s"
            + ("" if sd is None else f" +- {_num(sd)} s") for n, (v, sd) in _rig_offsets(cal).items()]


def _ros_tf(T, cal, camera_frame, lidar_frame, parent, origin) -> str:
    Tp, par, child, name, maps = _tree(T, camera_frame, lidar_frame, parent)
    t, q, rpy = Tp[:3, 3], quat_xyzw_from_R(Tp[:3, :3]), rpy_from_R(Tp[:3, :3])
    return "\n".join([
        f"# {origin}",
        f"# The pose of child frame '{child}' in parent frame '{par}' ({name}): {maps}.",
        "# Argument order: x y z (m), then qx qy qz qw (or yaw pitch roll, rad, R = Rz(yaw) Ry(pitch) Rx(roll)),",
        "# then the parent frame, then the child frame.",
        "# ROS 1:",
        f"rosrun tf2_ros static_transform_publisher {_nums(t)} {_nums(q)} {par} {child}",
        "# ROS 1, yaw pitch roll form:",
        f"rosrun tf2_ros static_transform_publisher {_nums(t)} {_nums(rpy[::-1])} {par} {child}",
        "# ROS 2 (Humble and later, named arguments):",
        f"ros2 run tf2_ros static_transform_publisher --x {_num(t[0])} --y {_num(t[1])} --z {_num(t[2])} "
        f"--qx {_num(q[0])} --qy {_num(q[1])} --qz {_num(q[2])} --qw {_num(q[3])} "
        f"--frame-id {par} --child-frame-id {child}",
        *_offset_comment(cal),
        ""])


def _offset_comment(cal: dict) -> list[str]:
    """A comment line with the clocks' offset of a moving board's calibration (a transform has no place for it)."""
    if cal.get("time_offset_s") is None:
        return []
    sd = cal.get("time_offset_std_s")
    return [f"# The clocks' offset t_camera_stamp - t_lidar_stamp: {_num(float(cal['time_offset_s']))} s"
            + (f" +- {_num(float(sd))} s" if sd is not None else " (held)")
            + ": add it to a LiDAR stamp to find the camera's stamp of the same instant (no tf carries it)."]


def _urdf(T, cal, camera_frame, lidar_frame, parent, origin) -> str:
    Tp, par, child, name, maps = _tree(T, camera_frame, lidar_frame, parent)
    return "\n".join([
        '<?xml version="1.0"?>',
        f"<!-- {origin}. -->",
        f"<!-- The joint origin is the pose of child link '{child}' in parent link '{par}' ({name}): {maps};",
        "     rpy are fixed-axis roll, pitch, yaw in radians: R = Rz(yaw) Ry(pitch) Rx(roll). -->",
        '<robot name="lidarcam_calibration">',
        f'  <link name="{par}"/>',
        f'  <link name="{child}"/>',
        f'  <joint name="{par}_to_{child}" type="fixed">',
        f'    <parent link="{par}"/>',
        f'    <child link="{child}"/>',
        f'    <origin xyz="{_nums(Tp[:3, 3])}" rpy="{_nums(rpy_from_R(Tp[:3, :3]))}"/>',
        "  </joint>",
        "</robot>",
        ""])


def _kitti(T, cal, camera_frame, lidar_frame, parent, origin) -> str:
    when = _dt.datetime.now().strftime("%d-%b-%Y %H:%M:%S")
    return "\n".join([
        f"calib_time: {when}",
        f"R: {_nums(T[:3, :3])}",
        f"T: {_nums(T[:3, 3])}",
        f"Tr_velo_to_cam: {_nums(T[:3, :])}",
        f"direction: x_{camera_frame} = R x_{lidar_frame} + T, metres (velo to cam: lidarcam's T_camera_lidar; "
        f"Tr_velo_to_cam is [R | T] row-major); {origin}",
        ""])


def _opencv_yaml(T, cal, camera_frame, lidar_frame, parent, origin) -> str:
    fs = cv2.FileStorage("export.yaml", cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY)
    fs.write("source", origin)
    fs.write("camera_frame", camera_frame)
    fs.write("lidar_frame", lidar_frame)
    fs.write("direction", f"T_camera_lidar maps {lidar_frame} points into {camera_frame}: "
                          f"p_{camera_frame} = R p_{lidar_frame} + t (metres); T_lidar_camera is its inverse")
    fs.write("T_camera_lidar", T)
    fs.write("T_lidar_camera", T_inverse(T))
    if cal.get("covariance") is not None:
        fs.write("covariance", np.asarray(cal["covariance"], dtype=float))
        fs.write("covariance_convention", str(cal.get("covariance_convention", "")))
    if cal.get("time_offset_s") is not None:
        fs.write("time_offset_s", float(cal["time_offset_s"]))
        if cal.get("time_offset_std_s") is not None:
            fs.write("time_offset_std_s", float(cal["time_offset_std_s"]))
        fs.write("time_offset_convention", "t_camera_stamp - t_lidar_stamp for one instant (seconds)")
    intr = cal.get("intrinsics")
    if intr:
        fs.write("camera_model", str(intr["model"]))
        fs.write("image_width", int(intr["width"]))
        fs.write("image_height", int(intr["height"]))
        fs.write("camera_matrix", np.asarray(intr["K"], dtype=float))
        fs.write("distortion_coefficients", np.asarray(intr["dist"], dtype=float).reshape(1, -1))
    return fs.releaseAndGetString()


def _json(T, cal, camera_frame, lidar_frame, parent, origin) -> str:
    out = dict(cal)
    out["frame_names"] = {"camera": camera_frame, "lidar": lidar_frame}
    out["direction"] = (f"T_camera_lidar maps {lidar_frame} points into {camera_frame}: "
                        f"p_{camera_frame} = R p_{lidar_frame} + t (metres); T_lidar_camera is its inverse")
    out["T_lidar_camera"] = T_inverse(T).tolist()
    return json.dumps(out, indent=1) + "\n"
