"""Lines in a 2D LiDAR's scan plane (its x-y plane, z = 0): total-least-squares fits and intersections."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, eq=False)
class Line2D:
    """The line through ``point`` along the unit ``direction`` (scan-plane coordinates, metres)."""

    point: np.ndarray
    direction: np.ndarray

    def __post_init__(self):
        p = np.asarray(self.point, dtype=float).reshape(2)
        d = np.asarray(self.direction, dtype=float).reshape(2)
        norm = np.linalg.norm(d)
        if not np.isfinite(norm) or norm == 0:
            raise ValueError(f"Expected a non-zero finite direction, got {d}")
        object.__setattr__(self, "point", p)
        object.__setattr__(self, "direction", d / norm)

    @property
    def normal(self) -> np.ndarray:
        return np.array([-self.direction[1], self.direction[0]])

    def signed_distances(self, points: np.ndarray) -> np.ndarray:
        return (np.asarray(points, dtype=float).reshape(-1, 2) - self.point) @ self.normal

    def coordinates(self, points: np.ndarray) -> np.ndarray:
        """Position of each point's foot along the line (from ``point``)."""
        return (np.asarray(points, dtype=float).reshape(-1, 2) - self.point) @ self.direction


def fit_line_tls(points: np.ndarray) -> Line2D:
    """Total-least-squares line through (N >= 2, 2) points: centroid and principal direction."""
    P = np.asarray(points, dtype=float).reshape(-1, 2)
    if len(P) < 2:
        raise ValueError(f"Expected at least 2 points to fit a line, got {len(P)}")
    c = P.mean(0)
    _, vecs = np.linalg.eigh((P - c).T @ (P - c))
    return Line2D(c, vecs[:, 1])


def line_from_plane(normal: np.ndarray, distance: float) -> Line2D | None:
    """Where the plane ``normal . x = distance`` (scan-sensor frame) cuts the scan plane z = 0, or None
    when the plane is (nearly) parallel to it."""
    n = np.asarray(normal, dtype=float)
    g = np.linalg.norm(n[:2])
    if g < 1e-9:
        return None
    m = n[:2] / g
    return Line2D(m * distance / g, np.array([-m[1], m[0]]))


def intersect(a: Line2D, b: Line2D, min_sin: float = 1e-9) -> np.ndarray | None:
    """The crossing point of two lines, or None when they are parallel (|sin angle| < ``min_sin``)."""
    A = np.column_stack([a.direction, -b.direction])
    if abs(np.linalg.det(A)) < min_sin:
        return None
    s = np.linalg.solve(A, b.point - a.point)
    return a.point + s[0] * a.direction
