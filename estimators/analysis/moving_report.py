"""A moving board's report (``report.html``): the verdict, the transform and the clocks' offset, and the few images
``extract`` kept whole, each with the board's LiDAR returns of the sweeps about its instant carried to that instant
(de-skewed: each return moved with the board from where the camera saw it when the return was fired) and drawn
where the estimate maps them, beside the camera's board outline. Right, they fill the outline; a wrong offset or
extrinsic shifts them off it along the board's motion or as a whole.
"""
from __future__ import annotations

import html
from pathlib import Path

import cv2
import numpy as np

from geometry.rotations import transform_points

from ..io.motion_track import EXAMPLES
from ..io.output import write_atomic
from ..solvers.clock_offset import camera_trajectory, deskewed
from .report import html_page, spread_section, verdict_part

# Returns drawn: those fired within this (s) of the image's instant.
WINDOW_S = 0.06
_JPEG_QUALITY = 90


def _overlay(image: np.ndarray, result, board, trajectory, track, at_s: float) -> tuple[np.ndarray, int]:
    """The image with the camera's board outline (green) and the de-skewed returns (red); how many were drawn."""
    img = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR) if image.ndim == 2 else image.copy()
    camera, dt = result.camera, result.time_offset_s
    T_cb = trajectory(at_s)
    outline = camera.project(transform_points(T_cb, board.outline()))
    if np.all(np.isfinite(outline)):
        cv2.polylines(img, [np.round(outline * 16).astype(np.int32)], True, (60, 200, 60), 2, cv2.LINE_AA, 4)
    drawn = 0
    for s in track.sweeps():
        t = s.times_s
        near = (np.abs(t + dt - at_s) <= WINDOW_S) & trajectory.covers(t + dt)
        if not near.any():
            continue
        p_c = deskewed(s.points[near], t[near], result.T_camera_lidar, dt, trajectory, at_s)
        uv = camera.project(p_c)
        for u, v in uv[np.all(np.isfinite(uv), axis=1)]:
            cv2.circle(img, (int(round(u * 16)), int(round(v * 16))), 24, (40, 40, 230), -1, cv2.LINE_AA, 4)
            drawn += 1
    return img, drawn


def _posterior_part(result) -> str:
    """The posterior's run and the offset's intervals (or why it was not sampled), as HTML."""
    if result.posterior is None:
        return "" if result.posterior_note is None else f"<p>Posterior: {html.escape(result.posterior_note)}</p>"
    summary = result.posterior_summary()
    words = html.escape(result.posterior.run.words("gaussian"))
    offset = summary.get("time_offset_ms")
    rows = "" if offset is None else "; the clocks' offset's intervals " + ", ".join(
        f"{level}: [{offset[level][0]:+.2f}, {offset[level][1]:+.2f}] ms" for level in ("68%", "95%"))
    return f"<p>Posterior ({words}){rows}.</p>"


def write_moving_report(result, out: str | Path) -> Path:
    """``out/report.html`` and its overlays (``moving_NNNN.jpg``), each written atomically."""
    out, dataset, track, board = Path(out), Path(result.dataset), result.track, result.board
    trajectory = camera_trajectory(list(result.board_views))
    offset = ("held at" if result.time_offset_std_s is None else "") + f" {1000 * result.time_offset_s:+.2f} ms" \
        + ("" if result.time_offset_std_s is None else f" +- {1000 * result.time_offset_std_s:.2f} ms")
    t = result.T_camera_lidar[:3, 3]
    parts = ["<h1>lidarcam report: a moving board</h1>", verdict_part(result),
             f"<p>dataset: {html.escape(str(dataset))}; {result.views} images and {result.sweeps} LiDAR sweeps used; "
             f"returns timed by {html.escape(result.point_times or 'their sweep')}.</p>",
             f"<p>t = ({', '.join(f'{1000 * v:.1f}' for v in t)}) mm; clocks' offset t_camera_stamp - "
             f"t_lidar_stamp{html.escape(offset)}; the returns lie {1000 * result.rms_m:.1f} mm RMS along their beams "
             f"from the board where the camera saw it ({1000 * result.own_scatter_m:.1f} mm about their own "
             "planes).</p>", spread_section(result.pair, "Laplace" if result.posterior is None else "posterior"),
             _posterior_part(result),
             "<h2>The board's returns at each image's instant</h2><p>Red: the returns fired within "
             f"{1000 * WINDOW_S:.0f} ms of the image's instant, each carried with the board from where it was when "
             "fired to where it is in the image, mapped by the estimate. Green: the camera's board outline. They "
             "should fill it.</p>"]
    for k, stamp in enumerate(track.example_stamps_s):
        path = dataset / EXAMPLES / f"{k:04d}.png"
        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if image is None or not bool(trajectory.covers(np.array([stamp]))[0]):
            continue
        img, drawn = _overlay(image, result, board, trajectory, track, float(stamp))
        ok, jpg = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, _JPEG_QUALITY])
        name = f"moving_{k:04d}.jpg"
        write_atomic(out / name, lambda fh, data=jpg.tobytes(): fh.write(data), mode="wb")
        parts.append(f"<h3>t = {stamp:.2f} s: {drawn} returns</h3><img src='{name}'>")
    page = html_page("lidarcam moving board report", parts)
    return write_atomic(out / "report.html", lambda fh: fh.write(page))


def write_moving_rig_report(result, out: str | Path) -> list[Path]:
    """A moving board's rig (``pipeline.moving_rig``): each LiDAR's report in ``out/<lidar>/``, and
    ``out/report.html`` with the rig's verdict, each LiDAR's offset and a link to its page."""
    out = Path(out)
    pages = [write_moving_report(r, out / name) for name, r in result.lidars.items()]
    rows = "".join(
        f"<tr><td><a href='{name}/report.html'>{name}</a></td><td>{html.escape(r.verdict.level)}</td>"
        f"<td>{1000 * r.time_offset_s:+.2f}" + ("" if r.time_offset_std_s is None else
                                                 f" +- {1000 * r.time_offset_std_s:.2f}") + " ms</td></tr>"
        for name, r in result.lidars.items())
    parts = ["<h1>lidarcam report: a moving board's rig</h1>", verdict_part(result),
             f"<p>dataset: {html.escape(result.dataset)}; each LiDAR solved against {result.camera}.</p>",
             f"<table><tr><th>LiDAR</th><th>verdict</th><th>t_{result.camera}_stamp - t_lidar_stamp</th></tr>"
             f"{rows}</table>"]
    page = html_page("lidarcam moving board rig report", parts)
    return [write_atomic(out / "report.html", lambda fh: fh.write(page))] + pages
