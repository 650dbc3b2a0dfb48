"""Which LiDAR candidate is each frame's board: chosen jointly, by the extrinsic that most frames agree with.

Each frame keeps every plausible board candidate (a planar piece in front of the static scene that fits inside
the board). One extrinsic explains the true board of every frame, while a wrong piece (a door, a monitor, a
picture, a patch of ground) agrees with it only by chance. So (MSAC over triples of (frame, candidate)):

1. Hypotheses: three frames whose camera normals span 3D, one candidate of each; the closed form of the three
   plane pairs (MATH.md section 1) is exact for them. All combinations when few, else a weighted sample
   (candidates that agree better with the camera's rotation-invariant cues are drawn more often).
2. Score: under a hypothesis every candidate maps into the camera frame; its normal's angle from the frame's
   camera plane normal and its centroid's distance from that plane (not the plane's distance from the origin,
   whose error grows with range), over ``sigma_angle_rad`` and ``sigma_distance_m``, give a
   2-dof statistic, gated at its 99% point. A frame agrees when one of its candidates passes the gate; the
   cost is the truncated sum over frames (MSAC), so the hypothesis most frames agree with wins.
3. Refit: the closed form of all agreeing frames, then the choice again, until it no longer changes. Now that
   the extrinsic is known, each candidate is judged by its points inside the camera's board outline and near
   its plane (refitted robustly: a holder's arm or body joined to the board's piece neither tilts it nor
   counts); at least half of a candidate's points must be inside, and the best statistic within the gate wins.

A frame whose candidates all disagree is skipped with the reason. It works when every frame is ambiguous, and
needs at least three frames whose boards' normals span 3D.
"""
from __future__ import annotations

import itertools
import time
from dataclasses import dataclass, replace

import numpy as np

from geometry.board import BoardModel
from geometry.planes import Plane
from geometry.rotations import T_from_Rt, transform_points

from ..errors import DegenerateLayoutError, NoHypothesisError
from ..lidar.board_segmentation import robust_plane_fit
from .closed_form import MIN_NORMAL_SPREAD, WEAK_NORMAL_SPREAD, solve_closed_form

GATE_CHI2_2DOF = 9.21  # 99% point of chi-square with 2 dof
# How a frame skipped because none of its candidates agrees with the frames' extrinsic says so (the verdict counts
# those frames as disagreeing: ``pipeline.verdict``).
DISAGREES_WITH_CONSENSUS = "disagree with the extrinsic of"


@dataclass(frozen=True)
class AssociationParams:
    sigma_angle_rad: float = np.deg2rad(1.5)   # plane normal residual scale (noise and a triple's error)
    sigma_distance_m: float = 0.04             # plane distance residual scale
    max_hypotheses: int = 6000
    min_frames: int = 3
    outline_margin_m: float = 0.10             # points this far outside the board still count as inside
    min_inside: float = 0.5                    # share of a candidate's points inside the outline (the rest:
                                               # the holder's arms or body joined to the board's piece)
    refit_band_m: float = 0.10                 # refit a candidate's plane to its points this near the camera's


@dataclass(frozen=True, eq=False)
class FrameChoice:
    """One frame's decision: the chosen candidate (index or None), each candidate's residuals under the
    consensus extrinsic (normal angle rad, distance of its centroid from the camera's board plane m, share of
    points inside the camera's board outline), and why."""

    chosen: int | None
    residuals: tuple[tuple[float, float, float], ...]
    reason: str


@dataclass(frozen=True, eq=False)
class Association:
    T_camera_lidar: np.ndarray
    choices: tuple[FrameChoice, ...]
    agreeing: int
    hypotheses: int
    seconds: float


def _batch_closed_form(nc: np.ndarray, dc: np.ndarray, nl: np.ndarray, dl: np.ndarray,
                       min_spread: float = MIN_NORMAL_SPREAD) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closed form of many plane triples at once: nc, nl (H, 3, 3) normals by row, dc, dl (H, 3). Returns R
    (H, 3, 3), t (H, 3) and a validity mask (normals that span 3D: spread above ``min_spread``)."""
    K = np.einsum("hki,hkj->hij", nc, nl)
    U, _, Vt = np.linalg.svd(K)
    d = np.sign(np.linalg.det(U @ Vt))
    U = U * np.stack([np.ones_like(d), np.ones_like(d), d], axis=1)[:, None, :]
    R = U @ Vt
    s = np.linalg.svd(nc, compute_uv=False)
    ok = s[:, -1] / np.sqrt(3.0) > min_spread
    t = np.zeros((len(nc), 3))
    if ok.any():
        t[ok] = np.linalg.solve(nc[ok], (dc - dl)[ok][:, :, None])[:, :, 0]
    return R, t, ok


def _residuals(R: np.ndarray, t: np.ndarray, nl: np.ndarray, cl: np.ndarray, nc: np.ndarray, dc: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
    """Residuals of LiDAR board candidates (normals nl (C, 3), centroids cl (C, 3)) against their frames'
    camera planes (nc (C, 3), dc (C,)) under each of H hypotheses: the angle between the normals (rad) and the
    distance of the mapped centroid from the camera plane (m), two (H, C) arrays. The centroid, not the
    plane's distance from the origin, so that a candidate's normal error does not grow with its range."""
    # nc . (R x) = sum_ij R_ij nc_i x_j: one matrix product over all hypotheses and candidates.
    Rf = R.reshape(len(R), 9)
    cos = np.clip(Rf @ np.einsum("ci,cj->cij", nc, nl).reshape(-1, 9).T, -1.0, 1.0)
    dist = Rf @ np.einsum("ci,cj->cij", nc, cl).reshape(-1, 9).T + t @ nc.T - dc[None, :]
    return np.arccos(cos), dist


def inside_outline(points: np.ndarray, T_camera_lidar: np.ndarray, T_camera_board: np.ndarray,
                   board: BoardModel, margin: float, band: float = np.inf) -> np.ndarray:
    """Mask of the LiDAR points that fall inside the board's outline (grown by ``margin``) and within ``band``
    of its plane, mapped into the board frame through the extrinsic and the camera's board pose."""
    if len(points) == 0:
        return np.zeros(0, dtype=bool)
    q = transform_points(np.linalg.inv(T_camera_board) @ T_camera_lidar, points)
    corners = board.outline()[:, :2]
    return (np.all((q[:, :2] >= corners.min(0) - margin) & (q[:, :2] <= corners.max(0) + margin), axis=1)
            & (np.abs(q[:, 2]) <= band))


def associate(camera_planes: list[Plane], camera_poses: list[np.ndarray], candidates: list[list],
              board: BoardModel, rng: np.random.Generator, params: AssociationParams = AssociationParams(),
              weights: list[list[float]] | None = None) -> Association:
    """Choose one candidate (or none) per frame. ``candidates[k]``: frame k's LiDAR board observations (each
    with ``plane`` and ``points``); ``weights[k]``: relative sampling weights of its candidates.

    Raises :class:`NoHypothesisError` when fewer than ``min_frames`` frames with candidates span 3D, and
    :class:`DegenerateLayoutError` when no hypothesis is supported by that many frames."""
    t0 = time.perf_counter()
    frames = [k for k, c in enumerate(candidates) if c]
    if len(frames) < params.min_frames:
        raise NoHypothesisError(f"only {len(frames)} frame(s) have a board candidate; choosing among them "
                                f"needs {params.min_frames}")
    cand_frame = np.array([k for k in frames for _ in candidates[k]])
    nl = np.array([c.plane.normal for k in frames for c in candidates[k]])
    dl = np.array([c.plane.distance for k in frames for c in candidates[k]])
    cl = np.array([c.points.mean(0) for k in frames for c in candidates[k]])
    ncam = np.array([p.normal for p in camera_planes])
    dcam = np.array([p.distance for p in camera_planes])
    # (H, 3, 2): (frame, candidate) per row; triples spanning 3D well, else (hand-held boards, all facing the
    # rig) those above the factor graph's weak limit
    H, limit = _hypotheses(frames, candidates, ncam, rng, params, weights)
    if len(H) == 0:
        raise NoHypothesisError(f"no three of the {len(frames)} frames with board candidates have camera "
                                f"normals that span 3D (the best triple's spread is {limit:.3f}; the "
                                f"consensus needs {WEAK_NORMAL_SPREAD})")
    first = np.zeros(max(frames) + 1, dtype=int)
    first[frames] = np.searchsorted(cand_frame, frames)
    flat = first[H[:, :, 0]] + H[:, :, 1]
    R, t, ok = _batch_closed_form(ncam[H[:, :, 0]], dcam[H[:, :, 0]], nl[flat], dl[flat],
                                  limit)
    R, t = R[ok], t[ok]
    if len(R) == 0:
        raise NoHypothesisError("no triple of frames with board candidates has normals that span 3D")
    cost, agree = _score(R, t, nl, cl, ncam[cand_frame], dcam[cand_frame], cand_frame, frames, params)
    best = int(np.argmin(cost))
    if agree[best] < params.min_frames:
        raise DegenerateLayoutError(f"no extrinsic is supported by {params.min_frames} frames' candidates "
                                    f"(best: {int(agree[best])})")
    T = T_from_Rt(R[best], t[best])
    cov_R = _rotation_covariance(ncam[H[ok][best][:, 0]], params)
    chosen = _choose(T, candidates, camera_planes, camera_poses, board, params, cov_R)
    for _ in range(5):
        if len(chosen) < params.min_frames:
            raise DegenerateLayoutError(f"the best extrinsic keeps only {len(chosen)} frame(s) whose board lies "
                                        "inside the camera's outline")
        try:
            T = solve_closed_form([camera_planes[k] for k in chosen],
                                  [candidates[k][i].plane for k, i in chosen.items()], allow_weak=True).T_camera_lidar
        except DegenerateLayoutError:
            break
        cov_R = _rotation_covariance(ncam[list(chosen)], params)
        new = _choose(T, candidates, camera_planes, camera_poses, board, params, cov_R)
        if new == chosen:
            break
        chosen = new
    choices = _explain(T, candidates, camera_planes, camera_poses, board, params, chosen, cov_R)
    return Association(T, tuple(choices), len(chosen), len(R), time.perf_counter() - t0)


def _hypotheses(frames: list[int], candidates: list[list], ncam: np.ndarray, rng: np.random.Generator,
                params: AssociationParams, weights, allow_weak: bool = True) -> tuple[np.ndarray, float]:
    """(frame, candidate) triples, (H, 3, 2), from frames whose camera normals span 3D (spread above
    ``MIN_NORMAL_SPREAD``; when no triple reaches it and ``allow_weak``, above ``WEAK_NORMAL_SPREAD``, the factor
    graph's limit):
    all when they fit the budget, else a sample (without repeats) weighted by the candidates' weights. Also the
    spread limit used (the best triple's spread when none reaches the weak limit)."""
    tri = np.array(list(itertools.combinations(frames, 3)), dtype=int).reshape(-1, 3)
    if len(tri) == 0:
        return np.zeros((0, 3, 2), dtype=int), 0.0
    spread = np.linalg.svd(ncam[tri], compute_uv=False)[:, -1] / np.sqrt(3.0)
    limit = MIN_NORMAL_SPREAD if np.any(spread > MIN_NORMAL_SPREAD) or not allow_weak else WEAK_NORMAL_SPREAD
    if not np.any(spread > limit):
        return np.zeros((0, 3, 2), dtype=int), float(spread.max())
    tri = tri[spread > limit]
    sizes = np.zeros(len(ncam), dtype=int)
    sizes[frames] = [len(candidates[k]) for k in frames]
    if np.prod(sizes[tri], axis=1).sum() <= params.max_hypotheses:
        rows = [[(a, i), (b, j), (c, m)] for a, b, c in tri for i in range(sizes[a]) for j in range(sizes[b])
                for m in range(sizes[c])]
        return np.array(rows, dtype=int), limit
    # Cumulative sampling weights per frame, padded with 1 beyond each frame's candidates.
    cum = np.ones((len(ncam), sizes.max()))
    for k in frames:
        w = np.ones(sizes[k]) if weights is None else np.asarray(weights[k], dtype=float)
        cum[k, :sizes[k]] = np.cumsum(w / w.sum())
    picks = tri[rng.integers(0, len(tri), size=params.max_hypotheses)]
    u = rng.random(picks.shape)
    idx = np.minimum((u[:, :, None] > cum[picks]).sum(2), sizes[picks] - 1)
    H = np.unique(np.stack([picks, idx], axis=2).reshape(len(picks), 6), axis=0)
    return H.reshape(-1, 3, 2), limit


def _score(R, t, nl, cl, nc, dc, cand_frame, frames, params: AssociationParams, chunk: int = 1024):
    """MSAC cost (truncated sum over frames of each frame's best gated statistic) and the number of agreeing
    frames, per hypothesis."""
    cost = np.empty(len(R))
    agree = np.empty(len(R), dtype=int)
    starts = np.searchsorted(cand_frame, frames)  # candidates are stored frame by frame
    for s in range(0, len(R), chunk):
        ang, dist = _residuals(R[s:s + chunk], t[s:s + chunk], nl, cl, nc, dc)
        e2 = np.minimum((ang / params.sigma_angle_rad) ** 2 + (dist / params.sigma_distance_m) ** 2,
                        GATE_CHI2_2DOF)
        best = np.minimum.reduceat(e2, starts, axis=1)  # each frame's best candidate
        cost[s:s + chunk] = best.sum(1)
        agree[s:s + chunk] = (best < GATE_CHI2_2DOF).sum(1)
    return cost, agree


def _rotation_covariance(normals: np.ndarray, params: AssociationParams) -> np.ndarray:
    """The rotation's covariance (3x3, rad^2) of a closed form from boards with these camera normals, each
    normal known to ``sigma_angle_rad``: a rotation about ``a`` moves normal ``n`` by ``a x n``, so the
    information is ``sum (I - n n^T) / sigma^2``. Weak about the axis the normals crowd round."""
    info = sum(np.eye(3) - np.outer(n, n) for n in normals) / params.sigma_angle_rad**2
    return np.linalg.pinv(info)


def _stats(T, candidates, camera_planes, camera_poses, board, params, k, cov_R=None):
    """Per candidate of frame k: (angle, distance, inside share, gated statistic, points judged). A candidate
    that can be chosen (enough of it inside the camera's board outline) is judged by its points inside the
    outline and near the plane, refitted robustly, so that a holder's arm or body joined to the board's piece
    does not tilt it. ``cov_R``: the extrinsic's rotation covariance, which widens the angle's scale (a layout
    whose boards all face the rig leaves the rotation about its axis weak)."""
    out = []
    cam = camera_planes[k]
    sigma_angle = params.sigma_angle_rad
    if cov_R is not None:
        sigma_angle = float(np.sqrt(sigma_angle**2 + np.trace((np.eye(3) - np.outer(cam.normal, cam.normal))
                                                             @ cov_R)))
    for c in candidates[k]:
        inside = inside_outline(c.points, T, camera_poses[k], board, params.outline_margin_m + board.unknown_margin)
        share = float(np.mean(inside)) if len(inside) else 0.0
        plane, P = c.plane, c.points
        if share >= params.min_inside:
            near = inside & inside_outline(P, T, camera_poses[k], board, np.inf, params.refit_band_m)
            if 10 <= near.sum() < len(near):
                plane, keep = robust_plane_fit(P[near])
                P = P[near][keep]
        ang, dist = (float(v[0, 0]) for v in _residuals(T[None, :3, :3], T[None, :3, 3], plane.normal[None],
                                                        P.mean(0)[None], cam.normal[None], np.array([cam.distance])))
        e2 = (ang / sigma_angle) ** 2 + (dist / params.sigma_distance_m) ** 2
        out.append((ang, dist, share, e2, len(P)))
    return out


def _choose(T, candidates, camera_planes, camera_poses, board, params, cov_R=None) -> dict[int, int]:
    """Frame -> candidate: among candidates within the gate and inside the outline, the best statistic."""
    chosen = {}
    for k, cands in enumerate(candidates):
        stats = _stats(T, candidates, camera_planes, camera_poses, board, params, k, cov_R)
        ok = [(-n, e2, i) for i, (_, _, inside, e2, n) in enumerate(stats)
              if e2 < GATE_CHI2_2DOF and inside >= params.min_inside]
        if ok:  # the fullest piece that agrees: pieces of the board itself agree too, but hold fewer points
            chosen[k] = min(ok)[2]
    return chosen


def _explain(T, candidates, camera_planes, camera_poses, board, params, chosen: dict[int, int], cov_R=None
             ) -> list[FrameChoice]:
    out = []
    n = len(chosen)
    for k, cands in enumerate(candidates):
        stats = _stats(T, candidates, camera_planes, camera_poses, board, params, k, cov_R)
        res = tuple((a, d, inside) for a, d, inside, _, _ in stats)
        if not cands:
            out.append(FrameChoice(None, res, "no board candidate"))
        elif k in chosen:
            a, d, inside, _, _ = stats[chosen[k]]
            others = len(cands) - 1
            out.append(FrameChoice(chosen[k], res,
                                   f"agrees with the extrinsic of {n} frames ({np.degrees(a):.1f} deg, "
                                   f"{1000 * d:+.0f} mm, {100 * inside:.0f}% inside the board)"
                                   + (f"; {others} other candidate(s) disagree" if others else "")))
        else:
            j = int(np.argmin([s[3] for s in stats]))
            a, d, inside, _, _ = stats[j]
            out.append(FrameChoice(None, res,
                                   f"its {len(cands)} candidate(s) all {DISAGREES_WITH_CONSENSUS} {n} frames "
                                   f"(closest: {np.degrees(a):.1f} deg, {1000 * d:+.0f} mm, {100 * inside:.0f}% "
                                   "inside the board)"))
    return out


def associate_lines(camera_planes: list[Plane], camera_poses: list[np.ndarray], candidates: list[list],
                    board: BoardModel, rng: np.random.Generator, params: AssociationParams = AssociationParams(),
                    max_triples: int = 1500, sigma_line_m: float = 0.03, points_per_segment: int = 40
                    ) -> Association:
    """The 2D form of :func:`associate`: ``candidates[k]`` are frame k's laser segments (observations with
    ``line`` and ``points``). Hypotheses are the minimal solutions (MATH.md section 4) of triples of
    (frame, segment) from frames whose camera normals span 3D; a segment agrees with one when its points,
    mapped into the camera frame, lie on the frame's board plane (RMS distance within ``3 sigma_line_m``) and
    inside its outline. The hypothesis most frames agree with chooses each frame's segment (the fullest that
    agrees); a frame whose segments all disagree is skipped with the reason. Raises :class:`NoHypothesisError`
    when there is no hypothesis (too few frames, no triple spanning 3D, no minimal solution) and
    :class:`DegenerateLayoutError` when none has ``min_frames`` frames agreeing."""
    from .minimal_solver import solve_triples

    t0 = time.perf_counter()
    frames = [k for k, c in enumerate(candidates) if c]
    if len(frames) < params.min_frames:
        raise NoHypothesisError(f"only {len(frames)} frame(s) have a scan segment; choosing among them "
                                f"needs {params.min_frames}")
    ncam = np.array([p.normal for p in camera_planes])
    # Triples spanning 3D well only: the weak ones' minimal solutions would multiply near-degenerate roots.
    H, _ = _hypotheses(frames, candidates, ncam, rng, replace(params, max_hypotheses=max_triples), None,
                       allow_weak=False)
    if len(H) == 0:
        raise NoHypothesisError(f"no three of the {len(frames)} frames with scan segments have camera normals "
                                "that span 3D")
    flat = [(k, i) for k in frames for i in range(len(candidates[k]))]
    where = {fc: j for j, fc in enumerate(flat)}
    planes = [camera_planes[k] for k, _ in flat]
    lines = [candidates[k][i].line for k, i in flat]
    triples = [tuple(where[(int(k), int(i))] for k, i in row) for row in H]
    Ts = [T for sol in solve_triples(planes, lines, triples) for T in sol.T_camera_lidar]
    if not Ts:
        raise NoHypothesisError(f"no minimal solution from {len(triples)} triple(s) of scan segments")
    Ts = np.array(Ts)
    # Each segment's points (a subsample), with its frame's camera plane and board pose.
    seg_pts, seg_of = [], []
    for j, (k, i) in enumerate(flat):
        P = candidates[k][i].points
        P = P[np.linspace(0, len(P) - 1, min(points_per_segment, len(P))).astype(int)]
        seg_pts.append(P)
        seg_of += [j] * len(P)
    Pm, seg_of = np.vstack(seg_pts), np.array(seg_of)
    starts = np.searchsorted(seg_of, np.arange(len(flat)))
    counts = np.diff(np.append(starts, len(seg_of)))
    frame_of_seg = np.array([k for k, _ in flat])
    seg_frame_starts = np.searchsorted(frame_of_seg, frames)
    cost = np.empty(len(Ts))
    agree = np.empty(len(Ts), dtype=int)
    for s in range(0, len(Ts), 512):
        rms, inside = _line_stats(Ts[s:s + 512], Pm, seg_of, starts, counts, flat, camera_planes, camera_poses,
                                  board, params)
        e2 = np.where(inside >= params.min_inside, np.minimum((rms / sigma_line_m) ** 2, GATE_CHI2_2DOF),
                      GATE_CHI2_2DOF)
        best = np.minimum.reduceat(e2, seg_frame_starts, axis=1)
        cost[s:s + 512] = best.sum(1)
        agree[s:s + 512] = (best < GATE_CHI2_2DOF).sum(1)
    b = int(np.argmin(cost))
    if agree[b] < params.min_frames:
        raise DegenerateLayoutError(f"no minimal solution is supported by {params.min_frames} frames' scan segments "
                                    f"(best: {int(agree[b])})")
    T = Ts[b]
    rms, inside = (v[0] for v in _line_stats(T[None], Pm, seg_of, starts, counts, flat, camera_planes, camera_poses,
                                             board, params))
    ok = (rms < 3 * sigma_line_m) & (inside >= params.min_inside)
    chosen = {}
    for j, (k, i) in enumerate(flat):
        if ok[j] and (k not in chosen or len(candidates[k][i].points) > len(candidates[k][chosen[k]].points)):
            chosen[k] = i
    choices = []
    for k, cands in enumerate(candidates):
        res = tuple((float("nan"), float(rms[where[(k, i)]]), float(inside[where[(k, i)]]))
                    for i in range(len(cands)))
        if not cands:
            choices.append(FrameChoice(None, res, "no scan segment"))
        elif k in chosen:
            _, d, share = res[chosen[k]]
            choices.append(FrameChoice(chosen[k], res, f"lies on the board under the minimal solution of "
                                                       f"{len(chosen)} frames (RMS {1000 * d:.0f} mm from the "
                                                       f"camera's board plane, {100 * share:.0f}% inside it)"
                                       + (f"; {len(cands) - 1} other segment(s) do not" if len(cands) > 1 else "")))
        else:
            j = min(range(len(cands)), key=lambda i: res[i][1])
            choices.append(FrameChoice(None, res, f"its {len(cands)} segment(s) are off the board under the minimal "
                                                  f"solution of {len(chosen)} frames (closest: RMS "
                                                  f"{1000 * res[j][1]:.0f} mm, {100 * res[j][2]:.0f}% inside)"))
    return Association(T, tuple(choices), len(chosen), len(Ts), time.perf_counter() - t0)


def _line_stats(Ts, Pm, seg_of, starts, counts, flat, camera_planes, camera_poses, board, params):
    """Per hypothesis and segment: RMS distance (m) of its points from its frame's camera board plane, and the
    share of them inside the board's outline (grown by ``outline_margin_m``), two (H, S) arrays."""
    frame_of_pt = np.array([flat[j][0] for j in seg_of])
    n = np.array([camera_planes[k].normal for k in frame_of_pt])
    d = np.array([camera_planes[k].distance for k in frame_of_pt])
    pc = np.einsum("hij,mj->hmi", Ts[:, :3, :3], Pm) + Ts[:, None, :3, 3]  # (H, M, 3) in the camera frame
    r = np.einsum("hmi,mi->hm", pc, n) - d
    rms = np.sqrt(np.add.reduceat(r * r, starts, axis=1) / counts)
    T_bc = np.array([np.linalg.inv(camera_poses[k]) for k in frame_of_pt])  # (M, 4, 4)
    pb = np.einsum("mij,hmj->hmi", T_bc[:, :3, :3], pc) + T_bc[:, :3, 3]
    corners = board.outline()[:, :2]
    m = params.outline_margin_m
    inside = np.all((pb[..., :2] >= corners.min(0) - m) & (pb[..., :2] <= corners.max(0) + m), axis=2)
    share = np.add.reduceat(inside.astype(float), starts, axis=1) / counts
    return rms, share
