"""The verdict (issue 63): does a result whose answer is wrong ever say OK, and does a good one say UNTRUSTED?
(make bench; `python benchmarks/bench_verdict.py [--datasets N] [--wrong M] [--workers W]`).

Simulated datasets calibrated end to end as `lidarcam calibrate` does (measurement, graph, posterior), each
judged by its verdict and by its truth: the squared Mahalanobis distance of the truth under the reported
covariance, "off" beyond 20.06 (a 6-dof chi-square's 3-sigma point, 99.73%).

Good datasets: several LiDARs and scenes (HDL-64E and VLP-16 in the default room, an OS-64 in an office with the
board held, a VLP-16 in a hall, a VLP-16 whose ranges carry errors drawn from a Velodyne's priors, a 2D scanner in
the default room and a mounted 2D rig). Wrong ones, made so after
simulation, by what a user gets wrong: the square size 5% off (`scale`), the focal length 4% off (`focal`), the
principal point 20 px off (`cx`), two frames' scans swapped (`swapped`, a wrong segment in each), the board's size
10% off (`size`; only the edges use it).

Targets: no OK on a dataset whose answer is off; UNTRUSTED on at most 1% of good datasets. "px": the median
distance in the image between where the used frames' LiDAR board points land under the result (its camera model,
made wrong with the dataset, and its estimate) and under the truth: some wrong inputs leave the extrinsic off by
many standard deviations while it still projects the LiDAR where it belongs for the camera model given.
"""
from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
from collections import Counter
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import yaml  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

GOOD = [  # label, simulate_dataset's keywords
    ("HDL-64E room", dict(lidar="hdl64e")),
    ("VLP-16 room", dict(lidar="vlp16", sigma_range_m=0.03)),
    ("OS-64 office", dict(lidar="os64", scene="office")),
    ("VLP-16 hall", dict(lidar="vlp16", scene="hall", sigma_range_m=0.03)),
    # range errors drawn from a Velodyne's priors (offset and black squares 0 +- 3 cm, rings 0 +- 6 mm)
    ("VLP-16 biased", dict(lidar="vlp16", range_bias_family="velodyne")),
    ("2D room", dict(lidar="2d")),
    ("2D mounted", dict(lidar="2d", rig_config="mounted")),
]
WRONG_3D = ("scale", "focal", "cx", "swapped", "size")
WRONG_2D = ("scale", "swapped")
OFF_D2 = 20.06  # chi-square, 6 dof, 99.73%
PX_OFF = 2.0  # a projection this far off (median, pixels) is visibly wrong on the overlays


def corrupt(folder: Path, how: str) -> None:
    """Make the dataset wrong as ``how`` says (module docstring)."""
    path = folder / "dataset.yaml"
    spec = yaml.safe_load(path.read_text())
    if how == "scale":
        spec["board"]["square_size"] *= 1.05
    elif how == "focal":
        spec["camera"]["K"][0][0] *= 1.04
        spec["camera"]["K"][1][1] *= 1.04
    elif how == "cx":
        spec["camera"]["K"][0][2] += 20.0
    elif how == "size":
        spec["board"]["size"] = [1.1 * v for v in spec["board"]["size"]]
    elif how == "swapped":
        scans = sorted(p for p in folder.iterdir() if p.stem.isdigit() and p.suffix not in (".png", ".jpg"))
        a, b = scans[1], scans[3]
        tmp = a.with_name("swap" + a.suffix)
        a.rename(tmp)
        b.rename(a)
        tmp.rename(b)
    path.write_text(yaml.safe_dump(spec))


def trial(args) -> dict:
    label, kw, seed, how, tmp = args
    from estimators import calibrate
    from estimators.errors import LidarcamError
    from estimators.io.dataset import load_dataset
    from estimators.simulation.simulator import simulate_dataset
    from geometry.rotations import T_inverse, T_log

    folder = Path(tmp) / f"{label.replace(' ', '_')}_{seed}_{how}"
    poses = 6 if kw.get("lidar") == "2d" else 8
    simulate_dataset(folder, poses, seed, **kw)
    truth = np.array(__import__("json").loads((folder / "ground_truth.json").read_text())["T_camera_lidar"])
    camera = load_dataset(folder).camera  # the true intrinsics, before they are made wrong
    if how != "good":
        corrupt(folder, how)
    try:
        result = calibrate(folder, rng=np.random.default_rng(seed))
    except LidarcamError as exc:
        return {"label": label, "how": how, "seed": seed, "level": "refused", "d2": np.nan, "why": exc.problem[:100],
                "px": np.nan}
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    if result.covariance is None:
        return {"label": label, "how": how, "seed": seed, "level": result.verdict.level, "d2": np.inf, "why": "",
                "px": np.nan}
    xi = T_log(T_inverse(result.T_camera_lidar) @ truth)
    return {"label": label, "how": how, "seed": seed, "level": result.verdict.level,
            "d2": float(xi @ np.linalg.solve(result.covariance, xi)), "why": result.verdict.line[:160],
            "px": projection_px(result, camera, truth), "fit": fit_words(result),
            "p_planes": (result.to_json().get("consistency") or {}).get("p_value"),
            "p_outline": (result.edges.get("lidar0") or result.outline_checks.get(("cam0", "lidar0")) or {}).get(
                "mean_shift_p_value")}


def fit_words(result) -> str:
    """What the data say of their own fit: the planes' consistency (chi-square/dof, p) and the board outlines'
    mean shift (p), as a good dataset's would read."""
    cal = result.to_json()  # the pair folder's calibration.json: its consistency and board edges
    fit, edges = cal.get("consistency") or {}, cal.get("board_edges") or {}
    shift = edges.get("mean_shift_p_value")
    return (f"planes {fit.get('variance_factor', float('nan')):.2f} (p = {fit.get('p_value', float('nan')):.2g})"
            + (f", outlines p = {shift:.2g}" if shift is not None else ""))


def projection_px(result, camera, truth: np.ndarray) -> float:
    """Where the used frames' LiDAR board points land in the image under the result (its camera model, which a
    wrong dataset.yaml makes wrong, and its estimate) against under the truth (true intrinsics and extrinsic):
    the median distance in pixels. What a user projecting the LiDAR into the image with that camera model gets."""
    from geometry.rotations import transform_points

    pts = [f.lidar.points for f in result.pair_frames[("cam0", "lidar0")] if f.usable]
    if not pts:
        return float("nan")
    p = np.vstack(pts)
    uv_est = result.camera_model("cam0").project(transform_points(result.T_camera_lidar, p))
    uv_true = camera.project(transform_points(truth, p))
    return float(np.median(np.linalg.norm(uv_est - uv_true, axis=1)))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--datasets", type=int, default=12, help="good datasets per configuration")
    ap.add_argument("--wrong", type=int, default=3, help="datasets per configuration and way of being wrong")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--only", default=None, metavar="TEXT", help="the configurations whose label holds TEXT")
    ap.add_argument("--ways", nargs="+", default=None, help="only these ways of being wrong (and good)")
    a = ap.parse_args()
    jobs = []
    with tempfile.TemporaryDirectory() as tmp:
        for label, kw in GOOD:
            if a.only and a.only not in label:
                continue
            jobs += [(label, kw, s, "good", tmp) for s in range(a.datasets)]
            for how in (WRONG_2D if kw.get("lidar") == "2d" else WRONG_3D):
                if a.ways is None or how in a.ways:
                    jobs += [(label, kw, 100 + s, how, tmp) for s in range(a.wrong)]
        with ProcessPoolExecutor(a.workers) as pool:
            rows = list(pool.map(trial, jobs))
    print(f"{a.datasets} good datasets per configuration (seeds 0..), {a.wrong} per way of being wrong (seeds 100..); "
          f"'off': the truth beyond d2 {OFF_D2} under the reported covariance")
    print(f"{'configuration':14s}{'data':>9s}{'n':>4s}{'OK':>5s}{'CHECK':>7s}{'UNTR.':>7s}{'refused':>9s}"
          f"{'off':>5s}{'off and OK':>12s}{'px':>7s}")
    for label, _ in GOOD:
        for how in ("good",) + WRONG_3D:
            sel = [r for r in rows if r["label"] == label and r["how"] == how]
            if not sel:
                continue
            c = Counter(r["level"] for r in sel)
            off = [r for r in sel if r["level"] != "refused" and not r["d2"] <= OFF_D2]
            print(f"{label:14s}{how:>9s}{len(sel):4d}{c['OK']:5d}{c['CHECK']:7d}{c['UNTRUSTED']:7d}{c['refused']:9d}"
                  f"{len(off):5d}{sum(r['level'] == 'OK' for r in off):12d}"
                  f"{np.nanmedian([r['px'] for r in sel]) if any(np.isfinite(r['px']) for r in sel) else np.nan:7.1f}")
    good = [r for r in rows if r["how"] == "good"]
    wrong_ok = [r for r in rows if r["level"] == "OK" and not r["d2"] <= OFF_D2]
    untrusted = [r for r in good if r["level"] == "UNTRUSTED"]
    fits = [r for r in good if r.get("p_planes") is not None]
    outlines = [r["p_outline"] for r in fits if r["p_outline"] is not None]
    if fits and outlines:
        print(f"good datasets' own fit: planes p from {min(r['p_planes'] for r in fits):.2g}, outlines p from "
              f"{min(outlines):.2g} (their smallest)")
    print(f"good datasets UNTRUSTED: {len(untrusted)} of {len(good)} ({100 * len(untrusted) / max(len(good), 1):.1f}%; "
          "target at most 1%)")
    print(f"answers off by more than 3 sd with an OK verdict: {len(wrong_ok)} (target 0)")
    print(f"  of them, with the LiDAR's board points landing {PX_OFF:g} px or more from where the truth puts them "
          f"(the median, under the result's camera model and estimate): {sum(r['px'] >= PX_OFF for r in wrong_ok)}")
    for r in untrusted + wrong_ok:
        print(f"  {r['label']} {r['how']} seed {r['seed']}: {r['level']}, d2 {r['d2']:.1f}, {r['px']:.1f} px; "
              f"{r.get('fit', '')}; {r['why']}")
    print("CHECK verdicts, good and wrong datasets:")
    for r in rows:
        if r["level"] == "CHECK":
            print(f"  {r['label']} {r['how']} seed {r['seed']}: d2 {r['d2']:.1f}, {r['px']:.1f} px; "
                  f"{r.get('fit', '')}; {r['why']}")


if __name__ == "__main__":
    main()
