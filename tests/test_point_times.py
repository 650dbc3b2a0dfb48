"""Each LiDAR return's time within its sweep (``estimators.io.point_times``): the drivers' time-field conventions
told apart by their values, the sign (offset = the return's time less the sweep's stamp), the azimuth fallback on a
simulated sweep without a time field, and the fields that cannot be read as times."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from estimators.errors import BagError
from estimators.io.ros_messages import decode_point_cloud, decode_point_times

PERIOD_S = 0.1  # a 10 Hz spinning LiDAR
STAMP_NS = 1_700_000_123_456_789_000  # a header stamp in the epoch's clock
_CODES = {"i1": 1, "u1": 2, "i2": 3, "u2": 4, "i4": 5, "u4": 6, "f4": 7, "f8": 8}


def _sweep(rng, rings=16, columns=900, ring_major=False, azimuth_offsets_deg=1.5):
    """A clockwise sweep (seen from above, as a Velodyne turns) starting at 37 deg: each column fired at
    column * period / columns, each ring 2.3 us after the previous, each beam at its own small azimuth offset.
    Returns the points in the driver's stored order (column-major as Velodyne's, or ring-major as an organised
    Ouster cloud) and each return's true time from the sweep's start."""
    col, ring = np.meshgrid(np.arange(columns), np.arange(rings), indexing="xy" if ring_major else "ij")
    col, ring = col.ravel(), ring.ravel()
    beam_offset = np.radians(np.linspace(-azimuth_offsets_deg, azimuth_offsets_deg, rings))[ring]
    az = np.radians(37.0) - 2 * np.pi * col / columns + beam_offset
    elevation = np.radians(np.linspace(-15, 15, rings))[ring]
    r = rng.uniform(2.0, 30.0, col.size)
    points = np.column_stack([r * np.cos(elevation) * np.cos(az), r * np.cos(elevation) * np.sin(az),
                              r * np.sin(elevation)])
    return points, col * PERIOD_S / columns + ring * 2.3e-6


def _message(points, extra: dict, stamp_ns=STAMP_NS, height=1):
    """A PointCloud2-like message of float32 x, y, z and the ``extra`` columns (name -> (array, numpy type))."""
    fields = [("x", points[:, 0], "f4"), ("y", points[:, 1], "f4"), ("z", points[:, 2], "f4")]
    fields += [(n, a, t) for n, (a, t) in extra.items()]
    offsets = np.cumsum([0] + [np.dtype(t).itemsize for _, _, t in fields])
    dtype = np.dtype({"names": [f[0] for f in fields], "formats": ["<" + f[2] for f in fields],
                      "offsets": list(offsets[:-1]), "itemsize": int(offsets[-1])})
    arr = np.zeros(len(points), dtype)
    for n, a, _ in fields:
        arr[n] = a
    stamp = SimpleNamespace(sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000)
    return SimpleNamespace(
        header=SimpleNamespace(stamp=stamp), height=height, width=len(points) // height, is_bigendian=False,
        fields=[SimpleNamespace(name=n, offset=int(o), datatype=_CODES[t], count=1)
                for (n, _, t), o in zip(fields, offsets)],
        point_step=dtype.itemsize, row_step=dtype.itemsize * (len(points) // height),
        data=arr.view(np.uint8))


@pytest.mark.parametrize("driver", ["velodyne", "ouster", "hesai", "robosense", "livox", "livox_offset"])
def test_each_drivers_time_field_gives_every_returns_time_from_the_stamp(driver):
    """The stamp is the sweep's first return (Ouster, Livox, Hesai) or its last (a Velodyne whose stamp is its
    last packet: negative offsets); the offsets are each return's time less the stamp, to 1 us (float32 seconds
    carry 7 digits: 0.1 s to 10 ns)."""
    rng = np.random.default_rng(3)
    points, t = _sweep(rng, rings=8, columns=360)
    stamp_s = STAMP_NS * 1e-9
    first_return_ns = STAMP_NS if driver != "velodyne" else STAMP_NS - int(round(1e9 * PERIOD_S))
    truth = t + (first_return_ns - STAMP_NS) * 1e-9  # each return's time less the stamp
    fields = {
        "velodyne": {"ring": (np.zeros(len(t)), "u2"), "time": (truth, "f4")},
        "ouster": {"t": (np.round(1e9 * truth), "u4"), "reflectivity": (np.ones(len(t)), "u2")},
        "hesai": {"timestamp": (stamp_s + truth, "f8")},
        "robosense": {"timestamp": (stamp_s + truth, "f8"), "ring": (np.zeros(len(t)), "u2")},
        "livox": {"timestamp": (STAMP_NS + np.round(1e9 * truth), "f8")},
        "livox_offset": {"offset_time": (np.round(1e9 * truth), "u4")},
    }[driver]
    msg = _message(points, fields)
    times = decode_point_times(msg, "/points")
    assert len(times.offset_s) == len(decode_point_cloud(msg)[0]) == len(t)
    np.testing.assert_allclose(times.offset_s, truth, atol=1e-6)
    if driver == "velodyne":
        assert times.offset_s.max() <= 1e-6 and "seconds, from the message stamp" in times.source
    if driver in ("ouster", "livox_offset"):
        assert "nanoseconds, from the message stamp" in times.source
    if driver in ("hesai", "robosense"):
        assert "seconds, absolute in the stamps' clock" in times.source
    if driver == "livox":
        assert "nanoseconds, absolute in the stamps' clock" in times.source


def test_a_sensors_own_clock_is_kept_relative_and_said():
    """Absolute times in a clock other than the stamps' (a LiDAR counting from its power-on, unsynchronised):
    the returns' spacing kept, the first at the stamp (a constant the sensors' clock offset takes up)."""
    points, t = _sweep(np.random.default_rng(4), rings=4, columns=200)
    times = decode_point_times(_message(points, {"timestamp": (1234.5 + t, "f8")}), "/points")
    np.testing.assert_allclose(times.offset_s, t - t.min(), atol=1e-9)
    assert "absolute in a clock" in times.source and "first return placed at its stamp" in times.source


@pytest.mark.parametrize("ring_major", [False, True], ids=["column-major", "ring-major"])
def test_a_sweep_without_a_time_field_is_timed_by_its_azimuth(ring_major):
    """No time field: each return's time from its azimuth, the turning direction and the start read from the
    stored order; against the simulated firing times within the beams' azimuth offsets from the first return's
    beam (up to 3 deg of a 10 Hz turn: 0.83 ms) and the firing sequence's 35 us. Without a sweep period, or in a
    shuffled order, the times are unknown (None)."""
    rng = np.random.default_rng(5)
    points, t = _sweep(rng, ring_major=ring_major)
    msg = _message(points, {"intensity": (np.ones(len(t)), "f4")}, height=16 if ring_major else 1)
    times = decode_point_times(msg, "/points", period_s=PERIOD_S)
    err = times.offset_s - t
    assert np.abs(err).max() < 0.87e-3 and np.median(np.abs(err)) < 0.45e-3
    assert "clockwise seen from above" in times.source and "no time field" in times.source
    assert "counter-clockwise" not in times.source
    assert decode_point_times(msg, "/points") is None
    shuffled = rng.permutation(len(t))
    assert decode_point_times(_message(points[shuffled], {}), "/points", period_s=PERIOD_S) is None


def test_an_unfilled_time_field_falls_back_to_the_azimuth_and_says_so():
    points, t = _sweep(np.random.default_rng(6), rings=4, columns=400, azimuth_offsets_deg=0.0)
    times = decode_point_times(_message(points, {"time": (np.zeros(len(t)), "f4")}), "/points", period_s=PERIOD_S)
    np.testing.assert_allclose(times.offset_s, t, atol=0.05e-3)
    assert "time field 'time' holds one value throughout" in times.source


def test_time_fields_that_cannot_be_times_are_one_line_errors():
    points, t = _sweep(np.random.default_rng(7), rings=4, columns=100)
    # float32 absolute seconds: 128 s steps at today's epoch
    with pytest.raises(BagError, match=r"/points: time field 'timestamp' \(float32\) steps by .* too coarse"):
        decode_point_times(_message(points, {"timestamp": (STAMP_NS * 1e-9 + t, "f4")}), "/points")
    # a field whose spread no unit makes a sweep's (picoseconds)
    with pytest.raises(BagError, match=r"time field 't' \(float64\) spans .* no unit makes the returns span a sweep"):
        decode_point_times(_message(points, {"t": (1e12 * t, "f8")}), "/points")


@pytest.mark.parametrize("ring_major", [False, True], ids=["column-major", "ring-major"])
def test_a_time_field_counting_down_against_the_stored_order_is_marked(ring_major):
    """A field that counts down through the returns' stored order (the period less each time, as a driver's time to
    the sweep's end) is marked and said (a board spans too little of a turn to tell it, and it moved a waved
    board's clocks' offset by 8 ms, 11 standard deviations); fields that count up are not, whether from the
    stamp or before it (a Velodyne stamped at its last packet), nor is a shuffled cloud (no order to check)."""
    rng = np.random.default_rng(8)
    points, t = _sweep(rng, ring_major=ring_major)
    height = 16 if ring_major else 1
    down = decode_point_times(_message(points, {"t": (np.round(1e9 * (PERIOD_S - t)), "u4")}, height=height), "/p")
    assert down.against_order and down.source.endswith("runs backwards against the returns' stored order")
    for field in ({"t": (np.round(1e9 * t), "u4")}, {"time": (t - PERIOD_S, "f4")}):
        up = decode_point_times(_message(points, field, height=height), "/p")
        assert not up.against_order and "backwards" not in up.source
    shuffled = rng.permutation(len(t))
    assert not decode_point_times(_message(points[shuffled], {"t": (np.round(1e9 * (PERIOD_S - t[shuffled])), "u4")}),
                                  "/p").against_order
