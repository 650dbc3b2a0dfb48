"""A moving board's joint problem: every image's board pose, the extrinsic and the clocks' offset as unknowns.

Each image's board pose is a knot of the board's trajectory, held by its own measurement (the pose the corners
give, with its covariance: ``CameraBoardObservation.pose_covariance``); between knots the pose is a local cubic
(Hermite, tangents from the neighbouring knots, the rotation in a chart at the interval's first knot), so each
LiDAR return depends on the four knots about its time. A return's residual is its range less the range along its
beam to the board's plane at its time plus the offset (``clock_offset``), over the range noise.
Each image's stamp jitter (read from the stamps' spacing) grows its pose's covariance by its velocity; each sweep's
stamp jitter is a time nuisance of its own, shared by its returns, with that jitter as its prior. Solved by
Gauss-Newton from the two-step estimate (the knots at their measured poses), the Jacobian by forward differences
(the knots four apart perturbed together: a return sees one of them), the normal equations sparse; the extrinsic
and offset's covariance is their block of the inverse, so it carries the camera's pose noise with the LiDAR's.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu
from scipy.spatial.transform import Rotation

from geometry.rotations import T_exp, T_inverse, T_retract, exp_batch, log_batch

# Gauss-Newton steps at most; it has converged when the extrinsic's and offset's step is below this share of
# their standard deviations (the large residuals of a moving board make its convergence linear).
MAX_STEPS = 8
CONVERGED = 0.05
# Forward-difference step (radians, metres, seconds).
H = 1e-6


class Knots:
    """The board's trajectory through knot poses ``K`` (n, 4, 4) at increasing ``tau`` (s): local cubic between
    knots (see the module)."""

    def __init__(self, tau: np.ndarray, K: np.ndarray):
        self.tau, self.K = tau, K
        self._chart = None

    def _charts(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """For each interval k (1 .. n-3; the others zero): Log(R_k^T R_j) for j = k-1, k+1, k+2."""
        if self._chart is None:
            R = self.K[:, :3, :3]
            n = len(R)
            k = np.arange(1, n - 2)
            Rt = np.transpose(R[k], (0, 2, 1))
            out = []
            for j in (k - 1, k + 1, k + 2):
                a = np.zeros((n, 3))
                a[k] = Rotation.from_matrix(Rt @ R[j]).as_rotvec()
                out.append(a)
            self._chart = tuple(out)
        return self._chart

    def interval(self, t: np.ndarray) -> np.ndarray:
        """Each time's interval ``k`` (t in [tau_k, tau_k+1]); its four knots are k-1 .. k+2."""
        return np.clip(np.searchsorted(self.tau, t, side="right") - 1, 1, len(self.tau) - 3)

    def poses(self, t: np.ndarray, k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rotations (m, 3, 3) and translations (m, 3) at times ``t`` in intervals ``k``."""
        tau, K = self.tau, self.K
        h = tau[k + 1] - tau[k]
        u = ((t - tau[k]) / h)[:, None]
        u2, u3 = u ** 2, u ** 3  # the cubic Hermite basis
        h00, h10, h01, h11 = 2 * u3 - 3 * u2 + 1, u3 - 2 * u2 + u, -2 * u3 + 3 * u2, u3 - u2
        p = K[:, :3, 3]
        m0 = (p[k + 1] - p[k - 1]) / (tau[k + 1] - tau[k - 1])[:, None]
        m1 = (p[k + 2] - p[k]) / (tau[k + 2] - tau[k])[:, None]
        trans = h00 * p[k] + h10 * h[:, None] * m0 + h01 * p[k + 1] + h11 * h[:, None] * m1
        charts = self._charts()  # per interval: the neighbours' rotation vectors in its first knot's chart
        r_prev, r_next, r_next2 = charts[0][k], charts[1][k], charts[2][k]
        n0 = (r_next - r_prev) / (tau[k + 1] - tau[k - 1])[:, None]
        n1 = r_next2 / (tau[k + 2] - tau[k])[:, None]
        r = h10 * h[:, None] * n0 + h01 * r_next + h11 * h[:, None] * n1
        Rk = K[k, :3, :3]
        return Rk @ Rotation.from_rotvec(r).as_matrix(), trans


def along_beam_residuals(T: np.ndarray, R_cb: np.ndarray, o_cb: np.ndarray, ranges: np.ndarray,
                         beams: np.ndarray) -> np.ndarray:
    """Each return's range less the range along its beam (unit ``beams``, LiDAR frame) to its board's plane, the
    board at rotations ``R_cb`` (m, 3, 3) and origins ``o_cb`` (m, 3) in the camera, mapped by ``T`` =
    ``T_camera_lidar`` (m). Along the beam, as the LiDAR errs: a point-to-plane distance would take the noisy
    point into its own Jacobian, which biases the estimate by a share of the range variance that more data do not
    shrink."""
    n_c = R_cb[:, :, 2]
    along = np.einsum("ni,ni->n", n_c @ T[:3, :3], beams)  # (R^T n_c) . u
    with np.errstate(divide="ignore", invalid="ignore"):
        predicted = np.einsum("ni,ni->n", n_c, o_cb - T[:3, 3]) / along
    return np.where(np.abs(along) > 1e-3, ranges - predicted, 0.0)


def _lidar_residuals(T: np.ndarray, dt: float, knots: Knots, ranges: np.ndarray, beams: np.ndarray,
                     times: np.ndarray, k: np.ndarray) -> np.ndarray:
    """:func:`along_beam_residuals` with the board where the knots put it at each return's time plus ``dt``."""
    return along_beam_residuals(T, *knots.poses(times + dt, k), ranges, beams)


def _exp_all(xi: np.ndarray) -> np.ndarray:
    """``Exp(xi_i)`` of each row of (n, 6) ``xi``, (n, 4, 4)."""
    R, t = exp_batch(xi)
    out = np.zeros((len(xi), 4, 4))
    out[:, :3, :3], out[:, :3, 3], out[:, 3, 3] = R, t, 1.0
    return out


def stamp_jitter_s(stamps_s: np.ndarray) -> float:
    """A free-running sensor's stamp jitter (s): the spread of its stamps' spacing about the median period, over
    the spacings within half a period of it (a skipped frame is no jitter), robustly (MAD), as sqrt(2) stamps'."""
    d = np.diff(np.sort(np.asarray(stamps_s, dtype=float)))
    if len(d) < 3:
        return 0.0
    period = float(np.median(d))
    d = d[np.abs(d - period) < 0.5 * period]
    return float(1.4826 * np.median(np.abs(d - np.median(d))) / np.sqrt(2)) if len(d) >= 3 else 0.0


def with_stamp_jitter(tau: np.ndarray, K: np.ndarray, K_cov: np.ndarray, jitter_s: float) -> np.ndarray:
    """The knots' covariances grown by their stamps' jitter: a pose stamped ``jitter_s`` off its instant is off by
    its velocity times that (the velocity from the neighbouring knots, in the knot's right tangent)."""
    if jitter_s <= 0 or len(tau) < 3:
        return K_cov
    v = np.zeros((len(tau), 6))
    i = np.arange(1, len(tau) - 1)
    rel = np.einsum("nij,njk->nik", np.array([T_inverse(k) for k in K[i - 1]]), K[i + 1])
    v[i] = log_batch(rel[:, :3, :3], rel[:, :3, 3]) / (tau[i + 1] - tau[i - 1])[:, None]
    v[0], v[-1] = v[1], v[-2]
    return K_cov + jitter_s ** 2 * np.einsum("ni,nj->nij", v, v)


def refine_jointly(tau: np.ndarray, K0: np.ndarray, K_cov: np.ndarray, points: np.ndarray, times: np.ndarray,
                   T0: np.ndarray, dt0: float, sigma_r: float, free_offset: bool = True,
                   sweep: np.ndarray | None = None, sweep_jitter_s: float = 0.0
                   ) -> tuple[np.ndarray, float, np.ndarray, np.ndarray, np.ndarray]:
    """The joint solve (see the module) from knots ``K0`` (n, 4, 4) at ``tau`` with covariances ``K_cov`` (n, 6, 6),
    returns ``points`` (m, 3) at ``times`` (the LiDAR's clock; each within the knots' span less the offset's
    reach), and the start ``T0``, ``dt0``; ``sigma_r`` the returns' range noise (m). ``sweep``: each return's
    sweep (0 ..), whose stamp is off its instant by a Gaussian of ``sweep_jitter_s`` shared by its returns: one
    time nuisance per sweep with that prior (none when 0). Returns ``T_camera_lidar``, the offset, the 7x7
    covariance over ``[rot; trans; offset]`` (offset's row and column 0 when held), and where the solve left the
    knots (n, 4, 4) and each return's time nuisance (m,) (s): the board's trajectory at the joint estimate."""
    n, m = len(tau), len(points)
    ranges = np.linalg.norm(points, axis=1)
    beams = points / ranges[:, None]
    W = np.linalg.cholesky(np.linalg.inv(K_cov)).transpose(0, 2, 1)  # W^T W = C^-1: whitened prior W xi
    K = K0.copy()
    K0_inv = np.array([T_inverse(k0) for k0 in K0])
    T, dt = T0, dt0
    n_glob = 7 if free_offset else 6
    n_s = int(sweep.max()) + 1 if sweep is not None and sweep_jitter_s > 0 else 0
    cols = 6 * n + n_s + n_glob  # knots, sweeps' time nuisances, extrinsic and offset
    g0 = 6 * n + n_s
    shift_s = np.zeros(n_s)  # each sweep's time nuisance (s)
    shift = np.zeros(m)  # each return's sweep's
    for _ in range(MAX_STEPS):
        rel = K0_inv @ K
        xi = log_batch(rel[:, :3, :3], rel[:, :3, 3])  # each knot's move from its measured pose
        knots = Knots(tau, K)
        times_now = times + shift
        k = knots.interval(times_now + dt)
        r0 = _lidar_residuals(T, dt, knots, ranges, beams, times_now, k) / sigma_r
        prior = np.einsum("nij,nj->ni", W, xi).ravel()
        rows, cidx, vals = [], [], []
        base = r0 * sigma_r
        # the extrinsic's and the offset's columns: every return (forward differences)
        d_time = None
        for c in range(7):
            e = np.zeros(7)
            e[c] = H
            plus = _lidar_residuals(T_retract(T, e[:6]), dt + e[6], knots, ranges, beams, times_now, k)
            col = (plus - base) / (H * sigma_r)
            if c == 6:
                d_time = col  # a return's residual against its time: its sweep's nuisance's column too
            if c < n_glob:
                rows.append(np.arange(m))
                cidx.append(np.full(m, g0 + c))
                vals.append(col)
        if n_s:
            rows.append(np.arange(m))
            cidx.append(6 * n + sweep)
            vals.append(d_time)
        # the knots' columns: knots four apart perturbed together, each return's change put on its one knot
        for colour in range(4):
            chosen = np.arange(colour, n, 4)
            which = k - 1 + np.mod(colour - (k - 1), 4)  # the return's knot among k-1 .. k+2 of this colour
            for d in range(6):
                e = np.zeros(6)
                e[d] = H
                Kp = K.copy()
                Kp[chosen] = K[chosen] @ T_exp(e)
                plus = _lidar_residuals(T, dt, Knots(tau, Kp), ranges, beams, times_now, k)
                rows.append(np.arange(m))
                cidx.append(6 * which + d)
                vals.append((plus - base) / (H * sigma_r))
        J_l = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cidx))), shape=(m, cols))
        # the knots' priors: W_i xi_i (a knot's perturbation K Exp(e) moves its xi by e, to first order in xi)
        pr = np.repeat(np.arange(6 * n), 6)
        pc = 6 * np.repeat(np.arange(n), 36) + np.tile(np.arange(6), 6 * n)
        J_p = sp.csr_matrix((W.reshape(-1), (pr, pc)), shape=(6 * n, cols))
        nuisance = shift_s / sweep_jitter_s if n_s else np.zeros(0)
        J_s = sp.csr_matrix((np.full(n_s, 1.0 / sweep_jitter_s) if n_s else np.zeros(0),
                             (np.arange(n_s), 6 * n + np.arange(n_s))), shape=(n_s, cols))
        J = sp.vstack([J_l, J_p, J_s]).tocsc()
        r = np.concatenate([r0, prior, nuisance])
        Hm = (J.T @ J).tocsc()
        lu = splu(Hm)
        step = -lu.solve(J.T @ r)
        K = K @ _exp_all(step[:6 * n].reshape(n, 6))
        if n_s:
            shift_s = shift_s + step[6 * n:g0]
            shift = shift_s[sweep]
        T = T_retract(T, step[g0:g0 + 6])
        if free_offset:
            dt = dt + float(step[-1])
        E = np.zeros((cols, n_glob))
        E[g0:, :] = np.eye(n_glob)
        glob_cov = lu.solve(E)[g0:, :]
        if np.all(np.abs(step[g0:]) < CONVERGED * np.sqrt(np.diag(glob_cov))):
            break
    cov = np.zeros((7, 7))
    cov[:n_glob, :n_glob] = glob_cov
    return T, dt, cov, K, shift
