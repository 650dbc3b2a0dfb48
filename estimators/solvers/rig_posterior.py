"""The posterior of a rig's sensor poses by MCMC (emcee), in the joint graph's right tangent about its MAP.

Parameters: every sensor's pose but the graph's own reference camera's (``rig_graph.graph_reference``), 6 each:
``T_s = T_s_hat Exp(xi_s)``, so 48 parameters for 9 sensors. The likelihood is the joint graph's, at its noise
scales, with each frame's board pose integrated out:

- a camera's corners are linear in its pose's and the board's tangents about the MAP (the rig corner factor's
  Jacobians): hundreds of corners per board at sub-pixel noise, whose second order is far below their first;
- a LiDAR's board points enter exactly in the LiDAR's pose (the board's plane turned and moved into the LiDAR
  through ``T_ref_l Exp(xi_l)``, through the frame's ``W`` (a scan line divided by ``|n_xy|``) and whitened by its
  plane covariance at the MAP, ``LidarViews.plane_cov``) and linearly in the board's tangent.

The board tangent ``b_j`` of frame ``j`` then enters quadratically with a Hessian ``H_j`` that does not depend on
the sensor poses, and integrates out in closed form:

    log p(xi) = -1/2 sum_j [ c_j(xi) - g_j(xi)^T H_j^-1 g_j(xi) ] + const,

``c_j`` the frame's squared whitened residuals at ``b_j = 0`` and ``g_j`` their gradient by ``b_j``. Flat priors on
the poses. At the MAP its Hessian is the graph's information of the sensor poses (the Schur complement that
``gtsam.Marginals`` inverts), so the samples depart from the Laplace covariance only where the LiDAR planes are
nonlinear in the poses or the noise scale moves. Intrinsics refined with the rig are not sampled (the caller
reports the graph's covariance then).

The noise: each sensor's at the graph's scale (quasi-likelihood, by its chi-square), and the camera side's scale
``s`` sampled with the poses (last parameter, log-normal prior of sd ``LOG_SCALE_PRIOR_SD`` on ``log s``): the
corners' covariance and the boards' plane error (the per-board error and the pattern's scale error,
``LidarViews.plane_cov_parts``) times ``s^2``. The corners enter as a Gaussian measurement of
each board's pose given the cameras' (each frame's corners about their own best board, 6 directions a frame,
normalised), so ``s`` is told by how well the LiDARs' planes agree with the cameras' boards, not by the corners' own
scatter (which the graph's scale already holds); the samples then carry the noise level's uncertainty (1-6% wider
than the Laplace covariance on 8-board pairs). The cameras' poses relative to each other rest on the corners alone,
at the graph's scale: ``s`` is how far the boards' planes, which the LiDARs see, are from where the corners put them
(on a 6-camera rig s's posterior sits near 0.7, which applied to the camera-camera links would narrow them below
their errors). With one camera and one LiDAR this is a pair's likelihood (the tests build it from a pair's own
refinement, ``tests/numeric.py``, to hold it against that refinement): a 2D pair's segment ends enter by their own
likelihood, with the dataset's outline (4 parameters) under its prior,
and with several minima each is sampled within its cell, as a rig's are where a camera-scanner pair's boards leave
several (``pipeline.rig_modes``: each joint minimum within its cell of that pair's transform, mixed by
:func:`mix_modes`). With ``student-t``, each frame's share
of the squared residuals beyond its corners' own best board (its planes against its boards, ``k_j`` LiDAR rows) is
t-distributed with ``nu`` degrees of freedom; the corners' own part stays Gaussian. A 2D scanner's range noise,
which rests on a few dozen points a board, has its scale ``r`` sampled too (a parameter per scanner before ``log s``,
flat prior on ``log r`` within +-2), its own lines' residuals (``LidarViews.own_fit``) in its likelihood.

Samples are carried into the rig's reference frame exactly (``T_ref_s = T_ref_inner^-1 T_inner_s`` per sample) and
any pair's by composition (:meth:`RigPosterior.pair_samples`), so loops close sample by sample.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from geometry.differences import central_hessian
from geometry.rotations import T_log, between_batch, local_batch, retangent_batch, retract_batch

from ..errors import LidarcamError, PosteriorSkippedError
from .board_edges import EndTerms, outline_prior_sd
from .factors import lidar_plane, lidar_residual
from .noise_levels import robust_weight
from .sampler import ChainResult, mixture_picks, run_ensemble, run_with_proposal
from .factor_graph import CameraViews, LidarViews, rig_corner_residuals
from .graph_keys import edge_shift_key, outline_key
from .rig_graph import RigSolution, change_reference, graph_reference

# The prior's sd of ``log s``, the camera side's noise scale, in every posterior (a pair's and a rig's).
LOG_SCALE_PRIOR_SD = 0.5

# The camera side's noise scale ``s`` is sampled within ``exp(+-MAX_ABS_LOG_SCALE)`` of the graph's: 10 of its prior's
# standard deviations, beyond which the prior holds no mass worth a sample (and a proposal there is refused).
MAX_ABS_LOG_SCALE = 5.0

# Samples kept for the pairs' intervals and covariances (thinned evenly from the chain after burn-in).
MAX_KEPT = 20000


@dataclass(frozen=True, eq=False)
class RigPosterior:
    """Samples of every sensor's pose in the reference's frame: ``xi`` (M, 6N) in the order of ``names`` (right
    tangents of ``T_ref_s`` at the MAP; the reference's block zero), the MAP poses and the chain's diagnostics."""

    names: tuple[str, ...]
    reference: str
    T_ref: dict
    xi: np.ndarray
    run: ChainResult
    # Each LiDAR's range terms (m, (M, K) in its ``RangeTerms`` order) per sample, where the graph has them.
    range_terms: dict = field(default_factory=dict)
    # The camera side's noise scale ``s`` per sample (module docstring).
    camera_scale: np.ndarray | None = None
    likelihood: str = "gaussian"
    # Where a camera-LiDAR pair's boards leave several minima (``mix_modes``): each joint minimum's share of the
    # samples (the estimate's first) and each sample's minimum; else empty and None.
    mode_weights: tuple[float, ...] = ()
    mode_index: np.ndarray | None = None
    mixed: tuple = ()  # those pairs, ``(camera, lidar)``
    mode_T_ref: tuple = ()  # each joint minimum's sensor poses (``T_ref``), the estimate's first
    # Each pair's samples once composed (the warnings, the record, the printout and the report all read them).
    _pairs: dict = field(default_factory=dict, repr=False)
    _sensor_T: dict = field(default_factory=dict, repr=False)

    @property
    def covariance_joint(self) -> np.ndarray:
        """The samples' covariance of every sensor's pose (6N x 6N, ``names`` order)."""
        return np.cov(self.xi, rowvar=False)

    def pair_samples(self, a: str, b: str) -> np.ndarray:
        """Samples (M, 6) of ``T_a_b``'s right tangent at its MAP, each composed from one joint sample (read-only)."""
        if (a, b) not in self._pairs:
            self._pairs[(a, b)] = self._compose(a, b)
            self._pairs[(a, b)].setflags(write=False)
        return self._pairs[(a, b)]

    def _compose(self, a: str, b: str) -> np.ndarray:
        Ra, ta = self._sensor_poses(a)
        Rb, tb = self._sensor_poses(b)
        return local_batch(np.linalg.inv(self.T_ref[a]) @ self.T_ref[b], *between_batch(Ra, ta, Rb, tb))

    def mode_centers(self, a: str, b: str) -> np.ndarray | None:
        """Each joint minimum's ``T_a_b`` as a tangent offset (K, 6) of the estimate's, or None for one minimum."""
        if not self.mode_T_ref:
            return None
        T = np.linalg.inv(self.T_ref[a]) @ self.T_ref[b]
        return np.array([T_log(np.linalg.inv(T) @ np.linalg.inv(m[a]) @ m[b]) for m in self.mode_T_ref])

    def diagnostics(self) -> dict:
        out = {"likelihood": self.likelihood, **self.run.diagnostics(), "samples_kept": int(self.xi.shape[0])}
        if self.mode_weights:  # the chain's diagnostics are the estimate's minimum's
            out["mode_weights"] = list(self.mode_weights)
        return out

    def _sensor_poses(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """Every sample's ``T_ref_name`` (rotations, translations), made once."""
        if name not in self._sensor_T:
            self._sensor_T[name] = retract_batch(self.T_ref[name], self._block(name))
        return self._sensor_T[name]

    def _block(self, name: str) -> np.ndarray:
        k = self.names.index(name)
        return self.xi[:, 6 * k:6 * k + 6]


def _forward(L: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``L^-1 b`` for a stack of lower-triangular ``L`` (..., n, n) and ``b`` (..., n), by forward substitution over
    the n rows, each a vectorised step over the stack (numpy's batched solve of many 6x6 systems, a general LU per
    matrix, took 0.9 ms a call for a 6-camera rig's 16 frames and 124 walkers; this, 0.3 ms)."""
    z = np.empty_like(b)
    for i in range(b.shape[-1]):
        z[..., i] = (b[..., i] - np.einsum("...j,...j->...", L[..., i, :i], z[..., :i])) / L[..., i, i]
    return z


class RigLikelihood:
    """The vectorised log-posterior of the free sensors' tangents and the camera side's noise scale ``log s`` (last;
    module docstring), built at the MAP; a LiDAR's range terms held (:func:`hold_terms`)."""

    def __init__(self, solution: RigSolution, cameras: list[CameraViews], lidars: list[LidarViews],
                 quadratic: tuple[np.ndarray, np.ndarray] | None = None,
                 log_scale_prior_sd: float = LOG_SCALE_PRIOR_SD, likelihood: str = "gaussian", nu: float = 4.0,
                 ends: dict | None = None, cells: tuple = ()):
        names = solution.names
        self.inner = graph_reference(solution.reference, [c.name for c in cameras])
        T_inner = np.linalg.inv(solution.T_ref[self.inner])
        self.T = {n: T_inner @ solution.T_ref[n] for n in names}
        boards = {s: T_inner @ B for s, B in solution.T_ref_board.items()}
        self.stems = sorted(boards)
        frame = {s: j for j, s in enumerate(self.stems)}
        self.free = [n for n in names if n != self.inner]
        col = {n: 6 * k for k, n in enumerate(self.free)}
        F = len(self.stems)
        self.H_cam = np.zeros((F, 6, 6))  # the corners' information of each board pose, at s = 1
        self.g0 = np.zeros((F, 6))  # the camera parts of g_j at xi = 0
        self.c0 = 0.0
        self.cam_terms = []  # per free camera: (column, Q, q, frame indices, K^T (F_c, 6, 6))
        for c in cameras:
            scale = np.sqrt(solution.noise_scale.get(c.name, 1.0))
            T_rs = self.T[c.name]
            Q, q, idx, K = np.zeros((6, 6)), np.zeros(6), [], []
            for stem in c.corners_px:
                if stem not in frame:
                    continue
                j = frame[stem]
                s = c.sigma(stem) * scale
                r, A, B = rig_corner_residuals(T_rs, boards[stem], c.corners_board[stem], c.corners_px[stem],
                                               c.camera)
                r, A, B = r / s, A / s, B / s
                self.H_cam[j] += B.T @ B
                self.g0[j] += B.T @ r
                self.c0 += float(r @ r)
                if c.name != self.inner:
                    Q += A.T @ A
                    q += A.T @ r
                    idx.append(j)
                    K.append(B.T @ A)
            if c.name != self.inner and idx:  # K transposed: x @ K^T is K x for every walker
                self.cam_terms.append((col[c.name], Q, q, np.array(idx), np.transpose(np.array(K), (0, 2, 1))))
        if any(lv.has_terms for lv in lidars):
            raise ValueError("a LiDAR's range terms are held at the estimate in every posterior: hold_terms first")
        self.rows = np.zeros(F)  # each frame's LiDAR rows (the Student-t's dimensions)
        self.lidar_terms = []  # per LiDAR: (column, T_hat, frame indices, W^T (F_l, 4, k), normals, offsets, scan, G,
        #                                    signs (F_l,), e0 (F_l, k), each row's camera-side variance lam (F_l, k),
        #                                    its name)
        # Each 2D scanner's range noise rests on a few dozen points per board: its scale r (to the graph's) is a
        # parameter after the poses and outlines, its likelihood its lines' own residuals (``floors`` in units of
        # the graph's range variance, ``dof``) with the rest, under a flat prior on log r (|log r| < 2), as the
        # single pair's.
        self.scans = [lv.name for lv in lidars if lv.scan_line and lv.own_fit]
        self.scan_fit = {}
        for lv in lidars:
            scale = solution.noise_scale.get(lv.name, 1.0)
            if lv.name in self.scans:
                fits = [lv.own_fit[st] for st in lv.W if st in frame and st in lv.own_fit]
                self.scan_fit[lv.name] = (sum(ss for ss, _ in fits) / (lv.sigma_m**2 * scale),
                                          float(sum(d for _, d in fits)))
            idx, Ws, G, normals, points, signs, E0, lams = [], [], [], [], [], [], [], []
            rows = {st: (lv.ranged[st].W.shape[0] if lv.ranged is not None else W.shape[0]) for st, W in lv.W.items()}
            width = max((k for st, k in rows.items() if st in frame), default=0)
            for stem, W in lv.W.items():
                if stem not in frame:
                    continue
                j = frame[stem]
                fw = lv.ranged[stem] if lv.ranged is not None else None
                W4 = fw.W[:, :4] if fw is not None else W
                pi, _, H_b = lidar_plane(self.T[lv.name], boards[stem])
                r_map, D = lidar_residual(W4, pi, lv.scan_line)
                # The range model's form orients the plane like the fitted one (``factors.nuisance_residual``).
                sign = 1.0 if fw is None or float(pi[:3] @ fw.m_away) >= 0 else -1.0
                k = W4.shape[0]
                # The residual's covariance C(s) = A + s^2 B (LiDAR part, camera side): with A = L L^T and
                # L^-1 B L^-T = V diag(lam) V^T, P = V^T L^-1 whitens C(s) to diag(1 + s^2 lam).
                A_l, B_l = lv.plane_cov_parts(stem, scale)
                Li = np.linalg.inv(np.linalg.cholesky(A_l))
                lam, V = np.linalg.eigh(Li @ B_l @ Li.T)
                P = V.T @ Li
                if lv.robust is not None:  # the frame keeps the weight the graph's robust loss gave it at the MAP
                    e = sign * r_map + (fw.e0 if fw is not None else 0.0)
                    u = P @ e
                    P = P * np.sqrt(robust_weight(float(np.sqrt(u @ (u / (1.0 + np.maximum(lam, 0.0))))), lv.robust, k))
                Gj, Wp, lam_j = np.zeros((width, 6)), np.zeros((width, 4)), np.zeros(width)
                Gj[:k] = sign * P @ D @ H_b
                Wp[:k] = P @ W4
                lam_j[:k] = np.maximum(lam, 0.0)
                e0 = np.zeros(width)
                if fw is not None:
                    e0[:k] = P @ fw.e0
                self.rows[j] += k
                idx.append(j)
                Ws.append(Wp)
                G.append(Gj)
                normals.append(boards[stem][:3, 2])
                points.append(boards[stem][:3, 3])
                signs.append(sign)
                E0.append(e0)
                lams.append(lam_j)
            if idx:  # W transposed (pi^T W^T is (W pi)^T); each plane's offset n . t_board
                normals, points = np.array(normals), np.array(points)
                self.lidar_terms.append((col[lv.name], self.T[lv.name], np.array(idx),
                                         np.transpose(np.array(Ws), (0, 2, 1)), normals,
                                         np.sum(normals * points, axis=1), lv.scan_line, np.array(G),
                                         np.array(signs), np.array(E0), np.array(lams), lv.name))
        # Whether a LiDAR row has a camera side (its frames' board information then changes with s row by row).
        self.scaled = any(bool(np.any(t[10] > 0)) for t in self.lidar_terms) or bool(self.scans)
        self.nx = 6 * len(self.free)  # the poses: the outlines, log r and log s follow
        try:  # H_cam_j = M M^T; the corners' own best board per frame: g_cam^T H_cam^-1 g_cam = |M^-1 g_cam|^2
            M = np.linalg.cholesky(self.H_cam)
        except np.linalg.LinAlgError as exc:
            raise LidarcamError("a frame's board is not fixed by the cameras' corners; the rig's posterior weighs each "
                                "frame's planes against its cameras' board") from exc
        self._cam_whitener = np.linalg.inv(M)
        # A 2D scanner's segment ends (``ends``: its ``EndTerms`` by name; a single pair's): their
        # own likelihood at the scanner's pose, with its outline (4 parameters each, after the poses, its departure
        # from the graph's estimate) under its prior; each end's variance grows by its board pose's (the corners'
        # covariance at the graph's board, H_cam_j^-1 = M^-T M^-1). ``cells``: for each camera-LiDAR pair whose
        # boards leave several minima, ``(ModeCells, camera, lidar, k)``: the samples kept within minimum ``k``'s
        # cell of that pair's transform (``posterior.ModeCells``).
        self.col = col
        self.cells = tuple(cells)
        self.end_sets = []  # (scanner, its EndSet, its outline's first column)
        if ends:
            Mi = self._cam_whitener
            cov_b = dict(zip(self.stems, np.transpose(Mi, (0, 2, 1)) @ Mi))
            board = next(lv.board for lv in lidars if lv.board is not None)
            for name, terms in ends.items():
                if name in col and any(st in terms.edges for st in self.stems):
                    end_set = terms.end_set(self.T[name], {st: boards[st] for st in self.stems}, board, cov_b)
                    self.end_sets.append((name, end_set, self.nx + 4 * len(self.end_sets)))
        self.outline_map = {name: np.asarray(ends[name].outline, dtype=float) for name, _, _ in self.end_sets}
        self.outline_sd = outline_prior_sd()
        n_outline = 4 * len(self.end_sets)
        self.r_column = {n: self.nx + n_outline + k for k, n in enumerate(self.scans)}
        self.ndim = self.nx + n_outline + len(self.scans) + 1
        # The LiDARs whose rows change with neither s nor r (no camera side, not a scanner): summed once.
        self._fixed_information = np.zeros((F, 6, 6))
        for t in self.lidar_terms:
            if not self._varies(t):
                self._fixed_information[t[2]] += np.einsum("fka,fkb->fab", t[7], t[7])
        self.alpha = np.zeros(self.nx)  # each coordinate's power of s in the sampled parameters (:meth:`fit_alpha`)
        self.prior_sd = log_scale_prior_sd
        self.likelihood, self.nu = likelihood, nu
        # Without a camera side in the LiDARs' rows and without a scanner, H_j(s) = H_cam_j / s^2 + H_lidar_j: with
        # M^-1 H_lidar_j M^-T = U diag(nu) U^T, H_j(s)^-1 = M^-T U diag(1 / (1/s^2 + nu)) U^T M^-1 for every s at
        # once (``_basis``: U^T M^-1 per frame).
        self._basis = self._nu = None
        if not self.scaled:
            Mi = self._cam_whitener
            self._nu, U = np.linalg.eigh(Mi @ self._fixed_information @ np.transpose(Mi, (0, 2, 1)))
            self._basis = np.transpose(U, (0, 2, 1)) @ Mi
            self._logdet_cam = float(2.0 * np.sum(np.log(np.diagonal(M, axis1=1, axis2=2))))
        # Measurements held to second order about the MAP (a rig's board edges: :func:`edges_quadratic`):
        # ``(A, b)``, adding ``-1/2 x^T A x + b^T x`` (``x`` the poses) to the log-posterior.
        self.quadratic = quadratic

    def _varies(self, terms: tuple) -> bool:
        """Whether a LiDAR's rows (an entry of ``lidar_terms``) change with ``s`` or its ``r``."""
        return bool(np.any(terms[10] > 0)) or terms[11] in self.r_column

    def _lidar_information(self, s2: np.ndarray, r2: dict) -> np.ndarray:
        """Every frame's board information from the LiDARs at each walker's ``s^2`` and scanners' ``r^2`` (by name):
        (F, walkers, 6, 6); the LiDARs whose rows change with neither are summed once (``_fixed_information``)."""
        H = np.zeros((len(self.stems), len(s2), 6, 6))
        for terms in self.lidar_terms:
            if self._varies(terms):
                idx, G, lam = terms[2], terms[7], terms[10]
                w = 1.0 / (r2.get(terms[11], 1.0) + lam[:, None, :] * s2[None, :, None])  # (F_l, walkers, k)
                H[idx] += np.einsum("fka,fwk,fkb->fwab", G, w, G, optimize=True)  # a quarter of the time unoptimised
        return H + self._fixed_information[:, None]

    def to_poses(self, theta: np.ndarray) -> np.ndarray:
        """The parameters as sampled (each pose coordinate ``i`` divided by ``s^alpha_i``) to the poses'
        tangents: a coordinate the corners alone fix spreads as ``s`` (``alpha`` 1), one the LiDARs alone
        fix does not (0); in these, the funnel the scale makes in the poses is near a cylinder."""
        x = np.array(np.atleast_2d(theta), dtype=float)
        # (a scale beyond its range has no density, :meth:`log_posterior`: its poses are not blown up to overflow)
        x[:, :self.nx] *= np.exp(np.outer(np.clip(x[:, -1], -MAX_ABS_LOG_SCALE, MAX_ABS_LOG_SCALE), self.alpha))
        return x

    def __call__(self, theta: np.ndarray) -> np.ndarray:
        """The log-density of the sampled parameters (:meth:`to_poses`, its Jacobian included)."""
        theta = np.atleast_2d(theta)
        return self.log_posterior(self.to_poses(theta)) + float(np.sum(self.alpha)) * theta[:, -1]

    def fit_alpha(self, sd: np.ndarray, delta: float = 0.25) -> None:
        """Each coordinate's ``alpha`` (:meth:`to_poses`): how its curvature at the MAP changes with ``log s`` between
        ``-delta`` and ``+delta`` (``-d log H_ii / 2 d log s``, within [0, 1]); ``sd`` the graph's standard
        deviations of the coordinates, a tenth of which is the differences' step."""
        n, h = self.nx, 0.1 * np.asarray(sd, dtype=float)
        curv = []
        for ls in (delta, -delta):
            base = np.zeros(self.ndim)
            base[-1] = ls
            e = np.zeros((n, self.ndim))
            e[np.arange(n), np.arange(n)] = h
            f = self.log_posterior(np.vstack([base, base + e, base - e]))
            curv.append(-(f[1:n + 1] - 2 * f[0] + f[n + 1:]) / h**2)
        ratio = np.maximum(curv[0], 1e-300) / np.maximum(curv[1], 1e-300)
        self.alpha = np.clip(-np.log(ratio) / (4 * delta), 0.0, 1.0)

    def log_posterior(self, theta: np.ndarray) -> np.ndarray:
        """The log-posterior at the poses' tangents and ``log s`` (not divided by ``s``); none (-inf) where
        a noise scale leaves its range (``|log s|`` beyond ``MAX_ABS_LOG_SCALE``, ``|log r|`` beyond 2), where the
        boards' information would lose its definiteness too."""
        theta = np.atleast_2d(theta)
        n = theta.shape[0]
        outside = np.abs(theta[:, -1]) > MAX_ABS_LOG_SCALE
        for k in self.r_column.values():
            outside |= np.abs(theta[:, k]) >= 2.0
        if outside.any():  # evaluated at the graph's scales there, then dropped
            theta = theta.copy()
            theta[outside, -1] = 0.0
            theta[np.ix_(outside, list(self.r_column.values()))] = 0.0
        log_s = theta[:, -1]
        s2 = np.exp(2.0 * log_s)
        # Frame-major batches (F, walkers, .): each product below is one batched matrix product over the frames.
        g_cam = np.broadcast_to(self.g0[:, None, :], (len(self.g0), n, 6)).copy()
        c_cam = np.full(n, self.c0)
        for k0, Q, q, idx, Kt in self.cam_terms:
            x = theta[:, k0:k0 + 6]
            c_cam += np.sum((x @ Q) * x, axis=1) + 2.0 * x @ q
            g_cam[idx] += x @ Kt
        g = g_cam / s2[None, :, None]
        # The corners: each board about its cameras' best board (scaled by s^2), and what is left, the cameras'
        # poses against each other (at the graph's scale).
        y_c = g_cam @ np.swapaxes(self._cam_whitener, 1, 2)  # batched matmul: a tenth of einsum's time
        boards = np.sum(y_c * y_c, axis=2)  # (F, walkers)
        c = c_cam - boards.sum(axis=0) + boards.sum(axis=0) / s2
        c_lid = np.zeros((len(self.stems), n))  # each frame's LiDAR rows, squared and whitened
        logdet_c = np.zeros(n)
        r2 = {n: np.exp(2.0 * theta[:, k])[None, :, None] for n, k in self.r_column.items()}
        for k0, T_hat, idx, Wt, normals, offsets, scan, G, signs, E0, lam, name in self.lidar_terms:
            R, t = retract_batch(T_hat, theta[:, k0:k0 + 6])
            pi = np.empty((len(idx), n, 4))
            pi[..., :3] = np.tensordot(normals, R, axes=([1], [1]))  # R^T n
            pi[..., 3] = normals @ t.T - offsets[:, None]
            e = pi @ Wt  # (F_l, walkers, k)
            if scan:
                e /= np.hypot(pi[..., 0], pi[..., 1])[..., None]
            e = e * signs[:, None, None] + E0[:, None, :]
            if self.scaled:  # (F_l, walkers, k): each row's variance
                v = r2.get(name, 1.0) + lam[:, None, :] * s2[None, :, None]
                logdet_c += np.sum(np.log(v), axis=(0, 2))
                we = e / v
            else:
                we = e
            cl = np.einsum("fwk,fwk->fw", we, e)
            c_lid[idx] += cl
            c += cl.sum(axis=0)
            g[idx] += we @ G
        # Each board pose integrated out: H_j(s) = H_cam_j / s^2 + H_lidar_j(s).
        if self._basis is not None:
            d = 1.0 / s2[None, :, None] + self._nu[:, None, :]  # (F, walkers, 6)
            y = g @ np.swapaxes(self._basis, 1, 2)
            quad = np.sum(y * y / d, axis=2)  # (F, walkers)
            logdet_h = self._logdet_cam + np.sum(np.log(d), axis=(0, 2))
        else:
            H = self.H_cam[:, None] / s2[None, :, None, None] + self._lidar_information(s2, r2)  # (F, walkers, 6, 6)
            L = np.linalg.cholesky(H)
            z = _forward(L, g)  # g^T H^-1 g = |L^-1 g|^2
            quad = np.einsum("fwa,fwa->fw", z, z)
            logdet_h = 2.0 * np.sum(np.log(np.diagonal(L, axis1=2, axis2=3)), axis=(0, 2))
        chi2 = c - quad.sum(axis=0)
        if self.likelihood == "student-t":
            # Each frame's planes against its boards: its share of chi2 beyond the corners' own best board (the
            # camera's g^T H_cam^-1 g), k_j rows, t-distributed (the pair's ``--likelihood student-t``).
            q = np.maximum(c_lid + boards / s2[None, :] - quad, 0.0)  # (F, walkers)
            chi2 = chi2 - q.sum(axis=0) + np.sum((self.nu + self.rows[:, None]) * np.log1p(q / self.nu), axis=0)
        out = (-0.5 * chi2 - 0.5 * logdet_h - 0.5 * logdet_c
               - 6 * len(self.stems) * log_s - 0.5 * (log_s / self.prior_sd) ** 2)
        for name, k in self.r_column.items():  # each scanner's own lines' residuals at its range scale
            floors, dof = self.scan_fit[name]
            log_r = theta[:, k]
            out += -dof * log_r - 0.5 * floors * np.exp(-2.0 * log_r)
        if self.quadratic is not None:
            A, b = self.quadratic
            x = theta[:, :self.nx]
            out += -0.5 * np.sum((x @ A) * x, axis=1) + x @ b
        for name, end_set, k in self.end_sets:  # each scanner's segment ends at its pose, its outline under its prior
            R, t = retract_batch(self.T[name], theta[:, self.col[name]:self.col[name] + 6])
            Ts = np.tile(np.eye(4), (n, 1, 1))
            Ts[:, :3, :3], Ts[:, :3, 3] = R, t
            outline = self.outline_map[name] + theta[:, k:k + 4]  # sampled as its departure from the estimate
            out += end_set.log_likelihood(Ts, outline) - 0.5 * np.sum((outline / self.outline_sd) ** 2, axis=1)
        for mode_cells, a, b, k in self.cells:  # each ambiguous pair's T_a_b within its minimum k's cell
            (Ra, ta), (Rb, tb) = (self._pose_of(n, theta) for n in (a, b))
            R = np.einsum("wji,wjk->wik", Ra, Rb)
            t = np.einsum("wji,wj->wi", Ra, tb - ta)
            out = np.where(mode_cells.nearest(R, t) == k, out, -np.inf)
        return np.where(outside, -np.inf, out)

    def _pose_of(self, name: str, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Sensor ``name``'s pose in the graph's reference camera's frame at each walker's tangents."""
        if name == self.inner:
            return np.broadcast_to(np.eye(3), (len(theta), 3, 3)), np.zeros((len(theta), 3))
        return retract_batch(self.T[name], theta[:, self.col[name]:self.col[name] + 6])

    def start(self, rng: np.random.Generator, covariance: np.ndarray, walkers: int) -> np.ndarray:
        """Walkers about the graph's estimate: the poses from its covariance, ``log s`` near 0, the outline
        near its estimate (half its prior's spread), each ``log r`` within its own residuals' spread; a walker
        outside the mode's cell is moved halfway towards the estimate until it is inside."""
        start = np.zeros((walkers, self.ndim))
        start[:, :self.nx] = rng.multivariate_normal(np.zeros(self.nx), covariance, walkers)
        start[:, -1] = rng.normal(0.0, 0.05, walkers)
        for name, _, k in self.end_sets:
            start[:, k:k + 4] = rng.normal(0.0, 0.5, (walkers, 4)) * self.outline_sd
        for name, k in self.r_column.items():
            start[:, k] = rng.normal(0.0, 0.5 / np.sqrt(max(self.scan_fit[name][1], 1.0)), walkers)
        for _ in range(20):
            outside = ~np.isfinite(self(start))
            if not outside.any():
                break
            start[outside, :self.nx] *= 0.5
        return start

    def extra_sd(self) -> np.ndarray:
        """A spread for each parameter after the poses (the outline's prior's, then ``log r``'s and ``log
        s``'s prior's): :func:`laplace_at_mode`'s steps and its fallback."""
        out = np.full(self.ndim - self.nx, self.prior_sd)
        out[:4 * len(self.end_sets)] = np.tile(self.outline_sd, len(self.end_sets))
        return out


def scan_end_terms(lv: LidarViews, solution: RigSolution) -> EndTerms:
    """A scanner's segment ends in the joint graph as a single pair's refinement gives them (``EndTerms``): its ends,
    its frames' outline shifts and its outline at ``solution``, and the ends' scale."""
    k, stems = solution.names.index(lv.name), sorted(solution.T_ref_board)
    shifts = {st: np.asarray(solution.vectors.get(edge_shift_key(k, stems.index(st)), np.zeros(2)), dtype=float)
              for st in lv.edges if st in stems}
    return EndTerms(dict(lv.edges), shifts, np.asarray(solution.vectors[outline_key(k)], dtype=float),
                    float(lv.edge_scale))


def edges_quadratic(like: RigLikelihood, solution: RigSolution, cameras: list[CameraViews],
                    lidars: list[LidarViews], exact: set = frozenset(), h: float = 1e-5
                    ) -> tuple[np.ndarray, np.ndarray]:
    """The board edges' share of the log-posterior to second order about the MAP: the information they add to the
    free sensors' tangents (the graph's with them less the graph's without them, both at the MAP, each sensor's own
    outline shifts and outline marginalised; negative directions clipped) and the gradient that makes the MAP
    stationary (the planes' and corners' gradient at it, which the edges balance, by central differences of
    ``like``). The LiDARs in ``exact`` (scanners whose ends ``like`` holds by their own likelihood) keep their ends
    on both sides of the difference. Returns ``(A, b)`` for ``RigLikelihood.quadratic``."""
    from dataclasses import replace

    from .rig_graph import inner_covariance

    planes = [replace(lv, edges=None) if lv.edges and lv.name not in exact else lv for lv in lidars]
    C_p = inner_covariance(solution.names, solution.reference, cameras, planes, solution)
    A = np.linalg.inv(solution.covariance_inner) - np.linalg.inv(C_p)
    ev, V = np.linalg.eigh(0.5 * (A + A.T))
    A = ((V * np.maximum(ev, 0.0)) @ V.T)[:like.nx, :like.nx]  # the terms, when held, at their MAP
    E = np.eye(like.nx, like.ndim) * h
    f = like(np.vstack([E, -E]))
    grad = (f[:like.nx] - f[like.nx:]) / (2 * h)
    return A, -grad


# A Laplace covariance beyond these limits does not describe a posterior worth sampling: some direction is
# not determined by the data (an ensemble started there is degenerate, and emcee refuses it).
MAX_SAMPLED_ROTATION_SD_RAD = float(np.deg2rad(10.0))
MAX_SAMPLED_TRANSLATION_SD_M = 0.5
MAX_SAMPLED_CONDITION = 1e12


def unsampled_reason(covariance: np.ndarray) -> str | None:
    """Why a posterior with this Laplace covariance (GTSAM tangent) should not be sampled, or None."""
    C = np.asarray(covariance, dtype=float)
    if C.shape != (6, 6) or not np.all(np.isfinite(C)):
        return "the Laplace covariance is not finite"
    sd = np.sqrt(np.maximum(np.diag(C), 0.0))
    w = np.linalg.eigvalsh(0.5 * (C + C.T))
    if sd[:3].max() > MAX_SAMPLED_ROTATION_SD_RAD or sd[3:].max() > MAX_SAMPLED_TRANSLATION_SD_M:
        return (f"the problem is nearly degenerate (Laplace standard deviations up to {np.degrees(sd[:3].max()):.1f} "
                f"deg and {1000 * sd[3:].max():.0f} mm): the data do not determine every direction")
    if w[0] <= 0 or w[-1] / w[0] > MAX_SAMPLED_CONDITION:
        return (f"the Laplace covariance is nearly singular (condition number {w[-1] / max(w[0], 1e-300):.1e}): "
                "some direction is determined far better than the others can be sampled together")
    return None


def sample_rig_posterior(solution: RigSolution, cameras: list[CameraViews], lidars: list[LidarViews],
                         rng: np.random.Generator, min_ess: int = 1000, max_steps: int = 40000,
                         likelihood: str = "gaussian", nu: float = 4.0, cells: tuple = (),
                         exact_ends: frozenset = frozenset(), ensemble: bool = False) -> RigPosterior:
    """Sample the rig's sensor poses (module docstring) from the joint graph's MAP and measurements; a sensor whose
    Laplace covariance the data barely determine (:func:`unsampled_reason`) raises :class:`PosteriorSkippedError`.

    Parameters
    ----------
    solution : RigSolution
        The joint graph's estimate (``rig_graph.solve_rig``) from the same ``cameras`` and ``lidars``.
    cameras, lidars : list
        The views the graph was solved from.
    rng : numpy.random.Generator
        Seeds the walkers' start and the sampler.
    min_ess : int
        Effective samples wanted (of the slowest-mixing parameter).
    max_steps : int
        Steps at most.
    likelihood, nu : str, float
        ``gaussian``, or ``student-t`` with ``nu`` degrees of freedom on each frame's planes against its boards (the
        single pair's ``--likelihood``).
    cells : tuple
        For each camera-LiDAR pair whose boards leave several minima, ``(ModeCells, camera, lidar, k)``: sampled
        within minimum ``k``'s cell (:class:`RigLikelihood`), the walkers started about the estimate and the
        proposal tuned by a pilot run.
    exact_ends : frozenset
        The scanners whose segment ends enter by their own likelihood, as a single pair's do (its outline sampled
        too, the walkers started about the estimate and the proposal tuned by a pilot run), not to second order
        about the estimate: a scanner of few boards, whose ends' likelihood is far from a Gaussian's.
    ensemble : bool
        The ensemble moves alone (``PosteriorOptions.sampler`` ``ensemble``: slower to mix, for comparison) instead
        of the tuned independence proposal.

    Returns
    -------
    RigPosterior
        Samples of every sensor's pose in the reference's frame and the chain's diagnostics.
    """
    # Each LiDAR's range terms held at the MAP: their share of the poses' covariance is convolved into the samples
    # below (marginal intervals), with the terms' own samples.
    held = [hold_terms(lv, solution.range_terms[lv.name][0]) if lv.has_terms else lv for lv in lidars]
    ends = {lv.name: scan_end_terms(lv, solution) for lv in lidars if lv.name in exact_ends and lv.edges}
    like = RigLikelihood(solution, cameras, held, likelihood=likelihood, nu=nu, cells=cells, ends=ends)
    if any(lv.edges and lv.name not in ends for lv in lidars):
        like.quadratic = edges_quadratic(like, solution, cameras, lidars, set(ends))
    names = solution.names
    n_p = like.nx
    n_t = sum(lv.terms.size for lv in lidars if lv.has_terms)  # the held terms' count
    if solution.covariance_inner is not None and solution.covariance_inner.shape[0] == n_p + n_t:
        full = solution.covariance_inner  # the poses', then each ranged LiDAR's terms in the order of ``lidars``
        S_pt, S_tt = full[:n_p, n_p:], full[n_p:, n_p:]
        gain = S_pt @ np.linalg.pinv(S_tt, rcond=1e-12, hermitian=True) if n_t else np.zeros((n_p, 0))
        cov = full[:n_p, :n_p] - gain @ S_pt.T  # the poses' given the terms
    else:
        if n_t:
            raise LidarcamError("the rig's solution has no covariance of its range terms to start the posterior")
        _, cov_inner = change_reference(names, solution.T_ref, solution.covariance_joint, like.inner)
        cols = np.concatenate([np.arange(6 * names.index(n), 6 * names.index(n) + 6) for n in like.free])
        cov, S_tt, gain = cov_inner[np.ix_(cols, cols)], np.zeros((0, 0)), np.zeros((n_p, 0))
    for k, n in enumerate(like.free):  # a sensor the data barely determine: its Laplace covariance stands, said
        if (reason := unsampled_reason(cov[6 * k:6 * k + 6, 6 * k:6 * k + 6])) is not None:
            raise PosteriorSkippedError(f"{n}: {reason}", hint="the covariance is the graph's Laplace one; add board "
                                                                "poses that constrain the weak direction")
    try:
        keep, run = run_chain(like, cov, rng, min_ess, max_steps, label="rig posterior",
                              pilot=bool(cells) or bool(ends), ensemble=ensemble)
    except ValueError as exc:  # emcee refuses a degenerate ensemble or a chain without an autocorrelation time
        raise PosteriorSkippedError(f"the sampler refused the problem ({exc})",
                                    hint="the covariance is the graph's Laplace one") from exc
    m = len(keep)
    dt = rng.multivariate_normal(np.zeros(n_t), S_tt, m, method="eigh") if n_t else np.zeros((m, 0))
    keep[:, :n_p] += dt @ gain.T
    # Each sample's poses in the graph's frame, then in the rig's reference frame, as right tangents at the MAP.
    R_in, t_in = {like.inner: np.broadcast_to(np.eye(3), (m, 3, 3))}, {like.inner: np.zeros((m, 3))}
    for k, n in enumerate(like.free):
        R_in[n], t_in[n] = retract_batch(like.T[n], keep[:, 6 * k:6 * k + 6])
    ref = solution.reference
    xi = np.zeros((m, 6 * len(names)))
    for k, n in enumerate(names):
        if n == ref:
            continue
        R = np.einsum("nji,njk->nik", R_in[ref], R_in[n])
        t = np.einsum("nji,nj->ni", R_in[ref], t_in[n] - t_in[ref])
        xi[:, 6 * k:6 * k + 6] = local_batch(solution.T_ref[n], R, t)
    terms, at = {}, 0
    for lv in lidars:
        if lv.has_terms:
            terms[lv.name] = dt[:, at:at + lv.terms.size] + solution.range_terms[lv.name][0]
            at += lv.terms.size
    return RigPosterior(names, ref, dict(solution.T_ref), xi, run, terms, np.exp(keep[:, -1]), likelihood)


def mix_modes(parts: list[tuple[RigPosterior, float]], rng: np.random.Generator) -> RigPosterior:
    """The posteriors about several joint minima (``(posterior, mass)``, the estimate's first), each sampled within
    its cell, mixed by their masses as a single pair's minima are (``sampler.mixture_picks``): every sample carried
    into the first's right tangents (``T_ref_s = T_ref_s^k Exp(xi^k) = T_ref_s^1 Exp(xi)``), so the intervals and
    the covariance cover every minimum; ``mode_index`` says whose each sample is."""
    first = parts[0][0]
    picks = mixture_picks([len(p.xi) for p, _ in parts], [m for _, m in parts], len(first.xi), rng)
    xi, scale, index, terms = [], [], [], {n: [] for n in first.range_terms}
    for k, ((p, _), pick) in enumerate(zip(parts, picks)):
        x = p.xi[pick].copy()
        for j, n in enumerate(p.names):
            if n != p.reference and k > 0:
                x[:, 6 * j:6 * j + 6] = retangent_batch(p.T_ref[n], x[:, 6 * j:6 * j + 6], first.T_ref[n])
        xi.append(x)
        scale.append(p.camera_scale[pick])
        index.append(np.full(len(pick), k))
        for n in terms:
            terms[n].append(p.range_terms[n][pick])
    w = np.array([m for _, m in parts], dtype=float)
    return replace(first, xi=np.concatenate(xi), camera_scale=np.concatenate(scale),
                   range_terms={n: np.concatenate(v) for n, v in terms.items()},
                   mode_weights=tuple(float(v) for v in w / w.sum()), mode_index=np.concatenate(index),
                   mode_T_ref=tuple(dict(p.T_ref) for p, _ in parts), _pairs={}, _sensor_T={})


def laplace_at_mode(like: RigLikelihood, cov: np.ndarray, newton_steps: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """The proposal's centre and covariance over every sampled parameter: the log-posterior's mode and the inverse
    of its negative Hessian there, both by central differences (steps of a tenth of the graph's standard deviations
    ``cov`` of the poses and terms, 0.05 in ``log s``), from the graph's MAP at ``s = 1`` by Newton steps. The
    mode's ``s`` is not the graph's 1, and the poses' spread changes with it; the Laplace approximation at the
    graph's MAP would be too wide or too narrow in every direction at once (on a 6-camera rig, 49 parameters,
    the chain's autocorrelation was 170 steps with it)."""
    n = like.ndim
    h = np.append(0.1 * np.sqrt(np.diag(cov)), 0.1 * like.extra_sd())
    # Where the log-posterior is not concave, or a step leaves a mode's cell: the graph's covariance, the other
    # parameters at their priors' spread.
    fallback = np.zeros((n, n))
    fallback[:len(cov), :len(cov)] = cov
    fallback[len(cov):, len(cov):] = np.diag(like.extra_sd() ** 2)
    x0, full = np.zeros(n), None
    for _ in range(newton_steps):
        found = central_hessian(lambda pts: np.concatenate([like(pts[k:k + 256]) for k in range(0, len(pts), 256)]),
                                x0, h)  # memory: 256 points at once
        if found is None:
            break
        _, grad, H = found
        try:
            full = np.linalg.inv(-H)
            np.linalg.cholesky(full)
        except np.linalg.LinAlgError:
            return np.zeros(n), fallback
        step = full @ grad
        x0 = x0 + step
        if np.all(np.abs(step) < 0.01 * np.sqrt(np.diag(full))):
            break
    return (x0, full) if full is not None else (np.zeros(n), fallback)


def run_chain(like: RigLikelihood, cov: np.ndarray, rng: np.random.Generator, min_ess: int, max_steps: int,
              walkers: int | None = None, ensemble: bool = False, chunk: int = 500, progress: bool = False,
              label: str = "posterior", pilot: bool = False) -> tuple[np.ndarray, ChainResult]:
    """Sample ``like`` from the graph's covariance ``cov`` of its poses and terms: each coordinate's power of ``s``
    fitted (``RigLikelihood.fit_alpha``), the proposal at the joint mode (:func:`laplace_at_mode`), the chain run
    (``sampler.run_with_proposal``; ``ensemble``: its ensemble moves alone). ``pilot``, for a posterior the Laplace
    approximation describes poorly (a 2D pair's curved valley and segment ends, a mode within its cell): the walkers
    start about the graph's estimate (:meth:`RigLikelihood.start`) and a pilot run gives the proposal its centre,
    covariance and heavier tails. Returns the samples kept (at most ``MAX_KEPT``, thinned
    evenly, in the poses' tangents: ``RigLikelihood.to_poses``) and the chain."""
    cov = 0.5 * (cov + cov.T)
    walkers = walkers or max(64, 2 * like.ndim + 16)
    if pilot:  # about the graph's estimate, in the poses' own tangents
        start = like.start(rng, cov, walkers)
    else:
        like.fit_alpha(np.sqrt(np.diag(cov)))
        centre, cov = laplace_at_mode(like, cov)
        start = rng.multivariate_normal(centre, 0.25 * cov, walkers)
    if ensemble:
        run = run_ensemble(like, start, rng, min_ess, max_steps, chunk, progress, label)
    elif pilot:
        run = run_with_proposal(like, start, rng, None, min_ess, max_steps, chunk, progress, label)
    else:
        run = run_with_proposal(like, start, rng, cov, min_ess, max_steps, chunk, progress, label, centre=centre)
    keep = like.to_poses(run.samples[np.linspace(0, len(run.samples) - 1,
                                                 min(MAX_KEPT, len(run.samples))).astype(int)])
    return keep, run


def hold_terms(lidar: LidarViews, values: np.ndarray) -> LidarViews:
    """The LiDAR's views with its range terms held at ``values`` (their residual's constant part), no longer
    parameters: how every posterior takes them (a rig's and a pair's), their share convolved in by the caller."""
    beta = np.asarray(values, dtype=float)
    return replace(lidar, terms=None, terms_prior_sd=None,
                   ranged={st: replace(fw, e0=fw.e0 + fw.W_nuisance @ beta) for st, fw in lidar.ranged.items()})
