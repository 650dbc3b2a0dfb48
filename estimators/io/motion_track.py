"""A moving board's record, ``motion.npz`` in a dataset folder: the board's corners in every image that shows it and
the board's returns of every LiDAR sweep that holds it, each with its own stamp, and each return with its own time.

Written by ``lidarcam extract`` from a bag whose board moves; read by ``lidarcam calibrate``, which then solves the
extrinsic and the sensors' clock offset together (a still-pose recording's, its board between the poses: the
offset alone, the poses giving the extrinsic). Times are seconds after ``origin_ns`` (the recording's first
stamp, ns), the camera's stamps in the camera's clock and the LiDAR's in the LiDAR's. Loaded without pickles.
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import DatasetError
from ..measurements import TimedSweep
from .input_files import load_npz

FILE = "motion.npz"
# A rig's still poses with the board moved between them: the camera whose images ``lidarcam extract`` follows the
# board in, for every 3D LiDAR's motion.npz (in the LiDAR's folder); their clock offsets are against its clock.
FOLLOWED_CAMERA = "cam0"
STILL_POSES = "still poses"  # extract.json's recording of frames held still (bag_extract.STILL)
MOVING_BOARD = "moving board"  # and of a board that moves throughout (bag_extract.MOVING)
EXAMPLES = "examples"  # the folder beside it of the few images kept whole
# What a command that takes still poses says of a moving board's folder (a pair's or a rig's).
STILL_POSES_ONLY = "this command takes a folder of still poses; lidarcam calibrate takes the recording"
# The stamps lie within this many seconds of the recording's first (11 days): beyond, a damaged record, and times
# in float64 no longer resolve the microseconds a sweep's returns are timed by.
MAX_STAMP_S = 1e6
_ARRAYS = ("origin_ns", "view_stamps_s", "corners_px", "sweep_stamps_s", "sweep_sizes", "points", "offsets_s")


@dataclass(frozen=True, eq=False)
class MotionTrack:
    """The board's corners per image and its returns per sweep through a continuous recording.

    Attributes
    ----------
    origin_ns : int
        The stamp (ns) the times count from.
    view_stamps_s : numpy.ndarray
        (V,) each image's stamp (camera's clock).
    corners_px : numpy.ndarray
        (V, K, 2) the board's inner corners in each image (NaN: a ChArUco corner not seen).
    sweep_stamps_s : numpy.ndarray
        (S,) each sweep's header stamp (LiDAR's clock).
    sweep_sizes : numpy.ndarray
        (S,) how many of ``points`` each sweep holds, in order.
    points : numpy.ndarray
        (M, 3) the board's returns in the LiDAR frame, sweep after sweep.
    offsets_s : numpy.ndarray
        (M,) each return's time less its sweep's stamp.
    point_times : str
        How the returns' times were read, in words.
    example_stamps_s : numpy.ndarray
        (E,) the stamps of the few images kept whole for the report (``examples/NNNN.png``, in order).
    times_against_order : bool
        Whether most sweeps' time field ran backwards against their returns' stored order
        (``io.point_times.against_stored_order``): one of the two is not the firing order, and the clocks' offset
        rests on which.
    """

    origin_ns: int
    view_stamps_s: np.ndarray
    corners_px: np.ndarray
    sweep_stamps_s: np.ndarray
    sweep_sizes: np.ndarray
    points: np.ndarray
    offsets_s: np.ndarray
    point_times: str = ""
    example_stamps_s: np.ndarray = field(default_factory=lambda: np.zeros(0))
    times_against_order: bool = False

    def sweeps(self) -> list[TimedSweep]:
        """Each sweep's returns with their times."""
        ends = np.cumsum(self.sweep_sizes)
        return [TimedSweep(float(s), self.points[e - n:e].astype(float), self.offsets_s[e - n:e].astype(float))
                for s, n, e in zip(self.sweep_stamps_s, self.sweep_sizes, ends)]


def is_moving_dataset(folder: str | os.PathLike) -> bool:
    """Whether a dataset folder is a moving board's record: ``motion.npz``, and not beside still poses' frames (a
    still-pose recording's motion between its poses, which only times the clocks: :func:`has_motion`); or a rig
    folder extracted from such a recording (each LiDAR's ``motion.npz`` in its own folder)."""
    return (has_motion(folder) and _recording(folder) != STILL_POSES) or _recording(folder) == MOVING_BOARD


def has_motion(folder: str | os.PathLike) -> bool:
    """Whether a dataset folder holds a record of the board's motion (``motion.npz``)."""
    return (Path(folder) / FILE).is_file()


def _recording(folder: str | os.PathLike) -> str | None:
    """The recording's kind ``lidarcam extract`` wrote in extract.json (None when unread)."""
    try:
        record = json.loads((Path(folder) / "extract.json").read_text())
    except (OSError, ValueError):
        return None
    return record.get("recording") if isinstance(record, dict) else None


def save_motion_track(folder: str | os.PathLike, track: MotionTrack) -> Path:
    """``folder/motion.npz`` (the caller makes the folder atomic)."""
    path = Path(folder) / FILE
    np.savez_compressed(path, origin_ns=np.int64(track.origin_ns), view_stamps_s=track.view_stamps_s,
                        corners_px=track.corners_px.astype(np.float32), sweep_stamps_s=track.sweep_stamps_s,
                        sweep_sizes=track.sweep_sizes.astype(np.int64), points=track.points.astype(np.float32),
                        offsets_s=track.offsets_s.astype(np.float32), point_times=np.array(track.point_times),
                        example_stamps_s=np.asarray(track.example_stamps_s, dtype=float),
                        times_against_order=np.bool_(track.times_against_order))
    return path


def load_motion_track(folder: str | os.PathLike) -> MotionTrack:
    """``folder/motion.npz``, checked, or a one-line :class:`DatasetError`."""
    path = Path(folder) / FILE
    hint = "extract the bag again (lidarcam extract ... --overwrite)"
    try:
        z = load_npz(path)
    except Exception as exc:  # a damaged or foreign file: name it
        raise DatasetError(f"unreadable moving board's record ({type(exc).__name__}: "
                           f"{str(exc).splitlines()[0][:160] if str(exc) else 'no detail'})", path=path,
                           hint=hint) from None
    missing = [k for k in _ARRAYS if k not in z]
    if missing:
        raise DatasetError(f"not a moving board's record (no {', '.join(missing)})", path=path, hint=hint)
    a = {k: np.asarray(z[k]) for k in _ARRAYS}
    words = str(z["point_times"]) if "point_times" in z else ""
    flag = np.asarray(z.get("times_against_order", False))  # a record from before the check: not checked
    against = flag.shape == () and flag.dtype.kind in "biu" and bool(flag)
    examples = np.asarray(z.get("example_stamps_s", np.zeros(0)))
    if examples.dtype.kind not in "fiu" or examples.ndim != 1 or not np.all(np.isfinite(examples)):
        examples = np.zeros(0)  # the report's images only: a damaged list draws none
    if any(a[k].dtype.kind not in "fiu" for k in _ARRAYS):
        raise DatasetError("inconsistent moving board's record (an array is not numbers)", path=path, hint=hint)
    shapes = (a["origin_ns"].shape == () and a["view_stamps_s"].ndim == 1 and a["sweep_stamps_s"].ndim == 1
              and a["corners_px"].ndim == 3 and a["points"].ndim == 2)
    V, S = (len(a["view_stamps_s"]), len(a["sweep_stamps_s"])) if shapes else (0, 0)
    ok = (shapes and a["corners_px"].shape[0] == V and a["corners_px"].shape[2] == 2
          and a["sweep_sizes"].shape == (S,) and np.all(a["sweep_sizes"] >= 0)
          and a["points"].shape == (int(a["sweep_sizes"].sum()), 3) and a["offsets_s"].shape == (len(a["points"]),)
          and all(np.all(np.isfinite(a[k])) for k in ("view_stamps_s", "sweep_stamps_s", "points", "offsets_s"))
          and all(np.all(np.abs(a[k]) <= MAX_STAMP_S) for k in ("view_stamps_s", "sweep_stamps_s", "offsets_s")))
    if not ok:
        raise DatasetError("inconsistent moving board's record (its arrays' sizes disagree, or hold NaN or times "
                           f"beyond {MAX_STAMP_S:g} s)",
                           path=path, hint=hint)
    return MotionTrack(int(a["origin_ns"]), a["view_stamps_s"].astype(float), a["corners_px"].astype(float),
                       a["sweep_stamps_s"].astype(float), a["sweep_sizes"].astype(int), a["points"],
                       a["offsets_s"], words, examples.astype(float), against)
