"""A moving board's recording calibrated: the extrinsic and the sensors' clock offset together, from a dataset folder
that ``lidarcam extract`` wrote from a bag whose board moves (``io.motion_track``).

Every image's board pose is solved from its corners (``camera.board_pose``); the LiDAR's board returns, each at its
own time, are compared with the board where the camera saw it then (``solvers.clock_offset``). The verdict reads
the solution: the offset against its prior's edge, its own spread, the sweeps used, how far the board turned, and
how the camera's board distances scale against the LiDAR's (:func:`moving_distance_scale`).
"""
from __future__ import annotations

import os
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from geometry.camera import CameraModel
from geometry.planes import Plane, fit_plane_pca

from .. import __version__
from ..camera.board_pose import pose_of_corners
from ..errors import DatasetError, DegenerateLayoutError, MeasurementError, PosteriorSkippedError
from ..io.dataset import parse_board, parse_camera, read_dataset_yaml
from ..io.motion_track import MotionTrack, load_motion_track
from ..measurements import TimedBoardView
from ..solvers.clock_offset import OFFSET_PRIOR_S, POINTING_SD_PX, camera_trajectory, deskewed, solve_clock_offsets
from ..solvers.closed_form import distance_scale
from ..solvers.moving_posterior import MovingPosterior, sample_moving_posteriors
from ..solvers.posterior import INTERVAL_LEVELS, equal_tailed
from .pair_estimate import PairEstimate
from .result import CONVENTION, COVARIANCE_CONVENTION
from .verdict import CHECK, UNTRUSTED, Verdict, scale_level, scale_said, verdict_of

# The verdict's limits: an offset this near its prior's edge (s) may be the edge's, not the data's; an offset's
# standard deviation beyond this (s) says the board moved too little to time the sensors; fewer sweeps than this
# leave the estimate to a few seconds of motion; the sweeps' board normals spread less than this (the smallest
# singular value of their matrix over the largest) leave a direction of the extrinsic weak.
EDGE_S = 0.01
# A sweep's board returns enter the distances' scale with at least this many (a plane through them).
MIN_SCALE_RETURNS = 30
# The returns' RMS against the board where the camera saw it may exceed their scatter about each sweep's own plane
# by this ratio and this much (m): the camera's poses and the board's motion within a sweep add a little.
SCATTER_RATIO, SCATTER_SLACK_M = 1.5, 0.005
OFFSET_SD_S = 0.002
FEW_SWEEPS = 30
NORMAL_SPREAD = 0.03
# An image's board pose is solved from the one before within this (s).
FOLLOW_S = 0.15
# A time field that runs against its returns' stored order (``io.motion_track.MotionTrack.times_against_order``).
AGAINST_ORDER_WORDS = ("the LiDAR's time field runs backwards against the order its returns are stored in: the "
                       "clocks' offset holds only if the field, not the order, is the firing time (reversed, it "
                       "moves by up to a sweep; the extrinsic does not depend on it)")
TIME_OFFSET_CONVENTION = "time_offset_s = t_camera_stamp - t_lidar_stamp for one physical instant (seconds)"


@dataclass(frozen=True, eq=False)
class MovingBoardResult:
    """A moving board's calibration: ``pair`` (``cam0``, ``lidar0``: ``T_camera_lidar`` and its 6x6 covariance,
    the posterior's samples when sampled), the clocks' offset and its standard deviation (None when held), the 7x7
    covariance over ``[rot; trans; offset]``, what was used, the posterior (``solvers.moving_posterior``; None
    unsampled, ``posterior_note`` saying why where it was asked for), and for the report the images' board poses
    (``board_views``), the board and the record (``track``). Sampled, the covariances are the samples'."""

    pair: PairEstimate
    time_offset_s: float
    time_offset_std_s: float | None
    covariance_with_offset: np.ndarray
    rms_m: float
    views: int
    sweeps: int
    sweeps_recorded: int
    point_times: str
    normal_spread: float
    own_scatter_m: float
    camera: CameraModel
    dataset: str
    seconds: float
    board_views: tuple = ()
    board: object = None
    track: MotionTrack | None = None
    posterior: MovingPosterior | None = None
    posterior_note: str | None = None
    # ``(s, sd)``: the camera's board distances against the LiDAR's, ``d_c = (1 + s) d_l`` (None: too few sweeps).
    distance_scale: tuple | None = None
    ambiguous = False  # one answer (a 2D scanner's few boards may leave two; a moving board does not)

    @property
    def T_camera_lidar(self) -> np.ndarray:
        return self.pair.T

    @property
    def covariance(self) -> np.ndarray:
        return self.pair.covariance

    @property
    def verdict(self) -> Verdict:
        concerns = []
        if self.rms_m > SCATTER_RATIO * self.own_scatter_m + SCATTER_SLACK_M:
            concerns.append((UNTRUSTED, f"the board's returns lie {1000 * self.rms_m:.0f} mm RMS from the board where "
                                        f"the camera saw it, against {1000 * self.own_scatter_m:.0f} mm about their "
                                        "own planes: no extrinsic and offset explain them (a wrong board segment, "
                                        "a clock that jumps, or intrinsics off)"))
        if self.time_offset_std_s is not None and OFFSET_PRIOR_S - abs(self.time_offset_s) < EDGE_S:
            concerns.append((UNTRUSTED, f"the clocks' offset, {1000 * self.time_offset_s:+.1f} ms, lies at the edge "
                                        f"of its prior (+-{1000 * OFFSET_PRIOR_S:.0f} ms): the data may not hold it"))
        if self.time_offset_std_s is not None and self.time_offset_std_s > OFFSET_SD_S:
            concerns.append((CHECK, f"the clocks' offset is known to {1000 * self.time_offset_std_s:.1f} ms only: "
                                    "wave the board faster or longer"))
        level = scale_level(self.distance_scale)
        if level is not None:
            held = "" if self.time_offset_std_s is not None else (
                f", or the clocks' offset held at {1000 * self.time_offset_s:+.1f} ms (a board moving towards the "
                "camera at the wrong instants: solve it, without --time-offset)")
            concerns.append((level, f"{scale_said(self.distance_scale)}, which no LiDAR errs by: check "
                                    "board.square_size and the camera's intrinsics (its focal length and "
                                    f"distortion){held}; the extrinsic and the offset move with them"))
        if self.time_offset_std_s is not None and self.track is not None and self.track.times_against_order:
            concerns.append((CHECK, AGAINST_ORDER_WORDS))
        if self.sweeps < FEW_SWEEPS:
            concerns.append((CHECK, f"only {self.sweeps} LiDAR sweeps of the board were used: record longer"))
        if self.normal_spread < NORMAL_SPREAD:
            concerns.append((CHECK, "the board turned little while waved (its planes' normals span "
                                    f"{self.normal_spread:.2f} of a full spread): a direction of the extrinsic is "
                                    "weak; tilt it more"))
        return verdict_of(concerns)

    def posterior_summary(self) -> dict | None:
        """The posterior as calibration.json gives it (``posterior``): the chain's diagnostics, the extrinsic's
        standard deviations, intervals and credible regions (``PairEstimate.summary``) and the offset's
        standard deviation and intervals (ms); None unsampled."""
        if self.posterior is None:
            return None
        offset = 1000 * (self.time_offset_s + self.posterior.xi[:, 6])
        out = {**self.posterior.run.diagnostics(), "likelihood": "gaussian", **self.pair.summary(),
               "added": "the camera's board poses, the sweeps' time nuisances and the camera's pointing, as a "
                        "Gaussian draw per sample (solvers.moving_posterior)"}
        if self.time_offset_std_s is not None:
            out["time_offset_ms"] = {"std": float(np.std(offset, ddof=1)), **{
                f"{round(100 * q)}%": equal_tailed(offset[:, None], q)[0].tolist() for q in INTERVAL_LEVELS}}
        return out

    def to_dict(self) -> dict:
        held = self.time_offset_std_s is None
        source = ("the posterior's samples (emcee over the extrinsic and the offset given the board's trajectory, "
                  "the camera's share added; solvers.moving_posterior)" if self.posterior is not None else
                  "the joint solve's (Laplace): every image's board pose, the extrinsic and the offset together, "
                  f"with the camera's pointing (an image-wide corner shift of {POINTING_SD_PX} px) added")
        return {
            "verdict": self.verdict.to_dict(), "tool": "lidarcam", "version": __version__, "dataset": self.dataset,
            "recording": "moving board", "convention": CONVENTION,
            **{k: v for k, v in self.pair.camera_lidar_keys().items() if k not in ("covariance", "std")},
            "time_offset_s": self.time_offset_s, "time_offset_std_s": self.time_offset_std_s,
            "time_offset_held": held, "time_offset_convention": TIME_OFFSET_CONVENTION,
            "covariance": self.pair.covariance.tolist(), "covariance_convention": COVARIANCE_CONVENTION,
            "covariance_with_time_offset": self.covariance_with_offset.tolist(),
            "std": self.pair.camera_lidar_keys()["std"],
            "covariance_source": f"{source}; its coverage on simulated bags: docs/bench/moving_bag.md",
            **({} if self.posterior is None else {"posterior": self.posterior_summary()}),
            **({} if self.posterior_note is None else {"posterior_note": self.posterior_note}),
            "images_used": self.views, "sweeps_used": self.sweeps, "sweeps_with_board": self.sweeps_recorded,
            "range_rms_m": self.rms_m, "range_scatter_own_planes_m": self.own_scatter_m,
            "point_times": self.point_times, "normal_spread": self.normal_spread,
            "distance_scale": None if self.distance_scale is None else {
                "scale": self.distance_scale[0], "std": self.distance_scale[1],
                "meaning": "the camera's board distances against the LiDAR's, d_camera = (1 + scale) d_lidar, each "
                           "sweep's returns carried to one instant, along the camera's board normal then"},
            "intrinsics": self.camera.as_dict(),
            "timings_s": {"solve": self.seconds, **({} if self.posterior is None else
                                                    {"posterior": self.posterior.run.seconds})},
        }


def board_views(track: MotionTrack, board, camera: CameraModel) -> list[TimedBoardView]:
    """Each image's board pose at its stamp, followed from the pose in the image before where that one is within
    ``FOLLOW_S``, else solved from its corners alone (``camera.board_pose.pose_of_corners``); images whose corners
    give no pose are left out."""
    out: list[TimedBoardView] = []
    order = np.argsort(track.view_stamps_s, kind="stable")
    for stamp, corners in zip(track.view_stamps_s[order], track.corners_px[order]):
        if out and stamp <= out[-1].stamp_s:
            continue  # an image stamped as the one before (a driver's repeated stamp): that one holds the instant
        follow = out and stamp - out[-1].stamp_s <= FOLLOW_S
        try:
            obs = pose_of_corners(corners, board, camera, out[-1].camera.T_camera_board if follow else None)
        except MeasurementError:
            continue
        out.append(TimedBoardView(float(stamp), obs))
    return out


def moving_distance_scale(views: list[TimedBoardView], sweeps: list, T_camera_lidar: np.ndarray,
                          time_offset_s: float) -> tuple[float, float] | None:
    """How the camera's board distances scale against the LiDAR's (``closed_form.distance_scale``): each sweep's
    board returns carried to the instant of their mean time (``clock_offset.deskewed``), their median distance along
    the normal of the board where the camera's trajectory puts it then against that board's; the sweeps within the
    trajectory only. A LiDAR
    times its ranges to parts per million, so a percent is the camera's: a wrong square size, focal length or
    distortion. A moving board stands at much the same distance throughout, so the translation takes up most of
    such an error, and what is left is this scale: squares declared 5% long read OK 158 mm off, and scale by
    3.6% +- 0.1%; unmodelled barrel distortion (k1 -0.03 or -0.05 on a 640 x 480 camera) left 0.5-1.4 deg and
    25-130 mm that read OK on 11 of 12 simulated bags, and scales beyond the verdict's limits on 7 of them. With
    the right intrinsics, 44 recordings of ``simulation.waved_board`` and 8 bags scale within 0.7% and 2.8 of
    their standard deviations."""
    trajectory = camera_trajectory(views)
    camera_planes, lidar_planes = [], []
    for sweep in sweeps:
        times = sweep.stamp_s + sweep.offset_s
        if len(times) < MIN_SCALE_RETURNS:
            continue
        at = float(np.mean(times)) + time_offset_s
        if not np.all(trajectory.covers(np.append(times + time_offset_s, at))):
            continue  # its mean time too within a run (a slow LiDAR's sweep about a gap in the images)
        T_cb = trajectory(at)
        normal = T_cb[:3, 2]
        points = deskewed(sweep.points, times, T_camera_lidar, time_offset_s, trajectory, at)
        camera_planes.append(Plane(normal, float(normal @ T_cb[:3, 3])))
        # the returns' median distance along the camera's normal (a few rings' own plane tilts with their range
        # noise, and a regressor that noisy scaled the distances by -1.6 standard deviations on average)
        lidar_planes.append(Plane(normal, float(np.median(points @ normal))))
    return distance_scale(np.eye(4), camera_planes, lidar_planes)


def own_scatter(track: MotionTrack) -> float:
    """The returns' scatter about their own sweep's plane along their beams (m): the median over sweeps of each
    one's RMS; what the solve's residuals should come to."""
    rms = []
    for s in track.sweeps():
        if len(s.points) >= 10:
            plane = fit_plane_pca(s.points)
            beams = s.points / np.linalg.norm(s.points, axis=1, keepdims=True)
            along = plane.signed_distances(s.points) / np.maximum(np.abs(beams @ plane.normal), 0.1)
            rms.append(float(np.sqrt(np.mean(along ** 2))))
    return float(np.median(rms)) if rms else 0.0


def normal_spread(track: MotionTrack) -> float:
    """How far the board turned: the smallest singular value of the sweeps' board normals over the largest."""
    normals = np.array([fit_plane_pca(s.points).facing_away().normal for s in track.sweeps() if len(s.points) >= 3])
    sv = np.linalg.svd(normals, compute_uv=False)
    return float(sv[-1] / sv[0]) if len(sv) == 3 and sv[0] > 0 else 0.0


def calibrate_moving(folder: str | os.PathLike, rng: np.random.Generator, time_offset_s: float | None = None,
                     samples: int = 0) -> MovingBoardResult:
    """The extrinsic and the clocks' offset of a moving board's dataset folder.

    Parameters
    ----------
    folder : str or os.PathLike
        A folder ``lidarcam extract`` wrote from a bag whose board moves (``motion.npz``, dataset.yaml with the
        camera's intrinsics).
    rng : numpy.random.Generator
        Drives the solve's random draws.
    time_offset_s : float, optional
        Hold the clocks' offset ``t_camera_stamp - t_lidar_stamp`` at this value (s) instead of solving it.
    samples : int
        Effective posterior samples to draw (``solvers.moving_posterior``); 0 skips sampling.

    Returns
    -------
    MovingBoardResult
        ``T_camera_lidar`` with its covariance, the offset and its standard deviation, the 7x7 covariance of both,
        the posterior, the verdict (``to_dict`` is calibration.json).

    Raises
    ------
    DatasetError
        No intrinsics, or a record of another board.
    """
    root, ypath, spec = read_dataset_yaml(folder)
    if not isinstance(spec, dict) or spec.get("camera") is None:
        raise DatasetError("a moving board's folder needs the camera's intrinsics (camera: in dataset.yaml)",
                           path=ypath, hint="extract it from a bag with CameraInfo, or add camera: K, dist, width, "
                                            "height")
    board, camera = parse_board(spec.get("board"), ypath), parse_camera(spec["camera"], ypath)
    return solve_moving(root, board, camera, rng, time_offset_s, samples=samples)


def solve_moving(root: Path, board, camera: CameraModel, rng: np.random.Generator, time_offset_s: float | None = None,
                 names: tuple[str, str] = ("cam0", "lidar0"), samples: int = 0) -> MovingBoardResult:
    """The extrinsic and the clocks' offset from the record in ``root`` (``motion.npz``: a pair's folder), the
    ``names`` of its camera and LiDAR; with ``samples``, their posterior."""
    return solve_moving_many([root], board, camera, rng, time_offset_s, names[0], [names[1]], samples)[0][0]


def _track(root: Path, board) -> MotionTrack:
    track = load_motion_track(root)
    if track.corners_px.shape[1] != len(board.inner_corners()):
        raise DatasetError(f"motion.npz holds {track.corners_px.shape[1]} corners per image and the board "
                           f"{len(board.inner_corners())}", path=Path(root) / "motion.npz",
                           hint="give the board the bag was extracted with")
    return track


def solve_moving_many(roots: list[Path], board, camera: CameraModel, rng: np.random.Generator,
                      time_offset_s: float | None, camera_name: str, lidar_names: list[str], samples: int = 0
                      ) -> tuple[list[MovingBoardResult], np.ndarray]:
    """Several LiDARs' records of one camera's moving board (each LiDAR's folder's ``motion.npz``, the board
    followed in that camera's images; the first's views taken for all, each LiDAR's sweeps carried to its time
    base) in one joint solve (``clock_offset.solve_clock_offsets``): each LiDAR's result and the joint covariance
    (7 per LiDAR, the posterior samples' when sampled: row ``k`` of each LiDAR's samples is one joint sample)."""
    tracks = [_track(root, board) for root in roots]
    views = board_views(tracks[0], board, camera)
    if len(views) < 2:
        raise DegenerateLayoutError(f"{len(views)} of the recording's {len(tracks[0].view_stamps_s)} images give the "
                                    "board's pose from their stored corners",
                                    hint="extract the bag again with the board the recording shows")
    sweeps = [[replace(s, stamp_s=s.stamp_s + 1e-9 * (t.origin_ns - tracks[0].origin_ns)) for s in t.sweeps()]
              for t in tracks]
    t0 = time.perf_counter()
    sols, joint = solve_clock_offsets(
        views, sweeps, fixed_offset_s=time_offset_s, rng=rng, extent=board.extent,
        pointing_sd_rad=(POINTING_SD_PX / camera.K[1, 1], POINTING_SD_PX / camera.K[0, 0]),
        names=tuple(f"{camera_name}-{n}" for n in lidar_names) if len(lidar_names) > 1 else None)
    seconds = time.perf_counter() - t0
    posteriors, note = [None] * len(sols), None
    if samples > 0:
        try:
            posteriors = sample_moving_posteriors([s.fit for s in sols], joint, rng, min_ess=samples)
        except PosteriorSkippedError as exc:
            note = f"not sampled ({exc.message}): the covariance is the joint solve's"
        else:
            joint = np.cov(np.hstack([p.xi for p in posteriors]), rowvar=False)
            slow = [p for p in posteriors if not p.run.converged]
            if slow:
                note = (f"did not converge in {slow[0].run.chain.shape[0]} steps ({slow[0].run.ess:.0f} effective "
                        "samples): its intervals are rough")
    held = time_offset_s is not None
    out = []
    for j, (root, track, sol, post, name) in enumerate(zip(roots, tracks, sols, posteriors, lidar_names)):
        cov = joint[7 * j:7 * j + 7, 7 * j:7 * j + 7]
        pair = PairEstimate(camera_name, name, sol.T_camera_lidar, cov[:6, :6], None if post is None else
                            post.xi[:, :6], sol.sweeps)
        out.append(MovingBoardResult(pair, sol.time_offset_s, None if held else float(np.sqrt(cov[6, 6])), cov,
                                     sol.rms_m, len(views), sol.sweeps, len(track.sweep_stamps_s), track.point_times,
                                     normal_spread(track), own_scatter(track), camera, str(Path(root)), seconds,
                                     tuple(views), board, track, post, note,
                                     moving_distance_scale(views, sweeps[j], sol.T_camera_lidar, sol.time_offset_s)))
    return out, joint
