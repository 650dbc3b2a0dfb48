"""Beam models of spinning LiDARs, for the simulator (elevations, azimuth step, range noise), and the range
accuracy of sensor families (the range model's priors, ``solvers.range_model``)."""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

# A systematic range error's standard deviation (m) by sensor family, from the makers' accuracy figures
# (VLP-16 and Ouster OS: +-3 cm typical; HDL-64E, Hesai Pandar and Livox: 2 cm), and a conservative default.
RANGE_ACCURACY_M = {"velodyne": 0.03, "ouster": 0.03, "hesai": 0.02, "livox": 0.02, "default": 0.05}
DEFAULT_RANGE_ACCURACY_M = RANGE_ACCURACY_M["default"]
# Each ring's prior about the global offset, as a share of the range accuracy.
RING_PRIOR_SHARE = 0.2


def range_accuracy_for(family: str | None) -> float:
    """The default range accuracy (m) of a sensor family (``velodyne``, ``ouster``, ``hesai``, ``livox``), the
    conservative default for None or any other name."""
    return RANGE_ACCURACY_M.get(str(family).lower(), DEFAULT_RANGE_ACCURACY_M) if family else DEFAULT_RANGE_ACCURACY_M


@dataclass(frozen=True, eq=False)
class BeamModel:
    name: str
    elevations_rad: np.ndarray  # one per laser
    azimuth_step_rad: float
    sigma_range_m: float
    max_range_m: float
    # Field of view in azimuth (from, to), radians; None for a full turn.
    azimuth_limits_rad: tuple[float, float] | None = None
    # Where the sweep's firings fall (radians, within one step): a real sweep's phase differs from sweep to sweep.
    azimuth_phase_rad: float = 0.0

    @property
    def is_2d(self) -> bool:
        """A single-line scanner (its one beam plane is the LiDAR's x-y plane)."""
        return len(self.elevations_rad) == 1 and abs(float(self.elevations_rad[0])) < 1e-12

    def azimuths(self) -> np.ndarray:
        if self.azimuth_limits_rad is None:
            return np.arange(0.0, 2 * np.pi, self.azimuth_step_rad) + self.azimuth_phase_rad
        lo, hi = self.azimuth_limits_rad
        return np.arange(lo, hi + 0.5 * self.azimuth_step_rad, self.azimuth_step_rad) + self.azimuth_phase_rad

    def directions(self) -> tuple[np.ndarray, np.ndarray]:
        """Unit beam directions (N, 3) in the LiDAR frame (x forward, y left, z up) and ring ids (N,), read-only."""
        return self._directions

    @cached_property
    def _directions(self) -> tuple[np.ndarray, np.ndarray]:
        # Made once per model: a layout's information casts its beams at every candidate pose.
        az = self.azimuths()
        el, a = np.meshgrid(self.elevations_rad, az, indexing="ij")
        d = np.stack([np.cos(el) * np.cos(a), np.cos(el) * np.sin(a), np.sin(el)], axis=-1).reshape(-1, 3)
        ring = np.repeat(np.arange(len(self.elevations_rad)), len(az))
        d.setflags(write=False)
        ring.setflags(write=False)
        return d, ring


def hdl64e(sigma_range_m: float = 0.02) -> BeamModel:
    """Velodyne HDL-64E-like: +2 to -24.8 degrees, 1/3 degree upper block and 1/2 degree lower block,
    0.17 degree azimuth step (10 Hz)."""
    upper = np.linspace(2.0, -8.33, 32)
    lower = np.linspace(-8.83, -24.8, 32)
    return BeamModel("HDL-64E", np.deg2rad(np.concatenate([upper, lower])), np.deg2rad(0.17),
                     sigma_range_m, 120.0)


def vlp16(sigma_range_m: float = 0.02) -> BeamModel:
    """Velodyne VLP-16-like: -15 to +15 degrees every 2 degrees, 0.2 degree azimuth step."""
    return BeamModel("VLP-16", np.deg2rad(np.arange(-15.0, 15.1, 2.0)), np.deg2rad(0.2), sigma_range_m, 100.0)


def os64(sigma_range_m: float = 0.02) -> BeamModel:
    """Ouster OS1-64-like: 64 beams evenly from -16.6 to +16.6 degrees, 2048 columns a turn (0.176 degrees)."""
    return BeamModel("OS1-64", np.deg2rad(np.linspace(16.6, -16.6, 64)), 2 * np.pi / 2048, sigma_range_m, 120.0)


def scanner2d(sigma_range_m: float = 0.01) -> BeamModel:
    """A Hokuyo/SICK-like single-line scanner: 270 degrees in 0.25 degree steps, 30 m."""
    return BeamModel("2D scanner", np.array([0.0]), np.deg2rad(0.25), sigma_range_m, 30.0,
                     (-np.deg2rad(135.0), np.deg2rad(135.0)))


def spinning2d(sigma_range_m: float = 0.02) -> BeamModel:
    """A single-line scanner spun about the vertical axis (a lab's dense sweep): its scan line, vertical, holds
    -40 to +40 degrees in 0.25 degree steps (321 "rings"), turned in 0.5 degree steps, 30 m."""
    return BeamModel("spinning 2D laser", np.deg2rad(np.arange(40.0, -40.01, -0.25)), np.deg2rad(0.5),
                     sigma_range_m, 30.0)


@dataclass(frozen=True, eq=False)
class Rosette:
    """A Livox-like LiDAR (for the simulator): a non-repetitive rosette in a circular field of view ahead (x),
    from two prisms turning at incommensurate rates, each sweep a new stretch of it (25-40 thousand returns a
    sweep), no beam index. Its ``directions`` draw a sweep's."""

    name: str = "rosette"
    sigma_range_m: float = 0.01
    max_range_m: float = 40.0
    fov_deg: float = 38.4
    points: tuple[int, int] = (25000, 40000)   # returns a sweep (at 100 thousand a second)
    rates_hz: tuple[float, float] = (121.57, -77.73)  # the two prisms' turns a second
    is_2d: bool = False

    def directions(self, rng: np.random.Generator) -> np.ndarray:
        """One sweep's unit beam directions (N, 3): the rosette from a random start, N drawn in ``points``."""
        n = int(rng.integers(self.points[0], self.points[1] + 1))
        t = rng.uniform(0.0, 100.0) + np.arange(n) * 1e-5
        w1, w2 = 2 * np.pi * np.asarray(self.rates_hz)
        half = 0.25 * np.deg2rad(self.fov_deg)
        a = half * (np.cos(w1 * t) + np.cos(w2 * t))
        b = half * (np.sin(w1 * t) + np.sin(w2 * t))
        r, phi = np.hypot(a, b), np.arctan2(b, a)
        return np.column_stack([np.cos(r), np.sin(r) * np.cos(phi), np.sin(r) * np.sin(phi)])

    def in_view(self, points: np.ndarray, margin_rad: float = 0.0) -> np.ndarray:
        """Which points (LiDAR frame) lie inside the field of view, ``margin_rad`` inside its edge."""
        off = np.arccos(np.clip(points[:, 0] / np.linalg.norm(points, axis=1), -1.0, 1.0))
        return off <= 0.5 * np.deg2rad(self.fov_deg) - margin_rad


BEAM_MODELS = {"hdl64e": hdl64e, "vlp16": vlp16, "os64": os64, "2d": scanner2d, "spin2d": spinning2d}
