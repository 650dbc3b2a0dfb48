"""A rig's measurements: each camera's boards (corners at each board's own residual, the pattern's numbering
aligned across cameras), each LiDAR's board found once with the first camera sharing the frame, and the start of
every pose along the links that share the most frames.
"""
from __future__ import annotations

from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import replace

import numpy as np

from geometry.camera import CameraModel
from geometry.rotations import T_log, log_batch

from ..camera.board_pose import estimate_board_pose
from ..camera.detection import CornerDetection
from ..camera.intrinsics import calibrate_intrinsics
from ..errors import AmbiguousOrientationError, DatasetError, DegenerateLayoutError, LidarcamError, in_pair
from ..io.dataset import FrameFiles
from ..io.measurement_store import (RIG_FORMAT, RigMeasurements, cache_dir, dataset_key, generator_key,
                                     load_rig_measurements, save_rig_measurements)
from ..io.rig_dataset import RigDataset, Sensor
from ..lidar.board_segmentation import SegmentationParams
from ..measurements import FrameMeasurement
from ..pipeline.measurement import (SHIFTS, Hints, LidarSweeps, detect_in_image, measure_frames, model_as_given,
                                    read_sweeps, relative_name, shift_agrees, shift_words, squares_as_given)
from ..solvers.association import AssociationParams
from ..solvers.factor_graph import CameraViews, LidarViews, PlaneError
from ..solvers.noise_levels import corner_noise_levels, own_fit_residuals
from ..solvers.range_model import frame_whitener
from ..solvers.refinement_options import RefinementOptions

# Fewest frames a camera and a LiDAR must share (their boards found in both) to be linked and solved as a pair.
MIN_PAIR_FRAMES = 3


def camera_frames(sensor: Sensor) -> list[FrameFiles]:
    """A camera's frames, each image's path as both of its files (a LiDAR's are looked up apart)."""
    return [FrameFiles(stem, path, path) for stem, path in sensor.files]


def measure_camera(sensor: Sensor, board, detections: list
                   ) -> tuple[CameraModel, dict, dict, list[str], dict, frozenset]:
    """One camera's board poses by stem, the frames skipped with their reasons, its intrinsics (calibrated from
    its frames when the rig's dataset.yaml gives none), its images' corners by stem (for the pairs) and the stems
    whose board's tilt the corners leave ambiguous (skipped by the camera; a 2D scanner's pair may decide it), from
    each of its frames' ``detect_in_image`` (``detections``, in :func:`camera_frames`' order)."""
    warnings: list[str] = []
    frames = camera_frames(sensor)
    camera = sensor.camera
    if camera is None:
        found = [d for _, d in detections if isinstance(d, CornerDetection)]
        sizes = {s for s, _ in detections if s is not None}
        if len(sizes) != 1 or len(found) < 3:
            raise DegenerateLayoutError(f"camera {sensor.name}: intrinsics cannot be calibrated from "
                                        f"{len(found)} board view(s) of {len(sizes)} image size(s)",
                                        hint=f"give K, width and height for {sensor.name} in dataset.yaml, or more "
                                             "frames")
        camera, _ = calibrate_intrinsics([d.corners_px for d in found], board, *sizes.pop(),
                                         corner_ids=[d.corner_ids for d in found])
        warnings.append(f"camera {sensor.name}: no intrinsics in dataset.yaml: {camera.source}")
    poses, skipped, ambiguous = {}, {}, set()
    for f, (size, det) in zip(frames, detections):
        if isinstance(det, str):
            skipped[f.name] = det
        elif det is None:
            skipped[f.name] = "board not found in the image"
        elif size != (camera.width, camera.height):
            skipped[f.name] = f"image is {size[0]}x{size[1]} but the camera is {camera.width}x{camera.height}"
        else:
            try:
                poses[f.name] = estimate_board_pose(det, board, camera)
            except LidarcamError as exc:
                skipped[f.name] = f"board pose: {exc.message}"
                if isinstance(exc, AmbiguousOrientationError):
                    ambiguous.add(f.name)
    if sensor.camera is not None and not camera.source.startswith("refined"):
        model_as_given(camera, board, {f.name: det for f, (_, det) in zip(frames, detections) if f.name in poses},
                       poses, f"camera {sensor.name}")
    return camera, poses, skipped, warnings, {f.name: d for f, d in zip(frames, detections)}, frozenset(ambiguous)


def _squares_as_given(rig: RigDataset, sensor: Sensor, corners: dict) -> None:
    """``measurement.squares_as_given`` for one camera of ``rig`` (its images' corners in ``corners`` by path): in a
    rig of several cameras, called only where no camera found the board in 2 frames, so that a camera that sees it
    seldom (partly out of view, where a smaller pattern may be found) is not read as the board's count."""
    frames = camera_frames(sensor)
    squares_as_given(rig.board, [f.image for f in frames], [corners[f.image][1] for f in frames],
                     f"camera {sensor.name}")


def camera_views_of(name: str, camera: CameraModel, poses: dict, board,
                    options: RefinementOptions = RefinementOptions()) -> CameraViews:
    """The camera's corners for the graph, each board's with its own effective pixel noise and ``sigma_px`` the
    camera's (a board not yet recorded, as the advice asks), as a single pair's refinement weighs them
    (``noise_levels.corner_noise_levels``: the residuals times the corner-error correlation, or
    ``--corner-noise-px`` for every board)."""
    stems = list(poses)
    _, sigma_px, per_board = corner_noise_levels(((poses[s].T_camera_board, poses[s].corners_board(board),
                                                   poses[s].corners_px) for s in stems), camera, options)
    return CameraViews(name, camera, sigma_px,
                       {s: poses[s].corners_board(board) for s in stems}, {s: poses[s].corners_px for s in stems},
                       {s: poses[s].T_camera_board for s in stems}, dict(zip(stems, per_board)))


def pattern_flip(board) -> np.ndarray | None:
    """The board-frame transform that turns a checkerboard's pattern by 180 degrees about its centre, when the
    pattern looks the same turned (an even sum of squares: the detector may then number its corners from
    either end, each camera on its own); None for a ChArUco board (its ids fix the numbering) or an asymmetric
    pattern. A pose found with the corners numbered from the other end is ``T_camera_board @ flip``."""
    if board.is_charuco or sum(board.squares) % 2:
        return None
    c = board.inner_corners().mean(axis=0)
    flip = np.diag([-1.0, -1.0, 1.0, 1.0])
    flip[:2, 3] = 2 * c[:2]
    return flip


def _flipped(obs, flip: np.ndarray):
    """The camera's observation with its corners numbered from the other end (:func:`pattern_flip`)."""
    return replace(obs, corners_px=obs.corners_px[::-1].copy(), T_camera_board=obs.T_camera_board @ flip)


def align_numbering(cams: list[str], poses: dict, T_ref: dict, flip: np.ndarray) -> dict:
    """Each frame's boards numbered alike in every camera: as the first camera (in the rig's order) that saw the
    frame numbers it, each other camera's numbering the one whose pose lies nearer to where the start
    (``T_ref``, composed of numbering-free links: a LiDAR's plane, or the consensus of two cameras' frames) puts
    that board."""
    out = {c: dict(poses[c]) for c in cams}
    first: dict = {}
    for c in cams:
        for st in out[c]:
            first.setdefault(st, c)
    for c in cams:
        for st, obs in out[c].items():
            if first[st] == c:
                continue
            c0 = first[st]
            predicted = np.linalg.inv(T_ref[c]) @ T_ref[c0] @ out[c0][st].T_camera_board
            angle = [np.linalg.norm(T_log(np.linalg.inv(predicted) @ T)[:3])
                     for T in (obs.T_camera_board, obs.T_camera_board @ flip)]
            if angle[1] < angle[0]:
                out[c][st] = _flipped(obs, flip)
    return out


def _consensus_relative(rels: list[list[np.ndarray]]) -> np.ndarray:
    """The relative pose most frames agree with (within 2 degrees and 5 cm), each frame giving its candidates
    (one per numbering of the board), and its candidate nearest that (:func:`_agreed_relative`)."""
    return _agreed_relative(rels)[0]


def _agreed_relative(rels: list[list[np.ndarray]]) -> tuple[np.ndarray, int]:
    """:func:`_consensus_relative` and how many frames agree with it: every candidate against every other in one
    batch of logarithms (40 frames of two numberings each: 7 ms, against 2.2 s one by one)."""
    hyps = np.array([T for cands in rels for T in cands])
    frame = np.array([i for i, cands in enumerate(rels) for _ in cands])
    rel = np.linalg.inv(hyps)[:, None] @ hyps[None, :]  # [h, j]: hypothesis h to candidate j
    xi = log_batch(rel[..., :3, :3].reshape(-1, 3, 3), rel[..., :3, 3].reshape(-1, 3)).reshape(len(hyps),
                                                                                             len(hyps), 6)
    close = (np.linalg.norm(xi[..., :3], axis=-1) < np.deg2rad(2.0)) & (np.linalg.norm(xi[..., 3:], axis=-1) < 0.05)
    dist = np.linalg.norm(xi, axis=-1)
    agree = sum(close[:, frame == i].any(axis=1).astype(int) for i in range(len(rels)))
    spread = sum(dist[:, frame == i].min(axis=1) for i in range(len(rels)))
    best = max(range(len(hyps)), key=lambda h: (agree[h], -spread[h]))
    return hyps[best], int(agree[best])


def _cameras_not_shifted(rig: RigDataset, poses: dict) -> None:
    """Refuse two cameras whose images are numbered a few frames apart: where no more than three of the boards both
    saw agree on one relative pose as numbered (:func:`_agreed_relative`), but a shifted numbering's do
    (``measurement.shift_agrees``) with one camera's image paired with the other's up to three frames later or
    earlier (``measurement.SHIFTS``, nearest first; both numberings of a board that looks the same turned)."""
    flip = pattern_flip(rig.board)
    flips = [np.eye(4)] if flip is None else [np.eye(4), flip]
    stems = sorted({st for c in rig.cameras for st in poses[c.name]})

    def agreeing(a: str, b: str, pairs: list[tuple[str, str]]) -> int:
        return _agreed_relative([[poses[a][i].T_camera_board @ np.linalg.inv(poses[b][j].T_camera_board @ F)
                                  for F in flips] for i, j in pairs])[1] if pairs else 0

    for ia, a in enumerate(rig.cameras):
        for b in rig.cameras[ia + 1:]:
            shared = [(st, st) for st in stems if st in poses[a.name] and st in poses[b.name]]
            if len(shared) <= AssociationParams.min_frames or \
                    agreeing(a.name, b.name, shared) > AssociationParams.min_frames:
                continue
            for shift in SHIFTS:
                pairs = [(st, stems[k + shift]) for k, st in enumerate(stems) if 0 <= k + shift < len(stems)
                         and st in poses[a.name] and stems[k + shift] in poses[b.name]]
                n = agreeing(a.name, b.name, pairs)
                if shift_agrees(n, len(pairs)):
                    i, j = (relative_name(c.file(st), rig.root) for c, st in zip((a, b), pairs[0]))
                    frames, later = shift_words(shift)
                    raise DatasetError(
                        f"{a.name}'s and {b.name}'s boards agree on no one relative pose as the images are numbered, "
                        f"but {n} of {len(pairs)} do with {a.name}'s image paired with {b.name}'s {frames} {later} "
                        f"({i} with {j}): one camera's images are numbered {frames} off", path=rig.root,
                        hint="renumber the camera's images whose boards its LiDARs' scans do not match, so that each "
                             "NNNN was captured at one instant")


def measured_rig(rig: RigDataset, rng: np.random.Generator, workers: int = 2, cache: bool = True,
                 params: SegmentationParams = SegmentationParams(), hints: Hints = Hints(),
                 timings: dict | None = None, reused: dict | None = None) -> RigMeasurements:
    """:func:`measure_rig`, kept under the user's cache folder (``io.measurement_store.cache_dir``) when ``cache``,
    keyed by the rig's files, the code and the generator's state, and read back from it: the generators measuring
    would have drawn are drawn, so that later draws (the posterior's) are the same either way. ``timings`` gets
    the measurement's stage times, ``reused`` what measurements of the same files share (:func:`measure_rig`)."""
    folder = None
    if cache:
        options = {"format": RIG_FORMAT, "params": params, "hints": hints, **generator_key(rng)}
        refined = {s.name: s.camera.as_dict() for s in rig.cameras
                   if s.camera is not None and s.camera.source.startswith("refined")}
        if refined:  # measured again under refined intrinsics (``calibrate_rig``)
            options["cameras"] = refined
        files = [path for s in rig.sensors for _, path in s.files]
        folder = cache_dir() / f"rig-{dataset_key(rig.root, files, options)}"
        if (folder / "index.json").is_file():
            try:
                return replace(given_measurements(rig, load_rig_measurements(folder), rng), source="cache",
                               cache=folder)
            except DatasetError:
                pass  # a damaged cache entry is measured again (and overwritten)
    rm = measure_rig(rig, rng, workers, params, hints, timings, reused)
    if folder is not None:
        try:
            save_rig_measurements(folder, rm, rig.board, {s.name: s.lidar for s in rig.lidars})
            rm = replace(rm, cache=folder)
        except OSError as exc:
            rm = replace(rm, warnings=rm.warnings + (f"the measurement cache {folder} is not writable ({exc})",))
    return rm


def given_measurements(rig: RigDataset, rm: RigMeasurements, rng: np.random.Generator) -> RigMeasurements:
    """``rm`` checked against the rig (its cameras and LiDARs among the rig's, of the same kinds) and the
    generators measuring drew drawn; :class:`DatasetError` naming the rig's dataset.yaml when they do not fit."""
    cams, lidars = {s.name for s in rig.cameras}, {s.name: s.lidar for s in rig.lidars}
    foreign = sorted(set(rm.cameras) - cams) + sorted({lid for _, lid in rm.pairs} - set(lidars))
    if foreign:
        raise DatasetError(f"the measurements name sensors this rig does not have ({', '.join(foreign)})",
                           path=rig.yaml_path, hint="give the rig folder the measurements came from")
    for n in rm.spawned:
        rng.spawn(n)
    return rm


def measure_rig(rig: RigDataset, rng: np.random.Generator, workers: int = 2,
                params: SegmentationParams = SegmentationParams(), hints: Hints = Hints(),
                timings: dict | None = None, reused: dict | None = None) -> RigMeasurements:
    """Every sensor of the rig measured once (module docstring): each camera's boards, then each LiDAR's with each
    camera that shares at least ``MIN_PAIR_FRAMES`` of its frames, the cameras in the order of frames shared, under
    the board search's ``params`` and ``hints`` (a region of interest, in each LiDAR's own frame, and whether the
    static scene is used; a rig's initial guesses, ``hints.pair_guesses``, each its camera-LiDAR pair's; one
    ``initial_guess`` is refused, as a rig has several pairs). ``timings`` gets each stage's seconds summed over
    the threads (``load_images``, ``corners``, ``load_scans``, ``segmentation``), as a single pair's measurement
    gives them. ``reused``: what no camera's intrinsics change, kept by an earlier measurement of the same files
    with the same ``hints`` and taken from it (``corners``: each image's ``detect_in_image`` by its path;
    ``sweeps``: each 3D LiDAR's ``read_sweeps`` by its name and files), and filled here: a rig measured again
    under refined intrinsics (``calibrate_rig``) searches no image and reads no sweep twice."""
    timings = {} if timings is None else timings
    if hints.initial_guess is not None:
        raise DatasetError("an initial guess is one camera-LiDAR pair's T_camera_lidar, and a rig has several",
                           path=rig.yaml_path, hint="give a rig's calibration.json as the guess")
    warnings: list[str] = []
    cameras, poses, skipped, found, ambiguous = {}, {}, {}, {}, {}
    with ThreadPoolExecutor(max_workers=1) as ahead, ThreadPoolExecutor(max_workers=workers) as pool:
        # Each 3D LiDAR's sweeps read and its static scene built once (they need no camera), in a thread of their
        # own while the cameras' images are searched, for every camera it shares frames with.
        reused = {} if reused is None else reused
        corners, read = reused.setdefault("corners", {}), reused.setdefault("sweeps", {})
        sweeps = {lid.name: read.get((lid.name, lid.files)) or ahead.submit(
            read_sweeps, [FrameFiles(st, None, path) for st, path in lid.files], hints, timings)
            for lid in rig.lidars if lid.lidar != "2d"}
        # Every camera's images searched in one pool: no camera waits on its slowest image with a core idle, and
        # each camera's board poses are solved while the next cameras' images are searched.
        pending = {s.name: [(f.image, corners.get(f.image) or pool.submit(detect_in_image, f, rig.board, timings))
                            for f in camera_frames(s)] for s in rig.cameras}
        for s in rig.cameras:
            for image, p in pending[s.name]:
                corners.setdefault(image, p.result() if isinstance(p, Future) else p)
            if len(rig.cameras) == 1:  # before its intrinsics are calibrated from the boards found, if it has none
                _squares_as_given(rig, s, corners)
            cameras[s.name], poses[s.name], skipped[s.name], w, found[s.name], ambiguous[s.name] = measure_camera(
                s, rig.board, [corners[image] for image, _ in pending[s.name]])
            warnings.extend(w)
        if len(rig.cameras) > 1 and all(len(poses[c.name]) < 2 for c in rig.cameras):
            _squares_as_given(rig, max(rig.cameras, key=lambda c: len(c.files)), corners)
        sweeps = {name: got.result() if isinstance(got, Future) else got for name, got in sweeps.items()}
        read.update({(lid.name, lid.files): sweeps[lid.name] for lid in rig.lidars if lid.name in sweeps})
    _cameras_not_shifted(rig, poses)
    pairs, measured_by, spawned = {}, {}, []
    for lid in rig.lidars:
        shared = sorted(rig.cameras, key=lambda c: -sum(1 for st in poses[c.name] if lid.file(st) is not None))
        measured: dict = {}  # stem -> (the camera it was measured with, its frame): the LiDAR side tried once
        for k, cam in enumerate(shared):
            # a scanner's frames include those whose board's tilt the camera leaves ambiguous: the laser may decide
            # it (``solution_selection.select_and_refine``)
            stems = [st for st in cam.stems if lid.file(st) is not None and (
                st in poses[cam.name] or lid.lidar == "2d" and st in ambiguous[cam.name])]
            # a LiDAR that shares too few frames with every camera (the first, sharing most, among them) is measured
            # with the first still, so that its solve can say why it is not linked (its frames' reasons, a bad file)
            if len(stems) >= MIN_PAIR_FRAMES or k == 0 and stems:
                key = (cam.name, lid.name)
                guess = (hints.pair_guesses or {}).get(f"T_{cam.name}_{lid.name}")
                pairs[key] = measure_pair_frames(rig.pair(cam.name, lid.name, cameras[cam.name]), cam.name,
                                                 lid.name, stems, poses[cam.name], measured, rng, workers,
                                                 found[cam.name], warnings, spawned, params,
                                                 replace(hints, initial_guess=guess, pair_guesses=None),
                                                 sweeps.get(lid.name), timings)
                measured_by[key] = {f.name: measured[f.name][0] for f in pairs[key] if f.name in measured}
    return RigMeasurements(cameras, poses, skipped, pairs, measured_by, tuple(warnings), tuple(spawned))


def measure_pair_frames(ds, camera_name: str, lidar_name: str, stems: list[str], poses: dict, measured: dict, rng,
                        workers: int, found: dict, warnings: list, spawned: list,
                        params: SegmentationParams = SegmentationParams(), hints: Hints = Hints(),
                        sweeps: LidarSweeps | None = None, timings: dict | None = None) -> list[FrameMeasurement]:
    """A camera-LiDAR pair's frames: the LiDAR's board in a frame is found once, with the first camera that shares
    it (``measured``, updated), and paired with each later camera's own board pose. A camera with only one or two
    frames not yet measured measures them with those it shares (choosing each frame's board takes three). The
    camera's corners (``found``) and board poses (``poses``) are those ``measure_camera`` found, a 3D LiDAR's
    sweeps and static scene (``sweeps``) those of all its frames. ``spawned`` gets the number of generators drawn
    from ``rng`` (a cached rig draws as many)."""
    new = [st for st in stems if st not in measured]
    now = {}
    if new:
        keep = set(new) if len(new) >= MIN_PAIR_FRAMES else set(stems)
        subset = replace(ds, frames=tuple(f for f in ds.frames if f.name in keep))
        spawned.append(len(subset.frames) + 1)
        try:
            _, frames, w = measure_frames(subset, rng, params, timings, workers=workers, hints=hints, detections=found,
                                          board_poses=poses, sweeps=sweeps)
        except DatasetError as exc:  # the pair's data cannot be right (its scans numbered off, its K mis-scaled)
            if type(exc) is not DatasetError:
                raise
            raise in_pair(exc, f"{camera_name}-{lidar_name}") from None
        warnings.extend(f"{camera_name}-{lidar_name}: {x}" for x in w)
        now = {f.name: f for f in frames}
        for f in frames:
            if f.camera is not None:  # the LiDAR side was tried (it needs the camera's board)
                measured.setdefault(f.name, (camera_name, f))
    out = []
    for st in stems:
        if st in now:
            out.append(now[st])
        elif st in measured and st in poses:
            f = measured[st][1]
            out.append(FrameMeasurement(st, poses[st], f.lidar, None if f.lidar is not None else f.reason))
    return out


def lidar_views_of(name: str, sigma_m: float, frames: dict, T_ref_board: dict, board, scan_line: bool,
                   options: RefinementOptions) -> LidarViews:
    """A LiDAR's board points for the graph, as a single pair's refinement weighs them: by stem the frame (its
    LiDAR board, and the camera board it was found with) and the per-board plane error its pair estimated
    (``frames``: stem -> (FrameMeasurement, floor_m)), each plane at the range noise ``sigma_m`` with that error
    (``factor_graph.PlaneError``) under ``options``' robust loss; the stems a camera saw (``T_ref_board``)."""
    W, errors, own = {}, {}, {}
    for st, (f, floor_m) in frames.items():
        if st not in T_ref_board:
            continue
        fw = frame_whitener(f.lidar, sigma_m, None)
        W[st] = fw.W
        errors[st] = PlaneError.of_frame(f, fw.centre, board, floor_m, options.corner_scale_sd)
        own[st] = own_fit_residuals(f.lidar)
    return LidarViews(name, sigma_m, W, scan_line, plane_error=errors, robust=options, own_fit=own)


def start_poses(names, reference, parent, poses, pairwise, flip) -> dict:
    """Each sensor's starting pose in the reference's frame, composed along the tree from the reference."""
    T_ref = {reference: np.eye(4)}
    pending = [n for n in names if n != reference]
    while pending:
        for n in list(pending):
            p = parent[n]
            if p not in T_ref:
                continue
            T_ref[n] = T_ref[p] @ _relative(p, n, poses, pairwise, flip)
            pending.remove(n)
    return T_ref


def _relative(a: str, b: str, poses, pairwise, flip) -> np.ndarray:
    """``T_a_b`` from the pairwise solution (camera-LiDAR) or the shared boards' consensus (camera-camera; both
    numberings of a board that looks the same turned, ``flip``)."""
    if (a, b) in pairwise:
        return pairwise[(a, b)][0]
    if (b, a) in pairwise:
        return np.linalg.inv(pairwise[(b, a)][0])
    shared = [st for st in poses[a] if st in poses[b]]
    flips = [np.eye(4)] if flip is None else [np.eye(4), flip]
    return _consensus_relative([[poses[a][st].T_camera_board @ np.linalg.inv(poses[b][st].T_camera_board @ F)
                                 for F in flips] for st in shared])
