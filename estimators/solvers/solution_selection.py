"""Choosing a 2D LiDAR calibration among the minimal solutions of all board triples (MATH.md section 5).

``minimal-min-residual`` (the baseline after Vasconcelos, Barreto and Nunes, TPAMI 2012): every solution
of every triple is scored by the laser cost over all boards and the least one is refined.

``minimal-lower-bound`` (after Peng et al. 2022, with the extent cue added here):
1. Solutions whose laser segments, mapped into the camera, leave their boards' outlines are dropped
   (when the board size is known): this separates roots that fit the planes equally well.
2. The rest are clustered hierarchically (average linkage) under the distance
   ``angle(R_a^T R_b) / THETA0 + |t_a - t_b| / T0``, cut at 1; each cluster is represented by its least-cost
   member.
3. The cost is the negative log of the joint observation probability of all laser points (Gaussian
   range noise): ``S(T) = sum_i |W_i pi_i(T) / |n_xy||^2 / sigma^2`` over the boards (O(1) per board).
4. Effective lower bound: at the truth, ``S - min S`` over the 6 extrinsic parameters is about
   chi-square(6); a triple's solution carries the error of 3 boards' data, which costs about
   ``N / 3`` times more under all N boards. Representatives with
   ``S - min S <= chi2_6(1 - ALPHA) * max(1, N / 3)`` are kept (the effective lower bound on the
   probability), each is refined by the factor graph, and the least refined cost wins. Distinct refined
   minima within ``chi2_6(0.95)`` of the best make the answer ambiguous, which is reported.
"""
from __future__ import annotations

import itertools
import time
from dataclasses import dataclass

import numpy as np
from scipy.cluster.hierarchy import fcluster, linkage
from scipy.spatial.distance import cdist
from scipy.spatial.transform import Rotation
from . import chi_square as chi2

from geometry.board import BoardModel
from geometry.rotations import T_inverse

from ..errors import DegenerateLayoutError
from ..measurements import FrameMeasurement, lidar_whitener
from .closed_form import MIN_NORMAL_SPREAD, describe_direction, normal_spread
from .minimal_solver import solve_triples
from .refinement import pooled_range_noise_m

THETA0_RAD = np.deg2rad(2.0)
T0_M = 0.05
ALPHA = 0.01
# Laser segment end points may leave the board's outline by this much (beyond 3 sigma of range noise).
EXTENT_TOLERANCE_M = 0.03
METHODS = ("minimal-lower-bound", "minimal-min-residual")


@dataclass(frozen=True, eq=False)
class Candidate:
    T_camera_lidar: np.ndarray
    cost: float  # S(T): laser chi-square over all boards
    members: int  # solutions in its cluster


@dataclass(frozen=True, eq=False)
class MinimalSelection:
    """The initial candidates for refinement, best first, and how they were found."""

    method: str
    candidates: tuple[Candidate, ...]
    n_triples: int
    n_solutions: int
    n_inside_extent: int
    n_clusters: int
    threshold: float
    degenerate_triples: tuple[str, ...]
    seconds: float


def _board_data(frames: list[FrameMeasurement], sigma_r: float):
    normals = np.array([f.camera.T_camera_board[:3, 2] for f in frames])
    dists = np.array([n @ f.camera.T_camera_board[:3, 3] for n, f in zip(normals, frames)])
    Ws = [lidar_whitener(f.lidar, sigma_r) for f in frames]
    return normals, dists, Ws


def laser_costs(Ts: np.ndarray, frames: list[FrameMeasurement], sigma_r: float) -> np.ndarray:
    """``S(T)`` for each of (K, 4, 4) ``T_camera_lidar``: the boards' camera planes (from their PnP poses)
    mapped into the LiDAR frame, scored by every laser point's range residual."""
    normals, dists, Ws = _board_data(frames, sigma_r)
    R, t = Ts[:, :3, :3], Ts[:, :3, 3]
    S = np.zeros(len(Ts))
    for n, d, W, f in zip(normals, dists, Ws, frames):
        pi = np.empty((len(Ts), 4))
        pi[:, :3] = np.einsum("kji,j->ki", R, n)  # R^T n
        pi[:, 3] = t @ n - d
        e = pi @ W.T
        if f.lidar.is_scan_line:
            e = e / np.hypot(pi[:, 0], pi[:, 1])[:, None]
        S += np.sum(e * e, axis=1)
    return S / sigma_r**2


def extent_violation(Ts: np.ndarray, frames: list[FrameMeasurement], board: BoardModel) -> np.ndarray:
    """Largest distance (m) by which any board's laser segment end point, mapped by each ``T_camera_lidar``
    into the board's frame, falls outside the board's outline (0 when every end point is inside)."""
    w, h = board.extent
    worst = np.zeros(len(Ts))
    for f in frames:
        P = f.lidar.points
        s = f.lidar.line.coordinates(P[:, :2]) if f.lidar.is_scan_line else None
        ends = P[[int(np.argmin(s)), int(np.argmax(s))]] if s is not None else P[:2]
        T_bc = T_inverse(f.camera.T_camera_board)
        # End points in the board frame for every candidate: T_bc (R p + t).
        pc = np.einsum("kij,mj->kmi", Ts[:, :3, :3], ends) + Ts[:, None, :3, 3]
        pb = pc @ T_bc[:3, :3].T + T_bc[:3, 3]
        out = np.maximum.reduce([-pb[..., 0], pb[..., 0] - w, -pb[..., 1], pb[..., 1] - h, np.zeros(pb.shape[:2])])
        worst = np.maximum(worst, out.max(axis=1))
    return worst


def solution_distances(Ts: np.ndarray) -> np.ndarray:
    """Condensed pairwise distances ``angle / THETA0 + |dt| / T0`` between (K, 4, 4) transforms."""
    q = Rotation.from_matrix(Ts[:, :3, :3]).as_quat()
    angle = 2 * np.arccos(np.clip(np.abs(q @ q.T), 0.0, 1.0))
    D = angle / THETA0_RAD + cdist(Ts[:, :3, 3], Ts[:, :3, 3]) / T0_M
    iu = np.triu_indices(len(Ts), 1)
    return D[iu]


def select_minimal(frames: list[FrameMeasurement], board: BoardModel, method: str = "minimal-lower-bound",
                   use_extent: bool | None = None) -> MinimalSelection:
    """Minimal solutions of all C(N, 3) triples of usable 2D frames, and the candidates to refine."""
    if method not in METHODS:
        raise ValueError(f"Expected method in {METHODS}, got {method!r}")
    t0 = time.perf_counter()
    frames = [f for f in frames if f.usable]
    if len(frames) < 3:
        raise DegenerateLayoutError(
            f"only {len(frames)} usable frame(s); a 2D LiDAR needs at least 3 boards",
            hint="record more boards; if frames were skipped as ambiguous, a tighter --max-sensor-separation "
                 "(the camera-LiDAR distance bound) leaves fewer scan segments where the camera puts the board")
    sigma_r = max(pooled_range_noise_m(frames), 1e-5)
    planes = [f.camera.plane for f in frames]
    lines = [f.lidar.line for f in frames]
    Ts, degenerate = [], []
    triples = list(itertools.combinations(range(len(frames)), 3))
    for tri, res in zip(triples, solve_triples(planes, lines, triples)):
        if res.degenerate:
            degenerate.append(f"boards {', '.join(frames[i].name for i in tri)}: {res.degenerate}")
        Ts.extend(res.T_camera_lidar)
    n_solutions = len(Ts)
    if not Ts:
        spread, weak = normal_spread(np.array([p.normal for p in planes]))
        if spread[-1] < MIN_NORMAL_SPREAD:
            axis, advice = describe_direction(weak)
            raise DegenerateLayoutError(
                f"the {len(frames)} board normals all lie in one plane (spread {spread[-1]:.3f} along {axis}): "
                f"with one scan line per board, translation along {axis} and rotation about the two axes "
                "perpendicular to it are unobservable", hint=advice)
        raise DegenerateLayoutError(
            f"no minimal solution from {len(triples)} triple(s) of boards"
            + (f" ({degenerate[0]})" if degenerate else ""),
            hint="tilt the boards in different directions (about both horizontal and vertical axes)")
    Ts = np.array(Ts)
    S = laser_costs(Ts, frames, sigma_r)
    if method == "minimal-min-residual":
        k = int(np.argmin(S))
        return MinimalSelection(method, (Candidate(Ts[k], float(S[k]), 1),), len(triples), n_solutions,
                                n_solutions, 1, 0.0, tuple(degenerate), time.perf_counter() - t0)
    if use_extent is None:
        use_extent = board.size_known
    n_inside = n_solutions
    if use_extent:
        inside = extent_violation(Ts, frames, board) <= EXTENT_TOLERANCE_M + 3 * sigma_r
        n_inside = int(inside.sum())
        if n_inside:
            Ts, S = Ts[inside], S[inside]
    if len(Ts) > 1:
        labels = fcluster(linkage(solution_distances(Ts), method="average"), t=1.0, criterion="distance")
    else:
        labels = np.ones(1, dtype=int)
    reps = []
    for lab in np.unique(labels):
        idx = np.nonzero(labels == lab)[0]
        best = idx[np.argmin(S[idx])]
        reps.append(Candidate(Ts[best], float(S[best]), len(idx)))
    reps.sort(key=lambda c: c.cost)
    threshold = float(chi2.ppf(1 - ALPHA, 6) * max(1.0, len(frames) / 3.0))
    kept = tuple(c for c in reps if c.cost - reps[0].cost <= threshold)
    return MinimalSelection(method, kept, len(triples), n_solutions, n_inside, len(reps), threshold,
                            tuple(degenerate), time.perf_counter() - t0)
