"""A rig's joint minima where a camera-scanner pair's own boards leave several (a 2D scanner with few boards), and
its posterior mixed over them, as a single pair's is.

Each such pair's minima (``solution_selection.Mode``, weighed by the pair's own evidence, its segment ends
included) are joint minima too: the joint graph is solved again from each, the scanner started at that minimum's
transform from its camera, everything else at the estimate. The masses are the pair's (its scanner's data alone
tell the minima apart; the other sensors fix the boards alike under each); with two such pairs, the products. Each
joint minimum's posterior is sampled within its cell of the pair's transform (``posterior.ModeCells``) and the
samples mixed by the masses (``rig_posterior.mix_modes``): the intervals then cover every minimum.
"""
from __future__ import annotations

import itertools
from dataclasses import replace

import numpy as np

from ..errors import LidarcamError
from ..solvers.posterior import ModeCells
from ..solvers.rig_graph import solve_rig
from ..solvers.rig_posterior import mix_modes
from .rig_edges import ends_view

# Joint minima sampled at most (the most probable), when two ambiguous pairs multiply their minima.
MAX_JOINT_MODES = 8


def mixable_minima(minima: dict, boards: dict, pair_frames: dict) -> dict:
    """The pairs of ``minima`` (``(camera, lidar) -> modes``) whose minima are the rig's: the pair holds every board
    its scanner gives the graph (``boards``: per LiDAR, by stem; ``pair_frames``: each pair's frames), so its masses
    are the rig's (elsewhere the other pairs' boards may decide); one pair a scanner, as two cameras that saw the
    same boards see the same minima of it, not two to multiply."""
    out: dict = {}
    for (c, d), modes in minima.items():
        if set(boards[d]) <= {f.name for f in pair_frames[(c, d)]} and all(d != e for _, e in out):
            out[(c, d)] = modes
    return out


def joint_starts(minima: dict, T_ref: dict, reference: str) -> list[tuple[dict, float, tuple]]:
    """Every combination of the pairs' minima (``minima``: ``(camera, lidar) -> modes``, the most probable first)
    holding at least ``MIN_MODE_MASS`` of their product, most probable first, at most ``MAX_JOINT_MODES``: the
    start of its joint solve (``T_ref`` with each scanner moved to its minimum's transform from its camera), its
    mass and its cells (``(ModeCells, camera, lidar, k)`` per pair). A pair whose scanner is the rig's reference
    (which is not moved) is left out."""
    links = [(c, d, modes) for (c, d), modes in minima.items() if len(modes) > 1 and d != reference]
    if not links:
        return []
    from ..solvers.solution_selection import MIN_MODE_MASS  # a 2D scanner's (scipy.optimize: here, when needed)

    cells = [ModeCells([m.refinement for m in modes]) for _, _, modes in links]
    combos = []
    for ks in itertools.product(*(range(len(modes)) for _, _, modes in links)):
        mass = float(np.prod([modes[k].mass for (_, _, modes), k in zip(links, ks)]))
        if mass < MIN_MODE_MASS and any(ks):
            continue
        start = dict(T_ref)
        for (c, d, modes), k in zip(links, ks):
            if k:
                start[d] = T_ref[c] @ modes[k].T_camera_lidar
        combos.append((start, mass, tuple((mc, c, d, k) for mc, (c, d, _), k in zip(cells, links, ks))))
    first, rest = combos[0], sorted(combos[1:], key=lambda s: -s[1])
    return [first] + rest[:MAX_JOINT_MODES - 1]


def in_cells(solution, cells: tuple) -> bool:
    """Whether ``solution`` lies in each of its pairs' cells (a joint solve from one minimum can slide to another)."""
    for mode_cells, c, d, k in cells:
        T = np.linalg.inv(solution.T_ref[c]) @ solution.T_ref[d]
        if mode_cells.nearest(T[None, :3, :3], T[None, :3, 3])[0] != k:
            return False
    return True


def minimum_solver(solution, camera_views: list, lidar_views: list, with_ends: frozenset, board, lidar_obs: dict):
    """The ``solve(T_ref_start)`` of :func:`mixed_posterior`: the joint graph of ``solution`` solved again from a
    start, each scanner of ``with_ends`` (its pairs solved with their segment ends) with its ends assigned to the
    board's sides under that start (``rig_edges.ends_view``, its boards ``lidar_obs``), at the ends' scatter and
    scale of the estimate; it returns the minimum and the LiDAR views it was solved with."""
    def solve(start: dict):
        lvs = [replace(ends_view(lv, board, lidar_obs[lv.name], start[lv.name], solution.T_ref_board),
                       edge_tau_m=lv.edge_tau_m, edge_scale=lv.edge_scale)
               if lv.edges and lv.name in with_ends else lv for lv in lidar_views]
        return solve_rig(solution.names, solution.reference, camera_views, lvs, start, solution.T_ref_board,
                         False), lvs
    return solve


def mixed_posterior(solution, minima: dict, solve, sample, rng: np.random.Generator, warnings: list[str]):
    """The rig's posterior about ``solution`` (``sample(solution, views, cells)`` draws one; ``views`` None: the
    LiDAR views of the estimate), mixed over the joint minima of the pairs with several (``minima``; module
    docstring) that ``solve(T_ref_start)`` reaches within their cells (it returns the minimum and the LiDAR views
    it was solved with: a scanner's ends assigned to the board's sides under that start, as its pair's refinement
    of that minimum assigned them); a minimum that slides to another's, or cannot be solved or sampled, is said in
    ``warnings`` and its mass given to the rest."""
    starts = joint_starts(minima, solution.T_ref, solution.reference)
    if not starts or not in_cells(solution, starts[0][2]):  # (the joint graph moved off its pair's first minimum)
        return sample(solution, None, ())
    parts = [(sample(solution, None, starts[0][2]), starts[0][1])]
    for start, mass, cells in starts[1:]:
        try:
            other, views = solve(start)
            if not in_cells(other, cells):
                raise LidarcamError("solved from its pair's, it slid to another")
            parts.append((sample(other, views, cells), mass))
        except LidarcamError as exc:
            warnings.append(f"a joint minimum ({mass:.0%} of the mass) is not in the posterior ({exc.message}): "
                            "the posterior mixes the others")
    if len(parts) == 1:
        return parts[0][0]
    return replace(mix_modes(parts, rng), mixed=tuple(sorted({(c, d) for _, c, d, _ in starts[0][2]})))
