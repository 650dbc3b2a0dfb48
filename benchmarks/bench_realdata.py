"""The recorded VLP-16 + fisheye set against its reference and against itself, and the Ouster office set
(make bench; each skipped when absent from ../shared/realdata).

Every estimate is the engine's (``calibrate``, as ``lidarcam calibrate`` gives it), solved again from its
measurements for subsets of frames. Prints: closed form and factor graph against the source tool's reference
extrinsic; the plane-consistency statistic; the squared Mahalanobis distance between estimates from two disjoint
halves (interleaved, and first against last); the consistency statistic with every range shifted by a constant
offset; and, on both sets, each LiDAR plane's tilt from the camera's about the board's axes against what the points'
noise allows; on the Ouster set, how far from the reference the estimate lands with each frame left out; and on
both, the static scene's rig-moved check on the sweeps as recorded, one sweep turned or shifted, and half of them
turned; both calibrated with board.size left out; and both with the camera's intrinsics refined with the extrinsic.
"""
from __future__ import annotations

import json
import os
import sys
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # as the CLI does (see bench_refinement.py)

import numpy as np  # noqa: E402
from scipy.stats import chi2  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from estimators.io.measurement_store import Measurements, pair_as_rig  # noqa: E402
from estimators.io.dataset import load_dataset  # noqa: E402
from estimators.measurements import FrameMeasurement, observe_lidar_board  # noqa: E402
from estimators.rig_calibration import calibrate, calibrate_rig  # noqa: E402
from estimators.solvers.closed_form import solve_closed_form  # noqa: E402
from estimators.solvers.intrinsics_refinement import param_names  # noqa: E402
from estimators.solvers.refinement_options import RefinementOptions  # noqa: E402
from geometry.rotations import T_inverse, T_log, rotation_error  # noqa: E402

DATA = Path(__file__).resolve().parents[2] / "shared" / "realdata" / "acfr_vlp16_a"
OFFICE = DATA.parent / "acfr_ouster64_b"


def solved_again(res, stems=None, frames=None, **kw):
    """The engine (``calibrate_rig``) on ``res``'s pair folder again, from its measurements (no frame measured
    twice): those of the frames ``stems`` only, or the frames ``frames`` (measured, then changed) instead."""
    rig = res.rig
    m = res.measurements if frames is None else pair_as_rig(
        Measurements(res.cameras["cam0"], rig.board, rig.lidars[0].lidar, tuple(frames)))
    if stems is not None:
        m = m.restricted(stems)
    return calibrate_rig(rig, np.random.default_rng(0), advise=False, measurements=m, **kw)


def _consistency(res) -> tuple[float, float]:
    """The LiDAR's boards' chi-square and its degrees of freedom in the joint graph."""
    return res.solution.chi2_dof["lidar0"]


def _halves_d2(res, a, b) -> float:
    ra, rb = solved_again(res, stems=a), solved_again(res, stems=b)
    xi = T_log(T_inverse(ra.T_camera_lidar) @ rb.T_camera_lidar)
    return float(xi @ np.linalg.solve(ra.covariance + rb.covariance, xi))


def _tilts(res, frames) -> None:
    """Per used frame, the LiDAR plane's tilt from the camera's board plane (under the estimate) about the
    board's horizontal (x) and vertical (y) axes, each against the standard deviation that the board points'
    noise and spread allow (the camera's normal is far more precise). A range error shared by the boards
    moves their planes along the normals; a warped board tilts them the same way in the board's frame."""
    R = res.T_camera_lidar[:3, :3]
    ratios = []
    for f in frames:
        if not f.usable:
            continue
        n_c, n_l = f.camera.plane.normal, R @ f.lidar.plane.normal
        n_l = n_l if n_l @ n_c > 0 else -n_l
        R_cb = f.camera.T_camera_board[:3, :3]
        tilt = R_cb.T @ np.cross(n_c, n_l)  # small rotation taking the camera's normal to the LiDAR's
        q = (R_cb.T @ (R @ f.lidar.points.T)).T[:, :2]  # the points in the board's axes (in-plane part)
        q -= q.mean(0)
        sd = f.lidar.plane_rms_m / np.sqrt(np.sum(q[:, ::-1] ** 2, axis=0))  # about x: spread along y
        ratios += list(np.abs(tilt[:2]) / sd)
        print(f"    {f.name}: tilt about board x {np.degrees(tilt[0]):+.2f} deg (sd {np.degrees(sd[0]):.2f}), "
              f"about board y {np.degrees(tilt[1]):+.2f} deg (sd {np.degrees(sd[1]):.2f})")
    print(f"    tilt / sd: median {np.median(ratios):.1f}, largest {np.max(ratios):.1f}")


def _recorded(path: Path, **kw):
    """A recorded set calibrated by the engine from its folder (``calibrate``, as ``lidarcam calibrate`` does, no
    posterior unless asked) and its reference extrinsic, or None (said) when absent."""
    if not (path / "dataset.yaml").is_file():
        print(f"recorded data: {path} is absent; skipped")
        return None
    kw.setdefault("samples", 0)
    res = calibrate(path, rng=np.random.default_rng(0), **kw)
    return res, np.array(json.loads((path / "reference.json").read_text())["T_camera_lidar"])


def _against(T, ref) -> str:
    return (f"{np.degrees(rotation_error(T[:3, :3], ref[:3, :3])):.2f} deg, "
            f"{1000 * np.linalg.norm(T[:3, 3] - ref[:3, 3]):.0f} mm")


def main() -> None:
    if (recorded := _recorded(DATA)) is None:
        return
    res, ref = recorded
    frames = res.frames
    used = [f for f in frames if f.usable]
    print(f"recorded data: {DATA.name}, {len(used)}/{len(frames)} frames usable; the engine (calibrate)")
    closed = solve_closed_form([f.camera.plane for f in used], [f.lidar.plane for f in used]).T_camera_lidar
    print(f"  {'closed form':24s} against the reference: {_against(closed, ref)}")
    for label, r in (("graph, no range model", solved_again(res, range_model="none")),
                     ("graph, range model auto", res)):
        print(f"  {label:24s} against the reference: {_against(r.T_camera_lidar, ref)}")
    print("  the LiDAR planes' tilts from the camera's (range model auto):")
    _tilts(res, frames)
    fit = res.range_models.get("lidar0", {})
    terms = fit.get("terms", {})
    print(f"  range model: {fit.get('model', 'none')}" + "".join(
        f"; {n} {1000 * t['value_m']:+.1f} +- {1000 * t['sd_m']:.1f} mm" for n, t in terms.items()
        if not n.startswith("ring"))
          + " (the source tool's hand correction, distance_offset_mm -30, shortens every range: +30 mm in this sign)")
    ss, dof = _consistency(res)
    floor = res.pair_results[("cam0", "lidar0")].refinement.plane_floor_m
    print(f"  consistency: the LiDAR's chi-square {ss:.0f} on {dof:.0f} dof (p = {chi2.sf(ss, dof):.1g}); per-board "
          f"plane error estimated {1000 * floor:.1f} mm")
    stems = [f.name for f in used]
    n = len(stems)
    limit = chi2.ppf(0.99, 6)
    for label, a, b in (("interleaved", stems[0::2], stems[1::2]), ("first/last", stems[:n // 2], stems[n // 2:])):
        d2 = _halves_d2(res, a, b)
        print(f"  halves {label:12s}: squared Mahalanobis distance {d2:5.1f} (p = {chi2.sf(d2, 6):.3f}; "
              f"99% limit {limit:.1f})")
    print("  consistency (the LiDAR's chi-square/dof, no plane error) with every range shifted by an offset:")
    plain = RefinementOptions(estimate_plane_floor=False)
    for offset in (-0.02, 0.0, 0.02, 0.035, 0.05):
        shifted = []
        for f in frames:
            if f.lidar is None:
                shifted.append(f)
                continue
            P = f.lidar.points
            beams = P / np.linalg.norm(P, axis=1, keepdims=True)
            shifted.append(FrameMeasurement(f.name, f.camera, observe_lidar_board(P + offset * beams)))
        ss, dof = _consistency(solved_again(res, frames=shifted, range_model="none", options=plain))
        print(f"    {100 * offset:+5.1f} cm: {ss / dof:.2f}")


def office() -> None:
    """The Ouster office set: frames used, how each frame's board was chosen, and the estimate against the
    reference (angle, distance, and the reference's squared Mahalanobis distance under the estimate's posterior)."""
    if (recorded := _recorded(OFFICE, samples=2000)) is None:
        return
    res, ref = recorded
    frames = res.frames
    T = res.T_camera_lidar
    xi = T_log(T_inverse(T) @ ref)
    d2 = float(xi @ np.linalg.solve(res.covariance, xi))
    cands = [len(f.decision.candidates) for f in frames if f.decision is not None]
    pair = res.only_pair()
    print(f"recorded data: {OFFICE.name}, {pair.frames}/{len(frames)} frames used; candidates per frame "
          f"{min(cands)}-{max(cands)} (median {int(np.median(cands))}); "
          f"{frames[0].decision.method if frames[0].decision else '-'}")
    print(f"  the engine against the reference: {_against(T, ref)}; reference's squared Mahalanobis distance under "
          f"the estimate {d2:.1f} (99% limit {chi2.ppf(0.99, 6):.1f})")
    print("  the LiDAR planes' tilts from the camera's:")
    _tilts(res, frames)
    away = []
    kept = [f.name for f in frames if f.usable]
    for leave in kept:
        T_k = solved_again(res, stems=[s for s in kept if s != leave]).T_camera_lidar
        away.append((1000 * np.linalg.norm(T_k[:3, 3] - ref[:3, 3]), leave))
    print(f"  leaving one frame out, against the reference: {min(away)[0]:.0f} mm (without {min(away)[1]}) to "
          f"{max(away)[0]:.0f} mm (without {max(away)[1]})")
    print(f"  std of t in camera x/y/z: {np.round(pair.std_translation_camera_mm, 1).tolist()} mm; measuring "
          f"{res.timings_s.get('measurements', float('nan')):.2f} s for {len(frames)} frames")


def rig_moved() -> None:
    """The static scene's rig-moved check on both 3D sets: each frame's share of its judged background that it
    matches (with beam indices, and as unorganised clouds: direction bins), and whether a frame contradicts the
    scene ("moved") or the note says the stillness could not be checked ("unchecked"), then with the third sweep
    turned about the vertical or shifted forwards, and with the second half of the sweeps turned by 2 degrees."""
    from estimators.io.pointcloud_io import read_sweep
    from estimators.lidar.static_scene import build_static_scene
    from geometry.rotations import R_from_rotvec

    for root in (DATA, OFFICE):
        if not (root / "dataset.yaml").is_file():
            print(f"recorded data: {root} is absent; skipped")
            continue
        sweeps = [read_sweep(f.scan) for f in load_dataset(root).frames]
        P, rings = [s.points for s in sweeps], [s.ring for s in sweeps]

        def check(points, label):
            rows = []
            for kind, r in (("rings", rings), ("bins", None)):
                scene = build_static_scene(points, r)
                said = "moved" if scene.moved else "unchecked" if "checked" in scene.note else "still"
                rows.append(f"{kind} {said} {np.nanmin(scene.match):.3f}-{np.nanmax(scene.match):.3f}")
            print(f"    {label:28s} {'; '.join(rows)}")

        print(f"recorded data: {root.name}, rig-moved check (share of the judged background each frame matches, "
              "min-max over frames)")
        check(P, "as recorded")
        for deg in (1, 2, 3):
            turn = R_from_rotvec([0.0, 0.0, np.deg2rad(deg)])
            check([p @ turn.T if k == 2 else p for k, p in enumerate(P)], f"sweep 2 turned {deg} deg")
        for dx in (0.1, 0.2):
            check([p + [dx, 0.0, 0.0] if k == 2 else p for k, p in enumerate(P)], f"sweep 2 shifted {dx} m")
        turn = R_from_rotvec([0.0, 0.0, np.deg2rad(2.0)])
        check([p @ turn.T if k >= len(P) // 2 else p for k, p in enumerate(P)], "second half turned 2 deg")


def without_size() -> None:
    """Both 3D sets calibrated as given and with board.size left out of dataset.yaml (the board judged by its
    pattern's extent and margin, its border kept as far as it stays in the pattern's plane): the translation's
    difference, and the boards' plane consistency (the LiDAR's chi-square per dof) of each."""
    import re
    import shutil
    import tempfile

    for root in (DATA, OFFICE):
        if not (root / "dataset.yaml").is_file():
            print(f"recorded data: {root} is absent; skipped")
            continue
        with tempfile.TemporaryDirectory() as tmp:
            copy = Path(shutil.copytree(root, Path(tmp) / root.name))
            yaml = copy / "dataset.yaml"
            yaml.write_text(re.sub(r"(?m)^  size:.*\n", "", yaml.read_text()))
            given = calibrate(root, rng=np.random.default_rng(0), samples=0)
            unknown = calibrate(copy, rng=np.random.default_rng(0), samples=0)
        dt = 1000 * (unknown.T_camera_lidar[:3, 3] - given.T_camera_lidar[:3, 3])
        (su, du), (sg, dg) = _consistency(unknown), _consistency(given)
        print(f"recorded data: {root.name} with board.size left out: {unknown.only_pair().frames}/"
              f"{len(unknown.frames)} frames used; translation {np.round(dt, 1).tolist()} mm from the sized estimate "
              f"(its sd {np.round(given.std_translation_mm, 1).tolist()} mm); plane consistency {su / du:.2f} "
              f"(sized {sg / dg:.2f})")


def intrinsics() -> None:
    """Both 3D sets with the camera's intrinsics refined with the extrinsic (no prior: the sets state no
    uncertainty for theirs): the LiDAR's boards' chi-square per dof under the given and the refined intrinsics, how
    far each parameter moved in its standard deviations, and the estimate against the reference (the reference's
    squared Mahalanobis distance under each estimate's covariance)."""
    for path in (DATA, OFFICE):
        if (recorded := _recorded(path)) is None:
            continue
        res, ref = recorded
        print(f"recorded data: {path.name}, the camera's intrinsics refined with the extrinsic (no prior)")
        for label, r in (("given intrinsics", res),
                         ("refined intrinsics", calibrate(path, rng=np.random.default_rng(0), samples=0,
                                                          options=RefinementOptions(refine_intrinsics=True)))):
            T = r.T_camera_lidar
            xi = T_log(T_inverse(T) @ ref)
            d2 = float(xi @ np.linalg.solve(r.covariance, xi))
            ss, dof = _consistency(r)
            print(f"  {label:18s} against the reference: {_against(T, ref)} (reference's d2 {d2:.1f}); plane "
                  f"consistency {ss / dof:.2f}; std of t in camera x/y/z "
                  f"{np.round(r.only_pair().std_translation_camera_mm, 1).tolist()} mm")
        t = r.intrinsics_test
        print(f"  the test: chi-square {t['chi_square_given']:.0f} -> {t['chi_square_refined']:.0f} on {t['dof']:.0f} "
              f"dof, {t['own_corners_drop']:.0f} of the drop on the camera's own corners alone; the rest "
              f"{'lowers' if t['lowers_disagreement'] else 'does not lower'} the disagreement (F test p = "
              f"{t['p_value']:.2g})")
        params, sd = r.solution.intrinsics["cam0"]
        given = res.cameras["cam0"].params
        print("  moved (in their sd): " + ", ".join(f"{n} {(v - g) / s:+.1f}" for n, g, v, s in
                                                   zip(param_names(len(params)), given, params, sd)))


if __name__ == "__main__":
    main()
    office()
    rig_moved()
    without_size()
    intrinsics()
