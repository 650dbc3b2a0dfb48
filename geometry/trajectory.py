"""A rigid body's pose continuous in time through timed poses: the rotation by scipy's ``RotationSpline`` (cubic
in the rotation vector between samples, continuous angular velocity and acceleration), the translation by a cubic
spline per axis (``CubicSpline``, not-a-knot ends); or, from noisy poses, a smoothing spline per axis of the
translation and of the rotation vector about the middle pose, each smoothed as Generalised Cross-Validation
chooses (scipy's ``make_smoothing_spline``)."""
from __future__ import annotations

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.spatial.transform import Rotation, RotationSpline


class PoseSpline:
    """``T(t)``, 4x4, through poses ``T[i]`` at strictly increasing ``times_s[i]`` (at least 2). Defined on
    ``[times_s[0], times_s[-1]]`` (:attr:`span_s`); evaluation outside it raises ValueError."""

    def __init__(self, times_s: np.ndarray, T: np.ndarray):
        times_s = np.asarray(times_s, dtype=float)
        T = np.asarray(T, dtype=float).reshape(-1, 4, 4)
        if len(times_s) != len(T) or len(times_s) < 2:
            raise ValueError(f"Expected as many times as poses, at least 2; got {len(times_s)} and {len(T)}")
        if not np.all(np.diff(times_s) > 0):
            raise ValueError("Expected strictly increasing times")
        self.times_s = times_s
        self._rotation = RotationSpline(times_s, Rotation.from_matrix(T[:, :3, :3]))
        self._translation = CubicSpline(times_s, T[:, :3, 3], axis=0)

    @property
    def span_s(self) -> tuple[float, float]:
        return float(self.times_s[0]), float(self.times_s[-1])

    def __call__(self, t: np.ndarray | float) -> np.ndarray:
        """The poses at times ``t`` (seconds), (n, 4, 4) (or 4x4 for a scalar ``t``)."""
        scalar = np.ndim(t) == 0
        t = np.atleast_1d(np.asarray(t, dtype=float))
        lo, hi = self.span_s
        if np.any(t < lo) or np.any(t > hi):
            raise ValueError(f"times outside the spline's span [{lo:.6f}, {hi:.6f}] s")
        out = np.zeros((len(t), 4, 4))
        out[:, :3, :3] = self._rotation(t).as_matrix()
        out[:, :3, 3] = self._translation(t)
        out[:, 3, 3] = 1.0
        return out[0] if scalar else out


class PoseSplines:
    """Poses continuous in time through runs of timed poses: a :class:`PoseSpline` through each run, the runs split
    where consecutive ``times_s`` lie more than ``max_gap_s`` apart (a body out of view: no spline through a gap,
    whose ends would pull it about); a run of one pose holds no time. :meth:`covers` says which times lie within a
    run; evaluation elsewhere raises ValueError."""

    def __init__(self, times_s: np.ndarray, T: np.ndarray, max_gap_s: float):
        times_s = np.asarray(times_s, dtype=float)
        T = np.asarray(T, dtype=float).reshape(-1, 4, 4)
        cuts = np.flatnonzero(np.diff(times_s) > max_gap_s) + 1
        self.runs = [PoseSpline(times_s[a:b], T[a:b]) for a, b in zip(np.r_[0, cuts], np.r_[cuts, len(times_s)])
                     if b - a >= 2]
        if not self.runs:
            raise ValueError(f"Expected two or more poses within {max_gap_s} s of each other")
        self._starts = np.array([r.span_s[0] for r in self.runs])

    @property
    def span_s(self) -> tuple[float, float]:
        return self.runs[0].span_s[0], self.runs[-1].span_s[1]

    def _run(self, t: np.ndarray) -> np.ndarray:
        return np.clip(np.searchsorted(self._starts, t, side="right") - 1, 0, len(self.runs) - 1)

    def covers(self, t: np.ndarray, margin_s: float = 0.0) -> np.ndarray:
        """Which times ``t`` lie in a run, at least ``margin_s`` from its ends (bool array)."""
        t = np.asarray(t, dtype=float)
        k = self._run(t)
        lo = np.array([r.span_s[0] for r in self.runs])[k]
        hi = np.array([r.span_s[1] for r in self.runs])[k]
        return (t - margin_s >= lo) & (t + margin_s <= hi)

    def __call__(self, t: np.ndarray | float) -> np.ndarray:
        """The poses at times ``t`` (seconds), (n, 4, 4) (or 4x4 for a scalar ``t``), each from its run."""
        scalar = np.ndim(t) == 0
        t = np.atleast_1d(np.asarray(t, dtype=float))
        if not np.all(self.covers(t)):
            raise ValueError("times outside the runs of poses")
        k = self._run(t)
        out = np.empty((len(t), 4, 4))
        for i in np.unique(k):
            out[k == i] = self.runs[i](t[k == i])
        return out[0] if scalar else out
