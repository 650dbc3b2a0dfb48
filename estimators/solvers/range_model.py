"""The LiDAR range model: systematic range errors as nuisance terms of the plane and scan-line factors.

A return's measured range is ``rho = rho_true + a . beta + noise``, with ``a`` the return's regressors:

- ``offset``: 1 for every return (a global range offset; prior 0 +- 5 cm);
- ``ring r``: 1 for the returns of beam ``r`` (per-laser offsets of a multi-beam LiDAR, deviations from the
  global offset; prior 0 +- 1 cm). Rings come from the scan's ``ring`` field (or an organised cloud's rows),
  or from clustering the board points' beam elevations when the scan has neither;
- ``dark``: 1 for returns from the board's black squares (a reflectivity-dependent offset; prior 0 +- 5 cm).
  Black and white returns are told apart by their intensity (two clusters, Otsu's threshold) where the scan
  has an intensity field and the board's intensities are clearly bimodal.

Each return is modelled as ``rho = d / (m . b) + a . beta + noise`` (``b`` its unit beam, ``[m; -d]`` the
board's plane; MATH.md section 2). Each frame is compressed once: its plane fitted to its ranges, and the
cost's second-order expansion there in the plane and the frame's own terms (Gauss-Newton, :func:`_range_fit`),
so the factor keeps O(1) statistics per frame. The residual is ``W [s pi; S beta] + e0``, with ``S`` the
frame's own terms from the shared ones (:func:`frame_design`) and ``s = sign(m . m_away)`` orienting the
camera's plane like the fitted one (facing away from the sensor). Within one board a distance and an offset
trade along a weak direction (``FrameWhitener.weak``); the refinement estimates a per-board scatter along it
when the boards disagree there beyond the noise.

Model choice (``auto``): the terms are added in order (offset, per-ring, dark) while the data support them:
a likelihood-ratio test at 0.1% on the refined objective, the boards' best-fit floors included, against the
degrees of freedom the term adds (0.1%, not 1%: a needless offset costs a VLP-16's translation much, `make bench`).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from geometry.planes import sqrt_excess_moment, sqrt_excess_moment_scan

from ..measurements import MIN_INCIDENCE_COS, FrameMeasurement, LidarBoardObservation

RANGE_MODELS = ("none", "offset", "per-ring", "full", "auto")
OFFSET_PRIOR_SD_M = 0.05
RING_PRIOR_SD_M = 0.01
DARK_PRIOR_SD_M = 0.05
# Significance of the likelihood-ratio test that adds a term in ``auto``.
MODEL_TEST_P = 0.001
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
    """A frame's plane-factor data: the residual ``W [s pi; S beta] + e0`` (``W`` k x (4 + K_f)), ``S``
    (K_f x K) the frame's own terms from the shared ``beta`` (a ring's term is the global offset plus the
    ring's own), the fitted plane's normal facing away from the sensor, the best fit's cost ``floor`` (m^2),
    and with terms ``R`` (``W = R P``: the square root of the information on ``x = [tangent part of the
    normal; d; frame terms]``, ``nt`` tangent coordinates)."""

    W: np.ndarray
    S: np.ndarray
    m_away: np.ndarray
    floor: float
    e0: np.ndarray
    R: np.ndarray | None = None
    nt: int = 0
    # The board's weak direction in x: its distance and its offsets trading (d up by mean incidence x eps,
    # every offset down by eps), told apart only by how incidence varies across the board (unit vector).
    weak: np.ndarray | None = None

    @property
    def W_plane(self) -> np.ndarray:
        return self.W[:, :4]

    @property
    def W_nuisance(self) -> np.ndarray:
        """``dW/dbeta``: the residual's Jacobian by the shared terms (k x K)."""
        return self.W[:, 4:] @ self.S


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
    terms_covariance: np.ndarray | None = None  # K x K, marginal
    # The part of the extrinsic's covariance due to the nuisance terms' uncertainty (6x6; zeros for none).
    extrinsic_share: np.ndarray = field(default_factory=lambda: np.zeros((6, 6)))
    # Correlation of the global offset with the translation along the LiDAR's x, y, z.
    offset_translation_correlation: tuple[float, ...] = ()
    # How far the boards' own terms are from the shared ones (chi-square, dof, p) and the per-board scatter.
    term_consistency: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        terms = [{"term": n, "value_mm": 1000 * v, "std_mm": 1000 * s}
                 for n, v, s in zip(self.names, self.values_m, self.std_m)]
        return {"requested": self.requested, "chosen": self.chosen, "reason": self.reason, "terms": terms,
                "tests": list(self.tests), "test": f"likelihood-ratio test at p < {MODEL_TEST_P} per added term",
                "offset_translation_correlation_lidar_xyz": list(self.offset_translation_correlation),
                "board_terms_consistency": self.term_consistency}

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


def frame_design(n_points: int, terms: RangeTerms, rings: np.ndarray | None, dark: np.ndarray | None
                 ) -> tuple[np.ndarray, np.ndarray]:
    """A frame's own terms: each point's regressors ``A`` (n x K_f, independent columns) and ``S`` (K_f x K)
    mapping the shared ``beta`` to them. With rings: one column per ring seen (its term: the global offset
    plus the ring's own); without: the global offset; then the black squares' term when both colours are
    seen."""
    if not terms.size:
        return np.zeros((n_points, 0)), np.zeros((0, 0))
    cols, rows = [], []
    if terms.rings and rings is not None:
        index = {r: 1 + j for j, r in enumerate(terms.rings)}
        for r in np.unique(rings):
            if int(r) in index:
                cols.append((rings == r).astype(float))
                row = np.zeros(terms.size)
                row[0], row[index[int(r)]] = 1.0, 1.0
                rows.append(row)
        covered = np.sum(cols, axis=0) if cols else np.zeros(n_points)
        if np.any(covered == 0):  # returns of rings the terms do not hold: the global offset alone
            cols.append((covered == 0).astype(float))
            rows.append(np.eye(terms.size)[0])
    else:
        cols.append(np.ones(n_points))
        rows.append(np.eye(terms.size)[0])
    if "dark" in terms.names and dark is not None and dark.any() and not dark.all():
        cols.append(np.asarray(dark, dtype=float))
        rows.append(np.eye(terms.size)[terms.names.index("dark")])
    return np.column_stack(cols), np.array(rows)


def frame_whitener(obs: LidarBoardObservation, sigma_range_m: float, terms: RangeTerms | None,
                   rings: np.ndarray | None = None, dark: np.ndarray | None = None) -> FrameWhitener:
    """The frame's plane-factor data. Without terms (None): the square root of the board points' range
    moment with its noise term removed at ``sigma_range_m`` (:func:`~estimators.measurements.lidar_whitener`,
    weighed at the recorded plane). With terms (an empty :class:`RangeTerms` included): the frame's own
    plane and terms from its ranges, and their information (:func:`_range_fit`)."""
    m = obs.plane.normal
    P = obs.points if not obs.is_scan_line else np.column_stack([obs.points[:, :2], np.zeros(obs.n_points)])
    beams = P / np.linalg.norm(P, axis=1, keepdims=True)
    m_away = m if float(np.mean(beams @ m)) >= 0 else -m
    if terms is None:
        c = np.maximum(np.abs(beams @ m), MIN_INCIDENCE_COS)
        Z = np.column_stack([P, np.ones(len(P))]) / c[:, None]
        M = Z.T @ Z
        M[:3, :3] -= sigma_range_m**2 * (beams / c[:, None] ** 2).T @ beams
        W, floor = (sqrt_excess_moment_scan if obs.is_scan_line else sqrt_excess_moment)(M)
        return FrameWhitener(W, np.zeros((0, 0)), m_away, floor, np.zeros(W.shape[0]))
    A, S = frame_design(len(P), terms, rings, dark)
    W, e0, floor, R = _range_fit(np.linalg.norm(P, axis=1), beams, A, m_away, obs.is_scan_line)
    nt = 1 if obs.is_scan_line else 2
    vals, vecs = np.linalg.eigh(R.T @ R)
    weak = vecs[:, 0]
    return FrameWhitener(W, S, m_away, floor, e0, R, nt, weak)


def _tangent(m: np.ndarray, scan_line: bool) -> np.ndarray:
    """Unit vectors (3 x 2, or 3 x 1 in the scan plane for a scan line) orthogonal to the normal ``m``."""
    if scan_line:
        return np.array([[-m[1], m[0], 0.0]]).T / max(np.hypot(m[0], m[1]), 1e-12)
    return np.linalg.svd(m[None, :])[2][1:].T


def _range_fit(rho: np.ndarray, beams: np.ndarray, A: np.ndarray, m0: np.ndarray, scan_line: bool,
               iterations: int = 8) -> tuple[np.ndarray, np.ndarray, float, np.ndarray]:
    """One board's plane and range terms from its ranges, compressed to a residual.

    The model of each return is ``rho = d / (m . b) + a . beta + noise``: the ranges are the observations and
    the beams are known, so Gauss-Newton on it is plain least squares (no errors in the variables, and no
    spurious minimum where an offset mimics a rescaled normal, as it does in a moment's quadratic form).
    The plane alone is fitted first (``beta = 0``); about that point, with ``x = [tangent part of the
    normal; d; beta]``, the cost is ``floor + |R (x - x*)|^2`` to second order (Gauss-Newton; ``beta`` stays
    near 0, while within one board an offset and the plane's distance can trade far along a flat valley).
    Returned as ``W = R P`` and ``e0`` with ``x = P theta`` read from ``theta = [n; -d; beta]`` (the normal's
    tangent part), the floor, and ``R``.
    """
    m = m0 / np.linalg.norm(m0)
    mb = np.maximum(beams @ m, MIN_INCIDENCE_COS)
    d = float(np.sum(rho / mb) / np.sum(1.0 / mb**2))  # least squares d for the initial normal

    def jacobian(m, d):
        T = _tangent(m, scan_line)
        mb = np.maximum(beams @ m, MIN_INCIDENCE_COS)
        return T, rho - d / mb, np.hstack([(d / mb**2)[:, None] * (beams @ T), -(1.0 / mb)[:, None], -A])

    nt = 1 if scan_line else 2
    for _ in range(iterations):
        T, r, J = jacobian(m, d)
        step = np.linalg.lstsq(J[:, :nt + 1], -r, rcond=None)[0]
        m = m + T @ step[:nt]
        m /= np.linalg.norm(m)
        d += step[nt]
        if np.max(np.abs(step)) < 1e-10:
            break
    T, r, J = jacobian(m, d)
    vals, vecs = np.linalg.eigh(J.T @ J)
    keep = vals > 1e-10 * vals[-1]
    g = J.T @ r
    Hg = (vecs[:, keep] / vals[keep]) @ (vecs[:, keep].T @ g)
    K = A.shape[1]
    x_star = np.concatenate([np.zeros(nt), [d], np.zeros(K)]) - Hg
    R = np.sqrt(vals[keep])[:, None] * vecs[:, keep].T
    Pm = np.zeros((nt + 1 + K, 4 + K))  # x = Pm theta
    Pm[:nt, :3] = T.T
    Pm[nt, 3] = -1.0
    Pm[nt + 1:, 4:] = np.eye(K)
    return R @ Pm, -R @ x_star, float(r @ r - g @ Hg), R


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
