"""One factor graph for a rig: every sensor's pose in the reference sensor's frame, one board pose per frame.

Variables: ``T_ref_s`` for every sensor but the reference (the identity), and ``T_ref_board`` for every frame stem
that a camera saw. The graph's reference is a camera (the first when the rig's reference is a LiDAR, whose frame
the poses and their covariance are then carried into: :func:`change_reference`); its factors are
``factor_graph``'s.

The noise: each camera's corners with each board's own pixel noise, each LiDAR's points with its range noise and
each board's plane error (``factor_graph.LidarViews.plane_cov``); a sensor whose chi-square exceeds its degrees of
freedom beyond chance (``noise_levels.excess_scale``) has its noise scaled by their ratio and the graph is solved
again (quasi-likelihood, a variance factor per sensor). Its degrees of freedom are its
residuals less its share of the unknowns (:func:`redundancy`): a LiDAR's planes also fix the board poses that
few cameras saw, so residuals less 6 would count its chi-square against too many and miss its excess.
The joint covariance of all sensor poses is the graph's marginal; any pair's transform ``T_a_b = T_ref_a^-1
T_ref_b`` has the covariance ``J Sigma_ab J^T`` with ``J = [-Ad(T_a_b^-1), I]`` (:func:`pair_transform`).
Loops close exactly: every pair's transform is composed of the same sensor poses.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import gtsam
import numpy as np

from ..errors import DegenerateLayoutError
from . import chi_square as chi2
from .factor_graph import (CameraViews, LidarViews, adjoint, build_graph, graph_values, lidar_frame_residual,
                           vector_keys)
from .factors import corner_residuals, lidar_plane
from .graph_keys import edge_shift_key, frame_key, intrinsics_key, outline_key, sensor_key, terms_key
from .noise_levels import excess_scale
from .refinement_options import RefinementOptions, intrinsics_step_scale


@dataclass(frozen=True, eq=False)
class RigSolution:
    """The rig's sensor poses in the reference sensor's frame (``T_ref``, by name, in ``names`` order), their
    joint covariance (6N x 6N, right tangents, in ``names`` order), the board poses by stem, each sensor's noise
    scale (quasi-likelihood, 1 when its factors agree with their noise) and its chi-square and dof."""

    names: tuple[str, ...]
    reference: str
    T_ref: dict
    covariance_joint: np.ndarray
    T_ref_board: dict
    noise_scale: dict
    chi2_dof: dict
    iterations: int
    # With the intrinsics refined: each camera's ``(params, their 1-sd)`` (``CameraModel.params`` order).
    intrinsics: dict | None = None
    # Each LiDAR with range terms in the graph: ``(values, sds)`` (m, arrays in its ``RangeTerms`` order).
    range_terms: dict = field(default_factory=dict)
    # The Laplace covariance of the free sensors' tangents in the graph's reference camera's frame (in ``names``
    # order, that camera left out) and then the LiDARs' range terms (in ``range_terms`` order).
    covariance_inner: np.ndarray | None = None
    # The graph's vector variables at the estimate (range terms, outlines, outline shifts; by key).
    vectors: dict = field(default_factory=dict)

    def camera_model(self, name: str, given):
        """Camera ``name``'s model (``given``: its ``CameraModel`` as measured) at the solution's refined intrinsics,
        where they were refined, else ``given``."""
        refined = (self.intrinsics or {}).get(name)
        if refined is None:
            return given
        return replace(given.with_params(refined[0]), source=f"refined with the rig (given: {given.source})")

    def covariance(self, name: str) -> np.ndarray:
        k = self.names.index(name)
        return self.covariance_joint[6 * k:6 * k + 6, 6 * k:6 * k + 6]

    def transform(self, a: str, b: str) -> tuple[np.ndarray, np.ndarray]:
        """``T_a_b`` (maps b's points into a's frame) and its 6x6 covariance (right tangent of ``T_a_b``)."""
        ka, kb = self.names.index(a), self.names.index(b)
        idx = np.r_[6 * ka:6 * ka + 6, 6 * kb:6 * kb + 6]
        return pair_transform(self.T_ref[a], self.T_ref[b], self.covariance_joint[np.ix_(idx, idx)])


def pair_transform(T_ref_a: np.ndarray, T_ref_b: np.ndarray, cov_ab: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``T_a_b = T_ref_a^-1 T_ref_b`` and its covariance from the joint covariance ``cov_ab`` (12 x 12) of the two
    poses' right tangents: ``T_a_b Exp(xi_b - Ad(T_a_b^-1) xi_a)`` to first order."""
    T_ab = np.linalg.inv(T_ref_a) @ T_ref_b
    J = np.hstack([-adjoint(np.linalg.inv(T_ab)), np.eye(6)])
    return T_ab, J @ cov_ab @ J.T


def translation_sd_in_first(T_ab: np.ndarray, cov_ab: np.ndarray) -> np.ndarray:
    """The standard deviations of ``T_a_b``'s translation in a's frame (its covariance's tangent translation is
    along b's axes: ``R C R^T``)."""
    return np.sqrt(np.maximum(np.diag(T_ab[:3, :3] @ cov_ab[3:, 3:] @ T_ab[:3, :3].T), 0.0))


def redundancy(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, owners: list) -> dict:
    """Each sensor's share of the unknowns its residuals fix: the trace of the graph's hat matrix over the rows
    of the factors it owns (``owners``, per factor: :func:`_graph`), at ``values``. Its residuals less this share
    are its redundancy, the degrees of freedom its chi-square has at the estimate: a LiDAR whose planes also fix
    board poses that few cameras saw leaves less than its residuals less 6."""
    linear = graph.linearize(values)
    cov, index = dense_covariance(graph, values, linear)
    out: dict = {}
    for i, owner in enumerate(owners):
        if owner is None:
            continue
        factor = linear.at(i)
        idx = np.concatenate([index[k] for k in factor.keys()])
        A = factor.getA()
        out[owner] = out.get(owner, 0.0) + float(np.sum((A @ cov[np.ix_(idx, idx)]) * A))
    return out


def _pose(values, names, reference, name) -> np.ndarray:
    return np.eye(4) if name == reference else values.atPose3(sensor_key(names.index(name))).matrix()


def change_reference(names: tuple[str, ...], T_ref: dict, cov: np.ndarray, new: str) -> tuple[dict, np.ndarray]:
    """The poses ``T_new_s = T_ref_new^-1 T_ref_s`` and their joint covariance: to first order ``xi'_s = xi_s -
    Ad(T_new_s^-1) xi_new`` (``pair_transform``), the new reference's block zero."""
    k_new = names.index(new)
    out, J = {}, np.zeros((6 * len(names), 6 * len(names)))
    for k, n in enumerate(names):
        out[n] = np.linalg.inv(T_ref[new]) @ T_ref[n]
        if n == new:
            continue
        J[6 * k:6 * k + 6, 6 * k:6 * k + 6] = np.eye(6)
        J[6 * k:6 * k + 6, 6 * k_new:6 * k_new + 6] = -adjoint(np.linalg.inv(out[n]))
    out[new] = np.eye(4)
    return out, J @ cov @ J.T


def _chi2(names, cameras, lidars, stems, values, reference, refine_intrinsics, shares: dict) -> dict:
    """Each sensor's chi-square of its factors at ``values`` (unit scale) and its degrees of freedom: its
    residuals less the share of the unknowns they fix (``shares``, by sensor: :func:`redundancy`)."""
    out = {}
    for c in cameras:
        T_rs = _pose(values, names, reference, c.name)
        cam = c.camera.with_params(values.atVector(intrinsics_key(names.index(c.name)))) if refine_intrinsics \
            else c.camera
        ss, n = 0.0, 0
        for stem in c.corners_px:
            T_sb = np.linalg.inv(T_rs) @ values.atPose3(frame_key(stems.index(stem))).matrix()
            r, _ = corner_residuals(T_sb, c.corners_board[stem], c.corners_px[stem], cam, jacobian=False)
            ss += float(r @ r) / c.sigma(stem)**2
            n += r.size
        out[c.name] = (ss, max(n - shares[c.name], 1.0))
    for lv in lidars:
        T_rs = _pose(values, names, reference, lv.name)
        ss, n = 0.0, 0
        k = names.index(lv.name)
        beta = values.atVector(terms_key(k)) if lv.has_terms else None
        for stem in lv.W:
            if stem not in stems:
                continue
            pi, _, _ = lidar_plane(T_rs, values.atPose3(frame_key(stems.index(stem))).matrix())
            e = lidar_frame_residual(lv, stem, pi, beta)
            ss += lv.chi2(stem, e)
            n += e.size
        out[lv.name] = (ss, max(n - shares[lv.name], 1.0))
    return out


def own_corner_drop(cv: CameraViews) -> float:
    """The drop in camera ``cv``'s corners' chi-square (unit scale) when its intrinsics are freed with no other
    sensor, its board poses free (Zhang's problem on its own views, under the same prior): what refining them gains
    on its own corners alone. NaN where that graph cannot be solved."""
    stems = sorted(cv.T_camera_board)
    ss = []
    for refine in (False, True):
        values = gtsam.Values()
        for j, st in enumerate(stems):
            values.insert(frame_key(j), gtsam.Pose3(cv.T_camera_board[st]))
        if refine:
            values.insert(intrinsics_key(0), np.asarray(cv.camera.params, dtype=float))
        owners: list = []
        graph = build_graph((cv.name,), [cv], [], stems, {cv.name: 1.0}, cv.name, refine, owners)
        try:
            values = gtsam.LevenbergMarquardtOptimizer(graph, values, gtsam.LevenbergMarquardtParams()).optimize()
        except RuntimeError:
            return float("nan")
        ss.append(sum(2.0 * graph.at(i).error(values) for i, o in enumerate(owners) if o == cv.name))
    return ss[0] - ss[1]


def intrinsics_test(given: "RigSolution", refined: "RigSolution", own_drop: float = 0.0) -> dict:
    """Whether refining the cameras' intrinsics with the rig (``refined``) lowers its factors' disagreement beyond
    what freed intrinsics fit, against the same views under the given ones (``given``): the F test of the drop in
    the sensors' total chi-square (unit scale), less ``own_drop`` (what each camera's freed intrinsics gain on its
    own corners alone, :func:`own_corner_drop`), against the intrinsics' count of parameters ``k``, over the refined
    chi-square per degree of freedom. Credited is what the other sensors confirm: the LiDARs' planes and the other
    cameras' corners of the boards they share. A camera's own views alone (Zhang's problem) are fitted better by
    freed intrinsics wherever its model is imperfect for them, right for the rig or not: on the recorded VLP-16 set
    a fisheye's twelve central views gained 250 of the whole graph's drop of 260 on its own corners, and the whole
    drop alone credited intrinsics whose planes agree no better with the LiDAR's. A camera whose views alone cannot
    be solved so (NaN) has no own share: its intrinsics rest on the other sensors."""
    k = sum(len(p) for p, _ in refined.intrinsics.values())
    ss_g = sum(ss for ss, _ in given.chi2_dof.values())
    ss_r, dof = (sum(v[i] for v in refined.chi2_dof.values()) for i in (0, 1))
    own = float(own_drop) if np.isfinite(own_drop) else 0.0
    p = chi2.drop_p(k, ss_r + max(ss_g - ss_r - own, 0.0), ss_r, dof)
    return {"parameters": k, "chi_square_given": ss_g, "chi_square_refined": ss_r, "own_corners_drop": own,
            "dof": dof, "p_value": p, "lowers_disagreement": bool(p < 0.05),
            "meaning": "every sensor's chi-square under the given intrinsics and the refined ones (the same views and "
                       "noise), and own_corners_drop: what the freed intrinsics gain on each camera's own corners "
                       "with no other sensor; refined intrinsics are credited when the F test of the rest of the drop "
                       "(what the other sensors confirm) against their number of parameters has p < 0.05"}


def graph_reference(reference: str, camera_names: list[str]) -> str:
    """The camera whose frame the graph is solved in: the rig's reference when it is a camera, else the first
    camera (module docstring)."""
    return reference if reference in camera_names else camera_names[0]


def solve_rig(names: tuple[str, ...], reference: str, cameras: list[CameraViews], lidars: list[LidarViews],
              T_ref_init: dict, T_ref_board_init: dict, refine_intrinsics: bool = False) -> RigSolution:
    """The joint estimate of every sensor's pose (module docstring) from the starts ``T_ref_init`` (by name, in
    the frame of ``reference``) and ``T_ref_board_init`` (by stem; the frames a camera saw); with
    ``refine_intrinsics``, every camera's intrinsics too."""
    camera_names = [c.name for c in cameras]
    inner = graph_reference(reference, camera_names)
    stems = sorted(T_ref_board_init)
    values = graph_values(names, inner, stems, T_ref_init, T_ref_board_init, lidars)
    if refine_intrinsics:
        for c in cameras:
            values.insert(intrinsics_key(names.index(c.name)), np.asarray(c.camera.params, dtype=float))
    scale = {n: 1.0 for n in names}
    plain = {lv.name for lv in lidars if lv.plane_error is None}  # no plane error: every excess scaled
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(100)
    iterations = 0
    for _ in range(3):
        owners: list = []
        graph = build_graph(names, cameras, lidars, stems, scale, inner, refine_intrinsics, owners)
        opt = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
        try:
            values = opt.optimize()
        except RuntimeError as exc:  # an indeterminate system: a pose no factor fixes
            raise DegenerateLayoutError("the rig's graph cannot be solved: a sensor or board pose is not fixed by "
                                        "any frame", hint="check that every sensor shares frames with a camera that "
                                                          "saw the board") from exc
        iterations += opt.iterations()
        stats = _chi2(names, cameras, lidars, stems, values, inner, refine_intrinsics,
                      redundancy(graph, values, owners))
        new = {n: ss / dof if n in plain and ss > dof else excess_scale(ss, dof) for n, (ss, dof) in stats.items()}
        new = {n: new.get(n, 1.0) for n in names}
        converged = all(abs(np.log(new[n] / scale[n])) < 0.05 for n in names)
        scale = new
        if converged:
            break
    graph = build_graph(names, cameras, lidars, stems, scale, inner, refine_intrinsics)
    marginals, cov = _joint_marginal(graph, values, names, inner)
    ranged = [lv for lv in lidars if lv.has_terms]
    keys = [sensor_key(k) for k, n in enumerate(names) if n != inner] + [terms_key(names.index(lv.name))
                                                                        for lv in ranged]
    if ranged:
        cov_inner = marginals.jointMarginalCovariance(gtsam.KeyVector(keys)).fullMatrix()
    else:
        idx = np.concatenate([np.arange(6 * k, 6 * k + 6) for k, n in enumerate(names) if n != inner])
        cov_inner = cov[np.ix_(idx, idx)]
    at = 6 * (len(names) - 1)
    range_terms = {}
    for lv in ranged:
        K = lv.terms.size
        sd = np.sqrt(np.maximum(np.diag(cov_inner)[at:at + K], 0.0))
        range_terms[lv.name] = (values.atVector(terms_key(names.index(lv.name))).copy(), sd)
        at += K
    intrinsics = None
    if refine_intrinsics:
        intrinsics = {}
        for c in cameras:
            key = intrinsics_key(names.index(c.name))
            intrinsics[c.name] = (values.atVector(key).copy(), np.sqrt(np.diag(marginals.marginalCovariance(key))))
    T = {n: _pose(values, names, inner, n) for n in names}
    boards = {s: values.atPose3(frame_key(j)).matrix() for j, s in enumerate(stems)}
    if inner != reference:
        T_inner_ref = T[reference]
        T, cov = change_reference(tuple(names), T, cov, reference)
        boards = {s: np.linalg.inv(T_inner_ref) @ B for s, B in boards.items()}
    vectors = {key: values.atVector(key).copy() for key in vector_keys(names, stems, lidars)}
    return RigSolution(tuple(names), reference, T, 0.5 * (cov + cov.T), boards, scale,
                       {n: (float(ss), float(dof)) for n, (ss, dof) in stats.items()}, iterations, intrinsics,
                       range_terms, 0.5 * (cov_inner + cov_inner.T), vectors)


def _joint_marginal(graph, values, names, inner: str) -> tuple:
    """GTSAM's marginals at ``values`` and the joint covariance (6N x 6N, ``names`` order, the graph's reference
    camera's block zero); a singular information is a one-line error."""
    others = [k for k, n in enumerate(names) if n != inner]
    try:
        marginals = gtsam.Marginals(graph, values)
        inner_cov = marginals.jointMarginalCovariance(gtsam.KeyVector([sensor_key(k) for k in others])).fullMatrix()
    except RuntimeError as exc:
        raise DegenerateLayoutError("the rig's sensor poses are not all fixed by the frames (the graph's "
                                    "information is singular)",
                                    hint="record more board poses that the weakly linked sensors see") from exc
    cov = np.zeros((6 * len(names), 6 * len(names)))
    idx = np.concatenate([np.arange(6 * k, 6 * k + 6) for k in others])
    cov[np.ix_(idx, idx)] = inner_cov
    return marginals, cov


def rig_bound(names: tuple[str, ...], reference: str, cameras: list[CameraViews], lidars: list[LidarViews],
              T_ref: dict, T_ref_board: dict, noise_scale: dict | None = None,
              intrinsics: dict | None = None, range_terms: dict | None = None) -> np.ndarray:
    """The joint covariance of every sensor's pose (6N x 6N, ``names`` order, in the frame of ``reference``) that
    the graph's information gives at the poses ``T_ref`` and board poses ``T_ref_board`` (by stem): at a
    simulation's truth, the Cramer-Rao bound of the graph's measurement model for these views (their corners,
    their board points' moments) at the views' noise levels (times ``noise_scale``, by sensor). ``intrinsics``
    (camera name -> ``CameraModel.params``, for every camera): the cameras' intrinsics are unknowns of the graph
    too (``--refine-intrinsics``, under each camera's ``param_std`` prior where it has one), at these values.
    A LiDAR with range terms has them as unknowns too, at ``range_terms`` (by name, m; 0 where not given)."""
    inner = graph_reference(reference, [c.name for c in cameras])
    stems = sorted(T_ref_board)
    scale = {n: (noise_scale or {}).get(n, 1.0) for n in names}
    graph = build_graph(names, cameras, lidars, stems, scale, inner, intrinsics is not None)
    vectors = {terms_key(names.index(n)): np.atleast_1d(np.asarray(v, dtype=float))
               for n, v in (range_terms or {}).items()}
    values = graph_values(names, inner, stems, T_ref, T_ref_board, lidars, vectors)
    for c in cameras if intrinsics is not None else ():
        values.insert(intrinsics_key(names.index(c.name)), np.asarray(intrinsics[c.name], dtype=float))
    _, cov = _joint_marginal(graph, values, names, inner)
    if inner != reference:
        _, cov = change_reference(tuple(names), {n: np.linalg.inv(T_ref[inner]) @ T_ref[n] for n in names}, cov,
                                  reference)
    return 0.5 * (cov + cov.T)


def spanning_tree(names: tuple[str, ...], reference: str, links: dict) -> dict:
    """Each sensor's parent on the path to the reference, by the links that share the most frames (``links``:
    ``(a, b) -> frames shared``, only the usable ones); raises a one-line error naming a sensor with no path."""
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import breadth_first_order, minimum_spanning_tree

    n = len(names)
    w = np.zeros((n, n))
    for (a, b), count in links.items():
        if count > 0:
            i, j = names.index(a), names.index(b)
            w[i, j] = w[j, i] = 1.0 / count  # fewer shared frames: a longer edge
    tree = minimum_spanning_tree(csr_matrix(w))
    tree = tree + tree.T
    order, pred = breadth_first_order(tree, names.index(reference), directed=False, return_predecessors=True)
    reached = set(order.tolist())
    missing = [names[k] for k in range(n) if k not in reached]
    if missing:
        raise DegenerateLayoutError(f"sensor(s) {', '.join(missing)} share no usable frames with the rest of the rig "
                                    f"(no path to the reference {reference})",
                                    hint="record board poses that they and a connected camera see together (a "
                                         "LiDAR needs 3 or more with a camera, a 2D scanner 2 where the board's "
                                         "size is given; two cameras 1 or more)")
    return {names[k]: (names[pred[k]] if pred[k] >= 0 else None) for k in range(n)}


def _graph_at(names: tuple[str, ...], reference: str, cameras: list[CameraViews], lidars: list[LidarViews],
              solution: RigSolution) -> tuple:
    """The graph of these views at ``solution``'s noise scales and its values at ``solution`` (its poses, vector
    variables and refined intrinsics), with the graph's reference camera and the stems."""
    inner = graph_reference(reference, [c.name for c in cameras])
    stems = sorted(solution.T_ref_board)
    refine = solution.intrinsics is not None
    graph = build_graph(names, cameras, lidars, stems, solution.noise_scale, inner, refine)
    values = graph_values(names, inner, stems, solution.T_ref, solution.T_ref_board, lidars, solution.vectors)
    for c in cameras if refine else ():
        values.insert(intrinsics_key(names.index(c.name)), solution.intrinsics[c.name][0])
    return graph, values, inner, stems


def graph_step(names: tuple[str, ...], reference: str, cameras: list[CameraViews], lidars: list[LidarViews],
               solution: RigSolution) -> dict:
    """One Gauss-Newton step of the graph of these views from ``solution``'s values (at its noise scales): by key,
    each variable's step (a pose's right tangent in the graph's reference camera's frame). With views that differ
    from the solution's in what they measure (their labels, say), the shift that difference calls for, to first
    order."""
    graph, values, _, _ = _graph_at(names, reference, cameras, lidars, solution)
    delta = graph.linearize(values).optimize()
    return {k: np.asarray(delta.at(k), dtype=float).copy() for k in values.keys() if delta.exists(k)}


def sensors_share(names: tuple, reference: str, inner: str, solution: RigSolution, share_inner: np.ndarray
                  ) -> np.ndarray:
    """A share of the covariance over the free sensors' tangents in the graph's reference camera ``inner``'s frame
    (``RigSolution.covariance_inner``'s order, range terms after them) as a share of the sensors' joint covariance
    (6N x 6N, ``names`` order), carried into the rig's reference's frame."""
    share = np.zeros((6 * len(names), 6 * len(names)))
    free = [k for k, n in enumerate(names) if n != inner]
    cols = np.concatenate([np.arange(6 * k, 6 * k + 6) for k in free])
    share[np.ix_(cols, cols)] = share_inner[:6 * len(free), :6 * len(free)]
    if inner != reference:
        T_inner = {n: np.linalg.inv(solution.T_ref[inner]) @ solution.T_ref[n] for n in names}
        share = change_reference(names, T_inner, share, reference)[1]
    return 0.5 * (share + share.T)


def held_intrinsics_share(names: tuple[str, ...], reference: str, cameras: list[CameraViews],
                          lidars: list[LidarViews], solution: RigSolution, options: RefinementOptions
                          ) -> np.ndarray | None:
    """The share of the sensors' joint covariance (6N x 6N, ``names`` order, ``reference``'s frame) that the
    cameras' uncertain intrinsics, held at their values in the graph, leave: as a single pair's refinement adds it
    (``refinement._intrinsics_covariance``, first order), each camera with ``param_std`` (dataset.yaml's, or
    OpenCV's where they were calibrated from the images) moved by one standard deviation along each principal
    direction of their covariance (each parameter alone where only standard deviations are known), the joint graph
    stepped once from ``solution`` under it, and the free sensors' shifts summed in outer product (the standard
    deviations scaled by ``refinement_options.intrinsics_step_scale`` of ``options``, a ``RefinementOptions``).
    None where no camera has them."""
    moves = [(k, step) for k, c in enumerate(cameras)
             for step in c.camera.param_steps(intrinsics_step_scale(options, c.camera))]
    if not moves:
        return None
    inner = graph_reference(reference, [c.name for c in cameras])
    order = [sensor_key(k) for k, n in enumerate(names) if n != inner]
    base = graph_step(names, reference, cameras, lidars, solution)  # the solution's own remaining step

    def shift(views) -> np.ndarray:
        step = graph_step(names, reference, views, lidars, solution)
        return np.concatenate([step[k] - base[k] for k in order])

    extra = np.zeros((6 * len(order), 6 * len(order)))
    for k, step in moves:
        d = shift([replace(c, camera=c.camera.with_params(c.camera.params + step)) if j == k else c
                   for j, c in enumerate(cameras)])
        extra += np.outer(d, d)
    return sensors_share(names, reference, inner, solution, extra)


def dense_covariance(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values,
                     linear: gtsam.GaussianFactorGraph | None = None) -> tuple[np.ndarray, dict]:
    """The graph's whole Laplace covariance at ``values`` (its information, dense, inverted: for a rig's few hundred
    unknowns far quicker than ``gtsam.Marginals``' joint marginals of many keys) and each key's indices in it.
    ``linear``: the graph linearised at ``values`` already."""
    keys = list(values.keys())
    ordering = gtsam.Ordering()
    index, start = {}, 0
    for k in keys:
        ordering.push_back(k)
        dim = 6 if gtsam.Symbol(k).chr() in (ord("s"), ord("f")) else len(values.atVector(k))
        index[k] = np.arange(start, start + dim)
        start += dim
    H, _ = (graph.linearize(values) if linear is None else linear).hessian(ordering)
    return np.linalg.inv(0.5 * (H + H.T)), index


def pair_board_covariance(names: tuple[str, ...], reference: str, cameras: list[CameraViews],
                          lidars: list[LidarViews], solution: RigSolution, requests: list[tuple[str, str, list]]
                          ) -> list[np.ndarray]:
    """For each request ``(camera, lidar, stems)``: the joint covariance (6 + 6n) of ``T_camera_lidar`` and the
    board poses ``T_camera_board`` of those frames (right tangents), from the graph's marginals at ``solution``.
    Right tangents are the same in any reference frame, so with ``J`` of :func:`pair_transform`:
    ``xi_cl = xi_l - Ad(T_cl^-1) xi_c`` and ``xi_cb = xi_b - Ad(T_cb^-1) xi_c``."""
    graph, values, inner, stems = _graph_at(names, reference, cameras, lidars, solution)
    full, index = dense_covariance(graph, values)
    out = []
    for cam, lidar, frames in requests:
        sensors = [s for s in (cam, lidar) if s != inner]
        keys = [sensor_key(names.index(s)) for s in sensors] + [frame_key(stems.index(st)) for st in frames]
        idx = np.concatenate([index[k] for k in keys])
        S = full[np.ix_(idx, idx)]
        col = {s: 6 * i for i, s in enumerate(sensors)}
        nb = 6 * len(sensors)
        J = np.zeros((6 + 6 * len(frames), S.shape[0]))
        T_c = solution.T_ref[cam]
        T_cl = np.linalg.inv(T_c) @ solution.T_ref[lidar]
        J[:6, col[lidar]:col[lidar] + 6] = np.eye(6)
        if cam in col:
            J[:6, col[cam]:col[cam] + 6] = -adjoint(np.linalg.inv(T_cl))
        for j, st in enumerate(frames):
            rows = slice(6 + 6 * j, 12 + 6 * j)
            J[rows, nb + 6 * j:nb + 6 * j + 6] = np.eye(6)
            if cam in col:
                T_cb = np.linalg.inv(T_c) @ solution.T_ref_board[st]
                J[rows, col[cam]:col[cam] + 6] = -adjoint(np.linalg.inv(T_cb))
        C = J @ S @ J.T
        out.append(0.5 * (C + C.T))
    return out


def outline_covariance(names: tuple[str, ...], reference: str, cameras: list[CameraViews], lidars: list[LidarViews],
                       solution: RigSolution) -> dict:
    """Each LiDAR with edges: its outline (4) and its outline shifts (2 each) jointly, with the stems they are in the
    order of, from one inversion of the graph of these views at ``solution`` (``name -> (covariance, stems)``): what
    its board-edges record states their uncertainty and tests its mean shift with (``pipeline.rig_edges``), as a
    single pair's (``edges_in_graph.edges_summary``)."""
    graph, values, _, stems = _graph_at(names, reference, cameras, lidars, solution)
    full, index = dense_covariance(graph, values)
    out = {}
    for lv in lidars:
        k = names.index(lv.name)
        if outline_key(k) not in index:
            continue
        shifted = [st for j, st in enumerate(stems) if edge_shift_key(k, j) in index]
        idx = np.concatenate([index[outline_key(k)]] + [index[edge_shift_key(k, stems.index(st))] for st in shifted])
        C = full[np.ix_(idx, idx)]
        out[lv.name] = (0.5 * (C + C.T), shifted)
    return out


def inner_covariance(names: tuple[str, ...], reference: str, cameras: list[CameraViews], lidars: list[LidarViews],
                     solution: RigSolution) -> np.ndarray:
    """The Laplace covariance of the free sensors' tangents (and the range terms) in the graph's reference
    camera's frame, as ``RigSolution.covariance_inner`` orders them, for these views at ``solution``'s values:
    with views other than the solution's (the LiDARs without their edges, say), that model's curvature at this
    estimate."""
    graph, values, inner, stems = _graph_at(names, reference, cameras, lidars, solution)
    keys = [sensor_key(k) for k, n in enumerate(names) if n != inner] + [terms_key(names.index(lv.name))
                                                                        for lv in lidars if lv.has_terms]
    C = gtsam.Marginals(graph, values).jointMarginalCovariance(gtsam.KeyVector(keys)).fullMatrix()
    return 0.5 * (C + C.T)
