"""The LiDAR range model: systematic range errors as nuisance terms of the plane and scan-line factors.

A return's measured range is ``rho = rho_true + a . beta + noise``, with ``a`` the return's regressors:

- ``offset``: 1 for every return (a global range offset);
- ``ring r``: 1 for the returns of beam ``r`` (per-laser offsets of a multi-beam LiDAR, deviations from the
  global offset). Rings come from the scan's ``ring`` field (or an organised cloud's rows), or from clustering
  the board points' beam elevations when the scan has neither;
- ``dark``: 1 for returns from the board's black squares (a reflectivity-dependent offset; near an edge, the
  chance that the beam's centre is on black). The squares are placed by geometry: the camera's board pose, the
  printed pattern (a ChArUco board's markers included; a checkerboard's colours read from the image) and the
  current extrinsic (:func:`geometric_dark`), so a LiDAR whose intensity is saturated or uncalibrated still
  has the term. Where the scan's intensities fall in two clear groups, they
  cross-check the geometry (:attr:`FrameLabels.intensity_agreement`).

Priors come from the sensor's range accuracy (``range_accuracy_m``: ``lidar.range_accuracy_m`` in dataset.yaml,
``--range-accuracy``, or the sensor family's default, :data:`RANGE_ACCURACY_M`): the global offset and the
black-square term 0 +- the accuracy, each ring 0 +- a fifth of it about the global offset.

Each return is modelled as ``rho = d / (m . b) + a . beta + noise`` (``b`` its unit beam, ``[m; -d]`` the
board's plane; MATH.md section 2). Each frame is compressed once: its plane fitted to its ranges, and the
cost's second-order expansion there in the plane and the frame's own terms (Gauss-Newton, :func:`_range_fit`),
so the factor keeps O(1) statistics per frame. The residual is ``W [s pi; S beta] + e0``, with ``S`` the
frame's own terms from the shared ones (:func:`frame_design`) and ``s = sign(m . m_away)`` orienting the
camera's plane like the fitted one (facing away from the sensor). Within one board a distance and an offset
trade along a weak direction (``FrameWhitener.weak``, scaled to one metre of the board's offset); the
refinement estimates a per-board scatter of the offset along it (``board_scatter_m``: a range error that grows
with incidence shows there as tenths of metres) when the boards disagree there beyond the noise.

Model choice (``auto``, ``solvers.refinement``): a global offset, then the per-ring and the black-square terms,
each kept while a likelihood-ratio test at 0.1% supports it. When the boards' planes disagree beyond the noise
(overdispersed data: every recorded set), the test is made with the per-board plane error estimated under the
larger model in place and against an F distribution, so that board-to-board structure the model does not
explain is not read as a range term.
"""
from __future__ import annotations

import weakref
from dataclasses import dataclass, field

import numpy as np

from geometry.planes import cut_with_board, plane_basis, sqrt_excess_moment, sqrt_excess_moment_scan
from geometry.rotations import T_exp
from geometry.vectors import row_norms

from ..lidar.board_segmentation import along_beams
from ..lidar.lidar_models import (DEFAULT_RANGE_ACCURACY_M, RANGE_ACCURACY_M, RING_PRIOR_SHARE,  # noqa: F401
                                   range_accuracy_for)
from ..measurements import MIN_INCIDENCE_COS, FrameMeasurement, LidarBoardObservation

RANGE_MODELS = ("none", "offset", "per-ring", "offset+dark", "full", "auto")
OFFSET_PRIOR_SD_M = DEFAULT_RANGE_ACCURACY_M
# A term further than this many prior standard deviations from its prior mean is not believed (confounding, a
# wrong segment, a moving board): it is held at the prior and its prior variance propagated instead.
MAX_PRIOR_SIGMAS = 3.0
# Correlation of a term with a direction of the extrinsic above which the two are called confounded.
CONFOUNDED_CORRELATION = 0.9
# The board's position along its own plane from the camera and the extrinsic (m, 1 sd) at which the colours
# are placed: a return's black share is the chance that its beam's centre lies on black. Not the footprint's
# area: at an edge the white part's echo dominates a mixed return (a black square reflects a tenth as much), so
# the area share would overstate its black share (and in simulation, whose beams are points, it biased the
# black-square term by a standard deviation).
LABEL_POSITION_SD_M = 0.001
# Below this agreement between intensity and geometry on clearly black or white returns, a warning is given (the
# recorded sets agree at 78-95%: Otsu's threshold on noisy intensities; swapped colours agree at 15-30%).
MIN_INTENSITY_AGREEMENT = 0.7
# Significance of the likelihood-ratio test that adds a term in ``auto``.
MODEL_TEST_P = 0.001
# Below this p-value (and above MODEL_TEST_P) a global offset ``auto`` passes over is still evidence: the covariance
# holds the answer with it beside the one without (``RangeModelFit.weak_offset``). On boards facing a VLP-16 ranging
# 2 cm long the offset's test read p = 0.002-0.03 in 3 of 24 layouts, whose answers, 14-20 mm off, lay at d2 470-580
# under a covariance without it (bench_weak_offset); on the same 48 layouts ranging right 1 test read below it.
OFFSET_HELD_P = 0.05
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
            return "full" if self.rings else "offset+dark"
        return "per-ring" if self.rings else "offset"


@dataclass(frozen=True)
class FrameLabels:
    """Per frame, each board point's ring (None: not known) and its footprint's share on the black squares
    (None: not told apart), from geometry where the board and the extrinsic are given, else from intensity.
    ``intensity_agreement``: per frame, the share of clearly black or white returns whose intensity says the
    same (None where the intensities are not two clear groups or the colours come from intensity)."""

    rings: tuple
    dark: tuple
    source: str = "intensity"
    intensity_agreement: tuple = ()
    names: tuple = ()  # the frames' names, in order
    # The extrinsic's covariance (6 x 6, tangent) the geometric colours were placed under (None: the floor only).
    placement_cov: np.ndarray | None = None

    def select(self, frames: list[FrameMeasurement]) -> "FrameLabels | None":
        """These labels for ``frames`` (by name), or None when a frame has none."""
        index = {n: k for k, n in enumerate(self.names)}
        if not all(f.name in index for f in frames):
            return None
        ks = [index[f.name] for f in frames]
        return FrameLabels(tuple(self.rings[k] for k in ks), tuple(self.dark[k] for k in ks), self.source,
                           tuple(self.intensity_agreement[k] for k in ks) if self.intensity_agreement else (),
                           tuple(self.names[k] for k in ks), self.placement_cov)

    def agreement(self) -> float | None:
        """The intensity's agreement with geometry over all frames (None when it could not be checked)."""
        pairs = [a for a in self.intensity_agreement if a is not None]
        return float(np.sum([a[0] for a in pairs]) / np.sum([a[1] for a in pairs])) if pairs and sum(
            a[1] for a in pairs) else None


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
    # every offset down by eps), told apart only by how incidence varies across the board (scaled to one metre
    # of the board's own offset).
    weak: np.ndarray | None = None
    # The board points' centroid (LiDAR frame; a scan line's in its plane): a per-board plane error tilts the
    # board about it. With terms, the tangent basis (3 x nt) of the normal in ``x``.
    centre: np.ndarray | None = None
    tangent: np.ndarray | None = None

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
    # The sensor's range accuracy (m) that set the priors.
    range_accuracy_m: float = DEFAULT_RANGE_ACCURACY_M
    # Where the black squares came from (geometry or intensity) and, with geometry, the intensity's agreement.
    labels_from: str = "intensity"
    intensity_agreement: float | None = None
    # Terms held at 0 because their estimates lay beyond MAX_PRIOR_SIGMAS prior sds, and those estimates (m).
    pinned: tuple[str, ...] = ()
    pinned_values_m: tuple[float, ...] = ()
    # The term most correlated with a direction of the extrinsic, when above CONFOUNDED_CORRELATION.
    confounding: dict | None = None
    # The frames' ring and black-square labels the terms were estimated with.
    labels: FrameLabels | None = None
    # Under ``auto``, the models whose terms the tests supported but which left the boards' planes more inconsistent
    # than the offset alone, so the choice fell back past them: structure the estimate does not hold.
    left_out: tuple[str, ...] = ()
    # Under ``auto``, a global offset not taken that its last test still supported at ``OFFSET_HELD_P``: that test's
    # p-value, whether the ring ends were in its graph, the offset (mm) and the estimate's shift with it (the
    # project's 6-vector tangent at the estimate without it), whose outer product the covariance holds. None else.
    weak_offset: dict | None = None

    def labels_for(self, frames: list[FrameMeasurement], board=None, T_camera_lidar=None) -> FrameLabels:
        """The labels of ``frames``: the estimate's own where it has them, else placed anew (by geometry when
        the estimate's were and the board and extrinsic are given)."""
        own = self.labels.select(frames) if self.labels is not None else None
        if own is not None:
            return own
        if self.labels_from == "geometry":
            return frame_labels(frames, board, T_camera_lidar)
        return frame_labels(frames)

    def to_dict(self) -> dict:
        terms = [{"term": n, "value_mm": 1000 * v, "std_mm": 1000 * s,
                  "prior_sd_mm": 1000 * float(self.terms.prior_sd[k]) if self.terms is not None else None,
                  "held_at_prior": n in self.pinned}
                 for k, (n, v, s) in enumerate(zip(self.names, self.values_m, self.std_m))]
        return {"requested": self.requested, "chosen": self.chosen, "reason": self.reason, "terms": terms,
                "tests": list(self.tests),
                "test": (f"likelihood-ratio test at p < {MODEL_TEST_P} per added block of terms, referred to F; with "
                         "the per-board plane error estimated under the larger model when the boards' planes "
                         "disagree beyond the noise"),
                "range_accuracy_m": self.range_accuracy_m,
                "black_squares_from": self.labels_from, "intensity_agreement": self.intensity_agreement,
                "held_at_prior": [{"term": n, "estimate_mm": 1000 * v}
                                  for n, v in zip(self.pinned, self.pinned_values_m)],
                "left_out": list(self.left_out),
                "weak_offset": self.weak_offset,
                "confounding": self.confounding,
                "offset_translation_correlation_lidar_xyz": list(self.offset_translation_correlation),
                "board_terms_consistency": self.term_consistency}

    def value(self, name: str) -> float | None:
        return self.values_m[self.names.index(name)] if name in self.names else None


def frame_labels(frames: list[FrameMeasurement], board=None, T_camera_lidar: np.ndarray | None = None,
                 boards: list | None = None, placement_cov: np.ndarray | None = None) -> FrameLabels:
    """Ring and black-square labels of every frame's board points. Given the board model and the extrinsic, the
    black squares are placed by geometry (:func:`geometric_dark`, on each frame's board pose: ``boards`` or
    the camera's own; ``placement_cov`` the extrinsic's 6 x 6 covariance, whose spread blurs the placement) and
    the intensities only cross-check them; else they come from intensity."""
    rings = tuple(frame_rings([f.lidar for f in frames]))
    if board is None or T_camera_lidar is None:
        return FrameLabels(rings, tuple(dark_labels(f.lidar) for f in frames), names=tuple(f.name for f in frames))
    from ..camera.charuco import pattern_reflectance  # the printed pattern, a ChArUco board's markers included

    reflectance = pattern_reflectance(board)
    T_lidar_camera = np.linalg.inv(T_camera_lidar)
    dark, agree = [], []
    for i, f in enumerate(frames):
        if f.lidar.is_scan_line or f.camera is None:
            dark.append(None)
            agree.append(None)
            continue
        T_cb = boards[i] if boards is not None else f.camera.T_camera_board
        flip = _inverted(board, reflectance) if f.camera.pattern_inverted else reflectance
        share = geometric_dark(f.lidar.points, T_lidar_camera @ T_cb, flip, placement_cov=placement_cov)
        dark.append(share)
        by_intensity = dark_labels(f.lidar)
        clear = (share < 0.1) | (share > 0.9)
        agree.append(None if by_intensity is None or not clear.any() else
                     (int(np.sum(by_intensity[clear] == (share[clear] > 0.5))), int(clear.sum())))
    return FrameLabels(rings, tuple(dark), "geometry", tuple(agree), tuple(f.name for f in frames), placement_cov)


def _inverted(board, reflectance):
    """``reflectance`` with black and white swapped inside the printed pattern (the board's margins stay white):
    the colours of a checkerboard whose detected grid started at a corner of the other colour."""
    lo = board.offset
    hi = lo + np.array(board.pattern_extent)

    def swapped(x, y):
        r = reflectance(x, y)
        inside = (x >= lo[0]) & (x < hi[0]) & (y >= lo[1]) & (y < hi[1]) & np.isfinite(r)
        return np.where(inside, 1.0 - r, r)

    return swapped


def geometric_dark(points: np.ndarray, T_lidar_board: np.ndarray, reflectance,
                   position_sd_m: float = LABEL_POSITION_SD_M, placement_cov: np.ndarray | None = None) -> np.ndarray:
    """Each return's black share: its beam cut with the board's plane (the camera's, so the range noise does not
    move it), the printed pattern's reflectance there (``reflectance(x, y)`` in board coordinates, below 0.5 on
    black) averaged over a Gaussian of the position's uncertainty by 5 x 5 Gauss-Hermite quadrature. Returns off
    the board count as white.

    The position's uncertainty is ``position_sd_m`` in both board axes, plus, given ``placement_cov`` (the
    extrinsic's 6 x 6 covariance in the tangent convention), each cut's own 2 x 2 covariance under it (its cut
    moved along each principal direction by one standard deviation each way). The share is then the chance of
    black given what is known of the placement: regressed on it, the black-square term is not shrunk by the
    placement's error (Berkson's error model), where shares placed sharper than they are known would shrink it."""
    P = np.asarray(points, dtype=float)
    beams = P / row_norms(P)[:, None]
    T_board_lidar = np.linalg.inv(T_lidar_board)
    local = cut_with_board(T_board_lidar, beams)[0]
    cxx = np.full(len(P), position_sd_m ** 2)
    cyy, cxy = cxx.copy(), np.zeros(len(P))
    if placement_cov is not None and np.all(np.isfinite(placement_cov)):
        ev, V = np.linalg.eigh(0.5 * (placement_cov + placement_cov.T))
        for lam, v in zip(ev, V.T):
            step = np.sqrt(max(lam, 0.0)) * v
            # T_camera_lidar Exp(xi) moves T_lidar_board to Exp(-xi) T_lidar_board.
            ahead = cut_with_board(T_board_lidar @ T_exp(step), beams)[0]
            back = cut_with_board(T_board_lidar @ T_exp(-step), beams)[0]
            d = 0.5 * (ahead - back)
            cxx += d[:, 0] ** 2
            cyy += d[:, 1] ** 2
            cxy += d[:, 0] * d[:, 1]
    # Each cut's Cholesky factor [[l11, 0], [l21, l22]].
    l11 = np.sqrt(cxx)
    l21 = cxy / l11
    l22 = np.sqrt(np.maximum(cyy - l21 ** 2, 0.0))
    nodes, weights = np.polynomial.hermite_e.hermegauss(5)
    weights = weights / weights.sum()
    share = np.zeros(len(P))
    for zi, wi in zip(nodes, weights):
        for zj, wj in zip(nodes, weights):
            r = reflectance(local[:, 0] + l11 * zi, local[:, 1] + l21 * zi + l22 * zj)
            share += wi * wj * (np.nan_to_num(r, nan=1.0) < 0.5)
    return share


def _two_colours(dark: np.ndarray | None) -> bool:
    """Whether a frame's black shares hold both colours (a black-square term is then told from an offset)."""
    return dark is not None and bool(np.any(dark > 0.5)) and bool(np.any(dark < 0.5))


def frame_rings(observations: list) -> list[np.ndarray | None]:
    """Each LiDAR board observation's points' ring ids: the scan's own, or the beams' elevations clustered over
    every observation (one ring per cluster; None for 2D scans, and for a board that no separate beams swept)."""
    if any(o.is_scan_line for o in observations):
        return [None] * len(observations)
    if all(o.rings is not None for o in observations):
        return [np.asarray(o.rings, dtype=np.int64) for o in observations]
    # No ring field: cluster the beams' elevations over every frame's board points (one ring per cluster). A board
    # whose elevations span several gaps' widths yet fall in fewer than three clusters was not swept by separate
    # beams (a non-repetitive pattern fills the elevations between them): it has no rings.
    elev = [np.arctan2(o.points[:, 2], np.hypot(o.points[:, 0], o.points[:, 1])) for o in observations]
    allv = np.sort(np.concatenate(elev))
    edges = allv[:-1][np.diff(allv) > RING_GAP_RAD] if len(allv) > 1 else np.array([])
    rings = [np.searchsorted(edges, e, side="left").astype(np.int64) for e in elev]
    return [None if len(np.unique(r)) < 3 and np.ptp(e) > 3 * RING_GAP_RAD else r for r, e in zip(rings, elev)]


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


def terms_for(model: str, labels: FrameLabels, range_accuracy_m: float = DEFAULT_RANGE_ACCURACY_M
              ) -> RangeTerms | None:
    """The nuisance terms of a model, or None for ``none``, with priors from the range accuracy. ``per-ring``
    without known rings (a 2D scanner, one elevation) and ``full`` or ``offset+dark`` without both colours on
    the boards fall back to the terms the data allow."""
    if model == "none":
        return None
    acc = float(range_accuracy_m)
    names, sds, rings = ["offset"], [acc], ()
    if model in ("per-ring", "full"):
        known = [r for r in labels.rings if r is not None]
        ids = sorted(set(np.concatenate(known).tolist())) if known else []
        if len(ids) > 1:
            rings = tuple(int(r) for r in ids)
            names += [f"ring {r}" for r in rings]
            sds += [RING_PRIOR_SHARE * acc] * len(rings)
    if model in ("full", "offset+dark") and any(_two_colours(d) for d in labels.dark):
        names.append("dark")
        sds.append(acc)
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
    if "dark" in terms.names and _two_colours(dark):
        cols.append(np.asarray(dark, dtype=float))
        rows.append(np.eye(terms.size)[terms.names.index("dark")])
    return np.column_stack(cols), np.array(rows)


def symmetric_band(obs: LidarBoardObservation, terms: RangeTerms, beta: np.ndarray, rings: np.ndarray | None,
                   dark: np.ndarray | None) -> np.ndarray | None:
    """Which of a 3D board's returns to keep so that each one's range noise is cut symmetrically about its own
    expected range under the range terms ``beta`` (None: all of them, or too few left).

    The segmentation keeps a board's returns within a band of its plane along their beams (``NOISE_BAND_SIGMA``
    robust sd), a plane fitted without the terms: a return the terms put behind it (a black square's, 1 cm) has
    the far tail of its noise cut more than the near one, which pulls its term towards 0
    (``bench_range_model_scenes.py --dark-bias``). Here the band is the returns' own (``h``: the largest distance
    along a beam from the observation's plane, which the band's own plane is close to); each return's expected
    distance ``mu`` from that plane is its terms' offset plus the frame's own plane under them (fitted to the
    ranges less the offsets: a board's own plane error and offset stay its own), and the returns kept are those
    within ``h - |mu|`` of it, so that every return's noise is cut at the same distance on both sides, as the
    terms' regression takes it."""
    if obs.is_scan_line or not terms.size:
        return None
    A, S = frame_design(obs.n_points, terms, rings, dark)
    if not A.size:
        return None
    P = obs.points
    plane = obs.plane.facing_away()  # its normal away from the LiDAR: longer ranges lie on its positive side
    r = along_beams(P, plane)  # each return's distance from it along its beam
    cos = np.maximum(P @ plane.normal / row_norms(P), MIN_INCIDENCE_COS)
    m = A @ (S @ np.asarray(beta, dtype=float))
    # A plane's change moves a return's range by (dd - dn . p) / cos with dn in the plane: [1, u, v] / cos.
    uv = (P - P.mean(0)) @ plane_basis(plane.normal)
    Z = np.column_stack([np.ones(len(P)), uv]) / cos[:, None]
    mu = m + Z @ np.linalg.lstsq(Z, r - m, rcond=None)[0]
    keep = np.abs(r - mu) <= np.max(np.abs(r)) - np.abs(mu)
    return None if keep.all() or keep.sum() < max(0.9 * len(P), 10) else keep


def frame_whitener(obs: LidarBoardObservation, sigma_range_m: float, terms: RangeTerms | None,
                   rings: np.ndarray | None = None, dark: np.ndarray | None = None) -> FrameWhitener:
    """The frame's plane-factor data. Without terms (None): the square root of the board points' range
    moment with its noise term removed at ``sigma_range_m`` (:func:`~estimators.measurements.lidar_whitener`,
    weighed at the recorded plane). With terms (an empty :class:`RangeTerms` included): the frame's own
    plane and terms from its ranges, and their information (:func:`_range_fit`)."""
    m = obs.plane.normal
    P = obs.points if not obs.is_scan_line else np.column_stack([obs.points[:, :2], np.zeros(obs.n_points)])
    beams = P / row_norms(P)[:, None]
    m_away = m if float(np.mean(beams @ m)) >= 0 else -m
    if terms is None:
        c = np.maximum(np.abs(beams @ m), MIN_INCIDENCE_COS)
        Z = np.column_stack([P, np.ones(len(P))]) / c[:, None]
        M = Z.T @ Z
        M[:3, :3] -= sigma_range_m**2 * (beams / c[:, None] ** 2).T @ beams
        W, floor = (sqrt_excess_moment_scan if obs.is_scan_line else sqrt_excess_moment)(M)
        return FrameWhitener(W, np.zeros((0, 0)), m_away, floor, np.zeros(W.shape[0]), centre=P.mean(0))
    key = (terms.names, terms.rings, None if rings is None else np.asarray(rings).tobytes(),
           None if dark is None else np.asarray(dark, dtype=float).tobytes())
    known = _WHITENERS.setdefault(obs, {})
    if key not in known:
        known[key] = _terms_whitener(obs, P, beams, m_away, terms, rings, dark)
    return known[key]


def _terms_whitener(obs: LidarBoardObservation, P: np.ndarray, beams: np.ndarray, m_away: np.ndarray,
                    terms: RangeTerms, rings: np.ndarray | None, dark: np.ndarray | None) -> FrameWhitener:
    """:func:`frame_whitener` with terms, made once per observation, terms and labels (``_WHITENERS``)."""
    A, S = frame_design(len(P), terms, rings, dark)
    rho = row_norms(P)
    plane = _PLANE_FITS.get(obs)
    if plane is None:
        plane = _PLANE_FITS[obs] = _plane_fit(rho, beams, m_away, obs.is_scan_line)
    W, e0, floor, R, T = _range_fit(rho, beams, A, m_away, obs.is_scan_line, plane)
    nt = 1 if obs.is_scan_line else 2
    vals, vecs = np.linalg.eigh(R.T @ R)
    weak = vecs[:, 0]
    # Scaled to one metre of the board's own offset (the mean of its offset columns: a ring's term holds the
    # global offset), so that a scatter along it is in metres of range offset.
    offset_cols = np.flatnonzero(S[:, 0] == 1.0) if S.size else np.array([], dtype=int)
    along = float(np.mean(weak[nt + 1 + offset_cols])) if offset_cols.size else 0.0
    if abs(along) > 1e-3:
        weak = weak / along
    return FrameWhitener(W, S, m_away, floor, e0, R, nt, weak, P.mean(0), T)


def _tangent(m: np.ndarray, scan_line: bool) -> np.ndarray:
    """Unit vectors (3 x 2, or 3 x 1 in the scan plane for a scan line) orthogonal to the normal ``m``."""
    if scan_line:
        return np.array([[-m[1], m[0], 0.0]]).T / max(np.hypot(m[0], m[1]), 1e-12)
    return np.linalg.svd(m[None, :])[2][1:].T


def _plane_fit(rho: np.ndarray, beams: np.ndarray, m0: np.ndarray, scan_line: bool, iterations: int = 8
               ) -> tuple[np.ndarray, float]:
    """A board's plane alone (``beta = 0``) from its ranges by Gauss-Newton (:func:`_range_fit`): its unit normal
    and distance, started at the normal ``m0``."""
    m = m0 / np.linalg.norm(m0)
    mb = np.maximum(beams @ m, MIN_INCIDENCE_COS)
    d = float(np.sum(rho / mb) / np.sum(1.0 / mb**2))  # least squares d for the initial normal
    nt = 1 if scan_line else 2
    for _ in range(iterations):
        T, r, J = _range_jacobian(rho, beams, m, d, np.zeros((len(rho), 0)), scan_line)
        step = np.linalg.lstsq(J[:, :nt + 1], -r, rcond=None)[0]
        m = m + T @ step[:nt]
        m /= np.linalg.norm(m)
        d += step[nt]
        if np.max(np.abs(step)) < 1e-10:
            break
    return m, d


def _range_jacobian(rho, beams, m, d, A, scan_line):
    """The tangent basis at ``m``, the ranges' residuals at the plane ``(m, d)`` and their Jacobian by ``[tangent
    part of the normal; d; beta]``."""
    T = _tangent(m, scan_line)
    mb = np.maximum(beams @ m, MIN_INCIDENCE_COS)
    return T, rho - d / mb, np.hstack([(d / mb**2)[:, None] * (beams @ T), -(1.0 / mb)[:, None], -A])


# Each board observation's plane fit (:func:`_plane_fit`), the same for every range model it is put in: a rig's
# pairs try several models, each over every frame.
_PLANE_FITS: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()
# Each board observation's whiteners with terms, by the terms and labels they were made for: a pair's
# refinement, its range-term tests and a rig's joint choice build the same ones many times over.
_WHITENERS: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()


def _range_fit(rho: np.ndarray, beams: np.ndarray, A: np.ndarray, m0: np.ndarray, scan_line: bool,
               plane: tuple[np.ndarray, float] | None = None
               ) -> tuple[np.ndarray, np.ndarray, float, np.ndarray, np.ndarray]:
    """One board's plane and range terms from its ranges, compressed to a residual.

    The model of each return is ``rho = d / (m . b) + a . beta + noise``: the ranges are the observations and
    the beams are known, so Gauss-Newton on it is plain least squares (no errors in the variables, and no
    spurious minimum where an offset mimics a rescaled normal, as it does in a moment's quadratic form).
    The plane alone is fitted first (``beta = 0``; ``plane``: that fit, :func:`_plane_fit`, when made already);
    about that point, with ``x = [tangent part of the normal; d; beta]``, the cost is ``floor + |R (x - x*)|^2``
    to second order (Gauss-Newton; ``beta`` stays near 0, while within one board an offset and the plane's
    distance can trade far along a flat valley). Returned as ``W = R P`` and ``e0`` with ``x = P theta`` read from
    ``theta = [n; -d; beta]`` (the normal's tangent part), the floor, ``R`` and the tangent basis.
    """
    m, d = plane if plane is not None else _plane_fit(rho, beams, m0, scan_line)
    nt = 1 if scan_line else 2
    T, r, J = _range_jacobian(rho, beams, m, d, A, scan_line)
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
    return R @ Pm, -R @ x_star, float(r @ r - g @ Hg), R, T


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
    beams = P / row_norms(P)[:, None]
    mb = beams @ pi[:3]
    mb = np.where(np.abs(mb) < 1e-9, 1e-9, mb)
    r = (P @ pi[:3] + pi[3]) / mb
    if terms is not None and beta is not None:
        r = r - regressors(len(P), terms, rings, dark) @ beta
    return r


def without_terms(obs: LidarBoardObservation, terms: RangeTerms, beta: np.ndarray, rings: np.ndarray | None = None,
                  dark: np.ndarray | None = None) -> np.ndarray:
    """The board's returns with the range terms taken off (``rho - a . beta``): each moved along its beam, so that
    a board's plane drawn through them is the one the estimate holds it to (a 5 cm range offset would otherwise
    read as a board 5 cm off the camera's)."""
    P = np.asarray(obs.points, dtype=float)
    r = row_norms(P)
    return P * (1.0 - (regressors(len(P), terms, rings, dark) @ np.asarray(beta, dtype=float))
                / np.maximum(r, 1e-9))[:, None]
