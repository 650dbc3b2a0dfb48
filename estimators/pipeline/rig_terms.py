"""A rig's LiDAR range terms: each LiDAR's model (its first camera-LiDAR pair's choice under ``auto``), its black
squares placed on the joint board poses, its board returns cut again symmetrically about the terms, the terms its
pair held at 0 held here too, the placement's and the held terms' shares of the covariance, and its record.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from geometry.rotations import T_exp

from ..errors import LidarcamError
from ..io.rig_dataset import RigDataset
from ..lidar.lidar_models import range_accuracy_for
from ..measurements import observe_lidar_board
from ..solvers.range_model import (MAX_PRIOR_SIGMAS, MODEL_TEST_P, FrameLabels, RangeTerms, frame_labels,
                                   frame_rings, frame_whitener, symmetric_band, terms_for)
from ..solvers.graph_keys import sensor_key, terms_key
from ..solvers.rig_graph import RigSolution, graph_reference, graph_step, inner_covariance, sensors_share

# The prior standard deviation (m) that holds a pinned range term at 0 in the graph.
HELD_SD_M = 1e-7


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
                 models: dict, range_accuracy_m: float | None = None, blurred: bool = False, band: dict | None = None
                 ) -> tuple[list, dict]:
    """Each LiDAR's views with the range terms of its model in ``models`` (by name: ``none``, ``per-ring``,
    ``offset+dark``, ...; a LiDAR not named keeps its planes, without a record), under priors from its range
    accuracy (``range_accuracy_m``, ``--range-accuracy``, every LiDAR's; else dataset.yaml's ``range_accuracy_m`` or
    its family's), its black squares placed on ``solution``'s board poses (``blurred``: by its covariance, for a
    solution with the terms in), and per LiDAR the start of its record (``prior_sd_m``, ``model``: the terms the
    data allow of those asked, ``reason`` where none could be formed). Under ``auto`` the model is the one its
    first camera-LiDAR pair chose (``range_terms_choice.choose_range_model``): the rig has one choice of range
    terms, the single pair's. ``band``: per LiDAR, the frames whose returns :func:`banded` cut, by stem."""
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
            cut = (band or {}).get(lv.name, {})

            def whitener(st):  # a frame's returns, those its band kept where it cut them
                if st not in cut:
                    return frame_whitener(obs[st], lv.sigma_m, terms, *labels[st])
                kept, keep = cut[st]
                return frame_whitener(kept, lv.sigma_m, terms, *(None if a is None else a[keep] for a in labels[st]))

            chosen = replace(lv, ranged={st: whitener(st) for st in lv.W}, terms=terms)
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


def with_range_terms(rig: RigDataset, lidar_views: list, lidar_obs: dict, pair_frames: dict, solution: RigSolution,
                     choices: dict, range_model: str, board_scatter: dict, range_accuracy_m: float | None,
                     warnings: list, solve) -> tuple[list, RigSolution, dict, dict, tuple]:
    """The joint graph with every LiDAR's range terms: one choice of them, the single pair's. ``choices``: per
    LiDAR its first camera-LiDAR pair's ``(RangeModelFit, "<camera>-<lidar>")``, whose model ``auto`` takes (its
    tests, with the per-board plane error and the boards' scatter modelled, go into the record) and whose held
    terms (an estimate beyond ``MAX_PRIOR_SIGMAS`` prior sds) are held at 0 here too (:func:`held_views`); a
    requested ``range_model`` is every LiDAR's. The terms are placed on ``solution``'s board poses (the black
    squares again on the solution with the terms, blurred by its covariance: a range offset the planes absorb
    moves their placement and would shrink their term), with ``board_scatter`` (per LiDAR, m) as their pair
    weighed them; ``solve(views)`` solves the joint graph. Returns the views, the solution, per LiDAR its record,
    the held terms' names (for :func:`with_held_share`, once every solve is done) and how its terms were placed
    (for :func:`with_placement_share`: the model asked of each LiDAR and the returns the terms' final solve kept,
    :func:`banded`, cut under the first solve's terms); warnings are added."""
    asked = {n: fit.chosen if range_model == "auto" else range_model for n, (fit, _) in choices.items()}
    views, records = ranged_views(rig, lidar_views, lidar_obs, pair_frames, solution, asked, range_accuracy_m)
    ranged = {lv.name for lv in views if lv.has_terms}
    pins = {n: fit.pinned for n, (fit, _) in choices.items() if fit.pinned and n in ranged}
    views = held_views([replace(lv, tau_m=board_scatter.get(lv.name, 0.0)) for lv in views], pins)
    for name, record in records.items():
        fit, by = choices[name]
        record.update(requested=range_model, chosen_by=by)
        if range_model == "auto":
            record.setdefault("reason", fit.reason)  # unless its terms could not be formed here
            record.update(tests=list(fit.tests), test_p=MODEL_TEST_P, left_out=list(fit.left_out),
                          weak_offset=fit.weak_offset)
    for name in pins:
        fit, by = choices[name]
        records[name]["held_at_prior"] = [{"term": t, "estimate_mm": 1000 * v}
                                          for t, v in zip(fit.pinned, fit.pinned_values_m)]
        said = ", ".join(f"{t} {1000 * v:+.0f} mm" for t, v in zip(fit.pinned, fit.pinned_values_m))
        warnings.append(f"{name}: its range terms {said} (as {by} estimated them) lie beyond {MAX_PRIOR_SIGMAS:.0f} "
                        "prior standard deviations of its range accuracy: held at 0 with their prior variance "
                        "propagated into the covariance, as a single pair holds them (likely a term confounded with "
                        "the extrinsic, a wrong LiDAR segment or a board that moved; set the LiDAR's "
                        "range_accuracy_m if it is known to err more)")
    band: dict = {}
    if ranged:
        solution = solve(views)
        band = banded(rig, [lv for lv in views if lv.name not in pins], lidar_obs, pair_frames, solution)
        if band or any("dark" in lv.terms.names for lv in views if lv.has_terms):
            views = held_views(ranged_views(rig, views, lidar_obs, pair_frames, solution, asked, range_accuracy_m,
                                            blurred=True, band=band)[0], pins)
            solution = solve(views)
    return views, solution, records, pins, (asked, band)


def banded(rig: RigDataset, lidar_views: list, lidar_obs: dict, pair_frames: dict, solution: RigSolution) -> dict:
    """Per LiDAR with range terms, the frames whose returns ``range_model.symmetric_band`` cuts under
    ``solution``'s terms (its colours placed on ``solution``, blurred): by stem, the observation of the returns
    kept and their mask (for their labels). Not for a LiDAR with a term held at 0 (the caller leaves it out): its
    returns are not where its held terms put them."""
    out = {}
    for lv in (v for v in lidar_views if v.has_terms):
        obs = lidar_obs[lv.name]
        labels = _lidar_labels(rig, lv.name, obs, pair_frames, solution, True)
        beta = solution.range_terms[lv.name][0]
        cut = {}
        for st in lv.W:
            keep = symmetric_band(obs[st], lv.terms, beta, *labels[st])
            if keep is not None:
                o = obs[st]
                kept = observe_lidar_board(o.points[keep], o.candidates)
                cut[st] = (replace(kept, rings=None if o.rings is None else o.rings[keep],
                                   intensity=None if o.intensity is None else o.intensity[keep],
                                   open_ends=None if o.open_ends is None else o.open_ends[keep]), keep)
        if cut:
            out[lv.name] = cut
    return out


def held_views(lidar_views: list, pinned: dict) -> list:
    """The views with the range terms named in ``pinned`` (by LiDAR, the names its first pair's refinement held at
    0: estimates beyond ``range_model.MAX_PRIOR_SIGMAS`` prior standard deviations) held at 0 in the graph, as the
    single pair holds them, by a prior of ``HELD_SD_M`` (the posterior samples them under it too)."""
    out = []
    for lv in lidar_views:
        idx = [k for k, n in enumerate(lv.terms.names) if n in pinned.get(lv.name, ())] if lv.has_terms else []
        if idx:
            sd = np.array(lv.terms.prior_sd, dtype=float)
            sd[idx] = HELD_SD_M
            lv = replace(lv, terms_prior_sd=sd)
        out.append(lv)
    return out


def weak_offset_share(names: tuple, records: dict) -> np.ndarray | None:
    """The share of the sensors' joint covariance (6N x 6N, ``names`` order) that holds, for each LiDAR whose pair
    passed over a global offset its test still half supported (``RangeModelFit.weak_offset``), the answer with
    it: the outer product of the pair's shift in that LiDAR's block (a shift of the pair's transform with its
    camera held is the same shift of the LiDAR's pose, whichever camera is the reference). None where none did."""
    weak = {n: r["weak_offset"] for n, r in records.items() if r.get("weak_offset")}
    if not weak:
        return None
    share = np.zeros((6 * len(names), 6 * len(names)))
    for name, w in weak.items():
        k = names.index(name)
        d = np.asarray(w["difference_tangent"], dtype=float)
        share[6 * k:6 * k + 6, 6 * k:6 * k + 6] += np.outer(d, d)
    return share


def with_held_share(names: tuple, reference: str, camera_views: list, lidar_views: list, solution: RigSolution,
                    pinned: dict) -> tuple[RigSolution, np.ndarray]:
    """``solution`` (solved with :func:`held_views`) with the held terms' prior variance propagated into its joint
    covariance and their standard deviations, as the single pair's ``range_terms_choice.consider_pinned`` does:
    ``A^-1 + G P G^T`` with ``G = A^-1 B`` (``A`` the information of everything else, ``B`` its coupling to the held
    terms, ``P`` their prior covariance). Both come from the joint marginal ``M`` of the free poses and the terms
    at the held estimate under the terms' own priors: ``A^-1`` restricted to them is ``M - M_p M_pp^-1 M_p^T`` and
    ``G = -M_p M_pp^-1``. Also returns that share of the sensors' joint covariance (6N x 6N, ``names`` order, the
    reference's frame), which the posterior's samples get convolved with; the solution's inner covariance, the
    posterior's curvature, is left without it."""
    free_terms = [replace(lv, terms_prior_sd=None) for lv in lidar_views]
    M = inner_covariance(names, reference, camera_views, free_terms, solution)
    inner = graph_reference(reference, [c.name for c in camera_views])
    at, p, prior = 6 * (len(names) - 1), [], []
    for lv in (v for v in free_terms if v.has_terms):
        for k, n in enumerate(lv.terms.names):
            if n in pinned.get(lv.name, ()):
                p.append(at + k)
                prior.append(lv.terms.prior_sd[k])
        at += lv.terms.size
    G = -M[:, p] @ np.linalg.inv(M[np.ix_(p, p)])
    share_inner = G @ np.diag(np.square(prior)) @ G.T
    full = M + G @ M[p, :] + share_inner  # A^-1 (the held terms' rows zero) and the share
    share = sensors_share(names, reference, inner, solution, share_inner)
    terms, at = dict(solution.range_terms), 6 * (len(names) - 1)
    for lv in (v for v in free_terms if v.has_terms):
        K = lv.terms.size
        terms[lv.name] = (terms[lv.name][0], np.sqrt(np.maximum(np.diag(full)[at:at + K], 0.0)))
        at += K
    return replace(solution, covariance_joint=solution.covariance_joint + share, range_terms=terms), share


def with_placement_share(rig: RigDataset, names: tuple, camera_views: list, lidar_views: list, lidar_obs: dict,
                         pair_frames: dict, solution: RigSolution, placing: tuple, range_accuracy_m: float | None,
                         pinned: dict) -> tuple[RigSolution, np.ndarray | None]:
    """The black squares' placement propagated into the covariance ("consider" covariance, as for the held terms):
    the squares are placed under the estimate, itself uncertain, and placed a few millimetres off they give the
    returns near the squares' edges other colours, which move the black-square term and, through it, the rest. For
    each LiDAR with a free black-square term, its squares are placed again with its pose moved by one standard
    deviation each way along each principal direction of its transform to the camera it shares most frames with,
    and the joint graph takes one Gauss-Newton step from the estimate under those colours; half the two steps'
    difference, summed in outer product over the directions, is added to the covariance (the sensors' and the
    terms' sds) and returned as the sensors' share, which the posterior's samples get convolved with.

    Their mean is not taken off the estimate, as the single pair's ``range_terms_choice.consider_placement`` takes
    it: the shares are blurred by the same covariance already (the chance of black given what is known of the
    placement, Berkson's error model), so moved and blurred again they are blurred twice, and the pair's mean also
    holds the move that placing them again under the estimate itself makes, once per direction
    (docs/range_model.md). ``placing``: the range model per LiDAR, as :func:`ranged_views` takes them, and the
    returns kept (:func:`with_range_terms`). Returns the solution and the share (None where no LiDAR has it)."""
    models, band = placing
    darkened = [lv for lv in lidar_views if lv.has_terms and "dark" in lv.terms.names
                and "dark" not in pinned.get(lv.name, ()) and lv.name in models]
    if not darkened:
        return solution, None
    reference = solution.reference
    inner = graph_reference(reference, [c.name for c in camera_views])
    free = [k for k, n in enumerate(names) if n != inner]
    ranged = [lv for lv in lidar_views if lv.has_terms]
    order = [sensor_key(k) for k in free] + [terms_key(names.index(lv.name)) for lv in ranged]
    size = 6 * len(free) + sum(lv.terms.size for lv in ranged)
    extra = np.zeros((size, size))
    for lv in darkened:
        frames: dict = {}
        for (cam, lid), fs in pair_frames.items():
            if lid == lv.name:
                frames[cam] = frames.get(cam, 0) + len(fs)
        _, C = solution.transform(max(sorted(frames), key=frames.get), lv.name)
        ev, V = np.linalg.eigh(0.5 * (C + C.T))
        for lam, v in zip(ev, V.T):
            steps = []
            for sign in (1.0, -1.0):
                T_moved = solution.T_ref[lv.name] @ T_exp(sign * np.sqrt(max(lam, 0.0)) * v)
                moved = replace(solution, T_ref={**solution.T_ref, lv.name: T_moved})
                views = ranged_views(rig, lidar_views, lidar_obs, pair_frames, moved, {lv.name: models[lv.name]},
                                     range_accuracy_m, blurred=True, band=band)[0]
                again = next(w for w in views if w.name == lv.name)
                if not again.has_terms or again.terms.names != lv.terms.names:  # the colours left no such term
                    break
                step = graph_step(names, reference, camera_views, held_views(views, pinned), solution)
                steps.append(np.concatenate([step[k] for k in order]))
            if len(steps) == 2:
                spread = 0.5 * (steps[0] - steps[1])
                extra += np.outer(spread, spread)
    at, terms = 6 * len(free), dict(solution.range_terms)
    for lv in ranged:
        K = lv.terms.size
        terms[lv.name] = (terms[lv.name][0], np.sqrt(np.square(terms[lv.name][1]) + np.diag(extra)[at:at + K]))
        at += K
    share = sensors_share(names, reference, inner, solution, extra)
    return replace(solution, covariance_joint=solution.covariance_joint + share, range_terms=terms), share
