"""Planes ``n . x = d`` with a unit normal, and the point statistics that fit and score them."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Plane:
    """A plane ``normal . x = distance`` with ``|normal| = 1``.

    The canonical orientation (see :meth:`facing_away`) has ``distance >= 0``: the normal points away
    from the frame's origin (from the sensor towards the board).
    """

    normal: np.ndarray
    distance: float

    def __post_init__(self):
        n = np.asarray(self.normal, dtype=float).reshape(3)
        norm = np.linalg.norm(n)
        if not np.isfinite(norm) or norm < 1e-12:
            raise ValueError(f"Expected a non-zero finite plane normal, got {n}")
        if abs(norm - 1.0) <= 4e-16:  # a unit normal kept as it is: a plane made again from its own normal (read
            norm = 1.0  # back from a file) is the same to the bit, where dividing by a norm an ulp off 1 is not
        object.__setattr__(self, "normal", n / norm)
        object.__setattr__(self, "distance", float(self.distance) / norm)

    @property
    def coefficients(self) -> np.ndarray:
        """``pi = [n; -d]`` so that ``pi . [x; 1]`` is the signed point-to-plane distance."""
        return np.append(self.normal, -self.distance)

    def facing_away(self) -> "Plane":
        """The same plane with ``distance >= 0``."""
        return self if self.distance >= 0 else Plane(-self.normal, -self.distance)

    def signed_distances(self, points: np.ndarray) -> np.ndarray:
        return np.asarray(points) @ self.normal - self.distance

    def transformed(self, T_b_a: np.ndarray) -> "Plane":
        """This plane (given in frame a) expressed in frame b."""
        R, t = T_b_a[:3, :3], T_b_a[:3, 3]
        n_b = R @ self.normal
        return Plane(n_b, self.distance + n_b @ t)


def plane_difference(a: Plane, b: Plane) -> tuple[float, float]:
    """Angle (rad) between the normals of two planes in one frame, and ``a.distance - b.distance`` (m)."""
    return float(np.arccos(np.clip(a.normal @ b.normal, -1.0, 1.0))), float(a.distance - b.distance)


def moment_matrix(points: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """``M = sum_k w_k [p_k; 1][p_k; 1]^T`` (4x4): exact sufficient statistics for point-to-plane sums."""
    P = np.hstack([np.asarray(points, dtype=float), np.ones((len(points), 1))])
    if weights is None:
        return P.T @ P
    return (P * np.asarray(weights, dtype=float)[:, None]).T @ P


def sum_squared_distances(plane_coefficients: np.ndarray, M: np.ndarray) -> float:
    """``sum_k (pi . [p_k; 1])^2 = pi^T M pi`` for ``pi = [n; -d]``."""
    pi = np.asarray(plane_coefficients, dtype=float)
    return float(pi @ M @ pi)


def _sqrt_excess(M: np.ndarray, k: int, rel_tol: float) -> tuple[np.ndarray, float]:
    """``W`` and ``floor`` of a moment matrix, the floor taken over the first ``k`` coordinates' scatter."""
    M = np.asarray(M, dtype=float)
    n = M[3, 3]
    if n <= 0:
        raise ValueError("Expected a moment matrix of at least one point (M[3, 3] > 0)")
    s = M[:k, 3]
    floor = float(np.linalg.eigvalsh(M[:k, :k] - np.outer(s, s) / n)[0])
    E = M.copy()
    E[:k, :k] -= floor * np.eye(k)
    vals, vecs = np.linalg.eigh(E)
    keep = vals > rel_tol * vals[-1]
    return np.sqrt(vals[keep])[:, None] * vecs[:, keep].T, floor


def sqrt_excess_moment(M: np.ndarray, rel_tol: float = 1e-10) -> tuple[np.ndarray, float]:
    """Square-root form of a point set's plane cost: ``W`` (k x 4) and ``floor`` with, for every plane
    ``pi = [n; -d]`` with a unit normal, ``pi^T M pi = |W pi|^2 + floor`` exactly.

    ``floor`` is the cost of the best-fitting plane (the smallest eigenvalue of the scatter, the
    4x4 moment ``M`` being ``sum w [p; 1][p; 1]^T``), so ``|W pi|^2`` is the excess of ``pi`` over the
    best fit: about chi-square with 3 degrees of freedom (times the noise variance) at the true plane.
    Rank ``k`` is 3 for a board seen by a 3D LiDAR; for points on one line (a 2D scan without
    noise) it drops to 2. ``floor`` may be negative for a noise-corrected moment. MATH.md section 2.
    """
    return _sqrt_excess(M, 3, rel_tol)


def sqrt_excess_moment_scan(M: np.ndarray, rel_tol: float = 1e-10) -> tuple[np.ndarray, float]:
    """The scan-line form of :func:`sqrt_excess_moment` for points on a 2D LiDAR's scan plane (z = 0):
    ``W`` (2 x 4) and ``floor`` with ``pi^T M pi = |W pi|^2 + floor |n_xy|^2`` for every plane
    ``pi = [n; -d]``. ``floor`` is the cost of the best-fitting line; dividing ``|W pi|^2`` by
    ``|n_xy|^2`` gives the excess of the plane's trace (a line) over that best line, in the units of the
    points' in-scan-plane residuals. MATH.md section 4."""
    return _sqrt_excess(M, 2, rel_tol)


def plane_from_moment(M: np.ndarray) -> Plane:
    """The plane minimising ``pi^T M pi`` over unit normals (weighted centroid, smallest scatter direction);
    ``M`` may be noise-corrected (see ``LidarBoardObservation.unbiased_range_moment``)."""
    M = np.asarray(M, dtype=float)
    c = M[:3, 3] / M[3, 3]
    scatter = M[:3, :3] - M[3, 3] * np.outer(c, c)
    n = np.linalg.eigh(scatter)[1][:, 0]
    return Plane(n, n @ c).facing_away()


def fit_plane_pca(points: np.ndarray, weights: np.ndarray | None = None) -> Plane:
    """Least-squares (total) plane through points: centroid and the smallest-eigenvalue eigenvector."""
    P = np.asarray(points, dtype=float)
    if len(P) < 3:
        raise ValueError(f"Expected at least 3 points to fit a plane, got {len(P)}")
    w = np.ones(len(P)) if weights is None else np.asarray(weights, dtype=float)
    c = (w[:, None] * P).sum(0) / w.sum()
    Q = P - c
    S = (Q * w[:, None]).T @ Q
    _, vecs = np.linalg.eigh(S)
    n = vecs[:, 0]
    return Plane(n, n @ c).facing_away()


def plane_basis(normal: np.ndarray) -> np.ndarray:
    """A 3x2 orthonormal basis of the plane orthogonal to ``normal``."""
    n = np.asarray(normal, dtype=float)
    a = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(n, a)
    u /= np.linalg.norm(u)
    return np.column_stack([u, np.cross(n, u)])


def on_plane_along_beams(points: np.ndarray, plane: Plane) -> np.ndarray:
    """Where each point's beam from the sensor's origin meets ``plane`` (points (N, 3), sensor frame): the point
    without its range noise, for a point of the plane. A beam nearly parallel to the plane keeps its point."""
    P = np.asarray(points, dtype=float)
    r = np.linalg.norm(P, axis=1)
    cos = (P @ plane.normal) / np.maximum(r, 1e-12)
    ok = np.abs(cos) > 1e-3
    out = P.copy()
    out[ok] = P[ok] * (plane.distance / (cos[ok] * r[ok]))[:, None]
    return out


def cut_with_board(T_board_sensor: np.ndarray, beams: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rays from a sensor's origin along unit ``beams`` (K, 3, sensor frame) cut with a board's plane (z = 0 of
    the board frame): ``(q, s, Rb)``, the cuts in the board frame (K, 3), their distances along the beams, and
    the beams in the board frame. A beam parallel to the board is cut far away (its z taken as 1e-9)."""
    R, t = T_board_sensor[:3, :3], T_board_sensor[:3, 3]
    Rb = np.asarray(beams, dtype=float) @ R.T
    z = np.where(np.abs(Rb[:, 2]) < 1e-9, 1e-9, Rb[:, 2])
    s = -t[2] / z
    return Rb * s[:, None] + t, s, Rb
