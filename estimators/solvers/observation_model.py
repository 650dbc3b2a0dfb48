"""The generative measurement model of a calibration layout: its Fisher information, its Cramer-Rao
bound, and measurement-level simulation drawn from exactly that model.

A layout is the rig (camera, LiDAR beams, board) with the true extrinsic and the true board poses.
Measurements are the board's corner pixels (independent Gaussian, ``corner_noise_px`` per axis) and
the ranges of the LiDAR beams that hit the board (independent Gaussian along the beam,
``range_noise_m``). The parameters are ``T_camera_lidar`` and every ``T_camera_board``, perturbed in
GTSAM's right tangent; the bound on the extrinsic is the Schur complement of the full information.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from functools import partial

import numpy as np

from geometry.board import BoardModel
from geometry.camera import CameraModel
from geometry.rotations import T_inverse, transform_points

from ..camera.board_pose import estimate_board_pose
from ..camera.detection import CornerDetection
from ..errors import AmbiguousOrientationError, MeasurementError
from ..lidar.lidar_models import BeamModel
from ..measurements import FrameMeasurement, observe_lidar_board, observe_lidar_line
from ..simulation.range_bias import RangeBias
from ..simulation.scene import cast, rectangle
from .factors import corner_residuals, lidar_plane
from .range_model import FrameLabels, RangeTerms, regressors, terms_for


@dataclass(frozen=True, eq=False)
class Layout:
    """A rig and a set of board poses: everything the bound and the measurement simulation need.

    Attributes
    ----------
    camera : CameraModel
        The camera model.
    board : BoardModel
        The board.
    beams : BeamModel
        The LiDAR's beam model (its range noise included).
    T_camera_lidar : numpy.ndarray
        4x4, the extrinsic.
    T_camera_board : tuple of numpy.ndarray
        Each board pose, 4x4.
    corner_noise_px : float
        Effective per-corner pixel noise.
    range_noise_m : float
        Range noise, m.
    hits : tuple or None
        Measured beams per frame (directions and ranges in the LiDAR frame, and their rings when known) instead of
        the beam model's cast.
    outline_error_m : tuple of float or None
        The physical board's outline against the declared one, as the edge model's nuisance
        (``board_edges.OUTLINE``): the growth of the x and the y sides and the outline's offset along the board's
        x and y (m); the LiDAR's beams hit the physical board, the camera sees the pattern where the board frame
        puts it. None: the declared outline.
    """

    camera: CameraModel
    board: BoardModel
    beams: BeamModel
    T_camera_lidar: np.ndarray
    T_camera_board: tuple[np.ndarray, ...]
    corner_noise_px: float
    range_noise_m: float
    # Measured beams per frame ((dirs, ranges) in the LiDAR frame, and their rings when known) instead of the
    # beam model's cast.
    hits: tuple | None = None
    outline_error_m: tuple[float, float, float, float] | None = None

    @property
    def n_frames(self) -> int:
        return len(self.T_camera_board)


def board_hits(layout: Layout, i: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit beam directions (n, 3) of the LiDAR that hit board ``i`` and their true ranges (n,) (LiDAR
    frame). The board is taken as unoccluded. A layout with measured ``hits`` returns those."""
    return board_returns(layout, i)[:2]


def board_returns(layout: Layout, i: int, pointing: tuple[np.random.Generator, float] | None = None
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]:
    """:func:`board_hits` with each return's ring id and whether it lies on a black square (for a layout with
    measured ``hits``: the rings when they hold them, ``(dirs, ranges, rings)``, and no colours). ``pointing``:
    ``(rng, sd)``, each beam's true direction off its nominal one by an isotropic Gaussian angle of ``sd`` rad
    (its footprint's spread and pointing error): whether it hits the board, and its range, are the true
    direction's; the direction returned is the nominal one, as a LiDAR reports it."""
    if layout.hits is not None:
        h = layout.hits[i]
        return h[0], h[1], h[2] if len(h) > 2 else None, None
    T_lidar_board = T_inverse(layout.T_camera_lidar) @ layout.T_camera_board[i]
    R, o = T_lidar_board[:3, :3], T_lidar_board[:3, 3]
    w, h = layout.board.extent
    dirs, rings = layout.beams.directions()
    # Only beams within the board's angular box can hit it: cheap pre-selection before the exact cast.
    x0, y0, x1, y1 = 0.0, 0.0, w, h
    if layout.outline_error_m is not None:  # the physical board: grown and moved against the declared outline
        gx, gy, ox, oy = layout.outline_error_m
        x0, y0, x1, y1 = ox - gx, oy - gy, w + gx + ox, h + gy + oy
    corners = np.array([[x0, y0, 0.0], [x1, y0, 0.0], [x1, y1, 0.0], [x0, y1, 0.0]])
    outline = transform_points(T_lidar_board, corners)
    centre = outline.mean(0) / np.linalg.norm(outline.mean(0))
    cos_min = float(np.min((outline / np.linalg.norm(outline, axis=1, keepdims=True)) @ centre))
    widen = 5.0 * pointing[1] if pointing is not None else 0.0  # beams just outside may hit off their nominal
    keep = dirs @ centre >= np.cos(np.arccos(min(cos_min, 1.0)) + widen) - 1e-9
    near, rings = dirs[keep], rings[keep]
    true = near
    if pointing is not None:
        rng, sd = pointing
        off = rng.normal(0.0, sd, near.shape)
        off -= near * np.sum(off * near, axis=1, keepdims=True)  # across the beam
        true = near + off
        true /= np.linalg.norm(true, axis=1, keepdims=True)
    reflectance = layout.board.reflectance
    if (x0, y0) != (0.0, 0.0):
        reflectance = partial(_shifted_reflectance, layout.board.reflectance, x0, y0)
    board = rectangle(o + x0 * R[:, 0] + y0 * R[:, 1], R[:, 0], R[:, 1], x1 - x0, y1 - y0, reflectance)
    ranges, which, refl = cast(np.zeros(3), true, [board], layout.beams.max_range_m)
    hit = which == 0
    return near[hit], ranges[hit], rings[hit], refl[hit] < 0.5


def _shifted_reflectance(reflectance, x0: float, y0: float, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The board's reflectance on a patch whose origin is ``(x0, y0)`` in the board's frame."""
    return reflectance(a + x0, b + y0)


def corner_pixels(layout: Layout, i: int) -> np.ndarray:
    """True pixels of board ``i``'s inner corners (M, 2), in the board model's row-major order."""
    return layout.camera.project(transform_points(layout.T_camera_board[i], layout.board.inner_corners()))


def seen_corners(layout: Layout, i: int) -> np.ndarray:
    """Which of board ``i``'s inner corners the camera sees: all of a checkerboard's (it is seen whole or
    not at all), the ones inside the image of a ChArUco board."""
    n = len(layout.board.inner_corners())
    if not layout.board.is_charuco:
        return np.arange(n)
    return np.nonzero(layout.camera.sees(transform_points(layout.T_camera_board[i], layout.board.inner_corners())))[0]


def frame_information(layout: Layout, i: int, terms: RangeTerms | None = None) -> np.ndarray:
    """Fisher information of frame ``i`` over ``[xi_extrinsic, xi_board_i]`` (12 x 12), or with range terms
    over ``[xi_extrinsic, beta, xi_board_i]`` (12 + K square; their priors not included)."""
    T_cb = layout.T_camera_board[i]
    K = terms.size if terms is not None else 0
    F = np.zeros((12 + K, 12 + K))
    seen = seen_corners(layout, i)
    _, Jc = corner_residuals(T_cb, layout.board.inner_corners()[seen], corner_pixels(layout, i)[seen], layout.camera)
    F[6 + K:, 6 + K:] += Jc.T @ Jc / layout.corner_noise_px**2
    dirs, ranges, rings, dark = board_returns(layout, i)
    if len(dirs):
        pi, H_x, H_b = lidar_plane(layout.T_camera_lidar, T_cb)
        P1 = np.hstack([dirs * ranges[:, None], np.ones((len(dirs), 1))])
        # A beam's range rho solves pi . [rho b; 1] = 0, so d rho = -[p; 1] . d pi / (m . b); the range terms
        # add a . beta to every measured range.
        scale = -1.0 / (dirs @ pi[:3])
        blocks = [(P1 @ H_x) * scale[:, None]]
        if terms is not None:
            blocks.append(regressors(len(dirs), terms, rings, dark))
        blocks.append((P1 @ H_b) * scale[:, None])
        J = np.hstack(blocks)
        F += J.T @ J / layout.range_noise_m**2
    return F


def frame_contribution(F_frame: np.ndarray) -> np.ndarray:
    """A frame's 6x6 share of the extrinsic's information: its board pose marginalised (Schur complement).
    Frames have their own board poses, so the extrinsic's information is the sum of these shares."""
    return extrinsic_information(F_frame)


def fisher_information(layout: Layout) -> np.ndarray:
    """Fisher information (6 + 6N square) of ``[xi_extrinsic, xi_board_1, ..., xi_board_N]``."""
    N = layout.n_frames
    F = np.zeros((6 + 6 * N, 6 + 6 * N))
    for i in range(N):
        idx = np.r_[0:6, 6 + 6 * i:12 + 6 * i]
        F[np.ix_(idx, idx)] += frame_information(layout, i)
    return F


def extrinsic_information(F: np.ndarray, keep: int = 6) -> np.ndarray:
    """The information on the first ``keep`` parameters (the extrinsic's 6 by default) with the rest (board poses,
    nuisances) marginalised (Schur complement)."""
    A, B, C = F[:keep, :keep], F[:keep, keep:], F[keep:, keep:]
    try:
        return A - B @ np.linalg.solve(C, B.T)
    except np.linalg.LinAlgError:  # board poses the corners do not fix (a board far away): what is fixed
        return A - B @ np.linalg.pinv(C, hermitian=True) @ B.T


def cramer_rao_bound(layout: Layout, terms: RangeTerms | None = None, edges: bool = False,
                     beam_sd_rad: float | None = None) -> np.ndarray:
    """The Cramer-Rao bound of a layout: the least covariance any unbiased estimator can reach.

    Parameters
    ----------
    layout : Layout
        The rig and its board poses.
    terms : RangeTerms, optional
        LiDAR range terms estimated too (with their priors); the bound is then marginal over them.
    edges : bool
        Include the board's edges (ring or segment ends) with the planes; no range terms then.
    beam_sd_rad : float, optional
        The beam's footprint and pointing error for the edges (default: the edge model's).

    Returns
    -------
    numpy.ndarray
        6x6 covariance in the right tangent of ``T_camera_lidar`` (``xi = [rot; trans]``).

    Raises
    ------
    numpy.linalg.LinAlgError
        The information is singular (a degenerate layout); :func:`analyse` names the directions instead.
    ValueError
        ``edges`` with range terms, or without the board's size.
    """
    if edges:
        if terms is not None:
            raise ValueError("the bound with edges and range terms together is not built")
        return np.linalg.inv(edges_information(layout, beam_sd_rad=beam_sd_rad))
    if terms is None:
        return np.linalg.inv(extrinsic_information(fisher_information(layout)))
    return np.linalg.inv(range_model_information(layout, terms))[:6, :6]


def edges_information(layout: Layout, board_scatter_m: float = 0.0, beam_sd_rad: float | None = None) -> np.ndarray:
    """The 6x6 information on the extrinsic from the board planes and the board's edges (every ring end on the
    board's outline, ``solvers.board_edges``), with the board poses, each frame's outline shift (0 +-
    ``board_scatter_m``; none when 0) and the dataset's outline growth and offset (their priors) marginalised:
    the bound of ``--edges``. ``beam_sd_rad``: the ends' angular noise beyond the azimuth step's (default the
    model's beam footprint, ``board_edges.BEAM_SD_RAD``; 0 for this module's simulated beams, which are exact).
    Needs the board's size; a 2D scan's segment is one ring, its two ends the edges."""
    from .board_edges import (BEAM_SD_RAD, GROWTH_PRIOR_SD_M, OFFSET_PRIOR_SD_M, crossings, edge_residuals,
                              nuisance_jacobians)

    if layout.board.size is None:
        raise ValueError("the edges' bound needs the board's size")
    shifts = board_scatter_m > 0
    info = np.zeros((10, 10))  # extrinsic, the outline's growth (x, y sides) and offset (x, y)
    info[6:, 6:] = np.diag(1.0 / np.array([GROWTH_PRIOR_SD_M] * 2 + [OFFSET_PRIOR_SD_M] * 2) ** 2)
    for i in range(layout.n_frames):
        T_cb = layout.T_camera_board[i]
        # [extrinsic, outline, board pose, shift]
        n = 16 + 2 * shifts
        F = np.zeros((n, n))
        F12 = frame_information(layout, i)
        idx = np.r_[0:6, 10:16]
        F[np.ix_(idx, idx)] += F12
        dirs, ranges, rings, _ = board_returns(layout, i)
        if layout.beams.is_2d:  # one scan line: one ring
            rings = np.zeros(len(dirs), dtype=np.int64)
        if len(dirs) and rings is not None:
            e = crossings(dirs * ranges[:, None], rings, T_inverse(T_cb) @ layout.T_camera_lidar, layout.board,
                          BEAM_SD_RAD if beam_sd_rad is None else beam_sd_rad)
            if e.size:
                _, H_x, H_b = edge_residuals(layout.T_camera_lidar, T_cb, e, layout.board)
                H_g, H_s = nuisance_jacobians(e)
                blocks = [H_x, H_g, H_s, H_b] + ([H_s] if shifts else [])
                J = np.hstack(blocks) / e.sd_m[:, None]
                F += J.T @ J
        if shifts:
            F[16:, 16:] += np.eye(2) / board_scatter_m**2
        info += extrinsic_information(F, keep=10)
    return extrinsic_information(info)


def range_model_information(layout: Layout, terms: RangeTerms) -> np.ndarray:
    """The (6 + K) square information on ``[xi_extrinsic, beta]`` with the board poses marginalised and the
    terms' priors added (Bayesian Cramer-Rao bound of the range model)."""
    K = terms.size
    A = np.diag(1.0 / np.asarray(terms.prior_sd, dtype=float) ** 2)
    info = np.zeros((6 + K, 6 + K))
    info[6:, 6:] = A
    for i in range(layout.n_frames):
        F = frame_information(layout, i, terms)
        n = 6 + K
        info += F[:n, :n] - F[:n, n:] @ np.linalg.solve(F[n:, n:], F[n:, :n])
    return info


def layout_range_terms(layout: Layout, model: str) -> RangeTerms | None:
    """The range terms of ``model`` for the rings and squares this layout's boards are hit on."""
    rets = [board_returns(layout, i) for i in range(layout.n_frames)]
    labels = FrameLabels(tuple(r[2] if not layout.beams.is_2d else None for r in rets),
                         tuple(r[3] if not layout.beams.is_2d else None for r in rets))
    return terms_for(model, labels)


INTENSITY_MODES = ("contrast", "flat", "saturated")


def with_outline_error(layout: Layout, pattern_shift_m: tuple[float, float] = (0.0, 0.0),
                       size_error_m: float = 0.0) -> Layout:
    """The layout when the dataset misstates the board: the pattern printed ``pattern_shift_m`` (board x, y)
    from where the dataset puts it, or the board ``size_error_m`` larger on each axis than given (the pattern
    centred): its ``outline_error_m``. The camera still places the given board."""
    half = 0.5 * size_error_m
    return replace(layout, outline_error_m=(half, half, float(pattern_shift_m[0]), float(pattern_shift_m[1])))


def simulate_measurements(layout: Layout, rng: np.random.Generator, bias: RangeBias | None = None,
                          board_error_m: float = 0.0, rings: bool = True, intensity: str = "contrast",
                          azimuth_phase: bool = False, beam_sd_rad: float = 0.0) -> list[FrameMeasurement]:
    """Simulated measurements of a layout, without rendering or segmentation.

    Per frame: corners with Gaussian pixel noise (the board pose fitted as from a detection) and the board's beam
    returns with Gaussian range noise.

    Parameters
    ----------
    layout : Layout
        The rig and its board poses.
    rng : numpy.random.Generator
        Draws the noise.
    bias : RangeBias, optional
        Systematic range errors added to the returns.
    board_error_m : float
        Each board as the LiDAR sees it is moved from the camera's by a random plane error (distance sd this, tilt
        sd this over the board's half-size): the overdispersion of real recordings.
    rings : bool
        Give the returns their ring ids (False: as a cloud without a ``ring`` field).
    intensity : str
        ``contrast`` (0 on black squares, 100 elsewhere), ``flat`` (50 +- 5) or ``saturated`` (255).
    azimuth_phase : bool
        Fire each sweep at a random phase of its azimuth step, as real sweeps do.
    beam_sd_rad : float
        Each beam's footprint and pointing error (the board's edges blur by it); 0: exact beams.

    Returns
    -------
    list of FrameMeasurement
    """
    if intensity not in INTENSITY_MODES:
        raise ValueError(f"Expected intensity in {INTENSITY_MODES}, got {intensity!r}")
    frames = []
    seen_by_lidar = layout
    if board_error_m > 0:
        from geometry.rotations import R_from_rotvec, T_from_Rt

        err = np.random.default_rng(rng.integers(2**63))  # its own stream: the rest of the draws stay the same
        half = 0.5 * float(np.mean(layout.board.extent))
        moved = []
        for T_cb in layout.T_camera_board:
            tilt = np.append(err.normal(0.0, board_error_m / half, 2), 0.0)
            centre = np.append(0.5 * np.array(layout.board.extent), 0.0)
            # about the board's centre, then along its normal
            T_local = T_from_Rt(R_from_rotvec(tilt), centre - R_from_rotvec(tilt) @ centre
                                + np.array([0.0, 0.0, err.normal(0.0, board_error_m)]))
            moved.append(T_cb @ T_local)
        seen_by_lidar = replace(layout, T_camera_board=tuple(moved))
    phases = pointing = None
    if azimuth_phase:
        phases = np.random.default_rng(rng.integers(2**63)).uniform(0.0, layout.beams.azimuth_step_rad,
                                                                     layout.n_frames)
    if beam_sd_rad > 0:  # its own stream: the rest of the draws stay the same
        pointing = (np.random.default_rng(rng.integers(2**63)), beam_sd_rad)
    for i in range(layout.n_frames):
        uv = corner_pixels(layout, i)
        uv = uv + rng.normal(0.0, layout.corner_noise_px, uv.shape)
        if layout.board.is_charuco:  # the corners in the image, with their ids
            seen = seen_corners(layout, i)
            det = CornerDetection(uv[seen], "simulated", corner_ids=seen)
        else:
            det = CornerDetection(uv, "simulated")
        alternatives: tuple = ()
        try:
            cam, why = estimate_board_pose(det, layout.board, layout.camera), None
        except AmbiguousOrientationError as exc:  # kept with both tilts, for a choice by the laser (2D)
            cam, why, alternatives = None, f"board pose: {exc.message}", exc.observations
        except MeasurementError as exc:  # as the pipeline does: the frame is kept, unusable, with the reason
            cam, why = None, f"board pose: {exc.message}"
        swept = seen_by_lidar
        if phases is not None:
            swept = replace(seen_by_lidar, beams=replace(layout.beams, azimuth_phase_rad=float(phases[i])))
        dirs, ranges, ring_ids, dark = board_returns(swept, i, pointing)
        if len(dirs) < 3:
            frames.append(FrameMeasurement(f"{i:04d}", cam, None, why or f"only {len(dirs)} LiDAR beams hit the board"))
            continue
        measured = ranges + rng.normal(0.0, layout.range_noise_m, len(ranges))
        if bias is not None and ring_ids is not None:
            measured = measured + bias.of(ring_ids, dark)
        points = dirs * measured[:, None]
        if layout.beams.is_2d:
            frames.append(FrameMeasurement(f"{i:04d}", cam, observe_lidar_line(points), why,
                                           camera_alternatives=alternatives))
            continue
        obs = observe_lidar_board(points)
        if ring_ids is not None:
            value = {"contrast": lambda: np.where(dark, 0.0, 100.0),
                     "flat": lambda: rng.normal(50.0, 5.0, len(dark)),
                     "saturated": lambda: np.full(len(dark), 255.0)}[intensity]()
            obs = replace(obs, rings=ring_ids if rings else None, intensity=value)
        frames.append(FrameMeasurement(f"{i:04d}", cam, obs, why))
    return frames
