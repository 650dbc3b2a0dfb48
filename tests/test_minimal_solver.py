"""The 2D minimal solver: on noise-free triples every real root is found, the truth among them, and
degenerate triples are reported with the reason."""
from __future__ import annotations

import numpy as np

from estimators.solvers.minimal_solver import edge_conditioning, solve_p3p_edges, solve_three_boards
from geometry.lines import Line2D, fit_line_tls, intersect, line_from_plane
from geometry.planes import Plane
from geometry.rotations import R_from_rotvec, T_from_Rt, T_inverse, rotation_error

# LiDAR x forward, y left, z up; camera x right, y down, z forward.
R_CAMERA_LIDAR = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])


def _random_rig(rng):
    R = R_from_rotvec(rng.normal(0.0, 0.1, 3)) @ R_CAMERA_LIDAR
    return T_from_Rt(R, rng.normal(0.0, 0.1, 3))


def _random_board(rng, T_cl):
    """A board plane (camera frame) facing the sensors, centred on the scan plane 1.5-4 m ahead."""
    R, t = T_cl[:3, :3], T_cl[:3, 3]
    while True:
        c = R @ np.array([rng.uniform(1.5, 4.0), rng.uniform(-1.5, 1.5), 0.0]) + t
        n = rng.normal(size=3)
        n /= np.linalg.norm(n)
        ray = c / np.linalg.norm(c)
        n = n if n @ ray > 0 else -n
        if n @ ray > 0.4:
            return Plane(n, n @ c)


def _laser_line(T_cl, plane):
    T_lc = T_inverse(T_cl)
    return line_from_plane(T_lc[:3, :3] @ plane.normal, plane.distance - plane.normal @ T_cl[:3, 3])


def test_line_fit_and_intersection():
    rng = np.random.default_rng(0)
    line = Line2D([1.0, 2.0], [3.0, 4.0])
    pts = line.point + np.outer(rng.uniform(-1, 1, 50), line.direction)
    fit = fit_line_tls(pts)
    np.testing.assert_allclose(np.abs(fit.direction @ line.direction), 1.0, atol=1e-12)
    np.testing.assert_allclose(line.signed_distances(pts), 0.0, atol=1e-12)
    other = Line2D([0.0, 0.0], [1.0, 0.0])
    x = intersect(line, other)
    assert abs(line.signed_distances(x)[0]) < 1e-12 and abs(x[1]) < 1e-12
    assert intersect(other, Line2D([0.0, 1.0], [2.0, 0.0])) is None
    assert line_from_plane([0.0, 0.0, 1.0], 1.0) is None  # parallel to the scan plane


def test_edge_system_roots_satisfy_it_and_come_in_sign_pairs():
    rng = np.random.default_rng(1)
    for _ in range(50):
        lam = rng.uniform(-3, 3, 3)
        c = rng.uniform(-0.9, 0.9, 3)
        D2 = np.array([lam[0] ** 2 + lam[1] ** 2 - 2 * lam[0] * lam[1] * c[0],
                       lam[0] ** 2 + lam[2] ** 2 - 2 * lam[0] * lam[2] * c[1],
                       lam[1] ** 2 + lam[2] ** 2 - 2 * lam[1] * lam[2] * c[2]])
        if np.min(D2) < 1e-3:
            continue
        roots = solve_p3p_edges(c, D2)
        assert len(roots) % 2 == 0 and len(roots) <= 8
        if edge_conditioning(lam, c) > 1e-3:
            assert min(np.linalg.norm(r - lam) for r in roots) < 1e-7
        for r in roots:
            assert min(np.linalg.norm(-r - g) for g in roots) < 1e-7


def test_truth_is_among_the_solutions_of_random_noise_free_triples():
    """300 random rigs and board triples: every well-conditioned non-degenerate triple's solutions include
    the truth to 1e-7 (the ill-conditioned ones sit on the P3P danger surface, where two roots merge)."""
    rng = np.random.default_rng(2)
    found = total = 0
    counts = []
    for _ in range(300):
        T = _random_rig(rng)
        planes = [_random_board(rng, T) for _ in range(3)]
        res = solve_three_boards(planes, [_laser_line(T, p) for p in planes])
        if res.degenerate:
            assert res.T_camera_lidar == ()
            continue
        counts.append(len(res.T_camera_lidar))
        errs = [rotation_error(S[:3, :3], T[:3, :3]) + np.linalg.norm(S[:3, 3] - T[:3, 3]) for S in res.T_camera_lidar]
        best = int(np.argmin(errs)) if errs else -1
        if best >= 0 and res.conditioning[best] < 1e-3:
            continue
        total += 1
        found += bool(errs) and min(errs) < 1e-7
        # Every solution puts all three laser lines on their boards.
        for S in res.T_camera_lidar:
            for p in planes:
                line = _laser_line(S, p)
                assert line is not None
    assert total > 200 and found == total
    assert max(counts) <= 8


def test_degenerate_triples_are_reported():
    rng = np.random.default_rng(3)
    T = _random_rig(rng)
    # Boards all turned about the camera's vertical axis: normals coplanar, no trihedron vertex.
    flat = [Plane([np.sin(a), 0.0, np.cos(a)], 3.0) for a in (-0.4, 0.0, 0.5)]
    res = solve_three_boards(flat, [_laser_line(T, p) for p in flat])
    assert res.degenerate is not None and "coplanar" in res.degenerate and res.T_camera_lidar == ()
    # Two boards parallel to each other: their laser lines are parallel.
    planes = [Plane([0.0, 0.3, 1.0], 3.0), Plane([0.0, 0.3, 1.0], 4.0), Plane([0.6, -0.2, 1.0], 3.5)]
    res = solve_three_boards(planes, [_laser_line(T, p) for p in planes])
    assert res.degenerate is not None and res.T_camera_lidar == ()


def test_lidar_behind_a_board_is_not_a_solution():
    """Over 40 noise-free triples: the edge system's roots include rigs that put the LiDAR behind a board (on its
    side the camera does not see) in some triples, and the solver drops exactly those; every root it returns has
    the LiDAR in front of all three boards, and the truth is among them."""
    from estimators.solvers.minimal_solver import _trihedron, solve_p3p_edges
    from geometry.rotations import T_align

    rng = np.random.default_rng(4)
    dropped = 0
    for _ in range(40):
        T = _random_rig(rng)
        planes = [_random_board(rng, T) for _ in range(3)]
        lines = [_laser_line(T, p) for p in planes]
        res = solve_three_boards(planes, lines)
        assert res.degenerate is None
        N, d, V, edges, q, c, D2, _ = _trihedron(planes, lines, (0, 1, 2))
        every = [T_align(q[None], (V + lam[:, None] * edges)[None])[0] for lam in solve_p3p_edges(c, D2)]
        front = [S for S in every if np.all(N @ S[:3, 3] - d < 0)]
        dropped += len(every) - len(front)
        assert len(res.T_camera_lidar) == len(front)
        for S in res.T_camera_lidar:
            assert all(p.normal @ S[:3, 3] < p.distance for p in planes)
        assert min(np.degrees(rotation_error(S[:3, :3], T[:3, :3])) + np.linalg.norm(S[:3, 3] - T[:3, 3])
                   for S in res.T_camera_lidar) < 1e-6
    assert dropped > 0