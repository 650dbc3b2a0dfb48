"""The camera's intrinsics against a 3D camera-LiDAR pair's boards: their parameters' names, and the quick check
of every 3D result (:func:`intrinsics_drop`) whether the boards' planes disagree in a way the intrinsics explain.

With ``--refine-intrinsics`` the intrinsics ``[fx, fy, cx, cy, dist...]`` are variables of the engine's joint graph
(``rig_graph``, under ``camera.param_std`` from dataset.yaml as a prior where given); the check here frees them in a
pair's own graph of corners and planes (with the range terms it chose, no edges) and tests the planes' chi-square
drop.
"""
from __future__ import annotations

from dataclasses import replace

import gtsam
import numpy as np

from geometry.camera import CameraModel

from ..measurements import FrameMeasurement
from .chi_square import drop_p
from .graph_keys import EXTRINSIC, INTRINSICS
from .plane_graph import PlaneProblem
from .refinement import Refinement
from .refinement_options import RefinementOptions


def param_names(n: int) -> list[str]:
    """The names of a camera's ``n`` intrinsics ``[fx, fy, cx, cy, dist...]`` (a single pair's and a rig's)."""
    return ["fx", "fy", "cx", "cy"] + [f"d{k}" for k in range(n - 4)]


def _intrinsics_graph(frames: list[FrameMeasurement], board, camera: CameraModel, ref: Refinement,
                      options: RefinementOptions, plane_floor_m: float, prior_sd: np.ndarray | None):
    """The frames ``ref`` kept, the graph of their corners and planes with the intrinsics a variable (under
    ``prior_sd`` where given; the planes at ``plane_floor_m``, no robust loss) and its values at ``ref``'s solution
    and ``camera``'s intrinsics."""
    dropped = {f.name for f in ref.frames if f.dropped}
    used = [f for f in frames if f.usable and f.name not in dropped and f.name in ref.T_camera_board]
    fits = {f.name: f for f in ref.frames}
    # The range terms the refinement chose, free in both solves from its values (their priors, those it held at 0
    # held): without them a LiDAR's range offset or ring errors read as planes the intrinsics could move.
    fit = ref.range_model
    terms = fit.terms if fit is not None and fit.names else None
    labels = fit.labels_for(used, board, ref.T_camera_lidar) if terms is not None else None
    prob = PlaneProblem(used, board, camera, ref.corner_noise_px, ref.range_noise_m, options, terms, labels,
                        sigma_board=[fits[f.name].corner_noise_px for f in used] if options.corner_noise_px is None
                        else None)
    if prob.has_beta:
        prob.beta = np.array(fit.values_m, dtype=float)
        prob.pinned = tuple(fit.names.index(n) for n in fit.pinned if n in fit.names)
    prob.camera = replace(camera, param_std=prior_sd)  # the prior, where one
    active = list(range(len(used)))
    graph = prob.graph(active, plane_floor_m, robust=False, intrinsics=True)
    values = prob.values(active, ref.T_camera_lidar, [ref.T_camera_board[f.name] for f in used], plane_floor_m)
    values.insert(INTRINSICS, np.asarray(camera.params, dtype=float).copy())
    return used, graph, values


# Below this p-value, the intrinsics' drop test (:func:`intrinsics_drop`) makes the verdict a CHECK.
INTRINSICS_CHECK_P = 1e-3


def intrinsics_drop(frames: list[FrameMeasurement], board, camera: CameraModel, ref: Refinement,
                    options: RefinementOptions = RefinementOptions()) -> dict | None:
    """Whether the boards' camera and LiDAR planes disagree in a way the camera's intrinsics explain: the planes'
    chi-square (weighed with the per-board plane error ``ref`` estimated) with the intrinsics held as given and with
    them freed, the extrinsic and board poses solved in both, and the F test of the drop against the intrinsics'
    count over what the freed planes leave per degree of freedom. Two solves of the graph, no re-measurement: a
    quick check of every 3D result (``pipeline.verdict``), where ``--refine-intrinsics`` is the full
    procedure. None where the graph cannot be solved so."""
    given = np.asarray(camera.params, dtype=float)
    try:
        _, graph, values = _intrinsics_graph(frames, board, camera, ref, options, ref.plane_floor_m, None)
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(options.max_iterations)
        held = gtsam.NonlinearFactorGraph(graph)
        held.add(gtsam.PriorFactorVector(INTRINSICS, given, gtsam.noiseModel.Isotropic.Sigma(len(given), 1e-9)))
        at_given = gtsam.LevenbergMarquardtOptimizer(held, values, params).optimize()
        freed = gtsam.LevenbergMarquardtOptimizer(graph, at_given, params).optimize()
    except RuntimeError:
        return None
    planes = [f for f in (graph.at(i) for i in range(graph.size())) if f is not None and EXTRINSIC in f.keys()]
    ss_g, ss_r = (sum(2.0 * f.error(v) for f in planes) for v in (at_given, freed))
    k, dof = len(given), float(ref.consistency_dof) - len(given)
    if dof <= 0:
        return None
    p = drop_p(k, ss_g, ss_r, dof)
    return {"parameters": k, "chi_square_given": float(ss_g), "chi_square_refined": float(ss_r), "dof": dof,
            "p_value": p, "explains": bool(p < INTRINSICS_CHECK_P),
            "meaning": "the planes' chi-square (with the per-board plane error) under the given intrinsics and with "
                       "them freed; the intrinsics explain the planes' disagreement when the F test of the drop "
                       f"has p < {INTRINSICS_CHECK_P:g} (--refine-intrinsics is the full procedure)"}

