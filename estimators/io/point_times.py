"""Each LiDAR return's time within its sweep, as an offset from the sweep's header stamp: from the cloud's time
field, or, where it has none, from each return's azimuth and the sweep's period; and the words that say which.

Drivers disagree on the field: Velodyne's ``time`` (float32 seconds from the stamp, negative where the stamp is
the sweep's last packet), Ouster's ``t`` (uint32 nanoseconds from the stamp), Hesai's and Robosense's
``timestamp`` (float64 absolute seconds), Livox's ``timestamp`` (float64 absolute nanoseconds) or
``offset_time`` (uint32 nanoseconds from the stamp). The values tell them apart, not the name: the unit is the one
under which the sweep's returns span a sweep's duration, and the reference the stamp when the values are small
(relative), the stamp's clock when they lie near it (absolute), else another clock (a sensor's own, unsynchronised:
the offsets are kept and the sweep's first return placed at its stamp, a constant the clock offset takes up).

A field is also checked against the order the returns are stored in, where that order turns once through the sweep
as a spinning LiDAR fires (:func:`against_stored_order`): a field that counts down through it (a driver's time to
the sweep's end, or a reversed field) and a cloud stored against its firing order cannot be told apart by a board,
which spans too little of a turn, yet either moves the clocks' offset by up to a sweep. The moving board's verdict
says so.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import BagError

# Point fields that may hold a return's time, in the order they are looked for.
TIME_FIELDS = ("t", "time", "timestamp", "time_stamp", "offset_time", "timeoffset", "ts", "stamps")
# Candidate units (seconds per count), in the order tried: integer fields count nanoseconds (or microseconds);
# float fields hold seconds (or Livox's nanoseconds).
_UNITS = {"int": ((1e-9, "nanoseconds"), (1e-6, "microseconds")),
          "float": ((1.0, "seconds"), (1e-9, "nanoseconds"), (1e-6, "microseconds"), (1e-3, "milliseconds"))}
# A sweep's returns span at least this (a cloud cropped to a few degrees of a 20 Hz sweep) and at most this (a
# 1 Hz scanner), seconds.
SWEEP_SPAN_S = (1e-3, 1.0)
# Relative times lie within this of the stamp; absolute ones of the stamp's clock within SAME_CLOCK_S of it.
RELATIVE_S = 1.0
SAME_CLOCK_S = 10.0
# A time field coarser than this (float32 absolute seconds: 128 s steps) tells nothing within a sweep.
FINEST_STEP_S = 1e-5
# A time field whose rank correlation with the stored order's turn through the sweep is below this runs against it
# (a field and its order agree to about +1, whatever the row layout; a reversed one to about -1).
AGAINST_ORDER = -0.5
AGAINST_WORDS = "; it runs backwards against the returns' stored order"
ORDER_SAMPLE = 4096  # returns (every k-th) the check reads: 1 ms a sweep


@dataclass(frozen=True)
class PointTimes:
    """A sweep's per-return times.

    Attributes
    ----------
    offset_s : numpy.ndarray
        (N,) each return's time less the sweep's header stamp, seconds.
    source : str
        How they were found, in words for the printout (the field, its unit and reference, or the azimuth).
    """

    offset_s: np.ndarray
    source: str
    against_order: bool = False


def time_field(names) -> str | None:
    """The name among a cloud's field ``names`` that holds its returns' times, or None."""
    names = set(names)
    return next((n for n in TIME_FIELDS if n in names), None)


def field_times(values: np.ndarray, name: str, stamp_ns: int, where: str = "") -> PointTimes | None:
    """Per-return times from a time field's raw ``values`` (their dtype as stored), the sweep's header stamp in
    ns; ``where`` names the topic or file in errors. None where the field holds one value for every return (some
    drivers write it unfilled). Raises BagError where the field cannot be read as times (no unit makes the returns
    span a sweep, or too coarse a float)."""
    values = np.asarray(values)
    if values.size == 0:
        return PointTimes(np.zeros(0), f"field {name!r} (empty sweep)")
    integer = np.issubdtype(values.dtype, np.integer)
    v = values.astype(np.float64)
    lo, hi = float(v.min()), float(v.max())
    step = 0.0 if integer else float(np.spacing(np.array(max(abs(lo), abs(hi)), dtype=values.dtype)))
    if lo == hi:
        if step > FINEST_STEP_S and abs(lo - stamp_ns * 1e-9) <= SAME_CLOCK_S + step:  # seconds rounded to one
            _too_coarse(name, values.dtype, step, where)
        return None
    for unit, unit_name in _UNITS["int" if integer else "float"]:
        if SWEEP_SPAN_S[0] <= (hi - lo) * unit <= SWEEP_SPAN_S[1]:
            break
    else:
        raise BagError(f"time field {name!r} ({values.dtype}) spans {hi - lo:.6g} counts: no unit makes the returns "
                       f"span a sweep ({SWEEP_SPAN_S[0] * 1000:g} ms to {SWEEP_SPAN_S[1]:g} s)", path=where or None,
                       hint="check the driver's time field, or record without it (times then follow the azimuth)")
    if step * unit > FINEST_STEP_S:
        _too_coarse(name, values.dtype, step * unit, where)
    stamp_s = stamp_ns * 1e-9
    middle = 0.5 * (lo + hi) * unit
    kind = f"field {name!r} ({values.dtype}, {unit_name}"
    if abs(middle) <= RELATIVE_S:
        return PointTimes(v * unit, f"{kind}, from the message stamp)")
    if abs(middle - stamp_s) <= SAME_CLOCK_S:
        if unit == 1e-9:  # whole nanoseconds since the epoch: subtracted exactly
            offset = (np.round(v).astype(np.int64) - np.int64(stamp_ns)) * 1e-9
        else:
            offset = v * unit - stamp_s
        return PointTimes(offset, f"{kind}, absolute in the stamps' clock)")
    return PointTimes((v - lo) * unit, f"{kind}, absolute in a clock {middle - stamp_s:+.3g} s from the stamps': "
                                      "the sweep's first return placed at its stamp)")


def _too_coarse(name: str, dtype, step_s: float, where: str):
    raise BagError(f"time field {name!r} ({dtype}) steps by {step_s:.3g} s at its values: too coarse for times "
                   "within a sweep", path=where or None,
                   hint="record the driver's relative time field, or none (times then follow the azimuth)")


def azimuth_times(points: np.ndarray, period_s: float, why: str = "the cloud has no time field",
                  rows: np.ndarray | None = None) -> PointTimes | None:
    """Per-return times of a spinning LiDAR's sweep without a time field, from each return's azimuth: its turn
    from the first stored return, as a fraction of a turn of ``period_s``. The points must be the sweep's
    returns in the order the driver stored them (``rows``: each one's row of an organised cloud, or None). The
    turning direction is the one the stored order sweeps; the azimuth is followed return by return (unwrapped),
    through the whole cloud where it turns once (a Velodyne's columns), else through each row where each row turns
    once (an organised cloud's rings), the row placed by its first return's azimuth. None where the stored order
    does neither (a shuffled or non-repetitive pattern): the returns' times are then unknown. ``why`` the time
    field was not used, for the words."""
    points = np.asarray(points, dtype=float)
    if len(points) < 3:
        return None
    az = np.arctan2(points[:, 1], points[:, 0])
    runs = [np.arange(len(az))] if rows is None else [np.flatnonzero(rows == r) for r in np.unique(rows)]
    turns = [float(np.sum(np.angle(np.exp(1j * np.diff(az[i]))))) for i in runs]
    if len(runs) > 1 and not all(_one_turn(t) and np.sign(t) == np.sign(turns[0]) for t in turns):
        runs, turns = [np.arange(len(az))], [float(np.sum(np.angle(np.exp(1j * np.diff(az)))))]
    if not _one_turn(turns[0]):
        return None
    direction = np.sign(turns[0])
    offset = np.empty(len(az))
    for i in runs:
        run_start = np.angle(np.exp(1j * direction * (az[i[0]] - az[0])))  # the row's first return, from the first
        progress = direction * np.concatenate([[0.0], np.cumsum(np.angle(np.exp(1j * np.diff(az[i]))))])
        offset[i] = (run_start + progress) / (2 * np.pi) * period_s
    turn = "counter-clockwise" if direction > 0 else "clockwise"
    return PointTimes(offset, f"azimuth ({turn} seen from above, from the first stored return at the stamp, "
                              f"{1 / period_s:.3g} Hz): {why}")


def against_stored_order(times: PointTimes, points: np.ndarray, rows: np.ndarray | None = None) -> PointTimes:
    """``times`` read from a field, marked (``against_order``, and its words) where they run backwards against the
    order the returns are stored in: their rank correlation with that order's turn through the sweep
    (:func:`azimuth_times`: where the stored order turns once, whole or row by row) below ``AGAINST_ORDER``.
    Unchanged where the stored order does not turn once (a cropped, shuffled or non-repetitive cloud): there is
    nothing to check against."""
    if len(times.offset_s) != len(points):
        return times
    every = max(1, len(points) // ORDER_SAMPLE)  # a stride keeps the stored order's turn (5.6 deg steps at 64 x 1024)
    order = azimuth_times(points[::every], 1.0, rows=None if rows is None else rows[::every])
    if order is None:
        return times
    ranks = [np.argsort(np.argsort(a, kind="stable")).astype(float) for a in (times.offset_s[::every], order.offset_s)]
    if np.ptp(ranks[0]) == 0 or np.ptp(ranks[1]) == 0:
        return times
    if float(np.corrcoef(*ranks)[0, 1]) >= AGAINST_ORDER:
        return times
    return PointTimes(times.offset_s, times.source + AGAINST_WORDS, True)


def _one_turn(turned_rad: float) -> bool:
    """Whether an azimuth followed return by return turned about once (half to one and a half turns)."""
    return np.pi <= abs(turned_rad) <= 3 * np.pi
