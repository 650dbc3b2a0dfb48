"""The LiDAR range model: systematic range errors as nuisance terms of the plane and scan-line factors.

A return's measured range is ``rho = rho_true + a . beta + noise``, with ``a`` the return's regressors:

- ``offset``: 1 for every return (a global range offset; prior 0 +- 5 cm);
- ``ring r``: 1 for the returns of beam ``r`` (per-laser offsets of a multi-beam LiDAR, deviations from the
  global offset; prior 0 +- 1 cm). Rings come from the scan's ``ring`` field (or an organised cloud's rows),
  or from clustering the board points' beam elevations when the scan has neither;
- ``dark``: 1 for returns from the board's black squares (a reflectivity-dependent offset; prior 0 +- 5 cm).
  Black and white returns are told apart by their intensity (two clusters, Otsu's threshold) where the scan
  has an intensity field and the board's intensities are clearly bimodal.

The range residual of a board point on plane ``pi = [m; -d]`` is ``pi . [p; 1] / (m . b) - a . beta``
(``b`` its unit beam; MATH.md section 2). With the incidence taken at the fitted plane, a frame's cost is a
quadratic form in ``theta = [s pi; beta]`` over the moment of ``z = [[p; 1] / |m_hat . b|; -a]``, so the
factor keeps O(1) sufficient statistics per frame (``geometry.planes.sqrt_excess_moment_nuisance``);
``s = sign(m . m_away)`` orients the camera's plane like the fitted one (facing away from the sensor).

Model choice (``auto``): the terms are added in order (offset, per-ring, dark) while the data support them:
a likelihood-ratio test at 1% on the refined cost, points' whole cost included, against the degrees of
freedom the term adds.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from geometry.planes import sqrt_excess_moment_nuisance

from ..measurements import MIN_INCIDENCE_COS, FrameMeasurement, LidarBoardObservation

RANGE_MODELS = ("none", "offset", "per-ring", "full", "auto")
OFFSET_PRIOR_SD_M = 0.05
RING_PRIOR_SD_M = 0.01
DARK_PRIOR_SD_M = 0.05
# Significance of the likelihood-ratio test that adds a term in ``auto``.
MODEL_TEST_P = 0.01
# Beam elevations further apart than this (rad) belong to different rings when the scan has no ring field.
RING_GAP_RAD = float(np.deg2rad(0.15))
# Intensity clusters at least this many pooled standard deviations apart count as black and white squares.
MIN_INTENSITY_SEPARATION = 3.0


@dataclass(frozen=True)
class RangeTerms:
    """The nuisance vector ``beta``: its terms' names, prior standard deviations (m), and for ``ring r`` terms
    the ring ids in order."""

    names: tuple[str, ...]
    prior_sd: tuple[float, ...]
    rings: tuple[int, ...] = ()

    @property
    def size(self) -> int:
        return len(self.names)

    @property
    def model(self) -> str:
        if "dark" in self.names:
            return "full"
        return "per-ring" if self.rings else "offset"


@dataclass(frozen=True)
class FrameLabels:
    """Per frame, each board point's ring (None: not known) and whether it is on a black square (None: not
    told apart)."""

    rings: tuple
    dark: tuple


@dataclass(frozen=True, eq=False)
class FrameWhitener:
    """A frame's plane factor data: ``W`` (k x (4 + len(cols))), the indices ``cols`` of ``beta`` its points
    touch, the fitted plane's normal facing away from the sensor, and the best fit's cost ``floor`` (m^2)."""

    W: np.ndarray
    cols: np.ndarray
    m_away: np.ndarray
    floor: float

    @property
    def W_plane(self) -> np.ndarray:
        return self.W[:, :4]

    @property
    def W_nuisance(self) -> np.ndarray:
        return self.W[:, 4:]


@dataclass(frozen=True)
class RangeModelFit:
    """What the refinement chose and estimated: the requested and chosen model, why, the terms' values and
    standard deviations (m, marginal), and the model tests (one dict per model tried)."""

    requested: str
    chosen: str
    reason: str
    names: tuple[str, ...] = ()
    values_m: tuple[float, ...] = ()
    std_m: tuple[float, ...] = ()
    tests: tuple[dict, ...] = ()
    terms: RangeTerms | None = None
    # The part of the extrinsic's covariance due to the nuisance terms' uncertainty (6x6; zeros for none).
    extrinsic_share: np.ndarray = field(default_factory=lambda: np.zeros((6, 6)))
    # Correlation of the global offset with the translation along the LiDAR's x, y, z.
    offset_translation_correlation: tuple[float, ...] = ()
    range_consistency: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        terms = [{"term": n, "value_mm": 1000 * v, "std_mm": 1000 * s}
                 for n, v, s in zip(self.names, self.values_m, self.std_m)]
        return {"requested": self.requested, "chosen": self.chosen, "reason": self.reason, "terms": terms,
                "tests": list(self.tests), "test": f"likelihood-ratio test at p < {MODEL_TEST_P} per added term",
                "offset_translation_correlation_lidar_xyz": list(self.offset_translation_correlation),
                "range_consistency": self.range_consistency}

    def value(self, name: str) -> float | None:
        return self.values_m[self.names.index(name)] if name in self.names else None


def frame_labels(frames: list[FrameMeasurement]) -> FrameLabels:
    """Ring and black-square labels of every frame's board points."""
    return FrameLabels(tuple(_rings(frames)), tuple(dark_labels(f.lidar) for f in frames))


def _rings(frames: list[FrameMeasurement]) -> list[np.ndarray | None]:
    if any(f.lidar.is_scan_line for f in frames):
        return [None] * len(frames)
    if all(f.lidar.rings is not None for f in frames):
        return [np.asarray(f.lidar.rings, dtype=np.int64) for f in frames]
    # No ring field: cluster the beams' elevations over every frame's board points (one ring per cluster).
    elev = [np.arctan2(f.lidar.points[:, 2], np.hypot(f.lidar.points[:, 0], f.lidar.points[:, 1])) for f in frames]
    allv = np.sort(np.concatenate(elev))
    edges = allv[:-1][np.diff(allv) > RING_GAP_RAD] if len(allv) > 1 else np.array([])
    return [np.searchsorted(edges, e, side="left").astype(np.int64) for e in elev]


def dark_labels(obs: LidarBoardObservation) -> np.ndarray | None:
    """True for a board point on a black square, from its intensity (Otsu's threshold on the board's
    points), or None when the scan has no intensity or the board's intensities are not clearly two groups."""
    if obs.intensity is None or obs.is_scan_line or len(obs.intensity) < 20:
        return None
    x = np.asarray(obs.intensity, dtype=float)
    s = np.sort(x)
    n = len(s)
    k = np.arange(1, n)
    c = np.cumsum(s)[:-1]
    m0, m1 = c / k, (c[-1] + s[-1] - c) / (n - k)
    between = k * (n - k) * (m1 - m0) ** 2
    j = int(np.argmax(between))
    lo, hi = s[: j + 1], s[j + 1:]
    if min(len(lo), len(hi)) < 0.1 * n:
        return None
    pooled = np.sqrt((lo.var() * len(lo) + hi.var() * len(hi)) / n)
    if hi.mean() - lo.mean() < MIN_INTENSITY_SEPARATION * max(pooled, 1e-9):
        return None
    return x <= s[j]


def terms_for(model: str, labels: FrameLabels) -> RangeTerms | None:
    """The nuisance terms of a model, or None for ``none``. ``per-ring`` without known rings (a 2D scanner,
    one elevation) and ``full`` without black/white labels fall back to the terms the data allow."""
    if model == "none":
        return None
    names, sds, rings = ["offset"], [OFFSET_PRIOR_SD_M], ()
    if model in ("per-ring", "full"):
        known = [r for r in labels.rings if r is not None]
        ids = sorted(set(np.concatenate(known).tolist())) if known else []
        if len(ids) > 1:
            rings = tuple(int(r) for r in ids)
            names += [f"ring {r}" for r in rings]
            sds += [RING_PRIOR_SD_M] * len(rings)
    if model == "full" and any(d is not None and d.any() and not d.all() for d in labels.dark):
        names.append("dark")
        sds.append(DARK_PRIOR_SD_M)
    return RangeTerms(tuple(names), tuple(sds), rings)


def regressors(n_points: int, terms: RangeTerms, rings: np.ndarray | None, dark: np.ndarray | None) -> np.ndarray:
    """Each point's regressors ``a`` (n x K) over ``terms``."""
    A = np.zeros((n_points, terms.size))
    A[:, 0] = 1.0
    if terms.rings and rings is not None:
        col = {r: 1 + j for j, r in enumerate(terms.rings)}
        idx = np.array([col.get(int(r), -1) for r in rings])
        ok = idx >= 0
        A[np.flatnonzero(ok), idx[ok]] = 1.0
    if "dark" in terms.names and dark is not None:
        A[:, terms.names.index("dark")] = dark
    return A


def frame_whitener(obs: LidarBoardObservation, sigma_range_m: float, terms: RangeTerms | None,
                   rings: np.ndarray | None = None, dark: np.ndarray | None = None) -> FrameWhitener:
    """The frame's plane-factor data at range noise ``sigma_range_m`` (the moments' noise term removed):
    the range moment of :func:`~estimators.measurements.lidar_whitener`, weighed at the recorded plane and
    extended by the terms' regressors."""
    m = obs.plane.normal
    P = obs.points if not obs.is_scan_line else np.column_stack([obs.points[:, :2], np.zeros(obs.n_points)])
    beams = P / np.linalg.norm(P, axis=1, keepdims=True)
    m_away = m if float(np.mean(beams @ m)) >= 0 else -m
    if terms is None:
        A, cols = np.zeros((len(P), 0)), np.zeros(0, dtype=int)
    else:
        A = regressors(len(P), terms, rings, dark)
        cols = np.flatnonzero(np.any(A != 0, axis=0))
        A = A[:, cols]
    c = np.maximum(np.abs(beams @ m), MIN_INCIDENCE_COS)
    # Each term moves its points' plane distance by (term) x (the board's mean incidence cosine): a global
    # offset is then, within one board, exactly a shift of the board's plane, and is told from the plane
    # only by the camera across boards. (Read from the incidence of each point instead, it would lean on
    # how ranges vary with incidence within a board, which real sensors bias in other ways.)
    A = A * (float(np.mean(c)) / c)[:, None]
    Z = np.hstack([np.column_stack([P, np.ones(len(P))]) / c[:, None], -A])
    M = Z.T @ Z
    M[:3, :3] -= sigma_range_m**2 * (beams / c[:, None] ** 2).T @ beams
    W, floor = sqrt_excess_moment_nuisance(M, obs.is_scan_line)
    return FrameWhitener(W, cols, m_away, floor)


def frame_whiteners(frames: list[FrameMeasurement], sigma_range_m: float, terms: RangeTerms | None,
                    labels: FrameLabels | None = None) -> list[FrameWhitener]:
    labels = labels or frame_labels(frames)
    return [frame_whitener(f.lidar, sigma_range_m, terms, labels.rings[i], labels.dark[i])
            for i, f in enumerate(frames)]


def point_residuals(obs: LidarBoardObservation, pi: np.ndarray, terms: RangeTerms | None, beta: np.ndarray | None,
                    rings: np.ndarray | None = None, dark: np.ndarray | None = None) -> np.ndarray:
    """Each board point's range residual (m) under plane ``pi`` (LiDAR frame) and the range terms (the report
    plots them against range, ring and square colour)."""
    P = obs.points if not obs.is_scan_line else np.column_stack([obs.points[:, :2], np.zeros(obs.n_points)])
    beams = P / np.linalg.norm(P, axis=1, keepdims=True)
    mb = beams @ pi[:3]
    mb = np.where(np.abs(mb) < 1e-9, 1e-9, mb)
    r = (P @ pi[:3] + pi[3]) / mb
    if terms is not None and beta is not None:
        r = r - regressors(len(P), terms, rings, dark) @ beta
    return r
