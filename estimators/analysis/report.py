"""The report's parts (``analysis.rig_report`` writes the one report, a pair folder's too): the verdict, a pair's
spread and intervals, the MCMC diagnostics, the board edges, the range model, the board choices, the layout, the
outline offsets; the overlays (LiDAR points and both board outlines in the image, JPEG) and the board choices' top
views; each pair's residual arrays for the matplotlib figures.
"""
from __future__ import annotations

import base64
import html

import cv2
import numpy as np

from geometry.camera import CameraModel
from geometry.rotations import transform_points
from geometry.vectors import row_norms

from ..io.image_io import read_gray
from ..io.pointcloud_io import read_scan, read_scan_2d
from ..solvers.closed_form import describe_direction
from ..solvers.factors import lidar_plane
from ..solvers.intrinsics_refinement import param_names
from ..solvers.posterior import INTERVAL_LEVELS
from ..solvers.range_model import frame_labels, point_residuals
from .top_view import top_view_png

_PROJECTION_WIDTH_PX = 1200  # the projection figures' image width: 8 in at 90 dpi is 720 px, with room to zoom
# The overlays are photographs: JPEG at this quality is a quarter of a PNG's size (a grey image's noise is what a
# lossless encoding keeps: 1.2 MB a frame, 85 MB for the 78 overlays of a 10-pose rig of 3 cameras and 3 LiDARs)
# and encodes 6-8 times faster; the dots and outlines keep their colours.
_OVERLAY_JPEG_QUALITY = 90


def overlay_name(*parts: str) -> str:
    """The file of a :func:`projection_figure`: ``projection_<parts joined by _>.jpg``."""
    return f"projection_{'_'.join(parts)}.jpg"


def residual_arrays(result) -> dict[str, np.ndarray]:
    """What ``report_figures.residuals_pngs`` draws: per used frame, its plane consistency chi-square (NaN where
    the refinement has none), outlier flag, corner RMS and the camera-vs-LiDAR plane angle and distance."""
    fits = {f.name: f for f in result.refinement.frames} if result.refinement else {}
    names = [f.name for f in result.frames if f.usable]
    return {"names": np.array(names, dtype=str),
            "chi2": np.array([fits[n].consistency_chi2 if n in fits else np.nan for n in names], float),
            "outlier": np.array([bool(fits[n].outlier) if n in fits else False for n in names], bool),
            "corner_rms_px": np.array([f.camera.reprojection_rms_px for f in result.frames if f.usable], float),
            "angle_deg": np.array([np.degrees(result.plane_residuals[n][0]) if n in result.plane_residuals
                                   else np.nan for n in names], float),
            "distance_mm": np.array([1000 * result.plane_residuals[n][1] if n in result.plane_residuals
                                     else np.nan for n in names], float)}


def edges_section(edges: dict, title: str = "") -> str:
    """A board-edges record (``edges_in_graph``: a single pair's, a rig LiDAR's used in its graph, or a rig pair's
    check), used or as a check of the planes' estimate (and why the default left them out, where it did): the
    outlines' mean shift with its 99% test (where the
    record is a pair's), the outline's growth (and offset, when used), the test of the planes against the edges,
    and each frame's shift (where listed)."""
    def pm(key: str, k: int, factor: float = 1.0) -> str:  # a value with its sd where the record has one
        sd = edges.get(key[:-len("_m")] + "_sd_m")
        return f"{factor * 1000 * edges[key][k]:+.1f}" + (f" ± {factor * 1000 * sd[k]:.1f}" if sd else "")

    left = (f"<p>The board's edges were left out of the estimate: {html.escape(edges['left_out'])}. The answer is "
            "the planes' alone; the edges' answer is in calibration.json (board_edges.with_edges).</p>"
            if edges.get("left_out") else "")
    if "ends" not in edges:  # no ring end found under the planes' estimate
        return f"<h2>{title}Board edges</h2>" + left
    how = ("used in the estimate" if edges["used"] else "not used in the estimate: they check it (calibrate with "
           "--edges to use them)")
    text = left + f"<p>{edges['ends']} ring ends on the boards' outlines, {how}."
    if "mean_shift_camera_m" in edges:
        m = 1000 * np.array(edges["mean_shift_camera_m"])
        sd = 1000 * np.sqrt(np.maximum(np.diag(np.array(edges["mean_shift_covariance"])), 0.0))
        text += (f" The LiDAR's outlines sit {np.linalg.norm(m):.1f} mm off the camera's on average (camera x y z: "
                 + ", ".join(f"{v:+.1f} ± {e:.1f}" for v, e in zip(m, sd))
                 + f" mm; p = {edges['mean_shift_p_value']:.2g}: "
                 + ("beyond" if edges["mean_shift_p_value"] < 0.01 else "within") + " its 99% limit).")
    text += f" The board looks {pm('growth_m', 0, 2)} mm wider and {pm('growth_m', 1, 2)} mm taller than board.size"
    if edges["used"]:
        text += (f"; its pattern sits {pm('outline_offset_m', 0)} / {pm('outline_offset_m', 1)} mm (x / y) from where "
                 "dataset.yaml puts it")
    text += ".</p>"
    test = edges.get("planes_against_edges")
    if test:
        text += (f"<p>The planes alone against the planes with the edges: d2 {test['d2']:.1f} on {test['dof']} dof "
                 f"(p = {test['p_value']:.2g}); below 0.01 the boards' planes or their outlines carry a bias (see "
                 "the warnings).</p>")

    def cell(f, k):
        v, e = f["shift_board_xy_m"][k], f["shift_sd_m"][k]
        return "-" if v is None else f"{1000 * v:+.1f} ± {1000 * e:.1f}"

    frames = edges["frames"] if isinstance(edges.get("frames"), list) else []
    rows = [[f["frame"], f["ends"], cell(f, 0), cell(f, 1)] for f in frames]
    return (f"<h2>{title}Board edges</h2>" + text
            + (_table(rows, ["frame", "ring ends", "outline shift x [mm]", "outline shift y [mm]"]) if rows else ""))


def terms_table(terms: list[tuple]) -> str:
    """A LiDAR's range terms ``(name, value m, sd m, prior sd m, held at the prior)`` as a table (a single pair's
    and each of a rig's LiDARs), or nothing without terms."""
    rows = [[n, f"{1000 * v:+.1f}", f"{1000 * sd:.1f}", f"{1000 * p:.1f}", "held at the prior" if held else "estimated"]
            for n, v, sd, p, held in terms]
    return _table(rows, ["term", "value [mm]", "std [mm]", "prior sd [mm]", ""]) if rows else ""


def params_table(given, refined, sd) -> str:
    """Intrinsics ``[fx, fy, cx, cy, dist...]`` given and refined, each with its standard deviation and how many of
    them it moved (a single pair's and each camera of a rig's)."""
    rows = [[n, f"{g:.6g}", f"{v:.6g}", f"{e:.3g}", f"{(v - g) / e:+.1f}"]
            for n, g, v, e in zip(param_names(len(refined)), given, refined, sd)]
    return _table(rows, ["parameter", "given", "refined", "sd", "moved [sd]"])


def board_outline_offset(cam: CameraModel, T_camera_lidar: np.ndarray, frame, board
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The camera's board outline and the LiDAR's (pixels), and the pixel offset ``(du, dv)`` of the LiDAR's.

    The LiDAR points, mapped by the estimate into the camera's board frame, span ``[x0, x1] x [y0, y1]``
    (0.5% / 99.5% quantiles, so stray stand points do not count); the beams' spacing shrinks that span
    alike on opposite sides, so its centre against the board's centre is the offset, which is then shown
    as the board outline shifted by it and measured in pixels."""
    T_board_lidar = np.linalg.inv(frame.camera.T_camera_board) @ T_camera_lidar
    pb = transform_points(T_board_lidar, frame.lidar.points)
    lo, hi = np.percentile(pb[:, :2], [0.5, 99.5], axis=0)
    w, h = board.extent
    shift = np.array([(lo[0] + hi[0] - w) / 2, (lo[1] + hi[1] - h) / 2, 0.0])
    outline = board.outline()
    board_px = cam.project(transform_points(frame.camera.T_camera_board, outline))
    lidar_px = cam.project(transform_points(frame.camera.T_camera_board, outline + shift))
    centre = cam.project(transform_points(frame.camera.T_camera_board, np.array([board.centre, board.centre + shift])))
    return board_px, lidar_px, centre[1] - centre[0]


def projection_figure(cam: CameraModel, T_camera_lidar: np.ndarray, frame, board, image_path, scan_path
                      ) -> tuple[bytes, np.ndarray]:
    """A frame's image with the LiDAR's points under ``T_camera_lidar`` (coloured by depth), the camera's board
    outline and the LiDAR's, as JPEG bytes (``projection_*.jpg``), and the LiDAR outline's pixel offset
    (:func:`board_outline_offset`)."""
    gray = read_gray(image_path)
    if frame.lidar.is_scan_line:
        xy = read_scan_2d(scan_path)
        scan = np.column_stack([xy, np.zeros(len(xy))])
    else:
        scan = read_scan(scan_path)
    pc = transform_points(T_camera_lidar, scan)
    # Only the points within the camera's field (a degree beyond its border's widest ray) are projected: a sweep
    # holds several times as many outside it, and projecting them was a third of a figure's time.
    cos_field = np.cos(min(cam.field_angle() + np.radians(1.0), 0.5 * np.pi))
    pc = pc[(pc[:, 2] > 0.3) & (pc[:, 2] >= cos_field * row_norms(pc))]
    uv = cam.project(pc)
    inside = cam.in_image(uv)
    uv, depth = uv[inside], pc[inside, 2]
    # Drawn with OpenCV straight into the image, reduced to the report's width (area averaging): points as
    # dots of a few pixels coloured by depth (the nearest painted last), the outlines as anti-aliased
    # polygons, and a caption strip with the title, the legend and the depth scale. A matplotlib figure of
    # the same content cost about 0.4 s per frame (half the report of a 28-frame recording).
    lo_hi = np.percentile(depth, [2, 98]) if len(depth) else np.array([0.0, 1.0])
    scale = min(1.0, _PROJECTION_WIDTH_PX / max(gray.shape[1], 1))
    if scale < 1.0:
        gray = cv2.resize(gray, (max(1, round(gray.shape[1] * scale)), max(1, round(gray.shape[0] * scale))),
                          interpolation=cv2.INTER_AREA)
    if gray.dtype != np.uint8:  # 16-bit images: shown by their own range
        g = gray.astype(np.float64)
        gray = np.clip(255 * (g - g.min()) / max(np.ptp(g), 1e-9), 0, 255).astype(np.uint8)
    h, w = gray.shape[:2]
    bgr = cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR)
    dot = max(1, round(max(w, h) / (500 if frame.lidar.is_scan_line else 1000)))
    order = np.argsort(-depth)
    colours = _turbo((depth[order] - lo_hi[0]) / max(lo_hi[1] - lo_hi[0], 1e-12))
    iu = np.rint((uv[order, 0] + 0.5) * scale - 0.5).astype(int)
    iv = np.rint((uv[order, 1] + 0.5) * scale - 0.5).astype(int)
    for du in range(-dot + 1, dot + 1):  # a square of 2 * dot pixels
        for dv in range(-dot + 1, dot + 1):
            ok = (iu + du >= 0) & (iu + du < w) & (iv + dv >= 0) & (iv + dv < h)
            bgr[iv[ok] + dv, iu[ok] + du] = colours[ok]
    if frame.lidar.is_scan_line:
        # One scan line fixes no board outline: show the camera's outline and the line only.
        board_px = cam.project(transform_points(frame.camera.T_camera_board, board.outline()))
        outlines, offset = ((board_px, _LIME, "board (camera)"),), np.full(2, np.nan)
    else:
        board_px, lidar_px, offset = board_outline_offset(cam, T_camera_lidar, frame, board)
        outlines = ((board_px, _LIME, "board (camera)"), (lidar_px, _RED, "board (LiDAR)"))
    # The board's inner corners: the ones the detector saw as small circles, the others (a ChArUco board
    # cut by the image's edge or hidden) in grey where the board pose puts them inside the image.
    corners_c = transform_points(frame.camera.T_camera_board, board.inner_corners())
    seen = np.zeros(len(corners_c), bool)
    seen[frame.camera.corner_ids if frame.camera.corner_ids is not None else slice(None)] = True
    inside = cam.sees(corners_c)
    for k, (cu, cv) in zip(np.nonzero(inside)[0], _subpixel_points(cam.project(corners_c[inside]), scale)):
        cv2.circle(bgr, (int(cu), int(cv)), 3 * 16, _LIME if seen[k] else _GREY, 1, cv2.LINE_AA, shift=4)
    for poly, colour, _ in outlines:
        pts = _subpixel_points(poly, scale)
        if np.all(np.abs(pts) < 2**28):
            cv2.polylines(bgr, [pts.reshape(-1, 1, 2)], True, colour, 2, cv2.LINE_AA, shift=4)
    title = (f"frame {frame.name}: laser line on the board" if frame.lidar.is_scan_line else
             f"frame {frame.name}: LiDAR board offset du {offset[0]:+.1f} px, dv {offset[1]:+.1f} px")
    legend = [(c, label) for _, c, label in outlines]
    if not seen.all():
        legend.append((_GREY, f"corners not seen ({int((~seen).sum())})"))
    caption = _caption(w, title, legend, lo_hi)
    ok, jpg = cv2.imencode(".jpg", np.vstack([caption, bgr]), [cv2.IMWRITE_JPEG_QUALITY, _OVERLAY_JPEG_QUALITY])
    return jpg.tobytes(), offset


_LIME, _RED, _GREY = (0, 255, 0), (0, 0, 255), (150, 150, 150)  # BGR


def _subpixel_points(uv, scale: float) -> np.ndarray:
    """Camera pixels as OpenCV drawing coordinates in the reduced image, with 4 fractional bits (``shift=4``)."""
    return np.rint((np.asarray(uv, dtype=float) + 0.5) * scale * 16 - 8).astype(np.int32)


def _turbo(x: np.ndarray) -> np.ndarray:
    """The turbo colour map of values in [0, 1] (clipped), as BGR bytes (N, 3)."""
    index = np.clip(np.rint(255 * np.asarray(x, float)), 0, 255).astype(np.uint8)
    return cv2.applyColorMap(index.reshape(-1, 1), cv2.COLORMAP_TURBO).reshape(-1, 3)


def _caption(width: int, title: str, legend: list[tuple[tuple[int, int, int], str]], depth_range) -> np.ndarray:
    """A white strip (BGR) above a projection: the title, the outlines' legend and the depth colour scale."""
    strip = np.full((48, width, 3), 255, np.uint8)
    font = cv2.FONT_HERSHEY_SIMPLEX
    cv2.putText(strip, title, (8, 18), font, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    x = 8
    for colour, label in legend:
        cv2.line(strip, (x, 36), (x + 24, 36), colour, 2, cv2.LINE_AA)
        cv2.putText(strip, label, (x + 30, 41), font, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
        x += 40 + cv2.getTextSize(label, font, 0.45, 1)[0][0]
    bar_w = max(20, min(200, width - x - 220))
    x0 = width - bar_w - 110
    if x0 > x:
        ramp = _turbo(np.linspace(0, 1, bar_w))
        strip[30:42, x0:x0 + bar_w] = ramp[None, :, :]
        cv2.putText(strip, f"{depth_range[0]:.1f}", (x0 - 34, 41), font, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
        cv2.putText(strip, f"{depth_range[1]:.1f} m depth", (x0 + bar_w + 4, 41), font, 0.4, (0, 0, 0), 1,
                    cv2.LINE_AA)
    return strip


def board_choice_figure(frame, scan_path, two_d: bool = False) -> bytes:
    """Top view of a frame's sweep or scan (LiDAR x forward, y left): every return grey, the board candidates
    coloured and numbered, the chosen one ringed in black (``top_view``)."""
    dec = frame.decision
    scan = read_scan_2d(scan_path) if two_d else read_scan(scan_path)
    return top_view_png(scan, list(dec.candidate_points), dec.chosen, f"frame {frame.name}: {dec.method}",
                        dot_px=2 if two_d else 1)


def _table(rows: list[list[str]], head: list[str]) -> str:
    h = "".join(f"<th>{html.escape(c)}</th>" for c in head)
    b = "".join("<tr>" + "".join(f"<td>{html.escape(str(c))}</td>" for c in r) + "</tr>" for r in rows)
    return f"<table><tr>{h}</tr>{b}</table>"


def range_residual_arrays(result) -> dict[str, np.ndarray] | None:
    """What ``report_figures.range_residuals_pngs`` draws: the board points' range residuals (the refined
    board planes) without the LiDAR range terms (before) and with the chosen ones (after), with each point's
    range, ring (-1: none) and square colour; None for a 2D LiDAR."""
    ref = result.refinement
    used = [f for f in result.frames if f.usable and f.name in ref.T_camera_board and not f.lidar.is_scan_line]
    if not used:
        return None
    fit = ref.range_model
    terms = fit.terms if fit is not None else None
    beta = np.asarray(fit.values_m) if terms is not None else None
    labels = fit.labels_for(used) if fit is not None else frame_labels(used)
    rows: dict[str, list] = {"range_m": [], "ring": [], "dark": [], "before_m": [], "after_m": []}
    for k, f in enumerate(used):
        pi, _, _ = lidar_plane(result.T_camera_lidar, ref.T_camera_board[f.name])
        n = f.lidar.n_points
        rows["range_m"].append(np.linalg.norm(f.lidar.points, axis=1))
        rows["ring"].append(labels.rings[k] if labels.rings[k] is not None else np.full(n, -1))
        rows["dark"].append(labels.dark[k] > 0.5 if labels.dark[k] is not None else np.zeros(n, dtype=bool))
        rows["before_m"].append(point_residuals(f.lidar, pi, None, None))
        rows["after_m"].append(point_residuals(f.lidar, pi, terms, beta, labels.rings[k], labels.dark[k]))
    return {**{k: np.concatenate(v) for k, v in rows.items()},
            "chosen": np.array(fit.chosen if fit is not None else "none")}


def range_model_part(fit, title: str = "") -> str:
    """A LiDAR's range model (``RangeModelFit``) as the report's section opens: the model chosen and why, the
    priors, the terms held at 0, and the confounding of a term with the extrinsic with the pose that best separates
    them (the terms' table follows it: the single pair's own, a rig's from its joint graph)."""
    notes = [f"Priors from a range accuracy of {1000 * fit.range_accuracy_m:.0f} mm; black squares placed by "
             f"{html.escape(fit.labels_from)}"
             + (f" (the intensities agree on {100 * fit.intensity_agreement:.0f}% of clearly placed returns)"
                if fit.intensity_agreement is not None else "") + "."]
    for n, v in zip(fit.pinned, fit.pinned_values_m):
        notes.append(f"{html.escape(n)} was estimated at {1000 * v:+.1f} mm, beyond 3 prior standard deviations: "
                     "held at 0 with its prior variance in the covariance.")
    if fit.confounding:
        c = fit.confounding
        notes.append(f"Confounded: the {html.escape(c['term'])} with {html.escape(c['direction'])} (correlation "
                     f"{c['correlation']:.2f}); that direction's standard deviation is {c['sd']:.1f} {c['unit']} with "
                     f"the term marginalised, {c['sd_if_known']:.1f} were it known. {html.escape(c['advice'])}")
        if c.get("separating_pose"):
            sp = c["separating_pose"]
            x, y, z = sp["board_centre_camera_m"]
            nx, ny, nz = sp["board_normal_camera"]
            now, then = (sp["predicted_translation_std_mm_with_offset"][k] for k in ("now", "with_this_pose"))
            notes.append(f"The next pose that best separates them ({sp['beam_model']} beams assumed): the board's "
                         f"centre at ({x:+.2f}, {y:+.2f}, {z:.2f}) m in the camera frame, its normal ({nx:+.2f}, "
                         f"{ny:+.2f}, {nz:+.2f}); the predicted translation standard deviations along the LiDAR's "
                         "x y z with the offset estimated, predicted from the point and corner noise alone (as "
                         "`lidarcam layout` does), go from " + " ".join(f"{v:.1f}" for v in now) + " to "
                         + " ".join(f"{v:.1f}" for v in then) + " mm.")
    return (f"<h2>{title}LiDAR range model: {html.escape(fit.chosen)}</h2><p>{html.escape(fit.reason)}</p>"
            + "".join(f"<p>{t}</p>" for t in notes))


def board_choice_part(frames: list, title: str = "") -> str:
    """Which LiDAR points are each frame's board (``frames``: those with a board-choice record): the method, the
    candidates, the one chosen and why."""
    rows = [[f.name, f.decision.method, len(f.decision.candidates),
             "-" if f.decision.chosen is None else f.decision.chosen, f.decision.reason] for f in frames]
    return (f"<h2>{title}Which LiDAR points are the board</h2><p>Each frame's candidates are planar pieces in "
            "front of the static scene that fit inside the board; one per frame is chosen by the "
            "extrinsic most frames agree with (or, without enough frames, by the frame's own cues). "
            "calibration.json lists every candidate with its residuals.</p>"
            + _table(rows, ["frame", "method", "candidates", "chosen", "why"]))


def layout_part(result, title: str = "") -> str:
    """The board normals' spread (a pair's ``normal_singular_values``) and the direction it constrains least."""
    axis, advice = describe_direction(result.weakest_direction_camera)
    return (f"<h2>{title}Layout</h2><p>singular values of the board normals (per frame): "
            f"{np.round(result.normal_singular_values, 3).tolist()}, condition number "
            f"{result.condition_number:.2f}; weakest direction: {html.escape(axis)} (to constrain it "
            f"further, {html.escape(advice)})</p>")


def _img(name: str, data: bytes) -> str:
    """A figure embedded in the page: a PNG, or a JPEG (``.jpg``, the overlays)."""
    kind = "jpeg" if name.endswith(".jpg") else "png"
    return f"<img alt='{name}' src='data:image/{kind};base64,{base64.b64encode(data).decode('ascii')}'>"


def offsets_section(offsets: list[tuple[str, np.ndarray]], title: str = "") -> str:
    """Each frame's board outline offset in pixels (``projection_figure``'s), as an HTML section."""
    rows = [[n, f"{o[0]:+.1f}", f"{o[1]:+.1f}"] for n, o in offsets]
    return (f"<h2>{title}Board outline offsets (LiDAR board mapped into the image vs the camera's board)</h2>"
            "<p>Offset of the board as the LiDAR sees it (its points mapped by the estimate into the camera's board "
            "frame: the centre of their extent) from the camera's board, in pixels: the planar method's "
            "re-projection check, horizontal and vertical. Sparse rings leave a few pixels of sampling error even "
            "when the extrinsic is right.</p>" + _table(rows, ["frame", "horizontal du [px]", "vertical dv [px]"]))


def verdict_part(result) -> str:
    """The result's verdict (``pipeline.verdict``: OK, CHECK or UNTRUSTED and why), the page's first paragraph."""
    v = result.verdict
    colour = {"OK": "#1a7f37", "CHECK": "#9a6700", "UNTRUSTED": "#cf222e"}[v.level]
    said = "; ".join(v.reasons)
    return (f'<p class="verdict" style="font-size:1.2em"><b style="color:{colour}">{v.level}</b>'
            + (f": {html.escape(said)}" if said else "") + "</p>")


def mcmc_part(posterior) -> str:
    """How a posterior was sampled (a single pair's or a rig's: ``ChainResult.words``), with its walkers, steps and
    burn-in, as a paragraph."""
    r = posterior.run
    return (f"<p>Posterior sampled with {html.escape(r.words(posterior.likelihood))}; {r.chain.shape[1]} walkers x "
            f"{r.chain.shape[0]} steps, burn-in {r.burn}.</p>")


def spread_section(p, kind: str, title: str = "") -> str:
    """A camera-LiDAR pair's standard deviations (``kind``: posterior or Laplace) and, when sampled, its intervals
    and credible regions, as HTML (``p``: a ``PairEstimate``; a single pair's and each of a rig's alike)."""
    rows = [["rotation about LiDAR x/y/z [deg]"] + [f"{v:.4f}" for v in p.std_rotation_deg],
            ["translation along LiDAR x/y/z [mm]"] + [f"{v:.2f}" for v in p.std_translation_mm],
            ["t in camera x/y/z [mm]"] + [f"{v:.2f}" for v in p.std_translation_camera_mm]]
    out = f"<h2>{title}Standard deviations ({kind})</h2>" + _table(rows, ["", "x", "y", "z"])
    summary = p.summary()
    if summary is None:
        return out
    rows = []
    for level in INTERVAL_LEVELS:
        iv = summary[f"{round(100 * level)}%"]
        rows.append([f"{round(100 * level)}% rotation [deg]"]
                    + [f"[{a:+.4f}, {b:+.4f}]" for a, b in iv["rotation_deg"]])
        rows.append([f"{round(100 * level)}% translation [mm]"]
                    + [f"[{a:+.4f}, {b:+.4f}]" for a, b in iv["translation_mm"]])
    regions = summary["credible_regions"]
    return (out + f"<h2>{title}Intervals (offsets from the estimate, GTSAM tangent)</h2>"
            + _table(rows, ["", "x", "y", "z"])
            + "<p>Credible regions: the covariance's ellipsoid about the estimate (with several modes: about each "
            "mode, under its own covariance) holding 99% / 99.9% of the samples "
            f"reaches a squared Mahalanobis distance of {regions['99%']['d2']:.1f} / {regions['99.9%']['d2']:.1f} (a "
            f"Gaussian's: {regions['99%']['gaussian_d2']:.1f} / {regions['99.9%']['gaussian_d2']:.1f}).</p>")


def html_page(title: str, parts: list[str]) -> str:
    """A self-contained report page of HTML ``parts`` (the figures embedded)."""
    return (f"<!doctype html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title><style>"
            "body{font-family:sans-serif;max-width:1100px;margin:auto}table{border-collapse:collapse}"
            "td,th{border:1px solid #ccc;padding:3px 8px;font-size:13px}img{max-width:100%}</style></head><body>"
            + "".join(parts) + "</body></html>")
