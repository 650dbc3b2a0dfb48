"""The dataset folder: ``dataset.yaml`` plus one image and one scan per frame, paired by file stem.

See docs/reference/dataset.md for the contract other tools write to.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from geometry.board import CHARUCO, CHECKERBOARD, PATTERNS, BoardModel
from geometry.camera import FISHEYE, PINHOLE, CameraModel

from ..errors import DatasetError
from .input_files import load_json, load_yaml
from .motion_track import STILL_POSES_ONLY, has_motion
from .pointcloud_io import SCAN_2D_SUFFIXES, SCAN_SUFFIXES

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
# The ArUco dictionary of a ChArUco board whose entry names none (the one OpenCV's examples print).
DEFAULT_DICTIONARY = "DICT_5X5_100"
LIDAR_KINDS = ("3d", "2d")


@dataclass(frozen=True)
class FrameFiles:
    name: str
    image: Path
    scan: Path


@dataclass(frozen=True)
class Dataset:
    """A loaded dataset description (files are read later, frame by frame).

    Attributes
    ----------
    root : Path
        The dataset folder.
    lidar : str
        ``3d`` or ``2d``.
    board : BoardModel
        The board: pattern, squares, square size, and its physical size when known.
    camera : CameraModel or None
        The intrinsics, or None to calibrate them from the images.
    frames : tuple of FrameFiles
        Each frame's image and scan file.
    lidar_family : str or None
        The sensor family named in ``dataset.yaml`` (velodyne, ouster, hesai, livox, or any name).
    range_accuracy_m : float or None
        The sensor's range accuracy (m, 1 sd of a systematic range error), when given.
    """

    root: Path
    lidar: str
    board: BoardModel
    camera: CameraModel | None
    frames: tuple[FrameFiles, ...]
    # ``lidar: {type, family, range_accuracy_m}`` in dataset.yaml: the sensor family (velodyne, ouster, hesai,
    # livox, or any name) and its range accuracy (m, 1 sd of a systematic range error); None when not given.
    lidar_family: str | None = None
    range_accuracy_m: float | None = None

    @property
    def yaml_path(self) -> Path:
        return self.root / "dataset.yaml"

    def ground_truth(self) -> np.ndarray | None:
        """``T_camera_lidar`` from ``ground_truth.json`` when the simulator wrote one (evaluation only)."""
        path = self.root / "ground_truth.json"
        if not path.exists():
            return None
        try:
            T = np.asarray(load_json(path, "ground truth")["T_camera_lidar"], dtype=float)
        except (ValueError, KeyError, TypeError) as exc:
            raise DatasetError(f"unreadable ground truth ({exc})", path=path,
                               hint='expected {"T_camera_lidar": 4x4}') from exc
        if T.shape != (4, 4):
            raise DatasetError(f"T_camera_lidar has shape {T.shape}", path=path, hint="expected 4x4")
        return T


def load_dataset(path: str | os.PathLike) -> Dataset:
    """Read ``dataset.yaml`` and pair the frames of a dataset folder (files are read later, frame by frame).

    Parameters
    ----------
    path : str or os.PathLike
        The dataset folder (see the dataset reference for its format).

    Returns
    -------
    Dataset

    Raises
    ------
    DatasetError
        A missing folder or ``dataset.yaml``, a bad key (named, with what to write), or an image without its scan
        (or a scan without its image).

    Examples
    --------
    >>> ds = lc.load_dataset("/tmp/sim")            # doctest: +SKIP
    >>> ds.lidar, ds.board.squares, len(ds.frames)  # doctest: +SKIP
    """
    root, ypath, spec = read_dataset_yaml(path)
    if not isinstance(spec, dict):
        raise DatasetError("expected a mapping with keys lidar, board, camera", path=ypath,
                           hint="see docs/reference/dataset.md")
    if "sensors" in spec:
        raise DatasetError("this is a rig folder (sensors: in dataset.yaml), where one camera-LiDAR pair's folder is "
                           "expected", path=ypath, hint="lidarcam calibrate, validate and layout take a rig folder, "
                           "and in Python estimators.calibrate_rig(estimators.load_rig(folder), rng)")
    lidar, family, accuracy = _parse_lidar(spec.get("lidar", "3d"), ypath)
    board = parse_board(spec.get("board"), ypath)
    camera = parse_camera(spec["camera"], ypath) if spec.get("camera") is not None else None
    suffixes = SCAN_2D_SUFFIXES if lidar == "2d" else SCAN_SUFFIXES
    return Dataset(root=root, lidar=lidar, board=board, camera=camera, frames=_pair_frames(root, suffixes),
                   lidar_family=family, range_accuracy_m=accuracy)


def load_scene_folder(path: str | os.PathLike, need_camera: bool = True, pair: tuple[str, str] | None = None
                      ) -> tuple[Path, CameraModel | None, BoardModel | None, tuple[FrameFiles, ...]]:
    """A folder of synchronised frames for the scene's check: its root, the camera's intrinsics (required unless
    ``need_camera`` is False: the caller has them; None when absent), the board if dataset.yaml has one (a folder
    of scenes alone has none) and its image-scan pairs (3D scans); ``pair``: None or ``("cam0", "lidar0")``, the
    names a camera-LiDAR folder's sensors take in a rig."""
    root, ypath, spec = read_dataset_yaml(path)
    if not isinstance(spec, dict) or "sensors" in spec:
        raise DatasetError("expected a camera-LiDAR folder's dataset.yaml (camera:, and board: if one is in view)",
                           path=ypath, hint="see docs/reference/dataset.md; a rig folder: io.rig_dataset.scene_pair")
    if pair is not None and tuple(pair) != ("cam0", "lidar0"):
        raise DatasetError(f"a camera-LiDAR folder holds cam0 and lidar0, not {pair[0]} and {pair[1]}", path=ypath,
                           hint="name the sensors only for a rig folder")
    if spec.get("camera") is None and need_camera:
        raise DatasetError("the scene's check needs the camera's intrinsics (camera: in dataset.yaml)", path=ypath,
                           hint="add camera: K, dist, width, height (or calibrate the intrinsics first)")
    lidar, _, _ = _parse_lidar(spec.get("lidar", "3d"), ypath)
    if lidar != "3d":
        raise DatasetError("the scene's check takes a 3D LiDAR's sweeps", path=ypath,
                           hint="a 2D scanner's line holds too few contours")
    board = parse_board(spec["board"], ypath) if spec.get("board") is not None else None
    camera = None if spec.get("camera") is None else parse_camera(spec["camera"], ypath)
    return root, camera, board, _pair_frames(root, SCAN_SUFFIXES)


# The top-level keys of a camera-LiDAR folder's dataset.yaml.
PAIR_KEYS = frozenset({"lidar", "board", "camera"})


def read_dataset_yaml(path: str | os.PathLike) -> tuple[Path, Path, object]:
    """The folder, its ``dataset.yaml`` and that file's content (``yaml.safe_load``), or a one-line error for a
    missing folder or file."""
    root = Path(path)
    if not root.is_dir():
        raise DatasetError("dataset folder not found", path=root, hint="give the folder holding dataset.yaml")
    ypath = root / "dataset.yaml"
    if not ypath.exists():
        raise DatasetError("no dataset.yaml", path=root, hint="create one (see docs/reference/dataset.md)")
    spec = load_yaml(ypath, "dataset.yaml")
    if isinstance(spec, dict) and "sensors" not in spec:  # a pair's folder (a rig's checks its own keys)
        unknown = sorted(str(k) for k in set(spec) - PAIR_KEYS)
        if unknown:  # a key misplaced or misspelt would be ignored, and the calibration made without it
            nested = [k for k in unknown if k in ("family", "range_accuracy_m", "type")]
            raise DatasetError(f"unknown key(s) {unknown} (a camera-LiDAR folder's are {', '.join(sorted(PAIR_KEYS))})",
                               path=ypath, hint=f"write {nested[0]} under lidar: {{type: 3d, {nested[0]}: ...}}"
                               if nested else "fix or remove them (see docs/reference/dataset.md)")
    return root, ypath, spec


def _parse_lidar(value: object, ypath: Path) -> tuple[str, str | None, float | None]:
    """``lidar: 3d`` (or ``2d``), or a mapping ``{type: 3d, family: velodyne, range_accuracy_m: 0.03}``."""
    family = accuracy = None
    if isinstance(value, dict):
        unknown = set(value) - {"type", "family", "range_accuracy_m"}
        if unknown:
            raise DatasetError(f"unknown lidar key(s) {sorted(unknown)}", path=ypath,
                               hint="lidar takes type (3d or 2d), family and range_accuracy_m")
        family = None if value.get("family") is None else str(value["family"]).lower()
        if value.get("range_accuracy_m") is not None:
            a = value["range_accuracy_m"]
            if isinstance(a, bool) or not isinstance(a, (int, float)) or not (0 < a < 1):
                raise DatasetError(f"lidar range_accuracy_m must be a number of metres between 0 and 1, got {a!r}",
                                   path=ypath, hint="for example range_accuracy_m: 0.03 (3 cm)")
            accuracy = float(a)
        value = value.get("type", "3d")
    lidar = str(value).lower()
    if lidar not in LIDAR_KINDS:
        raise DatasetError(f"lidar must be '3d' or '2d', got {value!r}", path=ypath,
                           hint="set lidar: 3d or lidar: 2d (or lidar: {type: 3d, family: ouster})")
    return lidar, family, accuracy


def dataset_spec(lidar: str, board: BoardModel, camera: CameraModel | None) -> dict:
    """The ``dataset.yaml`` mapping for a LiDAR kind, a board and (optionally) the camera intrinsics."""
    spec = {"lidar": lidar, "board": {"squares": list(board.squares), "square_size": board.square_size}}
    if board.size is not None:
        spec["board"]["size"] = list(board.size)
    if board.pattern_offset is not None:
        spec["board"]["pattern_offset"] = list(board.pattern_offset)
    if board.is_charuco:
        spec["board"].update({"pattern": CHARUCO, "marker_size": board.marker_size, "dictionary": board.dictionary,
                              "legacy_pattern": board.legacy_pattern})
    if camera is not None:
        spec["camera"] = {"model": camera.model, "width": camera.width, "height": camera.height,
                          "K": camera.K.tolist(), "dist": camera.dist.tolist()}
    return spec


def write_dataset_yaml(folder: Path, spec: dict, comment: str) -> Path:
    """``folder/dataset.yaml`` holding ``spec`` under a one-line ``# comment`` (the caller makes it atomic)."""
    path = Path(folder) / "dataset.yaml"
    path.write_text(f"# {comment}\n" + yaml.safe_dump(spec, sort_keys=False, default_flow_style=None))
    return path


def _number(value: object, key: str, ypath: Path) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise DatasetError(f"board {key} must be a number (m), got {value!r}", path=ypath,
                           hint="see docs/reference/dataset.md")
    return float(value)


def parse_board(b: object, ypath: Path) -> BoardModel:
    if not isinstance(b, dict) or "squares" not in b or "square_size" not in b:
        raise DatasetError("board needs squares: [nx, ny] and square_size (m)", path=ypath,
                           hint="see docs/reference/dataset.md")
    pattern = b.get("pattern", CHECKERBOARD)
    if pattern not in PATTERNS:
        raise DatasetError(f"board pattern must be one of {', '.join(PATTERNS)}, got {pattern!r}", path=ypath,
                           hint="see docs/reference/dataset.md")
    extra = {}
    if pattern == CHARUCO:
        if b.get("marker_size") is None:
            raise DatasetError("a charuco board needs marker_size (m, the markers' side)", path=ypath,
                               hint="see docs/reference/dataset.md, ChArUco boards")
        legacy = b.get("legacy_pattern", False)
        if not isinstance(legacy, bool):
            raise DatasetError(f"board legacy_pattern must be true or false, got {legacy!r}", path=ypath,
                               hint="true only for boards printed by OpenCV before 4.6")
        extra = {"pattern": CHARUCO, "marker_size": _number(b["marker_size"], "marker_size", ypath),
                 "dictionary": b.get("dictionary", DEFAULT_DICTIONARY), "legacy_pattern": legacy}
    try:
        return BoardModel(squares=tuple(b["squares"]), square_size=float(b["square_size"]),
                          size=tuple(b["size"]) if b.get("size") is not None else None,
                          pattern_offset=tuple(b["pattern_offset"]) if b.get("pattern_offset") is not None
                          else None, **extra)
    except (ValueError, TypeError, OverflowError) as exc:
        raise DatasetError(f"invalid board ({exc})", path=ypath, hint="fix the board entry") from exc


def parse_camera(c: object, ypath: Path) -> CameraModel:
    if not isinstance(c, dict):
        raise DatasetError("camera must be a mapping", path=ypath, hint="see docs/reference/dataset.md")
    missing = [k for k in ("K", "width", "height") if k not in c]
    if missing:
        raise DatasetError(f"camera lacks {', '.join(missing)}", path=ypath,
                           hint="give K, width, height (and dist), or drop camera to calibrate intrinsics")
    model = str(c.get("model", PINHOLE)).lower()
    if model not in (PINHOLE, FISHEYE):
        raise DatasetError(f"camera model must be pinhole or fisheye, got {model!r}", path=ypath,
                           hint="use pinhole (radial-tangential) or fisheye (Kannala-Brandt)")
    try:
        camera = CameraModel(K=np.asarray(c["K"], dtype=float), dist=np.asarray(c.get("dist") or [], dtype=float),
                             width=int(c["width"]), height=int(c["height"]), model=model, source="dataset.yaml")
        std = c.get("param_std")
        if std is not None:
            std = np.asarray(std, dtype=float).ravel()
            if std.size != camera.params.size or not np.all(np.isfinite(std)) or np.any(std <= 0):
                raise ValueError(f"param_std must hold {camera.params.size} positive numbers (fx fy cx cy and "
                                 f"{camera.dist.size} distortion coefficients), got {std.tolist()}")
            camera = CameraModel(camera.K, camera.dist, camera.width, camera.height, model, camera.source, std)
        return camera
    except (ValueError, TypeError, OverflowError) as exc:
        raise DatasetError(f"invalid camera ({exc})", path=ypath, hint="fix the camera entry") from exc


def _pair_frames(root: Path, scan_suffixes: tuple[str, ...] = SCAN_SUFFIXES) -> tuple[FrameFiles, ...]:
    images: dict[str, Path] = {}
    scans: dict[str, Path] = {}
    for p in sorted(root.iterdir()):
        if not p.is_file():
            continue
        suffix = p.suffix.lower()
        table = images if suffix in IMAGE_SUFFIXES else scans if suffix in scan_suffixes else None
        if table is None:
            continue
        if p.stem in table:
            raise DatasetError(f"two files for frame {p.stem!r} ({table[p.stem].name}, {p.name})", path=p,
                               hint="keep one image and one scan per frame")
        table[p.stem] = p
    for stem, img in images.items():
        if stem not in scans:
            other = [p.name for p in sorted(root.glob(f"{stem}.*")) if p.suffix.lower() in
                     set(SCAN_SUFFIXES + SCAN_2D_SUFFIXES) - set(scan_suffixes)]
            raise DatasetError(f"image has no scan {stem}{{{','.join(scan_suffixes)}}}", path=img,
                               hint=f"{other[0]} is a {'2D' if scan_suffixes == SCAN_SUFFIXES else '3D'} LiDAR's "
                                    "scan: set lidar in dataset.yaml to match" if other else
                               "add the scan or remove the image")
    for stem, scan in scans.items():
        if stem not in images:
            raise DatasetError(f"scan has no image {stem}{{{','.join(IMAGE_SUFFIXES)}}}", path=scan,
                               hint="add the image or remove the scan")
    if not images:
        if has_motion(root):  # a board waved before the rig: its motion, no still frames
            raise DatasetError("a moving board's recording (motion.npz), without still frames (image + scan pairs)",
                               path=root, hint=STILL_POSES_ONLY)
        raise DatasetError("no frames (image + scan pairs with the same stem)", path=root,
                           hint="add NNNN.png and NNNN.pcd files")
    return tuple(FrameFiles(stem, images[stem], scans[stem]) for stem in sorted(images))
