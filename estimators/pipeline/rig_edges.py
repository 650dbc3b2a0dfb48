"""A rig's board edges: every LiDAR's ring or segment ends in the joint graph (``--edges``), or each 3D
camera-LiDAR pair's outline check under the joint estimate.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..errors import LidarcamError
from ..io.rig_dataset import RigDataset
from geometry.rotations import T_log

from ..solvers.board_edges import edge_scatter
from ..solvers.edges_in_graph import (EDGE_ROUNDS, conflict_covariance, edges_left_out, hausman,
                                      lidar_crossings, outline_statistics)
from ..solvers.outline_check import outline_check
from ..solvers.graph_keys import edge_shift_key, outline_key
from ..solvers.rig_graph import RigSolution, outline_covariance, pair_board_covariance, solve_rig


def with_edges(rig: RigDataset, names: tuple, camera_views: list, lidar_views: list, lidar_obs: dict,
               solution: RigSolution, T_ref: dict, T_ref_board: dict, refine_intrinsics: bool, which: set,
               default: bool = False, pair_frames: dict | None = None) -> tuple[list, RigSolution, dict,
                                                                              np.ndarray | None]:
    """:func:`_with_edges`; by ``default`` (``--edges`` not given), a 3D LiDAR whose edges carry its pose while
    something at the boards' sides moved them (``edges_in_graph.edges_left_out``) has them left out, as a single
    pair's, and the rest solved again: its record then says why (``left_out``) and keeps its pose and record with
    the edges (``with_edges``)."""
    out = _with_edges(rig, names, camera_views, lidar_views, lidar_obs, solution, T_ref, T_ref_board,
                      refine_intrinsics, which, pair_frames)
    left = {n: why for n, r in out[2].items() if default and (why := edges_left_out(r)) is not None}
    if not left:
        return out
    rest = which - set(left)  # the others' edges, solved again without the left-out ones
    views, solved, records, share = with_edges(rig, names, camera_views, lidar_views, lidar_obs, solution, T_ref,
                                               T_ref_board, refine_intrinsics, rest, default, pair_frames) if rest \
        else \
        (lidar_views, solution, {}, None)
    records = dict(records)
    for n, why in left.items():
        records[n] = {"used": False, "left_out": why, "with_edges": {"T_ref": out[1].T_ref[n].tolist(), **out[2][n]}}
    return views, solved, records, share


def _with_edges(rig: RigDataset, names: tuple, camera_views: list, lidar_views: list, lidar_obs: dict,
                solution: RigSolution, T_ref: dict, T_ref_board: dict, refine_intrinsics: bool, which: set,
                pair_frames: dict | None = None) -> tuple[list, RigSolution, dict, np.ndarray | None]:
    """The joint graph with every LiDAR's board edges, as the single pair's ``--edges`` has them
    (``solvers.board_edges``): each frame's ring ends (a scan's segment ends) assigned to the board's sides under
    the planes' estimate, an outline shift per LiDAR and frame (0 +- the boards' in-plane scatter) and an outline
    per LiDAR (its sides' growth and the pattern's offset, under their priors); the scatter and the ends' scale
    estimated by the method of moments (``board_edges.edge_scatter``), the graph solved again until they settle.
    Only the LiDARs named in ``which`` have their edges. Each 3D LiDAR's pose is tested against the planes alone
    (:func:`planes_against_edges`); where they conflict, the joint covariance holds both answers
    (:func:`conflict_share`, added to the solution's). Its record states the outline's uncertainty and the mean
    outline shift (:func:`_outline_statistics`) and, with ``pair_frames`` (each camera-LiDAR pair's frames), a 3D
    LiDAR's outline check under the planes alone with its first camera (``planes_only_check``, with
    ``planes_only_camera``), as a single pair's record does. Returns the views, the solution, per LiDAR its record
    (ends, scale, scatter, outline, the test) and the conflict's share (None when none), which the posterior's
    samples are convolved with. (A scanner of so few boards that its pairs took their ends has them in ``solution``
    already, from ``rig_calibration``'s first joint solve.)"""
    views = [ends_view(lv, rig.board, lidar_obs[lv.name], solution.T_ref[lv.name], solution.T_ref_board)
             if lv.name in which else lv for lv in lidar_views]
    if not any(v.edges for v in views):
        return lidar_views, solution, {}, None
    planes = solution
    for round_ in range(EDGE_ROUNDS):
        try:
            solution = solve_rig(names, rig.reference, camera_views, views, T_ref, T_ref_board, refine_intrinsics)
        except LidarcamError:
            return lidar_views, planes, {}, None
        settled, new = True, []
        for lv in views:
            if not lv.edges:
                new.append(lv)
                continue
            k = names.index(lv.name)
            outline = solution.vectors[outline_key(k)]
            T_l = solution.T_ref[lv.name]
            frames = [(np.eye(4), np.linalg.inv(T_l) @ solution.T_ref_board[st], e) for st, e in lv.edges.items()]
            tau, scale = edge_scatter(frames, rig.board, outline, lv.edge_scale, lv.edge_tau_m)
            settled &= (abs(np.log(max(tau, 1e-4) / max(lv.edge_tau_m, 1e-4))) < 0.1
                        and abs(np.log(scale / lv.edge_scale)) < 0.05)
            new.append(replace(lv, edge_tau_m=tau, edge_scale=scale))
        # the views the solution was solved with stand (the shifts' test needs their own prior): a scatter
        # shrinking to its floor may take more rounds than EDGE_ROUNDS, and the last one's is kept
        if settled or round_ == EDGE_ROUNDS - 1:
            break
        views = new
    records = {}
    first = {}  # each LiDAR's first pair (its camera sharing the most frames): the ends are the LiDAR's own
    for (c, d), frames in (pair_frames or {}).items():
        first.setdefault(d, (c, frames))
    checks = pairs_outline_checks(rig, names, camera_views, lidar_views, planes,
                                  {(c, d): frames for d, (c, frames) in first.items() if d in which}, [])
    covariances = outline_covariance(names, rig.reference, camera_views, views, solution)
    for lv in views:
        if lv.edges:
            outline = solution.vectors[outline_key(names.index(lv.name))]
            records[lv.name] = {"used": True,
                                "ends": int(sum(e.size for e in lv.edges.values())),
                                "end_scale": lv.edge_scale, "board_scatter_in_plane_m": lv.edge_tau_m,
                                "growth_m": outline[:2].tolist(), "outline_offset_m": outline[2:].tolist(),
                                **_outline_statistics(names, solution, lv, *covariances[lv.name]),
                                "planes_against_edges": None if lv.scan_line else
                                planes_against_edges(planes, solution, lv.name)}
            # the planes alone's outline check beside it, with its first camera (the single pair's)
            own = [(c, r) for (c, d), r in checks.items() if d == lv.name]
            if own:
                records[lv.name].update(planes_only_check=own[0][1], planes_only_camera=own[0][0])
    share = conflict_share(planes, solution, records)
    if share is not None:
        solution = replace(solution, covariance_joint=solution.covariance_joint + share)
    return views, solution, records, share


def _outline_statistics(names: tuple, solution: RigSolution, lv, J: np.ndarray, stems: list) -> dict:
    """LiDAR ``lv``'s ``edges_in_graph.outline_statistics`` at the joint ``solution``: its frames' board poses in
    the reference's frame (a camera's: for a pair folder, its camera's) and its outline shifts in ``stems``, ``J``
    their joint covariance with its outline (``rig_graph.outline_covariance``)."""
    k, order = names.index(lv.name), sorted(solution.T_ref_board)
    return outline_statistics([(st, int(lv.edges[st].size)) for st in stems],
                              [solution.T_ref_board[st] for st in stems],
                              [solution.vectors.get(edge_shift_key(k, order.index(st)), np.zeros(2)) for st in stems],
                              J, lv.edge_tau_m**2)


def ends_view(lv, board, obs: dict, T_ref_l: np.ndarray, T_ref_board: dict):
    """LiDAR view ``lv`` with its ring or segment ends (``obs``: its board observations by stem) assigned to the
    board's sides under its pose ``T_ref_l`` and the boards' ``T_ref_board``, at the edges' starting scatter and
    scale (``_with_edges`` estimates them)."""
    stems = [st for st in lv.W if st in T_ref_board]
    ends = lidar_crossings([obs[st] for st in stems], [np.linalg.inv(T_ref_board[st]) @ T_ref_l for st in stems],
                           board)
    found = {st: e for st, e in zip(stems, ends) if e is not None and e.size}
    return replace(lv, edges=found or None, board=board, edge_tau_m=1e-3, edge_scale=1.0)


def planes_against_edges(planes: RigSolution, edged: RigSolution, name: str) -> dict | None:
    """The LiDAR ``name``'s pose with the edges against the planes alone, as a single pair's
    (``edges_in_graph.edges_summary``): their difference (tangent, the reference's frame) against the difference
    of their covariances, which is the edges' share (a Hausman test). None for the rig's reference, whose pose is
    fixed. Not for a 2D scanner, whose lines alone have several minima."""
    C = planes.covariance(name) - edged.covariance(name)
    if not np.any(C):
        return None
    return {"planes_only_T_ref": planes.T_ref[name].tolist(),
            **hausman(planes.T_ref[name], edged.T_ref[name], planes.covariance(name), edged.covariance(name))}


def conflict_share(planes: RigSolution, edged: RigSolution, records: dict) -> np.ndarray | None:
    """Where any LiDAR's planes conflict with its edges (``edges_in_graph.conflict_covariance``), the share of the
    joint covariance (6N x 6N, ``names`` order) that holds both answers, the planes-only and the edges' own: the
    outer product of the joint difference of every sensor's pose, and in each conflicting LiDAR's block that of
    its edges' own answer's offset (``edges_in_graph.edges_own_offset``). None when they agree."""
    if not any(conflict_covariance(r) is not None for r in records.values()):
        return None
    delta = np.concatenate([T_log(np.linalg.inv(planes.T_ref[n]) @ edged.T_ref[n]) for n in edged.names])
    share = np.outer(delta, delta)
    for name, r in records.items():
        if conflict_covariance(r) is not None:
            k = edged.names.index(name)
            own = np.asarray(r["planes_against_edges"].get("edges_own_offset_tangent", np.zeros(6)), dtype=float)
            share[6 * k:6 * k + 6, 6 * k:6 * k + 6] += np.outer(own, own)
    return share


def pairs_outline_checks(rig: RigDataset, names: tuple, camera_views: list, lidar_views: list, solution: RigSolution,
                         pair_frames: dict, warnings: list) -> dict:
    """Each camera-LiDAR pair's board-edges check under the joint estimate (``solvers.outline_check``, as every
    single 3D pair's result has): the ring ends of the LiDAR's boards against the outline the camera places, each
    frame's shift and their mean against its 99% limit, with the joint covariance of the pair's transform and
    its board poses from the graph. 3D LiDARs with ``board.size`` given; a pair whose frames show no ring ends
    has none. Warnings (prefixed with the pair) are added to ``warnings``."""
    if not rig.board.size_known:
        return {}
    scan = {lv.name: lv.scan_line or bool(lv.edges) for lv in lidar_views}  # with the edges used: not a check
    seen = {cv.name: set(cv.corners_px) for cv in camera_views}
    jobs, found = [], {}  # a LiDAR's ends in a frame are the same with every camera (T_board_lidar is the rig's)
    for (cam, lid), frames in (pair_frames or {}).items():
        if scan.get(lid, True) or cam not in seen:
            continue
        frames = [f for f in frames if f.name in seen[cam] and f.name in solution.T_ref_board]
        T_cl = solution.transform(cam, lid)[0]
        T_c = solution.T_ref[cam]
        boards = [np.linalg.inv(T_c) @ solution.T_ref_board[f.name] for f in frames]
        new = [(f, B) for f, B in zip(frames, boards) if (lid, f.name) not in found]
        ends = lidar_crossings([f.lidar for f, _ in new], [np.linalg.inv(B) @ T_cl for _, B in new], rig.board)
        found.update({(lid, f.name): e for (f, _), e in zip(new, ends)})
        edges = [found[(lid, f.name)] for f in frames]
        used = [j for j, e in enumerate(edges) if e is not None and e.size]
        if used:
            jobs.append((cam, lid, T_cl, [frames[j].name for j in used], [boards[j] for j in used],
                         [edges[j] for j in used]))
    if not jobs:
        return {}
    try:
        covs = pair_board_covariance(names, rig.reference, camera_views, lidar_views, solution,
                                     [(cam, lid, stems) for cam, lid, _, stems, _, _ in jobs])
    except (RuntimeError, np.linalg.LinAlgError) as exc:
        warnings.append(f"board edges: the joint estimate is not checked by them (its covariance with the board "
                        f"poses could not be formed: {exc})")
        return {}
    out = {}
    for (cam, lid, T_cl, stems, boards, edges), cov in zip(jobs, covs):
        record, found = outline_check(T_cl, boards, edges, rig.board, stems, cov)
        out[(cam, lid)] = record
        warnings.extend(f"{cam}-{lid}: {w}" for w in found)
    return out
