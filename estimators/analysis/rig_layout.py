"""The next board pose for a rig's weakest camera-LiDAR pair.

A new frame seen by a camera and a LiDAR depends on the rig only through their relative pose ``T_camera_lidar``
(its board pose is a new unknown of its own). Its information on that pose, the board marginalised, is the
single pair's ``observation_model.frame_contribution`` ``S`` (in the right tangent of ``T_camera_lidar``), and the
pair's covariance after it is exactly ``(P^-1 + S)^-1``, ``P`` the pair's covariance from the rig's joint one
(``RigSolution.transform``): every other sensor's factors reach the pair only through ``P``. Candidates are the
single pair's feasible poses (``simulation.simulator.sample_board_poses``: in the camera's image, in the LiDAR's
field of view, hit by enough beams), scored by the pair's largest translation standard deviation after them.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from geometry.camera import CameraModel
from geometry.rotations import T_inverse

from ..lidar.lidar_models import BEAM_MODELS
from ..simulation.simulator import Rig, _pose_fits, min_in_image, sample_board_poses
from ..solvers.observation_model import Layout, board_returns, frame_contribution, frame_information

# Fewest beams on a candidate board (a 3D LiDAR's; a 2D scanner's line) for it to count as seen.
MIN_HITS_3D = 50
MIN_HITS_2D = 15


def beam_model_name(scan_line: bool, rings: int | None) -> str:
    """The beam model that casts a rig LiDAR's candidate boards: a 2D scanner's, a VLP-16's for a LiDAR whose
    boards show at most 20 rings, else an HDL-64E's (for the poses' feasibility and their beams)."""
    if scan_line:
        return "2d"
    return "vlp16" if rings is not None and 0 < rings <= 20 else "hdl64e"


def predicted_pair_covariance(P: np.ndarray, S: np.ndarray) -> np.ndarray:
    """``(P^-1 + S)^-1`` written without inverting ``P`` or ``S`` (either may be near singular): the pair's
    covariance ``P`` after a frame that adds information ``S`` on its tangent alone."""
    C = P @ np.linalg.solve(np.eye(6) + S @ P, np.eye(6))
    return 0.5 * (C + C.T)


def _max_translation_sd(C: np.ndarray) -> float:
    return float(np.sqrt(max(np.linalg.eigvalsh(C[3:, 3:])[-1], 0.0)))


# Draws for each candidate pose before the search gives up (no pose both sensors see: no advice, not an error).
CANDIDATE_TRIES = 2000


def next_pose_for_pair(camera: CameraModel, board, T_camera_lidar: np.ndarray, P: np.ndarray, corner_noise_px: float,
                       range_noise_m: float, beams_model: str, rng: np.random.Generator, candidates: int = 60
                       ) -> dict | None:
    """The board pose, among ``candidates`` feasible ones, after which the pair's largest translation standard
    deviation is smallest (module docstring); None when no candidate is feasible.

    Parameters
    ----------
    camera, board : CameraModel, BoardModel
        The pair's camera and the rig's board.
    T_camera_lidar : numpy.ndarray
        4x4, the pair's estimate.
    P : numpy.ndarray
        6x6, its covariance now (right tangent of ``T_camera_lidar``).
    corner_noise_px, range_noise_m : float
        The camera's effective corner noise and the LiDAR's range noise, as the graph weighs them.
    beams_model : str
        A key of ``lidar.lidar_models.BEAM_MODELS`` (:func:`beam_model_name`).
    rng : numpy.random.Generator
        Draws the candidates.

    Returns
    -------
    dict or None
        ``T_camera_board`` (4x4 list), ``board_centre_camera_m``, ``board_normal_camera``, ``distance_m``, the
        pair's largest translation standard deviation (mm) and rotation standard deviations (deg) before and
        after it, and its covariance after it (``covariance_after``).
    """
    beams = BEAM_MODELS[beams_model](range_noise_m)
    rig = Rig(camera, beams, board, T_camera_lidar)
    if beams.is_2d:  # boards near a 2D scanner's plane, as the 2D simulator places them
        rig = replace(rig, lidar_height_m=0.6, min_distance_m=1.5, max_distance_m=4.0)
    cut_share = 0.3 if board.is_charuco else 0.0
    try:
        drawn = sample_board_poses(rig, candidates, rng, max_tries=CANDIDATE_TRIES, outside_image_share=cut_share)
    except RuntimeError:  # no pose both sensors would see (a scan plane far from the camera's view): no advice
        return None
    pool = [T for T in drawn if _pose_fits(rig, T, min_in_image=min_in_image(board))]
    base = Layout(camera, board, beams, T_camera_lidar, (), corner_noise_px, range_noise_m)
    best, best_sd, best_C = None, np.inf, None
    for T in pool:
        trial = replace(base, T_camera_board=(T,))
        dirs, ranges, rings, _ = board_returns(trial, 0)
        if len(dirs) < (MIN_HITS_2D if beams.is_2d else MIN_HITS_3D):
            continue
        try:  # its information from the returns just cast (no range terms: their colours are not needed)
            F = frame_information(replace(trial, hits=((dirs, ranges, rings),)), 0)
            C = predicted_pair_covariance(P, frame_contribution(F))
        except np.linalg.LinAlgError:  # a candidate whose frame fixes no direction of its own board
            continue
        sd = _max_translation_sd(C)
        if sd < best_sd:
            best, best_sd, best_C = T, sd, C
    if best is None:
        return None
    centre = best[:3, :3] @ board.centre + best[:3, 3]
    return {"T_camera_board": best.tolist(), "board_centre_camera_m": centre.tolist(),
            "board_normal_camera": best[:3, 2].tolist(), "distance_m": float(np.linalg.norm(centre)),
            "board_centre_lidar_m": (T_inverse(T_camera_lidar)[:3, :3] @ centre
                                     + T_inverse(T_camera_lidar)[:3, 3]).tolist(),
            "max_translation_sd_mm_before": 1000 * _max_translation_sd(P),
            "max_translation_sd_mm_after": 1000 * best_sd,
            "std_rotation_deg_before": np.degrees(np.sqrt(np.maximum(np.diag(P)[:3], 0.0))).tolist(),
            "std_rotation_deg_after": np.degrees(np.sqrt(np.maximum(np.diag(best_C)[:3], 0.0))).tolist(),
            "covariance_after": best_C.tolist()}


def pair_next_pose(result, cam: str, lid: str, P: np.ndarray, rng: np.random.Generator, candidates: int = 60
                   ) -> dict | None:
    """:func:`next_pose_for_pair` for a rig's (``RigResult``) camera ``cam`` and LiDAR ``lid`` whose pair's
    covariance is ``P``, at the noise levels the graph weighed the two with, with ``pair``, ``camera`` and
    ``lidar`` added; None when either has no views in the graph or no candidate is feasible."""
    sol = result.solution
    cv = next((v for v in result.camera_views if v.name == cam), None)
    lv = next((v for v in result.lidar_views if v.name == lid), None)
    if cv is None or lv is None:
        return None
    rings = [len(np.unique(f.lidar.rings)) for (_, d), frames in (result.pair_frames or {}).items() if d == lid
             for f in frames if f.lidar is not None and f.lidar.rings is not None]
    camera = result.camera_model(cam)
    found = next_pose_for_pair(camera, result.rig.board, sol.transform(cam, lid)[0], P,
                               cv.sigma_px * np.sqrt(sol.noise_scale.get(cam, 1.0)),
                               lv.sigma_m * np.sqrt(sol.noise_scale.get(lid, 1.0)),
                               beam_model_name(lv.scan_line, max(rings) if rings else None), rng, candidates)
    return None if found is None else {"pair": f"T_{cam}_{lid}", "camera": cam, "lidar": lid, **found}


def suggest_rig_poses(result, k: int, rng: np.random.Generator, target: tuple[float, float] | None = None,
                      candidates: int = 60) -> list[dict]:
    """Up to ``k`` board poses to add to a rig, greedily: each for the camera-LiDAR pair whose predicted largest
    translation standard deviation is then the largest (:func:`pair_next_pose`), that pair's covariance updated
    to its prediction after it (the others' kept: a pose seen by two sensors tightens the rest of the rig only
    through them, so their predictions are conservative). ``target``: ``(deg, mm)``, stop as soon as every
    camera-LiDAR pair's rotation and translation standard deviations meet it. Each pose is
    :func:`pair_next_pose`'s."""
    covs = {(c.name, d.name): result.solution.transform(c.name, d.name)[1] for c in result.rig.cameras
            for d in result.rig.lidars}
    out: list[dict] = []
    while len(out) < k and covs:
        sd_t = {p: _max_translation_sd(C) for p, C in covs.items()}
        if target is not None and all(np.degrees(np.sqrt(max(np.diag(C)[:3].max(), 0.0))) <= target[0]
                                      and 1000 * sd_t[p] <= target[1] for p, C in covs.items()):
            break
        cam, lid = max(sd_t, key=sd_t.get)
        found = pair_next_pose(result, cam, lid, covs[(cam, lid)], rng, candidates)
        if found is None:  # no feasible pose for it: the next weakest pair
            covs.pop((cam, lid))
            continue
        covs[(cam, lid)] = np.array(found["covariance_after"])
        out.append(found)
    return out


def next_pose_words(found: dict) -> str:
    """:func:`next_pose_for_pair`'s pose (with ``camera``, ``lidar`` and ``pair`` added) in words."""
    c, n = np.array(found["board_centre_camera_m"]), np.array(found["board_normal_camera"])
    tilt = np.degrees(np.arccos(min(abs(float(n @ c)) / np.linalg.norm(c), 1.0)))
    return (f"the board's centre at ({c[0]:.2f}, {c[1]:.2f}, {c[2]:.2f}) m in {found['camera']}'s frame, its normal "
            f"({n[0]:.2f}, {n[1]:.2f}, {n[2]:.2f}) ({tilt:.0f} deg from the line of sight), seen by "
            f"{found['camera']} and {found['lidar']}: {found['pair']}'s translation sd up to "
            f"{found['max_translation_sd_mm_before']:.1f} -> {found['max_translation_sd_mm_after']:.1f} mm (predicted)")
