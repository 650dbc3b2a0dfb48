"""A camera-LiDAR pair's own solve: a dataset measured (``pipeline.measurement``), solved (closed form or minimal
solutions, the factor graph; under the given intrinsics, no posterior) into its result (``pipeline.result``). It
starts each camera-LiDAR pair of the engine (``rig_calibration``), gives ``--refine none``, and is kept as
``calibrate_pair`` for the studies and benchmark pages that measured it; ``estimators.calibrate`` is the engine's
(its posterior, refined intrinsics)."""
from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

from geometry.camera import CameraModel

from .errors import DatasetError, DegenerateLayoutError, LidarcamError
from .io.dataset import Dataset, load_dataset
from .io.measurement_store import Measurements, cache_dir
from .lidar.board_segmentation import SegmentationParams
from .measurements import FrameMeasurement
from .pipeline.measurement import CONSENSUS_FAILED, Hints, measure
from .pipeline.result import CalibrationResult
from .pipeline.verdict import frame_disagrees, plane_residuals, returns_without_terms
from .solvers.closed_form import (MIRROR_CAUSE, MIRROR_HINT, describe_direction, mirrored, normal_spread,
                                  solve_closed_form)
from .solvers.intrinsics_refinement import intrinsics_drop
from .solvers.posterior import PosteriorOptions
from .solvers.refinement import refine as refine_graph
from .solvers.refinement_options import RefinementOptions

INITS = ("closed-form", "minimal-lower-bound", "minimal-min-residual")
REFINES = ("factor-graph", "none")
# ``lidarcam calibrate --strict`` exits with this code when the answer is ambiguous or contradicted.
EXIT_AMBIGUOUS = 3


@threadpool_limits.wrap(limits=1, user_api="blas")  # as the command line runs (rig_calibration.calibrate_rig)
def calibrate_pair(dataset: Dataset | str | Path, init: str = "closed-form", refine: str = "factor-graph",
                   rng: np.random.Generator | None = None, params: SegmentationParams = SegmentationParams(),
                   options: RefinementOptions = RefinementOptions(),
                   posterior: PosteriorOptions | None = None, use_extent: bool | None = None,
                   samples: int | None = None, hints: Hints = Hints(), cache: bool = False) -> CalibrationResult:
    """The pair's own solve of a dataset: ``T_camera_lidar`` and its Laplace covariance (``estimators.calibrate``
    gives the engine's, which starts from this, with its posterior).

    Measures every frame (the board in each image and scan), solves in closed form (3D) or by the minimal
    solutions (2D) and refines in the factor graph.

    Parameters
    ----------
    dataset : Dataset, str or Path
        A loaded :class:`Dataset` or its folder.
    init : str
        ``closed-form`` (3D; for a 2D LiDAR it means ``minimal-lower-bound``), ``minimal-lower-bound`` or
        ``minimal-min-residual`` (2D).
    refine : str
        ``factor-graph`` or ``none`` (the initial solution, without covariance).
    rng : numpy.random.Generator, optional
        Drives the board segmentation's RANSAC; a fixed seed when None, so runs repeat.
    params : SegmentationParams
        The LiDAR board segmentation's settings.
    options : RefinementOptions
        The factor graph's noise, robust loss, range model and edges (refined intrinsics are the engine's:
        ``refine_intrinsics`` is refused with a ValueError).
    posterior : None
        The posterior is the engine's (``estimators.calibrate``); a request here is refused (:func:`_no_posterior`).
    use_extent : bool, optional
        2D only: drop minimal solutions whose laser segments leave the boards' outlines (default: when the board
        size is known).
    samples : int, optional
        0 or None: the engine samples the posterior.
    hints : Hints
        An initial guess and a region of interest, for scenes beyond automation.
    cache : bool
        Keep and reuse the measurements (see :func:`measure`).

    Returns
    -------
    CalibrationResult
        The estimate, its covariance, every frame's measurements and the warnings.

    Raises
    ------
    LidarcamError
        A missing or corrupt file (:class:`~estimators.errors.DatasetError`), or too few usable frames or a
        degenerate layout (:class:`~estimators.errors.DegenerateLayoutError`). Frames that cannot be used are
        skipped with their reason instead.

    Examples
    --------
    >>> import estimators as lc
    >>> result = lc.calibrate_pair(lc.simulate("/tmp/sim", n_poses=8, seed=1))  # doctest: +SKIP
    >>> result.std_rotation_deg, result.std_translation_mm  # doctest: +SKIP
    """
    _check_methods(init, refine)
    _no_posterior(posterior, samples)
    _no_intrinsics(options)
    if not isinstance(dataset, Dataset):
        dataset = load_dataset(dataset)
    if dataset.lidar == "3d" and init != "closed-form":
        raise DatasetError(f"init {init!r} is for 2D LiDAR datasets", path=dataset.yaml_path,
                           hint="use --init closed-form for lidar: 3d")
    rng = np.random.default_rng(0) if rng is None else rng
    if options.range_accuracy_m is None:  # the dataset's, or its LiDAR family's (an explicit option wins)
        options = replace(options, range_accuracy_m=dataset_range_accuracy(dataset))
    # One bound on the sensors' separation: the board search's (``params``) also bounds the 2D solutions.
    options = replace(options, max_sensor_separation_m=params.max_sensor_separation_m)
    timings: dict = {}
    t_start = time.perf_counter()
    m = measure(dataset, rng, params, hints, cache=cache, timings=timings)
    camera, frames, warnings = m.camera, list(m.frames), list(m.warnings)
    if m.source == "cache":
        warnings.append(f"measurements taken from the cache ({cache_dir() / m.key[:16]}...): images and scans were "
                        "not read again")
    try:
        result = solve(frames, dataset.board, camera, init, refine, options, name=str(dataset.root),
                       warnings=warnings, timings=timings, use_extent=use_extent)
    except DegenerateLayoutError as exc:
        skipped = [f"{f.name}: {f.reason}" for f in frames if not f.usable]
        detail = f" (skipped: {'; '.join(skipped)})" if skipped else ""
        raise DegenerateLayoutError(exc.problem + detail, path=dataset.root, hint=exc.hint) from exc
    timings["total_wall"] = time.perf_counter() - t_start
    return replace(result, timings_s={k: round(v, 4) for k, v in timings.items()}, measurements_source=m.source)


def dataset_range_accuracy(dataset: Dataset) -> float:
    """The LiDAR's range accuracy (m) for the range model's priors: dataset.yaml's ``lidar.range_accuracy_m``,
    else its family's default (``solvers.range_model.RANGE_ACCURACY_M``), else the conservative default."""
    from .solvers.range_model import range_accuracy_for

    return dataset.range_accuracy_m if dataset.range_accuracy_m is not None else range_accuracy_for(
        dataset.lidar_family)


def _check_methods(init: str, refine: str) -> None:
    if init not in INITS:
        raise ValueError(f"Expected init in {INITS}, got {init!r}")
    if refine not in REFINES:
        raise ValueError(f"Expected refine in {REFINES}, got {refine!r}")


def solve(frames: list[FrameMeasurement] | Measurements, board=None, camera: CameraModel | None = None,
          init: str = "closed-form", refine: str = "factor-graph", options: RefinementOptions = RefinementOptions(),
          name: str = "", warnings: list[str] | None = None, timings: dict | None = None,
          posterior: PosteriorOptions | None = None, rng: np.random.Generator | None = None,
          use_extent: bool | None = None, samples: int | None = None, memo: dict | None = None
          ) -> CalibrationResult:
    """The pair's own solver stage alone, on measured frames: initial solution and factor graph (the posterior is
    the engine's: ``estimators.calibrate`` takes measured frames too).

    Parameters
    ----------
    frames : Measurements or list of FrameMeasurement
        From :func:`measure` or :func:`load_measurements` (then ``board`` and ``camera`` come with them), or a list
        of frames with ``board`` and ``camera`` given.
    board : BoardModel, optional
        The board, with a list of frames.
    camera : CameraModel, optional
        The camera model, with a list of frames.
    init, refine : str
        As for :func:`calibrate`.
    options : RefinementOptions
        The factor graph's settings (``refine_intrinsics`` is the engine's: refused with a ValueError).
    name : str
        The dataset's name in the result.
    warnings : list of str, optional
        Warnings from measuring, carried into the result.
    timings : dict, optional
        Stage times (s) so far, carried into the result.
    posterior : None
        The posterior is the engine's (``estimators.calibrate`` takes measured frames); a request here is refused.
    rng : numpy.random.Generator, optional
        Unused: the pair's own solve draws nothing at random.
    samples : int, optional
        0 or None (a request for samples is refused, as ``posterior``).
    use_extent : bool, optional
        As for :func:`calibrate_pair`.
    memo : dict, optional
        A 3D LiDAR's range-term choices made before (``solvers.choice_memo``): replayed where the refinement's
        inputs are the same, and filled with the choices made here.

    Returns
    -------
    CalibrationResult

    Raises
    ------
    DegenerateLayoutError
        Too few usable frames, or board normals that do not determine the transform.

    Examples
    --------
    >>> m = lc.measure("/tmp/sim")                                           # doctest: +SKIP
    >>> a = lc.solve(m, refine="none"); b = lc.solve(m)                      # doctest: +SKIP
    """
    if isinstance(frames, Measurements):
        m = frames
        result = solve(list(m.frames), m.board, m.camera, init, refine, options, name or m.dataset,
                       list(m.warnings) + list(warnings or []), timings, posterior, rng, use_extent, samples, memo)
        return replace(result, measurements_source=m.source)
    if board is None or camera is None:
        raise ValueError("solve needs board and camera with a list of frames (or a Measurements)")
    _no_posterior(posterior, samples)
    _check_methods(init, refine)
    _no_intrinsics(options)
    warnings = list(warnings or [])
    timings = {} if timings is None else timings
    used = [f for f in frames if f.usable]
    scan_lines = any(f.lidar is not None and f.lidar.is_scan_line for f in frames)
    if init.startswith("minimal") and not scan_lines and any(f.lidar is not None for f in frames):
        raise LidarcamError(f"init {init!r} is for 2D LiDAR datasets; these frames hold a 3D LiDAR's boards",
                            hint="use init closed-form")
    if scan_lines or init.startswith("minimal"):
        return _solve_2d(frames, board, camera, init, refine, options, name, warnings, timings, use_extent)
    t0 = time.perf_counter()
    _not_mirrored(used)
    # A weak layout is refused by the closed form alone, but only starts the factor graph, which judges
    # what the full model determines (and names what it does not).
    try:
        sol = solve_closed_form([f.camera.plane for f in used], [f.lidar.plane for f in used],
                                allow_weak=refine == "factor-graph")
    except DegenerateLayoutError as exc:
        # Frames skipped as ambiguous because the frames' joint choice failed: the error says why it failed.
        failed = [w for w in warnings if w.startswith(CONSENSUS_FAILED)]
        if not failed:
            raise
        raise DegenerateLayoutError(f"{exc.problem}; {failed[0]}", path=exc.path, hint=exc.hint) from exc
    timings["solve"] = time.perf_counter() - t0
    T, ref = sol.T_camera_lidar, None
    if refine == "factor-graph":
        t0 = time.perf_counter()
        ref = refine_graph(used, board, camera, T, options, memo)
        timings["refine"] = time.perf_counter() - t0
        T = ref.T_camera_lidar
        warnings += ref.warnings
    tail = []  # the warnings after the refinement's
    if sol.condition_number > 10:
        axis, advice = describe_direction(sol.weakest_direction_camera)
        tail.append(f"board normals are poorly spread (condition {sol.condition_number:.1f}): "
                    f"translation along {axis} is weakly constrained; {advice}")
    dropped = {f.name for f in ref.frames if f.dropped} if ref else set()
    kept = [f for f in used if f.name not in dropped]
    residuals = plane_residuals(T, kept, returns_without_terms(kept, ref.range_model, None, board, T) if ref else None)
    for fname, (angle, dist) in residuals.items():
        if frame_disagrees(angle, dist):
            tail.append(f"frame {fname}: its planes disagree with the estimate by {np.degrees(angle):.1f} deg "
                        f"and {1000 * dist:.0f} mm; check that the right LiDAR segment was taken as the board")
    tail += [f"frame {f.name}: {f.reason}" for f in frames if not f.usable]
    check = None
    if ref is not None and options.checks:  # do the intrinsics explain the planes' disagreement? (two solves)
        check = intrinsics_drop(used, board, camera, ref, options)
    return CalibrationResult(T, init, refine, tuple(frames), camera, sol.normal_singular_values,
                             sol.weakest_direction_camera, name, tuple(warnings + tail),
                             {k: round(v, 4) for k, v in timings.items()}, residuals, ref, intrinsics_check=check)


def _not_mirrored(used: list[FrameMeasurement]) -> None:
    """Refuse a 3D LiDAR whose boards fit the camera's through a mirror (``closed_form.mirrored``): no rotation,
    and so no extrinsic, can be right for its points."""
    fit = mirrored([f.camera.plane for f in used], [f.lidar.plane for f in used])
    if fit is not None:
        raise DatasetError(f"the LiDAR's boards match the camera's through a mirror, not a rotation (their normals "
                           f"{fit[1]:.1f} deg apart reflected, {fit[0]:.1f} deg turned): {MIRROR_CAUSE}",
                           hint=MIRROR_HINT)


def _no_posterior(posterior: PosteriorOptions | None, samples: int | None) -> None:
    """The pair's own solve draws no posterior: a request for one is refused with where it is (the engine's)."""
    if posterior is not None or (samples or 0) > 0:
        raise ValueError("the pair's own solve draws no posterior: the engine samples it (estimators.calibrate("
                         "dataset or measurements, samples=N), as lidarcam calibrate does)")


def _no_intrinsics(options: RefinementOptions) -> None:
    """The pair's own solve refines no intrinsics: a request is refused with where it is (the engine's)."""
    if options.refine_intrinsics:
        raise ValueError("the pair's own solve does not refine the intrinsics: the engine does (estimators.calibrate("
                         "dataset or measurements, options=RefinementOptions(refine_intrinsics=True)), as lidarcam "
                         "calibrate --refine-intrinsics)")


def _solve_2d(frames: list[FrameMeasurement], board, camera: CameraModel, init: str, refine: str,
              options: RefinementOptions, name: str, warnings: list[str], timings: dict,
              use_extent: bool | None = None) -> CalibrationResult:
    """2D LiDAR: candidates from the minimal solutions of all board triples (``solution_selection``), each
    refined by the factor graph; the least refined cost wins, and near-equal distinct minima are reported."""
    from .solvers.solution_selection import select_and_refine, select_minimal  # 2D only

    method = "minimal-lower-bound" if init == "closed-form" else init
    t0 = time.perf_counter()
    if refine == "none":
        sel = select_minimal([f for f in frames if f.usable], board, method, use_extent,
                             options.max_sensor_separation_m)
        timings["solve"] = time.perf_counter() - t0
    else:  # the boards skipped as ambiguous in their orientation may be used with the tilt the laser decides
        frames, sel, ref, modes, notes = select_and_refine(frames, board, camera, method, options, use_extent)
        warnings += notes
        timings["solve"] = sel.seconds
        timings["refine"] = time.perf_counter() - t0 - sel.seconds
    used = [f for f in frames if f.usable]
    if sel.degenerate_triples:
        warnings.append(f"{len(sel.degenerate_triples)} of {sel.n_triples} board triples are degenerate and give "
                        f"no solution (first: {sel.degenerate_triples[0]})")
    if sel.weak_triples:
        warnings.append(f"{len(sel.weak_triples)} of {sel.n_triples} board triples are ill-conditioned and were "
                        f"solved anyway (first: {sel.weak_triples[0]})")
    if sel.fallback:
        why = (f" that could be the rig ({sel.n_unphysical} put the LiDAR behind a board, a segment behind the "
               f"camera, or the sensors more than {sel.max_separation_m:g} m apart)"
               if sel.n_unphysical and sel.max_separation_m is not None else "")
        warnings.append(f"no board triple gave a minimal solution{why}: the candidates come from a multi-start "
                        "search over rotations seeded by the camera's board planes")
    spread, weak = normal_spread(np.array([f.camera.plane.normal for f in used]))
    if refine == "none":
        T = sel.candidates[0].T_camera_lidar
        ref, modes = None, ()
    else:
        T = ref.T_camera_lidar
        warnings += ref.warnings
        if len(modes) > 1:
            warnings.append(f"ambiguous: {len(modes)} distinct solutions fit the boards (posterior mass "
                            f"{', '.join(f'{m.mass:.0%}' for m in modes)}; the first is reported, all are in "
                            "calibration.json); add boards tilted in other directions to decide")
    residuals = plane_residuals(T, used, returns_without_terms(used, ref.range_model, None, board, T) if ref else None)
    tail = [f"frame {f.name}: {f.reason}" for f in frames if not f.usable]
    return CalibrationResult(T, method, refine, tuple(frames), camera, spread, weak, name, tuple(warnings + tail),
                             {k: round(v, 4) for k, v in timings.items()}, residuals, ref, sel, tuple(modes))
