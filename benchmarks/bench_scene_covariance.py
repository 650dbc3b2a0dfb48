"""The scene check's covariance taken apart (make bench; `python benchmarks/bench_scene_covariance.py [--scenes N]
[--workers W] [--seed S]`): which of its parts the truth needs, and what the alternatives tried instead would do.

The scenes and cases are ``bench_scene_check``'s (rooms without a board, offices with the board left out and
kept; each checked under the truth, the truth turned by 0.2 degrees and moved by 2 cm; VLP-16- and 64-beam
LiDARs in turn). For each check the scene's estimate and its minima are sought as ``check_scene`` seeks them, and
the estimate's NEES against the truth (6 dof) is read under each covariance:

- ``reported``: what the check reports, ``H^-1 (blocks + structure draws) H^-1`` plus the scatter of the minima the
  blocks cannot tell from the estimate (``scene_alignment.align_once``, ``minima_scatter``);
- ``no minima``: without that scatter;
- ``no draws``: the block sandwich and the scatter, without the structures' azimuth draws;
- ``draws by leverage``: each structure's draw weighed by its leverage (the share of it the fit absorbs, which the
  blocks' residuals cannot show), on the view that the blocks already hold the rest; with the scatter;
- ``minima by likelihood``: the minima weighed by their likelihood relative to the estimate, ``exp(-dSSR / 2 s2
  phi)`` with ``s2`` the residual variance and ``phi`` the overdispersion along the minimum's direction, in place
  of the blocks' test.

Printed per row: each covariance's NEES mean / median / share beyond chi2(6)'s 99% point (6 / 5.3 / 1% if the
covariance were the error's), and the share beyond the 99% point were the reported covariance scaled so that the
mean NEES is 6: a covariance of the right size on average that still leaves many beyond its 99% point has the
wrong shape for the errors' tail, and the tail is what the check's false alarms come from.
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

from bench_scene_check import MODELS, simulated_cases  # noqa: E402  (the same scenes and cases)

CHI2_6_99 = 16.81
VARIANTS = ("reported", "no minima", "no draws", "draws by leverage", "minima by likelihood")


def _draws_by_leverage(J: np.ndarray, labels: np.ndarray, sd: np.ndarray, H_inv: np.ndarray) -> np.ndarray:
    """Each structure's draw (``structure_information``'s) times its leverage ``a' H^-1 a / |v|^2``, ``v`` the
    draw's effect on its residuals (``J[:, 2]`` on its returns) and ``a = J' v``."""
    v = J[:, 2]
    m = int(labels.max()) + 1
    a = np.zeros((m, 6))
    np.add.at(a, labels, J * v[:, None])
    vv = np.zeros(m)
    np.add.at(vv, labels, v ** 2)
    var = np.zeros(m)
    np.add.at(var, labels, sd ** 2)
    var /= np.maximum(np.bincount(labels, minlength=m), 1)
    h = np.clip(np.einsum("ij,jk,ik->i", a, H_inv, a) / np.maximum(vv, 1e-30), 0.0, 1.0)
    return (a * (var * h)[:, None]).T @ a


def _covariances(fits, views, camera, T_given) -> dict:
    from estimators.solvers import scene_alignment as sa
    from geometry.rotations import T_inverse, T_log

    best = fits[0]
    stage = [v for v in sa.narrowest(views) if len(v.points)]
    parts = sa.stacked_residuals(best.T_camera_lidar, stage, camera)
    J = np.concatenate([J for _, J in parts])
    labels = sa.structures(stage)
    sd = np.concatenate([np.full(len(v.points), v.azimuth_step / np.sqrt(12.0)) for v in stage])
    H_inv = np.linalg.inv(J.T @ J)
    g = sa.block_gradients(best.T_camera_lidar, stage, parts, camera)  # the blocks' meat, as ``align_once``
    B = H_inv @ (g.T @ g * len(g) / (len(g) - 1)) @ H_inv
    M = sa.minima_scatter(fits, views, camera, T_given)
    # the minima by likelihood: the cost's rise over the estimate's in residual variances, over the overdispersion
    # along the minimum's direction (the information H / s2 against the covariance's)
    s2 = best.rms_px ** 2
    xs, ws = [np.zeros(6)], [1.0]
    for f in fits[1:]:
        x = T_log(T_inverse(best.T_camera_lidar) @ f.T_camera_lidar)
        rise = best.points * (f.rms_px ** 2 - s2) / s2
        phi = (x @ best.hessian @ x / s2) / max(float(x @ np.linalg.solve(best.covariance, x)), 1e-12)
        xs.append(x)
        ws.append(min(1.0, float(np.exp(-0.5 * rise / max(phi, 1e-12)))))
    M_lik = sum(w * np.outer(x, x) for x, w in zip(xs, ws)) / sum(ws)
    return {"reported": best.covariance + M, "no minima": best.covariance,
            "no draws": B + M, "draws by leverage": B + H_inv @ _draws_by_leverage(J, labels, sd, H_inv) @ H_inv + M,
            "minima by likelihood": best.covariance + M_lik}


def _trial(job: tuple[str, int]) -> list[dict]:
    from estimators.errors import LidarcamError
    from estimators.pipeline.scene_check import read_scene_frames, scene_views
    from estimators.solvers.scene_alignment import nearest_decided, scene_minima
    from geometry.rotations import T_inverse, T_log

    generator, seed = job
    rows = []
    with tempfile.TemporaryDirectory(prefix="lidarcam-bench-") as tmp:
        model, truth, cases = simulated_cases(generator, seed, Path(tmp) / "ds")
        for keep in ((False, True) if generator == "office" else (False,)):
            board = "none" if generator == "room" else "kept" if keep else "left out"
            for name, T in cases.items():
                try:
                    _, camera, _, frames, skipped = read_scene_frames(Path(tmp) / "ds", keep)
                    views = scene_views(frames, T, camera, skipped)
                    fits = nearest_decided(scene_minima(views, camera, T, decided=True), views, camera, T)
                    covs = _covariances(fits, views, camera, T)
                except (LidarcamError, np.linalg.LinAlgError):
                    continue
                xi = T_log(T_inverse(fits[0].T_camera_lidar) @ truth)
                rows.append({"generator": generator, "model": model, "board": board, "case": name,
                             **{k: float(xi @ np.linalg.solve(C, xi)) for k, C in covs.items()}})
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=24)
    ap.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    ap.add_argument("--seed", type=int, default=100)
    a = ap.parse_args()
    t0 = time.time()
    jobs = [(g, s) for g in ("room", "office") for s in range(a.seed, a.seed + a.scenes)]
    with ProcessPoolExecutor(a.workers) as pool:
        rows = [r for rs in pool.map(_trial, jobs) for r in rs]
    print(f"{a.scenes} simulated scenes per generator of 10 frames, as bench_scene_check's; the scene estimate's NEES "
          "against the truth under each covariance, as mean / median / share beyond chi2(6)'s 99% point "
          "(6 / 5.3 / 1% if the covariance were the error's):\n")
    print("| scenes | LiDAR | board | sought from | estimates | " + " | ".join(VARIANTS)
          + " | reported, scaled to a mean of 6: beyond the 99% point |")
    print("|---|---|---|---|---|" + "---|" * (len(VARIANTS) + 1))
    for g, model, board in [(g, m, b) for g in ("room", "office") for m in MODELS
                            for b in (("none",) if g == "room" else ("left out", "kept"))]:
        for start, cases in (("the truth", ("truth",)), ("turned or moved", ("turned", "moved"))):
            sel = [r for r in rows if (r["generator"], r["model"], r["board"]) == (g, model, board)
                   and r["case"] in cases]
            if not sel:
                continue
            cells = []
            for k in VARIANTS:
                v = np.array([r[k] for r in sel])
                cells.append(f"{v.mean():.1f} / {np.median(v):.1f} / {np.mean(v > CHI2_6_99):.0%}")
            v = np.array([r["reported"] for r in sel])
            print(f"| {g} | {model} | {board} | {start} | {len(sel)} | " + " | ".join(cells)
                  + f" | {np.mean(v * 6 / v.mean() > CHI2_6_99):.0%} |")
    print(f"\n({len(jobs)} scenes in {time.time() - t0:.0f} s on {a.workers} processes; seeds "
          f"{a.seed}..{a.seed + a.scenes - 1})")


if __name__ == "__main__":
    main()
