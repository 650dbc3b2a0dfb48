"""LiDAR range model on whole simulated datasets without range errors: does `auto` add a term that is not there?
(make bench; `python benchmarks/bench_range_model_scenes.py [--datasets N] [--workers W]`).

Per configuration (scene x LiDAR): datasets of 10 poses rendered, ray-cast and calibrated end to end (images
searched, the board segmented, `auto`, no posterior) with no range error injected: the default scene (a board on
a stand in an empty room), an office (clutter, the board held by a person in 70% of the frames, some boards
partly outside the vertical field of view) and a hall; HDL-64E-, VLP-16- and OS1-64-like LiDARs, 2 cm range
noise. Printed: how often auto adds a range term, the mean squared Mahalanobis distance of the truth (6 ideal),
the share of datasets with a translation error beyond 4 reported standard deviations on some axis, the mean
plane-consistency variance factor (its overdispersion before any per-board plane error), and the RMS errors.

`--beyond-prior N`: then N datasets per LiDAR of the office scene (8 poses) whose per-ring offsets are drawn with
sd 15 mm, beyond the 10 mm prior of a LiDAR of no named family: terms held at 0, errors, the truth's d2 and the
verdicts (an off answer, d2 beyond 22.5, that reads `OK` is the failure that matters).

`--inject N`: then N datasets per recording variant (the clouds with or without a ring field, the intensity
with or without black/white contrast) of the default scene with a 3 cm offset, per-ring offsets drawn with sd
5 mm and 1 cm on the black squares injected, the LiDAR cycling through the three: how often each term is in the
chosen model and, when it is, in its 95% interval; the truth's mean d2.

`--dark-bias N`: then N datasets per LiDAR with the injected errors (ring field, contrast): the black-square
term's mean error (mm), mean error in its own standard deviations and the share of 95% intervals holding it, by
the engine and by its pair's own solve (which takes the mean of its placement's shifts off), and by both with
the board's returns kept within 4 robust standard deviations of its plane instead of 3
(``board_segmentation.NOISE_BAND_SIGMA``): a band centred on a plane fitted without the terms cuts the black
returns' far tail (they lie 1 cm behind) more than the white ones', which pulls the term towards 0.

`--long-offset N`: then N HDL-64E datasets of the default scene (10 poses) per variant: no range error, a 5 cm
offset, and a 5 cm offset with per-ring offsets (sd 6 mm) and 3 cm on the black squares. Each is measured once
and solved with the ring ends as measured and with those marked open used too (``board_edges.open_ends``: a ring
that goes on in the board's plane beyond its end, where the board's window cut returns that a range offset spread
beyond the board's size): the truth's mean d2 (6 ideal), over every dataset and over those reading OK, and the
verdicts.
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

LIDARS = ("hdl64e", "vlp16", "os64")
SCENES = ("default", "office", "hall")
POSES = 10


def _trial(args) -> dict:
    from estimators import calibrate
    from estimators.errors import LidarcamError
    from estimators.io.dataset import load_dataset
    from estimators.simulation.simulator import simulate_dataset
    from geometry.rotations import T_inverse, T_log, rotation_error

    lidar, scene, seed, tmp = args
    path = Path(tmp) / f"{lidar}_{scene}_{seed}"
    simulate_dataset(path, POSES, seed, lidar, scene=scene, overwrite=True)
    try:
        res = calibrate(path, rng=np.random.default_rng(seed), posterior=None)
    except LidarcamError as exc:  # a refused calibration is a result of the benchmark
        return {"failed": str(exc)[:120]}
    res_truth = load_dataset(path).ground_truth()
    T = res.T_camera_lidar
    xi = T_log(T_inverse(T) @ res_truth)
    sd = np.sqrt(np.diag(res.covariance))
    return {"chosen": res.range_models.get("lidar0", {}).get("model", "none"),
            "d2": float(xi @ np.linalg.solve(res.covariance, xi)),
            "max_sigmas": float(np.max(np.abs(xi[3:]) / sd[3:])),
            "rot": float(np.degrees(rotation_error(T[:3, :3], res_truth[:3, :3]))),
            "trans": float(1000 * np.linalg.norm(T[:3, 3] - res_truth[:3, 3])),
            "vf": float(res.pair_results[("cam0", "lidar0")].refinement.variance_factor)}  # the pair's planes


def _injected(args) -> dict:
    import json

    from estimators import calibrate
    from estimators.errors import LidarcamError
    from estimators.io.dataset import load_dataset
    from estimators.simulation.simulator import simulate_dataset
    from geometry.rotations import T_inverse, T_log

    lidar, ring, intensity, seed, tmp = args
    path = Path(tmp) / f"inj_{lidar}_{ring}_{intensity}_{seed}"
    simulate_dataset(path, POSES, seed, lidar, range_bias=(0.03, 0.005, 0.01), intensity=intensity, ring_field=ring,
                     overwrite=True)
    try:
        res = calibrate(path, rng=np.random.default_rng(seed), posterior=None)
    except LidarcamError as exc:
        return {"failed": str(exc)[:120]}
    truth = load_dataset(path).ground_truth()
    bias = json.loads((path / "ground_truth.json").read_text())["range_bias"]
    xi = T_log(T_inverse(res.T_camera_lidar) @ truth)
    record = res.range_models.get("lidar0", {})  # the terms as the joint graph estimates them
    terms = record.get("terms") or {}
    names = tuple(terms)
    v, sd = np.array([t["value_m"] for t in terms.values()]), np.array([t["sd_m"] for t in terms.values()])
    out = {"lidar": lidar, "d2": float(xi @ np.linalg.solve(res.covariance, xi)),
           "chosen": record.get("model", "none"),
           "offset": bool(abs(v[0] - bias["offset_m"]) <= 1.96 * sd[0]) if "offset" in names else None,
           "dark": (bool(abs(v[names.index("dark")] - bias["dark_m"]) <= 1.96 * sd[names.index("dark")])
                    if "dark" in names else None)}
    return out


def _beyond_prior(args) -> dict:
    from estimators import calibrate
    from estimators.errors import LidarcamError
    from estimators.io.dataset import load_dataset
    from estimators.simulation.simulator import simulate_dataset
    from geometry.rotations import T_inverse, T_log

    lidar, seed, tmp = args
    path = Path(tmp) / f"beyond_{lidar}_{seed}"
    simulate_dataset(path, 8, seed, lidar, scene="office", range_bias=(0.0, 0.015, 0.0), overwrite=True)
    try:
        res = calibrate(path, rng=np.random.default_rng(seed), posterior=None)
    except LidarcamError as exc:
        return {"failed": str(exc)[:120]}
    xi = T_log(T_inverse(res.T_camera_lidar) @ load_dataset(path).ground_truth())
    return {"held": bool(res.range_models.get("lidar0", {}).get("held_at_prior")),
            "rot": float(np.degrees(np.linalg.norm(xi[:3]))),
            "trans": float(1000 * np.linalg.norm(xi[3:])), "d2": float(xi @ np.linalg.solve(res.covariance, xi)),
            "verdict": res.verdict.line.split(":")[0]}


LONG_OFFSETS = {"none": None, "offset 5 cm": (0.05, 0.0, 0.0), "offset, rings, black": (0.05, 0.006, 0.03)}


def _long_offset(args) -> dict:
    from dataclasses import replace

    from estimators import calibrate, measure
    from estimators.errors import LidarcamError
    from estimators.io.dataset import load_dataset
    from estimators.simulation.simulator import simulate_dataset
    from geometry.rotations import T_inverse, T_log

    variant, seed, tmp = args
    path = Path(tmp) / f"long_{variant.split()[0]}_{seed}"
    simulate_dataset(path, POSES, seed, "hdl64e", range_bias=LONG_OFFSETS[variant], overwrite=True)
    m = measure(path, np.random.default_rng(seed))
    open_kept = replace(m, frames=tuple(f if f.lidar is None else replace(f, lidar=replace(f.lidar, open_ends=None))
                                        for f in m.frames))
    truth = load_dataset(path).ground_truth()
    out = {"open": sum(int(f.lidar.open_ends.sum()) for f in m.frames
                       if f.lidar is not None and f.lidar.open_ends is not None)}
    for key, meas in (("marked", m), ("all", open_kept)):
        try:
            res = calibrate(meas, rng=np.random.default_rng(seed), posterior=None)
        except LidarcamError as exc:
            return {"failed": str(exc)[:120]}
        xi = T_log(T_inverse(res.T_camera_lidar) @ truth)
        out[key] = (float(xi @ np.linalg.solve(res.covariance, xi)), res.verdict.line.split(":")[0])
    return out


def long_offset(args) -> None:
    print(f"A LiDAR ranging long, its boards' ring ends: {args.long_offset} HDL-64E datasets per variant, default "
          f"scene, {POSES} poses, 2 cm range noise, auto; solved with the open ring ends left out (as calibrate does) "
          "and used")
    print(f"{'variant':22s}{'open/frame':>11s}{'ends':>9s}{'d2':>7s}{'d2 OK':>7s}{'>22.5':>7s}{'OK':>5s}{'CHECK':>7s}"
          f"{'UNTR.':>7s}{'off, OK':>9s}{'refused':>9s}")
    with tempfile.TemporaryDirectory() as tmp, ProcessPoolExecutor(args.workers) as pool:
        for variant in LONG_OFFSETS:
            rows = list(pool.map(_long_offset, [(variant, 51 + s, tmp) for s in range(args.long_offset)]))
            ok = [r for r in rows if "failed" not in r]
            for key, label in (("marked", "left out"), ("all", "used")):
                d2 = np.array([r[key][0] for r in ok])
                verdict = np.array([r[key][1] for r in ok])
                per_frame = f"{np.mean([r['open'] for r in ok]) / POSES:.1f}" if key == "marked" else ""
                print(f"{variant if key == 'marked' else '':22s}{per_frame:>11s}{label:>9s}"
                      f"{d2.mean():7.1f}{d2[verdict == 'OK'].mean() if (verdict == 'OK').any() else np.nan:7.1f}"
                      f"{int((d2 > 22.5).sum()):7d}" + "".join(f"{int((verdict == v).sum()):{w}d}" for v, w in
                                                               (("OK", 5), ("CHECK", 7), ("UNTRUSTED", 7)))
                      + f"{int(((d2 > 22.5) & (verdict == 'OK')).sum()):9d}{len(rows) - len(ok):9d}")
    print("open/frame: ring ends marked open per frame; ends: the open ones left out or used; d2: the truth's mean "
          "squared Mahalanobis distance under the reported covariance (6 ideal; 22.5 holds 99.9%), over every dataset "
          "and over those reading OK; >22.5: datasets beyond; OK, CHECK, UNTR.: the verdicts; off, OK: beyond 22.5 "
          "and reading OK")


def beyond_prior(args) -> None:
    print(f"Range terms beyond their prior: {args.beyond_prior} datasets per LiDAR, office scene, 8 poses, per-ring "
          "offsets drawn with sd 15 mm (the prior: 10 mm), 2 cm range noise, auto")
    print(f"{'lidar':8s}{'held':>7s}{'rot deg':>9s}{'trans mm':>10s}{'d2':>8s}{'d2>22.5':>9s}{'OK':>6s}{'CHECK':>7s}"
          f"{'UNTR.':>7s}{'off, OK':>9s}{'refused':>9s}")
    with tempfile.TemporaryDirectory() as tmp, ProcessPoolExecutor(args.workers) as pool:
        for lidar in LIDARS:
            rows = list(pool.map(_beyond_prior, [(lidar, 11000 + s, tmp) for s in range(args.beyond_prior)]))
            ok = [r for r in rows if "failed" not in r]

            def share(pred):
                return 100 * np.mean([pred(r) for r in ok])

            print(f"{lidar:8s}{share(lambda r: r['held']):6.0f}%{np.sqrt(np.mean([r['rot'] ** 2 for r in ok])):9.3f}"
                  f"{np.sqrt(np.mean([r['trans'] ** 2 for r in ok])):10.1f}{np.median([r['d2'] for r in ok]):8.1f}"
                  f"{share(lambda r: r['d2'] > 22.5):8.0f}%"
                  + "".join(f"{share(lambda r, v=v: r['verdict'] == v):5.0f}%" if v == "OK" else
                            f"{share(lambda r, v=v: r['verdict'] == v):6.0f}%" for v in ("OK", "CHECK", "UNTRUSTED"))
                  + f"{share(lambda r: r['d2'] > 22.5 and r['verdict'] == 'OK'):8.0f}%{len(rows) - len(ok):9d}")
    print("held: datasets where a term beyond 3 prior sds is held at 0; rot, trans: RMS errors; d2: median squared "
          "Mahalanobis distance of the truth (6 ideal; 22.5 holds 99.9%); OK, CHECK, UNTR.: the verdicts; off, OK: "
          "d2 beyond 22.5 and the verdict OK")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--datasets", type=int, default=23, help="per configuration (default 23: 207 in all)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--inject", type=int, default=0, metavar="N",
                    help="instead: N datasets per recording variant with injected range errors")
    ap.add_argument("--beyond-prior", type=int, default=0, metavar="N",
                    help="instead: N datasets per LiDAR whose per-ring offsets exceed their prior")
    ap.add_argument("--dark-bias", type=int, default=0, metavar="N",
                    help="instead: N datasets per LiDAR: the black-square term's error, the noise band at 3 and 4 sd")
    ap.add_argument("--long-offset", type=int, default=0, metavar="N",
                    help="instead: N HDL-64E datasets per variant ranging 5 cm long: its open ring ends left out, used")
    args = ap.parse_args()
    if args.long_offset:
        long_offset(args)
        return
    if args.dark_bias:
        dark_bias(args)
        return
    if args.beyond_prior:
        beyond_prior(args)
        return
    if args.inject:
        injected(args)
        return
    print(f"Range model on whole simulated datasets without range errors: {args.datasets} datasets per "
          f"configuration, {POSES} poses, 2 cm range noise, auto")
    print(f"{'configuration':22s}{'terms added':>12s}{'d2':>7s}{'>4sd':>7s}{'vf':>7s}{'rot deg':>9s}{'trans mm':>10s}"
          f"{'refused':>9s}")
    every = []
    with tempfile.TemporaryDirectory() as tmp, ProcessPoolExecutor(args.workers) as pool:
        for scene in SCENES:
            for lidar in LIDARS:
                rows = list(pool.map(_trial, [(lidar, scene, 7000 + s, tmp) for s in range(args.datasets)]))
                ok = [r for r in rows if "failed" not in r]
                every += ok
                added = np.mean([r["chosen"] != "none" for r in ok])
                print(f"{scene + ' ' + lidar:22s}{100 * added:11.1f}%{np.mean([r['d2'] for r in ok]):7.1f}"
                      f"{100 * np.mean([r['max_sigmas'] > 4 for r in ok]):6.1f}%{np.mean([r['vf'] for r in ok]):7.2f}"
                      f"{np.sqrt(np.mean([r['rot'] ** 2 for r in ok])):9.3f}"
                      f"{np.sqrt(np.mean([r['trans'] ** 2 for r in ok])):10.1f}{len(rows) - len(ok):9d}")
    print(f"{'all':22s}{100 * np.mean([r['chosen'] != 'none' for r in every]):11.1f}%"
          f"{np.mean([r['d2'] for r in every]):7.1f}{100 * np.mean([r['max_sigmas'] > 4 for r in every]):6.1f}%"
          f"{np.mean([r['vf'] for r in every]):7.2f}  ({len(every)} datasets calibrated)")
    print("terms added: share of datasets where auto adds a range term (none is there); d2: mean squared Mahalanobis "
          "distance of the truth under the reported covariance (6 ideal); >4sd: datasets with a translation error "
          "beyond 4 reported standard deviations on some axis; vf: mean plane-consistency variance factor; refused: "
          "datasets the pipeline refused (too few usable frames)")


def _dark_error(args) -> dict:
    import json

    from estimators import calibrate
    from estimators.errors import LidarcamError
    from estimators.lidar import board_segmentation
    from estimators.simulation.simulator import simulate_dataset

    lidar, band, seed, tmp = args
    board_segmentation.NOISE_BAND_SIGMA = band  # a worker runs tasks of either band
    path = Path(tmp) / f"dark_{lidar}_{band}_{seed}"
    simulate_dataset(path, POSES, seed, lidar, range_bias=(0.03, 0.005, 0.01), overwrite=True)
    try:
        res = calibrate(path, rng=np.random.default_rng(seed), posterior=None)
    except LidarcamError as exc:
        return {"failed": str(exc)[:120]}
    true = json.loads((path / "ground_truth.json").read_text())["range_bias"]["dark_m"]
    out = {}
    engine = (res.range_models.get("lidar0", {}).get("terms") or {}).get("dark")
    if engine is not None:
        out["engine"] = (engine["value_m"] - true, engine["sd_m"])
    fit = res.pair_results[("cam0", "lidar0")].refinement.range_model
    if fit is not None and "dark" in fit.names:
        k = fit.names.index("dark")
        out["pair"] = (fit.values_m[k] - true, fit.std_m[k])
    return out


def dark_bias(args) -> None:
    print(f"The black-square term's error on whole simulated datasets (3 cm offset, 5 mm per ring, 1 cm on black "
          f"squares; ring field, contrast): {args.dark_bias} datasets per LiDAR, {POSES} poses, default scene, 2 cm "
          "range noise, auto")
    print(f"{'lidar':8s}{'band':>5s}{'engine: err mm':>16s}{'z':>7s}{'in 95%':>8s}{'pair: err mm':>14s}{'z':>7s}"
          f"{'in 95%':>8s}{'terms':>7s}")
    with tempfile.TemporaryDirectory() as tmp, ProcessPoolExecutor(args.workers) as pool:
        for lidar in LIDARS:
            for band in (3.0, 4.0):
                rows = list(pool.map(_dark_error, [(lidar, band, 9000 + 3 * s + LIDARS.index(lidar), tmp)
                                                   for s in range(args.dark_bias)]))
                line = f"{lidar:8s}{band:5.0f}"
                for who, width in (("engine", 16), ("pair", 14)):
                    e = np.array([r[who][0] for r in rows if who in r])
                    z = np.array([r[who][0] / r[who][1] for r in rows if who in r])
                    line += (f"{1000 * e.mean():+{width}.2f}{z.mean():+7.2f}{100 * np.mean(np.abs(z) < 1.96):7.0f}%"
                             if len(e) else f"{'-':>{width}s}{'-':>7s}{'-':>8s}")
                print(f"{line}{sum('engine' in r for r in rows):7d}")
    print("err: the term's mean error (estimate - injected); z: its mean in the term's own standard deviations; "
          "in 95%: "
          "share of the intervals holding the injected value; band: the board's returns kept within this many robust "
          "standard deviations of its plane (3: the measurement's); terms: datasets whose engine kept the term")


def injected(args) -> None:
    print(f"Range model on whole simulated datasets with injected range errors (3 cm offset, 5 mm per ring, 1 cm on "
          f"black squares): {args.inject} datasets per variant, {POSES} poses, default scene, 2 cm range noise, "
          "LiDARs hdl64e, vlp16, os64 in turn, auto")
    print(f"{'variant':34s}{'offset kept':>12s}{'in 95%':>8s}{'dark kept':>10s}{'in 95%':>8s}"
          + "".join(f"{lidar:>8s}" for lidar in LIDARS) + f"{'d2':>7s}{'refused':>9s}")
    with tempfile.TemporaryDirectory() as tmp, ProcessPoolExecutor(args.workers) as pool:
        for ring in (True, False):
            for intensity in ("contrast", "flat"):
                rows = list(pool.map(_injected, [(LIDARS[s % 3], ring, intensity, 9000 + s, tmp)
                                                 for s in range(args.inject)]))
                ok = [r for r in rows if "failed" not in r]

                def kept(key):
                    return np.mean([r[key] is not None for r in ok])

                def covered(key, lidar=None):
                    h = [r[key] for r in ok if r[key] is not None and lidar in (None, r["lidar"])]
                    return np.mean(h) if h else np.nan

                label = f"{'ring field' if ring else 'no ring field'}, {intensity} intensity"
                print(f"{label:34s}{100 * kept('offset'):11.0f}%{100 * covered('offset'):7.1f}%"
                      f"{100 * kept('dark'):9.0f}%{100 * covered('dark'):7.1f}%"
                      + "".join(f"{100 * covered('dark', lidar):7.1f}%" for lidar in LIDARS)
                      + f"{np.mean([r['d2'] for r in ok]):7.1f}{len(rows) - len(ok):9d}")
    print("in 95%: share of the datasets keeping a term whose 95% interval holds the injected value; hdl64e, vlp16, "
          "os64: the black-square term's by LiDAR; d2: mean squared Mahalanobis distance of the truth (6 ideal)")


if __name__ == "__main__":
    main()
