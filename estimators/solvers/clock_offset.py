"""The extrinsic and the sensors' clock offset together, from a board moving through a continuous recording.

The camera's board poses, each at its image's stamp (mid-exposure, the camera's clock), make the board's pose a
continuous function of time (``geometry.trajectory.PoseSpline``). A LiDAR return fired at ``t`` in the LiDAR's
clock happened when the camera's clock read ``t + dt``, ``dt = t_camera_stamp - t_lidar_stamp`` (the project's
convention); mapped by ``T_camera_lidar`` it lies on the board's plane where the board was then. Each return's
range less the range along its beam to that plane is a residual (along the beam, as the LiDAR errs);
``T_camera_lidar`` and ``dt`` minimise their sum of squares.

The start: for each ``dt`` of a grid over the offset's prior interval, the closed form of the sweeps' planes (each
LiDAR sweep's board returns fitted, against the camera's board plane at their mean time plus ``dt``), scored by the
residuals; the best starts a trust-region refinement of the seven unknowns (scipy's ``least_squares``) against the
camera's trajectory as given. Then every image's board pose joins them as an unknown held by its own measurement
(``moving_board_graph``): the estimate and its 7x7 covariance carry the camera's pose noise with the LiDAR's.
The joint solve keeps the returns whose beam meets the board well inside its edges (``EDGE_MARGIN_M``), and the
camera's pointing is added to the covariance (``POINTING_SD_PX``).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from geometry.planes import Plane, fit_plane_pca
from geometry.rotations import T_inverse, T_retract, transform_points
from geometry.trajectory import PoseSplines

from ..errors import DatasetError, DegenerateLayoutError, LidarcamError, in_pair
from ..measurements import TimedBoardView, TimedSweep
from .closed_form import (MIRROR_CAUSE, MIRROR_HINT, is_mirror_fit, solve_closed_form,
                          turned_and_reflected_deg)
from .factor_graph import adjoint
from .moving_board_graph import LidarBlock, along_beam_residuals, refine_many, stamp_jitter_s, with_stamp_jitter

# The clocks' offset is looked for within this (seconds) unless told: driver and transport delays.
OFFSET_PRIOR_S = 0.2
# The start's grid over the offset (s): finer than the refinement's basin (the board's motion within it moves
# the planes by millimetres).
GRID_STEP_S = 0.005
# Returns per sweep used at most (spread over the sweep's board returns): the refinement's cost stays bounded.
MAX_RETURNS_PER_SWEEP = 200
MIN_SWEEPS = 6
# The longest gap between the camera's views across which the board's pose is interpolated (s).
MAX_GAP_S = 0.15
# Returns per sweep that score the start's grid.
GRID_RETURNS = 20
# A return is used only where its beam meets the board (where the camera puts it) this far inside the board's
# edge (m) plus EDGE_SIGMAS of the returns' range noise. Segmentation cuts each sweep's returns to the board's
# rectangle by the noisy points, so by the edges it keeps the returns whose noise pulled them inwards: a bias
# shared by every sweep, which the hundreds of thousands of returns of a recording no longer average away (on a
# simulated bag, the extrinsic and offset's NEES 33 -> 10 with it). The beam's own meeting point carries no range
# noise: chosen by it, the returns kept are unbiased.
EDGE_MARGIN_M = 0.015
EDGE_SIGMAS = 2.5
# Returns this far off the board (RMS, m) at the best fit are not its returns (a spinning LiDAR's range noise is
# 1-3 cm): refused as such rather than as too few inside its edges.
FAR_RMS_M = 0.2
# The standard deviation (px) of an image-wide shift of the detected corners: a principal point's error, a
# detector's bias. It turns every board pose the camera gives about its centre, which no number of images
# averages away, and no data can tell from the extrinsic's own rotation. On the simulated bags (exact
# intrinsics; corners detected in drawn, blurred images) the extrinsic's rotation about the camera's x and y was
# off by more than the corners' noise explains (NEES 11 over 12 bags), and 0.1 px made it 6.9. Much of that excess
# was a resting board's images counted as independent (``STILL_M``): with them counted once, the NEES over 24 bags
# (seeds 0-11 and 100-111) is 7.6 without this term, 7.0 at 0.03 px, 6.6 at 0.05 px (6.2 and 6.9 per set) and 6.0
# at 0.1 px; 0.05 px keeps both sets within 7 +- 1 on the sure side. A principal point known to less makes the
# rotation less sure (the moving-board how-to).
POINTING_SD_PX = 0.05
# A board that rests shows every image the same corners, and their errors with them (the detector's bias on that
# view, the pixels' fixed pattern): images of one still board pose count together as one, each image's pose
# covariance multiplied by the number of images in its run of poses that moved less than this (m) from one to the
# next (a board moving at 0.1 m/s moves 5 mm between images at 20 Hz).
STILL_M = 0.002
# A sweep whose board the segmentation took from another planar piece of the scene (a patch of wall of the board's
# size at the board's range: 1 of 469 sweeps of a simulated 48 s bag) lies metres from the board, and along a beam
# that meets the board's plane at a grazing angle, more: left alone it decides the start's grid and drags the
# refinement off (the bag was refused). The grid scores residuals clipped at OUTLIER_M (m), and a sweep whose returns'
# median distance from the board's plane at the start exceeds OUTLIER_M, or OUTLIER_FACTOR times the sweeps' median
# of it, is left out (not counted in ``sweeps``; ``sweeps_with_board`` still counts it). From the plane, not along
# the beam: a board seen at a grazing angle has long residuals along its beams (3 sweeps of one of 30 simulated
# recordings were left out that way) and is no outlier.
OUTLIER_M = 0.15
OUTLIER_FACTOR = 5.0


@dataclass(frozen=True, eq=False)
class MovingFit:
    """The joint solve's problem at its estimate, for the posterior (``moving_posterior``): the board's trajectory
    where the solve left it (knots ``K`` at ``tau``), the returns it used (``points``, LiDAR frame, at ``times_s``
    in the LiDAR's clock with their sweep's time nuisance), their range noise ``sigma_r`` (m), the estimate, its
    7x7 covariance without the camera's pointing and that pointing's 6x6 share, the offset's prior half-width
    (s) and whether the offset was free. ``sigma_r`` is the noise the joint solve weighed the returns by."""

    tau: np.ndarray
    K: np.ndarray
    points: np.ndarray
    times_s: np.ndarray
    sigma_r: float
    T_camera_lidar: np.ndarray
    time_offset_s: float
    covariance: np.ndarray
    pointing: np.ndarray
    offset_prior_s: float
    free_offset: bool


@dataclass(frozen=True)
class ClockOffsetSolution:
    """``T_camera_lidar`` with the clocks' offset.

    Attributes
    ----------
    T_camera_lidar : numpy.ndarray
        4x4.
    time_offset_s : float
        ``t_camera_stamp - t_lidar_stamp`` for one instant.
    covariance : numpy.ndarray
        7x7 over ``[rot; trans; offset]`` (the extrinsic's in GTSAM's right tangent; see the module for what it
        counts). Held offset: its row and column 0.
    rms_m : float
        The returns' RMS range residual against the board where it was (on the camera's trajectory as measured).
    sweeps : int
        Sweeps used (those whose returns fall within the camera's trajectory at every offset of the prior).
    grid : tuple
        ``(offsets_s, rms_m)``: the start's profile over the prior interval.
    fit : MovingFit or None
        The joint solve's problem at the estimate (for the posterior).
    """

    T_camera_lidar: np.ndarray
    time_offset_s: float
    covariance: np.ndarray
    rms_m: float
    sweeps: int
    grid: tuple
    fit: MovingFit | None = None


def camera_trajectory(views: list[TimedBoardView]) -> PoseSplines:
    """The board's pose in the camera, continuous in the camera's clock through its views (in stamp order), in runs
    split where the views are more than ``MAX_GAP_S`` apart."""
    views = sorted(views, key=lambda v: v.stamp_s)
    return PoseSplines(np.array([v.stamp_s for v in views]), np.array([v.camera.T_camera_board for v in views]),
                       MAX_GAP_S)


def deskewed(points: np.ndarray, times_s: np.ndarray, T_camera_lidar: np.ndarray, time_offset_s: float,
             trajectory, at_s: float) -> np.ndarray:
    """A moving board's LiDAR returns (``points``, LiDAR frame, fired at ``times_s`` in the LiDAR's clock) in the
    camera's frame as they would lie had the board stood where it was at the camera's time ``at_s``: each mapped
    into the camera, then carried with the board from where the camera's ``trajectory`` puts it at the return's
    time (plus the offset) to where it puts it at ``at_s``."""
    p_c = points @ T_camera_lidar[:3, :3].T + T_camera_lidar[:3, 3]
    then = trajectory(np.asarray(times_s, dtype=float) + time_offset_s)
    now = trajectory(float(at_s))
    in_board = np.einsum("nji,nj->ni", then[:, :3, :3], p_c - then[:, :3, 3])  # R^T (p - t), per return
    return in_board @ now[:3, :3].T + now[:3, 3]


def inside_board_by(T: np.ndarray, dt: float, trajectory, points: np.ndarray, times_s: np.ndarray,
                    extent: tuple[float, float]) -> np.ndarray:
    """How far (m) inside the board's ``extent`` (its rectangle from the board frame's origin) each return's beam
    meets the board's plane, the board where the camera's trajectory puts it at the return's time plus ``dt``, the
    beam mapped by ``T`` = ``T_camera_lidar``; negative outside (a beam along the plane: its return's own point)."""
    T_cb = trajectory(np.asarray(times_s, dtype=float) + dt)
    ranges = np.linalg.norm(points, axis=1)
    reach = ranges - along_beam_residuals(T, T_cb[:, :3, :3], T_cb[:, :3, 3], ranges, points / ranges[:, None])
    hit = transform_points(T, points * (reach / ranges)[:, None]) - T_cb[:, :3, 3]  # the cut, camera frame
    local = np.einsum("nji,nj->ni", T_cb[:, :3, :3], hit)  # in the board frame
    w, h = extent
    return np.minimum.reduce([local[:, 0], w - local[:, 0], local[:, 1], h - local[:, 1]])


def still_runs(K: np.ndarray, extent: tuple[float, float]) -> np.ndarray:
    """For each of the board poses ``K`` (n, 4, 4, in time order) the number of poses in its run of consecutive ones
    whose board (its outline's corners, ``extent``) moved less than ``STILL_M`` from the one before: 1 for a
    moving board."""
    w, h = extent
    outline = np.array([[0, 0, 0], [w, 0, 0], [w, h, 0], [0, h, 0]], dtype=float)
    P = np.einsum("nij,kj->nki", K[:, :3, :3], outline) + K[:, None, :3, 3]
    still = np.linalg.norm(np.diff(P, axis=0), axis=2).max(axis=1) < STILL_M
    run_id = np.concatenate([[0], np.cumsum(~still)])  # a new run wherever the board moved
    return np.bincount(run_id)[run_id].astype(float)


def pointing_covariance(T_camera_lidar: np.ndarray, sd_x_rad: float, sd_y_rad: float) -> np.ndarray:
    """The camera's pointing as a 6x6 covariance of ``T_camera_lidar`` (its right tangent): the camera's frame
    turned about its x and y axes by these standard deviations (an image-wide shift of the corners turns every
    board pose so, and the extrinsic's rotation takes it up whole: added, not estimated)."""
    return joint_pointing([T_camera_lidar], sd_x_rad, sd_y_rad)[:6, :6]


def joint_pointing(Ts: list[np.ndarray], sd_x_rad: float, sd_y_rad: float) -> np.ndarray:
    """:func:`pointing_covariance` of several LiDARs' ``T_camera_lidar`` together, (7L, 7L) over each one's
    ``[rot; trans; offset]``: one turn of the camera's frame moves every LiDAR's extrinsic (``Exp(d) T = T
    Exp(Ad(T^-1) [d; 0])``), so their shares correlate fully, and a transform between two LiDARs is free of it."""
    A = np.zeros((7 * len(Ts), 3))
    for j, T in enumerate(Ts):
        A[7 * j:7 * j + 6] = adjoint(T_inverse(T))[:, :3]
    return A @ np.diag([sd_x_rad ** 2, sd_y_rad ** 2, 0.0]) @ A.T


def _residuals(T: np.ndarray, dt: float, trajectory, points: np.ndarray, times_s: np.ndarray
               ) -> np.ndarray:
    """``moving_board_graph.along_beam_residuals`` with the board where the camera's trajectory puts it at each
    return's time plus ``dt`` (m)."""
    T_cb = trajectory(times_s + dt)
    ranges = np.linalg.norm(points, axis=1)
    return along_beam_residuals(T, T_cb[:, :3, :3], T_cb[:, :3, 3], ranges, points / ranges[:, None])


@dataclass(frozen=True, eq=False)
class _Start:
    """One LiDAR's two-step estimate (``T``, ``dt``) and what the joint solve takes of it: the returns inside the
    camera's trajectory and the board (``block``), every kept return (``points``, ``times``: the final RMS), the
    sweeps used and the start's grid."""

    block: LidarBlock
    points: np.ndarray
    times: np.ndarray
    sweeps: int
    grid: tuple


def _start(views: list[TimedBoardView], trajectory, sweeps: list[TimedSweep], offset_prior_s: float,
           grid_step_s: float, fixed_offset_s: float | None, rng: np.random.Generator, returns_per_sweep: int,
           extent: tuple[float, float] | None) -> _Start:
    """One LiDAR's sweeps against the camera's ``trajectory``: the grid over the offset, the two-step refinement
    and the returns the joint solve keeps (see :func:`solve_clock_offset`)."""
    kept = []
    for s in sweeps:
        # A sweep's returns where the camera followed the board at every offset of the prior (no gap of its views
        # over MAX_GAP_S within reach): elsewhere no spline says where the board was.
        inside = trajectory.covers(s.times_s + (fixed_offset_s or 0.0), offset_prior_s if fixed_offset_s is None
                                   else 0.0)
        points, t = s.points[inside], s.times_s[inside]
        if len(t) >= 10:
            pick = rng.choice(len(t), returns_per_sweep, replace=False) if len(t) > returns_per_sweep \
                else np.arange(len(t))
            kept.append((points[pick], t[pick], fit_plane_pca(points)))
    if len(kept) < MIN_SWEEPS:
        raise DegenerateLayoutError(f"only {len(kept)} LiDAR sweeps see the board within the camera's recording "
                                    f"(at least {MIN_SWEEPS} needed)")
    points = np.concatenate([k[0] for k in kept])
    times = np.concatenate([k[1] for k in kept])
    mean_times = np.array([k[1].mean() for k in kept])

    offsets = np.arange(-offset_prior_s, offset_prior_s + 0.5 * grid_step_s, grid_step_s) \
        if fixed_offset_s is None else np.array([float(fixed_offset_s)])
    few_points = np.concatenate([k[0][:GRID_RETURNS] for k in kept])  # each sweep's first: the grid's score
    few_times = np.concatenate([k[1][:GRID_RETURNS] for k in kept])
    rms, starts, fits = [], [], []
    planes_l = [k[2].facing_away() for k in kept]
    for dt in offsets:
        cam = trajectory(mean_times + dt)
        planes_c = [Plane(T[:3, 2], T[:3, 2] @ T[:3, 3]).facing_away() for T in cam]
        fits.append(turned_and_reflected_deg(planes_c, planes_l))
        try:
            T0 = solve_closed_form(planes_c, planes_l, allow_weak=True).T_camera_lidar
        except DegenerateLayoutError:
            rms.append(np.inf)
            starts.append(None)
            continue
        r = np.minimum(np.abs(_residuals(T0, dt, trajectory, few_points, few_times)), OUTLIER_M)
        rms.append(float(np.sqrt(np.mean(r ** 2))))
        starts.append(T0)
    _not_mirrored(np.array(fits))
    best = int(np.argmin(rms))
    if not np.isfinite(rms[best]):
        raise DegenerateLayoutError("the sweeps' board planes do not determine the extrinsic at any clock offset "
                                    "(their normals do not span 3D: turn the board more while waving it)")
    # (the grid's last step may overshoot the prior's edge by a rounding: held inside it, the bounds' start; a held
    # offset stays as given)
    T0, dt0 = starts[best], float(offsets[best] if fixed_offset_s is not None else
                                  np.clip(offsets[best], -offset_prior_s, offset_prior_s))

    kept = _on_the_board(kept, T0, dt0, trajectory)
    points = np.concatenate([k[0] for k in kept])
    times = np.concatenate([k[1] for k in kept])

    free = 7 if fixed_offset_s is None else 6

    def f(x):
        return _residuals(T_retract(T0, x[:6]), x[6] if free == 7 else dt0, trajectory, points, times)

    from scipy.optimize import least_squares  # here: scipy.optimize takes 0.1 s to import, and every calibration
    # imports this module (a still-pose recording's offset), few solve a moving board

    x0 = np.r_[np.zeros(6), dt0][:free]
    bounds = (np.r_[[-np.inf] * 6, -offset_prior_s][:free], np.r_[[np.inf] * 6, offset_prior_s][:free])
    fit = least_squares(f, x0, method="trf", x_scale=np.r_[[1e-3] * 3, [1e-2] * 3, 1e-3][:free], bounds=bounds,
                        ftol=1e-12, xtol=1e-12, gtol=1e-12)
    T, dt = T_retract(T0, fit.x[:6]), float(fit.x[6]) if free == 7 else dt0
    r = fit.fun
    # Returns in a gap of the camera's views (the board out of view, a frame skipped) longer than MAX_GAP_S are
    # left out: no cubic through its ends says where the board was.
    tau = np.sort([v.stamp_s for v in views])
    gap = np.diff(tau)[np.clip(np.searchsorted(tau, times + dt, side="right") - 1, 0, len(tau) - 2)]
    inside = gap <= MAX_GAP_S
    if extent is not None:
        margin = EDGE_MARGIN_M + EDGE_SIGMAS * float(np.sqrt(np.mean(r ** 2)))
        inside &= inside_board_by(T, dt, trajectory, points, times, extent) >= margin
    if inside.sum() < MIN_SWEEPS * GRID_RETURNS:
        rms = float(np.sqrt(np.mean(r ** 2)))
        if rms > FAR_RMS_M:  # no board of any size helps: the returns are not where the camera saw the board
            raise DegenerateLayoutError(f"the LiDAR's board returns lie {1000 * rms:.0f} mm RMS from the board the "
                                        "camera saw, at the best extrinsic and clocks' offset: they do not follow one "
                                        "board", hint="check that the camera's and the LiDAR's topics are of one "
                                                      "recording and the LiDAR's returns are the board's")
        raise DegenerateLayoutError(f"only {int(inside.sum())} LiDAR returns fall where the camera saw the board "
                                    f"at least every {MAX_GAP_S:.2f} s" + ("" if extent is None else
                                    f" and {1000 * margin:.0f} mm inside its edges (a larger board helps)"))
    sweep = np.repeat(np.arange(len(kept)), [len(k[1]) for k in kept])
    block = LidarBlock(points[inside], times[inside], T, dt, float(np.sqrt(np.mean(r[inside] ** 2))), sweep[inside],
                       stamp_jitter_s([s.stamp_s for s in sweeps]))
    return _Start(block, points, times, len(kept), (offsets, np.array(rms)))


# A moving board's sweeps whose normals the best rotation leaves a median this far from the camera's boards, at
# every clocks' offset, fit no extrinsic: with 50 or more sweeps the right one leaves 0.14-0.34 deg, the same
# sweeps mirrored 2.9-33 deg (the clock-offset page's 30 simulated recordings and 12 more with the VLP-16 yawed up
# to 40 deg; an offset held 100 ms off leaves up to 4.1 deg turned, but no reflection within 5 deg). Still poses'
# few boards take MIRROR_MISFIT_DEG.
MOVING_MIRROR_MISFIT_DEG = 1.5


def _not_mirrored(fits: np.ndarray) -> None:
    """Refuse a LiDAR whose sweeps' boards fit the camera's through a mirror at some clock offset of the grid and
    through no rotation at any (``closed_form.is_mirror_fit`` with ``MOVING_MIRROR_MISFIT_DEG``; ``fits``: per
    offset, the median angle left under the best rotation and under the best reflection): its points are in a
    left-handed frame. A simulated waved board's 56 sweeps, y negated or x and y swapped, leave 0.2 deg reflected
    and 14 deg turned at best (the set as recorded the other way round); it read UNTRUSTED as returns 141 mm from
    the board, blaming the board's segment, the clock or the intrinsics."""
    turned, reflected = float(fits[:, 0].min()), float(fits[:, 1].min())
    if is_mirror_fit(turned, reflected, MOVING_MIRROR_MISFIT_DEG):
        raise DatasetError(f"the LiDAR's sweeps of the board match the camera's board through a mirror, and at no "
                           f"clocks' offset through a rotation (their normals {reflected:.1f} deg apart reflected, "
                           f"{turned:.1f} deg turned at best): {MIRROR_CAUSE}", hint=MIRROR_HINT)


def _on_the_board(kept: list, T: np.ndarray, dt: float, trajectory) -> list:
    """The sweeps (``(points, times, plane)``) whose returns' median distance from the board's plane at the start
    (``T``, ``dt``) is within ``OUTLIER_M`` or ``OUTLIER_FACTOR`` times the sweeps' median (see there);
    DegenerateLayoutError where fewer than ``MIN_SWEEPS`` are."""
    def off_plane(points, times):  # the distance from the board's plane (along the beam, a grazing return's is more)
        T_cb = trajectory(times + dt)
        return np.einsum("ni,ni->n", T_cb[:, :3, 2], transform_points(T, points) - T_cb[:, :3, 3])

    medians = np.array([np.median(np.abs(off_plane(k[0], k[1]))) for k in kept])
    on = medians <= max(OUTLIER_M, OUTLIER_FACTOR * float(np.median(medians)))
    if on.sum() < MIN_SWEEPS:
        raise DegenerateLayoutError(f"only {int(on.sum())} of {len(kept)} LiDAR sweeps' board returns lie on the "
                                    "board where the camera saw it at any clock offset of the prior: the LiDAR's "
                                    "board was found elsewhere in the scene")
    return [k for k, ok in zip(kept, on) if ok]


def solve_clock_offset(views: list[TimedBoardView], sweeps: list[TimedSweep],
                       offset_prior_s: float = OFFSET_PRIOR_S, grid_step_s: float = GRID_STEP_S,
                       fixed_offset_s: float | None = None, rng: np.random.Generator | None = None,
                       returns_per_sweep: int = MAX_RETURNS_PER_SWEEP, extent: tuple[float, float] | None = None,
                       pointing_sd_rad: tuple[float, float] = (0.0, 0.0), still_runs_count_once: bool = True
                       ) -> ClockOffsetSolution:
    """``T_camera_lidar`` and the clocks' offset from a moving board (see the module), the offset within
    ``+-offset_prior_s``, or held at ``fixed_offset_s`` (its variance then 0). ``rng`` picks the returns a sweep
    keeps where it has more than ``returns_per_sweep`` (a fixed seed when None): fewer solve faster and see less.
    ``extent``: the board's (width, height) (``BoardModel.extent``): the joint solve then keeps the returns whose beams
    meet it ``EDGE_MARGIN_M`` and ``EDGE_SIGMAS`` of their noise inside its edges (see there); all when None.
    ``pointing_sd_rad``: the camera's pointing uncertainty about its x and y axes (``POINTING_SD_PX`` over the
    focal lengths), added to the extrinsic's covariance.
    Raises DegenerateLayoutError with fewer than ``MIN_SWEEPS`` sweeps inside the camera's trajectory, too few
    returns where the camera saw the board, or an offset outside its prior."""
    return solve_clock_offsets(views, [sweeps], offset_prior_s, grid_step_s, fixed_offset_s, rng, returns_per_sweep,
                               extent, pointing_sd_rad, still_runs_count_once)[0][0]


def solve_clock_offsets(views: list[TimedBoardView], sweeps: list[list[TimedSweep]],
                        offset_prior_s: float = OFFSET_PRIOR_S, grid_step_s: float = GRID_STEP_S,
                        fixed_offset_s: float | None = None, rng: np.random.Generator | None = None,
                        returns_per_sweep: int = MAX_RETURNS_PER_SWEEP, extent: tuple[float, float] | None = None,
                        pointing_sd_rad: tuple[float, float] = (0.0, 0.0), still_runs_count_once: bool = True,
                        names: tuple[str, ...] | None = None) -> tuple[list[ClockOffsetSolution], np.ndarray]:
    """:func:`solve_clock_offset` of several LiDARs (each one's sweeps in the views' time base, its own clock's
    offset) against one camera, in one joint solve: they share the camera's board poses. Each LiDAR's solution
    (its covariance its block of the joint one) and the joint covariance (7 per LiDAR, with the camera's pointing,
    which every LiDAR shares: :func:`joint_pointing`). ``names``: each LiDAR's pair ("cam0-lidar1"), which prefixes
    the error one LiDAR's sweeps raise."""
    rng = rng if rng is not None else np.random.default_rng(0)
    try:
        trajectory = camera_trajectory(views)
    except ValueError as exc:
        raise DegenerateLayoutError(f"the camera's views do not follow the board ({exc})") from None
    starts = []
    for k, s in enumerate(sweeps):
        try:
            starts.append(_start(views, trajectory, s, offset_prior_s, grid_step_s, fixed_offset_s, rng,
                                 returns_per_sweep, extent))
        except LidarcamError as exc:
            if names is None:
                raise
            raise in_pair(exc, names[k]) from exc
    # Then every image's board pose joins the extrinsics and the offsets as an unknown (``moving_board_graph``):
    # the camera's pose noise is in the estimates and their covariance.
    # Both sensors' stamps jitter (read from their spacing): the camera's grows each image's pose covariance, the
    # LiDAR's is a time nuisance per sweep.
    views = sorted(views, key=lambda v: v.stamp_s)
    tau = np.array([v.stamp_s for v in views])
    K = np.array([v.camera.T_camera_board for v in views])
    K_cov = np.array([v.camera.pose_covariance for v in views])
    if still_runs_count_once:
        K_cov = K_cov * still_runs(K, extent if extent is not None else (1.0, 1.0))[:, None, None]
    K_cov = with_stamp_jitter(tau, K, K_cov, stamp_jitter_s(tau))
    free = fixed_offset_s is None
    Ts, dts, cov, K_fit, shifts = refine_many(tau, K, K_cov, [s.block for s in starts], free_offset=free)
    pointing = joint_pointing(Ts, *pointing_sd_rad)
    out = []
    for j, (st, T, dt, shift) in enumerate(zip(starts, Ts, dts, shifts)):
        b = st.block
        at = slice(7 * j, 7 * j + 7)
        fit = MovingFit(tau, K_fit, b.points, b.times + shift, b.sigma_r, T, dt, cov[at, at].copy(),
                        pointing[at, at][:6, :6].copy(), offset_prior_s, free)
        if abs(dt) > offset_prior_s:
            raise DegenerateLayoutError(f"the clocks' offset the recording gives, {1000 * dt:+.0f} ms, lies outside "
                                        f"its prior of +-{1000 * offset_prior_s:.0f} ms: the sensors' clocks are "
                                        "further apart than assumed, or the board's motion leaves the offset "
                                        "unobservable")
        r = _residuals(T, dt, trajectory, st.points, st.times)
        out.append(ClockOffsetSolution(T, dt, cov[at, at] + pointing[at, at], float(np.sqrt(np.mean(r ** 2))),
                                       st.sweeps, st.grid, fit))
    return out, cov + pointing
