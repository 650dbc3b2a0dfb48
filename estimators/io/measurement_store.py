"""Measurements on disk: ``measurements.npz`` (arrays) + ``measurements.json`` (everything else), no pickles.

A dataset is measured once (corners, board poses and planes in the images; the LiDAR board points of each
frame with their rings and intensities, and how they were chosen) and solved many times. The LiDAR planes and
moments are recomputed from the stored points on load (deterministic), so the store holds only what was
measured. :func:`dataset_key` names a dataset's content and the measurement options, for the cache.
"""
from __future__ import annotations

import functools
import hashlib
import json
import os
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from geometry.board import BoardModel
from geometry.camera import CameraModel
from geometry.planes import Plane

from ..errors import DatasetError
from ..measurements import (BoardDecision, CameraBoardObservation, FrameMeasurement, observe_lidar_board,
                            observe_lidar_line)
from .dataset import dataset_spec, parse_board
from .input_files import load_json, load_npz
from .output import write_json_atomic, write_npz_atomic

FORMAT = "lidarcam-measurements-1"
CACHE_ENV = "LIDARCAM_CACHE_DIR"


@dataclass(frozen=True, eq=False)
class Measurements:
    """A dataset's measured frames, ready to :func:`solve`.

    Attributes
    ----------
    camera : CameraModel
        The camera model the frames were measured with.
    board : BoardModel
        The board.
    lidar : str
        ``3d`` or ``2d``.
    frames : tuple of FrameMeasurement
        Every frame, usable or with the reason it is not.
    warnings : tuple of str
        Warnings from measuring.
    dataset : str
        The dataset's name.
    source : str
        ``measured``, ``cache`` or the file they were read from.
    key : str
        The key of the dataset content and options they were measured from.
    """

    camera: CameraModel
    board: BoardModel
    lidar: str
    frames: tuple[FrameMeasurement, ...]
    warnings: tuple[str, ...] = ()
    dataset: str = ""
    source: str = "measured"
    key: str = ""


@dataclass(frozen=True, eq=False)
class RigMeasurements:
    """A rig's sensors measured once (``pipeline.rig_measurement.measure_rig``), for its solve to take.

    Attributes
    ----------
    cameras : dict
        Camera name -> the ``CameraModel`` its boards were measured with.
    poses, skipped : dict
        Camera name -> stem -> its board (``CameraBoardObservation``), or the reason it has none.
    pairs : dict
        ``(camera, lidar)`` -> that pair's frames (``FrameMeasurement``, usable or with their reason), in the
        order they were measured.
    measured_by : dict
        ``(camera, lidar)`` -> stem -> the camera the LiDAR's board in that frame had been found with when the
        pair was measured (an earlier camera's, or this one's).
    warnings : tuple of str
    spawned : tuple of int
        The generators each pair's measurement drew (a cached rig draws as many, so that later draws match).
    source : str
        ``measured``, ``cache`` or the folder they were read from.
    cache : Path or None
        The cache folder they are kept in (``pipeline.rig_measurement.measured_rig``), which keeps the range
        terms' choices made on them too (:func:`load_choices`); None: not kept.
    """

    cameras: dict
    poses: dict
    skipped: dict
    pairs: dict
    measured_by: dict
    warnings: tuple = ()
    spawned: tuple = ()
    source: str = "measured"
    cache: Path | None = None

    @property
    def stems(self) -> list[str]:
        """The frames any camera found the board in, in name order."""
        return sorted({st for v in self.poses.values() for st in v})

    def restricted(self, stems) -> "RigMeasurements":
        """These measurements of the frames ``stems`` alone (nothing drawn from a generator to use them)."""
        keep = set(stems)

        def only(d: dict) -> dict:
            return {k: {st: v for st, v in by.items() if st in keep} for k, by in d.items()}

        return replace(self, poses=only(self.poses), skipped=only(self.skipped), measured_by=only(self.measured_by),
                       pairs={k: [f for f in v if f.name in keep] for k, v in self.pairs.items()}, spawned=())


def pair_as_rig(m: Measurements, camera: str = "cam0", lidar: str = "lidar0") -> RigMeasurements:
    """A camera-LiDAR pair's measurements (a pair folder's ``measurements.npz``) as its rig's: the rig of ``camera``
    and ``lidar`` that a pair folder loads as, each frame's camera board its pose, each frame without one skipped by
    the camera with its reason; a frame whose board's tilt the camera leaves ambiguous, with its LiDAR board, is
    the pair's too (the laser may decide its tilt)."""
    poses = {f.name: f.camera for f in m.frames if f.camera is not None}
    skipped = {f.name: f.reason for f in m.frames if f.camera is None}
    frames = [f for f in m.frames if f.camera is not None or f.camera_alternatives and f.lidar is not None]
    return RigMeasurements({camera: m.camera}, {camera: poses}, {camera: skipped}, {(camera, lidar): frames},
                           {(camera, lidar): {f.name: camera for f in frames}}, m.warnings, (), m.source)


def rig_as_pair(rm: RigMeasurements, board: BoardModel, lidar_kind: str, dataset: str = "") -> Measurements:
    """A rig of one camera and one LiDAR's measurements as the pair's (:func:`save_measurements` writes them as a
    pair folder's ``measurements.npz``): its pair's frames and, without a camera board, the camera's skipped ones."""
    ((camera, _), frames), = rm.pairs.items()
    paired = {f.name for f in frames}
    skipped = [FrameMeasurement(st, None, None, why) for st, why in rm.skipped[camera].items() if st not in paired]
    every = sorted(list(frames) + skipped, key=lambda f: f.name)
    return Measurements(rm.cameras[camera], board, lidar_kind, tuple(every), tuple(rm.warnings), dataset, rm.source)


RIG_FORMAT = "lidarcam-rig-measurements-1"


def save_rig_measurements(folder: str | Path, rm: RigMeasurements, board: BoardModel, lidar_kinds: dict) -> Path:
    """Each camera's boards and each pair's frames as :func:`save_measurements` folders under ``folder``, then
    ``index.json`` (written last: a folder without it is incomplete). ``lidar_kinds``: LiDAR name -> ``3d``/``2d``."""
    folder = Path(folder)
    cams = list(rm.cameras)
    for k, c in enumerate(cams):
        frames = [FrameMeasurement(st, obs, None) for st, obs in rm.poses[c].items()]
        frames += [FrameMeasurement(st, None, None, why) for st, why in rm.skipped[c].items()]
        save_measurements(folder / f"camera{k}", Measurements(rm.cameras[c], board, "3d", tuple(frames)))
    pairs = list(rm.pairs)
    for k, (c, lid) in enumerate(pairs):
        save_measurements(folder / f"pair{k}", Measurements(rm.cameras[c], board, lidar_kinds[lid],
                                                             tuple(rm.pairs[(c, lid)])))
    index = {"format": RIG_FORMAT, "cameras": cams, "pairs": [list(p) for p in pairs],
             "measured_by": [rm.measured_by[p] for p in pairs], "warnings": list(rm.warnings),
             "spawned": list(rm.spawned)}
    return write_json_atomic(folder / "index.json", index)


def load_rig_measurements(folder: str | Path) -> RigMeasurements:
    """What :func:`save_rig_measurements` wrote; :class:`DatasetError` for a missing, incomplete or foreign
    folder."""
    folder = Path(folder)
    if folder.name == "index.json":
        folder = folder.parent
    if folder.is_file():  # a pair's measurements.npz or .json given for a rig folder
        raise DatasetError("a file, where a rig's measurements folder is expected (a pair's measurements.npz is "
                           "read with its pair's folder)", path=folder,
                           hint="give the measurements folder `lidarcam calibrate RIG` wrote (it holds index.json)")
    index = load_json(folder / "index.json", "rig measurements index",
                      "give the measurements folder that `lidarcam calibrate RIG` wrote (it holds index.json)")
    try:
        if index.get("format") != RIG_FORMAT:
            raise ValueError(f"format {index.get('format')!r}, expected {RIG_FORMAT!r}")
        cameras, poses, skipped = {}, {}, {}
        for k, c in enumerate(index["cameras"]):
            m = load_measurements(folder / f"camera{k}")
            cameras[str(c)] = m.camera
            poses[str(c)] = {f.name: f.camera for f in m.frames if f.camera is not None}
            skipped[str(c)] = {f.name: f.reason for f in m.frames if f.camera is None}
        pairs = {(str(c), str(lid)): list(load_measurements(folder / f"pair{k}").frames)
                 for k, (c, lid) in enumerate(index["pairs"])}
        measured_by = {p: {str(st): str(c) for st, c in by.items()} for p, by in zip(pairs, index["measured_by"])}
        return RigMeasurements(cameras, poses, skipped, pairs, measured_by, tuple(map(str, index["warnings"])),
                               tuple(int(n) for n in index["spawned"]), str(folder))
    except DatasetError:
        raise
    except Exception as exc:
        raise DatasetError(f"not a readable lidarcam rig measurements folder ({type(exc).__name__}: "
                           f"{str(exc).splitlines()[0][:160] if str(exc) else 'no detail'})", path=folder,
                           hint="measure the rig again: `lidarcam calibrate RIG --out OUT` writes OUT/measurements"
                           ) from None


CHOICES = "choices.json"


def load_choices(folder: Path) -> dict:
    """The range terms' choices kept beside cached measurements (``solvers.choice_memo``: inputs' digest ->
    decisions, as the file holds them: ``choice_memo.recallable`` keeps those of a decision's form); {} where there
    are none or the file is not JSON (they are made again)."""
    try:
        kept = load_json(folder / CHOICES, "range-term choices")
    except DatasetError:
        return {}
    return kept if isinstance(kept, dict) else {}


def save_choices(folder: Path, choices: dict) -> None:
    """:func:`load_choices`'s file written (atomically); a cache that cannot be written is left as it is."""
    try:
        write_json_atomic(folder / CHOICES, choices)
    except OSError:
        pass


@functools.lru_cache(maxsize=1)
def code_key() -> str:
    """SHA-256 over the source of the package that measures (every module of ``estimators`` and ``geometry``):
    measurements cached by another version of the code are measured again, not returned."""
    h = hashlib.sha256()
    top = Path(__file__).resolve().parents[2]
    for path in sorted([*(top / "estimators").rglob("*.py"), *(top / "geometry").rglob("*.py")]):
        h.update(str(path.relative_to(top)).encode())
        h.update(path.read_bytes())
    return h.hexdigest()


def generator_key(rng: np.random.Generator) -> dict:
    """The generator's state and seed, for a cache key: measurements drawn with another stream are not returned."""
    ss = rng.bit_generator.seed_seq
    return {"rng": rng.bit_generator.state, "seed": [getattr(ss, "entropy", None), getattr(ss, "spawn_key", None),
                                                     getattr(ss, "n_children_spawned", None)]}


def dataset_key(root: Path, files: list[Path], options: dict) -> str:
    """SHA-256 over ``dataset.yaml``, every frame file's bytes (in order), the measurement options and the code
    that measures (:func:`code_key`)."""
    h = hashlib.sha256()
    h.update(FORMAT.encode())
    h.update(code_key().encode())
    h.update(json.dumps(options, sort_keys=True, default=_plain).encode())
    for path in [root / "dataset.yaml", *files]:
        h.update(path.name.encode())
        with open(path, "rb") as fh:
            for chunk in iter(lambda: fh.read(1 << 20), b""):
                h.update(chunk)
    return h.hexdigest()


def _plain(x):
    """JSON stand-ins for option values: arrays as lists, dataclasses as dicts, anything else as text."""
    if hasattr(x, "__dataclass_fields__"):
        return {k: getattr(x, k) for k in x.__dataclass_fields__}
    if isinstance(x, np.ndarray):
        return x.tolist()
    return str(x)


def cache_dir() -> Path:
    """The measurement cache: ``$LIDARCAM_CACHE_DIR``, else ``$XDG_CACHE_HOME/lidarcam``, else
    ``~/.cache/lidarcam``."""
    if os.environ.get(CACHE_ENV):
        return Path(os.environ[CACHE_ENV])
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "lidarcam"


def save_measurements(out_dir: str | Path, m: Measurements) -> Path:
    """Write ``OUT/measurements.npz`` and then ``OUT/measurements.json``, each atomically.

    Parameters
    ----------
    out_dir : str or Path
        The output folder (created when missing).
    m : Measurements
        From :func:`measure`.

    Returns
    -------
    Path
        The path of ``measurements.json``.
    """
    out = Path(out_dir)
    arrays: dict[str, np.ndarray] = {}
    frames = []
    for k, f in enumerate(m.frames):
        d: dict = {"name": f.name, "reason": f.reason}
        if f.camera is not None:
            d["camera"] = _save_camera(f.camera, f"f{k}_camera_", arrays)
        if f.camera_alternatives:  # both tilts of a board ambiguous in its orientation
            d["camera_alternatives"] = [_save_camera(c, f"f{k}_alternative{j}_camera_", arrays)
                                        for j, c in enumerate(f.camera_alternatives)]
        if f.lidar is not None:
            o = f.lidar
            p = f"f{k}_lidar_"
            arrays[p + "points"] = o.points
            if o.rings is not None:
                arrays[p + "rings"] = np.asarray(o.rings)
            if o.intensity is not None:
                arrays[p + "intensity"] = np.asarray(o.intensity, dtype=float)
            if o.open_ends is not None:
                arrays[p + "open_ends"] = np.asarray(o.open_ends, dtype=bool)
            d["lidar"] = {"scan_line": o.is_scan_line, "candidates": o.candidates}
        if f.decision is not None:
            dd = f.decision
            d["decision"] = {"method": dd.method, "candidates": list(dd.candidates), "chosen": dd.chosen,
                             "reason": dd.reason, "rejected": list(dd.rejected),
                             "candidate_points": len(dd.candidate_points)}
            for j, pts in enumerate(dd.candidate_points):
                arrays[f"f{k}_decision_points_{j}"] = np.asarray(pts, dtype=float)
        frames.append(d)
    board = dataset_spec(m.lidar, m.board, None)["board"]  # the dataset.yaml board entry
    meta = {"format": FORMAT, "dataset": m.dataset, "key": m.key, "lidar": m.lidar, "board": board,
            "camera": m.camera.as_dict(), "warnings": list(m.warnings), "frames": frames}
    write_npz_atomic(out / "measurements.npz", arrays)
    return write_json_atomic(out / "measurements.json", _jsonable(meta))


def load_measurements(path: str | Path) -> Measurements:
    """Read measurements that :func:`save_measurements` (or ``lidarcam calibrate``) wrote.

    Parameters
    ----------
    path : str or Path
        ``measurements.npz``, its folder, or ``measurements.json``; the two files are read together.

    Returns
    -------
    Measurements

    Raises
    ------
    DatasetError
        A missing, corrupt or mismatched file (never unpickled: the arrays are read without pickle).
    """
    path = Path(path)
    if path.is_dir():
        path = path / "measurements.npz"
    npz, meta_path = path.with_suffix(".npz"), path.with_suffix(".json")
    for p in (npz, meta_path):
        if not p.is_file():
            raise DatasetError("measurements file not found", path=p,
                               hint="give the measurements.npz that `lidarcam calibrate` wrote (beside its .json)")
    try:
        meta = load_json(meta_path, "measurements file",
                         "give the measurements.npz (and .json) that `lidarcam calibrate` wrote")
        if meta.get("format") != FORMAT:
            raise ValueError(f"format {meta.get('format')!r}, expected {FORMAT!r}")
        arrays = load_npz(npz)
        camera = _camera(meta["camera"])
        board = parse_board(meta["board"], meta_path)
        frames = tuple(_frame(k, d, arrays, board) for k, d in enumerate(meta["frames"]))
        return Measurements(camera, board, str(meta["lidar"]), frames, tuple(meta.get("warnings", ())),
                            str(meta.get("dataset", "")), str(npz), str(meta.get("key", "")))
    except DatasetError:
        raise
    except Exception as exc:  # a damaged or foreign file: name it
        raise DatasetError(f"not a readable lidarcam measurements file ({type(exc).__name__}: "
                           f"{str(exc).splitlines()[0][:160] if str(exc) else 'no detail'})", path=npz,
                           hint="measure again: `lidarcam calibrate DATASET --out OUT` writes it") from None


def _camera(d: dict) -> CameraModel:
    std = d.get("param_std")
    return CameraModel(np.array(d["K"], dtype=float), np.array(d["dist"], dtype=float), int(d["width"]),
                       int(d["height"]), d["model"], d.get("source", "given"),
                       None if std is None else np.array(std, dtype=float))


def _finite(a: np.ndarray, name: str) -> np.ndarray:
    a = np.asarray(a)
    if a.dtype.kind not in "fiu" or not np.all(np.isfinite(a)):
        raise ValueError(f"array {name} is not finite numbers")
    return a


def _per_point(arrays: dict, p: str, name: str, n: int, kinds: str) -> np.ndarray | None:
    """The optional per-point array ``p + name`` (None when absent): ``n`` finite values of a dtype kind in
    ``kinds``."""
    a = arrays.get(p + name)
    if a is None:
        return None
    a = np.asarray(a)
    if a.shape != (n,) or a.dtype.kind not in kinds or (a.dtype.kind == "f" and not np.all(np.isfinite(a))):
        raise ValueError(f"array {p}{name} is not one value per point ({n})")
    return a


def _corner_ids(arrays: dict, p: str, n_corners: int, board: BoardModel) -> np.ndarray | None:
    ids = arrays.get(p + "corner_ids")
    if ids is None:
        if n_corners != len(board.inner_corners()):
            raise ValueError(f"{p}corners_px holds {n_corners} corners, the board has {len(board.inner_corners())}")
        return None
    ids = np.asarray(ids)
    if (ids.dtype.kind not in "iu" or ids.shape != (n_corners,) or np.any(ids < 0)
            or np.any(ids >= len(board.inner_corners())) or np.any(np.diff(ids) <= 0)):
        raise ValueError(f"array {p}corner_ids is not {n_corners} ascending ids of the board's corners")
    return ids.astype(int)


def _save_camera(c: CameraBoardObservation, p: str, arrays: dict) -> dict:
    """A camera observation's arrays into ``arrays`` under prefix ``p``; the rest as a JSON dict."""
    arrays.update({p + "corners_px": c.corners_px, p + "T_camera_board": c.T_camera_board,
                   p + "plane": np.append(c.plane.normal, c.plane.distance),
                   p + "pose_covariance": c.pose_covariance, p + "plane_covariance": c.plane_covariance})
    if c.corner_ids is not None:
        arrays[p + "corner_ids"] = np.asarray(c.corner_ids, dtype=np.int64)
    return {"reprojection_rms_px": c.reprojection_rms_px, "detector": c.detector,
            "orientation_excess_chi2": c.orientation_excess_chi2, "pattern_inverted": c.pattern_inverted}


def _load_camera(d: dict, p: str, arrays: dict, board: BoardModel) -> CameraBoardObservation:
    plane = _finite(arrays[p + "plane"], p + "plane")
    corners = _finite(arrays[p + "corners_px"], p + "corners_px").reshape(-1, 2)
    return CameraBoardObservation(corners,
                                  _finite(arrays[p + "T_camera_board"], p + "T_camera_board"),
                                  Plane(plane[:3], float(plane[3])),
                                  _finite(arrays[p + "pose_covariance"], p + "pose_covariance"),
                                  _finite(arrays[p + "plane_covariance"], p + "plane_covariance"),
                                  float(d["reprojection_rms_px"]), str(d["detector"]),
                                  _corner_ids(arrays, p, len(corners), board),
                                  float(d.get("orientation_excess_chi2", 0.0)),
                                  _optional_bool(d.get("pattern_inverted"), p + "pattern_inverted"))


def _optional_bool(value, name: str) -> bool | None:
    if value is None or isinstance(value, bool):
        return value
    raise ValueError(f"{name} is {value!r}, expected true, false or null")


def _frame(k: int, d: dict, arrays: dict, board: BoardModel) -> FrameMeasurement:
    cam = lid = dec = None
    if "camera" in d:
        cam = _load_camera(d["camera"], f"f{k}_camera_", arrays, board)
    alternatives = tuple(_load_camera(c, f"f{k}_alternative{j}_camera_", arrays, board)
                         for j, c in enumerate(d.get("camera_alternatives", ())))
    if "lidar" in d:
        p = f"f{k}_lidar_"
        points = _finite(arrays[p + "points"], p + "points").astype(float)
        observe = observe_lidar_line if d["lidar"]["scan_line"] else observe_lidar_board
        lid = observe(points, int(d["lidar"]["candidates"]))
        lid = replace(lid, **{k: _per_point(arrays, p, k, len(points), kinds)
                              for k, kinds in (("rings", "iu"), ("intensity", "fiu"), ("open_ends", "b"))})
    if "decision" in d:
        dd = d["decision"]
        pts = tuple(arrays[f"f{k}_decision_points_{j}"] for j in range(int(dd["candidate_points"])))
        dec = BoardDecision(dd["method"], tuple(dd["candidates"]), dd["chosen"], dd["reason"],
                            tuple(dd["rejected"]), pts)
    return FrameMeasurement(str(d["name"]), cam, lid, d.get("reason"), dec, alternatives)


def _jsonable(x):
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, (np.floating, np.integer, np.bool_)):
        return x.item()
    return x
