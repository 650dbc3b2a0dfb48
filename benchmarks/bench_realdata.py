"""The recorded VLP-16 + fisheye set against its reference and against itself, and the Ouster office set
(make bench; each skipped when absent from ../shared/realdata).

Prints: closed form and factor graph against the source tool's reference extrinsic; the plane-consistency
statistic; the squared Mahalanobis distance between estimates from two disjoint halves (interleaved, and
first against last); the consistency statistic with every range shifted by a constant offset; and, on both
sets, each LiDAR plane's tilt from the camera's about the board's axes against what the points' noise allows;
on the Ouster set, how far from the reference the estimate lands with each frame left out; and on both, the
static scene's rig-moved check on the sweeps as recorded, one sweep turned or shifted, and half of them turned;
both calibrated with board.size left out; and both with the camera's intrinsics refined with the extrinsic.
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

from estimators.calibration import solve  # noqa: E402
from estimators.pipeline.measurement import measure_frames  # noqa: E402
from estimators.io.dataset import load_dataset  # noqa: E402
from estimators.measurements import FrameMeasurement, observe_lidar_board  # noqa: E402
from estimators.solvers.refinement_options import RefinementOptions  # noqa: E402
from geometry.rotations import T_inverse, T_log, rotation_error  # noqa: E402

DATA = Path(__file__).resolve().parents[2] / "shared" / "realdata" / "acfr_vlp16_a"
OFFICE = DATA.parent / "acfr_ouster64_b"


def _halves_d2(frames, ds, camera, a, b, options=RefinementOptions()):
    ra = solve([frames[i] for i in a], ds.board, camera, options=options)
    rb = solve([frames[i] for i in b], ds.board, camera, options=options)
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


def _recorded(path: Path):
    """A recorded set measured (``ds, camera, frames``) and its reference extrinsic, or None (said) when absent."""
    if not (path / "dataset.yaml").is_file():
        print(f"recorded data: {path} is absent; skipped")
        return None
    ds = load_dataset(path)
    camera, frames, _ = measure_frames(ds, np.random.default_rng(0))
    return ds, camera, frames, np.array(json.loads((path / "reference.json").read_text())["T_camera_lidar"])


def main() -> None:
    if (recorded := _recorded(DATA)) is None:
        return
    ds, camera, frames, ref = recorded
    print(f"recorded data: {DATA.name}, {sum(f.usable for f in frames)}/{len(frames)} frames usable")
    for label, method, model in (("closed form", "none", "none"), ("graph, no range model", "factor-graph", "none"),
                                 ("graph, range model auto", "factor-graph", "auto")):
        res = solve(frames, ds.board, camera, refine=method, options=RefinementOptions(range_model=model))
        T = res.T_camera_lidar
        print(f"  {label:24s} against the reference: {np.degrees(rotation_error(T[:3, :3], ref[:3, :3])):.2f} deg, "
              f"{1000 * np.linalg.norm(T[:3, 3] - ref[:3, 3]):.0f} mm")
    print("  the LiDAR planes' tilts from the camera's (range model auto):")
    _tilts(res, frames)
    r = res.refinement
    fit = r.range_model
    print(f"  range model: {fit.chosen}" + "".join(f"; {n} {1000 * v:+.1f} +- {1000 * sd:.1f} mm"
                                                for n, v, sd in zip(fit.names, fit.values_m, fit.std_m)
                                                if not n.startswith("ring"))
          + " (the source tool's hand correction, distance_offset_mm -30, shortens every range: +30 mm in this sign)")
    print(f"  consistency: chi-square {r.variance_factor * r.consistency_dof:.0f} on {r.consistency_dof} dof "
          f"(p = {r.consistency_p:.1g}); per-board plane error estimated {1000 * r.plane_floor_m:.1f} mm")
    n = len(frames)
    limit = chi2.ppf(0.99, 6)
    for label, a, b in (("interleaved", range(0, n, 2), range(1, n, 2)),
                        ("first/last", range(n // 2), range(n // 2, n))):
        d2 = _halves_d2(frames, ds, camera, list(a), list(b))
        print(f"  halves {label:12s}: squared Mahalanobis distance {d2:5.1f} (p = {chi2.sf(d2, 6):.3f}; "
              f"99% limit {limit:.1f})")
    print("  consistency (chi-square/dof, no plane error) with every range shifted by an offset:")
    plain = RefinementOptions(estimate_plane_floor=False, range_model="none")
    for offset in (-0.02, 0.0, 0.02, 0.035, 0.05):
        shifted = []
        for f in frames:
            P = f.lidar.points
            beams = P / np.linalg.norm(P, axis=1, keepdims=True)
            shifted.append(FrameMeasurement(f.name, f.camera, observe_lidar_board(P + offset * beams)))
        vf = solve(shifted, ds.board, camera, options=plain).refinement.variance_factor
        print(f"    {100 * offset:+5.1f} cm: {vf:.2f}")


def office() -> None:
    """The Ouster office set: frames used, how each frame's board was chosen, and the estimate against the
    reference (angle, distance, and the reference's squared Mahalanobis distance under the estimate)."""
    if not (OFFICE / "dataset.yaml").is_file():
        print(f"recorded data: {OFFICE} is absent; skipped")
        return
    ds = load_dataset(OFFICE)
    timings: dict = {}
    camera, frames, warnings = measure_frames(ds, np.random.default_rng(0), timings=timings)
    ref = np.array(json.loads((OFFICE / "reference.json").read_text())["T_camera_lidar"])
    res = solve(frames, ds.board, camera)
    T = res.T_camera_lidar
    xi = T_log(T_inverse(T) @ ref)
    d2 = float(xi @ np.linalg.solve(res.covariance, xi))
    cands = [len(f.decision.candidates) for f in frames if f.decision is not None]
    print(f"recorded data: {OFFICE.name}, {res.frames_used}/{len(frames)} frames used; candidates per frame "
          f"{min(cands)}-{max(cands)} (median {int(np.median(cands))}); "
          f"{frames[0].decision.method if frames[0].decision else '-'}")
    print(f"  factor-graph  against the reference: {np.degrees(rotation_error(T[:3, :3], ref[:3, :3])):.2f} deg, "
          f"{1000 * np.linalg.norm(T[:3, 3] - ref[:3, 3]):.0f} mm; reference's squared Mahalanobis distance under "
          f"the estimate {d2:.1f} (99% limit {chi2.ppf(0.99, 6):.1f})")
    print("  the LiDAR planes' tilts from the camera's:")
    _tilts(res, frames)
    away = []
    for leave in [f.name for f in frames if f.usable]:
        T_k = solve([f for f in frames if f.name != leave], ds.board, camera, posterior=None).T_camera_lidar
        away.append((1000 * np.linalg.norm(T_k[:3, 3] - ref[:3, 3]), leave))
    print(f"  leaving one frame out, against the reference: {min(away)[0]:.0f} mm (without {min(away)[1]}) to "
          f"{max(away)[0]:.0f} mm (without {max(away)[1]})")
    print(f"  std of t in camera x/y/z: {np.round(res.std_translation_camera_mm, 1).tolist()} mm; LiDAR side "
          f"{sum(timings.get(k, 0.0) for k in ('load_scans', 'static_scene', 'segmentation', 'association')):.2f} s "
          f"CPU for {len(frames)} frames")


def rig_moved() -> None:
    """The static scene's rig-moved check on both 3D sets: each frame's share of its judged background that it
    matches (with beam indices, and as unorganised clouds: direction bins), and whether a frame contradicts the
    scene ("moved") or the note says the stillness could not be checked ("unchecked"), then with the third sweep turned about the vertical
    or shifted forwards, and with the second half of the sweeps turned by 2 degrees."""
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
    difference, and the boards' plane consistency (chi-square per dof) of each."""
    import re
    import shutil
    import tempfile

    from estimators.calibration import calibrate_pair

    for root in (DATA, OFFICE):
        if not (root / "dataset.yaml").is_file():
            print(f"recorded data: {root} is absent; skipped")
            continue
        with tempfile.TemporaryDirectory() as tmp:
            copy = Path(shutil.copytree(root, Path(tmp) / root.name))
            yaml = copy / "dataset.yaml"
            yaml.write_text(re.sub(r"(?m)^  size:.*\n", "", yaml.read_text()))
            given = calibrate_pair(root, rng=np.random.default_rng(0), samples=0)
            unknown = calibrate_pair(copy, rng=np.random.default_rng(0), samples=0)
        dt = 1000 * (unknown.T_camera_lidar[:3, 3] - given.T_camera_lidar[:3, 3])
        print(f"recorded data: {root.name} with board.size left out: {unknown.frames_used}/{len(unknown.frames)} "
              f"frames used; translation {np.round(dt, 1).tolist()} mm from the sized estimate (its sd "
              f"{np.round(given.std_translation_mm, 1).tolist()} mm); plane consistency "
              f"{unknown.refinement.variance_factor:.2f} (sized {given.refinement.variance_factor:.2f})")


def intrinsics() -> None:
    """Both 3D sets with the camera's intrinsics refined with the extrinsic (no prior: the sets state no
    uncertainty for theirs): the boards' plane-consistency variance factor under the given and the refined
    intrinsics, how far each parameter moved in its standard deviations, and the estimate against the reference
    (the reference's squared Mahalanobis distance under each estimate's covariance)."""
    for path in (DATA, OFFICE):
        if (recorded := _recorded(path)) is None:
            continue
        ds, camera, frames, ref = recorded
        print(f"recorded data: {path.name}, the camera's intrinsics refined with the extrinsic (no prior)")
        for label, refine in (("given intrinsics", False), ("refined intrinsics", True)):
            res = solve(frames, ds.board, camera, options=RefinementOptions(refine_intrinsics=refine))
            T = res.T_camera_lidar
            xi = T_log(T_inverse(T) @ ref)
            d2 = float(xi @ np.linalg.solve(res.covariance, xi))
            print(f"  {label:18s} against the reference: {np.degrees(rotation_error(T[:3, :3], ref[:3, :3])):.2f} "
                  f"deg, {1000 * np.linalg.norm(T[:3, 3] - ref[:3, 3]):.0f} mm (reference's d2 {d2:.1f}); plane "
                  f"consistency {res.refinement.variance_factor:.2f}; std of t in camera x/y/z "
                  f"{np.round(res.std_translation_camera_mm, 1).tolist()} mm")
        fit = res.intrinsics_refinement
        print("  moved (in their sd): " + ", ".join(f"{n} {(v - g) / sd:+.1f}" for n, g, v, sd in
                                                   zip(fit.names, fit.given_params, fit.params, fit.std)))


if __name__ == "__main__":
    main()
    office()
    rig_moved()
    without_size()
    intrinsics()
