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

# |det N| of the three unit normals below which the trihedron vertex is ill-conditioned (the normals nearly
# coplanar: boards that all turn about one axis), and |sin| of the angle between two laser lines below which
# their crossing point is. Such a triple is still solved and reported as weak: its solutions compete on their
# laser cost over all boards, so they win only where they fit (the conditioning weighs, it does not veto).
MIN_NORMAL_DET = 0.02
MIN_LINE_SIN = 0.05
# Below these the triple carries no solution at all (the vertex or a crossing point is at infinity).
DEGENERATE_NORMAL_DET = 1e-6
DEGENERATE_LINE_SIN = 1e-4
_SCAN_SAMPLES = 800


@dataclass(frozen=True, eq=False)
class TripleSolutions:
    """All solutions of one triple of boards, or none and the reason (``degenerate``)."""

    triple: tuple[int, int, int]
    T_camera_lidar: tuple[np.ndarray, ...]
    degenerate: str | None = None
    # Why the triple is ill-conditioned though solved (normals nearly coplanar, laser lines nearly parallel).
    weak: str | None = None
    # Per solution: smallest over largest singular value of the edge system's Jacobian there. Near 0 the
    # solution sits on the P3P danger surface (two roots merging) and is ill-conditioned.
    conditioning: tuple[float, ...] = ()


def _edge_equations(lam: np.ndarray, c: np.ndarray, D2: np.ndarray) -> np.ndarray:
    """The three distance equations at ``lam`` (..., 3) for cosines ``c`` and distances ``D2`` (..., 3)."""
    a, b, e = np.moveaxis(np.asarray(lam), -1, 0)
    c, D2 = np.asarray(c), np.asarray(D2)
    return np.stack([a * a + b * b - 2 * a * b * c[..., 0] - D2[..., 0],
                     a * a + e * e - 2 * a * e * c[..., 1] - D2[..., 1],
                     b * b + e * e - 2 * b * e * c[..., 2] - D2[..., 2]], axis=-1)


def _edge_jacobian(lam: np.ndarray, c: np.ndarray) -> np.ndarray:
    a, b, e = np.moveaxis(np.asarray(lam), -1, 0)
    c = np.asarray(c)
    zero = np.zeros_like(a)
    rows = [[2 * a - 2 * b * c[..., 0], 2 * b - 2 * a * c[..., 0], zero],
            [2 * a - 2 * e * c[..., 1], zero, 2 * e - 2 * a * c[..., 1]],
            [zero, 2 * b - 2 * e * c[..., 2], 2 * e - 2 * b * c[..., 2]]]
    return np.stack([np.stack(r, axis=-1) for r in rows], axis=-2)


def edge_conditioning(lam: np.ndarray, c: np.ndarray) -> np.ndarray | float:
    """Reciprocal condition number of the edge system's Jacobian at ``lam`` (one or a stack)."""
    sv = np.linalg.svd(_edge_jacobian(lam, c), compute_uv=False)
    out = np.where(sv[..., 0] > 0, sv[..., -1] / np.where(sv[..., 0] > 0, sv[..., 0], 1.0), 0.0)
    return float(out) if out.ndim == 0 else out


def _polish(lam: np.ndarray, c: np.ndarray, D2: np.ndarray, steps: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """Gauss-Newton on the three distance equations for a stack of starts (K, 3), each with its own ``c``
    and ``D2`` (K, 3); a start stops moving once its step is negligible. Returns the points and their
    residual norms."""
    lam = np.array(lam, dtype=float)
    active = np.ones(len(lam), dtype=bool)
    for _ in range(steps):
        if not active.any():
            break
        J, r = _edge_jacobian(lam[active], c[active]), _edge_equations(lam[active], c[active], D2[active])
        try:
            step = np.linalg.solve(J, -r[..., None])[..., 0]
        except np.linalg.LinAlgError:  # a singular Jacobian (a double root): least squares for each
            step = np.array([np.linalg.lstsq(Jk, -rk, rcond=None)[0] for Jk, rk in zip(J, r)])
        lam[active] += step
        idx = np.nonzero(active)[0]
        active[idx] = np.linalg.norm(step, axis=1) >= 1e-13 * (1 + np.linalg.norm(lam[idx], axis=1))
    return lam, np.linalg.norm(_edge_equations(lam, c, D2), axis=-1)


def solve_p3p_edges(c: np.ndarray, D2: np.ndarray, near_tol: float = 0.01) -> list[np.ndarray]:
    """All real ``(lambda_01, lambda_02, lambda_12)`` of the edge system: ``c`` the cosines between edge pairs
    (01,02), (01,12), (02,12) and ``D2`` the squared distances between the corresponding crossing points.

    ``near_tol`` (relative to the distances) admits near-tangent minima that Gauss-Newton then closes."""
    return solve_p3p_edges_batch(np.asarray(c, dtype=float)[None], np.asarray(D2, dtype=float)[None], near_tol)[0]


def solve_p3p_edges_batch(c: np.ndarray, D2: np.ndarray, near_tol: float = 0.01) -> list[list[np.ndarray]]:
    """``solve_p3p_edges`` for M systems at once (``c``, ``D2``: (M, 3)): one vectorised scan, bisection and
    Gauss-Newton over all of them, so that all C(N, 3) triples of a 2D calibration cost a few array passes."""
    c, D2 = np.asarray(c, dtype=float), np.asarray(D2, dtype=float)
    M = len(c)
    s0 = np.sqrt(np.maximum(1 - c[:, 0] ** 2, 1e-15))
    s1 = np.sqrt(np.maximum(1 - c[:, 1] ** 2, 1e-15))
    L = np.minimum(np.sqrt(D2[:, 0]) / s0, np.sqrt(D2[:, 1]) / s1)
    # Cosine spacing resolves the ends of the range, where the branches meet with infinite slope.
    x = L[:, None] * np.cos(np.linspace(np.pi, 0.0, _SCAN_SAMPLES))[None, :]  # (M, S)
    signs = np.array([(-1.0, -1.0), (-1.0, 1.0), (1.0, -1.0), (1.0, 1.0)])

    def branches(xv, cc, dd, sg):
        """Values along the four sign branches; every argument broadcasts (cosines and distances last-axis 3)."""
        rb = np.sqrt(np.maximum(dd[..., 0] - xv * xv * (1 - cc[..., 0] ** 2), 0.0))
        re = np.sqrt(np.maximum(dd[..., 1] - xv * xv * (1 - cc[..., 1] ** 2), 0.0))
        bv = xv * cc[..., 0] + sg[..., 0] * rb
        ev = xv * cc[..., 1] + sg[..., 1] * re
        return bv, ev, bv * bv + ev * ev - 2 * bv * ev * cc[..., 2] - dd[..., 2]

    # (M, 4, S): every system's four sign branches at once.
    b, e, f = branches(x[:, None, :], c[:, None, None, :], D2[:, None, None, :], signs[None, :, None, :])
    scale = np.max(D2, axis=1)
    owner, starts = [], []
    # Sign changes: vectorised bisection inside every bracket (close roots stay apart), then Gauss-Newton.
    m, br, k = np.nonzero(np.sign(f[..., :-1]) * np.sign(f[..., 1:]) < 0)
    if len(m):
        lo, hi, sg, cc, dd = x[m, k], x[m, k + 1], signs[br], c[m], D2[m]
        f_lo = f[m, br, k]
        for _ in range(22):  # then Gauss-Newton finishes the root
            mid = 0.5 * (lo + hi)
            fm = branches(mid, cc, dd, sg)[2]
            left = np.sign(fm) == np.sign(f_lo)
            lo, f_lo = np.where(left, mid, lo), np.where(left, fm, f_lo)
            hi = np.where(left, hi, mid)
        root = 0.5 * (lo + hi)
        rb_, re_, _ = branches(root, cc, dd, sg)
        owner.append(m)
        starts.append(np.column_stack([root, rb_, re_]))
    # Near-tangent local minima of |f| with no sign change beside them (a double root that noise pushed
    # just off the real line).
    af = np.abs(f)
    same = (np.sign(f[..., :-2]) == np.sign(f[..., 1:-1])) & (np.sign(f[..., 1:-1]) == np.sign(f[..., 2:]))
    m, br, k = np.nonzero(same & (af[..., 1:-1] < af[..., :-2]) & (af[..., 1:-1] <= af[..., 2:])
                          & (af[..., 1:-1] < near_tol * scale[:, None, None]))
    owner.append(m)
    starts.append(np.column_stack([x[m, k + 1], b[m, br, k + 1], e[m, br, k + 1]]))
    owner, starts = np.concatenate(owner), np.concatenate(starts)
    # Per system: its sign-change roots first, then its near-tangent ones (a stable sort keeps that order).
    order = np.argsort(owner, kind="stable")
    owner, starts = owner[order], starts[order]
    lam, res = _polish(starts, c[owner], D2[owner], steps=12)
    found: list[list[np.ndarray]] = [[] for _ in range(M)]
    for j, (i, ok) in enumerate(zip(owner, res < 1e-9 * scale[owner])):
        if ok and not any(np.linalg.norm(lam[j] - g) < 1e-7 * (1 + L[i]) for g in found[i]):
            found[i].append(lam[j])
    return found


def solve_three_boards(camera_planes: list[Plane], lidar_lines: list[Line2D],
                       triple: tuple[int, int, int] = (0, 1, 2)) -> TripleSolutions:
    """Every ``T_camera_lidar`` that puts the three laser lines (LiDAR scan plane, z = 0) on the three
    board planes (camera frame, ``normal . x = distance``), with the LiDAR in front of every board."""
    triple = tuple(triple)
    return _solve_trihedra([_trihedron(camera_planes, lidar_lines, triple)], [triple])[0]


def _trihedron(planes: list[Plane], lines: list[Line2D], triple: tuple[int, int, int]):
    """The vertex, edges, crossing points, cosines and distances of one triple, or the reason it is degenerate."""
    N = np.array([p.normal for p in planes])
    d = np.array([p.distance for p in planes])
    det = abs(np.linalg.det(N))
    if det < DEGENERATE_NORMAL_DET:
        return f"board normals coplanar (|det| {det:.1e})"
    weak = [f"board normals nearly coplanar (|det| {det:.3f})"] if det < MIN_NORMAL_DET else []
    V = np.linalg.solve(N, d)
    pairs = ((0, 1), (0, 2), (1, 2))
    edges, q = [], []
    for a, b in pairs:
        e = np.cross(N[a], N[b])
        edges.append(e / np.linalg.norm(e))
        u, v = lines[a].direction, lines[b].direction
        sin = abs(u[0] * v[1] - u[1] * v[0])
        if sin < DEGENERATE_LINE_SIN:
            return f"laser lines {triple[a]} and {triple[b]} parallel"
        if sin < MIN_LINE_SIN:
            weak.append(f"laser lines {triple[a]} and {triple[b]} nearly parallel "
                        f"(angle {np.degrees(np.arcsin(sin)):.1f} deg)")
        q.append(np.append(intersect(lines[a], lines[b]), 0.0))
    q = np.array(q)
    # Points 0, 1, 2 sit on edges 01, 02, 12; distances between them pair the edges as (01,02), (01,12), (02,12).
    D2 = np.array([np.sum((q[0] - q[1]) ** 2), np.sum((q[0] - q[2]) ** 2), np.sum((q[1] - q[2]) ** 2)])
    spread = np.sqrt(D2.max())
    area = 0.5 * np.linalg.norm(np.cross(q[1] - q[0], q[2] - q[0]))
    if area < 1e-4 * spread**2 or spread < 1e-6:
        return "the laser lines cross in (nearly) one point: the scan plane runs through the boards' common vertex"
    edges = np.array(edges)
    c = np.array([edges[0] @ edges[1], edges[0] @ edges[2], edges[1] @ edges[2]])
    return N, d, V, edges, q, c, D2, "; ".join(weak) or None


def solve_triples(planes: list[Plane], lines: list[Line2D], triples: list[tuple[int, int, int]]
                  ) -> list[TripleSolutions]:
    """``solve_three_boards`` for many triples of one calibration's boards at once (the edge systems of all of
    them are solved in one batch)."""
    return _solve_trihedra([_trihedron([planes[i] for i in tri], [lines[i] for i in tri], tri) for tri in triples],
                           triples)


def _solve_trihedra(geo: list, triples: list[tuple[int, int, int]]) -> list[TripleSolutions]:
    """The solutions of each triple's trihedron (``_trihedron``'s result, or the reason it is degenerate)."""
    good = [i for i, g in enumerate(geo) if not isinstance(g, str)]
    roots = solve_p3p_edges_batch(np.array([geo[i][5] for i in good]).reshape(-1, 3),
                                  np.array([geo[i][6] for i in good]).reshape(-1, 3)) if good else []
    out = [TripleSolutions(tri, (), g) if isinstance(g, str) else None for tri, g in zip(triples, geo)]
    # Every solution's rigid transform in one batched Kabsch: crossing points (LiDAR) onto edge points (camera).
    owner = [i for i, r in zip(good, roots) for _ in r]
    lams = [lam for r in roots for lam in r]
    if lams:
        lam = np.array(lams)
        Q = np.array([geo[i][4] for i in owner])
        P = np.array([geo[i][2] for i in owner])[:, None, :] + lam[:, :, None] * np.array([geo[i][3] for i in owner])
        Ts = T_align(Q, P)
        cond = np.atleast_1d(edge_conditioning(lam, np.array([geo[i][5] for i in owner])))
    roots_of: dict[int, list[int]] = {}  # each triple's rows of the batch
    for j, o in enumerate(owner):
        roots_of.setdefault(o, []).append(j)
    for i in good:
        N, d = geo[i][0], geo[i][1]
        sols, conds = [], []
        for j in roots_of.get(i, ()):
            # The LiDAR sits on the camera's side of every board (the camera at the origin has n . 0 - d < 0).
            if np.all(N @ Ts[j][:3, 3] - d < 0):
                sols.append(Ts[j])
                conds.append(float(cond[j]))
        out[i] = TripleSolutions(triples[i], tuple(sols), None, geo[i][7], tuple(conds))
    return out
