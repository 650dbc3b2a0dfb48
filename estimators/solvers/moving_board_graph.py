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
Several LiDARs on one camera are one problem: the knots shared, each LiDAR's extrinsic, offset and sweeps' nuisances
its own, so the covariance holds what the shared board poses make common to their estimates.
"""
from __future__ import annotations

from dataclasses import dataclass

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


@dataclass(frozen=True, eq=False)
class LidarBlock:
    """One LiDAR's part of the joint solve: its returns (``points``, its frame) at ``times`` (its clock, in the
    knots' time base less its offset), its start ``T0`` (``T_camera_lidar``) and ``dt0``, its range noise
    ``sigma_r`` (m), each return's ``sweep`` (0 ..; None: no sweep nuisances) and the sweeps' stamp jitter (s)."""

    points: np.ndarray
    times: np.ndarray
    T0: np.ndarray
    dt0: float
    sigma_r: float
    sweep: np.ndarray | None = None
    sweep_jitter_s: float = 0.0


def refine_many(tau: np.ndarray, K0: np.ndarray, K_cov: np.ndarray, blocks: list[LidarBlock],
                free_offset: bool = True) -> tuple[list, list, np.ndarray, np.ndarray, list]:
    """The joint solve (see the module) of one or several LiDARs on one board trajectory, from knots ``K0`` (n, 4,
    4) at ``tau`` with covariances ``K_cov`` (n, 6, 6) and each LiDAR's ``blocks`` (its returns within the knots'
    span less its offset's reach, its start, its range noise; a return's sweep's stamp off its instant by a
    Gaussian of the sweeps' jitter shared by its returns: one time nuisance per sweep with that prior, none when
    0): each LiDAR's extrinsic and offset, the knots and the sweeps' time nuisances as unknowns. Returns each
    LiDAR's ``T_camera_lidar`` and offset, the joint covariance over
    each LiDAR's ``[rot; trans; offset]`` in turn (7 per LiDAR; an offset's row and column 0 when held: the LiDARs
    share the camera's board poses, so their estimates correlate), the knots where the solve left them and each
    LiDAR's returns' time nuisances (s)."""
    n, L = len(tau), len(blocks)
    ranges = [np.linalg.norm(b.points, axis=1) for b in blocks]
    beams = [b.points / r[:, None] for b, r in zip(blocks, ranges)]
    sizes = [len(b.points) for b in blocks]
    row0 = np.concatenate([[0], np.cumsum(sizes)])
    W = np.linalg.cholesky(np.linalg.inv(K_cov)).transpose(0, 2, 1)  # W^T W = C^-1: whitened prior W xi
    K = K0.copy()
    K0_inv = np.array([T_inverse(k0) for k0 in K0])
    Ts, dts = [b.T0 for b in blocks], [float(b.dt0) for b in blocks]
    n_glob = 7 if free_offset else 6
    n_s = [int(b.sweep.max()) + 1 if b.sweep is not None and b.sweep_jitter_s > 0 else 0 for b in blocks]
    s0 = 6 * n + np.concatenate([[0], np.cumsum(n_s)])  # each LiDAR's first sweep nuisance's column
    g0 = int(s0[-1])  # then each LiDAR's extrinsic and offset, n_glob columns each
    cols = g0 + n_glob * L
    shift_s = [np.zeros(k) for k in n_s]  # each sweep's time nuisance (s)
    shift = [np.zeros(m) for m in sizes]  # each return's sweep's
    for _ in range(MAX_STEPS):
        rel = K0_inv @ K
        xi = log_batch(rel[:, :3, :3], rel[:, :3, 3])  # each knot's move from its measured pose
        knots = Knots(tau, K)
        rows, cidx, vals, r0, base, ks = [], [], [], [], [], []
        for j, b in enumerate(blocks):
            times_now = b.times + shift[j]
            k = knots.interval(times_now + dts[j])
            res = _lidar_residuals(Ts[j], dts[j], knots, ranges[j], beams[j], times_now, k)
            r0.append(res / b.sigma_r)
            base.append(res)
            ks.append(k)
            here = row0[j] + np.arange(sizes[j])
            # the extrinsic's and the offset's columns: every return (forward differences)
            d_time = None
            for c in range(7):
                e = np.zeros(7)
                e[c] = H
                plus = _lidar_residuals(T_retract(Ts[j], e[:6]), dts[j] + e[6], knots, ranges[j], beams[j],
                                        times_now, k)
                col = (plus - res) / (H * b.sigma_r)
                if c == 6:
                    d_time = col  # a return's residual against its time: its sweep's nuisance's column too
                if c < n_glob:
                    rows.append(here)
                    cidx.append(np.full(sizes[j], g0 + n_glob * j + c))
                    vals.append(col)
            if n_s[j]:
                rows.append(here)
                cidx.append(s0[j] + b.sweep)
                vals.append(d_time)
        # the knots' columns: knots four apart perturbed together, each return's change put on its one knot
        for colour in range(4):
            chosen = np.arange(colour, n, 4)
            for d in range(6):
                e = np.zeros(6)
                e[d] = H
                Kp = K.copy()
                Kp[chosen] = K[chosen] @ T_exp(e)
                moved = Knots(tau, Kp)
                for j, b in enumerate(blocks):
                    k = ks[j]
                    which = k - 1 + np.mod(colour - (k - 1), 4)  # the return's knot among k-1 .. k+2 of this colour
                    plus = _lidar_residuals(Ts[j], dts[j], moved, ranges[j], beams[j], b.times + shift[j], k)
                    rows.append(row0[j] + np.arange(sizes[j]))
                    cidx.append(6 * which + d)
                    vals.append((plus - base[j]) / (H * b.sigma_r))
        J_l = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cidx))),
                            shape=(int(row0[-1]), cols))
        # the knots' priors: W_i xi_i (a knot's perturbation K Exp(e) moves its xi by e, to first order in xi)
        pr = np.repeat(np.arange(6 * n), 6)
        pc = 6 * np.repeat(np.arange(n), 36) + np.tile(np.arange(6), 6 * n)
        J_p = sp.csr_matrix((W.reshape(-1), (pr, pc)), shape=(6 * n, cols))
        jit = [np.full(k, 1.0 / b.sweep_jitter_s) if k else np.zeros(0) for k, b in zip(n_s, blocks)]
        nuisance = np.concatenate([sh / b.sweep_jitter_s if len(sh) else sh for sh, b in zip(shift_s, blocks)])
        J_s = sp.csr_matrix((np.concatenate(jit), (np.arange(g0 - 6 * n), 6 * n + np.arange(g0 - 6 * n))),
                            shape=(g0 - 6 * n, cols))
        J = sp.vstack([J_l, J_p, J_s]).tocsc()
        r = np.concatenate(r0 + [np.einsum("nij,nj->ni", W, xi).ravel(), nuisance])
        Hm = (J.T @ J).tocsc()
        lu = splu(Hm)
        step = -lu.solve(J.T @ r)
        K = K @ _exp_all(step[:6 * n].reshape(n, 6))
        for j, b in enumerate(blocks):
            if n_s[j]:
                shift_s[j] = shift_s[j] + step[s0[j]:s0[j + 1]]
                shift[j] = shift_s[j][b.sweep]
            g = g0 + n_glob * j
            Ts[j] = T_retract(Ts[j], step[g:g + 6])
            if free_offset:
                dts[j] = dts[j] + float(step[g + 6])
        E = np.zeros((cols, n_glob * L))
        E[g0:, :] = np.eye(n_glob * L)
        glob_cov = lu.solve(E)[g0:, :]
        if np.all(np.abs(step[g0:]) < CONVERGED * np.sqrt(np.diag(glob_cov))):
            break
    cov = np.zeros((7 * L, 7 * L))
    at = np.concatenate([7 * j + np.arange(n_glob) for j in range(L)])
    cov[np.ix_(at, at)] = glob_cov
    return Ts, dts, cov, K, shift
