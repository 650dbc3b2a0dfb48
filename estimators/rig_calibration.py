"""A whole rig in one graph: measure every sensor, start each pose along the links that share the most frames,
solve jointly (``solvers.rig_graph``), and write every pair's transform with its covariance.

Measurement (``pipeline.rig_measurement.measure_rig``, cached) reuses the single pair's pipeline: each camera's
corners and board poses (intrinsics calibrated from its frames when dataset.yaml gives none); each LiDAR's board in
a frame, found once with the first camera (the one sharing most frames) that shares at least ``MIN_PAIR_FRAMES``
frames with it (``pipeline.measurement.measure_frames`` on that pair) and paired with every other camera's board
pose of the frame. Each such camera-LiDAR pair is also solved alone as a single pair is (:func:`pair_options`):
its estimate starts the joint graph and is reported beside it ("pairwise only"), and its refinement weighs the
LiDAR's boards in the joint graph (each board's plane error, the boards' scatter, its outlier frames left out) and
chooses the LiDAR's range terms (those it held at 0 held there too). Two cameras are linked by every frame both
saw.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np
from threadpoolctl import threadpool_limits

from .calibration import solve
from .camera.board_pose import reobserve_frames
from .errors import DatasetError, DegenerateLayoutError, LidarcamError, PosteriorSkippedError, in_pair
from .io.measurement_store import RigMeasurements, load_choices, save_choices
from .io.rig_dataset import RigDataset
from .lidar.board_segmentation import SegmentationParams
from .pipeline.measurement import Hints
from .pipeline.rig_edges import ends_view, pairs_outline_checks, with_edges
from .pipeline.rig_measurement import (MIN_PAIR_FRAMES, align_numbering, camera_views_of, lidar_views_of,
                                       given_measurements, measured_rig, pattern_flip, start_poses)
from .pipeline.rig_modes import minimum_solver, mixable_minima, mixed_posterior
from .pipeline.rig_result import NOISE_WARNING_P, RigResult
from .pipeline.rig_terms import (range_record, weak_offset_share, with_held_share, with_placement_share,
                                  with_range_terms)
from .solvers import chi_square as chi2
from .solvers.choice_memo import recallable
from .solvers.edges_in_graph import conflict_words, left_out_warning
from .solvers.noise_levels import pooled_range_noise_m
from .solvers.posterior import PosteriorOptions, heavy_tails
from .solvers.range_model import OFFSET_HELD_P
from .solvers.refusal import POSTERIOR_REFUSAL_FACTOR, scan_refusal
from .solvers.refinement_options import RefinementOptions
from .solvers.rig_graph import held_intrinsics_share, intrinsics_test, own_corner_drop, solve_rig, spanning_tree
from .solvers.rig_posterior import sample_rig_posterior

# Fewest boards a camera and a 2D scanner whose segment ends are measurements must share to be linked: a single
# pair of them is solved from two (``solution_selection.select_minimal``).
MIN_SCANNER_FRAMES_WITH_ENDS = 2
# With refined intrinsics, rounds of the pairs solved again under them at most (each round's per-board plane errors
# weigh the next joint solve; :meth:`PairsAlone.settled` ends them sooner).
INTRINSICS_ROUNDS = 3


def pair_options(options: RefinementOptions, range_model: str, params: SegmentationParams,
                 edges: bool | None = None) -> RefinementOptions:
    """The options each camera-LiDAR pair is solved alone with first, as a single pair is (its robust loss and
    outlier frames, its range terms chosen before its per-board plane error is estimated, which the joint graph then
    weighs the LiDAR's boards with, and the board search's bound on the sensors' separation): its estimate starts
    the joint graph and is reported beside it. No edges, no checks (by the edges, by the intrinsics) and no intrinsics
    (the joint graph has its own); its range offset is tested with the ring ends unless ``edges`` (the joint
    graph's) is False."""
    return replace(options, edges=False, checks=False, range_model=range_model, refine_intrinsics=False,
                   max_sensor_separation_m=params.max_sensor_separation_m,
                   offset_with_ends=options.offset_with_ends is not False and edges is not False
                   and options.edges is not False)



@dataclass(frozen=True)
class PairsAlone:
    """Each camera-LiDAR pair that shares enough frames, solved alone as a single pair is (:func:`solve_pairs_alone`):
    what the joint graph takes from them.

    Attributes
    ----------
    pairwise : dict
        ``(camera, lidar) -> (T_camera_lidar, covariance, frames)``: each pair's own estimate.
    pair_frames, links : dict
        Each pair's usable frames and their number.
    lidar_obs, plane_frames : dict
        Per LiDAR and stem: the board it was used from, and ``(frame, per-board plane error)`` of that frame's pair.
    board_scatter, sigma_r : dict
        Per LiDAR: its boards' scatter along their range terms' weak direction (its first pair's) and its range noise.
    term_choices : dict
        Per LiDAR: its range model's choice (``RangeModelFit``) and the pair that chose it.
    ambiguous : dict
        The pairs whose own boards leave a second minimum with at least ``AMBIGUOUS_MASS``: ``(camera, lidar) ->
        modes``.
    with_ends : frozenset
        The scanners whose pairs were solved with their segment ends (few boards).
    minima : dict
        Every pair solved with its segment ends whose boards leave more than one minimum holding mass, ``(camera,
        lidar) -> modes``: the rig's posterior mixes them (``pipeline.rig_modes``), as a single pair's does.
    skipped : dict
        Per LiDAR: ``stem -> reason`` for the frames it does not give the joint graph.
    first, warnings : tuple of str
        What to say before every other warning (an ambiguous pair), and the rest: each pair's own, as a single
        pair's result says them, prefixed with the pair.
    failed : dict
        ``(camera, lidar) -> DegenerateLayoutError``: the pairs not solved (too few usable frames, or boards that
        leave the transform unobservable), and why.
    intrinsics_checks : dict
        ``(camera, lidar) -> record`` of ``intrinsics_refinement.intrinsics_drop``: for each 3D pair, whether its
        planes disagree in a way the camera's intrinsics explain.
    results : dict
        ``(camera, lidar) -> CalibrationResult``: each pair's own solve (its start, its frames' fits, its range
        model's choice, a scanner's minimal solutions), which a two-sensor rig's calibration.json reports as a
        single pair's file does (``RigResult.pair_keys``).
    decided : dict
        ``camera -> {stem: CameraBoardObservation}``: the boards whose tilt the camera left ambiguous and a scanner's
        pair decided by its laser points, each with the tilt chosen (the camera's board pose in the joint graph).
    """

    pairwise: dict
    pair_frames: dict
    links: dict
    lidar_obs: dict
    plane_frames: dict
    board_scatter: dict
    sigma_r: dict
    term_choices: dict
    ambiguous: dict
    with_ends: frozenset
    minima: dict
    skipped: dict
    first: tuple
    warnings: tuple
    failed: dict
    intrinsics_checks: dict
    results: dict
    decided: dict

    def settled(self, before: "PairsAlone") -> bool:
        """Every board's plane error within a tenth of ``before``'s (or 0.1 mm) and the same boards used: the
        rounds of a refinement of the intrinsics stop there (``INTRINSICS_ROUNDS``)."""
        now = {(n, st): e for n, frames in self.plane_frames.items() for st, (_, e) in frames.items()}
        then = {(n, st): e for n, frames in before.plane_frames.items() for st, (_, e) in frames.items()}
        return now.keys() == then.keys() and all(abs(now[k] - then[k]) <= max(0.1 * then[k], 1e-4) for k in now)


def solve_pairs_alone(rig: RigDataset, frames_by_pair: dict, measured_by: dict, cameras: dict,
                      alone: RefinementOptions, init: str, options: RefinementOptions,
                      scanner_ends: bool = False, check_intrinsics: bool = False, memo: dict | None = None
                      ) -> PairsAlone:
    """Each camera-LiDAR pair of ``frames_by_pair`` (``(camera, lidar) -> frames``, measured or observed again under
    refined intrinsics, ``cameras`` the models they were observed under) with at least ``MIN_PAIR_FRAMES`` usable
    frames (``MIN_SCANNER_FRAMES_WITH_ENDS`` for a scanner taking its segment ends, below) solved alone with
    ``alone`` (:func:`pair_options`). A LiDAR's range model is chosen once, by its pair
    with the camera that shares the most frames (the first): its other pairs are solved with that model, not tested
    again on fewer frames. Each LiDAR board enters the joint graph once, from the first pair that used it; a pair's
    outlier frame is left out. With ``scanner_ends`` (the board's size known and the edges not refused), a 2D
    scanner that saw at most ``REFINE_ALL_UP_TO`` boards in all has its pairs solved as the single pair is, the
    segment ends in the graph and in the weighing of the minima (``solution_selection``): with so few boards they
    alone tell its minima apart (without them a 3-board pair folder's rig started from a planes-only minimum 5
    degrees and 24 cm off, which its joint graph kept, and read ``OK``). With more boards, its joint graph decides
    among them and the planes alone start it: weighed with the ends, a 6-camera rig's 3- and 4-board scanner
    pairs took 17 s, the whole rig's solve 2.4 s without them. With ``check_intrinsics``, each 3D pair's boards are
    checked for planes that disagree in a way the camera's intrinsics explain (``intrinsics_refinement.
    intrinsics_drop``, as every single 3D pair's result is; about 10 ms a pair). ``memo``: the range terms'
    choices made before on the same inputs (``solvers.choice_memo``), replayed, and filled with those made here."""
    lidar_obs: dict = {s.name: {} for s in rig.lidars}
    plane_frames: dict = {s.name: {} for s in rig.lidars}
    skipped: dict = {s.name: {} for s in rig.lidars}
    board_scatter, sigma_r, term_choices, terms_noise = {}, {}, {}, {}
    pairwise, links, pair_frames, ambiguous, minima, failed, checks, results = {}, {}, {}, {}, {}, {}, {}, {}
    first: list[str] = []
    warnings: list[str] = []
    with_ends = set()
    decided: dict = {}
    for lid in rig.lidars:
        seen = {f.name for (_, d), frames in frames_by_pair.items() if d == lid.name for f in frames if f.usable}
        ends = scanner_ends and lid.lidar == "2d" and len(seen) <= _few_boards()
        if ends:
            with_ends.add(lid.name)
        for (cam_name, lid_name), frames in frames_by_pair.items():
            if lid_name != lid.name:
                continue
            usable = [f for f in frames if f.usable]
            # a scanner's boards whose tilt the camera leaves ambiguous: its pair's solve may decide them by the
            # laser (``solution_selection.select_and_refine``), and the camera's board pose is then that tilt
            tilts = [f for f in frames if not f.usable and f.camera_alternatives and f.lidar is not None] \
                if lid.lidar == "2d" else []
            for f in frames:
                if not f.usable and f.name not in lidar_obs[lid.name]:
                    by = measured_by[(cam_name, lid_name)].get(f.name, cam_name)
                    skipped[lid.name].setdefault(f.name, f"with {by}: {f.reason}")
            # Two boards link a scanner whose segment ends are measurements, as they solve a single pair
            # (``solution_selection.select_minimal``): their ends hold what two planes leave.
            least = MIN_SCANNER_FRAMES_WITH_ENDS if ends else MIN_PAIR_FRAMES
            if len(usable) + len(tilts) < least:
                warnings.append(f"{cam_name}-{lid.name}: only {len(usable)} usable frame(s); not linked")
                failed[(cam_name, lid.name)] = DegenerateLayoutError(
                    f"only {len(usable)} usable frame(s); a camera-LiDAR pair needs at least {least}",
                    hint="record more board poses that both sensors see")
                continue
            chooses = lid.name not in term_choices  # its range terms are the LiDAR's in the joint graph
            try:
                opts = alone if chooses else replace(alone, range_model=term_choices[lid.name][0].chosen)
                res = solve(usable + tilts, rig.board, cameras[cam_name],
                            init if lid.lidar == "2d" else "closed-form",
                            options=replace(opts, edges=True) if ends else opts, use_extent=ends, memo=memo)
            except DatasetError as exc:  # its data cannot be right (a mirrored LiDAR): the rig is refused
                raise in_pair(exc, f"{cam_name}-{lid.name}", rig.root) from exc
            except DegenerateLayoutError as exc:
                failed[(cam_name, lid.name)] = exc
                warnings.append(f"{cam_name}-{lid.name}: not solved as a pair ({exc.message})")
                continue
            if tilts:
                usable = [f for f in res.frames if f.usable]
                named = {t.name for t in tilts}
                decided.setdefault(cam_name, {}).update({f.name: f.camera for f in usable if f.name in named})
            # What its boards say of themselves, as a single pair's result says it (the joint graph weighs them
            # as this refinement did): its range terms' choice, plane error, outliers, spread. Said elsewhere:
            # its second minimum (``first``, below) and, where it chose them, terms held at 0 (``rig_terms``).
            warnings.extend(f"{cam_name}-{lid.name}: {w}" for w in res.warnings if not w.startswith("ambiguous:")
                            and not (chooses and w.startswith("range model: ") and " lie beyond " in w))
            if check_intrinsics and lid.lidar != "2d":
                from .solvers.intrinsics_refinement import intrinsics_drop

                checks[(cam_name, lid.name)] = intrinsics_drop(usable, rig.board, cameras[cam_name], res.refinement,
                                                               opts)
            if ends and len(res.modes) > 1:  # weighed by the ends, as the joint graph has them
                minima[(cam_name, lid.name)] = tuple(res.modes)
            if res.ambiguous:
                ambiguous[(cam_name, lid.name)] = tuple(res.modes)
                masses = ", ".join(f"{m.mass:.0%}" for m in res.modes)
                first.insert(0, f"{cam_name}-{lid.name}: {len(res.modes)} distinct solutions fit its boards "
                                f"(posterior mass {masses}); the rig starts from the most probable: add boards "
                                "tilted in other directions to decide")
            if lid.name not in term_choices and res.refinement.range_model is not None:
                term_choices[lid.name] = (res.refinement.range_model, f"{cam_name}-{lid.name}")
                if res.refinement.range_model.names:  # its points' scatter about each board's plane and terms
                    terms_noise[lid.name] = res.refinement.range_noise_m
            pairwise[(cam_name, lid.name)] = (res.T_camera_lidar, res.covariance, len(usable))
            results[(cam_name, lid.name)] = res
            pair_frames[(cam_name, lid.name)] = usable
            links[(cam_name, lid.name)] = len(usable)
            dropped = {fit.name: fit.outlier for fit in res.refinement.frames if fit.dropped}
            fit = res.refinement.range_model
            board_scatter.setdefault(lid.name, float(fit.term_consistency.get("board_scatter_m", 0.0)) if fit else 0.0)
            for f in usable:
                if f.name in lidar_obs[lid.name] or f.name in skipped[lid.name] and f.name in dropped:
                    continue
                if f.name in dropped:  # the pair's outlier: its LiDAR board or its board pose is not this board
                    skipped[lid.name][f.name] = f"with {cam_name}: {dropped[f.name]}"
                    continue
                lidar_obs[lid.name][f.name] = f.lidar
                plane_frames[lid.name][f.name] = (f, res.refinement.plane_floor_m)
                skipped[lid.name].pop(f.name, None)
        if lidar_obs[lid.name]:
            # With range terms, the range noise is the scatter the terms leave, as the pair that chose them
            # estimated it: the scatter about each board's plane also holds the structure they explain.
            sigma_r[lid.name] = options.range_noise_m or terms_noise.get(lid.name) or \
                pooled_range_noise_m(list(lidar_obs[lid.name].values()))
    return PairsAlone(pairwise, pair_frames, links, lidar_obs, plane_frames, board_scatter, sigma_r, term_choices,
                      ambiguous, frozenset(with_ends), minima, skipped, tuple(first), tuple(warnings), failed,
                      {k: v for k, v in checks.items() if v is not None}, results, decided)


def unlinked_lidar(rig: RigDataset, fit: PairsAlone, skipped: dict) -> None:
    """A LiDAR left without a link to any camera (too few usable frames, or boards that leave its transform
    unobservable) raises its first pair's reason (the camera sharing most frames), as a single pair's calibration
    says it, with the frames it skipped and why; one that no camera found the board with, the frames its camera
    (the one that skipped most of its frames) skipped and why."""
    for lid in rig.lidars:
        if any(d == lid.name for _, d in fit.links):
            continue
        reasons = [(c, exc) for (c, d), exc in fit.failed.items() if d == lid.name]
        if not reasons and rig.cameras:  # no camera found the board in a frame it has a scan of
            cam = max((c.name for c in rig.cameras), key=lambda c: sum(
                lid.file(st) is not None for st in skipped.get(c, {})))
            said = "; ".join(f"{st}: {why}" for st, why in sorted(skipped.get(cam, {}).items())
                             if lid.file(st) is not None)
            raise DegenerateLayoutError(f"{cam}-{lid.name}: no frame where {cam} found the board has a {lid.name} "
                                        "scan" + (f" (skipped: {said})" if said else ""), path=rig.root,
                                        hint="record board poses that both sensors see (a LiDAR needs 3 or more with "
                                             "a camera, a 2D scanner 2 where the board's size is given)")
        if reasons:
            cam, exc = reasons[0]
            frames = {**skipped.get(lid.name, {}), **fit.skipped.get(lid.name, {})}
            said = "; ".join(f"{st}: {why}" for st, why in sorted(frames.items()))
            raise DegenerateLayoutError(f"{cam}-{lid.name}: {exc.problem}" + (f" (skipped: {said})" if said else ""),
                                        path=rig.root, hint=exc.hint)


def _few_boards() -> int:
    """The boards up to which a scanner's minima may fit alike (``solution_selection.REFINE_ALL_UP_TO``; imported
    here, with a scanner: it loads scipy.optimize)."""
    from .solvers.solution_selection import REFINE_ALL_UP_TO

    return REFINE_ALL_UP_TO


# One BLAS thread, as the command line runs: the solves' matrices are small, and OpenBLAS's own threads cost more
# than they give there (a 6-camera rig's camera-LiDAR pairs, solved in two threads, took 6x as long with two BLAS
# threads each); restored on return.
@threadpool_limits.wrap(limits=1, user_api="blas")
def calibrate_rig(rig: RigDataset, rng: np.random.Generator, workers: int = 2, refine_intrinsics: bool = False,
                  samples: int = 0, advise: bool = True, range_model: str = "auto", edges: bool | None = None,
                  options: RefinementOptions = RefinementOptions(), cache: bool = False,
                  measurements: RigMeasurements | None = None, init: str = "closed-form",
                  params: SegmentationParams = SegmentationParams(), hints: Hints = Hints(),
                  likelihood: str = "gaussian", remeasure: bool = True, on_solved=None,
                  sampler: str = "proposal") -> RigResult:
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
        skips sampling. With ``refine_intrinsics`` the poses are sampled with the intrinsics held at their refined
        values and the samples convolved with the intrinsics' share of the joint covariance
        (:func:`_at_refined_intrinsics`).
    likelihood : str
        The posterior's likelihood of each frame's planes against its boards, as the single pair's
        ``--likelihood``: ``gaussian`` or ``student-t`` (4 degrees of freedom).
    sampler : str
        ``proposal`` (the default: mostly moves from an independence proposal at the posterior's Laplace
        approximation) or ``ensemble`` (emcee's ensemble moves alone: slower to mix, for comparison;
        ``PosteriorOptions.sampler``).
    range_model : str
        Each LiDAR's range model, as the single pair's ``--range-model``: ``none`` (planes), ``offset``,
        ``per-ring``, ``offset+dark``, ``full`` (the terms under priors from its range accuracy, dataset.yaml's
        ``range_accuracy_m`` or its family's), or ``auto``: the terms that likelihood-ratio tests at
        ``MODEL_TEST_P`` support, as its first camera-LiDAR pair tests them (``rig_terms.ranged_views``).
    edges : bool or None
        The board's edges as measurements too: each LiDAR's ring ends (a 2D scanner's segment ends) on the board's
        outline, in the joint graph (:func:`with_edges`); the posterior holds their share to second order about
        the estimate (``rig_posterior.edges_quadratic``); each 3D LiDAR's planes are tested against its edges, and
        where they conflict the joint covariance holds both answers (``rig_edges.conflict_share``). None (the
        default, as for a single pair) or True (``--edges``): every LiDAR's, where the board's size is given;
        False (``--no-edges``): none (each 3D camera-LiDAR pair is then checked by its ring ends).
    options : RefinementOptions
        The solver's settings that every camera-LiDAR pair and the joint graph share (``--robust``, ``--outliers``,
        ``--corner-noise-px``, ``--range-noise-m``, ``--range-accuracy``, ``--max-sensor-separation``); its
        ``range_model``, ``edges`` and ``refine_intrinsics`` are this function's own arguments.
    cache : bool
        Keep the measurements under the user's cache folder and read them back on a second call with the same
        files, code and generator (``pipeline.rig_measurement.measured_rig``).
    measurements : RigMeasurements or None
        Solve from these (``result.measurements`` of an earlier call, or ``load_rig_measurements``) instead of
        measuring.
    init : str
        How each 2D scanner's pairs start (``--init``: ``closed-form``, which for a scanner means
        ``minimal-lower-bound``, or ``minimal-min-residual``); a 3D LiDAR's pairs start in closed form.
    params : SegmentationParams
        The LiDAR board search's settings (``--max-sensor-separation``: also the bound on a scanner's minimal
        solutions).
    hints : Hints
        A region of interest (``--roi``, in each LiDAR's own frame) and ``--no-static-scene``; an initial guess is
        one pair's, and refused.
    advise : bool
        Find the board pose that most helps the weakest camera-LiDAR pair (:func:`rig_next_pose`, in
        ``result.next_pose``; about a second).
    remeasure : bool
        With ``refine_intrinsics`` and the rig measured here (not ``measurements``): the LiDARs' boards measured
        again under the refined intrinsics (chosen under the given ones, their points follow the given ones'
        error) and the rig solved again from them, the cameras' side as before; False: measured once.
    on_solved : callable, optional
        Called with each camera-LiDAR pair's own result (``(camera, lidar) -> CalibrationResult``) once the joint
        graph is solved, before the posterior is sampled: the command line starts the report's figures of them
        then (``analysis.rig_report.draw_pairs_ahead``).

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
    if init != "closed-form" and not any(s.lidar == "2d" for s in rig.lidars):
        raise DatasetError(f"init {init!r} is for 2D LiDARs, and this rig has none", path=rig.yaml_path,
                           hint="use --init closed-form")
    alone = pair_options(options, range_model, params, edges)
    stages: dict = {}  # the measurement's stage times, summed over its threads (as a single pair's)
    reused: dict = {}  # the images' corners and the sweeps, shared with a measurement under refined intrinsics
    measured = measured_rig(rig, rng, workers, cache, params, hints, stages, reused) if measurements is None else \
        given_measurements(rig, measurements, rng)
    cameras, poses = measured.cameras, measured.poses
    skipped = {c: dict(v) for c, v in measured.skipped.items()}
    warnings: list[str] = list(measured.warnings)
    if measured.source != "measured":
        warnings.append(f"measurements taken from {'the cache' if measured.source == 'cache' else measured.source}:"
                        " images and sweeps were not read again")
    t_meas = time.perf_counter()
    # Each camera-LiDAR pair that shares enough frames solved alone, as a single pair is.
    scanner_ends = edges is not False and rig.board.size_known
    # The range terms' choices kept beside cached measurements: a re-solve replays them (``solvers.choice_memo``).
    memo = recallable(load_choices(measured.cache)) if measured.cache is not None else None
    kept = dict(memo or {})
    alone_fit = solve_pairs_alone(rig, measured.pairs, measured.measured_by, cameras, alone, init, options,
                                  scanner_ends, check_intrinsics=not refine_intrinsics, memo=memo)
    t_pairs = time.perf_counter()
    cams = [c.name for c in rig.cameras]
    links = dict(alone_fit.links)
    for i, a in enumerate(cams):
        for b in cams[i + 1:]:
            links[(a, b)] = sum(1 for st in poses[a] if st in poses[b])
    names = tuple(s.name for s in rig.sensors)
    unlinked_lidar(rig, alone_fit, skipped)
    if alone_fit.decided:  # a board's tilt a scanner's laser decided is the camera's board pose from here on
        poses = {c: {**by, **alone_fit.decided.get(c, {})} for c, by in poses.items()}
        for c, by in alone_fit.decided.items():
            for st in by:
                skipped[c].pop(st, None)
    parent = spanning_tree(names, rig.reference, links)
    flip = pattern_flip(rig.board)
    T_ref = start_poses(names, rig.reference, parent, poses, alone_fit.pairwise, flip)
    if flip is not None:
        poses = align_numbering(cams, poses, T_ref, flip)
    # Each frame a camera saw starts from the first camera (in the rig's order) that saw it.
    T_ref_board = {}
    for c in cams:
        for st, p in poses[c].items():
            T_ref_board.setdefault(st, T_ref[c] @ p.T_camera_board)
    camera_views = [camera_views_of(c, cameras[c], poses[c], rig.board, options) for c in cams if poses[c]]

    def joint(fit: PairsAlone):
        views = [lidar_views_of(lid.name, fit.sigma_r[lid.name], fit.plane_frames[lid.name], T_ref_board, rig.board,
                                lid.lidar == "2d", alone) for lid in rig.lidars if fit.lidar_obs[lid.name]]
        # A scanner of so few boards that its pairs took their segment ends has them from the first joint solve
        # (under its start): its planes alone leave its pose free (the graph's information singular, or the pose
        # astray), which the single pair never solves without them either.
        views = [ends_view(lv, rig.board, fit.lidar_obs[lv.name], T_ref[lv.name], T_ref_board)
                 if lv.name in fit.with_ends else lv for lv in views]
        return views, solve_rig(names, rig.reference, camera_views, views, T_ref, T_ref_board, refine_intrinsics)

    lidar_views, solution = joint(alone_fit)
    # Refined intrinsics, in rounds as a single pair's: each pair solved again with its boards observed under them
    # gives the LiDAR boards' plane errors the next joint solve weighs them with (errors estimated under wrong
    # intrinsics hold their error, and would weaken the planes that reveal it), until those settle.
    # The rounds keep the first round's answer on an offset its planes passed over (``RefinementOptions.
    # offset_with_ends``): tested again with the ends only where the ends took it then, or held it in the covariance
    # (``RangeModelFit.weak_offset``), so that it stays.
    ended = any(t.get("with_ring_ends") and (t.get("included") or t["p_value"] < OFFSET_HELD_P)
                for fit, _ in alone_fit.term_choices.values() for t in fit.tests)
    rounds = replace(alone, offset_with_ends=alone.offset_with_ends and ended)
    for _ in range(INTRINSICS_ROUNDS if refine_intrinsics else 0):
        if not solution.intrinsics:
            break
        seen = {c: solution.camera_model(c, cameras[c]) for c in cameras}
        try:
            again = solve_pairs_alone(rig, {(c, d): reobserve_frames(frames, rig.board, seen[c])
                                            for (c, d), frames in measured.pairs.items()},
                                      measured.measured_by, seen, rounds, init, options, scanner_ends, memo=memo)
            settled = again.settled(alone_fit)
            views, joint_again = joint(again)
        except LidarcamError as exc:  # the last round that could be solved stands
            warnings.append(f"refined intrinsics: the boards observed under them could not be solved again "
                            f"({exc.message}); their plane errors are those of the round before")
            break
        alone_fit, lidar_views, solution = again, views, joint_again
        if settled:
            break
    if memo is not None and memo != kept:
        save_choices(measured.cache, memo)
    if refine_intrinsics and solution.intrinsics and measurements is None and remeasure:
        refined = replace(rig, sensors=tuple(
            replace(s, camera=solution.camera_model(s.name, cameras[s.name]))
            if s.name in solution.intrinsics else s for s in rig.sensors))
        again = measured_rig(refined, rng, workers, cache, params, hints, stages, reused)
        merged = replace(measured, pairs={k: reobserve_frames(frames, rig.board, cameras[k[0]])
                                          for k, frames in again.pairs.items()},
                         measured_by=again.measured_by, spawned=measured.spawned + again.spawned)
        result = calibrate_rig(rig, rng, workers=workers, refine_intrinsics=True, samples=samples, advise=advise,
                               range_model=range_model, edges=edges, options=options, cache=cache,
                               measurements=merged, init=init, params=params, hints=hints, likelihood=likelihood,
                               remeasure=False, on_solved=on_solved, sampler=sampler)
        # the solve given the measurements timed no measuring stage: this call's stages are the measuring's
        timings = dict(result.timings_s, **{k: round(v, 3) for k, v in stages.items()}, measurements=round(
            time.perf_counter() - t0 - sum(v for k, v in result.timings_s.items() if k != "measurements"), 3))
        return replace(result, timings_s=timings)
    pairwise, pair_frames, lidar_obs = alone_fit.pairwise, alone_fit.pair_frames, alone_fit.lidar_obs
    ambiguous = alone_fit.ambiguous
    skipped.update(alone_fit.skipped)
    warnings[:0] = alone_fit.first
    warnings += alone_fit.warnings
    range_models, pins, placing, pinned_share, placement_share = {}, {}, None, None, None
    if range_model != "none" and lidar_views:
        lidar_views, solution, range_models, pins, placing = with_range_terms(
            rig, lidar_views, lidar_obs, pair_frames, solution, alone_fit.term_choices, range_model,
            alone_fit.board_scatter, options.range_accuracy_m, warnings,
            lambda views: solve_rig(names, rig.reference, camera_views, views, T_ref, T_ref_board, refine_intrinsics))
    for n, s in solution.noise_scale.items():
        ss, dof = solution.chi2_dof[n]
        if s > 1.0 and chi2.sf(ss, dof) < NOISE_WARNING_P:
            hint = ("; a camera whose corners disagree this much with the rest of the rig may have wrong intrinsics "
                    "(--refine-intrinsics estimates them with the rig)" if n in cameras and not refine_intrinsics
                    and s > 2.0 else "")
            warnings.append(f"{n}: its factors disagree beyond their noise (chi-square {ss:.0f} on {dof:.0f} dof): its "
                            f"noise is scaled by {s:.2f}{hint}")
    edge_records: dict = {}
    conflict = None
    edged = {lv.name for lv in lidar_views if edges or edges is None and rig.board.size_known}
    if edges and not rig.board.size_known:
        warnings.append("--edges: the board's size is not in dataset.yaml (board.size): planes alone")
    elif edged and rig.board.size_known:
        lidar_views, solution, edge_records, conflict = with_edges(rig, names, camera_views, lidar_views, lidar_obs,
                                                                   solution, T_ref, T_ref_board, refine_intrinsics,
                                                                   edged, default=edges is None,
                                                                   pair_frames=alone_fit.pair_frames)
        for name, record in edge_records.items():
            if record.get("left_out"):
                warnings.append(f"{name}: {left_out_warning(record['left_out'])}")
            warnings.extend(f"{name}: {w}" for w in edge_warnings(record))
            if (said := conflict_words(record)) is not None:
                warnings.append(f"{name}: {said}: the covariance holds both answers (the planes' and the "
                                "edges' own, each added along its offset); the planes-only pose is in "
                                "calibration.json (board_edges)")
        if not edge_records and edges:
            warnings.append("--edges: no LiDAR's board shows ends on the board's outline (or the graph with them "
                            "could not be solved): planes alone")
    if pins:  # after every solve: the held terms' prior propagated into the covariance, as the pair's
        solution, pinned_share = with_held_share(names, rig.reference, camera_views, lidar_views, solution, pins)
    if placing is not None:  # then the black squares' placement, as the pair's refinement ends
        solution, placement_share = with_placement_share(
            rig, names, camera_views, lidar_views, lidar_obs, pair_frames, solution, placing, options.range_accuracy_m,
            pins)
    weak_share = weak_offset_share(names, range_models)  # an offset half supported, not taken
    if weak_share is not None:
        solution = replace(solution, covariance_joint=solution.covariance_joint + weak_share)
    stated_share = None  # intrinsics held at uncertain values (dataset.yaml's param_std, or calibrated from the images)
    if not refine_intrinsics:
        stated_share = held_intrinsics_share(names, rig.reference, camera_views, lidar_views, solution, options)
        if stated_share is not None:
            solution = replace(solution, covariance_joint=solution.covariance_joint + stated_share)
    for lv in lidar_views:
        if lv.has_terms:
            range_record(range_models[lv.name], lv.terms, *solution.range_terms[lv.name], warnings, lv.name)
    if refine_intrinsics and solution.intrinsics:  # each pair's boards as the refined intrinsics see them
        pair_frames = {(c, d): reobserve_frames(frames, rig.board, solution.camera_model(c, cameras[c]))
                       for (c, d), frames in pair_frames.items()}
    outline_checks = pairs_outline_checks(rig, names, camera_views, lidar_views, solution, pair_frames, warnings)
    test = None
    if refine_intrinsics and solution.intrinsics:
        own = float(np.nansum([own_corner_drop(cv) for cv in camera_views if cv.name in solution.intrinsics]))
        test = intrinsics_test(solve_rig(names, rig.reference, camera_views, lidar_views, T_ref, T_ref_board, False),
                               solution, own)
        if not test["lowers_disagreement"]:  # said first: the refined intrinsics are then not to be used
            warnings.insert(0, f"refining the intrinsics did not lower the rig's disagreement beyond what "
                               f"{test['parameters']} freed parameters fit (chi-square "
                               f"{test['chi_square_given']:.0f} -> {test['chi_square_refined']:.0f} on "
                               f"{test['dof']:.0f} dof, {test['own_corners_drop']:.0f} of the drop on the cameras' "
                               f"own corners alone; F test of the rest p = {test['p_value']:.2g}): the other sensors "
                               "do not confirm them; keep the given intrinsics (calibrate without --refine-intrinsics) "
                               "unless a calibration made for the cameras confirms the refined ones")
    t_joint = time.perf_counter()
    if on_solved is not None:
        on_solved(alone_fit.results)
    advice_rng = np.random.default_rng(rng.integers(2**32))  # the advice does not depend on the sampling
    posterior = None
    if samples > 0:
        sampled, views, intrinsics_share = solution, camera_views, None
        if refine_intrinsics and solution.intrinsics:
            sampled, views, intrinsics_share = _at_refined_intrinsics(names, rig.reference, camera_views, lidar_views,
                                                                      solution, (pinned_share, conflict,
                                                                                 placement_share, weak_share))
        try:
            posterior = mixed_posterior(
                sampled, mixable_minima(alone_fit.minima, lidar_obs, pair_frames),
                minimum_solver(sampled, views, lidar_views, alone_fit.with_ends, rig.board, lidar_obs),
                lambda sol, lvs, cells: sample_rig_posterior(sol, views, lidar_views if lvs is None else lvs, rng,
                                                             min_ess=samples, likelihood=likelihood, cells=cells,
                                                             exact_ends=alone_fit.with_ends,
                                                             ensemble=sampler == "ensemble"), rng, warnings)
        except PosteriorSkippedError as exc:
            warnings.append(f"the rig's posterior was not sampled ({exc.message}): the covariance is the graph's")
        # The held terms' prior, the planes' conflict with the edges, the black squares' placement, an offset half
        # supported and the intrinsics' uncertainty (refined, or held at uncertain values), convolved in (first
        # order, Gaussian).
        for share in (s for s in (pinned_share, conflict, placement_share, weak_share, intrinsics_share, stated_share)
                      if s is not None and posterior is not None):
            posterior = replace(posterior, xi=posterior.xi + rng.multivariate_normal(
                np.zeros(len(share)), share, len(posterior.xi), method="eigh"))
        if posterior is not None and not posterior.run.converged:
            warnings.append(f"the rig's posterior did not converge in {posterior.run.chain.shape[0]} steps "
                            f"({posterior.run.ess:.0f} effective samples): its intervals are rough")
    t_post = time.perf_counter()
    result = RigResult(rig, solution, cameras, pairwise, {}, skipped, (), {}, pair_frames, dict(links), None,
                       tuple(camera_views), tuple(lidar_views))
    for a, b in result.pairs() if posterior is not None else ():
        note = heavy_tails(posterior.pair_samples(a, b), what=f"T_{a}_{b} posterior")
        if note is not None:
            warnings.append(note)
    warnings[:0] = unobservable_scanners(replace(result, posterior=posterior), {lv.name for lv in lidar_views
                                                                                if lv.edges})
    next_pose = rig_next_pose(result, advice_rng) if advise else None
    used = {c.name: tuple(c.corners_px) for c in camera_views}
    used.update({lv.name: tuple(lv.W) for lv in lidar_views})
    timings = {**stages, "measurements": t_meas - t0, "pairs": t_pairs - t_meas, "joint": t_joint - t_pairs}
    if posterior is not None:
        timings["posterior"] = t_post - t_joint
    if advise:
        timings["next_pose"] = time.perf_counter() - t_post
    result = RigResult(rig, solution, cameras, pairwise, used, skipped, tuple(warnings),
                       {k: round(v, 3) for k, v in timings.items()}, pair_frames, dict(links), posterior,
                       tuple(camera_views), tuple(lidar_views), next_pose, range_models, outline_checks, edge_records,
                       measured, ambiguous, test, alone_fit.intrinsics_checks, alone_fit.results)
    return _with_time_offset(result, rng)


def _with_time_offset(result: RigResult, rng: np.random.Generator) -> RigResult:
    """Still poses with the board's motion between them: each 3D LiDAR's clock offset against the camera that
    followed the board, read at the poses' estimate (``pipeline.offset_between_poses``): a pair folder's from its
    ``motion.npz``, a rig's from each LiDAR's folder's (``RIG/lidar0/motion.npz``, the first camera's corners:
    ``io.rig_bag_extract``). The result as it was otherwise."""
    from .io.motion_track import FOLLOWED_CAMERA, has_motion

    rig = result.rig
    pair = len(rig.cameras) == 1 and len(rig.lidars) == 1
    camera = rig.cameras[0] if pair else next((c for c in rig.cameras if c.name == FOLLOWED_CAMERA), None)
    folders = {lid.name: rig.root if pair else rig.root / lid.name for lid in rig.lidars if lid.lidar == "3d"}
    folders = {n: f for n, f in folders.items() if has_motion(f)}
    if not folders or camera is None:
        return result
    from .pipeline.offset_between_poses import offset_between_poses  # here: it loads scipy's splines and optimizer

    t0 = time.perf_counter()
    offsets = {}
    for name, folder in folders.items():
        p = result.pair(camera.name, name)
        offsets[name] = offset_between_poses(folder, rig.board, camera.camera, p.T, p.covariance, rng)
    return replace(result, time_offsets={n: o for n, o in offsets.items() if o is not None},
                   timings_s={**result.timings_s, "time_offset": round(time.perf_counter() - t0, 3)})


def _at_refined_intrinsics(names: tuple, reference: str, camera_views: list, lidar_views: list, solution, shares
                           ) -> tuple:
    """What a rig's posterior is sampled from when its intrinsics were refined (the intrinsics are not sampled): the
    graph solved again with every camera at its refined intrinsics, held; those views; and the intrinsics' share of
    the sensors' joint covariance, the joint graph's (``shares``, the covariances already added to it, taken out)
    less the held graph's, which the samples are convolved with."""
    views = [replace(c, camera=solution.camera_model(c.name, c.camera)) for c in camera_views]
    held = solve_rig(names, reference, views, lidar_views, solution.T_ref, solution.T_ref_board, False)
    free = solution.covariance_joint - sum(s for s in shares if s is not None)
    ev, V = np.linalg.eigh(0.5 * (free - held.covariance_joint + (free - held.covariance_joint).T))
    return held, views, (V * np.maximum(ev, 0.0)) @ V.T


def edge_warnings(record: dict) -> list[str]:
    """What a LiDAR's board-edges record with the edges used warns of, as a single pair's does
    (``outline_check.outline_warnings``): its outlines' mean shift, its sides' growth and its outline's offset
    beyond their limits, and the planes alone's outlines beside them (with its first camera)."""
    from .solvers.outline_check import outline_warnings

    if not record.get("used") or "mean_shift_dof" not in record:
        return []
    out = outline_warnings(record, used=True)
    if record.get("planes_only_check"):
        out += [f"with {record['planes_only_camera']}: {w}"
                for w in outline_warnings(record["planes_only_check"], used=False, beside_edges=True)]
    return out


def unobservable_scanners(result: RigResult, edged: set) -> list[str]:
    """A warning for each camera-scanner pair whose transform the rig leaves nearly unobservable, as a single
    pair's answer would be refused (``refusal.scan_refusal``): its posterior's spread beyond
    ``POSTERIOR_REFUSAL_FACTOR`` times the limits when sampled, else the graph's covariance beyond them. The rest
    of the rig stands; that pair's transform is not an answer. ``edged``: the LiDARs whose ends are in the graph
    (found on their boards, not merely asked for)."""
    out = []
    for c in result.rig.cameras:
        for d in result.rig.lidars:
            if d.lidar != "2d" or d.name not in result.solution.names:
                continue
            pair = result.pair(c.name, d.name)
            cov = pair.covariance
            if pair.samples is not None and result.posterior.mode_index is not None:  # the estimate's minimum's
                cov = np.cov(pair.samples[result.posterior.mode_index == 0], rowvar=False)
            weak = scan_refusal(cov, pair.T, (result.links or {}).get((c.name, d.name), 0), d.name in edged,
                                POSTERIOR_REFUSAL_FACTOR if pair.samples is not None else 1.0)
            if weak is not None:
                out.append(f"T_{c.name}_{d.name}: {'sampled, ' if pair.samples is not None else ''}{weak.problem}: "
                           f"not an answer, though the rest of the rig stands; {weak.hint}")
    return out


def rig_next_pose(result: RigResult, rng: np.random.Generator, candidates: int = 60) -> dict | None:
    """The board pose that most lowers the weakest camera-LiDAR pair's largest translation standard deviation
    (``analysis.rig_layout.pair_next_pose``), with ``pair``, ``camera`` and ``lidar``; None without a weakest pair
    or a feasible pose."""
    from .analysis.rig_layout import pair_next_pose

    weakest = result.layout()["weakest_pair"]
    if weakest is None:
        return None
    cam, lid = next((c.name, d.name) for c in result.rig.cameras for d in result.rig.lidars
                    if f"T_{c.name}_{d.name}" == weakest)
    return pair_next_pose(result, cam, lid, result.solution.transform(cam, lid)[1], rng, candidates)


def pair_guess(rig: RigDataset, hints: Hints) -> Hints:
    """``hints`` with a two-sensor rig's initial guess (one ``T_camera_lidar``) as its one camera-LiDAR pair's."""
    if hints.initial_guess is None or len(rig.cameras) != 1 or len(rig.lidars) != 1:
        return hints
    name = f"T_{rig.cameras[0].name}_{rig.lidars[0].name}"
    return replace(hints, initial_guess=None, pair_guesses={name: hints.initial_guess})


def calibrate(dataset, init: str = "closed-form", refine: str = "factor-graph", rng: np.random.Generator | None = None,
              params: SegmentationParams = SegmentationParams(), options: RefinementOptions = RefinementOptions(),
              posterior: PosteriorOptions | None = PosteriorOptions(), use_extent: bool | None = None,
              samples: int | None = None, hints: Hints = Hints(), cache: bool = False) -> RigResult:
    """The Python API's calibration, by the engine the command line runs (:func:`calibrate_rig`): a rig folder, or a
    pair folder (a loaded :class:`~estimators.io.dataset.Dataset`, or its frames measured: ``measure``'s
    :class:`~estimators.io.measurement_store.Measurements`) as the rig of ``cam0`` and ``lidar0``. Its arguments
    are the pair's own solve's (``calibrate_pair``).

    Parameters
    ----------
    dataset : Dataset, RigDataset, Measurements, str or Path
        A folder, or one loaded (a Dataset's camera model, replaced in memory, is the one used), or a pair's frames
        measured (solved without measuring again; frames simulated at the measurement level alike).
    init : str
        A 2D scanner's start: ``closed-form`` (for a scanner, ``minimal-lower-bound``) or ``minimal-min-residual``.
    refine : str
        ``factor-graph``; the closed form alone (``none``) is the pair's own solve's: ``estimators.solve(
        estimators.measure(dataset, rng), refine="none")``.
    rng : numpy.random.Generator, optional
        Drives the board segmentation's random draws and the sampler; a fixed seed when None, so runs repeat.
    params : SegmentationParams
        The LiDAR board search's settings.
    options : RefinementOptions
        The graph's settings; its ``range_model``, ``edges`` and ``refine_intrinsics`` are the engine's.
    posterior : PosteriorOptions or None
        The sampler's effective samples (``min_ess``), likelihood and sampler; None skips sampling.
    use_extent : None
        The pair's own 2D solve's option; the engine drops a scanner's minimal solutions whose segments leave the
        boards' outlines whenever the board's size is known.
    samples : int, optional
        Effective posterior samples (0: none); overrides ``posterior``'s.
    hints : Hints
        A region of interest; a pair's ``initial_guess`` is that of its camera-LiDAR pair.
    cache : bool
        Keep and reuse the measurements (under the user's cache folder).

    Returns
    -------
    RigResult
        Every sensor's pose, one joint covariance and posterior; ``result.pair("cam0", "lidar0")`` gives a pair, and
        for a pair folder ``result.T_camera_lidar``, ``result.covariance`` and ``result.samples`` give it directly.
    """
    from .io.dataset import Dataset
    from .io.measurement_store import Measurements, pair_as_rig
    from .io.rig_dataset import load_rig

    import os

    for name, value, kinds in (("dataset", dataset, (Dataset, RigDataset, Measurements, str, os.PathLike)),
                               ("rng", rng, (np.random.Generator, type(None))), ("params", params, SegmentationParams),
                               ("options", options, RefinementOptions),
                               ("posterior", posterior, (PosteriorOptions, type(None))), ("hints", hints, Hints)):
        if not isinstance(value, kinds):  # a wrong type named here, not as an attribute missing deep inside
            wanted = " or ".join("None" if k is type(None) else "a folder" if k is os.PathLike else k.__name__
                                 for k in (kinds if isinstance(kinds, tuple) else (kinds,)) if k is not str)
            raise TypeError(f"calibrate: {name} must be {wanted}, got {type(value).__name__}")
    if refine != "factor-graph":
        raise ValueError(f"refine {refine!r}: the engine refines in the factor graph; the closed form alone is "
                         "estimators.solve(estimators.measure(dataset, rng), refine='none')")
    if use_extent is not None:
        raise ValueError("use_extent is the pair's own 2D solve's option (calibration.calibrate_pair); the engine "
                         "uses the boards' outlines whenever the board's size is known")
    given = pair_as_rig(dataset) if isinstance(dataset, Measurements) else None
    rig = dataset if isinstance(dataset, RigDataset) else RigDataset.of_measurements(dataset) if given else \
        RigDataset.of_pair(dataset) if isinstance(dataset, Dataset) else load_rig(dataset)
    if samples is None:
        samples = 0 if posterior is None else posterior.min_ess
    sampling = posterior if posterior is not None else PosteriorOptions()
    return calibrate_rig(rig, np.random.default_rng(0) if rng is None else rng, samples=max(int(samples), 0),
                         refine_intrinsics=options.refine_intrinsics, range_model=options.range_model,
                         edges=options.edges, options=options, cache=cache, init=init, params=params,
                         hints=pair_guess(rig, hints), measurements=given, likelihood=sampling.likelihood,
                         sampler=sampling.sampler)
