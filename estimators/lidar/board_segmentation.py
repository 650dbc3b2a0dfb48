"""Finding the board in a full LiDAR sweep, and fitting its plane robustly.

1. Gate by range: the board's distance from the camera (from its PnP pose) bounds its distance from the
   LiDAR, to within the sensors' separation (``max_sensor_separation_m``).
2. Sequential RANSAC extracts planes; each plane's inliers are split into connected pieces.
3. A piece is a board candidate when its extent fits the board: its minimum-area rectangle is no larger
   than the board (plus a tolerance) and its hull covers enough of the board's area.
4. Candidates are ranked by rotation-invariant agreement with the camera's view of the board: plane
   distance, centre distance, and the angle between the normal and the line of sight. A frame with no
   candidate, or two that agree equally well, is skipped with the reason.
5. The chosen piece is refitted by PCA with a robust (median absolute deviation) inlier step, which drops
   mixed edge returns and stand points that stray from the plane.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from geometry.board import BoardModel
from geometry.planes import Plane, fit_plane_pca, plane_basis, plane_difference
from geometry.vectors import row_norms

from ..errors import AmbiguousBoardError, MeasurementError
from ..measurements import MIN_INCIDENCE_COS, CameraBoardObservation, LidarBoardObservation, observe_lidar_board


@dataclass(frozen=True)
class SegmentationParams:
    max_sensor_separation_m: float = 1.0
    plane_threshold_m: float = 0.06
    min_points: int = 15
    extent_tolerance_m: float = 0.10
    min_area_fraction: float = 0.15
    max_planes: int = 12
    ransac_hypotheses: int = 400
    neighbour_angle_rad: float = 0.06  # connection radius per metre of range (beam spacing allowance)
    ambiguity_ratio: float = 2.0


def _ransac_plane(P: np.ndarray, threshold: float, hypotheses: int, rng: np.random.Generator
                  ) -> tuple[np.ndarray, np.ndarray] | None:
    """Best plane (normal, d) by inlier count over random triples, evaluated in one batch."""
    n = len(P)
    if n < 3:
        return None
    idx = rng.integers(0, n, size=(hypotheses, 3))
    a, b, c = P[idx[:, 0]], P[idx[:, 1]], P[idx[:, 2]]
    normals = np.cross(b - a, c - a)
    norms = np.linalg.norm(normals, axis=1)
    good = norms > 1e-9
    if not good.any():
        return None
    normals = normals[good] / norms[good, None]
    ds = np.einsum("ij,ij->i", normals, a[good])
    counts = np.zeros(len(normals), dtype=np.int64)
    for start in range(0, n, 20000):
        chunk = P[start:start + 20000].astype(np.float32)
        counts += (np.abs(chunk @ normals.T.astype(np.float32) - ds.astype(np.float32)) < threshold).sum(0)
    k = int(np.argmax(counts))
    return normals[k], ds[k]


def _pieces(P: np.ndarray, normal: np.ndarray, radius_per_m: float) -> list[np.ndarray]:
    """Index arrays of the connected pieces of coplanar points: occupancy of a grid in the plane whose
    cell follows the range (so ring gaps are bridged), labelled with 8-connectivity."""
    from scipy import ndimage  # here: scipy.ndimage, unused from the cache
    if len(P) == 0:
        return []
    cell = max(0.08, radius_per_m * float(np.median(np.linalg.norm(P, axis=1)))) / 1.5
    uv = P @ plane_basis(normal)
    ij = np.floor((uv - uv.min(0)) / cell).astype(int)
    grid = np.zeros(ij.max(0) + 1, dtype=bool)
    grid[ij[:, 0], ij[:, 1]] = True
    labels_grid, _ = ndimage.label(grid, structure=np.ones((3, 3)))
    labels = labels_grid[ij[:, 0], ij[:, 1]]
    order = np.argsort(labels, kind="stable")
    splits = np.nonzero(np.diff(labels[order]))[0] + 1
    return np.split(order, splits)


def _best_window(uv: np.ndarray, w: float, h: float, thetas: np.ndarray, cell: float
                 ) -> tuple[float, float, np.ndarray]:
    """The in-plane rotation and lower corner of the ``w x h`` window (sides rounded to whole cells) that
    holds the most points: (count, theta, corner in the rotated coordinates). Among equally full offsets
    the middle one is taken."""
    best = (-1.0, 0.0, np.zeros(2))
    nw, nh = max(int(round(w / cell)), 1), max(int(round(h / cell)), 1)
    for theta in thetas:
        c, s = np.cos(theta), np.sin(theta)
        q = uv @ np.array([[c, -s], [s, c]])
        lo = np.array([q[:, 0].min(), q[:, 1].min()])  # column by column: numpy's min(0) is ten times slower
        ij = np.floor((q - lo) / cell).astype(int)
        shape = (ij[:, 0].max() + 2, ij[:, 1].max() + 2)
        hist = np.bincount(ij[:, 0] * shape[1] + ij[:, 1], minlength=shape[0] * shape[1]).reshape(shape)
        # The integral image of the counts, in integers, written into its zero-padded array in place.
        integral = np.zeros((shape[0] + 1, shape[1] + 1), np.int64)
        inner = integral[1:, 1:]
        np.cumsum(hist, 0, out=inner)
        np.cumsum(inner, 1, out=inner)
        a, b = min(nw, shape[0]), min(nh, shape[1])
        sums = integral[a:, b:] - integral[:-a, b:] - integral[a:, :-b] + integral[:-a, :-b]
        top = sums.max()
        if top > best[0]:
            k = np.mean(np.argwhere(sums == top), axis=0)
            best = (float(top), float(theta), k * cell + lo)
    return best


def _rotate(uv: np.ndarray, theta: float) -> np.ndarray:
    c, s = np.cos(theta), np.sin(theta)
    return uv @ np.array([[c, -s], [s, c]])


def _board_window(uv: np.ndarray, w: float, h: float, slack: float = 0.015) -> np.ndarray:
    """Mask of the points inside the board's rectangle (``w x h``, grown by ``slack`` on every side).

    The rectangle is the board-sized window that holds the most points: first over in-plane rotations
    every 3 degrees on 2 cm cells, then within 3 degrees of that every 0.25 degree on 5 mm cells. A
    board-sized window cannot grow towards a stand or a tripod head without losing a whole board edge,
    so those points fall outside it; the slack keeps edge points that range noise moved sideways.
    """
    return _in_rectangle(uv, _board_rectangle(uv, w, h), slack)


def _board_rectangle(uv: np.ndarray, w: float, h: float) -> tuple[float, np.ndarray, np.ndarray]:
    """The board-sized window that holds the most points (:func:`_board_window`): its in-plane rotation,
    lower corner in the rotated coordinates and size."""
    _, theta, _ = _best_window(uv, w + 0.03, h + 0.03, np.deg2rad(np.arange(0.0, 180.0, 3.0)), 0.02)
    fine = theta + np.deg2rad(np.arange(-3.0, 3.01, 0.25))
    cell = 0.005
    _, theta, lo = _best_window(uv, w, h, fine, cell)
    size = np.array([max(round(w / cell), 1), max(round(h / cell), 1)]) * cell
    return theta, lo, size


def _in_rectangle(uv: np.ndarray, rect: tuple[float, np.ndarray, np.ndarray], slack: float) -> np.ndarray:
    theta, lo, size = rect
    q = _rotate(uv, theta)
    return np.all((q >= lo - slack) & (q <= lo + size + slack), axis=1)


def _board_piece(P: np.ndarray, plane: Plane, board: BoardModel, params: SegmentationParams
                 ) -> tuple[np.ndarray | None, str]:
    """The points of a planar piece that can be the board (trimmed of a stand), or None and why not."""
    uv = (P - P.mean(0)) @ plane_basis(plane.normal)
    (_, _), (w, h), _ = cv2.minAreaRect(uv.astype(np.float32))
    big, small = max(w, h), min(w, h)
    bw, bh = max(board.judged_extent), min(board.judged_extent)  # a board of unknown size: the pattern and margin
    tol = params.extent_tolerance_m
    keep = np.ones(len(P), dtype=bool)
    if big > np.hypot(bw, bh) + tol or small > bw + tol:
        # Larger than the board: a board on a stand, or a wall. Keep the best board-sized window when
        # it holds most of the piece (a stand is thin); a wall spreads far beyond any window.
        # Cheap necessary condition first: most points near the median point (a wall fails it at once).
        near = np.linalg.norm(uv - np.median(uv, axis=0), axis=1) <= np.hypot(bw, bh) / 2 + 0.05
        if near.mean() < 0.7:
            return None, f"too large ({big:.2f} x {small:.2f} m)"
        keep = np.zeros(len(uv), dtype=bool)
        keep[near] = _board_window(uv[near], bw, bh, slack=0.03)
        if keep.mean() < 0.7:
            return None, f"too large ({big:.2f} x {small:.2f} m)"
        uv = uv[keep]
    area = cv2.contourArea(cv2.convexHull(uv.astype(np.float32)))
    pw, ph = board.extent
    if area < params.min_area_fraction * pw * ph:
        return None, f"too small ({area:.3f} m^2 of {pw * ph:.3f})"
    return P[keep], ""


def robust_plane_fit(P: np.ndarray, iterations: int = 50) -> tuple[Plane, np.ndarray]:
    """PCA plane with an iterated 3-sigma inlier step (sigma from the median absolute deviation), to convergence
    (the inliers no longer change; at most ``iterations``): a stand's posts joined to the board tilt the first
    fits by degrees and take a dozen steps to leave."""
    keep = np.ones(len(P), dtype=bool)
    plane = fit_plane_pca(P)
    for _ in range(iterations):
        r = plane.signed_distances(P)
        sigma = 1.4826 * np.median(np.abs(r[keep] - np.median(r[keep])))
        new = np.abs(r) <= max(3.0 * sigma, 1e-6)
        if new.sum() < 3:
            break
        plane = fit_plane_pca(P[new])
        if np.array_equal(new, keep):
            break
        keep = new
    return plane, keep


# A board of unknown size: the border beyond its pattern is grown outwards in steps of this width (m), and stops
# at the first step whose points sit, on average, this many of their standard errors and this share of the
# noise off the pattern's plane (a stand's upright or a tripod head a few centimetres behind it).
BORDER_STEP_M = 0.01
BORDER_STOP_SE = 4.0
BORDER_STOP_SIGMA = 0.5


def border_trim(xy: np.ndarray, residual: np.ndarray, extent: tuple[float, float], sigma: float) -> np.ndarray:
    """Mask of a board's points (``xy`` in the board frame, the pattern's extent ``(0, 0)-extent``) kept when
    its size is unknown: all of the pattern's, and beyond each of its four sides the steps outwards up to the
    first one whose points leave the plane (``residual``: each point's distance from the plane fitted to the
    pattern's points; ``sigma``: their noise). What lies past that step is not the board's border."""
    w, h = extent
    past = np.stack([-xy[:, 0], xy[:, 0] - w, -xy[:, 1], xy[:, 1] - h], axis=1)  # beyond each side (m)
    side = np.argmax(past, axis=1)
    beyond = past[np.arange(len(xy)), side]
    keep = beyond <= 0.0
    for s in range(4):
        on = (side == s) & (beyond > 0.0)
        if not on.any():
            continue
        step = np.floor(beyond[on] / BORDER_STEP_M).astype(int)
        stop = step.max() + 1
        for k in range(stop):
            r = residual[on][step == k]
            if len(r) and abs(r.mean()) > max(BORDER_STOP_SE * sigma / np.sqrt(len(r)), BORDER_STOP_SIGMA * sigma):
                stop = k
                break
        idx = np.nonzero(on)[0]
        keep[idx[step < stop]] = True
    return keep


def _camera_cue_cost(plane: Plane, P: np.ndarray, cam: CameraBoardObservation, board: BoardModel,
                     sep: float) -> float:
    """Disagreement with the camera's board in quantities that do not depend on the unknown rotation."""
    c_cam = cam.T_camera_board[:3, :3] @ board.centre + cam.T_camera_board[:3, 3]
    c_lid = P.mean(0)
    r_cam, r_lid = np.linalg.norm(c_cam), np.linalg.norm(c_lid)
    cos_cam = abs(cam.plane.normal @ c_cam) / r_cam
    cos_lid = abs(plane.normal @ c_lid) / r_lid
    return float(abs(plane.distance - cam.plane.distance) / sep + abs(r_lid - r_cam) / sep
                 + abs(np.arccos(min(cos_lid, 1.0)) - np.arccos(min(cos_cam, 1.0))) / (0.1 + sep / r_cam))


@dataclass(frozen=True, eq=False)
class BoardCandidate:
    """A planar piece of a sweep that can be the board: its observation (points gathered and trimmed), its
    rotation-invariant disagreement with the camera's board (``cue_cost``, 0 is perfect), and whether it was
    searched among the points in front of the static scene only (``in_foreground``; False when the frame was
    judged alone)."""

    observation: LidarBoardObservation
    cue_cost: float
    in_foreground: bool = False

    def to_dict(self) -> dict:
        obs = self.observation
        return {"points": obs.n_points, "centre_lidar_m": np.round(obs.points.mean(0), 4).tolist(),
                "normal_lidar": np.round(obs.plane.normal, 5).tolist(), "distance_m": round(obs.plane.distance, 4),
                "camera_cue_cost": round(self.cue_cost, 3), "in_front_of_static_scene": self.in_foreground}


def range_gate(board: BoardModel, camera: CameraBoardObservation | None, sep: float) -> tuple[float, float]:
    """Ranges (m) from the LiDAR where the camera puts the board, to within the sensors' separation."""
    if camera is None:
        return 0.3, 15.0
    outline = (camera.T_camera_board[:3, :3] @ board.outline().T).T + camera.T_camera_board[:3, 3]
    dist = np.linalg.norm(outline, axis=1)
    return float(dist.min() - sep), float(dist.max() + sep)


def board_candidates(points: np.ndarray, board: BoardModel, camera: CameraBoardObservation | None,
                     rng: np.random.Generator, params: SegmentationParams = SegmentationParams(),
                     foreground: np.ndarray | None = None) -> tuple[list[BoardCandidate], list[str]]:
    """Every planar piece of the sweep that fits inside the board and covers enough of it, where the camera
    puts the board (``cue_cost`` below 3), with the reasons the other pieces were rejected.

    ``foreground``: mask of the points in front of the static scene; only those are searched (a board is
    never background), so the board's plane is found even in a room full of larger planes.
    """
    ranges = row_norms(points)
    sep = params.max_sensor_separation_m
    lo, hi = range_gate(board, camera, sep)
    keep = (ranges >= lo) & (ranges <= hi)
    if foreground is not None:
        keep &= foreground
    P = points[keep]
    if len(P) < params.min_points:
        where = "in front of the static scene " if foreground is not None else ""
        raise MeasurementError(f"only {len(P)} points {where}within {lo:.1f}-{hi:.1f} m, where the camera puts "
                               "the board")
    pieces: list[tuple[np.ndarray, Plane, float]] = []
    rejected: list[str] = []
    remaining = P
    for _ in range(params.max_planes):
        if len(remaining) < params.min_points:
            break
        found = _ransac_plane(remaining, params.plane_threshold_m, params.ransac_hypotheses, rng)
        if found is None:
            break
        n, d = found
        inl = np.abs(remaining @ n - d) < params.plane_threshold_m
        if inl.sum() < params.min_points:
            break
        plane_pts = remaining[inl]
        remaining = remaining[~inl]
        for piece in _pieces(plane_pts, n, params.neighbour_angle_rad):
            Q = plane_pts[piece]
            if len(Q) < params.min_points:
                continue
            plane, keep_q = robust_plane_fit(Q)
            Q, why = _board_piece(Q[keep_q], plane, board, params)
            if Q is None:
                rejected.append(why)
                continue
            plane, _ = robust_plane_fit(Q)
            cost = _camera_cue_cost(plane, Q, camera, board, sep) if camera is not None else 0.0
            if camera is not None and cost >= 3.0:
                rejected.append(f"where the camera does not put the board (cue cost {cost:.1f})")
                continue
            pieces.append((Q, plane, cost))
    pieces.sort(key=lambda c: c[2])
    finished = _one_per_board([(_finish(Q, P, board, len(pieces)), cost) for Q, _, cost in pieces], P, board)
    return [BoardCandidate(obs, cost, foreground is not None) for obs, cost in finished], rejected


# Two candidates are one board when they share this share of the smaller's points (each piece's points are
# gathered again around it, so two pieces of one board end up holding the same returns), or when their planes
# agree within these limits and their points touch.
SAME_BOARD_SHARED = 0.5
SAME_BOARD_ANGLE_RAD = np.deg2rad(3.0)
SAME_BOARD_OFFSET_M = 0.03
SAME_BOARD_GAP_M = 0.08


def _one_per_board(found: list[tuple[LidarBoardObservation, float]], P: np.ndarray, board: BoardModel
                   ) -> list[tuple[LidarBoardObservation, float]]:
    """One candidate per board: pieces that share most of their points, or lie in one plane and touch, are
    merged (their points joined and finished again), keeping the best camera cue; ``found`` is sorted by it."""
    out: list[tuple[LidarBoardObservation, float]] = []
    for obs, cost in found:
        for k, (kept, kept_cost) in enumerate(out):
            if _same_board(kept, obs):
                joined = np.unique(np.vstack([kept.points, obs.points]), axis=0)
                merged = _finish(joined, P, board, len(found))
                out[k] = (merged, min(kept_cost, cost))
                break
        else:
            out.append((obs, cost))
    return out


def _same_board(a: LidarBoardObservation, b: LidarBoardObservation) -> bool:
    from scipy.spatial import cKDTree  # here: scipy.spatial takes 0.3 s to import
    small, large = (a, b) if len(a.points) <= len(b.points) else (b, a)
    gap = cKDTree(large.points).query(small.points, distance_upper_bound=SAME_BOARD_GAP_M)[0]
    if np.mean(gap < 1e-9) >= SAME_BOARD_SHARED:  # the same returns
        return True
    angle = float(np.arccos(min(1.0, abs(float(a.plane.normal @ b.plane.normal)))))
    offset = float(np.median(np.abs(large.plane.signed_distances(small.points))))
    return angle < SAME_BOARD_ANGLE_RAD and offset < SAME_BOARD_OFFSET_M and bool(np.any(np.isfinite(gap)))


def find_board(points: np.ndarray, board: BoardModel, camera: CameraBoardObservation | None,
               rng: np.random.Generator, params: SegmentationParams = SegmentationParams()
               ) -> LidarBoardObservation:
    """The board's points and plane in a full sweep, decided from this frame alone, or
    :class:`MeasurementError` with the reason (:class:`AmbiguousBoardError` with the candidates when several
    pieces agree with the camera's board about equally well)."""
    candidates, rejected = board_candidates(points, board, camera, rng, params)
    if not candidates:
        lo, hi = range_gate(board, camera, params.max_sensor_separation_m)
        raise MeasurementError(
            f"no planar segment of the board's size {board.extent[0]:.2f} x {board.extent[1]:.2f} m "
            f"between {lo:.1f} and {hi:.1f} m ({len(rejected)} planar pieces rejected)")
    return decide_alone(candidates, camera is not None, params)


def decide_alone(candidates: list[BoardCandidate], with_camera: bool, params: SegmentationParams
                 ) -> LidarBoardObservation:
    """The one candidate whose camera cue is clearly the best, or :class:`AmbiguousBoardError`."""
    best = candidates[0].cue_cost
    close = [c for c in candidates if not with_camera or c.cue_cost < params.ambiguity_ratio * best + 0.05]
    if len(close) > 1:
        raise AmbiguousBoardError(f"ambiguous: {len(close)} board-sized planes agree with the camera's board",
                                  candidates=[c.observation for c in close])
    return candidates[0].observation


def _finish(points: np.ndarray, P: np.ndarray, board: BoardModel, n_candidates: int) -> LidarBoardObservation:
    from scipy.spatial import cKDTree  # here: scipy.spatial takes 0.3 s to import
    # Gather again every gated point near the chosen piece and its plane (RANSAC's band was centred on a
    # noisy three-point plane and cut the noise unevenly), then refit robustly.
    near = cKDTree(points).query(P, distance_upper_bound=0.03)[0] < np.inf
    Q = P[near]
    plane, keep = robust_plane_fit(Q)
    Q = Q[keep]
    if len(Q) >= 3:
        # Cut to the board's rectangle (of unknown size: the pattern's and the margin): the few centimetres of
        # a stand or tripod head just outside the board lie within the noise band of its plane but tilt it (they
        # sit at one edge, behind it).
        origin, basis = Q.mean(0), plane_basis(plane.normal)
        uv = (Q - origin) @ basis
        rect = _board_rectangle(uv, *board.judged_extent)
        inside = _in_rectangle(uv, rect, 0.015)
        if inside.sum() >= 3:
            plane, keep = robust_plane_fit(Q[inside])
            Q = Q[inside][keep]
            # Then every gated point in the rectangle and in the board's noise band around this plane: the
            # steps above cut the noise's tails at about 2.3 sigma around noisy fits, keeping the points
            # that agree with each fit's own error. On simulated VLP-16 boards at 3 cm noise that made planes
            # up to 1.8x as far off as all the board's returns give, a range noise 7% low, and planes that
            # disagreed beyond it (errors 1.3x the Cramer-Rao bound over 40 layouts; now 1.0-1.06).
            R = P[_in_rectangle((P - origin) @ basis, rect, 0.015) & (np.abs(plane.signed_distances(P)) < 0.3)]
            band = noise_band(R, plane)
            if band.sum() >= len(Q):  # (never fewer points than the trims left)
                Q = R[band]
    return observe_lidar_board(Q, n_candidates)


# The board's returns kept: within this many (robust) standard deviations of its plane along their beams. At 3
# the simulated results equal 4's within their noise, and recorded boards (heavier tails) fit a little better.
NOISE_BAND_SIGMA = 3.0


def along_beams(P: np.ndarray, plane: Plane) -> np.ndarray:
    """Each point's distance from ``plane`` along its own beam (its range noise, for a point of the plane)."""
    beams = P / np.maximum(row_norms(P)[:, None], 1e-9)
    cos = np.maximum(np.abs(beams @ plane.normal), MIN_INCIDENCE_COS)
    return plane.signed_distances(P) / cos


def noise_band(P: np.ndarray, plane: Plane, of: np.ndarray | None = None) -> np.ndarray:
    """Points within ``NOISE_BAND_SIGMA`` range-noise standard deviations of ``plane`` along their beams, the
    deviation from the median absolute residual of the points ``of`` (default ``P``; mostly the board's)."""
    r = along_beams(P, plane)
    ref = r if of is None else along_beams(of, plane)
    sigma = 1.4826 * float(np.median(np.abs(ref - np.median(ref))))
    return np.abs(r) <= max(NOISE_BAND_SIGMA * sigma, 1e-3)


def choose_by_prediction(candidates: list[LidarBoardObservation], predicted: Plane,
                         max_angle_rad: float = np.deg2rad(5.0), max_distance_m: float = 0.10
                         ) -> LidarBoardObservation | None:
    """The one candidate whose plane matches a predicted LiDAR-frame plane, or None if none or several do."""
    diffs = [plane_difference(c.plane, predicted) for c in candidates]
    fits = [c for c, (angle, dist) in zip(candidates, diffs) if angle < max_angle_rad and abs(dist) < max_distance_m]
    return fits[0] if len(fits) == 1 else None
