"""One factor graph for a rig: every sensor's pose in the reference sensor's frame, one board pose per frame.

Variables: ``T_ref_s`` for every sensor but the reference (the identity), and ``T_ref_board`` for every frame stem
that a camera saw. The graph's reference is a camera (the first when the rig's reference is a LiDAR, whose frame
the poses and their covariance are then carried into: :func:`change_reference`). Factors:

- each camera's corners in each frame it saw: the pair's corner factor through ``T_s_board = T_ref_s^-1
  T_ref_board``. With right tangents, ``T_s_board`` moves by ``xi_board`` for the board's and by
  ``-Ad(T_s_board^-1) xi_s`` for the sensor's (:func:`_rig_corner_error`);
- each LiDAR's board points in each frame it saw: the pair's plane factor, unchanged, with the reference frame in
  the camera's place (it maps the board's plane into the LiDAR frame through ``T_ref_s`` and ``T_ref_board``).

With ``refine_intrinsics`` each camera's intrinsics ``[fx, fy, cx, cy, dist...]`` are a vector variable of its
corner factors too (the corners' Jacobians by them from ``geometry.camera``), under a prior of the camera's
``param_std`` when it has one.

The noise: each camera's corners with its own effective pixel noise, each LiDAR's points with its own range noise
(``W`` whitens by it); a sensor whose chi-square per degree of freedom is above 1 has its noise scaled by it and
the graph is solved again (quasi-likelihood, a variance factor per sensor). Its degrees of freedom are its
residuals less its share of the unknowns (:func:`redundancy`): a LiDAR's planes also fix the board poses that
few cameras saw, so residuals less 6 would count its chi-square against too many and miss its excess.
The joint covariance of all sensor poses is the graph's marginal; any pair's transform ``T_a_b = T_ref_a^-1
T_ref_b`` has the covariance ``J Sigma_ab J^T`` with ``J = [-Ad(T_a_b^-1), I]`` (:func:`pair_transform`).
Loops close exactly: every pair's transform is composed of the same sensor poses.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from functools import partial

import gtsam
import numpy as np

from geometry.camera import CameraModel

from ..errors import DegenerateLayoutError
from . import chi_square as chi2
from .board_edges import edge_factor, outline_prior, shift_prior
from .factors import (affine_plane_factor, corner_factor, corner_intrinsics_factor, corner_residuals,
                      corner_residuals_intrinsics, lidar_plane, lidar_residual, nuisance_plane_factor,
                      nuisance_residual, plane_factor)
from .range_model import RangeTerms


def sensor_key(k: int) -> int:
    return gtsam.symbol("s", k)


def frame_key(k: int) -> int:
    return gtsam.symbol("f", k)


def intrinsics_key(k: int) -> int:
    return gtsam.symbol("k", k)


def terms_key(k: int) -> int:
    """A LiDAR's range terms (a vector, m: ``range_model.RangeTerms``, the global offset first)."""
    return gtsam.symbol("o", k)


def outline_key(k: int) -> int:
    """A LiDAR's view of the board's outline (``board_edges.OUTLINE``: its sides' growth, the pattern's offset)."""
    return gtsam.symbol("g", k)


def edge_shift_key(k: int, j: int) -> int:
    """Sensor ``k``'s outline shift in frame ``j`` (``board_edges.shift_key``)."""
    return gtsam.symbol("e", 100000 * k + j)


@dataclass(frozen=True, eq=False)
class CameraViews:
    """One camera's frames: per stem the board's corners (board frame, (M, 3)) and their detections (M, 2), the
    board's pose from them alone (``T_camera_board``, the start) and its corners' pixel noise (``sigma_board``;
    ``sigma_px`` where a stem has none, and for a board not recorded)."""

    name: str
    camera: CameraModel
    sigma_px: float
    corners_board: dict = field(default_factory=dict)
    corners_px: dict = field(default_factory=dict)
    T_camera_board: dict = field(default_factory=dict)
    sigma_board: dict = field(default_factory=dict)

    def sigma(self, stem: str) -> float:
        """The pixel noise of the corners of frame ``stem``."""
        return float(self.sigma_board.get(stem, self.sigma_px))


@dataclass(frozen=True, eq=False)
class LidarViews:
    """One LiDAR's frames: per stem the square root ``W`` of its board points' range moment
    (``measurements.lidar_whitener``: ``|W pi|^2`` is their sum of squared range errors), its range noise (m),
    and whether it is a scan line (2D).

    ``ranged``: per stem the frame's ``range_model.FrameWhitener`` in the range model's form (the residual
    ``W [s pi; S beta] + e0`` from the points' ranges), used instead of ``W`` when given: with the range terms
    ``terms`` when they are set and not empty (the global offset, per-ring offsets, the black squares' offset: one
    vector variable of the graph under their priors), else without terms (``affine``: the form the terms are
    tested against)."""

    name: str
    sigma_m: float
    W: dict = field(default_factory=dict)
    scan_line: bool = False
    ranged: dict | None = None
    terms: RangeTerms | None = None
    # With the board's edges (``--edges``): per stem the frame's ends (``board_edges.EdgeCrossings``), the board,
    # the boards' in-plane scatter (m, each frame's shift prior) and the ends' scale (``board_edges.edge_factor``).
    edges: dict | None = None
    board: object = None
    edge_tau_m: float = 0.0
    edge_scale: float = 1.0

    @property
    def has_terms(self) -> bool:
        return self.ranged is not None and self.terms is not None and self.terms.size > 0


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

    def covariance(self, name: str) -> np.ndarray:
        k = self.names.index(name)
        return self.covariance_joint[6 * k:6 * k + 6, 6 * k:6 * k + 6]

    def transform(self, a: str, b: str) -> tuple[np.ndarray, np.ndarray]:
        """``T_a_b`` (maps b's points into a's frame) and its 6x6 covariance (right tangent of ``T_a_b``)."""
        ka, kb = self.names.index(a), self.names.index(b)
        idx = np.r_[6 * ka:6 * ka + 6, 6 * kb:6 * kb + 6]
        return pair_transform(self.T_ref[a], self.T_ref[b], self.covariance_joint[np.ix_(idx, idx)])


def adjoint(T: np.ndarray) -> np.ndarray:
    """GTSAM's Pose3 adjoint in ``[rot; trans]`` order: ``T Exp(xi) T^-1 = Exp(Ad(T) xi)``."""
    return gtsam.Pose3(T).AdjointMap()


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


def rig_corner_residuals(T_rs: np.ndarray, T_rb: np.ndarray, corners_board: np.ndarray, corners_px: np.ndarray,
                         camera: CameraModel, jacobian: bool = True) -> tuple:
    """A camera's corner residuals through its pose ``T_rs`` and the board's ``T_rb`` (both in the reference's
    frame), and their Jacobians by the sensor's and the board's right tangents (module docstring; None without
    ``jacobian``)."""
    T_sb = np.linalg.inv(T_rs) @ T_rb
    r, J = corner_residuals(T_sb, corners_board, corners_px, camera, jacobian)
    if not jacobian:
        return r, None, None
    return r, -J @ adjoint(np.linalg.inv(T_sb)), J


def _rig_corner_error(corners_board, corners_px, camera, this, values, H):
    keys = this.keys()
    r, H_s, H_b = rig_corner_residuals(values.atPose3(keys[0]).matrix(), values.atPose3(keys[1]).matrix(),
                                       corners_board, corners_px, camera, H is not None)
    if H is not None:
        H[0], H[1] = H_s, H_b
    return r


def _rig_corner_intrinsics_error(corners_board, corners_px, camera, this, values, H):
    keys = this.keys()
    T_rs, T_rb = values.atPose3(keys[0]).matrix(), values.atPose3(keys[1]).matrix()
    T_sb = np.linalg.inv(T_rs) @ T_rb
    cam = camera.with_params(values.atVector(keys[2]))
    r, J, J_k = corner_residuals_intrinsics(T_sb, corners_board, corners_px, cam, H is not None)
    if H is not None:
        H[0] = -J @ adjoint(np.linalg.inv(T_sb))
        H[1] = J
        H[2] = J_k
    return r


def rig_corner_factor(key_sensor: int, key_board: int, corners_board: np.ndarray, corners_px: np.ndarray,
                      camera: CameraModel, noise: gtsam.noiseModel.Base) -> gtsam.CustomFactor:
    """A camera's corners of one frame through its pose in the rig and the board's (module docstring)."""
    return gtsam.CustomFactor(noise, [key_sensor, key_board],
                              partial(_rig_corner_error, np.asarray(corners_board, dtype=float),
                                      np.asarray(corners_px, dtype=float).reshape(-1, 2), camera))


def _graph(names, cameras, lidars, stems, scale, reference, refine_intrinsics=False, owners: list | None = None):
    """The rig's factor graph; ``owners`` (a list, filled): per factor the sensor whose measurement residuals it
    holds (the residuals :func:`_chi2` counts: corners, LiDAR planes), None for the others (priors, edges)."""
    factors = gtsam.NonlinearFactorGraph()

    def add(factor, owner: str | None = None) -> None:
        factors.add(factor)
        if owners is not None:
            owners.append(owner)

    for c in cameras:
        k = names.index(c.name)
        if refine_intrinsics and c.camera.param_std is not None:
            add(gtsam.PriorFactorVector(intrinsics_key(k), c.camera.params,
                                        gtsam.noiseModel.Diagonal.Sigmas(np.asarray(c.camera.param_std))))
        for stem in c.corners_px:
            px = c.corners_px[stem]
            noise = gtsam.noiseModel.Isotropic.Sigma(px.size, c.sigma(stem) * np.sqrt(scale[c.name]))
            fk = frame_key(stems.index(stem))
            if refine_intrinsics and c.name == reference:
                add(corner_intrinsics_factor(fk, intrinsics_key(k), c.corners_board[stem], px, c.camera, noise),
                    c.name)
            elif refine_intrinsics:
                add(gtsam.CustomFactor(noise, [sensor_key(k), fk, intrinsics_key(k)],
                                       partial(_rig_corner_intrinsics_error,
                                               np.asarray(c.corners_board[stem], dtype=float),
                                               np.asarray(px, dtype=float).reshape(-1, 2), c.camera)), c.name)
            elif c.name == reference:
                add(corner_factor(fk, c.corners_board[stem], px, c.camera, noise), c.name)
            else:
                add(rig_corner_factor(sensor_key(k), fk, c.corners_board[stem], px, c.camera, noise), c.name)
    for lv in lidars:
        k = names.index(lv.name)
        sd = lv.sigma_m * np.sqrt(scale[lv.name])
        if lv.has_terms:
            add(gtsam.PriorFactorVector(terms_key(k), np.zeros(lv.terms.size),
                                        gtsam.noiseModel.Diagonal.Sigmas(np.asarray(lv.terms.prior_sd))))
        if lv.edges:
            add(outline_prior(outline_key(k)))
            for stem, e in lv.edges.items():
                if stem in stems:
                    j = stems.index(stem)
                    add(shift_prior(edge_shift_key(k, j), lv.edge_tau_m))
                    add(edge_factor(sensor_key(k), frame_key(j), edge_shift_key(k, j), e, lv.board,
                                    lv.edge_scale, outline_key(k)))
        for stem, W in lv.W.items():
            if stem not in stems:
                continue
            fk = frame_key(stems.index(stem))
            if lv.ranged is None:
                add(plane_factor(sensor_key(k), fk, W, gtsam.noiseModel.Isotropic.Sigma(W.shape[0], sd),
                                 lv.scan_line), lv.name)
                continue
            fw = lv.ranged[stem]
            noise = gtsam.noiseModel.Isotropic.Sigma(fw.W.shape[0], sd)
            if lv.has_terms:
                add(nuisance_plane_factor(sensor_key(k), fk, terms_key(k), fw.W, fw.S, fw.m_away, fw.e0, noise,
                                          lv.scan_line), lv.name)
            else:
                add(affine_plane_factor(sensor_key(k), fk, fw.W, fw.m_away, fw.e0, noise, lv.scan_line), lv.name)
    return factors


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


def lidar_frame_residual(lv: LidarViews, stem: str, pi: np.ndarray, beta: np.ndarray | None = None) -> np.ndarray:
    """The LiDAR's residual of frame ``stem`` (m) at the board plane ``pi`` (in the LiDAR frame) and its range
    terms ``beta`` (ignored without them)."""
    if lv.ranged is None:
        return lidar_residual(lv.W[stem], pi, lv.scan_line)[0]
    fw = lv.ranged[stem]
    beta = np.asarray(beta, dtype=float) if lv.has_terms else np.zeros(0)
    S = fw.S if lv.has_terms else np.zeros((0, 0))
    return nuisance_residual(fw.W, S, fw.m_away, pi, beta, lv.scan_line, fw.e0)[0]


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
    """Each sensor's chi-square of its factors at ``values`` (unit noise) and its degrees of freedom: its
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
            ss += float(e @ e) / lv.sigma_m**2
            n += e.size
        out[lv.name] = (ss, max(n - shares[lv.name], 1.0))
    return out


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
    values = _values(names, inner, stems, T_ref_init, T_ref_board_init, lidars)
    if refine_intrinsics:
        for c in cameras:
            values.insert(intrinsics_key(names.index(c.name)), np.asarray(c.camera.params, dtype=float))
    scale = {n: 1.0 for n in names}
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(100)
    iterations = 0
    for _ in range(3):
        owners: list = []
        graph = _graph(names, cameras, lidars, stems, scale, inner, refine_intrinsics, owners)
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
        new = {n: max(1.0, ss / dof) for n, (ss, dof) in stats.items()}
        new = {n: new.get(n, 1.0) for n in names}
        converged = all(abs(np.log(new[n] / scale[n])) < 0.05 for n in names)
        scale = new
        if converged:
            break
    graph = _graph(names, cameras, lidars, stems, scale, inner, refine_intrinsics)
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
    vectors = {key: values.atVector(key).copy() for key in _vector_keys(names, stems, lidars)}
    return RigSolution(tuple(names), reference, T, 0.5 * (cov + cov.T), boards, scale,
                       {n: (float(ss), float(dof)) for n, (ss, dof) in stats.items()}, iterations, intrinsics,
                       range_terms, 0.5 * (cov_inner + cov_inner.T), vectors)


def _vector_keys(names, stems: list[str], lidars) -> dict:
    """The graph's vector variables of the ``lidars`` (each key and its size): range terms, and with the
    board's edges each LiDAR's outline and its frames' outline shifts."""
    out = {}
    for lv in lidars:
        k = names.index(lv.name)
        if lv.has_terms:
            out[terms_key(k)] = lv.terms.size
        if lv.edges:
            out[outline_key(k)] = 4
            out.update({edge_shift_key(k, stems.index(st)): 2 for st in lv.edges if st in stems})
    return out


def _values(names, inner: str, stems: list[str], T_ref: dict, T_ref_board: dict, lidars=(),
            vectors: dict | None = None) -> gtsam.Values:
    """The graph's pose variables in the frame of its reference camera ``inner``, and the vector variables of the
    ``lidars`` (:func:`_vector_keys`) at ``vectors`` (by key; 0 where not given or of another size)."""
    T_inner = np.linalg.inv(T_ref[inner])
    values = gtsam.Values()
    for key, size in _vector_keys(names, stems, lidars).items():
        given = np.asarray((vectors or {}).get(key, np.zeros(size)), dtype=float)
        values.insert(key, given if given.size == size else np.zeros(size))  # another model's terms: from 0
    for k, n in enumerate(names):
        if n != inner:
            values.insert(sensor_key(k), gtsam.Pose3(T_inner @ T_ref[n]))
    for j, s in enumerate(stems):
        values.insert(frame_key(j), gtsam.Pose3(T_inner @ T_ref_board[s]))
    return values


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
    graph = _graph(names, cameras, lidars, stems, scale, inner, intrinsics is not None)
    vectors = {terms_key(names.index(n)): np.atleast_1d(np.asarray(v, dtype=float))
               for n, v in (range_terms or {}).items()}
    values = _values(names, inner, stems, T_ref, T_ref_board, lidars, vectors)
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
                                         "LiDAR needs 3 or more with a camera; two cameras 1 or more)")
    return {names[k]: (names[pred[k]] if pred[k] >= 0 else None) for k in range(n)}


def terms_fit(names: tuple[str, ...], reference: str, cameras: list[CameraViews], lidars: list[LidarViews],
              solution: RigSolution, views: LidarViews) -> dict:
    """The graph solved with one LiDAR's frames as ``views`` (in the range model's form: ``ranged`` given, with
    or without terms), every other view as in ``lidars``, at the noise scales of ``solution`` (quasi-likelihood:
    an overdispersed sensor's costs are scaled down by its excess), started from ``solution``.

    Returns ``cost`` (the total cost, each of the LiDAR's frames' floor included: its points' scatter about
    their own best fit under these terms), ``size`` (the terms' count), and with terms ``values_m`` and ``sd_m``
    (marginal; inf where the graph's marginals cannot be formed)."""
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(100)
    k = names.index(views.name)
    graph, values, _, stems = _graph_at(names, reference, cameras,
                                        [views if v.name == views.name else v for v in lidars], solution)
    try:
        values = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    except RuntimeError as exc:
        raise DegenerateLayoutError(f"{views.name}: its range terms cannot be tested (the graph with them cannot be "
                                    "solved)", hint="calibrate with --range-model none") from exc
    floor = sum(fw.floor for st, fw in views.ranged.items() if st in stems)
    out = {"cost": 2.0 * graph.error(values) + floor / (views.sigma_m**2 * solution.noise_scale.get(views.name, 1.0)),
           "size": views.terms.size if views.has_terms else 0}
    if views.has_terms:
        out["values_m"] = values.atVector(terms_key(k)).copy()
        try:
            out["sd_m"] = np.sqrt(np.maximum(np.diag(gtsam.Marginals(graph, values).marginalCovariance(terms_key(k))),
                                             0.0))
        except RuntimeError:
            out["sd_m"] = np.full(out["size"], np.inf)
    return out


def terms_test(smaller: dict, larger: dict) -> dict:
    """The likelihood-ratio test of a LiDAR's larger range model against its smaller one (two :func:`terms_fit`
    results of nested models): the drop of the total cost, chi-square with the added terms' count as its dof.
    Returns ``statistic``, ``dof`` and ``p_value``."""
    stat = smaller["cost"] - larger["cost"]
    dof = max(larger["size"] - smaller["size"], 1)
    return {"statistic": float(stat), "dof": int(dof), "p_value": float(chi2.sf(max(stat, 0.0), dof))}


def _graph_at(names: tuple[str, ...], reference: str, cameras: list[CameraViews], lidars: list[LidarViews],
              solution: RigSolution) -> tuple:
    """The graph of these views at ``solution``'s noise scales and its values at ``solution`` (its poses, vector
    variables and refined intrinsics), with the graph's reference camera and the stems."""
    inner = graph_reference(reference, [c.name for c in cameras])
    stems = sorted(solution.T_ref_board)
    refine = solution.intrinsics is not None
    graph = _graph(names, cameras, lidars, stems, solution.noise_scale, inner, refine)
    values = _values(names, inner, stems, solution.T_ref, solution.T_ref_board, lidars, solution.vectors)
    for c in cameras if refine else ():
        values.insert(intrinsics_key(names.index(c.name)), solution.intrinsics[c.name][0])
    return graph, values, inner, stems


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
