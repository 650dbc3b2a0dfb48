"""``lidarcam calibrate DATA --targetless --initial-guess T``: the extrinsic from the scene alone, no board.

The scene's contours are laid on the image's edges (``solvers.scene_alignment``) starting from the guess: first
by their plain distance to the nearest edge truncated at ``COARSE_PX`` (a start a few degrees off lies tens of
pixels from its edges; that distance, unlike the residual along the ring, pulls from anywhere near an edge),
then as the check does (``align_scene``: along the rings, truncated at 20 px, then 6 px), the contours the camera
sees recomputed under each stage's start. The same is done from ``PROBES`` starts about the guess (turned by
``PROBE_DEG`` about, or moved by ``PROBE_M`` along, the camera's axes); the lowest end is the estimate, and from
there the check's 13 starts (``scene_minima``) give its covariance (the block sandwich plus the scatter of the
minima the blocks cannot tell from it).

Refused (a :class:`DegenerateLayoutError`, nothing written), never returned as converged:

- fewer than ``MIN_LANDED`` of the starts end together at the lowest end (from there the 13 starts may still
  find a lower minimum nearby: the estimate): a start the scene cannot pull in wanders to a minimum of its own (on
  a simulated room, from 15 degrees and 80 cm off, the seven ends lay apart, each with most contours off the
  edges), while the starts about a guess within reach end together. Together: within the 0.999 region of the
  covariance the estimate is reported with (its minima's scatter included; the estimate's own curvature alone
  refused 4 of 12 VLP-16 rooms from 2 degrees and 10 cm off, whose starts had ended at minima the scene's blocks
  cannot tell apart, 1 with it, docs/bench/targetless.md);
- another end as low (within ``RIVAL_RMS`` of its RMS residual) lies beyond the estimate's 0.999 region: the
  scene's cost has several minima within the start's reach, and which is the extrinsic is not known;
- the scene constrains fewer than all six directions (standard deviations within 1 degree and 10 cm);
- fewer than two frames hold contours in the camera's view.

The verdict is UNTRUSTED where the even and the odd frames, solved apart from the estimate, do not solve or land
farther apart than ``HALVES_D2`` under the sum of their covariances, scaled by the excess that covariance shows
on simulated rooms (``COVARIANCE_EXCESS``; a VLP-16's room of 100 contour returns can
hold a lower minimum a degree from the truth, which every start then reaches; its halves cannot pin it), CHECK
otherwise.

The board, where the folder has one and the camera finds it, is left out as in the check (``keep_board`` keeps
it). The covariance is the scene's Laplace one (no sampled posterior: the residuals are neither Gaussian nor
independent, and the blocks' sandwich stands in for their likelihood) times ``COVARIANCE_EXCESS``. On simulated
rooms it holds the truth (docs/bench/targetless.md); on recorded frames the estimate moves with the check's own
edge and contour settings by several of its standard deviations (docs/bench/scene_sensitivity.md), which the
verdict says.
"""
from __future__ import annotations

import os
import time
from dataclasses import dataclass, replace

import numpy as np

from geometry.camera import CameraModel
from geometry.rotations import R_from_rotvec, T_from_Rt, T_inverse, T_log

from .. import __version__
from ..camera.edge_map import TRUNCATE_PX
from ..errors import DegenerateLayoutError, about
from ..solvers.scene_alignment import (CONSTRAINED, RIVAL_D2, RIVAL_RMS, STAGES_PX, SceneFit, align_once,
                                      align_scene, consistency, constrained_directions, minima_scatter, narrowed,
                                      rival_minima, rms_px, scene_minima)
from .measurement import rigid
from .result import CONVENTION, COVARIANCE_CONVENTION
from .scene_check import SceneCheck, frame_edges, read_scene_frames, refuse_inverted, scene_view, too_few
from .verdict import CHECK, UNTRUSTED, Verdict

# The factor on a targetless estimate's covariance. The lowest of many starts' minima, it can lie at another
# minimum than the truth's: with the minima's scatter counting only those within 1% of its RMS, its NEES had median
# 12 on simulated 64-beam rooms (seeds 0-39) and this was 2. Counting the minima the blocks cannot tell from it
# (``minima_scatter``), at 1 its NEES means were 2.5 (VLP-16) and 2.8 (64 beams) from 2 degrees and 10 cm off
# (seeds 0-23, ad hoc); docs/bench/targetless.md gives seeds 100-123.
COVARIANCE_EXCESS = 1.0
COARSE_PX = (60.0,)
PROBE_DEG, PROBE_M = 2.0, 0.10
PROBES = 6  # the guess turned about each camera axis by +-PROBE_DEG alternately, then moved along each
# Starts that must end together at the lowest end (the 0.999 region of the estimate's reported covariance, or
# within SAME_DEG and SAME_M of it).
MIN_LANDED = 3
SAME_DEG, SAME_M = 0.05, 0.005
# The even and the odd frames' estimates may differ by up to this squared distance (chi-square, 6 dof, 0.999),
# under the sum of their covariances scaled by the excess the scene's covariance shows (``COVARIANCE_EXCESS``).
HALVES_D2 = 22.46


@dataclass(frozen=True, eq=False)
class TargetlessResult:
    """The scene's extrinsic refined from ``T_guess``: the scene's estimate with its covariance and minima (``scene``:
    a :class:`~estimators.pipeline.scene_check.SceneCheck` of the guess), every start's end (``ends``: start, end,
    RMS residual) and the time taken."""

    T_guess: np.ndarray
    scene: SceneCheck
    ends: tuple
    seconds: float
    # The even and the odd frames solved apart from the estimate: ``d2`` (their difference under the sum of
    # their covariances, 6 dof), ``apart_deg`` and ``apart_mm``; or ``problem`` where a half does not solve.
    halves: dict | None = None
    # How many of the starts ended together at the lowest end (``MIN_LANDED``'s count: within the 0.999 region of
    # the covariance reported, or within ``SAME_DEG`` and ``SAME_M``), the lowest's own start included.
    landed: int | None = None

    @property
    def T_camera_lidar(self) -> np.ndarray:
        return self.scene.fit.T_camera_lidar

    @property
    def covariance(self) -> np.ndarray:
        return self.scene.believed_covariance

    @property
    def verdict(self) -> Verdict:
        h = self.halves or {}
        if h.get("problem"):
            return Verdict(UNTRUSTED, (f"targetless: {h['problem']}: the scene is too thin to trust this estimate "
                                       "(give more frames, with objects at several distances)",))
        if h.get("d2") is not None and h["d2"] > HALVES_D2:
            return Verdict(UNTRUSTED, (f"targetless: the even and the odd frames disagree ({h['apart_deg']:.2f} deg "
                                       f"and {h['apart_mm']:.0f} mm apart, d2 {h['d2']:.0f} on 6 dof): the scene's "
                                       "cost leads each half elsewhere",))
        return Verdict(CHECK, ("targetless: on simulated rooms the scene's covariance holds the truth "
                               "(docs/bench/targetless.md), but on recorded frames the scene's estimate moves with "
                               "its own edge and contour settings by several of its standard deviations "
                               "(docs/bench/scene_sensitivity.md): check the estimate against a board calibration "
                               "where one is at hand",))

    def moved(self) -> tuple[float, float]:
        """How far the estimate lies from the guess: angle (deg) and translation (mm)."""
        xi = T_log(T_inverse(self.T_guess) @ self.T_camera_lidar)
        return (float(np.degrees(np.linalg.norm(xi[:3]))),
                1000 * float(np.linalg.norm(self.T_camera_lidar[:3, 3] - self.T_guess[:3, 3])))

    def to_dict(self) -> dict:
        rot, trans = self.scene.camera_axes_sd()
        angle, shift = self.moved()
        fit = self.scene.fit
        return {
            "verdict": self.verdict.to_dict(), "tool": "lidarcam", "version": __version__,
            "dataset": self.scene.dataset, "method": "targetless: the scene's depth contours on the image's edges",
            "T_camera_lidar": self.T_camera_lidar.tolist(), "convention": CONVENTION,
            "covariance": self.covariance.tolist(), "covariance_convention": COVARIANCE_CONVENTION,
            "posterior": "Laplace (the covariance); no samples",
            "std_rotation_deg_about_camera_xyz": rot.tolist(), "std_translation_mm_along_camera_xyz": trans.tolist(),
            "initial_guess": self.T_guess.tolist(), "intrinsics": self.scene.camera.as_dict(),
            "moved_from_guess": {"rotation_deg": angle, "translation_mm": shift},
            "scene": {"rms_px": fit.rms_px, "contour_returns": fit.points, "blocks": fit.blocks,
                      "converged": fit.converged,
                      "rival_minima": [{"T_camera_lidar": f.T_camera_lidar.tolist(), "rms_px": f.rms_px}
                                       for f in self.scene.rivals]},
            "starts": [{"T_start": s.tolist(), "T_end": e.tolist(), "rms_px": r} for s, e, r in self.ends],
            "starts_together": self.landed,
            "halves": self.halves,
            "frames_used": list(self.scene.frames_used), "frames_skipped": self.scene.skipped,
            "board_left_out": self.scene.board_left_out, "timings_s": {"targetless": self.seconds},
        }


def _within(T: np.ndarray, T_other: np.ndarray, cov: np.ndarray) -> bool:
    """Whether ``T_other`` lies within ``T``'s 0.999 region under ``cov``, or within ``SAME_DEG`` and ``SAME_M``."""
    xi = T_log(T_inverse(T) @ T_other)
    return bool(xi @ np.linalg.solve(cov, xi) <= RIVAL_D2
                or (np.linalg.norm(xi[:3]) <= np.radians(SAME_DEG) and np.linalg.norm(xi[3:]) <= SAME_M))


def _starts(T_guess: np.ndarray) -> list[np.ndarray]:
    """The guess and ``PROBES`` starts about it: turned about the camera's x, y, z by +-PROBE_DEG (signs
    alternating), then moved along them by +-PROBE_M."""
    starts = [T_guess]
    for k in range(PROBES):
        e = np.zeros(3)
        e[k % 3] = 1.0 if k % 2 == 0 else -1.0
        if k < 3:
            starts.append(T_from_Rt(R_from_rotvec(np.radians(PROBE_DEG) * e), np.zeros(3)) @ T_guess)
        else:
            starts.append(T_from_Rt(np.eye(3), PROBE_M * e) @ T_guess)
    return starts


def calibrate_targetless(folder: str | os.PathLike, T_guess: np.ndarray, keep_board: bool = False,
                         camera: CameraModel | None = None) -> TargetlessResult:
    """The extrinsic from the scene of ``folder``, refined from ``T_guess`` (module docstring).

    Parameters
    ----------
    folder : str or os.PathLike
        A camera-LiDAR folder of synchronised frames (dataset.yaml with ``camera:``; ``board:`` optional); the
        sweeps need each return's beam (a ``ring`` field or an organised cloud).
    T_guess : numpy.ndarray
        4x4 ``T_camera_lidar`` to start from: within a few degrees and 10-20 cm.
    keep_board : bool
        Keep the board's edges and contours (by default left out where the camera finds it).
    camera : CameraModel, optional
        The camera's model to refine under (default dataset.yaml's): a guess from a calibration is refined under
        the intrinsics it was estimated with, refined or given (``measurement.given_camera``), as ``check`` does.
        Its image size must be the folder's camera's.

    Returns
    -------
    TargetlessResult
        The estimate, its covariance, every start's end and the verdict.

    Raises
    ------
    DegenerateLayoutError
        Several minima as low within the start's reach, fewer than six constrained directions, or fewer than
        two frames with contours in view.
    """
    t0 = time.perf_counter()
    T_guess = rigid(T_guess, folder, "the initial guess")
    root, camera, board, frames, skipped = read_scene_frames(folder, keep_board, camera)
    # The edges square to the rings under the guess (a few degrees turn them by a few degrees): made once.
    edges = {f.name: frame_edges(f.gray, T_guess, camera, f.board_mask) for f in frames}

    def views_at(T: np.ndarray, truncate_px: float, chamfer: bool = False) -> list:
        out = []
        for f in frames:
            v = scene_view(f.name, f.gray, f.sweep, T, camera, f.board_mask, truncate_px, edges[f.name])
            v = replace(v, chamfer=chamfer)
            if len(v.points):
                out.append(v)
        if len(out) < 2:
            raise too_few(out, skipped, root)
        return out

    def refine(T: np.ndarray) -> SceneFit:
        with about(root):
            for px in sorted(COARSE_PX, reverse=True):
                T = align_once(views_at(T, px, chamfer=True), camera, T, 60).T_camera_lidar
            return align_scene(views_at(T, TRUNCATE_PX), camera, T)

    ends = []
    for start in _starts(T_guess):
        try:
            fit = refine(start)
        except DegenerateLayoutError:
            if start is T_guess:
                refuse_inverted((root, camera, board, frames, skipped), T_guess, keep_board, None, "the initial guess")
                raise
            continue
        ends.append((start, fit))
    ends.sort(key=lambda e: e[1].rms_px)
    best = ends[0][1]
    views = views_at(best.T_camera_lidar, TRUNCATE_PX)
    fits = scene_minima(views, camera, best.T_camera_lidar, narrow_from_every_start=True)
    cov = fits[0].covariance + minima_scatter(fits, views, camera, best.T_camera_lidar)
    estimate = fits[0]
    for _, f in ends[1:]:
        xi = T_log(T_inverse(estimate.T_camera_lidar) @ f.T_camera_lidar)
        if f.rms_px <= estimate.rms_px * (1 + RIVAL_RMS) and xi @ np.linalg.solve(cov, xi) > RIVAL_D2:
            angle = np.degrees(np.linalg.norm(xi[:3]))
            raise DegenerateLayoutError(
                f"the scene's cost has minima as low {angle:.2f} deg and "
                f"{1000 * np.linalg.norm(f.T_camera_lidar[:3, 3] - estimate.T_camera_lidar[:3, 3]):.0f} mm apart "
                "within the start's reach: the scene alone does not tell which is the extrinsic", path=root,
                hint="give more frames with objects at several distances, or calibrate with a board")
    landed = sum(_within(best.T_camera_lidar, f.T_camera_lidar, cov) for _, f in ends)
    if landed < MIN_LANDED:
        raise DegenerateLayoutError(
            f"{landed} of the {len(ends)} starts about the guess (within {PROBE_DEG:g} deg and {100 * PROBE_M:g} cm of "
            f"it) end together at the lowest end: the guess lies outside the scene's basin there", path=root,
            hint="give a guess within a few degrees and 10-20 cm (a board calibration, the rig's drawings), or "
                 "calibrate with a board")
    V, _ = constrained_directions(cov, CONSTRAINED)
    if V.shape[1] < 6:
        raise DegenerateLayoutError(f"the scene constrains {V.shape[1]} of the extrinsic's 6 directions (standard "
                                    "deviations within 1 deg and 10 cm)", path=root,
                                    hint="give frames with objects at several distances and in every part of the "
                                         "image, or calibrate with a board")
    # The page's "RMS at the given extrinsic": the guess's, on the estimate's contours and fields.
    estimate = replace(estimate, rms_start_px=rms_px(T_guess, [narrowed(v, min(STAGES_PX)) for v in views], camera))
    check = SceneCheck(str(root), T_guess, estimate, consistency(estimate, T_guess, covariance=cov),
                       tuple(v.name for v in views), skipped, camera, board is not None and not keep_board,
                       time.perf_counter() - t0, tuple(views), tuple(rival_minima(fits)), cov,
                       excess=COVARIANCE_EXCESS)
    halves = _halves(views, camera, estimate.T_camera_lidar)
    return TargetlessResult(T_guess, check, tuple((s, f.T_camera_lidar, f.rms_px) for s, f in ends),
                            time.perf_counter() - t0, halves, landed)


def _halves(views: list, camera, T: np.ndarray) -> dict:
    """The even and the odd frames solved apart from ``T`` (each with the check's starts and covariance), and
    how far apart they land against the sum of their covariances times ``COVARIANCE_EXCESS``; ``problem`` where a
    half does not solve."""
    got = []
    for name, part in (("the even frames", views[0::2]), ("the odd frames", views[1::2])):
        try:
            fits = scene_minima(part, camera, T)
        except DegenerateLayoutError as exc:
            return {"problem": f"{name} alone do not solve ({exc.problem})"}
        got.append((fits[0].T_camera_lidar, fits[0].covariance + minima_scatter(fits, part, camera, T)))
    (Ta, Ca), (Tb, Cb) = got
    xi = T_log(T_inverse(Ta) @ Tb)
    try:
        d2 = float(xi @ np.linalg.solve(COVARIANCE_EXCESS * (Ca + Cb), xi))
    except np.linalg.LinAlgError:
        return {"problem": "the halves' covariances are singular"}
    return {"d2": d2, "apart_deg": float(np.degrees(np.linalg.norm(xi[:3]))),
            "apart_mm": 1000 * float(np.linalg.norm(Ta[:3, 3] - Tb[:3, 3]))}
