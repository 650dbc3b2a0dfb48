"""A sweep's depth discontinuities: the returns on the near side of a jump in range along their beam's ring.

Along one beam (one ring of a spinning LiDAR, its returns ordered by azimuth), neighbouring returns a long way
apart in range straddle an occluding contour: the nearer one lies on the foreground object's silhouette, which
the camera sees as an image edge (the farther one lies on the background next to a contour the LiDAR and the
camera see from different places, so it is not kept). Returns nearer than ``MIN_RANGE_M`` (the rig and its
operator) are dropped first. A surface seen at a grazing angle also steps in range from beam to beam, but
evenly, and so does a crease's far side: the jump counted is the step's excess over the larger of the steps on
either side of it, so that a wall's grazing stretch and the corner where it meets another give no contour.

The silhouette lies somewhere between the near return and its far neighbour, evenly likely (the beams sample the
azimuth in steps): the near return itself would sit on average half a step inside it, every contour drawn in
towards its object (half a step of a 1024-column LiDAR is 3 px of a 1000-px focal length). Each contour point is
therefore the near return turned about the LiDAR's z axis half way to its neighbour's azimuth, at the near
return's range.

A gap in the ring (a step of ``GAP_STEPS`` or more: a return or more missing: sky, glass, a black surface, beyond range)
gives no contour: where the surface ends within it is unknown. A dark face's echoes fade as it turns away from
the beam, so its last return can lie several steps inside its silhouette (3-6 px on the simulated rooms); a
black screen before a wall leaves a gap between two wall returns whose silhouette is nearer than either side
(tens of pixels of parallax between the sensors). Neither side of a gap is a neighbour of the other.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from geometry.vectors import row_norms

# A contour: neighbouring returns this far apart in range (m); returns this many azimuth steps apart: a gap.
MIN_JUMP_M = 0.3
GAP_STEPS = 1.5
MIN_RANGE_M = 1.0


@dataclass(frozen=True, eq=False)
class DepthEdges:
    """The contour points (``points`` (N, 3), LiDAR frame: each near-side return turned half way to its far
    neighbour), how far the range jumps at each (``jump_m``) and the near return's index in the
    sweep (``index``; a return between two jumps gives two points)."""

    points: np.ndarray
    jump_m: np.ndarray
    index: np.ndarray


def depth_edges(points: np.ndarray, ring: np.ndarray, min_jump_m: float = MIN_JUMP_M, gap_steps: float = GAP_STEPS,
                min_range_m: float = MIN_RANGE_M) -> DepthEdges:
    """The near sides of a sweep's range jumps, ring by ring (module docstring); ``ring``: each return's beam."""
    P = np.asarray(points, dtype=float).reshape(-1, 3)
    ring = np.asarray(ring).reshape(-1)
    r_all = row_norms(P)
    keep_idx, jumps, turns = [], [], []
    for beam in np.unique(ring):
        idx = np.flatnonzero((ring == beam) & (r_all >= min_range_m))
        if len(idx) < 3:
            continue
        az = np.arctan2(P[idx, 1], P[idx, 0])
        order = np.argsort(az, kind="stable")
        idx, az, r = idx[order], az[order], r_all[idx[order]]
        step = float(np.median(np.diff(az)))
        gap = np.diff(az) > gap_steps * max(step, 1e-6)
        d = np.diff(r)  # r[k + 1] - r[k]
        # Point k is the near side where its next neighbour is farther (d > jump), point k + 1 where it is nearer;
        # each contour point turned half way to its neighbour's azimuth.
        half = 0.5 * np.diff(az)
        before = np.abs(np.r_[0.0, np.where(gap[:-1], 0.0, d[:-1])])  # the step before each one
        after = np.abs(np.r_[np.where(gap[1:], 0.0, d[1:]), 0.0])  # and after it
        beside = np.maximum(before, after)
        up, down = d - beside, -d - beside
        left = np.flatnonzero(~gap & (up > min_jump_m))
        right = np.flatnonzero(~gap & (down > min_jump_m))
        for k, sign, at, size in ((left, 1.0, left, up), (right + 1, -1.0, right, down)):
            keep_idx.append(idx[k])
            jumps.append(size[at])
            turns.append(sign * half[at])
    index = np.concatenate(keep_idx) if keep_idx else np.zeros(0, dtype=np.int64)
    turn = np.concatenate(turns) if turns else np.zeros(0)
    c, s_ = np.cos(turn), np.sin(turn)
    Q = P[index]
    pts = np.column_stack([c * Q[:, 0] - s_ * Q[:, 1], s_ * Q[:, 0] + c * Q[:, 1], Q[:, 2]])
    return DepthEdges(pts, np.concatenate(jumps) if jumps else np.zeros(0), index)
