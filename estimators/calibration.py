"""The calibration pipeline: dataset -> per-frame measurements -> solver -> result (and its JSON)."""
from __future__ import annotations

import importlib
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Callable

import cv2
import numpy as np
from scipy.spatial import cKDTree
from threadpoolctl import threadpool_limits

from geometry.camera import CameraModel
from geometry.planes import fit_plane_pca, on_plane_along_beams, plane_difference
from geometry.rotations import T_inverse, quat_xyzw_from_R, transform_points

from . import __version__
from .camera.board_pose import estimate_board_pose, reobserve
from .camera.charuco import MIN_CHARUCO_CORNERS
from .camera.corners import detect_corners
from .camera.detection import CornerDetection
from .camera.intrinsics import calibrate_intrinsics
from .errors import (AmbiguousBoardError, AmbiguousOrientationError, DatasetError, DegenerateLayoutError,
                     ImageReadError, LidarcamError, MeasurementError, PosteriorSkippedError, ScanReadError)
from .io.dataset import Dataset, load_dataset
from .io.measurement_store import Measurements, cache_dir, dataset_key, load_measurements, save_measurements
from .io.image_io import read_gray
from .io.input_files import load_json, regular_file
from .io.output import write_json_atomic, write_npz_atomic
from .io.pointcloud_io import read_scan_2d, read_sweep
from .lidar.board_segmentation import (BoardCandidate, SegmentationParams, board_candidates, border_trim,
                                       choose_by_prediction, decide_alone, noise_band, robust_plane_fit)
from .lidar.scan_segmentation import ScanSegmentationParams, scan_candidates
from .lidar.static_scene import StaticScene, StaticSceneParams, build_static_scene
from .measurements import (BoardDecision, FrameMeasurement, count_reasons, observe_lidar_board,
                           observe_lidar_line)
from .solvers.association import Association, AssociationParams, associate, associate_lines, inside_outline
from .solvers.closed_form import describe_direction, normal_spread, solve_closed_form
from .solvers.intrinsics_refinement import IntrinsicsFit, refine_intrinsics
from .solvers.posterior import Posterior, PosteriorOptions, sample_posterior
from .solvers.refinement import Refinement, RefinementOptions, contradiction
from .solvers.refinement import refine as refine_graph

if TYPE_CHECKING:  # the 2D solvers are imported where they are used (they load scipy.optimize)
    from .solvers.solution_selection import MinimalSelection

INITS = ("closed-form", "minimal-lower-bound", "minimal-min-residual")
# Part of the measurement cache's key: raised when what a measurement holds changes within a version, so that no
# cache entry from before is taken for a new one (2: the tilts of boards ambiguous in their orientation).
MEASUREMENT_REVISION = 3
REFINES = ("factor-graph", "none")
# 2D: a second minimum holding at least this share of the posterior mass makes the result ambiguous: the printed
# result begins with it and ``lidarcam calibrate --strict`` exits with EXIT_AMBIGUOUS.
AMBIGUOUS_MASS = 0.05
EXIT_AMBIGUOUS = 3
CONVENTION = ("T_camera_lidar maps LiDAR points into the camera frame: p_camera = R p_lidar + t. "
              "LiDAR x forward, y left, z up; camera x right, y down, z forward (OpenCV).")
COVARIANCE_CONVENTION = ("6x6 covariance of xi = [rotation (rad); translation (m)] in GTSAM's Pose3 tangent: "
                         "T_true = T_hat * Exp(xi), so both parts are along the LiDAR's axes")


@dataclass(frozen=True, eq=False)
class Hints:
    """Optional help for scenes beyond automation; never a factor, only a gate on the LiDAR candidates.

    ``initial_guess``: a rough ``T_camera_lidar``; a candidate whose plane, mapped through it, differs from the
    camera's board plane by more than ``guess_angle_rad`` or ``guess_distance_m`` is rejected.
    ``roi_min`` / ``roi_max``: a box in the LiDAR frame (m) outside which points are ignored.
    ``static_scene``: build the background model from all frames (default) or judge each frame alone."""

    initial_guess: np.ndarray | None = None
    guess_angle_rad: float = float(np.deg2rad(10.0))
    guess_distance_m: float = 0.30
    roi_min: np.ndarray | None = None
    roi_max: np.ndarray | None = None
    static_scene: bool = True

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
            x, y, z, roll, pitch, yaw = (float(v) for v in values)
        except ValueError:
            raise DatasetError(f"--initial-guess {' '.join(values)!r} is not six numbers",
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
        T = np.asarray(T, dtype=float)
    except (ValueError, KeyError, TypeError, OSError, UnicodeDecodeError) as exc:
        raise DatasetError(f"initial guess unreadable ({type(exc).__name__}: {exc})", path=path,
                           hint="give a calibration.json or a 4x4 matrix") from None
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise DatasetError(f"initial guess is not a finite 4x4 matrix (shape {T.shape})", path=path,
                           hint="give a calibration.json or a 4x4 matrix")
    R = T[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-3) or np.linalg.det(R) < 0:
        raise DatasetError("initial guess is not a rigid transform (its rotation is not orthonormal)", path=path,
                           hint="give T_camera_lidar as a 4x4 rigid transform")
    return T

@dataclass(frozen=True, eq=False)
class CalibrationResult:
    """The estimate and everything a reader needs to judge it; frames keep their measurements.

    ``covariance``, ``samples``, ``std_rotation_deg``, ``std_translation_mm`` and ``diagnostics`` are derived from
    these; ``report(out)`` writes ``report.html`` and ``to_dict()`` gives ``calibration.json``'s content.

    Attributes
    ----------
    T_camera_lidar : numpy.ndarray
        4x4, maps LiDAR points into the camera frame (``p_camera = R p_lidar + t``).
    init, refine : str
        The initial solver and the refinement used.
    frames : tuple of FrameMeasurement
        Every frame, used or skipped (with its reason).
    camera : CameraModel
        The camera model used (given, or calibrated from the images).
    normal_singular_values : numpy.ndarray
        Singular values of the used frames' stacked camera normals (their spread).
    weakest_direction_camera : numpy.ndarray
        The direction those normals constrain least, in the camera frame.
    dataset : str
        The dataset's name.
    warnings : tuple of str
        Everything that limits trust in the result, most important first.
    timings_s : dict
        Stage times (s).
    plane_residuals : dict
        Per frame: the normal angle (rad) and distance (m) between the camera's and the LiDAR's plane.
    refinement : Refinement or None
        The factor graph's solution and Laplace covariance.
    posterior : Posterior or None
        The posterior samples and their summary.
    selection : MinimalSelection or None
        2D: how the minimal solutions were chosen.
    modes : tuple
        2D: the refined minima that hold posterior mass, the chosen one first.
    measurements_source : str
        ``measured``, ``cache`` or a measurements file.
    intrinsics_refinement : IntrinsicsFit or None
        With ``RefinementOptions.refine_intrinsics``: the intrinsics given and refined, and the boards'
        overdispersion under each.
    """

    T_camera_lidar: np.ndarray
    init: str
    refine: str
    frames: tuple[FrameMeasurement, ...]
    camera: CameraModel
    normal_singular_values: np.ndarray
    weakest_direction_camera: np.ndarray
    dataset: str
    warnings: tuple[str, ...] = ()
    timings_s: dict = field(default_factory=dict)
    plane_residuals: dict = field(default_factory=dict)  # name -> (normal angle rad, distance m)
    refinement: Refinement | None = None
    posterior: Posterior | None = None
    selection: MinimalSelection | None = None  # 2D LiDAR: how the minimal solutions were chosen
    # 2D LiDAR: the refined minima that hold posterior mass (``solution_selection.Mode``), the chosen one first;
    # more than one means the data do not decide between them.
    modes: tuple = ()
    # Where the measurements came from: "measured" (images and scans read now), "cache" or a measurements file.
    measurements_source: str = "measured"
    # The intrinsics refined with the extrinsic (``--refine-intrinsics``; ``camera`` is then the refined model).
    intrinsics_refinement: IntrinsicsFit | None = None

    @property
    def covariance(self) -> np.ndarray | None:
        """6x6 covariance in GTSAM's right tangent (``T_true = T_hat Exp(xi)``, ``xi = [rot; trans]``): the
        posterior samples' when sampled, else the Laplace one (the factor graph's marginal)."""
        if self.posterior is not None:
            return self.posterior.covariance
        return self.covariance_laplace

    @property
    def samples(self) -> np.ndarray | None:
        """Posterior samples (M x 6) of the tangent offset ``xi`` (``T_true = T_hat Exp(xi)``), or None."""
        return None if self.posterior is None else self.posterior.xi

    @property
    def diagnostics(self) -> dict:
        """Noise levels, consistency test, MCMC diagnostics and timings, as written to calibration.json."""
        d = self.to_dict()
        return {k: d[k] for k in ("noise", "consistency", "posterior", "timings_s", "warnings") if k in d}

    @property
    def covariance_laplace(self) -> np.ndarray | None:
        return None if self.refinement is None else self.refinement.covariance

    @property
    def std_rotation_deg(self) -> np.ndarray | None:
        """Standard deviations of the rotation about the LiDAR's x, y, z axes (degrees)."""
        c = self.covariance
        return None if c is None else np.degrees(np.sqrt(np.diag(c)[:3]))

    @property
    def std_translation_mm(self) -> np.ndarray | None:
        """Standard deviations of the translation along the LiDAR's x, y, z axes (millimetres)."""
        c = self.covariance
        return None if c is None else 1000 * np.sqrt(np.diag(c)[3:])

    @property
    def std_translation_camera_mm(self) -> np.ndarray | None:
        """Standard deviations of the entries of ``t`` in ``T_camera_lidar`` (camera axes, millimetres)."""
        c = self.covariance
        if c is None:
            return None
        R = self.T_camera_lidar[:3, :3]
        return 1000 * np.sqrt(np.diag(R @ c[3:, 3:] @ R.T))

    def report(self, out_dir: str | Path) -> Path:
        """Write ``OUT/report.html`` and its figures (needs the dataset folder this result came from)."""
        from .analysis.report import write_report
        from .io.dataset import load_dataset

        return write_report(self, load_dataset(self.dataset), out_dir)

    @property
    def frames_used(self) -> int:
        dropped = {f.name for f in self.refinement.frames if f.dropped} if self.refinement else set()
        return sum(f.usable and f.name not in dropped for f in self.frames)

    @property
    def condition_number(self) -> float:
        s = self.normal_singular_values
        return float(s[0] / s[-1]) if s[-1] > 0 else float("inf")

    def _uncertainty_dict(self) -> dict:
        ref = self.refinement
        if ref is None:
            return {"covariance": None,
                    "covariance_note": "no covariance without refinement (refine: none)"}
        post = self.posterior
        sampled = {"covariance_laplace": ref.covariance.tolist(), "intervals": post.summary(),
                   "credible_regions": post.regions(),
                   "posterior": {**post.diagnostics(), "file": "posterior.npz"}} if post is not None else {
            "covariance_note": "Laplace approximation (no posterior samples were drawn)"}
        return {
            "covariance": self.covariance.tolist(),
            "covariance_convention": COVARIANCE_CONVENTION,
            **sampled,
            "std": {"rotation_deg_about_lidar_xyz": self.std_rotation_deg.tolist(),
                    "translation_mm_along_lidar_xyz": self.std_translation_mm.tolist(),
                    "translation_mm_of_t_camera_xyz": self.std_translation_camera_mm.tolist()},
            "noise": {"corner_noise_px": ref.corner_noise_px, "corner_residual_px": ref.corner_residual_px,
                      "range_noise_m": ref.range_noise_m, "plane_floor_m": ref.plane_floor_m},
            "consistency": {"variance_factor": ref.variance_factor, "dof": ref.consistency_dof,
                            "p_value": ref.consistency_p},
            "iterations": ref.iterations,
            "lidar_range_model": (ref.range_model.to_dict() if ref.range_model is not None else
                                  {"requested": "none", "chosen": "none", "reason": "not requested", "terms": []}),
            "board_edges": ref.edges if ref.edges is not None else {"used": False},
            "contradicted": self.contradicted,
        }

    @property
    def alternatives(self) -> tuple:
        """2D LiDAR: the other minima that hold posterior mass (empty when the answer is unambiguous)."""
        return tuple(self.modes[1:])

    @property
    def contradicted(self) -> str | None:
        """Why the answer cannot be trusted as its intervals say (``refinement.contradiction``: the boards'
        planes and their edges disagree far beyond their noise), or None. The printed result begins with it, and
        ``--strict`` exits non-zero."""
        return contradiction(self.refinement) if self.refinement is not None else None

    @property
    def ambiguous(self) -> bool:
        """A second minimum holds at least ``AMBIGUOUS_MASS`` of the posterior mass: the printed result starts
        with it, and ``--strict`` exits non-zero."""
        return any(m.mass >= AMBIGUOUS_MASS for m in self.modes[1:])

    def _minimal_dict(self) -> dict:
        sel = self.selection
        if sel is None:
            return {}
        return {"minimal_solutions": {
            "method": sel.method, "triples": sel.n_triples, "solutions": sel.n_solutions,
            "inside_board_extent": sel.n_inside_extent, "clusters": sel.n_clusters,
            "candidates_refined": len(sel.candidates), "cost_threshold": sel.threshold,
            "candidate_costs": [c.cost for c in sel.candidates], "degenerate_triples": list(sel.degenerate_triples),
            "weak_triples": list(sel.weak_triples), "multistart_fallback": sel.fallback, "seconds": sel.seconds,
            "max_sensor_separation_m": sel.max_separation_m, "unphysical_solutions": sel.n_unphysical},
            "modes": [{"T_camera_lidar": m.T_camera_lidar.tolist(), "posterior_mass": m.mass,
                       "covariance": m.refinement.covariance.tolist(), "refined_cost": m.cost,
                       "outline_cost": m.outline_cost, "evidence": m.evidence} for m in self.modes],
            "ambiguous": len(self.modes) > 1, "ambiguous_5_percent": self.ambiguous}

    def to_dict(self) -> dict:
        R, t = self.T_camera_lidar[:3, :3], self.T_camera_lidar[:3, 3]
        fits = {f.name: f for f in self.refinement.frames} if self.refinement else {}
        axis, advice = describe_direction(self.weakest_direction_camera)
        return {
            "tool": "lidarcam", "version": __version__, "dataset": self.dataset,
            "convention": CONVENTION,
            "T_camera_lidar": self.T_camera_lidar.tolist(),
            "quaternion_xyzw": quat_xyzw_from_R(R).tolist(),
            "translation_m": t.tolist(),
            "init": self.init, "refine": self.refine,
            "frames_used": self.frames_used, "frames_total": len(self.frames),
            **self._uncertainty_dict(),
            "frames": [_frame_dict(f, self.plane_residuals.get(f.name), fits.get(f.name)) for f in self.frames],
            "layout": {
                "normal_singular_values": self.normal_singular_values.tolist(),
                "condition_number": self.condition_number,
                "weakest_direction_camera": self.weakest_direction_camera.tolist(),
                "weakest_direction_words": f"{axis}: to constrain it further, {advice}",
            },
            **self._minimal_dict(),
            "intrinsics": self.camera.as_dict(),
            **({"intrinsics_refinement": self.intrinsics_refinement.to_dict()}
               if self.intrinsics_refinement is not None else {}),
            "warnings": list(self.warnings),
            "measurements_source": self.measurements_source,
            "timings_s": self.timings_s,
        }


def plane_residuals(T_camera_lidar: np.ndarray, frames: list[FrameMeasurement]) -> dict:
    """Per used frame: angle (rad) between the camera normal and the mapped LiDAR normal, and the
    difference of the plane distances (m), under ``T_camera_lidar``."""
    out = {}
    for f in frames:
        if f.usable and f.lidar.is_scan_line:
            # A laser line: the angle by which it leaves the board's plane, and its points' mean distance to it.
            direction = T_camera_lidar[:3, :3] @ np.append(f.lidar.line.direction, 0.0)
            dist = float(np.mean(_plane_distances(f.lidar.points, f.camera.plane, T_camera_lidar)))
            out[f.name] = (float(np.arcsin(min(abs(direction @ f.camera.plane.normal), 1.0))), dist)
        elif f.usable:
            out[f.name] = plane_difference(f.lidar.plane.transformed(T_camera_lidar), f.camera.plane)
    return out


def _frame_dict(f: FrameMeasurement, residual: tuple[float, float] | None = None, fit=None) -> dict:
    used = f.usable and not (fit is not None and fit.dropped)
    reason = f.reason if fit is None or not fit.dropped else f"dropped as an outlier: {fit.outlier}"
    d = {"name": f.name, "used": used, "reason": reason,
         "board_points": f.lidar.n_points if f.lidar else 0,
         "plane_rms_m": f.lidar.plane_rms_m if f.lidar else None,
         "corner_rms_px": f.camera.reprojection_rms_px if f.camera else None,
         "corner_detector": f.camera.detector if f.camera else None}
    if residual is not None:
        d["normal_residual_deg"] = float(np.degrees(residual[0]))
        d["distance_residual_m"] = residual[1]
    if fit is not None:
        d["plane_chi2"] = fit.plane_chi2
        d["consistency_chi2"] = fit.consistency_chi2
        d["plane_dof"] = fit.plane_dof
        d["robust_weight"] = fit.weight
        d["outlier"] = fit.outlier
    if f.camera is not None:
        d["camera_plane"] = {"normal": f.camera.plane.normal.tolist(), "distance_m": f.camera.plane.distance}
    if f.lidar is not None:
        d["lidar_plane"] = {"normal": f.lidar.plane.normal.tolist(), "distance_m": f.lidar.plane.distance}
    if f.decision is not None:
        d["lidar_board_choice"] = f.decision.to_dict()
    return d


_TIMING_LOCK = threading.Lock()


def _add_time(timings: dict, key: str, seconds: float) -> None:
    with _TIMING_LOCK:
        timings[key] = timings.get(key, 0.0) + seconds


def _detect(frame, board, timings) -> tuple[tuple[int, int] | None, CornerDetection | str | None]:
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
                   detections: dict | None = None, board_poses: dict | None = None
                   ) -> tuple[CameraModel, list[FrameMeasurement], list[str]]:
    """Detect the board in every frame, in the image and in the scan; frames that fail keep a reason.

    3D: the static scene of all sweeps, every frame's board candidates in front of it, and the choice of one
    candidate per frame by the extrinsic most frames agree with (``solvers.association``). 2D: each scan's
    board segment, with the other scans as the static background. ``detections``: the images' corners already
    found (frame name -> what ``_detect`` returns; a rig's cameras are searched once); ``board_poses``: the board
    poses already estimated from them (frame name -> ``estimate_board_pose``'s result, by this dataset's camera)."""
    # One worker budget: frames run in ``workers`` threads, each with one OpenCV thread and one BLAS thread
    # (their own pools on top of ours would oversubscribe the cores).
    with threadpool_limits(1 if workers > 1 else None):
        return _measure_frames(dataset, rng, params, timings, workers, hints, detections, board_poses)


def _measure_frames(dataset: Dataset, rng: np.random.Generator, params: SegmentationParams, timings: dict | None,
                    workers: int, hints: Hints, detections: dict | None = None, board_poses: dict | None = None
                    ) -> tuple[CameraModel, list[FrameMeasurement], list[str]]:
    timings = {} if timings is None else timings
    with ThreadPoolExecutor(max_workers=1) as ahead:
        # A 3D dataset's sweeps are read and its static scene built (they need no camera) while the images
        # are searched for the pattern, in a thread of their own: the static scene's build is otherwise a
        # stage that keeps one core idle.
        sweeps = ahead.submit(_sweeps_and_scene, dataset, hints, timings) if dataset.lidar != "2d" else None
        return _measure_frames_with(dataset, rng, params, timings, workers, hints, sweeps, detections, board_poses)


def _measure_frames_with(dataset: Dataset, rng: np.random.Generator, params: SegmentationParams, timings: dict,
                         workers: int, hints: Hints, sweeps_ahead, found: dict | None = None,
                         board_poses: dict | None = None) -> tuple[CameraModel, list[FrameMeasurement], list[str]]:
    """:func:`_measure_frames` given the future of :func:`_sweeps_and_scene` (None for a 2D dataset)."""
    warnings: list[str] = []
    cv_threads = cv2.getNumThreads()
    cv2.setNumThreads(1 if workers > 1 else cv_threads)
    try:
        with ThreadPoolExecutor(max_workers=workers) as pool:
            detections = list(pool.map(lambda f: found[f.name] if found and f.name in found else
                                       _detect(f, dataset.board, timings), dataset.frames))
    finally:
        cv2.setNumThreads(cv_threads)
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
    frame_rngs = rng.spawn(len(dataset.frames) + 1)
    if dataset.lidar == "2d":
        frames = _measure_scans_2d(dataset, cams, camera, frame_rngs[-1], params, timings, warnings, workers,
                                   alternatives)
    else:
        frames = _measure_sweeps_3d(dataset, cams, camera, frame_rngs, params, hints, timings, warnings, workers,
                                    sweeps_ahead.result())
    return camera, frames, warnings


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
    read = [_read_or_reason(read_scan_2d, f.scan) for f in dataset.frames]
    cams, good = _without_damaged_scans(cams, read)
    scans_2d = [xy if not isinstance(xy, str) else np.zeros((0, 2)) for xy in read]
    _add_time(timings, "load_scans", time.perf_counter() - t0)
    trees = {k: cKDTree(scans_2d[k]) for k in good}
    scene = build_static_scene([scans_2d[k] for k in good])
    if scene.note and len(scans_2d) >= scene.params.min_frames:
        warnings.append(f"static scene: {scene.note}")
    seg_params = ScanSegmentationParams(max_sensor_separation_m=params.max_sensor_separation_m)

    def search(k: int) -> tuple[list, str | None, list]:
        # an ambiguous board's tilts put it at one place: either finds its segments (outside the consensus)
        cam_obs = alternatives[k][0] if k in alternatives and k in good else cams[k][0]
        if cam_obs is None:
            return [], None, []
        t1 = time.perf_counter()
        static: list = []
        try:
            return scan_candidates(scans_2d[k], dataset.board, cam_obs, seg_params,
                                   [t for j, t in trees.items() if j != k],
                                   scene.frame_foreground(good.index(k)), static), None, static
        except MeasurementError as exc:
            return [], exc.message, []
        finally:
            _add_time(timings, "segmentation", time.perf_counter() - t1)

    with ThreadPoolExecutor(max_workers=workers) as pool:
        searched = list(pool.map(search, range(len(dataset.frames))))
    t0 = time.perf_counter()
    # The consensus also sees the segments judged static (boards held at one place in several frames look
    # static); without a consensus each frame decides from its moving segments alone.
    joint = [cands + sorted(static, key=lambda c: c[0]) for cands, _, static in searched]
    assoc, choice = _consensus(cams, [[obs for _, obs in c] for c in joint], warnings, "scan segments",
                               lambda planes, poses, cands, _: associate_lines(planes, poses, cands, dataset.board,
                                                                                rng))
    _add_time(timings, "association", time.perf_counter() - t0)
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
            lid = None if c.chosen is None else _trim_line(cands[c.chosen][1], assoc.T_camera_lidar,
                                                           cam_obs.T_camera_board, dataset.board)
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


def _trim_line(obs, T_camera_lidar: np.ndarray, T_camera_board: np.ndarray, board):
    """A laser segment cut to the camera's board outline (and its plane's band) under the extrinsic."""
    P = np.column_stack([obs.points[:, :2], np.zeros(len(obs.points))])
    inside = inside_outline(P, T_camera_lidar, T_camera_board, board, LINE_TRIM_M + board.unknown_margin,
                            OUTLINE_BAND_M)
    if inside.all() or inside.sum() < 5:
        return obs
    return observe_lidar_line(P[inside], obs.candidates)


def _trim_scan_lines(frames: list[FrameMeasurement], board) -> list[FrameMeasurement]:
    """Cut each frame's laser segment to the camera's board outline under the extrinsic the frames agree on
    (the minimal-solution selection, when it keeps a single candidate): the holder's hands and arms, in line
    with the board, leave the segment. Without a single candidate the segments stay as found."""
    from .solvers.solution_selection import select_minimal  # 2D only (it loads scipy.optimize)

    used = [f for f in frames if f.usable]
    if len(used) < 3 or not board.size_known:
        return frames
    try:
        sel = select_minimal(used, board)
    except DegenerateLayoutError:
        return frames
    if len(sel.candidates) != 1:
        return frames
    T = sel.candidates[0].T_camera_lidar
    out = []
    for f in frames:
        if f.usable:
            f = replace(f, lidar=_trim_line(f.lidar, T, f.camera.T_camera_board, board))
        out.append(f)
    return out


def _sweeps_and_scene(dataset: Dataset, hints: Hints, timings: dict) -> tuple[list, StaticScene]:
    """A 3D dataset's sweeps (or, for each one that cannot be read, the reason) and the static scene of those
    read (``hints``: the region of interest, and whether to build the scene at all)."""
    t0 = time.perf_counter()
    sweeps = [_read_or_reason(read_sweep, f.scan) for f in dataset.frames]
    if hints.roi_min is not None or hints.roi_max is not None:
        sweeps = [_cropped(s, hints.in_roi(s.points)) if not isinstance(s, str) else s for s in sweeps]
    good = [s for s in sweeps if not isinstance(s, str)]
    _add_time(timings, "load_scans", time.perf_counter() - t0)
    t0 = time.perf_counter()
    if hints.static_scene:
        scene = build_static_scene([s.points for s in good], [s.ring for s in good])
    else:
        scene = StaticScene("none", StaticSceneParams(), note="not used (each frame judged alone)")
    _add_time(timings, "static_scene", time.perf_counter() - t0)
    return sweeps, scene


def _measure_sweeps_3d(dataset: Dataset, cams: list[tuple], camera: CameraModel, rngs: list[np.random.Generator],
                       params: SegmentationParams, hints: Hints, timings: dict, warnings: list[str],
                       workers: int, sweeps_and_scene: tuple[list, StaticScene]) -> list[FrameMeasurement]:
    """Candidates per frame in its sweep, over the static scene (:func:`_sweeps_and_scene`), and the joint
    choice (module docstring of ``solvers.association``); without a consensus (fewer than 3 frames with
    candidates spanning 3D), each frame decides alone."""
    n = len(dataset.frames)
    sweeps, scene = sweeps_and_scene
    cams, good = _without_damaged_scans(cams, sweeps)
    if not dataset.board.size_known:
        w, h = dataset.board.judged_extent
        warnings.append(f"board.size is not given: the LiDAR's board returns are judged and trimmed by the "
                        f"pattern's extent and {100 * dataset.board.unknown_margin:.0f} cm on each side ({w:.2f} x "
                        f"{h:.2f} m), the border beyond the pattern kept as far as it stays in the pattern's plane; "
                        "give board.size in dataset.yaml (the backing board's) to trim to the board itself")
    if hints.static_scene and scene.note:
        warnings.append(f"static scene: {scene.note}")

    def search(k: int) -> tuple[list[BoardCandidate], list[str], str | None]:
        cam_obs = cams[k][0]
        if cam_obs is None:
            return [], [], None
        t1 = time.perf_counter()
        s = sweeps[k]
        fg = scene.frame_foreground(good.index(k))
        try:
            cands, rejected = board_candidates(s.points, dataset.board, cam_obs, rngs[k], params, fg)
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
    t0 = time.perf_counter()
    assoc, choice = _consensus(
        cams, [[c.observation for c in f[0]] for f in found], warnings, "board candidates",
        lambda planes, poses, cands, ks: associate(planes, poses, cands, dataset.board, rngs[-1], AssociationParams(),
                                                   [[1.0 / (1.0 + c.cue_cost) ** 2 for c in found[k][0]] for k in ks]))
    _add_time(timings, "association", time.perf_counter() - t0)
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
    if ambiguous:
        frames = _resolve_ambiguous(frames, ambiguous, warnings, dataset.board, camera)
    return [_with_beam_fields(f, sweeps[k]) for k, f in enumerate(frames)]


def _read_or_reason(reader, path):
    """What ``reader`` reads from ``path``, or the reason it cannot (a damaged scan skips its frame)."""
    try:
        return reader(path)
    except ScanReadError as exc:
        return f"scan: {exc.message}"


def _without_damaged_scans(cams: list[tuple], scans: list) -> tuple[list[tuple], list[int]]:
    """The camera observations with frames whose scan could not be read made unusable (with the reason), and
    the indices of the frames whose scan was read."""
    cams = [(None, s) if isinstance(s, str) else c for c, s in zip(cams, scans)]
    return cams, [k for k, s in enumerate(scans) if not isinstance(s, str)]


def _in_sweep(points: np.ndarray, sweep: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each of ``points`` (taken from ``sweep``, exact coordinates) as its index in the sweep, and which were found.
    Only the sweep's points in their bounding box can match: a tree over those, not the sweep."""
    lo, hi = points.min(axis=0) - 1e-6, points.max(axis=0) + 1e-6
    near = np.flatnonzero(np.all((sweep >= lo) & (sweep <= hi), axis=1))
    if len(near) == 0:
        return np.zeros(len(points), dtype=np.int64), np.zeros(len(points), dtype=bool)
    dist, found = cKDTree(sweep[near]).query(points, distance_upper_bound=1e-6)
    ok = np.isfinite(dist)
    return near[np.where(ok, found, 0)], ok


def _with_beam_fields(frame: FrameMeasurement, sweep) -> FrameMeasurement:
    """The frame with its board points' ring and intensity looked up in the sweep they came from (exact
    coordinates), for the range model's per-ring and reflectivity terms."""
    if not frame.usable or (sweep.ring is None and sweep.intensity is None):
        return frame
    idx, found = _in_sweep(frame.lidar.points, sweep.points)
    if not found.all():
        return frame
    lidar = replace(frame.lidar, rings=None if sweep.ring is None else sweep.ring[idx],
                    intensity=None if sweep.intensity is None else sweep.intensity[idx])
    return replace(frame, lidar=lidar)


CONSENSUS_FAILED = "the frames' joint choice of their boards failed: no extrinsic that enough frames'"


def _consensus(cams: list[tuple], candidates: list[list], warnings: list[str], what: str, choose):
    """The joint choice over the frames with a camera board (``choose(planes, poses, candidates, frame ids)``),
    and each such frame's :class:`FrameChoice`; (None, {}) with a warning when there is no consensus."""
    ks = [k for k, (c, _) in enumerate(cams) if c is not None]
    if sum(1 for k in ks if candidates[k]) < 3:
        return None, {}
    try:
        assoc = choose([cams[k][0].plane for k in ks], [cams[k][0].T_camera_board for k in ks],
                       [candidates[k] for k in ks], ks)
    except DegenerateLayoutError as exc:
        warnings.append(f"{CONSENSUS_FAILED} {what} agree on ({exc.problem}); each frame's is chosen from its own "
                        "cues")
        return None, {}
    return assoc, dict(zip(ks, assoc.choices))


def _cropped(sweep, keep: np.ndarray):
    return type(sweep)(sweep.points[keep], None if sweep.ring is None else sweep.ring[keep],
                       None if sweep.intensity is None else sweep.intensity[keep])


def _gate_by_guess(cands: list[BoardCandidate], cam_obs, hints: Hints) -> tuple[list[BoardCandidate], list[str]]:
    """The candidates whose planes, mapped through the initial guess, lie within its tolerance of the camera's
    board plane; the others with their reason."""
    kept, off = [], []
    for c in cands:
        angle, dist = plane_difference(c.observation.plane.transformed(hints.initial_guess), cam_obs.plane)
        if angle <= hints.guess_angle_rad and abs(dist) <= hints.guess_distance_m:
            kept.append(c)
        else:
            off.append(f"outside the initial guess's tolerance ({np.degrees(angle):.1f} deg, {1000 * dist:+.0f} mm)")
    return kept, off


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
        obs = _every_return_on(obs, *sweep, params)
    obs = _trim_to_outline(obs, assoc.T_camera_lidar, cam_obs.T_camera_board, board, len(cands), params)
    return FrameMeasurement(name, cam_obs, obs, None, decision)


def _every_return_on(obs, sweep, scene: StaticScene, params: SegmentationParams):
    """The chosen candidate with every return of its sweep in the range image's cells that hold its points and
    in its plane's noise band along the beam (``board_segmentation.noise_band``, as the candidate's own points
    were gathered), whatever the static scene said of each return.

    The static scene chooses which piece is the board, and which cells it covers; not which of a cell's returns
    are measured. Where the board stands close in front of a surface (a table it stands on, a wall it leans on),
    the scene calls the returns whose range noise carries them within its margin of that surface background and
    keeps the others: a selection on the noise, which tilts the fitted plane. The returns of the board's own cells,
    in a band symmetric in range, undo it; cells the board does not reach are not added."""
    keys = scene.cell_keys(sweep.points, sweep.ring)
    if not (keys >= 0).any():
        return obs
    idx, found = _in_sweep(obs.points, sweep.points)
    own = np.unique(keys[idx[found]])
    cells = np.flatnonzero(np.isin(keys, own[own >= 0]))
    take = cells[noise_band(sweep.points[cells], obs.plane, obs.points)]
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
OUTLINE_TRIM_M = 0.05
OUTLINE_BAND_M = 0.10  # and this far from the camera's board plane
# A scan line's points farther than this outside the outline: a line holds no other check of where the board
# ends, and the hands at its edges, in line with it, tilt it. At 0.05 m, 12 of 80 simulated office frames kept
# such points and the 2D office's translation error was 1.13x the Cramer-Rao bound over 40 layouts (1.03 in
# the empty room); at 0.01 m, 1.02 (0.98 in the empty room).
LINE_TRIM_M = 0.01


def _trim_to_outline(obs, T_camera_lidar: np.ndarray, T_camera_board: np.ndarray, board, n_candidates: int,
                     params: SegmentationParams):
    """The observation cut to the camera's board outline (grown by ``OUTLINE_TRIM_M``) under the extrinsic,
    and refitted robustly (the holder's points left in the plane band are outliers)."""
    inside = inside_outline(obs.points, T_camera_lidar, T_camera_board, board, OUTLINE_TRIM_M + board.unknown_margin,
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
    _, keep = robust_plane_fit(points[inside])
    q = transform_points(T_inverse(T_camera_board) @ T_camera_lidar,
                         on_plane_along_beams(points, fit_plane_pca(points[inside][keep])))
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
            from .solvers.solution_selection import refine_candidates, select_minimal

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
    fits = [c for c in candidates
            if np.sqrt(np.mean(_plane_distances(c.points, plane, T_camera_lidar) ** 2)) < SEGMENT_FIT_M]
    return fits[0] if len(fits) == 1 else None


def _plane_distances(points_lidar: np.ndarray, plane, T_camera_lidar: np.ndarray) -> np.ndarray:
    """Signed distances (m) of LiDAR-frame points, mapped into the camera frame, from a camera-frame plane."""
    return (points_lidar @ T_camera_lidar[:3, :3].T + T_camera_lidar[:3, 3]) @ plane.normal - plane.distance


def import_sampler_ahead() -> None:
    """Start importing the posterior's sampler in a thread: emcee loads scipy.stats, about 0.4 s of
    interpreter time, which then overlaps work that mostly waits on OpenCV and numpy with the interpreter
    free (measuring frames, simulating them); the sampler's own import finds it done or waits for it."""
    if "emcee" not in sys.modules:
        threading.Thread(target=_import_quietly, args=("emcee",), daemon=True, name="import emcee").start()


def _import_quietly(module: str) -> None:
    """Import ``module`` ahead of its use; a failure is left to the real import to report."""
    try:
        importlib.import_module(module)
    except Exception:  # noqa: BLE001 - reported where the module is used
        pass


def calibrate(dataset: Dataset | str | Path, init: str = "closed-form", refine: str = "factor-graph",
              rng: np.random.Generator | None = None, params: SegmentationParams = SegmentationParams(),
              options: RefinementOptions = RefinementOptions(),
              posterior: PosteriorOptions | None = PosteriorOptions(), use_extent: bool | None = None,
              samples: int | None = None, hints: Hints = Hints(), cache: bool = False,
              on_refined: Callable[[CalibrationResult], None] | None = None) -> CalibrationResult:
    """Estimate ``T_camera_lidar``, its covariance and posterior from a dataset.

    Measures every frame (the board in each image and scan), solves in closed form (3D) or by the minimal
    solutions (2D), refines in the factor graph and samples the posterior.

    Parameters
    ----------
    dataset : Dataset, str or Path
        A loaded :class:`Dataset` or its folder.
    init : str
        ``closed-form`` (3D; for a 2D LiDAR it means ``minimal-lower-bound``), ``minimal-lower-bound`` or
        ``minimal-min-residual`` (2D).
    refine : str
        ``factor-graph`` or ``none`` (the initial solution, without covariance).
    rng : numpy.random.Generator, optional
        Drives the board segmentation's RANSAC and the MCMC; a fixed seed when None, so runs repeat.
    params : SegmentationParams
        The LiDAR board segmentation's settings.
    options : RefinementOptions
        The factor graph's noise, robust loss, range model and edges.
    posterior : PosteriorOptions or None
        The sampler's settings; None skips sampling (the covariance is then the Laplace one).
    use_extent : bool, optional
        2D only: drop minimal solutions whose laser segments leave the boards' outlines (default: when the board
        size is known).
    samples : int, optional
        Effective posterior samples to draw (0: none); overrides ``posterior``'s.
    hints : Hints
        An initial guess and a region of interest, for scenes beyond automation.
    cache : bool
        Keep and reuse the measurements (see :func:`measure`).
    on_refined : callable, optional
        Called with the refined result just before the posterior is sampled (see :func:`solve`).

    Returns
    -------
    CalibrationResult
        The estimate, its covariance and posterior, every frame's measurements and the warnings.

    Raises
    ------
    LidarcamError
        A missing or corrupt file (:class:`~estimators.errors.DatasetError`), or too few usable frames or a
        degenerate layout (:class:`~estimators.errors.DegenerateLayoutError`). Frames that cannot be used are
        skipped with their reason instead.

    Examples
    --------
    >>> import estimators as lc
    >>> result = lc.calibrate(lc.simulate("/tmp/sim", n_poses=8, seed=1), samples=500)  # doctest: +SKIP
    >>> result.std_rotation_deg, result.std_translation_mm  # doctest: +SKIP
    """
    _check_methods(init, refine)
    if not isinstance(dataset, Dataset):
        dataset = load_dataset(dataset)
    if samples is not None:
        posterior = None if samples <= 0 else replace(posterior or PosteriorOptions(), min_ess=int(samples))
    if dataset.lidar == "3d" and init != "closed-form":
        raise DatasetError(f"init {init!r} is for 2D LiDAR datasets", path=dataset.yaml_path,
                           hint="use --init closed-form for lidar: 3d")
    rng = np.random.default_rng(0) if rng is None else rng
    if options.range_accuracy_m is None:  # the dataset's, or its LiDAR family's (an explicit option wins)
        options = replace(options, range_accuracy_m=dataset_range_accuracy(dataset))
    # One bound on the sensors' separation: the board search's (``params``) also bounds the 2D solutions.
    options = replace(options, max_sensor_separation_m=params.max_sensor_separation_m)
    timings: dict = {}
    t_start = time.perf_counter()
    if posterior is not None and refine != "none":
        import_sampler_ahead()  # while the frames are measured
    m = measure(dataset, rng, params, hints, cache=cache, timings=timings)
    camera, frames, warnings = m.camera, list(m.frames), list(m.warnings)
    if m.source == "cache":
        warnings.append(f"measurements taken from the cache ({cache_dir() / m.key[:16]}...): images and scans were "
                        "not read again")
    try:
        result = solve(frames, dataset.board, camera, init, refine, options, name=str(dataset.root),
                       warnings=warnings, timings=timings, posterior=posterior, rng=rng, use_extent=use_extent,
                       on_refined=on_refined)
    except DegenerateLayoutError as exc:
        skipped = [f"{f.name}: {f.reason}" for f in frames if not f.usable]
        detail = f" (skipped: {'; '.join(skipped)})" if skipped else ""
        raise DegenerateLayoutError(exc.problem + detail, path=dataset.root, hint=exc.hint) from exc
    timings["total_wall"] = time.perf_counter() - t_start
    return replace(result, timings_s={k: round(v, 4) for k, v in timings.items()}, measurements_source=m.source)


def dataset_range_accuracy(dataset: Dataset) -> float:
    """The LiDAR's range accuracy (m) for the range model's priors: dataset.yaml's ``lidar.range_accuracy_m``,
    else its family's default (``solvers.range_model.RANGE_ACCURACY_M``), else the conservative default."""
    from .solvers.range_model import range_accuracy_for

    return dataset.range_accuracy_m if dataset.range_accuracy_m is not None else range_accuracy_for(
        dataset.lidar_family)


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
        ss = rng.bit_generator.seed_seq
        options = {"params": params, "hints": hints, "version": __version__, "revision": MEASUREMENT_REVISION,
                   "rng": rng.bit_generator.state,
                   "seed": [getattr(ss, "entropy", None), getattr(ss, "spawn_key", None),
                            getattr(ss, "n_children_spawned", None)]}
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


def _check_methods(init: str, refine: str) -> None:
    if init not in INITS:
        raise ValueError(f"Expected init in {INITS}, got {init!r}")
    if refine not in REFINES:
        raise ValueError(f"Expected refine in {REFINES}, got {refine!r}")


def solve(frames: list[FrameMeasurement] | Measurements, board=None, camera: CameraModel | None = None,
          init: str = "closed-form", refine: str = "factor-graph", options: RefinementOptions = RefinementOptions(),
          name: str = "", warnings: list[str] | None = None, timings: dict | None = None,
          posterior: PosteriorOptions | None = None, rng: np.random.Generator | None = None,
          use_extent: bool | None = None, samples: int | None = None,
          on_refined: Callable[[CalibrationResult], None] | None = None) -> CalibrationResult:
    """The solver stage alone, on measured frames: initial solution, factor graph and posterior.

    Parameters
    ----------
    frames : Measurements or list of FrameMeasurement
        From :func:`measure` or :func:`load_measurements` (then ``board`` and ``camera`` come with them), or a list
        of frames with ``board`` and ``camera`` given.
    board : BoardModel, optional
        The board, with a list of frames.
    camera : CameraModel, optional
        The camera model, with a list of frames.
    init, refine : str
        As for :func:`calibrate`.
    options : RefinementOptions
        The factor graph's settings.
    name : str
        The dataset's name in the result.
    warnings : list of str, optional
        Warnings from measuring, carried into the result.
    timings : dict, optional
        Stage times (s) so far, carried into the result.
    posterior : PosteriorOptions, optional
        The sampler's settings; None (default) draws no samples unless ``samples`` asks.
    rng : numpy.random.Generator, optional
        Drives the MCMC (a fixed seed when None).
    use_extent : bool, optional
        As for :func:`calibrate`.
    samples : int, optional
        Effective posterior samples to draw; needs the factor graph.
    on_refined : callable, optional
        Called with the refined result (without the posterior) just before the posterior is sampled, e.g. to start
        drawing the report's other figures meanwhile.

    Returns
    -------
    CalibrationResult

    Raises
    ------
    DegenerateLayoutError
        Too few usable frames, or board normals that do not determine the transform.

    Examples
    --------
    >>> m = lc.measure("/tmp/sim")                                           # doctest: +SKIP
    >>> a = lc.solve(m, refine="none"); b = lc.solve(m, samples=1000)        # doctest: +SKIP
    """
    if isinstance(frames, Measurements):
        m = frames
        result = solve(list(m.frames), m.board, m.camera, init, refine, options, name or m.dataset,
                       list(m.warnings) + list(warnings or []), timings, posterior, rng, use_extent, samples,
                       on_refined)
        return replace(result, measurements_source=m.source)
    if board is None or camera is None:
        raise ValueError("solve needs board and camera with a list of frames (or a Measurements)")
    if samples is not None:
        posterior = None if samples <= 0 else replace(posterior or PosteriorOptions(), min_ess=int(samples))
    _check_methods(init, refine)
    if options.refine_intrinsics and refine == "factor-graph":
        return _solve_with_intrinsics(frames, board, camera, init, options, name, warnings, timings, posterior, rng,
                                      use_extent, on_refined)
    warnings = list(warnings or [])
    timings = {} if timings is None else timings
    used = [f for f in frames if f.usable]
    scan_lines = any(f.lidar is not None and f.lidar.is_scan_line for f in frames)
    if init.startswith("minimal") and not scan_lines and any(f.lidar is not None for f in frames):
        raise LidarcamError(f"init {init!r} is for 2D LiDAR datasets; these frames hold a 3D LiDAR's boards",
                            hint="use init closed-form")
    if scan_lines or init.startswith("minimal"):
        return _solve_2d(frames, board, camera, init, refine, options, name, warnings, timings, posterior, rng,
                         use_extent, on_refined)
    t0 = time.perf_counter()
    # A weak layout is refused by the closed form alone, but only starts the factor graph, which judges
    # what the full model determines (and names what it does not).
    try:
        sol = solve_closed_form([f.camera.plane for f in used], [f.lidar.plane for f in used],
                                allow_weak=refine == "factor-graph")
    except DegenerateLayoutError as exc:
        # Frames skipped as ambiguous because the frames' joint choice failed: the error says why it failed.
        failed = [w for w in warnings if w.startswith(CONSENSUS_FAILED)]
        if not failed:
            raise
        raise DegenerateLayoutError(f"{exc.problem}; {failed[0]}", path=exc.path, hint=exc.hint) from exc
    timings["solve"] = time.perf_counter() - t0
    T, ref = sol.T_camera_lidar, None
    if refine == "factor-graph":
        t0 = time.perf_counter()
        ref = refine_graph(used, board, camera, T, options)
        timings["refine"] = time.perf_counter() - t0
        T = ref.T_camera_lidar
        warnings += ref.warnings
    tail = []  # the warnings that follow the posterior's
    if sol.condition_number > 10:
        axis, advice = describe_direction(sol.weakest_direction_camera)
        tail.append(f"board normals are poorly spread (condition {sol.condition_number:.1f}): "
                    f"translation along {axis} is weakly constrained; {advice}")
    dropped = {f.name for f in ref.frames if f.dropped} if ref else set()
    residuals = plane_residuals(T, [f for f in used if f.name not in dropped])
    for fname, (angle, dist) in residuals.items():
        if angle > np.deg2rad(3.0) or abs(dist) > 0.05:
            tail.append(f"frame {fname}: its planes disagree with the estimate by {np.degrees(angle):.1f} deg "
                        f"and {1000 * dist:.0f} mm; check that the right LiDAR segment was taken as the board")
    tail += [f"frame {f.name}: {f.reason}" for f in frames if not f.usable]
    result = CalibrationResult(T, init, refine, tuple(frames), camera, sol.normal_singular_values,
                               sol.weakest_direction_camera, name, tuple(warnings + tail),
                               {k: round(v, 4) for k, v in timings.items()}, residuals, ref, None)
    return _with_posterior(result, used, board, camera, rng, posterior, (), warnings, tail, timings, on_refined)


# Joint solves of the intrinsics at most (each followed by a refinement whose plane error weights the next).
INTRINSICS_ROUNDS = 3


def _solve_with_intrinsics(frames, board, camera: CameraModel, init: str, options: RefinementOptions, name: str,
                           warnings, timings, posterior, rng, use_extent, on_refined) -> CalibrationResult:
    """:func:`solve` with the intrinsics refined (``solvers.intrinsics_refinement``): solved under the given
    intrinsics, then with them as variables, then, the boards observed again under the refined intrinsics, solved
    (and sampled) under those."""
    plain = replace(options, refine_intrinsics=False)
    t0 = time.perf_counter()
    first = solve(frames, board, camera, init, "factor-graph", plain, name, list(warnings or []), None, None, rng,
                  use_extent)
    timings = {} if timings is None else timings
    ref, floor = first.refinement, options.plane_floor_m or 0.0
    for _ in range(INTRINSICS_ROUNDS):
        fit = refine_intrinsics(list(first.frames), board, camera, ref, plain, floor)
        again = [replace(f, camera=reobserve(f.camera, board, fit.camera) if f.camera is not None else None,
                         camera_alternatives=tuple(reobserve(a, board, fit.camera) for a in f.camera_alternatives))
                 for f in frames]
        ref = solve(again, board, fit.camera, init, "factor-graph", plain, name, [], None, None, rng,
                    use_extent).refinement
        if abs(ref.plane_floor_m - floor) <= max(0.1 * floor, 1e-4):  # the plane error settled (0.1 mm)
            break
        floor = ref.plane_floor_m
    timings["intrinsics_refinement"] = time.perf_counter() - t0
    result = solve(again, board, fit.camera, init, "factor-graph", plain, name, warnings, timings, posterior, rng,
                   use_extent, on_refined=on_refined)
    ref = result.refinement
    fit = replace(fit, variance_factor_given=float(first.refinement.variance_factor),
                  corner_residual_given_px=float(first.refinement.corner_residual_px),
                  variance_factor_refined=float(ref.variance_factor),
                  corner_residual_refined_px=float(ref.corner_residual_px))
    warned = result.warnings
    if not fit.lowers_overdispersion:
        # The planes' other errors pull the intrinsics: said first, as the refined camera is then not to be used.
        moved = float(np.max(np.abs(fit.params - fit.given_params) / fit.std))
        warned = (f"refining the intrinsics did not lower the boards' plane disagreement (variance factor "
                  f"{fit.variance_factor_given:.2f} under the given intrinsics, {fit.variance_factor_refined:.2f} "
                  f"refined) while moving them by up to {moved:.1f} standard deviations (corner residual "
                  f"{fit.corner_residual_given_px:.3f} -> {fit.corner_residual_refined_px:.3f} px): the camera's "
                  "calibration is not what the boards disagree about; keep the given intrinsics (calibrate without "
                  "--refine-intrinsics) unless a calibration made for the camera confirms the refined ones",
                  ) + tuple(warned)
    return replace(result, intrinsics_refinement=fit, warnings=warned)


def _with_posterior(result: CalibrationResult, used, board, camera: CameraModel, rng, options: PosteriorOptions | None,
                    modes: tuple, head: list[str], tail: list[str], timings: dict,
                    on_refined: Callable[[CalibrationResult], None] | None) -> CalibrationResult:
    """``result`` with its posterior sampled (when refined and ``options`` are given), the posterior's warnings
    between ``head`` and ``tail``; ``on_refined`` sees ``result`` first."""
    if result.refinement is None or options is None:
        return result
    if on_refined is not None:
        on_refined(result)
    t0 = time.perf_counter()
    notes: list[str] = []
    post = _posterior_or_warning(used, board, camera, result.refinement, rng, options, modes, notes)
    timings["posterior"] = time.perf_counter() - t0
    return replace(result, posterior=post, warnings=tuple(head + notes + tail),
                   timings_s={k: round(v, 4) for k, v in timings.items()})


def _posterior_or_warning(used, board, camera: CameraModel, ref: Refinement, rng, options: PosteriorOptions,
                          modes: tuple, warnings: list[str]) -> Posterior | None:
    """Posterior samples, or None with the reason among the warnings (a nearly degenerate problem)."""
    try:
        post = sample_posterior(used, board, camera, ref, np.random.default_rng(0) if rng is None else rng,
                                options, tuple((m.refinement, m.mass) for m in modes[1:]),
                                modes[0].mass if modes else 1.0)
    except PosteriorSkippedError as exc:
        warnings.append(f"posterior not sampled: {exc.message}")
        return None
    warnings.extend(post.warnings)
    heavy = post.heavy_tails()
    if heavy is not None:
        warnings.append(heavy)
    return post


def _solve_2d(frames: list[FrameMeasurement], board, camera: CameraModel, init: str, refine: str,
              options: RefinementOptions, name: str, warnings: list[str], timings: dict,
              posterior: PosteriorOptions | None = None, rng: np.random.Generator | None = None,
              use_extent: bool | None = None, on_refined: Callable[[CalibrationResult], None] | None = None
              ) -> CalibrationResult:
    """2D LiDAR: candidates from the minimal solutions of all board triples (``solution_selection``), each
    refined by the factor graph; the least refined cost wins, and near-equal distinct minima are reported."""
    from .solvers.solution_selection import select_and_refine, select_minimal  # 2D only

    method = "minimal-lower-bound" if init == "closed-form" else init
    t0 = time.perf_counter()
    if refine == "none":
        sel = select_minimal([f for f in frames if f.usable], board, method, use_extent,
                             options.max_sensor_separation_m)
        timings["solve"] = time.perf_counter() - t0
    else:  # the boards skipped as ambiguous in their orientation may be used with the tilt the laser decides
        frames, sel, ref, modes, notes = select_and_refine(frames, board, camera, method, options, use_extent)
        warnings += notes
        timings["solve"] = sel.seconds
        timings["refine"] = time.perf_counter() - t0 - sel.seconds
    used = [f for f in frames if f.usable]
    if sel.degenerate_triples:
        warnings.append(f"{len(sel.degenerate_triples)} of {sel.n_triples} board triples are degenerate and give "
                        f"no solution (first: {sel.degenerate_triples[0]})")
    if sel.weak_triples:
        warnings.append(f"{len(sel.weak_triples)} of {sel.n_triples} board triples are ill-conditioned and were "
                        f"solved anyway (first: {sel.weak_triples[0]})")
    if sel.fallback:
        why = (f" that could be the rig ({sel.n_unphysical} put the LiDAR behind a board, a segment behind the "
               f"camera, or the sensors more than {sel.max_separation_m:g} m apart)"
               if sel.n_unphysical and sel.max_separation_m is not None else "")
        warnings.append(f"no board triple gave a minimal solution{why}: the candidates come from a multi-start "
                        "search over rotations seeded by the camera's board planes")
    spread, weak = normal_spread(np.array([f.camera.plane.normal for f in used]))
    if refine == "none":
        T = sel.candidates[0].T_camera_lidar
        ref, modes = None, ()
    else:
        T = ref.T_camera_lidar
        warnings += ref.warnings
        if len(modes) > 1:
            warnings.append(f"ambiguous: {len(modes)} distinct solutions fit the boards (posterior mass "
                            f"{', '.join(f'{m.mass:.0%}' for m in modes)}; the first is reported, all are in "
                            "calibration.json); add boards tilted in other directions to decide")
    residuals = plane_residuals(T, used)
    tail = [f"frame {f.name}: {f.reason}" for f in frames if not f.usable]
    result = CalibrationResult(T, method, refine, tuple(frames), camera, spread, weak, name, tuple(warnings + tail),
                               {k: round(v, 4) for k, v in timings.items()}, residuals, ref, None, sel,
                               tuple(modes))
    return _with_posterior(result, used, board, camera, rng, posterior, tuple(modes), warnings, tail, timings,
                           on_refined)


def write_calibration(result: CalibrationResult, out_dir: str | Path) -> Path:
    """Write ``OUT/posterior.npz`` (when sampled) and then ``OUT/calibration.json``, each atomically.

    Parameters
    ----------
    result : CalibrationResult
        From :func:`calibrate` or :func:`solve`.
    out_dir : str or Path
        The output folder (created when missing).

    Returns
    -------
    Path
        The path of ``calibration.json``.
    """
    out = Path(out_dir)
    if result.posterior is not None:
        p = result.posterior
        extra = {} if p.mode_index is None else {"mode_index": p.mode_index}
        write_npz_atomic(out / "posterior.npz", xi=p.xi, noise_scale=p.scale, T_map=p.T_map,
                         chain=p.run.chain, convention=np.array(COVARIANCE_CONVENTION), **extra)
    return write_json_atomic(out / "calibration.json", result.to_dict())
