"""The plane graph's problem (``PlaneProblem``): the extrinsic, one board pose per frame, each frame's corner and
plane factors and the range terms, built and solved in GTSAM; its Hessian, the extrinsic's information and the
degenerate directions.
"""
from __future__ import annotations

import gtsam
import numpy as np

from geometry.board import BoardModel
from geometry.camera import CameraModel

from ..errors import DegenerateLayoutError
from ..measurements import FrameMeasurement
from .closed_form import describe_direction
from .factor_graph import CameraViews, LidarViews, PlaneError, build_graph, graph_values
from .factors import corner_residuals, lidar_plane, lidar_residual, nuisance_residual
from .graph_keys import EXTRINSIC, OUTLINE, RANGE, board_key, deviation_key, shift_key
from .noise_levels import frame_noise, own_fit_residuals, pooled_range_noise_m
from .range_model import FrameLabels, RangeTerms, frame_whiteners
from .refinement_options import PINNED_SD_M, RefinementOptions

# A pair is the rig of its camera (the graph's reference) and its LiDAR (``graph_keys.EXTRINSIC``).
PAIR_NAMES = ("cam0", "lidar0")


def pooled_range_noise_with_terms_m(prob: "PlaneProblem", frames: list[int]) -> float:
    """Range noise pooled over the frames' best fits of their planes and range terms (``prob.fw``): each
    board spends as many degrees of freedom as its plane and terms span (the rank of its fit)."""
    ss = sum(prob.fw[i].floor for i in frames)
    dof = sum(prob.frames[i].lidar.n_points - prob.fw[i].R.shape[0] for i in frames)
    return float(np.sqrt(ss / max(dof, 1)))


class PlaneProblem:
    """The data of one refinement: per frame its plane whitener, the plane noise, the corner noise, and the
    range model's terms (None: none) with their current values ``beta``."""

    def __init__(self, frames: list[FrameMeasurement], board: BoardModel, camera: CameraModel, sigma_px: float,
                 sigma_r: float, options: RefinementOptions, terms: RangeTerms | None = None,
                 labels: FrameLabels | None = None, edges: list | None = None, sigma_board: list | None = None):
        self.frames, self.board, self.camera = frames, board, camera
        # Per frame, its ring ends used as the board's edges (``solvers.board_edges``; None: planes only), and
        # the edges' shared growth (m) and the scale of their standard deviations.
        self.edges = edges
        self.outline = np.zeros(4)  # the board's outline: sides' growth (x, y) and offset (x, y), m
        self.edge_scale = 1.0
        self.edge_tau = 1e-3  # the boards' in-plane scatter (m), estimated with the edges
        self.solved = None  # the last solve's (graph, values) when a step beyond the first solves again
        self.shifts: dict[int, np.ndarray] = {}
        self.ends_cache = None  # the rings and the ends' noise (``edges_in_graph._rings_and_noise``)
        # The corners' effective pixel noise: the camera's, and each frame's own (None: the camera's for all).
        self.sigma_px, self.sigma_r, self.options = sigma_px, sigma_r, options
        self.sigma_board = sigma_board
        self.terms, self.labels = terms, labels
        # Noise-corrected at the noise the data show (not at a given sigma_r, which sets the weights only).
        self.fw = frame_whiteners(frames, pooled_range_noise_m([f.lidar for f in frames]), terms, labels)
        self.whiteners = [w.W for w in self.fw]
        self.beta = np.zeros(terms.size if terms else 0)
        self.has_beta = bool(terms is not None and terms.size)
        # Scatter (m) of each board's own range terms about the shared ones: estimated when they disagree
        # beyond the noise (biases that vary with range, incidence or temperature, or terms the model lacks).
        self.tau = 0.0
        # Indices of terms held at their prior mean (0): not believed, their prior variance propagated instead.
        self.pinned: tuple[int, ...] = ()
        # The boards' variance factor beyond every modelled error (quasi-likelihood): the data's information is
        # divided by it, which for the solve is the terms' prior information multiplied by it (the covariance is
        # then scaled by it whole, ``refinement``).
        self.dispersion = 1.0
        self.corners_board = [f.camera.corners_board(board) for f in frames]  # the corners each frame saw
        self.pnp_chi2 = [self.corner_chi2(i, f.camera.T_camera_board) for i, f in enumerate(frames)]
        self._ranks: dict[tuple, int] = {}

    def whitener(self, i: int) -> np.ndarray:
        return self.whiteners[i]

    def nuisance_rank(self, frames: list[int]) -> int:
        """How many combinations of the nuisance terms the frames' points determine."""
        if self.terms is None:
            return 0
        key = tuple(frames)
        if key not in self._ranks:  # the whiteners are fixed with the problem
            self._ranks[key] = self._nuisance_rank(frames)
        return self._ranks[key]

    def _nuisance_rank(self, frames: list[int]) -> int:
        rows = []
        for i in frames:
            rows.append(self.fw[i].W_nuisance if self.fw[i].S.size else np.zeros((self.whiteners[i].shape[0],
                                                                                  self.terms.size)))
        return _rank(np.vstack(rows))

    def residual(self, i: int, T: np.ndarray, T_board: np.ndarray) -> np.ndarray:
        pi, _, _ = lidar_plane(T, T_board)
        scan = self.frames[i].lidar.is_scan_line
        if self.terms is None:
            return lidar_residual(self.whitener(i), pi, scan)[0]
        fw = self.fw[i]
        return nuisance_residual(fw.W, fw.S, fw.m_away, pi, self.beta, scan, fw.e0)[0]

    def plane_error(self, i: int, floor_m: float) -> PlaneError:
        """Frame ``i``'s board plane error (``factor_graph.PlaneError``) at the per-board plane error ``floor_m``."""
        return PlaneError.of_frame(self.frames[i], self.fw[i].centre, self.board, floor_m, self.options.corner_scale_sd)

    def plane_cov(self, i: int, floor_m: float) -> np.ndarray:
        pe = self.plane_error(i, floor_m)
        return frame_noise(self.fw[i], pe.normal, self.sigma_r, floor_m, pe.half_m, pe.scale_m, self.tau)

    def term_consistency(self, frames: list[int], T: np.ndarray, boards: list, floor_m: float) -> tuple[float, int]:
        """How far each board's residual lies along its weak direction (its distance against its offsets, told
        apart only by incidence across the board), in units of its noise: chi-square, one dof per board. Real
        sensors' incidence-dependent biases show here first."""
        stat, dof = 0.0, 0
        for i in frames:
            fw = self.fw[i]
            if fw.R is None or fw.weak is None:
                continue
            Rv = fw.R @ fw.weak
            u = Rv / np.linalg.norm(Rv)
            e = self.residual(i, T, boards[i])
            stat += float(u @ e) ** 2 / float(u @ self.plane_cov(i, floor_m) @ u)
            dof += 1
        return stat, max(dof, 1)

    def graph(self, active: list[int], floor_m: float, robust: bool = True, free_pinned: bool = False,
              intrinsics: bool = False) -> gtsam.NonlinearFactorGraph:
        """The graph of the ``active`` frames (``factor_graph.build_graph``, frame ``j`` the ``j``-th of them): the
        corners at the pooled pixel noise, each plane at its frame's covariance (:meth:`plane_cov`, robust unless
        ``robust`` is False), the terms under their priors (pinned ones at ``PINNED_SD_M`` unless
        ``free_pinned``); with ``intrinsics`` the camera's intrinsics a variable too (``graph_keys.INTRINSICS``,
        under a prior of its ``param_std`` when it has them)."""
        camera, lidar = self.views(active, floor_m, robust, free_pinned)
        return build_graph(PAIR_NAMES, [camera], [lidar], [self.frames[i].name for i in active],
                           {n: 1.0 for n in PAIR_NAMES}, PAIR_NAMES[0], intrinsics)

    def views(self, active: list[int], floor_m: float, robust: bool = True, free_pinned: bool = False
              ) -> tuple[CameraViews, LidarViews]:
        """The camera's and the LiDAR's views of the ``active`` frames that :meth:`graph` is built from."""
        stems = [self.frames[i].name for i in active]
        camera = CameraViews(PAIR_NAMES[0], self.camera, self.sigma_px,
                             {s: self.corners_board[i] for s, i in zip(stems, active)},
                             {s: self.frames[i].camera.corners_px for s, i in zip(stems, active)},
                             sigma_board={s: self.sigma(i) for s, i in zip(stems, active)})
        prior_sd = None
        if self.has_beta:
            prior_sd = self.terms_prior_sd()
            if self.pinned and not free_pinned:
                prior_sd[list(self.pinned)] = PINNED_SD_M
        lidar = LidarViews(PAIR_NAMES[1], self.sigma_r, {s: self.whitener(i) for s, i in zip(stems, active)},
                           any(self.frames[i].lidar.is_scan_line for i in active),
                           None if self.terms is None else {s: self.fw[i] for s, i in zip(stems, active)},
                           self.terms,
                           None if self.edges is None else {s: self.edges[i] for s, i in zip(stems, active)
                                                            if self.has_edges(i)},
                           self.board, self.edge_tau, self.edge_scale,
                           {s: self.plane_error(i, floor_m) for s, i in zip(stems, active)},
                           self.options if robust else None, self.tau, prior_sd,
                           {s: own_fit_residuals(self.frames[i].lidar) for s, i in zip(stems, active)})
        return camera, lidar

    def terms_prior_sd(self) -> np.ndarray:
        """The range terms' prior standard deviations in the graph: their priors over the square root of the
        boards' dispersion (:attr:`dispersion`)."""
        return np.array(self.terms.prior_sd, dtype=float) / np.sqrt(self.dispersion)

    def plane_chi2(self, i: int, T: np.ndarray, T_board: np.ndarray, floor_m: float) -> float:
        e = self.residual(i, T, T_board)
        return float(e @ np.linalg.solve(self.plane_cov(i, floor_m), e))

    def corner_chi2(self, i: int, T_board: np.ndarray) -> float:
        f = self.frames[i]
        r, _ = corner_residuals(T_board, self.corners_board[i], f.camera.corners_px, self.camera, jacobian=False)
        return float(r @ r) / self.sigma(i)**2

    def sigma(self, i: int) -> float:
        """The effective pixel noise of frame ``i``'s corners."""
        return self.sigma_px if self.sigma_board is None else self.sigma_board[i]

    def frame_chi2(self, i: int, T: np.ndarray, T_board: np.ndarray, floor_m: float) -> float:
        """The frame's share of the consistency statistic: its plane residual plus how far its board had
        to move from the camera's own fit (a cheap camera lets a bad LiDAR plane drag the board)."""
        return self.plane_chi2(i, T, T_board, floor_m) + self.corner_chi2(i, T_board) - self.pnp_chi2[i]

    def values(self, active: list[int], T: np.ndarray, boards: list, floor_m: float = 0.0) -> gtsam.Values:
        """The graph's variables (:meth:`graph` at ``floor_m``): the extrinsic, the active frames' boards, the range
        terms, the outline and the frames' outline shifts at their current values, and with a per-board plane
        error the deviations of the planes the ends lie on (0)."""
        vectors = {RANGE: self.beta.copy(), OUTLINE: np.array(self.outline, dtype=float)}
        vectors.update({shift_key(j): self.shifts.get(i, np.zeros(2)) for j, i in enumerate(active)})
        stems = [self.frames[i].name for i in active]
        lidar = LidarViews(PAIR_NAMES[1], self.sigma_r, terms=self.terms if self.has_beta else None,
                           ranged={} if self.has_beta else None,
                           edges=None if self.edges is None else {self.frames[i].name: None for i in active
                                                                  if self.has_edges(i)},
                           scan_line=any(self.frames[i].lidar.is_scan_line for i in active),
                           plane_error=None if self.edges is None or floor_m <= 0 else
                           {self.frames[i].name: self.plane_error(i, floor_m) for i in active})
        return graph_values(PAIR_NAMES, PAIR_NAMES[0], stems, {PAIR_NAMES[0]: np.eye(4), PAIR_NAMES[1]: T},
                            {s: boards[i] for s, i in zip(stems, active)}, [lidar], vectors)

    def has_edges(self, i: int) -> bool:
        return self.edges is not None and self.edges[i] is not None and self.edges[i].size > 0

    def variant(self, camera: CameraModel | None = None, labels: FrameLabels | None = None, edges: bool = True
                ) -> "PlaneProblem":
        """The same problem and state (terms and their values, scatter, pinned terms, edges) with another camera
        model or labels, or without the edges."""
        p = PlaneProblem(self.frames, self.board, camera or self.camera, self.sigma_px, self.sigma_r, self.options,
                         self.terms, labels or self.labels, sigma_board=self.sigma_board)
        p.beta, p.tau, p.pinned, p.ends_cache = self.beta.copy(), self.tau, self.pinned, self.ends_cache
        p.dispersion = self.dispersion
        if edges:
            p.copy_edges(self)
        return p

    def copy_edges(self, other: "PlaneProblem") -> None:
        self.edges, self.outline, self.edge_scale = other.edges, other.outline.copy(), other.edge_scale
        self.edge_tau, self.shifts = other.edge_tau, dict(other.shifts)

    def solve(self, active: list[int], T: np.ndarray, boards: list, floor_m: float, robust: bool = True
              ) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values, int]:
        values = self.values(active, T, boards, floor_m)
        graph = self.graph(active, floor_m, robust)
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(self.options.max_iterations)
        params.setRelativeErrorTol(1e-9)
        params.setAbsoluteErrorTol(1e-9)
        opt = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
        result = opt.optimize()
        T = result.atPose3(EXTRINSIC).matrix()
        for j, i in enumerate(active):
            boards[i] = result.atPose3(board_key(j)).matrix()
        if self.has_beta:
            self.beta = np.asarray(result.atVector(RANGE), dtype=float)
        if self.edges is not None:
            self.outline = np.asarray(result.atVector(OUTLINE), dtype=float)
            self.shifts = {i: np.asarray(result.atVector(shift_key(j)), dtype=float)
                           for j, i in enumerate(active) if self.has_edges(i)}
        return graph, result, int(opt.iterations())

    def plane_cost(self, frames: list[int], T: np.ndarray, boards: list, floor_m: float) -> float:
        """The cost the camera alone cannot explain, summed over ``frames``."""
        return sum(self.frame_chi2(i, T, boards[i], floor_m) for i in frames)

    def plane_directions(self, i: int, floor_m: float) -> tuple[np.ndarray, np.ndarray]:
        """Frame ``i``'s noise square root ``L`` (``plane_cov = L L^T``) and an orthonormal basis ``Q`` of the
        whitened residual's directions a per-board plane error can move (the board's normal and distance; with
        range terms the rest is the board's own terms against the shared ones, which no plane error holds)."""
        L = np.linalg.cholesky(self.plane_cov(i, floor_m))
        fw = self.fw[i]
        if fw.R is None:
            return L, np.eye(L.shape[0])
        return L, np.linalg.qr(np.linalg.solve(L, fw.R[:, :fw.nt + 1]))[0]

    def plane_moment(self, frames: list[int], T: np.ndarray, boards: list, floor_m: float) -> float:
        """The share of :meth:`plane_cost` a per-board plane error can explain: each frame's plane residual
        in its plane directions (:meth:`plane_directions`) plus its corners' move."""
        stat = 0.0
        for i in frames:
            L, Q = self.plane_directions(i, floor_m)
            p = Q.T @ np.linalg.solve(L, self.residual(i, T, boards[i]))
            stat += float(p @ p) + self.corner_chi2(i, boards[i]) - self.pnp_chi2[i]
        return stat

    def plane_moment_dof(self, frames: list[int], T: np.ndarray, boards: list, floor_m: float) -> float:
        """The degrees of freedom of :meth:`plane_moment`: the frames' plane directions less their share of the
        extrinsic's and free range terms' leverage (the hat matrix's trace over those rows)."""
        blocks, Qs = [], []
        free = [k for k in range(self.terms.size) if k not in self.pinned] if self.has_beta else []
        for i in frames:
            L, Q = self.plane_directions(i, floor_m)
            pi, H_x, _ = lidar_plane(T, boards[i])  # the factors' own Jacobians, in the extrinsic's right tangent
            fw, scan = self.fw[i], self.frames[i].lidar.is_scan_line
            if self.terms is None:
                J = lidar_residual(self.whitener(i), pi, scan)[1] @ H_x
            else:
                _, J_pi, H_beta = nuisance_residual(fw.W, fw.S, fw.m_away, pi, self.beta, scan, fw.e0)
                J = np.hstack([J_pi @ H_x, H_beta[:, free]])
            blocks.append(np.linalg.solve(L, J))
            Qs.append(Q)
        J = np.vstack(blocks)
        U = np.linalg.svd(J, full_matrices=False)[0][:, :_rank(J)]
        lev, r = 0.0, 0
        for Jb, Q in zip(blocks, Qs):
            Ub = U[r:r + len(Jb)]
            lev += float(np.sum((Q.T @ Ub) ** 2))
            r += len(Jb)
        return max(sum(Q.shape[1] for Q in Qs) - lev, 1.0)

    def planes_dof(self, frames: list[int]) -> int:
        """The frames' whitened rows less the extrinsic's 6 and the range terms' rank: :meth:`consistency`'s
        degrees of freedom without the edges."""
        return sum(self.whitener(i).shape[0] for i in frames) - 6 - self.nuisance_rank(frames)

    def consistency(self, frames: list[int], T: np.ndarray, boards: list, floor_m: float,
                    active: list[int]) -> tuple[float, float]:
        """:meth:`plane_cost` and its degrees of freedom under the model: the frames' whitened rows less 6 and
        the range terms' rank; with the edges in the graph of the ``active`` frames, more (:meth:`edge_leverage`)."""
        dof = self.planes_dof(frames)
        if self.edges is not None:
            dof += self.edge_leverage(active, T, boards, floor_m)
        return self.plane_cost(frames, T, boards, floor_m), max(dof, 1)

    def edge_leverage(self, active: list[int], T: np.ndarray, boards: list, floor_m: float) -> float:
        """How many of the extrinsic's and board poses' directions the edges fit rather than the corners and
        planes: ``P - tr(H_cp Sigma)``, ``H_cp`` the corners' and planes' information on those ``P`` unknowns
        and ``Sigma`` their covariance in the whole graph. The planes' and corners' cost at the joint estimate
        then has that many more degrees of freedom than ``3 N - 6`` (the expected cost of a linear model's rows
        is their count less their leverage): three 2D scan lines give their planes 6 rows, which alone would
        fit the extrinsic exactly, while the segment ends fix much of it. Kept within 0-6: the corners fix the
        board poses far better than the edges can, so what the edges take is the extrinsic's."""
        n = len(active)
        H_all = hessian(self.graph(active, floor_m), self.values(active, T, boards, floor_m), n)[0]
        planes = self.variant(edges=False)
        H_cp = hessian(planes.graph(active, floor_m), planes.values(active, T, boards, floor_m), n)[0]
        k = 6 + 6 * n  # extrinsic and board poses, first in both orderings; range terms last in both
        idx = np.r_[0:k, H_all.shape[0] - (H_cp.shape[0] - k):H_all.shape[0]]
        Sigma = np.linalg.pinv(H_all, hermitian=True)[np.ix_(idx, idx)]
        return float(np.clip(H_cp.shape[0] - np.trace(H_cp @ Sigma), 0.0, 6.0))


def _rank(A: np.ndarray) -> int:
    """Numerical rank, relative tolerance 1e-8 (the range regressors' exact collinearities, a global offset
    and the per-ring offsets, survive the square root only to about 1e-10)."""
    sv = np.linalg.svd(A, compute_uv=False)
    return int(np.sum(sv > 1e-8 * sv[0])) if sv.size and sv[0] > 0 else 0


def hessian(graph, values, n_frames: int) -> tuple[np.ndarray, np.ndarray]:
    """The graph's information and information vector at ``values`` (its cost there is ``0.5 d^T H d - eta^T d``
    + const in the tangent ``d``), ordered extrinsic, board poses, the edges' nuisances, range terms last (those
    present)."""
    ordering = gtsam.Ordering()
    ordering.push_back(EXTRINSIC)
    for j in range(n_frames):
        ordering.push_back(board_key(j))
    for key in [shift_key(j) for j in range(n_frames)] + [deviation_key(j) for j in range(n_frames)] + [OUTLINE,
                                                                                                      RANGE]:
        if values.exists(key):
            ordering.push_back(key)
    return graph.linearize(values).hessian(ordering)


def extrinsic_information(graph, values, n_frames: int) -> tuple[np.ndarray, np.ndarray]:
    """The graph's information and information vector on the extrinsic alone at ``values``, every other
    variable profiled out (Schur complement)."""
    H, eta = hessian(graph, values, n_frames)
    K = H[:6, 6:] @ np.linalg.pinv(H[6:, 6:])
    return H[:6, :6] - K @ H[:6, 6:].T, eta[:6] - K @ eta[6:]


def degenerate(graph, values, n_frames: int) -> DegenerateLayoutError:
    """Explain a singular system by the extrinsic's least-informed direction."""
    info, _ = extrinsic_information(graph, values, n_frames)
    vals, vecs = np.linalg.eigh(info)
    weak = vecs[:, 0]
    part = "rotation" if np.linalg.norm(weak[:3]) > np.linalg.norm(weak[3:]) else "translation"
    axis, advice = describe_direction(weak[:3] if part == "rotation" else weak[3:])
    return DegenerateLayoutError(
        f"the {n_frames} frames leave the extrinsic's {part} unobservable (information {vals[0]:.2g} "
        f"against {vals[-1]:.2g}; weakest direction {np.round(weak, 2).tolist()} in the LiDAR tangent)",
        hint=f"record more board poses; {advice}")


# Smallest over largest eigenvalue of the extrinsic's covariance (rad and m) below which a direction is
# taken as unobservable: a good layout of metre-scale boards is near 1e-2; one whose normals do not span 3D
# falls below 1e-6 (its weak translation std grows to metres).
MIN_INFORMATION_RATIO = 1e-6


def objective(p: PlaneProblem, graph, result, active: list[int], floor_m: float) -> float:
    """Minus twice the log-likelihood (up to a constant shared by every model of the same frames) at a solve:
    the objective the solve minimised (robust loss, priors), the boards' best-fit floors (they differ with the
    terms each board holds) and the log-determinants of the plane factors' covariances relative to the point
    noise (they differ with the terms once a per-board plane error is in place)."""
    logdet = 0.0
    for i in active:
        C = p.plane_cov(i, floor_m) / p.sigma_r**2
        logdet += float(np.linalg.slogdet(C)[1])
    return 2.0 * graph.error(result) + sum(p.fw[i].floor for i in active) / p.sigma_r**2 + logdet
