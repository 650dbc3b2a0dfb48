"""The board's edges as a check of an estimate that did not use them (every 3D result with a known board size).

Planes fix the translation only along the boards' normals, so an estimate from planes alone can sit centimetres
off along the boards while its planes fit. Each LiDAR ring stops at the board's outline, which the camera places
(``solvers.board_edges``): under a right extrinsic the outlines the rings draw sit on the camera's. Here the ends
are not in the estimate; they test it.

Per frame, the shift ``s_j`` (board axes) of the outline that its ring ends call for, with the dataset's growth
of the x and y sides ``g`` (prior 0 +- ``GROWTH_PRIOR_SD_M``: a beam footprint makes the board look larger) fitted
with them over all frames, robustly (``board_edges.end_loss``: an end hidden before its side stops pulling). The
pattern's offset on the board is not fitted: a wrong ``board.pattern_offset`` is one of the things the check is
for, and it shifts every frame alike.

The mean shift in camera axes ``m = sum_j B_j s_j / n`` (``B_j`` the board's x and y axes) has, if the estimate
and the outline are right, zero mean and covariance

    C = M (Cov_ends + tau^2 I) M^T + M G Sigma G^T M^T,

the ends' own (their standard deviations scaled by their scatter when it exceeds the model's), the boards'
in-plane scatter ``tau`` (a board that sways between the exposure and the sweep; method of moments about the
mean), and the estimate's joint covariance ``Sigma`` (the extrinsic and the board poses) carried by the fit's
sensitivity ``G`` to them (first order). The ends are independent of the planes that made the estimate, so the
terms add. A mean beyond its 99% limit says the estimate and the edges disagree: a wrong ``board.size`` or
``board.pattern_offset``, or an extrinsic the edges contradict (``--edges`` then uses them).
"""
from __future__ import annotations

import numpy as np

from geometry.board import BoardModel

from . import chi_square as chi2
from .board_edges import EDGE_HUBER, GROWTH_PRIOR_SD_M, OFFSET_PRIOR_SD_M, EdgeCrossings, edge_residuals, end_loss, \
    nuisance_jacobians

# A weak prior on each frame's shift (m), which only holds a direction its ends leave open (every ring crossing
# sides of one direction, as level rings on an upright board do); such directions are left out of the test.
SHIFT_PRIOR_SD_M = 1.0
# Bound of the boards' in-plane scatter (m): beyond it a shift is not a board that swayed.
MAX_SCATTER_M = 0.05
# The test's level: a mean beyond this tail probability is warned about.
CHECK_P = 0.01


def _fit(r0: np.ndarray, A: np.ndarray, sd: np.ndarray, prior_sd: np.ndarray, iterations: int = 30
         ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Robust Gauss-Newton for ``theta`` in ``r = r0 + A theta`` under ``end_loss`` with a zero-mean Gaussian
    prior: ``theta``, the whitened Jacobian ``J`` at it (prior rows last) and each end's ``de/dr``.

    It starts from the plain least-squares fit: inward, ``end_loss`` stops pulling an end a few standard
    deviations inside its side (it may have been hidden), so from ``theta = 0`` a side that every end sees
    inside (a board.size too large in dataset.yaml) gives no gradient, and a frame's shift could run off to where
    none of its ends pulls."""
    from scipy import sparse  # here: scipy.sparse, rarely needed
    P = np.diag(1.0 / prior_sd)
    As = sparse.csr_matrix(A)  # each end touches its sides' growth and its frame's shift: 4 of the columns
    p2 = 1.0 / prior_sd**2

    def solve(w, e, theta):  # the step from the normal equations of rows w * A (residuals e) and the prior's
        N = (As.T @ As.multiply(w[:, None] ** 2)).toarray() + np.diag(p2)
        return np.linalg.solve(N, -(As.T @ (w * e) + p2 * theta))

    theta = solve(1.0 / sd, r0 / sd, np.zeros(A.shape[1]))
    for _ in range(iterations):
        e, f = end_loss(r0 + As @ theta, sd)
        step = solve(f, e, theta)
        theta = theta + step
        if np.max(np.abs(step)) < 1e-7:
            break
    e, f = end_loss(r0 + A @ theta, sd)
    return theta, np.vstack([f[:, None] * A, P]), f


def shift_fit(T_camera_lidar: np.ndarray, boards: list, edges: list[EdgeCrossings], board: BoardModel,
              scale: float | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """The growth of the x and y sides and each frame's outline shift (board axes), ``theta = [g; s_1; ...; s_n]``
    (m), fitted robustly to the frames' ends under ``T_camera_lidar`` and the board poses ``boards``; its
    covariance; its sensitivity ``G = d theta / d (xi_extrinsic, xi_board_1, ...)`` (right tangents, first order);
    and the ends' scale (their scatter about the fit against their standard deviations, never below 1; estimated
    when ``scale`` is None)."""
    n = len(edges)
    rows = np.cumsum([0] + [e.size for e in edges])
    K, dim = rows[-1], 2 + 2 * n
    r0, A, D = np.zeros(K), np.zeros((K, dim)), np.zeros((K, 6 + 6 * n))
    for j, (Tb, e) in enumerate(zip(boards, edges)):
        sl = slice(rows[j], rows[j + 1])
        r0[sl], D[sl, :6], D[sl, 6 + 6 * j:12 + 6 * j] = edge_residuals(T_camera_lidar, Tb, e, board)
        H_g, H_s = nuisance_jacobians(e)
        A[sl, :2], A[sl, 2 + 2 * j:4 + 2 * j] = H_g, H_s
    sd0 = np.concatenate([e.sd_m for e in edges])
    prior_sd = np.concatenate([[GROWTH_PRIOR_SD_M] * 2, [SHIFT_PRIOR_SD_M] * (2 * n)])
    fixed = scale is not None
    scale = scale if fixed else 1.0
    for _ in range(0 if fixed else 4):
        theta, J, f = _fit(r0, A, scale * sd0, prior_sd)
        # Those within twice the Huber threshold count (quasi-likelihood).
        z = (r0 + A @ theta) / sd0
        core = np.abs(z) <= 2 * EDGE_HUBER * scale
        new = max(1.0, float(np.sqrt(np.sum(z[core] ** 2) / max(core.sum() - dim, 1)))) if core.sum() > dim + 10 \
            else 1.0
        converged = abs(np.log(new / scale)) < 0.02
        scale = new
        if converged:
            break
    theta, J, f = _fit(r0, A, scale * sd0, prior_sd)
    cov_theta = np.linalg.inv(J.T @ J)
    # At the optimum J^T e = 0 with e = e(r), de/dr = f, r = r0(x) + A theta: d theta / dx = -(J^T J)^-1 J^T f D.
    G = -cov_theta @ (J[:K].T @ (f[:, None] * D))
    return theta, cov_theta, G, scale


def outline_check(T_camera_lidar: np.ndarray, boards: list, edges: list[EdgeCrossings], board: BoardModel,
                  names: list[str], cov_joint: np.ndarray) -> tuple[dict, list[str]]:
    """The check (module docstring) for frames ``names`` with their board poses ``boards`` (``T_camera_board``)
    and ends ``edges`` (each with at least one end), under ``T_camera_lidar`` whose joint covariance with the
    board poses is ``cov_joint`` (6 + 6n, the extrinsic then each board, right tangents). Returns the record for
    calibration.json (``board_edges`` with ``used`` False) and its warnings."""
    n = len(edges)
    K, dim = sum(e.size for e in edges), 2 + 2 * n
    theta, cov_theta, G, scale = shift_fit(T_camera_lidar, boards, edges, board)
    # The mean in camera axes over the board axes each frame's ends measure (a side no ring crosses leaves its
    # axis to the prior, which says nothing).
    M = np.zeros((3, dim))
    shifts = theta[2:].reshape(n, 2)
    seen = []
    for j, Tb in enumerate(boards):
        ev, V = np.linalg.eigh(cov_theta[2 + 2 * j:4 + 2 * j, 2 + 2 * j:4 + 2 * j])
        seen.append((ev[ev < MAX_SCATTER_M**2], V[:, ev < MAX_SCATTER_M**2]))
        M[:, 2 + 2 * j:4 + 2 * j] = Tb[:3, :2] @ seen[j][1] @ seen[j][1].T / n
    mean = M @ theta
    estimate = G @ cov_joint @ G.T
    # The boards' in-plane scatter ``tau`` about the mean (method of moments over the board axes the ends
    # measure): each frame's deviation from the mean, d_j = Q_j theta, has E|d_j|^2 = tr(Q_j (Cov_ends +
    # Cov_estimate) Q_j^T) + tau^2 tr(Q_j Q_j^T) (the shifts' part).
    unit = np.zeros((dim, dim))
    unit[2:, 2:] = np.eye(2 * n)
    observed, expected, per_unit = 0.0, 0.0, 0.0
    for j, Tb in enumerate(boards):
        V = seen[j][1]
        Q = -V.T @ Tb[:3, :2].T @ M
        Q[:, 2 + 2 * j:4 + 2 * j] += V.T
        d = Q @ theta
        observed += float(d @ d)
        expected += float(np.trace(Q @ (cov_theta + estimate) @ Q.T))
        per_unit += float(np.trace(Q @ unit @ Q.T))
    tau = float(np.clip(np.sqrt(max(observed - expected, 0.0) / max(per_unit, 1e-12)), 0.0, MAX_SCATTER_M))
    S = tau**2 * unit
    C = M @ (cov_theta + S + estimate) @ M.T
    d2, dof = chi2.mahalanobis(mean, C, max_var=MAX_SCATTER_M**2)
    p = float(chi2.sf(d2, dof)) if dof else 1.0
    frame_cov = cov_theta + estimate
    per_frame = []
    for j, (nm, e) in enumerate(zip(names, edges)):
        sd = np.sqrt(np.diag(frame_cov[2 + 2 * j:4 + 2 * j, 2 + 2 * j:4 + 2 * j]))
        known = sd < MAX_SCATTER_M  # a board axis no end crosses has no shift (None)
        per_frame.append({"frame": nm, "ends": int(e.size),
                          "shift_board_xy_m": [float(v) if k else None for v, k in zip(shifts[j], known)],
                          "shift_sd_m": [float(v) if k else None for v, k in zip(sd, known)]})
    # The mean shift in board axes, over the frames whose ends measure each axis: a pattern placed off where
    # dataset.yaml says shifts every frame alike along the board's own axes.
    board_mean = [float(np.mean(v)) if (v := [f["shift_board_xy_m"][k] for f in per_frame
                                               if f["shift_board_xy_m"][k] is not None]) else None for k in (0, 1)]
    growth, growth_sd = theta[:2], np.sqrt(np.diag(cov_theta[:2, :2] + estimate[:2, :2]))
    record = {"used": False, "ends": int(K), "end_scale": scale, "board_scatter_in_plane_m": tau,
              "growth_m": growth.tolist(), "growth_sd_m": growth_sd.tolist(), "frames": per_frame,
              "mean_shift_camera_m": mean.tolist(), "mean_shift_covariance": C.tolist(), "mean_shift_d2": d2,
              "mean_shift_dof": dof, "mean_shift_p_value": p,
              "mean_shift_board_xy_m": board_mean}
    return record, outline_warnings(record, used=False)


def outline_warnings(record: dict, used: bool, beside_edges: bool = False) -> list[str]:
    """The warnings of a board-edges record (``outline_check``'s, or the refinement's with the edges ``used``):
    the outlines' mean shift beyond its 99% limit, the sides' growth and (with the edges) the outline's offset
    beyond their priors and 99% intervals. ``beside_edges``: ``outline_check``'s record of the planes-only
    estimate made beside one with the edges (its shift alone is warned of, as the planes')."""
    warnings = []
    mean, p = np.array(record["mean_shift_camera_m"]), record["mean_shift_p_value"]
    shifted = bool(record["mean_shift_dof"]) and p < CHECK_P
    if beside_edges:
        return [f"board edges: under the planes alone, the LiDAR's board outlines sit "
                f"{1000 * np.linalg.norm(mean):.0f} mm off the camera's on average (beyond the 99% limit, p = "
                f"{p:.2g}): a wrong board.pattern_offset or board.size in dataset.yaml, which also pulls the "
                "estimate with the edges, or planes the edges contradict"] if shifted else []
    if shifted:
        along = "".join(f", {1000 * v:+.0f} mm along the board's {a}" for a, v in
                        zip("xy", record.get("mean_shift_board_xy_m") or (None, None)) if v is not None)
        why = ("an extrinsic the edges contradict" if used else
               f"a wrong board.pattern_offset or board.size in dataset.yaml (on average{along[1:]}), or an "
               "extrinsic the board's edges contradict (the planes leave the translation along the boards weak; "
               "--edges uses the edges)")
        warnings.append(f"board edges: the LiDAR's board outlines sit {1000 * np.linalg.norm(mean):.0f} mm off the "
                        f"camera's on average (camera axes {np.round(1000 * mean, 1).tolist()} mm; beyond the 99% "
                        f"limit, p = {p:.2g}): {why}")
    g, gs = np.array(record["growth_m"]), np.array(record["growth_sd_m"])
    if np.any(np.abs(g) > np.maximum(GROWTH_PRIOR_SD_M, 2.576 * gs)):
        warnings.append(f"board edges: the LiDAR sees the board {2000 * g[0]:+.0f} mm wider and {2000 * g[1]:+.0f} mm "
                        "taller than board.size: check the size in dataset.yaml (the backing board's, not the "
                        "pattern's)")
    if used:
        o, os_ = np.array(record["outline_offset_m"]), np.array(record["outline_offset_sd_m"])
        if np.any(np.abs(o) > np.maximum(OFFSET_PRIOR_SD_M, 2.576 * os_)):
            warnings.append(f"board edges: the board's outline sits {1000 * o[0]:+.0f} mm along its x and "
                            f"{1000 * o[1]:+.0f} mm along its y from where dataset.yaml puts it: check "
                            "board.pattern_offset (the board corner to the pattern's corner) and board.size")
    return warnings


def outline_shift_words(record: dict, ends: bool = False) -> str:
    """A board-edges record's mean shift (camera axes, mm) with its standard deviations and p-value, in words
    (and its ring ends' count)."""
    m = 1000 * np.array(record["mean_shift_camera_m"])
    sd = 1000 * np.sqrt(np.maximum(np.diag(np.array(record["mean_shift_covariance"])), 0.0))
    return (" ".join(f"{v:+.1f}+-{e:.1f}" for v, e in zip(m, sd)) + f" mm off the camera's on average (p = "
            f"{record['mean_shift_p_value']:.2g}" + (f", {record['ends']} ring ends)" if ends else ")"))
