"""What the command line prints of a result: a rig's (every calibration's), with each camera-LiDAR pair's
intervals (``PairEstimate``); and the pair's own solve without its refinement (``--refine none``: the closed form
and each frame)."""
from __future__ import annotations


def print_result(result, truth=None) -> None:
    """The pair's own solve without its refinement (``--refine none``): the closed form (or a 2D scanner's minimal
    solution) and each frame, no covariance."""
    import numpy as np

    T = result.T_camera_lidar
    np.set_printoptions(precision=5, suppress=True)
    print(result.verdict.line)
    print(f"T_camera_lidar (p_camera = R p_lidar + t), {result.init}, refine {result.refine}:")
    _print_matrix(T)
    print(f"frames used: {result.frames_used} of {len(result.frames)}; normal condition number "
          f"{result.condition_number:.2f}")
    for f in result.frames:
        if f.usable:
            _print_frame(f)
        else:
            _print_skipped(f.name, f.reason)
    if truth is not None:
        print_truth(T, result.covariance, truth)
    for w in result.warnings:
        print(f"warning: {w}")


def print_truth(T, covariance, truth) -> None:
    """A simulated pair's error against its ground truth ``truth`` (``T_camera_lidar``), and the truth's squared
    Mahalanobis distance under ``covariance`` where there is one."""
    import numpy as np

    from geometry.rotations import T_inverse, T_log, rotation_error

    rot = np.degrees(rotation_error(T[:3, :3], truth[:3, :3]))
    tr = 1000 * np.linalg.norm(T[:3, 3] - truth[:3, 3])
    print(f"error against ground truth: rotation {rot:.3f} deg, translation {tr:.1f} mm")
    if covariance is not None:
        xi = T_log(T_inverse(T) @ truth)
        d2 = float(xi @ np.linalg.solve(covariance, xi))
        print(f"  squared Mahalanobis distance of the truth under the covariance: {d2:.1f} "
              f"(chi-square, 6 dof: mean 6, 95% below 12.6)")


def _print_matrix(T) -> None:
    """A 4x4 transform, a row a line."""
    for row in T:
        print("  [" + "  ".join(f"{v:+.5f}" for v in row) + "]")


def _print_frame(f) -> None:
    """A used frame's board: its LiDAR points and plane RMS, its corners' RMS."""
    print(f"  {f.name}: {f.lidar.n_points:6d} board points, plane RMS {1000 * f.lidar.plane_rms_m:.1f} mm, "
          f"corner RMS {f.camera.reprojection_rms_px:.3f} px")


def _print_weakest(what: str, w: dict) -> None:
    """Where a pair's translation is least certain and the board pose that constrains it
    (``PairEstimate.weakest_translation``): a single pair's, and a rig's weakest pair."""
    print(f"{what}translation sd up to {w['max_translation_sd_mm']:.1f} mm along {w['axis']}; to constrain it, "
          f"{w['advice']}")


def _print_skipped(frame: str, reason: str, indent: str = "  ") -> None:
    """A frame not used, with the reason (a single pair's frame, or a rig sensor's)."""
    print(f"{indent}{frame}: skipped: {reason}")


def noise_words(noise: dict) -> str:
    """The noise levels a sensor was weighed with (calibration.json's ``noise``: a single pair's, or a rig sensor's
    at its noise scale): corners, range, the boards' plane error and scatter, those it has."""
    said = []
    if "corner_noise_px" in noise:
        said.append(f"corners {noise['corner_noise_px']:.3f} px"
                    + (f" effective ({noise['corner_residual_px']:.3f} px residual)" if "corner_residual_px" in noise
                       else ""))
    if "range_noise_m" in noise:
        said.append(f"range {1000 * noise['range_noise_m']:.1f} mm")
    if noise.get("plane_floor_m"):
        said.append(f"per-board plane error {1000 * noise['plane_floor_m']:.1f} mm")
    if noise.get("board_scatter_m"):
        said.append(f"boards' scatter along their range terms' weak direction {1000 * noise['board_scatter_m']:.1f} mm")
    return ", ".join(said)


def _print_intervals(p, level: float, indent: str = "  ", axes: str = "") -> None:
    """A pair's equal-tailed posterior intervals at ``level`` (``PairEstimate.intervals``): degrees about, and
    millimetres along, its second sensor's axes (named by ``axes`` where the lines above do not)."""
    import numpy as np

    iv = p.intervals(level)
    head = f"{indent}{round(100 * level)}% intervals{axes}: "
    print(head + "rotation " + "  ".join(f"[{a:+.3f}, {b:+.3f}]" for a, b in np.degrees(iv[:3])) + " deg")
    print(" " * len(head) + "translation " + "  ".join(f"[{a:+.2f}, {b:+.2f}]" for a, b in 1000 * iv[3:]) + " mm")


def _print_params(given, refined, sd, indent: str = "  ") -> None:
    """Intrinsics ``[fx, fy, cx, cy, dist...]`` given and refined, each with its standard deviation and how many
    of them it moved (a single pair's and each camera of a rig's)."""
    from ..solvers.intrinsics_refinement import param_names

    for n, g, v, e in zip(param_names(len(refined)), given, refined, sd):
        print(f"{indent}{n:3s} {g:12.5g} -> {v:12.5g}  (sd {e:.3g}, moved {(v - g) / e:+.1f} sd)")


def _print_edges(edges, name: str = "", indent: str = "") -> None:
    """A LiDAR's board-edges record (``edges_in_graph``; a single pair's ``board_edges`` or a rig LiDAR's): its
    ends, where its outlines sit against the camera's (a single pair's; a rig gives each pair's outline check
    apart), the outline's growth and offset, the boards' in-plane scatter, and the test of the planes against the
    edges."""
    if not edges or "growth_m" not in edges:
        return
    from ..solvers.outline_check import outline_shift_words

    what = "used" if edges["used"] else "a check, not used in the estimate"
    frames = edges.get("frames")
    frames = len(frames) if isinstance(frames, list) else frames
    print(f"{indent}{name + ' ' if name else ''}board edges ({what}): {edges['ends']} ring ends"
          + (f" in {frames} frames" if frames else "")
          + (f"; the LiDAR's outlines sit (camera axes) {outline_shift_words(edges)}"
             if "mean_shift_camera_m" in edges else "") + "; growth "
          f"{1000 * edges['growth_m'][0]:+.1f} / {1000 * edges['growth_m'][1]:+.1f} mm per side"
          + (f", outline offset {1000 * edges['outline_offset_m'][0]:+.1f} / "
             f"{1000 * edges['outline_offset_m'][1]:+.1f} mm" if edges["used"] else "")
          + f"; in-plane board scatter {1000 * edges['board_scatter_in_plane_m']:.1f} mm")
    test = edges.get("planes_against_edges")
    if test:
        print(f"{indent}  planes alone against planes + edges: d2 {test['d2']:.1f} on {test['dof']} dof (p = "
              f"{test['p_value']:.2g})")


def _print_confounding(c: dict, whose: str) -> None:
    """A range term confounded with the extrinsic (``RangeModelFit.confounding``), and the board pose that best
    separates them where one was found."""
    print(f"  confounded: the {c['term']} with {c['direction']} (correlation {c['correlation']:.2f}{whose})")
    if c.get("separating_pose"):
        sp = c["separating_pose"]
        x, y, z = sp["board_centre_camera_m"]
        nx, ny, nz = sp["board_normal_camera"]
        now, then = (sp["predicted_translation_std_mm_with_offset"][k] for k in ("now", "with_this_pose"))
        print(f"  the pose that best separates them: board centre at camera ({x:+.2f}, {y:+.2f}, {z:.2f}) m, "
              f"normal ({nx:+.2f}, {ny:+.2f}, {nz:+.2f}); translation sd along the LiDAR's x y z, predicted from "
              "the point and corner noise alone (as lidarcam layout does), "
              + " ".join(f"{v:.1f}" for v in now) + " -> " + " ".join(f"{v:.1f}" for v in then) + " mm")


def print_rig(result) -> None:
    import numpy as np

    from ..pipeline.rig_result import range_model_words
    from ..solvers.outline_check import outline_shift_words

    sol = result.solution
    print(result.verdict.line)
    if len(result.rig.cameras) == 1 and len(result.rig.lidars) == 1:
        _print_pair_of_two(result)
    post = result.posterior
    if post is not None:
        print(f"rig: {len(sol.names)} sensors, reference {sol.reference}; one graph; posterior "
              f"({post.run.words(post.likelihood)})")
    else:
        print(f"rig: {len(sol.names)} sensors, reference {sol.reference}; one graph, Laplace covariance (posterior "
              "not sampled)")
    for s in result.rig.sensors:
        n = len(result.frames_used.get(s.name, ()))
        skipped = len(result.skipped.get(s.name, {}))
        scale, noise = sol.noise_scale.get(s.name, 1.0), result.noise(s.name)
        print(f"  {s.name:10s} {s.type:6s} {n:3d} frames used" + (f", {skipped} skipped" if skipped else "")
              + (f"; noise {noise_words(noise)}" if noise else "")
              + (f" (its noise scale {np.sqrt(scale):.2f} included)" if scale > 1.0 else "")
              + (f"; {range_model_words(result.range_models[s.name])}" if s.name in result.range_models else ""))
        for stem, why in sorted(result.skipped.get(s.name, {}).items()):
            _print_skipped(stem, why, indent="      ")
    print("every pair (joint graph; t and its standard deviations in the first sensor's frame, mm; rotation's about "
          "the second sensor's axes, deg; " + ("posterior" if post is not None else "Laplace")
          + " standard deviations; pairwise-only estimate in brackets, as far from the joint one):")
    for a, b in result.pairs():
        p = result.pair(a, b)  # the posterior's covariance when sampled
        T = p.T
        line = (f"  T_{a}_{b}: t = (" + ", ".join(f"{1000 * v:.1f}" for v in T[:3, 3]) + ") +- ("
                + ", ".join(f"{v:.1f}" for v in p.std_translation_camera_mm) + ") mm, rotation sd ("
                + ", ".join(f"{v:.3f}" for v in p.std_rotation_deg) + ") deg")
        if (a, b) in result.pairwise:
            from geometry.rotations import T_log

            Tp = result.pairwise[(a, b)][0]
            xi = T_log(np.linalg.inv(T) @ Tp)
            line += (f" [pairwise {np.degrees(np.linalg.norm(xi[:3])):.3f} deg, {1000 * np.linalg.norm(xi[3:]):.1f} mm "
                     "away]")
        print(line)
        if p.samples is not None and result.rig.sensor(a).is_camera and not result.rig.sensor(b).is_camera:
            # a camera-LiDAR pair's, as a single pair prints its own
            _print_intervals(p, 0.95, indent="    ", axes=f" (about/along {b}'s x y z)")
    for n, e in result.edges.items():
        _print_edges(e, n, indent="  ")
    if result.outline_checks:
        print("board edges (a check of the joint estimate, not used in it): each 3D pair's LiDAR board outlines, "
              "camera axes:")
        for (a, b), e in result.outline_checks.items():
            print(f"  T_{a}_{b}: {outline_shift_words(e, ends=True)}")
    for w in result.scene.values():
        _print_scene_witness(w)
    if result.time_offset is None:  # a rig's LiDARs' clocks (a pair's is printed with its transform)
        from ..io.motion_track import FOLLOWED_CAMERA

        for name, offset in result.time_offsets.items():
            print(offset.line(FOLLOWED_CAMERA, name))
    if result.intrinsics_test is not None:
        t = result.intrinsics_test
        print(f"intrinsics refined with the rig ({t['parameters']} parameters): chi-square {t['chi_square_given']:.0f} "
              f"under the given, {t['chi_square_refined']:.0f} refined, on {t['dof']:.0f} dof, "
              f"{t['own_corners_drop']:.0f} of the drop on the cameras' own corners alone (the rest "
              f"{'lowers' if t['lowers_disagreement'] else 'does not lower'} the disagreement, F test p = "
              f"{t['p_value']:.2g})")
    for n, (p, sd) in (sol.intrinsics or {}).items():
        print(f"  {n} intrinsics refined:")
        _print_params(result.cameras[n].params, p, sd, indent="    ")
    layout = result.layout()
    if layout["weakest_pair"]:
        _print_weakest(f"weakest pair: {layout['weakest_pair']}, ", layout["pairs"][layout["weakest_pair"]])
        if layout["next_pose"]:
            from ..analysis.rig_layout import next_pose_words

            print("  next pose for it: " + next_pose_words(layout["next_pose"]))
    for link, n in layout["links_with_few_frames"].items():
        print(f"  {link} share {n} frame(s) with the board found in both")
    for w in result.warnings[1 if result.ambiguous else 0:]:  # an ambiguous pair's, first, is the verdict's
        print(f"warning: {w}")


def _print_scene_witness(w) -> None:
    """``calibrate --scene``'s record (``pipeline.scene_witness.SceneWitness``): the boards', the scene's and the
    joint estimates along the boards' weak direction, their test, and whether the term was joined."""
    name = f"T_{w.camera}_{w.lidar}"
    if w.problem is not None:
        print(f"the scene's term for {name}: not formed ({w.problem})")
        return
    u = w.weak_direction()
    print(f"the scene's term for {name}: along the boards' weak direction (camera x y z: "
          + " ".join(f"{v:+.2f}" for v in u) + "), mm:")
    for which, mm, sd in w.along_weak():
        label = which if which != "joint" or w.joined else "joint (not joined)"
        print(f"  {label:19s}{mm:9.1f} +- {sd:.1f}")
    tests = [f"{t.p_value:.3g} along it" for t in (w.term,) if t is not None]
    tests += [f"{t.p_value:.3g} over its {t.dof} constrained directions" for t in (w.overall,) if t is not None]
    if tests:
        scale = f" x{w.check.excess:g}" if w.check.excess != 1 else ""
        print(f"  boards against scene (the scene's covariance{scale}): p = " + ", ".join(tests))
    print("  joined: the estimates above are the joint one's" if w.joined else f"  not joined: {w.reason}")


def _print_pair_of_two(result) -> None:
    """A rig of one camera and one LiDAR (a pair folder) printed as a single pair's result is, beside the rig's lines:
    its transform, each frame's board, the 99.9% region of its posterior and its range term's confounding with the
    extrinsic (as the pair solved alone found it)."""
    cam, lid = result.rig.cameras[0].name, result.rig.lidars[0].name
    p = result.pair(cam, lid)
    print(f"T_{cam}_{lid} (T_camera_lidar: p_camera = R p_lidar + t):")
    _print_matrix(p.T)
    for f in getattr(result.measurements, "pairs", {}).get((cam, lid), ()):
        if f.usable and f.name in result.frames_used.get(lid, ()):
            _print_frame(f)
    if p.samples is not None:
        print(f"  posterior 99.9% region: squared Mahalanobis distance up to {p.region_d2(0.999):.1f} under its "
              + ("covariance (a Gaussian's 22.5)" if p.mode_index is None else
                 f"nearest minimum's own covariance, of its {len(p.mode_weights)} (a Gaussian's 22.5)"))
        _print_intervals(p, 0.68, indent="  ", axes=f" (about/along {lid}'s x y z)")
    link = (result.pair_results or {}).get((cam, lid))
    fit = link.refinement.range_model if link is not None and link.refinement is not None else None
    if fit is not None and fit.confounding:
        _print_confounding(fit.confounding, ", the pair solved alone")
    if result.time_offset is not None:
        print(result.time_offset.line())


def source_words(source: str) -> str:
    if source == "measured":
        return "measured from the images and scans"
    if source == "cache":
        return "read from the measurement cache (same files and options as an earlier run; --no-cache measures again)"
    return f"read from {source}"


def export_hint(path) -> None:
    print(f"for ROS tf, URDF, KITTI or OpenCV: lidarcam export {path} --format ros-tf|urdf|kitti|opencv-yaml")


def print_check(result) -> None:
    """The scene's check: the verdict, whether consistent and the test, the scene's estimate near the given one
    and what the scene constrains (standard deviations about and along the camera's axes)."""
    import numpy as np

    from geometry.rotations import T_inverse, T_log

    from ..solvers.scene_alignment import STAGES_PX

    t = result.test
    print(result.verdict.line)
    p = "undetermined" if t["p_value"] is None else f"p = {t['p_value']:.3g}"
    pair = f"{result.sensors[0]} and {result.sensors[1]}: " if result.sensors else ""
    print(f"consistent: {str(result.consistent).lower() if result.consistent is not None else 'undetermined'} "
          f"({pair}{p}; {t['dof']} constrained directions, {result.fit.frames} frames, {result.fit.points} LiDAR "
          f"contour returns" + (", the board left out)" if result.board_left_out else ")"))
    T, T0 = result.fit.T_camera_lidar, result.T_given
    d = 1000 * (T[:3, 3] - T0[:3, 3])
    ang = np.degrees(np.linalg.norm(T_log(T_inverse(T0) @ T)[:3]))
    print(f"the scene's estimate: t = ({', '.join(f'{1000 * v:.1f}' for v in T[:3, 3])}) mm, "
          f"{ang:.2f} deg and ({', '.join(f'{v:+.1f}' for v in d)}) mm from the given one")
    rot, trans = result.camera_axes_sd()
    print(f"  its sd about the camera's x, y, z: ({', '.join(f'{v:.2f}' for v in rot)}) deg; along them: "
          f"({', '.join(f'{v:.1f}' for v in trans)}) mm")
    if result.given_covariance is not None:
        print("  tested against the scene's covariance plus the calibration's own (two independent estimates)")
    flagged = result.smallest_flagged()
    if flagged is not None:
        fmt = (lambda v, d: ", ".join(f"{x:.{d}f}" if np.isfinite(x) else "free" for x in v))
        print(f"  flagged from about ({fmt(flagged[0], 2)}) deg about the camera's x, y, z and ({fmt(flagged[1], 0)}) "
              "mm along them (the given extrinsic changed that much along one axis reaches the test's level)")
    print(f"  the camera's intrinsics: {result.camera.source}")
    print(f"  contours on edges: {result.fit.rms_start_px:.2f} px RMS at the given extrinsic, {result.fit.rms_px:.2f} "
          f"at the scene's (along the rings, truncated at {min(STAGES_PX):g} px)")
    if result.rivals:
        deg, mm = result.rivals_spread()
        print(f"  {len(result.rivals)} other minima as low, up to {deg:.2f} deg and {mm:.0f} mm away (rival_minima in "
              "check.json): their scatter is in the standard deviations above")
    for name, why in result.skipped.items():
        print(f"  frame {name} skipped: {why}")


def print_targetless(result) -> None:
    """A targetless calibration: the verdict, ``T_camera_lidar`` with its standard deviations about and along the
    camera's axes, how far it moved from the guess, and what the scene gave."""
    print(result.verdict.line)
    print("T_camera_lidar (p_camera = R p_lidar + t), from the scene alone:")
    for row in result.T_camera_lidar:
        print("  [" + "  ".join(f"{v:+.5f}" for v in row) + "]")
    rot, trans = result.scene.camera_axes_sd()
    print(f"  sd about the camera's x, y, z: ({', '.join(f'{v:.2f}' for v in rot)}) deg; along them: "
          f"({', '.join(f'{v:.1f}' for v in trans)}) mm (Laplace)")
    angle, shift = result.moved()
    fit = result.scene.fit
    print(f"moved {angle:.2f} deg and {shift:.0f} mm from the initial guess; {fit.frames} frames, {fit.points} LiDAR "
          f"contour returns at {fit.rms_px:.2f} px RMS from the image's edges"
          + (", the board left out" if result.scene.board_left_out else "")
          + f"; {result.landed} of {len(result.ends)} starts about the guess ended there (within its 0.999 region)")
    for name, why in result.scene.skipped.items():
        print(f"  frame {name} skipped: {why}")


def print_moving(result) -> None:
    """A moving board's calibration: the verdict, ``T_camera_lidar`` with its standard deviations, the clocks'
    offset, and what was used; a rig's (``pipeline.moving_rig``): its verdict, then each LiDAR's."""
    print(result.verdict.line)
    if hasattr(result, "lidars"):
        for name, r in result.lidars.items():
            print(f"\n{name} against {result.camera}: {r.verdict.line}")
            _print_moving_pair(r, result.camera, name)
        return
    _print_moving_pair(result, "camera", "lidar")


def _print_moving_pair(result, camera: str, lidar: str) -> None:
    p = result.pair
    print(f"recording: moving board; {result.views} images and {result.sweeps} of {result.sweeps_recorded} LiDAR "
          f"sweeps used (returns timed by {result.point_times or 'their sweep'})")
    print(f"T_{camera}_{lidar} (p_{camera} = R p_{lidar} + t):")
    _print_matrix(p.T)
    print("  t = (" + ", ".join(f"{1000 * v:.1f}" for v in p.T[:3, 3]) + ") +- ("
          + ", ".join(f"{v:.1f}" for v in p.std_translation_camera_mm) + ") mm, rotation sd ("
          + ", ".join(f"{v:.3f}" for v in p.std_rotation_deg) + ") deg ("
          + ("the posterior's" if result.posterior is not None else "Laplace")
          + ", with the camera's pointing: docs/bench/moving_bag.md)")
    what = f"time offset (t_{camera}_stamp - t_{lidar}_stamp)"
    if result.time_offset_std_s is None:
        print(f"{what}: held at {1000 * result.time_offset_s:+.2f} ms (--time-offset)")
    else:
        print(f"{what}: {1000 * result.time_offset_s:+.2f} +- {1000 * result.time_offset_std_s:.2f} ms")
    if result.posterior is not None:
        print(f"posterior ({result.posterior.run.words('gaussian')})")
        _print_intervals(p, 0.95, axes=f" (about/along {lidar}'s x y z)")
        summary = result.posterior_summary()
        if "time_offset_ms" in summary:
            lo, hi = summary["time_offset_ms"]["95%"]
            print(f"  95% interval of the time offset: [{lo:+.2f}, {hi:+.2f}] ms")
    if result.posterior_note is not None:
        print(f"posterior: {result.posterior_note}")
    print(f"board returns against the board where the camera saw it: {1000 * result.rms_m:.1f} mm RMS along the "
          "beams")
