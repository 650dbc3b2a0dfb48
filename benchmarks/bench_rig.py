"""Rigs in one graph against each camera-LiDAR pair alone, on simulated rig folders
(make bench; `python benchmarks/bench_rig.py [--rigs N] [--cameras C] [--lidars L] [--scanners S] [--poses P]
[--posterior N] [--range-offset M] [--range-bias OFF,RING,DARK] [--lidar L] [--edges | --no-edges] [--timed K]`).

Each rig (`simulation.rig_simulator`): C cameras and an HDL-64E-like LiDAR, P board poses sampled in the first
camera's view: cameras 1 and 2 pinhole beside the first; 3 a fisheye looking backwards, 4 a fisheye looking right,
5 a pinhole looking left, each with boards of its own (P/2, in its view and the LiDAR's). Every camera sees the
frames whose board lies wholly in its image. `--lidars 2` adds a VLP-16-like LiDAR, `--scanners 1` a 2D scanner.
`--range-offset M` adds a range offset of M metres to every return of lidar0 (each LiDAR's range terms are tested
and, where included, estimated: `rig_calibration.calibrate_rig`'s range model, summarised per LiDAR);
`--range-bias OFF,RING,DARK` injects the single pair's range errors into lidar0 instead (a global offset, per-ring
offsets drawn with sd RING, the black squares' offset) and adds each term's error over its sd; `--lidar` sets lidar0's
beams (HDL-64E, VLP-16 or OS1-64 like). `--posterior N`
samples the rig's posterior (`solvers.rig_posterior`, N effective samples) and adds the mean d2 of the truth under
each pair's posterior covariance and the posterior's time. `--edges` puts every LiDAR's board edges in the graph
(the bound then has them too), as the default does a 2D scanner's segment ends; `--no-edges` the planes alone.
Rendered and ray-cast, then calibrated from its folder (`rig_calibration.calibrate_rig`). Per pair: the RMS
rotation and translation error of the joint graph and of the pair alone (camera-LiDAR pairs), the mean frames
the camera saw, the joint errors over the RMS Cramer-Rao bound (`rig_graph.rig_bound`: the graph's information at
the truth, for the views measured, at the noise levels the graph used), and the mean squared Mahalanobis
distance of the truth under each covariance (6 ideal). The
time is measure + solve per rig, with one worker per rig and two rigs at a time on this machine's 2 cores;
`--timed K` then times the first K rigs once more one at a time with both cores, as `lidarcam calibrate` runs one
rig (its default 2 workers; the modules imported before the clock starts); `--rigs 0 --timed K` times them
alone, without the accuracy table.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def _one(args) -> dict:
    from estimators.io.rig_dataset import load_rig
    from estimators.rig_calibration import calibrate_rig
    from estimators.simulation.range_bias import RangeBias
    from estimators.simulation.rig_simulator import simulate_rig
    from estimators.solvers.rig_graph import pair_transform
    from geometry.rotations import T_log

    seed, cameras, poses, lidars, scanners, samples, offset, edges, bias, lidar = args
    with tempfile.TemporaryDirectory() as tmp:
        folder = simulate_rig(Path(tmp) / "rig", poses, seed, cameras, lidar, lidars=lidars, scanners=scanners,
                              range_offset_m=offset, range_bias=bias)
        gt = json.loads((folder / "ground_truth.json").read_text())
        rig = load_rig(folder)
        t0 = time.perf_counter()
        res = calibrate_rig(rig, np.random.default_rng(seed), workers=1, samples=samples, edges=edges)
        seconds = time.perf_counter() - t0
    # The worker's peak resident memory so far (simulating included: an upper bound of the calibration's).
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    out = {"frames_total": len(rig.sensor("lidar0").stems), "seconds": seconds,
           "posterior_s": res.timings_s.get("posterior", 0.0), "peak_mb": peak_mb, "pairs": {},
           "range_models": {n: (r["model"], r.get("value_m"), r.get("sd_m"))
                            for n, r in res.range_models.items()}}
    if bias is not None and "terms" in res.range_models.get("lidar0", {}):
        truth = RangeBias.from_record(gt["range_bias"]["lidar0"])
        out["terms_z"] = {n: (v["value_m"] - truth.term(n)) / v["sd_m"]
                          for n, v in res.range_models["lidar0"]["terms"].items()}
    bound = _bound(res, gt)
    for a, b in res.pairs():
        truth = np.linalg.inv(np.array(gt[f"T_cam0_{a}"])) @ np.array(gt[f"T_cam0_{b}"])
        rows = {}
        estimates = {"joint": res.solution.transform(a, b)}
        if (a, b) in res.pairwise:
            estimates["pair"] = res.pairwise[(a, b)][:2]
        for kind, (T, C) in estimates.items():
            xi = T_log(np.linalg.inv(T) @ truth)
            rows[kind] = (float(xi[:3] @ xi[:3]), float(xi[3:] @ xi[3:]), float(xi @ np.linalg.solve(C, xi)))
        if res.posterior is not None:
            xi = T_log(np.linalg.inv(estimates["joint"][0]) @ truth)
            rows["posterior"] = float(xi @ np.linalg.solve(np.cov(res.posterior.pair_samples(a, b), rowvar=False), xi))
        names = res.solution.names
        idx = np.r_[6 * names.index(a):6 * names.index(a) + 6, 6 * names.index(b):6 * names.index(b) + 6]
        _, Cb = pair_transform(np.array(gt[f"T_cam0_{a}"]), np.array(gt[f"T_cam0_{b}"]), bound[np.ix_(idx, idx)])
        rows["bound"] = (float(np.trace(Cb[:3, :3])), float(np.trace(Cb[3:, 3:])))
        out["pairs"][f"T_{a}_{b}"] = {"rows": rows, "frames": len(res.frames_used.get(a, ()))}
    return out


def numbered_as(T_hat: np.ndarray, T_true: np.ndarray, flip: np.ndarray | None) -> np.ndarray:
    """The true board pose numbered as the estimate ``T_hat`` (a checkerboard that looks the same turned, ``flip``
    not None, may be numbered from its other end): ``T_true`` or ``T_true @ flip``, whichever is nearer."""
    from geometry.rotations import T_log

    options = [T_true] + ([T_true @ flip] if flip is not None else [])
    return min(options, key=lambda T: np.linalg.norm(T_log(np.linalg.inv(T_hat) @ T)))


def _bound(res, gt, intrinsics: dict | None = None) -> np.ndarray:
    """The graph's information at the truth (every sensor's and board's pose), at the noise levels the graph used:
    the Cramer-Rao bound of the rig's measurement model for the views measured (``rig_graph.rig_bound``). A board
    numbered from its other end (a checkerboard that looks the same turned) is taken turned likewise.
    ``intrinsics`` (camera -> true params): the cameras' intrinsics unknowns too, at these values. The bound is the
    Gaussian model's: without the robust loss, whose weights at the truth would depend on the range terms' values
    there (0 in the bound's graph, not the injected errors); and without the per-board plane errors and the boards'
    scatter the calibration estimated from the data (the simulation has none): the measurement model's bound (the
    points' range noise, the corners, the pattern's scale error), not the estimate's own noise model's."""
    from dataclasses import replace

    from estimators.pipeline.rig_measurement import pattern_flip
    from estimators.solvers.rig_graph import rig_bound

    sol = res.solution
    flip = pattern_flip(res.rig.board)
    boards = {st: numbered_as(B, np.array(gt["T_cam0_board"][st]), flip) for st, B in sol.T_ref_board.items()}
    truth = {n: np.array(gt[f"T_cam0_{n}"]) for n in sol.names}
    lidars = [replace(lv, robust=None, tau_m=0.0, plane_error=None if lv.plane_error is None else
                      {st: replace(pe, floor_m=0.0) for st, pe in lv.plane_error.items()}) for lv in res.lidar_views]
    return rig_bound(sol.names, "cam0", list(res.camera_views), lidars,
                     truth, boards, sol.noise_scale, intrinsics)


def _timed(seed: int, cameras, poses, lidars, scanners, samples, offset, edges, bias, lidar) -> float:
    """Measure + solve (+ posterior) of rig ``seed`` in this process with 2 workers, as the command runs it."""
    from estimators.io.rig_dataset import load_rig
    from estimators.rig_calibration import calibrate_rig
    from estimators.simulation.rig_simulator import simulate_rig
    import emcee  # noqa: F401  (imported by the posterior: not part of a rig's time here)

    with tempfile.TemporaryDirectory() as tmp:
        folder = simulate_rig(Path(tmp) / "rig", poses, seed, cameras, lidar, lidars=lidars, scanners=scanners,
                              range_offset_m=offset, range_bias=bias)
        rig = load_rig(folder)
        t0 = time.perf_counter()
        calibrate_rig(rig, np.random.default_rng(seed), workers=2, samples=samples, edges=edges)
        return time.perf_counter() - t0


def _print_timed(args, bias) -> None:
    """``--timed K``: rigs 0 to K-1 timed one at a time with both cores, as `lidarcam calibrate` runs one."""
    t = [_timed(s, args.cameras, args.poses, args.lidars, args.scanners, args.posterior, args.range_offset,
                args.edges, bias, args.lidar) for s in range(args.timed)]
    what = "measure + solve + posterior" if args.posterior > 0 else "measure + solve"
    print(f"{what}, one rig at a time with both cores (as `lidarcam calibrate`, 2 workers), {args.timed} rigs: "
          f"median {np.median(t):.1f} s, max {np.max(t):.1f} s; each (s): " + ", ".join(f"{v:.1f}" for v in t))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--rigs", type=int, default=20)
    ap.add_argument("--cameras", type=int, default=3)
    ap.add_argument("--poses", type=int, default=12)
    ap.add_argument("--lidars", type=int, default=1)
    ap.add_argument("--scanners", type=int, default=0)
    ap.add_argument("--posterior", type=int, default=0, metavar="N", help="effective posterior samples (0: none)")
    ap.add_argument("--range-offset", type=float, default=0.0, metavar="M",
                    help="a range offset (m) on every return of lidar0")
    ap.add_argument("--range-bias", default=None, metavar="OFF,RING,DARK",
                    help="range errors (m) injected into lidar0: a global offset, per-ring offsets drawn with this "
                         "sd, the black squares' offset (as the single pair's --range-bias)")
    ap.add_argument("--lidar", default="hdl64e", choices=["hdl64e", "vlp16", "os64"], help="lidar0's beams")
    edges = ap.add_mutually_exclusive_group()
    edges.add_argument("--edges", action="store_true", default=None,
                       help="every LiDAR's board edges in the graph (default: a 2D scanner's segment ends)")
    edges.add_argument("--no-edges", dest="edges", action="store_false", default=None, help="the boards' planes alone")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--timed", type=int, default=0, metavar="K",
                    help="then time the first K rigs one at a time with both cores, as the command runs a rig")
    args = ap.parse_args()
    bias = tuple(float(v) for v in args.range_bias.split(",")) if args.range_bias else None
    if args.rigs == 0:  # ``--rigs 0 --timed K``: the timing alone, on a machine left otherwise idle
        _print_timed(args, bias)
        return
    with ProcessPoolExecutor(args.workers) as pool:
        runs = list(pool.map(_one, [(s, args.cameras, args.poses, args.lidars, args.scanners, args.posterior,
                                     args.range_offset, args.edges, bias, args.lidar) for s in range(args.rigs)]))
    more = (" + a VLP-16-like LiDAR" if args.lidars == 2 else "") + (" + a 2D scanner" if args.scanners else "")
    more += {True: "; every LiDAR's board edges in the graph (--edges)", False: "; planes alone (--no-edges)",
             None: "; a 2D scanner's segment ends in the graph" if args.scanners else ""}[args.edges]
    frames = np.mean([r["frames_total"] for r in runs])
    family = {"hdl64e": "an HDL-64E", "vlp16": "a VLP-16", "os64": "an OS1-64"}[args.lidar]
    print(f"{args.rigs} simulated rigs: {args.cameras} cameras + {family}-like LiDAR{more}, {args.poses} board poses "
          f"in the first camera's view, {frames:.0f} frames in all (the cameras that do not share its view have "
          "boards of their own)")
    post = args.posterior > 0
    print(f"{'pair':16s}{'frames':>8s}{'joint rot deg':>15s}{'trans mm':>10s}{'rot/CRB':>9s}{'tr/CRB':>8s}{'d2':>7s}"
          + (f"{'d2 post':>8s}" if post else "") + f"{'alone rot deg':>15s}{'trans mm':>10s}{'d2':>9s}")
    for name in runs[0]["pairs"]:
        rows = [r["pairs"][name] for r in runs]
        frames = np.mean([r["frames"] for r in rows])

        def rms(kind, k):
            return np.sqrt(np.mean([r["rows"][kind][k] for r in rows if kind in r["rows"]]))

        joint = (f"{np.degrees(rms('joint', 0)):15.4f}{1000 * rms('joint', 1):10.2f}"
                 f"{rms('joint', 0) / rms('bound', 0):9.2f}{rms('joint', 1) / rms('bound', 1):8.2f}"
                 f"{np.mean([r['rows']['joint'][2] for r in rows]):7.2f}")
        # A camera-LiDAR pair is solved alone where they share 3 usable frames: its columns are over those rigs.
        solved = sum("pair" in r["rows"] for r in rows)
        alone = (f"{np.degrees(rms('pair', 0)):15.4f}{1000 * rms('pair', 1):10.2f}"
                 f"{np.mean([r['rows']['pair'][2] for r in rows if 'pair' in r['rows']]):9.2f}"
                 + (f"  (in {solved} rigs)" if solved < len(rows) else "")) if solved else \
            f"{'-':>15s}{'-':>10s}{'-':>9s}"
        if post:
            joint += f"{np.mean([r['rows']['posterior'] for r in rows]):8.2f}"
        print(f"{name:16s}{frames:8.1f}{joint}{alone}")
    t = [r["seconds"] for r in runs]
    what = "measure + solve + posterior" if post else "measure + solve"
    print(f"{what} per rig: median {np.median(t):.1f} s, max {np.max(t):.1f} s (one worker per rig); peak resident "
          f"memory of a worker (simulating included) {max(r['peak_mb'] for r in runs):.0f} MB")
    if post:
        tp = [r["posterior_s"] for r in runs]
        print(f"of which the posterior: median {np.median(tp):.1f} s, max {np.max(tp):.1f} s")
    if args.timed:
        _print_timed(args, bias)
    for name in runs[0]["range_models"]:
        models = [r["range_models"][name] for r in runs]
        truth = args.range_offset + (bias[0] if bias else 0.0) if name == "lidar0" else 0.0
        chosen = {m: sum(c[0] == m for c in models) for m in ("per-ring", "offset+dark", "full")}
        line = (f"{name}: range offset (true {1000 * truth:.0f} mm) included by the tests in "
                f"{sum(m[0] != 'none' for m in models)} of {len(models)} rigs (per-ring offsets in "
                f"{chosen['per-ring'] + chosen['full']}, black squares in {chosen['offset+dark'] + chosen['full']})")
        err = np.array([m[1] - truth for m in models if m[0] != "none"])
        if err.size:
            sd = np.array([m[2] for m in models if m[0] != "none"])
            line += (f"; where included, its RMS error {1000 * np.sqrt(np.mean(err**2)):.1f} mm, mean sd "
                     f"{1000 * np.mean(sd):.1f} mm, mean d2 {np.mean((err / sd) ** 2):.2f} (1 ideal)")
        print(line)
    if bias is not None:
        z = [r["terms_z"] for r in runs if "terms_z" in r]
        full = sum(r["range_models"]["lidar0"][0] == "full" for r in runs)
        print(f"lidar0's injected errors (offset {1000 * bias[0]:.0f} mm, rings drawn with sd {1000 * bias[1]:.0f} mm, "
              f"black squares {1000 * bias[2]:.0f} mm): every term (full) chosen in {full} of {len(runs)} rigs")
        for name in ("offset", "dark"):
            v = np.array([d[name] for d in z if name in d])
            if v.size:
                print(f"  {name}: z (estimate - truth over its sd) mean {np.mean(v):+.2f}, RMS "
                      f"{np.sqrt(np.mean(v**2)):.2f} (1 ideal), beyond 3 in {np.sum(np.abs(v) > 3)} of {v.size}")
        rings = np.concatenate([[v for n, v in d.items() if n.startswith("ring ")] for d in z] or [[]])
        if rings.size:
            print(f"  ring terms: RMS z {np.sqrt(np.mean(rings**2)):.2f} over {rings.size} (below 1: their prior sd, a "
                  "fifth of the range accuracy, is wider than the sd they were drawn with)")


if __name__ == "__main__":
    main()
