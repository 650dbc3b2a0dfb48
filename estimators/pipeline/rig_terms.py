"""A rig's LiDAR range terms: each LiDAR's model (its first camera-LiDAR pair's choice under ``auto``), its black
squares placed on the joint board poses, and its record.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..errors import LidarcamError
from ..io.rig_dataset import RigDataset
from ..lidar.lidar_models import range_accuracy_for
from ..solvers.range_model import FrameLabels, RangeTerms, frame_labels, frame_rings, frame_whitener, terms_for
from ..solvers.rig_graph import RigSolution


def _lidar_labels(rig: RigDataset, name: str, obs: dict, pair_frames: dict, solution: RigSolution,
                  blurred: bool) -> dict:
    """Each of LiDAR ``name``'s frames' labels for the range terms, by stem: ``(rings, black shares)``. Rings come
    from the scan's field or its beams' elevations clustered over all its frames (``range_model.frame_rings``);
    the black squares are placed by geometry (``range_model.frame_labels``) on ``solution``'s board pose (the
    camera's own, noisier, would shrink the black squares' term as an error in a regressor does), with the colours
    that the image of the camera the board was found with shows (a numbering turned to the reference camera's is
    that of a pattern that looks the same turned), under ``solution``'s transform of that camera-LiDAR pair.
    ``blurred``: each placement blurred by that transform's covariance; else by the labels' floor alone (the
    covariance of a solution without the terms is inflated by them). A 2D scanner's frames have neither."""
    measured: dict = {}  # stem -> (camera, frame) whose LiDAR observation is the one in ``obs``
    for (cam, lid), frames in pair_frames.items():
        for f in frames if lid == name else ():
            if f.name in obs and obs[f.name] is f.lidar:
                measured.setdefault(f.name, (cam, f))
    stems = list(obs)
    rings = dict(zip(stems, frame_rings([obs[st] for st in stems])))
    dark = dict.fromkeys(stems)
    for cam in sorted({c for c, _ in measured.values()}):
        group = [st for st in stems if st in measured and measured[st][0] == cam]
        T, C = solution.transform(cam, name)
        T_c = np.linalg.inv(solution.T_ref[cam])
        boards = [T_c @ solution.T_ref_board[st] if st in solution.T_ref_board else
                  measured[st][1].camera.T_camera_board for st in group]
        labels = frame_labels([measured[st][1] for st in group], rig.board, T, boards,
                              placement_cov=C if blurred else None)
        dark.update(zip(group, labels.dark))
    return {st: (rings[st], dark[st]) for st in stems}


def ranged_views(rig: RigDataset, lidar_views: list, lidar_obs: dict, pair_frames: dict, solution: RigSolution,
                 models: dict, range_accuracy_m: float | None = None, blurred: bool = False) -> tuple[list, dict]:
    """Each LiDAR's views with the range terms of its model in ``models`` (by name: ``none``, ``per-ring``,
    ``offset+dark``, ...; a LiDAR not named keeps its planes, without a record), under priors from its range
    accuracy (``range_accuracy_m``, ``--range-accuracy``, every LiDAR's; else dataset.yaml's ``range_accuracy_m`` or
    its family's), its black squares placed on ``solution``'s board poses (``blurred``: by its covariance, for a
    solution with the terms in), and per LiDAR the start of its record (``prior_sd_m``, ``model``: the terms the
    data allow of those asked, ``reason`` where none could be formed). Under ``auto`` the model is the one its
    first camera-LiDAR pair chose (``range_terms_choice.choose_range_model``): the rig has one choice of range
    terms, the single pair's."""
    out, records = [], {}
    for lv in lidar_views:
        if lv.name not in models:
            out.append(lv)
            continue
        sensor = rig.sensor(lv.name)
        acc = float(range_accuracy_m or sensor.range_accuracy_m or range_accuracy_for(sensor.lidar_family))
        obs = lidar_obs[lv.name]
        record: dict = {"prior_sd_m": acc}
        if models[lv.name] == "none":
            records[lv.name] = {**record, "model": "none"}
            out.append(lv)
            continue
        try:
            labels = _lidar_labels(rig, lv.name, obs, pair_frames, solution, blurred)
            known = FrameLabels(tuple(r for r, _ in labels.values()), tuple(d for _, d in labels.values()))
            terms = terms_for(models[lv.name], known, acc) or RangeTerms((), ())
            chosen = replace(lv, ranged={st: frame_whitener(obs[st], lv.sigma_m, terms, *labels[st]) for st in lv.W},
                             terms=terms)
        except (LidarcamError, np.linalg.LinAlgError) as exc:
            why = exc.message if isinstance(exc, LidarcamError) else str(exc)
            records[lv.name] = {**record, "model": "none", "reason": f"its terms could not be formed: {why}"}
            out.append(lv)
            continue
        record["model"] = chosen.terms.model if chosen.has_terms else "none"
        out.append(chosen if chosen.has_terms else lv)
        records[lv.name] = record
    return out, records


def range_record(record: dict, terms: RangeTerms, values: np.ndarray, sds: np.ndarray, warnings: list,
                 name: str) -> None:
    """A LiDAR's range record with its terms' final estimates (``terms``: by name, ``value_m``, ``sd_m``,
    ``prior_sd_m``; the global offset's also as ``value_m`` and ``sd_m``), and a warning for each term beyond 3
    prior standard deviations (a wrong board in some frames, or a range accuracy too small for the sensor)."""
    record["terms"] = {n: {"value_m": float(v), "sd_m": float(s), "prior_sd_m": float(p)}
                       for n, v, s, p in zip(terms.names, values, sds, terms.prior_sd)}
    record.update(value_m=float(values[0]), sd_m=float(sds[0]))
    beyond = [n for n, v, p in zip(terms.names, values, terms.prior_sd) if abs(v) > 3 * p]
    if beyond:
        said = ", ".join(f"{n} {1000 * values[terms.names.index(n)]:+.1f} mm" for n in beyond)
        warnings.append(f"{name}: its range terms {said} lie beyond 3 times their prior sd (range accuracy "
                        f"{1000 * record['prior_sd_m']:.0f} mm): a wrong board in some frames, or a "
                        "range_accuracy_m in dataset.yaml too small for this sensor")
