"""A camera's intrinsics from a file a user already has, for a bag recorded without ``CameraInfo``.

Read: ROS ``camera_calibration``'s YAML (``image_width``, ``image_height``, ``camera_matrix``,
``distortion_model``, ``distortion_coefficients``: converted as a ``CameraInfo`` is, ``ros_messages``), OpenCV
``FileStorage`` YAML (the same keys as ``!!opencv-matrix``; lidarcam's own ``export --format opencv-yaml`` among
them; read by the safe YAML loader, not OpenCV's parser, which a damaged file can crash), a ``dataset.yaml`` (its
``camera:`` block) or a ``calibration.json`` (its ``intrinsics``).
"""
from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from geometry.camera import CameraModel

from ..errors import DatasetError
from .input_files import load_json, load_yaml

HINT = ("give ROS camera_calibration's YAML, an OpenCV FileStorage YAML (camera_matrix, distortion_coefficients, "
        "image_width, image_height), a dataset.yaml with a camera: block or a calibration.json")


def load_intrinsics(path: str | os.PathLike) -> CameraModel:
    """The camera model a file holds (see the module); a :class:`DatasetError` naming the file otherwise."""
    from .dataset import parse_camera

    path = Path(path)
    data = load_json(path, "intrinsics file", HINT) if path.suffix.lower() == ".json" else \
        load_yaml(path, "intrinsics file", HINT, opencv=True)
    if not isinstance(data, dict):
        raise DatasetError("holds no intrinsics (not a mapping)", path=path, hint=HINT)
    if "camera_matrix" in data:
        camera = _matrices(data, path)
    elif isinstance(data.get("camera"), dict):
        camera = parse_camera(data["camera"], path)
    elif isinstance(data.get("intrinsics"), dict):
        camera = parse_camera(data["intrinsics"], path)
    else:
        raise DatasetError("holds no intrinsics (no camera_matrix, camera: or intrinsics)", path=path, hint=HINT)
    return dataclasses.replace(camera, source=f"file {path.name}")


def _matrices(data: dict, path: Path) -> CameraModel:
    """ROS ``camera_calibration``'s YAML or OpenCV's (matrices as ``{rows, cols, data}``), converted as a
    ``CameraInfo`` is (``distortion_model``, or OpenCV's ``camera_model`` as lidarcam's export writes it)."""
    from .ros_messages import camera_from_info

    def values(key):
        node = data.get(key)
        v = node.get("data") if isinstance(node, dict) else node
        try:
            return np.asarray(v if v is not None else [], dtype=float).ravel()
        except (TypeError, ValueError, OverflowError):
            raise DatasetError(f"{key} is not a list of numbers", path=path, hint=HINT) from None

    K = values("camera_matrix")
    size = data.get("image_width"), data.get("image_height")
    if K.size != 9 or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v) and
                              0 < v < 1e6 for v in size):
        raise DatasetError("needs a 3x3 camera_matrix, image_width and image_height", path=path, hint=HINT)
    model = str(data.get("distortion_model", data.get("camera_model", "plumb_bob")))
    model = "plumb_bob" if model == "pinhole" else model
    msg = SimpleNamespace(k=K, d=values("distortion_coefficients"), distortion_model=model,
                          width=int(size[0]), height=int(size[1]))
    try:
        return camera_from_info(msg, str(path))
    except (TypeError, ValueError) as exc:
        raise DatasetError(f"invalid intrinsics ({exc})", path=path, hint=HINT) from None
