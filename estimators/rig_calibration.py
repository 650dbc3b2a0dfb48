"""A whole rig in one graph: measure every sensor, start each pose along the links that share the most frames,
solve jointly (``solvers.rig_graph``), and write every pair's transform with its covariance.

Measurement reuses the single pair's pipeline: each camera's corners and board poses (intrinsics calibrated from
its frames when dataset.yaml gives none); each LiDAR's board in a frame, found once with the first camera (the one
sharing most frames) that shares at least ``MIN_PAIR_FRAMES`` frames with it (``pipeline.measurement.measure_frames`` on that
pair) and paired with every other camera's board pose of the frame. Each such camera-LiDAR pair is
also solved alone (planes, no range terms and no segment ends: the joint graph's model), which starts the joint graph
and is reported beside it ("pairwise only"). Two cameras are linked by every frame both saw.
"""
from __future__ import annotations

import copy
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from geometry.camera import CameraModel
from geometry.rotations import T_log

from . import __version__
from .calibration import solve
from .camera.board_pose import estimate_board_pose
from .camera.detection import CornerDetection
from .camera.intrinsics import calibrate_intrinsics
from .errors import DegenerateLayoutError, LidarcamError
from .io.dataset import FrameFiles
from .io.output import write_json_atomic, write_npz_atomic
from .io.rig_dataset import RigDataset, Sensor
from .lidar.lidar_models import range_accuracy_for
from .measurements import FrameMeasurement, lidar_whitener
from .pipeline.measurement import detect_in_image, measure_frames
from .solvers import chi_square as chi2
from .solvers.board_edges import crossings, edge_scatter
from .solvers.closed_form import describe_direction
from .solvers.noise_levels import board_corner_residuals_px, pooled_range_noise_m
from .solvers.outline_check import outline_check
from .solvers.posterior import heavy_tails
from .solvers.range_model import (MODEL_TEST_P, FrameLabels, RangeTerms, frame_labels, frame_rings, frame_whitener,
                                  terms_for)
from .solvers.refinement_options import RefinementOptions
from .solvers.rig_graph import (CameraViews, LidarViews, RigSolution, outline_key, pair_board_covariance, solve_rig,
                                spanning_tree, terms_fit, terms_test, translation_sd_in_first)
from .solvers.rig_posterior import RigPosterior, sample_rig_posterior

# Fewest frames a camera and a LiDAR must share (their boards found in both) to be linked and solved as a pair.
MIN_PAIR_FRAMES = 3
# A rig camera's board pose error over what its corners' own residual (each board's, ``_camera_views``) predicts:
# measured by `make bench` (bench_rig_corners.py, 10 six-camera rigs, 702 boards: at 1.0, d2 mean 5.54 and median
# 4.48 (chi-square 5.35), 1.7% beyond the 99% point; one pooled residual per camera times 1.28, the single pair's
# model, gives mean 3.68 and median 2.23 with 2.6% beyond). The single pair keeps its pooled residual and
# ``refinement_options.CORNER_ERROR_CORRELATION``.
BOARD_CORNER_FACTOR = 1.0
# A sensor's noise is scaled by its chi-square per degree of freedom whenever that is above 1
# (``rig_graph.solve_rig``); the warning that its factors disagree beyond their noise is given when its chi-square
# is beyond this tail probability.
NOISE_WARNING_P = 0.01
# Above this variance factor of a LiDAR's planes under its largest range model (every term in), its per-ring and
# black-square terms are not tested (``_choose_terms``): simulated rigs with injected range errors leave 1.0-1.13,
# the recorded VLP-16 and Ouster sets 5.1 and 3.8 (their boards' planes disagree from board to board).
MAX_TERMS_DISPERSION = 2.0
# The pairwise solves start the joint graph and are reported beside it: no range terms, no edges and no check by
# the edges (the joint estimate is checked).
PAIR_OPTIONS = RefinementOptions(range_model="none", edges=False, outline_check=False)


@dataclass(frozen=True, eq=False)
class RigResult:
    """A rig's calibration: the joint solution, each camera's intrinsics, the pairwise-only estimates of the
    camera-LiDAR pairs (``(camera, lidar) -> (T, covariance, frames)``), the frames each sensor contributed,
    the frames skipped with their reasons (``sensor -> {stem: reason}``) and the warnings."""

    rig: RigDataset
    solution: RigSolution
    cameras: dict
    pairwise: dict
    frames_used: dict
    skipped: dict
    warnings: tuple[str, ...]
    timings_s: dict
    # Each camera-LiDAR pair's measured frames (``(camera, lidar) -> [FrameMeasurement]``), for the report.
    pair_frames: dict | None = None
    # The frames each pair of sensors shares where both found the board (``(a, b) -> count``; a camera-LiDAR
    # pair's usable frames, a camera pair's frames both saw).
    links: dict | None = None
    # The rig's posterior (``solvers.rig_posterior``) when sampled, and the views the graph was solved from.
    posterior: RigPosterior | None = None
    camera_views: tuple = ()
    lidar_views: tuple = ()
    # The board pose that most helps the weakest camera-LiDAR pair (``analysis.rig_layout``), with that pair's
    # predicted standard deviations before and after it; None when none was computed or none is feasible.
    next_pose: dict | None = None
    # Each LiDAR's range model: ``model`` (``none``, ``offset``, ``per-ring``, ``offset+dark`` or ``full``),
    # ``prior_sd_m``, the tests under ``auto``, and with terms each one's estimate (:func:`_range_models`).
    range_models: dict = field(default_factory=dict)
    # Each 3D camera-LiDAR pair's board-edges check under the joint estimate (``(camera, lidar) -> record``, as a
    # single pair's ``board_edges``; :func:`_outline_checks`).
    outline_checks: dict = field(default_factory=dict)
    # With ``--edges``: each LiDAR's board-edges record (:func:`_with_edges`).
    edges: dict = field(default_factory=dict)

    def layout(self) -> dict:
        """Where the rig is weakest: each camera-LiDAR pair's largest translation standard deviation (mm, the
        joint graph's) and the direction (camera axes) and advice for it (``closed_form.describe_direction``),
        the weakest pair, and the sensor pairs that share some frames but fewer than ``MIN_PAIR_FRAMES`` (a
        camera-LiDAR pair is then not solved alone; two cameras rest on one or two boards)."""
        pairs = {}
        for c in self.rig.cameras:
            for lid in self.rig.lidars:
                T, C = self.solution.transform(c.name, lid.name)
                ev, V = np.linalg.eigh(C[3:, 3:])
                weak = T[:3, :3] @ V[:, -1]  # along the LiDAR's axes, into the camera's
                axis, advice = describe_direction(weak)
                pairs[f"T_{c.name}_{lid.name}"] = {"max_translation_sd_mm": float(1000 * np.sqrt(max(ev[-1], 0.0))),
                                                   "weakest_direction_camera": weak.tolist(), "axis": axis,
                                                   "advice": advice}
        weakest = max(pairs, key=lambda k: pairs[k]["max_translation_sd_mm"]) if pairs else None
        few = {f"{a}-{b}": n for (a, b), n in (self.links or {}).items() if 0 < n < MIN_PAIR_FRAMES}
        return {"pairs": pairs, "weakest_pair": weakest, "links_with_few_frames": few, "next_pose": self.next_pose}

    def pairs(self) -> list[tuple[str, str]]:
        """Every camera-LiDAR pair, every camera-camera and every LiDAR-LiDAR pair (earlier sensor first), in
        sensor order."""
        cams, lidars = [s.name for s in self.rig.cameras], [s.name for s in self.rig.lidars]
        out = [(c, lid) for c in cams for lid in lidars]
        out += [(a, b) for i, a in enumerate(cams) for b in cams[i + 1:]]
        out += [(a, b) for i, a in enumerate(lidars) for b in lidars[i + 1:]]
        return out

    def to_json(self) -> dict:
        sol, ref = self.solution, self.rig.reference

        def entry(T, cov) -> dict:
            sd = np.sqrt(np.maximum(np.diag(cov), 0.0))
            return {"T": T.tolist(), "covariance": cov.tolist(), "std_rotation_deg": np.degrees(sd[:3]).tolist(),
                    "std_translation_mm": (1000 * sd[3:]).tolist(),
                    "std_translation_of_t_mm": (1000 * translation_sd_in_first(T, cov)).tolist()}

        sensors = []
        for s in self.rig.sensors:
            e = entry(sol.T_ref[s.name], sol.covariance(s.name))
            sensors.append({"name": s.name, "type": s.type, f"T_{ref}_{s.name}": e.pop("T"), **e,
                            "frames_used": len(self.frames_used.get(s.name, ())),
                            "noise_scale": sol.noise_scale.get(s.name, 1.0)})
            if s.name in self.edges:
                sensors[-1]["board_edges"] = self.edges[s.name]
            if s.name in self.range_models:
                record = sensors[-1]["range_model"] = copy.deepcopy(self.range_models[s.name])
                if self.posterior is not None and s.name in self.posterior.range_terms:
                    q = np.percentile(self.posterior.range_terms[s.name], [2.5, 97.5], axis=0)
                    record["posterior_95%_m"] = q[:, 0].tolist()
                    for k, term in enumerate(record["terms"].values()):
                        term["posterior_95%_m"] = q[:, k].tolist()
        transforms = {f"T_{a}_{b}": entry(*sol.transform(a, b)) for a, b in self.pairs()}
        for (a, b), record in self.outline_checks.items():
            transforms[f"T_{a}_{b}"]["board_edges"] = record
        posterior = None
        if self.posterior is not None:
            for a, b in self.pairs():
                transforms[f"T_{a}_{b}"]["posterior"] = self.posterior.pair_summary(a, b)
            posterior = {**self.posterior.diagnostics(), "covariance_joint": self.posterior.covariance_joint.tolist(),
                         "file": "posterior.npz"}
        pairwise = {f"T_{c}_{lid}": {**entry(T, cov), "frames": n} for (c, lid), (T, cov, n) in self.pairwise.items()}
        cameras = {n: {"model": m.model, "width": m.width, "height": m.height, "K": m.K.tolist(),
                       "dist": m.dist.tolist(), "source": m.source} for n, m in self.cameras.items()}
        for n, (p, sd) in (sol.intrinsics or {}).items():
            refined = self.cameras[n].with_params(p)
            cameras[n].update({"given_params": self.cameras[n].params.tolist(), "refined_params": p.tolist(),
                               "refined_params_sd": sd.tolist(), "K": refined.K.tolist(),
                               "dist": refined.dist.tolist(), "source": "refined with the rig"})
        return {"rig": True, "reference": ref, "sensors": sensors, "transforms": transforms, "layout": self.layout(),
                "covariance_joint": sol.covariance_joint.tolist(), "posterior": posterior,
                "pairwise_only": pairwise, "cameras": cameras,
                "frames_used": {n: list(v) for n, v in self.frames_used.items()},
                "skipped": self.skipped, "warnings": list(self.warnings), "timings_s": self.timings_s,
                "version": __version__,
                "convention": "T_a_b maps points from b's frame into a's: p_a = R p_b + t. Covariances are 6x6 in "
                              "GTSAM's Pose3 right tangent, T_true = T_hat * Exp(xi), xi = [rot; trans]; "
                              "covariance_joint holds every sensor's T_<reference>_<sensor> in the order of "
                              "sensors (the reference's block is zero)."}


def measure_camera(sensor: Sensor, board, workers: int = 2) -> tuple[CameraModel, dict, dict, list[str], dict]:
    """One camera's board poses by stem, the frames skipped with their reasons, its intrinsics (calibrated from
    its frames when the rig's dataset.yaml gives none) and its images' corners by stem (for the pairs)."""
    warnings: list[str] = []
    frames = [FrameFiles(stem, path, path) for stem, path in sensor.files]
    with ThreadPoolExecutor(max_workers=workers) as pool:
        detections = list(pool.map(lambda f: detect_in_image(f, board, {}), frames))
    camera = sensor.camera
    if camera is None:
        found = [d for _, d in detections if isinstance(d, CornerDetection)]
        sizes = {s for s, _ in detections if s is not None}
        if len(sizes) != 1 or len(found) < 3:
            raise DegenerateLayoutError(f"camera {sensor.name}: intrinsics cannot be calibrated from "
                                        f"{len(found)} board view(s) of {len(sizes)} image size(s)",
                                        hint=f"give K, width and height for {sensor.name} in dataset.yaml, or more "
                                             "frames")
        camera, _ = calibrate_intrinsics([d.corners_px for d in found], board, *sizes.pop(),
                                         corner_ids=[d.corner_ids for d in found])
        warnings.append(f"camera {sensor.name}: no intrinsics in dataset.yaml: {camera.source}")
    poses, skipped = {}, {}
    for f, (size, det) in zip(frames, detections):
        if isinstance(det, str):
            skipped[f.name] = det
        elif det is None:
            skipped[f.name] = "board not found in the image"
        elif size != (camera.width, camera.height):
            skipped[f.name] = f"image is {size[0]}x{size[1]} but the camera is {camera.width}x{camera.height}"
        else:
            try:
                poses[f.name] = estimate_board_pose(det, board, camera)
            except LidarcamError as exc:
                skipped[f.name] = f"board pose: {exc.message}"
    return camera, poses, skipped, warnings, {f.name: d for f, d in zip(frames, detections)}


def _camera_views(name: str, camera: CameraModel, poses: dict, board) -> CameraViews:
    """The camera's corners for the graph, each board's with its own pixel noise (its per-axis PnP residual,
    shrunk towards the camera's pooled one: ``noise_levels.board_corner_residuals_px``) times
    ``BOARD_CORNER_FACTOR``; ``sigma_px`` the pooled one times the factor (a board not yet recorded, as the advice
    asks)."""
    stems = list(poses)
    pooled, per_board = board_corner_residuals_px(((poses[s].T_camera_board, poses[s].corners_board(board),
                                                    poses[s].corners_px) for s in stems), camera)
    return CameraViews(name, camera, max(pooled, 1e-3) * BOARD_CORNER_FACTOR,
                       {s: poses[s].corners_board(board) for s in stems}, {s: poses[s].corners_px for s in stems},
                       {s: poses[s].T_camera_board for s in stems},
                       {s: max(v, 1e-3) * BOARD_CORNER_FACTOR for s, v in zip(stems, per_board)})


def pattern_flip(board) -> np.ndarray | None:
    """The board-frame transform that turns a checkerboard's pattern by 180 degrees about its centre, when the
    pattern looks the same turned (an even sum of squares: the detector may then number its corners from
    either end, each camera on its own); None for a ChArUco board (its ids fix the numbering) or an asymmetric
    pattern. A pose found with the corners numbered from the other end is ``T_camera_board @ flip``."""
    if board.is_charuco or sum(board.squares) % 2:
        return None
    c = board.inner_corners().mean(axis=0)
    flip = np.diag([-1.0, -1.0, 1.0, 1.0])
    flip[:2, 3] = 2 * c[:2]
    return flip


def _flipped(obs, flip: np.ndarray):
    """The camera's observation with its corners numbered from the other end (:func:`pattern_flip`)."""
    return replace(obs, corners_px=obs.corners_px[::-1].copy(), T_camera_board=obs.T_camera_board @ flip)


def _align_numbering(cams: list[str], poses: dict, T_ref: dict, flip: np.ndarray) -> dict:
    """Each frame's boards numbered alike in every camera: as the first camera (in the rig's order) that saw the
    frame numbers it, each other camera's numbering the one whose pose lies nearer to where the start
    (``T_ref``, composed of numbering-free links: a LiDAR's plane, or the consensus of two cameras' frames) puts
    that board."""
    out = {c: dict(poses[c]) for c in cams}
    first: dict = {}
    for c in cams:
        for st in out[c]:
            first.setdefault(st, c)
    for c in cams:
        for st, obs in out[c].items():
            if first[st] == c:
                continue
            c0 = first[st]
            predicted = np.linalg.inv(T_ref[c]) @ T_ref[c0] @ out[c0][st].T_camera_board
            angle = [np.linalg.norm(T_log(np.linalg.inv(predicted) @ T)[:3])
                     for T in (obs.T_camera_board, obs.T_camera_board @ flip)]
            if angle[1] < angle[0]:
                out[c][st] = _flipped(obs, flip)
    return out


def _consensus_relative(rels: list[list[np.ndarray]]) -> np.ndarray:
    """The relative pose most frames agree with (within 2 degrees and 5 cm), each frame giving its candidates
    (one per numbering of the board), and its candidate nearest that."""
    def close(A, B):
        xi = T_log(np.linalg.inv(A) @ B)
        return np.linalg.norm(xi[:3]) < np.deg2rad(2.0) and np.linalg.norm(xi[3:]) < 0.05

    hyps = [T for cands in rels for T in cands]
    return max(hyps, key=lambda H: (sum(any(close(H, T) for T in cands) for cands in rels),
                                    -sum(min(np.linalg.norm(T_log(np.linalg.inv(H) @ T)) for T in cands)
                                         for cands in rels)))


def calibrate_rig(rig: RigDataset, rng: np.random.Generator, workers: int = 2, refine_intrinsics: bool = False,
                  samples: int = 0, advise: bool = True, range_model: str = "auto", edges: bool = False
                  ) -> RigResult:
    """Measure and solve a rig in one graph (module docstring).

    Parameters
    ----------
    rig : RigDataset
        From :func:`~estimators.io.rig_dataset.load_rig`.
    rng : numpy.random.Generator
        Seeds the LiDAR board segmentation's random draws.
    workers : int
        Threads for the image and sweep work.
    refine_intrinsics : bool
        Every camera's intrinsics as variables of the graph too (under a prior of its ``param_std`` in
        dataset.yaml when given); the refined ones are in ``result.solution.intrinsics``.
    samples : int
        Effective posterior samples of every sensor's pose to draw with emcee (``solvers.rig_posterior``); 0
        skips sampling. Not drawn with ``refine_intrinsics`` (the intrinsics are not sampled; the graph's
        covariance, which carries them, is then the uncertainty reported), with a warning saying so.
    range_model : str
        Each LiDAR's range model, as the single pair's ``--range-model``: ``none`` (planes), ``offset``,
        ``per-ring``, ``offset+dark``, ``full`` (the terms under priors from its range accuracy, dataset.yaml's
        ``range_accuracy_m`` or its family's), or ``auto``: the terms that likelihood-ratio tests at
        ``MODEL_TEST_P`` support (:func:`_range_models`).
    edges : bool
        The board's edges as measurements too (``--edges``): each LiDAR's ring ends (a 2D scanner's segment ends)
        on the board's outline, in the joint graph (:func:`_with_edges`); the posterior holds their share to
        second order about the estimate (``rig_posterior.edges_quadratic``).
    advise : bool
        Find the board pose that most helps the weakest camera-LiDAR pair (:func:`rig_next_pose`, in
        ``result.next_pose``; about a second).

    Returns
    -------
    RigResult
        The joint solution (every sensor's pose in the reference's frame and their joint covariance; any pair's
        transform by ``result.solution.transform(a, b)``), the pairwise-only estimates, the frames used and
        skipped, and the warnings.

    Raises
    ------
    DegenerateLayoutError
        A sensor with no path to the reference (named), or a graph whose information is singular.
    """
    t0 = time.perf_counter()
    warnings: list[str] = []
    cameras, poses, skipped, found = {}, {}, {}, {}
    for s in rig.cameras:
        cameras[s.name], poses[s.name], skipped[s.name], w, found[s.name] = measure_camera(s, rig.board, workers)
        warnings.extend(w)
    t_cam = time.perf_counter()
    # Each LiDAR with each camera that shares enough frames: its boards chosen with that camera, the pair solved.
    lidar_obs: dict = {s.name: {} for s in rig.lidars}
    sigma_r: dict = {}
    pairwise, links, pair_frames = {}, {}, {}
    for lid in rig.lidars:
        skipped[lid.name] = {}
        shared = sorted(rig.cameras, key=lambda c: -sum(1 for st in poses[c.name] if lid.file(st) is not None))
        measured: dict = {}  # stem -> (the camera it was measured with, its frame): the LiDAR side tried once
        for cam in shared:
            stems = [st for st in poses[cam.name] if lid.file(st) is not None]
            if len(stems) < MIN_PAIR_FRAMES:
                continue
            frames = _pair_frames(rig.pair(cam.name, lid.name, cameras[cam.name]), cam.name, lid.name, stems,
                                  poses[cam.name], measured, rng, workers, found[cam.name], warnings)
            usable = [f for f in frames if f.usable]
            for f in frames:
                if not f.usable and f.name not in lidar_obs[lid.name]:
                    by = measured[f.name][0] if f.name in measured else cam.name
                    skipped[lid.name].setdefault(f.name, f"with {by}: {f.reason}")
            if len(usable) < MIN_PAIR_FRAMES:
                warnings.append(f"{cam.name}-{lid.name}: only {len(usable)} usable frame(s); not linked")
                continue
            try:
                res = solve(usable, rig.board, cameras[cam.name], options=PAIR_OPTIONS, use_extent=False)
            except DegenerateLayoutError as exc:
                warnings.append(f"{cam.name}-{lid.name}: not solved as a pair ({exc.message})")
                continue
            pairwise[(cam.name, lid.name)] = (res.T_camera_lidar, res.covariance, len(usable))
            pair_frames[(cam.name, lid.name)] = usable
            links[(cam.name, lid.name)] = len(usable)
            for f in usable:
                lidar_obs[lid.name].setdefault(f.name, f.lidar)
                skipped[lid.name].pop(f.name, None)
        if lidar_obs[lid.name]:
            sigma_r[lid.name] = pooled_range_noise_m([_Framed(o) for o in lidar_obs[lid.name].values()])
    t_pairs = time.perf_counter()
    cams = [c.name for c in rig.cameras]
    for i, a in enumerate(cams):
        for b in cams[i + 1:]:
            links[(a, b)] = sum(1 for st in poses[a] if st in poses[b])
    names = tuple(s.name for s in rig.sensors)
    parent = spanning_tree(names, rig.reference, links)
    flip = pattern_flip(rig.board)
    T_ref = _start(names, rig.reference, parent, poses, pairwise, flip)
    if flip is not None:
        poses = _align_numbering(cams, poses, T_ref, flip)
    # Each frame a camera saw starts from the first camera (in the rig's order) that saw it.
    T_ref_board = {}
    for c in cams:
        for st, p in poses[c].items():
            T_ref_board.setdefault(st, T_ref[c] @ p.T_camera_board)
    camera_views = [_camera_views(c, cameras[c], poses[c], rig.board) for c in cams if poses[c]]
    lidar_views = [LidarViews(lid.name, sigma_r[lid.name],
                              {st: lidar_whitener(o, sigma_r[lid.name]) for st, o in lidar_obs[lid.name].items()
                               if st in T_ref_board}, lid.lidar == "2d")
                   for lid in rig.lidars if lidar_obs[lid.name]]
    solution = solve_rig(names, rig.reference, camera_views, lidar_views, T_ref, T_ref_board, refine_intrinsics)
    range_models: dict = {}
    if range_model != "none" and lidar_views:
        lidar_views, range_models = _range_models(rig, names, camera_views, lidar_views, lidar_obs, pair_frames,
                                                  solution, range_model)
        if any(lv.has_terms for lv in lidar_views):
            solution = solve_rig(names, rig.reference, camera_views, lidar_views, T_ref, T_ref_board,
                                 refine_intrinsics)
        for lv in lidar_views:
            if lv.has_terms:
                _range_record(range_models[lv.name], lv.terms, *solution.range_terms[lv.name], warnings, lv.name)
    for n, s in solution.noise_scale.items():
        ss, dof = solution.chi2_dof[n]
        if s > 1.0 and chi2.sf(ss, dof) < NOISE_WARNING_P:
            hint = ("; a camera whose corners disagree this much with the rest of the rig may have wrong intrinsics "
                    "(--refine-intrinsics estimates them with the rig)" if n in cameras and not refine_intrinsics
                    and s > 2.0 else "")
            warnings.append(f"{n}: its factors disagree beyond their noise (chi-square {ss:.0f} on {dof:.0f} dof): its "
                            f"noise is scaled by {s:.2f}{hint}")
    edge_records: dict = {}
    if edges and not rig.board.size_known:
        warnings.append("--edges: the board's size is not in dataset.yaml (board.size): planes alone")
    elif edges:
        lidar_views, solution, edge_records = _with_edges(rig, names, camera_views, lidar_views, lidar_obs, solution,
                                                          T_ref, T_ref_board, refine_intrinsics)
        if not edge_records:
            warnings.append("--edges: no LiDAR's board shows ends on the board's outline (or the graph with them "
                            "could not be solved): planes alone")
    outline_checks = _outline_checks(rig, names, camera_views, lidar_views, solution, pair_frames, warnings)
    t_joint = time.perf_counter()
    advice_rng = np.random.default_rng(rng.integers(2**32))  # the advice does not depend on the sampling
    posterior = None
    if samples > 0 and refine_intrinsics:
        warnings.append("the posterior is not sampled with --refine-intrinsics for a rig (the intrinsics would be "
                        "held fixed): the uncertainty given is the joint graph's, which carries the intrinsics'")
    elif samples > 0:
        posterior = sample_rig_posterior(solution, camera_views, lidar_views, rng, min_ess=samples)
        if not posterior.run.converged:
            warnings.append(f"the rig's posterior did not converge in {posterior.run.chain.shape[0]} steps "
                            f"({posterior.run.ess:.0f} effective samples): its intervals are rough")
    t_post = time.perf_counter()
    result = RigResult(rig, solution, cameras, pairwise, {}, skipped, (), {}, pair_frames, dict(links), None,
                       tuple(camera_views), tuple(lidar_views))
    for a, b in result.pairs() if posterior is not None else ():
        note = heavy_tails(posterior.pair_samples(a, b), what=f"T_{a}_{b} posterior")
        if note is not None:
            warnings.append(note)
    next_pose = rig_next_pose(result, advice_rng) if advise else None
    used = {c.name: tuple(c.corners_px) for c in camera_views}
    used.update({lv.name: tuple(lv.W) for lv in lidar_views})
    timings = {"cameras": t_cam - t0, "lidars_and_pairs": t_pairs - t_cam, "joint": t_joint - t_pairs}
    if posterior is not None:
        timings["posterior"] = t_post - t_joint
    if advise:
        timings["next_pose"] = time.perf_counter() - t_post
    return RigResult(rig, solution, cameras, pairwise, used, skipped, tuple(warnings),
                     {k: round(v, 3) for k, v in timings.items()}, pair_frames, dict(links), posterior,
                     tuple(camera_views), tuple(lidar_views), next_pose, range_models, outline_checks, edge_records)


def _with_edges(rig: RigDataset, names: tuple, camera_views: list, lidar_views: list, lidar_obs: dict,
                solution: RigSolution, T_ref: dict, T_ref_board: dict, refine_intrinsics: bool
                ) -> tuple[list, RigSolution, dict]:
    """The joint graph with every LiDAR's board edges, as the single pair's ``--edges`` has them
    (``solvers.board_edges``): each frame's ring ends (a scan's segment ends) assigned to the board's sides under
    the planes' estimate, an outline shift per LiDAR and frame (0 +- the boards' in-plane scatter) and an outline
    per LiDAR (its sides' growth and the pattern's offset, under their priors); the scatter and the ends' scale
    estimated by the method of moments (``board_edges.edge_scatter``), the graph solved again until they settle.
    Returns the views, the solution and per LiDAR its record (ends, scale, scatter, outline)."""
    views = []
    for lv in lidar_views:
        obs = lidar_obs[lv.name]
        T_l = solution.T_ref[lv.name]
        stems = [st for st in lv.W if st in solution.T_ref_board]
        ends = _lidar_ends([obs[st] for st in stems],
                           [np.linalg.inv(solution.T_ref_board[st]) @ T_l for st in stems], rig.board)
        found = {st: e for st, e in zip(stems, ends) if e is not None and e.size}
        views.append(replace(lv, edges=found or None, board=rig.board, edge_tau_m=1e-3, edge_scale=1.0))
    if not any(v.edges for v in views):
        return lidar_views, solution, {}
    planes = solution
    for _ in range(4):
        try:
            solution = solve_rig(names, rig.reference, camera_views, views, T_ref, T_ref_board, refine_intrinsics)
        except LidarcamError:
            return lidar_views, planes, {}
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
        views = new
        if settled:
            break
    records = {}
    for lv in views:
        if lv.edges:
            outline = solution.vectors[outline_key(names.index(lv.name))]
            records[lv.name] = {"used": True, "frames": len(lv.edges), "ends": int(sum(e.size for e in lv.edges.values())),
                                "end_scale": lv.edge_scale, "board_scatter_in_plane_m": lv.edge_tau_m,
                                "growth_m": outline[:2].tolist(), "outline_offset_m": outline[2:].tolist()}
    return views, solution, records


def _lidar_ends(observations: list, T_board_lidar: list, board) -> list:
    """Each LiDAR board observation's ring ends on the board's outline (a scan line's two segment ends; rings from
    the scan's field or clustered over these observations, ``range_model.frame_rings``), sides assigned under its
    ``T_board_lidar``; None where the rings are unknown."""
    if not observations:
        return []
    rings = frame_rings([_Framed(o) for o in observations])
    return [crossings(o.points, np.zeros(len(o.points), dtype=np.int64) if o.is_scan_line else r, T, board)
            if o.is_scan_line or r is not None else None for o, r, T in zip(observations, rings, T_board_lidar)]


def _outline_checks(rig: RigDataset, names: tuple, camera_views: list, lidar_views: list, solution: RigSolution,
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
        ends = _lidar_ends([f.lidar for f, _ in new], [np.linalg.inv(B) @ T_cl for _, B in new], rig.board)
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


def range_model_words(record: dict) -> str:
    """A LiDAR's range model in words (:func:`_range_models`' record)."""
    tests = list(record.get("tests", ()))
    said = ", ".join(f"{t['model']} p = {t['p_value']:.2g}" for t in tests)
    how = f"tests at {record['test_p']:g}: {said}" if tests else "requested"
    how += "".join(f"; {n['model']} terms not tested: with them the planes still disagree with the rig's boards "
                   f"{n['variance_factor']:.1f}x beyond their noise in variance, board-to-board structure the rig's "
                   "graph does not model (a camera-LiDAR pair calibrated alone has its per-board plane error)"
                   for n in record.get("inconsistent", ()))
    terms = record.get("terms") or {}
    if not terms:
        return f"no range terms ({how})" if tests else "no range terms (--range-model none)"
    parts = [f"range offset {1000 * terms['offset']['value_m']:+.1f} +- {1000 * terms['offset']['sd_m']:.1f} mm"]
    rings = [v["value_m"] for n, v in terms.items() if n.startswith("ring ")]
    if rings:
        parts.append(f"{len(rings)} ring offsets, spread (sd) {1000 * float(np.std(rings)):.1f} mm")
    if "dark" in terms:
        parts.append(f"black squares {1000 * terms['dark']['value_m']:+.1f} +- {1000 * terms['dark']['sd_m']:.1f} mm")
    return "; ".join(parts) + f" ({how}; prior sd {1000 * record['prior_sd_m']:.0f} mm)"


def _lidar_labels(rig: RigDataset, name: str, obs: dict, pair_frames: dict, solution: RigSolution,
                  blurred: bool = True) -> dict:
    """Each of LiDAR ``name``'s frames' labels for the range terms, by stem: ``(rings, black shares)``. Rings come
    from the scan's field or its beams' elevations clustered over all its frames (``range_model.frame_rings``);
    the black squares are placed by geometry (``range_model.frame_labels``) on ``solution``'s board pose (the
    camera's own, noisier, would shrink the black squares' term as an error in a regressor does), with the colours
    that the image of the camera the board was found with shows (a numbering turned to the reference camera's is
    that of a pattern that looks the same turned), under ``solution``'s transform of that camera-LiDAR pair.
    ``blurred``: each placement blurred by that transform's covariance; else by the labels' floor alone (the
    covariance of a solution without the terms is inflated by them). A 2D scanner's frames have neither."""
    measured: dict = {}  # stem -> (camera, frame) whose LiDAR observation is the one in ``obs``
    for (cam, lid), frames in pair_frames.items():
        for f in frames if lid == name else ():
            if f.name in obs and obs[f.name] is f.lidar:
                measured.setdefault(f.name, (cam, f))
    stems = list(obs)
    rings = dict(zip(stems, frame_rings([_Framed(obs[st]) for st in stems])))
    dark = dict.fromkeys(stems)
    for cam in sorted({c for c, _ in measured.values()}):
        group = [st for st in stems if st in measured and measured[st][0] == cam]
        T, C = solution.transform(cam, name)
        T_c = np.linalg.inv(solution.T_ref[cam])
        boards = [T_c @ solution.T_ref_board[st] if st in solution.T_ref_board else
                  measured[st][1].camera.T_camera_board for st in group]
        labels = frame_labels([measured[st][1] for st in group], rig.board, T, boards,
                              placement_cov=C if blurred else None)
        dark.update(zip(group, labels.dark))
    return {st: (rings[st], dark[st]) for st in stems}


def _range_models(rig: RigDataset, names: tuple, camera_views: list, lidar_views: list, lidar_obs: dict,
                  pair_frames: dict, solution: RigSolution, range_model: str) -> tuple[list, dict]:
    """Each LiDAR's views with the range terms of its model (``solvers.range_model``: a global offset, per-ring
    offsets, the black squares' offset; priors from its range accuracy, dataset.yaml's ``range_accuracy_m`` or its
    family's), and per LiDAR the record (:func:`_range_record`).

    ``auto`` chooses as the single pair does (``range_terms_choice.choose_range_model``): a global offset against none,
    then the per-ring and the black-square blocks each against the offset (against none, with the offset in the
    block, when the offset alone is not supported); both when both pass. Each test is a likelihood ratio on the
    joint graph at the graph's noise scales (``rig_graph.terms_test``: an overdispersed sensor's statistic is
    scaled down by its excess), and only the offset is tested where the planes stay overdispersed under every
    term (:func:`_choose_terms`). A model the data cannot hold (per-ring without rings, the black squares without
    both colours on the boards) is not tried; a requested one falls back to the terms the data allow."""
    out, records = [], {}
    for lv in lidar_views:
        sensor = rig.sensor(lv.name)
        acc = float(sensor.range_accuracy_m or range_accuracy_for(sensor.lidar_family))
        obs = lidar_obs[lv.name]
        record: dict = {"requested": range_model, "prior_sd_m": acc}
        placed: dict = {}  # the labels under each solution, placed once
        try:
            def views(model: str, solved: RigSolution, blurred: bool = True) -> LidarViews:
                key = (id(solved), blurred)
                if key not in placed:
                    placed[key] = (solved, _lidar_labels(rig, lv.name, obs, pair_frames, solved, blurred))
                labels = placed[key][1]
                known = FrameLabels(tuple(r for r, _ in labels.values()), tuple(d for _, d in labels.values()))
                terms = terms_for(model, known, acc) or RangeTerms((), ())
                return replace(lv, ranged={st: frame_whitener(obs[st], lv.sigma_m, terms, *labels[st]) for st in lv.W},
                               terms=terms)

            if range_model != "auto":
                chosen = views(range_model, solution, blurred=False)
                record["model"] = chosen.terms.model if chosen.has_terms else "none"
            else:
                chosen, tests, notes = _choose_terms(names, rig.reference, camera_views, lidar_views, solution,
                                                     views, lv.name)
                record.update(model=chosen.terms.model if chosen.has_terms else "none", tests=tests,
                              test_p=MODEL_TEST_P)
                if notes:
                    record["inconsistent"] = notes
        except (LidarcamError, np.linalg.LinAlgError) as exc:
            why = exc.message if isinstance(exc, LidarcamError) else str(exc)
            records[lv.name] = {**record, "model": "none", "reason": f"not tested: {why}"}
            out.append(lv)
            continue
        out.append(chosen if chosen.has_terms else lv)
        records[lv.name] = record
    return out, records


def _choose_terms(names: tuple, reference: str, camera_views: list, lidar_views: list, solution: RigSolution,
                  views, name: str) -> tuple:
    """``auto``'s choice for LiDAR ``name`` (:func:`_range_models`): its chosen views (``views(model, solution)``),
    the tests (``model``, ``against``, ``statistic``, ``dof``, ``p_value``; the offset's estimate with it,
    ``offset_m`` and ``sd_m``), and the terms not tested (``model``, ``variance_factor``: the LiDAR's under its
    largest model, above ``MAX_TERMS_DISPERSION``).

    Where the LiDAR's planes disagree beyond their noise (its chi-square beyond ``NOISE_WARNING_P``), the tests
    are made at the sensors' noise scales under the largest model, and its colours placed under that model's
    estimate and blurred by its covariance: a range term left out inflates its LiDAR's excess and the
    extrinsic's covariance, which would scale down the very statistic that tests it (quasi-likelihood's
    dispersion is estimated under the largest model) and smear the squares' placement."""
    ss, dof = solution.chi2_dof.get(name, (0.0, 1.0))
    largest = views("full", solution, blurred=False)
    models, notes = ("none", "offset", "per-ring", "offset+dark"), []
    if largest.has_terms and chi2.sf(ss, dof) < NOISE_WARNING_P:  # without a significant excess: as they are
        planes = solution
        solution = solve_rig(names, reference, camera_views,
                             [largest if v.name == largest.name else v for v in lidar_views], solution.T_ref,
                             solution.T_ref_board, solution.intrinsics is not None)
        excess = solution.noise_scale.get(name, 1.0)
        if excess > MAX_TERMS_DISPERSION:
            # Even with every term the planes disagree with the rig's boards far beyond their noise: structure from
            # board to board that the rig graph does not model (the single pair's per-board plane error), which
            # the within-board terms' tests would read as terms. The global offset alone is tested, as at the
            # planes' noise scales.
            solution, models = planes, ("none", "offset")
            notes.append({"model": "per-ring and black-square", "variance_factor": float(excess)})
    fits, seen = {}, set()
    for model in models:
        v = views(model, solution)
        if v.terms.names in seen:  # per-ring without rings, black squares without both colours: nothing new
            continue
        seen.add(v.terms.names)
        fits[model] = (v, terms_fit(names, reference, camera_views, lidar_views, solution, v))

    def test(model: str, against: str) -> dict:
        return {"model": model, "against": against, **terms_test(fits[against][1], fits[model][1])}

    tests = [{**test("offset", "none"), "offset_m": float(fits["offset"][1]["values_m"][0]),
              "sd_m": float(fits["offset"][1]["sd_m"][0])}]
    base = "offset" if tests[0]["p_value"] < MODEL_TEST_P else "none"
    blocks = []
    for model in ("per-ring", "offset+dark"):
        if model in fits:
            tests.append(test(model, base))
            if tests[-1]["p_value"] < MODEL_TEST_P:
                blocks.append(model)
    if len(blocks) == 2:
        return views("full", solution), tests, notes
    return fits[blocks[0] if blocks else base][0], tests, notes


def _range_record(record: dict, terms: RangeTerms, values: np.ndarray, sds: np.ndarray, warnings: list,
                  name: str) -> None:
    """A LiDAR's range record with its terms' final estimates (``terms``: by name, ``value_m``, ``sd_m``,
    ``prior_sd_m``; the global offset's also as ``value_m`` and ``sd_m``), and a warning for each term beyond 3
    prior standard deviations (a wrong board in some frames, or a range accuracy too small for the sensor)."""
    record["terms"] = {n: {"value_m": float(v), "sd_m": float(s), "prior_sd_m": float(p)}
                       for n, v, s, p in zip(terms.names, values, sds, terms.prior_sd)}
    record.update(value_m=float(values[0]), sd_m=float(sds[0]))
    beyond = [n for n, v, p in zip(terms.names, values, terms.prior_sd) if abs(v) > 3 * p]
    if beyond:
        said = ", ".join(f"{n} {1000 * values[terms.names.index(n)]:+.1f} mm" for n in beyond)
        warnings.append(f"{name}: its range terms {said} lie beyond 3 times their prior sd (range accuracy "
                        f"{1000 * record['prior_sd_m']:.0f} mm): a wrong board in some frames, or a "
                        "range_accuracy_m in dataset.yaml too small for this sensor")


def rig_next_pose(result: RigResult, rng: np.random.Generator, candidates: int = 60) -> dict | None:
    """The board pose that most lowers the weakest camera-LiDAR pair's largest translation standard deviation
    (``analysis.rig_layout.next_pose_for_pair``, at the noise levels the graph weighed the two sensors with), with
    ``pair``, ``camera`` and ``lidar`` added; None without a weakest pair or a feasible pose."""
    from .analysis.rig_layout import beam_model_name, next_pose_for_pair

    weakest = result.layout()["weakest_pair"]
    if weakest is None:
        return None
    cam, lid = next((c.name, d.name) for c in result.rig.cameras for d in result.rig.lidars
                    if f"T_{c.name}_{d.name}" == weakest)
    sol = result.solution
    cv = next((v for v in result.camera_views if v.name == cam), None)
    lv = next((v for v in result.lidar_views if v.name == lid), None)
    if cv is None or lv is None:
        return None
    rings = [len(np.unique(f.lidar.rings)) for (_, d), frames in (result.pair_frames or {}).items() if d == lid
             for f in frames if f.lidar is not None and f.lidar.rings is not None]
    T, P = sol.transform(cam, lid)
    camera = result.cameras[cam]
    if sol.intrinsics and cam in sol.intrinsics:
        camera = camera.with_params(sol.intrinsics[cam][0])
    found = next_pose_for_pair(camera, result.rig.board, T, P, cv.sigma_px * np.sqrt(sol.noise_scale.get(cam, 1.0)),
                               lv.sigma_m * np.sqrt(sol.noise_scale.get(lid, 1.0)),
                               beam_model_name(lv.scan_line, max(rings) if rings else None), rng, candidates)
    return None if found is None else {"pair": weakest, "camera": cam, "lidar": lid, **found}


def _pair_frames(ds, camera_name: str, lidar_name: str, stems: list[str], poses: dict, measured: dict, rng,
                 workers: int, found: dict, warnings: list) -> list[FrameMeasurement]:
    """A camera-LiDAR pair's frames: the LiDAR's board in a frame is found once, with the first camera that shares
    it (``measured``, updated), and paired with each later camera's own board pose. A camera with only one or two
    frames not yet measured measures them with those it shares (choosing each frame's board takes three). The
    camera's corners (``found``) and board poses (``poses``) are those ``measure_camera`` found."""
    new = [st for st in stems if st not in measured]
    now = {}
    if new:
        keep = set(new) if len(new) >= MIN_PAIR_FRAMES else set(stems)
        _, frames, w = measure_frames(replace(ds, frames=tuple(f for f in ds.frames if f.name in keep)), rng,
                                      workers=workers, detections=found, board_poses=poses)
        warnings.extend(f"{camera_name}-{lidar_name}: {x}" for x in w)
        now = {f.name: f for f in frames}
        for f in frames:
            if f.camera is not None:  # the LiDAR side was tried (it needs the camera's board)
                measured.setdefault(f.name, (camera_name, f))
    out = []
    for st in stems:
        if st in now:
            out.append(now[st])
        elif st in measured and st in poses:
            f = measured[st][1]
            out.append(FrameMeasurement(st, poses[st], f.lidar, None if f.lidar is not None else f.reason))
    return out


@dataclass(frozen=True, eq=False)
class _Framed:
    """A LiDAR observation in the shape ``pooled_range_noise_m`` reads (``frame.lidar``)."""

    lidar: object


def _start(names, reference, parent, poses, pairwise, flip) -> dict:
    """Each sensor's starting pose in the reference's frame, composed along the tree from the reference."""
    T_ref = {reference: np.eye(4)}
    pending = [n for n in names if n != reference]
    while pending:
        for n in list(pending):
            p = parent[n]
            if p not in T_ref:
                continue
            T_ref[n] = T_ref[p] @ _relative(p, n, poses, pairwise, flip)
            pending.remove(n)
    return T_ref


def _relative(a: str, b: str, poses, pairwise, flip) -> np.ndarray:
    """``T_a_b`` from the pairwise solution (camera-LiDAR) or the shared boards' consensus (camera-camera; both
    numberings of a board that looks the same turned, ``flip``)."""
    if (a, b) in pairwise:
        return pairwise[(a, b)][0]
    if (b, a) in pairwise:
        return np.linalg.inv(pairwise[(b, a)][0])
    shared = [st for st in poses[a] if st in poses[b]]
    flips = [np.eye(4)] if flip is None else [np.eye(4), flip]
    return _consensus_relative([[poses[a][st].T_camera_board @ np.linalg.inv(poses[b][st].T_camera_board @ F)
                                 for F in flips] for st in shared])


def write_rig_calibration(result: RigResult, out: str | Path) -> Path:
    """Write a rig's ``calibration.json`` atomically.

    Parameters
    ----------
    result : RigResult
        From :func:`calibrate_rig`.
    out : str or Path
        The output folder (created when absent).

    Returns
    -------
    Path
        The file written (docs/reference/calibration_json.md, rigs); with a posterior, ``posterior.npz`` beside it
        first (``xi``: the samples of every sensor's pose, ``names``, ``T_ref``: the MAP poses in that order).
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    post = result.posterior
    if post is not None:
        write_npz_atomic(out / "posterior.npz", xi=post.xi, names=np.array(post.names),
                         T_ref=np.array([post.T_ref[n] for n in post.names]), reference=np.array(post.reference))
    path = out / "calibration.json"
    write_json_atomic(path, result.to_json())
    return path
