"""How a layout of board poses conditions the calibration, and which pose to add next.

From the Fisher information of the full model (corner pixels and beam ranges, board poses marginalised;
:mod:`estimators.solvers.observation_model`): the predicted covariance (the Cramer-Rao bound) and standard
deviations per axis, the condition number of the board normals, D- and E-optimality, the weakest
direction in words, and each frame's leverage. Optimality is measured in scaled units, milliradians and
millimetres, so that rotation and translation weigh alike: ``D = det(F)^(1/6)`` and ``E = lambda_min(F)``
(information per mrad^2 or mm^2).

A plan (``PLAN.yaml``) describes a rig and the board poses it will record::

    camera: {model: pinhole, width: 1024, height: 768, K: [[940, 0, 512], [0, 940, 384], [0, 0, 1]],
             dist: [-0.1, 0.06, 0, 0, 0]}
    board: {squares: [9, 7], square_size: 0.1, size: [1.0, 1.0]}
    lidar: {model: hdl64e, range_noise_m: 0.02}
    corner_noise_px: 0.2                  # effective per-corner noise (px)
    T_camera_lidar: 4x4                   # optional; default: the simulator's nominal mounting
    poses:                                # board centre in the camera frame (m), normal tilted from the
      - {centre_m: [0.3, -0.2, 3.0], tilt_deg: 30, azimuth_deg: 45, spin_deg: 0}   # line of sight
      - {T_camera_board: 4x4}             # or a full pose
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from geometry.rotations import R_from_rotvec, T_from_Rt

from ..errors import DatasetError
from ..lidar.lidar_models import BEAM_MODELS
from ..simulation.simulator import (R_CAMERA_LIDAR_NOMINAL, Rig, _pose_fits, board_pose, min_in_image,
                                    sample_board_poses)
from ..solvers.closed_form import describe_direction, normal_spread
from ..solvers.observation_model import (Layout, board_hits, board_returns, edges_information,
                                        frame_contribution, frame_information, range_model_information)
from ..solvers.range_model import OFFSET_PRIOR_SD_M, RangeTerms

_SCALE = np.array([1e3] * 6)  # rad -> mrad, m -> mm
MIN_BOARD_HITS = 50
MIN_BOARD_HITS_2D = 15  # one scan line crosses a board


@dataclass(frozen=True, eq=False)
class LayoutAnalysis:
    names: tuple[str, ...]
    covariance: np.ndarray  # predicted, GTSAM tangent of T_camera_lidar (inf where unobservable)
    information: np.ndarray
    normal_singular_values: np.ndarray
    d_optimality: float
    e_optimality: float
    weakest_words: str
    leverage: np.ndarray  # per frame: fraction of D-optimality lost without it
    # With a global LiDAR range offset estimated too (prior OFFSET_PRIOR_SD_M): the translation's standard
    # deviations (mm), the offset's (mm), and its correlation with the translation along the LiDAR's x y z.
    offset: dict | None = None
    # With the board's edges too (a 3D LiDAR's ``--edges``, a 2D scan's segment ends; the board's size known):
    # the predicted rotation (deg) and translation (mm) standard deviations.
    edges: dict | None = None

    @property
    def std_rotation_deg(self) -> np.ndarray:
        return np.degrees(np.sqrt(np.diag(self.covariance)[:3]))

    @property
    def std_translation_mm(self) -> np.ndarray:
        return 1000 * np.sqrt(np.diag(self.covariance)[3:])

    @property
    def condition_number(self) -> float:
        s = self.normal_singular_values
        return float(s[0] / s[-1]) if s[-1] > 0 else float("inf")

    def to_dict(self) -> dict:
        return {"frames": list(self.names),
                "predicted_std": {"rotation_deg_about_lidar_xyz": _finite(self.std_rotation_deg),
                                  "translation_mm_along_lidar_xyz": _finite(self.std_translation_mm)},
                "predicted_covariance": np.where(np.isfinite(self.covariance), self.covariance, None).tolist(),
                "normal_singular_values": self.normal_singular_values.tolist(),
                "condition_number": _finite([self.condition_number])[0],
                "d_optimality_per_mrad_mm": self.d_optimality, "e_optimality_per_mrad_mm": self.e_optimality,
                "weakest_direction": self.weakest_words,
                "leverage": dict(zip(self.names, self.leverage.tolist())),
                "with_range_offset": self.offset,
                "with_board_edges": None if self.edges is None else {
                    k: ({kk: _finite(vv) for kk, vv in v.items()} if isinstance(v, dict) else
                        _finite(v) if isinstance(v, np.ndarray) else v) for k, v in self.edges.items()}}

    def format(self) -> str:
        def fmt(v, unit, digits):
            return "  ".join("unobservable" if not np.isfinite(x) else f"{x:.{digits}f}" for x in v) + f" {unit}"
        lines = [f"{len(self.names)} frames; predicted standard deviations (about/along the LiDAR's x y z):",
                 f"  rotation    {fmt(self.std_rotation_deg, 'deg', 3)}",
                 f"  translation {fmt(self.std_translation_mm, 'mm', 2)}",
                 f"board normals: singular values {np.round(self.normal_singular_values, 3).tolist()}, "
                 f"condition number {self.condition_number:.2f}",
                 f"D-optimality {self.d_optimality:.3g}, E-optimality {self.e_optimality:.3g} (per mrad^2, mm^2)",
                 f"weakest: {self.weakest_words}",
                 "leverage (share of D-optimality lost without the frame):"]
        lines += [f"  {n}: {100 * v:5.1f}%" for n, v in zip(self.names, self.leverage)]
        if self.offset is not None:
            o = self.offset
            lines += [f"with a LiDAR range offset estimated too (prior {o['prior_sd_mm']:.0f} mm): translation "
                      + "  ".join(f"{v:.2f}" for v in o["translation_std_mm"]) + f" mm; offset {o['offset_std_mm']:.1f}"
                      " mm; its correlation with the translation along x y z "
                      + "  ".join(f"{c:+.2f}" for c in o["translation_correlation"])]
        if self.edges is not None:
            e = self.edges
            lines += [("with the segment ends on the boards' edges (used by default): rotation " if e.get("scan_line")
                       else "with the ring ends on the boards' edges (used by default; --no-edges: the planes alone): "
                            "rotation ")
                      + fmt(e["rotation_std_deg"], "deg", 3) + "; translation " + fmt(e["translation_std_mm"], "mm", 2)]
            if "turned_45_deg" in e:
                t = e["turned_45_deg"]
                lines += ["  with every board turned 45 degrees about its normal (the rings then leave each board by "
                          "slanted sides, which fix both directions along it; keep the turned boards in view): "
                          "rotation " + fmt(t["rotation_std_deg"], "deg", 3) + "; translation "
                          + fmt(t["translation_std_mm"], "mm", 2)]
        return "\n".join(lines)


def _d_opt(F: np.ndarray) -> float:
    vals = np.linalg.eigvalsh(F / np.outer(_SCALE, _SCALE))
    return float(np.exp(np.mean(np.log(np.maximum(vals, 1e-300)))))


def analyse(layout: Layout, names: list[str] | None = None) -> LayoutAnalysis:
    """The predicted uncertainty and conditioning of a layout of board poses.

    Never raises on a degenerate layout: its unobservable directions get infinite standard deviations and are
    named.

    Parameters
    ----------
    layout : Layout
        The rig and its board poses (:func:`layout_from_plan`, :func:`layout_from_result`).
    names : list of str, optional
        The frames' names, for the per-frame leverage.

    Returns
    -------
    LayoutAnalysis
        The predicted covariance (the Cramer-Rao bound, GTSAM tangent of ``T_camera_lidar``), the normals'
        singular values, D- and E-optimality, the weakest direction in words and each frame's leverage;
        ``format()`` gives the text ``lidarcam layout`` prints.

    Examples
    --------
    >>> layout, rig, names = lc.layout_from_result(result, lc.load_dataset(path).board)  # doctest: +SKIP
    >>> print(lc.analyse(layout, names).format())                                        # doctest: +SKIP
    """
    names = tuple(names or [f"{i:04d}" for i in range(layout.n_frames)])
    shares = [frame_contribution(frame_information(layout, i)) for i in range(layout.n_frames)]
    F = np.sum(shares, axis=0) if shares else np.zeros((6, 6))
    cov, vals, vecs, tiny = _bound(F)
    normals = np.array([T[:3, 2] for T in layout.T_camera_board]).reshape(-1, 3)
    s, _ = normal_spread(normals) if len(normals) else (np.zeros(3), None)
    D = _d_opt(F)
    leverage = np.array([1.0 - _d_opt(F - S) / D if D > 0 else 0.0 for S in shares])
    try:
        offset = _with_offset(layout) if not tiny.any() else None
    except np.linalg.LinAlgError:  # a board's own information is singular (absurd board sizes): no offset view
        offset = None
    return LayoutAnalysis(names, cov, F, s, D, float(vals[0]), _weakest_words(vecs[:, 0], layout, tiny[0]),
                          leverage, offset, _with_edges(layout))


def _bound(F: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The covariance bound of information ``F`` (6x6, rad and m), inf along the directions it leaves free (an
    eigenvalue of the scaled information within 1e-9 of its largest), with the scaled eigenvalues, their vectors
    and which are free."""
    vals, vecs = np.linalg.eigh(F / np.outer(_SCALE, _SCALE))
    tiny = vals <= 1e-9 * max(vals[-1], 1e-300)
    inv = np.where(tiny, np.inf, 1.0 / np.where(tiny, 1.0, vals))
    cov_s = (vecs * inv) @ vecs.T if not tiny.any() else _cov_with_inf(vecs, inv)
    return cov_s / np.outer(_SCALE, _SCALE), vals, vecs, tiny


def _with_edges(layout: Layout) -> dict | None:
    """The predicted standard deviations with the board's edges (``observation_model.edges_information``), for a
    layout whose board size is known: planned, or measured with the returns' rings (a 2D scan: its segments'
    ends)."""
    if layout.board.size is None:
        return None
    if not layout.beams.is_2d and layout.hits is not None and any(len(h) < 3 or h[2] is None for h in layout.hits):
        return None  # measured returns without rings: no ends to find
    try:
        sd = _edges_sd(layout)
    except np.linalg.LinAlgError:
        return None
    out = {**_sd_dict(sd), "scan_line": bool(layout.beams.is_2d)}
    if not layout.beams.is_2d and layout.hits is None:  # planned: the boards turned as a suggestion
        try:
            turned = _edges_sd(turned_boards(layout))
        except np.linalg.LinAlgError:
            return out
        if np.linalg.norm(turned[3:]) < (1.0 - MIN_TURN_GAIN) * np.linalg.norm(sd[3:]):
            out["turned_45_deg"] = _sd_dict(turned)
    return out


def _edges_sd(layout: Layout) -> np.ndarray:
    """The six standard deviations of the edges' bound (rad, m), inf along what they leave free (as
    :func:`analyse`'s: inverted as it came, a layout of one pose repeated printed 14 km)."""
    return np.sqrt(np.maximum(np.diag(_bound(edges_information(layout))[0]), 0.0))


def _sd_dict(sd: np.ndarray) -> dict:
    return {"rotation_std_deg": np.degrees(sd[:3]), "translation_std_mm": 1000 * sd[3:]}


def _finite(v) -> list:
    """``v`` as a JSON list: an unobservable (infinite) value as null."""
    return [float(x) if np.isfinite(x) else None for x in v]


# The boards turned 45 degrees about their normals are suggested (``lidarcam layout``, with the edges) when that
# shrinks the translation's predicted standard deviation by at least this share.
MIN_TURN_GAIN = 0.2


def turned_boards(layout: Layout, turn_deg: float = 45.0) -> Layout:
    """The layout with each board turned about its normal, through its centre, so that its x axis lies
    ``turn_deg`` from the camera's x axis seen in the board's plane (on the side it was turned to already): the
    rings of a spinning LiDAR then leave every board by slanted sides, which fix both directions along it."""
    poses = []
    c = layout.board.centre
    for T in layout.T_camera_board:
        n = T[:3, 2]
        x0 = np.array([1.0, 0.0, 0.0]) - n[0] * n
        x0 /= np.linalg.norm(x0)
        now = np.arctan2(np.cross(x0, T[:3, 0]) @ n, x0 @ T[:3, 0])
        R = R_from_rotvec(n * (np.copysign(np.deg2rad(turn_deg), now if now != 0 else 1.0) - now)) @ T[:3, :3]
        poses.append(T_from_Rt(R, T[:3, :3] @ c + T[:3, 3] - R @ c))
    return replace(layout, T_camera_board=tuple(poses))


OFFSET_TERMS = RangeTerms(("offset",), (OFFSET_PRIOR_SD_M,))


def offset_information(layout: Layout) -> np.ndarray:
    """The 7x7 information on ``[xi_extrinsic; range offset]`` (board poses marginalised, the offset's prior
    included)."""
    return range_model_information(layout, OFFSET_TERMS)


def _marginal(I7: np.ndarray) -> np.ndarray:
    """The extrinsic's 6x6 information with the offset marginalised."""
    return I7[:6, :6] - np.outer(I7[:6, 6], I7[6, :6]) / I7[6, 6]


def _with_offset(layout: Layout) -> dict:
    C = np.linalg.inv(offset_information(layout))
    sd = np.sqrt(np.diag(C))
    return {"prior_sd_mm": 1000 * OFFSET_PRIOR_SD_M, "translation_std_mm": (1000 * sd[3:6]).tolist(),
            "offset_std_mm": float(1000 * sd[6]), "translation_correlation": (C[3:6, 6] / sd[3:6] / sd[6]).tolist()}


def _cov_with_inf(vecs: np.ndarray, inv: np.ndarray) -> np.ndarray:
    finite = np.isfinite(inv)
    cov = (vecs[:, finite] * inv[finite]) @ vecs[:, finite].T
    for k in np.nonzero(~finite)[0]:
        cov[np.abs(vecs[:, k]) > 0.1, :] = np.inf
        cov[:, np.abs(vecs[:, k]) > 0.1] = np.inf
    return cov


def _weakest_words(v: np.ndarray, layout: Layout, unobservable: bool) -> str:
    R = layout.T_camera_lidar[:3, :3]
    rot, trans = v[:3], v[3:]
    state = "unobservable" if unobservable else "the least constrained"
    if np.linalg.norm(trans) >= np.linalg.norm(rot):
        axis, advice = describe_direction(R @ trans)
        return f"translation along {axis} is {state}: {advice}"
    axis, advice = describe_direction(R @ rot)
    return f"rotation about {axis} is {state}: add boards spread further over the image and tilted more"


def layout_from_result(result, board, beams_model: str = "hdl64e") -> tuple[Layout, Rig, list[str]]:
    """The layout of a calibration's measured frames.

    Parameters
    ----------
    result : CalibrationResult
        A refined result: its estimate, refined board poses, noise levels and measured board points are used.
    board : BoardModel
        The dataset's board.
    beams_model : str
        The 3D beam model (``hdl64e``, ``vlp16``, ``os64``) that pose suggestions cast.

    Returns
    -------
    tuple of (Layout, Rig, list of str)
        The layout, the rig (for :func:`suggest_poses`) and the used frames' names.
    """
    ref = result.refinement
    from ..solvers.range_model import frame_rings

    used = [f for f in result.frames if f.usable and f.name in ref.T_camera_board]
    rings = frame_rings([f.lidar for f in used]) if used else []
    hits = tuple((f.lidar.points / np.linalg.norm(f.lidar.points, axis=1, keepdims=True),
                  np.linalg.norm(f.lidar.points, axis=1), r) for f, r in zip(used, rings))
    beams = BEAM_MODELS[beams_model](ref.range_noise_m)
    layout = Layout(result.camera, board, beams, result.T_camera_lidar,
                    tuple(ref.T_camera_board[f.name] for f in used), ref.corner_noise_px, ref.range_noise_m, hits)
    rig = Rig(result.camera, beams, board, result.T_camera_lidar)
    if beams.is_2d:  # boards near a 2D scanner's plane, as the 2D simulator places them
        rig = replace(rig, lidar_height_m=0.6, min_distance_m=1.5, max_distance_m=4.0)
    return layout, rig, [f.name for f in used]


def layout_from_plan(plan: dict, source: str = "plan") -> tuple[Layout, Rig]:
    """A layout, and the rig for pose suggestions, from a parsed ``PLAN.yaml``.

    Parameters
    ----------
    plan : dict
        The plan: ``camera``, ``board``, ``lidar``, ``corner_noise_px``, ``poses`` and optionally
        ``T_camera_lidar`` (see the how-to on choosing board poses).
    source : str
        The plan's name in error messages.

    Returns
    -------
    tuple of (Layout, Rig)

    Raises
    ------
    DatasetError
        A missing or bad key, named with what to write.
    """
    from ..io.dataset import parse_board, parse_camera

    try:
        camera = parse_camera(plan["camera"], source)
        board = parse_board(plan["board"], source)
        lidar = plan.get("lidar", {})
        model = lidar.get("model", "hdl64e")
        if model not in BEAM_MODELS:
            raise DatasetError(f"unknown lidar model {model!r}", path=source, hint=f"use one of {sorted(BEAM_MODELS)}")
        beams = BEAM_MODELS[model](float(lidar.get("range_noise_m", 0.02)))
        T_cl = np.array(plan["T_camera_lidar"], dtype=float) if "T_camera_lidar" in plan else T_from_Rt(
            R_CAMERA_LIDAR_NOMINAL, -R_CAMERA_LIDAR_NOMINAL @ np.array([0.15, 0.0, -0.20]))
        poses = [_plan_pose(p, board) for p in plan.get("poses", [])]
        corner_noise = float(plan.get("corner_noise_px", 0.2))
        if not (np.all(np.isfinite(T_cl)) and T_cl.shape == (4, 4)):
            raise ValueError("T_camera_lidar must be a finite 4x4 matrix")
        if not all(np.all(np.isfinite(T)) for T in poses):
            raise ValueError("every pose must be finite")
        for k, T in enumerate(poses):
            why = _unseen(camera, board, T)
            if why:
                raise ValueError(f"pose {k + 1}: {why}")
        if not (np.isfinite(corner_noise) and corner_noise > 0 and np.isfinite(beams.sigma_range_m)
                and beams.sigma_range_m > 0):
            raise ValueError("corner_noise_px and range_noise_m must be positive and finite")
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise DatasetError(f"invalid plan ({exc})", path=source,
                           hint="see the PLAN.yaml format in docs/howto/layout.md (camera, board, lidar, poses)"
                           ) from exc
    rig = Rig(camera=camera, beams=beams, board=board, T_camera_lidar=T_cl)
    return Layout(camera, board, beams, T_cl, tuple(poses), corner_noise, beams.sigma_range_m), rig


# A planned board further than this from the camera is a typo (no camera resolves a board there).
MAX_PLAN_DISTANCE_M = 1000.0


# A planned board the camera cannot find predicts information no recording holds: its normal this far from the line
# of sight to its centre (foreshortened 2.9 times), or its squares this small in the image (median side, px).
MAX_VIEW_DEG, MIN_SQUARE_PX = 70.0, 5.0


def _unseen(camera, board, T: np.ndarray) -> str:
    """Why the camera would not find the board at ``T_camera_board`` ("" where it would): corners behind it or out
    of the image (a ChArUco board may be cut, ``min_in_image``), the board seen edge-on, or its squares too small."""
    from geometry.rotations import transform_points

    corners = transform_points(T, board.inner_corners())
    if np.any(corners[:, 2] <= 0):
        return "some of the board's corners are behind the camera"
    inside = float(np.mean(camera.sees(corners, margin_px=15.0)))
    if inside < min_in_image(board):
        return f"{1 - inside:.0%} of the board's corners fall outside the image"
    centre = T[:3, :3] @ board.centre + T[:3, 3]
    angle = np.degrees(np.arccos(min(abs(float(T[:3, 2] @ centre)) / float(np.linalg.norm(centre)), 1.0)))
    if angle > MAX_VIEW_DEG:
        return (f"the board is seen {angle:.0f} degrees from face-on (its corners are not found beyond "
                f"{MAX_VIEW_DEG:g})")
    cols, rows = board.inner_corners_shape
    uv = camera.project(corners).reshape(rows, cols, 2)
    sides = np.concatenate([np.linalg.norm(np.diff(uv, axis=0), axis=2).ravel(),
                            np.linalg.norm(np.diff(uv, axis=1), axis=2).ravel()])
    if float(np.median(sides)) < MIN_SQUARE_PX:
        return (f"its squares are {np.median(sides):.1f} px in the image (its corners are not found below "
                f"{MIN_SQUARE_PX:g} px): bring it nearer")
    return ""


def _plan_pose(p: dict, board) -> np.ndarray:
    if "T_camera_board" in p:
        T = np.array(p["T_camera_board"], dtype=float)
        if T.shape != (4, 4):
            raise ValueError("T_camera_board must be 4x4")
        if np.all(np.isfinite(T)) and np.linalg.norm(T[:3, 3]) > MAX_PLAN_DISTANCE_M:
            raise ValueError(f"a pose's board is more than {MAX_PLAN_DISTANCE_M:g} m from the camera")
        return T
    centre = np.array(p["centre_m"], dtype=float)
    if centre.shape != (3,) or not np.all(np.isfinite(centre)) or centre[2] <= 0:
        raise ValueError("centre_m must be 3 finite numbers, the board in front of the camera (z > 0)")
    if np.linalg.norm(centre) > MAX_PLAN_DISTANCE_M:
        raise ValueError(f"centre_m must be within {MAX_PLAN_DISTANCE_M:g} m of the camera")
    return board_pose(board, centre, np.deg2rad(float(p.get("tilt_deg", 0.0))),
                      np.deg2rad(float(p.get("azimuth_deg", 0.0))), np.deg2rad(float(p.get("spin_deg", 0.0))))


def meets(analysis: LayoutAnalysis, max_rotation_deg: float, max_translation_mm: float) -> bool:
    return bool(np.all(analysis.std_rotation_deg <= max_rotation_deg)
                and np.all(analysis.std_translation_mm <= max_translation_mm))


def suggest_poses(layout: Layout, rig: Rig, k: int, rng: np.random.Generator, candidates: int = 150,
                  target: tuple[float, float] | None = None, range_offset: bool = False
                  ) -> list[tuple[np.ndarray, LayoutAnalysis]]:
    """Greedily, ``k`` board poses that most raise the layout's D-optimality.

    Each is chosen from ``candidates`` feasible poses: fully in the image (a ChArUco board may be cut by its edge),
    inside the LiDAR's field of view, 2-5 m away and hit by enough beams.

    Parameters
    ----------
    layout : Layout
        The poses so far.
    rig : Rig
        The rig the candidates are drawn for.
    k : int
        Poses to add at most.
    rng : numpy.random.Generator
        Draws the candidates.
    candidates : int
        Candidate poses per step.
    target : tuple of float, optional
        ``(max_rotation_deg, max_translation_mm)``: stop as soon as every axis's predicted standard deviation
        meets it.
    range_offset : bool
        Score the extrinsic with a LiDAR range offset estimated too (poses that separate the offset from the
        translation score higher).

    Returns
    -------
    list of tuple of (numpy.ndarray, LayoutAnalysis)
        Each added pose's ``T_camera_board`` and the analysis of the layout with it.
    """
    out = []
    current = layout
    for _ in range(k):
        if target is not None and current.n_frames >= 3 and meets(analyse(current), *target):
            break
        # A ChArUco board may be cut by the image's edge (the poses the layout most often lacks are there).
        cut_share = 0.3 if rig.board.is_charuco else 0.0
        pool = [T for T in sample_board_poses(rig, candidates, rng, outside_image_share=cut_share)
                if _pose_fits(rig, T, min_in_image=min_in_image(rig.board))]
        F = analyse(current).information
        I7 = offset_information(current) if range_offset else None
        best, best_d = None, -np.inf
        for T in pool:
            trial = replace(current, T_camera_board=(T,), hits=None)
            if len(board_hits(trial, 0)[0]) < (MIN_BOARD_HITS_2D if rig.beams.is_2d else MIN_BOARD_HITS):
                continue
            if range_offset:
                share = frame_information(trial, 0, OFFSET_TERMS)
                d = _d_opt(_marginal(I7 + share[:7, :7] - share[:7, 7:] @ np.linalg.solve(share[7:, 7:],
                                                                                        share[7:, :7])))
            else:
                d = _d_opt(F + frame_contribution(frame_information(trial, 0)))
            if d > best_d:
                best, best_d = T, d
        if best is None:
            break
        hits = None if current.hits is None else current.hits + (board_returns(replace(current, T_camera_board=(best,),
                                                                                      hits=None), 0)[:3],)
        current = replace(current, T_camera_board=current.T_camera_board + (best,), hits=hits)
        out.append((best, analyse(current)))
    return out


def separating_pose(result, board, rng: np.random.Generator | None = None, candidates: int = 60) -> dict | None:
    """When the calibration's range offset is confounded with the extrinsic
    (``RangeModelFit.confounding``), the next board pose that best separates them: the D-optimal one among
    ``candidates`` feasible poses for the extrinsic with the offset estimated too (:func:`suggest_poses`), and
    the predicted standard deviations along the LiDAR's axes with the offset estimated, before and after it.
    The beams are a VLP-16's for a LiDAR whose boards show at most 20 rings, else an HDL-64E's (for the poses'
    feasibility only). None without a confounded offset."""
    ref = result.refinement
    fit = ref.range_model if ref is not None else None
    if fit is None or not fit.confounding or fit.confounding.get("term") != "offset":
        return None
    if any(f.lidar is not None and f.lidar.is_scan_line for f in result.frames if f.usable):
        return None  # a 2D scanner's poses are suggested by `lidarcam layout` with its own beam model
    labels = fit.labels
    rings = {int(r) for rr in (labels.rings if labels is not None else ()) if rr is not None for r in np.unique(rr)}
    beams = "vlp16" if 0 < len(rings) <= 20 else "hdl64e"
    layout, rig, _ = layout_from_result(result, board, beams)
    before = _with_offset(layout)
    found = suggest_poses(layout, rig, 1, rng or np.random.default_rng(0), candidates=candidates, range_offset=True)
    if not found:
        return None
    T, after = found[0]
    if after.offset is None:
        return None
    c = T[:3, :3] @ board.centre + T[:3, 3]
    return {"T_camera_board": T.tolist(), "board_centre_camera_m": c.tolist(), "board_normal_camera": T[:3, 2].tolist(),
            "beam_model": beams,
            "predicted_translation_std_mm_with_offset": {"now": before["translation_std_mm"],
                                                         "with_this_pose": after.offset["translation_std_mm"]}}
