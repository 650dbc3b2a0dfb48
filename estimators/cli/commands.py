"""The command line's commands, each from parsed arguments to printed and written results and an exit code."""
from __future__ import annotations

import contextlib
import sys
from pathlib import Path

from ..errors import DatasetError, LidarcamError, about
from .parser import board_argument, hints, refinement_options, study_spec_parser
from .printing import export_hint, print_result, print_rig, print_truth, source_words


def calibrate_command(args) -> int:
    """A rig folder, or a pair folder (the rig of ``cam0`` and ``lidar0``), through the one engine
    (``rig_calibration``); a pair folder's ``--refine none`` (the closed form alone) through the pair's."""
    from ..io.dataset import load_dataset
    from ..io.motion_track import is_moving_dataset
    from ..io.rig_dataset import is_rig

    if args.targetless:
        if args.scene:
            raise LidarcamError("--scene joins the scene's term to the boards' and --targetless has no boards",
                                path=args.dataset, hint="give one of the two")
        return _calibrate_targetless(args)
    if args.scene and args.refine == "none":
        raise LidarcamError("--scene is taken by a calibration refined in the graph, not --refine none",
                            path=args.dataset, hint="calibrate without --scene")
    if args.keep_board:
        raise LidarcamError("--keep-board is taken by --targetless only", path=args.dataset,
                            hint="calibrate without it")
    if is_moving_dataset(args.dataset):
        return _calibrate_moving(args)
    if args.time_offset is not None:
        raise LidarcamError("--time-offset is taken by a moving board's recording (motion.npz), and this folder "
                            "holds still poses", path=args.dataset, hint="calibrate without it")
    if is_rig(args.dataset) or args.refine != "none":
        return _calibrate_rig(args)
    return _closed_form_only(args, load_dataset(args.dataset))


def _calibrate_targetless(args) -> int:
    """``--targetless``: the scene's extrinsic refined from ``--initial-guess`` (``pipeline.targetless``), printed
    verdict first; calibration.json and report.html (the check's page: contours under the guess and the estimate)
    written into ``--out``."""
    from ..analysis.scene_check_page import write_check_page
    from ..io.output import write_json_atomic
    from ..io.rig_dataset import first_pair, is_rig
    from ..pipeline.measurement import given_camera, pair_from_calibration, parse_initial_guess
    from ..pipeline.targetless import calibrate_targetless
    from .printing import print_targetless

    if args.initial_guess is None:
        raise LidarcamError("--targetless refines an initial guess and none is given", path=args.dataset,
                            hint="add --initial-guess FILE (a calibration.json or a 4x4 T_camera_lidar) or "
                                 "'x y z roll pitch yaw'")
    sensors = first_pair(args.dataset) if is_rig(args.dataset) else None
    if sensors is not None and len(args.initial_guess) == 1:  # a rig's calibration.json: its first pair's
        T_guess = pair_from_calibration(args.initial_guess[0], *sensors)
    else:
        T_guess = parse_initial_guess(args.initial_guess)
    # a calibration's extrinsic refined under the intrinsics it was estimated with (refined or given), as check does
    camera = given_camera(args.initial_guess[0], sensors) if len(args.initial_guess) == 1 else None
    result = calibrate_targetless(args.dataset, T_guess, keep_board=args.keep_board, camera=camera)
    print_targetless(result)
    print(f"wrote {write_json_atomic(Path(args.out) / 'calibration.json', result.to_dict())}")
    if not args.no_report:
        print(f"wrote {write_check_page(result.scene, args.out, 'report.html', result, 'the initial guess')}")
    return 3 if args.strict and result.verdict.level == "UNTRUSTED" else 0


def _calibrate_rig(args) -> int:
    """A rig folder (``sensors:`` in dataset.yaml) or a pair folder: one graph for every sensor
    (``rig_calibration``). A pair folder's initial guess is its pair's, its earlier ``measurements.npz`` is taken
    as its rig's, and its output keeps the pair's files (calibration.json with every key of the pair's,
    measurements.npz beside the rig's measurements folder)."""
    import numpy as np

    from ..io.measurement_store import load_rig_measurements, pair_as_rig
    from ..io.rig_dataset import is_rig, load_rig
    from ..rig_calibration import calibrate_rig, pair_guess

    _refuse_what_a_rig_ignores(args)
    pair = not is_rig(args.dataset)
    rig = load_rig(args.dataset)
    given = None
    if args.measurements and pair and Path(args.measurements).is_file():
        m = _pair_measurements(args.measurements, rig.board, rig.lidars[0].lidar)
        given = pair_as_rig(m, rig.cameras[0].name, rig.lidars[0].name)
    elif args.measurements:
        given = load_rig_measurements(args.measurements)
    guide = pair_guess(rig, hints(args, rig=not pair))  # a pair's guess is its one camera-LiDAR pair's
    with _figures_ahead(not args.no_report) as figures:
        rng = np.random.default_rng(args.seed)
        scene_pairs = [(c.name, lid.name) for lid in rig.lidars if lid.lidar == "3d" for c in rig.cameras]
        if args.scene and not scene_pairs:
            raise LidarcamError("--scene takes a 3D LiDAR's sweeps, and this folder's LiDARs are 2D scanners",
                                path=args.dataset, hint="calibrate without --scene")
        with about(args.dataset):  # a solver's error names the folder it is about
            result = calibrate_rig(rig, rng, samples=args.samples, cache=not args.no_cache, measurements=given,
                                   hints=guide, on_solved=_draw_ahead(figures), **_rig_settings(args))
        if args.scene:
            from ..pipeline.scene_witness import with_scene

            for camera, lidar in scene_pairs:  # each camera with each 3D LiDAR, joined in turn
                result = with_scene(result, rng, camera, lidar)
        return _write_rig(args, rig, pair, _with_separating_poses(result), figures)


# The calibrate options a moving board's recording takes; the others are refused rather than ignored.
MOVING_TAKES = {"seed", "strict", "no_report", "time_offset", "samples"}


def _calibrate_moving(args) -> int:
    """A moving board's recording (``motion.npz``): the extrinsic and the clocks' offset together
    (``pipeline.moving_board``); calibration.json written and the result printed."""
    import numpy as np

    from ..io.output import write_json_atomic
    from ..io.rig_dataset import is_rig
    from ..pipeline.moving_board import calibrate_moving
    from ..pipeline.moving_rig import calibrate_moving_rig
    from .printing import print_moving

    _refuse_ignored(args, [f"--{k.replace('_', '-')}" for k in _given_options(args) if k not in MOVING_TAKES],
                    "a moving board's recording (motion.npz)", "calibrate without it")
    rig = is_rig(args.dataset)
    with about(args.dataset):
        result = (calibrate_moving_rig if rig else calibrate_moving)(args.dataset, np.random.default_rng(args.seed),
                                                                     args.time_offset, args.samples)
    path = write_json_atomic(Path(args.out) / "calibration.json", result.to_dict())
    print_moving(result)
    print(f"wrote {path}")
    if not args.no_report:
        from ..analysis.moving_report import write_moving_report, write_moving_rig_report

        page = write_moving_rig_report(result, args.out)[0] if rig else write_moving_report(result, args.out)
        print(f"wrote {page}")
    export_hint(path)
    return exit_code(args, result)


def _figures_ahead(report: bool):
    """The child that draws the report's matplotlib figures (``analysis.figure_process.FigureProcess``), started
    before the calibration so that it loads matplotlib meanwhile; nothing without a report."""
    if not report:
        return contextlib.nullcontext()
    from ..analysis.figure_process import FigureProcess

    return FigureProcess()


def _draw_ahead(figures):
    """``calibrate_rig``'s ``on_solved``: each camera-LiDAR pair's report figures started in the figure process
    while the posterior is sampled (None without one)."""
    if figures is None:
        return None
    from ..analysis.rig_report import draw_pairs_ahead

    return lambda links: draw_pairs_ahead(links, figures)


def _write_rig(args, rig, pair: bool, result, figures) -> int:
    """A rig's result written (calibration.json, its measurements, the report), printed, validated on request, and
    its exit code."""
    from ..io.measurement_store import rig_as_pair, save_measurements, save_rig_measurements
    from ..pipeline.rig_result import write_rig_calibration

    if args.split or args.cross_validate:  # frames too few for them: refused before anything is written or said
        from ..analysis.validation import refuse_runs

        with about(args.dataset):
            refuse_runs(len(result.measurements.stems), args.cross_validate or None, args.split or None)
    path = write_rig_calibration(result, args.out)
    print_rig(result)
    stored = save_rig_measurements(Path(args.out) / "measurements", result.measurements, rig.board,
                                   {s.name: s.lidar for s in rig.lidars})
    if pair:
        save_measurements(args.out, rig_as_pair(result.measurements, rig.board, rig.lidars[0].lidar, str(rig.root)))
    print(f"measurements: {source_words(result.measurements.source)}; wrote {stored.parent}"
          + (f" (and {Path(args.out) / 'measurements.npz'})" if pair else ""))
    print(f"wrote {path}")
    if args.split or args.cross_validate:
        _rig_validation_runs(args, rig, result)
    if not args.no_report:
        from ..analysis.rig_report import write_rig_report

        print(f"wrote {write_rig_report(result, args.out, figures)}")
        for (camera, lidar), w in result.scene.items():
            if w.check is not None:  # a rig's several pairs: a folder each
                from ..analysis.scene_check_page import write_check_page

                where = Path(args.out) / (f"scene_{camera}_{lidar}" if len(result.scene) > 1 else "")
                print(f"wrote {write_check_page(w.check, where, 'scene_check.html', given='the boards')}")
    if pair:
        export_hint(path)
    else:
        print(f"for ROS tf, URDF or OpenCV: lidarcam export {path} --format ros-tf|urdf|opencv-yaml")
    return exit_code(args, result)


def _with_separating_poses(result):
    """A rig's result with, for each camera-LiDAR pair whose range offset its own solve found confounded with the
    extrinsic, the board pose that best separates them in that record (``_with_separating_pose``), as a single
    pair's result has it."""
    from dataclasses import replace

    board = result.rig.board
    links = {k: _with_separating_pose(link, board) for k, link in (result.pair_results or {}).items()}
    return replace(result, pair_results=links)


def _rig_validation_runs(args, rig, result) -> None:
    """--split and --cross-validate K on a rig: subsets of its frames calibrated from the measurements already made
    (``analysis.validation.split_rig_halves``, ``cross_validate_rig``), validation.json written."""
    import numpy as np

    from ..analysis.validation import cross_validate_rig, split_rig_halves
    from ..io.output import write_json_atomic
    from ..rig_calibration import calibrate_rig

    def solve_subset(stems):
        return calibrate_rig(rig, np.random.default_rng(args.seed), samples=0, advise=False,
                             measurements=result.measurements.restricted(stems), **_rig_settings(args))

    out = {}
    if args.cross_validate:
        cv = out["cross_validation"] = cross_validate_rig(result.measurements, rig.board, args.cross_validate,
                                                          solve_subset)
        print(f"cross-validation ({cv['k']} folds), each camera-LiDAR pair's held-out frames:")
        for k, v in cv["pairs"].items():
            print(f"  {k}: {v['verdict']}" + (f" (chi-square {v['chi2']:.1f} on {v['dof']} dof, p = "
                                              f"{v['p_value']:.2g})" if "chi2" in v else ""))
    if args.split:
        sh = out["split_halves"] = split_rig_halves(result.measurements.stems, solve_subset, args.split)
        extra = (f" (squared Mahalanobis distance {sh['mahalanobis_d2']:.1f} on {sh['dof']} dof, 99% limit "
                 f"{sh['limit_99']:.1f})" if "mahalanobis_d2" in sh else "")
        print(f"split ({args.split}): {sh['verdict']}{extra}")
        for k, v in sh.get("pairs", {}).items():
            print(f"  {k}: {v['difference_rotation_deg']:.2f} deg, {v['difference_translation_mm']:.0f} mm apart "
                  f"(d2 {v['mahalanobis_d2']:.1f}, p = {v['p_value']:.2g})")
    print(f"wrote {write_json_atomic(Path(args.out) / 'validation.json', out)}")


def _rig_settings(args) -> dict:
    """The solver's settings of ``calibrate_rig`` from the command line (the whole calibration and each half of
    ``--split`` take the same)."""
    from ..lidar.board_segmentation import SegmentationParams

    return dict(refine_intrinsics=args.refine_intrinsics, range_model=args.range_model, edges=args.edges,
                likelihood=args.likelihood, options=refinement_options(args), init=getattr(args, "init", "closed-form"),
                params=SegmentationParams(max_sensor_separation_m=getattr(args, "max_sensor_separation", 1.0)))


# The calibrate options a rig folder does not take yet (its engine has no such setting), by argument name and flag:
# given with another value than the default, they are refused rather than ignored.
RIG_UNSUPPORTED = {"refine": "--refine"}


def _refuse_what_a_rig_ignores(args) -> None:
    """A one-line error naming the options given that a rig folder would ignore."""
    _refuse_ignored(args, [RIG_UNSUPPORTED[k] for k in _given_options(args) if k in RIG_UNSUPPORTED],
                    "a rig folder (sensors: in dataset.yaml)",
                    "calibrate without it, or calibrate the camera-LiDAR pair from a pair folder")


def _given_options(args) -> list[str]:
    """The names of the calibrate options given with another value than their default."""
    from .parser import build_parser

    default = vars(build_parser().parse_args(["calibrate", str(args.dataset), "--out", str(args.out)]))
    return [k for k, v in vars(args).items() if k in default and v != default[k]]


def _refuse_ignored(args, flags: list[str], what: str, hint: str) -> None:
    """A one-line error naming the options ``flags`` that ``what`` would ignore, if any."""
    if flags:
        raise LidarcamError(f"{', '.join(sorted(flags))} {'is' if len(flags) == 1 else 'are'} not taken by {what} "
                            "and would be ignored", path=args.dataset, hint=hint)


def _pair_measurements(path, board, lidar: str):
    """A pair folder's earlier ``measurements.npz``, refused in one line when taken with another board or LiDAR
    than the folder's dataset.yaml."""
    from ..io.measurement_store import load_measurements

    m = load_measurements(path)
    if m.board != board or m.lidar != lidar:
        raise DatasetError("the measurements were taken with another board or LiDAR than this dataset.yaml",
                           path=path, hint="give the dataset the measurements came from")
    return m


def _closed_form_only(args, ds) -> int:
    """A pair folder's ``--refine none``: the closed form alone (no covariance, no posterior, no report), from the
    images and scans or from ``--measurements`` (a pair's measurements.npz)."""
    import numpy as np

    from ..calibration import calibrate_pair, solve
    from ..io.measurement_store import Measurements, save_measurements
    from ..lidar.board_segmentation import SegmentationParams
    from ..pipeline.result import write_calibration

    if args.cross_validate or args.split:
        raise LidarcamError("--cross-validate and --split score frames against a covariance, which --refine none "
                            "does not give", path=args.dataset, hint="calibrate without --refine none")
    if args.measurements:
        m = _pair_measurements(args.measurements, ds.board, ds.lidar)
        result = solve(m, init=args.init, refine="none", options=refinement_options(args))
    else:
        result = calibrate_pair(ds, args.init, "none", np.random.default_rng(args.seed),
                           SegmentationParams(max_sensor_separation_m=args.max_sensor_separation),
                           refinement_options(args), None, hints=hints(args), cache=not args.no_cache)
        m = Measurements(result.camera, ds.board, ds.lidar, result.frames, (), str(ds.root),
                         result.measurements_source)
    path = write_calibration(result, args.out)
    print_result(result)
    save_measurements(args.out, m)
    print(f"measurements: {source_words(result.measurements_source)}; wrote "
          f"{Path(args.out) / 'measurements.npz'} (and .json)")
    print(f"wrote {path}")
    export_hint(path)
    return exit_code(args, result)


def exit_code(args, result) -> int:
    """0, or ``EXIT_AMBIGUOUS`` (said on stderr) under ``--strict`` for an answer whose verdict is ``UNTRUSTED`` or
    that its boards leave ambiguous."""
    from ..calibration import EXIT_AMBIGUOUS

    if getattr(args, "strict", False) and (result.verdict.untrusted or result.ambiguous):
        what = "untrusted" if result.verdict.untrusted else "ambiguous"
        print(f"lidarcam: the answer is {what} (--strict): exit code {EXIT_AMBIGUOUS}", file=sys.stderr)
        return EXIT_AMBIGUOUS
    return 0



def _with_separating_pose(result, board):
    """The result with, where its range offset is confounded with the extrinsic, the board pose that best separates
    them (``analysis.layout_analysis.separating_pose``) in the confounding record."""
    from dataclasses import replace

    ref = result.refinement
    fit = ref.range_model if ref is not None else None
    if fit is None or not fit.confounding:
        return result
    import numpy as np

    from ..analysis.layout_analysis import separating_pose

    try:
        pose = separating_pose(result, board)
    except (LidarcamError, ValueError, np.linalg.LinAlgError):  # advice only: the calibration stands without it
        pose = None
    if pose is None:
        return result
    fit = replace(fit, confounding={**fit.confounding, "separating_pose": pose})
    return replace(result, refinement=replace(ref, range_model=fit))


def check_command(args) -> int:
    """The scene's check of a given extrinsic (``pipeline.scene_check``): printed verdict first, check.json and
    check.html written; exit 0 consistent, 4 contradicted."""
    from ..analysis.scene_check_page import write_check_page
    from ..io.output import write_json_atomic
    from ..io.rig_dataset import first_pair, is_rig, scene_pair
    from ..pipeline.measurement import given_camera, given_covariance, pair_from_calibration, parse_initial_guess
    from ..pipeline.scene_check import EXIT_CONTRADICTED, check_scene
    from .printing import print_check

    sensors = None
    if is_rig(args.dataset):
        first = first_pair(args.dataset)
        sensors = (args.camera or first[0], args.lidar or first[1])
        scene_pair(args.dataset, need_camera=False, pair=sensors)  # sensors the rig has, before the file is read
        T = pair_from_calibration(args.calibration, *sensors)
    elif args.camera or args.lidar:
        raise DatasetError("--camera and --lidar name a rig folder's sensors; this is a camera-LiDAR folder",
                           path=args.dataset, hint="leave them out")
    else:
        T = parse_initial_guess([args.calibration])
    # the extrinsic checked under the intrinsics it was estimated with (a calibration's, refined or given)
    result = check_scene(args.dataset, T, keep_board=args.keep_board, sensors=sensors,
                         camera=given_camera(args.calibration, sensors),
                         given_covariance=given_covariance(args.calibration, sensors))
    print_check(result)
    print(f"wrote {write_json_atomic(Path(args.out) / 'check.json', result.to_dict())}")
    print(f"wrote {write_check_page(result, args.out)}")
    return EXIT_CONTRADICTED if result.consistent is False else 0


def validate_command(args) -> int:
    """Each camera-LiDAR pair's frames scored under the calibration (``analysis.validation``): a pair folder's one
    pair, or every camera-LiDAR pair of a rig folder under a rig's calibration.json."""
    import numpy as np

    from ..analysis.validation import pair_calibration, verdict
    from ..io.input_files import load_json
    from ..io.output import write_json_atomic
    from ..io.rig_dataset import is_rig

    cal_path = Path(args.calibration)
    if cal_path.is_dir():
        cal_path = cal_path / "calibration.json"
    cal = load_json(cal_path, "calibration file", "give the calibration.json that lidarcam calibrate wrote")
    rng = np.random.default_rng(args.seed)
    rig_folder = is_rig(args.dataset)
    if rig_folder and (not isinstance(cal, dict) or not cal.get("rig")):
        raise DatasetError("a rig folder is given with a single pair's calibration", path=cal_path,
                           hint="give the calibration.json that lidarcam calibrate wrote for this rig")
    if not rig_folder:
        from ..io.dataset import load_dataset

        ds = load_dataset(args.dataset)  # a pair folder's dataset.yaml checked as calibrate checks it
    if args.measurements and not rig_folder and not Path(args.measurements).is_dir():  # a pair's measurements.npz
        from ..io.measurement_store import load_measurements

        m = load_measurements(args.measurements)
        root, board, pairs = ds.root, ds.board, [(None, None, m.camera, list(m.frames), {})]
    else:  # a rig's measurements folder (a pair folder's: the rig of cam0 and lidar0), or the calibration's own
        # measurements, from the cache where it made them; the frames a camera skipped are not in its pairs'
        from ..io.measurement_store import load_rig_measurements
        from ..io.rig_dataset import load_rig
        from ..pipeline.rig_measurement import given_measurements, measured_rig

        rig = load_rig(args.dataset)
        measured = given_measurements(rig, load_rig_measurements(args.measurements), rng) if args.measurements \
            else measured_rig(rig, rng)
        root, board = rig.root, rig.board
        pairs = [(c, lid, measured.cameras[c], frames, measured.skipped.get(c, {}))
                 for (c, lid), frames in measured.pairs.items()] if rig_folder else \
            [(None, None, measured.cameras["cam0"], measured.pairs.get(("cam0", "lidar0"), []),
              measured.skipped.get("cam0", {}))]
    # Every pair's transform read before any is scored: a calibration without one of them is refused before a
    # line is printed, as every bad input is.
    calibrations = []
    for cam, lid, camera, frames, unseen in pairs:
        name = "T_camera_lidar" if cam is None else f"T_{cam}_{lid}"
        try:
            pc = pair_calibration(cal, cam, lid)
        except LidarcamError as exc:  # a rig's calibration.json for one pair's folder
            raise DatasetError(exc.problem, path=cal_path, hint=exc.hint) from None
        except (ValueError, KeyError, TypeError, AttributeError) as exc:
            raise DatasetError(f"not a calibration.json with {name} and its covariance and noise "
                               f"({type(exc).__name__}: {exc})", path=cal_path,
                               hint="give the calibration.json written by `lidarcam calibrate` (refined) for this "
                                    "folder") from None
        if not (np.all(np.isfinite(pc.T_camera_lidar)) and np.all(np.isfinite(pc.covariance))):
            raise DatasetError(f"the calibration's {name} or its covariance is not finite", path=cal_path,
                               hint="recalibrate")
        calibrations.append((name, pc))
    report = {}
    for (cam, lid, camera, frames, unseen), (name, pc) in zip(pairs, calibrations):
        same = Path(pc.dataset).resolve() == Path(root).resolve()
        held = [f for f in frames if f.usable and not (same and f.name in pc.used)]
        note = "frames the calibration did not use"
        if not held:
            held = [f for f in frames if f.usable]
            note = "every frame was used by the calibration: these scores are NOT held out (optimistic)"
        scores = pc.score(held, board, camera)
        v = verdict(scores)
        print(f"validate{'' if cam is None else ' ' + name}: {len(scores)} frame(s) scored ({note})")
        for s_ in scores:
            print(f"  {s_.name}: chi-square {s_.chi2:6.1f} on {s_.dof} dof (p = {s_.p_value:.2g}); plane offset "
                  f"{s_.plane_offset_mm:+6.1f} mm (predicted sd {s_.predicted_offset_sd_mm:.1f}); centre offset "
                  f"{s_.outline_offset_px:.1f} px{'  FLAGGED' if s_.flagged else ''}")
        print(f"verdict: {v['verdict']}" + (f" (chi-square {v['chi2']:.1f} on {v['dof']} dof, p = "
                                             f"{v['p_value']:.2g})" if "chi2" in v else ""))
        skipped = {**unseen, **{f.name: f.reason for f in frames if not f.usable}}
        for stem in sorted(skipped):
            print(f"  {stem}: skipped: {skipped[stem]}")
        report[name] = {"held_out": note, **v, "frame_scores": [x.to_dict() for x in scores]}
    # A pair folder's validation.json as before; a rig's, one entry per camera-LiDAR pair (their verdicts apart: two
    # pairs share a LiDAR's boards, so their chi-squares are not independent).
    body = report["T_camera_lidar"] if len(pairs) == 1 and pairs[0][0] is None else {"pairs": report}
    out = Path(args.out) if args.out else cal_path.parent
    path = write_json_atomic(out / "validation.json", {"calibration": str(cal_path), "dataset": str(root), **body})
    print(f"wrote {path}")
    return 0


def simulate_command(args) -> int:
    from ..simulation.simulator import simulate_dataset

    if args.cameras == 1 and (args.lidars != 1 or args.scanners != 0):
        raise LidarcamError("--lidars and --scanners are for a rig folder (add --cameras N, 2 or more)")
    if args.cameras != 1:
        if args.cameras < 2 or args.lidar == "2d":
            raise LidarcamError("--cameras N (2 or more) writes a rig folder with a 3D LiDAR")
        from ..simulation.rig_simulator import simulate_rig

        if args.lidars not in (1, 2):
            raise LidarcamError("--lidars is 1 or 2")
        if args.scanners not in (0, 1):
            raise LidarcamError("--scanners is 0 or 1")
        if args.range_bias_from_priors is not None:
            raise LidarcamError("--range-bias-from-priors is for a single pair (a rig takes "
                             "--range-bias, injected into lidar0)")
        out = simulate_rig(args.out, args.poses, args.seed, args.cameras, args.model, args.overwrite, args.lidars,
                           args.scanners, range_bias=None if args.range_bias is None else tuple(args.range_bias),
                           scene=args.scene)
        print(f"wrote a rig of {args.cameras} cameras, {args.lidars} 3D LiDAR(s) and {args.scanners} 2D scanner(s) "
              f"({args.poses} frames) to {out}")
        return 0
    two_d = args.lidar == "2d"
    fmt = args.scan_format or ("csv" if two_d else "pcd")
    allowed = ("csv", "npy", "pcd") if two_d else ("pcd", "ply", "bin", "npy")
    if fmt not in allowed:
        raise LidarcamError(f"--scan-format {fmt} is not a {args.lidar} scan format (use one of "
                         f"{', '.join(allowed)})")
    if args.rig != "default" and not two_d:
        raise LidarcamError("--rig varied is a 2D rig (add --lidar 2d)")
    if args.outside_image_share is not None and args.pattern != "charuco":
        raise LidarcamError("--outside-image-share is a share of the poses of a charuco board (a checkerboard must "
                            "be seen whole)")
    noise = args.range_noise if args.range_noise is not None else (0.01 if two_d else 0.02)
    model = "2d" if two_d else args.model
    out = simulate_dataset(args.out, args.poses, args.seed, model, noise, args.pixel_noise,
                           fmt, include_camera=not args.no_camera, overwrite=args.overwrite, scene=args.scene,
                           range_bias=None if args.range_bias is None else tuple(args.range_bias),
                           rig_config=args.rig, pattern=args.pattern, outside_image_share=args.outside_image_share,
                           range_bias_family=args.range_bias_from_priors, intensity=args.intensity,
                           ring_field=not args.no_ring)
    print(f"wrote {args.poses} frames ({'2D scanner' if two_d else args.model}, {args.scene} scene, {args.pattern}) "
          f"to {out}")
    return 0


def layout_command(args) -> int:
    import numpy as np

    from ..analysis.layout_analysis import analyse, layout_from_plan, suggest_poses
    from ..io.input_files import load_yaml
    from ..io.output import write_json_atomic
    from .parser import MAX_SUGGESTED

    src = Path(args.source)
    from ..io.rig_dataset import is_rig

    if src.is_dir() and is_rig(src):
        return _layout_rig(args)
    if src.is_dir():
        from ..analysis.layout_analysis import layout_from_result
        from ..calibration import calibrate_pair
        from ..io.dataset import load_dataset

        ds = load_dataset(src)
        result = calibrate_pair(ds, rng=np.random.default_rng(args.seed), posterior=None)
        model = "2d" if ds.lidar == "2d" else args.lidar_model
        layout, rig, names = layout_from_result(result, ds.board, model)
    elif src.is_file():
        plan = load_yaml(src, "plan", "fix the plan file")
        if not isinstance(plan, dict):
            raise DatasetError("a plan must be a mapping", path=src,
                               hint="see the PLAN.yaml format in docs/howto/layout.md")
        layout, rig = layout_from_plan(plan, str(src))
        names = [f"plan{i:02d}" for i in range(layout.n_frames)]
    else:
        raise DatasetError("no such dataset folder or plan file", path=src, hint="check the path")
    analysis = analyse(layout, names)
    print(analysis.format())
    out = analysis.to_dict()
    if args.suggest > 0 or args.target:
        from ..analysis.layout_analysis import meets

        k_max = args.suggest if not args.target else MAX_SUGGESTED
        target = tuple(args.target) if args.target else None
        print(f"suggested poses (greedy, D-optimal among sampled feasible poses, seed {args.seed}):")
        out["suggestions"] = []
        found = suggest_poses(layout, rig, k_max, np.random.default_rng(args.seed), target=target,
                              range_offset=args.range_offset)
        if target is not None:
            final = found[-1][1] if found else analysis
            if meets(final, *target):
                print(f"the target ({target[0]} deg, {target[1]} mm per axis) is met with {len(found)} more pose(s): "
                      f"{layout.n_frames + len(found)} in all")
            else:
                print(f"the target is not met even with {len(found)} more poses; the closest is below")
        for k, (T, after) in enumerate(found):
            c = T[:3, :3] @ layout.board.centre + T[:3, 3]
            n = T[:3, 2]
            print(f"  {k + 1}: board centre at camera ({c[0]:+.2f}, {c[1]:+.2f}, {c[2]:.2f}) m, normal "
                  f"({n[0]:+.2f}, {n[1]:+.2f}, {n[2]:+.2f}); then std rotation "
                  + " ".join(f"{v:.3f}" for v in after.std_rotation_deg) + " deg, translation "
                  + " ".join(f"{v:.2f}" for v in after.std_translation_mm) + " mm")
            out["suggestions"].append({"T_camera_board": T.tolist(), "centre_m": c.tolist(),
                                       "std_after": after.to_dict()["predicted_std"]})
    if args.json:
        print(f"wrote {write_json_atomic(args.json, out)}")
    return 0


def _layout_rig(args) -> int:
    """``layout`` on a rig folder: the rig calibrated (no posterior), each camera-LiDAR pair's largest translation
    standard deviation and its direction, and with ``--suggest``/``--target`` the poses to add, each for the pair
    then weakest (``analysis.rig_layout.suggest_rig_poses``)."""
    import numpy as np

    from ..analysis.rig_layout import next_pose_words, suggest_rig_poses
    from .parser import MAX_SUGGESTED
    from ..io.output import write_json_atomic
    from ..io.rig_dataset import load_rig
    from ..rig_calibration import calibrate_rig

    if args.range_offset or args.lidar_model != "hdl64e":
        raise LidarcamError(f"{'--range-offset' if args.range_offset else '--lidar-model'} is not taken by a rig "
                            "folder (each LiDAR's beams are read from its boards' rings)", path=args.source,
                            hint="leave it out")
    result = calibrate_rig(load_rig(args.source), np.random.default_rng(args.seed), samples=0, advise=False)
    layout = result.layout()
    print(f"rig: {len(result.solution.names)} sensors; each camera-LiDAR pair's largest translation standard "
          "deviation (the joint graph's):")
    for name, p in layout["pairs"].items():
        print(f"  {name}: {p['max_translation_sd_mm']:.2f} mm along {p['axis']}")
    if layout["weakest_pair"]:
        w = layout["pairs"][layout["weakest_pair"]]
        print(f"weakest pair: {layout['weakest_pair']}; to constrain it, {w['advice']}")
    for link, n in layout["links_with_few_frames"].items():
        print(f"  {link} share {n} frame(s) with the board found in both")
    out = {k: v for k, v in layout.items() if k != "next_pose"}
    if args.suggest > 0 or args.target:
        target = tuple(args.target) if args.target else None
        found = suggest_rig_poses(result, args.suggest if not target else MAX_SUGGESTED,
                                  np.random.default_rng(args.seed), target)
        print(f"suggested poses (greedy, each for the pair then weakest, among sampled feasible poses, seed "
              f"{args.seed}):")
        for k, f in enumerate(found):
            print(f"  {k + 1}: {next_pose_words(f)}")
        out["suggestions"] = found
    if args.json:
        print(f"wrote {write_json_atomic(args.json, out)}")
    return 0


def study_command(args) -> int:
    from ..analysis.coverage_study import format_summary, run_study

    summary = run_study(args.trials, args.out, args.mode, args.seed, args.workers, args.frames, args.samples,
                        progress=sys.stderr.isatty(), likelihood=args.likelihood)
    print(format_summary(summary))
    print(f"wrote {Path(args.out) / 'coverage.csv'} and coverage.json")
    return 0


def study_spec_command(argv: list[str]) -> int:
    from ..analysis.study import format_summary, parse_spec, run_study, summarize
    from ..io.input_files import load_yaml

    args = study_spec_parser().parse_args(argv)
    path = Path(args.spec)
    raw = load_yaml(path, "study spec", "fix the spec (see docs/howto/studies.md)")
    spec = parse_spec(raw, str(path))
    where = args.scheduler or f"{args.workers} local process(es)"
    print(f"{spec.name}: {spec.n_trials} trials x {len(spec.solvers)} solvers on {where}")
    rows = run_study(spec, args.out, args.workers, args.scheduler, progress=sys.stderr.isatty())
    print(format_summary(summarize(rows)))
    print(f"wrote {Path(args.out) / 'study.csv'}, summary.json and the plots")
    return 0


def extract_command(args) -> int:
    from ..io.bag_extract import STILL, ExtractOptions, extract_bag

    options = ExtractOptions(max_dt_s=args.max_dt, still_s=args.still_s, still_px=args.still_px,
                             check_hz=args.check_hz, scan_format=args.scan_format)
    if not args.cloud_topic and not args.scan_topic:
        raise LidarcamError("give a LiDAR topic: --cloud-topic (3D) or --scan-topic (2D)")
    if len(args.image_topic) + len(args.cloud_topic) + len(args.scan_topic) > 2:  # a rig folder
        from ..io.rig_bag_extract import extract_rig_bag

        if args.camera_info_topic is not None or args.intrinsics is not None:
            raise LidarcamError("--camera-info-topic and --intrinsics are for one camera; a rig's "
                             "cameras each take the CameraInfo beside their image topic")
        rig = extract_rig_bag(args.bag, args.out, board_argument(args.board), args.image_topic, args.cloud_topic,
                              args.scan_topic, use_camera_info=not args.no_camera_info, options=options,
                              progress=sys.stderr.isatty(), overwrite=args.overwrite)
        print("\n".join(rig.lines()))
        print(f"wrote {rig.out} (next: lidarcam calibrate {rig.out} --out OUT)")
        return 0
    intrinsics = None
    if args.intrinsics is not None:
        from ..io.intrinsics_file import load_intrinsics


        if args.no_camera_info or args.camera_info_topic is not None:
            raise LidarcamError("--intrinsics replaces the bag's CameraInfo", path=args.intrinsics,
                                hint="give it without --no-camera-info and --camera-info-topic")
        intrinsics = load_intrinsics(args.intrinsics)
    summary = extract_bag(args.bag, args.out, board_argument(args.board), args.image_topic[0],
                          cloud_topic=(args.cloud_topic or [None])[0], scan_topic=(args.scan_topic or [None])[0],
                          camera_info_topic=args.camera_info_topic, use_camera_info=not args.no_camera_info,
                          options=options, progress=sys.stderr.isatty(), overwrite=args.overwrite,
                          intrinsics=intrinsics)
    print("\n".join(summary.lines()))
    if summary.recording == STILL and summary.frames < 4:
        print(f"warning: only {summary.frames} frames; a 3D calibration needs 3 or more spread poses, 4+ "
              "are advised", file=sys.stderr)
    print(f"wrote {summary.out} (next: lidarcam calibrate {summary.out} --out OUT)")
    return 0


def export_command(args) -> int:
    """A calibration written for ROS tf, URDF, KITTI, OpenCV YAML or JSON, its verdict in the file's comment. An
    ``UNTRUSTED`` calibration is refused unless ``--allow-untrusted`` (copied into a robot's files it would read as
    an answer); a ``CHECK`` one is written, its verdict repeated on stderr."""
    from ..io.export import export_calibration, load_calibration, verdict_of, write_export

    frames = {"camera_frame": args.camera_frame, "lidar_frame": args.lidar_frame, "parent": args.parent}
    cal = load_calibration(args.calibration)
    level, reasons = verdict_of(cal)
    if level == "UNTRUSTED" and not args.allow_untrusted:
        raise LidarcamError("the calibration's verdict is UNTRUSTED: not exported as an answer", path=args.calibration,
                         hint="read its reasons (calibration.json, report.html) and fix the data, or pass "
                              "--allow-untrusted to export it anyway")
    if level in ("CHECK", "UNTRUSTED"):
        print(f"lidarcam: note: exporting a calibration whose verdict is {level}"
              + (f": {reasons[0]}" if reasons else ""), file=sys.stderr)
    if args.out is None:
        sys.stdout.write(export_calibration(cal, args.format, **frames))
    else:
        print(f"wrote {write_export(cal, args.format, args.out, **frames)}")
    return 0


def demo_command(args) -> int:
    """Simulate the default rig, calibrate its pair folder as every pair folder is (the one engine; ``--refine
    none``: the closed form alone), print the result and its error against the truth, and write the results."""
    import time

    import numpy as np

    from ..io.dataset import load_dataset
    from ..simulation.simulator import simulate_dataset

    base = Path(args.out)
    data = base / "dataset"
    print(f"simulating {args.poses} poses of the default rig ({args.model}, seed {args.seed}) into {data} ...")
    simulate_dataset(data, args.poses, args.seed, args.model, overwrite=True)
    ds = load_dataset(data)
    if args.refine == "none":
        from ..calibration import calibrate_pair
        from ..pipeline.result import write_calibration

        result = calibrate_pair(ds, refine="none", rng=np.random.default_rng(args.seed),
                                options=refinement_options(args))
        print_result(result, ds.ground_truth())
        path = write_calibration(result, base)
        print(f"wrote {path}")
        export_hint(path)
        return 0
    from ..io.rig_dataset import load_rig
    from ..pipeline.rig_result import write_rig_calibration
    from ..rig_calibration import calibrate_rig

    with _figures_ahead(True) as figures:
        t0 = time.perf_counter()
        result = calibrate_rig(load_rig(data), np.random.default_rng(args.seed), samples=args.samples,
                               on_solved=_draw_ahead(figures), **_rig_settings(args))
        seconds = time.perf_counter() - t0
        print_rig(result)
        pair = result.pair("cam0", "lidar0")
        print_truth(pair.T, pair.covariance, ds.ground_truth())
        print(f"time: {seconds:.1f} s for measurements, solve and posterior")
        path = write_rig_calibration(result, base)
        print(f"wrote {path}")
        from ..analysis.rig_report import write_rig_report

        print(f"wrote {write_rig_report(result, base, figures)} (open it in a browser)")
    export_hint(path)
    return 0
