"""A dataset's frames measured: each image's board and each sweep's or scan line's, chosen across frames over the
static scene (``measure_frames``), and kept in the measurement cache (``measure``); the hints that steer it."""
from __future__ import annotations

import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np
from threadpoolctl import threadpool_limits

from geometry.board import BoardModel
from geometry.camera import FISHEYE, PINHOLE, CameraModel
from geometry.planes import on_plane_along_beams, plane_difference
from geometry.rotations import T_inverse, skew, transform_points

from .. import __version__
from ..camera.board_pose import estimate_board_pose
from ..camera.charuco import MIN_CHARUCO_CORNERS
from ..camera.corners import detect_corners
from ..camera.detection import CornerDetection
from ..camera.intrinsics import calibrate_intrinsics
from ..errors import (AmbiguousBoardError, AmbiguousOrientationError, DatasetError, DegenerateLayoutError,
                      ImageReadError, MeasurementError, NoHypothesisError, ScanReadError, about)
from ..io.dataset import Dataset, load_dataset, parse_camera
from ..io.image_io import read_gray
from ..io.input_files import load_json, regular_file
from ..io.measurement_store import (Measurements, cache_dir, dataset_key, generator_key, load_measurements,
                                     save_measurements)
from ..io.pointcloud_io import SCAN_LINE_Z_M, read_scan_2d, read_sweep
from ..lidar.beam_rings import sweeps_beams
from ..lidar.board_segmentation import (BoardCandidate, SegmentationParams, board_candidates, border_trim,
                                        choose_by_prediction, decide_alone, noise_band, robust_plane_fit)
from ..lidar.scan_segmentation import ScanSegmentationParams, scan_candidates
from ..lidar.static_scene import StaticScene, StaticSceneParams, build_static_scene
from ..measurements import BoardDecision, FrameMeasurement, count_reasons, observe_lidar_board, observe_lidar_line
from ..solvers.association import Association, AssociationParams, associate, associate_lines, inside_outline
from ..solvers.board_edges import open_ends
from ..solvers.closed_form import solve_closed_form
from ..solvers.noise_levels import pooled_range_noise_m

# Part of the measurement cache's key: raised when what a measurement holds changes within a version, so that no
# cache entry from before is taken for a new one (2: the tilts of boards ambiguous in their orientation; 4: a scan
# line cut to the board's outline by the extrinsic's uncertainty too; 5: a ring field that does not index beams set
# aside; 6: sweeps without one measured along beams found from their elevations; 7: ring ends that are no edges).
MEASUREMENT_REVISION = 7


@dataclass(frozen=True, eq=False)
class Hints:
    """Optional help for scenes beyond automation; never a factor, only a gate on the LiDAR candidates.

    ``initial_guess``: a rough ``T_camera_lidar``; a candidate whose plane, mapped through it, differs from the
    camera's board plane by more than ``guess_angle_rad`` or ``guess_distance_m`` is rejected.
    ``roi_min`` / ``roi_max``: a box in the LiDAR frame (m) outside which points are ignored.
    ``static_scene``: build the background model from all frames (default) or judge each frame alone.
    ``pair_guesses``: a rig's rough transforms by pair name (``T_<camera>_<lidar>``), each the initial guess of that
    camera-LiDAR pair's board search."""

    initial_guess: np.ndarray | None = None
    guess_angle_rad: float = float(np.deg2rad(10.0))
    guess_distance_m: float = 0.30
    roi_min: np.ndarray | None = None
    roi_max: np.ndarray | None = None
    static_scene: bool = True
    pair_guesses: dict | None = None

    def in_roi(self, points: np.ndarray) -> np.ndarray:
        keep = np.ones(len(points), dtype=bool)
        if self.roi_min is not None:
            keep &= np.all(points >= np.asarray(self.roi_min), axis=1)
        if self.roi_max is not None:
            keep &= np.all(points <= np.asarray(self.roi_max), axis=1)
        return keep


def parse_initial_guess(values: list[str]) -> np.ndarray:
    """A rough ``T_camera_lidar`` from the command line: six numbers ``x y z roll pitch yaw`` (m, degrees;
    ``R = Rz(yaw) Ry(pitch) Rx(roll)``), or one file: a ``calibration.json`` (its ``T_camera_lidar``) or a 4x4
    matrix as JSON, text or ``.npy``."""
    from scipy.spatial.transform import Rotation

    from geometry.rotations import T_from_Rt

    if len(values) == 6:
        try:
            x, y, z, roll, pitch, yaw = numbers = [float(v) for v in values]
            if not np.all(np.isfinite(numbers)):
                raise ValueError("not finite")
        except ValueError:
            raise DatasetError(f"--initial-guess {' '.join(values)!r} is not six finite numbers",
                               hint="give x y z roll pitch yaw (m, degrees) or a file") from None
        R = Rotation.from_euler("ZYX", [yaw, pitch, roll], degrees=True).as_matrix()
        return T_from_Rt(R, np.array([x, y, z]))
    if len(values) != 1:
        raise DatasetError(f"--initial-guess takes six numbers or one file, got {len(values)} value(s)",
                           hint="give x y z roll pitch yaw (m, degrees) or a file")
    path = regular_file(values[0], "initial guess file", hint="give a calibration.json or a 4x4 matrix")
    try:
        if path.suffix.lower() == ".npy":
            T = np.load(path, allow_pickle=False)
        elif path.suffix.lower() == ".json":
            data = load_json(path, "initial guess file")
            T = data["T_camera_lidar"] if isinstance(data, dict) else data
        else:
            T = np.loadtxt(path)
    except (ValueError, KeyError, TypeError, OSError, UnicodeDecodeError) as exc:
        raise DatasetError(f"initial guess unreadable ({type(exc).__name__}: {exc})", path=path,
                           hint="give a calibration.json or a 4x4 matrix") from None
    return rigid(T, path, "initial guess")


def parse_rig_guess(values: list[str]) -> dict:
    """A rig's rough transforms from the command line: one file, a rig's ``calibration.json`` (its ``transforms``:
    every camera-LiDAR pair's ``T``), as a pair name -> 4x4 mapping (:attr:`Hints.pair_guesses`)."""
    if len(values) != 1:
        raise DatasetError(f"--initial-guess for a rig takes one file, got {len(values)} value(s)",
                           hint="give the calibration.json of an earlier calibration of this rig")
    path = regular_file(values[0], "initial guess file", hint="give a rig's calibration.json")
    data = load_json(path, "initial guess file")
    if not isinstance(data, dict) or not isinstance(data.get("transforms"), dict):
        raise DatasetError("initial guess for a rig has no transforms", path=path,
                           hint="give the calibration.json of an earlier calibration of this rig")
    try:
        return {name: rigid(t["T"], path, f"initial guess {name}") for name, t in data["transforms"].items()}
    except (KeyError, TypeError) as exc:
        raise DatasetError(f"initial guess unreadable ({type(exc).__name__}: {exc})", path=path,
                           hint="give the calibration.json of an earlier calibration of this rig") from None


def pair_from_calibration(value: str, camera: str, lidar: str) -> np.ndarray:
    """``T_camera_lidar`` of one camera-LiDAR pair of a rig from a file: a rig's ``calibration.json`` (its
    ``transforms``: ``T_<camera>_<lidar>``, or the inverse of ``T_<lidar>_<camera>``), or any file
    :func:`parse_initial_guess` reads (one ``T_camera_lidar``, taken as this pair's)."""
    path = regular_file(value, "calibration file", hint="give a calibration.json or a 4x4 matrix")
    data = load_json(path, "calibration file") if path.suffix.lower() == ".json" else None
    if not isinstance(data, dict) or not isinstance(data.get("transforms"), dict):
        return parse_initial_guess([value])
    found = _transform_entry(data, camera, lidar)
    if found is not None:
        key, entry, flip = found
        T = rigid(entry["T"], path, key)
        return np.linalg.inv(T) if flip else T
    raise DatasetError(f"the calibration has no transform between {camera} and {lidar} (it has "
                       f"{', '.join(sorted(data['transforms'])) or 'none'})", path=path,
                       hint="give the calibration of this rig, or name its sensors with --camera and --lidar")


def given_covariance(value: str, sensors: tuple[str, str] | None = None) -> np.ndarray | None:
    """The 6x6 covariance (the project's tangent) of the ``T_camera_lidar`` that :func:`parse_initial_guess` or
    :func:`pair_from_calibration` (``sensors``: a rig's camera and LiDAR) reads from ``value``, where the file holds
    one: a calibration.json's ``covariance``, or its ``transforms`` entry's (that of ``T_<lidar>_<camera>`` carried
    to the inverse); None for a file without one. A covariance that is not a finite symmetric positive semi-definite
    6x6 is a one-line error (``DatasetError``): taken as absent, a check would read its extrinsic as exact, and a
    negative one made the scene's directions look unconstrained."""
    from ..solvers.factor_graph import adjoint

    data = _calibration_data(value)
    if data is None:
        return None
    C, T_flip, key = None, None, "T_camera_lidar"
    if sensors is not None and isinstance(data.get("transforms"), dict):
        found = _transform_entry(data, *sensors)
        if found is not None:
            key, entry, flip = found
            C, T_flip = entry.get("covariance"), (entry["T"] if flip else None)
    elif "T_camera_lidar" in data:
        C = data.get("covariance")
    if C is None:
        return None
    problem = None
    try:
        C = np.asarray(C, dtype=float)
        if C.shape != (6, 6) or not np.all(np.isfinite(C)):
            problem = f"not a finite 6x6 matrix (shape {C.shape})"
        elif not np.allclose(C, C.T, rtol=1e-6, atol=1e-15):
            problem = "not symmetric"
        elif np.linalg.eigvalsh(0.5 * (C + C.T))[0] < -1e-9 * max(float(np.abs(C).max()), 1e-300):
            problem = "not positive semi-definite (a negative variance)"
        elif T_flip is not None:  # T_true = T Exp(e): its inverse is T^-1 Exp(-Ad(T) e)
            A = adjoint(rigid(T_flip, Path(value), key))
            C = A @ C @ A.T
    except (ValueError, TypeError) as exc:
        problem = f"unreadable ({type(exc).__name__}: {exc})"
    if problem is not None:
        raise DatasetError(f"{key}'s covariance is {problem}", path=Path(value),
                           hint="give the calibration.json lidarcam wrote, or remove its covariance to take the "
                                "extrinsic as exact")
    return 0.5 * (C + C.T)


def given_camera(value: str, sensors: tuple[str, str] | None = None) -> CameraModel | None:
    """The camera model a calibration.json's extrinsic was estimated under: a rig calibration's ``cameras`` entry
    for ``sensors[0]`` (a pair folder's calibration: its ``intrinsics``, or its one ``cameras`` entry), its
    intrinsics refined or given; None for any other file (a bare 4x4, a JSON without intrinsics)."""
    data = _calibration_data(value)
    if data is None:
        return None
    path = Path(value)
    cameras = data.get("cameras") if isinstance(data.get("cameras"), dict) else {}
    if sensors is not None:
        entry = cameras.get(sensors[0])
    else:
        entry = next(iter(cameras.values())) if len(cameras) == 1 else data.get("intrinsics")
    if not isinstance(entry, dict):
        return None
    camera = parse_camera(entry, path)
    return replace(camera, source=f"{path.name}: {entry.get('source') or 'given'}")


def _calibration_data(value: str) -> dict | None:
    """A calibration JSON's content (a one-line error for a file that does not parse), or None where ``value`` is
    not a JSON file holding a mapping (a 4x4 matrix given on the command line, another file)."""
    path = Path(value)
    if path.suffix.lower() != ".json" or not path.is_file():
        return None
    data = load_json(path, "calibration file")
    return data if isinstance(data, dict) else None


def _transform_entry(data: dict, camera: str, lidar: str) -> tuple[str, dict, bool] | None:
    """A rig calibration's ``transforms`` entry between ``camera`` and ``lidar``: its key, the entry, and whether it
    is the inverse (``T_<lidar>_<camera>``); None where there is none."""
    for key, flip in ((f"T_{camera}_{lidar}", False), (f"T_{lidar}_{camera}", True)):
        entry = data["transforms"].get(key)
        if isinstance(entry, dict) and "T" in entry:
            return key, entry, flip
    return None


def rigid(T, path, what: str) -> np.ndarray:
    """``T`` as a finite 4x4 rigid transform, or a one-line error naming ``path`` and ``what``."""
    try:
        T = np.asarray(T, dtype=float)
    except (ValueError, TypeError) as exc:
        raise DatasetError(f"{what} unreadable ({type(exc).__name__}: {exc})", path=path,
                           hint="give a calibration.json or a 4x4 matrix") from None
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise DatasetError(f"{what} is not a finite 4x4 matrix (shape {T.shape})", path=path,
                           hint="give a calibration.json or a 4x4 matrix")
    R = T[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-3) or np.linalg.det(R) < 0:
        raise DatasetError(f"{what} is not a rigid transform (its rotation is not orthonormal)", path=path,
                           hint="give T_camera_lidar as a 4x4 rigid transform")
    return T


_TIMING_LOCK = threading.Lock()


def _add_time(timings: dict, key: str, seconds: float) -> None:
    with _TIMING_LOCK:
        timings[key] = timings.get(key, 0.0) + seconds


def detect_in_image(frame, board, timings) -> tuple[tuple[int, int] | None, CornerDetection | str | None]:
    """The image's size and the corners found in it (None: no board; a string: why the frame is skipped)."""
    t0 = time.perf_counter()
    try:
        gray = read_gray(frame.image)
    except ImageReadError as exc:  # a damaged frame is skipped with its reason; the rest calibrate
        _add_time(timings, "load_images", time.perf_counter() - t0)
        return None, f"image: {exc.message}"
    t1 = time.perf_counter()
    try:
        det = detect_corners(gray, board)
    except MeasurementError as exc:  # past the time budget: the frame is skipped with the reason
        det = exc.message
    _add_time(timings, "load_images", t1 - t0)
    _add_time(timings, "corners", time.perf_counter() - t1)
    return (gray.shape[1], gray.shape[0]), det


def measure_frames(dataset: Dataset, rng: np.random.Generator, params: SegmentationParams = SegmentationParams(),
                   timings: dict | None = None, workers: int = 2, hints: Hints = Hints(),
                   detections: dict | None = None, board_poses: dict | None = None,
                   sweeps: "LidarSweeps | None" = None) -> tuple[CameraModel, list[FrameMeasurement], list[str]]:
    """Detect the board in every frame, in the image and in the scan; frames that fail keep a reason.

    3D: the static scene of all sweeps, every frame's board candidates in front of it, and the choice of one
    candidate per frame by the extrinsic most frames agree with (``solvers.association``). 2D: each scan's
    board segment, with the other scans as the static background. ``detections``: the images' corners already
    found (frame name -> what ``detect_in_image`` returns; a rig's cameras are searched once); ``board_poses``: the
    board poses already estimated from them (frame name -> ``estimate_board_pose``'s result, by this dataset's camera);
    ``sweeps``: a 3D LiDAR's sweeps already read and its static scene built (:func:`read_sweeps`, over these frames
    or more: a rig's LiDAR is read once for every camera it shares frames with)."""
    # One worker budget: frames run in ``workers`` threads, each with one OpenCV thread and one BLAS thread
    # (their own pools on top of ours would oversubscribe the cores).
    with threadpool_limits(1 if workers > 1 else None):
        return _measure_frames(dataset, rng, params, timings, workers, hints, detections, board_poses, sweeps)


def _measure_frames(dataset: Dataset, rng: np.random.Generator, params: SegmentationParams, timings: dict | None,
                    workers: int, hints: Hints, detections: dict | None = None, board_poses: dict | None = None,
                    sweeps: "LidarSweeps | None" = None) -> tuple[CameraModel, list[FrameMeasurement], list[str]]:
    timings = {} if timings is None else timings
    with ThreadPoolExecutor(max_workers=1) as ahead:
        # A 3D dataset's sweeps are read and its static scene built (they need no camera) while the images
        # are searched for the pattern, in a thread of their own: the static scene's build is otherwise a
        # stage that keeps one core idle.
        if dataset.lidar != "2d":
            sweeps = ahead.submit(read_sweeps, dataset.frames, hints, timings).result if sweeps is None else \
                (lambda given=sweeps: given)
        return _measure_frames_with(dataset, rng, params, timings, workers, hints, sweeps, detections, board_poses)


def _measure_frames_with(dataset: Dataset, rng: np.random.Generator, params: SegmentationParams, timings: dict,
                         workers: int, hints: Hints, sweeps_ahead, found: dict | None = None,
                         board_poses: dict | None = None) -> tuple[CameraModel, list[FrameMeasurement], list[str]]:
    """:func:`_measure_frames` given a call that returns :func:`read_sweeps`'s result (None for a 2D dataset)."""
    warnings: list[str] = []
    cv_threads = cv2.getNumThreads()
    cv2.setNumThreads(1 if workers > 1 else cv_threads)
    try:
        with ThreadPoolExecutor(max_workers=workers) as pool:
            detections = list(pool.map(lambda f: found[f.name] if found and f.name in found else
                                       detect_in_image(f, dataset.board, timings), dataset.frames))
    finally:
        cv2.setNumThreads(cv_threads)
    if not board_poses:  # a rig's cameras were checked when their boards were found
        with about(dataset.yaml_path):
            squares_as_given(dataset.board, [f.image for f in dataset.frames], [d for _, d in detections])
    camera = dataset.camera
    sizes = {s for s, _ in detections if s is not None}
    if camera is None:
        found = [d for _, d in detections if isinstance(d, CornerDetection)]
        if len(sizes) != 1:
            raise DatasetError(f"images have different sizes {sorted(sizes)}", path=dataset.root,
                               hint="use one camera resolution for all frames")
        if len(found) < 3:
            raise DegenerateLayoutError(f"intrinsics cannot be calibrated from {len(found)} board view(s)",
                                        path=dataset.yaml_path, hint="add camera: to dataset.yaml or more frames")
        t0 = time.perf_counter()
        camera, rms = calibrate_intrinsics([d.corners_px for d in found], dataset.board, *sizes.pop(),
                                           corner_ids=[d.corner_ids for d in found])
        _add_time(timings, "intrinsics", time.perf_counter() - t0)
        warnings.append(f"no camera in dataset.yaml: intrinsics {camera.source}")
    # An image of another size than the camera entry's is refused for its frame: the intrinsics are for
    # another resolution.
    detections = [(size, f"image is {size[0]}x{size[1]} but the camera entry is {camera.width}x{camera.height} "
                         "(its intrinsics are for another resolution; fix camera width/height in dataset.yaml)")
                  if size is not None and size != (camera.width, camera.height) else (size, det)
                  for size, det in detections]

    alternatives: dict[int, tuple] = {}  # both tilts of each board ambiguous in its orientation

    def camera_side(k: int, det) -> tuple:
        if det is None:
            return None, (f"fewer than {MIN_CHARUCO_CORNERS} ChArUco corners spanning the board seen in the image"
                          if dataset.board.is_charuco else "checkerboard not found in the image")
        if isinstance(det, str):
            return None, det
        if board_poses and dataset.frames[k].name in board_poses:
            return board_poses[dataset.frames[k].name], None
        try:
            return estimate_board_pose(det, dataset.board, camera), None
        except AmbiguousOrientationError as exc:
            alternatives[k] = exc.observations
            return None, f"board pose: {exc.message}"
        except MeasurementError as exc:
            return None, f"board pose: {exc.message}"

    cams = [camera_side(k, det) for k, (_, det) in enumerate(detections)]
    if dataset.camera is not None and not board_poses and not camera.source.startswith("refined"):
        with about(dataset.yaml_path):
            model_as_given(camera, dataset.board, {k: det for k, (_, det) in enumerate(detections)
                                                   if cams[k][0] is not None},
                           {k: obs for k, (obs, _) in enumerate(cams) if obs is not None})
    frame_rngs = rng.spawn(len(dataset.frames) + 1)
    if dataset.lidar == "2d":
        frames = _measure_scans_2d(dataset, cams, camera, frame_rngs[-1], params, timings, warnings, workers,
                                   alternatives)
    else:
        frames = _measure_sweeps_3d(dataset, cams, camera, frame_rngs, params, hints, timings, warnings, workers,
                                    sweeps_ahead())
    _in_the_images_scale(dataset, camera, frames)
    return camera, frames, warnings


# Images in which a checkerboard found in at most one frame is looked for with one square more and one fewer
# along each side (:func:`squares_as_given`).
SQUARES_TRIED_IMAGES = 3


def squares_as_given(board, images: list, detections: list, who: str = "the camera") -> None:
    """Refuse ``board.squares`` counted as inner corners (or one too many): where a checkerboard was found in at
    most one of 3 or more ``images`` (``detections`` their ``detect_in_image`` corners: None where not found), and
    one of a square more (or fewer) along each side is found in every one of up to ``SQUARES_TRIED_IMAGES`` images
    where it was not (no pair calibrates from one board: it would be refused for too few frames, blaming the
    layout). A simulated 9 x 7-square board declared 8 x 6 was found in 1 of 8 images and refused as "only 1 usable
    frame(s) ... record more board poses"; declared 10 x 8, in none, each frame skipped as "board not found in the
    image"."""
    if board.is_charuco or len(images) < 3:
        return
    found = sum(isinstance(d, CornerDetection) for d in detections)
    missed = [img for img, d in zip(images, detections) if d is None][:SQUARES_TRIED_IMAGES]
    if found >= 2 or len(missed) < 2:  # two boards calibrate a scanner whose board's size is given
        return
    nx, ny = board.squares
    for ax, ay in ((nx + 1, ny + 1), (nx - 1, ny - 1)):
        try:
            other = BoardModel((ax, ay), board.square_size)
        except ValueError:  # fewer than 3 squares along a side
            continue
        seen = []
        for img in missed:
            try:
                seen.append(detect_corners(read_gray(img), other) is not None)
            except (ImageReadError, MeasurementError):
                seen.append(False)
        if all(seen):
            names = ", ".join(Path(img).name for img in missed)
            raise DatasetError(f"{who} found the {nx} x {ny}-square board in {found} of {len(images)} images, and a "
                               f"{ax} x {ay}-square one in each of {names}, where it did not: board.squares counts "
                               f"the squares (a {ax} x {ay}-square board has {ax - 1} x {ay - 1} inner corners)",
                               hint=f"set board.squares: [{ax}, {ay}] if that is the board's count of squares")


# A camera's boards fitting its given intrinsics with a median reprojection RMS above this (px) are fitted again
# under the other lens model with the same coefficients (:func:`model_as_given`); below it, as good data's are
# (simulated 0.1-0.15 px, the recorded cameras 0.16), nothing is tried.
MODEL_SUSPECT_PX = 0.3
# ... and refused when the other model fits them this many times better.
MODEL_BETTER_FACTOR = 2.0


def other_model(camera: CameraModel) -> CameraModel | None:
    """``camera`` as the other lens model with the same K and coefficients: a fisheye's k1..k4 as a pinhole's k1 k2
    p1 p2, and back (a pinhole's fifth, k3, must be 0); None where the coefficients do not fit the other model."""
    dist = camera.dist
    if camera.model == FISHEYE:
        return replace(camera, model=PINHOLE)
    if len(dist) == 4 or len(dist) == 5 and dist[4] == 0.0:
        return replace(camera, model=FISHEYE, dist=dist[:4].copy())
    return None


def model_as_given(camera: CameraModel, board, detections: dict, poses: dict, who: str = "the camera") -> None:
    """Refuse a camera whose boards (``poses`` by frame, estimated from ``detections`` under ``camera``) fit its
    intrinsics read as the other lens model (:func:`other_model`) ``MODEL_BETTER_FACTOR`` times better, where they
    fit them as given worse than ``MODEL_SUSPECT_PX``: the dataset's ``camera.model`` is the other one; ``who``
    names the camera (a rig's "camera cam1"). The recorded Ouster set's fisheye read as a pinhole fits its
    boards at a median 1.55 px (0.19 as a fisheye), and read UNTRUSTED with the boards' choice blamed first; a
    simulated pinhole read as a fisheye at 0.70 px (0.06 as a pinhole), and UNTRUSTED with 7 of 8 boards off."""
    other = other_model(camera)
    if other is None or len(poses) < 3:
        return
    given = float(np.median([obs.reprojection_rms_px for obs in poses.values()]))
    if given <= MODEL_SUSPECT_PX:
        return
    fits = []
    for det in detections.values():
        try:
            fits.append(estimate_board_pose(det, board, other).reprojection_rms_px)
        except MeasurementError:  # no pose under the other model either (an ambiguous tilt among them)
            continue
    if len(fits) < len(poses) // 2 + 1:
        return
    better = float(np.median(fits))
    if better * MODEL_BETTER_FACTOR <= given:
        raise DatasetError(f"{who}'s boards fit the intrinsics as a {camera.model} camera with a median "
                           f"{given:.2f} px RMS, and {better:.2f} px as a {other.model} camera with the same "
                           f"coefficients: camera.model is {other.model}, not {camera.model}",
                           hint=f"set camera.model: {other.model} (dist: k1 k2 k3 k4 for a fisheye, k1 k2 p1 p2 [k3 "
                                "...] for a pinhole), as the camera was calibrated")


# How far from the image's centre (a share of its width or height) a principal point lies before a camera whose
# boards no LiDAR board matches is read as given intrinsics for another resolution.
CENTRE_SHARE = 0.2


def _in_the_images_scale(dataset: Dataset, camera: CameraModel, frames: list[FrameMeasurement]) -> None:
    """Refuse intrinsics for another resolution: where three or more frames have the camera's board and fewer than
    three the LiDAR's (too few to calibrate), and the principal point lies more than ``CENTRE_SHARE`` of the image's
    size from its centre (K for twice or half the images' size put every simulated board twice or half as far as
    its returns: the frames were skipped with "only 0 points ... where the camera puts the board", and the pair
    refused for too few frames)."""
    seen = [f for f in frames if f.camera is not None]
    found = sum(f.lidar is not None for f in seen)
    if len(seen) < 3 or found >= 3 or not off_centre(camera):
        return
    raise DatasetError(f"{found} of {len(seen)} frames have a LiDAR board where the camera puts theirs, and "
                       f"{off_centre_words(camera)}", path=dataset.yaml_path,
                       hint="give camera.K for the images' own size (fx, fy, cx and cy scaled by it)")


def off_centre(camera: CameraModel | None) -> bool:
    """Whether ``camera``'s principal point lies more than ``CENTRE_SHARE`` of its image's size from the centre."""
    return camera is not None and camera.principal_point_offset().max() > CENTRE_SHARE


def off_centre_words(camera: CameraModel) -> str:
    """Where a principal point lies, far from its image's centre (``CENTRE_SHARE``), and what that suggests."""
    share = camera.principal_point_offset()
    return (f"camera.K's principal point ({camera.K[0, 2]:.0f}, {camera.K[1, 2]:.0f}) lies {100 * share[0]:.0f}% of "
            f"the width and {100 * share[1]:.0f}% of the height from the centre of the {camera.width} x "
            f"{camera.height} images: intrinsics for another resolution?")


def _measure_scans_2d(dataset: Dataset, cams: list[tuple], camera: CameraModel, rng: np.random.Generator,
                      params: SegmentationParams, timings: dict, warnings: list[str], workers: int,
                      alternatives: dict[int, tuple] | None = None) -> list[FrameMeasurement]:
    """Each scan's board segment. Single-line scans are small, so all are read once: the static scene's
    per-beam ranges tell the board (which moves between frames) from background of the board's length, and
    every frame's candidate segments are chosen jointly by the minimal solution most frames agree with
    (``solvers.association.associate_lines``); without one, each frame decides alone. A board ambiguous in
    its orientation (``alternatives``: both tilts) keeps its segment when it is the only one where the camera
    puts the board, for the solver to try its tilts (``solution_selection.select_and_refine``)."""
    from scipy.spatial import cKDTree

    alternatives = alternatives or {}

    t0 = time.perf_counter()
    read = _read_every(read_scan_2d, [f.scan for f in dataset.frames])
    cams, good = _without_damaged_scans(cams, read)
    scans_2d = [xy if not isinstance(xy, str) else np.zeros((0, 2)) for xy in read]
    _add_time(timings, "load_scans", time.perf_counter() - t0)
    trees = {k: cKDTree(scans_2d[k]) for k in good}
    scene = build_static_scene([scans_2d[k] for k in good])
    if scene.note and len(scans_2d) >= scene.params.min_frames:
        warnings.append(f"static scene: {scene.note}")
    seg_params = ScanSegmentationParams(max_sensor_separation_m=params.max_sensor_separation_m)

    def search(k: int, j: int | None = None) -> tuple[list, str | None, list]:
        """Frame ``k``'s segments: the camera's board of image ``k`` looked for in scan ``j`` (``k``)."""
        j = k if j is None else j
        # an ambiguous board's tilts put it at one place: either finds its segments (outside the consensus)
        cam_obs = alternatives[k][0] if k in alternatives and k in good else cams[k][0]
        if cam_obs is None:
            return [], None, []
        t1 = time.perf_counter()
        static: list = []
        try:
            return scan_candidates(scans_2d[j], dataset.board, cam_obs, seg_params,
                                   [t for i, t in trees.items() if i != j],
                                   scene.frame_foreground(good.index(j)), static), None, static
        except MeasurementError as exc:
            return [], exc.message, []
        finally:
            _add_time(timings, "segmentation", time.perf_counter() - t1)

    with ThreadPoolExecutor(max_workers=workers) as pool:
        searched = list(pool.map(search, range(len(dataset.frames))))
    t0 = time.perf_counter()
    # The consensus also sees the segments judged static (boards held at one place in several frames look
    # static); without a consensus each frame decides from its moving segments alone.
    def consensus(cams_: list[tuple], searched_: list[tuple], warned: list[str], rng_: np.random.Generator) -> tuple:
        joint_ = [cands + sorted(static, key=lambda c: c[0]) for cands, _, static in searched_]
        return joint_, _consensus(cams_, [[obs for _, obs in c] for c in joint_], warned, "scan segments",
                                  lambda planes, poses, cands, _: associate_lines(planes, poses, cands, dataset.board,
                                                                                   rng_))

    joint, (assoc, choice) = consensus(cams, searched, warnings, rng)
    _add_time(timings, "association", time.perf_counter() - t0)
    if _unsettled(assoc):
        _not_shifted(dataset, cams, lambda j: j in good, lambda pairs, r: consensus(
            [cams[k] for k, _ in pairs], [search(k, j) for k, j in pairs], [], r)[1][0], rng)
    found = [(joint[k], error) if assoc is not None else (cands, error)
             for k, (cands, error, _) in enumerate(searched)]
    found = [(c, e if c else (e or "no straight scan segment of the board's length that moves between frames"))
             for c, e in found]
    frames, ambiguous = [], {}
    for k, frame in enumerate(dataset.frames):
        (cam_obs, why), (cands, error) = cams[k], found[k]
        if cam_obs is None and k in alternatives and len(searched[k][0]) == 1:
            _, seg = searched[k][0][0]
            frames.append(FrameMeasurement(
                frame.name, None, seg, why, BoardDecision(
                    "this frame alone", _segment_dicts(searched[k][0], chosen=0), 0,
                    "the only segment where the camera puts the board (its tilt is left to the solver)", (),
                    (seg.points,)), alternatives[k]))
            continue
        if cam_obs is None:
            frames.append(FrameMeasurement(frame.name, None, None, why))
            continue
        if not cands:
            frames.append(FrameMeasurement(frame.name, cam_obs, None, f"LiDAR board: {error}"))
            continue
        points = tuple(obs.points for _, obs in cands)
        if assoc is not None:
            c = choice[k]
            decision = BoardDecision(f"consensus of {assoc.agreeing} frames", _segment_dicts(cands, c.residuals,
                                                                                            c.chosen),
                                     c.chosen, c.reason, (), points)
            lid = None if c.chosen is None else cands[c.chosen][1]  # cut to the outline below
            frames.append(FrameMeasurement(frame.name, cam_obs, lid, None if lid else f"LiDAR board: {c.reason}",
                                           decision))
            continue
        if len(cands) > 1 and cands[1][0] < seg_params.ambiguity_ratio * cands[0][0] + 0.05:
            reason = f"ambiguous: {len(cands)} board-length scan segments lie where the camera puts the board"
            ambiguous[frame.name] = [obs for _, obs in cands]
            frames.append(FrameMeasurement(frame.name, cam_obs, None, f"LiDAR board: {reason}",
                                           BoardDecision("this frame alone", _segment_dicts(cands), None, reason,
                                                         (), points)))
            continue
        frames.append(FrameMeasurement(frame.name, cam_obs, cands[0][1], None,
                                       BoardDecision("this frame alone", _segment_dicts(cands, chosen=0), 0,
                                                     "the only segment that agrees with the camera's board", (),
                                                     points)))
    if assoc is not None:
        frames = _cut_lines(frames, assoc.T_camera_lidar, dataset.board)
    if ambiguous:
        frames = _resolve_ambiguous(frames, ambiguous, warnings, dataset.board, camera)
    return _trim_scan_lines(frames, dataset.board)


def _segment_dicts(cands: list, residuals=(), chosen: int | None = None) -> tuple[dict, ...]:
    out = []
    for i, (cost, obs) in enumerate(cands):
        d = {"points": obs.n_points, "centre_lidar_m": np.round(obs.points.mean(0), 4).tolist(),
             "length_m": round(float(np.ptp(obs.line.coordinates(obs.points[:, :2]))), 3),
             "camera_cue_cost": round(float(cost), 3)}
        if i < len(residuals):
            d.update({"rms_from_board_plane_mm": round(1000 * residuals[i][1], 1),
                      "inside_board": round(residuals[i][2], 3)})
        d["status"] = "chosen" if i == chosen else "rejected"
        out.append(d)
    return tuple(out)


def _trim_line(obs, T_camera_lidar: np.ndarray, T_camera_board: np.ndarray, board, cov: np.ndarray):
    """A laser segment cut to the camera's board outline (and its plane's band) under the extrinsic, the outline
    grown by ``LINE_TRIM_M`` and ``TRIM_SDS`` standard deviations of where the extrinsic (its covariance ``cov``)
    puts the segment's ends on the board."""
    P = np.column_stack([obs.points[:, :2], np.zeros(len(obs.points))])
    margin = LINE_TRIM_M + TRIM_SDS * _end_sd(P, T_camera_lidar, T_camera_board, cov)
    inside = inside_outline(P, T_camera_lidar, T_camera_board, board, margin + board.unknown_margin, OUTLINE_BAND_M)
    if inside.all() or inside.sum() < 5:
        return obs
    return observe_lidar_line(P[inside], obs.candidates)


def _trim_scan_lines(frames: list[FrameMeasurement], board) -> list[FrameMeasurement]:
    """Cut each frame's laser segment to the camera's board outline under the extrinsic the frames agree on
    (the minimal-solution selection, when it keeps a single candidate): the holder's hands and arms, in line
    with the board, leave the segment. Without a single candidate the segments stay as found."""
    from ..solvers.solution_selection import select_minimal  # 2D only (it loads scipy.optimize)

    used = [f for f in frames if f.usable]
    if len(used) < 3 or not board.size_known:
        return frames
    try:
        sel = select_minimal(used, board)
    except DegenerateLayoutError:
        return frames
    if len(sel.candidates) != 1:
        return frames
    return _cut_lines(frames, sel.candidates[0].T_camera_lidar, board)


def _cut_lines(frames: list[FrameMeasurement], T: np.ndarray, board) -> list[FrameMeasurement]:
    """Each usable frame's laser segment cut to the camera's board outline under ``T`` (:func:`_trim_line`), with
    ``T``'s covariance from the usable frames' planes (``solution_selection.plane_covariance``); the segments as
    they are where the planes leave it free."""
    from ..solvers.solution_selection import plane_covariance  # 2D only (it loads scipy.optimize)

    used = [f for f in frames if f.usable]
    cov = plane_covariance(T, used, max(pooled_range_noise_m([f.lidar for f in used]), 1e-5)) if used else None
    if cov is None:
        return frames
    return [replace(f, lidar=_trim_line(f.lidar, T, f.camera.T_camera_board, board, cov)) if f.usable else f
            for f in frames]


def _end_sd(P: np.ndarray, T_camera_lidar: np.ndarray, T_camera_board: np.ndarray, cov: np.ndarray) -> float:
    """The largest standard deviation (m), in the board's plane, of where ``T_camera_lidar`` (right-tangent
    covariance ``cov``) puts the two extreme points of the segment ``P`` on the board: ``q = T_board_camera T p``,
    ``dq / dxi = R_board_camera R [-[p]x, I]``."""
    along = P[:, :2] @ np.array([-P[:, 1].mean(), P[:, 0].mean()])  # azimuth order
    R = T_camera_board[:3, :3].T @ T_camera_lidar[:3, :3]
    sd = 0.0
    for p in P[[int(np.argmin(along)), int(np.argmax(along))]]:
        J = (R @ np.hstack([-skew(p), np.eye(3)]))[:2]
        sd = max(sd, float(np.sqrt(np.linalg.eigvalsh(J @ cov @ J.T)[-1])))
    return sd


@dataclass(frozen=True, eq=False)
class LidarSweeps:
    """A 3D LiDAR's sweeps by frame name (or, for each one that cannot be read, the reason), the static scene of
    those read, and each one's index among the scene's frames."""

    sweeps: dict
    scene: StaticScene
    scene_index: dict


def read_sweeps(frames, hints: Hints, timings: dict | None = None) -> LidarSweeps:
    """The 3D sweeps of ``frames`` (``FrameFiles``: their ``name`` and ``scan``) and the static scene of those read
    (``hints``: the region of interest, and whether to build the scene at all)."""
    timings = {} if timings is None else timings
    t0 = time.perf_counter()
    sweeps, _ = with_found_beams(dict(zip([f.name for f in frames], _read_every(read_sweep, [f.scan for f in frames]))))
    if hints.roi_min is not None or hints.roi_max is not None:
        sweeps = {n: s.kept(hints.in_roi(s.points)) if not isinstance(s, str) else s for n, s in sweeps.items()}
    good = [n for n, s in sweeps.items() if not isinstance(s, str)]
    if good and all(len(sweeps[n].points) and np.abs(sweeps[n].points[:, 2]).max() <= SCAN_LINE_Z_M for n in good):
        raise DatasetError(f"every return of the {len(good)} scans lies at z = 0: they are a 2D scanner's scan "
                           "lines, read as a 3D LiDAR's sweeps", hint="set lidar: 2d in dataset.yaml")
    _add_time(timings, "load_scans", time.perf_counter() - t0)
    t0 = time.perf_counter()
    if hints.static_scene:
        scene = build_static_scene([sweeps[n].points for n in good], [sweeps[n].ring for n in good])
    else:
        scene = StaticScene("none", StaticSceneParams(), note="not used (each frame judged alone)")
    _add_time(timings, "static_scene", time.perf_counter() - t0)
    return LidarSweeps(sweeps, scene, {n: i for i, n in enumerate(good)})


def _measure_sweeps_3d(dataset: Dataset, cams: list[tuple], camera: CameraModel, rngs: list[np.random.Generator],
                       params: SegmentationParams, hints: Hints, timings: dict, warnings: list[str],
                       workers: int, read: LidarSweeps) -> list[FrameMeasurement]:
    """Candidates per frame in its sweep, over the static scene (:func:`read_sweeps`), and the joint
    choice (module docstring of ``solvers.association``); without a consensus (fewer than 3 frames with
    candidates spanning 3D), each frame decides alone."""
    n = len(dataset.frames)
    sweeps, scene = [read.sweeps[f.name] for f in dataset.frames], read.scene
    cams, _ = _without_damaged_scans(cams, sweeps)
    if not dataset.board.size_known:
        w, h = dataset.board.judged_extent
        warnings.append(f"board.size is not given: the LiDAR's board returns are judged and trimmed by the "
                        f"pattern's extent and {100 * dataset.board.unknown_margin:.0f} cm on each side ({w:.2f} x "
                        f"{h:.2f} m), the border beyond the pattern kept as far as it stays in the pattern's plane; "
                        "give board.size in dataset.yaml (the backing board's) to trim to the board itself")
    if hints.static_scene and scene.note:
        warnings.append(f"static scene: {scene.note}")
    noted = [(f.name, s.ring_note) for f, s in zip(dataset.frames, sweeps) if not isinstance(s, str) and s.ring_note]
    if noted:
        warnings.append(f"{len(noted)} of {n} sweeps (the first {noted[0][0]}): {noted[0][1]}; read as sweeps "
                        "without one (each return's beam from its elevation where they fall into bands)")

    def search(k: int, j: int | None = None, rng: np.random.Generator | None = None
               ) -> tuple[list[BoardCandidate], list[str], str | None]:
        """Frame ``k``'s board candidates: the camera's board of image ``k`` looked for in sweep ``j`` (``k``)."""
        j = k if j is None else j
        cam_obs = cams[k][0]
        if cam_obs is None:
            return [], [], None
        t1 = time.perf_counter()
        s = sweeps[j]
        fg = scene.frame_foreground(read.scene_index[dataset.frames[j].name])
        try:
            cands, rejected = board_candidates(s.points, dataset.board, cam_obs, rngs[k] if rng is None else rng,
                                               params, fg)
        except MeasurementError as exc:
            return [], [], exc.message
        finally:
            _add_time(timings, "segmentation", time.perf_counter() - t1)
        if hints.initial_guess is not None:
            cands, off = _gate_by_guess(cands, cam_obs, hints)
            rejected = rejected + off
        return cands, rejected, None

    with ThreadPoolExecutor(max_workers=workers) as pool:
        found = list(pool.map(search, range(n)))
    if hints.initial_guess is not None:
        _not_inverted(found)
    t0 = time.perf_counter()

    def consensus(cams_: list[tuple], found_: list[tuple], warned: list[str], rng: np.random.Generator) -> tuple:
        return _consensus(cams_, [[c.observation for c in f[0]] for f in found_], warned, "board candidates",
                          lambda planes, poses, cands, ks: associate(
                              planes, poses, cands, dataset.board, rng, AssociationParams(),
                              [[1.0 / (1.0 + c.cue_cost) ** 2 for c in found_[k][0]] for k in ks]))

    assoc, choice = consensus(cams, found, warnings, rngs[-1])
    _add_time(timings, "association", time.perf_counter() - t0)
    if _unsettled(assoc):
        def shifted(pairs: list[tuple[int, int]], rng: np.random.Generator) -> Association | None:
            rs = rng.spawn(len(pairs) + 1)
            return consensus([cams[k] for k, _ in pairs], [search(k, j, r) for (k, j), r in zip(pairs, rs)], [],
                             rs[-1])[0]

        _not_shifted(dataset, cams, lambda j: not isinstance(sweeps[j], str), shifted, rngs[-1])
    frames, ambiguous = [], {}
    for k, frame in enumerate(dataset.frames):
        cam_obs, why = cams[k]
        cands, rejected, error = found[k]
        if cam_obs is None:
            frames.append(FrameMeasurement(frame.name, None, None, why))
        elif assoc is not None:
            frames.append(_consensus_frame(frame.name, cam_obs, cands, rejected, error, choice[k], assoc,
                                           dataset.board, params, (sweeps[k], scene)))
        else:
            frames.append(_alone_frame(frame.name, cam_obs, cands, rejected, error, dataset.board, params,
                                       ambiguous))
    if assoc is not None:
        frames = _trimmed_to_outlines(frames, assoc.T_camera_lidar, dataset.board, params,
                                      {f.name: len(found[k][0]) for k, f in enumerate(dataset.frames)})
    if ambiguous:
        frames = _resolve_ambiguous(frames, ambiguous, warnings, dataset.board, camera)
    return [_with_beam_fields(f, sweeps[k]) for k, f in enumerate(frames)]


def with_found_beams(sweeps: dict) -> tuple[dict, str | None]:
    """The sweeps (by frame name; a string: why one could not be read) read without a beam index (a KITTI .bin, an
    unorganised PCD, a ring field set aside) with each return's beam found from the returns' elevations over all
    of them (``lidar.beam_rings.sweeps_beams``: one set of beams, numbered alike in every sweep; the returns it
    gives none left out), so that they are measured and checked as sweeps with a ring field are (the static scene
    by beams, ring ends, per-ring terms, the scene's contours); where the elevations do not fall into beams (a
    rosette LiDAR's), the sweeps as read and why."""
    ringless = {n: s for n, s in sweeps.items() if not isinstance(s, str) and s.ring is None}
    if not ringless:
        return sweeps, None
    try:
        beams = sweeps_beams([s.points for s in ringless.values()])
    except ScanReadError as exc:
        return sweeps, exc.problem
    out = dict(sweeps)
    for n, s in ringless.items():
        ring = beams.rings_of(s.points)
        out[n] = replace(s, ring=ring).kept(ring >= 0)
    return out, None


def _read_or_reason(reader, path):
    """What ``reader`` reads from ``path``, or the reason it cannot (a damaged scan skips its frame)."""
    try:
        return reader(path)
    except ScanReadError as exc:
        return f"scan: {exc.message}"


def _read_every(reader, paths: list) -> list:
    """:func:`_read_or_reason` of each path; where none of several can be read, their one reason said once (points
    in millimetres, say), not frame by frame."""
    read = [_read_or_reason(reader, p) for p in paths]
    if len(read) > 1 and all(isinstance(r, str) for r in read):
        raise ScanReadError(f"none of the {len(read)} scans can be read; the first: {read[0]}")
    return read


def _without_damaged_scans(cams: list[tuple], scans: list) -> tuple[list[tuple], list[int]]:
    """The camera observations with frames whose scan could not be read made unusable (with the reason), and
    the indices of the frames whose scan was read."""
    cams = [(None, s) if isinstance(s, str) else c for c, s in zip(cams, scans)]
    return cams, [k for k, s in enumerate(scans) if not isinstance(s, str)]


def _in_sweep(points: np.ndarray, sweep: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each of ``points`` (taken from ``sweep``, exact coordinates) as its index in the sweep, and which were found.
    Only the sweep's points in their bounding box can match: a tree over those, not the sweep."""
    near = _near(sweep, points, 1e-6)
    if len(near) == 0:
        return np.zeros(len(points), dtype=np.int64), np.zeros(len(points), dtype=bool)
    from scipy.spatial import cKDTree  # here: scipy.spatial takes 0.3 s to import, unused from the cache

    dist, found = cKDTree(sweep[near]).query(points, distance_upper_bound=1e-6)
    ok = np.isfinite(dist)
    return near[np.where(ok, found, 0)], ok


def _near(sweep: np.ndarray, points: np.ndarray, grow: float) -> np.ndarray:
    """The indices of the sweep's points in ``points``' bounding box grown by ``grow`` (m)."""
    lo, hi = points.min(axis=0) - grow, points.max(axis=0) + grow
    near = np.flatnonzero((sweep[:, 0] >= lo[0]) & (sweep[:, 0] <= hi[0]))  # x first: one column of the sweep
    return near[np.all((sweep[near] >= lo) & (sweep[near] <= hi), axis=1)]


def _with_beam_fields(frame: FrameMeasurement, sweep) -> FrameMeasurement:
    """The frame with its board points' ring and intensity looked up in the sweep they came from (exact
    coordinates), for the range model's per-ring and reflectivity terms, and the ring ends that are no edges
    (:func:`_open_ends`)."""
    if not frame.usable or (sweep.ring is None and sweep.intensity is None):
        return frame
    idx, found = _in_sweep(frame.lidar.points, sweep.points)
    if not found.all():
        return frame
    lidar = replace(frame.lidar, rings=None if sweep.ring is None else sweep.ring[idx],
                    intensity=None if sweep.intensity is None else sweep.intensity[idx])
    if lidar.rings is not None and not lidar.is_scan_line:
        lidar = replace(lidar, open_ends=_open_ends(lidar, idx, sweep))
    return replace(frame, lidar=lidar)


def _open_ends(obs, idx: np.ndarray, sweep) -> np.ndarray:
    """Per board return (``obs``, at ``idx`` in ``sweep``): its ring's first or last on the board, with the ring's
    next firing beyond it in the board's plane band (``board_segmentation.noise_band``) yet not taken
    (``board_edges.open_ends``). The board's window is cut on the returns' positions, 1.5 cm beyond a board-sized
    rectangle: a range offset lays the returns on a plane further off, where the beams spread wider than the board,
    and the window cut the outermost (2-25 a frame on simulated HDL-64E boards 5 cm long in range), so that their
    rings seemed to end a step inside the edge (translation along the boards' normals biased, 0.7 of its sd). A
    hand or a wall in the board's plane goes on from it the same way."""
    # Only returns near the board can be its rings' next firings (1.5 azimuth steps of under 0.02 rad at its range):
    # a box grown by 0.05 rad of its farthest range, which spares testing the whole sweep (12 ms a 64-beam frame).
    near = _near(sweep.points, obs.points, 0.05 * float(np.max(np.linalg.norm(obs.points, axis=1))) + 0.1)
    near = near[np.isin(sweep.ring[near], np.unique(obs.rings)) & ~np.isin(near, idx)]
    at = near[noise_band(sweep.points[near], obs.plane, obs.points)]
    return open_ends(obs.points, obs.rings, sweep.points[at], sweep.ring[at])


CONSENSUS_FAILED = "the frames' joint choice of their boards failed: no extrinsic that enough frames'"


def _consensus(cams: list[tuple], candidates: list[list], warnings: list[str], what: str, choose):
    """The joint choice over the frames with a camera board (``choose(planes, poses, candidates, frame ids)``),
    and each such frame's :class:`FrameChoice`; (None, {}) with a warning when there is no consensus."""
    ks = [k for k, (c, _) in enumerate(cams) if c is not None]
    counts = [len(candidates[k]) for k in ks if candidates[k]]  # each frame's candidates, where it has some
    if len(counts) < 3:
        return None, {}
    try:
        assoc = choose([cams[k][0].plane for k in ks], [cams[k][0].T_camera_board for k in ks],
                       [candidates[k] for k in ks], ks)
    except DegenerateLayoutError as exc:
        if max(counts) == 1 and (isinstance(exc, NoHypothesisError) or len(counts) <= AssociationParams.min_frames):
            # No frame had a choice to make, and either the layout gave no extrinsic to test the candidates by,
            # or too few frames have one for the consensus to leave any out (it keeps all three or none): each
            # frame keeps its one, as the consensus would have; the solve's own checks judge them (a 2D answer's
            # segment ends on the outlines among them, which the consensus tests on rougher minimal roots).
            warnings.append(f"the frames' {what} were not checked against each other before solving "
                            f"({exc.problem}); each frame has one")
            return None, {}
        warnings.append(f"{CONSENSUS_FAILED} {what} agree on ({exc.problem}); each frame's is chosen from its own "
                        "cues")
        return None, {}
    return assoc, dict(zip(ks, assoc.choices))


def _unsettled(assoc: Association | None) -> bool:
    """Whether the frames' boards were chosen by no joint choice (it failed, or too few frames had a candidate to
    make one), or by one that kept only the three frames whose closed form (a scanner's minimal solution) any three
    boards fit."""
    return assoc is None or assoc.agreeing <= AssociationParams.min_frames


def _not_shifted(dataset: Dataset, cams: list[tuple], readable, choose, rng: np.random.Generator) -> None:
    """Where the frames' boards agree on no extrinsic (:func:`_unsettled`), refuse a folder whose scans are numbered
    a few frames off their images: each image's board looked for in the scan a frame later and a frame earlier
    (then two and three: ``SHIFTS``) and the joint choice made again (``choose(pairs, rng)``, the association of
    image ``k``'s board with scan ``j`` for each ``(k, j)``, or None); a shift that ``SHIFT_AGREEING`` of its
    pairs, and 4 or more, agree on is the folder's, not a failed choice (8 simulated VLP-16 frames, their scans
    renumbered by one, read UNTRUSTED with 5 frames 58-161 deg off and the choice blamed; a scanner's, refused as
    a layout that leaves the translation unobservable). ``readable(j)``: scan ``j`` was read."""
    names = [f.name for f in dataset.frames]
    for shift in SHIFTS:
        pairs = [(k, k + shift) for k in range(len(names)) if 0 <= k + shift < len(names)
                 and cams[k][0] is not None and readable(k + shift)]
        if len(pairs) < 4:
            continue
        assoc = choose(pairs, rng.spawn(1)[0])
        if assoc is None or not shift_agrees(assoc.agreeing, len(pairs)):
            continue
        (k, j), (frames, later) = pairs[0], shift_words(shift)
        image = relative_name(dataset.frames[k].image, dataset.root)
        scan = relative_name(dataset.frames[j].scan, dataset.root)
        raise DatasetError(
            f"the frames' LiDAR boards agree on no one extrinsic as the files are paired, but {assoc.agreeing} of "
            f"{len(pairs)} do with each image paired with the scan {frames} {later} ({image}'s board is in {scan}): "
            f"the scans are numbered {frames} off their images", path=dataset.root, hint=NUMBERING_HINT)


def relative_name(path, root) -> str:
    """``path`` as from ``root`` where it lies inside it (a rig's ``cam0/0001.png``), else its name."""
    try:
        return str(Path(path).relative_to(root))
    except ValueError:
        return Path(path).name


NUMBERING_HINT = ("renumber the scans (or the images) so that each NNNN pair was captured at one instant; lidarcam "
                  "extract pairs a bag's by their stamps")
# The share of a shift's pairs whose boards must agree for the scans to be read as numbered a frame off their images.
SHIFT_AGREEING = 2 / 3
# The numberings tried, nearest first: a frame off either way (a first frame dropped), then two and three (a
# folder whose scans began 2 frames after its images read UNTRUSTED, its boards' choice blamed).
SHIFTS = (1, -1, 2, -2, 3, -3)


def shift_words(shift: int) -> tuple[str, str]:
    """How far and which way a numbering is shifted, in words: ``("a frame", "later")``, ``("2 frames",
    "earlier")``."""
    return "a frame" if abs(shift) == 1 else f"{abs(shift)} frames", "later" if shift > 0 else "earlier"


def shift_agrees(agreeing: int, pairs: int) -> bool:
    """Whether ``agreeing`` of a shifted numbering's ``pairs`` read it as the files' own: more than the three any
    closed form fits, and ``SHIFT_AGREEING`` of them (a camera's and the LiDAR's boards, or two cameras')."""
    return agreeing > AssociationParams.min_frames and agreeing >= SHIFT_AGREEING * pairs


def _gate_by_guess(cands: list[BoardCandidate], cam_obs, hints: Hints) -> tuple[list[BoardCandidate], list[str]]:
    """The candidates whose planes, mapped through the initial guess, lie within its tolerance of the camera's
    board plane; the others with their reason."""
    kept, off = [], []

    def within(T: np.ndarray, c: BoardCandidate) -> tuple[bool, float, float]:
        angle, dist = plane_difference(c.observation.plane.transformed(T), cam_obs.plane)
        return angle <= hints.guess_angle_rad and abs(dist) <= hints.guess_distance_m, angle, dist

    for c in cands:
        ok, angle, dist = within(hints.initial_guess, c)
        if ok:
            kept.append(c)
        else:
            inverse = within(np.linalg.inv(hints.initial_guess), c)[0]
            off.append(f"outside the initial guess's tolerance ({np.degrees(angle):.1f} deg, {1000 * dist:+.0f} mm)"
                       + (f"{INVERSE_GUESS}" if inverse else ""))
    return kept, off


# A candidate off the initial guess yet within its inverse's tolerance says so; where no frame keeps a candidate and
# several say this, the guess is T_lidar_camera (:func:`_not_inverted`).
INVERSE_GUESS = ", within its inverse's"


def _not_inverted(found: list[tuple]) -> None:
    """Refuse an initial guess that no frame's LiDAR board lies within, where three or more lie within its
    inverse's (``found``: each frame's kept candidates, rejections and error)."""
    if any(cands for cands, _, _ in found):
        return
    inverted = sum(any(r.endswith(INVERSE_GUESS) for r in rejected) for _, rejected, _ in found)
    if inverted >= 3:
        raise DatasetError(f"no frame's LiDAR board lies within the initial guess's tolerance, but {inverted} lie "
                           "within its inverse's: the guess is T_lidar_camera",
                           hint="give T_camera_lidar, which maps LiDAR points into the camera: the guess inverted")


def _no_candidate_reason(board, rejected: list[str], error: str | None) -> str:
    if error is not None:
        return f"LiDAR board: {error}"
    detail = "; ".join(f"{n} {key}" for key, n in count_reasons(rejected).items()) or "none found"
    return (f"LiDAR board: no planar segment that fits inside the board's {board.extent[0]:.2f} x "
            f"{board.extent[1]:.2f} m where the camera puts it (planar pieces rejected: {detail})")


def _candidate_dicts(cands: list[BoardCandidate], residuals=(), chosen: int | None = None) -> tuple[dict, ...]:
    out = []
    for i, c in enumerate(cands):
        d = c.to_dict()
        if i < len(residuals):
            angle, dist, inside = residuals[i]
            d.update({"normal_residual_deg": round(float(np.degrees(angle)), 3),
                      "distance_residual_mm": round(1000 * dist, 1), "inside_board": round(inside, 3)})
        d["status"] = "chosen" if i == chosen else "rejected"
        out.append(d)
    return tuple(out)


def _consensus_frame(name: str, cam_obs, cands: list[BoardCandidate], rejected: list[str], error: str | None,
                     choice, assoc: Association, board, params: SegmentationParams,
                     sweep: tuple | None = None) -> FrameMeasurement:
    points = tuple(c.observation.points for c in cands)
    method = f"consensus of {assoc.agreeing} frames"
    if not cands:
        reason = _no_candidate_reason(board, rejected, error)
        return FrameMeasurement(name, cam_obs, None, reason, BoardDecision(method, (), None, reason, tuple(rejected)))
    decision = BoardDecision(method, _candidate_dicts(cands, choice.residuals, choice.chosen), choice.chosen,
                             choice.reason, tuple(rejected), points)
    if choice.chosen is None:
        return FrameMeasurement(name, cam_obs, None, f"LiDAR board: {choice.reason}", decision)
    obs = cands[choice.chosen].observation
    if sweep is not None:
        obs = _every_return_on(obs, *sweep, (assoc.T_camera_lidar, cam_obs.T_camera_board, board))
    return FrameMeasurement(name, cam_obs, obs, None, decision)


def _every_return_on(obs, sweep, scene: StaticScene, outline: tuple):
    """The chosen candidate with every return of its sweep in its plane's noise band along the beam
    (``board_segmentation.noise_band``, as the candidate's own points were gathered) that lies in the range
    image's cells that hold its points, or within the camera's board outline (``outline``: the consensus
    extrinsic, the camera's board pose and the board), whatever the static scene said of each return.

    The static scene chooses which piece is the board, and which cells it covers; not which of a cell's returns
    are measured. Where the board stands close in front of a surface (a table it stands on, a wall it leans on),
    the scene calls the returns whose range noise carries them within its margin of that surface background and
    keeps the others: a selection on the noise, which tilts the fitted plane. The returns of the board's own cells,
    in a band symmetric in range, undo it. Where the board rests at one place in most frames (a board waved about
    one pose and held still now and then), the scene takes the board itself for background there and whole cells
    of it go: on 9 simulated poses of that kind the LiDAR kept 309 of a frame's 502 board returns, holes in its
    middle. The camera says where the board is: returns in its outline (the pattern's, where board.size is not
    given) are the board's. Not beyond it: there the static scene is right more often (on the recorded VLP-16
    set, a few returns beside the boards, which pulled their edges; a small board's plate and table).

    Except the returns the scene called background within ``RESTORED_BEYOND_OUTLINE_M`` of the outline, where the
    sweep has beams: a range image's cell holds one return, so a board's own cells end at its last return, and the
    outline, drawn under the consensus extrinsic, falls a centimetre or two inside or outside the board's true
    edge. Where the scene took the board for background along one edge, that edge's returns were cut at the
    outline and the other edges' (foreground) were not: on a simulated OS1-64 bag of still poses about one place
    (its boards' beams from their elevations), the outline shifted 7 mm, the planes and ring ends 39 apart (d2,
    5 dof), 0.080 degree from the truth and CHECK; with them, 0.039 degree and OK. Returns the scene kept in front
    of it that the board's segmentation left out stay out: on the recorded VLP-16 set those are returns beside
    the boards, which pulled their edges (d2 against the planes 18 -> 31). Direction bins are a few returns
    wide: a board's own cells reach beyond its edge already. Not for a board of unknown size, whose outline is its
    pattern's and which has no edges to measure: beyond the pattern lie its plate and the table it stands on
    (small boards on a table under a dense spinning laser, 10 datasets: range terms that none had kept on 6 of
    them, the translation's error 1.3 -> 2.2 mm RMS)."""
    if not scene.usable:
        return obs

    def keys(at: np.ndarray) -> np.ndarray:  # the cells of the sweep's returns ``at`` (indices)
        return scene.cell_keys(sweep.points[at], None if sweep.ring is None else sweep.ring[at])

    idx, found = _in_sweep(obs.points, sweep.points)
    own = np.unique(keys(idx[found]))
    # The returns in the band, then those of them in the board's cells or its outline (every return's cell is a
    # whole sweep's work; the band's, a few thousand's).
    band = np.flatnonzero(noise_band(sweep.points, obs.plane, obs.points))
    T_camera_lidar, T_camera_board, board = outline
    P = sweep.points[band]
    inside = inside_outline(P, T_camera_lidar, T_camera_board, board, 0.0)
    if sweep.ring is not None and board.size is not None:  # the background just beyond the outline (docstring)
        beyond = inside_outline(P, T_camera_lidar, T_camera_board, board, RESTORED_BEYOND_OUTLINE_M) & ~inside
        inside[beyond] = ~scene.foreground(P[beyond], sweep.ring[band][beyond])
    take = band[np.isin(keys(band), own[own >= 0]) | inside]
    if len(take) <= obs.n_points:
        return obs
    return observe_lidar_board(sweep.points[take], obs.candidates)


def _alone_frame(name: str, cam_obs, cands: list[BoardCandidate], rejected: list[str], error: str | None, board,
                 params: SegmentationParams, ambiguous: dict) -> FrameMeasurement:
    points = tuple(c.observation.points for c in cands)
    if not cands:
        reason = _no_candidate_reason(board, rejected, error)
        return FrameMeasurement(name, cam_obs, None, reason,
                                BoardDecision("this frame alone", (), None, reason, tuple(rejected)))
    try:
        obs = decide_alone(cands, True, params)
    except AmbiguousBoardError as exc:
        ambiguous[name] = exc.candidates
        decision = BoardDecision("this frame alone", _candidate_dicts(cands), None, exc.message, tuple(rejected),
                                 points)
        return FrameMeasurement(name, cam_obs, None, f"LiDAR board: {exc.message}", decision)
    decision = BoardDecision("this frame alone", _candidate_dicts(cands, chosen=0), 0,
                             "the only candidate that agrees with the camera's board", tuple(rejected), points)
    return FrameMeasurement(name, cam_obs, obs, None, decision)


# Points of a chosen board farther than this outside the camera's board outline (under the consensus
# extrinsic) are the holder's hands and arms, or a stand: trimmed.
# The scene's background returns this far beyond the camera's board outline are the board's (``_every_return_on``):
# the consensus extrinsic (the candidates' planes in closed form) draws the outline 16 mm from the truth on the
# simulated bag there, 24 mm from the final estimate on the recorded VLP-16 set (82 mm on the Ouster set).
RESTORED_BEYOND_OUTLINE_M = 0.03
OUTLINE_TRIM_M = 0.05
OUTLINE_BAND_M = 0.10  # and this far from the camera's board plane
# A scan line's points farther than this outside the outline: a line holds no other check of where the board
# ends, and the hands at its edges, in line with it, tilt it. At 0.05 m, 12 of 80 simulated office frames kept
# such points and the 2D office's translation error was 1.13x the Cramer-Rao bound over 40 layouts (1.03 in
# the empty room); at 0.01 m, 1.02 (0.98 in the empty room).
LINE_TRIM_M = 0.01
# ... beyond TRIM_SDS standard deviations of where the extrinsic the cut is made under puts the segment's ends (the
# minimal solution of three boards, a few centimetres off): cut at 0.01 m alone, real ends of the board went, the
# segment ends then biased inward on one side, and 3 of 20 simulated 5-board scanner folders of the varied
# configuration read OK with the truth beyond their 99.9% region (d2 28-51; cut so, 4-8).
TRIM_SDS = 3.0


# The consensus extrinsic's residual scales are floored at these (its planes' fit can be closer than their noise).
CONSENSUS_FLOOR_M, CONSENSUS_FLOOR_RAD = 0.005, np.radians(0.2)


def _trimmed_to_outlines(frames: list[FrameMeasurement], T: np.ndarray, board, params: SegmentationParams,
                         n_candidates: dict) -> list[FrameMeasurement]:
    """Each usable frame's board returns cut to the camera's outline under the consensus extrinsic ``T``
    (:func:`_trim_to_outline`), the outline grown by ``OUTLINE_TRIM_M`` or, where ``T`` is less sure, by
    ``LINE_TRIM_M`` and ``TRIM_SDS`` standard deviations of where it puts the board's returns in its plane
    (:func:`consensus_covariance`), as a scan line's cut is. Boards that face the rig alike leave the consensus
    free along their planes: on 9 simulated poses of one board waved about one place it stood 81 mm off there, a
    cut 5 cm outside the outline took 40 mm off one side of every board, and the edges then put the extrinsic 0.3
    degrees off under an OK verdict (NEES 63; 5.5 so cut). Where the planes leave a direction free nothing is
    cut."""
    used = [f for f in frames if f.usable and not f.lidar.is_scan_line]
    cov = consensus_covariance(T, used)
    out, trim = [], {id(f) for f in used}
    for f in frames:
        if id(f) in trim:
            margin = np.inf if cov is None else max(OUTLINE_TRIM_M, LINE_TRIM_M + TRIM_SDS * _in_plane_sd(
                f.lidar.points, T, f.camera.T_camera_board, cov))
            f = replace(f, lidar=_trim_to_outline(f.lidar, T, f.camera.T_camera_board, board,
                                                   n_candidates.get(f.name, 1), params, margin))
        out.append(f)
    return out


def consensus_covariance(T: np.ndarray, frames: list[FrameMeasurement]) -> np.ndarray | None:
    """The covariance (6x6, right tangent) of ``T_camera_lidar`` that the frames' board planes give to first order:
    per frame the LiDAR board's centroid on the camera's plane (its distance) and its normal along the camera's
    (two angles), each weighed by its RMS over the frames (floored at ``CONSENSUS_FLOOR_M`` and
    ``CONSENSUS_FLOOR_RAD``); None where they leave a direction free."""
    if len(frames) < 3:
        return None
    R = T[:3, :3]
    rows_d, res_d, rows_a, res_a = [], [], [], []
    for f in frames:
        n_c, d_c = f.camera.plane.normal, f.camera.plane.distance
        c = f.lidar.points.mean(axis=0)
        n_l = R @ f.lidar.plane.normal
        n_l = n_l if n_l @ n_c > 0 else -n_l
        rows_d.append(n_c @ R @ np.hstack([-skew(c), np.eye(3)]))
        res_d.append(float(n_c @ (R @ c + T[:3, 3]) - d_c))
        # the normal's two angles: its turn about the camera plane's two in-plane axes
        u = np.cross(n_c, [1.0, 0.0, 0.0] if abs(n_c[0]) < 0.9 else [0.0, 1.0, 0.0])
        u /= np.linalg.norm(u)
        for a in (u, np.cross(n_c, u)):
            rows_a.append(np.hstack([-(a @ R @ skew(R.T @ n_l)), np.zeros(3)]))  # n_l = R Exp(dtheta) n_lidar
            res_a.append(float(a @ n_l))
    sd_d = max(float(np.sqrt(np.mean(np.square(res_d)))), CONSENSUS_FLOOR_M)
    sd_a = max(float(np.sqrt(np.mean(np.square(res_a)))), CONSENSUS_FLOOR_RAD)
    J = np.vstack([np.array(rows_d) / sd_d, np.array(rows_a) / sd_a])
    info = J.T @ J
    ev, V = np.linalg.eigh(info)
    if ev[0] <= 1e-9 * ev[-1]:
        return None
    return (V / ev) @ V.T


def _in_plane_sd(points: np.ndarray, T: np.ndarray, T_camera_board: np.ndarray, cov: np.ndarray) -> float:
    """The largest standard deviation (m), in the board's plane, of where ``T`` (covariance ``cov``) puts the
    board's returns ``points`` (LiDAR frame): at their centroid and their two farthest from it."""
    c = points.mean(axis=0)
    far = np.argsort(np.linalg.norm(points - c, axis=1))[-2:]
    R = T_camera_board[:3, :3].T @ T[:3, :3]
    sd = 0.0
    for p in np.vstack([c, points[far]]):
        J = (R @ np.hstack([-skew(p), np.eye(3)]))[:2]
        sd = max(sd, float(np.sqrt(np.linalg.eigvalsh(J @ cov @ J.T)[-1])))
    return sd


def _trim_to_outline(obs, T_camera_lidar: np.ndarray, T_camera_board: np.ndarray, board, n_candidates: int,
                     params: SegmentationParams, margin: float = OUTLINE_TRIM_M):
    """The observation cut to the camera's board outline (grown by ``margin``) under the extrinsic, and
    refitted robustly (the holder's points left in the plane band are outliers)."""
    inside = inside_outline(obs.points, T_camera_lidar, T_camera_board, board, margin + board.unknown_margin,
                            OUTLINE_BAND_M)
    if board.unknown_margin > 0 and inside.sum() >= params.min_points and not obs.is_scan_line:
        inside &= _border(obs.points, inside, T_camera_lidar, T_camera_board, board, params)
    if inside.all() or inside.sum() < params.min_points:
        return obs
    _, keep = robust_plane_fit(obs.points[inside])
    return observe_lidar_board(obs.points[inside][keep], n_candidates)


def _border(points: np.ndarray, inside: np.ndarray, T_camera_lidar: np.ndarray, T_camera_board: np.ndarray, board,
            params: SegmentationParams) -> np.ndarray:
    """A board of unknown size: its points in the pattern's extent, and the border beyond it as far as it stays
    in their plane (``board_segmentation.border_trim``); all True when the pattern holds too few points.

    Each point is placed on the board where its beam meets the board's plane, not where its range puts it: a
    return's range noise moves it across the board as well as off it at any incidence but square, so a cut by its
    own position would keep the returns whose noise carries them inwards at one edge and outwards at the other,
    and tilt the plane (by up to a degree on a board 18 cm wide at 1 cm noise)."""
    q = transform_points(T_inverse(T_camera_board) @ T_camera_lidar,
                         on_plane_along_beams(points, robust_plane_fit(points[inside])[0]))
    w, h = board.extent
    pattern = inside & np.all((q[:, :2] >= 0.0) & (q[:, :2] <= [w, h]), axis=1)
    if pattern.sum() < params.min_points:
        return np.ones(len(points), dtype=bool)
    plane, keep = robust_plane_fit(points[pattern])
    r = plane.signed_distances(points)
    sigma = float(np.sqrt(np.mean(r[pattern][keep] ** 2)))
    return border_trim(q[:, :2], r, (w, h), sigma)


# A 2D frame's ambiguous scan segment is chosen when exactly one lies within this RMS distance (m) of the
# camera's board plane under the clear frames' extrinsic.
SEGMENT_FIT_M = 0.05


def _resolve_ambiguous(frames: list[FrameMeasurement], ambiguous: dict, warnings: list[str], board,
                       camera: CameraModel) -> list[FrameMeasurement]:
    """Choose among a frame's candidate boards by agreement with the extrinsic of the clear frames.

    3D: needs at least 3 unambiguous frames whose normals span 3D. 2D: needs unambiguous frames whose
    minimal-solution selection leaves a single refined minimum. Otherwise those
    frames stay skipped.
    """
    clear = [f for f in frames if f.usable]
    scan_lines = bool(clear) and clear[0].lidar.is_scan_line
    try:
        if scan_lines:
            from ..solvers.solution_selection import refine_candidates, select_minimal

            ref, modes = refine_candidates(clear, board, camera, select_minimal(clear, board))
            if len(modes) != 1:
                return frames
            T_camera_lidar = ref.T_camera_lidar
        else:
            T_camera_lidar = solve_closed_form([f.camera.plane for f in clear], [f.lidar.plane for f in clear],
                                               allow_weak=True).T_camera_lidar
    except DegenerateLayoutError:
        return frames
    T_lidar_camera = np.linalg.inv(T_camera_lidar)
    out = []
    for f in frames:
        if f.name in ambiguous:
            if scan_lines:
                chosen = _choose_segment(ambiguous[f.name], f.camera.plane, T_camera_lidar)
            else:
                chosen = choose_by_prediction(ambiguous[f.name], f.camera.plane.transformed(T_lidar_camera))
            if chosen is not None:
                warnings.append(f"frame {f.name}: {len(ambiguous[f.name])} candidate boards; chose the one "
                                f"matching the extrinsic of the {len(clear)} unambiguous frames")
                f = replace(f, lidar=chosen, reason=None)
        out.append(f)
    return out


def _choose_segment(candidates: list, plane, T_camera_lidar: np.ndarray):
    """The one scan segment whose points lie on the camera's board plane under ``T_camera_lidar`` (RMS within
    ``SEGMENT_FIT_M``), or None if none or several do."""
    rms = [np.sqrt(np.mean(plane.signed_distances(transform_points(T_camera_lidar, c.points)) ** 2))
           for c in candidates]
    fits = [c for c, e in zip(candidates, rms) if e < SEGMENT_FIT_M]
    return fits[0] if len(fits) == 1 else None


def measure(dataset: Dataset | str | Path, rng: np.random.Generator | None = None,
            params: SegmentationParams = SegmentationParams(), hints: Hints = Hints(), cache: bool = False,
            timings: dict | None = None) -> Measurements:
    """Measure every frame of a dataset once, for :func:`solve` to take any number of times.

    Parameters
    ----------
    dataset : Dataset, str or Path
        A loaded :class:`Dataset` or its folder.
    rng : numpy.random.Generator, optional
        Drives the segmentation's RANSAC (a fixed seed when None).
    params : SegmentationParams
        The LiDAR board segmentation's settings.
    hints : Hints
        An initial guess and a region of interest, for scenes beyond automation.
    cache : bool
        Keep the measurements under the user's cache folder, keyed by the dataset files' content, the options and
        the generator's state: a second call with the same inputs reads them back (``source`` is ``cache``).
    timings : dict, optional
        Filled with the stage times (s).

    Returns
    -------
    Measurements

    Raises
    ------
    DatasetError
        A missing or corrupt file.
    """
    if not isinstance(dataset, Dataset):
        dataset = load_dataset(dataset)
    rng = np.random.default_rng(0) if rng is None else rng
    key, folder = "", None
    if cache:
        options = {"params": params, "hints": hints, "version": __version__, "revision": MEASUREMENT_REVISION,
                   **generator_key(rng)}
        if dataset.camera is not None and dataset.camera.source.startswith("refined"):  # measured again under it
            options["camera"] = dataset.camera.as_dict()
        key = dataset_key(dataset.root, [p for f in dataset.frames for p in (f.image, f.scan)], options)
        folder = cache_dir() / key
        if (folder / "measurements.json").is_file():
            try:
                m = load_measurements(folder)
                rng.spawn(len(dataset.frames) + 1)  # as measuring would have: later draws stay the same
                return replace(m, source="cache", dataset=str(dataset.root), key=key)
            except DatasetError:
                pass  # a damaged cache entry is measured again (and overwritten)
    camera, frames, warnings = measure_frames(dataset, rng, params, timings, hints=hints)
    m = Measurements(camera, dataset.board, dataset.lidar, tuple(frames), tuple(warnings), str(dataset.root),
                     "measured", key)
    if folder is not None:
        try:
            save_measurements(folder, m)
        except OSError as exc:
            m = replace(m, warnings=m.warnings + (f"the measurement cache {folder} is not writable ({exc})",))
    return m
