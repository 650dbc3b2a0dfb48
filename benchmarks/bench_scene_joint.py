"""The scene's term joined to the boards' graph (``calibrate --scene``) against simulated truth (make bench;
`python benchmarks/bench_scene_joint.py [--scenes N] [--workers W] [--seed S]`).

Each scene: 10 board poses (``simulate_dataset``) in the board scenes' office (``scene="office"``: the space
before the camera kept clear for the boards) or in a furnished room (``scene="furnished"``: the scene check's
rooms about a still rig, the furniture kept off the lines of sight to the boards), seen by a VLP-16- and a
64-beam LiDAR in turn, calibrated by the engine (``estimators.calibrate``, no posterior sampled: the Laplace
covariance) and then given the scene's term (``pipeline.scene_witness.with_scene``, the board left out).
Printed per LiDAR: how often the term is joined and how often the test says the two witnesses disagree; the
boards' and the joint estimates' errors (rotation, translation, and along the boards' weak direction) and
NEES (6 dof) over the scenes joined; and the scene's own error where it was not.
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

MODELS = ("vlp16", "os64")
SHIFT_MM = 20


def _errors(T: np.ndarray, C: np.ndarray, truth: np.ndarray, u: np.ndarray) -> dict:
    from geometry.rotations import T_inverse, T_log

    xi = T_log(T_inverse(T) @ truth)
    return {"rot_deg": float(np.degrees(np.linalg.norm(xi[:3]))),
            "trans_mm": float(1000 * np.linalg.norm(T[:3, 3] - truth[:3, 3])),
            "weak_mm": float(1000 * u @ (T[:3, 3] - truth[:3, 3])),
            "nees": float(xi @ np.linalg.solve(C, xi))}


def _trial(job: tuple[str, int]) -> dict:
    import json
    from dataclasses import replace

    import estimators as lc
    from estimators.errors import LidarcamError
    from estimators.pipeline.scene_witness import with_scene
    from estimators.simulation.simulator import simulate_dataset

    generator, seed = job
    model = MODELS[seed % 2]
    row = {"generator": generator, "seed": seed, "model": model}
    with tempfile.TemporaryDirectory() as tmp:
        simulate_dataset(Path(tmp) / "ds", n_poses=10, seed=seed, lidar=model, scene=generator)
        truth = np.array(json.loads((Path(tmp) / "ds" / "ground_truth.json").read_text())["T_camera_lidar"])
        t0 = time.perf_counter()
        try:
            result = lc.calibrate(Path(tmp) / "ds", rng=np.random.default_rng(seed), posterior=None)
        except LidarcamError as exc:
            return {**row, "refused": exc.problem}
        t1 = time.perf_counter()
        w = with_scene(result, np.random.default_rng(seed)).scene[("cam0", "lidar0")]
        row["seconds_scene"] = time.perf_counter() - t1
        row["seconds_boards"] = t1 - t0
        # The boards' estimate moved along its weak direction by SHIFT_MM, to one side or the other: does the
        # scene's term say CHECK?
        sol = result.solution
        T = sol.T_ref["lidar0"].copy()
        T[:3, 3] += (1 if seed % 4 < 2 else -1) * SHIFT_MM / 1000 * w.weak_direction()
        moved = replace(result, solution=replace(sol, T_ref={**sol.T_ref, "lidar0": T}))
        shifted = with_scene(moved, np.random.default_rng(seed)).scene[("cam0", "lidar0")]
        row.update(shift_contradicts=shifted.contradicts, shift_joined=shifted.joined)
    u = w.weak_direction()
    row.update(joined=w.joined, problem=w.problem, boards=_errors(w.T_boards, w.C_boards, truth, u),
               sd_weak_boards=w.along_weak()[0][2])
    if w.term is not None:
        row.update(p=w.term.p_value, p_all=None if w.overall is None else w.overall.p_value, reason=w.reason,
                   contradicts=w.contradicts, joint=_errors(w.T_joint, w.C_joint, truth, u),
                   sd_weak_joint=w.along_weak()[2][2], scene=_errors(w.check.fit.T_camera_lidar, w.C_scene, truth, u))
    return row


def _rms(rows: list, which: str, key: str) -> float:
    return float(np.sqrt(np.mean([r[which][key] ** 2 for r in rows]))) if rows else float("nan")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=24)
    ap.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--generator", choices=("office", "furnished", "both"), default="both")
    ap.add_argument("--rows", default=None, help="also write every scene's row to this JSON file")
    a = ap.parse_args()
    t0 = time.time()
    seeds = list(range(a.seed, a.seed + a.scenes))
    generators = ("office", "furnished") if a.generator == "both" else (a.generator,)
    with ProcessPoolExecutor(a.workers) as pool:
        rows = list(pool.map(_trial, [(g, s) for g in generators for s in seeds]))
    if a.rows:
        import json

        Path(a.rows).write_text(json.dumps(rows, indent=1, default=float))
    print(f"{a.scenes} simulated scenes per generator ({', '.join(generators)}) of 10 board poses (VLP-16- and "
          "64-beam LiDARs in turn), calibrated from the boards (Laplace covariance) and given the scene's term (the "
          "board left out)\n")
    print("| scenes | LiDAR | count | joined | CHECK: disagree along weak | CHECK: over every direction only | "
          f"undecided (rivals) | not formed | boards' sd along weak (median) | joint's (median) | boards moved "
          f"{SHIFT_MM} mm: CHECK / joined |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    configs = [(g, m) for g in generators for m in MODELS]
    for g, m in configs:
        sel = [r for r in rows if (r["generator"], r["model"]) == (g, m) and "refused" not in r]
        joined = [r for r in sel if r["joined"]]
        tested = [r for r in sel if "p" in r]
        agree = [r for r in tested if not r["contradicts"]]
        shifted = f"{sum(r['shift_contradicts'] for r in sel)} / {sum(r['shift_joined'] for r in sel)}"
        along = [r for r in tested if r["contradicts"] and r["p"] < 0.01]
        print(f"| {g} | {m} | {len(sel)} | {len(joined)} | {len(along)} | "
              f"{sum(r['contradicts'] for r in tested) - len(along)} | "
              f"{sum('minima' in (r['reason'] or '') for r in agree)} | "
              f"{sum(r['problem'] is not None for r in sel)} | "
              f"{np.median([r['sd_weak_boards'] for r in sel]):.1f} mm | "
              f"{np.median([r['sd_weak_joint'] for r in joined]) if joined else float('nan'):.1f} mm | {shifted} |")
    print("\nErrors against the truth (RMS; NEES mean / median, 6 if honest):\n")
    print("| scenes | LiDAR | count | estimate | rotation | translation | along the weak direction | NEES |")
    print("|---|---|---|---|---|---|---|---|")
    for g, m in configs:
        sel = [r for r in rows if (r["generator"], r["model"]) == (g, m) and "refused" not in r]
        groups = (("joined", [r for r in sel if r["joined"]], ("boards", "joint", "scene")),
                  ("not joined", [r for r in sel if not r["joined"] and "p" in r], ("boards", "scene")))
        for label, group, whichs in groups:
            for which in whichs if group else ():
                nees = np.array([r[which]["nees"] for r in group])
                print(f"| {g} | {m} | {label} ({len(group)}) | {which} | {_rms(group, which, 'rot_deg'):.3f} deg | "
                      f"{_rms(group, which, 'trans_mm'):.1f} mm | {_rms(group, which, 'weak_mm'):.1f} mm | "
                      f"{nees.mean():.1f} / {np.median(nees):.1f} |")
    for r in rows:
        if "refused" in r or r.get("problem"):
            print(f"- {r['generator']} seed {r['seed']} {r['model']}: {r.get('refused') or r['problem']}")
    done = [r for r in rows if "seconds_scene" in r]
    print(f"\nthe scene's term {np.median([r['seconds_scene'] for r in done]):.1f} s (median) after the boards' "
          f"{np.median([r['seconds_boards'] for r in done]):.1f} s; {len(rows)} scenes in {time.time() - t0:.0f} s on "
          f"{a.workers} processes; seeds {seeds[0]}..{seeds[-1]}")


if __name__ == "__main__":
    main()
