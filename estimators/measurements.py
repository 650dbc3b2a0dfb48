"""Per-frame measurements: the board seen by the camera and by the LiDAR (frozen records)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from geometry.lines import Line2D
from geometry.planes import (
    Plane,
    fit_plane_pca,
    moment_matrix,
    plane_from_moment,
    sqrt_excess_moment,
    sqrt_excess_moment_scan,
)


@dataclass(frozen=True, eq=False)
class CameraBoardObservation:
    """The board's pose and plane in the camera frame, from its detected corners.

    ``pose_covariance`` is 6x6 in the right tangent of ``T_camera_board`` (``[rot; trans]``);
    ``plane_covariance`` is 4x4 over ``[normal; distance]`` (rank 3).
    """

    corners_px: np.ndarray
    T_camera_board: np.ndarray
    plane: Plane
    pose_covariance: np.ndarray
    plane_covariance: np.ndarray
    reprojection_rms_px: float
    detector: str
    # Which of the board's inner corners ``corners_px`` are (ChArUco ids, ascending), None: all of them in
    # ``BoardModel.inner_corners()`` order.
    corner_ids: np.ndarray | None = None
    # One of two tilts that fit the corners alike (``FrameMeasurement.camera_alternatives``): its corner
    # chi-square above the better one's (0 for the better one, and for every unambiguous board).
    orientation_excess_chi2: float = 0.0
    # Checkerboard: whether the image shows white where the board model has black (the detector's grid started
    # at a corner of the other colour), None when not read; ChArUco: False (the ids fix the pattern).
    pattern_inverted: bool | None = None

    def corners_board(self, board) -> np.ndarray:
        """The seen corners in the board frame, (M, 3), in the order of ``corners_px``."""
        corners = board.inner_corners()
        return corners if self.corner_ids is None else corners[self.corner_ids]


@dataclass(frozen=True, eq=False)
class LidarBoardObservation:
    """The board's points and plane in the LiDAR frame (the sensor at the origin).

    ``moment`` is ``sum [p; 1][p; 1]^T`` over the inlier points: the exact sufficient statistics of
    every point-to-plane sum of squares. ``range_moment`` weighs each point by ``1 / cos^2`` of its
    beam's incidence on the fitted plane, so that its plane cost is a sum of squared *range* errors:
    LiDAR noise acts along the beam (MATH.md section 2). ``range_rms_m`` is the range noise that the
    best-fitting plane leaves (``n - 3`` degrees of freedom).

    The points carry their range noise in every coordinate, not only across the plane, so the expected
    moment holds a noise term ``sigma^2 sum w b b^T`` (``b`` the unit beams) that would bias the plane
    (and the extrinsic's rotation) by order ``sigma^2``; ``beam_moment = sum w b b^T`` lets
    :meth:`unbiased_range_moment` remove it (adjusted least squares).
    """

    points: np.ndarray
    plane: Plane
    moment: np.ndarray
    range_moment: np.ndarray
    beam_moment: np.ndarray
    plane_rms_m: float
    range_rms_m: float
    candidates: int
    # 2D LiDAR: the board's laser line in the scan plane (z = 0). ``plane`` is then the vertical plane
    # through it (a stand-in: one line does not fix a plane) and ``plane_rms_m`` the line fit's RMS.
    line: Line2D | None = None
    # Per point, when the scan tells them: the beam (laser) index and the return's intensity. The range
    # model's per-ring and reflectivity terms use them (``solvers.range_model``).
    rings: np.ndarray | None = None
    intensity: np.ndarray | None = None
    # Per point, where the sweep was at hand: its ring's first or last return on the board whose ring goes on in
    # the board's plane beyond it (``board_edges.open_ends``): no edge there.
    open_ends: np.ndarray | None = None

    @property
    def n_points(self) -> int:
        return int(len(self.points))

    @property
    def is_scan_line(self) -> bool:
        return self.line is not None

    def unbiased_range_moment(self, sigma_range_m: float) -> np.ndarray:
        """``range_moment`` less its expected noise term for range noise ``sigma_range_m``."""
        M = self.range_moment.copy()
        M[:3, :3] -= sigma_range_m**2 * self.beam_moment
        return M


# Beams more oblique than this to the board (cos of incidence) are weighed as if at this angle.
MIN_INCIDENCE_COS = 0.1


def observe_lidar_board(points: np.ndarray, candidates: int = 1) -> LidarBoardObservation:
    """The observation record of a board's inlier points (LiDAR frame, the sensor at the origin).

    Range noise lies along the beams, not along the normal, so a plain PCA plane of an oblique board is
    tilted (by up to a few milliradians, centimetres at the board's range). The plane recorded here
    minimises the 1/cos^2-weighted moment less its expected noise term at the noise the points show.
    """
    P = np.asarray(points, dtype=float)
    plane = fit_plane_pca(P)
    beams = P / np.linalg.norm(P, axis=1, keepdims=True)
    for _ in range(2):  # the weights depend on the plane's normal, weakly
        cos = np.maximum(np.abs(beams @ plane.normal), MIN_INCIDENCE_COS)
        w = 1.0 / cos**2
        range_moment = moment_matrix(P, w)
        beam_moment = (beams * w[:, None]).T @ beams
        _, floor = sqrt_excess_moment(range_moment)
        dof = max(len(P) - 3, 1)
        range_rms = float(np.sqrt(max(floor, 0.0) / dof))
        corrected = range_moment.copy()
        corrected[:3, :3] -= range_rms**2 * beam_moment
        plane = plane_from_moment(corrected)
    r = plane.signed_distances(P)
    return LidarBoardObservation(points=P, plane=plane, moment=moment_matrix(P), range_moment=range_moment,
                                 beam_moment=beam_moment, plane_rms_m=float(np.sqrt(np.mean(r**2))),
                                 range_rms_m=range_rms, candidates=candidates)


def observe_lidar_line(points: np.ndarray, candidates: int = 1) -> LidarBoardObservation:
    """The observation record of a board's points on a 2D LiDAR's scan plane ((N, 2) or (N, 3), z = 0).

    As for a plane, the weights are ``1 / cos^2`` of each beam's incidence on the fitted line, the line
    minimises the weighted moment less its expected range-noise term, and ``range_rms_m`` is the range
    noise the best line leaves (``n - 2`` degrees of freedom).
    """
    P2 = np.asarray(points, dtype=float)
    P2 = P2[:, :2] if P2.ndim == 2 and P2.shape[1] >= 2 else P2.reshape(-1, 2)
    if len(P2) < 3:
        raise ValueError(f"Expected at least 3 scan points on a board, got {len(P2)}")
    P = np.column_stack([P2, np.zeros(len(P2))])
    beams = P / np.linalg.norm(P, axis=1, keepdims=True)
    c = P2.mean(0)
    normal2 = np.linalg.eigh((P2 - c).T @ (P2 - c))[1][:, 0]
    for _ in range(2):  # the weights depend on the line's normal, weakly
        cos = np.maximum(np.abs(beams[:, :2] @ normal2), MIN_INCIDENCE_COS)
        w = 1.0 / cos**2
        range_moment = moment_matrix(P, w)
        beam_moment = (beams * w[:, None]).T @ beams
        _, floor = sqrt_excess_moment_scan(range_moment)
        range_rms = float(np.sqrt(max(floor, 0.0) / max(len(P) - 2, 1)))
        corrected = range_moment[np.ix_([0, 1, 3], [0, 1, 3])].copy()
        corrected[:2, :2] -= range_rms**2 * beam_moment[:2, :2]
        c = corrected[:2, 2] / corrected[2, 2]
        normal2 = np.linalg.eigh(corrected[:2, :2] - corrected[2, 2] * np.outer(c, c))[1][:, 0]
    line = Line2D(c, [-normal2[1], normal2[0]])
    r = line.signed_distances(P2)
    plane = Plane(np.append(normal2, 0.0), float(normal2 @ c)).facing_away()
    return LidarBoardObservation(points=P, plane=plane, moment=moment_matrix(P), range_moment=range_moment,
                                 beam_moment=beam_moment, plane_rms_m=float(np.sqrt(np.mean(r**2))),
                                 range_rms_m=range_rms, candidates=candidates, line=line)


def lidar_whitener(obs: LidarBoardObservation, sigma_range_m: float) -> np.ndarray:
    """``W`` of the observation's noise-corrected range moment: 3 x 4 for a board's plane, 2 x 4 for a
    scan line (whose residual is ``W pi / |n_xy|``, see ``factors.lidar_residual``)."""
    M = obs.unbiased_range_moment(sigma_range_m)
    return (sqrt_excess_moment_scan(M) if obs.is_scan_line else sqrt_excess_moment(M))[0]


@dataclass(frozen=True, eq=False)
class BoardDecision:
    """How a frame's LiDAR board was chosen: the method (``consensus`` of the frames under one extrinsic, or
    ``this frame alone`` from its own cues), every candidate with its features and verdict (dicts, as written
    to calibration.json), the index of the chosen one (None: none), why, the pieces rejected before they
    became candidates (reasons), and the candidates' points (LiDAR frame, for the report's top view)."""

    method: str
    candidates: tuple[dict, ...]
    chosen: int | None
    reason: str
    rejected: tuple[str, ...] = ()
    candidate_points: tuple[np.ndarray, ...] = ()

    def to_dict(self) -> dict:
        return {"method": self.method, "chosen": self.chosen, "reason": self.reason,
                "candidates": list(self.candidates), "pieces_rejected": count_reasons(self.rejected)}


def count_reasons(reasons) -> dict[str, int]:
    """How many times each kind of reason occurs (a reason's kind: its text before any parenthesised detail),
    most frequent first."""
    counts: dict[str, int] = {}
    for why in reasons:
        key = why.split(" (")[0]
        counts[key] = counts.get(key, 0) + 1
    return dict(sorted(counts.items(), key=lambda kv: -kv[1]))


@dataclass(frozen=True, eq=False)
class FrameMeasurement:
    name: str
    camera: CameraBoardObservation | None
    lidar: LidarBoardObservation | None
    reason: str | None = None
    decision: BoardDecision | None = None
    # A board whose orientation the corners leave ambiguous (``camera`` is then None): the observation of each
    # tilt, for a choice by the laser line (2D, ``solution_selection.select_and_refine``).
    camera_alternatives: tuple[CameraBoardObservation, ...] = ()

    @property
    def usable(self) -> bool:
        return self.camera is not None and self.lidar is not None


@dataclass(frozen=True, eq=False)
class TimedBoardView:
    """The board in one image of a moving board: its pose at the image's stamp (mid-exposure, the camera's
    clock, seconds)."""

    stamp_s: float
    camera: CameraBoardObservation


@dataclass(frozen=True, eq=False)
class TimedSweep:
    """A LiDAR sweep's returns on a moving board, each at its own time: ``stamp_s`` the sweep's header stamp (the
    LiDAR's clock, seconds), ``points`` (N, 3) in the LiDAR frame and ``offset_s`` (N,) each return's time less the
    stamp (``io.point_times``)."""

    stamp_s: float
    points: np.ndarray
    offset_s: np.ndarray

    @property
    def times_s(self) -> np.ndarray:
        """Each return's time in the LiDAR's clock."""
        return self.stamp_s + self.offset_s
