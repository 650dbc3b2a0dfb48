"""The 2D LiDAR minimal solver: ``T_camera_lidar`` from three boards (MATH.md section 4).

Three board planes (camera frame) meet at the trihedron vertex ``V``; the edge where boards a and b meet
runs through ``V`` along ``e_ab = n_a x n_b``. The scan plane cuts the three edges at the points where the
boards' laser lines cross (``q_ab``, known in the LiDAR frame), so ``V + lambda_ab e_ab = R q_ab + t``.
The three crossing points keep their mutual distances, which gives a P3P system with ``V`` as the centre
and the edges as bearings:

    lambda_a^2 + lambda_b^2 - 2 lambda_a lambda_b cos(theta_ab) = D_ab^2   for the three pairs of edges.

Edges are whole lines, so ``-lambda`` solves it too: up to 8 real solutions. They are found here by
scanning the one free unknown over its whole feasible range on the four sign branches of the other two
(every sign change is a root; near-tangent minima, roots that noise pushed off the real line, are
kept when Gauss-Newton on the three equations closes them), then each solution is the rigid transform
that carries the three crossing points onto the edges (Kabsch). All of them fit the three boards
exactly; physically impossible ones (the LiDAR behind a board) are dropped.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from geometry.lines import Line2D, intersect
from geometry.planes import Plane
from geometry.rotations import T_align

# |det N| of the three unit normals below which the trihedron vertex is ill-defined (the normals nearly
# coplanar: boards that all turn about one axis).
MIN_NORMAL_DET = 0.02
# |sin| of the angle between two laser lines below which their crossing point is ill-defined.
MIN_LINE_SIN = 0.05
_SCAN_SAMPLES = 800


@dataclass(frozen=True, eq=False)
class TripleSolutions:
    """All solutions of one triple of boards, or none and the reason (``degenerate``)."""

    triple: tuple[int, int, int]
    T_camera_lidar: tuple[np.ndarray, ...]
    degenerate: str | None = None
    # Per solution: smallest over largest singular value of the edge system's Jacobian there. Near 0 the
    # solution sits on the P3P danger surface (two roots merging) and is ill-conditioned.
    conditioning: tuple[float, ...] = ()


def _edge_equations(lam: np.ndarray, c: np.ndarray, D2: np.ndarray) -> np.ndarray:
    a, b, e = lam
    return np.array([a * a + b * b - 2 * a * b * c[0] - D2[0],
                     a * a + e * e - 2 * a * e * c[1] - D2[1],
                     b * b + e * e - 2 * b * e * c[2] - D2[2]])


def _edge_jacobian(lam: np.ndarray, c: np.ndarray) -> np.ndarray:
    a, b, e = lam
    return np.array([[2 * a - 2 * b * c[0], 2 * b - 2 * a * c[0], 0.0],
                     [2 * a - 2 * e * c[1], 0.0, 2 * e - 2 * a * c[1]],
                     [0.0, 2 * b - 2 * e * c[2], 2 * e - 2 * b * c[2]]])


def edge_conditioning(lam: np.ndarray, c: np.ndarray) -> float:
    """Reciprocal condition number of the edge system's Jacobian at ``lam``."""
    sv = np.linalg.svd(_edge_jacobian(lam, c), compute_uv=False)
    return float(sv[-1] / sv[0]) if sv[0] > 0 else 0.0


def _polish(lam: np.ndarray, c: np.ndarray, D2: np.ndarray, steps: int = 8) -> tuple[np.ndarray, float]:
    """Gauss-Newton on the three distance equations; returns the point and its residual norm."""
    for _ in range(steps):
        J = _edge_jacobian(lam, c)
        r = _edge_equations(lam, c, D2)
        try:
            step = np.linalg.solve(J, -r)
        except np.linalg.LinAlgError:
            step = np.linalg.lstsq(J, -r, rcond=None)[0]
        lam = lam + step
        if np.linalg.norm(step) < 1e-13 * (1 + np.linalg.norm(lam)):
            break
    return lam, float(np.linalg.norm(_edge_equations(lam, c, D2)))


def solve_p3p_edges(c: np.ndarray, D2: np.ndarray, near_tol: float = 0.01) -> list[np.ndarray]:
    """All real ``(lambda_01, lambda_02, lambda_12)`` of the edge system: ``c`` the cosines between edge pairs
    (01,02), (01,12), (02,12) and ``D2`` the squared distances between the corresponding crossing points.

    ``near_tol`` (relative to the distances) admits near-tangent minima that Gauss-Newton then closes."""
    s0, s1 = np.sqrt(max(1 - c[0] ** 2, 1e-15)), np.sqrt(max(1 - c[1] ** 2, 1e-15))
    L = min(np.sqrt(D2[0]) / s0, np.sqrt(D2[1]) / s1)
    # Cosine spacing resolves the ends of the range, where the branches meet with infinite slope.
    x = L * np.cos(np.linspace(np.pi, 0.0, _SCAN_SAMPLES))
    signs = np.array([(-1.0, -1.0), (-1.0, 1.0), (1.0, -1.0), (1.0, 1.0)])

    def branches(xv, sg):
        rb = np.sqrt(np.maximum(D2[0] - xv * xv * (1 - c[0] ** 2), 0.0))
        re = np.sqrt(np.maximum(D2[1] - xv * xv * (1 - c[1] ** 2), 0.0))
        bv = xv * c[0] + sg[..., 0] * rb
        ev = xv * c[1] + sg[..., 1] * re
        return bv, ev, bv * bv + ev * ev - 2 * bv * ev * c[2] - D2[2]

    b, e, f = branches(x[None, :], signs[:, None, :])  # (4, S): the four sign branches at once
    scale = float(np.max(D2))
    starts = []
    # Sign changes: vectorised bisection inside every bracket (close roots stay apart), then Gauss-Newton.
    br, k = np.nonzero(np.sign(f[:, :-1]) * np.sign(f[:, 1:]) < 0)
    if len(br):
        lo, hi, sg = x[k], x[k + 1], signs[br]
        f_lo = f[br, k]
        for _ in range(22):  # then Gauss-Newton finishes the root
            mid = 0.5 * (lo + hi)
            fm = branches(mid, sg)[2]
            left = np.sign(fm) == np.sign(f_lo)
            lo, f_lo = np.where(left, mid, lo), np.where(left, fm, f_lo)
            hi = np.where(left, hi, mid)
        root = 0.5 * (lo + hi)
        rb_, re_, _ = branches(root, sg)
        starts += [np.array(v) for v in zip(root, rb_, re_)]
    # Near-tangent local minima of |f| with no sign change beside them (a double root that noise pushed
    # just off the real line).
    af = np.abs(f)
    same = (np.sign(f[:, :-2]) == np.sign(f[:, 1:-1])) & (np.sign(f[:, 1:-1]) == np.sign(f[:, 2:]))
    br, k = np.nonzero(same & (af[:, 1:-1] < af[:, :-2]) & (af[:, 1:-1] <= af[:, 2:])
                       & (af[:, 1:-1] < near_tol * scale))
    starts += [np.array([x[kk + 1], b[j, kk + 1], e[j, kk + 1]]) for j, kk in zip(br, k)]
    found: list[np.ndarray] = []
    for lam0 in starts:
        lam, res = _polish(lam0, c, D2, steps=12)
        if res < 1e-9 * scale and not any(np.linalg.norm(lam - g) < 1e-7 * (1 + L) for g in found):
            found.append(lam)
    return found


def solve_three_boards(camera_planes: list[Plane], lidar_lines: list[Line2D],
                       triple: tuple[int, int, int] = (0, 1, 2)) -> TripleSolutions:
    """Every ``T_camera_lidar`` that puts the three laser lines (LiDAR scan plane, z = 0) on the three
    board planes (camera frame, ``normal . x = distance``), with the LiDAR in front of every board."""
    N = np.array([p.normal for p in camera_planes])
    d = np.array([p.distance for p in camera_planes])
    det = abs(np.linalg.det(N))
    if det < MIN_NORMAL_DET:
        return TripleSolutions(triple, (), f"board normals nearly coplanar (|det| {det:.3f})")
    V = np.linalg.solve(N, d)
    pairs = ((0, 1), (0, 2), (1, 2))
    edges, q = [], []
    for a, b in pairs:
        e = np.cross(N[a], N[b])
        edges.append(e / np.linalg.norm(e))
        u, v = lidar_lines[a].direction, lidar_lines[b].direction
        sin = abs(u[0] * v[1] - u[1] * v[0])
        if sin < MIN_LINE_SIN:
            return TripleSolutions(triple, (), f"laser lines {triple[a]} and {triple[b]} nearly parallel")
        q.append(np.append(intersect(lidar_lines[a], lidar_lines[b]), 0.0))
    q = np.array(q)
    # Points 0, 1, 2 sit on edges 01, 02, 12; distances between them pair the edges as (01,02), (01,12), (02,12).
    D2 = np.array([np.sum((q[0] - q[1]) ** 2), np.sum((q[0] - q[2]) ** 2), np.sum((q[1] - q[2]) ** 2)])
    spread = np.sqrt(D2.max())
    area = 0.5 * np.linalg.norm(np.cross(q[1] - q[0], q[2] - q[0]))
    if area < 1e-4 * spread**2 or spread < 1e-6:
        return TripleSolutions(triple, (), "the laser lines cross in (nearly) one point: the scan plane runs through "
                                           "the boards' common vertex")
    c = np.array([edges[0] @ edges[1], edges[0] @ edges[2], edges[1] @ edges[2]])
    solutions, conditioning = [], []
    for lam in solve_p3p_edges(c, D2):
        P = V + lam[:, None] * np.array(edges)
        T = T_align(q, P)
        t = T[:3, 3]
        # The LiDAR sits on the camera's side of every board (the camera at the origin has n . 0 - d < 0).
        if np.all(N @ t - d < 0):
            solutions.append(T)
            conditioning.append(edge_conditioning(lam, c))
    return TripleSolutions(triple, tuple(solutions), None, tuple(conditioning))
