"""The clocks' offset of a still-pose recording, from its board's motion between the poses.

``lidarcam extract`` keeps one frame per still pose; where it saw the board move between them it also follows it
into ``motion.npz`` (``io.bag_extract``). The poses give the extrinsic as they always did (a still board does not
care when either sensor looked); the motion gives the offset. It is solved with the extrinsic as a moving board's
is (``solvers.clock_offset``), from the sweeps near the motion (``moving_sweeps``), and then read at the poses'
extrinsic: the Gaussian conditional of the offset on the extrinsic, ``dt + g . log(T_motion^-1 T_poses)`` with
``g`` the 7x7 covariance's regression of the offset on the extrinsic, and the poses' covariance carried through
``g``; or, where the motion's own extrinsic is the surer along ``g`` (a few poses, a long motion), the motion's
own offset with its marginal variance. So the answer is today's, and its offset too.

The offset is given only where the motion's own extrinsic agrees with the poses' (``AGREE_P``), its returns lie on
the board where the camera saw it, and it keeps clear of its prior's edge; otherwise it is "not determined", with
the reason. The extrinsic's verdict does not depend on it.
"""
from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from geometry.rotations import T_inverse, T_log

from ..errors import DegenerateLayoutError
from ..io.motion_track import FOLLOWED_CAMERA, has_motion, load_motion_track
from ..solvers import chi_square as chi2
from ..solvers.clock_offset import MAX_GAP_S, OFFSET_PRIOR_S, POINTING_SD_PX, pointing_covariance, \
    solve_clock_offset, still_runs
from .moving_board import AGAINST_ORDER_WORDS, EDGE_S, OFFSET_SD_S, SCATTER_RATIO, SCATTER_SLACK_M, \
    TIME_OFFSET_CONVENTION, board_views, own_scatter

# The motion's extrinsic and the poses' must agree to this tail probability (chi-square, 6 dof, their covariances
# summed, the motion's with the camera's pointing as a moving board's; the two share only the sweeps at the ends
# of the still intervals, ``moving_sweeps``); below it one of them is off (a board seen moving where the LiDAR did
# not sweep it, a clock that jumps, or the poses' own estimate, which the verdict then questions) and the offset is
# not given.
AGREE_P = 0.001


@dataclass(frozen=True)
class OffsetBetweenPoses:
    """A still-pose recording's clock offset (s, ``t_camera_stamp - t_lidar_stamp``) and its standard deviation,
    None when not determined; ``words`` says how it was found or why not; the images and sweeps of the motion
    used, and the motion's extrinsic's disagreement with the poses' (chi-square, 6 dof)."""

    time_offset_s: float | None
    time_offset_std_s: float | None
    words: str
    images: int = 0
    sweeps: int = 0
    disagreement_chi2: float | None = None
    # The motion's own offset and its standard deviation (the joint solve's marginal, its extrinsic free).
    motion_offset_s: float | None = None
    motion_offset_std_s: float | None = None

    @property
    def disagrees(self) -> bool:
        """The motion's extrinsic and the poses' disagree beyond ``AGREE_P``: one of them is off (the verdict
        says so)."""
        return self.disagreement_chi2 is not None and bool(chi2.sf(self.disagreement_chi2, 6) < AGREE_P)

    def to_dict(self) -> dict:
        """calibration.json's keys (a pair's)."""
        return {"time_offset_s": self.time_offset_s, "time_offset_std_s": self.time_offset_std_s,
                "time_offset_held": False, "time_offset_convention": TIME_OFFSET_CONVENTION,
                "time_offset_source": self.words,
                "time_offset_motion": {"images": self.images, "sweeps": self.sweeps,
                                       "extrinsic_disagreement_chi2_6dof": self.disagreement_chi2,
                                       "own_time_offset_s": self.motion_offset_s,
                                       "own_time_offset_std_s": self.motion_offset_std_s}}

    def line(self, camera: str = "camera", lidar: str = "lidar") -> str:
        """The printout's line (a rig's: its sensors named)."""
        head = f"time offset (t_{camera}_stamp - t_{lidar}_stamp): "
        if self.time_offset_s is None:
            return head + self.words
        return head + f"{1000 * self.time_offset_s:+.2f} +- {1000 * self.time_offset_std_s:.2f} ms ({self.words})"


def time_offsets_keys(offsets: dict) -> dict:
    """A rig's calibration.json keys for its LiDARs' clock offsets (``lidar -> OffsetBetweenPoses``): each against
    the camera that followed the board (``io.motion_track.FOLLOWED_CAMERA``), None where not determined, with how
    it was found or why not."""
    return {"time_offsets_s": {n: o.time_offset_s for n, o in offsets.items()},
            "time_offsets_std_s": {n: o.time_offset_std_s for n, o in offsets.items()},
            "time_offsets_reference": FOLLOWED_CAMERA,
            "time_offsets_convention": f"t_{FOLLOWED_CAMERA}_stamp - t_<sensor>_stamp for one instant (seconds)",
            "time_offsets_source": {n: o.words for n, o in offsets.items()},
            "time_offsets_motion": {n: o.to_dict()["time_offset_motion"] for n, o in offsets.items()}}


def moving_sweeps(views: list, sweeps: list, extent: tuple[float, float]) -> list:
    """The sweeps within reach of the board's motion: those that, at any offset of the prior, fall where the
    camera saw the board move (an image whose board moved ``STILL_M`` or more since the one before). At rest a
    sweep says nothing of the clocks, and the poses already weigh those intervals; weighed again in the motion's
    solve they pulled its extrinsic and, through it, the offset (on a simulated bag of 10 poses the motion's
    extrinsic's NEES 21 with them and 6.4 without, the offset's error -4.9 and -1.9 ms, its sd 1.0 ms)."""
    views = sorted(views, key=lambda v: v.stamp_s)
    tau = np.array([v.stamp_s for v in views])
    moved = tau[still_runs(np.array([v.camera.T_camera_board for v in views]), extent) == 1][1:]
    reach = OFFSET_PRIOR_S + MAX_GAP_S
    return [s for s in sweeps if len(s.offset_s) and np.any(
        (moved >= s.times_s.min() - reach) & (moved <= s.times_s.max() + reach))]


def offset_between_poses(folder: str | os.PathLike, board, camera, T_camera_lidar: np.ndarray,
                         covariance: np.ndarray, rng: np.random.Generator) -> OffsetBetweenPoses | None:
    """The clocks' offset of a still-pose recording from the ``motion.npz`` in ``folder`` (see the module; a
    pair's dataset folder, or a rig's LiDAR's folder, ``RIG/lidar0``), the board followed in ``camera``'s images,
    read at the poses' estimate ``T_camera_lidar`` (6x6 ``covariance``); None when the folder holds no motion or
    the camera has no intrinsics."""
    if not has_motion(folder) or camera is None:
        return None
    track = load_motion_track(folder)
    if track.corners_px.shape[1] != len(board.inner_corners()):
        return OffsetBetweenPoses(None, None, "not determined: motion.npz was read with another board")
    views = board_views(track, board, camera)
    sweeps = moving_sweeps(views, track.sweeps(), board.extent)
    try:
        sol = solve_clock_offset(views, sweeps, rng=rng, extent=board.extent)
    except DegenerateLayoutError as exc:
        return OffsetBetweenPoses(None, None, f"not determined: {exc.problem}", len(views))
    C = sol.covariance  # without the camera's pointing: the offset's regression on the extrinsic is the data's
    g = np.linalg.solve(C[:6, :6], C[:6, 6])
    d = T_log(T_inverse(sol.T_camera_lidar) @ T_camera_lidar)
    pointing = pointing_covariance(sol.T_camera_lidar, POINTING_SD_PX / camera.K[1, 1], POINTING_SD_PX / camera.K[0, 0])
    disagreement = float(d @ np.linalg.solve(C[:6, :6] + pointing + covariance, d))
    # Read at the poses' extrinsic, or the motion's own where its extrinsic is the surer in the offset's direction
    # (g . S g against g . C_TT g: both honest, the smaller variance kept; chosen by the covariances, not the values).
    at_poses = g @ covariance @ g <= g @ C[:6, :6] @ g
    dt = float(sol.time_offset_s + g @ d) if at_poses else float(sol.time_offset_s)
    sd = float(np.sqrt(max(C[6, 6] - C[6, :6] @ g, 0.0) + g @ covariance @ g)) if at_poses else \
        float(np.sqrt(C[6, 6]))
    used = dict(images=len(views), sweeps=sol.sweeps, disagreement_chi2=disagreement,
                motion_offset_s=sol.time_offset_s, motion_offset_std_s=float(np.sqrt(C[6, 6])))
    scatter = own_scatter(track)
    if sol.rms_m > SCATTER_RATIO * scatter + SCATTER_SLACK_M:
        why = (f"its returns lie {1000 * sol.rms_m:.0f} mm RMS from the board where the camera saw it, against "
               f"{1000 * scatter:.0f} mm about their own planes")
    elif chi2.sf(disagreement, 6) < AGREE_P:
        why = (f"the motion's own extrinsic disagrees with the poses' (chi-square {disagreement:.0f}, 6 dof): one "
               "of the two is off")
    elif OFFSET_PRIOR_S - abs(dt) < EDGE_S:
        why = f"it lies at the edge of its prior (+-{1000 * OFFSET_PRIOR_S:.0f} ms)"
    else:
        words = (f"from the board's motion between the poses: {len(views)} images, {sol.sweeps} sweeps; "
                 + ("read at the poses' extrinsic" if at_poses else "the motion's own (its extrinsic the surer)"))
        if sd > OFFSET_SD_S:
            words += "; known to little: move the board faster between poses"
        if track.times_against_order:
            words += f"; {AGAINST_ORDER_WORDS}"
        return OffsetBetweenPoses(dt, sd, words, **used)
    return OffsetBetweenPoses(None, None, f"not determined from the board's motion between the poses: {why}", **used)
