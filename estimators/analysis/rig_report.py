"""A rig's report: its verdict, every pair from the joint graph beside each camera-LiDAR pair alone, each pair's
farthest-off overlay, then the warnings, every sensor, each camera-LiDAR pair's spread and posterior (the single
pair's tables, ``analysis.report.spread_section``, and corner plot, ``analysis.report_figures``) and its frames
with the LiDAR's points and board outline drawn into the image under the joint estimate (the single pair's
overlay, ``analysis.report.projection_figure``)."""
from __future__ import annotations

import contextlib
import html
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from geometry.rotations import T_log

from ..io.output import write_atomic
from ..solvers.rig_graph import translation_sd_in_first
from .report import (_img, _table, board_choice_figure, board_choice_part, edges_section, html_page,
                     layout_part, mcmc_part, offsets_section, overlay_name, params_table, projection_figure,
                     range_model_part, range_residual_arrays, residual_arrays, spread_section, terms_table,
                     verdict_part)
from .rig_layout import next_pose_words

# The overlays a pair folder's report shows right after the estimate, before its tables (a larger rig's: each
# pair's farthest-off one).
FIRST_OVERLAYS = 3
FIGURE_THREADS = 2


def _pair_rows(result) -> list[list[str]]:
    sol, rows = result.solution, []
    for a, b in result.pairs():
        T, C = sol.transform(a, b)
        sd = np.sqrt(np.maximum(np.diag(C), 0.0))
        row = [f"T_{a}_{b}", ", ".join(f"{1000 * v:.1f}" for v in T[:3, 3]),
               ", ".join(f"{1000 * v:.2f}" for v in translation_sd_in_first(T, C)),
               ", ".join(f"{np.degrees(v):.3f}" for v in sd[:3])]
        if (a, b) in result.pairwise:
            Tp, Cp, n = result.pairwise[(a, b)]
            xi = T_log(np.linalg.inv(T) @ Tp)
            row += [str(n), f"{np.degrees(np.linalg.norm(xi[:3])):.3f} deg, {1000 * np.linalg.norm(xi[3:]):.1f} mm",
                    ", ".join(f"{1000 * v:.2f}" for v in translation_sd_in_first(Tp, Cp))]
        else:
            row += ["-", "-", "-"]
        if result.posterior is not None:
            summary = result.pair(a, b).summary()
            row.append(", ".join(f"[{lo:+.2f}, {hi:+.2f}]" for lo, hi in summary["95%"]["translation_mm"]))
            row.append(f"{summary['credible_regions']['99.9%']['d2']:.1f}")
        rows.append(row)
    return rows


def write_rig_report(result, out_dir: str | Path, figure_process=None) -> Path:
    """Write ``OUT/report.html`` for a rig (module docstring) and its overlays (``projection_<camera>_<lidar>_
    <frame>.jpg``), each file atomically. ``figure_process``: the child that draws the matplotlib figures
    (``analysis.figure_process.FigureProcess``, started ahead of the calibration by the command line so that it has
    loaded matplotlib by now); without one, one is started here."""
    sol = result.solution
    post = result.posterior
    parts = [f"<h1>lidarcam rig report</h1><p>rig: {html.escape(str(result.rig.root))}; reference "
             f"{html.escape(sol.reference)}; one graph"
             + ("" if post is not None else ", Laplace covariance (posterior not sampled)") + ".</p>"]
    parts.append(verdict_part(result))
    if post is not None:
        parts.append(mcmc_part(post))
    parts.append("<h2>Every pair</h2><p>From the joint graph: the translation (mm, in the first sensor's frame) "
                 "with its standard deviations, the rotation's standard deviations (deg); for a camera-LiDAR pair, "
                 "the frames it shares, how far the pair solved alone lies, and that estimate's translation "
                 "standard deviations" + ("; the posterior's 95% interval of the translation's right tangent "
                                          "(mm, along the second sensor's axes) and its 99.9% credible region "
                                          "(the squared Mahalanobis distance under the pair's posterior "
                                          "covariance within which 99.9% of its samples lie)"
                                          if post is not None else "")
                 + ".</p>"
                 + _table(_pair_rows(result), ["pair", "t [mm]", "t sd [mm]", "rotation sd [deg]", "frames",
                                               "pair alone: away", "pair alone: t sd [mm]"]
                          + (["posterior 95%: t [mm]", "99.9% region: d2 (a Gaussian's 22.5)"]
                             if post is not None else [])))
    if result.time_offsets:  # a still-pose recording's clocks, from the board's motion between poses
        from ..io.motion_track import FOLLOWED_CAMERA

        lines = [result.time_offset.line()] if result.time_offset is not None else \
            [o.line(FOLLOWED_CAMERA, n) for n, o in result.time_offsets.items()]
        parts.append("<h2>The clocks' offset</h2>" + "".join(f"<p>{html.escape(w)}.</p>" for w in lines))
    kind = "posterior" if post is not None else "Laplace"
    for c in result.rig.cameras:  # each camera-LiDAR pair's spread as a single pair's report gives it
        for lid in result.rig.lidars:
            parts.append(spread_section(result.pair(c.name, lid.name), kind,
                                        f"T_{html.escape(c.name)}_{html.escape(lid.name)}: "))
    top = len(parts)  # each pair's farthest-off overlay goes here, once drawn (below)
    warnings = "".join(f"<li>{html.escape(w)}</li>" for w in result.warnings) or "<li>none</li>"
    parts.append(f"<h2>Warnings</h2><ul>{warnings}</ul>")
    from ..pipeline.rig_result import range_model_words

    rows = [[s.name, s.type, len(result.frames_used.get(s.name, ())), len(result.skipped.get(s.name, {})),
             f"{sol.noise_scale.get(s.name, 1.0):.2f}",
             range_model_words(result.range_models[s.name]) if s.name in result.range_models else "-"]
            for s in result.rig.sensors]
    parts.append("<h2>Sensors</h2>" + _table(rows, ["sensor", "type", "frames used", "skipped", "noise scale",
                                                    "LiDAR range model"]))
    parts += range_terms_parts(result)
    links = dict(result.pair_results or {})
    for (c, lid), link in links.items():  # each pair solved alone: its normals' spread, as a single pair's
        parts.append(layout_part(link, f"{html.escape(c)}-{html.escape(lid)}: "))
    first_pairs = {}  # each LiDAR's board choices, with the first camera that measured it
    for (c, lid), frames in (getattr(result.measurements, "pairs", None) or {}).items():
        first_pairs.setdefault(lid, (c, frames))
    for lid, (c, frames) in first_pairs.items():
        decided = [f for f in frames if f.decision is not None]
        if decided:
            parts.append(board_choice_part(decided, f"{html.escape(lid)} (with {html.escape(c)}): "))
    # Each LiDAR's edges in the joint graph, and each 3D pair's edges as a check of the joint estimate: the single
    # pair's section (a p-value of the outlines' shift below 0.01 is warned about: a wrong board.size or
    # pattern_offset, or an extrinsic the edges contradict)
    parts += [edges_section(e, f"{html.escape(n)}: ") for n, e in result.edges.items()]
    parts += [edges_section(e, f"T_{html.escape(a)}_{html.escape(b)}: ") for (a, b), e in result.outline_checks.items()]
    if result.intrinsics_test is not None:
        t = result.intrinsics_test
        parts.append(f"<h2>Intrinsics refined with the rig</h2><p>Every sensor's chi-square is "
                     f"{t['chi_square_given']:.0f} under the given intrinsics and {t['chi_square_refined']:.0f} under "
                     f"the refined ones, on {t['dof']:.0f} dof; {t['own_corners_drop']:.0f} of the drop is what they "
                     "gain on the cameras' own corners alone. Beyond that, refining "
                     + ("lowers the disagreement beyond what freed intrinsics fit: the other sensors confirm them" if
                        t["lowers_disagreement"] else "does not lower the disagreement beyond what freed intrinsics "
                        "fit: keep the given intrinsics") + f" (F test p = {t['p_value']:.2g}).</p>"
                     + "".join(f"<h3>{html.escape(n)}</h3>" + params_table(result.cameras[n].params, p, sd)
                               for n, (p, sd) in (sol.intrinsics or {}).items()))
    layout = result.layout()
    if layout["weakest_pair"]:
        w = layout["pairs"][layout["weakest_pair"]]
        few = ", ".join(f"{k} ({n})" for k, n in layout["links_with_few_frames"].items()) or "none"
        parts.append(f"<h2>Layout</h2><p>The weakest camera-LiDAR pair is {html.escape(layout['weakest_pair'])}: its "
                     f"translation's standard deviation reaches {w['max_translation_sd_mm']:.1f} mm along "
                     f"{html.escape(w['axis'])}; to constrain it, {html.escape(w['advice'])}. Sensor pairs sharing "
                     f"fewer than 3 frames with the board found in both: {html.escape(few)}.</p>"
                     + (f"<p>The next board pose for it: {html.escape(next_pose_words(layout['next_pose']))}; its 4x4 "
                        "<code>T_camera_board</code> is in calibration.json (<code>layout.next_pose</code>).</p>"
                        if layout["next_pose"] else ""))
    skipped = [[n, st, why] for n, d in result.skipped.items() for st, why in sorted(d.items())]
    if skipped:
        parts.append("<h2>Frames skipped</h2>" + _table(skipped, ["sensor", "frame", "why"]))
    out = Path(out_dir)
    from .figure_process import FigureProcess

    pictures = []  # (file, title, bytes): the matplotlib figures drawn in a child while the overlays are drawn here
    two = len(result.rig.cameras) == 1 and len(result.rig.lidars) == 1
    with contextlib.nullcontext(figure_process) if figure_process is not None else FigureProcess() as figures:
        # a pair's chain holds the tangent of T_<camera>_<lidar> first and the camera's noise scale last: its
        # traces are drawn as a single pair's (a larger rig's chain holds many sensors' tangents)
        chain = np.concatenate([post.run.chain[:, :, :6], post.run.chain[:, :, -1:]], axis=2) if post else None
        corners = {(c.name, d.name): figures.draw(
            "posterior" if two else "corner", xi=post.pair_samples(c.name, d.name),
            covariance_laplace=sol.transform(c.name, d.name)[1],
            **({"chain": chain, "burn": np.array(post.run.burn)} if two else {}))
            for c in result.rig.cameras for d in result.rig.lidars} if post is not None else {}
        residuals, ranges = draw_pairs_ahead(links, figures)
        overlays, first = _overlays(result, out)
        choices = _board_choices(result, first_pairs)
        for (c, lid), job in residuals.items():
            pictures.append((f"residuals_{c}_{lid}.png", f"{c}-{lid} solved alone: per-frame residuals",
                             job()["residuals.png"]))
        for (c, lid), job in ranges.items():
            pictures.append((f"range_residuals_{c}_{lid}.png", f"{c}-{lid} solved alone: LiDAR range residuals by "
                             "range, ring and square colour", job()["range_residuals.png"]))
        drawn = {pair: job() for pair, job in corners.items()}
        corner_pngs = {pair: pngs["corner.png"] for pair, pngs in drawn.items()}
        pictures += choices
        pictures += [("traces.png", "MCMC traces", pngs["traces.png"]) for pngs in drawn.values()
                     if "traces.png" in pngs]
    if corner_pngs:
        parts.append("<h2>Each camera-LiDAR pair's posterior</h2><p>Its samples (composed from the rig's joint "
                     "samples; tangent offsets from the estimate about and along the LiDAR's axes) against the joint "
                     "graph's Laplace covariance (red).</p>")
        for (cam, lidar), png in corner_pngs.items():
            name = f"corner_{cam}_{lidar}.png"
            write_atomic(out / name, lambda fh, png=png: fh.write(png), mode="wb")
            parts.append(f"<h3>T_{html.escape(cam)}_{html.escape(lidar)}</h3>" + _picture(result, name, png))
    for name, title, png in pictures:
        write_atomic(out / name, lambda fh, png=png: fh.write(png), mode="wb")
        parts.append(f"<h2>{html.escape(title)}</h2>" + _picture(result, name, png))
    if first:
        parts.insert(top, "<h2>Overlays</h2><p>Each camera-LiDAR pair's frame whose LiDAR board outline (red) sits "
                          "farthest from the camera's board (green) under the joint estimate; every frame's is "
                          "below.</p>" + "".join(first))
    parts += overlays
    return write_atomic(out / "report.html", lambda fh: fh.write(html_page("lidarcam rig report", parts)))


def _picture(result, name: str, data: bytes) -> str:
    """A figure in the page: embedded for a rig of one camera-LiDAR pair (a pair folder's report is
    self-contained, as a single pair's was), else the file beside it (a 6-camera rig's overlays alone would make a
    page of tens of MB)."""
    if len(result.pair_frames or {}) <= 1:
        return _img(name, data)
    return f"<img alt='{html.escape(name)}' src='{html.escape(name)}'>"


def draw_pairs_ahead(links: dict, figures) -> tuple[dict, dict]:
    """Start each camera-LiDAR pair's own figures (``links``: ``(camera, lidar) -> CalibrationResult``) in the
    figure process ``figures``: its per-frame residuals and its range residuals, each pair's waiter by pair. The
    command line calls it once the joint graph is solved (``calibrate_rig``'s ``on_solved``), so that they are drawn
    while the posterior is sampled; the report asks for the same figures later and gets these."""
    residuals = {k: figures.draw("residuals", **residual_arrays(link)) for k, link in links.items()
                 if link.refinement is not None}
    ranges = {k: figures.draw("range_residuals", **arrays) for k, link in links.items()
              if (arrays := range_residual_arrays(link)) is not None}
    return residuals, ranges


def range_terms_parts(result) -> list[str]:
    """Each LiDAR's range model as the pair that chose it reads it (``report.range_model_part``: why, the priors,
    the terms held, a term confounded with the extrinsic) and its range terms in the joint graph, as a single pair's
    report lists its own (``terms_table``)."""
    parts = []
    for name, record in result.range_models.items():
        held = {h["term"] for h in record.get("held_at_prior", ())}
        terms = [(n, t["value_m"], t["sd_m"], t["prior_sd_m"], n in held) for n, t in record.get("terms", {}).items()]
        chooser = tuple(record.get("chosen_by", "").split("-", 1))
        link = (result.pair_results or {}).get(chooser)
        fit = link.refinement.range_model if link is not None and link.refinement is not None else None
        if fit is not None:
            parts.append(range_model_part(fit, f"{html.escape(name)} (as {html.escape('-'.join(chooser))} chose it): "))
        if terms:
            parts.append(f"<h2>{html.escape(name)}: LiDAR range terms</h2>" + terms_table(terms))
    return parts


def _board_choices(result, first_pairs: dict) -> list[tuple[str, str, bytes]]:
    """Each LiDAR's frames with a board choice: its sweep's top view with the candidates (``report.board_choice_
    figure``), ``board_choice_<lidar>_<frame>.png``."""
    jobs = [(lid, f) for lid, (_, frames) in first_pairs.items() for f in frames
            if f.decision is not None and f.decision.candidate_points]

    def draw(job):
        lid, f = job
        sensor = result.rig.sensor(lid)
        return board_choice_figure(f, sensor.file(f.name), sensor.lidar == "2d")

    pngs = _each(draw, jobs)
    return [(f"board_choice_{lid}_{f.name}.png", f"{lid}, frame {f.name}: LiDAR board candidates (top view)", png)
            for (lid, f), png in zip(jobs, pngs)]


def _each(draw, items: list) -> list:
    """``draw`` of every item, in order, on ``FIGURE_THREADS`` threads: each figure reads its frame's image or
    sweep again (decoding and parsing release the interpreter), which one thread did in turn."""
    if len(items) < 2:
        return [draw(item) for item in items]
    with ThreadPoolExecutor(FIGURE_THREADS) as pool:
        return list(pool.map(draw, items))


def _overlays(result, out: Path) -> tuple[list[str], list[str]]:
    """Each camera-LiDAR pair's frames with the LiDAR's points and board outline drawn into the image under the
    joint estimate (``projection_<camera>_<lidar>_<frame>.jpg``, written here and embedded), as the page's parts;
    and each pair's farthest-off one (by its outline offset; a rig of one pair, its ``FIRST_OVERLAYS``), titled,
    for the page's top."""
    sol, parts, first = result.solution, [], []
    shown = FIRST_OVERLAYS if len(result.pair_frames or {}) == 1 else 1  # at the top: a single pair's three
    for (cam, lidar), frames in (result.pair_frames or {}).items():
        T, _ = sol.transform(cam, lidar)
        c, lid = result.rig.sensor(cam), result.rig.sensor(lidar)
        images, offsets, jpgs = [], [], {}
        drawn = _each(lambda f: projection_figure(result.camera_model(cam), T, f, result.rig.board, c.file(f.name),
                                                  lid.file(f.name)), frames)
        for f, (jpg, off) in zip(frames, drawn):
            if np.all(np.isfinite(off)):
                offsets.append((f.name, off))
            name = overlay_name(cam, lidar, f.name)
            write_atomic(out / name, lambda fh, jpg=jpg: fh.write(jpg), mode="wb")
            images.append(_picture(result, name, jpg))
            jpgs[f.name] = jpg
        if offsets:  # the single pair's table of the outline offsets, under the joint estimate
            parts.append(offsets_section(offsets, f"T_{html.escape(cam)}_{html.escape(lidar)}: "))
            for worst, _ in sorted(offsets, key=lambda o: -float(np.linalg.norm(o[1])))[:shown]:
                first.append(f"<p>T_{html.escape(cam)}_{html.escape(lidar)}, frame {html.escape(worst)}</p>"
                             + _picture(result, overlay_name(cam, lidar, worst), jpgs[worst]))
        parts.append(f"<h2>{html.escape(cam)} and {html.escape(lidar)}: the LiDAR's points and board outline in the "
                     "image (joint estimate)</h2>")
        parts += images
    return parts, first
