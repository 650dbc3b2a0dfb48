"""``lidarcam check``: whether the scene agrees with a given extrinsic (``solvers.scene_alignment``).

Per frame: the sweep's contour returns (``lidar.depth_edges``; each return's beam from its file's ``ring`` field or
organised rows, else from the elevations of all the sweeps' returns, ``measurement.with_found_beams``), those the
camera sees from its own centre under the given extrinsic, and the image's edge-distance field
(``camera.edge_map``). Where the folder has a board and the camera finds it, the board is left out by default
(``keep_board`` keeps it): its image edges (within ``BOARD_MARGIN_PX`` of its outline) and the contour returns that
land there, so that the check is the scene's and not the boards' again.
The scene's estimate is sought from the given extrinsic and from starts about it (``scene_minima``): the minimum
sought from the given one, unless another fits the scene significantly better over the image's blocks
(``nearest_decided``); the other minima it does not fit significantly better over the blocks say how far the
scene's cost leaves it undecided, and their scatter about it is added to its block covariance
(``minima_scatter``). The test reads the given extrinsic's difference from the estimate against that sum (plus
the given extrinsic's own covariance, when it is a calibration's) over the directions the scene constrains.
"""
from __future__ import annotations

import os
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace

import cv2
import numpy as np

from geometry.camera import CameraModel
from geometry.rotations import T_inverse, T_log, transform_points

from .. import __version__
from ..camera.detection import CornerDetection
from ..camera.edge_map import TRUNCATE_PX, EdgeMap, edges_with_normals
from ..errors import DatasetError, DegenerateLayoutError, LidarcamError, ScanReadError, about
from ..io.dataset import load_scene_folder
from ..io.image_io import read_gray
from ..io.pointcloud_io import read_sweep
from ..io.rig_dataset import first_pair, is_rig, scene_pair
from ..lidar.depth_edges import depth_edges
from ..solvers.scene_alignment import (SceneFit, SceneView, beam_spacing_px, beam_steps, consistency,
                                      minima_scatter, nearest_decided, rival_minima, scene_minima, smallest_flagged,
                                      transverse_edges, visible_from_camera)
from .measurement import (NUMBERING_HINT, SHIFT_AGREEING, SHIFTS, relative_name, rigid, shift_agrees, shift_words,
                          with_found_beams)
from .result import CONVENTION, COVARIANCE_CONVENTION
from .verdict import CHECK, OK, Verdict

# The board's outline, widened by this (px), is left out of the image's edges and of the contours.
BOARD_MARGIN_PX = 15
# The test's level: below it the scene contradicts the given extrinsic.
ALPHA = 0.01
EXIT_CONTRADICTED = 4
# A check that agrees but would flag a change of the given extrinsic along one of the camera's axes only beyond
# this (deg, mm; the changes its ``smallest_flagged`` gives) vouches for it no closer than that: its verdict says
# CHECK. Twice the turn and the move the recorded sets' checks flag along every axis (1 deg, 5 cm): on the recorded
# VLP-16 set turned by 1 deg about the camera's y the scene settles in a minimum of its own beside the given one and
# agrees (p = 1) while it could flag only (2.0, 2.3, 4.1) deg and (66, 121, 108) mm.
VOUCHES_WITHIN = (2.0, 100.0)
READ_THREADS = 2
# A return lies on the board within this (m) of its plane and its outline; a scan holds a camera's board with at
# least this many returns there (a recorded VLP-16's own scan puts 640-1250 on its board, the scans a frame off up
# to 460; a simulated 64-beam office's 1460-2450, the others up to 300).
ON_BOARD_M = 0.05
MIN_ON_BOARD = 20


@dataclass(frozen=True, eq=False)
class SceneCheck:
    """The scene's check of ``T_given``: the scene's estimate near it (``fit``), the test (``test``:
    ``consistency``), the frames used and those skipped with their reasons."""

    dataset: str
    T_given: np.ndarray
    fit: SceneFit
    test: dict
    frames_used: tuple
    skipped: dict
    camera: CameraModel
    board_left_out: bool
    seconds: float
    views: tuple = ()  # the frames' SceneViews, for the page
    # Other minima of the scene's cost as low as the estimate and beyond its covariance (``rival_minima``), and the
    # covariance tested against: the estimate's plus the scatter of the minima the blocks cannot tell from it
    # (``minima_scatter``).
    rivals: tuple = ()
    covariance: np.ndarray | None = None
    sensors: tuple | None = None  # a rig folder's camera and LiDAR checked (None: a camera-LiDAR folder)
    # The factor its covariance is believed at: 1 for the minimum sought from the given extrinsic
    # (``nearest_decided``); a targetless estimate, the lowest of many starts' minima, more
    # (``targetless.COVARIANCE_EXCESS``).
    excess: float = 1.0
    # The given extrinsic's own covariance (a calibration's), added to the scene's in the test: None, exact.
    given_covariance: np.ndarray | None = None

    @property
    def consistent(self) -> bool | None:
        p = self.test.get("p_value")
        return None if p is None else bool(p >= ALPHA)

    def rivals_spread(self) -> tuple[float, float]:
        """How far the rival minima lie from the best: the largest angle (deg) and translation (mm)."""
        xis = [T_log(T_inverse(self.fit.T_camera_lidar) @ f.T_camera_lidar) for f in self.rivals]
        return (max(float(np.degrees(np.linalg.norm(x[:3]))) for x in xis),
                max(1000 * float(np.linalg.norm(f.T_camera_lidar[:3, 3] - self.fit.T_camera_lidar[:3, 3]))
                    for f in self.rivals))

    @property
    def verdict(self) -> Verdict:
        if self.consistent is None:
            return Verdict(CHECK, (f"the scene constrains {self.test['dof']} direction(s) with {self.fit.frames} "
                                   "frames: too little to test the extrinsic; give more frames with objects at "
                                   "several distances",))
        if not self.consistent:
            return Verdict(CHECK, (f"the scene contradicts the given extrinsic (p = {self.test['p_value']:.2g}, "
                                   f"{self.test['dof']} constrained directions): it lays the LiDAR's contours on the "
                                   "image's edges elsewhere; on simulated rooms and offices this test flags the true "
                                   "extrinsic in 1 of 239 checks (docs/bench/scene_check.md, scene_check_seed0.md), "
                                   "so look at check.html before trusting either",))
        weak = self.weak_axes()
        if weak:
            return Verdict(CHECK, (f"the scene agrees (p = {self.test['p_value']:.2g}) but could not tell the given "
                                   f"extrinsic from one {', or '.join(weak)}: it vouches for it no closer than that; "
                                   "add frames with objects near and far across the image",))
        return Verdict(OK)

    def weak_axes(self) -> list[str]:
        """The changes along the camera's axes this check would not flag within ``VOUCHES_WITHIN`` (an axis the
        scene leaves free is said by the test's directions, not here), in words: ``turned 4.1 deg about camera z``."""
        flagged = self.smallest_flagged()
        if flagged is None:
            return []
        words = []
        for sizes, limit, how, unit, fmt in ((flagged[0], VOUCHES_WITHIN[0], "turned", "deg about", "{:.1f}"),
                                             (flagged[1], VOUCHES_WITHIN[1], "moved", "mm along", "{:.0f}")):
            beyond = [f"{fmt.format(v)} {unit} camera {axis}" for axis, v in zip("xyz", sizes)
                      if np.isfinite(v) and v > limit]
            if beyond:
                words.append(f"{how} {' or '.join(beyond)}")
        return words

    @property
    def believed_covariance(self) -> np.ndarray:
        """The scene estimate's covariance as tested and reported: its minimum's blocks and the scatter of the
        minima the blocks cannot tell from it (``covariance``) times ``excess``."""
        return self.excess * (self.covariance if self.covariance is not None else self.fit.covariance)

    @property
    def test_covariance(self) -> np.ndarray:
        """The covariance the test reads the difference against: the scene estimate's (``covariance``), plus the
        given extrinsic's own carried to the estimate's tangent where it has one (two independent estimates)."""
        C = self.covariance if self.covariance is not None else self.fit.covariance
        if self.given_covariance is None:
            return C
        return C + given_in_tangent(self.given_covariance, self.T_given, self.fit.T_camera_lidar)

    def smallest_flagged(self) -> tuple[np.ndarray, np.ndarray] | None:
        """How sensitive this check is: the turn about (deg) and the move along (mm) each of the camera's axes of
        the given extrinsic that the test would flag at its level, were the scene's estimate where the given one is
        (``scene_alignment.smallest_flagged``; inf along an axis the scene leaves free); None when undetermined."""
        x = smallest_flagged(self.test_covariance, self.T_given, self.fit.blocks, ALPHA)
        return None if x is None else (np.degrees(x[:3]), 1000 * x[3:])

    def camera_axes_sd(self) -> tuple[np.ndarray, np.ndarray]:
        """The scene estimate's standard deviations (``believed_covariance``): rotation about the camera's x, y, z
        (deg) and translation along them (mm)."""
        R = self.fit.T_camera_lidar[:3, :3]
        C = self.believed_covariance
        rot = np.degrees(np.sqrt(np.maximum(np.diag(R @ C[:3, :3] @ R.T), 0.0)))
        trans = 1000 * np.sqrt(np.maximum(np.diag(R @ C[3:, 3:] @ R.T), 0.0))
        return rot, trans

    def to_dict(self) -> dict:
        rot, trans = self.camera_axes_sd()
        flagged = self.smallest_flagged()
        finite = (lambda v: [float(x) if np.isfinite(x) else None for x in v])  # None: an axis the scene leaves free
        return {
            "verdict": self.verdict.to_dict(), "tool": "lidarcam", "version": __version__, "dataset": self.dataset,
            "consistent": self.consistent, "p_value": self.test["p_value"], "alpha": ALPHA,
            "test": {**self.test, "statistic": "Hotelling's F over the constrained directions of the frame-block "
                                               "sandwich covariance with the minima's scatter, times "
                                               f"{self.excess:g}"
                                               + (", plus the given extrinsic's own covariance"
                                                  if self.given_covariance is not None else ""),
                     "smallest_flagged": None if flagged is None else {
                         "rotation_deg_about_camera_xyz": finite(flagged[0]),
                         "translation_mm_along_camera_xyz": finite(flagged[1])}},
            "T_camera_lidar_given": self.T_given.tolist(), "convention": CONVENTION,
            "covariance_given": None if self.given_covariance is None else self.given_covariance.tolist(),
            "intrinsics": self.camera.as_dict(),
            "scene": {"T_camera_lidar": self.fit.T_camera_lidar.tolist(),
                      "covariance": self.believed_covariance.tolist(), "covariance_excess": self.excess,
                      "covariance_blocks": self.fit.covariance.tolist(),
                      "covariance_convention": COVARIANCE_CONVENTION,
                      "std_rotation_deg_about_camera_xyz": rot.tolist(),
                      "std_translation_mm_along_camera_xyz": trans.tolist(),
                      "rms_px_at_given": self.fit.rms_start_px, "rms_px": self.fit.rms_px,
                      "converged": self.fit.converged, "contour_returns": self.fit.points},
            "rival_minima": [{"T_camera_lidar": f.T_camera_lidar.tolist(), "rms_px": f.rms_px} for f in self.rivals],
            **({"camera": self.sensors[0], "lidar": self.sensors[1]} if self.sensors else {}),
            "frames_used": list(self.frames_used), "skipped": self.skipped, "board_left_out": self.board_left_out,
            "timings_s": {"check": self.seconds},
        }


def _board_pose(gray: np.ndarray, board, camera: CameraModel) -> np.ndarray | None:
    """``T_camera_board`` where the camera finds the board, else None (a calibration of these images searched them
    already, and so did the board's mask: ``detect_corners`` keeps what it found)."""
    from ..camera.board_pose import estimate_board_pose
    from ..camera.corners import detect_corners

    try:
        det = detect_corners(gray, board)
        if not isinstance(det, CornerDetection):
            return None
        return estimate_board_pose(det, board, camera).T_camera_board
    except LidarcamError:
        return None


def _board_mask(gray: np.ndarray, board, camera: CameraModel) -> np.ndarray | None:
    """The board's outline (widened by ``BOARD_MARGIN_PX``) as a mask, where the camera finds the board."""
    T_camera_board = _board_pose(gray, board, camera)
    if T_camera_board is None:
        return None
    uv = camera.project(transform_points(T_camera_board, board.outline()))
    if not np.all(np.isfinite(uv)):
        return None
    mask = np.zeros(gray.shape[:2], np.uint8)
    cv2.fillPoly(mask, [np.round(uv).astype(np.int32)], 1)
    k = 2 * BOARD_MARGIN_PX + 1
    return cv2.dilate(mask, np.ones((k, k), np.uint8)) > 0


def frame_edges(gray: np.ndarray, T: np.ndarray, camera: CameraModel, board_mask: np.ndarray | None = None
                ) -> EdgeMap:
    """A frame's image edges square enough to the LiDAR's rings under ``T`` (``transverse_edges``), the board's
    mask left out."""
    uv, normals = edges_with_normals(gray, ignore=board_mask)
    keep = transverse_edges(uv, normals, T, camera)
    return EdgeMap.of(gray.shape[:2], uv[keep], normals[keep])


def scene_view(name: str, gray: np.ndarray, sweep, T_given: np.ndarray, camera: CameraModel,
               board_mask: np.ndarray | None = None, truncate_px: float = TRUNCATE_PX,
               edges: EdgeMap | None = None) -> SceneView:
    """One frame's contour returns the camera sees under ``T_given`` and its edges (:func:`frame_edges`, or
    ``edges`` when made already), the board's mask left out of both; the residuals truncated at ``truncate_px``."""
    if sweep.ring is None:
        raise LidarcamError("the sweep has no beam index (a ring field or an organised cloud): its contours "
                            "cannot be found along the beams")
    contours = depth_edges(sweep.points, sweep.ring)
    steps = beam_steps(sweep.points, sweep.ring)
    spacing = beam_spacing_px(sweep.points, sweep.ring, camera, steps)
    P = contours.points[visible_from_camera(contours.points, sweep.points, T_given, camera, spacing_px=spacing)]
    if board_mask is not None:
        uv = camera.project(transform_points(T_given, P))
        ok = np.all(np.isfinite(uv), axis=1)
        on = np.zeros(len(P), bool)
        u = np.clip(np.round(uv[ok, 0]).astype(int), 0, gray.shape[1] - 1)
        v = np.clip(np.round(uv[ok, 1]).astype(int), 0, gray.shape[0] - 1)
        on[ok] = board_mask[v, u]
        P = P[~on]
    edges = frame_edges(gray, T_given, camera, board_mask) if edges is None else edges
    return SceneView(name, P, edges, truncate_px, steps[0])


@dataclass(frozen=True, eq=False)
class SceneFrame:
    """One frame as the scene's measurements read it: its image, its sweep and the board's mask (or None)."""

    name: str
    gray: np.ndarray
    sweep: object
    board_mask: np.ndarray | None
    index: int = 0  # its place in the folder's numbering
    files: tuple = ()  # its image's and scan's names, for the words


def read_scene_frames(folder: str | os.PathLike, keep_board: bool = False, camera: CameraModel | None = None,
                      sensors: tuple[str, str] | None = None
                      ) -> tuple[os.PathLike, CameraModel, object, list[SceneFrame], dict]:
    """A scene folder's root, camera (``camera`` when given, else dataset.yaml's), board (or None), its frames
    (images, sweeps with their beams, the board's masks unless ``keep_board``) and the frames skipped with their
    reasons; ``sensors``: a rig folder's camera and LiDAR (``io.rig_dataset.scene_pair``)."""
    load = scene_pair if is_rig(folder) else load_scene_folder
    root, own, board, frames = load(folder, camera is None, sensors)
    if camera is not None and own is not None and (camera.width, camera.height) != (own.width, own.height):
        raise DatasetError(f"the intrinsics given ({camera.source}) are for {camera.width}x{camera.height} images, the "
                           f"folder's camera for {own.width}x{own.height}", path=root,
                           hint="give a calibration of this camera at this resolution")
    camera = own if camera is None else camera

    def read(index_f) -> SceneFrame | str:
        index, f = index_f
        try:
            gray = read_gray(f.image)
            if gray.shape[:2] != (camera.height, camera.width):
                return (f"the image is {gray.shape[1]}x{gray.shape[0]}, the camera's intrinsics are for "
                        f"{camera.width}x{camera.height}")
            sweep = read_sweep(f.scan)
            mask = None if keep_board or board is None else _board_mask(gray, board, camera)
        except LidarcamError as exc:
            return exc.problem
        return SceneFrame(f.name, gray, sweep, mask, index, (relative_name(f.image, root), relative_name(f.scan, root)))

    # Decoding, reading and the board's search release the interpreter: two frames at a time.
    with ThreadPoolExecutor(max_workers=READ_THREADS) as pool:
        got = list(pool.map(read, enumerate(frames)))
    beams, why = with_found_beams({g.name: g.sweep for g in got if isinstance(g, SceneFrame)})
    got = [g if not isinstance(g, SceneFrame) else replace(g, sweep=beams[g.name])
           if beams[g.name].ring is not None else why for g in got]
    out = [g for g in got if isinstance(g, SceneFrame)]
    skipped = {f.name: g for f, g in zip(frames, got) if not isinstance(g, SceneFrame)}
    return root, camera, board, out, skipped


def scene_views(frames: list[SceneFrame], T: np.ndarray, camera: CameraModel, skipped: dict,
                truncate_px: float = TRUNCATE_PX) -> list[SceneView]:
    """Every frame's :func:`scene_view` under ``T``; a frame with no contour in the camera's view is added to
    ``skipped`` with that reason. Two frames at a time: the image's edges and their distance map release the
    interpreter."""
    def view_of(f: SceneFrame) -> SceneView | str:
        try:
            return scene_view(f.name, f.gray, f.sweep, T, camera, f.board_mask, truncate_px)
        except LidarcamError as exc:
            return exc.problem

    with ThreadPoolExecutor(max_workers=READ_THREADS) as pool:
        got = list(pool.map(view_of, frames))
    views = []
    for f, view in zip(frames, got):
        if isinstance(view, str):
            skipped[f.name] = view
            continue
        if len(view.points) == 0:
            skipped[f.name] = "no LiDAR contour in the camera's view"
            continue
        skipped.pop(f.name, None)
        views.append(view)
    return views


def too_few(views: list, skipped: dict, root) -> DegenerateLayoutError:
    return DegenerateLayoutError(f"{len(views)} frame(s) usable for the scene"
                                 + (f" (skipped: {'; '.join(f'{k}: {v}' for k, v in skipped.items())})"
                                    if skipped else ""), path=root, hint="give two or more frames")


def refuse_inverted(read: tuple, T_given: np.ndarray, keep_board: bool, sensors: tuple[str, str] | None,
                    what: str) -> None:
    """Refuse ``T_given`` (``what``: the given extrinsic, an initial guess), under which too few frames' contours
    fall in the camera's view, as ``T_lidar_camera`` where the scene agrees with its inverse, checked as
    :func:`check_scene` checks an extrinsic on the frames ``read`` (:func:`read_scene_frames`'s)."""
    try:
        agrees = _checked(read, np.linalg.inv(T_given), keep_board, sensors, None, time.perf_counter()).consistent
    except LidarcamError:
        return
    if agrees:
        raise DatasetError(f"under {what} too few frames' LiDAR contours fall in the camera's view, but under its "
                           "inverse the scene agrees with it: it is T_lidar_camera", path=read[0],
                           hint="give T_camera_lidar, which maps LiDAR points into the camera: inverted")


def check_scene(folder: str | os.PathLike, T_given: np.ndarray, keep_board: bool = False,
                camera: CameraModel | None = None, sensors: tuple[str, str] | None = None,
                given_covariance: np.ndarray | None = None) -> SceneCheck:
    """Check ``T_given`` (``T_camera_lidar``) against the scene of a dataset folder (module docstring).

    Parameters
    ----------
    folder : str or os.PathLike
        A camera-LiDAR folder of synchronised frames (dataset.yaml with ``camera:``; ``board:`` optional), or a
        rig folder (``sensors`` names the pair).
    T_given : numpy.ndarray
        4x4 ``T_camera_lidar`` to check (the camera's from the LiDAR's).
    keep_board : bool
        Keep the board's edges and contours (by default left out where the camera finds the board).
    camera : CameraModel, optional
        The camera's model (a calibration's, its intrinsics refined or estimated: the extrinsic is checked under the
        intrinsics it was estimated with); default dataset.yaml's. Its image size must be the folder's camera's.
    sensors : tuple of str, optional
        A rig folder's camera and 3D LiDAR (default its first camera and first 3D LiDAR).
    given_covariance : numpy.ndarray, optional
        ``T_given``'s own 6x6 covariance (the project's tangent), when it is a calibration's: the test is then of
        two independent estimates of one extrinsic, their difference's covariance the sum of theirs; without it,
        ``T_given`` is taken as exact.

    Returns
    -------
    SceneCheck
        The verdict, ``consistent`` and the test's p-value, the scene's estimate and covariance.

    Raises
    ------
    DatasetError
        A folder without intrinsics, or not a 3D LiDAR's.
    DegenerateLayoutError
        Fewer than two frames with contours in view.
    """
    t0 = time.perf_counter()
    T_given = rigid(T_given, folder, "the given extrinsic")
    read = read_scene_frames(folder, keep_board, camera, sensors)
    checked = _checked(read, T_given, keep_board, sensors, given_covariance, t0, try_inverse=True)
    if checked.consistent is False and read[2] is not None:
        not_numbered_off(read, T_given)
    return checked


def on_board(T_board_lidar: np.ndarray, points: np.ndarray, board) -> int:
    """How many of a sweep's ``points`` lie on the board at ``T_board_lidar``: within ``ON_BOARD_M`` of its plane
    and of its outline."""
    b = transform_points(T_board_lidar, points)
    xy = board.outline()[:, :2]
    inside = np.all((b[:, :2] > xy.min(axis=0) - ON_BOARD_M) & (b[:, :2] < xy.max(axis=0) + ON_BOARD_M), axis=1)
    return int(np.sum(inside & (np.abs(b[:, 2]) < ON_BOARD_M)))


def not_numbered_off(read: tuple, T_given: np.ndarray) -> None:
    """Where the scene contradicted ``T_given``, refuse a folder whose scans are numbered a few frames off its
    images, as ``calibrate`` refuses it from the boards (``measurement.SHIFTS``): under ``T_given``, each image's
    board (where the camera finds it) holds the returns of the scan paired with it (:func:`on_board`, at least
    ``MIN_ON_BOARD`` and half of the most any scan of the shifts puts there) in too few of the frames
    (``SHIFT_AGREEING``), and a shift's scans hold them in ``measurement.shift_agrees`` of its pairs. The scene
    alone cannot name it: a still rig's scene is the same in every frame (the recorded VLP-16 set, each scan a
    frame off, read p = 1e-8 with the next frame's board among the contours, and its own calibration's frames
    paired a frame off agree)."""
    root, camera, board, frames, _ = read
    by_index = {f.index: f for f in frames}
    poses = {f.index: T for f in frames if (T := _board_pose(f.gray, board, camera)) is not None}
    counts = {(i, j): on_board(T_inverse(T) @ T_given, by_index[j].sweep.points, board)
              for i, T in poses.items() for j in (i + s for s in (0,) + SHIFTS) if j in by_index}
    most = {i: max(n for (k, _), n in counts.items() if k == i) for i in poses}

    def held(shift: int) -> tuple[list, int]:
        pairs = [(i, i + shift) for i in poses if (i, i + shift) in counts]
        return pairs, sum(counts[p] >= max(MIN_ON_BOARD, 0.5 * most[p[0]]) for p in pairs)

    pairs, own = held(0)
    if own >= SHIFT_AGREEING * len(pairs) and own > 0:
        return
    for shift in SHIFTS:
        shifted, agreeing = held(shift)
        if len(shifted) < 4 or not shift_agrees(agreeing, len(shifted)):
            continue
        (i, j), (many, later) = shifted[0], shift_words(shift)
        raise DatasetError(
            f"the scene contradicts the given extrinsic, and under it the LiDAR's returns lie on the camera's board "
            f"in {own} of {len(pairs)} frames as the files are paired, but in {agreeing} of {len(shifted)} with each "
            f"image paired with the scan {many} {later} ({by_index[i].files[0]}'s board is in "
            f"{by_index[j].files[1]}): the scans are numbered {many} off their images", path=root, hint=NUMBERING_HINT)


def _checked(read: tuple, T_given: np.ndarray, keep_board: bool, sensors: tuple[str, str] | None,
             given_covariance: np.ndarray | None, t0: float, try_inverse: bool = False) -> SceneCheck:
    """:func:`check_scene` on the frames ``read`` (:func:`read_scene_frames`'s); with ``try_inverse``, a
    ``T_given`` under which too few contours fall in view is tried inverted (:func:`refuse_inverted`)."""
    root, camera, board, frames, skipped = read
    skipped = dict(skipped)
    views = scene_views(frames, T_given, camera, skipped)
    if len(views) < 2:
        if try_inverse:
            refuse_inverted(read, T_given, keep_board, sensors, "the given extrinsic")
        raise too_few(views, skipped, root)
    with about(root):
        fits = nearest_decided(scene_minima(views, camera, T_given, decided=True), views, camera, T_given)
    cov = fits[0].covariance + minima_scatter(fits, views, camera, T_given)
    if sensors is None and is_rig(root):
        sensors = first_pair(root)
    checked = SceneCheck(str(root), np.asarray(T_given, float), fits[0], {}, tuple(v.name for v in views), skipped,
                         camera, board is not None and not keep_board, time.perf_counter() - t0, tuple(views),
                         tuple(rival_minima(fits)), cov, tuple(sensors) if sensors else None,
                         given_covariance=None if given_covariance is None else np.asarray(given_covariance, float))
    return replace(checked, test=consistency(fits[0], T_given, covariance=checked.test_covariance))


def given_in_tangent(C_given: np.ndarray, T_given: np.ndarray, T: np.ndarray) -> np.ndarray:
    """``T_given``'s covariance (its own right tangent) carried to ``T``'s, where the check reads the difference
    ``Log(T^-1 T_given)``: ``T_given Exp(e) = T D Exp(e) = T Exp(Ad(D) e) D`` with ``D = T^-1 T_given``."""
    from ..solvers.factor_graph import adjoint

    A = adjoint(T_inverse(T) @ T_given)
    return A @ np.asarray(C_given, float) @ A.T
