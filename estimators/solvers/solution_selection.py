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
   probability), and each is refined by the factor graph.
5. Each distinct refined minimum gets its evidence (``Mode``: with the board size known, the joint cost near it
   of the laser points on the uncertain camera planes and of the segment ends) and its share of the posterior
   mass; every other minimum holding at least ``MIN_MODE_MASS`` makes the answer ambiguous, which is reported.
"""
from __future__ import annotations

import itertools
import threading
import time
from dataclasses import dataclass, replace

import numpy as np
from scipy.cluster.hierarchy import fcluster, linkage
from scipy.optimize import minimize
from scipy.spatial.distance import cdist
from scipy.spatial.transform import Rotation
from . import chi_square as chi2

from geometry.board import BoardModel
from geometry.differences import central_hessian
from geometry.rotations import T_inverse, exp_batch

from ..errors import DegenerateLayoutError
from ..measurements import FrameMeasurement, lidar_whitener
from .closed_form import MIN_SCAN_NORMAL_SPREAD, describe_direction, normal_spread
from .minimal_solver import solve_triples
from .noise_levels import pooled_range_noise_m
from .refinement import Refinement
from .refinement_options import RefinementOptions
from .refinement import refine as refine_graph

THETA0_RAD = np.deg2rad(2.0)
T0_M = 0.05
ALPHA = 0.01
# Laser segment end points may leave the board's outline by this much (beyond 3 sigma of range noise).
EXTENT_TOLERANCE_M = 0.03
METHODS = ("minimal-lower-bound", "minimal-min-residual")
# Other minima holding at least this share of the posterior mass are reported: the answer is ambiguous.
MIN_MODE_MASS = 0.01
# Cluster representatives held in reserve beyond the lower bound, and the board count up to which they are
# always refined (with 3-4 boards a wrong root can fit as well as the true one, and the true one can score
# worse before refinement).
MAX_RESERVE = 16
REFINE_ALL_UP_TO = 4
# A refined fit whose cost exceeds the chi-square quantile at this tail probability is implausible: the
# reserve and the multi-start search are then tried as well.
IMPLAUSIBLE_P = 1e-3
# Triples of boards solved at most (C(21, 3) = 1330: every triple up to 21 boards). With more boards, the triples
# whose normals span 3D best: the candidates' clustering grows with the square of their number, and a root
# from a well-spread triple is as good a seed as any (every candidate is scored on all boards).
MAX_TRIPLES = 1500


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
    # Triples solved though ill-conditioned, and why (``minimal_solver.MIN_NORMAL_DET``, ``MIN_LINE_SIN``).
    weak_triples: tuple[str, ...] = ()
    # True when no triple gave a solution and the candidates come from the multi-start search instead.
    fallback: bool = False
    # The other cluster representatives (beyond the lower bound), best first: refined when few boards leave
    # the minima close in cost, or when the kept candidates refine to an implausible fit.
    reserve: tuple[Candidate, ...] = ()
    # Roots that could not be the rig (``physical``), and the sensors' separation bound used (m; None: none).
    n_unphysical: int = 0
    max_separation_m: float | None = None


@dataclass(frozen=True, eq=False)
class Mode:
    """One refined minimum of a 2D calibration and its evidence. ``cost``: the factor graph's chi-square;
    ``evidence``: ``-2 log`` of the minimum's likelihood, from which ``mass``, its share of the posterior mass
    among the minima found, is ``exp(-evidence / 2)`` normalised (the basins' widths taken as equal). When the
    board size is known the evidence is the least joint cost of the laser points and the segment ends near
    the minimum (``outline_evidence``), and ``outline_cost`` the segment ends' share of it; minima whose joint
    optima coincide share that optimum's evidence, weighted by their distance to it
    (``_merge_by_joint_optimum``). Otherwise the evidence is ``cost`` and ``outline_cost`` 0."""

    T_camera_lidar: np.ndarray
    cost: float
    outline_cost: float
    evidence: float
    mass: float
    refinement: Refinement


def _camera_planes(frames: list[FrameMeasurement]) -> tuple[np.ndarray, np.ndarray]:
    """The boards' planes in the camera (``normal . x = distance``) from their PnP poses: (N, 3), (N,)."""
    normals = np.array([f.camera.T_camera_board[:3, 2] for f in frames])
    return normals, np.array([n @ f.camera.T_camera_board[:3, 3] for n, f in zip(normals, frames)])


def _in_front(Ts: np.ndarray, normals: np.ndarray, dists: np.ndarray) -> np.ndarray:
    """For (K, 4, 4) ``T_camera_lidar``: the LiDAR on the camera's side of every board (K,) bool."""
    return np.all(Ts[:, :3, 3] @ normals.T - dists < 0, axis=1)


def physical(Ts: np.ndarray, frames: list[FrameMeasurement], max_separation_m: float | None) -> np.ndarray:
    """For (K, 4, 4) ``T_camera_lidar``: whether each could be the rig (K,) bool. The sensors at most
    ``max_separation_m`` apart (None: no bound), the LiDAR on the camera's side of every board, and no scan
    segment wholly behind the camera (a root can put a segment on its board's plane behind the camera; one end
    may lie behind it, on a board close beside the camera that the image shows only in part)."""
    Ts = np.asarray(Ts).reshape(-1, 4, 4)
    normals, dists = _camera_planes(frames)
    ok = _in_front(Ts, normals, dists)
    if max_separation_m is not None:
        ok &= np.linalg.norm(Ts[:, :3, 3], axis=1) <= max_separation_m
    if frames:
        depth = np.einsum("kj,fmj->kfm", Ts[:, 2, :3], _outline_data(frames)[0]) + Ts[:, 2, 3][:, None, None]
        ok &= np.all(np.any(depth > 0.0, axis=2), axis=1)
    return ok


def _retract(T: np.ndarray, xi: np.ndarray) -> np.ndarray:
    """``T Exp(xi)`` for each row of (K, 6) ``xi``: (K, 4, 4)."""
    xi = np.asarray(xi, dtype=float).reshape(-1, 6)
    return _retract_each(np.broadcast_to(T, (len(xi), 4, 4)), xi)


def _retract_each(Ts: np.ndarray, xi: np.ndarray) -> np.ndarray:
    """``T_k Exp(xi_k)`` for (K, 4, 4) ``Ts`` and (K, 6) ``xi``: (K, 4, 4)."""
    R, t = exp_batch(xi)
    out = np.array(Ts, dtype=float)
    out[:, :3, :3] = Ts[:, :3, :3] @ R
    out[:, :3, 3] = np.einsum("kij,kj->ki", Ts[:, :3, :3], t) + Ts[:, :3, 3]
    return out


def _board_data(frames: list[FrameMeasurement], sigma_r: float):
    """The boards' camera planes (:func:`_camera_planes`) and their laser points' whiteners (``lidar_whitener``),
    kept for the last sets of frames (:func:`_per_frames`): the search scores one set thousands of times."""
    def compute():
        normals, dists = _camera_planes(frames)
        return normals, dists, [lidar_whitener(f.lidar, sigma_r) for f in frames]

    return _per_frames("board data", frames, sigma_r, compute)


def _plane_in_lidar(Ts: np.ndarray, n: np.ndarray, d: float) -> np.ndarray:
    """The camera plane ``n . x = d`` in the LiDAR frame for each of (K, 4, 4) ``T_camera_lidar``:
    ``[R^T n; t . n - d]``, (K, 4)."""
    pi = np.empty((len(Ts), 4))
    pi[:, :3] = np.einsum("kji,j->ki", Ts[:, :3, :3], n)
    pi[:, 3] = Ts[:, :3, 3] @ n - d
    return pi


def laser_costs(Ts: np.ndarray, frames: list[FrameMeasurement], sigma_r: float) -> np.ndarray:
    """``S(T)`` for each of (K, 4, 4) ``T_camera_lidar``: the boards' camera planes (from their PnP poses)
    mapped into the LiDAR frame, scored by every laser point's range residual."""
    return np.sum(laser_residuals(Ts, frames, sigma_r) ** 2, axis=1)


def laser_residuals(Ts: np.ndarray, frames: list[FrameMeasurement], sigma_r: float) -> np.ndarray:
    """The whitened residuals (K, M) behind ``laser_costs``: ``S(T)`` is the sum of their squares."""
    normals, dists, Ws = _board_data(frames, sigma_r)
    blocks = []
    for n, d, W, f in zip(normals, dists, Ws, frames):
        pi = _plane_in_lidar(Ts, n, d)
        e = pi @ W.T
        if f.lidar.is_scan_line:
            e = e / np.hypot(pi[:, 0], pi[:, 1])[:, None]
        blocks.append(e / sigma_r)
    return np.concatenate(blocks, axis=1)


def marginal_laser_costs(Ts: np.ndarray, frames: list[FrameMeasurement], sigma_r: float) -> np.ndarray:
    """``laser_costs`` with each board's camera plane uncertain: per board, the whitened laser residual ``e``
    (linear in the camera plane ``(n, d)``) is scored against ``I + J C J^T``, ``C`` the plane's covariance
    from its corners and ``J = de / d(n, d)`` at each ``T``. With 3 boards every root fits the camera planes
    exactly, and the true extrinsic lies off them by about the planes' own error: this cost sees it as
    such, where ``laser_costs`` (planes exact) cannot."""
    normals, dists, Ws = _board_data(frames, sigma_r)
    R, t = Ts[:, :3, :3], Ts[:, :3, 3]
    total = np.zeros(len(Ts))
    for n, d, W, f in zip(normals, dists, Ws, frames):
        pi = _plane_in_lidar(Ts, n, d)
        scale = sigma_r * (np.hypot(pi[:, 0], pi[:, 1]) if f.lidar.is_scan_line else np.ones(len(Ts)))
        e = (pi @ W.T) / scale[:, None]
        D = np.zeros((len(Ts), 4, 4))  # d pi / d (n, d)
        D[:, :3, :3] = np.transpose(R, (0, 2, 1))
        D[:, 3, :3] = t
        D[:, 3, 3] = -1.0
        J = np.einsum("ij,kjl->kil", W, D) / scale[:, None, None]
        S = np.eye(len(W))[None] + J @ f.camera.plane_covariance @ np.transpose(J, (0, 2, 1))
        total += np.einsum("ki,ki->k", e, np.linalg.solve(S, e[..., None])[..., 0])
    return total


def plane_covariance(T: np.ndarray, frames: list[FrameMeasurement], sigma_r: float, step: float = 1e-3
                     ) -> np.ndarray | None:
    """The covariance (6 x 6, right tangent) of ``T_camera_lidar`` about ``T`` that the boards' planes give: the
    inverse of half the Hessian of :func:`marginal_laser_costs` (a chi-square), by central differences of
    ``step`` (rad, m); None where that Hessian is not positive definite (``T`` off a minimum, or a direction the
    planes leave free)."""
    found = central_hessian(lambda xi: marginal_laser_costs(_retract(T, xi), frames, sigma_r), np.zeros(6),
                            np.full(6, step))
    if found is None or not np.all(np.isfinite(found[2])):
        return None
    H = found[2]
    ev, V = np.linalg.eigh(0.5 * H)
    if ev[0] <= 1e-9 * max(ev[-1], 1e-300):
        return None
    return (V / ev) @ V.T


def extent_violation(Ts: np.ndarray, frames: list[FrameMeasurement], board: BoardModel) -> np.ndarray:
    """Largest distance (m) by which any board's laser segment end point, mapped by each ``T_camera_lidar``
    into the board's frame, falls outside the board's outline (0 when every end point is inside)."""
    w, h = board.extent
    Ts = np.asarray(Ts, dtype=float).reshape(-1, 4, 4)
    if not frames:
        return np.zeros(len(Ts))
    pb = _ends_on_board(Ts, frames)
    out = np.maximum.reduce([-pb[..., 0], pb[..., 0] - w, -pb[..., 1], pb[..., 1] - h, np.zeros(pb.shape[:-1])])
    return out.reshape(len(Ts), -1).max(axis=1)


def _ends_on_board(Ts: np.ndarray, frames: list[FrameMeasurement]) -> np.ndarray:
    """Each scan segment's two ends on its board (board frame x, y) under each of (K, 4, 4) ``T_camera_lidar``:
    (K, boards, 2, 2), every board at once (:func:`_outline_data`; matmul, not einsum: 0.4 ms a call at the search's
    batch sizes)."""
    ends, _, A, b = _outline_data(frames)  # (F, 2, 3), (F, 2), (F, 2, 3), (F, 2)
    pc = (ends.reshape(1, -1, 3) @ np.transpose(Ts[:, :3, :3], (0, 2, 1)) + Ts[:, None, :3, 3])
    return pc.reshape(len(Ts), -1, 2, 3) @ np.transpose(A, (0, 2, 1)) + b[:, None, :]


# A laser segment's end is the last return on the board: it lies inside the board's edge by up to one beam
# spacing. Beyond that, edge effects (mixed returns, a rounded or dark margin) blur it by about this much.
EDGE_BLUR_M = 0.01
# Share of segment ends that are not at the board's edge (occluded by a hand or a stand, cut by a stray
# return, outside the scanner's field of view): they cost at most -2 log(EDGE_OUTLIER) each.
EDGE_OUTLIER = 0.05


def _segment_ends(f: FrameMeasurement) -> tuple[np.ndarray, np.ndarray]:
    """A scan segment's two end points (LiDAR frame) and the beam spacing (m) next to each."""
    P = f.lidar.points
    order = np.argsort(f.lidar.line.coordinates(P[:, :2]))
    P = P[order]
    gaps = np.linalg.norm(np.diff(P[:, :2], axis=0), axis=1)
    k = min(3, len(gaps))
    spacing = np.array([np.median(gaps[:k]), np.median(gaps[-k:])]) if k else np.zeros(2)
    return P[[0, -1]], spacing


def outline_costs(Ts: np.ndarray, frames: list[FrameMeasurement], board: BoardModel, sigma_r: float) -> np.ndarray:
    """Where each laser segment ends against where the scan plane leaves its board, for each of (K, 4, 4)
    ``T_camera_lidar``: ``-2 log`` of the end points' likelihood, summed over boards (:func:`outline_residuals`)."""
    return np.sum(outline_residuals(Ts, frames, board, sigma_r) ** 2, axis=1)


def outline_residuals(Ts: np.ndarray, frames: list[FrameMeasurement], board: BoardModel, sigma_r: float
                      ) -> np.ndarray:
    """Per segment end (K, 2 x boards), a signed residual whose square is ``-2 log`` of the end's likelihood
    relative to its best: its sign is that of the end's depth inside its end of the chord less its expected
    depth.

    Mapped into the board's frame, a segment lies on the chord that the scan plane cuts through the board's
    outline; its end points are the last returns inside the outline, so each lies between 0 and one beam
    spacing ``s`` inside its end of the chord (uniform, approximated by a Gaussian of mean ``s / 2`` and
    variance ``s^2 / 12`` plus edge blur and range noise), or anywhere (share ``EDGE_OUTLIER``) when the
    board's edge was hidden. Among the up to 8 solutions of 3 boards, which fit the planes alike, this
    tells the true one: a wrong solution slides or turns the chord against the segment. Every board at once
    (the search calls it thousands of times on one set of frames, :func:`_outline_data`)."""
    w, h = board.extent
    Ts = np.asarray(Ts, dtype=float).reshape(-1, 4, 4)
    K = len(Ts)
    if not frames:
        return np.zeros((K, 0))
    spacing = _outline_data(frames)[1]  # (F, 2)
    pb = _ends_on_board(Ts, frames)  # (K, F, 2 ends, 2 coordinates)
    d = pb[:, :, 1] - pb[:, :, 0]
    length = np.linalg.norm(d, axis=-1)
    d = d / np.maximum(length, 1e-12)[..., None]
    start = pb[:, :, 0]
    # The chord: the segment's line clipped to [0, w] x [0, h] (slabs), as positions s from end 0.
    lo, hi = np.full((K, len(frames)), -np.inf), np.full((K, len(frames)), np.inf)
    for axis, size in ((0, w), (1, h)):
        dk, ok = d[..., axis], np.abs(d[..., axis]) > 1e-12
        with np.errstate(divide="ignore", invalid="ignore"):
            a_ = np.where(ok, (0.0 - start[..., axis]) / dk, -np.inf)
            b_ = np.where(ok, (size - start[..., axis]) / dk, np.inf)
        inside = (start[..., axis] >= 0) & (start[..., axis] <= size)
        a_ = np.where(ok, a_, np.where(inside, -np.inf, np.inf))
        b_ = np.where(ok, b_, np.where(inside, np.inf, -np.inf))
        lo, hi = np.maximum(lo, np.minimum(a_, b_)), np.minimum(hi, np.maximum(a_, b_))
    missed = ~(hi > lo)
    # Depth of each end inside its end of the chord (negative: the end lies beyond the outline).
    depth = np.stack([0.0 - lo, hi - length], axis=-1)
    depth = np.where(missed[..., None] | ~np.isfinite(depth), -np.maximum(w, h), depth)
    var = spacing**2 / 12 + EDGE_BLUR_M**2 + sigma_r**2
    z2 = (depth - spacing / 2) ** 2 / var
    chord = np.maximum(np.where(missed, 0.0, hi - lo), 1e-3)[..., None]
    # -2 log of the mixture, relative to its value at the mode of the Gaussian part. A hidden edge leaves
    # the end anywhere on the chord, never beyond the outline.
    log_gauss = np.log(1 - EDGE_OUTLIER) - 0.5 * z2 - 0.5 * np.log(2 * np.pi * var)
    log_uniform = np.where(depth >= -EXTENT_TOLERANCE_M, np.log(EDGE_OUTLIER / chord), -np.inf)
    log_peak = np.logaddexp(np.log(1 - EDGE_OUTLIER) - 0.5 * np.log(2 * np.pi * var), np.log(EDGE_OUTLIER / chord))
    cost = np.maximum(-2 * (np.logaddexp(log_gauss, log_uniform) - log_peak), 0.0)
    return (np.where(depth >= spacing / 2, 1.0, -1.0) * np.sqrt(cost)).reshape(K, -1)


# What is computed from a set of frames alone, for the last few sets: the search scores one set of frames
# thousands of times (each entry holds its frames, so the identities it is keyed by stay theirs).
_PER_FRAMES: dict = {}
_PER_FRAMES_LOCK = threading.Lock()


def _per_frames(what: str, frames: list[FrameMeasurement], arg, compute):
    """``compute()``, which depends only on ``frames`` (frozen records) and ``arg``, kept for the last 16 calls'
    sets of frames."""
    key = (what, arg, tuple(id(f) for f in frames))
    with _PER_FRAMES_LOCK:
        hit = _PER_FRAMES.get(key)
    if hit is not None and all(a is b for a, b in zip(hit[0], frames)):
        return hit[1]
    value = compute()
    with _PER_FRAMES_LOCK:
        if len(_PER_FRAMES) >= 16:
            _PER_FRAMES.pop(next(iter(_PER_FRAMES)))
        _PER_FRAMES[key] = (tuple(frames), value)
    return value


def _outline_data(frames: list[FrameMeasurement]) -> tuple:
    """Per frame: its segment's two ends (F, 2, 3) and beam spacings (F, 2) (:func:`_segment_ends`), and the
    board's frame's first two rows (F, 2, 3) and offsets (F, 2) of ``T_board_camera`` (:func:`_per_frames`)."""
    def compute():
        ends, spacing = zip(*(_segment_ends(f) for f in frames))
        T_bc = np.array([T_inverse(f.camera.T_camera_board) for f in frames])
        return np.array(ends), np.array(spacing), T_bc[:, :2, :3].copy(), T_bc[:, :2, 3].copy()

    return _per_frames("outline", frames, None, compute)


def solution_distances(Ts: np.ndarray) -> np.ndarray:
    """Condensed pairwise distances ``angle / THETA0 + |dt| / T0`` between (K, 4, 4) transforms."""
    q = Rotation.from_matrix(Ts[:, :3, :3]).as_quat()
    angle = 2 * np.arccos(np.clip(np.abs(q @ q.T), 0.0, 1.0))
    D = angle / THETA0_RAD + cdist(Ts[:, :3, 3], Ts[:, :3, 3]) / T0_M
    iu = np.triu_indices(len(Ts), 1)
    return D[iu]


def _triples(normals: np.ndarray) -> list[tuple[int, int, int]]:
    """Every triple of boards, or the ``MAX_TRIPLES`` whose normals span 3D best (largest smallest singular
    value; ties in index order) when there are more."""
    triples = list(itertools.combinations(range(len(normals)), 3))
    if len(triples) <= MAX_TRIPLES:
        return triples
    spread = np.linalg.svd(normals[np.array(triples)], compute_uv=False)[:, -1]
    keep = np.sort(np.argsort(-spread, kind="stable")[:MAX_TRIPLES])
    return [triples[k] for k in keep]


def select_minimal(frames: list[FrameMeasurement], board: BoardModel, method: str = "minimal-lower-bound",
                   use_extent: bool | None = None, max_separation_m: float | None = None) -> MinimalSelection:
    """Minimal solutions of all C(N, 3) triples of usable 2D frames (at most ``MAX_TRIPLES``, the best spread), and
    the candidates to refine. Roots that
    cannot be the rig (:func:`physical`: the sensors farther apart than ``max_separation_m``, the LiDAR behind
    a board, a segment behind the camera) are not solutions."""
    if method not in METHODS:
        raise ValueError(f"Expected method in {METHODS}, got {method!r}")
    t0 = time.perf_counter()
    frames = [f for f in frames if f.usable]
    if use_extent is None:
        use_extent = board.size_known
    # Two boards give no minimal solution, but with a known board size their segments' four ends on the edges
    # and two lines on the planes are 8 constraints on 6 unknowns: the multi-start search seeds them.
    least = 2 if use_extent else 3
    if len(frames) < least:
        raise DegenerateLayoutError(
            f"only {len(frames)} usable frame(s); a 2D LiDAR needs at least 3 boards"
            + (" (2 with the board's size known, whose segment ends then hold what the planes leave)"
               if use_extent else " (2 with the board's size in dataset.yaml)"),
            hint="record more boards; if frames were skipped as ambiguous, a tighter --max-sensor-separation "
                 "(the camera-LiDAR distance bound) leaves fewer scan segments where the camera puts the board")
    sigma_r = max(pooled_range_noise_m([f.lidar for f in frames]), 1e-5)
    planes = [f.camera.plane for f in frames]
    lines = [f.lidar.line for f in frames]
    spread, weak = normal_spread(np.array([p.normal for p in planes]))
    # Normals in one plane leave the planes alone degenerate; the segment ends on the boards' edges may still
    # fix the extrinsic (the refinement's information, with them, decides).
    if spread[-1] < MIN_SCAN_NORMAL_SPREAD and not use_extent:
        axis, advice = describe_direction(weak)
        raise DegenerateLayoutError(
            f"the {len(frames)} board normals all lie in one plane (spread {spread[-1]:.3f} along {axis}): "
            f"with one scan line per board, translation along {axis} and rotation about the two axes "
            "perpendicular to it are unobservable", hint=advice)
    Ts, degenerate, weak_triples = [], [], []
    triples = _triples(np.array([p.normal for p in planes]))
    for tri, res in zip(triples, solve_triples(planes, lines, triples)):
        names = ', '.join(frames[i].name for i in tri)
        if res.degenerate:
            degenerate.append(f"boards {names}: {res.degenerate}")
        elif res.weak:
            weak_triples.append(f"boards {names}: {res.weak}")
        Ts.extend(res.T_camera_lidar)
    n_solutions = len(Ts)
    if Ts:
        Ts = [T for T, ok in zip(Ts, physical(np.array(Ts), frames, max_separation_m)) if ok]
    n_unphysical = n_solutions - len(Ts)
    fallback = not Ts
    if fallback:
        Ts = list(multistart_candidates(frames, sigma_r, max_separation_m=max_separation_m,
                                        board=board if use_extent else None))
        if not Ts:
            bound = (f" within {max_separation_m:g} m of the camera" if max_separation_m is not None else "")
            raise DegenerateLayoutError(
                f"no minimal solution from {len(triples)} triple(s) of boards"
                + (f" ({degenerate[0]})" if degenerate else "")
                + (f" puts the LiDAR{bound} on the camera's side of every board ({n_unphysical} root(s) do not)"
                   if n_unphysical else "")
                + ", and no start of the multi-start search puts the laser segments on their boards"
                + (" with the sensors that close" if max_separation_m is not None else ""),
                hint="tilt the boards in different directions (about both horizontal and vertical axes); if the "
                     "sensors are farther apart, raise --max-sensor-separation")
    Ts = np.array(Ts)
    S = laser_costs(Ts, frames, sigma_r)
    info = dict(degenerate_triples=tuple(degenerate), weak_triples=tuple(weak_triples), fallback=fallback,
                n_unphysical=n_unphysical, max_separation_m=max_separation_m)
    if method == "minimal-min-residual":
        k = int(np.argmin(S))
        return MinimalSelection(method, (Candidate(Ts[k], float(S[k]), 1),), len(triples), n_solutions,
                                n_solutions, 1, 0.0, seconds=time.perf_counter() - t0, **info)
    n_inside = n_solutions
    outside_reps: list[Candidate] = []
    if use_extent:
        inside = extent_violation(Ts, frames, board) <= EXTENT_TOLERANCE_M + 3 * sigma_r
        n_inside = int(inside.sum())
        if n_inside:
            # Roots outside the outlines go to the reserve: a noisy root of few boards can leave the outline
            # although its refined minimum is the true one.
            if n_inside < len(Ts):
                outside_reps = _representatives(Ts[~inside], S[~inside])
            Ts, S = Ts[inside], S[inside]
    reps = _representatives(Ts, S)
    threshold = float(chi2.ppf(1 - ALPHA, 6) * max(1.0, len(frames) / 3.0))
    kept = tuple(c for c in reps if c.cost - reps[0].cost <= threshold)
    reserve = tuple((reps[len(kept):] + outside_reps)[:MAX_RESERVE])
    return MinimalSelection(method, kept, len(triples), n_solutions, n_inside, len(reps) + len(outside_reps),
                            threshold, seconds=time.perf_counter() - t0, reserve=reserve, **info)


def _distinct(refined: list) -> list:
    """``(cost, Refinement)`` pairs, least cost first, keeping one per basin (``solution_distances`` > 1)."""
    out: list = []
    for cost, r in sorted(refined, key=lambda cr: cr[0]):
        if not out or np.all(solution_distances(np.array([*[d[1].T_camera_lidar for d in out],
                                                           r.T_camera_lidar]))[-len(out):] > 1.0):
            out.append((cost, r))
    return out


def _representatives(Ts: np.ndarray, S: np.ndarray) -> list[Candidate]:
    """Solutions clustered (average linkage, ``solution_distances`` cut at 1), each cluster represented by its
    least-cost member; best first."""
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
    return reps


def multistart_candidates(frames: list[FrameMeasurement], sigma_r: float, n_starts: int = 4096,
                          n_keep: int = 12, max_separation_m: float | None = None,
                          board: BoardModel | None = None) -> list[np.ndarray]:
    """``T_camera_lidar`` candidates without the minimal solver, from the camera's geometry alone: for each of
    ``n_starts`` rotations spread over SO(3) (a fixed quasi-random set), the translation that puts every
    segment's centre and ends on its board plane (linear least squares) with the LiDAR in front of every
    board; every such start is then polished by local minimisation of the laser cost (:func:`_polish`, all at
    once), those that could be the rig kept (:func:`physical`), and the least-cost member of each of the
    ``n_keep`` best clusters returned. With a ``board`` of known size the segment ends are part of the cost
    (:func:`outline_residuals`). For layouts where every triple is degenerate although the normals span 3D,
    and for roots that all leave the segment ends off their boards.

    Every start is polished, not the few of least cost: with 3 boards a start within the grid's spacing (about
    15 degrees) of the truth can have its translation metres off and a cost above many wrong starts'."""
    normals, dists = _camera_planes(frames)
    # Three points per segment: its ends and its centroid.
    pts, owner = [], []
    for i, f in enumerate(frames):
        ends, _ = _segment_ends(f)
        pts += [ends[0], ends[1], f.lidar.points.mean(0)]
        owner += [i, i, i]
    pts, owner = np.array(pts), np.array(owner)
    A = normals[owner]  # rows n_i^T t = d_i - n_i^T R p
    pinv = np.linalg.pinv(A)
    Rs = Rotation.from_quat(_quasi_uniform_quaternions(n_starts)).as_matrix()
    rhs = dists[owner][None, :] - np.einsum("mi,kij,mj->km", A, Rs, pts)
    ts = rhs @ pinv.T
    Ts = np.tile(np.eye(4), (n_starts, 1, 1))
    Ts[:, :3, :3], Ts[:, :3, 3] = Rs, ts
    front = _in_front(Ts, normals, dists)
    if not front.any():
        return []
    ends = board is not None and board.size_known

    def residuals(Ts: np.ndarray) -> np.ndarray:
        r = laser_residuals(Ts, frames, sigma_r)
        return np.hstack([r, outline_residuals(Ts, frames, board, sigma_r)]) if ends else r

    Ts, S = _polish(Ts[front], residuals)
    keep = np.isfinite(S) & physical(Ts, frames, max_separation_m)
    if not keep.any():
        return []
    return [c.T_camera_lidar for c in _representatives(Ts[keep], S[keep])[:n_keep]]


# A start of ``_polish`` is left where it is once this many iterations in a row lowered its cost by less than
# ``POLISH_TOLERANCE`` of it: converged to the cost's rounding (a start still creeping along a valley lowers it by
# more within a few). On simulated 2D layouts the polished costs differ from those of every start iterated to the
# end by under 1e-7 of their value, and the polish takes 40% less time (most starts settle in 20 of its 60).
POLISH_SETTLED_AFTER = 10
POLISH_TOLERANCE = 1e-9


def _polish(Ts: np.ndarray, residuals, iterations: int = 60) -> tuple[np.ndarray, np.ndarray]:
    """Levenberg-Marquardt from each of (K, 4, 4) ``T_camera_lidar`` at once, on ``T Exp(xi)`` with a
    forward-difference Jacobian; ``residuals`` maps (k, 4, 4) to (k, m) for any k. Each iteration takes the starts
    not yet settled (``POLISH_SETTLED_AFTER``). Returns the polished transforms and their costs (sums of squared
    residuals)."""
    Ts = Ts.copy()
    r = residuals(Ts)
    cost = np.sum(r**2, axis=1)
    lam = np.full(len(Ts), 1e-3)
    quiet = np.zeros(len(Ts), dtype=int)
    eps = 1e-6
    eye = np.eye(6)
    for _ in range(iterations):
        a = np.nonzero(quiet < POLISH_SETTLED_AFTER)[0]
        if not len(a):
            break
        T_a, r_a = Ts[a], r[a]
        J = np.stack([(residuals(_retract_each(T_a, np.broadcast_to(eps * eye[j], (len(a), 6)))) - r_a) / eps
                      for j in range(6)], axis=2)
        H = np.einsum("kmi,kmj->kij", J, J)
        g = np.einsum("kmi,km->ki", J, r_a)
        damp = lam[a, None, None] * (eye * np.diagonal(H, axis1=1, axis2=2)[:, :, None] + 1e-9 * eye)
        with np.errstate(invalid="ignore", over="ignore"):
            step = -np.linalg.solve(H + damp, g[..., None])[..., 0]
        trial = _retract_each(T_a, np.nan_to_num(step))
        r_trial = residuals(trial)
        c_trial = np.sum(r_trial**2, axis=1)
        better = np.isfinite(c_trial) & (c_trial < cost[a])
        quiet[a] = np.where(better & (cost[a] - c_trial > POLISH_TOLERANCE * cost[a]), 0, quiet[a] + 1)
        b = a[better]
        Ts[b], r[b], cost[b] = trial[better], r_trial[better], c_trial[better]
        lam[a] = np.clip(np.where(better, lam[a] / 3.0, lam[a] * 4.0), 1e-9, 1e9)
    return Ts, cost


def _quasi_uniform_quaternions(n: int) -> np.ndarray:
    """``n`` unit quaternions spread evenly over SO(3) (Shoemake's map of a Halton-like low-discrepancy set)."""
    k = np.arange(1, n + 1)
    u = np.column_stack([(k * g) % 1.0 for g in (0.5 * (np.sqrt(5) - 1), np.sqrt(2) - 1, np.sqrt(3) - 1)])
    a, b = np.sqrt(1 - u[:, 0]), np.sqrt(u[:, 0])
    return np.column_stack([a * np.sin(2 * np.pi * u[:, 1]), a * np.cos(2 * np.pi * u[:, 1]),
                            b * np.sin(2 * np.pi * u[:, 2]), b * np.cos(2 * np.pi * u[:, 2])])


def joint_costs(Ts: np.ndarray, frames: list[FrameMeasurement], board: BoardModel, sigma_r: float) -> np.ndarray:
    """``J(T) = marginal_laser_costs(T) + outline_costs(T)``: the laser points against the camera planes (with
    their uncertainty) and the segment ends against the boards' outlines, for (K, 4, 4) ``T_camera_lidar``."""
    return marginal_laser_costs(Ts, frames, sigma_r) + outline_costs(Ts, frames, board, sigma_r)


def outline_evidence(ref: Refinement, frames: list[FrameMeasurement], board: BoardModel, sigma_r: float,
                     rng: np.random.Generator | None = None, n_polish: int = 2) -> tuple[float, float, np.ndarray]:
    """The least joint cost ``J(T) = M(T) + outline_costs(T)`` near the refined minimum (``M``:
    ``marginal_laser_costs``, the laser points against the camera planes with their uncertainty), the
    outline's share of it, and the ``T`` where it is reached.

    At 3 boards the factor graph fits every minimum exactly and leaves a direction along the boards loose
    (standard deviations of tens of centimetres), and the true extrinsic can lie far along that curved valley,
    where a quadratic model of the basin puts it at tens of sigma; the segment ends pin it. With more boards
    the factor graph's cost is not comparable between minima (its per-board plane error, estimated at each
    minimum, absorbs a wrong minimum's misfit); ``J`` takes the same noise at every minimum. Searched in the
    minimum's whitened coordinates (its covariance): 2 x 1024 draws at 1.5 and 4 sigma, then a Powell polish
    of the ``n_polish`` best. The whitening is the covariance's symmetric square root: unique and continuous in
    the covariance, where eigenvectors' arbitrary signs would mirror the draws on a last-bit change."""
    rng = np.random.default_rng(0) if rng is None else rng
    w, V = np.linalg.eigh(0.5 * (ref.covariance + ref.covariance.T))
    L = (V * np.sqrt(np.maximum(w, 0.0))) @ V.T
    T = ref.T_camera_lidar

    def cost(Z: np.ndarray) -> np.ndarray:
        return joint_costs(_retract(T, np.atleast_2d(Z) @ L.T), frames, board, sigma_r)

    Z = np.vstack([np.zeros(6), rng.normal(0.0, 1.5, (1024, 6)), rng.normal(0.0, 4.0, (1024, 6))])
    values = cost(Z)
    k = int(np.argmin(values))
    best, z_best = float(values[k]), Z[k]
    for k in np.argsort(values)[:n_polish]:
        res = minimize(lambda z: float(cost(z)[0]), Z[k], method="Powell",
                       options={"xtol": 1e-3, "ftol": 1e-4, "maxfev": 3000})
        if res.fun < best:
            best, z_best = float(res.fun), res.x
    T_best = _retract(T, (z_best @ L.T)[None])
    return best, float(outline_costs(T_best, frames, board, sigma_r)[0]), T_best[0]


# Two minima that share one joint optimum (``_merge_by_joint_optimum``): the nearer one to that optimum is the
# truth's when its distance is under this share of the next one's; around and above it either can be (measured
# on simulated 3-board layouts, ``benchmarks/bench_2d_honesty.py``). A member at this distance ratio gets 1% of
# the nearest member's weight, and less the farther it lies.
SHARED_OPTIMUM_RATIO = 0.38


def _merge_by_joint_optimum(evidence: np.ndarray, optima: np.ndarray, refs: list) -> tuple[np.ndarray, np.ndarray]:
    """Minima whose joint optima (laser and outline cue, ``outline_evidence``) coincide are one mode of the
    posterior: roots at the ends of one shallow valley of the laser cost, the segment ends pinning a point
    between them. A group's members share its best evidence, weighted by how near each lies to that point
    (the nearest 1, one at ``1 / SHARED_OPTIMUM_RATIO`` times its distance 0.01). Returns each minimum's
    evidence and log weight."""
    groups: list[list[int]] = []
    for k in np.argsort(evidence):
        for g in groups:
            if solution_distances(np.array([optima[g[0]], optima[k]]))[0] < 1.0:
                g.append(k)
                break
        else:
            groups.append([k])
    c = np.log(100.0) / (SHARED_OPTIMUM_RATIO**-2 - 1.0)
    shared, log_weight = np.array(evidence, dtype=float), np.zeros(len(evidence))
    for g in groups:
        point = optima[g[0]]  # the least evidence: the group's optimum
        d = np.array([solution_distances(np.array([refs[k].T_camera_lidar, point]))[0] for k in g])
        nearest = max(d.min(), 0.05)
        shared[g] = evidence[g[0]]
        log_weight[g] = -c * ((np.maximum(d, nearest) / nearest) ** 2 - 1.0)
    return shared, log_weight


def refine_candidates(used: list[FrameMeasurement], board: BoardModel, camera, sel: MinimalSelection,
                      options: RefinementOptions = RefinementOptions(),
                      use_extent: bool | None = None) -> tuple[Refinement, tuple[Mode, ...]]:
    """Refine every selected candidate; return the refinement of the most probable minimum and every distinct
    minimum holding at least ``MIN_MODE_MASS`` of the posterior mass, most probable first.

    A minimum's evidence (``Mode``) is its refined cost or, when the board size is known, the joint cost of
    the laser points and the segment ends near it (``outline_evidence``). More than one mode returned means
    the data do not decide between them."""
    if use_extent is None:
        use_extent = board.size_known
    usable = [f for f in used if f.usable]
    sigma_r = max(pooled_range_noise_m([f.lidar for f in usable]), 1e-5)
    refined: list = []
    error: list = []
    unrefined: list = []  # the starts whose refinement was refused as unobservable

    def refine_all(starts) -> None:
        for T0 in starts:
            try:
                r = refine_graph(used, board, camera, T0, options)
            except DegenerateLayoutError as exc:
                error.append(exc)
                unrefined.append(T0)
                continue
            refined.append((sum(fr.consistency_chi2 for fr in r.frames), r))

    def plausible() -> bool:
        """The best refined minimum fits the laser points and, with a known board size, some minimum the segment
        ends."""
        if not refined:
            return False
        cost, best = min(refined, key=lambda cr: cr[0])
        if cost > chi2.isf(IMPLAUSIBLE_P, max(sum(fr.plane_dof for fr in best.frames) - 6, 1)):
            return False
        if not use_extent:
            return True
        return any(outline_costs(r.T_camera_lidar[None], usable, board, sigma_r)[0]
                   <= chi2.isf(IMPLAUSIBLE_P, 2 * len(usable)) for _, r in refined)

    refine_all([c.T_camera_lidar for c in sel.candidates])
    if len(usable) <= REFINE_ALL_UP_TO or not plausible():
        refine_all([c.T_camera_lidar for c in sel.reserve])
    if not sel.fallback and (not plausible() or (len(usable) <= REFINE_ALL_UP_TO and len(_distinct(refined)) < 2)):
        # An implausible best fit, or with few boards a single minimum: that no other root was found is no
        # proof that there is none (a root the minimal solver lost to noise), so the multi-start search looks
        # for others, whose evidence is then weighed against it.
        refine_all(multistart_candidates(usable, sigma_r, max_separation_m=options.max_sensor_separation_m,
                                         board=board if use_extent else None))
    if not refined:
        if error:
            raise error[0]
        raise DegenerateLayoutError("no candidate of the minimal solutions could be refined")
    # A refined minimum that puts the LiDAR behind a board (on the side the camera does not see), a segment
    # behind the camera, or the sensors farther apart than the bound is not physical.
    sep = options.max_sensor_separation_m
    front = [cr for cr in refined if physical(cr[1].T_camera_lidar, usable, sep)[0]]
    if not front:
        raise DegenerateLayoutError(
            "every refined minimum puts the LiDAR behind one of the boards, a scan segment behind the camera"
            + (f", or the LiDAR farther than {sep:g} m from the camera" if sep is not None else ""),
            hint="check that the camera and the LiDAR see the same side of each board; if the sensors are "
                 "farther apart, raise --max-sensor-separation")
    refined = front
    distinct = _distinct(refined)
    # The factor graph estimates its noise terms (the per-board plane error) from where it starts, so a
    # minimum reached from a far start is refined once more from itself: then every minimum's cost is taken
    # under noise estimated at that minimum, and the answer does not depend on the start.
    polished = []
    for _, r in distinct:
        try:
            r = refine_graph(used, board, camera, r.T_camera_lidar, options)
        except DegenerateLayoutError:
            pass
        polished.append((sum(fr.consistency_chi2 for fr in r.frames), r))
    distinct = _distinct(polished)
    costs = np.array([c for c, _ in distinct])
    refs = [r for _, r in distinct]
    if use_extent and len(distinct) > 1:
        evidence, outline, optima = (np.array(v) for v in zip(*(outline_evidence(r, usable, board, sigma_r)
                                                                 for r in refs)))
        evidence, log_weight = _merge_by_joint_optimum(evidence, optima, refs)
    else:
        evidence, outline, log_weight = costs, np.zeros(len(refs)), np.zeros(len(refs))
    log_mass = log_weight - 0.5 * evidence
    mass = np.exp(log_mass - log_mass.max())
    mass /= mass.sum()
    order = np.argsort(-mass)
    modes = tuple(Mode(refs[k].T_camera_lidar, float(costs[k]), float(outline[k]), float(evidence[k]),
                       float(mass[k]), refs[k]) for k in order)
    kept = (modes[0],) + tuple(m for m in modes[1:] if m.mass >= MIN_MODE_MASS)
    if len(usable) == 2 and use_extent:
        _two_boards_decided(kept, unrefined, usable, board, sigma_r)
    return kept[0].refinement, kept


# Two boards: a start whose refinement was refused as unobservable, away from every mode, with a joint cost of the
# laser points and segment ends within this of the answer's, fits the data as well: the answer is refused.
TWO_BOARD_MARGIN_CHI2 = 9.0


def _two_boards_decided(modes: tuple, unrefined: list, usable: list[FrameMeasurement], board: BoardModel,
                        sigma_r: float) -> None:
    """Raise :class:`DegenerateLayoutError` when, with two boards, more than one mode holds mass, or a pose the
    refinement could not settle (its covariance unobservable) fits the laser points and segment ends about as well
    as the answer: the weakest layout that can be solved is answered only when it is unambiguous. Two segments
    and their four ends are 8 constraints on 6 unknowns: besides the answer the data can hold a second, weakly
    determined pose (far from the truth, it can fit two segments better than the truth does), and a mode dropped
    for being wide is not evidence against it."""
    if len(modes) > 1:
        raise DegenerateLayoutError(
            f"with 2 boards, {len(modes)} distinct poses fit the scan segments and their ends on the boards' edges "
            f"(posterior mass {', '.join(f'{m.mass:.0%}' for m in modes)}): two boards do not decide between them",
            hint="record a third board, tilted in another direction")
    if not unrefined:
        return

    best = float(joint_costs(np.array([m.T_camera_lidar for m in modes]), usable, board, sigma_r).min())
    starts = np.array(unrefined)
    costs = joint_costs(starts, usable, board, sigma_r)
    for T, c in zip(starts, costs):
        far = all(solution_distances(np.array([T, m.T_camera_lidar]))[0] >= 1.0 for m in modes)
        if far and c <= best + TWO_BOARD_MARGIN_CHI2:
            raise DegenerateLayoutError(
                f"with 2 boards, another pose fits the scan segments and their ends on the boards' edges about as "
                f"well as the answer (joint cost {c:.1f} against {best:.1f}) but the data leave it unobservable: "
                "the two cannot be told apart",
                hint="record a third board, tilted in another direction")


# A board whose corners fit two tilts alike (``FrameMeasurement.camera_alternatives``) is skipped, unless the other
# boards alone cannot be solved or are only two (then tried before the two alone): then each combination of the
# ambiguous boards' tilts (at most ``MAX_AMBIGUOUS_BOARDS`` boards) is solved, and the one whose best minimum fits the
# laser points (and the segment ends, with a known board size) with a joint cost lower than every other combination's
# by at least this is used (a likelihood ratio of 90; the corners' own preference is added to each tilt's cost).
TILT_MARGIN_CHI2 = 9.0
MAX_AMBIGUOUS_BOARDS = 3


def select_and_refine(frames: list[FrameMeasurement], board: BoardModel, camera,
                      method: str = "minimal-lower-bound", options: RefinementOptions = RefinementOptions(),
                      use_extent: bool | None = None) -> tuple[list[FrameMeasurement], MinimalSelection, Refinement,
                                                               tuple[Mode, ...], tuple[str, ...]]:
    """:func:`select_minimal` and :func:`refine_candidates` over the usable frames. Where they are degenerate
    and some boards were skipped as ambiguous in their orientation, the tilts of those boards are tried
    (``TILT_MARGIN_CHI2``); with two usable boards the tilts are tried first, and the two alone only where no
    tilt decides. Returns the frames (an ambiguous board made usable with its chosen tilt), the
    selection, the refinement, the modes and notes on the tilts chosen."""
    ambiguous = [k for k, f in enumerate(frames)
                 if not f.usable and f.lidar is not None and len(f.camera_alternatives) > 1][:MAX_AMBIGUOUS_BOARDS]
    if ambiguous and sum(f.usable for f in frames) == 2:
        # Two boards alone are the weakest layout that can be solved: a third from the ambiguous ones, with the
        # tilt the laser decides, first; the two alone when no tilt decides.
        try:
            return _with_tilts(frames, board, camera, method, options, use_extent, ambiguous, DegenerateLayoutError(
                "only 2 usable frame(s); a 2D LiDAR needs at least 3 boards",
                hint="record more boards, or boards whose orientation the image decides"))
        except DegenerateLayoutError as exc:
            tilts_failed = exc
        try:
            return _select_and_refine(frames, board, camera, method, options, use_extent) + ((),)
        except DegenerateLayoutError:
            raise tilts_failed from None
    try:
        return _select_and_refine(frames, board, camera, method, options, use_extent) + ((),)
    except DegenerateLayoutError as exc:
        degenerate = exc
    if not ambiguous:
        raise degenerate
    return _with_tilts(frames, board, camera, method, options, use_extent, ambiguous, degenerate)


def _with_tilts(frames, board, camera, method, options, use_extent, ambiguous: list[int],
                degenerate: DegenerateLayoutError):
    """:func:`select_and_refine` over each combination of the ``ambiguous`` boards' tilts (``TILT_MARGIN_CHI2``);
    ``degenerate``: why the layout without them was not solved, the refusal's start."""
    use_extent = board.size_known if use_extent is None else use_extent
    tried = []
    for tilts in itertools.product(*(range(len(frames[k].camera_alternatives)) for k in ambiguous)):
        trial = list(frames)
        for k, c in zip(ambiguous, tilts):
            trial[k] = replace(frames[k], camera=frames[k].camera_alternatives[c], reason=None)
        try:
            out = _select_and_refine(trial, board, camera, method, options, use_extent)
        except DegenerateLayoutError:
            continue
        used = [f for f in out[0] if f.usable]
        sigma_r = max(pooled_range_noise_m([f.lidar for f in used]), 1e-5)
        if use_extent:
            # The least joint cost near each minimum (``outline_evidence``), not at it: an ambiguous board's
            # camera pose is weak along its tilt, and the factor graph's minimum, which moves that pose, can sit
            # well above the joint cost's own minimum close by (a right tilt was judged implausible).
            joint = np.array([outline_evidence(m.refinement, used, board, sigma_r)[0] for m in out[3]])
        else:
            joint = marginal_laser_costs(np.array([m.T_camera_lidar for m in out[3]]), used, sigma_r)
        corners = sum(frames[k].camera_alternatives[c].orientation_excess_chi2 for k, c in zip(ambiguous, tilts))
        tried.append((float(joint.min()) + corners, tilts, out, (4 if use_extent else 2) * len(used)))
    if not tried:
        raise degenerate
    tried.sort(key=lambda t: t[0])
    # The joint cost is about chi-square (2 laser and, with the outline, 2 segment-end terms per board) where the
    # answer is right: a best combination far above it was not solved (the layout is still too weak for the
    # factor graph's minimum to be the data's), and the refusal stands.
    if tried[0][0] > chi2.isf(IMPLAUSIBLE_P, tried[0][3]):
        raise DegenerateLayoutError(
            f"{degenerate.problem}; with the boards skipped as ambiguous in their orientation the best fit is "
            f"implausible (joint cost {tried[0][0]:.0f} on {tried[0][3]} degrees of freedom)", hint=degenerate.hint)
    margin = tried[1][0] - tried[0][0] if len(tried) > 1 else np.inf
    if margin < TILT_MARGIN_CHI2:
        raise DegenerateLayoutError(
            f"{degenerate.problem}; the boards skipped as ambiguous in their orientation do not decide it either "
            f"(their tilts fit the laser points alike: joint costs {tried[0][0]:.1f} and {tried[1][0]:.1f})",
            hint=degenerate.hint)
    cost, tilts, out, _ = tried[0]
    notes = tuple(f"frame {frames[k].name}: the board's orientation is ambiguous in the image; the tilt the laser "
                  f"line agrees with is used (joint cost {cost:.1f}, the next combination of tilts "
                  f"{tried[1][0]:.1f})" if len(tried) > 1 else
                  f"frame {frames[k].name}: the board's orientation is ambiguous in the image; the only tilt that "
                  "gives a solution is used" for k in ambiguous)
    return out + (notes,)


def _select_and_refine(frames, board, camera, method, options, use_extent):
    used = [f for f in frames if f.usable]
    sel = select_minimal(used, board, method, use_extent, options.max_sensor_separation_m)
    ref, modes = refine_candidates(used, board, camera, sel, options, use_extent)
    return frames, sel, ref, modes
