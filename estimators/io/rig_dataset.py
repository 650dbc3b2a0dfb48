"""A rig folder: several cameras and LiDARs, ``dataset.yaml`` with ``sensors:``, files ``<sensor>/NNNN.<ext>``.

```yaml
board: {squares: [8, 11], square_size: 0.1, size: [1.0, 1.2]}
sensors:                      # a list; names are folder names
  - {name: cam0, type: camera, model: pinhole, width: 1024, height: 768, K: [[...]], dist: [...]}
  - {name: cam1, type: camera}            # no K: calibrated from its frames
  - {name: lidar0, type: lidar, lidar: 3d}
reference: cam0               # optional; default the first sensor
```

A frame is a file stem; a sensor without a file for a stem did not see the board then. The single camera-LiDAR
folder (``io.dataset``) is the rig of ``cam0`` and ``lidar0`` (:meth:`RigDataset.of_pair`; :func:`load_rig` reads
either); :func:`is_rig` tells the two folders apart.
"""
from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

from geometry.board import BoardModel
from geometry.camera import CameraModel

from ..errors import DatasetError
from .dataset import (IMAGE_SUFFIXES, Dataset, FrameFiles, _parse_lidar, load_dataset, parse_board, parse_camera,
                      read_dataset_yaml)
from .input_files import load_yaml
from .motion_track import STILL_POSES_ONLY, is_moving_dataset
from .pointcloud_io import SCAN_2D_SUFFIXES, SCAN_SUFFIXES

SENSOR_TYPES = ("camera", "lidar")
# A single camera-LiDAR dataset's sensors as a rig's.
PAIR_CAMERA, PAIR_LIDAR = "cam0", "lidar0"
_NAME = re.compile(r"^[A-Za-z][A-Za-z0-9_\-]{0,63}$")


@dataclass(frozen=True)
class Sensor:
    """One sensor of a rig: its name (its folder), type, and for a camera its model (None: calibrated from its
    frames), for a LiDAR its kind (``3d`` or ``2d``), family and range accuracy; its files by stem."""

    name: str
    type: str
    camera: CameraModel | None = None
    lidar: str | None = None
    lidar_family: str | None = None
    range_accuracy_m: float | None = None
    files: tuple[tuple[str, Path], ...] = ()

    @property
    def is_camera(self) -> bool:
        return self.type == "camera"

    def file(self, stem: str) -> Path | None:
        return dict(self.files).get(stem)

    @property
    def stems(self) -> tuple[str, ...]:
        return tuple(s for s, _ in self.files)


@dataclass(frozen=True)
class RigDataset:
    """A loaded rig folder (files are read later)."""

    root: Path
    board: BoardModel
    sensors: tuple[Sensor, ...]
    reference: str

    @property
    def yaml_path(self) -> Path:
        return self.root / "dataset.yaml"

    def sensor(self, name: str) -> Sensor:
        return next(s for s in self.sensors if s.name == name)

    @property
    def cameras(self) -> tuple[Sensor, ...]:
        return tuple(s for s in self.sensors if s.is_camera)

    @property
    def lidars(self) -> tuple[Sensor, ...]:
        return tuple(s for s in self.sensors if not s.is_camera)

    @classmethod
    def of_pair(cls, dataset: Dataset) -> "RigDataset":
        """A single camera-LiDAR dataset as the rig of ``cam0`` (the reference) and ``lidar0``, frame by frame
        (``rig.pair("cam0", "lidar0")`` gives it back)."""
        camera = Sensor(PAIR_CAMERA, "camera", camera=dataset.camera,
                        files=tuple((f.name, f.image) for f in dataset.frames))
        lidar = Sensor(PAIR_LIDAR, "lidar", lidar=dataset.lidar, lidar_family=dataset.lidar_family,
                       range_accuracy_m=dataset.range_accuracy_m, files=tuple((f.name, f.scan) for f in dataset.frames))
        return cls(dataset.root, dataset.board, (camera, lidar), PAIR_CAMERA)

    @classmethod
    def of_measurements(cls, m) -> "RigDataset":
        """A pair's frames measured in memory (``io.measurement_store.Measurements``: ``estimators.measure``'s, or
        simulated ones) as the rig of ``cam0`` and ``lidar0`` their solve needs: its frames named, no files to read
        (its report has no images to draw on)."""
        root = Path(m.dataset or ".")
        stems = tuple((f.name, root / f.name) for f in m.frames)
        return cls(root, m.board, (Sensor(PAIR_CAMERA, "camera", camera=m.camera, files=stems),
                                   Sensor(PAIR_LIDAR, "lidar", lidar=m.lidar, files=stems)), PAIR_CAMERA)

    def pair(self, camera: str, lidar: str, camera_model: CameraModel | None = None) -> Dataset:
        """The camera-LiDAR pair as a single-pair :class:`~estimators.io.dataset.Dataset` over the stems both
        saw (``camera_model`` replaces the camera's entry, for intrinsics calibrated from its frames)."""
        c, lid = self.sensor(camera), self.sensor(lidar)
        stems = [s for s in c.stems if lid.file(s) is not None]
        return Dataset(root=self.root, lidar=lid.lidar, board=self.board,
                       camera=camera_model if camera_model is not None else c.camera,
                       frames=tuple(FrameFiles(s, c.file(s), lid.file(s)) for s in stems),
                       lidar_family=lid.lidar_family, range_accuracy_m=lid.range_accuracy_m)


def is_rig(path: str | os.PathLike) -> bool:
    """Whether the folder's dataset.yaml describes a rig (a ``sensors`` list)."""
    ypath = Path(path) / "dataset.yaml"
    if not ypath.is_file():
        return False
    spec = load_yaml(ypath, "dataset.yaml")
    return isinstance(spec, dict) and "sensors" in spec


def _sensor_files(folder: Path, suffixes: tuple[str, ...], ypath: Path) -> tuple[tuple[str, Path], ...]:
    if not folder.is_dir():
        raise DatasetError(f"sensor folder {folder.name}/ not found", path=folder,
                           hint="each sensor's files go in a folder named after it (<name>/NNNN.<ext>)")
    found: dict[str, Path] = {}
    for p in sorted(folder.iterdir()):
        if not p.is_file() or p.suffix.lower() not in suffixes:
            continue
        if p.stem in found:
            raise DatasetError(f"two files for frame {p.stem!r} ({found[p.stem].name}, {p.name})", path=p,
                               hint="keep one file per frame and sensor")
        found[p.stem] = p
    if not found:
        if is_moving_dataset(folder.parent):  # a board waved before the rig: each LiDAR's motion, no still frames
            raise DatasetError("a moving board's recording (each LiDAR's motion.npz), without still frames",
                               path=folder.parent, hint=STILL_POSES_ONLY)
        raise DatasetError(f"no frames in {folder.name}/ (files ending {', '.join(suffixes)})", path=folder,
                           hint="add NNNN files, or remove the sensor from dataset.yaml")
    return tuple(sorted(found.items()))


def load_rig(path: str | os.PathLike, files: bool = True) -> RigDataset:
    """Read a rig folder's ``dataset.yaml`` and list each sensor's files (module docstring).

    Parameters
    ----------
    path : str or os.PathLike
        The rig folder: ``dataset.yaml`` with ``sensors:`` and a folder of files per sensor; or a single
        camera-LiDAR dataset folder, read as the rig of ``cam0`` and ``lidar0`` (:meth:`RigDataset.of_pair`).
    files : bool
        False: the sensors alone, their folders not listed (a moving board's rig: each LiDAR's ``motion.npz``).

    Returns
    -------
    RigDataset
        The board, the sensors (each with its files by stem) and the reference sensor's name.

    Raises
    ------
    DatasetError
        A missing folder, a bad sensor entry (named, with what to write), a sensor folder missing or empty.
    """
    root, ypath, spec = read_dataset_yaml(path)
    if isinstance(spec, dict) and "sensors" not in spec:
        return RigDataset.of_pair(load_dataset(root))
    if not isinstance(spec, dict) or not isinstance(spec.get("sensors"), list) or not spec["sensors"]:
        raise DatasetError("sensors must be a non-empty list", path=ypath,
                           hint="list each sensor as {name: cam0, type: camera, ...} (docs/howto/rig.md)")
    unknown = set(spec) - {"board", "sensors", "reference"}
    if unknown:
        raise DatasetError(f"unknown rig key(s) {sorted(unknown)}", path=ypath,
                           hint="a rig's dataset.yaml takes board, sensors and reference")
    board = parse_board(spec.get("board"), ypath)
    sensors, names = [], set()
    for k, entry in enumerate(spec["sensors"]):
        if not isinstance(entry, dict):
            raise DatasetError(f"sensor {k} must be a mapping", path=ypath, hint="{name: cam0, type: camera}")
        name, kind = entry.get("name"), str(entry.get("type", "")).lower()
        if not isinstance(name, str) or not _NAME.match(name):
            raise DatasetError(f"sensor {k} needs a name (a folder name: letters, digits, _ or -), got {name!r}",
                               path=ypath, hint="for example name: cam0")
        if name in names:
            raise DatasetError(f"two sensors are named {name!r}", path=ypath, hint="give each sensor its own name")
        names.add(name)
        if kind not in SENSOR_TYPES:
            raise DatasetError(f"sensor {name!r} has type {entry.get('type')!r}", path=ypath,
                               hint="type is camera or lidar")
        if kind == "camera":
            extra = set(entry) - {"name", "type", "model", "width", "height", "K", "dist", "param_std"}
            if extra:
                raise DatasetError(f"unknown key(s) {sorted(extra)} for camera {name!r}", path=ypath,
                                   hint="a camera takes model, width, height, K, dist, param_std")
            body = {k2: v for k2, v in entry.items() if k2 not in ("name", "type")}
            camera = parse_camera(body, ypath) if "K" in body else None
            if camera is None and set(body) - {"model"}:
                raise DatasetError(f"camera {name!r} has intrinsics without K", path=ypath,
                                   hint="give K, width and height (and dist), or none to calibrate them")
            listed = _sensor_files(root / name, IMAGE_SUFFIXES, ypath) if files else ()
            sensors.append(Sensor(name, kind, camera=camera, files=listed))
        else:
            extra = set(entry) - {"name", "type", "lidar", "family", "range_accuracy_m"}
            if extra:
                raise DatasetError(f"unknown key(s) {sorted(extra)} for LiDAR {name!r}", path=ypath,
                                   hint="a LiDAR takes lidar (3d or 2d), family, range_accuracy_m")
            lidar, family, accuracy = _parse_lidar({"type": entry.get("lidar", "3d"), "family": entry.get("family"),
                                                    "range_accuracy_m": entry.get("range_accuracy_m")}, ypath)
            listed = _sensor_files(root / name, SCAN_2D_SUFFIXES if lidar == "2d" else SCAN_SUFFIXES, ypath) \
                if files else ()
            sensors.append(Sensor(name, kind, lidar=lidar, lidar_family=family, range_accuracy_m=accuracy,
                                  files=listed))
    reference = spec.get("reference", sensors[0].name)
    if reference not in names:
        raise DatasetError(f"reference {reference!r} is not a sensor", path=ypath,
                           hint=f"name one of {sorted(names)}")
    if not any(s.is_camera for s in sensors):
        raise DatasetError("a rig needs at least one camera", path=ypath,
                           hint="the board's pose comes from the cameras' images")
    return RigDataset(root, board, tuple(sensors), reference)


def first_pair(path: str | os.PathLike) -> tuple[str | None, str | None]:
    """A rig folder's first camera and first 3D LiDAR (None where it has none): the pair the scene's check takes
    unless told."""
    return _first(load_rig(path, files=False))


def _scene_sensors(rig: RigDataset) -> tuple[list[str], list[str]]:
    """The rig's cameras and its 3D LiDARs, by name (the sensors the scene's check pairs)."""
    return [c.name for c in rig.cameras], [s.name for s in rig.lidars if s.lidar == "3d"]


def _first(rig: RigDataset) -> tuple[str | None, str | None]:
    cameras, lidars = _scene_sensors(rig)
    return (cameras[0] if cameras else None), (lidars[0] if lidars else None)


def scene_pair(path: str | os.PathLike, need_camera: bool = True, pair: tuple[str, str] | None = None
               ) -> tuple[Path, CameraModel | None, BoardModel | None, tuple[FrameFiles, ...]]:
    """A rig folder for the scene's check (``io.dataset.load_scene_folder``): its root, ``pair``'s camera model
    (None without intrinsics, an error if ``need_camera``), the board and the frames both sensors of ``pair``
    (camera, 3D LiDAR; default :func:`first_pair`) saw."""
    rig = load_rig(path)
    ypath = rig.yaml_path
    cameras, lidars = _scene_sensors(rig)
    camera, lidar = pair if pair is not None else _first(rig)
    if camera not in cameras:
        raise DatasetError(f"the rig has no camera {camera!r} (cameras: {', '.join(cameras) or 'none'})", path=ypath,
                           hint="name one of its cameras (--camera)")
    if lidar not in lidars:
        raise DatasetError(f"the rig has no 3D LiDAR {lidar!r} (3D LiDARs: {', '.join(lidars) or 'none'})",
                           path=ypath, hint="name one of its 3D LiDARs (--lidar); a 2D scanner's line holds too few "
                                            "contours")
    ds = rig.pair(camera, lidar)
    if ds.camera is None and need_camera:
        raise DatasetError(f"the scene's check needs {camera}'s intrinsics (K in its sensor entry)", path=ypath,
                           hint="add K, dist, width, height to it, or check with a calibration that estimated them")
    return rig.root, ds.camera, rig.board, ds.frames
