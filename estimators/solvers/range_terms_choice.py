"""The choice of the LiDAR's range terms (``--range-model auto``): each block by a likelihood-ratio test with the
boards' disagreement modelled, the fall-backs, the pinned terms and the black squares' placement, and the
chosen terms' uncertainty.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import gtsam
import numpy as np

from geometry.rotations import T_exp, T_log

from . import chi_square as chi2
from .board_scatter import estimate_board_scatter, estimate_plane_error
from .chi_square import fdtrc
from .choice_memo import decided_fields
from .graph_keys import EXTRINSIC, RANGE
from .plane_graph import PlaneProblem, hessian, objective
from .range_model import (CONFOUNDED_CORRELATION, MODEL_TEST_P, OFFSET_HELD_P, FrameLabels, RangeModelFit, RangeTerms,
                          frame_labels, terms_for)
from .refinement_options import RefinementOptions


@dataclass
class _ModelFit:
    """One range model solved over the same frames: its problem, estimate, objective and nuisance rank."""

    model: str
    prob: PlaneProblem
    T: np.ndarray
    boards: list
    cost: float
    dof: int


def _gaussian_objective(p: PlaneProblem, graph, result, active: list[int], inliers: list[int], boards: list,
                        floor: float) -> float:
    """:func:`plane_graph.objective` under the Gaussian likelihood over the inlier frames, as the likelihood-ratio
    test needs it. The solve minimised the robust loss, which bends the residuals it reaches (Cauchy's every one,
    Huber's those beyond its threshold); and a board's within-board structure lies in its floor (unbent) under a
    model without the terms that read it, in its factor (bent) under one with them, so differences of the robust
    objective overstate what the terms explain: under Cauchy, per-ring terms passed at p < 1e-6 on boards without
    ring errors. Where the loss bends nothing and every frame is an inlier the solve's own objective is returned;
    else the inliers are solved again from it without the loss (the problem's state kept)."""
    if list(active) == list(inliers):
        bent = graph.error(result)
        if abs(p.graph(active, floor, robust=False).error(result) - bent) <= 1e-9 * max(1.0, bent):
            return objective(p, graph, result, active, floor)
    state = (p.beta.copy(), p.outline.copy(), dict(p.shifts))
    plain, solved, _ = p.solve(inliers, result.atPose3(EXTRINSIC).matrix(), list(boards), floor, robust=False)
    cost = objective(p, plain, solved, inliers, floor)
    p.beta, p.outline, p.shifts = state
    return cost


def _fit_model(prob: PlaneProblem, model: str, labels: FrameLabels, active: list[int], inliers: list[int],
               T: np.ndarray, boards: list, floor: float, options: RefinementOptions) -> _ModelFit:
    terms = terms_for(model, labels, options.range_accuracy_m)
    # The model without terms in the same (range) form, so that the objectives compare.
    p = PlaneProblem(prob.frames, prob.board, prob.camera, prob.sigma_px, prob.sigma_r, options,
                     terms if terms is not None else RangeTerms((), ()), labels, sigma_board=prob.sigma_board)
    p.copy_edges(prob)
    b = list(boards)
    graph, result, _ = p.solve(active, T, b, floor)
    p.solved = (graph, result)  # the refinement goes on from this solution
    return _ModelFit(model, p, result.atPose3(EXTRINSIC).matrix(), b,
                     _gaussian_objective(p, graph, result, active, inliers, b, floor), p.nuisance_rank(inliers))


def _model_test(small: _ModelFit, large: _ModelFit, active: list[int], inliers: list[int], floor: float,
                options: RefinementOptions) -> dict:
    """Whether the terms ``large`` adds to ``small`` are supported: a likelihood-ratio test at ``MODEL_TEST_P``.

    When the boards' planes disagree beyond the noise under the larger model (overdispersed data), the structure
    neither model explains would otherwise be read as a term: the per-board plane error is estimated under the
    larger model (method of moments, at most ``MAX_PLANE_ERROR_M``), both models are solved again with it in
    place, and the decrease of the objective, over the variance factor that remains (a quasi-likelihood scale:
    structure in the terms' own directions, which a plane error cannot hold), is referred to an F distribution
    (the error's size is itself estimated from the boards). Else the
    decrease is referred to chi-square with the added terms' degrees of freedom."""
    ddof = max(large.dof - small.dof, 1)
    stat, cdof = large.prob.consistency(inliers, large.T, large.boards, floor, active)
    dispersion = stat / cdof
    delta = small.cost - large.cost
    record = {"model": large.model, "against": small.model, "cost_decrease": float(delta), "added_dof": int(ddof),
              "variance_factor": float(dispersion), "consistency_dof": round(float(cdof), 2)}
    overdispersed = (chi2.sf(stat, cdof) < 0.01 and options.plane_floor_m is None and options.estimate_plane_floor)
    if overdispersed:
        p_l, p_s = large.prob, small.prob
        saved = [(p, p.beta.copy(), p.solved, p.tau) for p in (p_l, p_s)]
        T_l, b_l = large.T, large.boards
        if p_l.has_beta and chi2.sf(*p_l.term_consistency(inliers, T_l, b_l, floor)) < 0.01:
            T_l, b_l = estimate_board_scatter(p_l, active, inliers, T_l, b_l, floor)[:2]
        if p_s.has_beta:
            p_s.tau = p_l.tau
        fl, (T_l, b_l, graph_l, result_l, _) = estimate_plane_error(p_l, active, inliers, T_l, b_l, floor, cdof)
        # What the plane error leaves (structure in the terms' own directions, or beyond a plane error's physical
        # size) scales the test as a quasi-likelihood.
        scale = max(p_l.plane_cost(inliers, T_l, b_l, fl) / cdof, 1.0)
        b_s = list(small.boards)
        graph_s, result_s, _ = p_s.solve(active, small.T, b_s, fl)
        delta = (_gaussian_objective(p_s, graph_s, result_s, active, inliers, b_s, fl)
                 - _gaussian_objective(p_l, graph_l, result_l, active, inliers, b_l, fl))
        scatter = p_l.tau
        shift = T_log(np.linalg.inv(result_s.atPose3(EXTRINSIC).matrix()) @ result_l.atPose3(EXTRINSIC).matrix())
        added = p_l.beta.copy()
        for p, beta, solved, tau in saved:
            p.beta, p.solved, p.tau = beta, solved, tau
        p_value = float(fdtrc(ddof, cdof, max(delta, 0.0) / ddof / scale))
        record.update({"reference": f"F({ddof}, {cdof:.4g})", "plane_error_m": float(fl), "board_scatter_m": scatter,
                       "cost_decrease_with_plane_error": float(delta), "quasi_likelihood_scale": float(scale)})
    else:
        p_value = float(chi2.sf(max(delta, 0.0), ddof))
        record["reference"] = f"chi-square({ddof})"
        shift, added = T_log(np.linalg.inv(small.T) @ large.T), large.prob.beta
    # the larger model's terms and the estimate's shift to it, as the test weighed them (``weak_offset``)
    record.update({"p_value": p_value, "included": bool(p_value < MODEL_TEST_P), "shift_tangent": shift.tolist(),
                   "values_m": [float(v) for v in added]})
    return record


def _relative_consistency(fit: _ModelFit, base: _ModelFit, active: list[int], inliers: list[int], floor: float,
                          fit_test: dict, base_test: dict) -> tuple[float, float]:
    """How the boards agree under ``fit`` against under ``base`` (the global offset alone): the ratio of their
    variance factors and its p-value as F. Per-ring and black-square terms read structure within each board;
    when it differs from board to board, shared terms leave the boards worse than the offset alone. On
    overdispersed data the variance factors compared are those the boards' scatter and a per-board plane error
    of physical size leave (the tests' quasi-likelihood scales; when the offset's leaves none, the combination's is
    tested as chi-square on its own degrees of freedom), else the raw ones."""
    if "quasi_likelihood_scale" in fit_test and "quasi_likelihood_scale" in base_test:
        d1, d0 = fit_test["consistency_dof"], base_test["consistency_dof"]
        base_scale = base_test["quasi_likelihood_scale"]
        ratio = fit_test["quasi_likelihood_scale"] / max(base_scale, 1.0)
        if chi2.sf(base_scale * d0, d0) >= 0.01:
            # The offset alone leaves the boards consistent (its scatter and plane error of physical size explain
            # them): the combination must too, tested on its own degrees of freedom.
            return float(ratio), float(chi2.sf(fit_test["quasi_likelihood_scale"] * d1, d1))
    else:
        s1, d1 = fit.prob.consistency(inliers, fit.T, fit.boards, floor, active)
        s0, d0 = base.prob.consistency(inliers, base.T, base.boards, floor, active)
        ratio = (s1 / d1) / max(s0 / d0, 1.0)
    return float(ratio), float(fdtrc(d1, d0, ratio))


def _weak_offset(test: dict) -> dict | None:
    """A global offset passed over that its last test (``test``) still supports at ``OFFSET_HELD_P``: the record the
    covariance holds it by (``RangeModelFit.weak_offset``: the offset and the estimate's shift with it, as the test
    weighed them, with the boards' disagreement modelled), else None. The test at ``MODEL_TEST_P`` keeps a term out
    of the estimate unless the data ask for it; an offset its test half supports is still a possible answer, which
    a covariance without it would not hold (on boards facing the rig an offset moves the extrinsic along their
    normals by about itself)."""
    if test["p_value"] >= OFFSET_HELD_P:
        return None
    return {"p_value": float(test["p_value"]), "with_ring_ends": bool(test.get("with_ring_ends")),
            "offset_mm": 1000 * float(test["values_m"][0]), "difference_tangent": list(test["shift_tangent"])}


def _weak_words(weak: dict | None) -> str:
    """How a record's ``weak_offset`` is said after its reason ("" for None)."""
    if weak is None:
        return ""
    return (f"; a global offset of {weak['offset_mm']:+.1f} mm, half supported (p = {weak['p_value']:.2g}"
            f"{' with the ring ends' if weak['with_ring_ends'] else ''}, below {OFFSET_HELD_P}), is held in the "
            "covariance beside the answer without it (--range-model offset takes it)")


def choose_range_model(prob: PlaneProblem, active: list[int], inliers: list[int], T: np.ndarray, boards: list,
                       floor: float, options: RefinementOptions, labels: FrameLabels, ends=None,
                       decided: dict | None = None) -> tuple:
    """The range model to refine with (``solvers.range_model``): the requested one, or under ``auto`` the
    terms the data support (:func:`_model_test`): a global offset against none, then the per-ring and the
    black-square terms each against the offset (against none, with the offset, when the offset alone is not
    supported); both when both pass. A combination that leaves the boards'
    planes worse than the offset alone (:func:`_relative_consistency`, at 1%) tries the smaller ones before
    the offset alone. Returns the problem (solved at its estimate), the estimate and the record.

    ``ends``: a callable giving ``(problem, T, boards)`` with the ring ends on the board's outline in the graph,
    or None (``refinement._offset_ends``; called only where needed). Where the planes alone do not support the
    offset, it is tested again there,
    and taken when it passes: on boards facing the rig an offset is nearly the translation along their normals,
    which the planes cannot tell apart and the ends can (a VLP-16 ranging 2 cm long on such boards went unfound,
    its answers 14-25 mm off and reading ``OK``: bench_weak_offset). The other blocks are tested on the planes,
    against the offset, as before.

    ``decided``: under ``auto``, what this choice decided before on the same inputs (``choice_memo.decision``):
    the chosen model alone is solved, and the record is the tests' (``choice_memo``)."""
    wanted = options.range_model
    if decided is not None and wanted == "auto":
        record = decided_fields(decided)
        if record["chosen"] == "none":
            return prob, T, boards, RangeModelFit(**record)
        f = _fit_model(prob, record["chosen"], labels, active, inliers, T, boards, floor, options)
        return f.prob, f.T, f.boards, RangeModelFit(names=f.prob.terms.names, values_m=tuple(f.prob.beta.tolist()),
                                                    terms=f.prob.terms, **record)
    fits: dict[str, _ModelFit] = {}
    seen = set()

    def fit(model: str) -> None:
        terms = terms_for(model, labels, options.range_accuracy_m)
        key = terms.names if terms is not None else ()
        if key not in seen:  # per-ring without rings, black squares without both colours: nothing new to test
            seen.add(key)
            fits[model] = _fit_model(prob, model, labels, active, inliers, T, boards, floor, options)

    # A requested model is fitted, not tested; under auto every model but ``full``, which is fitted only when
    # both of its blocks pass (a fifth of the choice's time where they do not).
    for model in ["none", "offset", "per-ring", "offset+dark"] if wanted == "auto" else [wanted]:
        fit(model)
    record = dict(requested=wanted, range_accuracy_m=float(options.range_accuracy_m))
    if wanted != "auto":
        f = fits[wanted]
        got = f.prob.terms.model
        why = f"requested ({wanted})" + ("" if got == wanted else f"; the data allow only the {got} terms")
        return f.prob, f.T, f.boards, RangeModelFit(chosen=got, reason=why, names=f.prob.terms.names,
                                                    values_m=tuple(f.prob.beta.tolist()), terms=f.prob.terms, **record)
    tests = [_model_test(fits["none"], fits["offset"], active, inliers, floor, options)]
    ended = ends() if ends is not None and not tests[0]["included"] and "offset" in fits else None
    if ended is not None:
        e_prob, T_e, b_e = ended
        with_ends = [_fit_model(e_prob, m, labels, active, inliers, T_e, b_e, floor, options)
                     for m in ("none", "offset")]
        tests.append({**_model_test(*with_ends, active, inliers, floor, options), "with_ring_ends": True})
    offset_test = tests[-1]
    # The per-ring and black-square blocks are tested against the offset when it is supported, else against none
    # (with the offset in the block): a strong within-board structure can hide a global offset that only its own
    # terms make visible.
    base = "offset" if any(t["included"] for t in tests) else "none"
    blocks, by_model = [], {"offset": tests[0]}
    for model in ("per-ring", "offset+dark"):
        if model in fits:
            tests.append(_model_test(fits[base], fits[model], active, inliers, floor, options))
            by_model[model] = tests[-1]
            if tests[-1]["included"]:
                blocks.append(model)
    if not blocks and base == "none":
        also = "".join(f", {t['p_value']:.2g} with the ring ends" for t in tests if t.get("with_ring_ends"))
        why = (f"no range term is supported by the data (p = {tests[0]['p_value']:.2g}{also} for a global offset, "
               f"test at "
               f"{MODEL_TEST_P}" + (", with the per-board plane error in place" if "plane_error_m" in tests[0] else "")
               + ")")
        weak = _weak_offset(offset_test)
        return prob, T, boards, RangeModelFit(chosen="none", reason=why + _weak_words(weak), tests=tuple(tests),
                                              weak_offset=weak, **record)
    if len(blocks) == 2:
        fit("full")
    candidates = (["full"] if len(blocks) == 2 and "full" in fits else []) + blocks + [base]
    if candidates[0] == "full":
        by_model["full"] = _model_test(fits[base], fits["full"], active, inliers, floor, options)
    chosen, notes, left_out = base, [], []
    for model in candidates:
        if model == base:
            break
        ratio, p_rel = _relative_consistency(fits[model], fits["offset"], active, inliers, floor, by_model[model],
                                             tests[0])
        if p_rel >= 0.01:
            chosen = model
            break
        left_out.append(model)
        notes.append(f"the {model} terms left the boards' planes {ratio:.1f}x as inconsistent as the offset alone "
                     f"(p = {p_rel:.1g}): their within-board structure differs from board to board")
    if chosen == "none":
        why = ("no range term is kept: " + "; ".join(notes) + f" (a global offset alone: p = {tests[0]['p_value']:.2g}"
               f", test at {MODEL_TEST_P})")
        weak = _weak_offset(offset_test)
        return prob, T, boards, RangeModelFit(chosen="none", reason=why + _weak_words(weak), tests=tuple(tests),
                                              left_out=tuple(left_out), weak_offset=weak, **record)
    f = fits[chosen]
    why = f"the {chosen} terms are supported (" + "; ".join(
        f"{t['model']} against {t['against']}{' with the ring ends' if t.get('with_ring_ends') else ''}: "
        f"p = {t['p_value']:.2g}" for t in tests if t["included"]) + ")"
    if notes:
        why += "; " + "; ".join(notes) + f"; fell back to {chosen}"
    return f.prob, f.T, f.boards, RangeModelFit(chosen=chosen, reason=why, names=f.prob.terms.names,
                                                values_m=tuple(f.prob.beta.tolist()), tests=tuple(tests),
                                                terms=f.prob.terms, left_out=tuple(left_out), **record)


def with_uncertainty(fit: RangeModelFit, prob: PlaneProblem, marginals: gtsam.Marginals) -> RangeModelFit:
    """The record with the terms' final values, their marginal standard deviations, the share of the
    extrinsic's covariance due to them, the global offset's correlation with the translation, and the term
    most confounded with a direction of the extrinsic (its multiple correlation with the 6 parameters)."""
    keys = gtsam.KeyVector([EXTRINSIC, RANGE])
    J = marginals.jointMarginalCovariance(keys).fullMatrix()
    Cxx, Cxb, Cbb = J[:6, :6], J[:6, 6:], J[6:, 6:]
    share = Cxb @ np.linalg.solve(Cbb, Cxb.T)
    sd_b = np.sqrt(np.maximum(np.diag(Cbb), 0.0))
    corr = Cxb[3:, 0] / np.sqrt(np.maximum(np.diag(Cxx)[3:], 1e-300)) / max(sd_b[0], 1e-300)
    confounding = None
    best = (0.0, -1)
    for k in range(Cbb.shape[0]):
        if k in prob.pinned or sd_b[k] <= 0:
            continue
        r2 = float(Cxb[:, k] @ np.linalg.solve(Cxx, Cxb[:, k]) / Cbb[k, k])
        best = max(best, (r2, k))
    if best[1] >= 0 and np.sqrt(max(best[0], 0.0)) > CONFOUNDED_CORRELATION:
        k = best[1]
        g = np.linalg.solve(Cxx, Cxb[:, k])  # the extrinsic's combination most correlated with the term
        u = g / np.linalg.norm(g)
        part = "translation" if np.linalg.norm(u[3:]) >= np.linalg.norm(u[:3]) else "rotation"
        v = u[3:] if part == "translation" else u[:3]
        axis = int(np.argmax(np.abs(v)))
        direction = (f"the {part} {'along' if part == 'translation' else 'about'} the LiDAR's "
                     f"{'xyz'[axis]} axis" + ("" if abs(v[axis]) > 0.9 * np.linalg.norm(v) else
                                              f" (direction {np.round(v / np.linalg.norm(v), 2).tolist()})"))
        e = np.zeros(6)
        e[3 + axis if part == "translation" else axis] = 1.0
        unit, scale = ("mm", 1000.0) if part == "translation" else ("deg", float(np.degrees(1.0)))
        confounding = {"term": prob.terms.names[k], "correlation": float(np.sqrt(best[0])), "direction": direction,
                       "tangent_direction": u.tolist(), "unit": unit, "sd": float(scale * np.sqrt(e @ Cxx @ e)),
                       "sd_if_known": float(scale * np.sqrt(max(e @ (Cxx - share) @ e, 0.0))),
                       "advice": "Boards that face the LiDAR at varied incidence and distances separate them: "
                                 "`lidarcam layout DATASET --suggest 2 --range-offset` suggests the poses to add."}
    return replace(fit, values_m=tuple(prob.beta.tolist()), std_m=tuple(sd_b.tolist()), terms_covariance=Cbb,
                   extrinsic_share=0.5 * (share + share.T), offset_translation_correlation=tuple(corr.tolist()),
                   confounding=confounding)


def consider_pinned(prob: PlaneProblem, active: list[int], result: gtsam.Values, floor: float, fit: RangeModelFit
                    ) -> tuple[np.ndarray, RangeModelFit]:
    """The extrinsic's covariance with the pinned terms held at 0 and their prior variance propagated (a
    "consider" covariance): ``A^-1 + A^-1 B P B^T A^-1`` over the other variables, with ``A`` their information,
    ``B`` its coupling to the pinned terms and ``P`` the pinned terms' prior covariance. Also returns the record
    with that share in ``extrinsic_share`` and the pinned terms' standard deviations set to their priors."""
    H, _ = hessian(prob.graph(active, floor, free_pinned=True), result, len(active))
    K = prob.terms.size
    n = H.shape[0] - K
    pinned = [n + k for k in prob.pinned]
    rest = [i for i in range(H.shape[0]) if i not in pinned]
    A, B = H[np.ix_(rest, rest)], H[np.ix_(rest, pinned)]
    P = np.diag(prob.terms_prior_sd()[list(prob.pinned)] ** 2)
    Ainv = np.linalg.pinv(A)  # A is the information of a solve that succeeded; pinv keeps a rank loss finite
    G = Ainv @ B
    cov_rest = Ainv + G @ P @ G.T
    cov = cov_rest[:6, :6]
    cond = np.linalg.pinv(H[:n, :n])[:6, :6]  # every term known
    std = list(fit.std_m)
    for k in prob.pinned:
        std[k] = float(prob.terms_prior_sd()[k])
    share = cov - cond
    return 0.5 * (cov + cov.T), replace(fit, std_m=tuple(std), extrinsic_share=0.5 * (share + share.T))


def consider_placement(prob: PlaneProblem, active: list[int], T: np.ndarray, boards: list, floor: float,
                       cov: np.ndarray, fit: RangeModelFit) -> tuple[np.ndarray, RangeModelFit, np.ndarray]:
    """The black squares' placement propagated: the colours are placed under the estimate, itself uncertain, and
    a pattern placed a few millimetres off gives the returns near the squares' edges the wrong colour, which
    shrinks the black-square term (and, through it, moves the rest). Placed again under the extrinsic moved by
    one standard deviation each way along each principal direction of ``cov`` and solved again (one Gauss-Newton
    step): the shifts' spread is added to the covariance ("consider" covariance, as for pinned terms and
    intrinsics), and their mean, summed over the directions, is the shrinkage that the estimate's own error
    causes on average (second order): it is taken off the terms and the extrinsic, and its square kept in the
    covariance. Returns the covariance, the record and the extrinsic."""
    ev, V = np.linalg.eigh(0.5 * (cov + cov.T))
    values = prob.values(active, T, boards, floor)
    K = prob.terms.size
    extra = np.zeros((6 + K, 6 + K))
    bias = np.zeros(6 + K)
    for lam, v in zip(ev, V.T):
        shifts = []
        for sign in (1.0, -1.0):
            T_moved = T @ T_exp(sign * np.sqrt(max(lam, 0.0)) * v)
            labels = frame_labels(prob.frames, prob.board, T_moved, boards, prob.labels.placement_cov)
            moved = prob.variant(labels=replace(prob.labels, dark=labels.dark))
            # One Gauss-Newton step from the estimate: the shift the new colours call for, to first order.
            delta = moved.graph(active, floor).linearize(values).optimize()
            shifts.append(np.concatenate([delta.at(EXTRINSIC), delta.at(RANGE)]))
        spread, shrink = 0.5 * (shifts[0] - shifts[1]), 0.5 * (shifts[0] + shifts[1])
        extra += np.outer(spread, spread) + np.outer(shrink, shrink)
        bias += shrink
    std = np.sqrt(np.array(fit.std_m) ** 2 + np.diag(extra)[6:])
    Cbb = fit.terms_covariance + extra[6:, 6:] if fit.terms_covariance is not None else None
    if np.any(np.abs(bias[6:]) > std):  # beyond second order (a term the data barely hold): not corrected
        bias[:] = 0.0
    prob.beta = prob.beta - bias[6:]
    return (cov + extra[:6, :6], replace(fit, values_m=tuple(prob.beta.tolist()), std_m=tuple(std.tolist()),
                                         terms_covariance=Cbb), T @ T_exp(-bias[:6]))
