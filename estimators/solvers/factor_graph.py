"""The one factor graph of a calibration: every sensor's pose in the graph's reference camera's frame and one board
pose per frame (``graph_keys``), built from each sensor's views. A camera-LiDAR pair is the rig of its camera
(the reference) and its LiDAR (``graph_keys.EXTRINSIC``).

Factors:

- each camera's corners in each frame it saw, through ``T_s_board = T_ref_s^-1 T_ref_board``. With right tangents,
  ``T_s_board`` moves by ``xi_board`` for the board's and by ``-Ad(T_s_board^-1) xi_s`` for the sensor's
  (:func:`rig_corner_residuals`); the reference camera's through the board's pose alone. With
  ``refine_intrinsics`` each camera's intrinsics ``[fx, fy, cx, cy, dist...]`` are a vector variable of its corner
  factors too (the corners' Jacobians by them from ``geometry.camera``), under a prior of its ``param_std``;
- each LiDAR's board points in each frame it saw: the board's plane mapped into the LiDAR through ``T_ref_s`` and
  ``T_ref_board`` (``factors.plane_factor``), in the range model's form when the LiDAR has one (its terms a vector
  variable under their priors);
- with the board's edges, each LiDAR's ring ends on the board's outline (``board_edges.edge_factor``), with its
  outline and each frame's outline shift as vector variables under their priors.

The noise: each camera's corners isotropic at their frame's pixel noise; each LiDAR's planes at its range noise
with the board's plane error (``LidarViews.plane_cov``), under a robust loss when given; both times the sensor's
scale (quasi-likelihood, ``rig_graph.solve_rig``).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from functools import partial

import gtsam
import numpy as np

from geometry.camera import CameraModel

from .board_edges import deviation_prior, edge_factor, outline_prior, shift_prior
from .factors import (affine_plane_factor, corner_factor, corner_intrinsics_factor, corner_residuals,
                      corner_residuals_intrinsics, lidar_residual, nuisance_plane_factor, nuisance_residual,
                      plane_factor)
from .graph_keys import (edge_deviation_key, edge_shift_key, frame_key, intrinsics_key, outline_key, sensor_key,
                         terms_key)
from .noise_levels import frame_noise, plane_noise, robust_noise
from .range_model import RangeTerms


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
    (``range_model.frame_whitener``: ``|W pi|^2`` is their sum of squared range errors), its range noise (m),
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
    # Per stem the board's plane error beyond the points' range noise (:class:`PlaneError`; a stem without one:
    # the range noise alone), the robust loss on each plane (``RefinementOptions``; None: none), the boards'
    # scatter along their range terms' weak direction (m) and the terms' prior sds (None: ``terms.prior_sd``).
    plane_error: dict | None = None
    robust: object = None
    tau_m: float = 0.0
    terms_prior_sd: np.ndarray | None = None
    # Per stem the board points' squared range residuals about their own best fit (m^2) and their dof
    # (``noise_levels.own_fit_residuals``): a 2D scanner's range noise rests on them, and its posterior samples its
    # scale (``rig_posterior``).
    own_fit: dict | None = None

    @property
    def has_terms(self) -> bool:
        return self.ranged is not None and self.terms is not None and self.terms.size > 0

    def plane_cov(self, stem: str, scale: float = 1.0) -> np.ndarray | None:
        """The covariance of frame ``stem``'s plane residual in the form the graph uses (``W pi``, or the range
        model's), times ``scale``: the range noise, with the board's plane error and the boards' scatter
        (``noise_levels.frame_noise``); None when the frame has no plane error (the range noise alone)."""
        pe = None if self.plane_error is None else self.plane_error.get(stem)
        if pe is None:
            return None
        if self.ranged is not None:
            return scale * frame_noise(self.ranged[stem], pe.normal, self.sigma_m, pe.floor_m, pe.half_m, pe.scale_m,
                                       self.tau_m)
        return scale * plane_noise(self.W[stem], pe.normal, self.sigma_m, pe.floor_m, pe.half_m, pe.scale_m,
                                   pe.centre)

    def plane_cov_parts(self, stem: str, scale: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`plane_cov` (the range noise alone when None) split into its LiDAR part (the range noise and the
        boards' scatter) and its camera side (the per-board plane error and the pattern's scale error), whose scale
        the posterior samples (``rig_posterior``)."""
        k = (self.ranged[stem].W if self.ranged is not None else self.W[stem]).shape[0]
        pe = None if self.plane_error is None else self.plane_error.get(stem)
        if pe is None:
            return scale * self.sigma_m**2 * np.eye(k), np.zeros((k, k))
        if self.ranged is not None:
            fw = self.ranged[stem]
            return (scale * frame_noise(fw, pe.normal, self.sigma_m, 0.0, pe.half_m, 0.0, self.tau_m),
                    scale * frame_noise(fw, pe.normal, 0.0, pe.floor_m, pe.half_m, pe.scale_m, 0.0))
        W = self.W[stem]
        return (scale * plane_noise(W, pe.normal, self.sigma_m, 0.0, pe.half_m, 0.0, pe.centre),
                scale * plane_noise(W, pe.normal, 0.0, pe.floor_m, pe.half_m, pe.scale_m, pe.centre))

    def chi2(self, stem: str, e: np.ndarray, scale: float = 1.0) -> float:
        """The frame's residual ``e`` (:func:`lidar_frame_residual`) squared in units of its covariance."""
        C = self.plane_cov(stem, scale)
        return float(e @ e) / (self.sigma_m**2 * scale) if C is None else float(e @ np.linalg.solve(C, e))


@dataclass(frozen=True)
class PlaneError:
    """A board's plane error beyond its points' range noise (``noise_levels.plane_noise``): the LiDAR board's
    normal and centroid (LiDAR frame), the board's half-size, the per-board plane error (m at the board's edge
    and along its normal, estimated from the planes' disagreement) and the camera board's distance error from a
    scale error of its pattern (m)."""

    normal: np.ndarray
    centre: np.ndarray | None
    half_m: float
    floor_m: float
    scale_m: float

    @classmethod
    def of_frame(cls, frame, centre: np.ndarray | None, board, floor_m: float, corner_scale_sd: float) -> "PlaneError":
        """A frame's (``FrameMeasurement``) plane error: its LiDAR board's normal, the board points' ``centre``,
        half the board's mean extent, ``floor_m``, and the pattern-scale error ``corner_scale_sd`` (relative) at
        the camera board's distance."""
        return cls(frame.lidar.plane.normal, centre, 0.5 * float(np.mean(board.extent)), floor_m,
                   corner_scale_sd * frame.camera.plane.distance)


def adjoint(T: np.ndarray) -> np.ndarray:
    """GTSAM's Pose3 adjoint in ``[rot; trans]`` order: ``T Exp(xi) T^-1 = Exp(Ad(T) xi)``."""
    return gtsam.Pose3(T).AdjointMap()


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


def build_graph(names, cameras, lidars, stems, scale, reference, refine_intrinsics=False,
                owners: list | None = None) -> gtsam.NonlinearFactorGraph:
    """The factor graph of these views over the frames ``stems`` (``frame_key`` by their index; module docstring),
    each sensor's noise times its ``scale``, the camera ``reference`` the graph's own frame (no variable).
    ``owners`` (a list, filled): per factor the sensor whose measurement residuals it holds (corners, LiDAR
    planes), None for the others (priors, edges). The priors come first, then frame by frame its LiDARs' ends,
    its cameras' corners and its LiDARs' planes."""
    factors = gtsam.NonlinearFactorGraph()
    at = {s: j for j, s in enumerate(stems)}

    def add(factor, owner: str | None = None) -> None:
        factors.add(factor)
        if owners is not None:
            owners.append(owner)

    for c in cameras:
        if refine_intrinsics and c.camera.param_std is not None:
            add(gtsam.PriorFactorVector(intrinsics_key(names.index(c.name)), c.camera.params,
                                        gtsam.noiseModel.Diagonal.Sigmas(np.asarray(c.camera.param_std))))
    for lv in lidars:
        k = names.index(lv.name)
        if lv.has_terms:
            sd = lv.terms.prior_sd if lv.terms_prior_sd is None else lv.terms_prior_sd
            add(gtsam.PriorFactorVector(terms_key(k), np.zeros(lv.terms.size),
                                        gtsam.noiseModel.Diagonal.Sigmas(np.asarray(sd, dtype=float))))
        if lv.edges is not None:
            add(outline_prior(outline_key(k)))
    for stem, j in at.items():
        fk = frame_key(j)
        for lv in lidars:
            if lv.edges is not None and stem in lv.edges:
                k = names.index(lv.name)
                add(shift_prior(edge_shift_key(k, j), lv.edge_tau_m))
                pe = deviating(lv, stem)
                if pe is not None:
                    add(deviation_prior(edge_deviation_key(k, j), pe.floor_m, pe.half_m))
                add(edge_factor(sensor_key(k), fk, edge_shift_key(k, j), lv.edges[stem], lv.board, lv.edge_scale,
                                outline_key(k), None if pe is None else edge_deviation_key(k, j)))
        for c in cameras:
            if stem in c.corners_px:
                add(_corner_factor(c, names.index(c.name), stem, fk, scale[c.name], reference, refine_intrinsics),
                    c.name)
        for lv in lidars:
            if stem in lv.W:
                add(_plane_factor(lv, names.index(lv.name), stem, fk, scale[lv.name]), lv.name)
    return factors


def _corner_factor(c, k: int, stem: str, fk: int, scale: float, reference: str, refine_intrinsics: bool):
    """Camera ``c``'s (sensor ``k``) corners of frame ``stem`` (key ``fk``): through its pose in the rig, or the
    board's alone for the graph's reference camera; with its intrinsics as a variable too."""
    px = c.corners_px[stem]
    noise = gtsam.noiseModel.Isotropic.Sigma(px.size, c.sigma(stem) * np.sqrt(scale))
    if refine_intrinsics and c.name == reference:
        return corner_intrinsics_factor(fk, intrinsics_key(k), c.corners_board[stem], px, c.camera, noise)
    if refine_intrinsics:
        return gtsam.CustomFactor(noise, [sensor_key(k), fk, intrinsics_key(k)],
                                  partial(_rig_corner_intrinsics_error, np.asarray(c.corners_board[stem], dtype=float),
                                          np.asarray(px, dtype=float).reshape(-1, 2), c.camera))
    if c.name == reference:
        return corner_factor(fk, c.corners_board[stem], px, c.camera, noise)
    return rig_corner_factor(sensor_key(k), fk, c.corners_board[stem], px, c.camera, noise)


def _plane_factor(lv, k: int, stem: str, fk: int, scale: float):
    """LiDAR ``lv``'s (sensor ``k``) board points of frame ``stem`` (key ``fk``): its plane, in the range model's
    form when it has one (with its terms as a variable, or without terms: the form they are tested against)."""
    rows = (lv.W[stem] if lv.ranged is None else lv.ranged[stem].W).shape[0]
    C = lv.plane_cov(stem, scale)
    if C is None:
        noise = gtsam.noiseModel.Isotropic.Sigma(rows, lv.sigma_m * np.sqrt(scale))
    else:
        noise = gtsam.noiseModel.Gaussian.Covariance(C)
    if lv.robust is not None:
        noise = robust_noise(noise, lv.robust, rows)
    if lv.ranged is None:
        return plane_factor(sensor_key(k), fk, lv.W[stem], noise, lv.scan_line)
    fw = lv.ranged[stem]
    if lv.has_terms:
        return nuisance_plane_factor(sensor_key(k), fk, terms_key(k), fw.W, fw.S, fw.m_away, fw.e0, noise,
                                     lv.scan_line)
    return affine_plane_factor(sensor_key(k), fk, fw.W, fw.m_away, fw.e0, noise, lv.scan_line)


def lidar_frame_residual(lv: LidarViews, stem: str, pi: np.ndarray, beta: np.ndarray | None = None) -> np.ndarray:
    """The LiDAR's residual of frame ``stem`` (m) at the board plane ``pi`` (in the LiDAR frame) and its range
    terms ``beta`` (ignored without them)."""
    if lv.ranged is None:
        return lidar_residual(lv.W[stem], pi, lv.scan_line)[0]
    fw = lv.ranged[stem]
    beta = np.asarray(beta, dtype=float) if lv.has_terms else np.zeros(0)
    S = fw.S if lv.has_terms else np.zeros((0, 0))
    return nuisance_residual(fw.W, S, fw.m_away, pi, beta, lv.scan_line, fw.e0)[0]



def vector_keys(names, stems: list[str], lidars) -> dict:
    """The graph's vector variables of the ``lidars`` (each key and its size): range terms, and with the
    board's edges each LiDAR's outline and its frames' outline shifts."""
    out = {}
    for lv in lidars:
        k = names.index(lv.name)
        if lv.has_terms:
            out[terms_key(k)] = lv.terms.size
        if lv.edges is not None:
            out[outline_key(k)] = 4
            out.update({edge_shift_key(k, stems.index(st)): 2 for st in lv.edges if st in stems})
            out.update({edge_deviation_key(k, stems.index(st)): 3 for st in lv.edges
                        if st in stems and deviating(lv, st) is not None})
    return out


def deviating(lv: LidarViews, stem: str) -> "PlaneError | None":
    """Frame ``stem``'s plane error where its ends take it too (``board_edges.deviation_prior``): a 3D LiDAR's
    frame with edges whose planes need a per-board plane error; else None."""
    pe = None if lv.plane_error is None or lv.scan_line else lv.plane_error.get(stem)
    return pe if pe is not None and pe.floor_m > 0 else None


def graph_values(names, inner: str, stems: list[str], T_ref: dict, T_ref_board: dict, lidars=(),
            vectors: dict | None = None) -> gtsam.Values:
    """The graph's pose variables in the frame of its reference camera ``inner``, and the vector variables of the
    ``lidars`` (:func:`_vector_keys`) at ``vectors`` (by key; 0 where not given or of another size)."""
    T_inner = np.linalg.inv(T_ref[inner])
    values = gtsam.Values()
    for key, size in vector_keys(names, stems, lidars).items():
        given = np.asarray((vectors or {}).get(key, np.zeros(size)), dtype=float)
        values.insert(key, given if given.size == size else np.zeros(size))  # another model's terms: from 0
    for k, n in enumerate(names):
        if n != inner:
            values.insert(sensor_key(k), gtsam.Pose3(T_inner @ T_ref[n]))
    for j, s in enumerate(stems):
        values.insert(frame_key(j), gtsam.Pose3(T_inner @ T_ref_board[s]))
    return values


