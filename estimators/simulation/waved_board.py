"""A board waved by hand in front of a rig, recorded continuously: the camera's images at its own clock, a spinning
LiDAR's sweeps whose every return is fired at its own time (the board moving meanwhile), and the clocks' offset.

The board's motion is smooth and known in closed form: about a pose both sensors see, a sum of sines per axis
in translation and in rotation (0.15-0.35 Hz), scaled to a peak speed and a peak turn rate, with pauses optional
(the motion eased to rest and out again). The camera images at ``camera_hz``; its stamp is the mid-exposure
instant in its clock, which reads ``time_offset_s`` ahead of the LiDAR's (``t_camera_stamp - t_lidar_stamp`` for
one instant, the project's convention). The LiDAR turns clockwise seen from above, its sweep cut behind it,
each beam's return cast against the board where it is when the beam fires.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial.transform import Rotation

from geometry.rotations import T_inverse, transform_points

from ..camera.board_pose import estimate_board_pose
from ..camera.detection import CornerDetection
from ..errors import MeasurementError
from ..lidar.lidar_models import Rosette, vlp16
from ..measurements import TimedBoardView, TimedSweep
from .simulator import Rig, sample_board_poses

# The sweep is cut behind the LiDAR (azimuth pi), as drivers cut it by default.
CUT_AZIMUTH_RAD = np.pi


@dataclass(frozen=True)
class Waving:
    """A board's motion: ``T_camera_board(t)`` (true time, s): from ``T_base``, turned about the board's point
    ``centre_b`` (board frame) by rotation vectors ``amp_rad * sin(2 pi rot_freq_hz t + rot_phase)`` (camera axes)
    and moved by ``amp_m * sin(2 pi freq_hz t + phase)``; ``pauses``: (start, end) intervals (s) in which it
    rests, the motion eased to rest and out again over ``ease_s`` at either end (a cosine in speed)."""

    T_base: np.ndarray
    centre_b: np.ndarray
    amp_m: np.ndarray
    freq_hz: np.ndarray
    phase: np.ndarray
    amp_rad: np.ndarray
    rot_freq_hz: np.ndarray
    rot_phase: np.ndarray
    pauses: tuple = ()
    ease_s: float = 0.5

    def motion_time(self, t: np.ndarray) -> np.ndarray:
        """The motion's own clock: true time less the time lost resting (its rate falls to 0 and rises again as
        a cosine over ``ease_s`` at each pause's ends)."""
        t = np.asarray(t, dtype=float)
        lost = np.zeros_like(t)
        for a, b in self.pauses:
            e = min(self.ease_s, 0.5 * (b - a))
            x = np.clip(t - a, 0.0, e)  # the ramp down
            lost += 0.5 * x - e / (2 * np.pi) * np.sin(np.pi * x / e)
            lost += np.clip(t - (a + e), 0.0, b - a - 2 * e)  # at rest
            y = np.clip(t - (b - e), 0.0, e)  # the ramp up
            lost += 0.5 * y + e / (2 * np.pi) * np.sin(np.pi * y / e)
        return t - lost

    def __call__(self, t: np.ndarray | float) -> np.ndarray:
        """``T_camera_board`` at true times ``t``: (n, 4, 4), or 4x4 for a scalar."""
        scalar = np.ndim(t) == 0
        tau = self.motion_time(np.atleast_1d(np.asarray(t, dtype=float)))
        d = self.amp_m * np.sin(2 * np.pi * self.freq_hz * tau[:, None] + self.phase)
        w = self.amp_rad * np.sin(2 * np.pi * self.rot_freq_hz * tau[:, None] + self.rot_phase)
        out = np.repeat(self.T_base[None], len(tau), axis=0)
        out[:, :3, :3] = Rotation.from_rotvec(w).as_matrix() @ self.T_base[:3, :3]
        centre_c = self.T_base[:3, :3] @ self.centre_b + self.T_base[:3, 3]
        out[:, :3, 3] = centre_c[None] + d - out[:, :3, :3] @ self.centre_b
        return out[0] if scalar else out


def waving(rig: Rig, rng: np.random.Generator, speed_mps: float = 0.5, turn_dps: float = 45.0,
           pauses: tuple = ()) -> Waving:
    """A random waving about a pose both sensors see (``simulator.sample_board_poses``), turned about the board's
    centre: each axis' peak speed a share of ``speed_mps`` and each axis' peak turn rate a share of ``turn_dps``
    (shares drawn, their root sum of squares 1: the centre's mean speed is near ``speed_mps``)."""
    # A rosette has no rings to fit the pose to: a VLP-16's vertical view stands in (a rosette's cone is wider).
    T = sample_board_poses(replace(rig, beams=vlp16()) if isinstance(rig.beams, Rosette) else rig, 1, rng)[0]
    f, g = rng.uniform(0.15, 0.35, 3), rng.uniform(0.15, 0.35, 3)
    share, rshare = rng.dirichlet(np.ones(3)) ** 0.5, rng.dirichlet(np.ones(3)) ** 0.5
    amp = speed_mps * share / np.linalg.norm(share) / (2 * np.pi * f)
    amp_rad = np.radians(turn_dps) * rshare / np.linalg.norm(rshare) / (2 * np.pi * g)
    w, h = rig.board.extent
    return Waving(T, np.array([0.5 * w, 0.5 * h, 0.0]), amp, f, rng.uniform(0, 2 * np.pi, 3), amp_rad, g,
                  rng.uniform(0, 2 * np.pi, 3), tuple(pauses))


@dataclass(frozen=True)
class WavedRecording:
    """A simulated continuous recording: the camera's board views (its clock), the LiDAR's sweeps of board returns
    (its clock, each return at its own time), the truth (``motion`` in true time = the LiDAR's clock)."""

    rig: Rig
    motion: Waving
    time_offset_s: float
    views: tuple[TimedBoardView, ...]
    sweeps: tuple[TimedSweep, ...]


def simulate_waving(rig: Rig, duration_s: float, rng: np.random.Generator, time_offset_s: float = 0.0,
                    speed_mps: float = 0.5, turn_dps: float = 45.0, camera_hz: float = 20.0,
                    lidar_hz: float = 10.0, stamp_jitter_s: float = 0.0, pauses: tuple = (),
                    corner_noise_px: float = 0.2, camera_phase_s: float | None = None) -> WavedRecording:
    """``duration_s`` of a board waved in front of ``rig`` (see the module). Images whose board is not wholly in
    the image are not detected; each detection is the corners projected at the true instant with ``corner_noise_px``
    of Gaussian noise, its pose solved as ``lidarcam`` solves it. ``stamp_jitter_s``: each stamp off its instant by that
    (Gaussian) spread. ``camera_phase_s``: the first image's instant after the first sweep's start (a camera
    triggered by the LiDAR: 0); None: drawn within a camera period (free-running sensors)."""
    motion = waving(rig, rng, speed_mps, turn_dps, pauses)
    views = []
    X = rig.board.inner_corners()
    phase = rng.uniform(0.0, 1.0 / camera_hz) if camera_phase_s is None else camera_phase_s
    for t in np.arange(phase, duration_s, 1.0 / camera_hz):
        T_cb = motion(t)
        uv = rig.camera.project(transform_points(T_cb, X))
        if not np.all(rig.camera.in_image(uv, margin_px=5.0)):
            continue
        uv = uv + rng.normal(0.0, corner_noise_px, uv.shape)
        try:
            obs = estimate_board_pose(CornerDetection(uv, "simulated"), rig.board, rig.camera)
        except MeasurementError:
            continue
        jitter = rng.normal(0.0, stamp_jitter_s) if stamp_jitter_s else 0.0
        views.append(TimedBoardView(float(t + time_offset_s + jitter), obs))
    sweeps = []
    period = 1.0 / lidar_hz
    for stamp in np.arange(0.0, duration_s - period, period):
        sweep = _sweep(rig, motion, stamp, period, rng)
        if sweep is not None:
            jitter = rng.normal(0.0, stamp_jitter_s) if stamp_jitter_s else 0.0
            sweeps.append(TimedSweep(float(stamp + jitter), sweep[0], sweep[1]))  # its returns' times with it
    return WavedRecording(rig, motion, float(time_offset_s), tuple(views), tuple(sweeps))


def another_lidar(rec: WavedRecording, rig: Rig, duration_s: float, rng: np.random.Generator,
                  time_offset_s: float = 0.0, lidar_hz: float = 10.0) -> tuple[TimedSweep, ...]:
    """The sweeps of a second LiDAR of the rig (``rig``: the recording's camera and board, its own extrinsic and
    beams) seeing the same waving, stamped in its own clock: ``t_camera_stamp - t_its_stamp = time_offset_s``
    for one instant (its stamps are the true time plus the first LiDAR's offset less its own)."""
    sweeps = []
    period = 1.0 / lidar_hz
    shift = rec.time_offset_s - time_offset_s
    for stamp in np.arange(0.0, duration_s - period, period):
        sweep = _sweep(rig, rec.motion, stamp, period, rng)
        if sweep is not None:
            sweeps.append(TimedSweep(float(stamp + shift), sweep[0], sweep[1]))
    return tuple(sweeps)


def _fire_times(rig: Rig, period: float) -> tuple[np.ndarray, np.ndarray]:
    """The sweep's beams (N, 3) and each one's firing time after the sweep's start (clockwise from the cut)."""
    dirs, _ = rig.beams.directions()
    az = np.arctan2(dirs[:, 1], dirs[:, 0])
    return dirs, np.mod(CUT_AZIMUTH_RAD - az, 2 * np.pi) / (2 * np.pi) * period


def _board_ranges(rig: Rig, motion: Waving, stamp: float, d: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Each beam's range to the board where it is when the beam fires (``stamp + t``, true time); inf where the beam
    misses it."""
    T_lb = T_inverse(rig.T_camera_lidar)[None] @ motion(stamp + t)
    n, o = T_lb[:, :3, 2], T_lb[:, :3, 3]
    cos = np.einsum("ij,ij->i", n, d)
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.einsum("ij,ij->i", n, o) / cos
    local = np.einsum("nji,nj->ni", T_lb[:, :3, :3], r[:, None] * d - o)
    w, h = rig.board.extent
    hit = (r > 0.1) & (r < rig.beams.max_range_m) & (np.abs(cos) > 1e-3) & (local[:, 0] >= 0) \
        & (local[:, 0] <= w) & (local[:, 1] >= 0) & (local[:, 1] <= h)
    return np.where(hit, r, np.inf)


def _near_board(rig: Rig, motion: Waving, stamp: float, period: float, dirs: np.ndarray) -> np.ndarray:
    """The beams near the board where it is mid-sweep (its motion within a sweep is centimetres: 10 degrees
    spare)."""
    w, h = rig.board.extent
    T_lc = T_inverse(rig.T_camera_lidar)
    centre = transform_points(T_lc @ motion(stamp + 0.5 * period), np.array([[0.5 * w, 0.5 * h, 0.0]]))[0]
    reach = np.arctan2(0.5 * np.hypot(w, h), np.linalg.norm(centre)) + np.radians(10.0)
    return dirs @ (centre / np.linalg.norm(centre)) >= np.cos(reach)


def _sweep(rig: Rig, motion: Waving, stamp: float, period: float, rng: np.random.Generator):
    """The board's returns of the sweep starting at ``stamp`` (true time): each beam fired at its azimuth's
    time, cast against the board where it is then. (points (n, 3), offsets from the stamp (n,)) or None."""
    dirs, fire = _fire_times(rig, period)
    near = _near_board(rig, motion, stamp, period, dirs)
    if not near.any():
        return None
    d, t = dirs[near], fire[near]
    r = _board_ranges(rig, motion, stamp, d, t)
    hit = np.isfinite(r)
    if hit.sum() < 10:
        return None
    r = r[hit] + rng.normal(0.0, rig.beams.sigma_range_m, int(hit.sum()))
    return r[:, None] * d[hit], t[hit]


# A room round the LiDAR for whole-scene sweeps (LiDAR frame, m): x from, to; y from, to; floor and ceiling.
ROOM = ((-6.0, 12.0), (-5.0, 5.0), (-1.2, 2.2))
# The room's walls, floor and ceiling are kept this far (m) from wherever the waved board goes (``room_for``).
ROOM_CLEARANCE_M = 0.3


def room_for(rig: Rig, motion: Waving, duration_s: float, room: tuple = ROOM) -> tuple:
    """``room`` moved out to leave ``ROOM_CLEARANCE_M`` between its walls, floor and ceiling and the board's
    outline at every instant of ``[0, duration_s]``. A waving drawn about a low pose reaches below ``ROOM``'s
    floor; there the floor's returns beside the board's lower edge lie in its plane and pass for the board's, a
    bias of the simulator no recording has (a board is held above the floor)."""
    poses = motion(np.arange(0.0, duration_s, 0.02))
    T_lc = T_inverse(rig.T_camera_lidar)
    outline = rig.board.outline()
    corners = np.einsum("tij,kj->tki", poses[:, :3, :3], outline) + poses[:, None, :3, 3]  # camera frame
    pts = transform_points(T_lc, corners.reshape(-1, 3))
    lo, hi = pts.min(0) - ROOM_CLEARANCE_M, pts.max(0) + ROOM_CLEARANCE_M
    return tuple((min(a, float(lo[k])), max(b, float(hi[k]))) for k, (a, b) in enumerate(room))


def scene_sweep(rig: Rig, motion: Waving, stamp: float, period: float, rng: np.random.Generator,
                room: tuple = ROOM) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """A whole sweep starting at ``stamp`` (true time): every beam's return from the board where it is when the
    beam fires, or else from the room's walls, floor and ceiling; stored in firing order (a spinning LiDAR's
    column after column; a Livox-like rosette's, ``lidar_models.Rosette``, a new stretch of its pattern each
    sweep), with each return's time after the stamp and its beam (None for a rosette). (points (N, 3), offsets
    (N,), ring (N,))."""
    if isinstance(rig.beams, Rosette):  # a Livox-like rosette: its returns evenly through the sweep, in order
        dirs, ring = rig.beams.directions(rng), None
        fire = np.arange(len(dirs)) * (period / len(dirs))
    else:
        dirs, fire = _fire_times(rig, period)
        order = np.argsort(fire, kind="stable")
        dirs, fire, ring = dirs[order], fire[order], rig.beams.directions()[1][order]
    with np.errstate(divide="ignore"):
        bounds = np.array(room, dtype=float)  # (3, 2)
        walls = np.where(dirs > 0, bounds[:, 1] / dirs, bounds[:, 0] / dirs)
    r = np.min(np.where(walls > 0, walls, np.inf), axis=1)
    near = _near_board(rig, motion, stamp, period, dirs)
    if near.any():
        r[near] = np.minimum(r[near], _board_ranges(rig, motion, stamp, dirs[near], fire[near]))
    keep = np.isfinite(r) & (r < rig.beams.max_range_m)
    r = r[keep] + rng.normal(0.0, rig.beams.sigma_range_m, int(keep.sum()))
    return r[:, None] * dirs[keep], fire[keep], None if ring is None else ring[keep]
