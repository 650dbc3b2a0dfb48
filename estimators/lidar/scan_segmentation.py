"""Finding the board's segment in a single-line (2D) scan.

1. Gate by range: the board's distance from the camera (its PnP pose) bounds its distance from the
   LiDAR to within the sensors' separation.
2. Split the scan, in angle order, into runs of neighbouring returns (a gap larger than a few beam
   spacings ends a run), and each run into straight pieces (split-and-merge: split at the point
   farthest from the chord while it is farther than ``line_threshold_m``).
3. A piece is a board candidate when its length fits the board (no longer than its diagonal, no shorter
   than ``min_length_fraction`` of its smaller side) and its middle lies where the camera puts the board.
4. A piece that is mostly static background (a wall, furniture) is not the board, which moves between
   frames: by the static scene's per-beam ranges when given, else when most other scans hold its points
   (within ``static_radius_m``).
5. One candidate: refitted robustly (3-sigma MAD trimming) and recorded; none, or two that fit about as
   well: the frame is skipped with the reason.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from geometry.board import BoardModel
from geometry.lines import fit_line_tls

from ..errors import AmbiguousBoardError, MeasurementError
from ..measurements import CameraBoardObservation, LidarBoardObservation, observe_lidar_line

if TYPE_CHECKING:
    from scipy.spatial import cKDTree


@dataclass(frozen=True)
class ScanSegmentationParams:
    max_sensor_separation_m: float = 1.0
    line_threshold_m: float = 0.03
    min_points: int = 5
    gap_beams: float = 4.0  # a run ends at a gap wider than this many beam spacings at that range
    min_gap_m: float = 0.05
    min_length_fraction: float = 0.25
    length_tolerance_m: float = 0.08
    ambiguity_ratio: float = 2.0
    static_radius_m: float = 0.03
    bridge_fraction: float = 0.25  # join straight pieces across a gap up to this fraction of the board side


def _runs(P: np.ndarray, params: ScanSegmentationParams) -> list[np.ndarray]:
    """Indices of runs of neighbouring returns (P sorted by angle)."""
    if len(P) < 2:
        return [np.arange(len(P))]
    ang = np.arctan2(P[:, 1], P[:, 0])
    step = float(np.median(np.diff(ang))) if len(P) > 2 else 0.01
    r = np.linalg.norm(P, axis=1)
    gap = np.linalg.norm(np.diff(P, axis=0), axis=1)
    limit = np.maximum(params.min_gap_m, params.gap_beams * abs(step) * np.minimum(r[:-1], r[1:]))
    cuts = np.nonzero(gap > limit)[0] + 1
    return np.split(np.arange(len(P)), cuts)


def _split(P: np.ndarray, idx: np.ndarray, threshold: float, out: list[np.ndarray]) -> None:
    """Split-and-merge (the split half): recursive split at the farthest point from the chord."""
    if len(idx) < 3:
        out.append(idx)
        return
    a, b = P[idx[0]], P[idx[-1]]
    chord = b - a
    norm = np.linalg.norm(chord)
    if norm < 1e-9:
        out.append(idx)
        return
    dist = np.abs((P[idx] - a) @ np.array([-chord[1], chord[0]]) / norm)
    k = int(np.argmax(dist))
    if dist[k] > threshold and 0 < k < len(idx) - 1:
        _split(P, idx[: k + 1], threshold, out)
        _split(P, idx[k:], threshold, out)
    else:
        out.append(idx)


def _merge(P: np.ndarray, pieces: list[np.ndarray], threshold: float) -> list[np.ndarray]:
    """Split-and-merge (the merge half): neighbouring pieces are joined while every point of the union but
    one stays within ``threshold`` of its fitted line (range noise, or one stray return, can split one
    surface; the line fit drops the stray return later)."""
    out: list[np.ndarray] = []
    for idx in pieces:
        if out and len(out[-1]) + len(idx) >= 3:
            joint = np.union1d(out[-1], idx)
            if _straight(P[joint], threshold):
                out[-1] = joint
                continue
        out.append(idx)
    return out


def _straight(Q: np.ndarray, threshold: float) -> bool:
    """Whether all points of ``Q`` but at most one lie within ``threshold`` of their fitted line."""
    return int(np.sum(np.abs(fit_line_tls(Q).signed_distances(Q)) > threshold)) <= 1


def scan_noise(P: np.ndarray) -> float:
    """Robust range-noise scale of an angle-ordered scan: each point's distance from the line through
    its two neighbours (variance 1.5 sigma^2 on a straight surface), by the median absolute deviation."""
    if len(P) < 5:
        return 0.0
    a, b, c = P[:-2], P[1:-1], P[2:]
    chord = c - a
    norm = np.maximum(np.linalg.norm(chord, axis=1), 1e-12)
    d = np.abs((b - a)[:, 0] * chord[:, 1] - (b - a)[:, 1] * chord[:, 0]) / norm
    return float(1.4826 * np.median(d) / np.sqrt(1.5))


def _robust_line_points(Q: np.ndarray, iterations: int = 4) -> np.ndarray:
    keep = np.ones(len(Q), dtype=bool)
    for _ in range(iterations):
        line = fit_line_tls(Q[keep])
        r = line.signed_distances(Q)
        sigma = 1.4826 * np.median(np.abs(r[keep] - np.median(r[keep])))
        new = np.abs(r) <= max(3.0 * sigma, 1e-6)
        if new.sum() < 3 or np.array_equal(new, keep):
            break
        keep = new
    return Q[keep]


def is_static(Q: np.ndarray, others: list[cKDTree], radius: float) -> bool:
    """Whether most other scans also hold the points ``Q`` (background, not a board that moved)."""
    if not others:
        return False
    held = [np.mean(t.query(Q, distance_upper_bound=radius)[0] < np.inf) for t in others]
    return float(np.median(held)) > 0.5


def find_board_in_scan(points: np.ndarray, board: BoardModel, camera: CameraBoardObservation,
                       params: ScanSegmentationParams = ScanSegmentationParams(),
                       others: list[cKDTree] | None = None, foreground: np.ndarray | None = None
                       ) -> LidarBoardObservation:
    """The board's laser segment in a 2D scan ((N, 2) scan-plane points), decided from this frame alone, or
    :class:`MeasurementError` (:class:`AmbiguousBoardError` with the candidates when several segments agree
    with the camera about equally well). Arguments as :func:`scan_candidates`."""
    candidates = scan_candidates(points, board, camera, params, others, foreground)
    if len(candidates) > 1 and candidates[1][0] < params.ambiguity_ratio * candidates[0][0] + 0.05:
        raise AmbiguousBoardError(f"ambiguous: {len(candidates)} board-length scan segments lie where the camera "
                                  "puts the board", [obs for _, obs in candidates])
    return candidates[0][1]


def scan_candidates(points: np.ndarray, board: BoardModel, camera: CameraBoardObservation,
                    params: ScanSegmentationParams = ScanSegmentationParams(),
                    others: list[cKDTree] | None = None, foreground: np.ndarray | None = None,
                    static_out: list | None = None) -> list[tuple[float, LidarBoardObservation]]:
    """Every straight segment of a 2D scan ((N, 2) scan-plane points) that can be the board, as (camera cue
    cost, observation), best first; :class:`MeasurementError` when there is none.
    ``foreground``: mask of the returns in front of the static scene (``lidar.static_scene``); a segment
    must be mostly foreground. Without it, ``others`` (KD-trees of the other frames' scans) tell static
    background from the board. ``static_out``: a list that receives the segments judged static, in the same
    form (a board held at one place in several frames can look static; a cross-frame choice may still take
    it), and then no error is raised when only static segments were found."""
    P = np.asarray(points, dtype=float)[:, :2]
    sep = params.max_sensor_separation_m
    outline = (camera.T_camera_board[:3, :3] @ board.outline().T).T + camera.T_camera_board[:3, 3]
    dist = np.linalg.norm(outline, axis=1)
    lo, hi = dist.min() - sep, dist.max() + sep
    r = np.linalg.norm(P, axis=1)
    gate = (r >= lo) & (r <= hi)
    fg = None if foreground is None else np.asarray(foreground, dtype=bool)[gate]
    P = P[gate]
    if len(P) < params.min_points:
        raise MeasurementError(f"only {len(P)} returns within {lo:.1f}-{hi:.1f} m, where the camera puts the board")
    order = np.argsort(np.arctan2(P[:, 1], P[:, 0]))
    P = P[order]
    fg = None if fg is None else fg[order]
    w, h = board.extent
    max_len = float(np.hypot(w, h)) + params.length_tolerance_m
    min_len = params.min_length_fraction * min(w, h)
    centre_cam = camera.T_camera_board[:3, :3] @ board.centre + camera.T_camera_board[:3, 3]
    r_cam = float(np.linalg.norm(centre_cam))
    # Split at corners, not at range noise: the threshold grows with the noise the scan shows.
    threshold = max(params.line_threshold_m, 5.0 * scan_noise(P))
    pieces: list[np.ndarray] = []
    max_gap = params.bridge_fraction * min(w, h)
    for run in _runs(P, params):
        split: list[np.ndarray] = []
        _split(P, run, threshold, split)
        merged = _merge(P, split, threshold)
        # A few missing returns cut a board into two runs: join the pieces either side of a short gap when
        # they are one straight segment no longer than the board.
        if pieces and merged and np.linalg.norm(P[merged[0][0]] - P[pieces[-1][-1]]) <= max_gap:
            joint = np.concatenate([pieces[-1], merged[0]])
            Q = P[joint]
            if np.linalg.norm(Q[-1] - Q[0]) <= max_len and _straight(Q, threshold):
                pieces[-1] = joint
                merged = merged[1:]
        pieces += merged
    candidates, rejected, static = [], 0, 0
    for idx in pieces:
        if len(idx) < params.min_points:
            continue
        Q = P[idx]
        length = float(np.linalg.norm(Q[-1] - Q[0]))
        if length > max_len or length < min_len:
            rejected += 1
            continue
        # Where the camera puts the board: the piece's middle is on the board, so its range differs from
        # the board centre's range from the camera by at most the separation plus half the diagonal.
        cost = abs(float(np.linalg.norm(Q.mean(0))) - r_cam) / (sep + 0.5 * max_len)
        if cost >= 1.0:
            continue
        if (np.mean(fg[idx]) < 0.5) if fg is not None else is_static(Q, others or [], params.static_radius_m):
            static += 1
            if static_out is not None:
                static_out.append((cost, observe_lidar_line(_robust_line_points(Q))))
            continue
        candidates.append((cost, Q))
    if not candidates and not static_out:
        raise MeasurementError(f"no straight scan segment of the board's length ({min_len:.2f}-{max_len:.2f} m) "
                               f"between {lo:.1f} and {hi:.1f} m ({rejected} segments of other lengths, {static} "
                               "static in the other frames' scans)")
    candidates.sort(key=lambda c: c[0])
    return [(cost, observe_lidar_line(_robust_line_points(Q), len(candidates))) for cost, Q in candidates]
