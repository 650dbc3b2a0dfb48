"""A rig's LiDAR range terms: chosen per LiDAR as the single pair's are (likelihood-ratio tests, the offset alone
where the planes stay overdispersed), the black squares placed on the joint board poses, and their record.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..errors import LidarcamError
from ..io.rig_dataset import RigDataset
from ..lidar.lidar_models import range_accuracy_for
from ..solvers import chi_square as chi2
from ..solvers.range_model import (MODEL_TEST_P, FrameLabels, RangeTerms, frame_labels, frame_rings, frame_whitener,
                                   terms_for)
from ..solvers.factor_graph import LidarViews
from ..solvers.rig_graph import RigSolution, solve_rig, terms_fit, terms_test
from .rig_result import NOISE_WARNING_P

# Above this variance factor of a LiDAR's planes under its largest range model (every term in), its per-ring and
# black-square terms are not tested (``_choose_terms``): simulated rigs with injected range errors leave 1.0-1.13,
# the recorded VLP-16 and Ouster sets 5.1 and 3.8 (their boards' planes disagree from board to board).
MAX_TERMS_DISPERSION = 2.0


def _lidar_labels(rig: RigDataset, name: str, obs: dict, pair_frames: dict, solution: RigSolution,
                  blurred: bool = True) -> dict:
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


def choose_range_models(rig: RigDataset, names: tuple, camera_views: list, lidar_views: list, lidar_obs: dict,
                        pair_frames: dict, solution: RigSolution, range_model: str,
                        range_accuracy_m: float | None = None) -> tuple[list, dict]:
    """Each LiDAR's views with the range terms of its model (``solvers.range_model``: a global offset, per-ring
    offsets, the black squares' offset; priors from its range accuracy: ``range_accuracy_m`` (``--range-accuracy``,
    every LiDAR's) or dataset.yaml's ``range_accuracy_m`` or its family's), and per LiDAR the record
    (:func:`range_record`).

    ``auto`` chooses as the single pair does (``range_terms_choice.choose_range_model``): a global offset against none,
    then the per-ring and the black-square blocks each against the offset (against none, with the offset in the
    block, when the offset alone is not supported); both when both pass. Each test is a likelihood ratio on the
    joint graph at the graph's noise scales (``rig_graph.terms_test``: an overdispersed sensor's statistic is
    scaled down by its excess), and only the offset is tested where the planes stay overdispersed under every
    term (:func:`_choose_terms`). A model the data cannot hold (per-ring without rings, the black squares without
    both colours on the boards) is not tried; a requested one falls back to the terms the data allow."""
    out, records = [], {}
    for lv in lidar_views:
        sensor = rig.sensor(lv.name)
        acc = float(range_accuracy_m or sensor.range_accuracy_m or range_accuracy_for(sensor.lidar_family))
        obs = lidar_obs[lv.name]
        record: dict = {"requested": range_model, "prior_sd_m": acc}
        placed: dict = {}  # the labels under each solution, placed once
        try:
            def views(model: str, solved: RigSolution, blurred: bool = True) -> LidarViews:
                key = (id(solved), blurred)
                if key not in placed:
                    placed[key] = (solved, _lidar_labels(rig, lv.name, obs, pair_frames, solved, blurred))
                labels = placed[key][1]
                known = FrameLabels(tuple(r for r, _ in labels.values()), tuple(d for _, d in labels.values()))
                terms = terms_for(model, known, acc) or RangeTerms((), ())
                return replace(lv, ranged={st: frame_whitener(obs[st], lv.sigma_m, terms, *labels[st]) for st in lv.W},
                               terms=terms)

            if range_model != "auto":
                chosen = views(range_model, solution, blurred=False)
                record["model"] = chosen.terms.model if chosen.has_terms else "none"
            else:
                chosen, tests, notes = _choose_terms(names, rig.reference, camera_views, lidar_views, solution,
                                                     views, lv.name)
                record.update(model=chosen.terms.model if chosen.has_terms else "none", tests=tests,
                              test_p=MODEL_TEST_P)
                if notes:
                    record["inconsistent"] = notes
        except (LidarcamError, np.linalg.LinAlgError) as exc:
            why = exc.message if isinstance(exc, LidarcamError) else str(exc)
            records[lv.name] = {**record, "model": "none", "reason": f"not tested: {why}"}
            out.append(lv)
            continue
        out.append(chosen if chosen.has_terms else lv)
        records[lv.name] = record
    return out, records


def _choose_terms(names: tuple, reference: str, camera_views: list, lidar_views: list, solution: RigSolution,
                  views, name: str) -> tuple:
    """``auto``'s choice for LiDAR ``name`` (:func:`choose_range_models`): its chosen views
    (``views(model, solution)``),
    the tests (``model``, ``against``, ``statistic``, ``dof``, ``p_value``; the offset's estimate with it,
    ``offset_m`` and ``sd_m``), and the terms not tested (``model``, ``variance_factor``: the LiDAR's under its
    largest model, above ``MAX_TERMS_DISPERSION``).

    Where the LiDAR's planes disagree beyond their noise (its chi-square beyond ``NOISE_WARNING_P``), the tests
    are made at the sensors' noise scales under the largest model, and its colours placed under that model's
    estimate and blurred by its covariance: a range term left out inflates its LiDAR's excess and the
    extrinsic's covariance, which would scale down the very statistic that tests it (quasi-likelihood's
    dispersion is estimated under the largest model) and smear the squares' placement."""
    ss, dof = solution.chi2_dof.get(name, (0.0, 1.0))
    models, notes = ("none", "offset", "per-ring", "offset+dark"), []
    if chi2.sf(ss, dof) < NOISE_WARNING_P:  # without a significant excess: as they are
        largest = views("full", solution, blurred=False)  # the full model holds the offset at least
        planes = solution
        solution = solve_rig(names, reference, camera_views,
                             [largest if v.name == largest.name else v for v in lidar_views], solution.T_ref,
                             solution.T_ref_board, solution.intrinsics is not None)
        excess = solution.noise_scale.get(name, 1.0)
        if excess > MAX_TERMS_DISPERSION:
            # Even with every term the planes disagree with the rig's boards far beyond their noise: structure from
            # board to board that the rig graph does not model (the single pair's per-board plane error), which
            # the within-board terms' tests would read as terms. The global offset alone is tested, as at the
            # planes' noise scales.
            solution, models = planes, ("none", "offset")
            notes.append({"model": "per-ring and black-square", "variance_factor": float(excess)})
    fits, seen = {}, set()
    for model in models:
        v = views(model, solution)
        if v.terms.names in seen:  # per-ring without rings, black squares without both colours: nothing new
            continue
        seen.add(v.terms.names)
        fits[model] = (v, terms_fit(names, reference, camera_views, lidar_views, solution, v))

    def test(model: str, against: str) -> dict:
        return {"model": model, "against": against, **terms_test(fits[against][1], fits[model][1])}

    tests = [{**test("offset", "none"), "offset_m": float(fits["offset"][1]["values_m"][0]),
              "sd_m": float(fits["offset"][1]["sd_m"][0])}]
    base = "offset" if tests[0]["p_value"] < MODEL_TEST_P else "none"
    blocks = []
    for model in ("per-ring", "offset+dark"):
        if model in fits:
            tests.append(test(model, base))
            if tests[-1]["p_value"] < MODEL_TEST_P:
                blocks.append(model)
    if len(blocks) == 2:
        return views("full", solution), tests, notes
    return fits[blocks[0] if blocks else base][0], tests, notes


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
